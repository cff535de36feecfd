//! LSTM layer kernels on a flat parameter slice.
//!
//! For input xₜ (n_in) and hidden size h, one step is
//!
//! ```text
//! aₜ = W·xₜ + U·hₜ₋₁ + b                       (4h pre-activations)
//! iₜ = σ(a_i), fₜ = σ(a_f), gₜ = tanh(a_g), oₜ = σ(a_o)
//! cₜ = fₜ ⊙ cₜ₋₁ + iₜ ⊙ gₜ
//! hₜ = oₜ ⊙ tanh(cₜ)
//! ```
//!
//! with h₋₁ = c₋₁ = 0 (every window starts from rest). The gates are stacked
//! in the order i, f, g, o (rows `0..h`, `h..2h`, `2h..3h`, `3h..4h`).
//!
//! Parameter layout of one layer (n_in inputs, h hidden), chosen so that the
//! forward step is a sequence of contiguous `a += column·scalar` updates:
//!
//! * `Wᵀ`: n_in rows of 4h, `W[r][c]` at `c·4h + r`;
//! * `Uᵀ`: h rows of 4h, `U[r][c]` at `4h·n_in + c·4h + r`;
//! * `b`: 4h, at `4h·(n_in + h)`.

use super::dense::{add_matvec_cols, axpy, dot, sigmoid, tanh};

/// Shape of one LSTM layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Lstm {
    pub n_in: usize,
    pub hidden: usize,
}

/// What the backward pass needs from the forward pass over a sequence of
/// `steps` inputs, plus the scratch of the backward pass. Allocated once, reused.
#[derive(Debug, Clone)]
pub(crate) struct LstmTape {
    /// Activated gates (i, f, g, o) per step: steps × 4h.
    gates: Vec<f64>,
    /// Cell states per step: steps × h.
    c: Vec<f64>,
    /// tanh(cₜ) per step: steps × h.
    tanh_c: Vec<f64>,
    /// Hidden states per step: steps × h (the layer's output sequence).
    pub h: Vec<f64>,
    /// Backward scratch: ∂L/∂aₜ (4h), ∂L/∂cₜ carried back (h), ∂L/∂hₜ₋₁ (h).
    da: Vec<f64>,
    dc: Vec<f64>,
    dh: Vec<f64>,
}

impl LstmTape {
    /// Grows the tape to hold at least `steps` steps (never shrinks).
    pub fn ensure(&mut self, steps: usize, hidden: usize) {
        if self.h.len() < steps * hidden {
            self.gates.resize(steps * 4 * hidden, 0.0);
            self.c.resize(steps * hidden, 0.0);
            self.tanh_c.resize(steps * hidden, 0.0);
            self.h.resize(steps * hidden, 0.0);
        }
    }
}

impl Lstm {
    pub fn n_params(&self) -> usize {
        4 * self.hidden * (self.n_in + self.hidden + 1)
    }

    /// Glorot-uniform W (fan n_in + 4h) and U (fan h + 4h), zero biases except
    /// the forget gate's, which start at 1 (the usual "remember by default").
    pub fn init(&self, p: &mut [f64], draw: &mut impl FnMut() -> f64) {
        let g = 4 * self.hidden;
        let (w, rest) = p.split_at_mut(g * self.n_in);
        let (u, b) = rest.split_at_mut(g * self.hidden);
        let limit_w = (6.0 / (self.n_in + g) as f64).sqrt();
        let limit_u = (6.0 / (self.hidden + g) as f64).sqrt();
        for v in w {
            *v = limit_w * (2.0 * draw() - 1.0);
        }
        for v in u {
            *v = limit_u * (2.0 * draw() - 1.0);
        }
        b.fill(0.0);
        b[self.hidden..2 * self.hidden].fill(1.0);
    }

