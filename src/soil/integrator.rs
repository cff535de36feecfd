//! The column's own integrator: an L-stable, stiffly accurate SDIRK method of
//! order 3 with an embedded order-2 error estimate (Alexander 1977; Hairer &
//! Wanner, *Solving ODEs II*, §IV.6; three stages, γ ≈ 0.4359), applied to
//! the mixed form of Richards' equation (Celia et al. 1990) with Newton's
//! method on the heads.
//!
//! Stage i of a step from t to t + Δt solves, for the heads Hᵢ,
//!
//! ```text
//! Rᵢ(Hᵢ) = w(Hᵢ) − wⁿ − Δt·Σ_{j<i} a_ij·F(H_j) − γ·Δt·F(Hᵢ) = 0
//! ```
//!
//! with w(h) = θ(h) + Ss·h the stored water and F the cell rates of
//! [`Column::evaluate`]. The method is stiffly accurate (the last row of A is b),
//! so wⁿ⁺¹ = w(H_s); the water amounts advance by Δt·Σ b_j·G(H_j) with their
//! rates G. Because Σ dz·F = infiltration − drainage − uptake for any heads,
//! the water balance changes only by Σ dz·R_s per step, and Newton runs until
//! |R| ≤ 1e-13: the balance closes to round-off, not to the tolerance.
//!
//! The Newton matrix diag(C + Ss) − γ·Δt·∂F/∂h is tridiagonal and solved in
//! O(n); a backtracking line search keeps Newton from overshooting when a
//! saturated cell (C = 0) starts to drain. A one-step method needs no restart
//! when the forcing jumps at a sampling boundary.
//!
//! Two paths solve the stages of a step attempt. The fast one is plain
//! Newton in the heads from an extrapolated guess, to |R| ≤ 1e-13 in the last
//! stage, with the Thomas algorithm. Only if one of its stages fails is the
//! same attempt redone on the robust path (semismooth Newton in the
//! coordinates of `Coordinates` near saturation, a watchdog, a pivoting
//! solver, a looser tolerance with the last stage projected to exact
//! conservation, always at the default tolerances: see
//! `Integrator::project_last_stage`), which the next few attempts then take directly. The fast
//! path is what the coarse textures and all unponded runs need, at their old
//! cost; the robust one gets ponded, saturated columns of the finer textures
//! through the cusp of K at h = 0.
//!
//! Why not diffsol: `benches/integrator.rs` runs the same column through
//! diffsol's BDF (the DAE of [`super::diffsol_dae`]); it fails on a column
//! wetting up to saturation and is several times slower on the moderate case.

// Index loops over cells and stages read like the equations they implement.
#![allow(clippy::needless_range_loop)]

use super::column::{AMOUNTS, Column, Derivatives, Evaluation, Forcing};
use super::hydraulics::{HydraulicState, VanGenuchten};

/// Tolerances of the integrator's error control.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerances {
    /// Relative tolerance on the stored water of every cell.
    pub relative: f64,
    /// Absolute tolerance on the stored water of every cell [m³/m³].
    pub absolute: f64,
}

impl Default for Tolerances {
    /// 1e-5 relative, 1e-7 absolute: θ then moves by less than 1e-6 when both are
    /// tightened 100× (`tests/field.rs`).
    fn default() -> Self {
        Tolerances {
            relative: 1e-5,
            absolute: 1e-7,
        }
    }
}

impl Tolerances {
    pub fn validate(&self) -> Result<(), String> {
        let all = [self.relative, self.absolute];
        if !all.iter().all(|t| t.is_finite() && *t > 0.0) {
            return Err(format!(
                "tolerances must be finite and > 0, got relative {} and absolute {}",
                self.relative, self.absolute
            ));
        }
        Ok(())
    }
}

/// Why an integration stopped short.
#[derive(Debug, Clone, PartialEq)]
pub enum FailureKind {
    /// The input (duration, forcing, state) was not valid.
    InvalidInput(String),
    /// The step size fell below the smallest allowed.
    StepSizeCollapse,
    /// A sampling step took more step attempts or Newton iterations than
    /// its [`WorkLimits`] allow.
    WorkLimit(String),
    /// The caller's interrupt (a deadline, a shutdown) asked it to stop.
    Interrupted,
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FailureKind::InvalidInput(m) => f.write_str(m),
            FailureKind::StepSizeCollapse => write!(f, "step size fell below {MIN_STEP} s"),
            FailureKind::WorkLimit(m) => write!(f, "work limit reached: {m}"),
            FailureKind::Interrupted => f.write_str("interrupted by the caller"),
        }
    }
}

/// An integration that stopped short: what happened, and where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}", self.describe())]
pub struct IntegrationError {
    /// Time [s] the integration had reached.
    pub time: f64,
    pub kind: FailureKind,
    /// The sampling step (0-based) it failed in, where the caller knows it.
    pub step: Option<usize>,
    /// The smallest step size [s] tried in the failing sampling step.
    pub smallest_step: Option<f64>,
    /// The cell whose Newton residual or error estimate was largest at the
    /// last failed attempt.
    pub cell: Option<usize>,
}

impl IntegrationError {
    /// Input that cannot be integrated, at time `time`.
    pub fn invalid(time: f64, message: impl Into<String>) -> Self {
        IntegrationError {
            time,
            kind: FailureKind::InvalidInput(message.into()),
            step: None,
            smallest_step: None,
            cell: None,
        }
    }

    /// The same error, naming the sampling step it happened in.
    pub fn in_step(mut self, step: usize) -> Self {
        self.step = Some(step);
        self
    }

    fn describe(&self) -> String {
        let mut text = String::from("integration failed");
        if let Some(k) = self.step {
            text += &format!(" in sampling step {k}");
        }
        text += &format!(" at t = {} s: {}", self.time, self.kind);
        if let Some(dt) = self.smallest_step {
            text += &format!("; smallest step {dt:.3e} s");
        }
        if let Some(cell) = self.cell {
            text += &format!(", cell {cell}");
        }
        text
    }
}

/// Bounds on the work of one call of [`Integrator::advance`]: crossing one
/// is an [`IntegrationError`], never a loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WorkLimits {
    /// Step attempts (accepted, rejected and abandoned) per sampling step.
    pub step_attempts: usize,
    /// Newton iterations per sampling step.
    pub newton_iterations: usize,
}

impl Default for WorkLimits {
    /// 6,000 attempts and 600,000 Newton iterations per sampling step:
    /// enough for the slowest sampling step of `tests/textures.rs` (sandy
    /// clay wetted to just below saturation by rain, 3,211 attempts and
    /// 378,432 Newton iterations, 3 s in a release build), where most need
    /// a few and fewer than 300 accepted steps in all 60. A sampling step
    /// that reaches a limit has cost about 5 s.
    fn default() -> Self {
        WorkLimits {
            step_attempts: 6_000,
            newton_iterations: 600_000,
        }
    }
}

/// A check the integrator makes before every step attempt; when it returns
/// true the integration stops with [`FailureKind::Interrupted`]. The soil
/// module keeps no clock: a deadline or a shutdown flag lives in the closure.
#[derive(Clone)]
pub struct Interrupt(std::sync::Arc<dyn Fn() -> bool + Send + Sync>);

impl Interrupt {
    pub fn new(check: impl Fn() -> bool + Send + Sync + 'static) -> Self {
        Interrupt(std::sync::Arc::new(check))
    }

    pub fn requested(&self) -> bool {
        (self.0)()
    }
}

impl std::fmt::Debug for Interrupt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Interrupt(..)")
    }
}

/// Counters of the work the integrator did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IntegratorStatistics {
    /// Accepted steps.
    pub steps: usize,
    /// Steps rejected by the error test.
    pub error_test_failures: usize,
    /// Steps abandoned because a stage's Newton iteration did not converge
    /// on the robust path (see [`Integrator`]'s two paths).
    pub newton_failures: usize,
    /// Step attempts whose fast path failed and that were redone on the
    /// robust path with the same step size.
    pub fallbacks: usize,
    /// Newton iterations (each one tridiagonal solve).
    pub newton_iterations: usize,
    /// Evaluations of a stage's residual (and its Jacobian), by every stage
    /// solver: one per Newton iteration, plus one per solve, per line-search
    /// halving and per re-solve on a kink. (The diffsol cross-check does not
    /// count them.)
    pub residual_evaluations: usize,
    /// Calls of [`Integrator::advance`].
    pub sampling_steps: usize,
}

/// The state the integrator advances: heads and water amounts.
#[derive(Debug, Clone, PartialEq)]
pub struct ColumnState {
    /// Pressure head of every cell [m].
    pub heads: Vec<f64>,
    /// Cumulative infiltration, drainage, uptake, runoff [m].
    pub amounts: [f64; AMOUNTS],
}

