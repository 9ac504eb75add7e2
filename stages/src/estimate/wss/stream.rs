//! Streaming WSS: frame by frame, with the running best estimate after every
//! frame, equal to the batch result at the end, in memory that does not grow
//! with the stream.
//!
//! # Semantics
//!
//! After frame `k` the stream answers `argmax_θ max_{k' ≤ k} WSS_θ(k')` with the
//! weights of eq. 5 normalised by the largest frame count seen so far, `M_k`: it
//! is exactly the batch estimate of the trial truncated after frame `k`. Since
//! `M` can grow, the weights of earlier alignments change with it.
//!
//! # Bounded memory
//!
//! With `u = 1/M`, alignment `k'`'s score is a ratio of two functions linear
//! in `u`: for `w = 1 ∓ SR`, `Σ_i w_{k'−i} R = P ∓ u·Q` and `Σ_i w = n ∓ u·S`,
//! with `P_θ(k') = Σ_i R_{k'−i,i}`, `Q_θ(k') = Σ_i C_{k'−i} R_{k'−i,i}` and
//! `S = Σ_i C_{k'−i}` fixed once frame `k'` is in (`C` a frame's count). So
//! each alignment is kept as four numbers, its weighted numerator and
//! denominator at the `u` it was scored with and `Q`, `S`: its score at any
//! later `u' ≤ u` is `(N ± (u − u')·Q) / (D ± (u − u')·S)` (a Möbius function
//! of `u'`, monotone since the denominator never vanishes), with no frame
//! needed. `M` only grows, so `u' ∈ (0, u]`. An alignment is dropped as soon
//! as another one of its class is at least as good for every such `u'`
//! (earlier, so that the batch's first-maximum rule still holds) or strictly
//! better (later): their difference has the sign of a quadratic in `u − u'`,
//! whose minimum over the interval is checked exactly. What stays per class
//! is the upper envelope of the alignments' score curves over every maximum
//! the stream may still reach: in practice a handful (the best under the
//! current weights, the best under constant weights, a few in between;
//! `cargo bench --bench memory` prints the count). Pathological streams could
//! keep more (envelopes of `n` such curves have at most `2n − 1` pieces); they
//! are counted by [`WssStream::candidates`].
//!
//! Frames are kept only while some alignment still reads them: the longest
//! template (`max k(θ)`: about 3700 frames, 37 s, for the 10-degree class at 2
//! mm/s on the paper's array) and the two blocks of the partitioned convolution. The kept frames,
//! their prefix sums (rebased when frames are dropped, so long streams do not
//! lose precision), the frequency-domain delay line and the working buffers
//! are reserved when the stream is made and never reallocated: a stream's
//! memory is fixed by its templates, whatever its length. `refine = "search"`
//! re-runs the batch over the frames so far, so with it every frame is kept;
//! `refine = "timing"` fits the arrival-time plane to every frame's raw
//! counts, so with it those are kept (16 numbers a frame). Both act in
//! [`WssStream::estimate`], not in [`WssStream::push`].
//!
//! Exact fallbacks as in the batch: a window whose weights are all 0 scores
//! its constant-weight mean `P/n` (which is also its score under any larger
//! `M`: all its frames have the same count), and a window whose weights
//! average under 1e-3 per term is summed directly from the frames when it is
//! scored (its denominator then only grows with `M`, so the stored sums stay
//! accurate). When `M` grows, every kept alignment is re-scored: `O(classes ×
//! kept)` cheap arithmetic, on the handful of frames per trial that set a new
//! maximum.
//!
//! # Cost per frame
//!
//! `P` and `Q` are convolutions of the frame sequences with each class's
//! templates, computed by uniformly partitioned convolution with zero latency:
//! the first `B` templates directly each frame (`O(classes·B·taxels)`), the rest
//! by FFTs of length `2B` once per block of `B` frames over a frequency-domain
//! delay line of input spectra shared by every class, taxel sums done in the
//! frequency domain (amortised `O(classes·taxels·k(θ)/B)` per frame).
//!
//! Rounding: scores differ from the batch's directly weighted sums by ~1e-13,
//! so the two agree to well under 1e-9.

