//! Root water uptake: the Feddes et al. (1978) stress factor and the crop.

/// Feddes water-stress response: uptake is 0 when wetter than `h1` (anaerobiosis),
/// rises linearly to 1 at `h2`, stays 1 down to `h3`, falls linearly to 0 at the
/// wilting point `h4`, and is 0 below. Heads in m, `h1 > h2 > h3 > h4`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feddes {
    pub h1: f64,
    pub h2: f64,
    pub h3: f64,
    pub h4: f64,
}

impl Feddes {
    /// Grass, as in MODEL.md §1.
    pub const GRASS: Feddes = Feddes {
        h1: -0.10,
        h2: -0.25,
        h3: -2.0,
        h4: -80.0,
    };

    pub fn validate(&self) -> Result<(), String> {
        let ok = [self.h1, self.h2, self.h3, self.h4]
            .iter()
            .all(|v| v.is_finite())
            && self.h1 > self.h2
            && self.h2 >= self.h3
            && self.h3 > self.h4;
        if ok {
            Ok(())
        } else {
            Err(format!(
                "Feddes heads must satisfy h1 > h2 >= h3 > h4, got {}, {}, {}, {}",
                self.h1, self.h2, self.h3, self.h4
            ))
        }
    }

    /// Stress factor α_F(h) in [0, 1].
    pub fn stress(&self, pressure_head: f64) -> f64 {
        self.stress_and_derivative(pressure_head).0
    }

    /// α_F(h) and dα_F/dh (one-sided at the kinks: the value of the segment the head lies in).
    pub fn stress_and_derivative(&self, h: f64) -> (f64, f64) {
        let Feddes { h1, h2, h3, h4 } = *self;
        if h > h1 || h < h4 {
            (0.0, 0.0)
        } else if h > h2 {
            ((h1 - h) / (h1 - h2), -1.0 / (h1 - h2))
        } else if h >= h3 {
            (1.0, 0.0)
        } else {
            ((h - h4) / (h3 - h4), 1.0 / (h3 - h4))
        }
    }
}

/// The crop: its coefficient and its roots.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Crop {
    /// Crop coefficient Kc: potential transpiration = Kc·ET0.
    pub crop_coefficient: f64,
    /// Rooting depth z_r [m]: cells whose centre is shallower take up water.
    pub rooting_depth: f64,
    /// Water-stress response.
    pub stress: Feddes,
}

impl Default for Crop {
    /// Grass (Kc = 1) rooted to 0.13 m, MODEL.md §1.
    fn default() -> Self {
        Crop {
            crop_coefficient: 1.0,
            rooting_depth: 0.13,
            stress: Feddes::GRASS,
        }
    }
}

impl Crop {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.crop_coefficient.is_finite() && self.crop_coefficient >= 0.0) {
            return Err(format!(
                "crop coefficient must be finite and >= 0, got {}",
                self.crop_coefficient
            ));
        }
        if !(self.rooting_depth.is_finite() && self.rooting_depth > 0.0) {
            return Err(format!(
                "rooting depth must be > 0, got {}",
                self.rooting_depth
            ));
        }
        self.stress.validate()
    }
}
