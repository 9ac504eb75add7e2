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

use super::params::{Distance, WssParams};
use crate::estimate::vmath;
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

/// Most bytes of batch spectra a template set keeps (see [`SpectraLru`]): a
/// run over many trial lengths would otherwise keep one set per length
/// class. 64 MiB: with the depth-first runtime this cache is the largest
/// part of a run's peak (256 MiB of the quickstart's 345 MB before).
const BATCH_CACHE_BYTES: usize = 64 << 20;

/// The batch spectra of one template set, keyed by `(class, FFT length,
/// templates used)`, within a byte budget.
///
/// Why this policy: a trial asks for every class's spectra at one FFT length
/// (its classes share it, `batch::Fft::plan`), class after class, and the
/// next trials (the same angle, mostly) ask again at the same length. The
/// earlier policy emptied the whole cache when an insert overflowed it. At
/// the longest lab trials one class set (33 classes x 16 taxels x 8193 bins
/// x 16 bytes, 69 MB) exceeds 64 MiB, so every trial emptied it half-way
/// and computed every class's 16 FFTs again; at the other lengths a change
/// of length emptied the sets the next trials needed with the rest. Making
/// spectra was 29 % of a joint angle-speed search's samples, the searches'
/// probes included (`graphs/paper/speed_error.toml`, `joint` series; `perf`).
///
/// Now an insert that does not fit evicts the least recently used entries
/// *of other FFT lengths* (the sets of earlier trial lengths); when only
/// entries of the inserted one's length are left, it is not kept (returned
/// uncached) rather than evicting a class the next trial will ask for: an
/// over-budget set keeps most of its classes cached instead of none. A
/// cache only: the spectra are the same bits either way.
#[derive(Default)]
pub(crate) struct SpectraLru {
    entries: HashMap<(usize, usize, usize), (Spectra, u64)>,
    bytes: usize,
    /// Use counter: an entry's stamp is the count at its last use.
    tick: u64,
}

impl SpectraLru {
    /// The entry for `key`, marked as just used.
    pub(crate) fn get(&mut self, key: (usize, usize, usize)) -> Option<Spectra> {
        self.tick += 1;
        let tick = self.tick;
        self.entries.get_mut(&key).map(|(s, t)| {
            *t = tick;
            s.clone()
        })
    }

    /// A set's payload bytes (both parts).
    fn bytes(s: &Soa) -> usize {
        (s.re.len() + s.im.len()) * 8
    }

    /// Keeps `s` under `key` if it fits within `budget` bytes after
    /// evicting least recently used entries of other FFT lengths (`key.1`);
    /// returns whether it was kept.
    pub(crate) fn insert(&mut self, key: (usize, usize, usize), s: Spectra, budget: usize) -> bool {
        let bytes = Self::bytes(&s);
        if self.entries.contains_key(&key) {
            return true;
        }
        if bytes > budget {
            return false;
        }
        while self.bytes + bytes > budget {
            let victim = self
                .entries
                .iter()
                .filter(|((_, len, _), _)| *len != key.1)
                .min_by_key(|(_, (_, t))| *t)
                .map(|(k, (s, _))| (*k, Self::bytes(s)));
            let Some((k, b)) = victim else {
                return false;
            };
            self.entries.remove(&k);
            self.bytes -= b;
        }
        self.tick += 1;
        self.bytes += bytes;
        self.entries.insert(key, (s, self.tick));
        true
    }

    /// Entries kept.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.entries.len()
    }
}

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
    batch: SpectraLru,
    stream: HashMap<(usize, usize), Spectra>,
}

/// Most FFT lengths whose plans [`shared_plan`] keeps; past it the plans are
/// dropped and planned again as needed (plans in use live on: they are
/// shared). FFT lengths are of the forms 2^j, 3·2^j, 5·2^j and 9·2^j
/// (`nice_len`), so few distinct ones occur.
const SHARED_PLANS: usize = 64;

