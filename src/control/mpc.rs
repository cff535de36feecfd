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
//! (minimising over the slack y_z gives back dist², so the QP's value is the
//! objective of the linearised model). The trust region Δ globalises the
//! iteration: a step is accepted when the true objective falls by at least a
//! tenth of the decrease the linearised objective predicts (evaluated exactly
//! at the QP's plan, not taken from the QP solver, whose tolerance would
//! swamp small steps); Δ grows after good steps and shrinks after poor ones.
//! The iteration stops when a step changes no input by more than
//! `step_tolerance`, the predicted decrease is negligible, or three accepted
//! steps in a row each gain less than that tolerance (converged), when
//! the model is not smooth at the plan (converged, see `NONSMOOTH_STEP`),
//! at the iteration cap, when the model's work budget is spent, or at the
//! time budget, and always returns the best plan evaluated.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettingsBuilder, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus,
};

use super::model::PredictionModel;
use super::zone::ZoneSettings;
use crate::soil::Interrupt;

/// Consecutive accepted SQP steps, each gaining less than the objective
/// tolerance, after which a run counts as converged.
const STALL_STEPS: usize = 3;

/// A model that is not smooth at the plan: where a run's trials are
/// rejected at a step below `NONSMOOTH_STEP` (trust metric), or where the
/// linearisation promises less than `NONSMOOTH_GAIN` of J, the miss of each
/// rejected trial (its objective minus the linearisation's) is compared
/// with the previous one's. For a model smooth at the plan the miss falls
/// with the step, at least linearly (quadratically once the step is
/// small), and the trust region shrinks the step 4× per rejection; a miss
/// that does not halve from one rejection to the next says that the
/// prediction jumps at this plan, and the run ends there (converged: no
/// smaller step can be trusted either). On the fine textures near
/// saturation the Richards model's stage equations have several solutions
/// per cell (ARCHITECTURE.md, "Ponding and near-saturated flow"), and a
/// change of 1e-5 in the metric moved a silty clay's J from 0.76 to 2.1;
/// until this test the trust region shrank from 0.5 to `step_tolerance`
/// in 9 or 10 rejections, each a prediction.
const NONSMOOTH_STEP: f64 = 1e-3;
const NONSMOOTH_GAIN: f64 = 1e-2;

/// The largest |∂Se(ŷ_k)/∂ū_j| a QP is given. Mass balance caps the mean
/// slope over a whole cell's range: raising the sensor cell from θr to θs
/// takes its pore water dz·(θs − θr), 5.6 mm or more for every texture
/// (0.5 m in 26 cells, θs − θr ≥ 0.29), and one step at u_max brings
/// 72 mm, so that slope is below 13. Near saturation a fine soil's discrete solution is
/// hypersensitive and its tangents reach 1e16 (silty clay), a QP with
/// Q·G² ≈ 1e35 beside R = 100 that clarabel cannot solve (NumericalError):
/// the cap keeps the QP solvable, and the trust region's acceptance test on
/// the true model judges the step, as for any linearisation error.
const G_LIMIT: f64 = 1e4;

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
    /// Relative decrease of J, predicted by the linearisation, below which
    /// the iteration has converged.
    pub objective_tolerance: f64,
    pub time_budget: Duration,
    /// The model work one solve may spend over all its evaluations, in the
    /// model's unit ([`PredictionModel::set_work_budget`]: Newton
    /// iterations for the Richards model; the surrogates have none). The
    /// ordinary limit of a dear solve: a count, so the plan does not depend
    /// on the machine's load; `time_budget` is the safety net behind it.
    pub work_budget: Option<usize>,
    /// The rate [m/s] below which the trust region turns from logarithmic to
    /// linear (see [`TrustMetric`]) in cold runs; a knee as large as u_max
    /// makes it nearly linear, which explores widely.
    pub trust_region_knee: f64,
    /// The same for a warm-started run, which starts near the optimum.
    pub warm_trust_region_knee: f64,
    /// Most SQP runs of a solve: the start and the `starts − 1` most
    /// promising constant plans (see [`ZoneMpc::solve`]).
    pub starts: usize,
}

/// The default [`MpcSettings::work_budget`]: 60,000 Newton iterations of
/// the Richards model, at most 0.75 s of a solve (clay in rain, idle
/// machine, `examples/zmpc_textures.rs`), where solves that ran until the
/// old 1-s time budget made up to 176,000. Nine of the twelve textures'
/// solves make at most 47,000 and never reach it (sandy loam and loam at
/// most 14,000). The time budget behind it (2 s) leaves a machine more
/// than 2.5 times slower than an idle one before the wall clock decides
/// anything.
pub const WORK_BUDGET: usize = 60_000;

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
            objective_tolerance: 1e-5,
            time_budget: Duration::from_secs(2),
            work_budget: Some(WORK_BUDGET),
            starts: 4,
            trust_region_knee: 1.0,
            warm_trust_region_knee: crate::surrogate::scaling::DEFAULT_U0,
        }
    }
}

