//! N-step recursive prediction with a [`Surrogate`] and its exact Jacobian
//! with respect to the future irrigation rates.
//!
//! # Time convention
//!
//! The same as [`super::evaluate`] and [`super::dataset::Series`]: u[k] is the
//! irrigation rate applied over sampling step k and y[k] the water content
//! measured at the end of that step. At the current time t:
//!
//! * `past_u[i] = u[t − 20 + i]`, `past_y[i] = y[t − 20 + i]` for i = 0..20
//!   (the last measured output is y[t − 1]);
//! * `future_u[k] = u[t + k]` for k = 0..N (the plan; `future_u[0]` is the rate
//!   applied from now);
//! * the result `ŷ[k]` predicts y[t + k], the water content at the end of the
//!   step over which `future_u[k]` is applied.
//!
//! The network predicting y[s] sees the window (ū[s − 19..=s], ȳ[s − 20..s]):
//! window step τ = 0..20 is the pair (ū[s − 19 + τ], ȳ[s − 20 + τ]), i.e. the
//! input applied over the step being predicted is the last input of the
//! window. For ŷ[0] this is (`past_u[1..20]` ++ [`future_u[0]`], `past_y[0..20]`).
//! Outputs y[s] with s ≥ t are the model's own (unbiased) predictions fed back.
//!
//! # Output correction
//!
//! The additive correction `bias` is applied to the returned outputs only:
//! ŷ[k] = y(ȳ_k) + bias, while the windows are fed back the uncorrected
//! predictions. The Jacobian is therefore independent of `bias`.
//!
//! # Jacobian
//!
//! After the forward pass each window's local gradient g = ∂ȳ_k/∂(window) is
//! computed by one backward pass (inputs only). With D[k][j] = dȳ_k/dū_j
//! the chain rule through the fed-back outputs is
//!
//! ```text
//! D[k][j] = g_u[k][τ = j − k + 19] + Σ_{m<k} g_y[k][τ = m − k + 20] · D[m][j]
//! ```
//!
//! (terms whose τ falls outside 0..20 vanish), and in raw units
//! dŷ_k/du_j = (y_max − y_min) · D[k][j] · dū/du(u_j). The matrix is lower
//! triangular: ŷ_k does not depend on rates applied after step k.

use super::evaluate::WINDOW;
use super::network::{FEATURES, Surrogate, SurrogateWorkspace};
use super::scaling::Scaling;

/// Default prediction horizon N.
pub const HORIZON: usize = 20;

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
    ws: SurrogateWorkspace,
    /// Scaled inputs: 20 past then N future.
    u: Vec<f64>,
    /// Scaled outputs: 20 past then N predicted.
    y: Vec<f64>,
    /// The current window.
    x: Vec<f64>,
    /// Local window gradients, N × (2·WINDOW).
    local: Vec<f64>,
    /// dȳ_k/dū_j, N × N.
    d: Vec<f64>,
}

impl Predictor {
    pub fn new(model: Surrogate, scaling: Scaling) -> Predictor {
        let ws = model.workspace();
        Predictor {
            model,
            scaling,
            ws,
            u: Vec::new(),
            y: Vec::new(),
            x: vec![0.0; WINDOW * FEATURES],
            local: Vec::new(),
            d: Vec::new(),
        }
    }

    pub fn model(&self) -> &Surrogate {
        &self.model
    }

    pub fn scaling(&self) -> &Scaling {
        &self.scaling
    }

    fn check(
        past_u: &[f64],
        past_y: &[f64],
        future_u: &[f64],
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
        expect("past_u", WINDOW, past_u.len())?;
        expect("past_y", WINDOW, past_y.len())?;
        expect("out", future_u.len(), out.len())
    }

