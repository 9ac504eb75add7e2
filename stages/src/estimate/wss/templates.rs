//! Simulated edge templates (paper eq. 6) and their cached FFT spectra.
//!
//! For a class `θ`, with the array's unit normal `n = (sin θ, −cos θ)`
//! (core/src/geometry.rs), taxel `t`'s offset `o_t = n·p_t`, and the footprint
//! `[lo, hi]` of `n·p` over every taxel's area, the simulated line of template
//! `i` sits at offset `s_i = lo + i·Δs`, `Δs = v·sin θ·hop` (the distance the
//! line moves along `n` in one frame hop). Template 0 is the line just leaving
//! the array; `k(θ) = ⌈(hi − lo)/Δs⌉` frames take it back to where it first
//! touches a taxel. Taxel values are `exp(−d²/σ²)` with
//! `d = max(0, |o_t − s_i| − w/2)`, the distance from the taxel's centre to the
//! line of width `w`.
//!
//! Because `Δs ∝ sin θ`, `k(θ)` grows like `1/sin θ` near 0 and 180 degrees
//! (about 320 s at 1 degree on the paper's array at 2 mm/s). Templates are capped
//! at `max_template_s` of palpation: a longer crossing keeps its last part (the
//! templates nearest the line leaving the array, `i` small), which is the part
//! every alignment `k` uses first.
//!
//! Each template is stored centred and scaled to unit norm (`S̃_i`), or as zeros
//! when it has no spatial variance, so that Pearson's `R(I, S_i) = <Ĩ, S̃_i>`
//! with `Ĩ` the centred unit-norm frame.

use super::params::WssParams;
use palpate_core::geometry::Edge;
use palpate_core::{ConfigError, TaxelLayout};
use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Complex values stored as separate real and imaginary parts, so that the
/// frequency-domain multiply-accumulate loops vectorise.
#[derive(Clone, Debug, Default)]
pub(crate) struct Soa {
    pub re: Vec<f64>,
    pub im: Vec<f64>,
}

impl Soa {
    pub(crate) fn from_complex(v: &[Complex<f64>]) -> Soa {
        Soa {
            re: v.iter().map(|z| z.re).collect(),
            im: v.iter().map(|z| z.im).collect(),
        }
    }
}

/// A spectrum set: `[taxel][bin]` for one class (batch), or
/// `[partition][taxel][bin]` (streaming), flattened.
pub(crate) type Spectra = Arc<Soa>;

/// Bytes of batch spectra kept before the cache is emptied (a run over many
/// trial lengths would otherwise keep one set per length class). 64 MiB: with
/// the depth-first runtime this cache is the largest part of a run's peak
/// (256 MiB of the quickstart's 345 MB before).
const BATCH_CACHE_BYTES: usize = 64 << 20;

/// The templates of one class.
#[derive(Clone, Debug)]
pub struct ClassTemplates {
    /// The class's angle, degrees.
    pub angle_deg: f64,
    /// `k(θ)`: frames the line needs to cross the array (uncapped).
    pub crossing_frames: f64,
    /// Templates kept: `min(k(θ) + 1, cap)`.
    pub len: usize,
    /// `S̃_i[t]` at `i * n_taxels + t`, centred, unit norm (or zeros).
    pub data: Vec<f64>,
}

impl ClassTemplates {
    /// Template `i`, one value per taxel.
    pub fn template(&self, i: usize) -> &[f64] {
        let n = self.data.len() / self.len.max(1);
        &self.data[i * n..(i + 1) * n]
    }
}

#[derive(Default)]
struct Caches {
    batch: HashMap<(usize, usize, usize), Spectra>,
    batch_bytes: usize,
    stream: HashMap<(usize, usize), Spectra>,
    plans: HashMap<usize, FftPair>,
}

/// A forward and an inverse real FFT of one length.
#[derive(Clone)]
pub(crate) struct FftPair {
    pub fwd: Arc<dyn RealToComplex<f64>>,
    pub inv: Arc<dyn ComplexToReal<f64>>,
}

/// Every class's templates for one (layout, hop, parameters), with lazily built,
/// cached FFT spectra.
pub struct Templates {
    layout: TaxelLayout,
    hop_ms: f64,
    classes: Vec<ClassTemplates>,
    caches: Mutex<Caches>,
}

