//! Batch WSS: eq. 5 for every class and alignment `k`, eq. 7, the "no edge"
//! threshold and the continuous-angle refinement.
//!
//! Fast path. With `Ĩ_m` the centred unit-norm frame `m` (zero when its variance
//! is nil) and `S̃_i` the centred unit-norm template, Pearson's
//! `R(I_m, S_i) = <Ĩ_m, S̃_i>`, so the numerator of eq. 5,
//! `N_θ(k) = Σ_i w_{k−i} <Ĩ_{k−i}, S̃_i>`, is a sum over taxels of linear
//! convolutions of the sequences `a_m[t] = w_m Ĩ_m[t]` with the template
//! sequences `S̃_i[t]`. It is computed by overlap-save FFT convolution: per FFT
//! length `L` the input spectra (one per taxel and block) are made once per trial
//! and shared by every class; per class the taxel sum is done in the frequency
//! domain (`Σ_t A_t(f)·Ŝ_t(f)`), so there is one inverse FFT per class and block.
//! Template spectra are cached in [`Templates`]. The denominator is a windowed
//! sum of weights, from prefix sums. Cost per trial:
//! `O(n_taxels·K·log L)` for the inputs plus `O(classes·(n_taxels·K + K·log L))`.
//!
//! Exact fallbacks (the stability rules in the user guide's "Numerical hard cases"):
//! * a window whose weights are all 0 (only `one_minus_sr`, when every frame in
//!   it has the trial's largest count) uses constant weights: the plain mean of
//!   its correlations (from a second, unweighted convolution, or direct sums
//!   when few windows need it);
//! * a window whose weights sum to less than 1e-3 per term is summed directly
//!   (FFT rounding, ~1e-13 absolute, would otherwise be amplified by the small
//!   denominator); this is rare outside contrived trials whose every frame is
//!   within 0.1 % of the largest count, where it degrades to direct cost.
//!
//! [`wss_reference`] is the straightforward direct evaluation (Pearson from raw
//! frames and raw templates) that tests compare the fast path with.

use super::params::{BeforeStart, Refine, WssParams};
use super::simd::TAXEL_GROUP;
use super::templates::{normalize_with_sum, raw_templates, ClassTemplates, Soa, Templates};
use palpate_core::{ClassScore, Estimate, SpikeImages, StageError};
use realfft::num_complex::Complex;
use std::collections::HashMap;

/// Frames prepared for WSS: centred unit-norm images and per-frame counts.
#[derive(Clone, Debug)]
pub(crate) struct Prepared {
    pub n: usize,
    pub k: usize,
    /// `Ĩ_m[t]` at `m * n + t`.
    pub norm: Vec<f64>,
    /// Whether frame `m` has spatial variance (else `Ĩ_m = 0`).
    pub active: Vec<bool>,
    /// Total count `C_m` of frame `m`.
    pub count: Vec<f64>,
    /// `max_m C_m`.
    pub max_count: f64,
    pub hop_ms: f64,
    pub window_ms: f64,
}

/// Checks one frame's counts: finite and non-negative.
pub(crate) fn check_frame(frame: &[f64], k: usize) -> Result<(), StageError> {
    for (t, &c) in frame.iter().enumerate() {
        if !(c.is_finite() && c >= 0.0) {
            return Err(StageError::new(format!(
                "wss: spike count {c} of frame {k}, taxel {t} is not a finite non-negative number"
            )));
        }
    }
    Ok(())
}

/// Prepares `images` for templates built for `tpl`'s layout and hop.
pub(crate) fn prepare(images: &SpikeImages, tpl: &Templates) -> Result<Prepared, StageError> {
    let n = tpl.n_taxels();
    if images.layout.len() != n {
        return Err(StageError::new(format!(
            "wss: images have {} taxels but the templates were built for {n}",
            images.layout.len()
        )));
    }
    if images.counts.len() != images.n_frames * n {
        return Err(StageError::new(format!(
            "wss: images hold {} counts, expected {} frames x {n} taxels",
            images.counts.len(),
            images.n_frames
        )));
    }
    // Counts are checked by one branch-free pass (which vectorizes, where
    // an early-exit search did not); only when it finds a bad one are the
    // frames checked in order, so the error names the first, as
    // `Prepared::push` frame by frame does.
    let all_good = crate::wide::with_avx2(
        #[inline(always)]
        || {
            images
                .counts
                .iter()
                .fold(true, |ok, &c| ok & c.is_finite() & (c >= 0.0))
        },
    );
    if !all_good {
        for k in 0..images.n_frames {
            check_frame(images.frame(k), k)?;
        }
    }
    let mut norm = images.counts.clone();
    let mut active = vec![false; images.n_frames];
    let mut count = vec![0.0; images.n_frames];
    crate::wide::with_avx2(
        #[inline(always)]
        || normalize_frames(&mut norm, n, &mut count, &mut active),
    );
    let max_count = count.iter().fold(0.0, |m: f64, &c| m.max(c));
    Ok(Prepared {
        n,
        k: images.n_frames,
        norm,
        active,
        count,
        max_count,
        hop_ms: images.hop_ms,
        window_ms: images.window_ms,
    })
}

/// Frames normalised side by side by [`normalize_frames`].
const FRAME_LANES: usize = 8;

