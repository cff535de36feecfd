//! Training: Adam on the mean squared error, shuffled mini-batches whose
//! gradient is computed in parallel shards, early stopping on a held-out set.
//!
//! # Data
//!
//! * [`SequenceData`] (for [`SequenceNet`]): scaled series with the convention
//!   of [`super::dataset::Series`] and [`super::rollout`]: u[k] is the input
//!   applied over step k, y[k] the output at its end. Sample k (20 ≤ k,
//!   k + H ≤ len, H = [`SequenceData::horizon`]) is an H-step recursive
//!   prediction exactly as the controller makes it: the recurrence is warmed up
//!   on (ū[j], ȳ[j − 1], ē[j]), j = k − 19..k, then predicts ŷ[k + q], q = 0..H,
//!   from (ū[k + q], ŷ[k + q − 1], ē[k + q]) with ŷ[k − 1] = ȳ[k − 1] (free run: the
//!   network is fed its own predictions, as in closed loop). The sample loss
//!   is the mean of the H squared errors; the fed-back predictions are treated
//!   as data in the backward pass (truncated: no gradient through the
//!   feedback).
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
    COMBINER_INPUTS, FEATURES, Mlp, MlpWorkspace, SequenceNet, SequenceWorkspace, TwoLayerNet,
};
use super::rollout::HORIZON;
use super::scaling::Scaling;

/// Scaled time series for sequence models (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceData {
    /// Scaled inputs ū[k] (applied over step k).
    pub u: Vec<f64>,
    /// Scaled outputs ȳ[k] (at the end of step k).
    pub y: Vec<f64>,
    /// Scaled ET0 ē[k] (over step k).
    pub e: Vec<f64>,
    /// Steps H of the recursive prediction each sample is scored on.
    pub horizon: usize,
    /// Outputs the input windows read instead of `y` (same length), or empty
    /// when the windows read `y` itself.
    pub y_input: Vec<f64>,
}

impl Default for SequenceData {
    fn default() -> Self {
        SequenceData::new(HORIZON)
    }
}

impl SequenceData {
    /// No data yet, samples predicting `horizon` (≥ 1) steps.
    pub fn new(horizon: usize) -> SequenceData {
        SequenceData {
            u: Vec::new(),
            y: Vec::new(),
            e: Vec::new(),
            horizon: horizon.max(1),
            y_input: Vec::new(),
        }
    }

    /// Appends a raw series (supply u [m/s], y [m³/m³], ET0 e [m/s], equal
    /// lengths) after scaling it, and returns the indices of its samples:
    /// sequences never cross from one appended series into the next.
    ///
    /// # Panics
    /// If the lengths differ.
    pub fn push_series(
        &mut self,
        u: &[f64],
        y: &[f64],
        e: &[f64],
        scaling: &Scaling,
    ) -> Vec<usize> {
        assert!(
            u.len() == y.len() && u.len() == e.len(),
            "series lengths differ"
        );
        let start = self.u.len();
        self.u.extend(u.iter().map(|&v| scaling.input.scale(v)));
        self.y.extend(y.iter().map(|&v| scaling.output.scale(v)));
        self.e.extend(e.iter().map(|&v| scaling.et0.scale(v)));
        if !self.y_input.is_empty() {
            self.y_input.extend_from_slice(&self.y[start..]);
        }
        sample_indices(u.len(), self.horizon)
            .into_iter()
            .map(|k| k + start)
            .collect()
    }

    /// Writes the warm-up steps of sample k into `x` ((ū, ȳ, ē) interleaved,
    /// [`WINDOW`] − 1 steps).
    fn warm_up(&self, k: usize, x: &mut [f64]) {
        let s0 = k + 1 - WINDOW;
        for (tau, step) in x.chunks_exact_mut(FEATURES).take(WINDOW - 1).enumerate() {
            step[0] = self.u[s0 + tau];
            step[1] = self.window_y(s0 + tau - 1);
            step[2] = self.e[s0 + tau];
        }
    }

