//! Prediction models behind one interface.

use crate::soil::{
    Column, ColumnState, Crop, Field, Forcing, Integrator, Interrupt, Tolerances, VanGenuchten,
    WorkLimits,
};
use crate::surrogate::evaluate::WINDOW;
use crate::surrogate::{Past, Predictor};
use crate::weather::WeatherStep;

/// A prediction failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("prediction model: {0}")]
pub struct ModelError(pub String);

/// The N-step prediction of the output θ for a plan of irrigation rates
/// (m/s), given the state the model holds (its past window, bias, forecast),
/// and its Jacobian `jac[k·N + j] = dŷ_k/du_j`.
pub trait PredictionModel: Send {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError>;
    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError>;

    /// A check an evaluation makes while it runs: once it returns true the
    /// evaluation is abandoned with an error (the zone MPC's time budget, a
    /// shutdown). Models whose evaluation is short and bounded ignore it.
    fn set_interrupt(&mut self, _interrupt: Option<Interrupt>) {}

    /// Starts a budget of work, counted in the model's own unit, for the
    /// evaluations that follow (the zone MPC's solve), with nothing spent;
    /// None removes the bound (what was spent stays readable). An
    /// evaluation that would exceed what is left is abandoned with an
    /// error. Models whose every evaluation costs the same bounded work
    /// (the surrogates) have none.
    fn set_work_budget(&mut self, _budget: Option<usize>) {}

    /// The work spent since a budget was last started (0 for models
    /// without one).
    fn work_spent(&self) -> usize {
        0
    }

    /// Whether a budget is set and spent: the next evaluation would fail.
    fn out_of_work(&self) -> bool {
        false
    }

    /// An independent copy of the model, for evaluations on another
    /// thread beside this one's (the zone MPC predicts its first constant
    /// starts while its warm run goes on): the same state and forecast, no
    /// work budget, `interrupt` as its interrupt. None where that does not
    /// pay (the surrogates' evaluations take microseconds).
    fn fork(&self, _interrupt: Interrupt) -> Option<Box<dyn PredictionModel>> {
        None
    }

    /// Books against the budget the `work` of one evaluation that a fork
    /// made and the caller adopts as this model's own: the budget is then
    /// where the evaluation made here would have left it.
    fn book_work(&mut self, _work: usize) {}

    /// Whether more irrigation never lowers a predicted θ: for plans
    /// u ≤ v (every move), ŷ(u) ≤ ŷ(v) at every step. True of the
    /// Richards model (water only adds: the comparison principle of
    /// Richards' equation); the networks promise nothing.
    fn monotone_in_supply(&self) -> bool {
        false
    }
}

/// A surrogate ([`Predictor`]) with its window of applied inputs and measured
/// outputs and an additive bias correction.
///
/// The surrogates' inputs are the water supplied at the surface and the
/// reference evapotranspiration: the precipitation rate is added to the
/// irrigation, in the window (observed rain) and over the horizon (`rain`,
/// the forecast), and ET0 goes beside it, observed in the window (`past_e`)
/// and forecast over the horizon (`et0`).
#[derive(Debug, Clone)]
pub struct SurrogateModel {
    pub predictor: Predictor,
    /// Supply u + P over the last 20 steps (m/s), oldest first.
    pub past_u: Vec<f64>,
    /// Measured y[t − 20..t].
    pub past_y: Vec<f64>,
    /// ET0 over the last 20 steps (m/s), oldest first.
    pub past_e: Vec<f64>,
    pub bias: f64,
    /// Forecast precipitation rate of each horizon step [m/s] (missing
    /// entries count as no rain).
    pub rain: Vec<f64>,
    /// Forecast ET0 rate of each horizon step [m/s] (missing entries repeat
    /// the last one given, or the window's last when none is).
    pub et0: Vec<f64>,
    /// The plan plus the rain, reused between calls.
    supply: Vec<f64>,
    /// The horizon's ET0, reused between calls.
    horizon_e: Vec<f64>,
}

