//! The EDBN's RBM training ([`super::edbn`], persistent contrastive
//! divergence with the hybrid discriminative term) in `f32`, with the
//! network stored as `f64` before and after.
//!
//! # What is computed
//!
//! The algorithm of [`super::edbn`]'s module docs, minibatch by minibatch,
//! unchanged: the positive statistics `Σ_rows h vᵀ` with `h = p(h | v)` of
//! the data, one Gibbs step of every persistent chain (sample `h ~ p(h |
//! v)`, `v ~ p(v | h)` with the labels' softmax group, then `p(h | v)`), the
//! negative statistics from the chains, the top RBM's discriminative
//! gradient `∇ log p(y | x)`, and the momentum update `Δ ← mom·Δ + lr (g /
//! m − l2·W)`, `W ← W + Δ`, with the learning rate's linear decay.
//! Every value of the training (weights, gradients, activities, samples'
//! uniforms) is an `f32`; the weights are read from and written back to the
//! `f64` [`Rbm`] (exactly: every `f32` is an `f64`), so inference, saved
//! models and the layer above's mean-field inputs are as before.
//!
//! # Why `f32`
//!
//! Training is the EDBN's cost: ~0.3 s a `benches/peers` fold in `f64`
//! (against scikit-learn's RBM stack at ~0.63 s on the same host), spent on
//! small products (minibatches of 20 rows, 80 x 60 and 77 x 30 weights),
//! ~1 M sigmoids, ~35 M label-posterior terms and ~10 M uniforms a fit. In
//! `f32` a vector holds twice the values, the division of the posterior's
//! sigmoids and the uniforms (24 bits from a 32-bit word, half the random
//! stream) cost half, and the products are laid out so that each output
//! sums its terms sequentially with the outputs across the lanes (no
//! per-entry horizontal sums, which the `f64` kernels' fixed four-way
//! split needed). `f32` is what RBMs are usually trained in: the
//! gradient's own noise (one Gibbs sample a chain) is orders of magnitude
//! above `f32`'s rounding. It changes every EDBN figure in its digits (a
//! different rounding and random stream, not a different method);
//! RESULTS.md says what moved.
//!
//! Measured on 2026-12-06 22:46 (AMD EPYC, 2 cores, load ~1.1,
//! `benches/peers/run.sh --seed 1 -- --skip-encoder`, best wall sample per
//! call): the fit 138 ms against scikit-learn's 585 ms (4.24x; it was
//! 2.0-2.3x in `f64` on every host measured), the prediction (also in
//! `f32` up to the posterior, `Forward`) 0.77 ms against 3.00 ms (3.89x);
//! frame accuracy 0.469 against the `f64` training's 0.477 and
//! scikit-learn's 0.234 on the same arrays.
//!
//! # Layout and order (the same bits on every CPU)
//!
//! Hidden units are padded to a multiple of [`LANES`] (`nhp`), visible
//! units too (`nvp`). The weights are kept both as `Wᵀ` (`n_vis x nhp`,
//! the products `b + W v` and the statistics) and as `W` (`n_hid x nvp`,
//! the chains' `a + Wᵀ h`), the second copied from the first after each
//! update. A product adds its terms to its bias in input order, each term
//! fused (`s ← fma(x_i, w_i, s)`), skipping zero inputs (the spike counts'
//! zeros, and the chains' binary samples'), across the lanes; padding
//! lanes are zeroed after each activation so they never feed a real unit.
//! Sums over the hidden units (the posterior's free energies) run lane by
//! lane over the chunks, then over the 16 lanes in a fixed tree.
//! Only IEEE operations and fused multiply-adds: the loops run inside
//! [`crate::wide::with_avx2`] (AVX-512, AVX2 or the baseline), and every
//! path rounds the same (test `every_path_trains_the_same_bits`).
//!
//! # Functions
//!
//! `e^x` ([`exp_neg`], for `x ≤ 0`): Cody-Waite reduction `x = k ln 2 +
//! r`, Cephes' degree-7 polynomial for `e^r`, `2^k` from the exponent
//! bits; `x` is floored at `−87` (`e^−87 ≈ 1.6e-38`, the last normal
//! values), so `σ(z)` of `|z| > 87` is that far from 0 or 1, not closer.
//! Within 2 ulp of `exp` (test). `σ(z) = num / (1 + e)` with `e =
//! e^{−|z|}` (`num = 1` for `z ≥ 0`, `e` below): never overflows.
//! `softplus(o) = max(o, 0) + log1p(e^{−|o|})`, `log1p(e) = e·P(e)` on `[0,
//! 1]` with `P` the degree-9 Chebyshev interpolant of `log1p(e)/e` (about 1
//! ulp in `f32`; test).

