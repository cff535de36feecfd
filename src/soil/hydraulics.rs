//! Van Genuchten–Mualem soil hydraulics.
//!
//! Retention (van Genuchten 1980) and conductivity (Mualem 1976), with the
//! parameter sets of Carsel & Parrish (1988) for the twelve USDA textures.
//! Inside the kernels the usual symbols are used:
//!
//! ```text
//! a   = α·|h|                          (h < 0)
//! Se  = (1 + a^n)^(−m),  m = 1 − 1/n
//! θ   = θr + (θs − θr)·Se
//! C   = dθ/dh = (θs − θr)·α·n·m·a^(n−1)·(1 + a^n)^(−m−1)
//! K   = Ks·Se^½·[1 − (1 − Se^(1/m))^m]² = Ks·Se^½·(1 − a^(n−1)·Se)²
//! ```
//!
//! The last form of K follows from `(1 − Se^(1/m))^m = (a^n/(1+a^n))^m = a^(n−1)·Se`
//! and needs one power less. For h ≥ 0 the soil is saturated: Se = 1, θ = θs,
//! K = Ks, C = 0.

use std::fmt;
use std::str::FromStr;

/// Parameters of the van Genuchten–Mualem model. SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VanGenuchten {
    /// Residual water content θr [m³/m³].
    pub residual_water_content: f64,
    /// Saturated water content θs [m³/m³].
    pub saturated_water_content: f64,
    /// Inverse air-entry scale α [1/m].
    pub alpha: f64,
    /// Pore-size distribution index n [-], n > 1.
    pub n: f64,
    /// Saturated hydraulic conductivity Ks [m/s].
    pub saturated_conductivity: f64,
    /// Specific storage Ss [1/m], added to C so the system stays solvable at saturation.
    pub specific_storage: f64,
}

/// Hydraulic state of one pressure head, with the derivatives the Jacobian needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HydraulicState {
    /// Effective saturation Se [-].
    pub effective_saturation: f64,
    /// Water content θ [m³/m³].
    pub water_content: f64,
    /// Capacity C = dθ/dh [1/m] (without specific storage).
    pub capacity: f64,
    /// Conductivity K [m/s].
    pub conductivity: f64,
    /// dK/dh [1/s].
    pub conductivity_derivative: f64,
}

/// Smallest `a = α|h|` used in dK/dh: it grows like a^(n−2), without bound for
/// n < 2 as h → 0⁻. Below this dK/dh is evaluated at the floor; Se, θ, C and K
/// are always evaluated at the true a. (Flooring a in K too made K jump at
/// h = 0 by 1 − (1 − A_FLOOR^(n−1))² ≈ 2·A_FLOOR^(n−1): 16 % for n = 1.09, on
/// which Newton cycled, see the integrator.)
const A_FLOOR: f64 = 1e-12;

/// |θ(h) + Ss·h − w| at which the inverse w → h is accepted.
const INVERSE_TOLERANCE: f64 = 1e-12;

impl VanGenuchten {
    /// The sandy loam of MODEL.md §1 (Carsel & Parrish 1988, Ks rounded to 1.23e-5 m/s).
    pub const SANDY_LOAM: VanGenuchten = VanGenuchten {
        residual_water_content: 0.065,
        saturated_water_content: 0.41,
        alpha: 7.5,
        n: 1.89,
        saturated_conductivity: 1.23e-5,
        specific_storage: 1e-6,
    };

    /// m = 1 − 1/n.
    pub fn m(&self) -> f64 {
        1.0 - 1.0 / self.n
    }

    /// θs − θr.
    fn range(&self) -> f64 {
        self.saturated_water_content - self.residual_water_content
    }

