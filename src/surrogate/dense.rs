//! Dense (fully connected) layer kernels on a flat parameter slice.
//!
//! Layout of a layer n_in → n_out inside its slice: the weights W row-major
//! (`W[r][c]` at `r·n_in + c`), then the biases b (n_out).

/// Shape of a dense layer y = W·x + b.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Dense {
    pub n_in: usize,
    pub n_out: usize,
}

impl Dense {
    pub fn n_params(&self) -> usize {
        self.n_out * (self.n_in + 1)
    }

    /// Glorot-uniform weights, U(−√(6/(n_in + n_out)), +√(6/(n_in + n_out))),
    /// zero biases. `draw()` yields uniform numbers in [0, 1).
    pub fn init(&self, p: &mut [f64], draw: &mut impl FnMut() -> f64) {
        let limit = (6.0 / (self.n_in + self.n_out) as f64).sqrt();
        let (w, b) = p.split_at_mut(self.n_in * self.n_out);
        for v in w {
            *v = limit * (2.0 * draw() - 1.0);
        }
        b.fill(0.0);
    }

    /// y = W·x + b.
    pub fn forward(&self, p: &[f64], x: &[f64], y: &mut [f64]) {
        let (w, b) = p.split_at(self.n_in * self.n_out);
        for ((yr, row), br) in y.iter_mut().zip(w.chunks_exact(self.n_in)).zip(b) {
            *yr = br + dot(row, x);
        }
    }

    /// Backward pass for the upstream gradient dy = ∂L/∂y:
    /// ∂L/∂W += dy·xᵀ, ∂L/∂b += dy (into `grad` when given) and
    /// dx = Wᵀ·dy (overwriting `dx` when given).
    pub fn backward(
        &self,
        p: &[f64],
        x: &[f64],
        dy: &[f64],
        grad: Option<&mut [f64]>,
        dx: Option<&mut [f64]>,
    ) {
        let (w, _) = p.split_at(self.n_in * self.n_out);
        if let Some(g) = grad {
            let (gw, gb) = g.split_at_mut(self.n_in * self.n_out);
            for ((row, gbr), &d) in gw.chunks_exact_mut(self.n_in).zip(gb).zip(dy) {
                axpy(row, d, x);
                *gbr += d;
            }
        }
        if let Some(dx) = dx {
            dx.fill(0.0);
            for (row, &d) in w.chunks_exact(self.n_in).zip(dy) {
                axpy(dx, d, row);
            }
        }
    }
}

/// y += a·x (element-wise over the shorter length).
#[inline(always)]
pub(crate) fn axpy(y: &mut [f64], a: f64, x: &[f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += a * xi;
    }
}

/// Σ xᵢ·yᵢ with four independent partial sums (so that the loop vectorises).
#[inline(always)]
pub(crate) fn dot(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().min(y.len());
    let (x, y) = (&x[..n], &y[..n]);
    let mut acc = [0.0; 4];
    let mut xc = x.chunks_exact(4);
    let mut yc = y.chunks_exact(4);
    for (a, b) in (&mut xc).zip(&mut yc) {
        for k in 0..4 {
            acc[k] += a[k] * b[k];
        }
    }
    let mut s = (acc[0] + acc[2]) + (acc[1] + acc[3]);
    for (a, b) in xc.remainder().iter().zip(yc.remainder()) {
        s += a * b;
    }
    s
}

/// a += Σ_c M[:, c]·v[c], where M's columns (each `a.len()` long) are stored
/// one after another in `cols`. Blocked over 8 rows so that the partial sums
/// stay in registers; every aᵢ still receives its terms in column order.
#[inline(always)]
pub(crate) fn add_matvec_cols(a: &mut [f64], cols: &[f64], v: &[f64]) {
    const B: usize = 8;
    let n = a.len();
    let mut blocks = a.chunks_exact_mut(B);
    let mut r0 = 0;
    for block in &mut blocks {
        let mut acc = [0.0; B];
        acc.copy_from_slice(block);
        for (col, &vc) in cols.chunks_exact(n).zip(v) {
            let col = &col[r0..r0 + B];
            for i in 0..B {
                acc[i] += col[i] * vc;
            }
        }
        block.copy_from_slice(&acc);
        r0 += B;
    }
    let rest = blocks.into_remainder();
    if !rest.is_empty() {
        for (col, &vc) in cols.chunks_exact(n).zip(v) {
            axpy(rest, vc, &col[r0..]);
        }
    }
}