impl SurrogateModel {
    /// A model whose window is padded with (u = 0, y = `first`), as before
    /// 20 samples exist (MODEL.md §4), and ET0 = 0: no supply and no uptake,
    /// the one weather under which a flat θ is steady.
    pub fn padded(predictor: Predictor, first: f64) -> SurrogateModel {
        SurrogateModel::new(
            predictor,
            vec![0.0; WINDOW],
            vec![first; WINDOW],
            vec![0.0; WINDOW],
        )
    }

    /// A model with the given window (supply rates, measured outputs, ET0
    /// rates), no bias and no forecast.
    pub fn new(
        predictor: Predictor,
        past_u: Vec<f64>,
        past_y: Vec<f64>,
        past_e: Vec<f64>,
    ) -> SurrogateModel {
        SurrogateModel {
            predictor,
            past_u,
            past_y,
            past_e,
            bias: 0.0,
            rain: Vec::new(),
            et0: Vec::new(),
            supply: Vec::new(),
            horizon_e: Vec::new(),
        }
    }

    /// The supply of a plan (irrigation plus forecast rain) and the
    /// horizon's ET0, into the reused buffers.
    fn inputs(&mut self, plan: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let mut supply = std::mem::take(&mut self.supply);
        supply.clear();
        supply.extend(
            plan.iter()
                .enumerate()
                .map(|(k, u)| u + self.rain.get(k).copied().unwrap_or(0.0)),
        );
        let mut e = std::mem::take(&mut self.horizon_e);
        e.clear();
        let last = self
            .et0
            .last()
            .or(self.past_e.last())
            .copied()
            .unwrap_or(0.0);
        e.extend((0..plan.len()).map(|k| self.et0.get(k).copied().unwrap_or(last)));
        (supply, e)
    }

    /// The prediction without the bias of the supply `u` (rain included)
    /// over the next step, under the ET0 rate `et0` of that step.
    pub fn one_step(&mut self, u: f64, et0: f64) -> Result<f64, ModelError> {
        let mut out = [0.0];
        let past = Past {
            u: &self.past_u,
            y: &self.past_y,
            et0: &self.past_e,
        };
        self.predictor
            .predict(past, &[u], &[et0], 0.0, &mut out)
            .map_err(|e| ModelError(e.to_string()))?;
        finite(&out)?;
        Ok(out[0])
    }

    /// Shifts the window by one sample: supply `u` and ET0 `e` over the
    /// last step, `y` measured at its end.
    pub fn push(&mut self, u: f64, y: f64, e: f64) {
        self.past_u.remove(0);
        self.past_u.push(u);
        self.past_y.remove(0);
        self.past_y.push(y);
        self.past_e.remove(0);
        self.past_e.push(e);
    }
}

fn finite(out: &[f64]) -> Result<(), ModelError> {
    match out.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(k) => Err(ModelError(format!("non-finite prediction at step {k}"))),
    }
}

/// A linear prediction model, `ŷ_k = a_k + b·Σ_{j ≤ k} ρ^(k−j)·u_j`
/// (k = 0-based horizon step, u in m/s), with its exact Jacobian: the zone
/// MPC's problem on it is convex, which makes it the independent yardstick
/// of the solver's and the control step's tests. `a` holds the free
/// response (no irrigation) over the horizon.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearModel {
    pub a: Vec<f64>,
    pub b: f64,
    pub rho: f64,
}

impl PredictionModel for LinearModel {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        for (k, o) in out.iter_mut().enumerate() {
            *o = self.a[k]
                + (0..=k)
                    .map(|j| self.b * self.rho.powi((k - j) as i32) * plan[j])
                    .sum::<f64>();
        }
        Ok(())
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        let n = out.len();
        self.predict(plan, out)?;
        for k in 0..n {
            for j in 0..n {
                jac[k * n + j] = if j <= k {
                    self.b * self.rho.powi((k - j) as i32)
                } else {
                    0.0
                };
            }
        }
        Ok(())
    }
}

