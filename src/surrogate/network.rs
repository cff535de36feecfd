//! The networks: [`SequenceNet`] (stacked LSTM + dense head over a window),
//! [`Mlp`] (the combiner 3 → h → h → 1), [`TwoLayerNet`] (M1–M3 and M_A) and
//! [`Surrogate`], either of the two prediction models.
//!
//! All networks work on scaled quantities (see [`super::scaling`]) and keep
//! their parameters in one flat `Vec<f64>`, layer after layer.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::dense::{Dense, dot, sigmoid};
use super::evaluate::WINDOW;
use super::lstm::{Lstm, LstmTape};

/// Input features per window step: (ū, ȳ, ē), the supply, the output and
/// the reference evapotranspiration (see [`super::scaling`]).
pub const FEATURES: usize = 3;
/// Input features of the model files of version 1, before ET0: (ū, ȳ).
pub const LEGACY_FEATURES: usize = 2;
/// Inputs of the combiner M_A: the three sub-model predictions.
pub const COMBINER_INPUTS: usize = 3;
/// Largest hidden size accepted (a sanity bound for files).
pub const MAX_HIDDEN: usize = 1024;

/// A parameter vector of the wrong length was given.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("expected {expected} parameters, found {found}")]
pub struct ParamLengthError {
    pub expected: usize,
    pub found: usize,
}

impl ParamLengthError {
    /// Ok when `found` parameters are the `expected` number.
    fn check(expected: usize, found: usize) -> Result<(), ParamLengthError> {
        if found == expected {
            Ok(())
        } else {
            Err(ParamLengthError { expected, found })
        }
    }
}

/// Why an architecture is not accepted.
pub(crate) fn lstm_architecture_problem(hidden: &[usize]) -> Option<String> {
    if hidden.is_empty() || hidden.len() > 2 {
        Some(format!(
            "1 or 2 LSTM layers expected, found {}",
            hidden.len()
        ))
    } else if hidden.iter().any(|&h| h == 0 || h > MAX_HIDDEN) {
        Some(format!(
            "LSTM hidden sizes must be in 1..={MAX_HIDDEN}, found {hidden:?}"
        ))
    } else {
        None
    }
}

fn uniform_draw(seed: u64) -> impl FnMut() -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    move || rng.random::<f64>()
}

fn set_checked(dst: &mut [f64], src: &[f64]) -> Result<(), ParamLengthError> {
    ParamLengthError::check(dst.len(), src.len())?;
    dst.copy_from_slice(src);
    Ok(())
}

/// Stacked LSTM (1 or 2 layers) over a sequence of (ū[j], ȳ[j − 1]) pairs
/// with a dense head from the top hidden state to ȳ[j] at every step.
///
/// The recurrence starts from rest [`WINDOW`] − 1 steps before the first
/// prediction: the 20-sample window of MODEL.md §3 warms the state up, its
/// last pair gives the first prediction, and later predictions continue the
/// same recurrence one step at a time, each fed the previous prediction (see
/// [`super::rollout`]). A one-step prediction is therefore exactly a 20-step
/// window model; multi-step predictions cost one LSTM step each.
///
/// Parameters: layer 1, (layer 2), head (see [`super::lstm`] and
/// [`super::dense`] for the layouts).
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceNet {
    layers: Vec<Lstm>,
    head: Dense,
    params: Vec<f64>,
}

/// Forward/backward/tangent workspace of a [`SequenceNet`]; grows to the
/// longest sequence seen.
#[derive(Debug, Clone)]
pub struct SequenceWorkspace {
    tapes: Vec<LstmTape>,
    /// ∂L/∂h of every step, one buffer per layer.
    dh: Vec<Vec<f64>>,
    /// The inputs, (ū, ȳ, ē) per step.
    pub(crate) x: Vec<f64>,
    /// ∂L/∂x of the sequence, filled by the backward pass when asked.
    pub(crate) dx: Vec<f64>,
    /// Per-step output gradients for the backward pass.
    pub(crate) dout: Vec<f64>,
    /// Forward-mode tangents per layer: ∂h and ∂c, direction-major.
    th: Vec<Vec<f64>>,
    tc: Vec<Vec<f64>>,
    /// Tangent scratch (4h of the widest layer).
    ta: Vec<f64>,
    /// Output tangents ∂ŷ per direction after [`SequenceNet::tangent_step`].
    pub(crate) tz: Vec<f64>,
}