/// Centres every frame of `norm` (`n` values each) and scales it to unit
/// norm in place, as [`normalize_with_sum`] does frame by frame, writing
/// each frame's total count (`Σ_t x_t`, summed in taxel order) and whether
/// it is active.
///
/// Why frames side by side: a frame's three sums (count, energy, squared
/// deviations) are each a chain of `n` dependent additions, and frame by
/// frame the core waits on every one (`perf` on `palpate run
/// graphs/quickstart.toml --threads 1`: preparing the frames was 12.6 % of
/// the WSS stage). With [`FRAME_LANES`] frames transposed into a block,
/// the same additions in the same order run for eight frames at once, in
/// vector lanes: the same bits (test `frames_side_by_side_are_the_bits_of_frame_by_frame`).
#[inline(always)]
pub(crate) fn normalize_frames(norm: &mut [f64], n: usize, count: &mut [f64], active: &mut [bool]) {
    const L: usize = FRAME_LANES;
    let frames = count.len();
    // The neutral element `Iterator::sum` starts from, so that the sums
    // below are the bits of `frame.iter().sum()`.
    let zero: f64 = std::iter::empty::<f64>().sum();
    if n == 0 {
        // No taxels: every count is the empty sum; nothing is active.
        count.iter_mut().for_each(|c| *c = zero);
        active.iter_mut().for_each(|a| *a = false);
        return;
    }
    let nf = n as f64;
    let mut block = vec![0.0; n * L];
    let whole = frames / L * L;
    for g in (0..whole).step_by(L) {
        let rows = &mut norm[g * n..(g + L) * n];
        for (l, row) in rows.chunks_exact(n).enumerate() {
            for (t, &x) in row.iter().enumerate() {
                block[t * L + l] = x;
            }
        }
        let (mut sum, mut energy, mut ss) = ([zero; L], [zero; L], [zero; L]);
        for b in block.chunks_exact(L) {
            for l in 0..L {
                sum[l] += b[l];
                energy[l] += b[l] * b[l];
            }
        }
        let mut mean = [0.0; L];
        for l in 0..L {
            mean[l] = sum[l] / nf;
        }
        for b in block.chunks_exact(L) {
            for l in 0..L {
                ss[l] += (b[l] - mean[l]) * (b[l] - mean[l]);
            }
        }
        for (l, row) in rows.chunks_exact_mut(n).enumerate() {
            count[g + l] = sum[l];
            if !ss[l].is_finite() || ss[l] <= 1e-20 * energy[l] {
                row.iter_mut().for_each(|x| *x = 0.0);
                active[g + l] = false;
            } else {
                let inv = 1.0 / ss[l].sqrt();
                row.iter_mut().for_each(|x| *x = (*x - mean[l]) * inv);
                active[g + l] = true;
            }
        }
    }
    for k in whole..frames {
        let row = &mut norm[k * n..(k + 1) * n];
        let c: f64 = row.iter().sum();
        count[k] = c;
        active[k] = normalize_with_sum(row, c);
    }
}

impl Prepared {
    pub(crate) fn empty(n: usize, hop_ms: f64, window_ms: f64) -> Self {
        Prepared {
            n,
            k: 0,
            norm: Vec::new(),
            active: Vec::new(),
            count: Vec::new(),
            max_count: 0.0,
            hop_ms,
            window_ms,
        }
    }

    /// Appends one frame.
    pub(crate) fn push(&mut self, frame: &[f64]) -> Result<(), StageError> {
        if frame.len() != self.n {
            return Err(StageError::new(format!(
                "wss: frame {} has {} counts, expected {}",
                self.k,
                frame.len(),
                self.n
            )));
        }
        check_frame(frame, self.k)?;
        let c: f64 = frame.iter().sum();
        let start = self.norm.len();
        self.norm.extend_from_slice(frame);
        let active = normalize_with_sum(&mut self.norm[start..], c);
        self.active.push(active);
        self.count.push(c);
        self.max_count = self.max_count.max(c);
        self.k += 1;
        Ok(())
    }

    /// `Ĩ_m`.
    pub(crate) fn frame(&self, m: usize) -> &[f64] {
        &self.norm[m * self.n..(m + 1) * self.n]
    }

    /// The weight of frame `m` under `params.weighting`, with largest count `max`.
    pub(crate) fn weights(&self, params: &WssParams, max: f64) -> Vec<f64> {
        self.count.iter().map(|&c| weight(params, c, max)).collect()
    }

    /// End of frame `k`, ms from the trial's start.
    pub(crate) fn frame_end_ms(&self, k: usize) -> f64 {
        k as f64 * self.hop_ms + self.window_ms
    }

    /// Whether any frame has a spike.
    pub(crate) fn any_spikes(&self) -> bool {
        self.count.iter().any(|&c| c > 0.0)
    }

    /// End of the last frame, ms (`None` without frames).
    pub(crate) fn end_ms(&self) -> Option<f64> {
        (self.k > 0).then(|| self.frame_end_ms(self.k - 1))
    }
}

/// `w` of a frame with total count `c` when the trial's largest count is `max`.
pub(crate) fn weight(params: &WssParams, c: f64, max: f64) -> f64 {
    use super::params::Weighting::*;
    let sr = if max > 0.0 { (c / max).clamp(0.0, 1.0) } else { 0.0 };
    match params.weighting {
        Constant => 1.0,
        OneMinusSr => 1.0 - sr,
        OnePlusSr => 1.0 + sr,
    }
}

