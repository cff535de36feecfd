//! `rootzone train` and `rootzone experiment` end to end (the real binary),
//! and the shipped models against fresh data.

use std::path::{Path, PathBuf};
use std::process::Command;

use rootzone::soil::FieldSettings;
use rootzone::surrogate::dataset::load_or_generate;
use rootzone::surrogate::pipeline::{nrmse_scores, training_weather, validation_spec};
use rootzone::surrogate::{Mlp, ModelFile, Predictor, SequenceNet, Surrogate, TwoLayerNet};

fn rootzone(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rootzone"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn recorded(file: &ModelFile) -> [f64; 3] {
    ["nrmse_1", "nrmse_10", "nrmse_20"].map(|k| file.metadata.scores[k])
}

fn validation(
    which: usize,
    samples: usize,
    seed: u64,
    cache: &Path,
) -> rootzone::surrogate::dataset::Series {
    load_or_generate(
        &validation_spec(which, samples, seed),
        "sandy-loam",
        &FieldSettings::default(),
        training_weather().steps(),
        cache,
    )
    .unwrap()
}

/// The scores on `series` of a two-layer network with `file`'s architecture
/// and scaling, untrained (weights seeded from `seed`).
fn untrained_scores(
    file: &ModelFile,
    seed: u64,
    series: &rootzone::surrogate::dataset::Series,
) -> [f64; 3] {
    let Surrogate::TwoLayer(net) = &file.model else {
        panic!("two-layer.json holds a two-layer model")
    };
    let fresh = TwoLayerNet {
        sub_models: [0, 1, 2]
            .map(|i| SequenceNet::new(&net.sub_models[i].hidden_sizes(), seed + i as u64)),
        combiner: Mlp::new(net.combiner.hidden(), seed + 3),
    };
    nrmse_scores(
        &mut Predictor::new(Surrogate::TwoLayer(fresh), file.scaling),
        series,
    )
}

