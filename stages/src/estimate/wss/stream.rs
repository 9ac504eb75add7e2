//! Streaming WSS: frame by frame, with the running best estimate after every
//! frame, equal to the batch result at the end.
//!
//! # Semantics
//!
//! After frame `k` the stream answers `argmax_θ max_{k' ≤ k} WSS_θ(k')` with the
//! weights of eq. 5 normalised by the largest frame count seen so far, `M_k`: it
//! is exactly the batch estimate of the trial truncated after frame `k`. Since
//! `M` can grow, the weights of earlier alignments change with it; the stream
//! keeps, per class and alignment, the sufficient statistics
//! `P_θ(k) = Σ_i R_{k−i,i}` and `Q_θ(k) = Σ_i C_{k−i} R_{k−i,i}` (`C` the frame's
//! count), with which `Σ_i w_{k−i} R = P ∓ Q/M` and `Σ_i w = n ∓ ΣC/M` for
//! `w = 1 ∓ SR`. When `M` grows, every stored alignment is re-scored:
//! `O(classes·K)` cheap arithmetic, which happens only on frames that set a new
//! maximum (a handful per trial; every frame only in a trial whose counts rise
//! monotonically). Memory: `O(K·(classes + taxels))`.
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
//! Rounding: `P ∓ Q/M` differs from the batch's directly weighted sums by
//! ~1e-13; windows whose weights average under 1e-3 per term are re-summed
//! directly (as in the batch), so the two agree to well under 1e-9.

use super::batch::{best_of, combine, direct_value, fast_series, finish, window, Prepared, GUARD};
use super::params::{Refine, Weighting, WssParams};
use super::templates::{FftPair, Soa, Spectra, Templates};
use palpate_core::{Estimate, StageError};
use realfft::num_complex::Complex;
use std::collections::VecDeque;
use std::sync::Arc;

/// Frames per partition block.
const BLOCK: usize = 64;

