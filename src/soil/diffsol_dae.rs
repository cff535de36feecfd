//! The column as a semi-explicit DAE for diffsol's BDF (nalgebra backend), kept
//! as the reference the own integrator is measured against (`benches/integrator.rs`
//! and `tests/integrator.rs`).
//!
//! State `[w_0 … w_{n−1} | I, D, U, R | h_0 … h_{n−1}]`: stored water, water
//! amounts, heads. Equations: `dw/dt = F(h)`, amounts' rates from h, and the
//! algebraic retention rows `0 = θ(h) + Ss·h − w`, with mass matrix diag(1, …, 1,
//! 0, …, 0). Like the own integrator it conserves `Σ w·dz − I + D + U` exactly.
//!
//! diffsol's solvers borrow their problem, so one [`DaeIntegrator`] owns the
//! problem and builds a fresh BDF solver for every sampling step.

use diffsol::{
    ConstantOp, LinearOp, Matrix, NalgebraContext, NalgebraLU, NalgebraMat, NalgebraVec,
    NonLinearOp, NonLinearOpJacobian, OdeBuilder, OdeEquations, OdeEquationsRef, OdeSolverMethod,
    OdeSolverProblem, OdeSolverState, OdeSolverStopReason, Op, ParameterisedOp, UnitCallable,
    Vector, VectorCommon,
};

use std::cell::RefCell;

use super::column::{
    AMOUNTS, Column, DRAINAGE, Derivatives, Evaluation, Forcing, INFILTRATION, RUNOFF, UPTAKE,
};
use super::integrator::{
    ColumnState, FailureKind, IntegrationError, IntegratorStatistics, Tolerances,
};

/// BDF steps one call may take before it gives up (it stalls on a column
/// wetting up to saturation; see the module docs).
const MAX_STEPS: usize = 100_000;

type Mat = NalgebraMat<f64>;
type Vec64 = NalgebraVec<f64>;

/// Absolute tolerance on the heads [m].
const HEAD_TOLERANCE: f64 = 1e-6;

/// The right-hand side operator seen by diffsol.
pub struct ColumnRhs {
    column: Column,
    forcing: Forcing,
    eval: RefCell<Evaluation>,
    ctx: NalgebraContext,
}

impl ColumnRhs {
    fn residual(&self, x: &[f64], out: &mut [f64]) {
        let c = &self.column;
        let (n, o) = (c.cells(), c.cells() + AMOUNTS);
        let ss = c.soil().specific_storage;
        let mut e = self.eval.borrow_mut();
        c.evaluate(&x[o..], &self.forcing, &mut e, Derivatives::Omitted);
        out[..n].copy_from_slice(&e.storage);
        out[n..o].copy_from_slice(&e.amounts);
        for i in 0..n {
            out[o + i] = e.states[i].water_content + ss * x[o + i] - x[i];
        }
    }

    fn jacobian(&self, x: &[f64], jac: &mut nalgebra::DMatrix<f64>) {
        let c = &self.column;
        let (n, o) = (c.cells(), c.cells() + AMOUNTS);
        let ss = c.soil().specific_storage;
        let mut e = self.eval.borrow_mut();
        c.evaluate(&x[o..], &self.forcing, &mut e, Derivatives::Included);
        jac.fill(0.0);
        for i in 0..n {
            if i > 0 {
                jac[(i, o + i - 1)] = e.lower[i];
            }
            jac[(i, o + i)] = e.diagonal[i];
            if i + 1 < n {
                jac[(i, o + i + 1)] = e.upper[i];
            }
            jac[(n + UPTAKE, o + i)] = e.uptake_gradient[i];
            jac[(o + i, o + i)] = e.states[i].capacity + ss;
            jac[(o + i, i)] = -1.0;
        }
        jac[(n + INFILTRATION, o)] = e.top_gradient;
        jac[(n + RUNOFF, o)] = -e.top_gradient;
        jac[(n + DRAINAGE, o + n - 1)] = e.bottom_gradient;
    }
}

/// The initial state operator: the state at the start of the current step.
pub struct StartState {
    state: Vec64,
    ctx: NalgebraContext,
}

/// The mass matrix: identity on the storages and amounts, zero on the heads.
pub struct ColumnMass {
    /// Index of the first head.
    heads: usize,
    len: usize,
    ctx: NalgebraContext,
}

