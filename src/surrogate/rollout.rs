//! N-step recursive prediction with a [`Surrogate`] and its exact Jacobian
//! with respect to the future irrigation rates.
//!
//! # Time convention
//!
//! The same as [`super::evaluate`] and [`super::dataset::Series`]: u[k] is the
//! irrigation rate applied over sampling step k and y[k] the water content
//! measured at the end of that step. At the current time t:
//!
//! * `past.u[i] = u[t − 20 + i]`, `past.y[i] = y[t − 20 + i]` and
//!   `past.et0[i] = ET0[t − 20 + i]` for i = 0..20 (the last measured output
//!   is y[t − 1]);
//! * `future_u[k] = u[t + k]` for k = 0..N (the plan; `future_u[0]` is the rate
//!   applied from now) and `future_et0[k] = ET0[t + k]`, the forecast;
//! * the result `ŷ[k]` predicts y[t + k], the water content at the end of the
//!   step over which `future_u[k]` is applied.
//!
//! The prediction continues one recurrence (see [`SequenceNet`]): the LSTM
//! state is warmed up from rest on the steps (ū[t − 19 + τ], ȳ[t − 20 + τ],
//! ē[t − 19 + τ]), τ = 0..19, i.e. (`past.u[1..20]`, `past.y[0..19]`,
//! `past.et0[1..20]`): ET0 goes with the supply of the same step, the
//! weather over which y moved. ŷ[0] comes from the step (`future_u[0]`,
//! `past.y[19]`, `future_et0[0]`), so that it sees exactly the 20-sample
//! window; ŷ[k] comes from one more step on (`future_u[k]`, ŷ[k − 1],
//! `future_et0[k]`), the model's own (unbiased) prediction fed back. A rollout over N steps therefore costs 19 + N LSTM
//! steps, and the 19 warm-up steps are kept and reused while the past window
//! stays the same (as it does across the iterations of one MPC solve).
//!
//! # Output correction
//!
//! The additive correction `bias` is applied to the returned outputs only:
//! ŷ[k] = y(ȳ_k) + bias, while the recurrence is fed the uncorrected
//! predictions. The Jacobian is therefore independent of `bias`.
//!
//! # Jacobian
//!
//! Forward mode: direction j (the input ū_j) enters at step j, so at step k
//! the tangents of the directions 0..=k are carried through every LSTM layer
//! (∂h, ∂c), the heads, the combiner (∂ŷ = Σᵢ ∂M_A/∂zᵢ·∂zᵢ) and back into the
//! next step's input ȳ. That is Σ_k (k + 1) = N(N + 1)/2 tangent steps per
//! layer. In raw units dŷ_k/du_j = (y_max − y_min)·∂ȳ_k/∂ū_j·dū/du(u_j). The
//! matrix is lower triangular: ŷ_k does not depend on rates applied after
//! step k.

use super::evaluate::WINDOW;
use super::network::{FEATURES, MlpWorkspace, SequenceNet, SequenceWorkspace, Surrogate};
use super::scaling::Scaling;

/// Default prediction horizon N.
pub const HORIZON: usize = 20;

/// The past window of a prediction: the last [`WINDOW`] supplies u [m/s],
/// measured outputs y and ET0 rates [m/s], oldest first (see the module
/// docs).
#[derive(Debug, Clone, Copy)]
pub struct Past<'a> {
    pub u: &'a [f64],
    pub y: &'a [f64],
    pub et0: &'a [f64],
}

/// Wrong lengths passed to [`Predictor::predict`] or
/// [`Predictor::predict_with_jacobian`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RolloutError {
    #[error("{what} has {found} values, expected {expected}")]
    Length {
        what: &'static str,
        expected: usize,
        found: usize,
    },
}

/// A surrogate with its scaling and the workspace of recursive prediction.
/// Allocates when built; `predict` and `predict_with_jacobian` do not allocate
/// once a horizon has been seen.
#[derive(Debug, Clone)]
pub struct Predictor {
    model: Surrogate,
    scaling: Scaling,
    subs: Vec<SequenceWorkspace>,
    combiner: Option<MlpWorkspace>,
    /// The raw past window the warmed-up state belongs to.
    warm_u: Vec<f64>,
    warm_y: Vec<f64>,
    warm_e: Vec<f64>,
    warm: bool,
    /// Scaled (unbiased) predictions.
    y: Vec<f64>,
    /// dȳ_k/dū_j, N × N.
    d: Vec<f64>,
    /// Input tangents of the current step, N × 2.
    dx: Vec<f64>,
    /// Output tangents of the previous step, N.
    dy: Vec<f64>,
}

