//! Training: Adam on the mean squared error, shuffled mini-batches whose
//! gradient is computed in parallel shards, early stopping on a held-out set.
//!
//! # Data
//!
//! * [`SequenceData`] (for [`SequenceNet`]): scaled series with the convention
//!   of [`super::dataset::Series`] and [`super::rollout`]: u[k] is the input
//!   applied over step k, y[k] the output at its end. Sample k (k ≥ 20) is the
//!   window (ū[k − 19..=k], ȳ[k − 20..k]) with target ȳ[k].
//! * [`TabularData`] (for [`Mlp`]): rows of three inputs and a target.
//!
//! Samples are named by index; the training and validation sets are index
//! lists into (possibly different) data.
//!
//! # Determinism
//!
//! Each mini-batch is split into a fixed number of contiguous shards
//! ([`TrainConfig::shards`], independent of the thread count); each shard
//! accumulates its gradient in its own buffer and the buffers are summed in
//! shard order, so the result is bitwise the same for any rayon pool size.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::evaluate::WINDOW;
use super::network::{
    COMBINER_INPUTS, Mlp, MlpWorkspace, SequenceNet, SequenceWorkspace, fill_window,
};
use super::scaling::Scaling;

/// Scaled time series for sequence models (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SequenceData {
    /// Scaled inputs ū[k] (applied over step k).
    pub u: Vec<f64>,
    /// Scaled outputs ȳ[k] (at the end of step k).
    pub y: Vec<f64>,
}

impl SequenceData {
    /// Appends a raw series (u [m/s], y [m³/m³], equal lengths) after scaling
    /// it, and returns the indices of its samples: windows never cross from
    /// one appended series into the next.
    ///
    /// # Panics
    /// If `u` and `y` differ in length.
    pub fn push_series(&mut self, u: &[f64], y: &[f64], scaling: &Scaling) -> Vec<usize> {
        assert_eq!(u.len(), y.len(), "series lengths differ");
        let start = self.u.len();
        self.u.extend(u.iter().map(|&v| scaling.input.scale(v)));
        self.y.extend(y.iter().map(|&v| scaling.output.scale(v)));
        sample_indices(u.len())
            .into_iter()
            .map(|k| k + start)
            .collect()
    }

    /// Writes the window of sample k into `x` ((ū, ȳ) interleaved).
    fn window(&self, k: usize, x: &mut [f64]) {
        fill_window(x, &self.u[k + 1 - WINDOW..=k], &self.y[k - WINDOW..k]);
    }
}

/// The samples k = 20..len of one series of length `len`.
pub fn sample_indices(len: usize) -> Vec<usize> {
    (WINDOW..len).collect()
}

/// Rows of inputs and targets for the combiner.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TabularData {
    pub inputs: Vec<[f64; COMBINER_INPUTS]>,
    pub targets: Vec<f64>,
}

/// The combiner's training data: the sub-models' predictions on the samples
/// of `data`, with the sample targets, in the order of `samples`.
pub fn combiner_data(
    sub_models: &[SequenceNet; 3],
    data: &SequenceData,
    samples: &[usize],
) -> TabularData {
    let mut ws: Vec<SequenceWorkspace> = sub_models.iter().map(SequenceNet::workspace).collect();
    let mut out = TabularData::default();
    for &k in samples {
        let mut row = [0.0; COMBINER_INPUTS];
        for ((net, w), r) in sub_models.iter().zip(&mut ws).zip(&mut row) {
            data.window(k, &mut w.x);
            *r = net.forward(w);
        }
        out.inputs.push(row);
        out.targets.push(data.y[k]);
    }
    out
}

