//! The simulated field against independent expectations: a steady state solved
//! separately, the water balance, convergence in the tolerance, and physical
//! sense.

use rootzone::soil::{Field, FieldSettings, Forcing, Tolerances, VanGenuchten};
use rootzone::weather::{RAIN_SCENARIO, WeatherSeries};

const DT: f64 = 7200.0;

fn still(irrigation: f64) -> Forcing {
    Forcing {
        irrigation,
        reference_et: 0.0,
        precipitation: 0.0,
    }
}

/// h* with K(h*) = q by bisection on the (monotone) conductivity.
fn head_with_conductivity(soil: &VanGenuchten, q: f64) -> f64 {
    let (mut lo, mut hi) = (-1000.0, 0.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if soil.conductivity(mid) < q {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Moderate schedule: 1.5 mm per 2 h for 6 h each morning, weather-rain.
fn moderate(step: usize, weather: &WeatherSeries) -> Forcing {
    let irrigation = if (3..6).contains(&(step % 12)) {
        2e-7
    } else {
        0.0
    };
    weather.get(step).unwrap().forcing(irrigation, DT)
}

/// Heavy schedule: 1.5·Ks for 12 h, off for 12 h, on weather-rain: the top cells
/// saturate and water runs off.
fn heavy(step: usize, weather: &WeatherSeries) -> Forcing {
    let ks = VanGenuchten::SANDY_LOAM.saturated_conductivity;
    let irrigation = if step % 12 < 6 { 1.5 * ks } else { 0.0 };
    weather.get(step).unwrap().forcing(irrigation, DT)
}

fn rain() -> WeatherSeries {
    WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").unwrap()
}

#[test]
fn initial_state_follows_model_md() {
    let field = Field::new(FieldSettings::default()).unwrap();
    assert!((field.water_content() - 0.2659).abs() < 5e-5);
    for h in field.pressure_heads() {
        assert!((h + 0.2).abs() < 1e-9);
    }
}

#[test]
fn constant_infiltration_converges_to_the_uniform_head_with_k_equal_to_the_rate() {
    for q in [2e-7, 1e-6, 5e-6] {
        let mut field = Field::new(FieldSettings::default()).unwrap();
        let expected = head_with_conductivity(&field.settings().soil, q);
        for _ in 0..240 {
            field.step(still(q)).unwrap();
        }
        for (i, &h) in field.pressure_heads().iter().enumerate() {
            assert!(
                (h - expected).abs() < 1e-4 * expected.abs(),
                "q={q}: cell {i} at {h}, expected {expected}"
            );
        }
        let drainage_rate = {
            let before = field.water_balance().drainage;
            field.step(still(q)).unwrap();
            (field.water_balance().drainage - before) / DT
        };
        assert!(
            (drainage_rate - q).abs() < 1e-4 * q,
            "{drainage_rate} vs {q}"
        );
    }
}

#[test]
fn water_balance_closes_over_the_heavy_schedule() {
    let weather = rain();
    let mut field = Field::new(FieldSettings::default()).unwrap();
    let mut max_theta_top: f64 = 0.0;
    for step in 0..96 {
        field.step(heavy(step, &weather)).unwrap();
        max_theta_top = max_theta_top.max(field.water_contents()[0]);
        let residual = field.water_balance().residual();
        assert!(
            residual.abs() < 1e-9,
            "step {step}: residual {residual:e} m"
        );
    }
    let balance = field.water_balance();
    assert!(balance.runoff > 0.0, "the heavy schedule should run off");
    assert!(
        max_theta_top > 0.409,
        "top cell should saturate, max θ {max_theta_top}"
    );
    assert!(balance.uptake > 0.0 && balance.drainage > 0.0);
}

#[test]
fn water_balance_closes_with_process_noise_accounted() {
    let weather = rain();
    let settings = FieldSettings {
        process_noise: 0.05,
        seed: 7,
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    for step in 0..48 {
        field.step(moderate(step, &weather)).unwrap();
    }
    let balance = field.water_balance();
    assert!(balance.noise != 0.0);
    assert!(balance.residual().abs() < 1e-9, "{:e}", balance.residual());
}

#[test]
fn tightening_the_tolerance_changes_theta_by_less_than_1e_6() {
    let weather = rain();
    let default = FieldSettings::default();
    let tight = FieldSettings {
        tolerances: Tolerances {
            relative: default.tolerances.relative / 100.0,
            absolute: default.tolerances.absolute / 100.0,
        },
        ..default
    };
    let mut a = Field::new(default).unwrap();
    let mut b = Field::new(tight).unwrap();
    let mut worst: f64 = 0.0;
    for step in 0..60 {
        let ra = a.step(moderate(step, &weather)).unwrap();
        let rb = b.step(moderate(step, &weather)).unwrap();
        worst = worst.max((ra.water_content - rb.water_content).abs());
    }
    assert!(worst < 1e-6, "θ moved by {worst:e}");
}

#[test]
fn more_irrigation_never_gives_less_water() {
    let weather = rain();
    let mut fields: Vec<Field> = (0..3)
        .map(|_| Field::new(FieldSettings::default()).unwrap())
        .collect();
    for step in 0..60 {
        let mut last = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for (k, field) in fields.iter_mut().enumerate() {
            let base = moderate(step, &weather);
            let forcing = Forcing {
                irrigation: base.irrigation * k as f64 + 1e-8 * k as f64,
                ..base
            };
            let theta = field.step(forcing).unwrap().water_content;
            let storage = field.storage();
            assert!(theta >= last.0 - 1e-9, "step {step}, schedule {k}");
            assert!(storage >= last.1 - 1e-12, "step {step}, schedule {k}");
            last = (theta, storage);
        }
    }
}

#[test]
fn no_uptake_below_the_wilting_point() {
    let settings = FieldSettings {
        initial_head: -100.0,
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    for _ in 0..12 {
        field
            .step(Forcing {
                irrigation: 0.0,
                reference_et: 1e-7,
                precipitation: 0.0,
            })
            .unwrap();
    }
    assert_eq!(field.water_balance().uptake, 0.0);
}

#[test]
fn a_dry_column_without_supply_or_demand_only_drains() {
    let settings = FieldSettings {
        initial_head: -3.0,
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    let mut storage = field.storage();
    for _ in 0..24 {
        field.step(still(0.0)).unwrap();
        assert!(field.storage() < storage);
        storage = field.storage();
    }
    let balance = field.water_balance();
    assert_eq!(balance.infiltration, 0.0);
    assert_eq!(balance.uptake, 0.0);
    assert_eq!(balance.runoff, 0.0);
    assert!(balance.drainage > 0.0);
    assert!((balance.initial_storage - balance.storage - balance.drainage).abs() < 1e-12);
}

#[test]
fn supply_above_ks_on_a_wet_column_runs_off_without_building_pressure() {
    let settings = FieldSettings {
        initial_head: -0.05,
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    let ks = field.settings().soil.saturated_conductivity;
    for _ in 0..12 {
        field.step(still(4.0 * ks)).unwrap();
        let top = field.pressure_heads()[0];
        assert!(top > -0.05 && top < 0.05, "top head {top}");
    }
    let balance = field.water_balance();
    // Most of the supply cannot enter: the column conducts at most about Ks.
    let supplied = 4.0 * ks * 12.0 * DT;
    assert!(
        balance.runoff > 0.6 * supplied,
        "{} of {supplied}",
        balance.runoff
    );
    assert!(balance.infiltration < 0.4 * supplied);
    assert!(field.pressure_heads().iter().all(|h| *h < 0.1));
}

#[test]
fn noise_is_seeded_and_bounded() {
    let weather = rain();
    let run = |seed: u64| {
        let settings = FieldSettings {
            process_noise: 0.02,
            measurement_noise: 0.05,
            seed,
            ..FieldSettings::default()
        };
        let mut field = Field::new(settings).unwrap();
        (0..12)
            .map(|step| field.step(moderate(step, &weather)).unwrap())
            .collect::<Vec<_>>()
    };
    let (a, b, c) = (run(1), run(1), run(2));
    assert_eq!(a, b);
    assert_ne!(a, c);
    for r in &a {
        let relative = r.measured_water_content / r.water_content - 1.0;
        assert!(relative.abs() <= 0.05);
    }
    assert!(
        a.iter()
            .any(|r| r.measured_water_content != r.water_content)
    );
}

#[test]
fn invalid_settings_and_forcing_are_rejected() {
    let bad = FieldSettings {
        process_noise: -0.1,
        ..FieldSettings::default()
    };
    assert!(Field::new(bad).is_err());
    let mut field = Field::new(FieldSettings::default()).unwrap();
    assert!(field.step(still(f64::NAN)).is_err());
    assert!(field.step(still(-1e-7)).is_err());
    // A rejected step leaves the field as it was.
    assert_eq!(field.steps(), 0);
    assert!(field.step(still(1e-7)).is_ok());
}