impl SequenceWorkspace {
    /// Makes room for sequences of `steps` steps.
    pub(crate) fn ensure_steps(&mut self, steps: usize) {
        if self.x.len() < steps * FEATURES {
            self.x.resize(steps * FEATURES, 0.0);
            self.dx.resize(steps * FEATURES, 0.0);
            self.dout.resize(steps, 0.0);
        }
    }
}

impl SequenceNet {
    /// A network with LSTM layers of the given hidden sizes (1 or 2 layers),
    /// Glorot-uniform weights drawn from `ChaCha8Rng::seed_from_u64(seed)`.
    ///
    /// # Panics
    /// If the architecture is not 1–2 layers of hidden size 1..=[`MAX_HIDDEN`].
    pub fn new(hidden: &[usize], seed: u64) -> SequenceNet {
        if let Some(problem) = lstm_architecture_problem(hidden) {
            panic!("{problem}");
        }
        let mut layers = Vec::with_capacity(hidden.len());
        let mut n_in = FEATURES;
        for &h in hidden {
            layers.push(Lstm { n_in, hidden: h });
            n_in = h;
        }
        let head = Dense { n_in, n_out: 1 };
        let n = layers.iter().map(Lstm::n_params).sum::<usize>() + head.n_params();
        let mut net = SequenceNet {
            layers,
            head,
            params: vec![0.0; n],
        };
        let mut draw = uniform_draw(seed);
        let mut offset = 0;
        for layer in &net.layers {
            let len = layer.n_params();
            layer.init(&mut net.params[offset..offset + len], &mut draw);
            offset += len;
        }
        net.head.init(&mut net.params[offset..], &mut draw);
        net
    }

    /// Hidden sizes of the LSTM layers, bottom first.
    pub fn hidden_sizes(&self) -> Vec<usize> {
        self.layers.iter().map(|l| l.hidden).collect()
    }

    /// How many parameters this architecture had with the
    /// [`LEGACY_FEATURES`] inputs of model files before ET0.
    pub fn legacy_n_params(&self) -> usize {
        self.n_params() - 4 * self.layers[0].hidden * (FEATURES - LEGACY_FEATURES)
    }

    /// This architecture's parameters from those of a network without the
    /// ET0 input: the first layer's input weights of ē are zero, so the
    /// network predicts exactly what the old one did, whatever ET0 is.
    pub fn params_from_legacy(&self, legacy: &[f64]) -> Result<Vec<f64>, ParamLengthError> {
        let expected = self.legacy_n_params();
        ParamLengthError::check(expected, legacy.len())?;
        // Wᵀ is input-major (one row of 4h per input): ē's row goes after ȳ's
        let row = 4 * self.layers[0].hidden;
        let mut p = Vec::with_capacity(self.n_params());
        p.extend_from_slice(&legacy[..LEGACY_FEATURES * row]);
        p.resize(p.len() + (FEATURES - LEGACY_FEATURES) * row, 0.0);
        p.extend_from_slice(&legacy[LEGACY_FEATURES * row..]);
        Ok(p)
    }

    pub fn n_params(&self) -> usize {
        self.params.len()
    }

    pub fn params(&self) -> &[f64] {
        &self.params
    }

    pub fn set_params(&mut self, params: &[f64]) -> Result<(), ParamLengthError> {
        set_checked(&mut self.params, params)
    }