/// Newton stops when max|R| is below this fraction of the error tolerance's
/// scale at saturation, absolute + relative·θs (Hairer & Wanner, *Solving ODEs
/// II*, §IV.8: the iteration error a small fraction of the tolerance). With the
/// default tolerances that is 8e-8 in stored water; there the water balance
/// does not depend on it (the last stage is projected, see
/// `Integrator::project_last_stage`).
const NEWTON_FRACTION: f64 = 0.02;
const MAX_NEWTON_ITERATIONS: usize = 25;
/// The fast path's Newton residuals [m³/m³ of stored water]: the last stage
/// to round-off (it closes the water balance without projection), the inner
/// stages to this fraction of the robust path's tolerance (they only perturb
/// the solution: 8e-9 at the default tolerances; against a fixed 1e-10, 9 %
/// fewer instructions on sand and sandy loam, and the same θ change when the
/// tolerances tighten 100×, 1.9e-5 sand, 8.2e-6 sandy loam, 3.1e-5 loam).
const NEWTON_TOLERANCE: f64 = 1e-13;
const STAGE_FRACTION: f64 = 0.1;
/// Moves between the sets per cell in one active-set stage solve.
const MAX_SWITCHES: u8 = 3;
/// Step attempts that go straight to the robust path after the fast path failed.
const ROBUST_STREAK: usize = 20;
/// Cells with C below this multiple of Ss keep their heads in the projection
/// of the last stage.
const PROJECTION_CAPACITY: f64 = 100.0;
/// The largest change of head [m] by which the projection puts what no cell
/// can take into all cells alike. A stage's residuals sum to at most n times
/// Newton's tolerance, so at the default tolerances that change is at most
/// NEWTON_FRACTION·(1e-7 + 1e-5·θs)/Ss < 0.11 m for any θs ≤ 0.52: there the
/// water balance is always exact.
const UNIFORM_SHIFT: f64 = 0.15;
/// When even that is too much, at most this many Newton iterations try to
/// take the last stage's residual below Ss times this head [m] first.
const POLISH_HEAD: f64 = 1e-3;
const POLISH_ITERATIONS: usize = 4;
/// Full Newton steps a stage solve may take although they do not reduce the
/// residual (at most this many, and by at most [`WATCHDOG_GROWTH`]): near
/// saturation the residual has kinks, at which a descent test on max|R| can
/// stall a semismooth Newton that converges with full steps.
const WATCHDOG_STEPS: usize = 5;
const WATCHDOG_GROWTH: f64 = 1e3;
/// Pseudo-transient continuation's first pseudo time step τ₀ (its first
/// matrix is Newton's with each row's magnitude/τ₀ added on the diagonal),
/// its iterations per stage solve, the residual growth that takes a step
/// back, and τ's bounds. τ₀ from 1 to 100 all cut the clay and sandy clay
/// cases in rain (`tests/textures.rs`) from 2.5–3.7 s to 0.2–1.1 s; over
/// the whole matrix 10 meets the speed targets on the most textures
/// (ARCHITECTURE.md, "Ponding and near-saturated flow").
const PTC_INITIAL_TAU: f64 = 10.0;
const PTC_ITERATIONS: usize = 100;
const PTC_GROWTH: f64 = 10.0;
const PTC_SMALLEST_TAU: f64 = 1e-12;
const PTC_LARGEST_TAU: f64 = 1e12;
/// Levenberg–Marquardt's first damping, its largest, and its iterations
/// (each one a residual evaluation) per stage solve.
const LM_INITIAL_DAMPING: f64 = 1e-3;
const LM_LARGEST_DAMPING: f64 = 1e10;
const LM_ITERATIONS: usize = 60;
/// The smallest damping λ the line searches of the fast path's Newton and
/// the robust path's semismooth Newton try before they give the stage up
/// (to the robust path, or to pseudo-transient continuation). A Newton
/// direction along which the residual does not fall at λ = 1/64 is one the
/// iteration cannot use. Halving down to 1e-12, as before, spent up to 40
/// residual evaluations on each stalled iteration, on the fine textures
/// most of the work: silty clay at 1e-6 m/s (weather-dry, 60 steps) took
/// 5,375 halvings on the fast path and 3,398 on the robust one, against
/// about 2,500 Newton iterations (ARCHITECTURE.md, "A line search that
/// gives up early").
const LINE_SEARCH_FLOOR: f64 = 1e-2;
/// Smallest step before giving up [s].
const MIN_STEP: f64 = 1e-8;
/// First step of the very first call [s].
const FIRST_STEP: f64 = 60.0;
/// Longest first step after the forcing changed [s].
const RESTART_STEP: f64 = 1000.0;

/// The SDIRK tableau: Alexander's three-stage, third-order, L-stable method
/// (R. Alexander, SIAM J. Numer. Anal. 14 (1977) 1006–1021; Hairer & Wanner,
/// Solving ODEs II, §IV.6): γ on the diagonal, the root of
/// γ³ − 3γ² + 3γ/2 − 1/6 = 0 in (1/6, 1/2); c = (γ, (1 + γ)/2, 1); A strictly
/// below the diagonal; b = last row of A (stiffly accurate). b̂ are embedded
/// second-order weights with b̂₃ = 0 (Σb̂ = 1, Σb̂c = 1/2). Chosen over
/// Hairer & Wanner's five-stage SDIRK4 by measurement (ARCHITECTURE.md).
const STAGES: usize = 3;
const GAMMA: f64 = 0.435_866_521_508_459;
const A: [[f64; STAGES]; STAGES] = [
    [GAMMA, 0.0, 0.0],
    [(1.0 - GAMMA) / 2.0, GAMMA, 0.0],
    [
        -(6.0 * GAMMA * GAMMA - 16.0 * GAMMA + 1.0) / 4.0,
        (6.0 * GAMMA * GAMMA - 20.0 * GAMMA + 5.0) / 4.0,
        GAMMA,
    ],
];
const B_HAT: [f64; STAGES] = [
    1.0 - (1.0 - 2.0 * GAMMA) / (1.0 - GAMMA),
    (1.0 - 2.0 * GAMMA) / (1.0 - GAMMA),
    0.0,
];
/// Order of the embedded estimate + 1: the step-size controller's exponent is 1/this.
const ERROR_ORDER: f64 = 3.0;

/// The tableau, for tests of its order conditions.
pub fn tableau() -> ([[f64; STAGES]; STAGES], [f64; STAGES]) {
    (A, B_HAT)
}

/// Advances a column over sampling steps.
#[derive(Debug, Clone)]
pub struct Integrator {
    column: Column,
    tolerances: Tolerances,
    statistics: IntegratorStatistics,
    /// Step size proposed at the end of the last call, the first of the next.
    next_step: f64,
    /// Forcing of the last call.
    last_forcing: Option<Forcing>,
    limits: WorkLimits,
    /// A bound on [`IntegratorStatistics::newton_iterations`] over every
    /// call (a caller's budget across many integrations).
    newton_cap: Option<usize>,
    interrupt: Option<Interrupt>,
    work: Workspace,
}

/// Buffers reused by every step.
#[derive(Debug, Clone)]
struct Workspace {
    eval: Evaluation,
    /// The robust path's evaluation in the heads at a stage's solution,
    /// for the tangents.
    tangent_eval: Evaluation,
    /// Stored water at the start of the step, and the heads it is of.
    storage: Vec<f64>,
    storage_heads: Vec<f64>,
    /// Cell rates and amount rates of every stage.
    stage_rates: [Vec<f64>; STAGES],
    stage_amount_rates: [[f64; AMOUNTS]; STAGES],
    /// The known part of the stage equation: wⁿ + Δt·Σ_{j<i} a_ij·F_j.
    known: Vec<f64>,
    /// Newton iterate, its residual, the update, the last accepted iterate.
    trial: Vec<f64>,
    residual: Vec<f64>,
    update: Vec<f64>,
    base: Vec<f64>,
    /// The cell with the largest Newton residual or error estimate at the
    /// last failed attempt.
    worst_cell: Option<usize>,
    /// Per cell, the side of the kink its Newton derivative is taken on.
    side: Vec<Side>,
    /// The Newton unknown's coordinate at `base` (see `Coordinates::coordinate`).
    base_coordinate: Vec<Option<f64>>,
    solver: Tridiagonal,
    /// The robust path's starting guess of the stage being solved.
    start: Vec<f64>,
    /// Per cell, whether the active-set iteration holds it saturated, and
    /// how often it moved between the sets in this stage solve.
    saturated: Vec<bool>,
    switches: Vec<u8>,
    /// Scratch of the Thomas algorithm (the fast path).
    scratch: Vec<f64>,
    /// Levenberg–Marquardt's JᵀJ (n×n), its damped factor, JᵀR and the
    /// residual at the last accepted iterate.
    normal: Vec<f64>,
    factor: Vec<f64>,
    gradient: Vec<f64>,
    base_residual: Vec<f64>,
    /// Step attempts left that go straight to the robust path.
    robust_streak: usize,
    /// Stage residuals evaluated so far (see [`IntegratorStatistics`]).
    evaluations: usize,
    /// Kept only while tangents are propagated: diag(C + Ss) at the start of
    /// the step, and per stage the tridiagonal ∂F/∂H, diag(C + Ss) and
    /// ∂F_0/∂(irrigation) (1/dz while the top face takes all the supply).
    keep_jacobians: bool,
    start_capacity: Vec<f64>,
    stage_lower: [Vec<f64>; STAGES],
    stage_diagonal: [Vec<f64>; STAGES],
    stage_upper: [Vec<f64>; STAGES],
    stage_capacity: [Vec<f64>; STAGES],
    stage_supply_gain: [f64; STAGES],
    /// Per tangent, T_j·S_j + F_p,j of the stages of the step being carried,
    /// and one stage's solution.
    stage_df: Vec<[Vec<f64>; STAGES]>,
    tangent_stage: Vec<f64>,
}

impl Workspace {
    fn new(n: usize) -> Self {
        let z = vec![0.0; n];
        Workspace {
            eval: Evaluation::new(n),
            tangent_eval: Evaluation::new(n),
            storage: z.clone(),
            storage_heads: vec![f64::NAN; n],
            stage_rates: std::array::from_fn(|_| z.clone()),
            stage_amount_rates: [[0.0; AMOUNTS]; STAGES],
            known: z.clone(),
            trial: z.clone(),
            residual: z.clone(),
            update: z.clone(),
            base: z.clone(),
            worst_cell: None,
            side: vec![Side::BySign; n],
            base_coordinate: vec![None; n],
            solver: Tridiagonal::new(n),
            scratch: z.clone(),
            normal: vec![0.0; n * n],
            factor: vec![0.0; n * n],
            gradient: z.clone(),
            base_residual: z.clone(),
            start: z.clone(),
            saturated: vec![false; n],
            switches: vec![0; n],
            robust_streak: 0,
            evaluations: 0,
            keep_jacobians: false,
            start_capacity: z.clone(),
            stage_lower: std::array::from_fn(|_| z.clone()),
            stage_diagonal: std::array::from_fn(|_| z.clone()),
            stage_upper: std::array::from_fn(|_| z.clone()),
            stage_capacity: std::array::from_fn(|_| z.clone()),
            stage_supply_gain: [0.0; STAGES],
            stage_df: Vec::new(),
            tangent_stage: z.clone(),
        }
    }

    /// Takes the trial as a line search's base point, with its Newton
    /// coordinates (`base_coordinate`), computed once for all the trials.
    fn set_base(&mut self, coordinates: &Coordinates) {
        self.base.copy_from_slice(&self.trial);
        for (u, &h) in self.base_coordinate.iter_mut().zip(&self.base) {
            *u = coordinates.coordinate(h);
        }
    }
}

enum Step {
    Accepted { error: f64 },
    Rejected { error: f64 },
    NewtonFailed,
}

impl Integrator {
    pub fn new(column: Column, tolerances: Tolerances) -> Result<Self, String> {
        tolerances.validate()?;
        Ok(Integrator {
            column,
            tolerances,
            statistics: IntegratorStatistics::default(),
            next_step: FIRST_STEP,
            last_forcing: None,
            limits: WorkLimits::default(),
            newton_cap: None,
            interrupt: None,
            work: Workspace::new(column.cells()),
        })
    }

    /// A fresh integrator for a state that is already under way (an
    /// ensemble member's next forecast): its first step is the one taken
    /// after a change of forcing (1000 s), not the very first call's 60 s
    /// meant for a column just set up. The error test still decides: a
    /// first step too long is rejected and shortened. A step of the
    /// "unknown" prior's 96 members while it selects (`cargo bench --bench
    /// estimate`, `predict_update_unknown_selecting`) went from 6.2 to
    /// 3.9 ms with it.
    pub fn continuing(mut self) -> Self {
        self.next_step = RESTART_STEP;
        self
    }