use super::edbn::{EdbnConfig, Rbm};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Lanes the hidden and visible widths are padded to (one AVX-512 `f32`
/// vector).
pub(crate) const LANES: usize = 16;

/// Vectors on which each layer-epoch's reconstruction error is logged
/// (as the `f64` trainer did).
const RECON_SAMPLE: usize = 256;

/// `n` rounded up to a multiple of [`LANES`].
pub(super) fn padded(n: usize) -> usize {
    n.div_ceil(LANES) * LANES
}

/// `1.5·2^23`: adding it rounds an `f32` below `2^22` in magnitude to an
/// integer (ties to even), which subtracting it recovers exactly.
const SHIFT: f32 = 12_582_912.0;
/// `ln 2`'s leading bits (Cephes' `C1`): `k·LN2_HI` is exact for `|k| ≤ 2^8`.
const LN2_HI: f32 = 0.693_359_4;
/// `ln 2 − LN2_HI`.
const LN2_LO: f32 = -2.121_944_4e-4;
/// Floor of [`exp_neg`]'s argument: `2^k` stays normal.
const X_FLOOR: f32 = -87.0;

/// `e^x` for `x ≤ 0` (module docs); `x` below `−87` gives `e^−87`, NaN
/// gives NaN.
#[inline(always)]
pub(crate) fn exp_neg(x: f32) -> f32 {
    let x = x.clamp(X_FLOOR, 0.0);
    let k = x.mul_add(std::f32::consts::LOG2_E, SHIFT) - SHIFT;
    let r = (-k).mul_add(LN2_LO, (-k).mul_add(LN2_HI, x));
    let r2 = r * r;
    let mut p = 1.987_569_2e-4f32;
    p = p.mul_add(r, 1.398_199_9e-3);
    p = p.mul_add(r, 8.333_452e-3);
    p = p.mul_add(r, 4.166_579_6e-2);
    p = p.mul_add(r, 1.666_666_5e-1);
    p = p.mul_add(r, 0.5);
    let er = r2.mul_add(p, r) + 1.0;
    // k in [−126, 0]: 2^k is the normal float with exponent field
    // k + 127, which `k + 127 + 1.5·2^23` holds in its low bits (an
    // integer conversion would saturate, lane by lane).
    let scale = f32::from_bits((k + (SHIFT + 127.0)).to_bits() << 23);
    er * scale
}

/// `σ(z) = 1 / (1 + e^{−z})`, as `num / (1 + e)` with `e = e^{−|z|}`.
#[inline(always)]
pub(crate) fn sigmoid(z: f32) -> f32 {
    let e = exp_neg(-z.abs());
    let num = if z >= 0.0 { 1.0 } else { e };
    num / (1.0 + e)
}

/// `log1p(e)` for `e` in `[0, 1]`: `e·P(e)` (module docs).
#[inline(always)]
fn log1p_unit(e: f32) -> f32 {
    let mut p = -3.176_057e-3f32;
    p = p.mul_add(e, 1.954_252_6e-2);
    p = p.mul_add(e, -5.637_361e-2);
    p = p.mul_add(e, 1.054_362_4e-1);
    p = p.mul_add(e, -1.526_966_7e-1);
    p = p.mul_add(e, 1.966_327_4e-1);
    p = p.mul_add(e, -2.495_161_6e-1);
    p = p.mul_add(e, 3.332_971e-1);
    p = p.mul_add(e, -4.999_989_3e-1);
    p = p.mul_add(e, 1.0);
    e * p
}

/// `σ(o)` and `softplus(o) = ln(1 + e^o)` from one exponential.
#[inline(always)]
fn sigmoid_softplus(o: f32) -> (f32, f32) {
    let e = exp_neg(-o.abs());
    let num = if o >= 0.0 { 1.0 } else { e };
    (num / (1.0 + e), o.max(0.0) + log1p_unit(e))
}

/// Sum of a lane-padded row (`v.len()` a multiple of [`LANES`]) in a
/// fixed order: lane by lane over the chunks, then the 16 lanes as a tree.
#[inline(always)]
fn lane_sum(v: &[f32]) -> f32 {
    let mut acc = [0.0f32; LANES];
    for chunk in v.chunks_exact(LANES) {
        for (a, &x) in acc.iter_mut().zip(chunk) {
            *a += x;
        }
    }
    let mut w = LANES / 2;
    while w > 0 {
        for l in 0..w {
            acc[l] += acc[l + w];
        }
        w /= 2;
    }
    acc[0]
}

/// `σ` over a slice, then its lanes from `n` on set to 0.
#[inline(always)]
fn sigmoid_row(v: &mut [f32], n: usize) {
    for z in v.iter_mut() {
        *z = sigmoid(*z);
    }
    let from = n.min(v.len());
    for z in v[from..].iter_mut() {
        *z = 0.0;
    }
}

/// `v ← softmax(v)`: `e^{v − max v}`, each over their sum in order.
#[inline(always)]
fn softmax(v: &mut [f32]) {
    let mut top = f32::NEG_INFINITY;
    for &x in v.iter() {
        top = top.max(x);
    }
    let mut sum = 0.0f32;
    for z in v.iter_mut() {
        *z = exp_neg(*z - top);
        sum += *z;
    }
    for z in v.iter_mut() {
        *z /= sum;
    }
}

/// `out ← out + x·w` lane by lane, fused.
#[inline(always)]
fn axpy(out: &mut [f32], x: f32, w: &[f32]) {
    for (o, &w) in out.iter_mut().zip(w) {
        *o = x.mul_add(w, *o);
    }
}

/// Uniform draws on `[0, 1)`: the top 24 bits of each 32-bit word of the
/// stream times `2^−24`.
#[derive(Default)]
struct Uniforms {
    bits: Vec<u32>,
    u: Vec<f32>,
}

impl Uniforms {
    /// The next `n` uniforms of `rng`.
    fn draw(&mut self, rng: &mut ChaCha8Rng, n: usize) -> &[f32] {
        const SCALE: f32 = 1.0 / (1u32 << 24) as f32;
        self.bits.resize(n, 0);
        rng.fill(&mut self.bits[..n]);
        self.u.resize(n, 0.0);
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                for (u, &b) in self.u.iter_mut().zip(&self.bits) {
                    *u = SCALE * (b >> 8) as f32;
                }
            },
        );
        &self.u[..n]
    }
}

/// Appends the positions of `row`'s nonzero values to `out`, in order: a
/// mask of each chunk's nonzeros (a vector comparison), then its bits.
#[inline(always)]
pub(super) fn push_nonzeros(row: &[f32], out: &mut Vec<u32>) {
    let chunks = row.chunks_exact(LANES);
    let rest = chunks.remainder();
    let mut push = |base: usize, mut mask: u32| {
        while mask != 0 {
            out.push(base as u32 + mask.trailing_zeros());
            mask &= mask - 1;
        }
    };
    for (c, chunk) in chunks.enumerate() {
        // A whole chunk of fixed width: one vector comparison.
        let chunk: &[f32; LANES] = chunk.try_into().unwrap_or(&[0.0; LANES]);
        let mut mask = 0u32;
        for (l, &x) in chunk.iter().enumerate() {
            mask |= u32::from(x != 0.0) << l;
        }
        push(c * LANES, mask);
    }
    let mut mask = 0u32;
    for (l, &x) in rest.iter().enumerate() {
        mask |= u32::from(x != 0.0) << l;
    }
    push(row.len() - rest.len(), mask);
}

/// `dst ← srcᵀ` for `src` `rows x cols` (both multiples of 8), row-major.
/// With AVX2, 8 x 8 blocks transposed in registers (unpacks, shuffles and
/// lane swaps: 24 instructions a block against 64 scalar loads and
/// stores); the values are moved, not computed, so every path agrees.
fn transpose(src: &[f32], rows: usize, cols: usize, dst: &mut [f32]) {
    assert!(
        rows.is_multiple_of(8)
            && cols.is_multiple_of(8)
            && src.len() >= rows * cols
            && dst.len() >= rows * cols
    );
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        // SAFETY: the CPU has AVX2 (checked); the sizes are asserted above.
        unsafe { x86::transpose8(src, rows, cols, dst) };
        return;
    }
    for (i, row) in src.chunks_exact(cols).take(rows).enumerate() {
        for (j, &v) in row.iter().enumerate() {
            dst[j * rows + i] = v;
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// [`super::transpose`] by 8 x 8 blocks.
    ///
    /// # Safety
    /// The CPU must have AVX2; `rows` and `cols` multiples of 8 with
    /// `src` and `dst` holding `rows · cols` values (the caller asserts).
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn transpose8(src: &[f32], rows: usize, cols: usize, dst: &mut [f32]) {
        let (s, d) = (src.as_ptr(), dst.as_mut_ptr());
        for i0 in (0..rows).step_by(8) {
            for j0 in (0..cols).step_by(8) {
                // SAFETY: rows i0..i0 + 8 < rows, columns j0..j0 + 8 < cols of
                // src, and the transposed block of dst (caller's sizes).
                unsafe {
                    let r: [__m256; 8] =
                        std::array::from_fn(|q| _mm256_loadu_ps(s.add((i0 + q) * cols + j0)));
                    let o = crate::wide::transpose8_ps(r);
                    for (q, &v) in o.iter().enumerate() {
                        _mm256_storeu_ps(d.add((j0 + q) * rows + i0), v);
                    }
                }
            }
        }
    }
}

/// Rows of `n` values with, when sparse, each row's nonzero positions.
struct Rows {
    /// Values, `width` apart.
    x: Vec<f32>,
    width: usize,
    /// Row `r`'s nonzero positions are `idx[start[r]..start[r + 1]]`;
    /// empty `start` = dense rows (every position is read).
    start: Vec<usize>,
    idx: Vec<u32>,
}

impl Rows {
    /// Rows of `data` (`n` wide) in `f32`, `width ≥ n` apart (zero padded).
    fn new(data: &[f64], n: usize, width: usize, sparse: bool) -> Self {
        let rows = data.len() / n.max(1);
        let mut x = vec![0.0f32; rows * width];
        for (o, d) in x.chunks_exact_mut(width.max(1)).zip(data.chunks_exact(n.max(1))) {
            for (o, &d) in o.iter_mut().zip(d) {
                *o = d as f32;
            }
        }
        let mut r = Rows {
            x,
            width,
            start: Vec::new(),
            idx: Vec::new(),
        };
        if sparse {
            r.index(n);
        }
        r
    }

    /// Rebuilds every row's nonzero positions among its first `n`.
    #[inline(always)]
    fn index(&mut self, n: usize) {
        self.start.clear();
        self.idx.clear();
        self.start.push(0);
        for row in self.x.chunks_exact(self.width.max(1)) {
            push_nonzeros(&row[..n], &mut self.idx);
            self.start.push(self.idx.len());
        }
    }

    fn row(&self, r: usize) -> &[f32] {
        &self.x[r * self.width..(r + 1) * self.width]
    }
}

/// `out ← bias + Σ_i x_i w_i` over the positions `idx` of `x` (all of the
/// first `n` when `idx` is `None`), `w` rows `out.len()` wide (a multiple
/// of [`LANES`]): each output adds its terms to its bias in input order,
/// fused, with up to four vectors of outputs held in registers while the
/// terms pass. The order depends only on the terms visited, so a row gives
/// the same bits alone or in any batch, on every path. (Splitting each
/// output into interleaved partial sums, for more independent chains, was
/// tried: no faster on the EDBN's shapes.)
#[inline(always)]
fn product(x: &[f32], idx: Option<&[u32]>, n: usize, w: &[f32], bias: &[f32], out: &mut [f32]) {
    let width = out.len();
    let mut c0 = 0;
    while c0 < width {
        let vecs = ((width - c0) / LANES).min(4);
        match vecs {
            4 => product_block::<4>(x, idx, n, w, width, c0, bias, out),
            3 => product_block::<3>(x, idx, n, w, width, c0, bias, out),
            2 => product_block::<2>(x, idx, n, w, width, c0, bias, out),
            _ => product_block::<1>(x, idx, n, w, width, c0, bias, out),
        }
        c0 += vecs.max(1) * LANES;
    }
}

/// `acc ← acc + x·row` lane by lane, fused.
#[inline(always)]
pub(super) fn fma_row<const V: usize>(acc: &mut [[f32; LANES]; V], x: f32, row: &[f32]) {
    for (a, r) in acc.iter_mut().zip(row.chunks_exact(LANES)) {
        for (a, &r) in a.iter_mut().zip(r) {
            *a = x.mul_add(r, *a);
        }
    }
}

/// [`product`]'s outputs `c0 .. c0 + V·LANES`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn product_block<const V: usize>(
    x: &[f32],
    idx: Option<&[u32]>,
    n: usize,
    w: &[f32],
    width: usize,
    c0: usize,
    bias: &[f32],
    out: &mut [f32],
) {
    let mut acc = [[0.0f32; LANES]; V];
    for (q, a) in acc.iter_mut().enumerate() {
        a.copy_from_slice(&bias[c0 + q * LANES..c0 + (q + 1) * LANES]);
    }
    let at = |i: usize| i * width + c0;
    // (Helper functions, not closures, do the arithmetic: a closure called
    // from two places may be left out of line, compiled without FMA, where
    // `mul_add` becomes a library call.)
    match idx {
        Some(idx) => {
            for &i in idx {
                let i = i as usize;
                fma_row(&mut acc, x[i], &w[at(i)..at(i) + V * LANES]);
            }
        }
        None => {
            for (i, &xi) in x[..n].iter().enumerate() {
                fma_row(&mut acc, xi, &w[at(i)..at(i) + V * LANES]);
            }
        }
    }
    for (q, a) in acc.iter().enumerate() {
        out[c0 + q * LANES..c0 + (q + 1) * LANES].copy_from_slice(a);
    }
}