/// e^x, branch-free so that loops over it vectorise; x is clamped to
/// [−708, 708]. x = k·ln 2 + r with |r| ≤ ln 2/2 (k by the 1.5·2⁵² rounding
/// trick, ln 2 split in two for an exact k·ln2_hi), e^r by its degree-13
/// Taylor polynomial (truncation < 1e-17), 2^k written into the exponent bits.
/// Relative error a few units in the last place.
#[inline(always)]
pub(crate) fn exp(x: f64) -> f64 {
    const SHIFTER: f64 = 6_755_399_441_055_744.0; // 1.5·2⁵²
    const LN2_HI: f64 = 0.693_147_180_369_123_8;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    // 1/n! for n = 13 down to 2
    const C: [f64; 12] = [
        1.0 / 6_227_020_800.0,
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
    ];
    let x = x.clamp(-708.0, 708.0);
    let t = x * std::f64::consts::LOG2_E + SHIFTER;
    let k = t - SHIFTER;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let mut p = C[0];
    for c in &C[1..] {
        p = p * r + c;
    }
    p = p * r + 1.0;
    p = p * r + 1.0;
    // t's mantissa holds 2⁵¹ + k: the integer k + 1023 shifted into the exponent
    let bits = (t.to_bits().wrapping_sub(SHIFTER.to_bits()))
        .wrapping_add(1023)
        .wrapping_shl(52);
    p * f64::from_bits(bits)
}

/// Logistic sigmoid σ(x) = 1/(1 + e^(−x)).
#[inline(always)]
pub(crate) fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + exp(-x))
}

/// tanh x = 1 − 2/(e^(2x) + 1) (absolute error ~1e-16).
#[inline(always)]
pub(crate) fn tanh(x: f64) -> f64 {
    1.0 - 2.0 / (exp(2.0 * x) + 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_forward_and_backward_by_hand() {
        let layer = Dense { n_in: 2, n_out: 2 };
        // W = [[1, 2], [3, 4]], b = [0.5, -1]
        let p = [1.0, 2.0, 3.0, 4.0, 0.5, -1.0];
        let mut y = [0.0; 2];
        layer.forward(&p, &[1.0, -1.0], &mut y);
        assert_eq!(y, [-0.5, -2.0]);
        let mut g = [0.0; 6];
        let mut dx = [0.0; 2];
        layer.backward(&p, &[1.0, -1.0], &[2.0, 1.0], Some(&mut g), Some(&mut dx));
        assert_eq!(g, [2.0, -2.0, 1.0, -1.0, 2.0, 1.0]);
        assert_eq!(dx, [5.0, 8.0]);
    }

    #[test]
    fn fast_exp_sigmoid_and_tanh_match_the_standard_library() {
        for i in -4000..=4000 {
            let x = i as f64 * 0.1 + 0.0123;
            let (a, b) = (exp(x), x.exp());
            assert!((a - b).abs() <= 4e-16 * b, "exp({x}): {a} vs {b}");
            let s = 1.0 / (1.0 + (-x).exp());
            assert!((sigmoid(x) - s).abs() <= 4e-16 * s.max(1e-300), "σ({x})");
            assert!((tanh(x) - x.tanh()).abs() <= 4e-16, "tanh({x})");
        }
        assert!((exp(-1000.0) / (-708f64).exp() - 1.0).abs() < 1e-15);
        assert!(exp(1000.0).is_finite());
        assert_eq!(tanh(-400.0), -1.0);
        assert_eq!(tanh(400.0), 1.0);
    }

    #[test]
    fn blocked_matvec_equals_column_axpys() {
        for n in [4, 8, 12, 20, 128] {
            let cols: Vec<f64> = (0..n * 3).map(|i| (i as f64 * 0.37).sin()).collect();
            let v = [0.5, -1.25, 2.0];
            let mut a: Vec<f64> = (0..n).map(|i| i as f64).collect();
            let mut b = a.clone();
            add_matvec_cols(&mut a, &cols, &v);
            for (c, &vc) in v.iter().enumerate() {
                axpy(&mut b, vc, &cols[c * n..(c + 1) * n]);
            }
            assert_eq!(a, b);
        }
    }

    #[test]
    fn dot_handles_remainders() {
        let x: Vec<f64> = (0..7).map(f64::from).collect();
        assert_eq!(dot(&x, &x), 91.0);
    }
}
