//! The zone MPC of MODEL.md §4: the zone, the prediction models, the SQP
//! solver (QP subproblems with clarabel), the running controller and the
//! closed loop with a simulated field.

pub mod closed_loop;
pub mod controller;
pub mod estimated;
pub mod model;
pub mod mpc;
pub mod policy;
pub mod zone;

pub use closed_loop::{
    ClosedLoopRun, ClosedLoopSettings, EstimateRecord, LoopController, ObservedRun, StepRecord,
    run_closed_loop, run_observed_loop,
};
pub use controller::{Controller, Decision, reading_filter, relative_noise_sd};
pub use estimated::{EstimateView, EstimatedRichards, step_on_estimate};
pub use model::{LinearModel, ModelError, PredictionModel, RichardsModel, SurrogateModel};
pub use mpc::{MpcSettings, Solution, SolveStatus, ZoneMpc, objective};
pub use zone::ZoneSettings;