/// [`product`] over every input (no list) of two rows `x0`, `x1` at once,
/// into `out0`, `out1`: each row's terms in the order [`product`] adds
/// them, so the bits of two calls, with twice the independent chains
/// (a row alone waits on each fused add's latency: its 32 outputs are two
/// AVX-512 or four AVX2 vectors, against the two or four adds a cycle the
/// core could start).
#[inline(always)]
fn product2(x0: &[f32], x1: &[f32], n: usize, w: &[f32], bias: &[f32], out0: &mut [f32], out1: &mut [f32]) {
    let width = out0.len();
    let mut c0 = 0;
    while c0 < width {
        let vecs = ((width - c0) / LANES).min(2);
        match vecs {
            2 => product_block2::<2>(x0, x1, n, w, width, c0, bias, out0, out1),
            _ => product_block2::<1>(x0, x1, n, w, width, c0, bias, out0, out1),
        }
        c0 += vecs.max(1) * LANES;
    }
}

/// [`product2`]'s outputs `c0 .. c0 + V·LANES`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn product_block2<const V: usize>(
    x0: &[f32],
    x1: &[f32],
    n: usize,
    w: &[f32],
    width: usize,
    c0: usize,
    bias: &[f32],
    out0: &mut [f32],
    out1: &mut [f32],
) {
    let mut acc0 = [[0.0f32; LANES]; V];
    for (q, a) in acc0.iter_mut().enumerate() {
        a.copy_from_slice(&bias[c0 + q * LANES..c0 + (q + 1) * LANES]);
    }
    let mut acc1 = acc0;
    for (i, (&a, &b)) in x0[..n].iter().zip(&x1[..n]).enumerate() {
        let row = &w[i * width + c0..i * width + c0 + V * LANES];
        fma_row(&mut acc0, a, row);
        fma_row(&mut acc1, b, row);
    }
    for (q, (a, b)) in acc0.iter().zip(&acc1).enumerate() {
        out0[c0 + q * LANES..c0 + (q + 1) * LANES].copy_from_slice(a);
        out1[c0 + q * LANES..c0 + (q + 1) * LANES].copy_from_slice(b);
    }
}

/// One RBM in training: `f32` weights both ways round, biases, and the
/// minibatch's buffers.
struct Trainer {
    nv: usize,
    nh: usize,
    k: usize,
    nb: usize,
    nvp: usize,
    nhp: usize,
    /// `Wᵀ`, `nvp x nhp` (padding rows and columns 0).
    wt: Vec<f32>,
    /// `W`, `nhp x nvp` (copied from `wt`).
    w: Vec<f32>,
    /// Visible biases, `nvp`.
    a: Vec<f32>,
    /// Hidden biases, `nhp`.
    b: Vec<f32>,
    /// Gradients, shaped as the parameters.
    gt: Vec<f32>,
    ga: Vec<f32>,
    gb: Vec<f32>,
    /// Momentum terms, shaped as the parameters.
    vt: Vec<f32>,
    va: Vec<f32>,
    vb: Vec<f32>,
    /// One row's hidden activities (`nhp`), and the discriminative
    /// scratch: per label the sigmoids of `o_jy` (`k x nhp`), the softplus
    /// values (`nhp`), the free energies and the posterior (`k`), and the
    /// hidden gradient (`nhp`).
    h: Vec<f32>,
    sig: Vec<f32>,
    sp: Vec<f32>,
    p: Vec<f32>,
    g: Vec<f32>,
    /// 1 in the hidden lanes that are units, 0 in the padding (`nhp`).
    live: Vec<f32>,
}

impl Trainer {
    fn new(rbm: &Rbm) -> Self {
        let (nv, nh, k) = (rbm.n_vis, rbm.n_hid, rbm.labels);
        let (nvp, nhp) = (padded(nv), padded(nh));
        let wt = weights_t(rbm, nv, nvp);
        let (a, b) = (padded_f32(&rbm.a, nvp), padded_f32(&rbm.b, nhp));
        let mut t = Trainer {
            nv,
            nh,
            k,
            nb: nv - k,
            nvp,
            nhp,
            wt,
            w: vec![0.0; nhp * nvp],
            a,
            b,
            gt: vec![0.0; nvp * nhp],
            ga: vec![0.0; nvp],
            gb: vec![0.0; nhp],
            vt: vec![0.0; nvp * nhp],
            va: vec![0.0; nvp],
            vb: vec![0.0; nhp],
            h: vec![0.0; nhp],
            sig: vec![0.0; k * nhp],
            sp: vec![0.0; nhp],
            p: vec![0.0; k],
            g: vec![0.0; nhp],
            live: (0..nhp).map(|j| f32::from(u8::from(j < nh))).collect(),
        };
        t.copy_w();
        t
    }