/// The window of eq. 5 at alignment `k` for a class with `len` templates:
/// `(first frame, frames in the window, silent pre-start terms)`.
pub(crate) fn window(k: usize, len: usize, before: BeforeStart) -> (usize, usize, usize) {
    let nw = (k + 1).min(len);
    let extra = match before {
        BeforeStart::Exclude => 0,
        BeforeStart::Silent => len - nw,
    };
    (k + 1 - nw, nw, extra)
}

/// Direct evaluation of eq. 5 at `k` from prepared frames, with weights for a
/// largest count `max`: `(weighted numerator, denominator including silent
/// terms, unweighted numerator)`.
pub(crate) fn direct_k(
    prep: &Prepared,
    params: &WssParams,
    max: f64,
    cls: &ClassTemplates,
    k: usize,
) -> (f64, f64, f64) {
    let (_, nw, extra) = window(k, cls.len, params.before_start);
    let (mut num, mut den, mut p) = (0.0, extra as f64, 0.0);
    for i in 0..nw {
        let m = k - i;
        let w = weight(params, prep.count[m], max);
        den += w;
        if prep.active[m] {
            let r: f64 = prep
                .frame(m)
                .iter()
                .zip(cls.template(i))
                .map(|(a, b)| a * b)
                .sum();
            num += w * r;
            p += r;
        }
    }
    (num, den, p)
}

/// [`direct_k`] finished into `WSS_θ(k)` (with the constant-weight fallback).
pub(crate) fn direct_value(
    prep: &Prepared,
    params: &WssParams,
    max: f64,
    cls: &ClassTemplates,
    k: usize,
) -> f64 {
    let (num, den, p) = direct_k(prep, params, max, cls, k);
    let (_, nw, _) = window(k, cls.len, params.before_start);
    combine(num, den, p, nw, den == 0.0)
}

/// `WSS` from its parts, with the constant-weight fallback: `num / den`, or the
/// plain mean `p / terms` when every weight of the window is 0.
pub(crate) fn combine(num: f64, den: f64, p: f64, nw: usize, all_zero: bool) -> f64 {
    if all_zero {
        p / nw as f64
    } else {
        num / den
    }
}

/// Input spectra `[block][taxel][bin]` and, per block, whether it is non-zero.
type InputSpectra = (Soa, Vec<bool>);

/// Smallest FFT length `>= n` of the form `2^j`, `5·2^j` or `3·2^j` (even, and
/// fast for realfft), so that padding wastes at most a third.
pub(crate) fn nice_len(n: usize) -> usize {
    let n = n.max(16);
    let p = n.next_power_of_two();
    [p, p / 8 * 5, p / 4 * 3, p / 16 * 9]
        .into_iter()
        .filter(|&m| m >= n && m % 2 == 0)
        .min()
        .unwrap_or(p)
}

/// Template cuts are rounded up to this many frames (see `Fft::conv`).
const H_QUANTUM: usize = 256;

/// Longest single-block FFT; longer trials use overlap-save blocks.
const SINGLE_BLOCK_MAX: usize = 1 << 14;

/// How one class's convolution is blocked: FFT length, outputs per block and
/// template length used.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct Plan {
    len: usize,
    block: usize,
    h: usize,
    /// The frame a single block's segment starts at (the trial's first
    /// active frame, see [`Fft::new`]); 0 for overlap-save.
    origin: usize,
}

impl Plan {
    /// Single block when the linear convolution fits a modest FFT, otherwise
    /// overlap-save with an FFT about four template lengths long.
    fn new(k: usize, h: usize) -> Plan {
        match single_len(k, h) {
            Some(len) => Plan {
                len,
                block: k,
                h,
                origin: 0,
            },
            None => {
                let len = nice_len(4 * h);
                Plan {
                    len,
                    block: len - h + 1,
                    h,
                    origin: 0,
                }
            }
        }
    }
}

/// A trial's input sequences and their spectra per (sequence, plan), kept
/// across [`fast_series_in`] calls on the same trial: a refinement search
/// scores one template set after another against the same trial, and
/// without it every step re-ran the 16 forward FFTs of the trial (most of a
/// step's work). Spectra depend only on the sequence and the plan, so reuse
/// does not change a bit.
#[derive(Default)]
pub(crate) struct TrialSpectra {
    /// Taxel-major input sequences: 0 = weighted, 1 = unweighted (empty
    /// until a class needs it).
    seqs: [Vec<f64>; 2],
    inputs: HashMap<(usize, Plan), InputSpectra>,
    /// The weighting the weighted sequence and the prefix sums were made
    /// for (`None`: not yet made).
    weighting: Option<super::params::Weighting>,
    /// Prefix sums of the frames' weights and of their non-zero weights.
    wp: Vec<f64>,
    nzp: Vec<usize>,
    /// [`Fft::conv`]'s buffers, kept across calls: a search's probes call it
    /// hundreds of times per trial, and allocating (and zeroing) them each
    /// time was 5 % of a joint angle-speed search. Every value read is
    /// written first in each call, so reuse does not change a bit.
    work: ConvWork,
}