use super::batch::{
    best_of, check_frame, direct_k, fast_series_in, finish, window, Prepared, TrialSpectra, GUARD,
};
use super::params::{Refine, Weighting, WssParams};
use super::templates::{FftPair, Soa, Spectra, Templates};
use palpate_core::{Estimate, StageError};
use realfft::num_complex::Complex;
use std::collections::VecDeque;
use std::sync::Arc;

/// Frames per partition block.
const BLOCK: usize = 64;

/// One alignment, kept as its score's parts: the score at a largest-count
/// reciprocal `u' <= u` is `(num + σ(u − u')·q) / (den + σ(u − u')·s)` with
/// `σ = +1` for `1 − SR`, `−1` for `1 + SR`, `0` for constant weights.
#[derive(Clone, Copy, Debug)]
struct Cand {
    /// Alignment (absolute frame index).
    k: usize,
    num: f64,
    den: f64,
    q: f64,
    s: f64,
    /// `1/M` when `num` and `den` were computed.
    u: f64,
}

impl Cand {
    /// `(N, Q, D, S)` at `u`: the score at `u − x` is `(N + xQ) / (D + xS)`.
    #[inline]
    fn at(&self, u: f64, sigma: f64) -> (f64, f64, f64, f64) {
        let x = sigma * (self.u - u);
        (
            self.num + x * self.q,
            sigma * self.q,
            self.den + x * self.s,
            sigma * self.s,
        )
    }

    /// The score at `u`.
    #[inline]
    fn value(&self, u: f64, sigma: f64) -> f64 {
        if u == self.u {
            return self.num / self.den;
        }
        let (n, _, d, _) = self.at(u, sigma);
        n / d
    }
}

/// Whether `a`'s score is `>= b`'s (`> b`'s if `strict`) at every `u' ∈ [0, u]`:
/// `sign(f_a − f_b)` is that of `g(t) = (N_a + tQ_a)(D_b + tS_b) − (N_b + tQ_b)(D_a + tS_a)`,
/// with `t = (u − u')/u ∈ [0, 1]` (`Q`, `S` scaled by `u`, so that every term
/// is of the size of a window's length, whatever the counts) and the
/// denominators positive: a quadratic whose minimum over the interval is at
/// an end or at its vertex. A `g` that is not finite (overflow) keeps both.
fn dominates(a: &Cand, b: &Cand, u: f64, sigma: f64, strict: bool) -> bool {
    let (na, qa, da, sa) = a.at(u, sigma);
    let (nb, qb, db, sb) = b.at(u, sigma);
    let (qa, sa, qb, sb) = (qa * u, sa * u, qb * u, sb * u);
    let c0 = na * db - nb * da;
    let c1 = na * sb + qa * db - nb * sa - qb * da;
    let c2 = qa * sb - qb * sa;
    let g = |t: f64| c0 + t * (c1 + t * c2);
    let (g0, g1) = (g(0.0), g(1.0));
    let tv = -c1 / (2.0 * c2);
    let gv = if c2 > 0.0 && tv > 0.0 && tv < 1.0 {
        g(tv)
    } else {
        g0
    };
    [g0, g1, gv]
        .iter()
        .all(|&m| m.is_finite() && if strict { m > 0.0 } else { m >= 0.0 })
}

/// Adds alignment `c` (the newest) to its class's kept alignments `set`,
/// dropping whichever can no longer be the first maximum for any maximum
/// count still to come (`u' ∈ (0, u]`).
fn insert(set: &mut Vec<Cand>, c: Cand, u: f64, sigma: f64) {
    if set.iter().any(|b| dominates(b, &c, u, sigma, false)) {
        return;
    }
    set.retain(|b| !dominates(&c, b, u, sigma, true));
    set.push(c);
}