    /// `W` from `Wᵀ`.
    #[inline(always)]
    fn copy_w(&mut self) {
        transpose(&self.wt, self.nvp, self.nhp, &mut self.w);
    }

    /// Writes the weights back into `rbm` (exactly: `f32` values).
    fn store(&self, rbm: &mut Rbm) {
        let (nv, nhp) = (self.nv, self.nhp);
        for j in 0..self.nh {
            for i in 0..nv {
                rbm.w[j * nv + i] = f64::from(self.wt[i * nhp + j]);
            }
        }
        for (o, &v) in rbm.a.iter_mut().zip(&self.a) {
            *o = f64::from(v);
        }
        for (o, &v) in rbm.b.iter_mut().zip(&self.b) {
            *o = f64::from(v);
        }
    }

    /// Visible net inputs to probabilities in place: sigmoids of the data
    /// units, a softmax over the labels, padding zeroed.
    #[inline(always)]
    fn vis_activate(&self, v: &mut [f32]) {
        let nb = self.nb;
        for z in v[..nb].iter_mut() {
            *z = sigmoid(*z);
        }
        if self.k > 0 {
            softmax(&mut v[nb..self.nv]);
        }
        for z in v[self.nv..].iter_mut() {
            *z = 0.0;
        }
    }

    /// Samples visible probabilities `v` in place: a Bernoulli draw per data
    /// unit (`u` per unit), and one label from the softmax group with the
    /// next uniform (inverse CDF).
    #[inline(always)]
    fn sample_vis(&self, v: &mut [f32], u: &[f32]) {
        let nb = self.nb;
        for (p, &u) in v[..nb].iter_mut().zip(u) {
            *p = f32::from(u8::from(u < *p));
        }
        if self.k > 0 {
            let u = u[nb];
            let mut acc = 0.0f32;
            let mut pick = self.k - 1;
            for (c, &q) in v[nb..self.nv].iter().enumerate() {
                acc += q;
                if u < acc {
                    pick = c;
                    break;
                }
            }
            for (c, x) in v[nb..self.nv].iter_mut().enumerate() {
                *x = f32::from(u8::from(c == pick));
            }
        }
    }

    /// Uniforms a visible sample takes.
    fn vis_draws(&self) -> usize {
        self.nb + usize::from(self.k > 0)
    }

    /// The top RBM's row `x` (data part; label `y`) with data net inputs
    /// `base` (`b + W_data x`, `nhp`): the sigmoids of every label's
    /// hidden inputs into `self.sig`, the label posterior into `self.p`,
    /// and `weight ·` the gradient of `log p(y | x)` added to the
    /// gradients; the row's positive hidden activities `σ(base + U_y)`
    /// left in `self.h`.
    #[inline(always)]
    fn discriminative(&mut self, x: &[f32], y: usize, base: &[f32], weight: f32) {
        let (nb, nhp, k) = (self.nb, self.nhp, self.k);
        // Free energy of each label: c_y + Σ_j softplus(base_j + U_jy).
        for c in 0..k {
            let u = &self.wt[(nb + c) * nhp..(nb + c + 1) * nhp];
            let sig = &mut self.sig[c * nhp..(c + 1) * nhp];
            // Padding lanes (live 0) hold 0 in both.
            for ((((s, sp), &bj), &uj), &live) in sig
                .iter_mut()
                .zip(self.sp.iter_mut())
                .zip(base)
                .zip(u)
                .zip(&self.live)
            {
                let (sj, spj) = sigmoid_softplus(bj + uj);
                (*s, *sp) = (live * sj, live * spj);
            }
            self.p[c] = self.a[nb + c] + lane_sum(&self.sp);
        }
        softmax(&mut self.p);
        // g_j = σ_jy − Σ_c p_c σ_jc, and the label weights' factors.
        let sig_y = &self.sig[y * nhp..(y + 1) * nhp];
        self.h.copy_from_slice(sig_y);
        for g in self.g.iter_mut() {
            *g = 0.0;
        }
        for (c, &pc) in self.p.iter().enumerate() {
            axpy(&mut self.g, pc, &self.sig[c * nhp..(c + 1) * nhp]);
        }
        // g ← weight (σ_y − Σ p σ): the hidden gradient; then + h, the
        // positive statistics, which share every data column's product.
        for (g, &s) in self.g.iter_mut().zip(sig_y) {
            *g = weight * (s - *g);
        }
        for c in 0..k {
            let wd = weight * (f32::from(u8::from(c == y)) - self.p[c]);
            axpy(
                &mut self.gt[(nb + c) * nhp..(nb + c + 1) * nhp],
                wd,
                &self.sig[c * nhp..(c + 1) * nhp],
            );
            self.ga[nb + c] += wd;
        }
        let (g, h) = (&mut self.g, &self.h);
        for (g, &h) in g.iter_mut().zip(h) {
            *g += h;
        }
        // Data columns: + x_i (h + weight g); the label column y: + h.
        for (i, &xi) in x[..nb].iter().enumerate() {
            if xi != 0.0 {
                axpy(&mut self.gt[i * nhp..(i + 1) * nhp], xi, &self.g);
            }
        }
        axpy(&mut self.gt[(nb + y) * nhp..(nb + y + 1) * nhp], 1.0, &self.h);
        for (b, &g) in self.gb.iter_mut().zip(&self.g) {
            *b += g;
        }
        for (a, &x) in self.ga[..nb].iter_mut().zip(x) {
            *a += x;
        }
        self.ga[nb + y] += 1.0;
    }

    /// Adds `scale ·` one row's statistics (`x` visible, `self.h` hidden)
    /// to the gradients.
    #[inline(always)]
    fn add_stats(&mut self, x: &[f32], idx: Option<&[u32]>, scale: f32) {
        let nhp = self.nhp;
        let h = &self.h;
        match idx {
            Some(idx) => {
                for &i in idx {
                    let i = i as usize;
                    axpy(&mut self.gt[i * nhp..(i + 1) * nhp], scale * x[i], h);
                }
            }
            None => {
                for (i, &xi) in x[..self.nv].iter().enumerate() {
                    axpy(&mut self.gt[i * nhp..(i + 1) * nhp], scale * xi, h);
                }
            }
        }
        for (b, &h) in self.gb.iter_mut().zip(h) {
            *b = scale.mul_add(h, *b);
        }
        for (a, &x) in self.ga[..self.nv].iter_mut().zip(x) {
            *a = scale.mul_add(x, *a);
        }
    }
}

/// One layer of mean-field inference in `f32`: `σ(b + W x)` (or `b + W x`
/// for the top RBM's data columns), with `Wᵀ` laid out as in training
/// (`n_in x nhp`, outputs across the lanes) and the inputs' zeros skipped.
/// Built from the `f64` [`Rbm`], whose weights an `f32` training left
/// `f32`-valued, so nothing is rounded.
#[derive(Clone, Debug)]
pub(super) struct Forward {
    wt: Vec<f32>,
    b: Vec<f32>,
    n_in: usize,
    nh: usize,
    nhp: usize,
    sigmoid: bool,
    /// Visit only the nonzero inputs (the first layer's spike counts); the
    /// layers above read every input (mean-field activities: no zeros).
    skip_zeros: bool,
}

/// `rbm`'s weights of its first `n_in` visible units as `f32` `Wᵀ`: `rows`
/// rows (`n_in` and zero padding) of `padded(n_hid)` values, unit `j` of
/// input `i` at `i · padded(n_hid) + j`, the padding zero.
fn weights_t(rbm: &Rbm, n_in: usize, rows: usize) -> Vec<f32> {
    let (nh, nv, nhp) = (rbm.n_hid, rbm.n_vis, padded(rbm.n_hid));
    let mut wt = vec![0.0f32; rows * nhp];
    for j in 0..nh {
        for i in 0..n_in {
            wt[i * nhp + j] = rbm.w[j * nv + i] as f32;
        }
    }
    wt
}