/// How a solve ended.
#[derive(Debug, Clone, PartialEq)]
pub enum SolveStatus {
    Converged,
    IterationCap,
    /// The model's work budget ([`MpcSettings::work_budget`]) was spent:
    /// the best plan evaluated.
    WorkBudget,
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
    let mut j = 0.0;
    for ((below, above), &uk) in zone_excursions(settings, y).zip(ubar) {
        let d = below + above;
        j += settings.q * d * d + settings.r * uk * uk;
    }
    j
}

/// How far each prediction of `y` lies below and above its step's zone,
/// in effective saturation (each 0 on its own side of the zone).
fn zone_excursions<'a>(
    settings: &'a MpcSettings,
    y: &'a [f64],
) -> impl Iterator<Item = (f64, f64)> + 'a {
    let n = y.len();
    let span = settings.theta_s - settings.theta_r;
    let se = move |theta: f64| (theta - settings.theta_r) / span;
    y.iter().enumerate().map(move |(k, &yk)| {
        let (low, up) = settings.zone.bounds(k + 1, n);
        let s = se(yk);
        ((se(low) - s).max(0.0), (s - se(up)).max(0.0))
    })
}

/// The constant plans, as fractions of u_max, from which [`ZoneMpc::solve`]
/// also starts: spread over the logarithmic scale of the rate, in rising order.
const START_LEVELS: [f64; 7] = [0.0, 0.002, 0.01, 0.05, 0.2, 0.5, 1.0];

/// The constant plans of [`START_LEVELS`] (but `warm`) with their objective
/// `j0` (from `objective_of`, `None` where the model failed), best first:
/// those of the `runs` best that a solve whose best run so far has objective
/// `cutoff` would still run (it stops at the first `j0 ≥ cutoff`), maybe
/// followed by some it would not. A level whose objective's lower bound
/// ranks it behind `runs` plans already evaluated, or reaches `cutoff`, is
/// not evaluated, nor is any above it (their bound is larger).
///
/// The bound is the level's input cost, plus, for a model `monotone` in
/// the supply, the wet-side part of the objective of the highest level
/// evaluated so far: a higher constant plan predicts θ at least as high
/// at every step, so it is at least as far above the zone. After rain the
/// zone's top is exceeded whatever the plan, and the large levels, which
/// pond a fine soil and are the dearest to integrate, are then not
/// predicted.
fn start_candidates(
    s: &MpcSettings,
    warm: &[f64],
    runs: usize,
    cutoff: f64,
    monotone: bool,
    mut objective_of: impl FnMut(&[f64]) -> Option<(f64, f64)>,
) -> Vec<(f64, Vec<f64>)> {
    let mut candidates: Vec<(f64, Vec<f64>)> = Vec::new();
    // the wet-side part of the last evaluated level's objective
    let mut wet_floor = 0.0;
    for level in START_LEVELS {
        let plan = vec![level; warm.len()];
        if plan == warm {
            continue;
        }
        // the objective with every prediction inside the zone, or no
        // nearer its top than a lower level's: a lower bound of the true
        // one, also in floating point (each term adds a non-negative Q·d²),
        // rising with the level
        let floor = input_cost(s, &plan) + wet_floor;
        let ranked_out = runs == 0 || candidates.get(runs - 1).is_some_and(|c| floor > c.0);
        if ranked_out || floor >= cutoff {
            break;
        }
        if let Some((j0, wet)) = objective_of(&plan) {
            if monotone {
                wet_floor = wet;
            }
            // kept in order (ties in level order, as a stable sort leaves them)
            let at = candidates.partition_point(|c| c.0.total_cmp(&j0).is_le());
            candidates.insert(at, (j0, plan));
        }
    }
    candidates.truncate(runs);
    candidates
}

/// How many of the first constant plans of [`START_LEVELS`] a solve
/// predicts on rayon's pool while its warm run goes on: in a steady state
/// the candidates it goes on to predict are the lowest two (0 and 0.2 %),
/// two evaluations beside the warm run's one or two.
const SPECULATIVE_STARTS: usize = 2;

/// A fork's prediction of a constant plan ([`Speculation`]).
struct Forked {
    y: Vec<f64>,
    ok: bool,
    /// The model work it spent.
    work: usize,
    /// Whether the solve's stop (or its end) interrupted it, or it
    /// panicked: then it is not what the model would have predicted.
    interrupted: bool,
}