    /// Writes step q of sample k's prediction into step t of `x`: the input
    /// and ET0 of step k + q beside the output `prev` fed back.
    fn predict_step(&self, k: usize, q: usize, prev: f64, x: &mut [f64], t: usize) {
        x[t * FEATURES] = self.u[k + q];
        x[t * FEATURES + 1] = prev;
        x[t * FEATURES + 2] = self.e[k + q];
    }

    /// The output at step i as an input window sees it.
    fn window_y(&self, i: usize) -> f64 {
        if self.y_input.is_empty() {
            self.y[i]
        } else {
            self.y_input[i]
        }
    }
}

/// The samples k = 20..=len − horizon of one series of length `len`.
pub fn sample_indices(len: usize, horizon: usize) -> Vec<usize> {
    (WINDOW..(len + 1).saturating_sub(horizon.max(1))).collect()
}

/// Rows of inputs and targets for the combiner.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TabularData {
    pub inputs: Vec<[f64; COMBINER_INPUTS]>,
    pub targets: Vec<f64>,
}

/// Runs the free-running prediction of sample k with each network (fed back
/// their own predictions, or the combination of them when `combiner` is
/// given), calling `row(q, z, target)` for q = 0..H.
fn roll_sample(
    nets: &[SequenceNet],
    combiner: Option<(&Mlp, &mut MlpWorkspace)>,
    ws: &mut [SequenceWorkspace],
    data: &SequenceData,
    k: usize,
    mut row: impl FnMut(usize, [f64; COMBINER_INPUTS], f64),
) {
    let h = data.horizon;
    for (net, w) in nets.iter().zip(ws.iter_mut()) {
        w.ensure_steps(WINDOW - 1 + h);
        data.warm_up(k, &mut w.x);
        net.advance(w, 0, WINDOW - 1);
    }
    let mut combiner = combiner;
    let mut prev = [data.window_y(k - 1); COMBINER_INPUTS];
    for q in 0..h {
        let t = WINDOW - 1 + q;
        let mut z = [0.0; COMBINER_INPUTS];
        for (i, (net, w)) in nets.iter().zip(ws.iter_mut()).enumerate() {
            data.predict_step(k, q, prev[i], &mut w.x, t);
            net.advance(w, t, t + 1);
            z[i] = net.output(w, t);
        }
        match combiner.as_mut() {
            Some((mlp, c)) => prev = [mlp.predict(c, z); COMBINER_INPUTS],
            None => prev = z,
        }
        row(q, z, data.y[k + q]);
    }
}

/// The combiner's training data: every `horizon`-th sample of `samples` is
/// predicted `horizon` steps ahead by each sub-model on its own (each fed its
/// own predictions back); every step gives a row (M1, M2, M3 predictions) →
/// target.
pub fn combiner_data(
    sub_models: &[SequenceNet; 3],
    data: &SequenceData,
    samples: &[usize],
) -> TabularData {
    combiner_rows(sub_models, None, data, samples)
}

/// As [`combiner_data`], but the sub-models are fed back the combination of
/// their predictions by `combiner`, as in the two-layer network's own
/// rollout: the data for refining a combiner trained on [`combiner_data`].
pub fn combiner_data_closed_loop(
    sub_models: &[SequenceNet; 3],
    combiner: &Mlp,
    data: &SequenceData,
    samples: &[usize],
) -> TabularData {
    combiner_rows(sub_models, Some(combiner), data, samples)
}

fn combiner_rows(
    sub_models: &[SequenceNet; 3],
    combiner: Option<&Mlp>,
    data: &SequenceData,
    samples: &[usize],
) -> TabularData {
    let starts: Vec<usize> = samples.iter().copied().step_by(data.horizon).collect();
    let parts: Vec<TabularData> = starts
        .par_chunks(64)
        .map(|chunk| {
            let mut ws: Vec<SequenceWorkspace> =
                sub_models.iter().map(SequenceNet::workspace).collect();
            let mut cws = combiner.map(Mlp::workspace);
            let mut out = TabularData::default();
            for &k in chunk {
                let c = combiner.zip(cws.as_mut());
                roll_sample(sub_models, c, &mut ws, data, k, |_, z, target| {
                    out.inputs.push(z);
                    out.targets.push(target);
                });
            }
            out
        })
        .collect();
    let mut out = TabularData::default();
    for p in parts {
        out.inputs.extend(p.inputs);
        out.targets.extend(p.targets);
    }
    out
}