/// A frame-by-frame WSS estimator for one trial or stream.
pub struct WssStream {
    tpl: Arc<Templates>,
    params: WssParams,
    /// The kept frames: frame `base + j` at local index `j`.
    pub(super) prep: Prepared,
    /// Frames dropped from the front of `prep`.
    pub(super) base: usize,
    /// Frames kept behind the newest one (longest template, two blocks).
    pub(super) keep: usize,
    /// Frames dropped at once when `keep + drop` are held.
    pub(super) drop: usize,
    /// Every frame is kept (`refine = "search"` needs them).
    all_frames: bool,
    /// Every frame's raw counts, for `refine = "timing"` (else `None`).
    raw: Option<Vec<f64>>,
    any_spikes: bool,
    /// `σ` of [`Cand`].
    sigma: f64,
    b: usize,
    pair: FftPair,
    spectra: Vec<Spectra>,
    parts: Vec<usize>,
    /// Input spectra `[seq][taxel][bin]` of completed blocks, newest first,
    /// with a flag for "not all zero".
    pub(super) fdl: VecDeque<(Soa, bool)>,
    /// Reserved spectra for the delay line until it is full.
    spare: Vec<Soa>,
    pub(super) max_parts: usize,
    /// Per class, tails of `P` and `Q` for the current block.
    tail: Vec<[Vec<f64>; 2]>,
    /// Prefix sums of the kept frames' counts.
    pub(super) cp: Vec<f64>,
    /// Newest frames in a row whose weight is 0 under the current maximum.
    zero_run: usize,
    /// Per class, the alignments that may still be its best, oldest first.
    cands: Vec<Vec<Cand>>,
    best: Vec<(f64, usize)>,
    /// Every alignment, kept for [`WssStream::series`] when asked.
    history: Option<Vec<Vec<Cand>>>,
    acc: [Soa; 2],
    z: Vec<Complex<f64>>,
    spec: Vec<Complex<f64>>,
    buf: Vec<f64>,
    out: Vec<f64>,
    scratch: Vec<Complex<f64>>,
    fast: bool,
}

impl WssStream {
    /// A stream for frames of `templates`' layout and hop, each `window_ms` long
    /// (used only for `decision_time_ms`).
    pub fn new(templates: Arc<Templates>, params: WssParams, window_ms: f64) -> Result<Self, StageError> {
        params.validate()?;
        if params.speed_tolerance > 0.0 {
            return Err(StageError::new(
                "wss: speed_tolerance > 0 (the joint speed search) is batch only; streams need a known speed",
            ));
        }
        palpate_core::check_positive("window_ms", window_ms, "ms")?;
        let b = BLOCK;
        let pair = templates.plan(2 * b);
        let nc = templates.classes().len();
        let spectra: Vec<Spectra> = (0..nc).map(|c| templates.stream_spectra(c, b)).collect();
        let parts: Vec<usize> = templates.classes().iter().map(|c| c.len.div_ceil(b)).collect();
        let max_parts = parts.iter().copied().max().unwrap_or(1);
        let n = templates.n_taxels();
        let scratch = pair
            .fwd
            .make_scratch_vec()
            .len()
            .max(pair.inv.make_scratch_vec().len());
        let longest = templates.classes().iter().map(|c| c.len).max().unwrap_or(1);
        let keep = longest.max(2 * b);
        let drop = (keep / 2).max(b);
        let all_frames = params.refine == Refine::Search;
        let mut prep = Prepared::empty(n, templates.hop_ms(), window_ms);
        let mut cp = vec![0.0];
        if !all_frames {
            // Reserved once: the kept frames never need more.
            let cap = keep + drop + 1;
            prep.norm.reserve_exact(cap * n);
            prep.active.reserve_exact(cap);
            prep.count.reserve_exact(cap);
            cp.reserve_exact(cap + 1);
        }
        let bins = b + 1;
        let spare = (0..max_parts)
            .map(|_| Soa {
                re: Vec::with_capacity(2 * n * bins),
                im: Vec::with_capacity(2 * n * bins),
            })
            .collect();
        let sigma = match params.weighting {
            Weighting::Constant => 0.0,
            Weighting::OneMinusSr => 1.0,
            Weighting::OnePlusSr => -1.0,
        };
        Ok(WssStream {
            prep,
            base: 0,
            keep,
            drop,
            all_frames,
            raw: (params.refine == Refine::Timing).then(Vec::new),
            any_spikes: false,
            sigma,
            tpl: templates,
            params,
            b,
            pair,
            spectra,
            parts,
            fdl: VecDeque::with_capacity(max_parts + 1),
            spare,
            max_parts,
            tail: vec![[vec![0.0; b], vec![0.0; b]]; nc],
            cp,
            zero_run: 0,
            cands: (0..nc).map(|_| Vec::with_capacity(16)).collect(),
            best: vec![(f64::NEG_INFINITY, 0); nc],
            history: None,
            acc: [soa(bins), soa(bins)],
            z: vec![Complex::new(0.0, 0.0); bins],
            spec: vec![Complex::new(0.0, 0.0); bins],
            buf: vec![0.0; 2 * b],
            out: vec![0.0; 2 * b],
            scratch: vec![Complex::new(0.0, 0.0); scratch],
            fast: super::simd::fast_cpu(),
        })
    }