#[test]
fn quick_training_end_to_end_learns_and_the_experiments_run_on_its_models() {
    let dir = tempfile::tempdir().unwrap();
    let (models, cache, reports) = (
        dir.path().join("models"),
        dir.path().join("cache"),
        dir.path().join("reports"),
    );
    let s = |p: &PathBuf| p.display().to_string();
    let out = rootzone(&[
        "train",
        "--quick",
        "--out",
        &s(&models),
        "--cache",
        &s(&cache),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in [
        "m1.json",
        "m2.json",
        "m3.json",
        "single-lstm.json",
        "two-layer.json",
        "training-report.md",
    ] {
        assert!(models.join(f).is_file(), "{f} missing");
    }
    // the last stage refined both compared networks on the same fresh sets
    // (an impulse set and one per sub-model range, seed 1 + 10), recorded in
    // their files beside the first stages' sets
    let refined_sets = |file: &str| {
        let m = ModelFile::load(&models.join(file)).unwrap();
        m.metadata
            .data
            .iter()
            .filter(|(k, v)| k.starts_with("training_set_") && v.contains("seed 110"))
            .count()
    };
    assert_eq!(refined_sets("two-layer.json"), 4);
    assert_eq!(refined_sets("single-lstm.json"), 4);
    let report = std::fs::read_to_string(models.join("training-report.md")).unwrap();
    assert!(
        report.contains("two-layer (refined)") && report.contains("single LSTM (refined)"),
        "{report}"
    );
    // the recorded scores are those of the file's model on the quick plan's validation set
    // (600 samples, seed 1), recomputed here independently
    let two = ModelFile::load(&models.join("two-layer.json")).unwrap();
    let series = validation(3, 600, 1, &cache);
    let trained = nrmse_scores(&mut two.predictor(), &series);
    for (a, b) in trained.iter().zip(recorded(&two)) {
        assert!((a - b).abs() < 1e-12, "{a} vs recorded {b}");
    }
    // an untrained network of the same architecture
    let untrained = untrained_scores(&two, 100, &series);
    for (u, t) in untrained.iter().zip(trained) {
        assert!(
            *u > 5.0 * t,
            "untrained {untrained:?} vs trained {trained:?}"
        );
    }

    let out = rootzone(&[
        "experiment",
        "e2",
        "--models",
        &s(&models),
        "--out",
        &s(&reports),
        "--cache",
        &s(&cache),
        "--samples",
        "400",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let csv = std::fs::read_to_string(reports.join("e2.csv")).unwrap();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 3);
    assert!(rows.iter().flatten().all(|v| v.is_finite()));
    assert_eq!(
        rows.iter().map(|r| r[0]).collect::<Vec<_>>(),
        [1.0, 10.0, 20.0]
    );
    let md = std::fs::read_to_string(reports.join("e2.md")).unwrap();
    assert!(md.contains("| 20 |"));
    let svg = std::fs::read_to_string(reports.join("e2.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("<polyline"));

    // a short closed loop on the quick models, from a field drier than the zone
    closed_loop_on(&models);

    // a corrupt model file: exit 2, the file named
    std::fs::write(
        models.join("single-lstm.json"),
        "{\"format\": \"rootzone-surrogate\", ",
    )
    .unwrap();
    let out = rootzone(&[
        "experiment",
        "e2",
        "--models",
        &s(&models),
        "--out",
        &s(&reports),
        "--cache",
        &s(&cache),
        "--samples",
        "400",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("single-lstm.json") && err.starts_with("error:"),
        "{err}"
    );
    assert_eq!(err.lines().count(), 1, "{err}");
}

#[test]
fn unknown_soil_and_experiment_are_clear_errors() {
    let out = rootzone(&[
        "train",
        "--quick",
        "--soil",
        "moon-dust",
        "--out",
        "/nonexistent/x",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("moon-dust"));
    let out = rootzone(&["experiment", "e9"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("e9"));
    // each option's range, just past either end
    for (experiment, option, value, needle) in [
        (
            "e1",
            "--samples",
            "199",
            "--samples must be in 200 … 100000",
        ),
        (
            "e1",
            "--samples",
            "100001",
            "--samples must be in 200 … 100000",
        ),
        ("e7", "--seeds", "0", "--seeds"),
        ("e7", "--seeds", "501", "--seeds"),
    ] {
        let out = rootzone(&[
            "experiment",
            experiment,
            option,
            value,
            "--out",
            "/nonexistent/x",
        ]);
        assert_eq!(out.status.code(), Some(2), "{option} {value}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle) && err.contains(value), "{err}");
    }
}

#[test]
fn shipped_models_match_their_recorded_scores_on_fresh_data() {
    let dir = tempfile::tempdir().unwrap();
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    // the recorded scores are the file's own: recomputed on the validation
    // set they name (the full plan's, 5,000 samples of the training seed).
    // That set is simulated afresh: the files were trained when the column
    // was integrated by SDIRK4, whose θ on sandy loam differs from today's
    // SDIRK3 by about 1e-5 at the default tolerances, so the scores agree
    // to a relative 1e-4, not to round-off (another soil's network is 5× off)
    let own = validation(3, 5000, 1, dir.path());
    // and they generalise: a validation set with a seed no training run
    // used. Validation sets differ in difficulty by themselves: E2's seeds
    // 1–5 spread the two-layer network's 1-step NRMSE over 0.0084 … 0.0104
    // (1.24×), so 1.35× of the recorded score is the bound; a network for
    // another soil or an untrained one is 5× and more off
    let fresh_set = validation(3, 3000, 4242, dir.path());
    for file in ["two-layer.json", "single-lstm.json"] {
        let model = ModelFile::load(&models.join(file)).unwrap();
        assert!(
            model.metadata.data["validation_set"].contains("seed 1503"),
            "{file}: {:?}",
            model.metadata.data
        );
        let again = nrmse_scores(&mut model.predictor(), &own);
        for (a, r) in again.iter().zip(recorded(&model)) {
            assert!(
                (a - r).abs() <= 1e-4 * r,
                "{file}: {again:?} vs recorded {r}"
            );
        }
        let fresh = nrmse_scores(&mut model.predictor(), &fresh_set);
        for (f, r) in fresh.iter().zip(recorded(&model)) {
            assert!(
                *f <= 1.35 * r,
                "{file}: fresh {fresh:?} vs recorded {:?}",
                recorded(&model)
            );
        }
    }
}

/// Ten control steps with each controller (the quick surrogates and the
/// Richards model) from a field that starts below the zone [0.18, 0.23].
fn closed_loop_on(models: &std::path::Path) {
    use rootzone::control::{
        ClosedLoopSettings, Controller, MpcSettings, SolveStatus, run_closed_loop,
    };
    use rootzone::soil::FieldSettings;
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    let weather = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let settings = ClosedLoopSettings {
        field: FieldSettings {
            initial_head: -0.7,
            process_noise: 0.02,
            measurement_noise: 0.02,
            seed: 11,
            ..FieldSettings::default()
        },
        steps: 10,
        forecast_error: 0.2,
        forecast_seed: 12,
        ..ClosedLoopSettings::default()
    };
    let mpc = MpcSettings::default();
    let dt = settings.field.sampling_time;
    // the same field without irrigation, for reference
    let mut dry = rootzone::soil::Field::new(settings.field).unwrap();
    let mut unirrigated = Vec::new();
    for step in &weather.steps()[..10] {
        unirrigated.push(dry.step(step.forcing(0.0, dt)).unwrap().water_content);
    }
    let single = ModelFile::load(&models.join("single-lstm.json")).unwrap();
    let two = ModelFile::load(&models.join("two-layer.json")).unwrap();
    for name in ["richards", "single-lstm", "two-layer"] {
        let mut make = |first: f64| match name {
            "richards" => Controller::oracle(mpc, dt),
            "single-lstm" => Controller::surrogate(mpc, single.predictor(), 2, first, dt),
            _ => Controller::surrogate(mpc, two.predictor(), 2, first, dt),
        };
        let run = run_closed_loop(&settings, &weather, &mut make).unwrap();
        assert_eq!(run.records.len(), 10);
        assert!(
            run.initial_theta < 0.16,
            "the field starts dry: {}",
            run.initial_theta
        );
        for r in &run.records {
            assert!(
                r.irrigation.is_finite() && (0.0..=mpc.u_max).contains(&r.irrigation),
                "{name} step {}: setpoint {}",
                r.step,
                r.irrigation
            );
            assert!(
                !matches!(r.status, SolveStatus::Fallback(_)),
                "{name} step {}: {:?}",
                r.step,
                r.status
            );
            assert!(r.bias.is_finite() && r.solve_time.as_secs_f64() > 0.0);
        }
        // below the zone with no rain, every controller irrigates at once and
        // ends wetter than the unirrigated field
        assert!(run.records[0].irrigation > 0.0, "{name} waits while dry");
        let last = run.records.last().unwrap().true_theta;
        assert!(
            last > unirrigated[9] + 0.01,
            "{name}: θ {last} vs {} without irrigation",
            unirrigated[9]
        );
        // the scores, recomputed from the records
        let it: f64 = run.records.iter().map(|r| r.irrigation * dt * 1000.0).sum();
        assert!((run.total_irrigation_mm() - it).abs() < 1e-9 && it > 0.0);
        let violation: f64 = run
            .records
            .iter()
            .map(|r| (0.18 - r.true_theta).max(0.0) + (r.true_theta - 0.23).max(0.0))
            .sum::<f64>()
            / 10.0;
        assert!((run.zone_violation() - violation).abs() < 1e-15);
        // the plant conserved water under the controller's inputs
        assert!(run.water_balance.residual().abs() < 1e-9);
        assert!((run.water_balance.infiltration - it / 1000.0).abs() < 1e-9);
        eprintln!(
            "{name}: I_T {:.2} mm, θ_10 {last:.4} (unirrigated {:.4})",
            run.total_irrigation_mm(),
            unirrigated[9]
        );
    }
}

#[test]
fn training_for_given_soil_parameters_learns_that_soil() {
    use rootzone::soil::VanGenuchten;
    use rootzone::surrogate::pipeline::validation_spec_for;
    let dir = tempfile::tempdir().unwrap();
    let (models, cache) = (dir.path().join("models"), dir.path().join("cache"));
    let s = |p: &PathBuf| p.display().to_string();
    // a loam-like soil no texture is: Carsel & Parrish loam with α × 1.2
    let params = "ks=2.889e-6,alpha=4.32,n=1.56,theta_r=0.078,theta_s=0.43";
    let out = rootzone(&[
        "train",
        "--quick",
        "--soil-params",
        params,
        "--out",
        &s(&models),
        "--cache",
        &s(&cache),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let two = ModelFile::load(&models.join("two-layer.json")).unwrap();
    assert_eq!(two.metadata.soil, params);
    // the output scaling is sandy loam's [0.12, 0.41] at the same effective
    // saturation of this soil (sandy loam: θr 0.065, θs 0.41)
    let se = |t: f64| (t - 0.065) / (0.41 - 0.065);
    let theta = |t: f64| 0.078 + se(t) * (0.43 - 0.078);
    assert!((two.scaling.output.y_min - theta(0.12)).abs() < 1e-12);
    assert!((two.scaling.output.y_max - theta(0.41)).abs() < 1e-12);
    // it predicts that soil: scores on fresh data of it, against the same
    // architecture untrained
    let soil = VanGenuchten {
        saturated_conductivity: 2.889e-6,
        alpha: 4.32,
        n: 1.56,
        residual_water_content: 0.078,
        saturated_water_content: 0.43,
        specific_storage: 1e-6,
    };
    let spec = validation_spec_for(3, 600, 77, &soil);
    let (low, high) = spec.excitation.range();
    assert!((low - theta(0.12)).abs() < 1e-12 && (high - theta(0.40)).abs() < 1e-12);
    let series = load_or_generate(
        &spec,
        "loam-like",
        &FieldSettings {
            soil,
            ..FieldSettings::default()
        },
        training_weather().steps(),
        &cache,
    )
    .unwrap();
    let trained = nrmse_scores(&mut two.predictor(), &series);
    let untrained = untrained_scores(&two, 200, &series);
    for (u, t) in untrained.iter().zip(trained) {
        assert!(
            *u > 3.0 * t,
            "untrained {untrained:?} vs trained {trained:?}"
        );
    }
    // bad parameters: exit 2 naming the parameter
    let out = rootzone(&[
        "train",
        "--quick",
        "--soil-params",
        "ks=1e-6,alpha=4,n=0.9,theta_r=0.07,theta_s=0.43",
        "--out",
        &s(&models),
    ]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--soil-params") && err.contains('n'), "{err}");
}