    pub fn tape(&self, steps: usize) -> LstmTape {
        let h = self.hidden;
        LstmTape {
            gates: vec![0.0; steps * 4 * h],
            c: vec![0.0; steps * h],
            tanh_c: vec![0.0; steps * h],
            h: vec![0.0; steps * h],
            da: vec![0.0; 4 * h],
            dc: vec![0.0; h],
            dh: vec![0.0; h],
        }
    }

    fn split<'p>(&self, p: &'p [f64]) -> (&'p [f64], &'p [f64], &'p [f64]) {
        let g = 4 * self.hidden;
        let (w, rest) = p.split_at(g * self.n_in);
        let (u, b) = rest.split_at(g * self.hidden);
        (w, u, b)
    }

    /// On x86-64 CPUs with AVX2 the same code is run compiled for AVX2 (no FMA
    /// contraction: the results are bitwise those of the baseline build).
    ///
    /// Steps `from..to` of the forward pass, `x` holding the inputs of every
    /// step from 0 (row per step); the tape must hold steps `0..from` already.
    /// This is how a sequence is continued one step at a time.
    pub fn forward_range(&self, p: &[f64], x: &[f64], tape: &mut LstmTape, from: usize, to: usize) {
        tape.ensure(to, self.hidden);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is available on this CPU (checked just above).
            unsafe { self.forward_avx2(p, x, tape, from, to) };
            return;
        }
        self.forward_impl(p, x, tape, from, to);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn forward_avx2(&self, p: &[f64], x: &[f64], tape: &mut LstmTape, from: usize, to: usize) {
        self.forward_impl(p, x, tape, from, to);
    }

    #[inline(always)]
    fn forward_impl(&self, p: &[f64], x: &[f64], tape: &mut LstmTape, from: usize, to: usize) {
        let h = self.hidden;
        let g = 4 * h;
        let (wt, ut, b) = self.split(p);
        for t in from..to {
            let xt = &x[t * self.n_in..(t + 1) * self.n_in];
            let (h_done, h_rest) = tape.h.split_at_mut(t * h);
            let h_prev = if t > 0 {
                &h_done[(t - 1) * h..]
            } else {
                &[][..]
            };
            let a = &mut tape.gates[t * g..(t + 1) * g];
            // a = b + Σ_c W[:, c]·x[c] + Σ_c U[:, c]·h_prev[c]
            a.copy_from_slice(b);
            add_matvec_cols(a, wt, xt);
            add_matvec_cols(a, ut, h_prev);
            // activate in place: [i f] σ, [g] tanh, [o] σ (vectorisable loops)
            let (aif, rest) = a.split_at_mut(2 * h);
            let (ag, ao) = rest.split_at_mut(h);
            aif.iter_mut().for_each(|v| *v = sigmoid(*v));
            ag.iter_mut().for_each(|v| *v = tanh(*v));
            ao.iter_mut().for_each(|v| *v = sigmoid(*v));
            let (ai, af) = aif.split_at(h);
            let (c_done, c_rest) = tape.c.split_at_mut(t * h);
            let c_now = &mut c_rest[..h];
            if t > 0 {
                let c_prev = &c_done[(t - 1) * h..];
                for k in 0..h {
                    c_now[k] = af[k] * c_prev[k] + ai[k] * ag[k];
                }
            } else {
                for k in 0..h {
                    c_now[k] = ai[k] * ag[k];
                }
            }
            let tc = &mut tape.tanh_c[t * h..(t + 1) * h];
            let h_now = &mut h_rest[..h];
            for k in 0..h {
                tc[k] = tanh(c_now[k]);
                h_now[k] = ao[k] * tc[k];
            }
        }
    }

    /// Forward-mode derivatives through step `t` (after the forward pass
    /// reached `t`), for `dirs` directions at once, direction-major:
    ///
    /// * `dx`: the input tangents ∂xₜ (dirs × n_in);
    /// * `dh`, `dc`: on entry ∂hₜ₋₁, ∂cₜ₋₁, on exit ∂hₜ, ∂cₜ (dirs × h);
    /// * `da`: scratch of 4h.
    ///
    /// ```text
    /// ∂a = W·∂x + U·∂hₜ₋₁
    /// ∂i = i(1−i)∂a_i, ∂f = f(1−f)∂a_f, ∂g = (1−g²)∂a_g, ∂o = o(1−o)∂a_o
    /// ∂c = ∂f·cₜ₋₁ + f·∂cₜ₋₁ + ∂i·g + i·∂g
    /// ∂h = ∂o·tanh(c) + o·(1 − tanh²c)·∂c
    /// ```
    #[allow(clippy::too_many_arguments)]
    pub fn tangent_step(
        &self,
        p: &[f64],
        tape: &LstmTape,
        t: usize,
        dirs: usize,
        dx: &[f64],
        dh: &mut [f64],
        dc: &mut [f64],
        da: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is available on this CPU (checked just above).
            unsafe { self.tangent_avx2(p, tape, t, dirs, dx, dh, dc, da) };
            return;
        }
        self.tangent_impl(p, tape, t, dirs, dx, dh, dc, da);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    fn tangent_avx2(
        &self,
        p: &[f64],
        tape: &LstmTape,
        t: usize,
        dirs: usize,
        dx: &[f64],
        dh: &mut [f64],
        dc: &mut [f64],
        da: &mut [f64],
    ) {
        self.tangent_impl(p, tape, t, dirs, dx, dh, dc, da);
    }

    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn tangent_impl(
        &self,
        p: &[f64],
        tape: &LstmTape,
        t: usize,
        dirs: usize,
        dx: &[f64],
        dh: &mut [f64],
        dc: &mut [f64],
        da: &mut [f64],
    ) {
        let h = self.hidden;
        let g = 4 * h;
        let (wt, ut, _) = self.split(p);
        let gt = &tape.gates[t * g..(t + 1) * g];
        let tc = &tape.tanh_c[t * h..(t + 1) * h];
        let (i, rest) = gt.split_at(h);
        let (f, rest) = rest.split_at(h);
        let (gg, o) = rest.split_at(h);
        let zeros = [0.0; 0];
        let c_prev = if t > 0 {
            &tape.c[(t - 1) * h..t * h]
        } else {
            &zeros[..]
        };
        for d in 0..dirs {
            let da = &mut da[..g];
            da.fill(0.0);
            add_matvec_cols(da, wt, &dx[d * self.n_in..(d + 1) * self.n_in]);
            let dhd = &mut dh[d * h..(d + 1) * h];
            let dcd = &mut dc[d * h..(d + 1) * h];
            add_matvec_cols(da, ut, dhd);
            for k in 0..h {
                let di = i[k] * (1.0 - i[k]) * da[k];
                let df = f[k] * (1.0 - f[k]) * da[h + k];
                let dg = (1.0 - gg[k] * gg[k]) * da[2 * h + k];
                let dov = o[k] * (1.0 - o[k]) * da[3 * h + k];
                let cp = if t > 0 { c_prev[k] } else { 0.0 };
                let c_new = df * cp + f[k] * dcd[k] + di * gg[k] + i[k] * dg;
                dcd[k] = c_new;
                dhd[k] = dov * tc[k] + o[k] * (1.0 - tc[k] * tc[k]) * c_new;
            }
        }
    }

    /// Backpropagation through time after [`forward`](Self::forward) on the
    /// same `x`.
    ///
    /// `dh_out` holds ∂L/∂hₜ from above for every step (steps × h). Going back
    /// in time with δhₜ = dh_outₜ + Uᵀ·δaₜ₊₁ and δcₜ = δhₜ⊙oₜ⊙(1 − tanh²cₜ) + δcₜ₊₁⊙fₜ₊₁:
    ///
    /// ```text
    /// δa_i = δc⊙g⊙i(1−i)    δa_f = δc⊙cₜ₋₁⊙f(1−f)
    /// δa_g = δc⊙i⊙(1−g²)    δa_o = δh⊙tanh(cₜ)⊙o(1−o)
    /// ∂L/∂W += δaₜ·xₜᵀ, ∂L/∂U += δaₜ·hₜ₋₁ᵀ, ∂L/∂b += δaₜ   (into `grad`, if given)
    /// ∂L/∂xₜ = Wᵀ·δaₜ                                     (into `dx`, overwritten, if given)
    /// ```
    pub fn backward(
        &self,
        p: &[f64],
        x: &[f64],
        dh_out: &[f64],
        tape: &mut LstmTape,
        grad: Option<&mut [f64]>,
        dx: Option<&mut [f64]>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is available on this CPU (checked just above).
            unsafe { self.backward_avx2(p, x, dh_out, tape, grad, dx) };
            return;
        }
        self.backward_impl(p, x, dh_out, tape, grad, dx);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn backward_avx2(
        &self,
        p: &[f64],
        x: &[f64],
        dh_out: &[f64],
        tape: &mut LstmTape,
        grad: Option<&mut [f64]>,
        dx: Option<&mut [f64]>,
    ) {
        self.backward_impl(p, x, dh_out, tape, grad, dx);
    }

    #[inline(always)]
    fn backward_impl(
        &self,
        p: &[f64],
        x: &[f64],
        dh_out: &[f64],
        tape: &mut LstmTape,
        mut grad: Option<&mut [f64]>,
        mut dx: Option<&mut [f64]>,
    ) {
        let h = self.hidden;
        let g = 4 * h;
        let n_in = self.n_in;
        let (wt, ut, _) = self.split(p);
        let steps = x.len() / n_in;
        let LstmTape {
            gates,
            c,
            tanh_c,
            h: hs,
            da,
            dc,
            dh,
        } = tape;
        dc.fill(0.0);
        dh.fill(0.0);
        for t in (0..steps).rev() {
            let gt = &gates[t * g..(t + 1) * g];
            let tc = &tanh_c[t * h..(t + 1) * h];
            let dho = &dh_out[t * h..(t + 1) * h];
            for k in 0..h {
                let (i, f, gg, o) = (gt[k], gt[h + k], gt[2 * h + k], gt[3 * h + k]);
                let dhk = dho[k] + dh[k];
                let th = tc[k];
                let dck = dhk * o * (1.0 - th * th) + dc[k];
                let c_prev = if t > 0 { c[(t - 1) * h + k] } else { 0.0 };
                da[k] = dck * gg * i * (1.0 - i);
                da[h + k] = dck * c_prev * f * (1.0 - f);
                da[2 * h + k] = dck * i * (1.0 - gg * gg);
                da[3 * h + k] = dhk * th * o * (1.0 - o);
                dc[k] = dck * f;
            }
            let xt = &x[t * n_in..(t + 1) * n_in];
            if let Some(gr) = grad.as_deref_mut() {
                let (gw, rest) = gr.split_at_mut(g * n_in);
                let (gu, gb) = rest.split_at_mut(g * h);
                for (col, &xc) in gw.chunks_exact_mut(g).zip(xt) {
                    axpy(col, xc, da);
                }
                if t > 0 {
                    let h_prev = &hs[(t - 1) * h..t * h];
                    for (col, &hc) in gu.chunks_exact_mut(g).zip(h_prev) {
                        axpy(col, hc, da);
                    }
                }
                axpy(gb, 1.0, da);
            }
            if let Some(dx) = dx.as_deref_mut() {
                for (d, col) in dx[t * n_in..(t + 1) * n_in]
                    .iter_mut()
                    .zip(wt.chunks_exact(g))
                {
                    *d = dot(col, da);
                }
            }
            if t > 0 {
                for (d, col) in dh.iter_mut().zip(ut.chunks_exact(g)) {
                    *d = dot(col, da);
                }
            }
        }
    }
}