/// [`Fft::conv`]'s buffers (see [`TrialSpectra`]).
#[derive(Default)]
struct ConvWork {
    acc: Soa,
    z: Vec<Complex<f64>>,
    out: Vec<f64>,
    scratch: Vec<Complex<f64>>,
}

impl TrialSpectra {
    /// Makes the weighted sequence and the weights' prefix sums for
    /// `params.weighting`, unless they were made for it already: a search
    /// scores template after template against one trial with the same
    /// weights, and rebuilding (and comparing) the `taxels x frames`
    /// sequence each time was 6 % of a probe. A new weighting drops the
    /// weighted sequence's spectra.
    fn set_weights(&mut self, prep: &Prepared, params: &WssParams) {
        if self.weighting == Some(params.weighting) {
            return;
        }
        let (n, k) = (prep.n, prep.k);
        let w = prep.weights(params, prep.max_count);
        let mut wp = vec![0.0; k + 1];
        let mut nzp = vec![0usize; k + 1];
        for m in 0..k {
            wp[m + 1] = wp[m] + w[m];
            nzp[m + 1] = nzp[m] + usize::from(w[m] != 0.0);
        }
        let mut weighted = vec![0.0; n * k];
        for m in 0..k {
            if prep.active[m] {
                for t in 0..n {
                    weighted[t * k + m] = w[m] * prep.norm[m * n + t];
                }
            }
        }
        if self.seqs[0] != weighted {
            self.inputs.retain(|(s, _), _| *s != 0);
            self.seqs[0] = weighted;
        }
        self.wp = wp;
        self.nzp = nzp;
        self.weighting = Some(params.weighting);
    }
}

/// Per-call FFT workspace over a trial's [`TrialSpectra`].
struct Fft<'a> {
    tpl: &'a Templates,
    n: usize,
    k: usize,
    /// The FFT length every single-block class uses (see [`Fft::plan`]).
    shared_len: usize,
    /// The first frame with spatial variance and the frames from it to the
    /// last such frame (`0` and `k` when none has any): outside them both
    /// input sequences are exactly zero (see [`Fft::new`]).
    origin: usize,
    span: usize,
    spectra: &'a mut TrialSpectra,
}

/// The FFT length of a one-block convolution of `span` input frames with
/// `h` templates, if one block is not too long (else overlap-save).
fn single_len(span: usize, h: usize) -> Option<usize> {
    let len = nice_len(span + h - 1);
    (len <= SINGLE_BLOCK_MAX.max(4 * h)).then_some(len)
}

impl<'a> Fft<'a> {
    /// A trial's FFT workspace. Every class whose linear convolution fits
    /// one block shares the longest such block's FFT length, so the input
    /// spectra are made once (16 FFTs) rather than once per distinct length
    /// (three or four on a lab trial): the shorter classes' products and
    /// inverse FFTs grow a little, by less than the forward FFTs saved.
    ///
    /// A single block covers only the trial's active frames, `origin ..
    /// origin + span`: a frame without spatial variance is zero in both
    /// input sequences (its normalised image is 0), so the linear
    /// convolution of the trial equals that of its active stretch, shifted
    /// by `origin`, and is exactly zero from `origin + span + h − 1` on. On
    /// lab trials the active stretch is about half the trial (the array
    /// rests on the surface before and after the edge passes), so the
    /// FFTs, the products and the cached template spectra are built at
    /// about half the length. Only the rounding of the transforms changes.
    fn new(tpl: &'a Templates, prep: &Prepared, spectra: &'a mut TrialSpectra) -> Self {
        let (n, k) = (prep.n, prep.k);
        let (origin, span) = match (
            prep.active.iter().position(|&a| a),
            prep.active.iter().rposition(|&a| a),
        ) {
            (Some(first), Some(last)) => (first, last - first + 1),
            _ => (0, k),
        };
        let shared_len = tpl
            .classes()
            .iter()
            .filter_map(|cls| single_len(span, cut(cls.len, k)))
            .max()
            .unwrap_or(0);
        Fft {
            tpl,
            n,
            k,
            shared_len,
            origin,
            span,
            spectra,
        }
    }

    /// Whether `plan` is one block (from its origin to the trial's end).
    fn single(&self, plan: Plan) -> bool {
        plan.origin + plan.block >= self.k
    }

    /// The block plan of a class with `h` templates: its own for
    /// overlap-save, the shared length for a single block.
    fn plan(&self, h: usize) -> Plan {
        match single_len(self.span, h) {
            Some(len) => Plan {
                len: len.max(self.shared_len),
                block: self.k - self.origin,
                h,
                origin: self.origin,
            },
            // Never one block here: `span <= k`.
            None => Plan::new(self.k, h),
        }
    }