    /// Also keeps every alignment's score parts, for [`WssStream::series`]
    /// (tests and plots; it grows with the stream). Call before the first frame.
    pub fn with_series(mut self) -> Self {
        self.history = Some(vec![Vec::new(); self.best.len()]);
        self
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.base + self.prep.k
    }

    /// Alignments kept as possible bests, over every class (see the module docs).
    pub fn candidates(&self) -> usize {
        self.cands.iter().map(Vec::len).sum()
    }

    /// `1/M` for the current largest count (0 before any spike).
    fn u(&self) -> f64 {
        let max = self.prep.max_count;
        if max > 0.0 {
            1.0 / max
        } else {
            0.0
        }
    }

    /// Feeds one frame's counts (one per taxel) and returns the running best
    /// estimate, as the batch would give for the frames so far (refinement by
    /// search is left to [`WssStream::estimate`]).
    pub fn push(&mut self, frame: &[f64]) -> Result<Estimate, StageError> {
        let k = self.frames();
        if frame.len() != self.prep.n {
            return Err(StageError::new(format!(
                "wss: frame {k} has {} counts, expected {}",
                frame.len(),
                self.prep.n
            )));
        }
        check_frame(frame, k)?;
        if !self.all_frames && self.prep.k >= self.keep + self.drop {
            self.drop_frames();
        }
        let old_max = self.prep.max_count;
        self.prep.push(frame)?;
        if let Some(raw) = &mut self.raw {
            raw.extend_from_slice(frame);
        }
        let j = self.prep.k - 1;
        let max = self.prep.max_count;
        let c = self.prep.count[j];
        self.any_spikes |= c > 0.0;
        self.cp.push(self.cp[j] + c);
        let grew = max > old_max;
        if grew {
            // Under the new maximum only frames with its count weigh 0.
            self.zero_run = 0;
        }
        if self.weight(j, max) == 0.0 {
            self.zero_run += 1;
        } else {
            self.zero_run = 0;
        }
        let u = self.u();
        let r = k % self.b;
        for cl in 0..self.best.len() {
            let cand = self.score(cl, k, r, max, u);
            if let Some(h) = self.history.as_mut() {
                h[cl].push(cand);
            }
            insert(&mut self.cands[cl], cand, u, self.sigma);
            if !grew {
                let v = cand.value(u, self.sigma);
                if v > self.best[cl].0 {
                    self.best[cl] = (v, k);
                }
            }
        }
        if grew {
            for cl in 0..self.best.len() {
                let mut best = (f64::NEG_INFINITY, 0);
                for c in &self.cands[cl] {
                    let v = c.value(u, self.sigma);
                    if v > best.0 {
                        best = (v, c.k);
                    }
                }
                self.best[cl] = best;
            }
        }
        if r == self.b - 1 {
            self.end_block(k / self.b);
        }
        Ok(self.current(None, None))
    }

    /// Drops the oldest `drop` kept frames (no alignment reads them again).
    fn drop_frames(&mut self) {
        let (d, n) = (self.drop, self.prep.n);
        self.prep.norm.drain(..d * n);
        self.prep.active.drain(..d);
        self.prep.count.drain(..d);
        self.prep.k -= d;
        self.cp.drain(..d);
        let c0 = self.cp[0];
        self.cp.iter_mut().for_each(|v| *v -= c0);
        self.base += d;
    }