    pub fn column(&self) -> &Column {
        &self.column
    }

    pub fn statistics(&self) -> IntegratorStatistics {
        IntegratorStatistics {
            residual_evaluations: self.work.evaluations,
            ..self.statistics
        }
    }

    pub fn limits(&self) -> WorkLimits {
        self.limits
    }

    /// Replaces the bounds on the work of a sampling step.
    pub fn set_limits(&mut self, limits: WorkLimits) {
        self.limits = limits;
    }

    /// Bounds the Newton iterations counted in [`Integrator::statistics`]
    /// (over all calls, not per sampling step): once they reach `cap`, the
    /// next step attempt fails with [`FailureKind::WorkLimit`]. A caller
    /// spreading one budget over many integrations sets it to the count so
    /// far plus what is left. None removes the bound.
    pub fn set_newton_cap(&mut self, cap: Option<usize>) {
        self.newton_cap = cap;
    }

    /// Installs (or removes) the check made before every step attempt.
    pub fn set_interrupt(&mut self, interrupt: Option<Interrupt>) {
        self.interrupt = interrupt;
    }

    /// Advances `state` over `duration` seconds under constant `forcing`.
    /// `time` is only used in error messages. On error `state` is unchanged.
    pub fn advance(
        &mut self,
        state: &mut ColumnState,
        time: f64,
        duration: f64,
        forcing: Forcing,
    ) -> Result<(), IntegrationError> {
        self.advance_with_tangents(state, time, duration, forcing, &mut [], None)
    }

    /// [`Integrator::advance`] that also carries tangents: `tangents[p]` holds
    /// dH/dp_p (one entry per cell) at the start and at the end of the
    /// interval, and `irrigation` names the parameter, if any, that is this
    /// interval's irrigation rate (∂forcing.irrigation/∂p = 1).
    ///
    /// The tangents are the exact derivatives of the discrete solution with
    /// the accepted step sizes held fixed: for every stage
    ///
    /// ```text
    /// (diag(C + Ss) − γΔt·T_i)·S_i
    ///     = diag(C + Ss)ⁿ·Sⁿ + Δt·Σ_{j<i} a_ij·(T_j·S_j + F_p,j) + γΔt·F_p,i
    /// ```
    ///
    /// with T the tridiagonal ∂F/∂H, and Sⁿ⁺¹ = S_s (the method is stiffly
    /// accurate).
    pub fn advance_with_tangents(
        &mut self,
        state: &mut ColumnState,
        time: f64,
        duration: f64,
        forcing: Forcing,
        tangents: &mut [Vec<f64>],
        irrigation: Option<usize>,
    ) -> Result<(), IntegrationError> {
        let fail = |at: f64, message: String| IntegrationError::invalid(time + at, message);
        if !(duration.is_finite() && duration > 0.0) {
            return Err(fail(0.0, format!("duration must be > 0 s, got {duration}")));
        }
        forcing.validate().map_err(|m| fail(0.0, m))?;
        let n = self.column.cells();
        if state.heads.len() != n || state.heads.iter().any(|h| !h.is_finite()) {
            return Err(fail(0.0, "heads must be finite, one per cell".into()));
        }
        if tangents.iter().any(|t| t.len() != n) || irrigation.is_some_and(|p| p >= tangents.len())
        {
            return Err(fail(0.0, "tangents must hold one entry per cell".into()));
        }
        self.work.keep_jacobians = !tangents.is_empty();
        let mut heads = state.heads.clone();
        let mut amounts = state.amounts;
        let mut t = 0.0;
        // After a jump in the forcing the top cells go through a transient that
        // the step proposed in calmer times would overshoot: start short.
        let mut dt = match self.last_forcing {
            Some(last) if last == forcing => self.next_step,
            _ => self.next_step.min(RESTART_STEP),
        };
        self.last_forcing = Some(forcing);
        let (mut attempts, newton_at_start) = (0usize, self.statistics.newton_iterations);
        let mut smallest = f64::INFINITY;
        while t < duration {
            let now = t;
            let stop =
                move |kind: FailureKind, smallest: f64, cell: Option<usize>| IntegrationError {
                    time: time + now,
                    kind,
                    step: None,
                    smallest_step: smallest.is_finite().then_some(smallest),
                    cell,
                };
            if self.interrupt.as_ref().is_some_and(Interrupt::requested) {
                return Err(stop(FailureKind::Interrupted, smallest, None));
            }
            let total = self.statistics.newton_iterations;
            let newton = total - newton_at_start;
            let over = if attempts >= self.limits.step_attempts
                || newton >= self.limits.newton_iterations
            {
                Some(format!(
                    "{attempts} step attempts and {newton} Newton iterations in one sampling step \
                     (limits {} and {})",
                    self.limits.step_attempts, self.limits.newton_iterations
                ))
            } else {
                self.newton_cap.filter(|&cap| total >= cap).map(|cap| {
                    format!(
                        "the caller's budget of Newton iterations is spent ({total} of at most {cap})"
                    )
                })
            };
            if let Some(what) = over {
                return Err(stop(
                    FailureKind::WorkLimit(what),
                    smallest,
                    self.work.worst_cell,
                ));
            }
            attempts += 1;
            let remaining = duration - t;
            let mut this_dt = dt;
            if this_dt >= remaining * (1.0 - 1e-12) {
                this_dt = remaining;
            } else if this_dt > 0.5 * remaining {
                // Two even steps rather than a long one and a sliver.
                this_dt = 0.5 * remaining;
            }
            match self.try_step(&heads, &forcing, this_dt) {
                Step::Accepted { error } => {
                    self.propagate_tangents(tangents, this_dt, irrigation);
                    let w = &self.work;
                    heads.copy_from_slice(&w.trial);
                    for (k, amount) in amounts.iter_mut().enumerate() {
                        let rise: f64 = (0..STAGES)
                            .map(|j| A[STAGES - 1][j] * w.stage_amount_rates[j][k])
                            .sum();
                        *amount += this_dt * rise;
                    }
                    t += this_dt;
                    self.statistics.steps += 1;
                    let factor = 0.9 * error.max(1e-10).powf(-1.0 / ERROR_ORDER);
                    let proposal = this_dt * factor.clamp(0.2, 4.0);
                    // A step shortened to land on the end does not shrink the next.
                    dt = if this_dt < dt {
                        proposal.max(dt)
                    } else {
                        proposal
                    };
                }
                Step::Rejected { error } => {
                    self.statistics.error_test_failures += 1;
                    let factor = 0.9 * error.powf(-1.0 / ERROR_ORDER);
                    dt = this_dt * factor.clamp(0.1, 0.9);
                }
                Step::NewtonFailed => {
                    self.statistics.newton_failures += 1;
                    dt = this_dt * 0.25;
                }
            }
            smallest = smallest.min(this_dt);
            if dt < MIN_STEP {
                return Err(stop(
                    FailureKind::StepSizeCollapse,
                    smallest.min(dt),
                    self.work.worst_cell,
                ));
            }
        }
        self.next_step = dt;
        state.heads = heads;
        state.amounts = amounts;
        self.statistics.sampling_steps += 1;
        Ok(())
    }

    /// Tries one step of size `dt` from `heads`; on success the new heads are in
    /// `work.trial` and the stage rates in `work.stage_*`. The fast path
    /// first; if one of its stages' Newton fails, the same step again on the
    /// robust path, which the next [`ROBUST_STREAK`] attempts then take directly.
    fn try_step(&mut self, heads: &[f64], forcing: &Forcing, dt: f64) -> Step {
        if self.work.robust_streak == 0 {
            match self.try_step_on(Path::Fast, heads, forcing, dt) {
                Step::NewtonFailed => {
                    self.statistics.fallbacks += 1;
                    self.work.robust_streak = ROBUST_STREAK;
                }
                step => return step,
            }
        } else {
            self.work.robust_streak -= 1;
        }
        self.try_step_on(Path::Robust, heads, forcing, dt)
    }