    /// Input spectra for `plan`: block `b`'s segment is
    /// `x[origin + b·block − (h − 1) .. + len)` (zero outside the trial).
    fn input(&mut self, s: usize, plan: Plan) -> &InputSpectra {
        let (n, k) = (self.n, self.k);
        // A single block needs no overlap: its segment starts at its origin.
        let key = if self.single(plan) {
            Plan { h: 1, ..plan }
        } else {
            plan
        };
        let (tpl, seqs) = (self.tpl, &self.spectra.seqs);
        self.spectra.inputs.entry((s, key)).or_insert_with(|| {
            let Plan {
                len,
                block,
                h,
                origin,
            } = key;
            let bins = len / 2 + 1;
            let blocks = (k - origin).div_ceil(block);
            let pair = tpl.plan(len);
            let mut scratch = pair.fwd.make_scratch_vec();
            let mut spec = vec![Complex::new(0.0, 0.0); bins];
            let mut out = Soa {
                re: vec![0.0; blocks * n * bins],
                im: vec![0.0; blocks * n * bins],
            };
            let mut nonzero = vec![false; blocks];
            let mut buf = vec![0.0; len];
            for (b, nz) in nonzero.iter_mut().enumerate() {
                for t in 0..n {
                    let x = &seqs[s][t * k..(t + 1) * k];
                    let start = (origin + b * block) as isize - (h as isize - 1);
                    let mut any = false;
                    for (j, v) in buf.iter_mut().enumerate() {
                        let m = start + j as isize;
                        *v = if m >= 0 && (m as usize) < k {
                            x[m as usize]
                        } else {
                            0.0
                        };
                        any |= *v != 0.0;
                    }
                    *nz |= any;
                    if any {
                        let o = (b * n + t) * bins;
                        let _ = pair.fwd.process_with_scratch(&mut buf, &mut spec, &mut scratch);
                        for (f, z) in spec.iter().enumerate() {
                            out.re[o + f] = z.re;
                            out.im[o + f] = z.im;
                        }
                    }
                }
            }
            (out, nonzero)
        })
    }

    /// `Σ_t Σ_i x_{k−i}[t] S̃_i[t]` for every `k < K`, for class `c`, sequence `s`.
    fn conv(&mut self, c: usize, s: usize) -> Vec<f64> {
        let (n, k) = (self.n, self.k);
        let tpl = self.tpl;
        let h = cut(tpl.classes()[c].len, k);
        let plan = self.plan(h);
        let Plan {
            len, block, origin, ..
        } = plan;
        let bins = len / 2 + 1;
        let spec = tpl.batch_spectra(c, len, h);
        let pair = tpl.plan(len);
        let single = self.single(plan);
        // A single block's outputs past `origin + span + h − 1` are exactly
        // zero (see `Fft::new`) and are left so.
        let ends = if single { self.span + h - 1 } else { block };
        let mut work = std::mem::take(&mut self.spectra.work);
        let ConvWork { acc, z, out, scratch } = &mut work;
        // Sizes only: `acc` is zeroed per block, `z` filled from it, `out`
        // and `scratch` written by the inverse FFT before any read.
        acc.re.resize(bins, 0.0);
        acc.im.resize(bins, 0.0);
        z.resize(bins, Complex::new(0.0, 0.0));
        out.resize(len, 0.0);
        scratch.resize(pair.inv.get_scratch_len(), Complex::new(0.0, 0.0));
        let (x, nonzero) = self.input(s, plan);
        let mut y = vec![0.0; k];
        let fast = super::simd::fast_cpu();
        // Output `origin + b·block + r` sits at `r` (single block) or
        // `h − 1 + r` (overlap-save, whose origin is 0).
        let offset = if single { 0 } else { h - 1 };
        for (b, &nz) in nonzero.iter().enumerate() {
            if !nz {
                continue;
            }
            acc.re.iter_mut().for_each(|a| *a = 0.0);
            acc.im.iter_mut().for_each(|a| *a = 0.0);
            // Taxels in groups (the same bits as one by one, see
            // `simd::cmac_group`), the rest one by one.
            let xs = |t: usize| {
                let o = (b * n + t) * bins;
                (&x.re[o..o + bins], &x.im[o..o + bins])
            };
            let hs = |t: usize| {
                let r = t * bins..(t + 1) * bins;
                (&spec.re[r.clone()], &spec.im[r])
            };
            let grouped = n - n % TAXEL_GROUP;
            for t0 in (0..grouped).step_by(TAXEL_GROUP) {
                super::simd::cmac_group(
                    fast,
                    &mut acc.re,
                    &mut acc.im,
                    std::array::from_fn(|j| xs(t0 + j)),
                    std::array::from_fn(|j| hs(t0 + j)),
                );
            }
            for t in grouped..n {
                cmac(fast, acc, xs(t), hs(t));
            }
            for (f, v) in z.iter_mut().enumerate() {
                *v = Complex::new(acc.re[f], acc.im[f]);
            }
            // Real inputs: DC and Nyquist are real up to rounding.
            z[0].im = 0.0;
            z[bins - 1].im = 0.0;
            let _ = pair.inv.process_with_scratch(z, out, scratch);
            for r in 0..block.min(ends) {
                let kk = origin + b * block + r;
                if kk >= k {
                    break;
                }
                y[kk] = out[offset + r];
            }
        }
        self.spectra.work = work;
        y
    }
}

/// The templates of a class of `len` used against a trial of `k` frames.
///
/// Templates past the trial's last alignment never reach an output `< k`,
/// so a template longer than the trial is cut. It is cut at `k` rounded up
/// to a multiple of [`H_QUANTUM`], not at `k`: the cut templates' spectra
/// are cached by length, and trials of nearly the same length then share
/// them (cut at exactly `k`, every trial of a new length missed the cache).
fn cut(len: usize, k: usize) -> usize {
    len.min(k.next_multiple_of(H_QUANTUM))
}