/// A model the trainer can fit: one scalar prediction per sample.
pub trait Trainable: Sync {
    type Data: Sync;
    type Workspace: Send;
    fn parameters(&self) -> &[f64];
    fn parameters_mut(&mut self) -> &mut [f64];
    fn new_workspace(&self) -> Self::Workspace;
    /// Forward pass on sample `k`: (prediction, target).
    fn forward_sample(&self, ws: &mut Self::Workspace, data: &Self::Data, k: usize) -> (f64, f64);
    /// After `forward_sample`: adds `dout`·∂ŷ/∂θ to `grad`.
    fn backward_sample(&self, ws: &mut Self::Workspace, dout: f64, grad: &mut [f64]);
}

impl Trainable for SequenceNet {
    type Data = SequenceData;
    type Workspace = SequenceWorkspace;
    fn parameters(&self) -> &[f64] {
        self.params()
    }
    fn parameters_mut(&mut self) -> &mut [f64] {
        self.params_mut()
    }
    fn new_workspace(&self) -> SequenceWorkspace {
        self.workspace()
    }
    fn forward_sample(
        &self,
        ws: &mut SequenceWorkspace,
        data: &SequenceData,
        k: usize,
    ) -> (f64, f64) {
        data.window(k, &mut ws.x);
        (self.forward(ws), data.y[k])
    }
    fn backward_sample(&self, ws: &mut SequenceWorkspace, dout: f64, grad: &mut [f64]) {
        self.backward(ws, dout, Some(grad), false);
    }
}

impl Trainable for Mlp {
    type Data = TabularData;
    type Workspace = MlpWorkspace;
    fn parameters(&self) -> &[f64] {
        self.params()
    }
    fn parameters_mut(&mut self) -> &mut [f64] {
        self.params_mut()
    }
    fn new_workspace(&self) -> MlpWorkspace {
        self.workspace()
    }
    fn forward_sample(&self, ws: &mut MlpWorkspace, data: &TabularData, k: usize) -> (f64, f64) {
        ws.x = data.inputs[k];
        (self.forward(ws), data.targets[k])
    }
    fn backward_sample(&self, ws: &mut MlpWorkspace, dout: f64, grad: &mut [f64]) {
        self.backward(ws, dout, Some(grad));
    }
}

/// Samples of one data set.
#[derive(Debug, Clone, Copy)]
pub struct Split<'a, D> {
    pub data: &'a D,
    pub samples: &'a [usize],
}

/// Splits `samples` into (training, validation), the validation set being the
/// last `fraction` of them (a contiguous block: no window overlaps across the
/// split except at its edge).
pub fn holdout(samples: &[usize], fraction: f64) -> (Vec<usize>, Vec<usize>) {
    let n_val = ((samples.len() as f64) * fraction.clamp(0.0, 1.0)).round() as usize;
    let (a, b) = samples.split_at(samples.len() - n_val);
    (a.to_vec(), b.to_vec())
}

/// Settings of [`train`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainConfig {
    pub learning_rate: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    pub batch_size: usize,
    pub max_epochs: usize,
    /// Epochs without a better validation MSE before stopping.
    pub patience: usize,
    /// Fixed number of gradient shards per mini-batch (not the thread count).
    pub shards: usize,
    /// Seed of the shuffling.
    pub seed: u64,
    /// Rescale the mini-batch gradient to at most this Euclidean norm.
    pub clip_norm: Option<f64>,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            learning_rate: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            batch_size: 32,
            max_epochs: 200,
            patience: 20,
            shards: 8,
            seed: 0,
            clip_norm: Some(1.0),
        }
    }
}

/// Progress after one epoch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpochReport {
    /// 1-based.
    pub epoch: usize,
    pub max_epochs: usize,
    /// Mean of the mini-batch MSEs over the epoch (scaled units).
    pub training_mse: f64,
    /// Validation MSE after the epoch (scaled units).
    pub validation_mse: f64,
    pub best_validation_mse: f64,
    pub best_epoch: usize,
}