    /// Checks that the parameters describe a physical soil: every one finite,
    /// 0 ≤ θr < θs ≤ 1, α > 0, n > 1, Ks > 0 and Ss > 0. The message names
    /// the first parameter that is not (by its configuration name).
    pub fn validate(&self) -> Result<(), String> {
        let p = self;
        for (name, v) in [
            ("residual_water_content", p.residual_water_content),
            ("saturated_water_content", p.saturated_water_content),
            ("alpha", p.alpha),
            ("n", p.n),
            ("saturated_conductivity", p.saturated_conductivity),
            ("specific_storage", p.specific_storage),
        ] {
            if !v.is_finite() {
                return Err(format!("{name} must be finite, got {v}"));
            }
        }
        if !(0.0..1.0).contains(&p.residual_water_content) {
            return Err(format!(
                "residual_water_content must be in [0, 1), got {}",
                p.residual_water_content
            ));
        }
        if !(p.residual_water_content < p.saturated_water_content
            && p.saturated_water_content <= 1.0)
        {
            return Err(format!(
                "saturated_water_content must be in (residual_water_content, 1] = ({}, 1], got {}",
                p.residual_water_content, p.saturated_water_content
            ));
        }
        for (name, v, bound) in [
            ("alpha", p.alpha, 0.0),
            ("n", p.n, 1.0),
            ("saturated_conductivity", p.saturated_conductivity, 0.0),
            ("specific_storage", p.specific_storage, 0.0),
        ] {
            if v <= bound {
                return Err(format!("{name} must be > {bound}, got {v}"));
            }
        }
        Ok(())
    }

    /// Effective saturation Se(h).
    pub fn effective_saturation(&self, pressure_head: f64) -> f64 {
        if pressure_head >= 0.0 {
            return 1.0;
        }
        let a = -self.alpha * pressure_head;
        (-self.m() * a.powf(self.n).ln_1p()).exp()
    }

    /// Water content θ(h).
    pub fn water_content(&self, pressure_head: f64) -> f64 {
        if pressure_head >= 0.0 {
            return self.saturated_water_content;
        }
        self.residual_water_content + self.range() * self.effective_saturation(pressure_head)
    }

    /// Capacity C(h) = dθ/dh (without specific storage).
    pub fn capacity(&self, pressure_head: f64) -> f64 {
        self.state(pressure_head).capacity
    }

    /// Conductivity K(h).
    pub fn conductivity(&self, pressure_head: f64) -> f64 {
        self.state(pressure_head).conductivity
    }

    /// Everything at once, sharing the powers: Se, θ, C, K and dK/dh.
    pub fn state(&self, pressure_head: f64) -> HydraulicState {
        if pressure_head >= 0.0 {
            return HydraulicState {
                effective_saturation: 1.0,
                water_content: self.saturated_water_content,
                capacity: 0.0,
                conductivity: self.saturated_conductivity,
                conductivity_derivative: 0.0,
            };
        }
        let a = -self.alpha * pressure_head;
        if a == 0.0 {
            // h < 0 so small that α·h underflows: saturated to round-off
            return self.state(0.0);
        }
        let (se, dse, b, db) = self.kernel(a);
        let sqrt_se = se.sqrt();
        let ks = self.saturated_conductivity;
        let conductivity = ks * sqrt_se * b * b;
        let slope = |se: f64, dse: f64, b: f64, db: f64| {
            if se > 0.0 {
                ks * (0.5 * dse / se.sqrt() * b * b + se.sqrt() * 2.0 * b * db)
            } else {
                0.0
            }
        };
        let conductivity_derivative = if a < A_FLOOR {
            let (se, dse, b, db) = self.kernel(A_FLOOR);
            slope(se, dse, b, db)
        } else {
            slope(se, dse, b, db)
        };
        HydraulicState {
            effective_saturation: se,
            water_content: self.residual_water_content + self.range() * se,
            capacity: self.range() * dse,
            conductivity,
            conductivity_derivative,
        }
    }