impl PredictionModel for SurrogateModel {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        let (supply, e) = self.inputs(plan);
        let past = Past {
            u: &self.past_u,
            y: &self.past_y,
            et0: &self.past_e,
        };
        let result = self
            .predictor
            .predict(past, &supply, &e, self.bias, out)
            .map_err(|e| ModelError(e.to_string()));
        self.supply = supply;
        self.horizon_e = e;
        result?;
        finite(out)
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        // d(supply)/du = 1: the Jacobian in the supply is the one in u
        let (supply, e) = self.inputs(plan);
        let past = Past {
            u: &self.past_u,
            y: &self.past_y,
            et0: &self.past_e,
        };
        let result = self
            .predictor
            .predict_with_jacobian(past, &supply, &e, self.bias, out, jac)
            .map_err(|e| ModelError(e.to_string()));
        self.supply = supply;
        self.horizon_e = e;
        result?;
        finite(out)?;
        finite(jac)
    }
}

/// The work limits of a [`RichardsModel`]'s integrations per sampling step
/// (the simulator's defaults before every case of `tests/textures.rs`
/// finished; a prediction's cost at them is 0.2–0.6 s).
pub const MODEL_LIMITS: WorkLimits = WorkLimits {
    step_attempts: 2_000,
    newton_iterations: 40_000,
};

/// The Richards model of MODEL.md §1 as a prediction model: the column's
/// integrator from the full state (heads) under the weather forecast. Its
/// Jacobian comes from tangents carried through the integrator's implicit
/// stages ([`Integrator::advance_with_tangents`]), not finite differences.
///
/// Its integrations give up on a sampling step after [`MODEL_LIMITS`], well
/// below the simulator's defaults: a plan that needs more (a fine soil
/// wetted to just below saturation, `soil::WorkLimits`) fails as a trial in
/// about 0.4 s instead of spending the solve's whole time budget.
#[derive(Debug, Clone)]
pub struct RichardsModel {
    integrator: Integrator,
    state: ColumnState,
    /// ET0 and P of every horizon step (irrigation 0) [m/s].
    forecast: Vec<Forcing>,
    sampling_time: f64,
    /// The solve's budget of Newton iterations over all its evaluations
    /// ([`PredictionModel::set_work_budget`]), and what they have spent.
    work_budget: Option<usize>,
    work_spent: usize,
}

impl RichardsModel {
    /// The model at `field`'s current (true) state, with `forecast` (one step
    /// per horizon step; the last repeats if it is short). Reading the
    /// plant's truth is what the **oracle** does (experiments only).
    pub fn new(field: &Field, forecast: &[WeatherStep]) -> RichardsModel {
        let sampling_time = field.settings().sampling_time;
        RichardsModel {
            integrator: {
                let mut integrator = field.integrator().clone();
                integrator.set_limits(MODEL_LIMITS);
                integrator
            },
            state: field.state().clone(),
            forecast: forecast
                .iter()
                .map(|w| w.forcing(0.0, sampling_time))
                .collect(),
            sampling_time,
            work_budget: None,
            work_spent: 0,
        }
    }

    /// The model of a column of `soil` and `crop`, `depth` m deep with one
    /// cell per head, from `heads` (e.g. an estimator's mean state): what a
    /// controller that does not see the plant's truth predicts with.
    pub fn from_state(
        soil: VanGenuchten,
        crop: Crop,
        depth: f64,
        heads: Vec<f64>,
        forecast: &[WeatherStep],
        sampling_time: f64,
    ) -> Result<RichardsModel, ModelError> {
        let column = Column::new(soil, crop, depth, heads.len()).map_err(ModelError)?;
        let mut integrator = Integrator::new(column, Tolerances::default()).map_err(ModelError)?;
        integrator.set_limits(MODEL_LIMITS);
        if heads.iter().any(|h| !h.is_finite()) {
            return Err(ModelError("the Richards model needs finite heads".into()));
        }
        Ok(RichardsModel {
            integrator,
            state: ColumnState {
                heads,
                amounts: [0.0; crate::soil::column::AMOUNTS],
            },
            forecast: forecast
                .iter()
                .map(|w| w.forcing(0.0, sampling_time))
                .collect(),
            sampling_time,
            work_budget: None,
            work_spent: 0,
        })
    }