/// The first constant starts of [`start_candidates`], predicted by a fork
/// of the model ([`PredictionModel::fork`]) in one job on rayon's pool
/// while the warm run goes on. Each plan is predicted once: by the job if
/// it reaches that plan before the solve asks for it (the solve then waits
/// for it), else by the solve itself (the job, when it gets there, finds
/// the plan taken and skips it); a busy pool therefore never delays a
/// solve by more than the prediction under way. The solve uses a fork's
/// prediction only where the model would have made the same one, so a
/// solve's result is the same with or without the pool
/// (`tests/control.rs`). Dropping it tells the job to stop.
struct Speculation {
    shared: Arc<SpeculationState>,
}

struct SpeculationState {
    /// The scaled plans.
    plans: Vec<Vec<f64>>,
    /// Per plan: FREE, RUNNING (its job), DONE or TAKEN (by the solve).
    states: Vec<std::sync::atomic::AtomicU8>,
    results: std::sync::Mutex<Vec<Option<Forked>>>,
    done: std::sync::Condvar,
    cancelled: AtomicBool,
}

const FREE: u8 = 0;
const RUNNING: u8 = 1;
const DONE: u8 = 2;
const TAKEN: u8 = 3;

impl Speculation {
    /// Starts the job, or None when the model has no fork.
    fn start(
        model: &dyn PredictionModel,
        s: &MpcSettings,
        warm: &[f64],
        stop: Interrupt,
    ) -> Option<Speculation> {
        let plans: Vec<Vec<f64>> = START_LEVELS
            .iter()
            .map(|&level| vec![level; warm.len()])
            .filter(|plan| plan != warm)
            .take(SPECULATIVE_STARTS)
            .collect();
        let shared = Arc::new(SpeculationState {
            states: plans
                .iter()
                .map(|_| std::sync::atomic::AtomicU8::new(FREE))
                .collect(),
            results: std::sync::Mutex::new(plans.iter().map(|_| None).collect()),
            done: std::sync::Condvar::new(),
            cancelled: AtomicBool::new(false),
            plans,
        });
        let interrupt = {
            let shared = Arc::clone(&shared);
            Interrupt::new(move || shared.cancelled.load(Ordering::Relaxed) || stop.requested())
        };
        let mut fork = model.fork(interrupt.clone())?;
        let (job, u_max) = (Arc::clone(&shared), s.u_max);
        // one job for the plans, in the order the solve asks for them: one
        // thread beside the solve's, not one per plan
        rayon::spawn(move || {
            let shared = job;
            for (index, state) in shared.states.iter().enumerate() {
                if state
                    .compare_exchange(FREE, RUNNING, Ordering::AcqRel, Ordering::Acquire)
                    .is_err()
                {
                    continue;
                }
                let rates: Vec<f64> = shared.plans[index].iter().map(|v| v * u_max).collect();
                let mut y = vec![0.0; rates.len()];
                let before = fork.work_spent();
                let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    fork.predict(&rates, &mut y).is_ok()
                }));
                let forked = match run {
                    Ok(ok) => Forked {
                        interrupted: !ok && interrupt.requested(),
                        y,
                        ok,
                        work: fork.work_spent() - before,
                    },
                    Err(_) => Forked {
                        y,
                        ok: false,
                        work: 0,
                        interrupted: true,
                    },
                };
                let mut results = shared
                    .results
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                results[index] = Some(forked);
                state.store(DONE, Ordering::Release);
                shared.done.notify_all();
            }
        });
        Some(Speculation { shared })
    }

    /// The fork's prediction of `plan`, if it is one of the speculated
    /// plans and its job started first (waiting for it to finish); None
    /// where the solve must predict it itself.
    fn take(&self, plan: &[f64]) -> Option<Forked> {
        let shared = &self.shared;
        let index = shared.plans.iter().position(|p| p == plan)?;
        if shared.states[index]
            .compare_exchange(FREE, TAKEN, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
        {
            return None;
        }
        let mut results = shared
            .results
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        loop {
            if let Some(forked) = results[index].take() {
                shared.states[index].store(TAKEN, Ordering::Release);
                return Some(forked);
            }
            // its job stores the result and DONE under this lock
            if shared.states[index].load(Ordering::Acquire) != RUNNING {
                return None;
            }
            results = shared
                .done
                .wait(results)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

impl Drop for Speculation {
    fn drop(&mut self) {
        for state in &self.shared.states {
            let _ = state.compare_exchange(FREE, TAKEN, Ordering::AcqRel, Ordering::Acquire);
        }
        self.shared.cancelled.store(true, Ordering::Relaxed);
    }
}

/// The wet-side part of [`objective`]: Q·Σ (θ̂ above the zone's top)², in
/// effective saturation, the terms the objective adds for those steps at
/// least.
fn wet_side(settings: &MpcSettings, y: &[f64]) -> f64 {
    zone_excursions(settings, y)
        .map(|(_, above)| settings.q * above * above)
        .fold(0.0, |j, t| j + t)
}

/// The input part R·Σū² of [`objective`], summed in its order.
fn input_cost(settings: &MpcSettings, ubar: &[f64]) -> f64 {
    ubar.iter()
        .map(|u| settings.r * u * u)
        .fold(0.0, |j, t| j + t)
}

/// The metric of the trust region: t(ū) = ln(1 + ū/κ)/ln(1 + 1/κ) ∈ [0, 1],
/// κ = knee/u_max. Irrigation acts on the soil (and on the surrogates'
/// logarithmic input) over orders of magnitude: a linearisation at 1e-8 m/s
/// is good over a range of that size, one at 1e-6 m/s over a hundred times
/// more. A box of radius Δ in t is still a box in ū, so the QP keeps its form.
#[derive(Debug, Clone, Copy)]
struct TrustMetric {
    knee: f64,
    span: f64,
}

impl TrustMetric {
    fn new(knee: f64) -> TrustMetric {
        let knee = if knee > 0.0 && knee.is_finite() {
            knee
        } else {
            1e-3
        };
        TrustMetric {
            knee,
            span: (1.0 / knee).ln_1p(),
        }
    }

    fn t(&self, ubar: f64) -> f64 {
        (ubar.max(0.0) / self.knee).ln_1p() / self.span
    }

    fn inverse(&self, t: f64) -> f64 {
        self.knee * (t * self.span).exp_m1()
    }

    /// The ū within `radius` of `center` in t, inside [0, 1].
    fn interval(&self, center: f64, radius: f64) -> (f64, f64) {
        let t = self.t(center);
        (
            self.inverse((t - radius).max(0.0)).clamp(0.0, 1.0),
            self.inverse((t + radius).min(1.0)).clamp(0.0, 1.0),
        )
    }

    /// The largest distance in t between two plans.
    fn distance(&self, a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (self.t(*x) - self.t(*y)).abs())
            .fold(0.0, f64::max)
    }
}

/// The zone MPC: settings and the plan of the last solve (the warm start).
#[derive(Debug, Clone)]
pub struct ZoneMpc {
    pub settings: MpcSettings,
    previous: Option<Vec<f64>>,
    qp: QpCache,
    /// Set from outside (a shutdown): the running solve stops as at its
    /// time budget.
    cancel: Option<Arc<AtomicBool>>,
    /// The stop rule of the solve under way (its deadline or the cancel
    /// flag), the same check its model evaluations make.
    stop: Option<Interrupt>,
}

/// The QP solver of the last subproblem: its sparsity pattern is the same
/// for every linearisation of a horizon, so later subproblems only update
/// the data (no new symbolic factorisation).
#[derive(Default)]
struct QpCache {
    solver: Option<Box<DefaultSolver<f64>>>,
    size: usize,
    causal: bool,
}

impl Clone for QpCache {
    /// A clone starts without a solver (it builds its own on first use).
    fn clone(&self) -> Self {
        QpCache::default()
    }
}

impl std::fmt::Debug for QpCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QpCache")
            .field("size", &self.size)
            .field("built", &self.solver.is_some())
            .finish()
    }
}