    /// Forward rollout in scaled units: fills `self.y[WINDOW..]` and, when
    /// `local` is set, the local window gradients.
    fn run(&mut self, past_u: &[f64], past_y: &[f64], future_u: &[f64], local: bool) {
        let n = future_u.len();
        let (si, so) = (self.scaling.input, self.scaling.output);
        self.u.clear();
        self.u
            .extend(past_u.iter().chain(future_u).map(|&v| si.scale(v)));
        self.y.clear();
        self.y.extend(past_y.iter().map(|&v| so.scale(v)));
        self.y.resize(WINDOW + n, 0.0);
        if local {
            self.local.resize(n * WINDOW * FEATURES, 0.0);
        }
        for k in 0..n {
            // window for y[t + k]: ū[k + 1 ..= k + 20], ȳ[k .. k + 20] (array positions)
            for (tau, pair) in self.x.chunks_exact_mut(FEATURES).enumerate() {
                pair[0] = self.u[k + 1 + tau];
                pair[1] = self.y[k + tau];
            }
            let out = self.model.forward(&mut self.ws, &self.x);
            self.y[WINDOW + k] = out;
            if local {
                self.model.input_gradient(&mut self.ws);
                self.local[k * WINDOW * FEATURES..(k + 1) * WINDOW * FEATURES]
                    .copy_from_slice(&self.ws.dx);
            }
        }
    }

    /// Recursive prediction ŷ[k] of y[t + k], k = 0..N, into `out` (N =
    /// `future_u.len()`), with `bias` added to the returned values only. See
    /// the module docs for the convention.
    pub fn predict(
        &mut self,
        past_u: &[f64],
        past_y: &[f64],
        future_u: &[f64],
        bias: f64,
        out: &mut [f64],
    ) -> Result<(), RolloutError> {
        Self::check(past_u, past_y, future_u, out)?;
        self.run(past_u, past_y, future_u, false);
        let so = self.scaling.output;
        for (o, &v) in out.iter_mut().zip(&self.y[WINDOW..]) {
            *o = so.unscale(v) + bias;
        }
        Ok(())
    }

