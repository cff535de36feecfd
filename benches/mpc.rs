//! One zone-MPC solve with each prediction model: the shipped two-layer
//! network and single LSTM (cold controller: multi-start), from a dry and an
//! in-zone window, and the Richards model from a field state.

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::control::{MpcSettings, RichardsModel, SurrogateModel, ZoneMpc};
use rootzone::soil::{Field, FieldSettings};
use rootzone::surrogate::ModelFile;
use rootzone::weather::{DRY_SCENARIO, WeatherSeries, mm_to_rate};

fn solve(c: &mut Criterion) {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    // the dry scenario's ET0 (4 mm/day): the window's 20 steps, then the
    // horizon's, from midnight
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").expect("embedded weather");
    let et0: Vec<f64> = (0..40)
        .map(|k| mm_to_rate(dry.steps()[k % 12].et0_mm, 7200.0))
        .collect();
    for (file, name) in [
        ("two-layer.json", "two-layer"),
        ("single-lstm.json", "single-lstm"),
    ] {
        let file = ModelFile::load(&dir.join(file)).expect("the shipped model loads");
        for (case, level) in [("dry-0.15", 0.15), ("in-zone-0.20", 0.20)] {
            let mut model = SurrogateModel::new(
                file.predictor(),
                (0..20)
                    .map(|i| if i % 6 == 0 { 3e-6 } else { 0.0 })
                    .collect(),
                vec![level; 20],
                et0[..20].to_vec(),
            );
            model.et0 = et0[20..].to_vec();
            c.bench_function(&format!("zone-mpc-{name}/{case}"), |b| {
                b.iter(|| {
                    // a cold controller every time: no warm start
                    let mut mpc = ZoneMpc::new(MpcSettings::default());
                    mpc.solve(&mut model).plan[0]
                })
            });
        }
    }
    // the Richards model after two dry days (θ ≈ 0.20), dry forecast
    let weather = WeatherSeries::parse(DRY_SCENARIO, "dry").expect("embedded weather");
    let mut field = Field::new(FieldSettings::default()).expect("default field");
    for step in &weather.steps()[..24] {
        field
            .step(step.forcing(0.0, 7200.0))
            .expect("the field steps");
    }
    let mut model = RichardsModel::new(&field, &weather.steps()[24..44]);
    c.bench_function("zone-mpc-richards/after-two-dry-days", |b| {
        b.iter(|| {
            let mut mpc = ZoneMpc::new(MpcSettings::default());
            mpc.solve(&mut model).plan[0]
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = solve
}
criterion_main!(benches);
