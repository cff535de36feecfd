//! Recursive prediction with the surrogates: 20-step rollout, and rollout with
//! the 20×20 Jacobian, for the two-layer model (M1, M2: 1×32, M3: 2×32,
//! M_A: 16) and the single LSTM (2×32). Random weights.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::surrogate::{HORIZON, Mlp, Predictor, Scaling, SequenceNet, Surrogate, TwoLayerNet};

fn inputs() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let past_u = (0..20)
        .map(|i| if i % 5 == 0 { 4e-6 } else { 0.0 })
        .collect();
    let past_y = (0..20).map(|i| 0.25 + 0.002 * i as f64).collect();
    let future_u = (0..HORIZON).map(|k| 1e-7 + 2e-6 * (k % 3) as f64).collect();
    (past_u, past_y, future_u)
}

fn rollout(c: &mut Criterion) {
    let models = [
        (
            "two-layer",
            Surrogate::TwoLayer(TwoLayerNet {
                sub_models: [
                    SequenceNet::new(&[32], 1),
                    SequenceNet::new(&[32], 2),
                    SequenceNet::new(&[32, 32], 3),
                ],
                combiner: Mlp::new(16, 4),
            }),
        ),
        (
            "single-lstm",
            Surrogate::Single(SequenceNet::new(&[32, 32], 5)),
        ),
    ];
    let (past_u, past_y, future_u) = inputs();
    for (name, model) in models {
        let mut p = Predictor::new(model, Scaling::default());
        let mut out = vec![0.0; HORIZON];
        let mut jac = vec![0.0; HORIZON * HORIZON];
        c.bench_function(&format!("{name}/rollout-20"), |b| {
            b.iter(|| {
                p.predict(&past_u, &past_y, black_box(&future_u), 0.0, &mut out)
                    .unwrap();
                black_box(out[HORIZON - 1])
            })
        });
        c.bench_function(&format!("{name}/rollout-20+jacobian"), |b| {
            b.iter(|| {
                p.predict_with_jacobian(
                    &past_u,
                    &past_y,
                    black_box(&future_u),
                    0.0,
                    &mut out,
                    &mut jac,
                )
                .unwrap();
                black_box(jac[HORIZON * HORIZON - 1])
            })
        });
    }
}

criterion_group!(benches, rollout);
criterion_main!(benches);
