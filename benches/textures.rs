//! A 60-step run of every texture under every schedule family of issue 14
//! (weather-dry): no irrigation, constant 1e-7 / 1e-6 / 1e-5 m/s, u_max for
//! two steps, a 50-mm rain step. Target: median ≤ 10 ms, slowest ≤ 50 ms per
//! case. A run that stops at the integrator's work limit (ponding on the
//! finer textures, see ARCHITECTURE.md) is timed up to where it stopped.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::soil::{Field, FieldSettings, Forcing, Texture};
use rootzone::weather::{DRY_SCENARIO, WeatherSeries, mm_to_rate};

const DT: f64 = 7200.0;

fn schedule(name: &str, k: usize) -> (f64, f64) {
    match name {
        "none" => (0.0, 0.0),
        "constant-1e-7" => (1e-7, 0.0),
        "constant-1e-6" => (1e-6, 0.0),
        "constant-1e-5" => (1e-5, 0.0),
        "umax-two-steps" => (if k < 2 { 1e-5 } else { 0.0 }, 0.0),
        _ => (0.0, if k == 10 { 50.0 } else { 0.0 }),
    }
}

const SCHEDULES: [&str; 6] = [
    "none",
    "constant-1e-7",
    "constant-1e-6",
    "constant-1e-5",
    "umax-two-steps",
    "rain-step-50mm",
];

fn run(texture: Texture, weather: &WeatherSeries, name: &str) -> f64 {
    let mut field = Field::new(FieldSettings {
        soil: texture.parameters(),
        ..FieldSettings::default()
    })
    .unwrap();
    let mut theta = 0.0;
    for k in 0..60 {
        let (u, rain) = schedule(name, k);
        let w = weather.steps()[k];
        let f = Forcing {
            precipitation: mm_to_rate(w.precip_mm + rain, DT),
            ..w.forcing(u, DT)
        };
        match field.step(f) {
            Ok(r) => theta = r.water_content,
            Err(_) => break,
        }
    }
    theta
}

fn bench_textures(c: &mut Criterion) {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let mut group = c.benchmark_group("sixty_steps_per_texture");
    group.sample_size(10);
    for texture in Texture::ALL {
        for name in SCHEDULES {
            group.bench_function(format!("{texture}/{name}"), |b| {
                b.iter(|| black_box(run(texture, &dry, name)))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_textures);
criterion_main!(benches);
