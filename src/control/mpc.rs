//! The zone MPC problem and its SQP solver.
//!
//! With ū = u/u_max ∈ [0, 1]^N and Se(θ) = (θ − θr)/(θs − θr):
//!
//! ```text
//! J(ū) = Σ_k Q·dist(Se(ŷ_k(ū)), [Se(low_k), Se(up_k)])² + Σ_k R·ū_k²
//! ```
//!
//! Each SQP iteration linearises the model at the current plan ū⁰,
//! Se(ŷ) ≈ s⁰ + G·(ū − ū⁰) with G = (dŷ/du)·u_max/(θs − θr), and solves the
//! QP of the paper in x = (ū, y_z) with clarabel:
//!
//! ```text
//! min Q·‖G·ū + c − y_z‖² + R·‖ū‖²,  c = s⁰ − G·ū⁰
//! s.t. max(0, ū⁰ − Δ) ≤ ū ≤ min(1, ū⁰ + Δ),  Se(low_k) ≤ y_z,k ≤ Se(up_k)
//! ```
//!
//! (minimising over the slack y_z gives back dist², so the QP's value at ū⁰
//! is J(ū⁰) exactly). The trust region Δ globalises the iteration: a step is
//! accepted when the true objective falls by at least a tenth of what the QP
//! predicted; Δ grows after good steps and shrinks after poor ones. The
//! iteration stops when a step changes no input by more than `step_tolerance`
//! or the predicted decrease is negligible (converged), at the iteration cap,
//! or at the time budget, and always returns the best plan evaluated.

use std::time::{Duration, Instant};

use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettingsBuilder, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus,
};

use super::model::PredictionModel;
use super::zone::ZoneSettings;

/// Settings of the zone MPC (defaults: MODEL.md §4).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MpcSettings {
    pub horizon: usize,
    pub q: f64,
    pub r: f64,
    /// Largest irrigation rate [m/s].
    pub u_max: f64,
    pub zone: ZoneSettings,
    /// Residual and saturated water content of the soil (for Se).
    pub theta_r: f64,
    pub theta_s: f64,
    pub max_iterations: usize,
    /// Largest change of any ū_k below which the iteration has converged.
    pub step_tolerance: f64,
    pub time_budget: Duration,
}

impl Default for MpcSettings {
    fn default() -> Self {
        let soil = crate::soil::VanGenuchten::SANDY_LOAM;
        MpcSettings {
            horizon: 20,
            q: 4000.0,
            r: 100.0,
            u_max: 1e-5,
            zone: ZoneSettings::default(),
            theta_r: soil.residual_water_content,
            theta_s: soil.saturated_water_content,
            max_iterations: 50,
            step_tolerance: 1e-6,
            time_budget: Duration::from_secs(1),
        }
    }
}

/// How a solve ended.
#[derive(Debug, Clone, PartialEq)]
pub enum SolveStatus {
    Converged,
    IterationCap,
    TimeBudget,
    /// The model or the QP failed: the plan is the previous one shifted (or
    /// zero irrigation), for the reason given.
    Fallback(String),
}

/// The result of one solve.
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    /// Planned rates u_k [m/s], k = 0..N; the first is the setpoint.
    pub plan: Vec<f64>,
    /// Predicted θ at the end of each step (empty on a fallback whose model failed).
    pub predicted: Vec<f64>,
    /// (low_k, up_k), k = 1..N.
    pub zone: Vec<(f64, f64)>,
    pub status: SolveStatus,
    pub iterations: usize,
    pub objective: f64,
    pub solve_time: Duration,
}

/// J for predictions `y` and scaled inputs `ubar` (see the module docs).
pub fn objective(settings: &MpcSettings, y: &[f64], ubar: &[f64]) -> f64 {
    let n = y.len();
    let span = settings.theta_s - settings.theta_r;
    let se = |theta: f64| (theta - settings.theta_r) / span;
    let mut j = 0.0;
    for (k, (&yk, &uk)) in y.iter().zip(ubar).enumerate() {
        let (low, up) = settings.zone.bounds(k + 1, n);
        let s = se(yk);
        let d = (se(low) - s).max(0.0) + (s - se(up)).max(0.0);
        j += settings.q * d * d + settings.r * uk * uk;
    }
    j
}

/// The zone MPC: settings and the plan of the last solve (the warm start).
#[derive(Debug, Clone)]
pub struct ZoneMpc {
    pub settings: MpcSettings,
    previous: Option<Vec<f64>>,
}

struct Qp {
    /// ū of the QP's solution.
    ubar: Vec<f64>,
    /// The QP objective at that solution (constant included).
    value: f64,
}

impl ZoneMpc {
    pub fn new(settings: MpcSettings) -> ZoneMpc {
        ZoneMpc {
            settings,
            previous: None,
        }
    }