    pub(crate) fn params_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }

    /// A workspace for sequences of a window and a 20-step horizon (it grows
    /// when longer sequences are run).
    pub fn workspace(&self) -> SequenceWorkspace {
        let steps = WINDOW - 1 + super::rollout::HORIZON;
        let widest = self.layers.iter().map(|l| l.hidden).max().unwrap_or(1);
        SequenceWorkspace {
            tapes: self.layers.iter().map(|l| l.tape(steps)).collect(),
            dh: self.layers.iter().map(|_| Vec::new()).collect(),
            x: vec![0.0; steps * FEATURES],
            dx: vec![0.0; steps * FEATURES],
            dout: vec![0.0; steps],
            th: self.layers.iter().map(|_| Vec::new()).collect(),
            tc: self.layers.iter().map(|_| Vec::new()).collect(),
            ta: vec![0.0; 4 * widest],
            tz: Vec::new(),
        }
    }

    fn head_offset(&self) -> usize {
        self.params.len() - self.head.n_params()
    }

    /// ȳ_next from a window of scaled inputs `u`, outputs `y` and ET0 `e`
    /// (each [`WINDOW`] long, oldest first; step τ of the window is (u[τ],
    /// y[τ], e[τ])).
    pub fn predict(&self, ws: &mut SequenceWorkspace, u: &[f64], y: &[f64], e: &[f64]) -> f64 {
        ws.ensure_steps(WINDOW);
        fill_window(&mut ws.x, u, y, e);
        self.forward(ws)
    }

    /// Forward pass on the window already in `ws.x` (its first [`WINDOW`] steps).
    pub(crate) fn forward(&self, ws: &mut SequenceWorkspace) -> f64 {
        self.advance(ws, 0, WINDOW);
        self.output(ws, WINDOW - 1)
    }

    /// Runs steps `from..to` of every layer on the inputs in `ws.x`; steps
    /// `0..from` must have been run before.
    pub(crate) fn advance(&self, ws: &mut SequenceWorkspace, from: usize, to: usize) {
        let mut offset = 0;
        for (l, layer) in self.layers.iter().enumerate() {
            let p = &self.params[offset..offset + layer.n_params()];
            offset += layer.n_params();
            let (below, here) = ws.tapes.split_at_mut(l);
            let x = if l == 0 {
                &ws.x[..]
            } else {
                &below[l - 1].h[..]
            };
            layer.forward_range(p, x, &mut here[0], from, to);
        }
    }

    /// The head's output ȳ at step `t` (after [`advance`](Self::advance) past it).
    pub(crate) fn output(&self, ws: &SequenceWorkspace, t: usize) -> f64 {
        let top = &ws.tapes[self.layers.len() - 1];
        let h = self.head.n_in;
        let mut out = [0.0];
        self.head.forward(
            &self.params[self.head_offset()..],
            &top.h[t * h..(t + 1) * h],
            &mut out,
        );
        out[0]
    }

    /// Backward pass after [`forward`](Self::forward) for the output gradient
    /// `dout` = ∂L/∂ŷ: adds ∂L/∂θ to `grad` when given, and writes ∂L/∂x of
    /// the window into `ws.dx` when `want_dx`.
    #[cfg(test)]
    pub(crate) fn backward(
        &self,
        ws: &mut SequenceWorkspace,
        dout: f64,
        grad: Option<&mut [f64]>,
        want_dx: bool,
    ) {
        ws.dout[..WINDOW].fill(0.0);
        ws.dout[WINDOW - 1] = dout;
        self.backward_sequence(ws, WINDOW, grad, want_dx);
    }

    /// Backpropagation through the first `steps` steps, with the output
    /// gradients ∂L/∂ŷₜ in `ws.dout[..steps]` (zero where a step's output is
    /// not used). The inputs in `ws.x` are taken as given (outputs fed back as
    /// inputs are not differentiated through). Adds ∂L/∂θ to `grad` when
    /// given; writes ∂L/∂x into `ws.dx` when `want_dx`.
    pub(crate) fn backward_sequence(
        &self,
        ws: &mut SequenceWorkspace,
        steps: usize,
        mut grad: Option<&mut [f64]>,
        want_dx: bool,
    ) {
        let n_layers = self.layers.len();
        let head_offset = self.head_offset();
        let top = n_layers - 1;
        let h_top = self.head.n_in;
        for (dh, layer) in ws.dh.iter_mut().zip(&self.layers) {
            if dh.len() < steps * layer.hidden {
                dh.resize(steps * layer.hidden, 0.0);
            }
        }
        {
            let dh = &mut ws.dh[top][..steps * h_top];
            let hs = &ws.tapes[top].h;
            for t in 0..steps {
                let d = ws.dout[t];
                let dht = &mut dh[t * h_top..(t + 1) * h_top];
                if d == 0.0 {
                    dht.fill(0.0);
                    continue;
                }
                self.head.backward(
                    &self.params[head_offset..],
                    &hs[t * h_top..(t + 1) * h_top],
                    &[d],
                    grad.as_deref_mut().map(|g| &mut g[head_offset..]),
                    Some(dht),
                );
            }
        }
        let mut offset = head_offset;
        for l in (0..n_layers).rev() {
            let layer = self.layers[l];
            offset -= layer.n_params();
            let p = &self.params[offset..offset + layer.n_params()];
            let g = grad
                .as_deref_mut()
                .map(|g| &mut g[offset..offset + layer.n_params()]);
            let (below, here) = ws.tapes.split_at_mut(l);
            let (dh_below, dh_here) = ws.dh.split_at_mut(l);
            let dh_out = &dh_here[0][..steps * layer.hidden];
            if l == 0 {
                let dx = if want_dx {
                    Some(&mut ws.dx[..steps * FEATURES])
                } else {
                    None
                };
                layer.backward(p, &ws.x[..steps * FEATURES], dh_out, &mut here[0], g, dx);
            } else {
                let n_in = layer.n_in;
                layer.backward(
                    p,
                    &below[l - 1].h[..steps * n_in],
                    dh_out,
                    &mut here[0],
                    g,
                    Some(&mut dh_below[l - 1][..steps * n_in]),
                );
            }
        }
    }

    /// Clears the forward-mode tangents for up to `dirs` directions.
    pub(crate) fn reset_tangents(&self, ws: &mut SequenceWorkspace, dirs: usize) {
        for ((th, tc), layer) in ws.th.iter_mut().zip(&mut ws.tc).zip(&self.layers) {
            th.clear();
            th.resize(dirs * layer.hidden, 0.0);
            tc.clear();
            tc.resize(dirs * layer.hidden, 0.0);
        }
        ws.tz.clear();
        ws.tz.resize(dirs, 0.0);
    }

    /// Propagates the tangents of `dirs` directions through step `t` (after
    /// [`advance`](Self::advance) past it): `dx` holds the input tangents
    /// (dirs × 2, direction-major); the state tangents of step t − 1 are those
    /// left in the workspace by the previous call (zero after
    /// [`reset_tangents`](Self::reset_tangents)). Writes ∂ŷₜ per direction
    /// into `ws.tz[..dirs]`.
    pub(crate) fn tangent_step(
        &self,
        ws: &mut SequenceWorkspace,
        t: usize,
        dirs: usize,
        dx: &[f64],
    ) {
        let mut offset = 0;
        for (l, layer) in self.layers.iter().enumerate() {
            let p = &self.params[offset..offset + layer.n_params()];
            offset += layer.n_params();
            let h = layer.hidden;
            let (th_below, th_here) = ws.th.split_at_mut(l);
            let input = if l == 0 {
                &dx[..dirs * FEATURES]
            } else {
                &th_below[l - 1][..dirs * layer.n_in]
            };
            layer.tangent_step(
                p,
                &ws.tapes[l],
                t,
                dirs,
                input,
                &mut th_here[0][..dirs * h],
                &mut ws.tc[l][..dirs * h],
                &mut ws.ta,
            );
        }
        let h = self.head.n_in;
        let w = &self.params[self.head_offset()..self.head_offset() + h];
        let top = &ws.th[self.layers.len() - 1];
        for (z, dh) in ws.tz[..dirs].iter_mut().zip(top.chunks_exact(h)) {
            *z = dot(w, dh);
        }
    }
}