/// The column's equations in diffsol's terms.
pub struct ColumnEquations {
    rhs: ColumnRhs,
    mass: ColumnMass,
    init: StartState,
    ctx: NalgebraContext,
}

macro_rules! column_op {
    ($ty:ty, $len:expr) => {
        impl Op for $ty {
            type T = f64;
            type V = Vec64;
            type M = Mat;
            type C = NalgebraContext;
            fn context(&self) -> &Self::C {
                &self.ctx
            }
            fn nstates(&self) -> usize {
                $len(self)
            }
            fn nout(&self) -> usize {
                $len(self)
            }
            fn nparams(&self) -> usize {
                0
            }
        }
    };
}
column_op!(ColumnRhs, |s: &ColumnRhs| dae_len(&s.column));
column_op!(StartState, |s: &StartState| s.state.len());
column_op!(ColumnMass, |s: &ColumnMass| s.len);
column_op!(ColumnEquations, |s: &ColumnEquations| dae_len(
    &s.rhs.column
));

/// The DAE state of a column state: storages, amounts, heads.
fn dae_state(column: &Column, state: &ColumnState) -> Vec<f64> {
    let soil = column.soil();
    let mut y: Vec<f64> = state.heads.iter().map(|&h| soil.storage(h)).collect();
    y.extend(state.amounts);
    y.extend_from_slice(&state.heads);
    y
}

/// Length of the DAE state: storages, amounts, heads.
fn dae_len(column: &Column) -> usize {
    2 * column.cells() + AMOUNTS
}

impl NonLinearOp for ColumnRhs {
    fn call_inplace(&self, x: &Vec64, _t: f64, y: &mut Vec64) {
        self.residual(x.inner().as_slice(), y.inner_mut().as_mut_slice());
    }
}

impl NonLinearOpJacobian for ColumnRhs {
    fn jac_mul_inplace(&self, x: &Vec64, _t: f64, v: &Vec64, y: &mut Vec64) {
        let n = dae_len(&self.column);
        let mut jac = nalgebra::DMatrix::zeros(n, n);
        self.jacobian(x.inner().as_slice(), &mut jac);
        let out = &jac * v.inner();
        y.inner_mut().copy_from(&out);
    }

    fn jacobian_inplace(&self, x: &Vec64, _t: f64, y: &mut Mat) {
        self.jacobian(x.inner().as_slice(), y.inner_mut());
    }
}

impl LinearOp for ColumnMass {
    /// y = M·x + β·y
    fn gemv_inplace(&self, x: &Vec64, _t: f64, beta: f64, y: &mut Vec64) {
        let (x, y) = (x.inner().as_slice(), y.inner_mut().as_mut_slice());
        for (i, (yi, xi)) in y.iter_mut().zip(x).enumerate() {
            *yi = if i < self.heads {
                xi + beta * *yi
            } else {
                beta * *yi
            };
        }
    }

    fn matrix_inplace(&self, _t: f64, y: &mut Mat) {
        let m = y.inner_mut();
        m.fill(0.0);
        for i in 0..self.heads {
            m[(i, i)] = 1.0;
        }
    }
}

impl ConstantOp for StartState {
    fn call_inplace(&self, _t: f64, y: &mut Vec64) {
        y.copy_from(&self.state);
    }
}

impl<'a> OdeEquationsRef<'a> for ColumnEquations {
    type Rhs = &'a ColumnRhs;
    type Mass = &'a ColumnMass;
    type Root = ParameterisedOp<'a, UnitCallable<Mat>>;
    type Init = &'a StartState;
    type Out = ParameterisedOp<'a, UnitCallable<Mat>>;
    type Reset = ParameterisedOp<'a, UnitCallable<Mat>>;
}

impl OdeEquations for ColumnEquations {
    fn rhs(&self) -> &ColumnRhs {
        &self.rhs
    }
    fn mass(&self) -> Option<&ColumnMass> {
        Some(&self.mass)
    }
    fn init(&self) -> &StartState {
        &self.init
    }
    fn set_params(&mut self, _p: &Vec64) {}
    fn get_params(&self, _p: &mut Vec64) {}
}

/// Advances a column's ODE state over sampling steps with BDF.
pub struct DaeIntegrator {
    problem: OdeSolverProblem<ColumnEquations>,
    statistics: IntegratorStatistics,
    /// Size of the last full BDF step, the first step size of the next call.
    last_step_size: Option<f64>,
}