/// A model the trainer can fit.
pub trait Trainable: Sync {
    type Data: Sync;
    type Workspace: Send;
    fn parameters(&self) -> &[f64];
    fn parameters_mut(&mut self) -> &mut [f64];
    fn new_workspace(&self) -> Self::Workspace;
    /// Forward pass on sample `k`: its loss (a mean squared error).
    fn sample_loss(&self, ws: &mut Self::Workspace, data: &Self::Data, k: usize) -> f64;
    /// After `sample_loss`: adds `scale`·∂loss/∂θ to `grad`.
    fn backward_sample(&self, ws: &mut Self::Workspace, scale: f64, grad: &mut [f64]);
    /// Called after the parameters were changed through `parameters_mut`.
    fn parameters_changed(&mut self) {}
}

/// Workspace of a [`SequenceNet`] in training: the network's and the
/// sample's length.
#[derive(Debug, Clone)]
pub struct SequenceTrainWorkspace {
    ws: SequenceWorkspace,
    steps: usize,
}

impl Trainable for SequenceNet {
    type Data = SequenceData;
    type Workspace = SequenceTrainWorkspace;
    fn parameters(&self) -> &[f64] {
        self.params()
    }
    fn parameters_mut(&mut self) -> &mut [f64] {
        self.params_mut()
    }
    fn new_workspace(&self) -> SequenceTrainWorkspace {
        SequenceTrainWorkspace {
            ws: self.workspace(),
            steps: 0,
        }
    }
    fn sample_loss(&self, tw: &mut SequenceTrainWorkspace, data: &SequenceData, k: usize) -> f64 {
        let h = data.horizon;
        let steps = WINDOW - 1 + h;
        let ws = &mut tw.ws;
        ws.ensure_steps(steps);
        tw.steps = steps;
        data.warm_up(k, &mut ws.x);
        self.advance(ws, 0, WINDOW - 1);
        ws.dout[..WINDOW - 1].fill(0.0);
        let mut prev = data.window_y(k - 1);
        let mut loss = 0.0;
        for q in 0..h {
            let t = WINDOW - 1 + q;
            data.predict_step(k, q, prev, &mut ws.x, t);
            self.advance(ws, t, t + 1);
            let out = self.output(ws, t);
            let e = out - data.y[k + q];
            loss += e * e;
            ws.dout[t] = 2.0 * e / h as f64;
            prev = out;
        }
        loss / h as f64
    }
    fn backward_sample(&self, tw: &mut SequenceTrainWorkspace, scale: f64, grad: &mut [f64]) {
        let steps = tw.steps;
        tw.ws.dout[..steps].iter_mut().for_each(|d| *d *= scale);
        self.backward_sequence(&mut tw.ws, steps, Some(grad), false);
    }
}

/// Workspace of an [`Mlp`] in training: the network's and the residual.
#[derive(Debug, Clone)]
pub struct MlpTrainWorkspace {
    ws: MlpWorkspace,
    residual: f64,
}

impl Trainable for Mlp {
    type Data = TabularData;
    type Workspace = MlpTrainWorkspace;
    fn parameters(&self) -> &[f64] {
        self.params()
    }
    fn parameters_mut(&mut self) -> &mut [f64] {
        self.params_mut()
    }
    fn new_workspace(&self) -> MlpTrainWorkspace {
        MlpTrainWorkspace {
            ws: self.workspace(),
            residual: 0.0,
        }
    }
    fn sample_loss(&self, tw: &mut MlpTrainWorkspace, data: &TabularData, k: usize) -> f64 {
        tw.ws.x = data.inputs[k];
        tw.residual = self.forward(&mut tw.ws) - data.targets[k];
        tw.residual * tw.residual
    }
    fn backward_sample(&self, tw: &mut MlpTrainWorkspace, scale: f64, grad: &mut [f64]) {
        self.backward(&mut tw.ws, 2.0 * tw.residual * scale, Some(grad));
    }
}