/// Interleaves `u`, `y` and `e` into `x` = (u₀, y₀, e₀, u₁, y₁, e₁, …).
pub(crate) fn fill_window(x: &mut [f64], u: &[f64], y: &[f64], e: &[f64]) {
    for (((step, &ui), &yi), &ei) in x.chunks_exact_mut(FEATURES).zip(u).zip(y).zip(e) {
        step[0] = ui;
        step[1] = yi;
        step[2] = ei;
    }
}

/// Fully connected net 3 → h (sigmoid) → h (sigmoid) → 1 (linear): the
/// combiner M_A.
///
/// ```text
/// z₁ = σ(W₁·x + b₁),  z₂ = σ(W₂·z₁ + b₂),  ŷ = w₃·z₂ + b₃
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    layers: [Dense; 3],
    params: Vec<f64>,
}

/// Forward/backward workspace of an [`Mlp`].
#[derive(Debug, Clone)]
pub struct MlpWorkspace {
    pub(crate) x: [f64; COMBINER_INPUTS],
    z1: Vec<f64>,
    z2: Vec<f64>,
    d1: Vec<f64>,
    d2: Vec<f64>,
    pub(crate) dx: [f64; COMBINER_INPUTS],
}

impl Mlp {
    /// Hidden size `hidden` in both layers; Glorot-uniform weights from `seed`.
    ///
    /// # Panics
    /// If `hidden` is not in 1..=[`MAX_HIDDEN`].
    pub fn new(hidden: usize, seed: u64) -> Mlp {
        assert!(
            (1..=MAX_HIDDEN).contains(&hidden),
            "MLP hidden size must be in 1..={MAX_HIDDEN}, found {hidden}"
        );
        let layers = [
            Dense {
                n_in: COMBINER_INPUTS,
                n_out: hidden,
            },
            Dense {
                n_in: hidden,
                n_out: hidden,
            },
            Dense {
                n_in: hidden,
                n_out: 1,
            },
        ];
        let n = layers.iter().map(Dense::n_params).sum();
        let mut mlp = Mlp {
            layers,
            params: vec![0.0; n],
        };
        let mut draw = uniform_draw(seed);
        let mut offset = 0;
        for layer in &mlp.layers {
            layer.init(
                &mut mlp.params[offset..offset + layer.n_params()],
                &mut draw,
            );
            offset += layer.n_params();
        }
        mlp
    }

