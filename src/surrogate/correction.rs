//! Plant-model mismatch correction of the predictions.
//!
//! Two corrections of a prediction ŷ, both fitted on the last f pairs of
//! measured output y(t) and one-step prediction ŷ(t|t−1):
//!
//! * **bias**: y ≈ ŷ + b with b = mean(y − ŷ);
//! * **linear**: y ≈ a·ŷ + b, least squares with a ∈ [0.8, 1.5] and
//!   b ∈ [−0.2, 0.3]. With fewer than two pairs or (nearly) constant ŷ, the fit
//!   falls back to a = 1 and the (clamped) bias.
//!
//! [`CorrectionState`] refits every f steps (f ∈ {1, 2, 5, 10} in the paper).

use std::collections::VecDeque;

/// Bounds of the slope a of the linear correction.
pub const SLOPE_BOUNDS: (f64, f64) = (0.8, 1.5);
/// Bounds of the offset b of the linear correction.
pub const OFFSET_BOUNDS: (f64, f64) = (-0.2, 0.3);

/// y ≈ a·ŷ + b.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correction {
    pub a: f64,
    pub b: f64,
}

impl Default for Correction {
    /// The identity: a = 1, b = 0.
    fn default() -> Self {
        Correction { a: 1.0, b: 0.0 }
    }
}

impl Correction {
    pub fn apply(&self, predicted: f64) -> f64 {
        self.a * predicted + self.b
    }
}

/// Which correction to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorrectionKind {
    Bias,
    Linear,
}

/// b = mean(measured − predicted) over the pairs (a = 1); the identity when empty.
pub fn fit_bias(measured: &[f64], predicted: &[f64]) -> Correction {
    let n = measured.len().min(predicted.len());
    if n == 0 {
        return Correction::default();
    }
    let sum: f64 = measured.iter().zip(predicted).map(|(y, p)| y - p).sum();
    Correction {
        a: 1.0,
        b: sum / n as f64,
    }
}

/// Least-squares y ≈ a·ŷ + b over the pairs, constrained to
/// [`SLOPE_BOUNDS`] × [`OFFSET_BOUNDS`].
///
/// The sum of squares is a convex quadratic in (a, b), so its minimum over the
/// box is the unconstrained minimum if that is inside, otherwise the best of
/// the minima along the four edges (each a clamped 1-D least-squares fit).
pub fn fit_linear(measured: &[f64], predicted: &[f64]) -> Correction {
    let n = measured.len().min(predicted.len());
    let (y, p) = (&measured[..n], &predicted[..n]);
    let clamp_b = |b: f64| b.clamp(OFFSET_BOUNDS.0, OFFSET_BOUNDS.1);
    let fallback = || Correction {
        a: 1.0,
        b: clamp_b(fit_bias(y, p).b),
    };
    if n < 2 {
        return fallback();
    }
    let nf = n as f64;
    let mean_p = p.iter().sum::<f64>() / nf;
    let mean_y = y.iter().sum::<f64>() / nf;
    let spp: f64 = p.iter().map(|v| (v - mean_p) * (v - mean_p)).sum();
    let spy: f64 = p
        .iter()
        .zip(y)
        .map(|(a, b)| (a - mean_p) * (b - mean_y))
        .sum();
    let scale = p.iter().map(|v| v * v).sum::<f64>().max(f64::MIN_POSITIVE);
    if spp <= 1e-12 * scale {
        return fallback();
    }
    let sse = |c: Correction| {
        p.iter()
            .zip(y)
            .map(|(pi, yi)| {
                let r = yi - c.a * pi - c.b;
                r * r
            })
            .sum::<f64>()
    };
    let inside = |c: &Correction| {
        (SLOPE_BOUNDS.0..=SLOPE_BOUNDS.1).contains(&c.a)
            && (OFFSET_BOUNDS.0..=OFFSET_BOUNDS.1).contains(&c.b)
    };
    let a = spy / spp;
    let free = Correction {
        a,
        b: mean_y - a * mean_p,
    };
    if inside(&free) {
        return free;
    }
    // Edges: a fixed → b = mean(y − a·ŷ) clamped; b fixed → a = Σŷ(y − b)/Σŷ² clamped.
    let sum_pp: f64 = p.iter().map(|v| v * v).sum();
    let sum_p: f64 = p.iter().sum();
    let sum_py: f64 = p.iter().zip(y).map(|(a, b)| a * b).sum();
    let mut candidates = Vec::with_capacity(4);
    for a in [SLOPE_BOUNDS.0, SLOPE_BOUNDS.1] {
        candidates.push(Correction {
            a,
            b: clamp_b(mean_y - a * mean_p),
        });
    }
    for b in [OFFSET_BOUNDS.0, OFFSET_BOUNDS.1] {
        let a = ((sum_py - b * sum_p) / sum_pp).clamp(SLOPE_BOUNDS.0, SLOPE_BOUNDS.1);
        candidates.push(Correction { a, b });
    }
    candidates
        .into_iter()
        .map(|c| (sse(c), c))
        .min_by(|x, y| x.0.total_cmp(&y.0))
        .map_or_else(fallback, |(_, c)| c)
}