    /// Se, dSe/dh, B = 1 − (1 − Se^(1/m))^m and dB/dh at a = α|h| > 0.
    fn kernel(&self, a: f64) -> (f64, f64, f64, f64) {
        let (n, m, alpha) = (self.n, self.m(), self.alpha);
        // one logarithm serves both powers (cheaper than powf, the kernel
        // is most of the integrator's cost): a^(n−1) = e^((n−1)·ln a)
        let ln_a = a.ln();
        let y = ((n - 1.0) * ln_a).exp(); // a^(n−1)
        let x = a * y; // a^n
        let ln_1p_x = x.ln_1p();
        let se = (-m * ln_1p_x).exp();
        // dSe/dh = m·n·α·a^(n−1)·Se/(1 + a^n)
        let dse = m * n * alpha * y * se / (1.0 + x);
        // B = 1 − (1 − Se^(1/m))^m = 1 − a^(n−1)·Se = 1 − (1 + 1/x)^(−m). The middle form
        // cancels when dry (a^(n−1)·Se → 1), the last one does not. There
        // ln(1 + 1/x) = ln(1 + x) − n·ln a, to a relative ε·x·ln(1 + x) < 1e-11
        // while x < 1e4; beyond, its own ln_1p.
        let b = if x < 1.0 {
            1.0 - y * se
        } else if x < 1e4 {
            -(-m * (ln_1p_x - n * ln_a)).exp_m1()
        } else {
            -(-m * (1.0 / x).ln_1p()).exp_m1()
        };
        // dB/dh = m·n·α·a^(n−1)·(1 − B)/(x·(1 + x)) (only used for a ≥ A_FLOOR)
        let db = m * n * alpha * y * (1.0 - b) / (x * (1.0 + x));
        (se, dse, b, db)
    }

    /// Stored water per unit volume, w(h) = θ(h) + Ss·h: the quantity that is conserved.
    pub fn storage(&self, pressure_head: f64) -> f64 {
        self.water_content(pressure_head) + self.specific_storage * pressure_head
    }

    /// Pressure head whose water content is θ (inverse retention, no specific storage).
    /// θ ≥ θs gives 0; θ ≤ θr gives −∞.
    pub fn pressure_head_at(&self, water_content: f64) -> f64 {
        let se = (water_content - self.residual_water_content) / self.range();
        self.head_from_saturation(se)
    }

    fn head_from_saturation(&self, se: f64) -> f64 {
        if se >= 1.0 {
            return 0.0;
        }
        if se <= 0.0 {
            return f64::NEG_INFINITY;
        }
        // a^n = Se^(−1/m) − 1, computed without cancellation near Se = 1.
        let an = (-se.ln() / self.m()).exp_m1();
        -an.powf(1.0 / self.n) / self.alpha
    }

    /// Inverse of [`Self::storage`]: the head h with θ(h) + Ss·h = w, to
    /// |θ(h) + Ss·h − w| ≤ 1e-12.
    ///
    /// Above θs the column is saturated and h = (w − θs)/Ss. Below, Newton's
    /// method on g(h) = θ(h) + Ss·h − w is kept inside a bracket [lo, hi] of the
    /// root, bisecting when a step would leave it: g is increasing,
    /// g(0) = θs − w > 0 and g((w − θs)/Ss) = θ − θs < 0.
    pub fn pressure_head_from_storage(&self, storage: f64) -> f64 {
        let ss = self.specific_storage;
        if storage >= self.saturated_water_content {
            return (storage - self.saturated_water_content) / ss;
        }
        let (mut lo, mut hi) = ((storage - self.saturated_water_content) / ss, 0.0);
        // The closed-form inverse of θ alone is within Ss·h/C of the root.
        let mut h = self.pressure_head_at(storage);
        if !(h.is_finite() && h > lo && h < hi) {
            h = 0.5 * (lo + hi);
        }
        for _ in 0..200 {
            let s = self.state(h);
            let residual = s.water_content + ss * h - storage;
            if residual.abs() <= INVERSE_TOLERANCE {
                break;
            }
            if residual > 0.0 {
                hi = h;
            } else {
                lo = h;
            }
            let newton = h - residual / (s.capacity + ss);
            let next = if newton > lo && newton < hi {
                newton
            } else {
                0.5 * (lo + hi)
            };
            if next == h {
                break;
            }
            h = next;
        }
        h
    }
}