/// A process-wide plan of the forward and inverse real FFTs of length `len`.
///
/// Why process-wide and not per template set: a refinement search builds a
/// new one-angle template set at every step, and each planned its FFTs
/// afresh (twiddle factors: a sine and cosine per point; buffers): the
/// planner's `sincos` alone was ~4 % of a joint speed search's profile. A
/// plan is a deterministic function of the length and the CPU, so sharing
/// it does not change a bit.
pub(crate) fn shared_plan(len: usize) -> FftPair {
    static PLANS: Mutex<Option<HashMap<usize, FftPair>>> = Mutex::new(None);
    let mut guard = PLANS.lock().unwrap_or_else(|e| e.into_inner());
    let plans = guard.get_or_insert_with(HashMap::new);
    if let Some(p) = plans.get(&len) {
        return p.clone();
    }
    if plans.len() >= SHARED_PLANS {
        plans.clear();
    }
    let mut planner = RealFftPlanner::<f64>::new();
    let pair = FftPair {
        fwd: planner.plan_fft_forward(len),
        inv: planner.plan_fft_inverse(len),
    };
    plans.insert(len, pair.clone());
    pair
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
    ClassShape::new(layout, hop_ms, params, theta_deg).template(i)
}

/// The raw templates `0..len` of class `theta_deg` ([`raw_template`] each).
pub(crate) fn raw_templates(
    layout: &TaxelLayout,
    hop_ms: f64,
    params: &WssParams,
    theta_deg: f64,
    len: usize,
) -> Vec<Vec<f64>> {
    let shape = ClassShape::new(layout, hop_ms, params, theta_deg);
    (0..len).map(|i| shape.template(i)).collect()
}

/// What one class's templates share: the edge, the line's first offset and
/// step, and (for [`Distance::Area`]) the tabulated taxel response.
struct ClassShape {
    offsets: Vec<f64>,
    lo: f64,
    ds: f64,
    half: f64,
    inv_s2: f64,
    table: Option<AreaTable>,
}

impl ClassShape {
    fn new(layout: &TaxelLayout, hop_ms: f64, params: &WssParams, theta_deg: f64) -> ClassShape {
        let edge = Edge::new(theta_deg);
        let (lo, _) = edge.footprint(layout);
        let ds = edge.normal_speed(params.speed()) * hop_ms / 1000.0;
        let half = params.line_width_mm / 2.0;
        let table = (params.distance == Distance::Area)
            .then(|| AreaTable::new(edge.normal, layout.taxel_mm(), half, params.sigma_mm));
        ClassShape {
            offsets: layout.positions().into_iter().map(|p| edge.offset(p)).collect(),
            lo,
            ds,
            half,
            inv_s2: 1.0 / (params.sigma_mm * params.sigma_mm),
            table,
        }
    }

    /// Template `i`: the line at offset `lo + i·Δs`.
    fn template(&self, i: usize) -> Vec<f64> {
        let mut v = vec![0.0; self.offsets.len()];
        self.template_into(i, &mut v);
        v
    }