    pub fn hidden(&self) -> usize {
        self.layers[0].n_out
    }

    pub fn n_params(&self) -> usize {
        self.params.len()
    }

    pub fn params(&self) -> &[f64] {
        &self.params
    }

    pub fn set_params(&mut self, params: &[f64]) -> Result<(), ParamLengthError> {
        set_checked(&mut self.params, params)
    }

    pub(crate) fn params_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }

    pub fn workspace(&self) -> MlpWorkspace {
        let h = self.hidden();
        MlpWorkspace {
            x: [0.0; COMBINER_INPUTS],
            z1: vec![0.0; h],
            z2: vec![0.0; h],
            d1: vec![0.0; h],
            d2: vec![0.0; h],
            dx: [0.0; COMBINER_INPUTS],
        }
    }

    fn offsets(&self) -> [usize; 4] {
        let a = self.layers[0].n_params();
        let b = a + self.layers[1].n_params();
        [0, a, b, b + self.layers[2].n_params()]
    }

    /// ŷ for the inputs `x`.
    pub fn predict(&self, ws: &mut MlpWorkspace, x: [f64; COMBINER_INPUTS]) -> f64 {
        ws.x = x;
        self.forward(ws)
    }

    /// Forward pass on `ws.x`.
    pub(crate) fn forward(&self, ws: &mut MlpWorkspace) -> f64 {
        let o = self.offsets();
        let p = &self.params;
        self.layers[0].forward(&p[o[0]..o[1]], &ws.x, &mut ws.z1);
        ws.z1.iter_mut().for_each(|v| *v = sigmoid(*v));
        self.layers[1].forward(&p[o[1]..o[2]], &ws.z1, &mut ws.z2);
        ws.z2.iter_mut().for_each(|v| *v = sigmoid(*v));
        let mut out = [0.0];
        self.layers[2].forward(&p[o[2]..o[3]], &ws.z2, &mut out);
        out[0]
    }

    /// Backward pass after [`forward`](Self::forward) for `dout` = ∂L/∂ŷ: adds
    /// ∂L/∂θ to `grad` when given and writes ∂L/∂x into `ws.dx`
    /// (σ' = σ(1 − σ) at each hidden unit).
    pub(crate) fn backward(&self, ws: &mut MlpWorkspace, dout: f64, mut grad: Option<&mut [f64]>) {
        let o = self.offsets();
        let p = &self.params;
        let (g0, g1, g2) = match grad.take() {
            Some(g) => {
                let (g0, rest) = g.split_at_mut(o[1]);
                let (g1, g2) = rest.split_at_mut(o[2] - o[1]);
                (Some(g0), Some(g1), Some(g2))
            }
            None => (None, None, None),
        };
        self.layers[2].backward(&p[o[2]..o[3]], &ws.z2, &[dout], g2, Some(&mut ws.d2[..]));
        for (d, z) in ws.d2.iter_mut().zip(&ws.z2) {
            *d *= z * (1.0 - z);
        }
        self.layers[1].backward(&p[o[1]..o[2]], &ws.z1, &ws.d2, g1, Some(&mut ws.d1[..]));
        for (d, z) in ws.d1.iter_mut().zip(&ws.z1) {
            *d *= z * (1.0 - z);
        }
        self.layers[0].backward(&p[o[0]..o[1]], &ws.x, &ws.d1, g0, Some(&mut ws.dx[..]));
    }
}

/// The two-layer model: sub-models M1–M3 each predict ȳ_next from the same
/// window, the combiner M_A maps their three predictions to the final ȳ_next.
#[derive(Debug, Clone, PartialEq)]
pub struct TwoLayerNet {
    pub sub_models: [SequenceNet; 3],
    pub combiner: Mlp,
}

/// One prediction model: the single (benchmark) LSTM or the two-layer model.
#[derive(Debug, Clone, PartialEq)]
pub enum Surrogate {
    Single(SequenceNet),
    TwoLayer(TwoLayerNet),
}

impl Surrogate {
    /// The parameter count, each sequence network's counted by `per_net`.
    fn count(&self, per_net: fn(&SequenceNet) -> usize) -> usize {
        match self {
            Surrogate::Single(net) => per_net(net),
            Surrogate::TwoLayer(m) => {
                m.sub_models.iter().map(per_net).sum::<usize>() + m.combiner.n_params()
            }
        }
    }

