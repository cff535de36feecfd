//! rootzone: closed-loop irrigation by zone model predictive control.
//!
//! `soil` simulates the Richards soil-water equation (the plant), `weather`
//! reads weather scenarios and perturbs forecasts, `surrogate` holds the
//! neural-network models, `control` the zone MPC and the closed loop,
//! `experiment` the paper's experiments, `sim` the simulated plant of the
//! daemon and the field simulator, `service` the daemon. Data flows one
//! way: measurements and forecasts in at the edge, physics and surrogates
//! predict, the controller decides, the edge publishes.

pub mod adapters;
pub mod control;
pub mod estimate;
pub mod experiment;
pub mod fieldsim;
pub mod service;
pub mod sim;
pub mod simulate;
pub mod soil;
pub mod store;
pub mod surrogate;
pub mod weather;