/// A frame-by-frame WSS estimator for one trial.
pub struct WssStream {
    tpl: Arc<Templates>,
    params: WssParams,
    prep: Prepared,
    b: usize,
    pair: FftPair,
    spectra: Vec<Spectra>,
    parts: Vec<usize>,
    /// Input spectra `[seq][taxel][bin]` of completed blocks, newest first,
    /// with a flag for "not all zero".
    fdl: VecDeque<(Soa, bool)>,
    max_parts: usize,
    /// Per class, tails of `P` and `Q` for the current block.
    tail: Vec<[Vec<f64>; 2]>,
    p: Vec<Vec<f64>>,
    q: Vec<Vec<f64>>,
    /// Prefix sums of counts.
    cp: Vec<f64>,
    /// Prefix counts of frames with a non-zero weight under the current maximum.
    nzp: Vec<usize>,
    best: Vec<(f64, usize)>,
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
        Ok(WssStream {
            prep: Prepared::empty(n, templates.hop_ms(), window_ms),
            tpl: templates,
            params,
            b,
            pair,
            spectra,
            parts,
            fdl: VecDeque::new(),
            max_parts,
            tail: vec![[vec![0.0; b], vec![0.0; b]]; nc],
            p: vec![Vec::new(); nc],
            q: vec![Vec::new(); nc],
            cp: vec![0.0],
            nzp: vec![0],
            best: vec![(f64::NEG_INFINITY, 0); nc],
            acc: [soa(b + 1), soa(b + 1)],
            z: vec![Complex::new(0.0, 0.0); b + 1],
            spec: vec![Complex::new(0.0, 0.0); b + 1],
            buf: vec![0.0; 2 * b],
            out: vec![0.0; 2 * b],
            scratch: vec![Complex::new(0.0, 0.0); scratch],
            fast: super::simd::fast_cpu(),
        })
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.prep.k
    }

    /// Feeds one frame's counts (one per taxel) and returns the running best
    /// estimate, as the batch would give for the frames so far (refinement by
    /// search is left to [`WssStream::estimate`]).
    pub fn push(&mut self, frame: &[f64]) -> Result<Estimate, StageError> {
        let old_max = self.prep.max_count;
        self.prep.push(frame)?;
        let k = self.prep.k - 1;
        let max = self.prep.max_count;
        let c = self.prep.count[k];
        self.cp.push(self.cp[k] + c);
        let grew = max > old_max;
        if grew {
            // Weights depend on the maximum: recount the non-zero ones.
            self.nzp.truncate(1);
            for m in 0..=k {
                let nz = self.weight(m, max) != 0.0;
                self.nzp.push(self.nzp[m] + usize::from(nz));
            }
        } else {
            let nz = self.weight(k, max) != 0.0;
            self.nzp.push(self.nzp[k] + usize::from(nz));
        }
        let r = k % self.b;
        for cl in 0..self.best.len() {
            let (hp, hq) = self.head(cl, k);
            self.p[cl].push(hp + self.tail[cl][0][r]);
            self.q[cl].push(hq + self.tail[cl][1][r]);
        }
        if grew {
            for cl in 0..self.best.len() {
                let mut best = (f64::NEG_INFINITY, 0);
                for kk in 0..=k {
                    let v = self.value(cl, kk, max);
                    if v > best.0 {
                        best = (v, kk);
                    }
                }
                self.best[cl] = best;
            }
        } else {
            for cl in 0..self.best.len() {
                let v = self.value(cl, k, max);
                if v > self.best[cl].0 {
                    self.best[cl] = (v, k);
                }
            }
        }
        if r == self.b - 1 {
            self.end_block(k / self.b);
        }
        Ok(self.current(None))
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

    /// `WSS_θ(k)` of every class for every frame so far, with the current weights.
    pub fn series(&self) -> Vec<Vec<f64>> {
        let max = self.prep.max_count;
        (0..self.best.len())
            .map(|c| (0..self.prep.k).map(|k| self.value(c, k, max)).collect())
            .collect()
    }

    /// The estimate for the frames so far, with every refinement (including
    /// `refine = "search"`, which runs the batch search on the frames kept).
    pub fn estimate(&self) -> Estimate {
        if self.params.refine == Refine::Search {
            let (prep, params, tpl) = (&self.prep, &self.params, &self.tpl);
            let mut search = |theta: f64| -> f64 {
                match Templates::for_angles(tpl.layout(), tpl.hop_ms(), params, &[theta]) {
                    Ok(one) => best_of(&fast_series(prep, &one, params)[0]).0,
                    Err(_) => f64::NEG_INFINITY,
                }
            };
            self.current(Some(&mut search))
        } else {
            self.current(None)
        }
    }

    fn current(&self, search: Option<&mut dyn FnMut(f64) -> f64>) -> Estimate {
        let best: Vec<(f64, usize)> = self
            .best
            .iter()
            .map(|&(s, k)| if s == f64::NEG_INFINITY { (0.0, 0) } else { (s, k) })
            .collect();
        finish(
            &self.tpl.angles(),
            &best,
            &self.prep,
            self.prep.k,
            &self.params,
            search,
        )
    }

    fn weight(&self, m: usize, max: f64) -> f64 {
        super::batch::weight(&self.params, self.prep.count[m], max)
    }

    /// `WSS` of class `cl` at alignment `k` from the stored statistics.
    fn value(&self, cl: usize, k: usize, max: f64) -> f64 {
        let cls = &self.tpl.classes()[cl];
        let (lo, nw, extra) = window(k, cls.len, self.params.before_start);
        let (p, q) = (self.p[cl][k], self.q[cl][k]);
        let u = if max > 0.0 { 1.0 / max } else { 0.0 };
        let csum = self.cp[k + 1] - self.cp[lo];
        let n = nw as f64;
        let (num, den) = match self.params.weighting {
            Weighting::Constant => (p, n),
            Weighting::OneMinusSr => (p - q * u, n - csum * u),
            Weighting::OnePlusSr => (p + q * u, n + csum * u),
        };
        let den = den + extra as f64;
        let all_zero = extra == 0 && self.nzp[k + 1] == self.nzp[lo];
        if all_zero {
            combine(num, den, p, nw, true)
        } else if den < GUARD * (nw + extra) as f64 {
            direct_value(&self.prep, &self.params, max, cls, k)
        } else {
            num / den
        }
    }

    /// Direct part (templates `0..B`) of `P` and `Q` at `k`.
    fn head(&self, cl: usize, k: usize) -> (f64, f64) {
        let cls = &self.tpl.classes()[cl];
        let h = self.b.min(cls.len).min(k + 1);
        super::simd::head(
            self.fast,
            &self.prep.norm,
            &self.prep.active,
            &self.prep.count,
            &cls.data,
            self.prep.n,
            k,
            h,
        )
    }

    /// Block `blk` is complete: add its input spectra to the delay line and
    /// compute every class's tail for block `blk + 1`.
    fn end_block(&mut self, blk: usize) {
        let (b, n) = (self.b, self.prep.n);
        let bins = b + 1;
        // Reuse the delay line's oldest entry when it is full.
        let mut spec = if self.fdl.len() >= self.max_parts {
            self.fdl.pop_back().map(|(s, _)| s).unwrap_or_default()
        } else {
            Soa::default()
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
                    // Segment [x_{blk−1}, x_blk].
                    let m = (blk * b + j) as isize - b as isize;
                    let v = if m >= 0 {
                        let m = m as usize;
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
