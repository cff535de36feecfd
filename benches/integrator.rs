//! Speed of the soil-column simulation (issue targets: 60 steps of the moderate
//! case ≤ 5 ms, 30,000 steps ≤ 10 s), and the same column through diffsol's BDF
//! for comparison: the reason the column has its own integrator.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::soil::diffsol_dae::DaeIntegrator;
use rootzone::soil::{ColumnState, Field, FieldSettings, Forcing, Tolerances};
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries};

const DT: f64 = 7200.0;

/// The moderate case: 60 steps of weather-dry under a constant 2e-7 m/s
/// (1.44 mm per 2 h), which holds θ near the target zone.
fn moderate(weather: &WeatherSeries) -> impl Iterator<Item = Forcing> + '_ {
    weather.steps()[..60].iter().map(|w| w.forcing(2e-7, DT))
}

/// Moderate irrigation as a farm would apply it: 6 h each morning, weather-rain.
fn scheduled(weather: &WeatherSeries) -> impl Iterator<Item = Forcing> + '_ {
    weather.steps()[..60].iter().enumerate().map(|(k, w)| {
        let u = if (3..6).contains(&(k % 12)) {
            4e-7
        } else {
            0.0
        };
        w.forcing(u, DT)
    })
}

fn run_field(forcings: impl Iterator<Item = Forcing>) -> f64 {
    let mut field = Field::new(FieldSettings::default()).unwrap();
    let mut theta = 0.0;
    for f in forcings {
        theta = field.step(f).unwrap().water_content;
    }
    theta
}

fn bench_sixty_steps(c: &mut Criterion) {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let rain = WeatherSeries::parse(RAIN_SCENARIO, "rain").unwrap();
    let mut group = c.benchmark_group("sixty_steps");
    group.bench_function("own_sdirk3_moderate_dry", |b| {
        b.iter(|| black_box(run_field(moderate(&dry))))
    });
    group.bench_function("own_sdirk3_morning_irrigation_rain", |b| {
        b.iter(|| black_box(run_field(scheduled(&rain))))
    });
    group.sample_size(10);
    group.bench_function("diffsol_bdf_dae_moderate_dry", |b| {
        b.iter(|| {
            let settings = FieldSettings::default();
            let field = Field::new(settings).unwrap();
            let mut dae = DaeIntegrator::new(*field.column(), Tolerances::default()).unwrap();
            let mut state: ColumnState = field.state().clone();
            for (k, f) in moderate(&dry).enumerate() {
                dae.advance(&mut state, k as f64 * DT, DT, f).unwrap();
            }
            black_box(state.heads[6])
        })
    });
    group.finish();
}

/// One surrogate training set: 30,000 steps of multi-level irrigation.
fn bench_training_set(c: &mut Criterion) {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let levels = [0.0, 5e-8, 1e-7, 2e-7, 4e-7, 8e-7];
    let forcings: Vec<Forcing> = (0..30_000)
        .map(|k| {
            // a deterministic multi-level signal: level changes every 7 steps
            let level = levels[(k / 7 * 2654435761usize) % levels.len()];
            dry.steps()[k % dry.len()].forcing(level, DT)
        })
        .collect();
    let mut group = c.benchmark_group("training_set");
    group.sample_size(10);
    group.bench_function("own_sdirk3_30000_steps", |b| {
        b.iter(|| black_box(run_field(forcings.iter().copied())))
    });
    group.finish();
}

criterion_group!(benches, bench_sixty_steps, bench_training_set);
criterion_main!(benches);