/// The correction of a running controller: records (measured, predicted)
/// pairs and refits on the last `period` of them every `period` steps.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectionState {
    kind: CorrectionKind,
    period: usize,
    measured: VecDeque<f64>,
    predicted: VecDeque<f64>,
    since_update: usize,
    current: Correction,
}

impl CorrectionState {
    /// A state starting at the identity; `period` is clamped to at least 1.
    pub fn new(kind: CorrectionKind, period: usize) -> CorrectionState {
        let period = period.max(1);
        CorrectionState {
            kind,
            period,
            measured: VecDeque::with_capacity(period),
            predicted: VecDeque::with_capacity(period),
            since_update: 0,
            current: Correction::default(),
        }
    }

    /// Records y(t) and ŷ(t|t−1); refits when `period` pairs arrived since the
    /// last fit. Returns the correction in force.
    pub fn observe(&mut self, measured: f64, predicted: f64) -> Correction {
        if self.measured.len() == self.period {
            self.measured.pop_front();
            self.predicted.pop_front();
        }
        self.measured.push_back(measured);
        self.predicted.push_back(predicted);
        self.since_update += 1;
        if self.since_update >= self.period {
            self.since_update = 0;
            let (y, p) = (
                self.measured.make_contiguous(),
                self.predicted.make_contiguous(),
            );
            self.current = match self.kind {
                CorrectionKind::Bias => fit_bias(y, p),
                CorrectionKind::Linear => fit_linear(y, p),
            };
        }
        self.current
    }

    pub fn current(&self) -> Correction {
        self.current
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bias_is_the_mean_residual() {
        let y = [0.30, 0.31, 0.29];
        let p = [0.28, 0.30, 0.30];
        // (0.02 + 0.01 − 0.01)/3
        let c = fit_bias(&y, &p);
        assert_eq!(c.a, 1.0);
        assert!((c.b - 0.02 / 3.0).abs() < 1e-15);
        assert_eq!(fit_bias(&[], &[]), Correction::default());
    }

    #[test]
    fn linear_fit_recovers_exact_data() {
        let p = [0.20, 0.25, 0.31, 0.36, 0.22];
        let y: Vec<f64> = p.iter().map(|v| 1.2 * v - 0.05).collect();
        let c = fit_linear(&y, &p);
        assert!(
            (c.a - 1.2).abs() < 1e-12 && (c.b + 0.05).abs() < 1e-12,
            "{c:?}"
        );
    }

    #[test]
    fn linear_fit_clamps_to_the_bounds() {
        let p = [0.20, 0.25, 0.30, 0.35];
        // slope 3: clamped to 1.5, the offset refitted for it
        let y: Vec<f64> = p.iter().map(|v| 3.0 * v - 0.5).collect();
        let c = fit_linear(&y, &p);
        assert_eq!(c.a, 1.5);
        // b = mean(y − 1.5 p) = mean(1.5 p − 0.5) = 1.5·0.275 − 0.5 = −0.0875
        assert!((c.b + 0.0875).abs() < 1e-12, "{c:?}");
        // slope 0.5 and offset 0.5: b at its upper bound, a refitted on that
        // edge: a = Σp(y − 0.3)/Σp² = 0.5 + 0.2·Σp/Σp² = 0.5 + 0.2·1.1/0.315
        let y: Vec<f64> = p.iter().map(|v| 0.5 * v + 0.5).collect();
        let c = fit_linear(&y, &p);
        assert_eq!(c.b, 0.3);
        assert!((c.a - (0.5 + 0.2 * 1.1 / 0.315)).abs() < 1e-12, "{c:?}");
        // constrained optimum beats every other feasible corner/edge point
        let sse = |c: Correction| -> f64 {
            p.iter()
                .zip(&y)
                .map(|(pi, yi)| (yi - c.apply(*pi)).powi(2))
                .sum()
        };
        for a in [0.8, 1.0, 1.5] {
            for b in [-0.2, 0.0, 0.3] {
                assert!(sse(c) <= sse(Correction { a, b }) + 1e-15);
            }
        }
    }

    #[test]
    fn degenerate_data_falls_back_to_the_bias() {
        let c = fit_linear(&[0.3], &[0.25]);
        assert_eq!(c.a, 1.0);
        assert!((c.b - 0.05).abs() < 1e-15);
        let c = fit_linear(&[0.3, 0.32], &[0.25, 0.25]);
        assert_eq!(c.a, 1.0);
        assert!((c.b - 0.06).abs() < 1e-15);
        // the fallback bias is clamped to the offset bounds
        assert_eq!(fit_linear(&[0.9], &[0.1]).b, 0.3);
    }

    #[test]
    fn state_refits_every_period_on_the_last_pairs() {
        let mut s = CorrectionState::new(CorrectionKind::Bias, 2);
        assert_eq!(s.observe(0.30, 0.20).b, 0.0); // not yet
        assert!((s.observe(0.30, 0.25).b - 0.075).abs() < 1e-15);
        assert!((s.observe(0.30, 0.30).b - 0.075).abs() < 1e-15); // held
        // last two: residuals 0 and 0.02
        assert!((s.observe(0.30, 0.28).b - 0.01).abs() < 1e-15);
        let mut s = CorrectionState::new(CorrectionKind::Linear, 1);
        assert!((s.observe(0.31, 0.30).b - 0.01).abs() < 1e-15);
        assert_eq!(s.current().a, 1.0);
    }
}