    /// Templates `0, 1, ...` into the frames of `out` (`n` values each,
    /// frame-major), each [`Self::template_into`]'s values: the exponent
    /// arguments of every frame first, then one [`vmath::exp_in_place`]
    /// pass (the exponential is element-wise, so the same bits). A refining
    /// search builds a class per probe; one call per 16-value frame was most
    /// of that.
    fn templates_into(&self, out: &mut [f64]) {
        let n = self.offsets.len().max(1);
        if self.table.is_some() {
            for (i, t) in out.chunks_exact_mut(n).enumerate() {
                self.template_into(i, t);
            }
            return;
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                for (i, t) in out.chunks_exact_mut(n).enumerate() {
                    let s = self.lo + i as f64 * self.ds;
                    for (v, &o) in t.iter_mut().zip(&self.offsets) {
                        *v = self.exponent(o, s);
                    }
                }
            },
        );
        vmath::exp_in_place(out);
    }

    /// The Gaussian profile's exponent `−d²/σ²` for a taxel at offset `o`
    /// from the line at `s` (`d` past the line's half width): one
    /// expression for [`Self::template_into`] and [`Self::templates_into`],
    /// so the two give the same bits.
    #[inline(always)]
    fn exponent(&self, o: f64, s: f64) -> f64 {
        let d = ((o - s).abs() - self.half).max(0.0);
        -d * d * self.inv_s2
    }

    /// [`Self::template`] into `out` (one value per taxel), without
    /// allocating: a refining search builds a class's templates per probe.
    ///
    /// The Gaussian profile's exponential is [`vmath::exp`], not `f64::exp`:
    /// glibc's is a call per value that picks an FMA or a non-FMA variant
    /// at run time, so a template's last bits (and, through a refining
    /// search's comparisons, in rare ties an estimate's) depended on the
    /// CPU; `vmath::exp` gives the same bits on every x86-64 CPU and a
    /// row's values in one vectorised pass. It is within an ulp of glibc's
    /// (its module docs).
    fn template_into(&self, i: usize, out: &mut [f64]) {
        let s = self.lo + i as f64 * self.ds;
        match &self.table {
            Some(t) => {
                for (v, &o) in out.iter_mut().zip(&self.offsets) {
                    *v = t.value(o - s);
                }
            }
            None => crate::wide::with_avx2(
                #[inline(always)]
                || {
                    for (v, &o) in out.iter_mut().zip(&self.offsets) {
                        *v = vmath::exp(self.exponent(o, s));
                    }
                },
            ),
        }
    }
}

/// [`area_mean`] of one class tabulated over the distance `|c|` of a taxel's
/// centre from the line, read by linear interpolation: a class's templates need
/// `k(θ)·taxels` values (tens of thousands near 10 degrees) but only this one
/// curve. Step `σ/100` (interpolation error below `3e-4`, the curve's second
/// derivative being at most `2/σ²`), to the distance where the mean is 0.
struct AreaTable {
    step: f64,
    values: Vec<f64>,
}

impl AreaTable {
    fn new(n: [f64; 2], a: f64, h: f64, sigma: f64) -> AreaTable {
        // Beyond the taxel's half-footprint plus the flat top plus 6 σ, every
        // point of the taxel is farther than 6 σ from the line: exp(−36) ≈ 0.
        let reach = a / 2.0 * (n[0].abs() + n[1].abs()) + h + 6.0 * sigma;
        let step = sigma / 100.0;
        // reach / step is at most ~1e7 for validated inputs (σ, a, h are
        // checked positive and finite; a/σ is bounded by the layout check).
        let points = ((reach / step).ceil() as usize + 2).min(1 << 20);
        let step = reach / (points - 2) as f64;
        let values = (0..points)
            .map(|j| area_mean(j as f64 * step, n, a, h, sigma))
            .collect();
        AreaTable { step, values }
    }

    fn value(&self, c: f64) -> f64 {
        let x = c.abs() / self.step;
        let j = x.floor() as usize;
        if j + 1 >= self.values.len() {
            return 0.0;
        }
        let f = x - j as f64;
        self.values[j] * (1.0 - f) + self.values[j + 1] * f
    }
}

/// Points of the midpoint rule across the taxel (along its axis less aligned
/// with the line's normal; the other axis is integrated exactly).
const AREA_POINTS: usize = 8;