    /// Alignment `k` (local frame `prep.k − 1`) of class `cl`, scored under `max`.
    fn score(&self, cl: usize, k: usize, r: usize, max: f64, u: f64) -> Cand {
        let cls = &self.tpl.classes()[cl];
        let j = self.prep.k - 1;
        let (hp, hq) = self.head(cl, j);
        let (p, q) = (hp + self.tail[cl][0][r], hq + self.tail[cl][1][r]);
        let (lo, nw, extra) = window(k, cls.len, self.params.before_start);
        // `keep >= cls.len`, so the window's frames are all kept.
        let s = self.cp[j + 1] - self.cp[lo - self.base];
        let n = nw as f64;
        if extra == 0 && self.zero_run >= nw {
            // Every weight 0: the constant-weight mean, the same under any larger maximum.
            return Cand {
                k,
                num: p,
                den: n,
                q: 0.0,
                s: 0.0,
                u,
            };
        }
        let (num, den) = match self.params.weighting {
            Weighting::Constant => (p, n),
            Weighting::OneMinusSr => (p - q * u, n - s * u),
            Weighting::OnePlusSr => (p + q * u, n + s * u),
        };
        let den = den + extra as f64;
        let (num, den) = if den < GUARD * (nw + extra) as f64 {
            // Tiny weights: sum directly (the window's frames are all kept, and
            // the local index sees the same window as the absolute one).
            let (dn, dd, _) = direct_k(&self.prep, &self.params, max, cls, j);
            (dn, dd)
        } else {
            (num, den)
        };
        Cand { k, num, den, q, s, u }
    }

    /// The best class's score minus the second best's (0 with one class or
    /// before any frame).
    pub fn margin(&self) -> f64 {
        let (mut a, mut b) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for &(s, _) in &self.best {
            if s > a {
                b = a;
                a = s;
            } else if s > b {
                b = s;
            }
        }
        if b == f64::NEG_INFINITY || a == f64::NEG_INFINITY {
            0.0
        } else {
            a - b
        }
    }

    /// `WSS_θ(k)` of every class for every frame so far, with the current
    /// weights; `None` unless the stream was made [`WssStream::with_series`].
    pub fn series(&self) -> Option<Vec<Vec<f64>>> {
        let u = self.u();
        self.history.as_ref().map(|h| {
            h.iter()
                .map(|cs| cs.iter().map(|c| c.value(u, self.sigma)).collect())
                .collect()
        })
    }

    /// The estimate for the frames so far, with every refinement (including
    /// `refine = "search"`, which runs the batch search on the frames kept).
    pub fn estimate(&self) -> Estimate {
        if self.params.refine == Refine::Search {
            let (prep, params, tpl) = (&self.prep, &self.params, &self.tpl);
            let mut spectra = TrialSpectra::default();
            let mut search = |theta: f64| -> f64 {
                match Templates::for_angles(tpl.layout(), tpl.hop_ms(), params, &[theta]) {
                    Ok(one) => best_of(&fast_series_in(&mut spectra, prep, &one, params)[0]).0,
                    Err(_) => f64::NEG_INFINITY,
                }
            };
            self.current(Some(&mut search), None)
        } else {
            self.current(None, self.timing())
        }
    }

    /// The arrival-time plane's angle over the frames so far
    /// (`refine = "timing"`).
    fn timing(&self) -> Option<f64> {
        let raw = self.raw.as_ref()?;
        super::timing::Frames {
            layout: self.tpl.layout(),
            counts: raw,
            hop_ms: self.prep.hop_ms,
            window_ms: self.prep.window_ms,
        }
        .plane(self.params.timing_window_ms)
        .map(|f| f.angle_deg)
    }

    fn current(&self, search: Option<&mut dyn FnMut(f64) -> f64>, timing: Option<f64>) -> Estimate {
        let best: Vec<(f64, usize)> = self
            .best
            .iter()
            .map(|&(s, k)| if s == f64::NEG_INFINITY { (0.0, 0) } else { (s, k) })
            .collect();
        let upto = self.frames();
        finish(
            &self.tpl.angles(),
            &best,
            self.any_spikes,
            (upto > 0).then(|| self.prep.frame_end_ms(upto - 1)),
            &self.params,
            search,
            timing,
        )
    }

    fn weight(&self, j: usize, max: f64) -> f64 {
        super::batch::weight(&self.params, self.prep.count[j], max)
    }

    /// Direct part (templates `0..B`) of `P` and `Q` at local frame `j`.
    fn head(&self, cl: usize, j: usize) -> (f64, f64) {
        let cls = &self.tpl.classes()[cl];
        let h = self.b.min(cls.len).min(j + 1);
        super::simd::head(
            self.fast,
            &self.prep.norm,
            &self.prep.active,
            &self.prep.count,
            &cls.data,
            self.prep.n,
            j,
            h,
        )
    }

