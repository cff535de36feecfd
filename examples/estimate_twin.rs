//! Twin experiments of the estimator, for choosing its method and settings:
//! `cargo run --release --example estimate_twin -- [members] [sqrt|po] [head_infl] [param_infl] [localisation|none] [texture|unknown] [0|1|2|loam|sand|…] [steps] [dry|rain] [depths]`
//! (environment: SEL = selection updates, MPT = members per texture, RTOL =
//! the members' relative tolerance, the absolute one a hundredth of it)
//! prints sensor and profile RMS errors after the first day, the parameter
//! estimates and the cost per predict+update.

use std::time::Instant;

use rootzone::estimate::{Estimator, EstimatorSettings, InitialGuess, Prior, Scheme, Sensor};
use rootzone::soil::{Crop, Field, FieldSettings, Texture, VanGenuchten};
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |i: usize, d: &str| args.get(i).cloned().unwrap_or_else(|| d.to_string());
    let members: usize = get(0, "32").parse().unwrap();
    let scheme = match get(1, "sqrt").as_str() {
        "po" => Scheme::PerturbedObservations,
        _ => Scheme::SquareRoot,
    };
    let head_inflation: f64 = get(2, "1.02").parse().unwrap();
    let parameter_inflation: f64 = get(3, "1.02").parse().unwrap();
    let localisation = match get(4, "none").as_str() {
        "none" => None,
        s => Some(s.parse().unwrap()),
    };
    let prior_name = get(5, "texture");
    let variant = get(6, "0");
    let steps: usize = get(7, "60").parse().unwrap();
    let weather_name = get(8, "dry");
    let rtol: f64 = std::env::var("RTOL")
        .map_or(EstimatorSettings::default().relative_tolerance, |v| {
            v.parse().unwrap()
        });
    let base = match variant.as_str() {
        "1" => VanGenuchten {
            saturated_conductivity: 1.23e-5 * 0.5,
            alpha: 7.5 * 1.3,
            ..VanGenuchten::SANDY_LOAM
        },
        "2" => VanGenuchten {
            saturated_conductivity: 1.23e-5 * 2.0,
            alpha: 7.5 * 0.8,
            n: 1.89 * 1.05,
            ..VanGenuchten::SANDY_LOAM
        },
        "loam" => Texture::Loam.parameters(),
        "sand" => Texture::Sand.parameters(),
        "loamy-sand" => Texture::LoamySand.parameters(),
        "silt-loam" => Texture::SiltLoam.parameters(),
        _ => VanGenuchten::SANDY_LOAM,
    };
    let prior = match prior_name.as_str() {
        "unknown" => Prior::Unknown,
        _ => Prior::Texture(match variant.as_str() {
            "loam" => Texture::Loam,
            "sand" => Texture::Sand,
            "loamy-sand" => Texture::LoamySand,
            "silt-loam" => Texture::SiltLoam,
            _ => Texture::SandyLoam,
        }),
    };
    let weather = WeatherSeries::parse(
        if weather_name == "rain" {
            RAIN_SCENARIO
        } else {
            DRY_SCENARIO
        },
        "w",
    )
    .unwrap();
    let depths: Vec<f64> = get(9, "0.125")
        .split(',')
        .map(|s| s.parse().unwrap())
        .collect();
    let mut totals = (0.0, 0.0, 0.0, 0usize);
    for seed in 0..3u64 {
        let mut field = Field::new(FieldSettings {
            soil: base,
            process_noise: 0.02,
            measurement_noise: 0.02,
            seed,
            ..FieldSettings::default()
        })
        .unwrap();
        let sensors: Vec<Sensor> = depths
            .iter()
            .enumerate()
            .map(|(k, &d)| Sensor {
                id: format!("s{k}"),
                depth: d,
                noise: 0.02 * 0.22 / 3f64.sqrt(),
            })
            .collect();
        let first = field.measure();
        let mut est = Estimator::new(
            prior,
            Crop::default(),
            sensors,
            InitialGuess::Reading(first),
            EstimatorSettings {
                members,
                seed: seed + 100,
                scheme,
                head_inflation,
                parameter_inflation,
                localisation,
                selection_updates: std::env::var("SEL").map_or(12, |v| v.parse().unwrap()),
                members_per_texture: std::env::var("MPT").map_or(4, |v| v.parse().unwrap()),
                relative_tolerance: rtol,
                absolute_tolerance: rtol * 1e-2,
                ..EstimatorSettings::default()
            },
        )
        .unwrap();
        let (mut s2, mut p2, mut count) = (0.0, 0.0, 0usize);
        let mut cost = 0.0;
        for k in 0..steps {
            let u = if (3..6).contains(&(k % 12)) {
                6e-7
            } else {
                0.0
            };
            let forcing = weather.steps()[k].forcing(u, 7200.0);
            field.step(forcing).unwrap();
            let heads = field.pressure_heads().to_vec();
            let readings: Vec<(usize, f64)> = depths
                .iter()
                .enumerate()
                .map(|(i, &d)| {
                    let c = rootzone::estimate::cell_of(d, 0.5, 26);
                    (
                        i,
                        base.water_content(heads[c]) * (1.0 + 0.02 * (2.0 * frac(k, i) - 1.0)),
                    )
                })
                .collect();
            let t = Instant::now();
            est.predict(forcing, 7200.0).unwrap();
            let r = est.update(&readings);
            cost += t.elapsed().as_secs_f64();
            if let Err(e) = r {
                println!("seed {seed} step {k}: {e}");
            }
            if k >= 12 {
                let truth = field.water_contents();
                let prof = est.profile();
                let s = prof[6].theta_mean - truth[6];
                s2 += s * s;
                p2 += prof
                    .iter()
                    .zip(&truth)
                    .map(|(p, t)| (p.theta_mean - t).powi(2))
                    .sum::<f64>()
                    / 26.0;
                count += 1;
            }
        }
        let soil = est.soil();
        println!(
            "seed {seed}: sensor rmse {:.4} profile rmse {:.4} cost {:.2} ms/step replaced {} | Ks {:.3e} ({:.3e}) alpha {:.2} ({:.2}) n {:.3} ({:.3}) θr {:.3} ({:.3}) θs {:.3} ({:.3})",
            (s2 / count as f64).sqrt(),
            (p2 / count as f64).sqrt(),
            cost / steps as f64 * 1e3,
            est.statistics().replaced_members,
            soil.saturated_conductivity,
            base.saturated_conductivity,
            soil.alpha,
            base.alpha,
            soil.n,
            base.n,
            soil.residual_water_content,
            base.residual_water_content,
            soil.saturated_water_content,
            base.saturated_water_content
        );
        for p in est.parameters() {
            print!(
                "{}={:.3}±{:.3} ",
                p.transformed_name, p.transformed_mean, p.transformed_sd
            );
        }
        println!();
        totals.0 += (s2 / count as f64).sqrt();
        totals.1 += (p2 / count as f64).sqrt();
        totals.2 += cost / steps as f64 * 1e3;
        totals.3 += 1;
    }
    let n = totals.3 as f64;
    println!(
        "MEAN sensor {:.4} profile {:.4} cost {:.2} ms",
        totals.0 / n,
        totals.1 / n,
        totals.2 / n
    );
}

/// A deterministic pseudo-random fraction for the extra sensors' noise.
fn frac(k: usize, i: usize) -> f64 {
    let x = ((k * 7919 + i * 104_729 + 13) as f64 * 0.618_033_988_749_895).fract();
    x.abs()
}