impl Predictor {
    pub fn new(model: Surrogate, scaling: Scaling) -> Predictor {
        let (subs, combiner) = match &model {
            Surrogate::Single(net) => (vec![net.workspace()], None),
            Surrogate::TwoLayer(m) => (
                m.sub_models.iter().map(SequenceNet::workspace).collect(),
                Some(m.combiner.workspace()),
            ),
        };
        Predictor {
            model,
            scaling,
            subs,
            combiner,
            warm_u: Vec::with_capacity(WINDOW),
            warm_y: Vec::with_capacity(WINDOW),
            warm_e: Vec::with_capacity(WINDOW),
            warm: false,
            y: Vec::new(),
            d: Vec::new(),
            dx: Vec::new(),
            dy: Vec::new(),
        }
    }

    pub fn model(&self) -> &Surrogate {
        &self.model
    }

    pub fn scaling(&self) -> &Scaling {
        &self.scaling
    }

    fn check(
        past: Past<'_>,
        future_u: &[f64],
        future_et0: &[f64],
        out: &[f64],
    ) -> Result<(), RolloutError> {
        let expect = |what, expected, found| {
            if expected == found {
                Ok(())
            } else {
                Err(RolloutError::Length {
                    what,
                    expected,
                    found,
                })
            }
        };
        expect("past_u", WINDOW, past.u.len())?;
        expect("past_y", WINDOW, past.y.len())?;
        expect("past_et0", WINDOW, past.et0.len())?;
        expect("future_et0", future_u.len(), future_et0.len())?;
        expect("out", future_u.len(), out.len())
    }

    /// The rollout in scaled units into `self.y` and, when `jacobian`, the
    /// scaled sensitivities into `self.d`.
    fn run(&mut self, past: Past<'_>, future_u: &[f64], future_et0: &[f64], jacobian: bool) {
        let n = future_u.len();
        let (si, so, se) = (self.scaling.input, self.scaling.output, self.scaling.et0);
        let Predictor {
            model,
            subs,
            combiner,
            warm_u,
            warm_y,
            warm_e,
            warm,
            y,
            d,
            dx,
            dy,
            ..
        } = self;
        let (nets, mlp): (&[SequenceNet], _) = match &*model {
            Surrogate::Single(net) => (std::slice::from_ref(net), None),
            Surrogate::TwoLayer(m) => (&m.sub_models[..], Some(&m.combiner)),
        };
        let cached = *warm
            && warm_u.as_slice() == past.u
            && warm_y.as_slice() == past.y
            && warm_e.as_slice() == past.et0;
        for (net, ws) in nets.iter().zip(subs.iter_mut()) {
            ws.ensure_steps(WINDOW - 1 + n);
            if !cached {
                for tau in 0..WINDOW - 1 {
                    ws.x[tau * FEATURES] = si.scale(past.u[tau + 1]);
                    ws.x[tau * FEATURES + 1] = so.scale(past.y[tau]);
                    ws.x[tau * FEATURES + 2] = se.scale(past.et0[tau + 1]);
                }
                net.advance(ws, 0, WINDOW - 1);
            }
            if jacobian {
                net.reset_tangents(ws, n);
            }
        }
        if !cached {
            warm_u.clear();
            warm_u.extend_from_slice(past.u);
            warm_y.clear();
            warm_y.extend_from_slice(past.y);
            warm_e.clear();
            warm_e.extend_from_slice(past.et0);
            *warm = true;
        }
        y.clear();
        y.resize(n, 0.0);
        if jacobian {
            d.clear();
            d.resize(n * n, 0.0);
            dx.clear();
            dx.resize(n * FEATURES, 0.0);
            dy.clear();
            dy.resize(n, 0.0);
        }
        let mut prev = so.scale(past.y[WINDOW - 1]);
        for k in 0..n {
            let t = WINDOW - 1 + k;
            let uk = si.scale(future_u[k]);
            let ek = se.scale(future_et0[k]);
            let mut z = [0.0; 3];
            for ((net, ws), zi) in nets.iter().zip(subs.iter_mut()).zip(&mut z) {
                ws.x[t * FEATURES] = uk;
                ws.x[t * FEATURES + 1] = prev;
                ws.x[t * FEATURES + 2] = ek;
                net.advance(ws, t, t + 1);
                *zi = net.output(ws, t);
            }
            let out = match (mlp, combiner.as_mut()) {
                (Some(mlp), Some(c)) => {
                    c.x = z;
                    mlp.forward(c)
                }
                _ => z[0],
            };
            if jacobian {
                let dirs = k + 1;
                for j in 0..dirs {
                    dx[j * FEATURES] = if j == k { 1.0 } else { 0.0 };
                    dx[j * FEATURES + 1] = dy[j];
                    // ET0 is given: no tangent
                    dx[j * FEATURES + 2] = 0.0;
                }
                for (net, ws) in nets.iter().zip(subs.iter_mut()) {
                    net.tangent_step(ws, t, dirs, dx);
                }
                match (mlp, combiner.as_mut()) {
                    (Some(mlp), Some(c)) => {
                        mlp.backward(c, 1.0, None);
                        for (j, v) in dy[..dirs].iter_mut().enumerate() {
                            *v = subs.iter().zip(&c.dx).map(|(ws, g)| g * ws.tz[j]).sum();
                        }
                    }
                    _ => dy[..dirs].copy_from_slice(&subs[0].tz[..dirs]),
                }
                d[k * n..k * n + dirs].copy_from_slice(&dy[..dirs]);
            }
            y[k] = out;
            prev = out;
        }
    }