    /// The previous plan shifted by one step (last entry repeated), scaled
    /// and clamped to [0, 1]; zero irrigation without one.
    fn warm_start(&self) -> Vec<f64> {
        let n = self.settings.horizon;
        let mut u = vec![0.0; n];
        if let Some(prev) = &self.previous {
            for (k, v) in u.iter_mut().enumerate() {
                let p = prev.get(k + 1).or(prev.last()).copied().unwrap_or(0.0);
                *v = if p.is_finite() {
                    (p / self.settings.u_max).clamp(0.0, 1.0)
                } else {
                    0.0
                };
            }
        }
        u
    }

    /// Forgets the previous plan (the next solve starts from zero irrigation).
    pub fn reset(&mut self) {
        self.previous = None;
    }

    /// Solves the zone MPC for the state `model` holds.
    ///
    /// The problem is not convex (the model is not linear), so the SQP runs
    /// from the warm start and, while the time budget lasts, also from no
    /// irrigation and from 20 %, 50 % and 100 % of the largest rate; the best
    /// plan wins.
    pub fn solve(&mut self, model: &mut dyn PredictionModel) -> Solution {
        let start = Instant::now();
        let n = self.settings.horizon;
        let warm = self.warm_start();
        let mut best = self.solve_from(model, warm.clone(), start);
        if matches!(best.status, SolveStatus::Fallback(_)) {
            return best;
        }
        for level in [0.0, 0.2, 0.5, 1.0] {
            if start.elapsed() > self.settings.time_budget {
                break;
            }
            let other = vec![level; n];
            if other == warm {
                continue;
            }
            let sol = self.solve_from(model, other, start);
            if !matches!(sol.status, SolveStatus::Fallback(_)) && sol.objective < best.objective {
                best = Solution {
                    iterations: best.iterations + sol.iterations,
                    ..sol
                };
            } else {
                best.iterations += sol.iterations;
            }
        }
        best.solve_time = start.elapsed();
        self.previous = Some(best.plan.clone());
        best
    }

    /// One SQP run from the scaled plan `ubar`.
    fn solve_from(
        &mut self,
        model: &mut dyn PredictionModel,
        ubar: Vec<f64>,
        start: Instant,
    ) -> Solution {
        let s = self.settings;
        let n = s.horizon;
        let zone: Vec<(f64, f64)> = (1..=n).map(|k| s.zone.bounds(k, n)).collect();
        let mut ubar = ubar;
        let raw = |ub: &[f64]| ub.iter().map(|v| v * s.u_max).collect::<Vec<f64>>();
        let mut y = vec![0.0; n];
        let mut jac = vec![0.0; n * n];
        let fallback = |this: &mut ZoneMpc, ubar: &[f64], reason: String, iterations| {
            let plan = raw(ubar);
            this.previous = Some(plan.clone());
            Solution {
                plan,
                predicted: Vec::new(),
                zone: zone.clone(),
                status: SolveStatus::Fallback(reason),
                iterations,
                objective: f64::NAN,
                solve_time: start.elapsed(),
            }
        };
        if let Err(e) = model.predict_with_jacobian(&raw(&ubar), &mut y, &mut jac) {
            return fallback(self, &ubar, e.to_string(), 0);
        }
        let mut j = objective(&s, &y, &ubar);
        let mut radius = 0.5;
        let mut status = SolveStatus::IterationCap;
        let mut iterations = 0;
        let mut trial_y = vec![0.0; n];
        while iterations < s.max_iterations {
            if start.elapsed() > s.time_budget {
                status = SolveStatus::TimeBudget;
                break;
            }
            iterations += 1;
            let qp = match self.subproblem(&ubar, &y, &jac, radius) {
                Ok(qp) => qp,
                Err(reason) => {
                    if iterations == 1 {
                        return fallback(self, &self.warm_start(), reason, iterations);
                    }
                    status = SolveStatus::Fallback(format!("{reason}; best iterate kept"));
                    break;
                }
            };
            let predicted = j - qp.value;
            let step = qp
                .ubar
                .iter()
                .zip(&ubar)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            if step < s.step_tolerance || predicted <= 1e-10 * (1.0 + j) {
                status = SolveStatus::Converged;
                break;
            }
            let trial = match model.predict(&raw(&qp.ubar), &mut trial_y) {
                Ok(()) => objective(&s, &trial_y, &qp.ubar),
                Err(_) => f64::INFINITY,
            };
            let rho = (j - trial) / predicted;
            if rho > 0.1 {
                ubar = qp.ubar;
                if model
                    .predict_with_jacobian(&raw(&ubar), &mut y, &mut jac)
                    .is_err()
                {
                    // cannot happen for a model that just predicted this plan
                    status = SolveStatus::Fallback("model failed at an accepted plan".into());
                    break;
                }
                j = objective(&s, &y, &ubar);
                if rho > 0.75 && step > 0.99 * radius {
                    radius = (2.0 * radius).min(1.0);
                }
            } else {
                radius = 0.25 * step;
                if radius < s.step_tolerance {
                    status = SolveStatus::Converged;
                    break;
                }
            }
        }
        let plan = raw(&ubar);
        self.previous = Some(plan.clone());
        Solution {
            plan,
            predicted: y,
            zone,
            status,
            iterations,
            objective: j,
            solve_time: start.elapsed(),
        }
    }