    fn forcing(&self, k: usize, irrigation: f64) -> Result<Forcing, ModelError> {
        let base = self
            .forecast
            .get(k)
            .or(self.forecast.last())
            .ok_or_else(|| ModelError("the Richards model has no forecast".into()))?;
        Ok(Forcing {
            irrigation,
            ..*base
        })
    }

    /// A copy for another thread ([`PredictionModel::fork`]): the same
    /// state, forecast and integrator, no work budget, nothing spent, and
    /// `interrupt` as its interrupt. An evaluation's result depends only
    /// on the plan and these (each one starts from a clone of the
    /// integrator), so the copy predicts what this model would.
    pub fn forked(&self, interrupt: Interrupt) -> RichardsModel {
        let mut copy = self.clone();
        copy.work_budget = None;
        copy.work_spent = 0;
        copy.integrator.set_interrupt(Some(interrupt));
        copy
    }

    /// One evaluation, its Newton iterations booked against the budget.
    fn run(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: Option<&mut [f64]>,
    ) -> Result<(), ModelError> {
        let mut integrator = self.integrator.clone();
        let before = integrator.statistics().newton_iterations;
        if let Some(budget) = self.work_budget {
            let left = budget.saturating_sub(self.work_spent);
            if left == 0 {
                return Err(ModelError(format!(
                    "Richards model: the solve's work budget of {budget} Newton iterations is spent"
                )));
            }
            integrator.set_newton_cap(Some(before + left));
        }
        let result = self.run_on(&mut integrator, plan, out, jac);
        self.work_spent += integrator.statistics().newton_iterations - before;
        result
    }

    fn run_on(
        &self,
        integrator: &mut Integrator,
        plan: &[f64],
        out: &mut [f64],
        mut jac: Option<&mut [f64]>,
    ) -> Result<(), ModelError> {
        let n = plan.len();
        let mut state = self.state.clone();
        let soil = *integrator.column().soil();
        let sensor = integrator.column().sensor_cell();
        let cells = integrator.column().cells();
        let mut tangents = vec![vec![0.0; cells]; if jac.is_some() { n } else { 0 }];
        for (k, &u) in plan.iter().enumerate() {
            let forcing = self.forcing(k, u.max(0.0))?;
            let t = k as f64 * self.sampling_time;
            let result = if jac.is_some() {
                integrator.advance_with_tangents(
                    &mut state,
                    t,
                    self.sampling_time,
                    forcing,
                    &mut tangents[..=k],
                    Some(k),
                )
            } else {
                integrator.advance(&mut state, t, self.sampling_time, forcing)
            };
            result.map_err(|e| ModelError(format!("Richards model: {e}")))?;
            let h = state.heads[sensor];
            let hydraulic = soil.state(h);
            out[k] = hydraulic.water_content;
            if let Some(jac) = jac.as_deref_mut() {
                for j in 0..n {
                    jac[k * n + j] = if j <= k {
                        hydraulic.capacity * tangents[j][sensor]
                    } else {
                        0.0
                    };
                }
            }
        }
        finite(out)?;
        if let Some(jac) = jac {
            finite(jac)?;
        }
        Ok(())
    }
}

impl PredictionModel for RichardsModel {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        self.run(plan, out, None)
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        self.run(plan, out, Some(jac))
    }

    fn set_interrupt(&mut self, interrupt: Option<Interrupt>) {
        self.integrator.set_interrupt(interrupt);
    }

    fn monotone_in_supply(&self) -> bool {
        true
    }

    /// Counted in Newton iterations (each one tridiagonal solve), the
    /// integrator's unit of work.
    fn set_work_budget(&mut self, budget: Option<usize>) {
        self.work_budget = budget;
        if budget.is_some() {
            self.work_spent = 0;
        }
    }

    fn fork(&self, interrupt: Interrupt) -> Option<Box<dyn PredictionModel>> {
        Some(Box::new(self.forked(interrupt)))
    }

    fn book_work(&mut self, work: usize) {
        self.work_spent += work;
    }

    fn work_spent(&self) -> usize {
        self.work_spent
    }

    fn out_of_work(&self) -> bool {
        self.work_budget.is_some_and(|b| self.work_spent >= b)
    }
}