/// The two-layer network trained end to end (M1–M3 and M_A together) on
/// the free-running loss of [`SequenceData`] samples, the sub-models fed back
/// the combined prediction exactly as in [`super::rollout`]. Used to refine a
/// network trained stage-wise (sub-models on their ranges, then M_A).
///
/// Parameters: M1, M2, M3, M_A concatenated (the order of
/// [`super::Surrogate::params`]); kept flat here and copied into the networks
/// after every update.
#[derive(Debug, Clone)]
pub struct JointTwoLayer {
    net: TwoLayerNet,
    params: Vec<f64>,
}

impl JointTwoLayer {
    pub fn new(net: TwoLayerNet) -> JointTwoLayer {
        let mut params = Vec::new();
        for s in &net.sub_models {
            params.extend_from_slice(s.params());
        }
        params.extend_from_slice(net.combiner.params());
        JointTwoLayer { net, params }
    }

    pub fn into_inner(self) -> TwoLayerNet {
        self.net
    }

    fn offsets(&self) -> [usize; 4] {
        let mut o = [0; 4];
        let mut at = 0;
        for (i, s) in self.net.sub_models.iter().enumerate() {
            o[i] = at;
            at += s.n_params();
        }
        o[3] = at;
        o
    }
}

/// Workspace of [`JointTwoLayer`] in training.
#[derive(Debug, Clone)]
pub struct JointWorkspace {
    subs: Vec<SequenceWorkspace>,
    mlp: MlpWorkspace,
    /// Sub-model predictions per predicted step.
    z: Vec<[f64; COMBINER_INPUTS]>,
    /// ∂loss/∂ŷ per predicted step.
    dy: Vec<f64>,
    horizon: usize,
}

impl Trainable for JointTwoLayer {
    type Data = SequenceData;
    type Workspace = JointWorkspace;
    fn parameters(&self) -> &[f64] {
        &self.params
    }
    fn parameters_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }
    fn parameters_changed(&mut self) {
        let o = self.offsets();
        for (i, s) in self.net.sub_models.iter_mut().enumerate() {
            let n = s.n_params();
            s.params_mut().copy_from_slice(&self.params[o[i]..o[i] + n]);
        }
        self.net
            .combiner
            .params_mut()
            .copy_from_slice(&self.params[o[3]..]);
    }
    fn new_workspace(&self) -> JointWorkspace {
        JointWorkspace {
            subs: self
                .net
                .sub_models
                .iter()
                .map(SequenceNet::workspace)
                .collect(),
            mlp: self.net.combiner.workspace(),
            z: Vec::new(),
            dy: Vec::new(),
            horizon: 0,
        }
    }
    fn sample_loss(&self, ws: &mut JointWorkspace, data: &SequenceData, k: usize) -> f64 {
        let h = data.horizon;
        ws.horizon = h;
        ws.z.clear();
        ws.dy.clear();
        let mut loss = 0.0;
        let JointWorkspace {
            subs, mlp, z, dy, ..
        } = ws;
        roll_sample(
            &self.net.sub_models,
            Some((&self.net.combiner, mlp)),
            subs,
            data,
            k,
            |_, zq, _| z.push(zq),
        );
        for (q, zq) in z.iter().enumerate() {
            let e = self.net.combiner.predict(mlp, *zq) - data.y[k + q];
            loss += e * e;
            dy.push(2.0 * e / h as f64);
        }
        loss / h as f64
    }
    fn backward_sample(&self, ws: &mut JointWorkspace, scale: f64, grad: &mut [f64]) {
        let o = self.offsets();
        let h = ws.horizon;
        let steps = WINDOW - 1 + h;
        for s in &mut ws.subs {
            s.dout[..steps].fill(0.0);
        }
        let (g_subs, g_mlp) = grad.split_at_mut(o[3]);
        for q in 0..h {
            let d = ws.dy[q] * scale;
            self.net.combiner.predict(&mut ws.mlp, ws.z[q]);
            self.net.combiner.backward(&mut ws.mlp, d, Some(g_mlp));
            for (s, &dz) in ws.subs.iter_mut().zip(&ws.mlp.dx) {
                s.dout[WINDOW - 1 + q] = dz;
            }
        }
        for (i, (net, s)) in self.net.sub_models.iter().zip(&mut ws.subs).enumerate() {
            let n = net.n_params();
            net.backward_sequence(s, steps, Some(&mut g_subs[o[i]..o[i] + n]), false);
        }
    }
}

