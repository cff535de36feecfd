//! The zone MPC of MODEL.md §4: the zone, the prediction-model interface and
//! the SQP solver (QP subproblems with clarabel).

pub mod model;
pub mod mpc;
pub mod zone;

pub use model::{ModelError, PredictionModel, SurrogateModel};
pub use mpc::{MpcSettings, Solution, SolveStatus, ZoneMpc, objective};
pub use zone::ZoneSettings;