    /// Recursive prediction ŷ[k] of y[t + k], k = 0..N, into `out` (N =
    /// `future_u.len()`, as many forecast ET0 rates in `future_et0`), with
    /// `bias` added to the returned values only. See the module docs for the
    /// convention.
    pub fn predict(
        &mut self,
        past: Past<'_>,
        future_u: &[f64],
        future_et0: &[f64],
        bias: f64,
        out: &mut [f64],
    ) -> Result<(), RolloutError> {
        Self::check(past, future_u, future_et0, out)?;
        self.run(past, future_u, future_et0, false);
        let so = self.scaling.output;
        for (o, &v) in out.iter_mut().zip(&self.y) {
            *o = so.unscale(v) + bias;
        }
        Ok(())
    }

    /// [`predict`](Self::predict) and the exact Jacobian dŷ_k/du_j [(m³/m³)/(m/s)]
    /// into `jacobian` (N × N row-major, `jacobian[k·N + j]`; zero above the
    /// diagonal).
    pub fn predict_with_jacobian(
        &mut self,
        past: Past<'_>,
        future_u: &[f64],
        future_et0: &[f64],
        bias: f64,
        out: &mut [f64],
        jacobian: &mut [f64],
    ) -> Result<(), RolloutError> {
        Self::check(past, future_u, future_et0, out)?;
        let n = future_u.len();
        if jacobian.len() != n * n {
            return Err(RolloutError::Length {
                what: "jacobian",
                expected: n * n,
                found: jacobian.len(),
            });
        }
        self.run(past, future_u, future_et0, true);
        let (si, so) = (self.scaling.input, self.scaling.output);
        for (o, &v) in out.iter_mut().zip(&self.y) {
            *o = so.unscale(v) + bias;
        }
        let span = so.span();
        for (jrow, drow) in jacobian.chunks_exact_mut(n).zip(self.d.chunks_exact(n)) {
            for ((jv, &dv), &u) in jrow.iter_mut().zip(drow).zip(future_u) {
                *jv = span * dv * si.derivative(u);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surrogate::network::tests::jiggle;
    use crate::surrogate::network::{Mlp, SequenceNet, TwoLayerNet};

    fn single(hidden: &[usize]) -> Surrogate {
        let mut net = SequenceNet::new(hidden, 21);
        let mut p = net.params().to_vec();
        jiggle(&mut p, 22, 0.2);
        net.set_params(&p).unwrap();
        Surrogate::Single(net)
    }

    fn two_layer(hidden: usize, combiner: usize) -> Surrogate {
        let mut m = Surrogate::TwoLayer(TwoLayerNet {
            sub_models: [
                SequenceNet::new(&[hidden], 1),
                SequenceNet::new(&[hidden], 2),
                SequenceNet::new(&[hidden, hidden], 3),
            ],
            combiner: Mlp::new(combiner, 4),
        });
        let mut p = m.params();
        jiggle(&mut p, 5, 0.2);
        m.set_params(&p).unwrap();
        m
    }

    /// A past window, a plan with rates in the interior (1e-7..5e-6 m/s)
    /// and its ET0.
    struct Scenario {
        past_u: Vec<f64>,
        past_y: Vec<f64>,
        past_e: Vec<f64>,
        future_u: Vec<f64>,
        future_e: Vec<f64>,
    }

    impl Scenario {
        fn past(&self) -> Past<'_> {
            Past {
                u: &self.past_u,
                y: &self.past_y,
                et0: &self.past_e,
            }
        }
    }

    /// A diurnal ET0 rate around 4 mm/day [m/s].
    fn et0_at(k: usize) -> f64 {
        4.63e-8 * (1.0 + (k as f64 * std::f64::consts::PI / 6.0).sin())
    }

    fn scenario(n: usize) -> Scenario {
        let past_u: Vec<f64> = (0..WINDOW)
            .map(|i| if i % 4 == 0 { 3e-6 } else { 2e-7 })
            .collect();
        let past_y: Vec<f64> = (0..WINDOW)
            .map(|i| 0.25 + 0.03 * (i as f64 / 3.0).sin())
            .collect();
        let future_u: Vec<f64> = (0..n)
            .map(|k| 1e-7 + 4.9e-6 * (0.5 + 0.5 * (k as f64 * 1.3).sin()))
            .collect();
        Scenario {
            past_u,
            past_y,
            past_e: (0..WINDOW).map(et0_at).collect(),
            future_u,
            future_e: (WINDOW..WINDOW + n).map(et0_at).collect(),
        }
    }

    #[test]
    fn one_step_rollout_is_a_forward_pass_on_the_hand_built_window() {
        let Surrogate::Single(net) = single(&[4, 3]) else {
            unreachable!()
        };
        let scaling = Scaling::default();
        let sc = scenario(1);
        let mut p = Predictor::new(Surrogate::Single(net.clone()), scaling);
        let mut out = [0.0];
        p.predict(sc.past(), &sc.future_u, &sc.future_e, 0.0, &mut out)
            .unwrap();
        // window: u[t−19..=t] = past_u[1..] ++ future_u[0], y[t−20..t] =
        // past_y, ET0 with the supply
        let u: Vec<f64> = sc.past_u[1..]
            .iter()
            .chain(&sc.future_u[..1])
            .map(|&v| scaling.input.scale(v))
            .collect();
        let y: Vec<f64> = sc.past_y.iter().map(|&v| scaling.output.scale(v)).collect();
        let e: Vec<f64> = sc.past_e[1..]
            .iter()
            .chain(&sc.future_e[..1])
            .map(|&v| scaling.et0.scale(v))
            .collect();
        let direct = scaling
            .output
            .unscale(net.predict(&mut net.workspace(), &u, &y, &e));
        assert_eq!(out[0], direct);
        // the bias shifts the returned value only
        let mut biased = [0.0];
        p.predict(sc.past(), &sc.future_u, &sc.future_e, 0.01, &mut biased)
            .unwrap();
        assert!((biased[0] - direct - 0.01).abs() < 1e-15);
    }

    #[test]
    fn later_steps_continue_the_recurrence_on_the_unbiased_prediction() {
        let Surrogate::Single(net) = single(&[3]) else {
            unreachable!()
        };
        let scaling = Scaling::default();
        let sc = scenario(2);
        let mut p = Predictor::new(Surrogate::Single(net.clone()), scaling);
        let mut out = [0.0; 2];
        p.predict(sc.past(), &sc.future_u, &sc.future_e, 0.05, &mut out)
            .unwrap();
        // the 21-step sequence by hand: window, then (u[t + 1], ŷ[t], ē[t + 1])
        let y1 = out[0] - 0.05;
        let su = |v: f64| scaling.input.scale(v);
        let sy = |v: f64| scaling.output.scale(v);
        let se = |v: f64| scaling.et0.scale(v);
        let mut steps: Vec<[f64; 3]> = (0..WINDOW - 1)
            .map(|tau| {
                [
                    su(sc.past_u[tau + 1]),
                    sy(sc.past_y[tau]),
                    se(sc.past_e[tau + 1]),
                ]
            })
            .collect();
        steps.push([
            su(sc.future_u[0]),
            sy(sc.past_y[WINDOW - 1]),
            se(sc.future_e[0]),
        ]);
        steps.push([su(sc.future_u[1]), sy(y1), se(sc.future_e[1])]);
        let mut ws = net.workspace();
        ws.ensure_steps(steps.len());
        for (t, step) in steps.iter().enumerate() {
            ws.x[FEATURES * t..FEATURES * (t + 1)].copy_from_slice(step);
        }
        net.advance(&mut ws, 0, steps.len());
        let direct = scaling.output.unscale(net.output(&ws, WINDOW));
        assert!((out[1] - 0.05 - direct).abs() < 1e-14);
    }

    #[test]
    fn the_kept_warm_up_is_only_reused_for_the_same_past() {
        let model = two_layer(5, 4);
        let sc = scenario(20);
        let (fu, fe) = (&sc.future_u, &sc.future_e);
        let mut other = scenario(20);
        other.past_y[3] += 0.01;
        let mut other_e = scenario(20);
        other_e.past_e[7] *= 3.0;
        for changed in [&other, &other_e] {
            let mut reused = Predictor::new(model.clone(), Scaling::default());
            let mut a = vec![0.0; 20];
            reused.predict(sc.past(), fu, fe, 0.0, &mut a).unwrap();
            reused.predict(changed.past(), fu, fe, 0.0, &mut a).unwrap();
            let mut fresh = Predictor::new(model.clone(), Scaling::default());
            let mut b = vec![0.0; 20];
            fresh.predict(changed.past(), fu, fe, 0.0, &mut b).unwrap();
            assert_eq!(a, b);
            // and a changed past changes the prediction
            let mut c = vec![0.0; 20];
            fresh.predict(sc.past(), fu, fe, 0.0, &mut c).unwrap();
            assert_ne!(a, c);
        }
    }

    fn check_jacobian(model: Surrogate, n: usize) {
        let mut p = Predictor::new(model, Scaling::default());
        let sc = scenario(n);
        let (future_u, fe) = (&sc.future_u, &sc.future_e);
        let mut out = vec![0.0; n];
        let mut jac = vec![0.0; n * n];
        p.predict_with_jacobian(sc.past(), future_u, fe, 0.02, &mut out, &mut jac)
            .unwrap();
        let mut plain = vec![0.0; n];
        p.predict(sc.past(), future_u, fe, 0.02, &mut plain)
            .unwrap();
        assert_eq!(out, plain);
        let mut biggest: f64 = 0.0;
        for j in 0..n {
            let h = 1e-4 * future_u[j];
            let (mut up, mut down) = (future_u.clone(), future_u.clone());
            up[j] += h;
            down[j] -= h;
            let (mut yp, mut ym) = (vec![0.0; n], vec![0.0; n]);
            p.predict(sc.past(), &up, fe, 0.02, &mut yp).unwrap();
            p.predict(sc.past(), &down, fe, 0.02, &mut ym).unwrap();
            // scale for the relative error: the largest entry of the column
            let col_scale = (0..n)
                .map(|k| jac[k * n + j].abs())
                .fold(0.0, f64::max)
                .max(1e-12);
            for k in 0..n {
                let fd = (yp[k] - ym[k]) / (2.0 * h);
                let a = jac[k * n + j];
                if k < j {
                    assert_eq!(a, 0.0);
                    assert_eq!(fd, 0.0, "future input cannot act on the past");
                    continue;
                }
                let err = (fd - a).abs() / fd.abs().max(a.abs()).max(1e-3 * col_scale);
                assert!(err < 1e-5, "J[{k}][{j}]: fd {fd} vs {a}");
                biggest = biggest.max(a.abs());
            }
        }
        // nontrivial: irrigation moves the prediction noticeably
        assert!(biggest > 100.0, "{biggest}");
    }

    #[test]
    fn single_lstm_jacobian_matches_finite_differences() {
        check_jacobian(single(&[4, 3]), 23);
    }

    #[test]
    fn two_layer_jacobian_matches_finite_differences() {
        check_jacobian(two_layer(4, 3), 20);
    }

    #[test]
    fn wrong_lengths_are_errors() {
        let mut p = Predictor::new(single(&[2]), Scaling::default());
        let mut out = [0.0; 3];
        let past = |n_u: usize, n_e: usize| Past {
            u: &[0.0; 20][..n_u],
            y: &[0.2; 20],
            et0: &[4e-8; 20][..n_e],
        };
        assert_eq!(
            p.predict(past(19, 20), &[0.0; 3], &[0.0; 3], 0.0, &mut out),
            Err(RolloutError::Length {
                what: "past_u",
                expected: 20,
                found: 19
            })
        );
        assert_eq!(
            p.predict(past(20, 20), &[0.0; 3], &[0.0; 2], 0.0, &mut out),
            Err(RolloutError::Length {
                what: "future_et0",
                expected: 3,
                found: 2
            })
        );
        assert!(
            p.predict(past(20, 19), &[0.0; 3], &[0.0; 3], 0.0, &mut out)
                .is_err()
        );
        let mut jac = [0.0; 8];
        assert!(
            p.predict_with_jacobian(past(20, 20), &[0.0; 3], &[0.0; 3], 0.0, &mut out, &mut jac)
                .is_err()
        );
    }
}