struct Qp {
    /// ū of the QP's solution.
    ubar: Vec<f64>,
}

impl ZoneMpc {
    pub fn new(settings: MpcSettings) -> ZoneMpc {
        ZoneMpc {
            settings,
            previous: None,
            qp: QpCache::default(),
            cancel: None,
            stop: None,
        }
    }

    /// A flag that, once set, ends the running and every later solve as if
    /// its time budget had run out.
    pub fn set_cancel(&mut self, cancel: Option<Arc<AtomicBool>>) {
        self.cancel = cancel;
    }

    /// Whether the solve under way must stop: its time budget ran out or
    /// the cancel flag is set.
    fn out_of_time(&self) -> bool {
        self.stop.as_ref().is_some_and(Interrupt::requested)
    }

    /// Which of the solve's budgets is spent, if any: its time budget (or
    /// the cancel flag) first, then `model`'s work budget.
    fn spent_budget(&self, model: &dyn PredictionModel) -> Option<SolveStatus> {
        if self.out_of_time() {
            Some(SolveStatus::TimeBudget)
        } else if model.out_of_work() {
            Some(SolveStatus::WorkBudget)
        } else {
            None
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

    /// Takes `plan` (rates [m/s]) as the previous solve's, so the next solve
    /// starts from it shifted by one step (a controller rebuilt from storage).
    pub fn remember(&mut self, plan: Vec<f64>) {
        self.previous = Some(plan);
    }

    /// Forgets the previous plan (the next solve starts from zero irrigation).
    pub fn reset(&mut self) {
        self.previous = None;
    }

    /// Solves the zone MPC for the state `model` holds.
    ///
    /// The problem is not convex (the model is not linear), so the SQP may
    /// end in a local minimum. The first run starts from the previous plan
    /// shifted by one step (zero irrigation on the first solve). A new
    /// measurement can move the optimum into another basin, so every solve
    /// also runs from the most promising constant plans: 0, 0.2 %, 1 %, 5 %,
    /// 20 %, 50 % and 100 % of the largest rate (spread over the logarithmic
    /// scale on which the surrogates see the rate), ranked by their
    /// objective (one prediction each), up to `starts` runs in all while the
    /// time budget lasts; the best plan wins. After a converged warm run,
    /// only constant plans whose objective is already lower are run.
    ///
    /// A constant plan's input cost R·Σū² bounds its objective from below.
    /// The levels are predicted in rising order, and one whose input cost
    /// alone ranks it behind `starts − 1` plans already predicted, or (after
    /// a converged warm run) exceeds that run's objective, is not predicted,
    /// nor is any level above it: it could not be chosen. The plans and the
    /// result are those of predicting all seven; the skipped ones are the
    /// dearest to integrate (at half and full rate a fine soil ponds), so a
    /// solve in a steady state costs one run plus a few predictions of small
    /// rates.
    pub fn solve(&mut self, model: &mut dyn PredictionModel) -> Solution {
        let start = Instant::now();
        // every model evaluation is bound by the budget: one that runs past
        // it is abandoned, and the solve keeps its best iterate
        let deadline = start + self.settings.time_budget;
        let cancel = self.cancel.clone();
        let stop = Interrupt::new(move || {
            Instant::now() > deadline || cancel.as_ref().is_some_and(|c| c.load(Ordering::Relaxed))
        });
        model.set_interrupt(Some(stop.clone()));
        model.set_work_budget(self.settings.work_budget);
        self.stop = Some(stop);
        let solution = self.solve_within(model, start);
        self.stop = None;
        model.set_interrupt(None);
        model.set_work_budget(None);
        solution
    }

    fn solve_within(&mut self, model: &mut dyn PredictionModel, start: Instant) -> Solution {
        let s = self.settings;
        let n = s.horizon;
        let warm = self.warm_start();
        let warm_started = self.previous.is_some();
        // a warm start lies near the optimum: a trust region logarithmic in
        // the rate takes the small rates' curvature in few steps
        let knee = if warm_started {
            s.warm_trust_region_knee
        } else {
            s.trust_region_knee
        };
        // the first constant starts, predicted beside the warm run
        let speculation = self
            .stop
            .clone()
            .and_then(|stop| Speculation::start(model, &s, &warm, stop));
        let mut best = self.solve_from(model, warm.clone(), start, knee);
        if matches!(best.status, SolveStatus::Fallback(_)) {
            return best;
        }
        let warm_converged = warm_started && best.status == SolveStatus::Converged;
        let runs = s.starts.saturating_sub(1);
        let cutoff = if warm_converged {
            best.objective
        } else {
            f64::INFINITY
        };
        let mut y = vec![0.0; n];
        let monotone = model.monotone_in_supply();
        let candidates = start_candidates(&s, &warm, runs, cutoff, monotone, |plan| {
            // a fork's prediction where it made one that this model would
            // have made the same: within what is left of the budget (the
            // evaluation here would have stopped on it) and not interrupted
            let left = s
                .work_budget
                .map_or(usize::MAX, |b| b.saturating_sub(model.work_spent()));
            let forked = speculation
                .as_ref()
                .and_then(|sp| sp.take(plan))
                .filter(|f| !f.interrupted && f.work < left);
            let ok = match forked {
                Some(f) => {
                    model.book_work(f.work);
                    y.copy_from_slice(&f.y);
                    f.ok
                }
                None => {
                    let rates: Vec<f64> = plan.iter().map(|v| v * s.u_max).collect();
                    model.predict(&rates, &mut y).is_ok()
                }
            };
            ok.then(|| (objective(&s, &y, plan), wet_side(&s, &y)))
        });
        drop(speculation);
        for (j0, other) in candidates {
            if self.spent_budget(model).is_some() {
                break;
            }
            // a converged warm run is beaten only from a start that is
            // already better: the others are not worth an SQP run
            if warm_converged && j0 >= best.objective {
                break;
            }
            let sol = self.solve_from(model, other, start, s.trust_region_knee);
            if !matches!(sol.status, SolveStatus::Fallback(_)) && sol.objective < best.objective {
                best = Solution {
                    iterations: best.iterations + sol.iterations,
                    ..sol
                };
            } else {
                best.iterations += sol.iterations;
            }
        }
        // a solve the budget cut short says so, even when its first run had
        // converged: the starts it did not try could have beaten that run
        if !matches!(best.status, SolveStatus::Fallback(_))
            && let Some(spent) = self.spent_budget(model)
        {
            best.status = spent;
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
        knee: f64,
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
            let reason = if self.out_of_time() {
                format!("time budget of {:?} ran out: {e}", s.time_budget)
            } else {
                e.to_string()
            };
            return fallback(self, &ubar, reason, 0);
        }
        let mut j = objective(&s, &y, &ubar);
        let metric = TrustMetric::new(knee / s.u_max);
        let mut radius = 0.5;
        let mut status = SolveStatus::IterationCap;
        let mut iterations = 0;
        let mut trial_y = vec![0.0; n];
        let mut trial_jac = vec![0.0; n * n];
        let mut stalled = 0;
        let mut rejected = false;
        // the last rejected trial's miss, while rejections run (see
        // NONSMOOTH_STEP)
        let mut last_miss: Option<f64> = None;
        while iterations < s.max_iterations {
            if let Some(spent) = self.spent_budget(model) {
                status = spent;
                break;
            }
            iterations += 1;
            let qp = match self.subproblem(&ubar, &y, &jac, &metric, radius, j) {
                Ok(qp) => qp,
                Err(reason) => {
                    if iterations == 1 {
                        return fallback(self, &self.warm_start(), reason, iterations);
                    }
                    status = SolveStatus::Fallback(format!("{reason}; best iterate kept"));
                    break;
                }
            };
            // the decrease the linearisation predicts, evaluated exactly at
            // the QP's plan (the QP's own objective carries its tolerance)
            let predicted = j - self.linearised_objective(&ubar, &y, &jac, &qp.ubar);
            let step = metric.distance(&qp.ubar, &ubar);
            if step < s.step_tolerance || predicted <= s.objective_tolerance * j + 1e-12 {
                status = SolveStatus::Converged;
                break;
            }
            // after an accepted step the trial carries its Jacobian: it is
            // then usually accepted too, and needs it next (the model's
            // prediction is the same with or without). After a rejection
            // (a model far from linear, rejections come in runs) it does
            // not, and an accepted one gets its Jacobian after.
            let with_jacobian = !rejected;
            let evaluated = if with_jacobian {
                model.predict_with_jacobian(&raw(&qp.ubar), &mut trial_y, &mut trial_jac)
            } else {
                model.predict(&raw(&qp.ubar), &mut trial_y)
            };
            let trial = match evaluated {
                Ok(()) => objective(&s, &trial_y, &qp.ubar),
                Err(_) => f64::INFINITY,
            };
            let rho = (j - trial) / predicted;
            rejected = rho <= 0.1;
            if rho > 0.1 {
                // a run that creeps (each accepted step gains less than the
                // objective tolerance) has stalled at its optimum: the trust
                // region is too small to leave it and too large to shrink
                stalled = if j - trial < s.objective_tolerance * j {
                    stalled + 1
                } else {
                    0
                };
                last_miss = None;
                ubar = qp.ubar;
                if with_jacobian {
                    std::mem::swap(&mut y, &mut trial_y);
                    std::mem::swap(&mut jac, &mut trial_jac);
                } else if model
                    .predict_with_jacobian(&raw(&ubar), &mut y, &mut jac)
                    .is_err()
                {
                    // the model just predicted this plan, so only the budget
                    // running out in the evaluation gets here: keep the plan
                    // with that prediction
                    y.copy_from_slice(&trial_y);
                    j = trial;
                    status = self.spent_budget(model).unwrap_or_else(|| {
                        SolveStatus::Fallback("model failed at an accepted plan".into())
                    });
                    break;
                }
                j = trial;
                if stalled >= STALL_STEPS {
                    status = SolveStatus::Converged;
                    break;
                }
                if rho > 0.75 && step > 0.99 * radius {
                    radius = (2.0 * radius).min(1.0);
                }
            } else {
                if trial.is_finite() && (step < NONSMOOTH_STEP || predicted < NONSMOOTH_GAIN * j) {
                    let miss = trial - (j - predicted);
                    if last_miss.is_some_and(|previous| miss >= 0.5 * previous) {
                        status = SolveStatus::Converged;
                        break;
                    }
                    last_miss = Some(miss);
                } else {
                    last_miss = None;
                }
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

    /// J of the model linearised at ū⁰ (predictions `y`, Jacobian `jac`),
    /// evaluated at `ubar`.
    fn linearised_objective(&self, u0: &[f64], y: &[f64], jac: &[f64], ubar: &[f64]) -> f64 {
        let s = &self.settings;
        let n = u0.len();
        let linear: Vec<f64> = (0..n)
            .map(|k| {
                y[k] + (0..n)
                    .map(|j| jac[k * n + j] * s.u_max * (ubar[j] - u0[j]))
                    .sum::<f64>()
            })
            .collect();
        objective(s, &linear, ubar)
    }

    /// The QP of one SQP iteration (module docs) at ū⁰ with predictions `y`
    /// and Jacobian `jac` (raw units), in the trust region `radius`.
    fn subproblem(
        &mut self,
        u0: &[f64],
        y: &[f64],
        jac: &[f64],
        metric: &TrustMetric,
        radius: f64,
        current: f64,
    ) -> Result<Qp, String> {
        let s = &self.settings;
        let n = u0.len();
        let span = s.theta_s - s.theta_r;
        let se = |theta: f64| (theta - s.theta_r) / span;
        // G = Jacobian of Se(ŷ) in ū, its entries within ±G_LIMIT
        let g: Vec<f64> = jac
            .iter()
            .map(|v| (v * s.u_max / span).clamp(-G_LIMIT, G_LIMIT))
            .collect();
        let c: Vec<f64> = (0..n)
            .map(|k| se(y[k]) - (0..n).map(|j| g[k * n + j] * u0[j]).sum::<f64>())
            .collect();
        // ½xᵀPx + qᵀx with x = (ū, y_z):
        // P = 2[Q·GᵀG + R·I, −Q·Gᵀ; −Q·G, Q·I], q = 2[Q·Gᵀc; −Q·c], + Q·‖c‖²
        let m = 2 * n;
        // a large objective is divided by J, so that the solver's absolute
        // tolerances act as relative ones there; small ones are solved to
        // the solver's (tightened) absolute tolerances as they are
        let w = 1.0 / current.max(1.0);
        let (q_w, r_w) = (s.q * w, s.r * w);
        let mut dense = vec![0.0; m * m];
        for a in 0..n {
            for b in a..n {
                let gg: f64 = (0..n).map(|k| g[k * n + a] * g[k * n + b]).sum();
                dense[a * m + b] = 2.0 * q_w * gg + if a == b { 2.0 * r_w } else { 0.0 };
            }
            for k in 0..n {
                // row a (ū_a), column n + k (y_z,k): −2Q·G[k][a]
                dense[a * m + n + k] = -2.0 * q_w * g[k * n + a];
            }
        }
        for k in 0..n {
            dense[(n + k) * m + n + k] = 2.0 * q_w;
        }
        // every entry of the upper triangle is kept (zeros included), so the
        // pattern is the same in every iteration and the solver can be reused
        let mut colptr = vec![0usize];
        let (mut rowval, mut nzval) = (Vec::new(), Vec::new());
        // a causal model (ŷ_k independent of later inputs) leaves the coupling
        // of y_z,k with ū_j, j > k, empty
        let causal = (0..n).all(|k| (k + 1..n).all(|j| g[k * n + j] == 0.0));
        for col in 0..m {
            let rows = if col < n {
                0..col + 1
            } else if causal {
                0..col - n + 1
            } else {
                0..n
            };
            for row in rows {
                rowval.push(row);
                nzval.push(dense[row * m + col]);
            }
            if col >= n {
                rowval.push(col);
                nzval.push(dense[col * m + col]);
            }
            colptr.push(rowval.len());
        }
        let mut q = vec![0.0; m];
        for a in 0..n {
            q[a] = 2.0 * q_w * (0..n).map(|k| g[k * n + a] * c[k]).sum::<f64>();
        }
        for k in 0..n {
            q[n + k] = -2.0 * q_w * c[k];
        }
        // A·x + s = b, s ≥ 0: for every variable, x ≤ upper and −x ≤ −lower
        let mut b = vec![0.0; 2 * m];
        for col in 0..m {
            let (lo, hi) = if col < n {
                metric.interval(u0[col], radius)
            } else {
                let (low, up) = s.zone.bounds(col - n + 1, n);
                (se(low), se(up))
            };
            b[2 * col] = hi;
            b[2 * col + 1] = -lo;
        }
        let reused = match self.qp.solver.as_mut() {
            Some(solver) if self.qp.size == n && self.qp.causal == causal => solver
                .update_P(&nzval)
                .and_then(|()| solver.update_q(&q))
                .and_then(|()| solver.update_b(&b))
                .is_ok(),
            _ => false,
        };
        if !reused {
            let p = CscMatrix::new(m, m, colptr, rowval, nzval);
            let mut colptr = vec![0usize];
            let (mut rowval, mut values) = (Vec::new(), Vec::new());
            for col in 0..m {
                rowval.extend([2 * col, 2 * col + 1]);
                values.extend([1.0, -1.0]);
                colptr.push(rowval.len());
            }
            let a = CscMatrix::new(2 * m, m, colptr, rowval, values);
            let cones = [NonnegativeConeT(2 * m)];
            let settings = DefaultSettingsBuilder::default()
                .verbose(false)
                .max_iter(100)
                .presolve_enable(false)
                .iterative_refinement_enable(false)
                .tol_gap_abs(1e-10)
                .tol_gap_rel(1e-9)
                .build()
                .map_err(|e| format!("QP settings: {e:?}"))?;
            let solver = DefaultSolver::new(&p, &q, &a, &b, &cones, settings)
                .map_err(|e| format!("QP setup: {e:?}"))?;
            self.qp = QpCache {
                solver: Some(Box::new(solver)),
                size: n,
                causal,
            };
        }
        let Some(solver) = self.qp.solver.as_mut() else {
            return Err("QP solver missing".into());
        };
        solver.solve();
        let sol = &solver.solution;
        match sol.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            other => {
                // start afresh next time
                self.qp = QpCache::default();
                return Err(format!("QP not solved: {other:?}"));
            }
        }
        if sol.x.iter().any(|v| !v.is_finite()) {
            self.qp = QpCache::default();
            return Err("QP returned non-finite values".into());
        }
        let ubar: Vec<f64> = sol.x[..n].iter().map(|v| v.clamp(0.0, 1.0)).collect();
        Ok(Qp { ubar })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// What the solve ran before candidates were skipped: every level
    /// evaluated, sorted stably by j0, the best `runs`, up to the first at or
    /// above the cutoff.
    fn exhaustive(
        warm: &[f64],
        runs: usize,
        cutoff: f64,
        objective_of: &mut dyn FnMut(&[f64]) -> Option<f64>,
    ) -> Vec<(f64, Vec<f64>)> {
        let mut all: Vec<(f64, Vec<f64>)> = START_LEVELS
            .iter()
            .map(|&l| vec![l; warm.len()])
            .filter(|p| p != warm)
            .filter_map(|p| objective_of(&p).map(|j| (j, p)))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0));
        all.into_iter()
            .take(runs)
            .take_while(|c| c.0 < cutoff)
            .collect()
    }

    #[test]
    fn skipping_constant_plans_by_their_input_cost_runs_the_same_starts() {
        let s = MpcSettings::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(14);
        let (mut skipped, mut skipped_monotone) = (0, 0);
        let draw = |rng: &mut rand_chacha::ChaCha8Rng| match rng.random_range(0..10) {
            0..=3 => 0.0,
            _ => 10f64.powf(rng.random_range(-4.0..4.0)),
        };
        for case in 0..2000 {
            let n = s.horizon;
            // the zone part of each plan's objective, split into its dry and
            // its wet side: often 0, sometimes large, so that every level can
            // rank anywhere; some fail. The wet side does not fall as the
            // level rises (a model monotone in the supply)
            let mut wet = 0.0;
            let zone_part: Vec<Option<(f64, f64)>> = START_LEVELS
                .iter()
                .map(|_| {
                    wet += if rng.random_range(0..3) == 0 {
                        draw(&mut rng)
                    } else {
                        0.0
                    };
                    let dry = draw(&mut rng);
                    (rng.random_range(0..10) > 0).then_some((dry, wet))
                })
                .collect();
            let objective_of = |plan: &[f64]| {
                let k = START_LEVELS.iter().position(|&l| l == plan[0]).unwrap();
                zone_part[k].map(|(dry, wet)| (dry + wet + input_cost(&s, plan), wet))
            };
            let warm = if case % 3 == 0 {
                vec![START_LEVELS[rng.random_range(0..START_LEVELS.len())]; n]
            } else {
                vec![0.3; n]
            };
            let runs = rng.random_range(0..5);
            let cutoff = match rng.random_range(0..3) {
                0 => f64::INFINITY,
                _ => 10f64.powf(rng.random_range(-4.0..4.0)),
            };
            let want = exhaustive(&warm, runs, cutoff, &mut |p| objective_of(p).map(|j| j.0));
            for monotone in [false, true] {
                let mut evaluated = 0;
                let got = start_candidates(&s, &warm, runs, cutoff, monotone, |p| {
                    evaluated += 1;
                    objective_of(p)
                });
                let run: Vec<_> = got.into_iter().take_while(|c| c.0 < cutoff).collect();
                assert_eq!(
                    run, want,
                    "case {case}: runs {runs}, cutoff {cutoff}, {monotone}"
                );
                if monotone {
                    skipped_monotone += START_LEVELS.len() - evaluated;
                } else {
                    skipped += START_LEVELS.len() - evaluated;
                }
            }
        }
        // the bound does skip work: the highest levels cost R·N·ū² = 500 and
        // 2000, above most cutoffs and most zone parts; a monotone model's
        // wet side skips more
        assert!(skipped > 2000, "only {skipped} evaluations skipped");
        assert!(
            skipped_monotone > skipped + 300,
            "{skipped_monotone} skipped with the wet side, {skipped} without"
        );
    }

    #[test]
    fn the_input_cost_bounds_the_objective_from_below() {
        let s = MpcSettings::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..1000 {
            let ubar: Vec<f64> = (0..s.horizon).map(|_| rng.random::<f64>()).collect();
            let y: Vec<f64> = (0..s.horizon).map(|_| rng.random_range(0.1..0.4)).collect();
            assert!(input_cost(&s, &ubar) <= objective(&s, &y, &ubar));
            // inside the zone the two are the same number
            let inside = vec![0.2; s.horizon];
            assert_eq!(input_cost(&s, &ubar), objective(&s, &inside, &ubar));
        }
    }
}