/// `v` as `f32`, zero-padded to `len`.
pub(super) fn padded_f32(v: &[f64], len: usize) -> Vec<f32> {
    let mut o = vec![0.0f32; len];
    for (o, &v) in o.iter_mut().zip(v) {
        *o = v as f32;
    }
    o
}

impl Forward {
    /// The layer of `rbm`'s first `n_in` visible units (all but the labels
    /// for the top RBM); `sigmoid`: apply `σ` (false: the net inputs);
    /// `skip_zeros`: see the field.
    pub(super) fn new(rbm: &Rbm, n_in: usize, sigmoid: bool, skip_zeros: bool) -> Self {
        let (nh, nhp) = (rbm.n_hid, padded(rbm.n_hid));
        let (wt, b) = (weights_t(rbm, n_in, n_in), padded_f32(&rbm.b, nhp));
        Forward {
            wt,
            b,
            n_in,
            nh,
            nhp,
            sigmoid,
            skip_zeros,
        }
    }

    /// Output width (padded to the lanes).
    pub(super) fn width(&self) -> usize {
        self.nhp
    }

    /// Units.
    pub(super) fn units(&self) -> usize {
        self.nh
    }

    /// Inputs.
    pub(super) fn inputs(&self) -> usize {
        self.n_in
    }

    /// `out` (`nhp`) from the first `n_in` values of `x` (`nz` is scratch);
    /// padding lanes 0.
    #[inline(always)]
    pub(super) fn apply(&self, x: &[f32], nz: &mut Vec<u32>, out: &mut [f32]) {
        let idx = if self.skip_zeros {
            nz.clear();
            push_nonzeros(&x[..self.n_in], nz);
            Some(nz.as_slice())
        } else {
            None
        };
        product(x, idx, self.n_in, &self.wt, &self.b, &mut out[..self.nhp]);
        if self.sigmoid {
            sigmoid_row(&mut out[..self.nhp], self.nh);
        }
    }
}

impl Forward {
    /// [`Self::apply`] of two rows: a layer that reads every input takes
    /// them together ([`product2`], the same bits); one that skips zeros
    /// takes them one by one (their lists differ).
    #[inline(always)]
    fn apply2(&self, x0: &[f32], x1: &[f32], nz: &mut Vec<u32>, out0: &mut [f32], out1: &mut [f32]) {
        if self.skip_zeros {
            self.apply(x0, nz, out0);
            self.apply(x1, nz, out1);
            return;
        }
        let (o0, o1) = (&mut out0[..self.nhp], &mut out1[..self.nhp]);
        product2(x0, x1, self.n_in, &self.wt, &self.b, o0, o1);
        if self.sigmoid {
            sigmoid_row(o0, self.nh);
            sigmoid_row(o1, self.nh);
        }
    }
}

/// A chain of [`Forward`] layers over rows of `f64` inputs: the last
/// layer's outputs of every row, as `f64`, `out_width` apart.
///
/// Rows go two at a time through the layers that read every input
/// ([`Forward::apply2`]): the same bits as one by one (test
/// `forward_rows_pairs_are_the_bits_of_one_row`). The EDBN's prediction of
/// `benches/peers`' 3154 x 80 vectors (`RAYON_NUM_THREADS=1
/// target/release/examples/peers --out <dir> --seed 1 --only edbn`, two
/// runs each, 2026-12-07): 0.76-0.77 -> 0.62-0.63 ms with AVX-512, 0.85
/// -> 0.79-0.81 ms with `PALPATE_NO_AVX512=1`; per-frame scores
/// `cmp`-identical.
pub(super) fn forward_rows(layers: &[Forward], x: &[f64], out: &mut [f64], out_width: usize) {
    let Some(first) = layers.first() else {
        return;
    };
    let dim = first.inputs().max(1);
    let wide = layers
        .iter()
        .map(Forward::width)
        .max()
        .unwrap_or(0)
        .max(padded(dim));
    let mut a = vec![0.0f32; wide];
    let mut b = vec![0.0f32; wide];
    let (mut a1, mut b1) = (a.clone(), b.clone());
    let mut nz = Vec::with_capacity(wide);
    let ow = out_width.max(1);
    let last = layers.last().map_or(0, Forward::units);
    let rows = (x.len() / dim).min(out.len() / ow);
    // Two rows at a time ([`Forward::apply2`]: the same bits as one by
    // one), the last odd one alone.
    let pairs = rows / 2;
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for p in 0..pairs {
                let (r0, r1) = (
                    &x[2 * p * dim..(2 * p + 1) * dim],
                    &x[(2 * p + 1) * dim..(2 * p + 2) * dim],
                );
                a.iter_mut().zip(r0).for_each(|(a, &v)| *a = v as f32);
                a1.iter_mut().zip(r1).for_each(|(a, &v)| *a = v as f32);
                for layer in layers {
                    layer.apply2(&a, &a1, &mut nz, &mut b, &mut b1);
                    std::mem::swap(&mut a, &mut b);
                    std::mem::swap(&mut a1, &mut b1);
                }
                let (o0, o1) = out[2 * p * ow..(2 * p + 2) * ow].split_at_mut(ow);
                o0.iter_mut()
                    .zip(&a[..last])
                    .for_each(|(o, &v)| *o = f64::from(v));
                o1.iter_mut()
                    .zip(&a1[..last])
                    .for_each(|(o, &v)| *o = f64::from(v));
            }
        },
    );
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for (row, o) in x[2 * pairs * dim..rows * dim]
                .chunks_exact(dim)
                .zip(out[2 * pairs * ow..].chunks_exact_mut(ow))
            {
                for (a, &v) in a.iter_mut().zip(row) {
                    *a = v as f32;
                }
                for layer in layers {
                    layer.apply(&a, &mut nz, &mut b);
                    std::mem::swap(&mut a, &mut b);
                }
                for (o, &v) in o.iter_mut().zip(&a[..last]) {
                    *o = f64::from(v);
                }
            }
        },
    );
}

/// Trains `rbm` with PCD on the rows of `data` (each `rbm.n_vis` long; the
/// top RBM's rows end with their one-hot label) as [`super::edbn`]'s module
/// docs describe, in `f32` (module docs); `sparse`: the rows are mostly
/// zeros, and the products visit only their nonzero values. Returns the
/// reconstruction error after each epoch.
pub(super) fn train_pcd(
    rbm: &mut Rbm,
    data: &[f64],
    sparse: bool,
    cfg: &EdbnConfig,
    rng: &mut ChaCha8Rng,
) -> Vec<f64> {
    let mut t = Trainer::new(rbm);
    let errors = crate::wide::with_avx2(
        #[inline(always)]
        || run(&mut t, data, sparse, cfg, rng),
    );
    t.store(rbm);
    errors
}