impl std::fmt::Debug for Templates {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Templates")
            .field("layout", &self.layout)
            .field("hop_ms", &self.hop_ms)
            .field("classes", &self.classes.len())
            .finish()
    }
}

/// The raw (uncentred) template `i` of class `theta_deg`: `exp(−d²/σ²)` per taxel.
/// Exposed for the reference implementation and plots.
pub fn raw_template(
    layout: &TaxelLayout,
    hop_ms: f64,
    params: &WssParams,
    theta_deg: f64,
    i: usize,
) -> Vec<f64> {
    let edge = Edge::new(theta_deg);
    let (lo, _) = edge.footprint(layout);
    let ds = edge.normal_speed(params.speed_mm_s) * hop_ms / 1000.0;
    let s = lo + i as f64 * ds;
    let half = params.line_width_mm / 2.0;
    let inv_s2 = 1.0 / (params.sigma_mm * params.sigma_mm);
    layout
        .positions()
        .into_iter()
        .map(|p| {
            let d = ((edge.offset(p) - s).abs() - half).max(0.0);
            (-d * d * inv_s2).exp()
        })
        .collect()
}

/// `k(θ)` (frames to cross the array, uncapped, as a float) and the number of
/// templates kept.
fn lengths(layout: &TaxelLayout, hop_ms: f64, params: &WssParams, theta_deg: f64) -> (f64, usize) {
    let edge = Edge::new(theta_deg);
    let (lo, hi) = edge.footprint(layout);
    let ds = edge.normal_speed(params.speed_mm_s) * hop_ms / 1000.0;
    let k = ((hi - lo) / ds).ceil().max(0.0);
    let cap = (params.max_template_s * 1000.0 / hop_ms).floor() + 1.0;
    // Both are finite and positive here (validated inputs); `as` saturates anyway.
    (k, (k + 1.0).min(cap).max(1.0) as usize)
}

/// Centres `v` and scales it to unit norm in place; zeros it when its variance
/// is negligible (below 1e-20 of its energy, i.e. rounding noise), so that a
/// constant image correlates 0 with everything.
pub(crate) fn normalize(v: &mut [f64]) -> bool {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let energy: f64 = v.iter().map(|x| x * x).sum();
    let ss: f64 = v.iter().map(|x| (x - mean) * (x - mean)).sum();
    if !ss.is_finite() || ss <= 1e-20 * energy {
        v.iter_mut().for_each(|x| *x = 0.0);
        return false;
    }
    let inv = 1.0 / ss.sqrt();
    v.iter_mut().for_each(|x| *x = (*x - mean) * inv);
    true
}

impl Templates {
    /// Builds every class's templates for images of `layout` taken every
    /// `hop_ms`. Errors name the key at fault (`layout`, `hop_ms`, or a parameter).
    pub fn new(layout: &TaxelLayout, hop_ms: f64, params: &WssParams) -> Result<Templates, ConfigError> {
        Self::for_angles(layout, hop_ms, params, &params.angles)
    }

    /// Like [`Templates::new`] for an explicit list of angles (used by the
    /// refining search).
    pub fn for_angles(
        layout: &TaxelLayout,
        hop_ms: f64,
        params: &WssParams,
        angles: &[f64],
    ) -> Result<Templates, ConfigError> {
        params.validate()?;
        layout.validate().map_err(|m| ConfigError::key("layout", m))?;
        palpate_core::check_positive("hop_ms", hop_ms, "ms")?;
        let n = layout.len();
        let classes = angles
            .iter()
            .map(|&a| {
                let (crossing_frames, len) = lengths(layout, hop_ms, params, a);
                let mut data = Vec::with_capacity(len * n);
                for i in 0..len {
                    let mut t = raw_template(layout, hop_ms, params, a, i);
                    normalize(&mut t);
                    data.extend_from_slice(&t);
                }
                ClassTemplates {
                    angle_deg: a,
                    crossing_frames,
                    len,
                    data,
                }
            })
            .collect();
        Ok(Templates {
            layout: layout.clone(),
            hop_ms,
            classes,
            caches: Mutex::new(Caches::default()),
        })
    }

    /// The layout the templates were built for.
    pub fn layout(&self) -> &TaxelLayout {
        &self.layout
    }

