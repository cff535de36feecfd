//! The ensemble Kalman analysis step, on plain matrices.
//!
//! An ensemble is an `n × N` matrix whose columns are the members; the
//! members' predicted observations are an `m × N` matrix. Two updates:
//!
//! * [`Scheme::SquareRoot`], the serial ensemble square-root filter of
//!   Whitaker & Hamill (2002, Mon. Wea. Rev. 130, 1913–1924): observations one
//!   at a time; the mean moves by the Kalman gain of the ensemble covariance,
//!   the deviations shrink by `1 − α̃·K·H` with
//!   `α̃ = 1/(1 + √(R/(HPHᵀ + R)))`, so that the posterior sample covariance
//!   is exactly `(I − KH)P`. No random draws. The predicted observations are
//!   updated with the state (they are part of the augmented state, Anderson
//!   2001, Mon. Wea. Rev. 129, 2884–2903), so later observations of the same
//!   batch see the earlier ones.
//! * [`Scheme::PerturbedObservations`], the stochastic EnKF of Evensen (2003,
//!   Ocean Dynamics 53, 343–367) with the perturbed observations of Burgers,
//!   van Leeuwen & Evensen (1998, Mon. Wea. Rev. 126, 1719–1724): every
//!   member is moved by `K·(y + εⱼ − H(xⱼ))`, `εⱼ ~ N(0, R)`, with
//!   `K = C_xy·(C_yy + R)⁻¹` for the whole batch (a Cholesky factorisation;
//!   a matrix that is not positive definite is reported, never inverted).
//!
//! Optional localisation multiplies the gain's row `i` for observation `k`
//! by a taper `ρ_ik ∈ [0, 1]` (Houtekamer & Mitchell 2001; the taper itself
//! is Gaspari & Cohn 1999, eq. 4.10, in [`gaspari_cohn`]).

use nalgebra::{DMatrix, DVector};
use rand::Rng;

use super::normal;

/// Which ensemble update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scheme {
    SquareRoot,
    PerturbedObservations,
}

/// The update could not be made.
#[derive(Debug, Clone, PartialEq)]
pub enum AnalysisError {
    /// The innovation covariance of the batch (or of observation `k`) is not
    /// positive definite, or not finite.
    NotPositiveDefinite(String),
    /// Shapes do not agree.
    Shape(String),
}

/// Gaspari & Cohn (1999) compactly supported fifth-order taper (their
/// eq. 4.10) at distance `distance` for half-width `c` (support 2c): 1 at 0,
/// 0 from 2c on.
pub fn gaspari_cohn(distance: f64, c: f64) -> f64 {
    if c <= 0.0 {
        return if distance == 0.0 { 1.0 } else { 0.0 };
    }
    let r = distance.abs() / c;
    if r >= 2.0 {
        0.0
    } else if r <= 1.0 {
        (((-0.25 * r + 0.5) * r + 0.625) * r - 5.0 / 3.0) * r * r + 1.0
    } else {
        ((((r / 12.0 - 0.5) * r + 0.625) * r + 5.0 / 3.0) * r - 5.0) * r + 4.0 - 2.0 / (3.0 * r)
    }
}

/// Row means of a matrix.
pub fn row_means(x: &DMatrix<f64>) -> DVector<f64> {
    let n = x.ncols().max(1) as f64;
    DVector::from_iterator(x.nrows(), x.row_iter().map(|r| r.sum() / n))
}