    /// [`predict`](Self::predict) and the exact Jacobian dŷ_k/du_j [(m³/m³)/(m/s)]
    /// into `jacobian` (N × N row-major, `jacobian[k·N + j]`; zero above the
    /// diagonal).
    pub fn predict_with_jacobian(
        &mut self,
        past_u: &[f64],
        past_y: &[f64],
        future_u: &[f64],
        bias: f64,
        out: &mut [f64],
        jacobian: &mut [f64],
    ) -> Result<(), RolloutError> {
        Self::check(past_u, past_y, future_u, out)?;
        let n = future_u.len();
        if jacobian.len() != n * n {
            return Err(RolloutError::Length {
                what: "jacobian",
                expected: n * n,
                found: jacobian.len(),
            });
        }
        self.run(past_u, past_y, future_u, true);
        let (si, so) = (self.scaling.input, self.scaling.output);
        for (o, &v) in out.iter_mut().zip(&self.y[WINDOW..]) {
            *o = so.unscale(v) + bias;
        }
        // D[k][j] = g_u[k][j − k + 19] + Σ_{m<k, m ≥ k−20} g_y[k][m − k + 20]·D[m][j]
        self.d.clear();
        self.d.resize(n * n, 0.0);
        for k in 0..n {
            let g = &self.local[k * WINDOW * FEATURES..(k + 1) * WINDOW * FEATURES];
            let (done, row_and_rest) = self.d.split_at_mut(k * n);
            let row = &mut row_and_rest[..n];
            // direct: window step τ = j − k + 19 ∈ 0..20 ⇔ j ∈ k−19..=k
            for j in (k + 1).saturating_sub(WINDOW)..=k {
                row[j] = g[(j + WINDOW - 1 - k) * FEATURES];
            }
            // through the fed-back outputs ȳ_m, m ∈ max(0, k−20)..k
            for m in k.saturating_sub(WINDOW)..k {
                let gy = g[(m + WINDOW - k) * FEATURES + 1];
                let dm = &done[m * n..m * n + m + 1];
                for (r, &v) in row.iter_mut().zip(dm) {
                    *r += gy * v;
                }
            }
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

    /// A past window and a plan with rates in the interior (1e-7..5e-6 m/s).
    fn scenario(n: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let past_u: Vec<f64> = (0..WINDOW)
            .map(|i| if i % 4 == 0 { 3e-6 } else { 2e-7 })
            .collect();
        let past_y: Vec<f64> = (0..WINDOW)
            .map(|i| 0.25 + 0.03 * (i as f64 / 3.0).sin())
            .collect();
        let future_u: Vec<f64> = (0..n)
            .map(|k| 1e-7 + 4.9e-6 * (0.5 + 0.5 * (k as f64 * 1.3).sin()))
            .collect();
        (past_u, past_y, future_u)
    }

    #[test]
    fn one_step_rollout_is_a_forward_pass_on_the_hand_built_window() {
        let Surrogate::Single(net) = single(&[4, 3]) else {
            unreachable!()
        };
        let scaling = Scaling::default();
        let (past_u, past_y, future_u) = scenario(1);
        let mut p = Predictor::new(Surrogate::Single(net.clone()), scaling);
        let mut out = [0.0];
        p.predict(&past_u, &past_y, &future_u, 0.0, &mut out)
            .unwrap();
        // window: u[t−19..=t] = past_u[1..] ++ future_u[0], y[t−20..t] = past_y
        let u: Vec<f64> = past_u[1..]
            .iter()
            .chain(&future_u[..1])
            .map(|&v| scaling.input.scale(v))
            .collect();
        let y: Vec<f64> = past_y.iter().map(|&v| scaling.output.scale(v)).collect();
        let direct = scaling
            .output
            .unscale(net.predict(&mut net.workspace(), &u, &y));
        assert_eq!(out[0], direct);
        // the bias shifts the returned value only
        let mut biased = [0.0];
        p.predict(&past_u, &past_y, &future_u, 0.01, &mut biased)
            .unwrap();
        assert!((biased[0] - direct - 0.01).abs() < 1e-15);
    }

    #[test]
    fn second_step_feeds_back_the_unbiased_prediction() {
        let Surrogate::Single(net) = single(&[3]) else {
            unreachable!()
        };
        let scaling = Scaling::default();
        let (past_u, past_y, future_u) = scenario(2);
        let mut p = Predictor::new(Surrogate::Single(net.clone()), scaling);
        let mut out = [0.0; 2];
        p.predict(&past_u, &past_y, &future_u, 0.05, &mut out)
            .unwrap();
        let y1 = out[0] - 0.05;
        let u: Vec<f64> = past_u[2..]
            .iter()
            .chain(&future_u[..2])
            .map(|&v| scaling.input.scale(v))
            .collect();
        let y: Vec<f64> = past_y[1..]
            .iter()
            .chain(&[y1])
            .map(|&v| scaling.output.scale(v))
            .collect();
        let direct = scaling
            .output
            .unscale(net.predict(&mut net.workspace(), &u, &y));
        assert!((out[1] - 0.05 - direct).abs() < 1e-14);
    }

    fn check_jacobian(model: Surrogate, n: usize) {
        let mut p = Predictor::new(model, Scaling::default());
        let (past_u, past_y, future_u) = scenario(n);
        let mut out = vec![0.0; n];
        let mut jac = vec![0.0; n * n];
        p.predict_with_jacobian(&past_u, &past_y, &future_u, 0.02, &mut out, &mut jac)
            .unwrap();
        let mut plain = vec![0.0; n];
        p.predict(&past_u, &past_y, &future_u, 0.02, &mut plain)
            .unwrap();
        assert_eq!(out, plain);
        let mut biggest: f64 = 0.0;
        for j in 0..n {
            let h = 1e-4 * future_u[j];
            let (mut up, mut down) = (future_u.clone(), future_u.clone());
            up[j] += h;
            down[j] -= h;
            let (mut yp, mut ym) = (vec![0.0; n], vec![0.0; n]);
            p.predict(&past_u, &past_y, &up, 0.02, &mut yp).unwrap();
            p.predict(&past_u, &past_y, &down, 0.02, &mut ym).unwrap();
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
        assert_eq!(
            p.predict(&[0.0; 19], &[0.2; 20], &[0.0; 3], 0.0, &mut out),
            Err(RolloutError::Length {
                what: "past_u",
                expected: 20,
                found: 19
            })
        );
        let mut jac = [0.0; 8];
        assert!(
            p.predict_with_jacobian(&[0.0; 20], &[0.2; 20], &[0.0; 3], 0.0, &mut out, &mut jac)
                .is_err()
        );
    }
}