/// Outcome of [`train`]; the model holds the best parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainReport {
    /// Validation MSE of the initial parameters.
    pub initial_validation_mse: f64,
    pub best_validation_mse: f64,
    /// 0 if no epoch improved on the initial parameters.
    pub best_epoch: usize,
    pub history: Vec<EpochReport>,
    /// Whether the training stopped on a non-finite loss.
    pub diverged: bool,
}

/// Training cannot start.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TrainError {
    #[error("no training samples")]
    NoTrainingSamples,
    #[error("no validation samples")]
    NoValidationSamples,
    #[error("invalid training configuration: {0}")]
    InvalidConfig(&'static str),
}

struct Shard<W> {
    ws: W,
    grad: Vec<f64>,
    loss: f64,
}

/// Sum over `samples` of the squared errors, in fixed shards (deterministic).
fn squared_error_sum<M: Trainable>(
    model: &M,
    data: &M::Data,
    samples: &[usize],
    shards: &mut [Shard<M::Workspace>],
    grad_scale: Option<f64>,
) -> f64 {
    let chunk = samples.len().div_ceil(shards.len()).max(1);
    shards.par_iter_mut().enumerate().for_each(|(s, shard)| {
        shard.loss = 0.0;
        if grad_scale.is_some() {
            shard.grad.fill(0.0);
        }
        let lo = (s * chunk).min(samples.len());
        let hi = ((s + 1) * chunk).min(samples.len());
        for &k in &samples[lo..hi] {
            let (pred, target) = model.forward_sample(&mut shard.ws, data, k);
            let e = pred - target;
            shard.loss += e * e;
            if let Some(scale) = grad_scale {
                model.backward_sample(&mut shard.ws, 2.0 * e * scale, &mut shard.grad);
            }
        }
    });
    shards.iter().map(|s| s.loss).sum()
}

