//! The simulator on soils that are not textures: random van Genuchten soils
//! through the schedules of issue 14's matrix (`tests/textures.rs`: no
//! irrigation, 1e-7, 1e-6 and 1e-5 m/s, u_max for two steps, 50 mm of extra
//! rain at step 10) under both weather files, 60 steps each, at the
//! default work limits. Prints every run that stops or takes more than
//! 50 ms, with the soil, and a summary.
//!
//! `cargo run --release --example random_soils [SOILS] [SEED]` (defaults 40
//! and 11). The soils are drawn from a seeded generator: Ks log-uniform in
//! [1e-8, 1e-4] m/s, α log-uniform in [0.5, 20] 1/m, n uniform in
//! [1.05, 3.5], θr in [0, 0.12], θs in [0.33, 0.52] (about the span of
//! Carsel & Parrish 1988's texture means and their spread).

use std::time::Instant;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rootzone::soil::{Field, FieldSettings, Forcing, VanGenuchten};
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries, mm_to_rate};

const STEPS: usize = 60;
const STEP_SECONDS: f64 = 7200.0;
const U_MAX: f64 = 1e-5;
const SCHEDULES: [&str; 6] = ["none", "1e-7", "1e-6", "1e-5", "u_max x2", "rain step"];

fn forcing(weather: &WeatherSeries, schedule: usize, k: usize) -> Forcing {
    let w = weather.steps()[k];
    let irrigation = match schedule {
        1 => 1e-7,
        2 => 1e-6,
        3 => 1e-5,
        4 if k < 2 => U_MAX,
        _ => 0.0,
    };
    let extra = if schedule == 5 && k == 10 { 50.0 } else { 0.0 };
    Forcing {
        precipitation: mm_to_rate(w.precip_mm + extra, STEP_SECONDS),
        ..w.forcing(irrigation, STEP_SECONDS)
    }
}

fn main() {
    let mut args = std::env::args().skip(1);
    let soils: usize = args
        .next()
        .map_or(40, |s| s.parse().expect("SOILS: a count"));
    let seed: u64 = args
        .next()
        .map_or(11, |s| s.parse().expect("SEED: an integer"));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let weathers = [
        (
            "dry",
            WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").unwrap(),
        ),
        (
            "rain",
            WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").unwrap(),
        ),
    ];
    let (mut runs, mut stopped, mut slow) = (0, 0, 0);
    let mut times = Vec::new();
    println!("| soil | Ks m/s | α 1/m | n | weather | schedule | ms | outcome |");
    println!("|---|---|---|---|---|---|---|---|");
    for s in 0..soils {
        let soil = VanGenuchten {
            saturated_conductivity: 10f64.powf(rng.random_range(-8.0..-4.0)),
            alpha: 10f64.powf(rng.random_range(0.5f64.log10()..20f64.log10())),
            n: rng.random_range(1.05..3.5),
            residual_water_content: rng.random_range(0.0..0.12),
            saturated_water_content: rng.random_range(0.33..0.52),
            ..VanGenuchten::SANDY_LOAM
        };
        for (name, weather) in &weathers {
            for (schedule, label) in SCHEDULES.iter().enumerate() {
                let mut field = Field::new(FieldSettings {
                    soil,
                    ..FieldSettings::default()
                })
                .expect("the ranges give valid soils");
                let start = Instant::now();
                let mut error = None;
                for k in 0..STEPS {
                    if let Err(e) = field.step(forcing(weather, schedule, k)) {
                        error = Some(e);
                        break;
                    }
                }
                let ms = start.elapsed().as_secs_f64() * 1e3;
                runs += 1;
                times.push(ms);
                slow += usize::from(ms > 50.0);
                stopped += usize::from(error.is_some());
                if error.is_some() || ms > 50.0 {
                    println!(
                        "| {s} | {:.2e} | {:.2} | {:.3} | {name} | {label} | {ms:.0} | {} |",
                        soil.saturated_conductivity,
                        soil.alpha,
                        soil.n,
                        error.map_or("finished".to_string(), |e| e.to_string())
                    );
                }
            }
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "\n{runs} runs of {soils} soils (seed {seed}): {stopped} stopped at the work limits, \
         {slow} took more than 50 ms; median {:.1} ms",
        times[times.len() / 2]
    );
}