/// [`train_pcd`]'s loop, compiled inside [`crate::wide::with_avx2`].
#[inline(always)]
fn run(t: &mut Trainer, data: &[f64], sparse: bool, cfg: &EdbnConfig, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let (nv, nh, nb, k, nvp, nhp) = (t.nv, t.nh, t.nb, t.k, t.nvp, t.nhp);
    let n = data.len() / nv.max(1);
    let rows = Rows::new(data, nv, nv, sparse);
    let bs = cfg.batch_size.min(n).max(1);
    let disc = k > 0 && cfg.discriminative > 0.0;
    let weight = cfg.discriminative as f32;
    let mut uni = Uniforms::default();
    // Persistent chains start at binarised random data vectors.
    let mut chains = Rows {
        x: vec![0.0; bs * nvp],
        width: nvp,
        start: Vec::new(),
        idx: Vec::new(),
    };
    for c in 0..bs {
        let i = rng.random_range(0..n);
        let v = &mut chains.x[c * nvp..(c + 1) * nvp];
        v[..nv].copy_from_slice(&rows.row(i)[..nv]);
        let u = uni.draw(rng, t.vis_draws());
        t.sample_vis(v, u);
    }
    chains.index(nv);
    // Each chain's hidden probabilities (`bs x nhp`), and its samples.
    let mut hc = vec![0.0f32; bs * nhp];
    let mut base = vec![0.0f32; nhp];
    // A chain's hidden units that fired.
    let mut ones: Vec<u32> = Vec::with_capacity(nh);
    let mut order: Vec<usize> = (0..n).collect();
    let mut errors = Vec::with_capacity(cfg.epochs);
    for epoch in 0..cfg.epochs {
        let lr = (cfg.learning_rate * (1.0 - 0.9 * epoch as f64 / cfg.epochs.max(1) as f64)) as f32;
        let mom: f32 = if epoch < 5 { 0.5 } else { 0.9 };
        let l2 = cfg.l2 as f32;
        rand::seq::SliceRandom::shuffle(order.as_mut_slice(), rng);
        for batch in order.chunks(bs) {
            for g in t.gt.iter_mut() {
                *g = 0.0;
            }
            for g in t.ga.iter_mut() {
                *g = 0.0;
            }
            for g in t.gb.iter_mut() {
                *g = 0.0;
            }
            // Positive phase, row by row.
            for &r in batch {
                let x = rows.row(r);
                let idx = (!rows.start.is_empty()).then(|| &rows.idx[rows.start[r]..rows.start[r + 1]]);
                if k > 0 {
                    // The data columns' net inputs, then the label's weights.
                    let y = x[nb..nv].iter().position(|&v| v > 0.5).unwrap_or(0);
                    let idx_data = idx.map(|ix| {
                        let end = ix.partition_point(|&i| (i as usize) < nb);
                        &ix[..end]
                    });
                    product(x, idx_data, nb, &t.wt, &t.b, &mut base);
                    if disc {
                        t.discriminative(x, y, &base, weight);
                        continue;
                    }
                    t.h.copy_from_slice(&base);
                    axpy(&mut t.h, 1.0, &t.wt[(nb + y) * nhp..(nb + y + 1) * nhp]);
                } else {
                    product(x, idx, nv, &t.wt, &t.b, &mut t.h);
                }
                sigmoid_row(&mut t.h, nh);
                t.add_stats(x, idx, 1.0);
            }
            // Negative phase: one Gibbs step of every chain.
            for c in 0..bs {
                let idx = &chains.idx[chains.start[c]..chains.start[c + 1]];
                let h = &mut hc[c * nhp..(c + 1) * nhp];
                product(chains.row(c), Some(idx), nv, &t.wt, &t.b, h);
                sigmoid_row(h, nh);
            }
            let u = uni.draw(rng, bs * nh);
            for (h, u) in hc.chunks_exact_mut(nhp).zip(u.chunks_exact(nh.max(1))) {
                for (h, &u) in h.iter_mut().zip(u) {
                    *h = f32::from(u8::from(u < *h));
                }
            }
            let draws = t.vis_draws();
            let u = uni.draw(rng, bs * draws);
            for (c, u) in u.chunks_exact(draws.max(1)).enumerate().take(bs) {
                let h = &hc[c * nhp..c * nhp + nh];
                ones.clear();
                push_nonzeros(h, &mut ones);
                let v = &mut chains.x[c * nvp..(c + 1) * nvp];
                product(h, Some(&ones), nh, &t.w, &t.a, v);
                t.vis_activate(v);
                t.sample_vis(v, u);
            }
            chains.index(nv);
            let scale = -(batch.len() as f32 / bs as f32);
            for c in 0..bs {
                let idx = &chains.idx[chains.start[c]..chains.start[c + 1]];
                product(chains.row(c), Some(idx), nv, &t.wt, &t.b, &mut t.h);
                sigmoid_row(&mut t.h, nh);
                t.add_stats(chains.row(c), Some(idx), scale);
            }
            // The update.
            let inv = 1.0 / batch.len() as f32;
            momentum_step(&mut t.wt, &mut t.vt, &t.gt, mom, lr, inv, l2);
            momentum_step(&mut t.a, &mut t.va, &t.ga, mom, lr, inv, 0.0);
            momentum_step(&mut t.b, &mut t.vb, &t.gb, mom, lr, inv, 0.0);
            t.copy_w();
        }
        errors.push(recon_error(t, &rows, n));
    }
    errors
}

/// `v ← mom·v + lr (g·inv − decay·w)`, `w ← w + v`, entry by entry.
#[inline(always)]
fn momentum_step(w: &mut [f32], v: &mut [f32], g: &[f32], mom: f32, lr: f32, inv: f32, decay: f32) {
    for ((w, v), &g) in w.iter_mut().zip(v.iter_mut()).zip(g) {
        *v = mom * *v + lr * (g * inv - decay * *w);
        *w += *v;
    }
}