    pub fn n_params(&self) -> usize {
        self.count(SequenceNet::n_params)
    }

    /// The parameter count of this architecture before ET0 (model files of
    /// version 1).
    pub fn legacy_n_params(&self) -> usize {
        self.count(SequenceNet::legacy_n_params)
    }

    /// Sets the parameters from those of the same architecture without the
    /// ET0 input (see [`SequenceNet::params_from_legacy`]).
    pub fn set_legacy_params(&mut self, legacy: &[f64]) -> Result<(), ParamLengthError> {
        let expected = self.legacy_n_params();
        ParamLengthError::check(expected, legacy.len())?;
        let mut widened = Vec::with_capacity(self.n_params());
        match self {
            Surrogate::Single(net) => widened = net.params_from_legacy(legacy)?,
            Surrogate::TwoLayer(m) => {
                let mut offset = 0;
                for s in &m.sub_models {
                    let n = s.legacy_n_params();
                    widened.extend(s.params_from_legacy(&legacy[offset..offset + n])?);
                    offset += n;
                }
                widened.extend_from_slice(&legacy[offset..]);
            }
        }
        self.set_params(&widened)
    }

    /// All parameters, concatenated (two-layer: M1, M2, M3, M_A).
    pub fn params(&self) -> Vec<f64> {
        match self {
            Surrogate::Single(net) => net.params().to_vec(),
            Surrogate::TwoLayer(m) => {
                let mut p = Vec::with_capacity(self.n_params());
                for s in &m.sub_models {
                    p.extend_from_slice(s.params());
                }
                p.extend_from_slice(m.combiner.params());
                p
            }
        }
    }