/// Mean over a square taxel of side `a` whose centre sits at signed distance
/// `c` from the line's centre, of `f(u) = exp(−max(0, |u| − h)²/σ²)`, `u` the
/// signed distance of a point of the taxel to the line (unit normal `n`,
/// line half-width `h`).
///
/// `u = c + n₀x + n₁y` over `x, y ∈ [−a/2, a/2]`. Along the axis with the larger
/// normal component `A` the mean is exact, `(F(c + Aa/2) − F(c − Aa/2)) / (Aa)`
/// with `F` the antiderivative of `f` (erfc-based, [`flat_gauss_integral`]);
/// along the other, `B ≤ A`, it is an 8-point midpoint rule (`f` varies over at
/// most `Ba ≤ a/√2`).
fn area_mean(c: f64, n: [f64; 2], a: f64, h: f64, sigma: f64) -> f64 {
    let (p, q) = (n[0].abs(), n[1].abs());
    let (big, small) = if p >= q { (p, q) } else { (q, p) };
    let half = big * a / 2.0;
    let mut sum = 0.0;
    for j in 0..AREA_POINTS {
        let x = ((j as f64 + 0.5) / AREA_POINTS as f64 - 0.5) * a;
        // f is even: work on the left of the line, where F's tail is exact.
        let cc = -(c + small * x).abs();
        let (lo, hi) = (cc - half, cc + half);
        sum += (flat_gauss_integral(hi, h, sigma) - flat_gauss_integral(lo, h, sigma)) / (2.0 * half);
    }
    (sum / AREA_POINTS as f64).clamp(0.0, 1.0)
}

/// `∫_{−∞}^{t} exp(−max(0, |u| − h)²/σ²) du`: a Gaussian of spread `σ` split
/// at 0 by a flat top of width `2h`.
fn flat_gauss_integral(t: f64, h: f64, sigma: f64) -> f64 {
    // ∫_{−∞}^{t} exp(−u²/σ²) du = σ·√π/2 · erfc(−t/σ).
    let g = |t: f64| sigma * std::f64::consts::PI.sqrt() / 2.0 * crate::scene::special::erfc(-t / sigma);
    if t <= -h {
        g(t + h)
    } else if t <= h {
        g(0.0) + (t + h)
    } else {
        2.0 * h + g(t - h)
    }
}

/// `k(θ)` (frames to cross the array, uncapped, as a float) and the number of
/// templates kept.
/// Most template values (frames x taxels, over every class) one set of
/// templates may hold: 2^27, 1 GiB of f64. The paper's grid (33 classes,
/// 16 taxels, 10 ms frames) takes about 1 million, and even a 1 ms hop ten
/// times that. Why a cap: a class's length is capped by `max_template_s /
/// hop`, which an absurd hop (images built every 10^-6 ms, from a file or
/// Python) turned into terabytes, and the allocation's failure aborted the
/// process where it must fail the trial.
pub const MAX_TEMPLATE_VALUES: usize = 1 << 27;

fn lengths(layout: &TaxelLayout, hop_ms: f64, params: &WssParams, theta_deg: f64) -> (f64, usize) {
    let edge = Edge::new(theta_deg);
    let (lo, hi) = edge.footprint(layout);
    let ds = edge.normal_speed(params.speed()) * hop_ms / 1000.0;
    let k = ((hi - lo) / ds).ceil().max(0.0);
    let cap = (params.max_template_s * 1000.0 / hop_ms).floor() + 1.0;
    // Both are finite and positive here (validated inputs); `as` saturates anyway.
    (k, (k + 1.0).min(cap).max(1.0) as usize)
}

/// Centres `v` and scales it to unit norm in place; zeros it when its variance
/// is negligible (below 1e-20 of its energy, i.e. rounding noise), so that a
/// constant image correlates 0 with everything.
pub(crate) fn normalize(v: &mut [f64]) -> bool {
    let sum = v.iter().sum::<f64>();
    normalize_with_sum(v, sum)
}

