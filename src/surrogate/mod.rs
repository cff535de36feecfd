//! Neural-network surrogates of the soil column (MODEL.md §3).
//!
//! Layout, bottom up:
//!
//! * [`scaling`]: ū = ln(1 + u/u₀)/ln(1 + u_max/u₀), ȳ = min-max of y,
//!   ē = ET0/ET0_ref;
//! * `dense`, `lstm` (private): kernels on flat parameter slices, forward and
//!   backward (parameter and input gradients), allocation-free;
//! * [`network`]: [`SequenceNet`] (1–2 LSTM layers + dense head over a
//!   20-step window of (ū, ȳ, ē)), [`Mlp`] (the combiner M_A), [`TwoLayerNet`]
//!   and [`Surrogate`] (either prediction model);
//! * [`train`]: Adam with parallel, deterministic mini-batch gradients and
//!   early stopping;
//! * [`rollout`]: [`Predictor`], N-step recursive prediction and its exact
//!   Jacobian with respect to the future irrigation rates;
//! * [`correction`]: bias and bounded linear plant-model mismatch correction;
//! * [`file`]: the versioned JSON model file;
//! * [`finetune`]: a warm start, the shipped two-layer network refined for
//!   another soil (the daemon's per-field jobs);
//! * [`dataset`], [`evaluate`]: training data from the simulator and
//!   open-loop scoring.
//!
//! Time convention everywhere: u[k] is the rate applied over step k (the
//! supply, irrigation + rain), ET0[k] the reference evapotranspiration over
//! it, y[k] the water content at its end; y[k] is predicted from
//! ū[k − 19..=k], ē[k − 19..=k], ȳ[k − 20..k].

pub mod correction;
pub mod dataset;
pub(crate) mod dense;
pub mod evaluate;
pub mod file;
pub mod finetune;
pub(crate) mod lstm;
pub mod network;
pub mod pipeline;
pub mod rollout;
pub mod scaling;
pub mod train;

pub use file::{Metadata, ModelFile, ModelFileError};
pub use network::{Mlp, SequenceNet, Surrogate, TwoLayerNet};
pub use rollout::{HORIZON, Past, Predictor};
pub use scaling::Scaling;