/// Mean squared reconstruction error `‖v − p(v | p(h | v))‖² / n_vis` over
/// a fixed evenly spaced subset of at most [`RECON_SAMPLE`] rows.
#[inline(always)]
fn recon_error(t: &mut Trainer, rows: &Rows, n: usize) -> f64 {
    let (nv, nh, nvp) = (t.nv, t.nh, t.nvp);
    let m = n.min(RECON_SAMPLE);
    let mut v = vec![0.0f32; nvp];
    let mut err = 0.0f64;
    for s in 0..m {
        let r = s * n / m;
        let x = rows.row(r);
        let idx = (!rows.start.is_empty()).then(|| &rows.idx[rows.start[r]..rows.start[r + 1]]);
        product(x, idx, nv, &t.wt, &t.b, &mut t.h);
        sigmoid_row(&mut t.h, nh);
        v.copy_from_slice(&t.a);
        for (j, &hj) in t.h[..nh].iter().enumerate() {
            axpy(&mut v, hj, &t.w[j * nvp..(j + 1) * nvp]);
        }
        t.vis_activate(&mut v);
        let e: f64 = x[..nv]
            .iter()
            .zip(&v)
            .map(|(&a, &b)| f64::from(a - b) * f64::from(a - b))
            .sum();
        err += e / nv as f64;
    }
    err / m.max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    use rand::SeedableRng;

    /// Training data: `rows` vectors of `nb` values, a fraction `zeros` of
    /// them 0 and the rest small counts, with one-hot labels of `k`
    /// classes appended when `k > 0`.
    fn data(rows: usize, nb: usize, k: usize, zeros: f64, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut d = Vec::with_capacity(rows * (nb + k));
        for r in 0..rows {
            for _ in 0..nb {
                let x = if rng.random::<f64>() < zeros {
                    0.0
                } else {
                    f64::from(rng.random_range(1u8..4)) * 0.5
                };
                d.push(x);
            }
            d.extend((0..k).map(|c| f64::from(u8::from(c == r % k.max(1)))));
        }
        d
    }

    fn trained(nb: usize, nh: usize, k: usize, zeros: f64, cfg: &EdbnConfig) -> (Rbm, Vec<f64>) {
        let rows = 53;
        let d = data(rows, nb, k, zeros, 7);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let nv = nb + k;
        let mean: Vec<f64> = (0..nv)
            .map(|i| d.chunks_exact(nv).map(|r| r[i]).sum::<f64>() / rows as f64)
            .collect();
        let mut rbm = Rbm::new(nv, nh, k, &mean, &mut rng);
        let sparse = 2 * d.iter().filter(|&&x| x == 0.0).count() >= d.len();
        let errors = train_pcd(&mut rbm, &d, sparse, cfg, &mut rng);
        (rbm, errors)
    }

    fn bits(r: &Rbm, e: &[f64]) -> Vec<u64> {
        r.w.iter()
            .chain(&r.a)
            .chain(&r.b)
            .chain(e)
            .map(|v| v.to_bits())
            .collect()
    }

    /// `forward_rows` of a batch (rows two at a time, the last odd one
    /// alone) gives every row the bits of that row passed alone, on every
    /// path: a sparse first layer, a dense sigmoid layer and a dense top
    /// without one, of widths on both sides of the lanes.
    #[test]
    fn forward_rows_pairs_are_the_bits_of_one_row() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        for (nb, h1, h2) in [(80, 60, 30), (7, 16, 33), (20, 5, 1)] {
            let k = 3;
            let bottom = Rbm::new(nb, h1, 0, &vec![0.3; nb], &mut rng);
            let mut top = Rbm::new(h1 + k, h2, k, &vec![0.3; h1 + k], &mut rng);
            top.b.iter_mut().for_each(|b| *b = rng.random_range(-1.0..1.0));
            let layers = [
                Forward::new(&bottom, nb, true, true),
                Forward::new(&top, h1, false, false),
            ];
            for n in [1, 2, 3, 5, 8] {
                let x = data(n, nb, 0, 0.7, n as u64);
                let run = || {
                    let mut out = vec![0.0; n * h2];
                    forward_rows(&layers, &x, &mut out, h2);
                    out
                };
                let batch = run();
                for i in 0..n {
                    let mut one = vec![0.0; h2];
                    forward_rows(&layers, &x[i * nb..(i + 1) * nb], &mut one, h2);
                    let want: Vec<u64> = one.iter().map(|v| v.to_bits()).collect();
                    let got: Vec<u64> = batch[i * h2..(i + 1) * h2].iter().map(|v| v.to_bits()).collect();
                    assert_eq!(got, want, "{nb}-{h1}-{h2}, n {n}, row {i}");
                }
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&crate::wide::without_avx512(run)),
                    bits(&batch),
                    "without AVX-512"
                );
                assert_eq!(bits(&crate::wide::baseline_only(run)), bits(&batch), "baseline");
            }
        }
    }

    /// The AVX-512, AVX2 and baseline builds of the trainer give the same
    /// weights and errors bit for bit: sparse and dense rows, with and
    /// without labels (and the discriminative term), widths that are not
    /// multiples of the lanes, a last minibatch shorter than the others.
    #[test]
    fn every_path_trains_the_same_bits() {
        let cfg = EdbnConfig {
            epochs: 7,
            batch_size: 10,
            ..EdbnConfig::default()
        };
        for (nb, nh, k, zeros) in [
            (80, 60, 0, 0.8),
            (21, 30, 5, 0.0),
            (13, 17, 3, 0.7),
            (9, 5, 0, 0.0),
        ] {
            let (r0, e0) = trained(nb, nh, k, zeros, &cfg);
            assert!(r0.w.iter().all(|w| w.is_finite()) && e0.iter().all(|e| e.is_finite()));
            let (r1, e1) = crate::wide::without_avx512(|| trained(nb, nh, k, zeros, &cfg));
            let (r2, e2) = crate::wide::baseline_only(|| trained(nb, nh, k, zeros, &cfg));
            assert!(bits(&r0, &e0) == bits(&r1, &e1), "AVX2 differs: {nb} {nh} {k}");
            assert!(
                bits(&r0, &e0) == bits(&r2, &e2),
                "baseline differs: {nb} {nh} {k}"
            );
        }
    }

    /// Training lowers the reconstruction error of data with structure:
    /// noisy copies (5 % of bits flipped) of three binary patterns.
    #[test]
    fn training_lowers_the_reconstruction_error() {
        let (rows, nv) = (300, 40);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let patterns: Vec<Vec<f64>> = (0..3)
            .map(|_| {
                (0..nv)
                    .map(|_| f64::from(u8::from(rng.random::<bool>())))
                    .collect()
            })
            .collect();
        let d: Vec<f64> = (0..rows)
            .flat_map(|r| patterns[r % 3].clone())
            .map(|x| if rng.random::<f64>() < 0.05 { 1.0 - x } else { x })
            .collect();
        let cfg = EdbnConfig {
            epochs: 15,
            ..EdbnConfig::default()
        };
        let mut rbm = Rbm::new(nv, 20, 0, &vec![0.5; nv], &mut rng);
        let e = train_pcd(&mut rbm, &d, false, &cfg, &mut rng);
        assert!(e[e.len() - 1] < 0.5 * e[0], "errors {e:?}");
    }

    /// `log p(y | x)` of a label-augmented RBM by its definition, in `f64`.
    fn log_posterior(w: &[f64], a: &[f64], b: &[f64], nb: usize, k: usize, x: &[f64], y: usize) -> f64 {
        let nv = nb + k;
        let free: Vec<f64> = (0..k)
            .map(|c| {
                a[nb + c]
                    + (0..b.len())
                        .map(|j| {
                            let o = b[j]
                                + (0..nb).map(|i| w[j * nv + i] * x[i]).sum::<f64>()
                                + w[j * nv + nb + c];
                            o.max(0.0) + (-o.abs()).exp().ln_1p()
                        })
                        .sum::<f64>()
            })
            .collect();
        let top = free.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        free[y] - top - free.iter().map(|f| (f - top).exp()).sum::<f64>().ln()
    }

    /// The discriminative step adds `weight ·` the gradient of `log p(y |
    /// x)` (checked against central differences of its definition) plus
    /// the positive statistics `x σ(base + U_y)`.
    #[test]
    fn discriminative_step_is_the_gradient_of_the_log_posterior() {
        let (nb, nh, k) = (7, 5, 4);
        let nv = nb + k;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut rbm = Rbm::new(nv, nh, k, &vec![0.3; nv], &mut rng);
        for v in rbm.w.iter_mut().chain(rbm.a.iter_mut()).chain(rbm.b.iter_mut()) {
            // Values an f32 holds exactly, so both sides see the same model.
            *v = f64::from((rng.random::<f64>() * 2.0 - 1.0) as f32);
        }
        let x: Vec<f64> = (0..nb).map(|i| [0.0, 0.5, 1.0, 0.25][i % 4]).collect();
        let y = 2;
        let weight = 3.0f32;
        let mut t = Trainer::new(&rbm);
        let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let mut base = vec![0.0f32; t.nhp];
        product(&x32, None, nb, &t.wt, &t.b, &mut base);
        t.discriminative(&x32, y, &base, weight);
        let nhp = t.nhp;
        let h = 1e-6;
        let lp = |w: &[f64], a: &[f64], b: &[f64]| log_posterior(w, a, b, nb, k, &x, y);
        // σ(base + U_y) per hidden unit, for the positive statistics.
        let sig_y: Vec<f64> = (0..nh)
            .map(|j| {
                let o = rbm.b[j]
                    + (0..nb).map(|i| rbm.w[j * nv + i] * x[i]).sum::<f64>()
                    + rbm.w[j * nv + nb + y];
                1.0 / (1.0 + (-o).exp())
            })
            .collect();
        for j in 0..nh {
            for i in 0..nv {
                let (mut up, mut dn) = (rbm.w.clone(), rbm.w.clone());
                up[j * nv + i] += h;
                dn[j * nv + i] -= h;
                let grad = (lp(&up, &rbm.a, &rbm.b) - lp(&dn, &rbm.a, &rbm.b)) / (2.0 * h);
                let xi = if i < nb {
                    x[i]
                } else {
                    f64::from(u8::from(i - nb == y))
                };
                let want = f64::from(weight) * grad + xi * sig_y[j];
                let got = f64::from(t.gt[i * nhp + j]);
                assert!(
                    (got - want).abs() < 2e-4 * (1.0 + want.abs()),
                    "W[{j}][{i}]: {got} vs {want}"
                );
            }
            let (mut up, mut dn) = (rbm.b.clone(), rbm.b.clone());
            up[j] += h;
            dn[j] -= h;
            let grad = (lp(&rbm.w, &rbm.a, &up) - lp(&rbm.w, &rbm.a, &dn)) / (2.0 * h);
            let want = f64::from(weight) * grad + sig_y[j];
            assert!(
                (f64::from(t.gb[j]) - want).abs() < 2e-4 * (1.0 + want.abs()),
                "b[{j}]"
            );
        }
        for c in 0..k {
            let (mut up, mut dn) = (rbm.a.clone(), rbm.a.clone());
            up[nb + c] += h;
            dn[nb + c] -= h;
            let grad = (lp(&rbm.w, &up, &rbm.b) - lp(&rbm.w, &dn, &rbm.b)) / (2.0 * h);
            let want = f64::from(weight) * grad + f64::from(u8::from(c == y));
            assert!((f64::from(t.ga[nb + c]) - want).abs() < 2e-4, "c[{c}]");
        }
        // Padding lanes stay 0, so no padded unit ever feeds a real one.
        for i in 0..nv {
            assert!(t.gt[i * nhp + nh..(i + 1) * nhp].iter().all(|&g| g == 0.0));
        }
    }

    /// Degenerate and extreme training sets train without panic and give
    /// finite weights: one row, a minibatch larger than the set, all-zero
    /// rows, tiny values, a single hidden unit; huge values (1e30) that
    /// overflow leave non-finite weights, which `fit_set` refuses.
    #[test]
    fn hard_training_sets_stay_finite() {
        let cfg = EdbnConfig {
            epochs: 3,
            batch_size: 64,
            ..EdbnConfig::default()
        };
        for (rows, nb, nh, k, fill) in [
            (1usize, 5usize, 3usize, 0usize, 1.0f64),
            (3, 4, 1, 2, 0.0),
            (10, 6, 4, 3, 1e30),
            (10, 6, 4, 0, 1e-30),
            (5, 1, 2, 0, 0.0),
        ] {
            let nv = nb + k;
            let mut d = vec![fill; rows * nv];
            for (r, row) in d.chunks_exact_mut(nv).enumerate() {
                row[nb..]
                    .iter_mut()
                    .enumerate()
                    .for_each(|(c, v)| *v = f64::from(u8::from(c == r % k.max(1))));
            }
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let mut rbm = Rbm::new(nv, nh, k, &vec![0.5; nv], &mut rng);
            let e = train_pcd(&mut rbm, &d, fill == 0.0, &cfg, &mut rng);
            assert_eq!(e.len(), cfg.epochs);
            let finite = rbm.w.iter().chain(&rbm.a).chain(&rbm.b).all(|w| w.is_finite());
            let case = format!("{rows} rows, {nb}+{k} visible, {nh} hidden, values {fill}: {e:?}");
            if fill.abs() < 1e3 {
                assert!(finite && e.iter().all(|e| e.is_finite()), "{case}");
            } else {
                // Inputs of 1e30 overflow the products: the weights must
                // show it (EdbnConfig::fit_set then refuses the model),
                // never a finite model from a NaN training.
                assert!(finite == e.iter().all(|e| e.is_finite()), "{case}");
            }
        }
    }

    #[test]
    fn exp_neg_is_within_two_ulp_of_exp() {
        let mut worst = 0.0f64;
        let mut x = 0.0f32;
        while x > -87.0 {
            let got = f64::from(exp_neg(x));
            let want = f64::from(x).exp();
            let ulp = f64::from(f32::EPSILON) * want;
            worst = worst.max((got - want).abs() / ulp);
            x -= 0.001_37;
        }
        assert!(worst <= 2.0, "worst {worst} ulp");
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(-1e30), exp_neg(-87.0));
        assert!(exp_neg(f32::NEG_INFINITY) > 0.0);
        assert!(exp_neg(f32::NAN).is_nan());
    }

    #[test]
    fn sigmoid_and_softplus_are_accurate_and_finite_everywhere() {
        for z in [
            f32::NEG_INFINITY,
            -1e30,
            -100.0,
            -20.0,
            -1.0,
            -1e-30,
            0.0,
            1e-30,
            0.5,
            3.0,
            20.0,
            100.0,
            1e30,
            f32::INFINITY,
        ] {
            let (s, sp) = sigmoid_softplus(z);
            assert!((0.0..=1.0).contains(&s), "σ({z}) = {s}");
            assert!(sp.is_finite() || z == f32::INFINITY, "softplus({z}) = {sp}");
            assert!(sp >= 0.0);
            let zd = f64::from(z);
            let want_s = 1.0 / (1.0 + (-zd).exp());
            let want_sp = zd.max(0.0) + (-zd.abs()).exp().ln_1p();
            if z.abs() < 80.0 {
                assert!(
                    (f64::from(s) - want_s).abs() <= 3e-7 * want_s.max(1e-30),
                    "σ({z})"
                );
                assert!(
                    (f64::from(sp) - want_sp).abs() <= 3e-7 * want_sp.max(1e-30),
                    "softplus({z}): {sp} vs {want_sp}"
                );
            }
            assert_eq!(sigmoid(z), s);
        }
    }

    #[test]
    fn log1p_polynomial_is_within_two_ulp_on_the_unit_interval() {
        let mut worst = 0.0f64;
        for i in 0..=100_000 {
            let e = i as f32 / 100_000.0;
            let got = f64::from(log1p_unit(e));
            let want = f64::from(e).ln_1p();
            if want > 0.0 {
                worst = worst.max((got - want).abs() / (f64::from(f32::EPSILON) * want));
            }
        }
        // Tiny arguments keep their relative accuracy.
        let tiny = 1e-30f32;
        assert!((f64::from(log1p_unit(tiny)) - 1e-30).abs() < 1e-36);
        assert!(worst <= 2.0, "worst {worst} ulp");
    }

    #[test]
    fn transposes_agree_on_every_path() {
        for (rows, cols) in [(8, 8), (80, 64), (16, 32), (24, 8)] {
            let src: Vec<f32> = (0..rows * cols).map(|v| v as f32 * 0.5 - 3.0).collect();
            let mut want = vec![0.0f32; rows * cols];
            for i in 0..rows {
                for j in 0..cols {
                    want[j * rows + i] = src[i * cols + j];
                }
            }
            let mut wide = vec![f32::NAN; rows * cols];
            transpose(&src, rows, cols, &mut wide);
            assert_eq!(wide, want, "{rows} x {cols}");
            let mut base = vec![f32::NAN; rows * cols];
            crate::wide::baseline_only(|| transpose(&src, rows, cols, &mut base));
            assert_eq!(base, want, "{rows} x {cols}, baseline");
        }
    }

    #[test]
    fn lane_sum_adds_in_its_fixed_order() {
        let v: Vec<f32> = (0..48).map(|i| i as f32 + 0.25).collect();
        // Lane l holds l + (l + 16) + (l + 32) + 0.75; the tree adds lanes
        // 8 apart, then 4, 2, 1: all exact here.
        assert_eq!(lane_sum(&v), (0..48).map(|i| i as f32 + 0.25).sum::<f32>());
        assert_eq!(lane_sum(&[]), 0.0);
        // Not the sequential sum, which loses every 1 added to 2^24: lane
        // 0 (2^24 + 1, rounded to 2^24) takes lane 8's 1 (lost again), then
        // lane 4's 2, lane 2's 4 and lane 1's 8 as the tree pairs them.
        let mut w = vec![0.0f32; 32];
        w[0] = 16_777_216.0;
        w[1..17].iter_mut().for_each(|x| *x = 1.0);
        let sequential: f32 = w.iter().sum();
        assert_eq!(sequential, 16_777_216.0);
        assert_eq!(lane_sum(&w), 16_777_230.0);
    }
}