/// `acc += x ⊙ h` over complex bins stored as separate parts.
#[inline]
pub(crate) fn cmac(fast: bool, acc: &mut Soa, x: (&[f64], &[f64]), h: (&[f64], &[f64])) {
    super::simd::cmac(fast, &mut acc.re, &mut acc.im, x.0, x.1, h.0, h.1)
}

/// Windows whose weights average less than this per term are summed directly.
pub(crate) const GUARD: f64 = 1e-3;

/// Fewest fallback windows for which the unweighted numerator is convolved
/// rather than summed directly.
const FALLBACK_FFT_MIN: usize = 32;

/// `WSS_θ(k)` for every class of `tpl` and every `k`, by the fast path.
pub(crate) fn fast_series(prep: &Prepared, tpl: &Templates, params: &WssParams) -> Vec<Vec<f64>> {
    fast_series_in(&mut TrialSpectra::default(), prep, tpl, params)
}

/// [`fast_series`], reusing (and adding to) the trial's `spectra`: every call
/// with one `spectra` must be on the same `prep`.
pub(crate) fn fast_series_in(
    spectra: &mut TrialSpectra,
    prep: &Prepared,
    tpl: &Templates,
    params: &WssParams,
) -> Vec<Vec<f64>> {
    let (n, k) = (prep.n, prep.k);
    if k == 0 {
        return vec![Vec::new(); tpl.classes().len()];
    }
    spectra.set_weights(prep, params);
    let (wp, nzp) = (spectra.wp.clone(), spectra.nzp.clone());
    let mut fft = Fft::new(tpl, prep, spectra);
    let before = params.before_start;
    let mut all = Vec::with_capacity(tpl.classes().len());
    for (c, cls) in tpl.classes().iter().enumerate() {
        let num = fft.conv(c, 0);
        let mut out = vec![0.0; k];
        let mut fallback = Vec::new();
        for kk in 0..k {
            let (lo, nw, extra) = window(kk, cls.len, before);
            let nz = nzp[kk + 1] - nzp[lo] + extra;
            if nz == 0 {
                fallback.push(kk);
                continue;
            }
            let den = wp[kk + 1] - wp[lo] + extra as f64;
            out[kk] = if den < GUARD * (nw + extra) as f64 {
                direct_value(prep, params, prep.max_count, cls, kk)
            } else {
                num[kk] / den
            };
        }
        if fallback.len() >= FALLBACK_FFT_MIN {
            if fft.spectra.seqs[1].is_empty() {
                let mut u = vec![0.0; n * k];
                for m in 0..k {
                    for t in 0..n {
                        u[t * k + m] = prep.norm[m * n + t];
                    }
                }
                fft.spectra.seqs[1] = u;
            }
            let p = fft.conv(c, 1);
            for kk in fallback {
                let (_, nw, _) = window(kk, cls.len, before);
                out[kk] = p[kk] / nw as f64;
            }
        } else {
            for kk in fallback {
                let (_, nw, _) = window(kk, cls.len, before);
                let (_, _, p) = direct_k(prep, params, prep.max_count, cls, kk);
                out[kk] = p / nw as f64;
            }
        }
        all.push(out);
    }
    all
}

/// Pearson's correlation with the zero-variance rule (0 when either image has
/// negligible variance), computed directly from raw values.
pub fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx, mut syy, mut ex, mut ey) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx) * (a - mx);
        syy += (b - my) * (b - my);
        ex += a * a;
        ey += b * b;
    }
    if sxx.is_nan() || syy.is_nan() || sxx <= 1e-20 * ex || syy <= 1e-20 * ey {
        return 0.0;
    }
    sxy / (sxx * syy).sqrt()
}

/// `WSS_θ(k)` for every class and `k` by direct sums over raw frames and raw
/// templates (paper eq. 5 as written): the reference the fast path is tested
/// against. Cost `O(classes·K·k(θ)·n_taxels)`.
pub fn wss_reference_series(
    images: &SpikeImages,
    tpl: &Templates,
    params: &WssParams,
) -> Result<Vec<Vec<f64>>, StageError> {
    let prep = prepare(images, tpl)?;
    let k = images.n_frames;
    let w = prep.weights(params, prep.max_count);
    let mut all = Vec::new();
    for cls in tpl.classes() {
        let raws = raw_templates(tpl.layout(), tpl.hop_ms(), params, cls.angle_deg, cls.len);
        let mut out = Vec::with_capacity(k);
        for kk in 0..k {
            let (_, nw, extra) = window(kk, cls.len, params.before_start);
            let (mut num, mut den, mut p) = (0.0, extra as f64, 0.0);
            let mut all_zero = extra == 0;
            for (i, raw) in raws.iter().enumerate().take(nw) {
                let m = kk - i;
                let r = pearson(images.frame(m), raw);
                num += w[m] * r;
                den += w[m];
                p += r;
                all_zero &= w[m] == 0.0;
            }
            out.push(combine(num, den, p, nw, all_zero));
        }
        all.push(out);
    }
    Ok(all)
}