/// [`normalize`] on each `n`-value frame of `v`, with its bits: frames are
/// taken eight at a time, each in its own lane, so the three sums per frame
/// (values, squares, squared deviations), each in taxel order as
/// [`normalize`] adds them, run side by side instead of as one chain of
/// dependent additions after another (a class's frames are thousands).
pub(crate) fn normalize_frames(v: &mut [f64], n: usize) {
    const L: usize = 8;
    if n == 0 {
        return;
    }
    let whole = v.len() / (n * L) * (n * L);
    let (head, tail) = v.split_at_mut(whole);
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for block in head.chunks_exact_mut(n * L) {
                let mut sum = [0.0f64; L];
                let mut energy = [0.0f64; L];
                for t in 0..n {
                    for l in 0..L {
                        let x = block[l * n + t];
                        sum[l] += x;
                        energy[l] += x * x;
                    }
                }
                let mut mean = [0.0f64; L];
                for l in 0..L {
                    mean[l] = sum[l] / n as f64;
                }
                let mut ss = [0.0f64; L];
                for t in 0..n {
                    for l in 0..L {
                        let d = block[l * n + t] - mean[l];
                        ss[l] += d * d;
                    }
                }
                for (l, frame) in block.chunks_exact_mut(n).enumerate() {
                    if !ss[l].is_finite() || ss[l] <= 1e-20 * energy[l] {
                        frame.iter_mut().for_each(|x| *x = 0.0);
                    } else {
                        let inv = 1.0 / ss[l].sqrt();
                        let m = mean[l];
                        frame.iter_mut().for_each(|x| *x = (*x - m) * inv);
                    }
                }
            }
        },
    );
    for frame in tail.chunks_exact_mut(n) {
        normalize(frame);
    }
}