    /// The frame hop the templates were built for, ms.
    pub fn hop_ms(&self) -> f64 {
        self.hop_ms
    }

    /// Every class, in grid order.
    pub fn classes(&self) -> &[ClassTemplates] {
        &self.classes
    }

    /// Every class's angle, degrees, in grid order.
    pub fn angles(&self) -> Vec<f64> {
        self.classes.iter().map(|c| c.angle_deg).collect()
    }

    /// Number of taxels.
    pub fn n_taxels(&self) -> usize {
        self.layout.len()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Caches> {
        // A poisoned cache only means another thread panicked mid-insert of a
        // complete value; the map itself is still consistent.
        self.caches.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Forward and inverse real FFTs of length `len`, planned once.
    pub(crate) fn plan(&self, len: usize) -> FftPair {
        let mut c = self.lock();
        c.plans
            .entry(len)
            .or_insert_with(|| {
                let mut p = RealFftPlanner::<f64>::new();
                FftPair {
                    fwd: p.plan_fft_forward(len),
                    inv: p.plan_fft_inverse(len),
                }
            })
            .clone()
    }

    /// Spectra `[taxel][bin]` of class `c`'s first `h` templates, zero-padded to
    /// `fft_len`, scaled by `1/fft_len` so that the inverse FFT of a product is
    /// the convolution.
    pub(crate) fn batch_spectra(&self, c: usize, fft_len: usize, h: usize) -> Spectra {
        if let Some(s) = self.lock().batch.get(&(c, fft_len, h)) {
            return s.clone();
        }
        let pair = self.plan(fft_len);
        let cls = &self.classes[c];
        let n = self.n_taxels();
        let bins = fft_len / 2 + 1;
        let h = h.min(cls.len).min(fft_len);
        let scale = 1.0 / fft_len as f64;
        let mut out = vec![Complex::new(0.0, 0.0); n * bins];
        let mut buf = vec![0.0; fft_len];
        for t in 0..n {
            buf.iter_mut().for_each(|x| *x = 0.0);
            for (i, v) in buf.iter_mut().take(h).enumerate() {
                *v = cls.data[i * n + t] * scale;
            }
            // Lengths match by construction, so the FFT cannot fail.
            let _ = pair.fwd.process(&mut buf, &mut out[t * bins..(t + 1) * bins]);
        }
        let s = Arc::new(Soa::from_complex(&out));
        let mut cache = self.lock();
        let bytes = n * bins * 16;
        if cache.batch_bytes + bytes > BATCH_CACHE_BYTES {
            cache.batch.clear();
            cache.batch_bytes = 0;
        }
        cache.batch_bytes += bytes;
        cache.batch.insert((c, fft_len, h), s.clone());
        s
    }

    /// Partition spectra for uniformly partitioned streaming convolution with
    /// block `b`: for partitions `p = 1 .. ⌈len/b⌉`, the spectra (FFT length
    /// `2b`, scaled by `1/(2b)`) of templates `p·b .. p·b + b` of class `c`,
    /// `[p - 1][taxel][bin]`. Partition 0 is computed directly, so it is absent.
    pub(crate) fn stream_spectra(&self, c: usize, b: usize) -> Spectra {
        if let Some(s) = self.lock().stream.get(&(c, b)) {
            return s.clone();
        }
        let fft_len = 2 * b;
        let pair = self.plan(fft_len);
        let cls = &self.classes[c];
        let n = self.n_taxels();
        let bins = b + 1;
        let parts = cls.len.div_ceil(b);
        let scale = 1.0 / fft_len as f64;
        let mut out = vec![Complex::new(0.0, 0.0); parts.saturating_sub(1) * n * bins];
        let mut buf = vec![0.0; fft_len];
        for p in 1..parts {
            for t in 0..n {
                buf.iter_mut().for_each(|x| *x = 0.0);
                for (j, v) in buf.iter_mut().take(b).enumerate() {
                    let i = p * b + j;
                    if i < cls.len {
                        *v = cls.data[i * n + t] * scale;
                    }
                }
                let o = ((p - 1) * n + t) * bins;
                let _ = pair.fwd.process(&mut buf, &mut out[o..o + bins]);
            }
        }
        let s = Arc::new(Soa::from_complex(&out));
        self.lock().stream.insert((c, b), s.clone());
        s
    }
}
