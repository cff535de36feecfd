//! One zone-MPC solve (SQP, multi-start) with the shipped two-layer surrogate,
//! from a dry and from an in-zone state.

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::control::{MpcSettings, SurrogateModel, ZoneMpc};
use rootzone::surrogate::ModelFile;

fn solve(c: &mut Criterion) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/two-layer.json");
    let file = ModelFile::load(&path).expect("the shipped model loads");
    for (name, level) in [("dry-0.15", 0.15), ("in-zone-0.20", 0.20)] {
        let mut model = SurrogateModel {
            predictor: file.predictor(),
            past_u: (0..20)
                .map(|i| if i % 6 == 0 { 3e-6 } else { 0.0 })
                .collect(),
            past_y: vec![level; 20],
            bias: 0.0,
        };
        c.bench_function(&format!("zone-mpc-two-layer/{name}"), |b| {
            b.iter(|| {
                // a cold controller every time: no warm start
                let mut mpc = ZoneMpc::new(MpcSettings::default());
                mpc.solve(&mut model).plan[0]
            })
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = solve
}
criterion_main!(benches);