/// Trains `model` by Adam on the MSE over `training`, keeps the parameters
/// with the best MSE on `validation` and stops after `patience` epochs
/// without improvement, after `max_epochs`, or on a non-finite loss.
/// `on_epoch` is called after every epoch.
///
/// Adam (bias-corrected): m ← β₁m + (1−β₁)g, v ← β₂v + (1−β₂)g²,
/// θ ← θ − lr·m̂/(√v̂ + ε) with m̂ = m/(1−β₁ᵗ), v̂ = v/(1−β₂ᵗ).
pub fn train<M: Trainable>(
    model: &mut M,
    training: Split<'_, M::Data>,
    validation: Split<'_, M::Data>,
    config: &TrainConfig,
    mut on_epoch: impl FnMut(&EpochReport),
) -> Result<TrainReport, TrainError> {
    if training.samples.is_empty() {
        return Err(TrainError::NoTrainingSamples);
    }
    if validation.samples.is_empty() {
        return Err(TrainError::NoValidationSamples);
    }
    if config.batch_size == 0 || config.shards == 0 {
        return Err(TrainError::InvalidConfig(
            "batch size and shards must be positive",
        ));
    }
    if !(config.learning_rate > 0.0
        && (0.0..1.0).contains(&config.beta1)
        && (0.0..1.0).contains(&config.beta2)
        && config.epsilon > 0.0)
    {
        return Err(TrainError::InvalidConfig(
            "need lr > 0, 0 ≤ β₁, β₂ < 1 and ε > 0",
        ));
    }
    let n = model.parameters().len();
    let mut shards: Vec<Shard<M::Workspace>> = (0..config.shards)
        .map(|_| Shard {
            ws: model.new_workspace(),
            grad: vec![0.0; n],
            loss: 0.0,
        })
        .collect();
    let val_mse = |model: &M, shards: &mut [Shard<M::Workspace>]| {
        squared_error_sum(model, validation.data, validation.samples, shards, None)
            / validation.samples.len() as f64
    };
    let initial = val_mse(model, &mut shards);
    let mut report = TrainReport {
        initial_validation_mse: initial,
        best_validation_mse: initial,
        best_epoch: 0,
        history: Vec::new(),
        diverged: !initial.is_finite(),
    };
    if report.diverged {
        return Ok(report);
    }
    let mut best = model.parameters().to_vec();
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut order = training.samples.to_vec();
    let (mut m, mut v) = (vec![0.0; n], vec![0.0; n]);
    let mut grad = vec![0.0; n];
    let mut step = 0i32;
    for epoch in 1..=config.max_epochs {
        // Fisher–Yates shuffle
        for i in (1..order.len()).rev() {
            let j = rng.random_range(0..=i);
            order.swap(i, j);
        }
        let mut loss_sum = 0.0;
        let mut batches = 0usize;
        for batch in order.chunks(config.batch_size) {
            let scale = 1.0 / batch.len() as f64;
            let loss = squared_error_sum(&*model, training.data, batch, &mut shards, Some(scale));
            loss_sum += loss * scale;
            batches += 1;
            grad.fill(0.0);
            for s in &shards {
                for (g, d) in grad.iter_mut().zip(&s.grad) {
                    *g += d;
                }
            }
            if let Some(max) = config.clip_norm {
                let norm = grad.iter().map(|g| g * g).sum::<f64>().sqrt();
                if norm > max {
                    grad.iter_mut().for_each(|g| *g *= max / norm);
                }
            }
            step += 1;
            let c1 = 1.0 - config.beta1.powi(step);
            let c2 = 1.0 - config.beta2.powi(step);
            let params = model.parameters_mut();
            for (((p, g), mi), vi) in params.iter_mut().zip(&grad).zip(&mut m).zip(&mut v) {
                *mi = config.beta1 * *mi + (1.0 - config.beta1) * g;
                *vi = config.beta2 * *vi + (1.0 - config.beta2) * g * g;
                *p -= config.learning_rate * (*mi / c1) / ((*vi / c2).sqrt() + config.epsilon);
            }
        }
        let training_mse = loss_sum / batches as f64;
        let validation_mse = val_mse(model, &mut shards);
        if !training_mse.is_finite() || !validation_mse.is_finite() {
            report.diverged = true;
            break;
        }
        if validation_mse < report.best_validation_mse {
            report.best_validation_mse = validation_mse;
            report.best_epoch = epoch;
            best.copy_from_slice(model.parameters());
        }
        let epoch_report = EpochReport {
            epoch,
            max_epochs: config.max_epochs,
            training_mse,
            validation_mse,
            best_validation_mse: report.best_validation_mse,
            best_epoch: report.best_epoch,
        };
        report.history.push(epoch_report);
        on_epoch(&epoch_report);
        if epoch - report.best_epoch >= config.patience.max(1) {
            break;
        }
    }
    model.parameters_mut().copy_from_slice(&best);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// y_{k+1} = 0.9·y_k + 0.1·g(u_k) in scaled units, g(ū) = ū, with a
    /// piecewise-constant input.
    fn synthetic(len: usize, seed: u64) -> SequenceData {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut data = SequenceData::default();
        let mut y = 0.5;
        let mut u = 0.0;
        for k in 0..len {
            if k % 5 == 0 {
                u = rng.random::<f64>();
            }
            // y[k] is the output after u[k] was applied
            y = 0.9 * y + 0.1 * u;
            data.u.push(u);
            data.y.push(y);
        }
        data
    }

    fn config(seed: u64) -> TrainConfig {
        TrainConfig {
            learning_rate: 0.01,
            batch_size: 16,
            max_epochs: 30,
            patience: 30,
            shards: 4,
            seed,
            ..TrainConfig::default()
        }
    }

    #[test]
    fn windows_follow_the_series_convention() {
        let scaling = Scaling::default();
        let u: Vec<f64> = (0..25).map(|k| k as f64 * 1e-7).collect();
        let y: Vec<f64> = (0..25).map(|k| 0.12 + 0.01 * k as f64).collect();
        let mut data = SequenceData::default();
        assert_eq!(data.push_series(&u[..22], &y[..22], &scaling), vec![20, 21]);
        // a second series: its samples start 20 after its own beginning
        assert_eq!(
            data.push_series(&u, &y, &scaling),
            (42..47).collect::<Vec<_>>()
        );
        let mut x = vec![0.0; 2 * WINDOW];
        data.window(21, &mut x);
        // last step: the input applied over step 21 and the output of step 20
        assert_eq!(x[2 * WINDOW - 2], scaling.input.scale(u[21]));
        assert_eq!(x[2 * WINDOW - 1], scaling.output.scale(y[20]));
        assert_eq!(x[0], scaling.input.scale(u[2]));
        assert_eq!(x[1], scaling.output.scale(y[1]));
        assert_eq!(
            holdout(&[1, 2, 3, 4, 5, 6, 7, 8, 9, 10], 0.2),
            (vec![1, 2, 3, 4, 5, 6, 7, 8], vec![9, 10])
        );
    }

    #[test]
    fn training_reduces_validation_error_and_is_deterministic() {
        let data = synthetic(260, 1);
        let (tr, va) = holdout(&sample_indices(data.u.len()), 0.25);
        let run = || {
            let mut net = SequenceNet::new(&[4], 3);
            let mut epochs = 0;
            let report = train(
                &mut net,
                Split {
                    data: &data,
                    samples: &tr,
                },
                Split {
                    data: &data,
                    samples: &va,
                },
                &config(9),
                |_| epochs += 1,
            )
            .unwrap();
            assert_eq!(epochs, report.history.len());
            (net, report)
        };
        let (net, report) = run();
        assert!(
            report.best_validation_mse * 5.0 < report.initial_validation_mse,
            "{} → {}",
            report.initial_validation_mse,
            report.best_validation_mse
        );
        // the model holds the best parameters: recompute the validation MSE
        let mut ws = net.workspace();
        let mse = va
            .iter()
            .map(|&k| {
                let (p, t) = net.forward_sample(&mut ws, &data, k);
                (p - t) * (p - t)
            })
            .sum::<f64>()
            / va.len() as f64;
        assert!((mse - report.best_validation_mse).abs() < 1e-12 * mse);
        // same seed, same bits, also on a one-thread pool
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let (again, _) = pool.install(run);
        assert_eq!(net.params(), again.params());
    }

    #[test]
    fn combiner_trains_and_early_stopping_keeps_the_best() {
        // target = mean of the inputs passed through a smooth map
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut data = TabularData::default();
        for _ in 0..200 {
            let x = [
                rng.random::<f64>(),
                rng.random::<f64>(),
                rng.random::<f64>(),
            ];
            data.inputs.push(x);
            data.targets.push(0.2 + 0.5 * (x[0] + x[1] + x[2]) / 3.0);
        }
        let all: Vec<usize> = (0..200).collect();
        let (tr, va) = holdout(&all, 0.2);
        let mut mlp = Mlp::new(6, 2);
        let cfg = TrainConfig {
            patience: 3,
            max_epochs: 400,
            ..config(5)
        };
        let report = train(
            &mut mlp,
            Split {
                data: &data,
                samples: &tr,
            },
            Split {
                data: &data,
                samples: &va,
            },
            &cfg,
            |_| {},
        )
        .unwrap();
        assert!(report.best_validation_mse * 5.0 < report.initial_validation_mse);
        let last = report.history.last().unwrap();
        assert!(last.epoch < 400 && last.epoch - report.best_epoch == 3);
        assert!(
            report
                .history
                .iter()
                .all(|e| e.validation_mse >= report.best_validation_mse)
        );
        assert_eq!(
            train(
                &mut mlp,
                Split {
                    data: &data,
                    samples: &[]
                },
                Split {
                    data: &data,
                    samples: &va
                },
                &cfg,
                |_| {}
            ),
            Err(TrainError::NoTrainingSamples)
        );
    }
}
