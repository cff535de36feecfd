//! The target zone over the horizon (MODEL.md §4).

/// A time-invariant (μ = 0) or shrinking (μ > 0) target zone.
///
/// At prediction step k = 1..N: `low_k = min(low₀·e^(μk/N), Y_low)` and
/// `up_k = max(up₀·e^(−μk/N), Y_up)`: the band narrows towards the terminal
/// zone [Y_low, Y_up] and never beyond it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZoneSettings {
    pub low0: f64,
    pub up0: f64,
    /// Terminal zone.
    pub y_low: f64,
    pub y_up: f64,
    /// Shrinking speed μ (0: time-invariant).
    pub mu: f64,
}

impl Default for ZoneSettings {
    /// The time-invariant zone [0.18, 0.23].
    fn default() -> Self {
        ZoneSettings {
            low0: 0.18,
            up0: 0.23,
            y_low: 0.18,
            y_up: 0.23,
            mu: 0.0,
        }
    }
}

impl ZoneSettings {
    /// (low_k, up_k) at prediction step `k` (1-based) of a horizon `n`.
    pub fn bounds(&self, k: usize, n: usize) -> (f64, f64) {
        let s = self.mu * k as f64 / n.max(1) as f64;
        (
            (self.low0 * s.exp()).min(self.y_low),
            (self.up0 * (-s).exp()).max(self.y_up),
        )
    }

    /// Why the zone cannot be used, if it cannot.
    pub fn problem(&self) -> Option<String> {
        let all = [self.low0, self.up0, self.y_low, self.y_up, self.mu];
        if all.iter().any(|v| !v.is_finite()) {
            Some("zone values must be finite".into())
        } else if !(self.low0 <= self.up0 && self.y_low <= self.y_up) {
            Some(format!(
                "zone bounds must be ordered: low {} ≤ up {}, terminal {} ≤ {}",
                self.low0, self.up0, self.y_low, self.y_up
            ))
        } else if !(self.low0 <= self.y_low && self.y_up <= self.up0) {
            Some("the terminal zone must lie inside the initial zone".into())
        } else if self.mu < 0.0 {
            Some(format!("μ must be ≥ 0, got {}", self.mu))
        } else {
            None
        }
    }
}
