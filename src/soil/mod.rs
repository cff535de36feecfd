//! The physics, pure: soil hydraulics, root water uptake, the Richards column
//! and its integrators, and the field that advances one sampling step at a time.
//! No I/O, no clock, no async.

pub mod column;
pub mod diffsol_dae;
pub mod field;
pub mod hydraulics;
pub mod integrator;
pub mod uptake;

pub use column::{Column, Derivatives, Evaluation, Forcing};
pub use field::{Field, FieldSettings, StepReport, WaterBalance};
pub use hydraulics::{HydraulicState, Texture, VanGenuchten};
pub use integrator::{
    ColumnState, FailureKind, IntegrationError, Integrator, IntegratorStatistics, Interrupt,
    Tolerances, WorkLimits,
};
pub use uptake::{Crop, Feddes};
