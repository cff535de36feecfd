//! rootzone: closed-loop irrigation by zone model predictive control.
//!
//! `soil` simulates the Richards soil-water equation (the plant), `weather`
//! reads weather scenarios and perturbs forecasts, `simulate` runs the
//! simulator over files for the CLI. Data flows one way: files and
//! measurements in at the edge, physics in the middle, reports out.

pub mod control;
pub mod experiment;
pub mod simulate;
pub mod soil;
pub mod surrogate;
pub mod weather;