    /// Sets all parameters from the concatenation [`params`](Self::params) returns.
    pub fn set_params(&mut self, params: &[f64]) -> Result<(), ParamLengthError> {
        let expected = self.n_params();
        ParamLengthError::check(expected, params.len())?;
        match self {
            Surrogate::Single(net) => net.set_params(params),
            Surrogate::TwoLayer(m) => {
                let mut offset = 0;
                for s in &mut m.sub_models {
                    let n = s.n_params();
                    s.set_params(&params[offset..offset + n])?;
                    offset += n;
                }
                m.combiner.set_params(&params[offset..])
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A window of plausible scaled values, deterministic in `seed`.
    pub(crate) fn random_window(seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut draw = uniform_draw(seed);
        let u = (0..WINDOW).map(|_| draw()).collect();
        let y = (0..WINDOW).map(|_| 0.2 + 0.6 * draw()).collect();
        let e = (0..WINDOW).map(|_| 2.0 * draw()).collect();
        (u, y, e)
    }

    /// Parameters perturbed away from the initialisation so that no gradient
    /// is trivially zero (biases especially).
    pub(crate) fn jiggle(p: &mut [f64], seed: u64, size: f64) {
        let mut draw = uniform_draw(seed);
        for v in p {
            *v += size * (2.0 * draw() - 1.0);
        }
    }

    fn check_sequence_gradients(hidden: &[usize]) {
        let mut net = SequenceNet::new(hidden, 7);
        let mut p = net.params().to_vec();
        jiggle(&mut p, 8, 0.3);
        net.set_params(&p).unwrap();
        let (u, y, e) = random_window(9);
        let mut ws = net.workspace();
        // loss L = ŷ²/2 so that dL/dŷ = ŷ
        let out = net.predict(&mut ws, &u, &y, &e);
        let mut grad = vec![0.0; net.n_params()];
        net.backward(&mut ws, out, Some(&mut grad), true);
        let dx = ws.dx.clone();
        let loss = |net: &SequenceNet, u: &[f64], y: &[f64], e: &[f64]| {
            let mut ws = net.workspace();
            let o = net.predict(&mut ws, u, y, e);
            0.5 * o * o
        };
        let eps = 1e-6;
        let mut worst: f64 = 0.0;
        for (k, &gk) in grad.iter().enumerate() {
            let mut plus = net.clone();
            plus.params_mut()[k] += eps;
            let mut minus = net.clone();
            minus.params_mut()[k] -= eps;
            let fd = (loss(&plus, &u, &y, &e) - loss(&minus, &u, &y, &e)) / (2.0 * eps);
            let err = (fd - gk).abs() / (fd.abs().max(gk.abs()).max(1e-3));
            worst = worst.max(err);
            assert!(err < 1e-5, "param {k}: fd {fd} vs {}", gk);
        }
        // Input gradients: ∂L/∂x = ŷ·∂ŷ/∂x.
        for tau in 0..WINDOW {
            for f in 0..FEATURES {
                let mut plus = [u.clone(), y.clone(), e.clone()];
                let mut minus = plus.clone();
                plus[f][tau] += eps;
                minus[f][tau] -= eps;
                let fd = (loss(&net, &plus[0], &plus[1], &plus[2])
                    - loss(&net, &minus[0], &minus[1], &minus[2]))
                    / (2.0 * eps);
                let a = dx[tau * FEATURES + f];
                let err = (fd - a).abs() / fd.abs().max(a.abs()).max(1e-3);
                assert!(err < 1e-5, "x[{tau}][{f}]: fd {fd} vs {a}");
            }
        }
        // the gradient is not trivially small
        assert!(grad.iter().map(|g| g.abs()).fold(0.0, f64::max) > 1e-3);
        assert!(worst < 1e-5);
    }

    #[test]
    fn one_layer_lstm_gradients_match_finite_differences() {
        check_sequence_gradients(&[4]);
    }

    #[test]
    fn two_layer_lstm_gradients_match_finite_differences() {
        check_sequence_gradients(&[3, 5]);
    }

    /// Outputs at several steps of a longer sequence (fixed inputs): the
    /// gradient of L = Σₜ wₜ·ŷₜ²/2 against finite differences.
    #[test]
    fn sequence_gradients_with_outputs_at_many_steps_match_finite_differences() {
        let steps = WINDOW + 6;
        let mut net = SequenceNet::new(&[3, 4], 17);
        let mut p = net.params().to_vec();
        jiggle(&mut p, 18, 0.3);
        net.set_params(&p).unwrap();
        let mut draw = uniform_draw(19);
        let x: Vec<f64> = (0..steps * FEATURES).map(|_| draw()).collect();
        let weights: Vec<f64> = (0..steps)
            .map(|t| {
                if t >= WINDOW - 1 {
                    1.0 + t as f64 / 10.0
                } else {
                    0.0
                }
            })
            .collect();
        let loss_and_dout = |net: &SequenceNet, ws: &mut SequenceWorkspace| {
            ws.ensure_steps(steps);
            ws.x[..steps * FEATURES].copy_from_slice(&x);
            net.advance(ws, 0, steps);
            let mut loss = 0.0;
            for (t, &w) in weights.iter().enumerate() {
                let o = net.output(ws, t);
                loss += 0.5 * w * o * o;
                ws.dout[t] = w * o;
            }
            loss
        };
        let mut ws = net.workspace();
        loss_and_dout(&net, &mut ws);
        let mut grad = vec![0.0; net.n_params()];
        net.backward_sequence(&mut ws, steps, Some(&mut grad), true);
        let eps = 1e-6;
        for (k, &gk) in grad.iter().enumerate() {
            let mut plus = net.clone();
            plus.params_mut()[k] += eps;
            let mut minus = net.clone();
            minus.params_mut()[k] -= eps;
            let fd = (loss_and_dout(&plus, &mut plus.workspace())
                - loss_and_dout(&minus, &mut minus.workspace()))
                / (2.0 * eps);
            let err = (fd - gk).abs() / (fd.abs().max(gk.abs()).max(1e-3));
            assert!(err < 1e-5, "param {k}: fd {fd} vs {gk}");
        }
        assert!(grad.iter().map(|g| g.abs()).fold(0.0, f64::max) > 1e-3);
    }

    #[test]
    fn mlp_gradients_match_finite_differences() {
        let mut mlp = Mlp::new(4, 3);
        let mut p = mlp.params().to_vec();
        jiggle(&mut p, 4, 0.3);
        mlp.set_params(&p).unwrap();
        let x = [0.3, 0.7, -0.2];
        let mut ws = mlp.workspace();
        let out = mlp.predict(&mut ws, x);
        let mut grad = vec![0.0; mlp.n_params()];
        mlp.backward(&mut ws, out, Some(&mut grad));
        let loss = |m: &Mlp, x: [f64; 3]| {
            let o = m.predict(&mut m.workspace(), x);
            0.5 * o * o
        };
        let eps = 1e-6;
        for (k, &gk) in grad.iter().enumerate() {
            let mut plus = mlp.clone();
            plus.params_mut()[k] += eps;
            let mut minus = mlp.clone();
            minus.params_mut()[k] -= eps;
            let fd = (loss(&plus, x) - loss(&minus, x)) / (2.0 * eps);
            let err = (fd - gk).abs() / fd.abs().max(gk.abs()).max(1e-3);
            assert!(err < 1e-5, "param {k}: fd {fd} vs {}", gk);
        }
        for i in 0..3 {
            let (mut xp, mut xm) = (x, x);
            xp[i] += eps;
            xm[i] -= eps;
            let fd = (loss(&mlp, xp) - loss(&mlp, xm)) / (2.0 * eps);
            let err = (fd - ws.dx[i]).abs() / fd.abs().max(1e-3);
            assert!(err < 1e-5, "x[{i}]: fd {fd} vs {}", ws.dx[i]);
        }
    }

    #[test]
    fn forward_matches_a_hand_computed_one_unit_lstm() {
        // 1 layer, hidden 1: set every weight by hand and recompute.
        let mut net = SequenceNet::new(&[1], 0);
        // layout: Wᵀ (3 rows × 4), Uᵀ (1 × 4), b (4), head w (1), head b (1)
        let wt = [
            0.5, -0.3, 0.8, 0.1, 0.2, 0.4, -0.6, 0.7, -0.4, 0.3, 0.2, -0.1,
        ];
        let ut = [0.3, -0.2, 0.5, 0.9];
        let b = [0.1, 1.0, -0.1, 0.0];
        let mut p = Vec::new();
        p.extend_from_slice(&wt);
        p.extend_from_slice(&ut);
        p.extend_from_slice(&b);
        p.extend_from_slice(&[1.5, -0.25]);
        net.set_params(&p).unwrap();
        let (u, y, e) = random_window(1);
        let s = |x: f64| 1.0 / (1.0 + (-x).exp());
        let (mut h, mut c) = (0.0, 0.0);
        for t in 0..WINDOW {
            let a =
                |g: usize| wt[g] * u[t] + wt[4 + g] * y[t] + wt[8 + g] * e[t] + ut[g] * h + b[g];
            let (i, f, g, o) = (s(a(0)), s(a(1)), a(2).tanh(), s(a(3)));
            c = f * c + i * g;
            h = o * c.tanh();
        }
        let expected = 1.5 * h - 0.25;
        let got = net.predict(&mut net.workspace(), &u, &y, &e);
        assert!((got - expected).abs() < 1e-14, "{got} vs {expected}");
    }

    #[test]
    fn a_network_widened_from_one_without_et0_predicts_as_it_did_for_any_et0() {
        for hidden in [&[3][..], &[4, 2]] {
            // the old network: the same weights with ē's input row left out
            let mut net = SequenceNet::new(hidden, 3);
            let mut p = net.params().to_vec();
            jiggle(&mut p, 4, 0.3);
            net.set_params(&p).unwrap();
            let row = 4 * hidden[0];
            let mut legacy = p[..2 * row].to_vec();
            legacy.extend_from_slice(&p[3 * row..]);
            assert_eq!(legacy.len(), net.legacy_n_params());
            let (u, y, e) = random_window(5);
            let mut old = net.clone();
            let mut zeroed = p.clone();
            zeroed[2 * row..3 * row].fill(0.0);
            old.set_params(&zeroed).unwrap();
            let widened = net.params_from_legacy(&legacy).unwrap();
            assert_eq!(widened, zeroed);
            let reference = old.predict(&mut old.workspace(), &u, &y, &[0.0; WINDOW]);
            let got = old.predict(&mut old.workspace(), &u, &y, &e);
            assert_eq!(got, reference, "ET0 changed a widened network's prediction");
            // and the ē row does matter once it is not zero
            let with_e = net.predict(&mut net.workspace(), &u, &y, &e);
            assert!((with_e - reference).abs() > 1e-6);
            assert!(net.params_from_legacy(&legacy[1..]).is_err());
        }
    }

    #[test]
    fn initialisation_is_seeded_and_sized() {
        let a = SequenceNet::new(&[16, 8], 5);
        // 4·16·(3+16+1) + 4·8·(16+8+1) + 9
        assert_eq!(a.n_params(), 1280 + 800 + 9);
        assert_eq!(a, SequenceNet::new(&[16, 8], 5));
        assert_ne!(a.params(), SequenceNet::new(&[16, 8], 6).params());
        // forget-gate biases start at 1, the others at 0
        let b = &a.params()[4 * 16 * 19..4 * 16 * 20];
        assert!(b[16..32].iter().all(|&v| v == 1.0));
        assert!(b[..16].iter().chain(&b[32..]).all(|&v| v == 0.0));
        assert_eq!(Mlp::new(8, 1).n_params(), 8 * 4 + 8 * 9 + 9);
        let mut m = Mlp::new(8, 1);
        assert_eq!(
            m.set_params(&[0.0; 3]),
            Err(ParamLengthError {
                expected: 113,
                found: 3
            })
        );
    }
}