/// Best score and frame of one series (first maximum; `(0, 0)` when empty).
pub(crate) fn best_of(series: &[f64]) -> (f64, usize) {
    let mut best = (f64::NEG_INFINITY, 0);
    for (k, &v) in series.iter().enumerate() {
        if v > best.0 {
            best = (v, k);
        }
    }
    if best.0 == f64::NEG_INFINITY {
        (0.0, 0)
    } else {
        best
    }
}

/// Vertex of the parabola through three points, if it opens downwards, clamped
/// to `[x0, x2]`.
pub fn parabola_peak(x: [f64; 3], y: [f64; 3]) -> Option<f64> {
    let d1 = (y[1] - y[0]) / (x[1] - x[0]);
    let d2 = (y[2] - y[1]) / (x[2] - x[1]);
    let a = (d2 - d1) / (x[2] - x[0]);
    if a.is_nan() || a >= 0.0 {
        return None;
    }
    let b = d1 - a * (x[0] + x[1]);
    let v = -b / (2.0 * a);
    v.is_finite().then(|| v.clamp(x[0], x[2]))
}

/// Builds the estimate from each class's best `(score, frame)`, whether any
/// frame so far has a spike, and the end of the last frame (`None`: no
/// frames). `search` evaluates `max_k WSS` at an arbitrary angle for
/// [`Refine::Search`]; `timing` is the arrival-time plane's angle for
/// [`Refine::Timing`] (`None`: no plane fits).
pub(crate) fn finish(
    angles: &[f64],
    best: &[(f64, usize)],
    any_spikes: bool,
    decision_time_ms: Option<f64>,
    params: &WssParams,
    search: Option<&mut dyn FnMut(f64) -> f64>,
    timing: Option<f64>,
) -> Estimate {
    let scores: Vec<ClassScore> = angles
        .iter()
        .zip(best)
        .map(|(&a, &(s, _))| ClassScore {
            angle_deg: a,
            score: s,
        })
        .collect();
    let mut b = 0;
    for (c, &(s, _)) in best.iter().enumerate() {
        if s > best[b].0 {
            b = c;
        }
    }
    if !any_spikes || best[b].0 < params.threshold {
        return Estimate {
            angle_deg: None,
            class_deg: None,
            scores,
            best_frame: any_spikes.then_some(best[b].1),
            decision_time_ms,
            uncertain: false,
        };
    }
    let class = angles[b];
    let mut angle = class;
    // A rival: the best score of the classes that are not the best's grid
    // neighbours (nor the best itself).
    let rival = best
        .iter()
        .enumerate()
        .filter(|(c, _)| c.abs_diff(b) > 1)
        .map(|(_, s)| s.0)
        .fold(f64::NEG_INFINITY, f64::max);
    let mut uncertain = best[b].0 - rival < params.uncertain_margin;
    let neighbours = (b > 0 && b + 1 < angles.len()).then(|| {
        (
            [angles[b - 1], angles[b], angles[b + 1]],
            [best[b - 1].0, best[b].0, best[b + 1].0],
        )
    });
    match params.refine {
        Refine::None => {}
        Refine::Parabola => {
            if let Some(v) = neighbours.and_then(|(x, y)| parabola_peak(x, y)) {
                angle = v;
            }
        }
        Refine::Search => {
            if let Some(f) = search {
                let lo = if b > 0 { angles[b - 1] } else { class / 2.0 };
                let hi = if b + 1 < angles.len() {
                    angles[b + 1]
                } else {
                    (class + 180.0) / 2.0
                };
                let (x, fx) = golden_max(f, lo, hi, params.refine_tol_deg);
                if fx > best[b].0 {
                    angle = x;
                }
            }
        }
        Refine::Timing => {
            if let Some(a) = timing {
                // The grid's local step: the wider gap beside the best class
                // (taken as 5 degrees on a grid of one class).
                let step = [
                    b.checked_sub(1).map(|p| class - angles[p]),
                    angles.get(b + 1).map(|n| n - class),
                ]
                .into_iter()
                .flatten()
                .fold(0.0, f64::max);
                let step = if step > 0.0 { step } else { 5.0 };
                uncertain |= (a - class).abs() > 1.5 * step;
                angle = a;
            }
        }
    }
    Estimate {
        angle_deg: Some(angle),
        class_deg: Some(class),
        scores,
        best_frame: Some(best[b].1),
        decision_time_ms,
        uncertain,
    }
}

/// The arrival-time plane's angle when `params` ask for it.
pub(crate) fn timing_angle(images: &SpikeImages, params: &WssParams) -> Option<f64> {
    (params.refine == Refine::Timing)
        .then(|| super::timing::arrival_plane(images, params.timing_window_ms))
        .flatten()
        .map(|f| f.angle_deg)
}

