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

/// The pressure heads [m] of MODEL.md §4's zone: [0.18, 0.23] is the
/// sandy-loam water content between them.
pub const DEFAULT_ZONE_HEADS: (f64, f64) = (-0.43, -0.27);

impl ZoneSettings {
    /// A time-invariant zone between two water contents.
    pub fn band(low: f64, up: f64) -> ZoneSettings {
        ZoneSettings {
            low0: low,
            up0: up,
            y_low: low,
            y_up: up,
            mu: 0.0,
        }
    }

    /// The time-invariant zone of `soil` between two pressure heads [m]
    /// (low_head < up_head ≤ 0): the water contents θ(low_head) … θ(up_head).
    pub fn from_heads(soil: &crate::soil::VanGenuchten, low_head: f64, up_head: f64) -> Self {
        ZoneSettings::band(soil.water_content(low_head), soil.water_content(up_head))
    }

    /// A soil's default zone (MODEL.md §4): [0.18, 0.23] for the sandy loam
    /// of MODEL.md §1, else the water contents of the heads
    /// [`DEFAULT_ZONE_HEADS`] in that soil.
    pub fn default_for(soil: &crate::soil::VanGenuchten) -> ZoneSettings {
        if *soil == crate::soil::VanGenuchten::SANDY_LOAM {
            ZoneSettings::default()
        } else {
            let (low, up) = DEFAULT_ZONE_HEADS;
            ZoneSettings::from_heads(soil, low, up)
        }
    }

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