    /// One step attempt on the given path.
    fn try_step_on(&mut self, path: Path, heads: &[f64], forcing: &Forcing, dt: f64) -> Step {
        let n = self.column.cells();
        let soil = *self.column.soil();
        let ss = soil.specific_storage;
        // the stored water at the step's start is the same for every attempt
        // from these heads
        if self.work.storage_heads != heads {
            for i in 0..n {
                self.work.storage[i] = soil.storage(heads[i]);
            }
            self.work.storage_heads.copy_from_slice(heads);
        }
        if self.work.keep_jacobians {
            for i in 0..n {
                self.work.start_capacity[i] = soil.state(heads[i]).capacity + ss;
            }
        }
        self.work.trial.copy_from_slice(heads);
        for stage in 0..STAGES {
            {
                let w = &mut self.work;
                for i in 0..n {
                    let mut known = w.storage[i];
                    for j in 0..stage {
                        known += dt * A[stage][j] * w.stage_rates[j][i];
                    }
                    w.known[i] = known;
                }
            }
            let solved = match path {
                Path::Fast => {
                    // Starting guess: from the previous stage's heads, the step
                    // in stored water that the stage equation asks for, through
                    // the capacity. Only the last stage's residual enters the
                    // water balance.
                    if stage > 0 {
                        let w = &mut self.work;
                        let prev = &w.stage_rates[stage - 1];
                        for i in 0..n {
                            let s = &w.eval.states[i];
                            let water = s.water_content + ss * w.trial[i];
                            let target = w.known[i] + GAMMA * dt * prev[i];
                            w.trial[i] += (target - water) / (s.capacity + ss);
                        }
                    }
                    let tolerance = if stage + 1 == STAGES {
                        NEWTON_TOLERANCE
                    } else {
                        STAGE_FRACTION * self.newton_tolerance()
                    };
                    self.solve_stage_fast(forcing, GAMMA * dt, tolerance)
                }
                Path::Robust => {
                    // Starting guess: the previous stage's heads. (Extrapolating
                    // the stored water through 1/(C + Ss) throws a saturated
                    // cell, C = 0, metres away from its root.)
                    let tolerance = self.newton_tolerance();
                    self.work.base.copy_from_slice(&self.work.trial);
                    self.work.start.copy_from_slice(&self.work.trial);
                    self.solve_stage(forcing, GAMMA * dt, tolerance, MAX_NEWTON_ITERATIONS)
                        || {
                            let w = &mut self.work;
                            w.trial.copy_from_slice(&w.start);
                            self.solve_stage_pseudo_transient(forcing, GAMMA * dt, tolerance)
                        }
                        || {
                            let w = &mut self.work;
                            w.trial.copy_from_slice(&w.start);
                            self.solve_stage_active_set(forcing, GAMMA * dt, tolerance)
                        }
                        || {
                            let w = &mut self.work;
                            w.trial.copy_from_slice(&w.start);
                            self.solve_stage_least_squares(forcing, GAMMA * dt, tolerance)
                        }
                }
            };
            if !solved {
                return Step::NewtonFailed;
            }
            if path == Path::Robust && stage + 1 == STAGES {
                self.project_last_stage(forcing, dt);
            }
            let w = &mut self.work;
            if path == Path::Robust && w.keep_jacobians {
                // the tangents need ∂F/∂H in the heads (Newton's may be in
                // ψ), at the projected heads; evaluated aside, so that the
                // step (its error estimate) is the same without tangents
                self.column.evaluate(
                    &w.trial,
                    forcing,
                    &mut w.tangent_eval,
                    Derivatives::Included,
                );
            }
            w.stage_rates[stage].copy_from_slice(&w.eval.storage);
            w.stage_amount_rates[stage] = w.eval.amounts;
            if w.keep_jacobians {
                let e = if path == Path::Robust {
                    &w.tangent_eval
                } else {
                    &w.eval
                };
                w.stage_lower[stage].copy_from_slice(&e.lower);
                w.stage_diagonal[stage].copy_from_slice(&e.diagonal);
                w.stage_upper[stage].copy_from_slice(&e.upper);
                for i in 0..n {
                    w.stage_capacity[stage][i] = e.states[i].capacity + ss;
                }
                // the top face passes the whole supply unless it is capped
                // (then its derivative is in ∂F/∂H, and the supply runs off);
                // the runoff is the stage's own
                w.stage_supply_gain[stage] =
                    if e.top_gradient == 0.0 && w.eval.amounts[super::column::RUNOFF] == 0.0 {
                        1.0 / self.column.cell_thickness()
                    } else {
                        0.0
                    };
            }
        }
        // Embedded estimate: Δt·Σ (b_j − b̂_j)·F_j, scaled per cell.
        let w = &self.work;
        let tol = self.tolerances;
        let mut sum = 0.0;
        let (mut worst, mut largest) = (None, -1.0);
        for i in 0..n {
            let mut e = 0.0;
            for j in 0..STAGES {
                e += (A[STAGES - 1][j] - B_HAT[j]) * w.stage_rates[j][i];
            }
            let water = w.eval.states[i].water_content + ss * w.trial[i];
            let scale = tol.absolute + tol.relative * water.abs().max(w.storage[i].abs());
            let r = dt * e / scale;
            // a NaN error counts as the largest
            if r.is_nan() || r.abs() > largest {
                (worst, largest) = (Some(i), r.abs());
            }
            sum += r * r;
        }
        let error = (sum / n as f64).sqrt();
        if !(error.is_finite() && error <= 1.0) {
            self.work.worst_cell = worst;
        }
        if error.is_finite() && error <= 1.0 {
            if path == Path::Fast {
                // the fast path's last Newton iterate is the new heads and
                // was evaluated there: its stored water is the next step's
                // start, not computed again
                let w = &mut self.work;
                for i in 0..n {
                    w.storage[i] = w.eval.states[i].water_content + ss * w.trial[i];
                }
                w.storage_heads.copy_from_slice(&w.trial);
            }
            Step::Accepted { error }
        } else {
            Step::Rejected {
                error: if error.is_finite() { error } else { 1e6 },
            }
        }
    }

    /// The robust path's last stage, solved to Newton's tolerance, made
    /// exact in water. Newton stops at a residual far below the error
    /// tolerance but not at round-off. The new stored water is what the stage
    /// equation gives for the rates at the solution, wⁿ⁺¹ = known +
    /// γΔt·F(H_s) = w(H_s) − R, so that Σ dz·wⁿ⁺¹ − Σ dz·wⁿ is exactly Δt·Σ b_j
    /// times the boundary and sink rates: the water balance closes to
    /// round-off. The heads follow by the inverse of w(h).
    ///
    /// Past θs that inverse is (w − θs)/Ss: a correction of 1e-6 would be a
    /// metre of head. So a cell takes its correction −R only if it has
    /// capacity (C above [`PROJECTION_CAPACITY`]·Ss) and the new water stays
    /// at most half-way to saturation. What the other cells do not take goes
    /// to one cell that can take it all (the one of largest capacity, as
    /// before this rule, else the one of most room), else to the taking cells
    /// in proportion to their room, else to all cells alike as a change of
    /// head of at most [`UNIFORM_SHIFT`]. Failing all of these, a few Newton
    /// iterations try to take the residual below Ss·[`POLISH_HEAD`] (in
    /// saturated cells it is linear in the heads) and the placement is
    /// chosen again; if it still fails, the cells that cannot take keep their
    /// heads and the water balance is off by their residual. That happens
    /// only at tolerances far looser than the default (see `UNIFORM_SHIFT`),
    /// such as the ensemble filter's.
    fn project_last_stage(&mut self, forcing: &Forcing, dt: f64) {
        let n = self.column.cells();
        let soil = *self.column.soil();
        let ss = soil.specific_storage;
        let gamma_dt = GAMMA * dt;
        let room = |w: &Workspace, i: usize| {
            soil.saturated_water_content - w.eval.states[i].water_content - ss * w.trial[i]
        };
        let takes = |w: &Workspace, i: usize, correction: f64| {
            w.eval.states[i].capacity > PROJECTION_CAPACITY * ss && correction <= 0.5 * room(w, i)
        };
        let place = |w: &Workspace| {
            let taking: Vec<bool> = (0..n).map(|i| takes(w, i, -w.residual[i])).collect();
            let moved: f64 = (0..n).filter(|&i| !taking[i]).map(|i| w.residual[i]).sum();
            let fits = |k: usize| takes(w, k, -w.residual[k] - moved);
            let among = |key: &dyn Fn(usize) -> f64| {
                (0..n)
                    .filter(|&i| taking[i])
                    .max_by(|&a, &b| key(a).total_cmp(&key(b)))
            };
            let largest = among(&|i| w.eval.states[i].capacity);
            let roomiest = among(&|i| room(w, i));
            let total_room: f64 = (0..n).filter(|&i| taking[i]).map(|i| room(w, i)).sum();
            let placement = if let Some(k) = largest.filter(|&k| fits(k)) {
                Placement::Sink(k)
            } else if let Some(k) = roomiest.filter(|&k| fits(k)) {
                Placement::Sink(k)
            } else if largest.is_some() && -moved <= 0.5 * total_room {
                Placement::Spread(total_room)
            } else if moved.abs() <= UNIFORM_SHIFT * ss * n as f64 {
                Placement::Uniform
            } else {
                Placement::Keep
            };
            (taking, moved, placement)
        };
        let mut placed = place(&self.work);
        if matches!(placed.2, Placement::Keep) {
            let w = &mut self.work;
            w.start.copy_from_slice(&w.trial);
            let polish = POLISH_HEAD * ss;
            if !self.solve_stage(forcing, gamma_dt, polish, POLISH_ITERATIONS) {
                let w = &mut self.work;
                w.trial.copy_from_slice(&w.start);
                w.side.fill(Side::BySign);
                let coordinates = Coordinates::new(&soil);
                stage_residual(&self.column, &coordinates, forcing, gamma_dt, w);
            }
            placed = place(&self.work);
        }
        let (taking, moved, placement) = placed;
        let w = &mut self.work;
        for i in 0..n {
            let target = w.known[i] + gamma_dt * w.eval.storage[i];
            let own = if taking[i] {
                target
            } else {
                target + w.residual[i]
            };
            let target = match placement {
                Placement::Sink(k) if i == k => target - moved,
                Placement::Spread(total) if taking[i] => target - moved * room(w, i) / total,
                Placement::Uniform => own - moved / n as f64,
                _ if taking[i] => target,
                _ => continue,
            };
            w.trial[i] = soil.pressure_head_from_storage(target);
        }
    }

    /// Carries the tangents over the step just accepted (see
    /// [`Integrator::advance_with_tangents`]); `irrigation` names the tangent,
    /// if any, whose parameter is the irrigation rate of this interval. A
    /// stage's matrix is the same for every tangent: it is factorised once.
    fn propagate_tangents(
        &mut self,
        tangents: &mut [Vec<f64>],
        dt: f64,
        irrigation: Option<usize>,
    ) {
        let n = self.column.cells();
        let w = &mut self.work;
        // dF_j = T_j·S_j + F_p,j of every tangent's stages so far
        if w.stage_df.len() < tangents.len() {
            w.stage_df
                .resize_with(tangents.len(), || std::array::from_fn(|_| vec![0.0; n]));
        }
        let gamma_dt = GAMMA * dt;
        for stage in 0..STAGES {
            let (lower, diagonal, upper, capacity) = (
                &w.stage_lower[stage],
                &w.stage_diagonal[stage],
                &w.stage_upper[stage],
                &w.stage_capacity[stage],
            );
            // the same matrix Newton just factorised: it cannot be singular,
            // but should it be, the tangents say so by being NaN
            let factored = w.solver.factor(
                |i| -gamma_dt * lower[i],
                |i| capacity[i] - gamma_dt * diagonal[i],
                |i| -gamma_dt * upper[i],
            );
            for (p, tangent) in tangents.iter_mut().enumerate() {
                let df = &mut w.stage_df[p];
                for i in 0..n {
                    let mut rhs = w.start_capacity[i] * tangent[i];
                    for j in 0..stage {
                        rhs += dt * A[stage][j] * df[j][i];
                    }
                    w.known[i] = rhs;
                }
                let gain = if irrigation == Some(p) {
                    w.stage_supply_gain[stage]
                } else {
                    0.0
                };
                w.known[0] += gamma_dt * gain;
                let s = &mut w.tangent_stage;
                if !(factored && w.solver.solve_factored(&w.known, s)) {
                    s.fill(f64::NAN);
                }
                let out = &mut df[stage];
                for i in 0..n {
                    let mut v = diagonal[i] * s[i];
                    if i > 0 {
                        v += lower[i] * s[i - 1];
                    }
                    if i + 1 < n {
                        v += upper[i] * s[i + 1];
                    }
                    out[i] = v;
                }
                out[0] += gain;
                if stage + 1 == STAGES {
                    tangent.copy_from_slice(s);
                }
            }
        }
    }