    /// Block `blk` is complete: add its input spectra to the delay line and
    /// compute every class's tail for block `blk + 1`.
    fn end_block(&mut self, blk: usize) {
        let (b, n) = (self.b, self.prep.n);
        let bins = b + 1;
        // Reuse the delay line's oldest entry when it is full, else a reserved one.
        let mut spec = if self.fdl.len() >= self.max_parts {
            self.fdl.pop_back().map(|(s, _)| s).unwrap_or_default()
        } else {
            self.spare.pop().unwrap_or_default()
        };
        spec.re.clear();
        spec.re.resize(2 * n * bins, 0.0);
        spec.im.clear();
        spec.im.resize(2 * n * bins, 0.0);
        let mut any = false;
        for s in 0..2 {
            for t in 0..n {
                let mut nz = false;
                for j in 0..2 * b {
                    // Segment [x_{blk−1}, x_blk] (kept: `keep >= 2B`).
                    let m = (blk * b + j) as isize - b as isize;
                    let v = if m >= 0 {
                        let m = m as usize - self.base;
                        let x = self.prep.norm[m * n + t];
                        if s == 0 {
                            x
                        } else {
                            self.prep.count[m] * x
                        }
                    } else {
                        0.0
                    };
                    self.buf[j] = v;
                    nz |= v != 0.0;
                }
                if nz {
                    any = true;
                    let o = (s * n + t) * bins;
                    let _ =
                        self.pair
                            .fwd
                            .process_with_scratch(&mut self.buf, &mut self.spec, &mut self.scratch);
                    for (f, z) in self.spec.iter().enumerate() {
                        spec.re[o + f] = z.re;
                        spec.im[o + f] = z.im;
                    }
                }
            }
        }
        self.fdl.push_front((spec, any));
        self.fdl.truncate(self.max_parts);
        for cl in 0..self.best.len() {
            let parts = self.parts[cl];
            let spectra = &self.spectra[cl];
            for a in self.acc.iter_mut() {
                a.re.iter_mut().for_each(|v| *v = 0.0);
                a.im.iter_mut().for_each(|v| *v = 0.0);
            }
            let mut used = false;
            // Partition p pairs with the block p − 1 back from the newest.
            for p in 1..parts.min(self.fdl.len() + 1) {
                let (x, nz) = &self.fdl[p - 1];
                if !nz {
                    continue;
                }
                used = true;
                for t in 0..n {
                    let ho = ((p - 1) * n + t) * bins;
                    let h = (&spectra.re[ho..ho + bins], &spectra.im[ho..ho + bins]);
                    for s in 0..2 {
                        let xo = (s * n + t) * bins;
                        let xs = (&x.re[xo..xo + bins], &x.im[xo..xo + bins]);
                        super::batch::cmac(self.fast, &mut self.acc[s], xs, h);
                    }
                }
            }
            for s in 0..2 {
                if !used {
                    self.tail[cl][s].iter_mut().for_each(|v| *v = 0.0);
                    continue;
                }
                for (f, v) in self.z.iter_mut().enumerate() {
                    *v = Complex::new(self.acc[s].re[f], self.acc[s].im[f]);
                }
                self.z[0].im = 0.0;
                self.z[b].im = 0.0;
                let _ = self
                    .pair
                    .inv
                    .process_with_scratch(&mut self.z, &mut self.out, &mut self.scratch);
                self.tail[cl][s].copy_from_slice(&self.out[b..2 * b]);
            }
        }
    }
}

fn soa(n: usize) -> Soa {
    Soa {
        re: vec![0.0; n],
        im: vec![0.0; n],
    }
}

/// [`dominates`] and scores on bare parts `[num, den, q, s]`, for tests.
#[cfg(test)]
pub(crate) mod tests_support {
    use super::{dominates, Cand};

    fn cand(p: [f64; 4], u: f64) -> Cand {
        Cand {
            k: 0,
            num: p[0],
            den: p[1],
            q: p[2],
            s: p[3],
            u,
        }
    }

    pub(crate) fn dominates_parts(a: [f64; 4], b: [f64; 4], u: f64, sigma: f64, strict: bool) -> bool {
        dominates(&cand(a, u), &cand(b, u), u, sigma, strict)
    }

    /// Score at `u2 <= u` of parts scored at `u`.
    pub(crate) fn value_parts(p: [f64; 4], u: f64, u2: f64, sigma: f64) -> f64 {
        cand(p, u).value(u2, sigma)
    }
}