/// Updates `ensemble` (n × N) and its predicted observations `predicted`
/// (m × N) with the observations `y` (m) of error variances `r` (m).
/// `taper(i, k)` is the localisation weight of state row `i` for
/// observation `k` (return 1 for none). Returns the innovation variances
/// `HPHᵀ + R` of each observation (before the update of the batch for the
/// perturbed-observation scheme, before that observation's own update for the
/// serial one).
pub fn analysis(
    ensemble: &mut DMatrix<f64>,
    predicted: &mut DMatrix<f64>,
    y: &[f64],
    r: &[f64],
    scheme: Scheme,
    taper: &dyn Fn(usize, usize) -> f64,
    rng: &mut impl Rng,
) -> Result<Vec<f64>, AnalysisError> {
    let (n, members) = ensemble.shape();
    let m = y.len();
    if predicted.shape() != (m, members) || r.len() != m {
        return Err(AnalysisError::Shape(format!(
            "{m} observations with {} variances need a {m} × {members} prediction matrix, got {:?}",
            r.len(),
            predicted.shape()
        )));
    }
    if members < 2 {
        return Err(AnalysisError::Shape(
            "an ensemble needs at least 2 members".into(),
        ));
    }
    let scale = 1.0 / (members as f64 - 1.0);
    match scheme {
        Scheme::SquareRoot => {
            let mut variances = Vec::with_capacity(m);
            for k in 0..m {
                let x_mean = row_means(ensemble);
                let y_mean = row_means(predicted);
                let y_dev: DVector<f64> =
                    DVector::from_iterator(members, predicted.row(k).iter().map(|v| v - y_mean[k]));
                let hph = y_dev.dot(&y_dev) * scale;
                let s = hph + r[k];
                if !(s.is_finite() && s > 0.0 && r[k] > 0.0) {
                    return Err(AnalysisError::NotPositiveDefinite(format!(
                        "observation {k}: innovation variance {s:e} (HPHᵀ {hph:e}, R {:e})",
                        r[k]
                    )));
                }
                variances.push(s);
                let innovation = y[k] - y_mean[k];
                let shrink = 1.0 / (1.0 + (r[k] / s).sqrt());
                // state rows
                for i in 0..n {
                    let dev_i = ensemble
                        .row(i)
                        .iter()
                        .zip(y_dev.iter())
                        .fold(0.0, |a, (x, yd)| a + (x - x_mean[i]) * yd);
                    let gain = taper(i, k) * dev_i * scale / s;
                    if gain == 0.0 {
                        continue;
                    }
                    for j in 0..members {
                        ensemble[(i, j)] += gain * (innovation - shrink * y_dev[j]);
                    }
                }
                // the predicted observations, as part of the augmented state
                for l in 0..m {
                    let dev_l = predicted
                        .row(l)
                        .iter()
                        .zip(y_dev.iter())
                        .fold(0.0, |a, (x, yd)| a + (x - y_mean[l]) * yd);
                    let gain = dev_l * scale / s;
                    for j in 0..members {
                        predicted[(l, j)] += gain * (innovation - shrink * y_dev[j]);
                    }
                }
            }
            Ok(variances)
        }
        Scheme::PerturbedObservations => {
            let x_mean = row_means(ensemble);
            let y_mean = row_means(predicted);
            let mut x_dev = ensemble.clone();
            for (i, mut row) in x_dev.row_iter_mut().enumerate() {
                row.add_scalar_mut(-x_mean[i]);
            }
            let mut y_dev = predicted.clone();
            for (k, mut row) in y_dev.row_iter_mut().enumerate() {
                row.add_scalar_mut(-y_mean[k]);
            }
            let c_xy = &x_dev * y_dev.transpose() * scale;
            let mut c_yy = &y_dev * y_dev.transpose() * scale;
            for k in 0..m {
                c_yy[(k, k)] += r[k];
            }
            let variances: Vec<f64> = (0..m).map(|k| c_yy[(k, k)]).collect();
            if c_yy.iter().any(|v| !v.is_finite()) || r.iter().any(|&v| v.is_nan() || v <= 0.0) {
                return Err(AnalysisError::NotPositiveDefinite(
                    "the innovation covariance is not finite or R is not positive".into(),
                ));
            }
            let chol = c_yy.clone().cholesky().ok_or_else(|| {
                AnalysisError::NotPositiveDefinite(format!(
                    "the innovation covariance of {m} observations has no Cholesky factor"
                ))
            })?;
            // K = C_xy·C_yy⁻¹, tapered
            let mut gain = chol.solve(&c_xy.transpose()).transpose();
            for i in 0..n {
                for k in 0..m {
                    gain[(i, k)] *= taper(i, k);
                }
            }
            let gain_y = chol
                .solve(&(&y_dev * y_dev.transpose() * scale))
                .transpose();
            let mut d = DMatrix::zeros(m, members);
            for j in 0..members {
                for k in 0..m {
                    d[(k, j)] = y[k] + r[k].sqrt() * normal(rng) - predicted[(k, j)];
                }
            }
            *ensemble += &gain * &d;
            *predicted += &gain_y * &d;
            Ok(variances)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaspari_cohn_is_one_at_zero_zero_beyond_support_and_continuous() {
        assert!((gaspari_cohn(0.0, 1.0) - 1.0).abs() < 1e-15);
        assert_eq!(gaspari_cohn(2.0, 1.0), 0.0);
        assert_eq!(gaspari_cohn(3.0, 1.0), 0.0);
        let (a, b) = (gaspari_cohn(1.0 - 1e-9, 1.0), gaspari_cohn(1.0 + 1e-9, 1.0));
        assert!((a - b).abs() < 1e-7, "{a} {b}");
        assert!((gaspari_cohn(1.0, 1.0) - 5.0 / 24.0).abs() < 1e-12);
    }
}