/// Golden-section search for the maximum of `f` on `[a, b]` to width `tol`.
pub(crate) fn golden_max(f: &mut dyn FnMut(f64) -> f64, mut a: f64, mut b: f64, tol: f64) -> (f64, f64) {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = b - g * (b - a);
    let mut d = a + g * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    while b - a > tol {
        if fc >= fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    if fc >= fd {
        (c, fc)
    } else {
        (d, fd)
    }
}

/// The estimate for one trial's images: eq. 5 for every class and alignment by
/// the fast path, eq. 7, threshold and refinement. The templates must have been
/// built for the images' layout and hop ([`Templates::new`]). With
/// `speed_tolerance > 0` the templates of the other speeds are built here; a
/// caller estimating many trials should build them once and call
/// [`wss_batch_speeds`].
pub fn wss_batch(images: &SpikeImages, tpl: &Templates, params: &WssParams) -> Result<Estimate, StageError> {
    let factors = params.speed_factors();
    if factors.len() == 1 {
        return wss_batch_speeds(images, &[(1.0, tpl)], params);
    }
    let mut owned = Vec::with_capacity(factors.len());
    for &f in &factors {
        owned.push(
            Templates::for_angles(tpl.layout(), tpl.hop_ms(), &params.at_speed(f), &tpl.angles())
                .map_err(|e| StageError::new(format!("wss: {e}")))?,
        );
    }
    let sets: Vec<(f64, &Templates)> = factors.iter().copied().zip(owned.iter()).collect();
    wss_batch_speeds(images, &sets, params)
}

/// [`wss_batch`] over templates built for several speeds: `sets` pairs each
/// speed factor (of `params.speed_mm_s`) with templates built at that speed,
/// for the same layout, hop and angles (factor 1 alone: the known speed).
///
/// Joint speed and angle: every class scores its best over the speeds
/// (`max_v max_k WSS_{θ,v}(k)`), and eq. 7 picks the class. With
/// `refine = "search"` the speed is then refined by a golden-section search
/// around the best class's grid speed (to 0.1 %), and the angle searched at
/// that speed. The speed matters because the templates' timing is the
/// normal speed `v·sin θ`: a declared speed 10 % off is matched best by an
/// angle whose `sin θ` is 10 % off.
pub fn wss_batch_speeds(
    images: &SpikeImages,
    sets: &[(f64, &Templates)],
    params: &WssParams,
) -> Result<Estimate, StageError> {
    let Some(&(_, first)) = sets.first() else {
        return Err(StageError::new("wss: no templates"));
    };
    let prep = prepare(images, first)?;
    let spectra = std::cell::RefCell::new(TrialSpectra::default());
    let angles = first.angles();
    let mut best = vec![(f64::NEG_INFINITY, 0usize); angles.len()];
    let mut best_f = vec![sets[0].0; angles.len()];
    for &(f, tpl) in sets {
        if tpl.angles() != angles || tpl.n_taxels() != first.n_taxels() || tpl.hop_ms() != first.hop_ms() {
            return Err(StageError::new(
                "wss: the templates of every speed must share layout, hop and angles",
            ));
        }
        let series = fast_series_in(&mut spectra.borrow_mut(), &prep, tpl, params);
        for (c, s) in series.iter().enumerate() {
            let b = best_of(s);
            if b.0 > best[c].0 {
                best[c] = b;
                best_f[c] = f;
            }
        }
    }
    for b in &mut best {
        if b.0 == f64::NEG_INFINITY {
            *b = (0.0, 0);
        }
    }
    let layout = first.layout();
    let hop = first.hop_ms();
    let score = |theta: f64, f: f64| -> f64 {
        let p = params.at_speed(f);
        match Templates::for_angles(layout, hop, &p, &[theta]) {
            Ok(one) => best_of(&fast_series_in(&mut spectra.borrow_mut(), &prep, &one, &p)[0]).0,
            Err(_) => f64::NEG_INFINITY,
        }
    };
    let mut b = 0;
    for (c, &(s, _)) in best.iter().enumerate() {
        if s > best[b].0 {
            b = c;
        }
    }
    let mut f_star = best_f[b];
    if sets.len() > 1 && params.refine == Refine::Search && prep.any_spikes() && best[b].0 >= params.threshold
    {
        let tol = params.speed_tolerance;
        let df = 2.0 * tol / (sets.len() - 1) as f64;
        let (lo, hi) = ((f_star - df).max(1.0 - tol), (f_star + df).min(1.0 + tol));
        let theta = angles[b];
        let (f, v) = golden_max(&mut |f| score(theta, f), lo, hi, 1e-3);
        if v > best[b].0 {
            f_star = f;
        }
    }
    let mut search = |theta: f64| -> f64 { score(theta, f_star) };
    Ok(finish(
        &angles,
        &best,
        prep.any_spikes(),
        prep.end_ms(),
        params,
        Some(&mut search),
        timing_angle(images, params),
    ))
}

/// The same estimate as [`wss_batch`] computed by direct sums
/// ([`wss_reference_series`]); refinement by search is not applied.
pub fn wss_reference(
    images: &SpikeImages,
    tpl: &Templates,
    params: &WssParams,
) -> Result<Estimate, StageError> {
    let prep = prepare(images, tpl)?;
    let series = wss_reference_series(images, tpl, params)?;
    let best: Vec<(f64, usize)> = series.iter().map(|s| best_of(s)).collect();
    Ok(finish(
        &tpl.angles(),
        &best,
        prep.any_spikes(),
        prep.end_ms(),
        params,
        None,
        timing_angle(images, params),
    ))
}

/// `WSS_θ(k)` for every class and `k` by the fast path (for plots and tests).
pub fn wss_series(
    images: &SpikeImages,
    tpl: &Templates,
    params: &WssParams,
) -> Result<Vec<Vec<f64>>, StageError> {
    let prep = prepare(images, tpl)?;
    Ok(fast_series(&prep, tpl, params))
}
