//! Recursive prediction with the surrogates: a 20-step rollout, and a rollout
//! with its 20×20 Jacobian, for the two-layer model (M1, M2: 1 layer of h,
//! M3: 2 layers of h, M_A: 8) and the single LSTM (2 layers of h), for
//! h = 8, 12, 16. Random weights (the cost does not depend on them).
//!
//! `rollout-20` and `rollout-20+jacobian` are what the controller pays per
//! SQP iteration: the past window is the same across a solve, so its 19
//! warm-up steps are kept. `rollout-20-cold` starts from a new past window
//! every time (what the first call of a control step pays).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rootzone::surrogate::{
    HORIZON, Mlp, Past, Predictor, Scaling, SequenceNet, Surrogate, TwoLayerNet,
};

fn inputs() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let past_u = (0..20)
        .map(|i| if i % 5 == 0 { 4e-6 } else { 0.0 })
        .collect();
    let past_y = (0..20).map(|i| 0.25 + 0.002 * i as f64).collect();
    let future_u = (0..HORIZON).map(|k| 1e-7 + 2e-6 * (k % 3) as f64).collect();
    (past_u, past_y, future_u)
}

fn rollout(c: &mut Criterion) {
    for h in [8, 12, 16] {
        let models = [
            (
                "two-layer",
                Surrogate::TwoLayer(TwoLayerNet {
                    sub_models: [
                        SequenceNet::new(&[h], 1),
                        SequenceNet::new(&[h], 2),
                        SequenceNet::new(&[h, h], 3),
                    ],
                    combiner: Mlp::new(8, 4),
                }),
            ),
            (
                "single-lstm",
                Surrogate::Single(SequenceNet::new(&[h, h], 5)),
            ),
        ];
        let (past_u, past_y, future_u) = inputs();
        let mut other_y = past_y.clone();
        other_y[0] += 0.01;
        // a diurnal ET0 about 4 mm/day
        let et0 = |k: usize| 4.6e-8 * (1.0 + (k as f64 * std::f64::consts::PI / 6.0).sin());
        let past_e: Vec<f64> = (0..20).map(et0).collect();
        let future_e: Vec<f64> = (20..20 + HORIZON).map(et0).collect();
        let past = |y| Past {
            u: &past_u,
            y,
            et0: &past_e,
        };
        for (name, model) in models {
            let mut p = Predictor::new(model, Scaling::default());
            let mut out = vec![0.0; HORIZON];
            let mut jac = vec![0.0; HORIZON * HORIZON];
            c.bench_function(&format!("{name}-h{h}/rollout-20"), |b| {
                b.iter(|| {
                    p.predict(
                        past(&past_y),
                        black_box(&future_u),
                        &future_e,
                        0.0,
                        &mut out,
                    )
                    .unwrap();
                    black_box(out[HORIZON - 1])
                })
            });
            let mut flip = false;
            c.bench_function(&format!("{name}-h{h}/rollout-20-cold"), |b| {
                b.iter(|| {
                    flip = !flip;
                    let py = if flip { &past_y } else { &other_y };
                    p.predict(past(py), black_box(&future_u), &future_e, 0.0, &mut out)
                        .unwrap();
                    black_box(out[HORIZON - 1])
                })
            });
            c.bench_function(&format!("{name}-h{h}/rollout-20+jacobian"), |b| {
                b.iter(|| {
                    p.predict_with_jacobian(
                        past(&past_y),
                        black_box(&future_u),
                        &future_e,
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
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .warm_up_time(std::time::Duration::from_millis(500))
        .measurement_time(std::time::Duration::from_secs(2));
    targets = rollout
}
criterion_main!(benches);