    /// The QP of one SQP iteration (module docs) at ū⁰ with predictions `y`
    /// and Jacobian `jac` (raw units), in the trust region `radius`.
    fn subproblem(&self, u0: &[f64], y: &[f64], jac: &[f64], radius: f64) -> Result<Qp, String> {
        let s = &self.settings;
        let n = u0.len();
        let span = s.theta_s - s.theta_r;
        let se = |theta: f64| (theta - s.theta_r) / span;
        // G = Jacobian of Se(ŷ) in ū
        let g: Vec<f64> = jac.iter().map(|v| v * s.u_max / span).collect();
        let c: Vec<f64> = (0..n)
            .map(|k| se(y[k]) - (0..n).map(|j| g[k * n + j] * u0[j]).sum::<f64>())
            .collect();
        // ½xᵀPx + qᵀx with x = (ū, y_z):
        // P = 2[Q·GᵀG + R·I, −Q·Gᵀ; −Q·G, Q·I], q = 2[Q·Gᵀc; −Q·c], + Q·‖c‖²
        let m = 2 * n;
        let mut dense = vec![0.0; m * m];
        for a in 0..n {
            for b in a..n {
                let gg: f64 = (0..n).map(|k| g[k * n + a] * g[k * n + b]).sum();
                dense[a * m + b] = 2.0 * s.q * gg + if a == b { 2.0 * s.r } else { 0.0 };
            }
            for k in 0..n {
                // row a (ū_a), column n + k (y_z,k): −2Q·G[k][a]
                dense[a * m + n + k] = -2.0 * s.q * g[k * n + a];
            }
        }
        for k in 0..n {
            dense[(n + k) * m + n + k] = 2.0 * s.q;
        }
        let mut colptr = vec![0usize];
        let (mut rowval, mut nzval) = (Vec::new(), Vec::new());
        for col in 0..m {
            for row in 0..=col {
                let v = dense[row * m + col];
                if v != 0.0 {
                    rowval.push(row);
                    nzval.push(v);
                }
            }
            colptr.push(rowval.len());
        }
        let p = CscMatrix::new(m, m, colptr, rowval, nzval);
        let mut q = vec![0.0; m];
        for a in 0..n {
            q[a] = 2.0 * s.q * (0..n).map(|k| g[k * n + a] * c[k]).sum::<f64>();
        }
        for k in 0..n {
            q[n + k] = -2.0 * s.q * c[k];
        }
        let constant = s.q * c.iter().map(|v| v * v).sum::<f64>();
        // A·x + s = b, s ≥ 0: for every variable, x ≤ upper and −x ≤ −lower
        let mut colptr = vec![0usize];
        let (mut rowval, mut nzval) = (Vec::new(), Vec::new());
        let mut b = vec![0.0; 2 * m];
        for col in 0..m {
            rowval.extend([2 * col, 2 * col + 1]);
            nzval.extend([1.0, -1.0]);
            colptr.push(rowval.len());
            let (lo, hi) = if col < n {
                ((u0[col] - radius).max(0.0), (u0[col] + radius).min(1.0))
            } else {
                let (low, up) = s.zone.bounds(col - n + 1, n);
                (se(low), se(up))
            };
            b[2 * col] = hi;
            b[2 * col + 1] = -lo;
        }
        let a = CscMatrix::new(2 * m, m, colptr, rowval, nzval);
        let cones = [NonnegativeConeT(2 * m)];
        let settings = DefaultSettingsBuilder::default()
            .verbose(false)
            .max_iter(100)
            .build()
            .map_err(|e| format!("QP settings: {e:?}"))?;
        let mut solver = DefaultSolver::new(&p, &q, &a, &b, &cones, settings)
            .map_err(|e| format!("QP setup: {e:?}"))?;
        solver.solve();
        let sol = &solver.solution;
        match sol.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            other => return Err(format!("QP not solved: {other:?}")),
        }
        if sol.x.iter().any(|v| !v.is_finite()) {
            return Err("QP returned non-finite values".into());
        }
        let ubar: Vec<f64> = sol.x[..n].iter().map(|v| v.clamp(0.0, 1.0)).collect();
        Ok(Qp {
            ubar,
            value: sol.obj_val + constant,
        })
    }
}