/// The twelve USDA soil textures with the mean parameters of Carsel & Parrish (1988),
/// Water Resources Research 24(5), 755–769, table 3.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Texture {
    Sand,
    LoamySand,
    SandyLoam,
    Loam,
    Silt,
    SiltLoam,
    SandyClayLoam,
    ClayLoam,
    SiltyClayLoam,
    SandyClay,
    SiltyClay,
    Clay,
}

impl Texture {
    /// Every texture, in the order of Carsel & Parrish's table.
    pub const ALL: [Texture; 12] = [
        Texture::Sand,
        Texture::LoamySand,
        Texture::SandyLoam,
        Texture::Loam,
        Texture::Silt,
        Texture::SiltLoam,
        Texture::SandyClayLoam,
        Texture::ClayLoam,
        Texture::SiltyClayLoam,
        Texture::SandyClay,
        Texture::SiltyClay,
        Texture::Clay,
    ];

    /// The name used in configuration and on the command line (`sandy-loam`).
    pub fn name(self) -> &'static str {
        match self {
            Texture::Sand => "sand",
            Texture::LoamySand => "loamy-sand",
            Texture::SandyLoam => "sandy-loam",
            Texture::Loam => "loam",
            Texture::Silt => "silt",
            Texture::SiltLoam => "silt-loam",
            Texture::SandyClayLoam => "sandy-clay-loam",
            Texture::ClayLoam => "clay-loam",
            Texture::SiltyClayLoam => "silty-clay-loam",
            Texture::SandyClay => "sandy-clay",
            Texture::SiltyClay => "silty-clay",
            Texture::Clay => "clay",
        }
    }

    /// The texture's parameters. Table values: θr, θs, α [1/cm], n, Ks [cm/day].
    pub fn parameters(self) -> VanGenuchten {
        if self == Texture::SandyLoam {
            return VanGenuchten::SANDY_LOAM;
        }
        let (theta_r, theta_s, alpha_per_cm, n, ks_cm_per_day) = match self {
            Texture::Sand => (0.045, 0.43, 0.145, 2.68, 712.8),
            Texture::LoamySand => (0.057, 0.41, 0.124, 2.28, 350.2),
            Texture::SandyLoam => unreachable!("returned above"),
            Texture::Loam => (0.078, 0.43, 0.036, 1.56, 24.96),
            Texture::Silt => (0.034, 0.46, 0.016, 1.37, 6.0),
            Texture::SiltLoam => (0.067, 0.45, 0.020, 1.41, 10.8),
            Texture::SandyClayLoam => (0.100, 0.39, 0.059, 1.48, 31.44),
            Texture::ClayLoam => (0.095, 0.41, 0.019, 1.31, 6.24),
            Texture::SiltyClayLoam => (0.089, 0.43, 0.010, 1.23, 1.68),
            Texture::SandyClay => (0.100, 0.38, 0.027, 1.23, 2.88),
            Texture::SiltyClay => (0.070, 0.36, 0.005, 1.09, 0.48),
            Texture::Clay => (0.068, 0.38, 0.008, 1.09, 4.8),
        };
        VanGenuchten {
            residual_water_content: theta_r,
            saturated_water_content: theta_s,
            alpha: alpha_per_cm * 100.0,
            n,
            saturated_conductivity: ks_cm_per_day / 100.0 / 86_400.0,
            specific_storage: 1e-6,
        }
    }
}

impl fmt::Display for Texture {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown texture name; carries the name and the list of known ones.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown soil '{name}' (known: {known})")]
pub struct UnknownTexture {
    pub name: String,
    pub known: String,
}

impl FromStr for Texture {
    type Err = UnknownTexture;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let wanted = s.trim().to_ascii_lowercase().replace(['_', ' '], "-");
        Texture::ALL
            .into_iter()
            .find(|t| t.name() == wanted)
            .ok_or_else(|| UnknownTexture {
                name: s.to_string(),
                known: Texture::ALL.map(Texture::name).join(", "),
            })
    }
}