/// Samples of one data set.
#[derive(Debug)]
pub struct Split<'a, D> {
    pub data: &'a D,
    pub samples: &'a [usize],
}

impl<D> Clone for Split<'_, D> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<D> Copy for Split<'_, D> {}

impl<'a, D> Split<'a, D> {
    /// The training and the held-out split of one data set.
    pub fn pair(
        data: &'a D,
        training: &'a [usize],
        validation: &'a [usize],
    ) -> (Split<'a, D>, Split<'a, D>) {
        (
            Split {
                data,
                samples: training,
            },
            Split {
                data,
                samples: validation,
            },
        )
    }
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
    /// The caller's stop check ([`train_until`]) said so.
    #[error("training cancelled")]
    Cancelled,
}

struct Shard<W> {
    ws: W,
    grad: Vec<f64>,
    loss: f64,
}

/// Sum over `samples` of the sample losses, in fixed shards (deterministic).
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
            shard.loss += model.sample_loss(&mut shard.ws, data, k);
            if let Some(scale) = grad_scale {
                model.backward_sample(&mut shard.ws, scale, &mut shard.grad);
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
    on_epoch: impl FnMut(&EpochReport),
) -> Result<TrainReport, TrainError> {
    train_until(model, training, validation, config, on_epoch, &|| false)
}