impl DaeIntegrator {
    pub fn new(column: Column, tolerances: Tolerances) -> Result<Self, String> {
        tolerances.validate()?;
        let ctx = NalgebraContext::default();
        let n = dae_len(&column);
        let eqn = ColumnEquations {
            rhs: ColumnRhs {
                column,
                forcing: Forcing::default(),
                eval: RefCell::new(Evaluation::new(column.cells())),
                ctx,
            },
            mass: ColumnMass {
                heads: column.cells() + AMOUNTS,
                len: n,
                ctx,
            },
            init: StartState {
                state: Vec64::zeros(n, ctx),
                ctx,
            },
            ctx,
        };
        let problem = OdeBuilder::<Mat>::new()
            .rtol(tolerances.relative)
            .atol(
                (0..n)
                    .map(|i| {
                        if i < column.cells() + AMOUNTS {
                            tolerances.absolute
                        } else {
                            HEAD_TOLERANCE
                        }
                    })
                    .collect::<Vec<_>>(),
            )
            .build_from_eqn(eqn)
            .map_err(|e| e.to_string())?;
        Ok(DaeIntegrator {
            problem,
            statistics: IntegratorStatistics::default(),
            last_step_size: None,
        })
    }

    pub fn column(&self) -> &Column {
        &self.problem.eqn.rhs.column
    }

    pub fn statistics(&self) -> IntegratorStatistics {
        self.statistics
    }

    /// Advances `state` from `time` over `duration` seconds under constant `forcing`.
    ///
    /// Every call starts BDF afresh at order 1 (the forcing, and with process
    /// noise the state, change discontinuously between calls), with the step
    /// size the previous call ended with: far better than the generic first-step
    /// heuristic, which starts seconds long and needs a dozen steps to grow.
    pub fn advance(
        &mut self,
        state: &mut ColumnState,
        time: f64,
        duration: f64,
        forcing: Forcing,
    ) -> Result<(), IntegrationError> {
        let fail = |e: diffsol::DiffsolError| IntegrationError::invalid(time, e.to_string());
        if !(duration > 0.0 && duration.is_finite()) {
            return Err(IntegrationError::invalid(
                time,
                format!("duration must be > 0 s, got {duration}"),
            ));
        }
        self.problem.eqn.rhs.forcing = forcing;
        let start_state = dae_state(self.column(), state);
        self.problem
            .eqn
            .init
            .state
            .inner_mut()
            .as_mut_slice()
            .copy_from_slice(&start_state);
        self.problem.t0 = time;
        let mut start = self.problem.bdf_state::<NalgebraLU<f64>>().map_err(fail)?;
        if let Some(h) = self.last_step_size {
            *start.as_mut().h = h.min(duration);
        }
        let mut solver = self
            .problem
            .bdf_solver::<NalgebraLU<f64>>(start)
            .map_err(fail)?;
        solver.set_stop_time(time + duration).map_err(fail)?;
        let mut last_h = None;
        for taken in 0.. {
            if taken == MAX_STEPS {
                return Err(IntegrationError {
                    time: solver.state().t,
                    kind: FailureKind::WorkLimit(format!("{MAX_STEPS} BDF steps in one call")),
                    step: None,
                    smallest_step: Some(solver.state().h),
                    cell: None,
                });
            }
            let reason = solver.step().map_err(fail)?;
            if let OdeSolverStopReason::TstopReached = reason {
                break;
            }
            // The step that lands on the stop time is cut short; remember a full one.
            last_h = Some(solver.state().h);
        }
        let y = solver.state().y.inner().as_slice();
        if y.iter().any(|v| !v.is_finite()) {
            return Err(IntegrationError::invalid(
                time + duration,
                "non-finite state",
            ));
        }
        let o = self.column().cells() + AMOUNTS;
        state.heads.copy_from_slice(&y[o..]);
        state.amounts.copy_from_slice(&y[o - AMOUNTS..o]);
        if let Some(h) = last_h.filter(|h| *h > 0.0) {
            self.last_step_size = Some(h);
        }
        let stats = solver.get_statistics();
        self.statistics.steps += stats.number_of_steps;
        self.statistics.error_test_failures += stats.number_of_error_test_failures;
        self.statistics.newton_iterations += stats.number_of_nonlinear_solver_iterations;
        self.statistics.newton_failures += stats.number_of_nonlinear_solver_fails;
        self.statistics.sampling_steps += 1;
        Ok(())
    }
}
