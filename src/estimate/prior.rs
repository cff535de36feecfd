//! The soil parameters as the filter sees them, their bounds and their priors.
//!
//! The filter estimates five transformed parameters, in this order:
//! `ln Ks`, `ln α`, `ln(n − 1)`, `θr`, `θs`. The logarithms keep Ks, α and
//! n − 1 positive and make their (multiplicative) uncertainty additive.
//!
//! Priors. A texture prior is centred on the texture's mean parameters of
//! Carsel & Parrish (1988, Water Resour. Res. 24(5), 755–769, table 3), with
//! spreads chosen here (not Carsel & Parrish's within-texture standard
//! deviations, which are far wider for Ks and α): sd 0.7 in ln Ks (a factor
//! of two), 0.25 in ln α, 0.1 in ln(n − 1), 0.01 in θr and 0.02 in θs. They
//! cover MODEL.md §6's perturbed fields (Ks × 0.5 … × 2, α × 0.8 … × 1.3,
//! n × 0.95 … × 1.05) at about one standard deviation. The "unknown" prior is
//! the equal mixture of the twelve texture priors: member j draws from the
//! texture j mod 12 (stratified, so every texture is represented).

use rand::Rng;

use crate::soil::{Texture, VanGenuchten};

use super::normal;

/// Number of estimated parameters.
pub const PARAMETERS: usize = 5;
/// Names of the transformed parameters, in state order.
pub const TRANSFORMED_NAMES: [&str; PARAMETERS] =
    ["ln_ks", "ln_alpha", "ln_n_minus_1", "theta_r", "theta_s"];
/// Names of the natural parameters, in state order.
pub const NAMES: [&str; PARAMETERS] = ["ks", "alpha", "n", "theta_r", "theta_s"];
/// Units of the natural parameters.
pub const UNITS: [&str; PARAMETERS] = ["m/s", "1/m", "-", "m3/m3", "m3/m3"];

/// Prior standard deviations of the transformed parameters around a texture.
pub const TEXTURE_SD: [f64; PARAMETERS] = [0.7, 0.25, 0.1, 0.01, 0.02];

/// Physical bounds of the transformed parameters; the estimate and every
/// member are kept inside them. Ks 1e-9 … 1e-3 m/s, α 0.1 … 50 1/m,
/// n 1.03 … 4, θr 0 … 0.2, θs 0.25 … 0.6.
pub const BOUNDS: [(f64, f64); PARAMETERS] = [
    (-20.723_265_836_946_41, -6.907_755_278_982_137),
    (-std::f64::consts::LN_10, 3.912_023_005_428_146),
    (-3.506_557_897_319_982, 1.098_612_288_668_11),
    (0.0, 0.2),
    (0.25, 0.6),
];
/// Smallest θs − θr kept.
pub const MIN_RANGE: f64 = 0.1;

/// The prior the filter starts from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Prior {
    /// Around one of the twelve textures.
    Texture(Texture),
    /// The mixture of the twelve texture priors.
    Unknown,
    /// Around given parameters, with the texture spreads.
    Soil(VanGenuchten),
}

impl Prior {
    /// The name used on the command line and in snapshots.
    pub fn describe(&self) -> String {
        match self {
            Prior::Texture(t) => t.name().to_string(),
            Prior::Unknown => "unknown".to_string(),
            Prior::Soil(s) => format!(
                "ks={},alpha={},n={},theta_r={},theta_s={}",
                s.saturated_conductivity,
                s.alpha,
                s.n,
                s.residual_water_content,
                s.saturated_water_content
            ),
        }
    }

    /// Draws member `j`'s transformed parameters.
    pub fn sample(&self, j: usize, rng: &mut impl Rng) -> [f64; PARAMETERS] {
        let centre = match self {
            Prior::Texture(t) => to_transformed(&t.parameters()),
            Prior::Soil(s) => to_transformed(s),
            Prior::Unknown => to_transformed(&Texture::ALL[j % Texture::ALL.len()].parameters()),
        };
        let mut p = [0.0; PARAMETERS];
        for q in 0..PARAMETERS {
            p[q] = centre[q] + TEXTURE_SD[q] * normal(rng);
        }
        clamp(&mut p);
        p
    }
}

/// The transformed parameters of a soil.
pub fn to_transformed(s: &VanGenuchten) -> [f64; PARAMETERS] {
    [
        s.saturated_conductivity.ln(),
        s.alpha.ln(),
        (s.n - 1.0).ln(),
        s.residual_water_content,
        s.saturated_water_content,
    ]
}

/// The soil of transformed parameters (clamped to the bounds first);
/// specific storage 1e-6 1/m (MODEL.md §1).
pub fn to_soil(p: &[f64]) -> VanGenuchten {
    let mut q = [0.0; PARAMETERS];
    q.copy_from_slice(&p[..PARAMETERS]);
    clamp(&mut q);
    VanGenuchten {
        saturated_conductivity: q[0].exp(),
        alpha: q[1].exp(),
        n: 1.0 + q[2].exp(),
        residual_water_content: q[3],
        saturated_water_content: q[4],
        specific_storage: 1e-6,
    }
}

/// Keeps transformed parameters inside [`BOUNDS`] with θs − θr ≥ [`MIN_RANGE`]
/// (θr gives way). Non-finite values are left for the caller to detect.
pub fn clamp(p: &mut [f64]) {
    for (q, &(lo, hi)) in BOUNDS.iter().enumerate() {
        if p[q].is_finite() {
            p[q] = p[q].clamp(lo, hi);
        }
    }
    if p[3].is_finite() && p[4].is_finite() && p[4] - p[3] < MIN_RANGE {
        p[3] = (p[4] - MIN_RANGE).max(0.0);
    }
}

/// The natural value of transformed parameter `q`.
pub fn natural(q: usize, value: f64) -> f64 {
    match q {
        0 | 1 => value.exp(),
        2 => 1.0 + value.exp(),
        _ => value,
    }
}