/// [`train`] with a stop check, asked before every mini-batch: when it
/// says stop, the model is left as it was before training and the answer
/// is [`TrainError::Cancelled`].
pub fn train_until<M: Trainable>(
    model: &mut M,
    training: Split<'_, M::Data>,
    validation: Split<'_, M::Data>,
    config: &TrainConfig,
    mut on_epoch: impl FnMut(&EpochReport),
    stop: &dyn Fn() -> bool,
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
    let initial_params = best.clone();
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
            if stop() {
                let start = initial_params.as_slice();
                model.parameters_mut().copy_from_slice(start);
                model.parameters_changed();
                return Err(TrainError::Cancelled);
            }
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
            model.parameters_changed();
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
    model.parameters_changed();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// y_{k+1} = 0.9·y_k + 0.1·g(u_k) in scaled units, g(ū) = ū, with a
    /// piecewise-constant input.
    fn synthetic(len: usize, seed: u64) -> SequenceData {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut data = SequenceData::new(5);
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
            data.e.push(0.5);
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
    fn samples_follow_the_series_convention() {
        let scaling = Scaling::default();
        let u: Vec<f64> = (0..30).map(|k| k as f64 * 1e-7).collect();
        let y: Vec<f64> = (0..30).map(|k| 0.12 + 0.01 * k as f64).collect();
        let e: Vec<f64> = (0..30).map(|k| (k + 1) as f64 * 1e-9).collect();
        let mut data = SequenceData::new(3);
        // sample k needs y[k − 20] and y[k + 2]
        assert_eq!(
            data.push_series(&u[..24], &y[..24], &e[..24], &scaling),
            vec![20, 21]
        );
        // a second series: its samples start 20 after its own beginning
        assert_eq!(
            data.push_series(&u, &y, &e, &scaling),
            (44..52).collect::<Vec<_>>()
        );
        let mut x = vec![0.0; FEATURES * WINDOW];
        data.warm_up(21, &mut x);
        // first warm-up step: the input and ET0 over step 2 and the output
        // of step 1; last: those over step 20 and the output of step 19
        assert_eq!(x[0], scaling.input.scale(u[2]));
        assert_eq!(x[1], scaling.output.scale(y[1]));
        assert_eq!(x[2], scaling.et0.scale(e[2]));
        let last = FEATURES * (WINDOW - 2);
        assert_eq!(x[last], scaling.input.scale(u[20]));
        assert_eq!(x[last + 1], scaling.output.scale(y[19]));
        assert_eq!(x[last + 2], scaling.et0.scale(e[20]));
        assert_eq!(
            holdout(&[1, 2, 3, 4, 5, 6, 7, 8, 9, 10], 0.2),
            (vec![1, 2, 3, 4, 5, 6, 7, 8], vec![9, 10])
        );
    }

    #[test]
    fn sample_loss_is_the_free_running_prediction_error() {
        // the loss of a sample is that of the rollout the controller makes
        let scaling = Scaling::default();
        let u: Vec<f64> = (0..40).map(|k| ((k % 7) as f64) * 1e-6).collect();
        let y: Vec<f64> = (0..40).map(|k| 0.2 + 0.002 * k as f64).collect();
        let e: Vec<f64> = (0..40).map(|k| ((k % 12) as f64) * 1e-8).collect();
        let mut data = SequenceData::new(5);
        data.push_series(&u, &y, &e, &scaling);
        let net = SequenceNet::new(&[3], 11);
        let mut tw = net.new_workspace();
        let loss = net.sample_loss(&mut tw, &data, 25);
        let mut p = crate::surrogate::Predictor::new(
            crate::surrogate::Surrogate::Single(net.clone()),
            scaling,
        );
        let mut out = [0.0; 5];
        let past = crate::surrogate::Past {
            u: &u[5..25],
            y: &y[5..25],
            et0: &e[5..25],
        };
        p.predict(past, &u[25..30], &e[25..30], 0.0, &mut out)
            .unwrap();
        let expected = (0..5)
            .map(|q| (scaling.output.scale(out[q]) - data.y[25 + q]).powi(2))
            .sum::<f64>()
            / 5.0;
        assert!(
            (loss - expected).abs() < 1e-12 * expected,
            "{loss} vs {expected}"
        );
    }

    #[test]
    fn training_reduces_validation_error_and_is_deterministic() {
        let data = synthetic(260, 1);
        let (tr, va) = holdout(&sample_indices(data.u.len(), data.horizon), 0.25);
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
        let mut ws = net.new_workspace();
        let mse = va
            .iter()
            .map(|&k| net.sample_loss(&mut ws, &data, k))
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

    /// With a one-step horizon nothing is fed back, so the gradient of the
    /// joint two-layer loss is exact: compare it with finite differences.
    #[test]
    fn joint_two_layer_gradient_matches_finite_differences() {
        let scaling = Scaling::default();
        let u: Vec<f64> = (0..30).map(|k| ((k % 4) as f64) * 2e-6).collect();
        let y: Vec<f64> = (0..30)
            .map(|k| 0.2 + 0.1 * (k as f64 / 5.0).sin())
            .collect();
        let e: Vec<f64> = (0..30).map(|k| 3e-8 * (1.0 + (k as f64).cos())).collect();
        let mut data = SequenceData::new(1);
        data.push_series(&u, &y, &e, &scaling);
        let mut joint = JointTwoLayer::new(TwoLayerNet {
            sub_models: [
                SequenceNet::new(&[2], 1),
                SequenceNet::new(&[3], 2),
                SequenceNet::new(&[2, 2], 3),
            ],
            combiner: Mlp::new(3, 4),
        });
        let mut p = joint.parameters().to_vec();
        crate::surrogate::network::tests::jiggle(&mut p, 6, 0.3);
        joint.parameters_mut().copy_from_slice(&p);
        joint.parameters_changed();
        let mut ws = joint.new_workspace();
        joint.sample_loss(&mut ws, &data, 24);
        let mut grad = vec![0.0; p.len()];
        joint.backward_sample(&mut ws, 1.0, &mut grad);
        let eps = 1e-6;
        for k in 0..p.len() {
            let loss_at = |v: f64| {
                let mut j = joint.clone();
                j.parameters_mut()[k] = v;
                j.parameters_changed();
                j.sample_loss(&mut j.new_workspace(), &data, 24)
            };
            let fd = (loss_at(p[k] + eps) - loss_at(p[k] - eps)) / (2.0 * eps);
            let err = (fd - grad[k]).abs() / fd.abs().max(grad[k].abs()).max(1e-4);
            assert!(err < 1e-5, "param {k}: fd {fd} vs {}", grad[k]);
        }
        assert!(grad.iter().map(|g| g.abs()).fold(0.0, f64::max) > 1e-3);
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