/// [`normalize`] given `v.iter().sum()` (a frame's spike count, which the
/// caller has already summed in that order: the same bits).
pub(crate) fn normalize_with_sum(v: &mut [f64], sum: f64) -> bool {
    let n = v.len() as f64;
    let mean = sum / n;
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
        // Every class's size first, so that an absurd hop is an error before
        // anything is allocated (see `MAX_TEMPLATE_VALUES`).
        let sizes: Vec<(f64, usize)> = angles
            .iter()
            .map(|&a| lengths(layout, hop_ms, params, a))
            .collect();
        let values = sizes
            .iter()
            .fold(0u128, |sum, &(_, len)| sum + len as u128 * n as u128);
        if values > MAX_TEMPLATE_VALUES as u128 {
            return Err(ConfigError::key(
                "hop_ms",
                format!(
                    "templates of {} classes for images every {} ms need {values} values (frames x {n} \
                     taxels), over the cap of {MAX_TEMPLATE_VALUES} (1 GiB): is the images' hop right? \
                     Or use fewer classes, or a shorter `max_template_s`",
                    angles.len(),
                    palpate_core::fmt_num(hop_ms)
                ),
            ));
        }
        let classes = angles
            .iter()
            .zip(sizes)
            .map(|(&a, (crossing_frames, len))| {
                let mut data = vec![0.0; len * n];
                let shape = ClassShape::new(layout, hop_ms, params, a);
                shape.templates_into(&mut data);
                normalize_frames(&mut data, n);
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

    /// Forward and inverse real FFTs of length `len`, planned once per
    /// process (see [`shared_plan`]).
    pub(crate) fn plan(&self, len: usize) -> FftPair {
        shared_plan(len)
    }

    /// Spectra `[taxel][bin]` of class `c`'s first `h` templates, zero-padded to
    /// `fft_len`, scaled by `1/fft_len` so that the inverse FFT of a product is
    /// the convolution.
    pub(crate) fn batch_spectra(&self, c: usize, fft_len: usize, h: usize) -> Spectra {
        if let Some(s) = self.lock().batch.get((c, fft_len, h)) {
            return s;
        }
        let pair = self.plan(fft_len);
        let cls = &self.classes[c];
        let n = self.n_taxels();
        let bins = fft_len / 2 + 1;
        let h = h.min(cls.len).min(fft_len);
        let scale = 1.0 / fft_len as f64;
        // One taxel's spectrum at a time, written straight into the split
        // parts (no interleaved copy of the whole set), with one scratch.
        let mut soa = Soa {
            re: Vec::with_capacity(n * bins),
            im: Vec::with_capacity(n * bins),
        };
        let mut spec = vec![Complex::new(0.0, 0.0); bins];
        let mut buf = vec![0.0; fft_len];
        let mut scratch = pair.fwd.make_scratch_vec();
        for t in 0..n {
            for (i, v) in buf.iter_mut().take(h).enumerate() {
                *v = cls.data[i * n + t] * scale;
            }
            // The FFT leaves its input as scratch: the padding is zeroed
            // again for every taxel.
            buf[h..].iter_mut().for_each(|x| *x = 0.0);
            // Lengths match by construction, so the FFT cannot fail.
            let _ = pair.fwd.process_with_scratch(&mut buf, &mut spec, &mut scratch);
            soa.re.extend(spec.iter().map(|z| z.re));
            soa.im.extend(spec.iter().map(|z| z.im));
        }
        let s = Arc::new(soa);
        self.lock()
            .batch
            .insert((c, fft_len, h), s.clone(), BATCH_CACHE_BYTES);
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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Eight frames at a time in lanes gives each frame's bits, for any
        /// frame width, frame count (with a tail) and values, constant and
        /// all-zero frames included.
        #[test]
        fn frames_in_lanes_are_normalised_as_one_by_one(
            n in 1usize..20,
            frames in 0usize..30,
            seed in any::<u64>(),
            constant in any::<bool>(),
        ) {
            let mut x = seed | 1;
            let mut next = || {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 11) as f64 / (1u64 << 53) as f64
            };
            let mut v: Vec<f64> = (0..n * frames).map(|_| next() * 3.0).collect();
            if constant && frames > 2 {
                v[n..2 * n].iter_mut().for_each(|x| *x = 0.7);
                v[2 * n..3 * n].iter_mut().for_each(|x| *x = 0.0);
            }
            let mut one = v.clone();
            for f in one.chunks_exact_mut(n) {
                normalize(f);
            }
            normalize_frames(&mut v, n);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            prop_assert_eq!(bits(&v), bits(&one));
        }
    }

    /// An absurd hop is refused by name before anything is allocated (it
    /// asked for 7e12 values and aborted); the paper's hop and a 1 ms hop
    /// build.
    #[test]
    fn templates_over_the_value_cap_are_refused_naming_the_hop() {
        let layout = TaxelLayout::paper();
        let params = WssParams::default();
        for hop in [1e-6, 1e-3] {
            let Err(e) = Templates::new(&layout, hop, &params) else {
                panic!("{hop} ms: over the cap, built")
            };
            assert_eq!(e.key.as_deref(), Some("hop_ms"));
            assert!(e.message.contains("over the cap of 134217728"), "{e}");
        }
        for hop in [1.0, 10.0] {
            let t = Templates::new(&layout, hop, &params).unwrap();
            let values: usize = t.classes().iter().map(|c| c.data.len()).sum();
            assert!(values <= MAX_TEMPLATE_VALUES, "{hop} ms: {values}");
        }
    }

    /// The batched build gives every class the bits of building each
    /// template by itself (`template_into`, then `normalize`), for both
    /// distances.
    #[test]
    fn batched_templates_are_the_bits_of_one_at_a_time() {
        let layout = TaxelLayout::paper();
        for distance in [Distance::Centre, Distance::Area] {
            let params = WssParams {
                distance,
                ..WssParams::default()
            };
            for a in [7.5, 33.3, 90.0, 151.0] {
                let t = Templates::for_angles(&layout, 10.0, &params, &[a]).unwrap();
                let cls = &t.classes()[0];
                let shape = ClassShape::new(&layout, 10.0, &params, a);
                let n = layout.len();
                for (i, frame) in cls.data.chunks_exact(n).enumerate() {
                    let mut one = vec![0.0; n];
                    shape.template_into(i, &mut one);
                    normalize(&mut one);
                    let same = frame.iter().zip(&one).all(|(x, y)| x.to_bits() == y.to_bits());
                    assert!(same, "{distance:?} {a} frame {i}: {frame:?} vs {one:?}");
                }
            }
        }
    }

    /// Brute-force mean over the taxel's square on a fine grid.
    fn brute(c: f64, n: [f64; 2], a: f64, h: f64, sigma: f64) -> f64 {
        let m = 400;
        let mut s = 0.0;
        for i in 0..m {
            for j in 0..m {
                let x = ((i as f64 + 0.5) / m as f64 - 0.5) * a;
                let y = ((j as f64 + 0.5) / m as f64 - 0.5) * a;
                let d = ((c + n[0] * x + n[1] * y).abs() - h).max(0.0);
                s += (-d * d / (sigma * sigma)).exp();
            }
        }
        s / (m * m) as f64
    }

    #[test]
    fn area_mean_and_its_table_match_brute_force() {
        for theta in [1.0f64, 10.0, 30.0, 45.0, 60.0, 90.0, 135.0, 179.0] {
            let t = theta.to_radians();
            let n = [t.sin(), -t.cos()];
            for (sigma, h) in [(1.0, 0.1), (0.5, 0.1), (0.2, 0.0)] {
                let table = AreaTable::new(n, 2.0, h, sigma);
                for c in [-3.0, -1.7, -0.4, 0.0, 0.3, 1.0, 1.5, 2.2, 6.0, 40.0] {
                    let b = brute(c, n, 2.0, h, sigma);
                    let e = area_mean(c, n, 2.0, h, sigma);
                    assert!((e - b).abs() < 2e-3, "θ {theta} σ {sigma} c {c}: {e} vs {b}");
                    let v = table.value(c);
                    assert!(
                        (v - e).abs() < 5e-4,
                        "table θ {theta} σ {sigma} c {c}: {v} vs {e}"
                    );
                    assert!(v.is_finite() && (0.0..=1.0).contains(&v));
                }
            }
        }
    }

    #[test]
    fn flat_gauss_integral_is_monotone_and_totals_right() {
        let (h, sigma) = (0.1, 0.7);
        let total = 2.0 * h + sigma * std::f64::consts::PI.sqrt();
        let mut last = 0.0;
        for j in -100..=100 {
            let v = flat_gauss_integral(j as f64 * 0.1, h, sigma);
            assert!(v >= last - 1e-15);
            last = v;
        }
        assert!((last - total).abs() < 1e-12);
        assert!(flat_gauss_integral(-10.0, h, sigma) < 1e-40);
    }

    /// A spectrum set of `bins` bins (one taxel), `bins * 16` bytes.
    fn set(bins: usize) -> Spectra {
        Arc::new(Soa {
            re: vec![0.0; bins],
            im: vec![0.0; bins],
        })
    }

    /// Misses of `rounds` passes over classes `0..classes` at FFT length `len`.
    fn misses(c: &mut SpectraLru, classes: usize, len: usize, rounds: usize, budget: usize) -> usize {
        let mut miss = 0;
        for _ in 0..rounds {
            for k in 0..classes {
                if c.get((k, len, 7)).is_none() {
                    miss += 1;
                    c.insert((k, len, 7), set(10), budget);
                }
            }
        }
        miss
    }

    #[test]
    fn an_over_budget_class_set_stays_mostly_cached() {
        // 33 classes of 160 bytes against room for 30: emptying the cache
        // on overflow missed all 33 every pass; now 3 per pass after the first.
        let mut c = SpectraLru::default();
        assert_eq!(misses(&mut c, 33, 64, 1, 30 * 160), 33);
        assert_eq!(misses(&mut c, 33, 64, 4, 30 * 160), 12);
        assert_eq!(c.len(), 30);
    }

    #[test]
    fn a_new_length_evicts_the_least_recently_used_other_length() {
        let mut c = SpectraLru::default();
        let budget = 20 * 160;
        assert_eq!(misses(&mut c, 10, 64, 1, budget), 10);
        assert_eq!(misses(&mut c, 10, 96, 1, budget), 10);
        // Length 64 used last: a third length evicts 96's sets, not 64's.
        assert_eq!(misses(&mut c, 10, 64, 1, budget), 0);
        assert_eq!(misses(&mut c, 10, 128, 1, budget), 10);
        assert_eq!(misses(&mut c, 10, 64, 1, budget), 0);
        assert_eq!(misses(&mut c, 10, 96, 1, budget), 10);
        // A set larger than the whole budget is returned, not kept, and
        // nothing is evicted for it.
        assert!(!c.insert((0, 4096, 7), set(1000), budget));
        assert_eq!(c.len(), 20);
    }
}
