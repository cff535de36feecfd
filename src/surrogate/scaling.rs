//! Input and output scaling of the surrogates.
//!
//! The networks work on scaled quantities:
//!
//! * water content: affine min-max, ȳ = (y − y_min)/(y_max − y_min), so the
//!   configured range maps to [0, 1];
//! * irrigation rate: logarithmic, ū = ln(1 + u/u₀)/ln(1 + u_max/u₀), which maps
//!   [0, u_max] to [0, 1] and resolves the small rates (u₀ = 1e-8 m/s is the
//!   rate below which the scale becomes linear). Its derivative is
//!   dū/du = 1/((u₀ + u)·ln(1 + u_max/u₀));
//! * reference evapotranspiration ET0 [m/s]: linear, ē = ET0/ET0_ref, with
//!   ET0_ref = 1e-7 m/s (8.64 mm/day), so the daily means of 0.5–8 mm/day
//!   map to about 0.06–0.93 and the midday peaks stay below about 3.

/// Default u₀ of the logarithmic input scaling [m/s].
pub const DEFAULT_U0: f64 = 1e-8;
/// Default largest irrigation rate u_max [m/s].
pub const DEFAULT_U_MAX: f64 = 1e-5;
/// Default ET0 rate mapped to 1 [m/s] (8.64 mm/day).
pub const DEFAULT_ET0_REF: f64 = 1e-7;

/// Logarithmic scaling of the irrigation rate u [m/s].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InputScaling {
    /// Rate where the scale turns from linear to logarithmic [m/s].
    pub u0: f64,
    /// Rate mapped to 1 [m/s].
    pub u_max: f64,
}

impl InputScaling {
    fn log_span(&self) -> f64 {
        (self.u_max / self.u0).ln_1p()
    }

    /// ū = ln(1 + u/u₀)/ln(1 + u_max/u₀); negative rates are treated as 0.
    pub fn scale(&self, u: f64) -> f64 {
        (u.max(0.0) / self.u0).ln_1p() / self.log_span()
    }

    /// dū/du = 1/((u₀ + u)·ln(1 + u_max/u₀)) [s/m]; 0 for negative rates
    /// (where [`scale`](Self::scale) is flat).
    pub fn derivative(&self, u: f64) -> f64 {
        if u < 0.0 {
            0.0
        } else {
            1.0 / ((self.u0 + u) * self.log_span())
        }
    }

    /// The inverse: u = u₀·(exp(ū·ln(1 + u_max/u₀)) − 1).
    pub fn unscale(&self, scaled: f64) -> f64 {
        self.u0 * (scaled * self.log_span()).exp_m1()
    }
}

/// Affine min-max scaling of the water content y [m³/m³].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputScaling {
    /// Water content mapped to 0.
    pub y_min: f64,
    /// Water content mapped to 1.
    pub y_max: f64,
}

impl OutputScaling {
    /// y_max − y_min: dy/dȳ.
    pub fn span(&self) -> f64 {
        self.y_max - self.y_min
    }

    /// ȳ = (y − y_min)/(y_max − y_min).
    pub fn scale(&self, y: f64) -> f64 {
        (y - self.y_min) / self.span()
    }

    /// y = y_min + ȳ·(y_max − y_min).
    pub fn unscale(&self, scaled: f64) -> f64 {
        self.y_min + scaled * self.span()
    }
}

/// Linear scaling of the reference evapotranspiration rate ET0 [m/s].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Et0Scaling {
    /// Rate mapped to 1 [m/s].
    pub reference: f64,
}

impl Et0Scaling {
    /// ē = ET0/ET0_ref; negative or non-finite rates count as 0.
    pub fn scale(&self, et0: f64) -> f64 {
        if et0.is_finite() {
            et0.max(0.0) / self.reference
        } else {
            0.0
        }
    }
}

/// The scalings of a surrogate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scaling {
    pub input: InputScaling,
    pub output: OutputScaling,
    pub et0: Et0Scaling,
}

impl Default for Scaling {
    /// u₀ = 1e-8 m/s, u_max = 1e-5 m/s, y ∈ [0.12, 0.41].
    fn default() -> Self {
        Scaling {
            input: InputScaling {
                u0: DEFAULT_U0,
                u_max: DEFAULT_U_MAX,
            },
            output: OutputScaling {
                y_min: 0.12,
                y_max: 0.41,
            },
            et0: Et0Scaling {
                reference: DEFAULT_ET0_REF,
            },
        }
    }
}

impl Scaling {
    /// Why the scaling is unusable, if it is: parameters must be finite with
    /// 0 < u₀ < u_max, y_min < y_max and ET0_ref > 0.
    pub fn problem(&self) -> Option<&'static str> {
        let InputScaling { u0, u_max } = self.input;
        let OutputScaling { y_min, y_max } = self.output;
        let reference = self.et0.reference;
        if ![u0, u_max, y_min, y_max, reference]
            .iter()
            .all(|v| v.is_finite())
        {
            Some("scaling parameters must be finite")
        } else if !(u0 > 0.0 && u_max > u0) {
            Some("input scaling needs 0 < u0 < u_max")
        } else if y_max <= y_min {
            Some("output scaling needs y_min < y_max")
        } else if reference <= 0.0 {
            Some("ET0 scaling needs et0_ref > 0")
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn input_scaling_maps_the_range_and_inverts() {
        let s = Scaling::default().input;
        assert_eq!(s.scale(0.0), 0.0);
        assert!((s.scale(1e-5) - 1.0).abs() < 1e-15);
        // u = u0 gives ln 2 / ln 1001
        assert!((s.scale(1e-8) - 2f64.ln() / 1001f64.ln()).abs() < 1e-15);
        for u in [0.0, 3e-9, 1e-7, 4.2e-6, 1e-5] {
            assert!((s.unscale(s.scale(u)) - u).abs() <= 1e-12 * (u + 1e-8));
        }
        assert_eq!(s.scale(-1e-6), 0.0);
    }

    #[test]
    fn input_derivative_matches_finite_differences() {
        let s = Scaling::default().input;
        for u in [1e-9, 1e-7, 2e-6, 9e-6] {
            let h = 1e-4 * u;
            let fd = (s.scale(u + h) - s.scale(u - h)) / (2.0 * h);
            let d = s.derivative(u);
            assert!((fd - d).abs() < 1e-7 * d.abs(), "u {u}: {fd} vs {d}");
        }
    }

    #[test]
    fn output_scaling_is_affine() {
        let s = Scaling::default().output;
        assert!((s.scale(0.12)).abs() < 1e-15);
        assert!((s.scale(0.41) - 1.0).abs() < 1e-15);
        assert!((s.unscale(0.5) - 0.265).abs() < 1e-15);
        assert!(Scaling::default().problem().is_none());
        let mut bad = Scaling::default();
        bad.output.y_max = 0.1;
        assert!(bad.problem().is_some());
    }
}