    /// The fast path's stage solve: Newton in the heads with a backtracking
    /// line search on max|R|, the Thomas algorithm for the tridiagonal system.
    /// On success `work.eval` holds the evaluation at the solution.
    fn solve_stage_fast(&mut self, forcing: &Forcing, gamma_dt: f64, tolerance: f64) -> bool {
        let n = self.column.cells();
        let ss = self.column.soil().specific_storage;
        let column = self.column;
        let residual = |w: &mut Workspace| -> f64 {
            w.evaluations += 1;
            column.evaluate(&w.trial, forcing, &mut w.eval, Derivatives::Included);
            let mut norm = 0.0f64;
            for i in 0..n {
                let water = w.eval.states[i].water_content + ss * w.trial[i];
                w.residual[i] = water - w.known[i] - gamma_dt * w.eval.storage[i];
                norm = norm.max(w.residual[i].abs());
            }
            if norm.is_finite() {
                norm
            } else {
                f64::INFINITY
            }
        };
        let w = &mut self.work;
        let mut norm = residual(w);
        let mut iterations = 0;
        while norm > tolerance {
            if iterations == MAX_NEWTON_ITERATIONS || !norm.is_finite() {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            iterations += 1;
            self.statistics.newton_iterations += 1;
            // (diag(C + Ss) − γΔt·T)·δ = R, T tridiagonal; then H ← H − λ·δ.
            let e = &w.eval;
            let ok = solve_thomas(
                |i| -gamma_dt * e.lower[i],
                |i| e.states[i].capacity + ss - gamma_dt * e.diagonal[i],
                |i| -gamma_dt * e.upper[i],
                &w.residual,
                &mut w.update,
                &mut w.scratch,
            );
            if !ok {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            w.base.copy_from_slice(&w.trial);
            let mut lambda = 1.0;
            loop {
                for i in 0..n {
                    w.trial[i] = w.base[i] - lambda * w.update[i];
                }
                let next = residual(w);
                if next <= tolerance || next < (1.0 - 1e-4 * lambda) * norm {
                    norm = next;
                    break;
                }
                lambda *= 0.5;
                if lambda < LINE_SEARCH_FLOOR {
                    w.worst_cell = largest_entry(&w.residual);
                    return false;
                }
            }
        }
        true
    }

    /// The robust path's second try at a stage whose semismooth Newton
    /// failed: an active-set iteration (primary variable switching, Forsyth,
    /// Wu & Pruess 1995, Adv. Water Resources 18, 25–38; as a semismooth
    /// Newton method, Hintermüller, Ito & Kunisch 2003, SIAM J. Optim. 13,
    /// 865–888). Every cell is in one of two sets: saturated, evaluated on
    /// the saturated branch (θ = θs, K = Ks, storage θs + Ss·h) for any head,
    /// its unknown h; or unsaturated, evaluated by van Genuchten–Mualem, its
    /// unknown ψ of [`Coordinates`] (h stops at 0). Newton runs on the
    /// branches' residual, which is smooth in each cell, and after every
    /// iteration a saturated cell below h = 0 becomes unsaturated and an
    /// unsaturated cell on h = 0 that Newton pushes up becomes saturated
    /// (each cell at most [`MAX_SWITCHES`] times, then it stays). The solve
    /// succeeds when the sets agree with the heads (a saturated cell still a
    /// little below 0 is put on 0) and the residual of the model itself is
    /// within the tolerance.
    fn solve_stage_active_set(&mut self, forcing: &Forcing, gamma_dt: f64, tolerance: f64) -> bool {
        let n = self.column.cells();
        let ss = self.column.soil().specific_storage;
        let column = self.column;
        let coordinates = Coordinates::new(self.column.soil());
        let residual = |w: &mut Workspace| -> f64 {
            w.evaluations += 1;
            let saturated = &w.saturated;
            let chain = |i: usize, h: f64, st: &HydraulicState| {
                if saturated[i] {
                    (0.0, 1.0)
                } else {
                    coordinates.chain(h, st, Side::Below)
                }
            };
            w.eval.saturated_branch.copy_from_slice(&w.saturated);
            column.evaluate_in(
                &w.trial,
                forcing,
                &mut w.eval,
                Derivatives::Included,
                Some(&chain),
            );
            w.eval.saturated_branch.fill(false);
            let mut norm = 0.0f64;
            for i in 0..n {
                let water = w.eval.states[i].water_content + ss * w.trial[i];
                w.residual[i] = water - w.known[i] - gamma_dt * w.eval.storage[i];
                norm = norm.max(w.residual[i].abs());
            }
            if norm.is_finite() {
                norm
            } else {
                f64::INFINITY
            }
        };
        let w = &mut self.work;
        for i in 0..n {
            w.saturated[i] = w.trial[i] >= 0.0;
        }
        w.switches.fill(0);
        let mut norm = residual(w);
        let mut iterations = 0;
        loop {
            let consistent = (0..n).all(|i| !w.saturated[i] || w.trial[i] >= 0.0);
            if norm <= tolerance && consistent {
                break;
            }
            if iterations == MAX_NEWTON_ITERATIONS || !norm.is_finite() {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            iterations += 1;
            self.statistics.newton_iterations += 1;
            let e = &w.eval;
            let (trial, saturated) = (&w.trial, &w.saturated);
            let ok = w.solver.solve(
                |i| -gamma_dt * e.lower[i],
                |i| {
                    let dh = if saturated[i] {
                        1.0
                    } else {
                        coordinates.chain(trial[i], &e.states[i], Side::Below).1
                    };
                    (e.states[i].capacity + ss) * dh - gamma_dt * e.diagonal[i]
                },
                |i| -gamma_dt * e.upper[i],
                &w.residual,
                &mut w.update,
            );
            if !ok {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            // an unsaturated cell on h = 0 that Newton pushes up is saturated
            let mut switched = false;
            for i in 0..n {
                if !w.saturated[i]
                    && w.trial[i] == 0.0
                    && w.update[i] < 0.0
                    && w.switches[i] < MAX_SWITCHES
                {
                    w.saturated[i] = true;
                    w.switches[i] += 1;
                    switched = true;
                }
            }
            if switched {
                norm = residual(w);
                continue;
            }
            w.set_base(&coordinates);
            let mut lambda = 1.0;
            loop {
                for i in 0..n {
                    w.trial[i] = if w.saturated[i] {
                        w.base[i] - lambda * w.update[i]
                    } else {
                        coordinates
                            .step_from(w.base_coordinate[i], w.base[i], lambda * w.update[i])
                            .min(0.0)
                    };
                }
                let next = residual(w);
                if next <= tolerance || next < (1.0 - 1e-4 * lambda) * norm || lambda < 0.1 {
                    norm = next;
                    break;
                }
                lambda *= 0.5;
            }
            // a saturated cell below h = 0 is unsaturated
            let mut switched = false;
            for i in 0..n {
                if w.saturated[i] && w.trial[i] < 0.0 && w.switches[i] < MAX_SWITCHES {
                    w.saturated[i] = false;
                    w.switches[i] += 1;
                    switched = true;
                }
            }
            if switched {
                norm = residual(w);
            } else if norm <= tolerance {
                // the cells that may not switch any more go on the kink
                for i in 0..n {
                    if w.saturated[i] && w.trial[i] < 0.0 {
                        w.trial[i] = 0.0;
                    }
                }
                norm = residual(w);
            }
        }
        // the model's own residual, at the heads found
        w.saturated.fill(false);
        let norm = residual(w);
        if norm > tolerance {
            w.worst_cell = largest_entry(&w.residual);
            return false;
        }
        true
    }

    /// Pseudo-transient continuation (Kelley & Keyes 1998, SIAM J. Numer.
    /// Anal. 35, 508–523) for one stage, where semismooth Newton failed:
    /// Newton's matrix with its diagonal raised by D/τ, D the magnitude of
    /// each row (so a cell whose storage is below round-off gets a diagonal
    /// too), full steps, and τ growing as max|R| falls (switched evolution
    /// relaxation: τ ← τ·|R_old|/|R_new|), so the iteration turns into Newton
    /// near the solution. A step that raises max|R| more than
    /// [`PTC_GROWTH`]-fold is taken back and τ cut tenfold. Where the stage
    /// equations have several solutions per cell (the arithmetic-mean face
    /// flux near saturation for n near 1, `tests/column.rs`), the damped
    /// first steps follow the pseudo-time flow from the starting guess
    /// instead of jumping between branches. Starts from `work.trial`; on
    /// success `work.eval` holds the evaluation at the solution.
    fn solve_stage_pseudo_transient(
        &mut self,
        forcing: &Forcing,
        gamma_dt: f64,
        tolerance: f64,
    ) -> bool {
        let n = self.column.cells();
        let ss = self.column.soil().specific_storage;
        let column = self.column;
        let coordinates = Coordinates::new(self.column.soil());
        let residual =
            |w: &mut Workspace| stage_residual(&column, &coordinates, forcing, gamma_dt, w);
        let w = &mut self.work;
        w.side.fill(Side::BySign);
        let mut norm = residual(w);
        let mut tau = PTC_INITIAL_TAU;
        let mut iterations = 0;
        while norm > tolerance {
            if iterations == PTC_ITERATIONS || !norm.is_finite() || tau < PTC_SMALLEST_TAU {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            iterations += 1;
            self.statistics.newton_iterations += 1;
            // the evaluation at the iterate took its derivatives by the
            // heads' signs (w.side is BySign throughout): its dh/du is the
            // chain's
            let e = &w.eval;
            let diagonal =
                |i: usize| (e.states[i].capacity + ss) * e.chains[i].1 - gamma_dt * e.diagonal[i];
            let shift = |i: usize| {
                (diagonal(i).abs() + gamma_dt * (e.lower[i].abs() + e.upper[i].abs())) / tau
            };
            let ok = w.solver.solve(
                |i| -gamma_dt * e.lower[i],
                |i| diagonal(i) + shift(i),
                |i| -gamma_dt * e.upper[i],
                &w.residual,
                &mut w.update,
            );
            if !ok {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            w.base.copy_from_slice(&w.trial);
            for i in 0..n {
                w.trial[i] = coordinates.step(w.base[i], w.update[i]);
            }
            let next = residual(w);
            if next.is_finite() && next < PTC_GROWTH * norm {
                tau = (tau * norm / next.max(f64::MIN_POSITIVE)).min(PTC_LARGEST_TAU);
                norm = next;
            } else {
                tau *= 0.1;
                w.trial.copy_from_slice(&w.base);
                norm = residual(w);
            }
        }
        true
    }

    /// The robust path's last try at a stage: Levenberg–Marquardt on ½|R|²
    /// in the coordinates of [`Coordinates`] (Moré 1978, Lecture Notes in
    /// Mathematics 630, 105–116). Near saturation a run of cells whose
    /// storage vanishes (dθ/dψ → 0) has a Newton matrix that is a centred
    /// difference of K, singular for a run of odd length (the odd–even
    /// decoupling of the arithmetic face mean): Newton's updates there are
    /// huge in the null direction and its line search stalls. The damped
    /// normal equations (JᵀJ + μ·diag(JᵀJ))·δ = JᵀR stay solvable and give
    /// a descent direction for |R|² whatever the rank; μ falls after a step
    /// that reduces |R|² and rises after one that does not. The solution is
    /// that of the same residual, to the same tolerance.
    fn solve_stage_least_squares(
        &mut self,
        forcing: &Forcing,
        gamma_dt: f64,
        tolerance: f64,
    ) -> bool {
        let n = self.column.cells();
        let ss = self.column.soil().specific_storage;
        let column = self.column;
        let coordinates = Coordinates::new(self.column.soil());
        let residual = |w: &mut Workspace| -> (f64, f64) {
            let norm = stage_residual(&column, &coordinates, forcing, gamma_dt, w);
            let squares: f64 = w.residual.iter().map(|r| r * r).sum();
            if squares.is_finite() {
                (norm, squares)
            } else {
                (f64::INFINITY, f64::INFINITY)
            }
        };
        let w = &mut self.work;
        w.side.fill(Side::BySign);
        let (mut norm, mut squares) = residual(w);
        let mut mu = LM_INITIAL_DAMPING;
        let mut iterations = 0;
        while norm > tolerance {
            if iterations >= LM_ITERATIONS || !norm.is_finite() {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            // JᵀJ and JᵀR of the tridiagonal J at the iterate
            let normal = &mut w.normal;
            normal.fill(0.0);
            w.gradient.fill(0.0);
            for i in 0..n {
                let (_, dh) = coordinates.chain(w.trial[i], &w.eval.states[i], Side::BySign);
                let row = [
                    (i.wrapping_sub(1), -gamma_dt * w.eval.lower[i]),
                    (
                        i,
                        (w.eval.states[i].capacity + ss) * dh - gamma_dt * w.eval.diagonal[i],
                    ),
                    (i + 1, -gamma_dt * w.eval.upper[i]),
                ];
                for &(j, a) in &row {
                    if j >= n {
                        continue;
                    }
                    w.gradient[j] += a * w.residual[i];
                    for &(k, b) in &row {
                        if k < n {
                            normal[j * n + k] += a * b;
                        }
                    }
                }
            }
            let largest = (0..n).map(|j| normal[j * n + j]).fold(0.0, f64::max);
            if !(largest > 0.0 && largest.is_finite()) {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            w.set_base(&coordinates);
            w.base_residual.copy_from_slice(&w.residual);
            loop {
                iterations += 1;
                self.statistics.newton_iterations += 1;
                let factor = &mut w.factor;
                factor.copy_from_slice(&w.normal);
                for j in 0..n {
                    let d = w.normal[j * n + j].max(1e-12 * largest);
                    factor[j * n + j] += mu * d;
                }
                // JᵀJ of a tridiagonal J is pentadiagonal
                let solved = cholesky_solve(factor, n, 2, &w.gradient, &mut w.update);
                if solved {
                    for i in 0..n {
                        w.trial[i] = match w.base_coordinate[i] {
                            Some(u) => coordinates.head(u - w.update[i]),
                            None => w.base[i] - w.update[i],
                        };
                    }
                    let (next_norm, next_squares) = residual(w);
                    if next_squares < squares {
                        (norm, squares) = (next_norm, next_squares);
                        mu = (mu / 3.0).max(1e-12);
                        break;
                    }
                }
                mu *= 4.0;
                if mu > LM_LARGEST_DAMPING || iterations >= LM_ITERATIONS {
                    w.trial.copy_from_slice(&w.base);
                    w.residual.copy_from_slice(&w.base_residual);
                    w.worst_cell = largest_entry(&w.residual);
                    return false;
                }
            }
        }
        true
    }

    /// Newton's stopping residual, [`NEWTON_FRACTION`] of the error scale at saturation.
    fn newton_tolerance(&self) -> f64 {
        let soil = self.column.soil();
        NEWTON_FRACTION
            * (self.tolerances.absolute + self.tolerances.relative * soil.saturated_water_content)
    }

    /// Semismooth Newton with a backtracking line search on max|R| for one
    /// stage: w(H) − known − γΔt·F(H) = 0, starting from `work.trial`. On
    /// success `work.eval` holds the evaluation at the solution.
    ///
    /// Near saturation the unknowns are the coordinates of [`Coordinates`],
    /// in which K is Lipschitz; where the residual has a kink (a cell at
    /// h = 0, K' = 0 above and K' → ∞ below) the Jacobian takes the side the
    /// step goes to, a step that crosses the kink stops on it, and a few full
    /// steps are taken even when they do not reduce max|R| (a watchdog).
    fn solve_stage(
        &mut self,
        forcing: &Forcing,
        gamma_dt: f64,
        tolerance: f64,
        iterations: usize,
    ) -> bool {
        let n = self.column.cells();
        let ss = self.column.soil().specific_storage;
        let column = self.column;
        let coordinates = Coordinates::new(self.column.soil());
        let residual =
            |w: &mut Workspace| stage_residual(&column, &coordinates, forcing, gamma_dt, w);
        let w = &mut self.work;
        w.side.fill(Side::BySign);
        let mut norm = residual(w);
        let mut done = 0;
        let mut watchdog = WATCHDOG_STEPS;
        while norm > tolerance {
            if done == iterations || !norm.is_finite() {
                w.worst_cell = largest_entry(&w.residual);
                return false;
            }
            done += 1;
            self.statistics.newton_iterations += 1;
            // (∂w/∂u − γΔt·∂F/∂u)·δ = R, tridiagonal; then u ← u − λ·δ. A cell
            // on a kink whose step leaves it to the other side than the one
            // its Jacobian was taken on is given that side, and δ solved again
            // (at most three times).
            let mut flips = 0;
            loop {
                // the evaluation at the iterate took its derivatives with
                // the same heads and sides: its dh/du is the chain's
                let e = &w.eval;
                let ok = w.solver.solve(
                    |i| -gamma_dt * e.lower[i],
                    |i| (e.states[i].capacity + ss) * e.chains[i].1 - gamma_dt * e.diagonal[i],
                    |i| -gamma_dt * e.upper[i],
                    &w.residual,
                    &mut w.update,
                );
                if !ok {
                    w.worst_cell = largest_entry(&w.residual);
                    return false;
                }
                if flips == 3 || !coordinates.active {
                    break;
                }
                let mut changed = false;
                for i in 0..n {
                    if coordinates.on_kink(w.trial[i]) {
                        let to = if w.update[i] > 0.0 {
                            Side::Below
                        } else {
                            Side::Above
                        };
                        let now = match w.side[i] {
                            Side::BySign => Side::Above,
                            s => s,
                        };
                        if to != now {
                            w.side[i] = to;
                            changed = true;
                        }
                    }
                }
                if !changed {
                    break;
                }
                flips += 1;
                residual(w);
            }
            w.set_base(&coordinates);
            w.side.fill(Side::BySign);
            let mut lambda = 1.0;
            loop {
                for i in 0..n {
                    w.trial[i] = coordinates.step_from(
                        w.base_coordinate[i],
                        w.base[i],
                        lambda * w.update[i],
                    );
                }
                let next = residual(w);
                // the watchdog's full steps are the first few of the solve
                let full = watchdog > 0 && lambda == 1.0 && next < WATCHDOG_GROWTH * norm;
                if full {
                    watchdog -= 1;
                }
                if next <= tolerance || next < (1.0 - 1e-4 * lambda) * norm || full {
                    norm = next;
                    break;
                }
                lambda *= 0.5;
                if lambda < LINE_SEARCH_FLOOR {
                    w.worst_cell = largest_entry(&w.residual);
                    return false;
                }
            }
        }
        true
    }
}

/// The robust path's stage residual R = w(H) − known − γΔt·F(H) at
/// `work.trial`, with the derivatives in each cell's Newton unknown (the
/// kink's side from `work.side`) in `work.eval`; returns max|R| (infinite
/// when it is not finite).
fn stage_residual(
    column: &Column,
    coordinates: &Coordinates,
    forcing: &Forcing,
    gamma_dt: f64,
    w: &mut Workspace,
) -> f64 {
    w.evaluations += 1;
    let ss = column.soil().specific_storage;
    let side = &w.side;
    let chain = |i: usize, h: f64, st: &HydraulicState| coordinates.chain(h, st, side[i]);
    column.evaluate_in(
        &w.trial,
        forcing,
        &mut w.eval,
        Derivatives::Included,
        Some(&chain),
    );
    let mut norm = 0.0f64;
    for i in 0..column.cells() {
        let water = w.eval.states[i].water_content + ss * w.trial[i];
        w.residual[i] = water - w.known[i] - gamma_dt * w.eval.storage[i];
        norm = norm.max(w.residual[i].abs());
    }
    if norm.is_finite() {
        norm
    } else {
        f64::INFINITY
    }
}

/// Where the last stage's projection puts the water that the cells that
/// cannot take their own residual leave (see `Integrator::project_last_stage`).
#[derive(Debug, Clone, Copy)]
enum Placement {
    /// One cell takes it all.
    Sink(usize),
    /// The taking cells, in proportion to their room (the total given).
    Spread(f64),
    /// Every cell alike.
    Uniform,
    /// Nobody: those cells keep their heads.
    Keep,
}

/// How a step attempt solves its stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Path {
    /// Newton in the heads from an extrapolated guess, to round-off in the
    /// last stage, with the Thomas algorithm: cheap, and enough wherever the
    /// residual is smooth (no cell at the cusp of K at saturation).
    Fast,
    /// Semismooth Newton in the coordinates of [`Coordinates`] with a
    /// watchdog, a pivoting solver and the projected last stage.
    Robust,
}

/// Which one-sided derivative a cell at the kink h = 0 takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Side {
    /// Below (h < 0) or above (h ≥ 0) by the sign of h.
    BySign,
    Below,
    Above,
}

/// Newton's unknowns near saturation, for n < 2.
///
/// For n < 2 the Mualem conductivity has a cusp at saturation: with
/// a = α|h|, K ≈ Ks·(1 − 2a^(n−1)) as h → 0⁻, so dK/dh ~ a^(n−2) → ∞, while
/// K = Ks above. In ψ = −a^(n−1) below saturation K is Lipschitz (dK/dψ → 2Ks)
/// and h, θ are C¹ (dh/dψ → 0); above, the unknown is ψ = α·h. The residual
/// is then piecewise smooth with a kink at ψ = 0, the setting of semismooth
/// Newton methods (Qi & Sun 1993, Math. Programming 58, 353–367) and of the
/// primary variable switching of Forsyth, Wu & Pruess (1995, Adv. Water
/// Resources 18, 25–38), which likewise changes the unknown where a cell
/// crosses saturation. Only the iteration changes: the residual, and so the
/// solution, is that of MODEL.md. Far from saturation (a^(n−1) ≥ 1/2) the
/// unknown is h itself.
#[derive(Debug, Clone, Copy)]
struct Coordinates {
    alpha: f64,
    exponent: f64,
    saturated_conductivity: f64,
    /// Whether ψ is used at all (n < 2: there is a cusp).
    active: bool,
    /// α|h| at or above which ψ is not the unknown, PSI_LIMIT^(1/(n−1)):
    /// a cell away from the cusp then costs no power.
    limit: f64,
}

/// a^(n−1) below which ψ is the unknown.
const PSI_LIMIT: f64 = 0.5;

impl Coordinates {
    fn new(soil: &VanGenuchten) -> Self {
        Coordinates {
            alpha: soil.alpha,
            exponent: soil.n - 1.0,
            saturated_conductivity: soil.saturated_conductivity,
            active: soil.n < 2.0,
            limit: PSI_LIMIT.powf(1.0 / (soil.n - 1.0)),
        }
    }

    /// ψ of h where ψ is the unknown: α·h for h ≥ 0, −(α|h|)^(n−1) below.
    fn coordinate(&self, h: f64) -> Option<f64> {
        if !self.active {
            return None;
        }
        if h >= 0.0 {
            return Some(self.alpha * h);
        }
        let a = -self.alpha * h;
        if a >= self.limit {
            return None;
        }
        let p = a.powf(self.exponent);
        (p < PSI_LIMIT).then_some(-p)
    }

    /// (dK/du, dh/du) at h for the cell's unknown u.
    fn chain(&self, h: f64, s: &HydraulicState, side: Side) -> (f64, f64) {
        if !self.has_coordinate(h) {
            return (s.conductivity_derivative, 1.0);
        }
        let below = match side {
            Side::BySign => h < 0.0,
            Side::Below => true,
            Side::Above => false,
        };
        if !below {
            return (0.0, 1.0 / self.alpha);
        }
        let a = (-self.alpha * h).max(0.0);
        if a < 1e-12 {
            // dK/dh is floored there (see hydraulics): with Se = 1 − O(a^n),
            // K = Ks·(1 − |ψ|)² + O(a^n), so dK/dψ = 2Ks·(1 − |ψ|)
            let y = a.powf(self.exponent);
            let dh = if a > 0.0 {
                a / (y * self.alpha * self.exponent)
            } else {
                0.0
            };
            return (2.0 * self.saturated_conductivity * (1.0 - y), dh);
        }
        // h = −|ψ|^(1/(n−1))/α: dh/dψ = a^(2−n)/(α(n−1))
        let dh = a.powf(1.0 - self.exponent) / (self.alpha * self.exponent);
        (s.conductivity_derivative * dh, dh)
    }

    /// The head of coordinate ψ.
    fn head(&self, psi: f64) -> f64 {
        if psi >= 0.0 {
            psi / self.alpha
        } else {
            -(-psi).powf(1.0 / self.exponent) / self.alpha
        }
    }

    /// Whether the cell's unknown is ψ, i.e. `coordinate(h).is_some()`,
    /// with the power only where α|h| is within 1e-12 (relative) of the
    /// limit: below it a^(n−1) < PSI_LIMIT by far more than the power's
    /// rounding (under an ulp), at or above it ψ is not the unknown.
    fn has_coordinate(&self, h: f64) -> bool {
        if !self.active {
            return false;
        }
        if h >= 0.0 {
            return true;
        }
        let a = -self.alpha * h;
        if a < self.limit * (1.0 - 1e-12) {
            true
        } else {
            self.coordinate(h).is_some()
        }
    }

    /// Whether the cell's unknown is ψ and ψ = 0, i.e. `coordinate(h) ==
    /// Some(0.0)`, without the power: for h < 0, a^(n−1) ≥ a > 0 when
    /// 0 < a ≤ 1 and n < 2, so ψ = 0 only where α·h is 0.
    fn on_kink(&self, h: f64) -> bool {
        self.active && self.alpha * h == 0.0
    }

    /// The head after the step −δ in the cell's unknown; a step that crosses
    /// the kink from either side stops on it (h = 0).
    fn step(&self, base: f64, delta: f64) -> f64 {
        self.step_from(self.coordinate(base), base, delta)
    }

    /// [`Coordinates::step`] with the base's coordinate already known
    /// (`coordinate(base)`), as a line search needs it at every trial.
    fn step_from(&self, coordinate: Option<f64>, base: f64, delta: f64) -> f64 {
        match coordinate {
            None => base - delta,
            Some(u) => {
                let to = u - delta;
                if u != 0.0 && to != 0.0 && (to < 0.0) != (u < 0.0) {
                    0.0
                } else {
                    self.head(to)
                }
            }
        }
    }
}

/// The index of the entry of largest magnitude (NaN counts as largest).
fn largest_entry(values: &[f64]) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for (i, v) in values.iter().enumerate() {
        let m = if v.is_nan() { f64::INFINITY } else { v.abs() };
        if best.is_none_or(|(_, b)| m > b) {
            best = Some((i, m));
        }
    }
    best.map(|(i, _)| i)
}

/// Solves the symmetric positive definite system `matrix·x = rhs` (`matrix`
/// n×n, row-major, overwritten by its Cholesky factor), whose entries are
/// zero more than `bandwidth` places off the diagonal. The factor of a band
/// matrix has the same band (no fill-in outside it), so only the band is
/// computed: O(n·bandwidth²) instead of O(n³), and the same numbers as the
/// dense algorithm, whose terms outside the band are products with zeros.
/// Returns false if a pivot is not positive or the solution is not finite.
fn cholesky_solve(
    matrix: &mut [f64],
    n: usize,
    bandwidth: usize,
    rhs: &[f64],
    x: &mut [f64],
) -> bool {
    for j in 0..n {
        let mut d = matrix[j * n + j];
        for k in j.saturating_sub(bandwidth)..j {
            d -= matrix[j * n + k] * matrix[j * n + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        matrix[j * n + j] = d;
        for i in j + 1..(j + bandwidth + 1).min(n) {
            let mut v = matrix[i * n + j];
            for k in i.saturating_sub(bandwidth)..j {
                v -= matrix[i * n + k] * matrix[j * n + k];
            }
            matrix[i * n + j] = v / d;
        }
    }
    for i in 0..n {
        let mut v = rhs[i];
        for k in i.saturating_sub(bandwidth)..i {
            v -= matrix[i * n + k] * x[k];
        }
        x[i] = v / matrix[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = x[i];
        for k in i + 1..(i + bandwidth + 1).min(n) {
            v -= matrix[k * n + i] * x[k];
        }
        x[i] = v / matrix[i * n + i];
    }
    x.iter().all(|v| v.is_finite())
}

/// Solves the tridiagonal system with sub-diagonal `a(i)` (row i, column i−1),
/// diagonal `b(i)` and super-diagonal `c(i)` by the Thomas algorithm (the
/// fast path: its Newton matrices are diagonally dominant away from the cusp).
/// Returns false if a pivot vanishes or is not finite.
fn solve_thomas(
    a: impl Fn(usize) -> f64,
    b: impl Fn(usize) -> f64,
    c: impl Fn(usize) -> f64,
    rhs: &[f64],
    x: &mut [f64],
    scratch: &mut [f64],
) -> bool {
    let n = rhs.len();
    let mut pivot = b(0);
    if pivot.abs() < 1e-300 || !pivot.is_finite() {
        return false;
    }
    x[0] = rhs[0] / pivot;
    for i in 1..n {
        scratch[i] = c(i - 1) / pivot;
        pivot = b(i) - a(i) * scratch[i];
        if pivot.abs() < 1e-300 || !pivot.is_finite() {
            return false;
        }
        x[i] = (rhs[i] - a(i) * x[i - 1]) / pivot;
    }
    for i in (0..n - 1).rev() {
        x[i] -= scratch[i + 1] * x[i + 1];
    }
    true
}

/// Tridiagonal solver by Gaussian elimination with partial pivoting (the
/// scheme of LAPACK's `dgtsv`: a row swap fills one second super-diagonal).
/// Near saturation the Newton matrix in ψ is not diagonally dominant (a cell
/// on a kink has a near-zero diagonal and large off-diagonals), where the
/// Thomas algorithm is unstable.
#[derive(Debug, Clone)]
struct Tridiagonal {
    /// U of the factorisation: its diagonal, first and second super-diagonal.
    diagonal: Vec<f64>,
    upper: Vec<f64>,
    second: Vec<f64>,
    /// Per elimination step i, the multiplier and whether rows i and i+1
    /// were swapped.
    multiplier: Vec<f64>,
    swapped: Vec<bool>,
    rhs: Vec<f64>,
}

impl Tridiagonal {
    fn new(n: usize) -> Self {
        let z = vec![0.0; n];
        Tridiagonal {
            diagonal: z.clone(),
            upper: z.clone(),
            second: z.clone(),
            multiplier: z.clone(),
            swapped: vec![false; n],
            rhs: z,
        }
    }

    /// Solves the system with sub-diagonal `a(i)` (row i, column i−1),
    /// diagonal `b(i)` and super-diagonal `c(i)` for `x`. Returns false if a
    /// pivot vanishes or the solution is not finite (the matrix is then
    /// treated as singular).
    fn solve(
        &mut self,
        a: impl Fn(usize) -> f64,
        b: impl Fn(usize) -> f64,
        c: impl Fn(usize) -> f64,
        rhs: &[f64],
        x: &mut [f64],
    ) -> bool {
        self.factor(a, b, c) && self.solve_factored(rhs, x)
    }

    /// Factorises the matrix of [`Tridiagonal::solve`] for
    /// [`Tridiagonal::solve_factored`]; false if a pivot vanishes.
    fn factor(
        &mut self,
        a: impl Fn(usize) -> f64,
        b: impl Fn(usize) -> f64,
        c: impl Fn(usize) -> f64,
    ) -> bool {
        let n = self.diagonal.len();
        let (d, du, du2) = (&mut self.diagonal, &mut self.upper, &mut self.second);
        for i in 0..n {
            d[i] = b(i);
            du[i] = if i + 1 < n { c(i) } else { 0.0 };
            du2[i] = 0.0;
        }
        for i in 0..n.saturating_sub(1) {
            let below = a(i + 1);
            if d[i].abs() >= below.abs() {
                if d[i] == 0.0 {
                    return false;
                }
                let f = below / d[i];
                d[i + 1] -= f * du[i];
                self.multiplier[i] = f;
                self.swapped[i] = false;
            } else {
                // swap rows i and i+1
                let f = d[i] / below;
                d[i] = below;
                let t = d[i + 1];
                d[i + 1] = du[i] - f * t;
                if i + 2 < n {
                    du2[i] = du[i + 1];
                    du[i + 1] = -f * du2[i];
                }
                du[i] = t;
                self.multiplier[i] = f;
                self.swapped[i] = true;
            }
        }
        d[n - 1] != 0.0
    }

    /// Solves with the last factorisation (which must have succeeded) for
    /// the right-hand side `rhs`; false if the solution is not finite.
    fn solve_factored(&mut self, rhs: &[f64], x: &mut [f64]) -> bool {
        let n = rhs.len();
        let r = &mut self.rhs;
        r.copy_from_slice(rhs);
        for i in 0..n.saturating_sub(1) {
            let f = self.multiplier[i];
            if self.swapped[i] {
                let t = r[i];
                r[i] = r[i + 1];
                r[i + 1] = t - f * r[i + 1];
            } else {
                r[i + 1] -= f * r[i];
            }
        }
        let (d, du, du2) = (&self.diagonal, &self.upper, &self.second);
        for i in (0..n).rev() {
            let mut v = r[i];
            if i + 1 < n {
                v -= du[i] * x[i + 1];
            }
            if i + 2 < n {
                v -= du2[i] * x[i + 2];
            }
            x[i] = v / d[i];
        }
        x.iter().all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The order conditions up to order 3 for b (= last row of A) and up to 2 for b̂.
    #[test]
    fn tableau_satisfies_the_order_conditions() {
        let c: Vec<f64> = A.iter().map(|row| row.iter().sum()).collect();
        let b = A[STAGES - 1];
        let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(a, b)| a * b).sum::<f64>();
        let ac = |v: &[f64]| -> Vec<f64> { A.iter().map(|row| dot(row, v)).collect() };
        let c2: Vec<f64> = c.iter().map(|x| x * x).collect();
        let c3: Vec<f64> = c.iter().map(|x| x * x * x).collect();
        let ac_ = ac(&c);
        let checks = |w: &[f64], order: usize| {
            let mut conditions = vec![(dot(w, &[1.0; STAGES]), 1.0), (dot(w, &c), 0.5)];
            if order >= 3 {
                conditions.push((dot(w, &c2), 1.0 / 3.0));
                conditions.push((dot(w, &ac_), 1.0 / 6.0));
            }
            for (k, (got, want)) in conditions.into_iter().enumerate() {
                assert!((got - want).abs() < 1e-12, "condition {k}: {got} vs {want}");
            }
        };
        checks(&b, 3);
        checks(&B_HAT, 2);
        // the first fourth-order condition (Σ b c³ = 1/4) fails: order 3, not more
        assert!((dot(&b, &c3) - 0.25).abs() > 1e-3);
        assert!((c[STAGES - 1] - 1.0).abs() < 1e-15);
        for (i, row) in A.iter().enumerate() {
            assert_eq!(row[i], GAMMA);
        }
    }

    /// L-stability from the stability function R(z) = 1 + z·bᵀ(I − zA)⁻¹𝟙,
    /// by forward substitution (A is lower triangular): |R(iy)| ≤ 1 on the
    /// imaginary axis (A-stable) and R(z) → 0 as z → −∞.
    #[test]
    fn tableau_is_l_stable() {
        use nalgebra::Complex;
        let r = |z: Complex<f64>| {
            let mut k = [Complex::new(0.0, 0.0); STAGES];
            for i in 0..STAGES {
                let mut sum = Complex::new(1.0, 0.0);
                for j in 0..i {
                    sum += z * A[i][j] * k[j];
                }
                k[i] = sum / (Complex::new(1.0, 0.0) - z * GAMMA);
            }
            let mut out = Complex::new(1.0, 0.0);
            for i in 0..STAGES {
                out += z * A[STAGES - 1][i] * k[i];
            }
            out
        };
        for e in -40..=80 {
            let y = 10f64.powf(f64::from(e) / 10.0);
            let m = r(Complex::new(0.0, y)).norm();
            assert!(m <= 1.0 + 1e-12, "|R({y}i)| = {m}");
        }
        for x in [1e6, 1e9, 1e12] {
            let m = r(Complex::new(-x, 0.0)).norm();
            assert!(m < 10.0 / x, "|R(−{x})| = {m}");
        }
        // and it is consistent: R(z) = e^z + O(z⁴) at small z
        let m = r(Complex::new(-0.01, 0.0)).re;
        assert!((m - (-0.01f64).exp()).abs() < 1e-8, "{m}");
    }

    #[test]
    fn the_tridiagonal_solver_solves_known_systems() {
        let mut solver = Tridiagonal::new(3);
        let mut x = vec![0.0; 3];
        // [[4,1,0],[1,4,1],[0,1,4]]·x = [5,6,5] has x = [1,1,1].
        assert!(solver.solve(|_| 1.0, |_| 4.0, |_| 1.0, &[5.0, 6.0, 5.0], &mut x));
        for v in &x {
            assert!((v - 1.0).abs() < 1e-14);
        }
        // a zero diagonal needs the row swaps: [[0,1,0],[1,0,1],[0,1,1]]·x = [2,4,5]
        // has x = [1,2,3].
        assert!(solver.solve(
            |_| 1.0,
            |i| if i == 2 { 1.0 } else { 0.0 },
            |_| 1.0,
            &[2.0, 4.0, 5.0],
            &mut x
        ));
        for (v, want) in x.iter().zip([1.0, 2.0, 3.0]) {
            assert!((v - want).abs() < 1e-14, "{x:?}");
        }
        assert!(!solver.solve(|_| 0.0, |_| 0.0, |_| 0.0, &[1.0; 3], &mut x));
    }

    /// The banded Cholesky solve of the normal equations: JᵀJ·x = JᵀJ·x* for
    /// a tridiagonal J gives x* back, to the same bits with the band as
    /// with the whole matrix (bandwidth n − 1, the dense algorithm), and a
    /// matrix that is not positive definite is refused.
    #[test]
    fn the_banded_cholesky_solves_normal_equations_as_the_dense_one_does() {
        let n = 9;
        let j = |r: usize, c: usize| -> f64 {
            match (r as i64 - c as i64).abs() {
                0 => 3.0 + 0.25 * r as f64,
                1 => -1.0 + 0.1 * (r + c) as f64,
                _ => 0.0,
            }
        };
        let mut normal = vec![0.0; n * n];
        for a in 0..n {
            for b in 0..n {
                normal[a * n + b] = (0..n).map(|r| j(r, a) * j(r, b)).sum();
            }
        }
        let want: Vec<f64> = (0..n).map(|i| (i as f64 - 3.5) / 2.0).collect();
        let rhs: Vec<f64> = (0..n)
            .map(|a| (0..n).map(|b| normal[a * n + b] * want[b]).sum())
            .collect();
        let (mut banded, mut dense) = (normal.clone(), normal.clone());
        let (mut x_banded, mut x_dense) = (vec![0.0; n], vec![0.0; n]);
        assert!(cholesky_solve(&mut banded, n, 2, &rhs, &mut x_banded));
        assert!(cholesky_solve(&mut dense, n, n - 1, &rhs, &mut x_dense));
        for (got, want) in x_banded.iter().zip(&want) {
            assert!((got - want).abs() < 1e-12, "{x_banded:?}");
        }
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&x_banded), bits(&x_dense));
        assert_eq!(bits(&banded), bits(&dense));
        let mut indefinite = normal.clone();
        indefinite[4 * n + 4] = -1.0;
        assert!(!cholesky_solve(&mut indefinite, n, 2, &rhs, &mut x_banded));
    }

    /// The shortcuts of the Newton coordinates say what `coordinate` says:
    /// whether ψ is the unknown, and whether it is the kink ψ = 0, on both
    /// sides of the limit and at saturation.
    #[test]
    fn the_coordinate_shortcuts_agree_with_the_coordinate() {
        for texture in crate::soil::Texture::ALL {
            let c = Coordinates::new(&texture.parameters());
            let limit_head = -c.limit / c.alpha;
            let mut heads = vec![
                0.0,
                -0.0,
                1e-6,
                -1e-300,
                -1e-9,
                -1e-3,
                -0.1,
                -10.0,
                f64::NAN,
            ];
            for f in [
                0.5,
                1.0 - 1e-9,
                1.0 - 1e-13,
                1.0,
                1.0 + 1e-13,
                1.0 + 1e-9,
                2.0,
            ] {
                heads.push(limit_head * f);
            }
            for h in heads {
                assert_eq!(
                    c.has_coordinate(h),
                    c.coordinate(h).is_some(),
                    "{texture} h = {h}"
                );
                assert_eq!(
                    c.on_kink(h),
                    c.coordinate(h) == Some(0.0),
                    "{texture} h = {h}"
                );
                assert_eq!(
                    c.step_from(c.coordinate(h), h, 1e-4).to_bits(),
                    c.step(h, 1e-4).to_bits()
                );
            }
        }
    }

    /// The Newton coordinates near saturation map back to the heads and
    /// have the derivatives they claim.
    #[test]
    fn psi_coordinates_are_consistent() {
        let soil = crate::soil::Texture::Loam.parameters();
        let c = Coordinates::new(&soil);
        for h in [-0.05, -1e-3, -1e-7, 0.0, 1e-6] {
            let u = c.coordinate(h).unwrap();
            assert!((c.head(u) - h).abs() <= 1e-12 * h.abs().max(1e-300), "{h}");
            let (dk, dh) = c.chain(h, &soil.state(h), Side::BySign);
            let e = 1e-7 * u.abs().max(1e-9);
            let (hp, hm) = (c.head(u + e), c.head(u - e));
            let fd_h = (hp - hm) / (2.0 * e);
            let fd_k = (soil.conductivity(hp) - soil.conductivity(hm)) / (2.0 * e);
            if h != 0.0 {
                assert!(
                    (fd_h - dh).abs() <= 1e-4 * dh.abs() + 1e-12,
                    "{h}: {fd_h} vs {dh}"
                );
                assert!(
                    (fd_k - dk).abs() <= 1e-4 * dk.abs() + 1e-15,
                    "{h}: {fd_k} vs {dk}"
                );
            }
        }
        // far from saturation the unknown is the head
        assert!(c.coordinate(-1.0).is_none());
        assert!(
            Coordinates::new(&crate::soil::Texture::Sand.parameters())
                .coordinate(-1e-3)
                .is_none()
        );
    }
}
