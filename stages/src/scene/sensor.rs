//! Sensor-level effects of a soft piezoresistive array, each an opt-in scene
//! effect (listed in a scene's `effects`, never computed otherwise): the
//! mechanisms behind what Kumar et al. 2020 saw on their real sensor (section
//! 3.1, Fig. 5: taxels fire long before and after the edge crosses them, peaks
//! off the crossing, every taxel different).
//!
//! * `sleeve` (phase: trial): the soft sleeve's thickness and the friction
//!   that drags it. The sleeve spreads pressure like `skin`
//!   (`σ = thickness / 2`, in quadrature), and its outer surface sticks to the
//!   object while the array slides: the sleeve shears by `u` (mm), which grows
//!   at the sliding speed while it sticks, until the shear stress
//!   `G u / T` reaches static friction `μ_s p`, i.e. `u_s = μ_s p T / G`; then
//!   it slips back to where kinetic friction holds it, `u_k = μ_k p T / G`
//!   (stick-slip; each slip's threshold varies by `threshold_sd`, relative,
//!   fresh per event). The taxels see the contact pattern lag the array by `u`
//!   (the edge seems to reach a taxel up to `u_s / v` late, in jumps), and the
//!   friction's moment about the sleeve tilts the pressure it transmits: a
//!   loaded taxel at `x` (mm, along the slide) reads `p (1 + c (u / u_s) x / R)`
//!   with `R` the largest `|x|` of the array and `c` = `pressure_coupling`.
//!   Every slip then changes every loaded taxel's pressure at once: the FA-I
//!   response to it is not tied to the edge. Simplification: the friction is
//!   taken at the nominal contact pressure throughout the slide.
//! * `tilt` (phase: trial): the end effector is not parallel to the object. A
//!   tilt `α` (rad) about an axis through the array's centre indents the
//!   sleeve by an extra `α x`; a linear-elastic layer pressed to `δ₀` then
//!   carries `p (1 + α x / δ₀)`: a relative gradient `g = α / δ₀` per mm.
//!   Per trial `g = (gx, gy)` is `mean + N(0, sd)` per component (3-SD
//!   truncated); taxel `i` at `p_i` reads `max(0, 1 + g·p_i)` times its
//!   pressure. E.g. `δ₀ = 0.3 mm`, `α = 0.3°`: 1.7 %/mm.
//! * `hysteresis` (phase: signal, before `piezo`: pressure): the cloth's
//!   conductance follows a rising load at once but recovers slowly when it is
//!   unloaded (the fibres' contacts separate slowly): `y = (1 - f) x + f z`,
//!   with `z = x` while `x >= z` (loading) and `dz/dt = (x - z) / τ` while
//!   `x < z` (unloading, slow recovery), starting settled. A loading/unloading
//!   loop: at the same pressure, the unloading branch reads higher.
//! * `dynamics` (phase: signal): every taxel responds through its own
//!   first-order lag, `dy/dt = (x - y) / τ_i`, `τ_i = tau_s · exp(N(0,
//!   log_sd))` (log-normal, 3-SD truncated) drawn once per array from the
//!   array seed: hand-made taxels differ in how fast they follow a load.
//!   Starting settled.
//! * `ghosting` (phase: signal, before `piezo`, grid arrays): a passive
//!   row/column read-out without isolation measures taxel `(r, c)` in
//!   parallel with the sneak paths `(r, c') → (r', c') → (r', c)` through
//!   three other taxels in series. With conductance proportional to pressure
//!   (the `piezo` default), the reading is
//!   `g(r,c) = p(r,c) + s Σ_{r'≠r, c'≠c} S(p(r,c'), p(r',c'), p(r',c))` with
//!   `S(a, b, d) = 1 / (1/a + 1/b + 1/d)` (0 when any is 0) and `s` the share
//!   of sneak current the read-out lets through (`sneak`: 1 = floating lines,
//!   0 = perfect isolation). A taxel off the object still reads its
//!   neighbours' sneak paths, which change as *they* cross the edge: spikes
//!   before and after its own crossing. Negative pressures read as 0.
//!
//! Units: pressure is "pressure" (1 = full contact with a flat surface);
//! effects marked "before `piezo`" are an error when listed after it, since
//! their physics is about pressure and conductance, not volts.

use super::effects::{normal3, Block, SignalEffect, SignalState, TrialInfo};
use palpate_core::TaxelLayout;
use rand_chacha::ChaCha8Rng;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The soft sleeve: thickness (pressure spreading) and friction-driven
/// stick-slip shear (phase: trial). See the module docs for the physics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SleeveConfig {
    /// Sleeve thickness T, mm: spreads pressure by σ = T/2 (like `skin`) and
    /// sets the shear compliance. Default 1.
    pub thickness_mm: f64,
    /// Shear modulus G of the sleeve, kPa. Default 30 (a soft silicone).
    pub shear_modulus_kpa: f64,
    /// Nominal contact pressure p, kPa. Default 10.
    pub pressure_kpa: f64,
    /// Static friction coefficient μ_s between sleeve and object. Default 1.0.
    pub friction_static: f64,
    /// Kinetic friction coefficient μ_k (<= μ_s). Default 0.7.
    pub friction_kinetic: f64,
    /// Relative SD of each slip's threshold, unitless. Default 0.2.
    pub threshold_sd: f64,
    /// Relative pressure change at the array's rim at full shear `u_s`
    /// (the friction's moment), unitless. Default 0.05.
    pub pressure_coupling: f64,
}

impl Default for SleeveConfig {
    fn default() -> Self {
        SleeveConfig {
            thickness_mm: 1.0,
            shear_modulus_kpa: 30.0,
            pressure_kpa: 10.0,
            friction_static: 1.0,
            friction_kinetic: 0.7,
            threshold_sd: 0.2,
            pressure_coupling: 0.05,
        }
    }
}

impl SleeveConfig {
    /// Static shear limit `u_s = μ_s p T / G`, mm.
    pub fn u_static(&self) -> f64 {
        self.friction_static * self.pressure_kpa * self.thickness_mm / self.shear_modulus_kpa
    }
    /// Kinetic shear `u_k = μ_k p T / G`, mm.
    pub fn u_kinetic(&self) -> f64 {
        self.friction_kinetic * self.pressure_kpa * self.thickness_mm / self.shear_modulus_kpa
    }
    /// The largest shear a trial can reach (3-SD threshold), mm.
    pub fn u_max(&self) -> f64 {
        self.u_static() * (1.0 + 3.0 * self.threshold_sd)
    }

    /// The sleeve's shear `u` (mm) at every sample of a trial: 0 until the
    /// slide starts at sample `k0`, stick-slip while it lasts (`v_per_sample`
    /// mm per sample) until sample `k1`, then held.
    pub fn track(&self, n: usize, k0: usize, k1: usize, v_per_sample: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
        let (us, uk) = (self.u_static(), self.u_kinetic());
        // A slip always drops the shear by at least 1 % of u_s: the sawtooth
        // cannot degenerate into a slip every sample.
        let floor = uk + 0.01 * us;
        let mut threshold = (us * (1.0 + normal3(rng, self.threshold_sd))).max(floor);
        let mut u = 0.0;
        let mut out = Vec::with_capacity(n);
        for k in 0..n {
            if k >= k0 && k < k1 {
                u += v_per_sample;
                if u >= threshold {
                    u = uk;
                    threshold = (us * (1.0 + normal3(rng, self.threshold_sd))).max(floor);
                }
            }
            out.push(u);
        }
        out
    }
}

/// End-effector tilt: a pressure gradient across the array that varies per
/// trial (phase: trial). See the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TiltConfig {
    /// Mean relative pressure gradient along x (the slide), per mm. Default 0.
    pub mean_x_per_mm: f64,
    /// Mean relative pressure gradient along y, per mm. Default 0.
    pub mean_y_per_mm: f64,
    /// SD of each component's per-trial draw, per mm. Default 0.01.
    pub sd_per_mm: f64,
}

impl Default for TiltConfig {
    fn default() -> Self {
        TiltConfig {
            mean_x_per_mm: 0.0,
            mean_y_per_mm: 0.0,
            sd_per_mm: 0.01,
        }
    }
}

impl TiltConfig {
    /// One trial's per-taxel pressure factors, `max(0, 1 + g·p_i)`.
    pub fn gains(&self, layout: &TaxelLayout, rng: &mut ChaCha8Rng) -> Vec<f64> {
        let gx = self.mean_x_per_mm + normal3(rng, self.sd_per_mm);
        let gy = self.mean_y_per_mm + normal3(rng, self.sd_per_mm);
        layout
            .positions()
            .iter()
            .map(|p| (1.0 + gx * p[0] + gy * p[1]).max(0.0))
            .collect()
    }
}

/// Loading/unloading hysteresis and slow recovery of the piezoresistive cloth
/// (phase: signal, before `piezo`). See the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct HysteresisConfig {
    /// Share of the response that recovers slowly on unloading, in [0, 1]. Default 0.3.
    pub fraction: f64,
    /// Recovery time constant on unloading, s. Default 1.0.
    pub tau_s: f64,
}

impl Default for HysteresisConfig {
    fn default() -> Self {
        HysteresisConfig {
            fraction: 0.3,
            tau_s: 1.0,
        }
    }
}

/// Per-taxel first-order dynamics with log-normally spread time constants,
/// fixed per array (phase: signal). See the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DynamicsConfig {
    /// Median time constant, s. Default 0.2.
    pub tau_s: f64,
    /// SD of ln(τ) across taxels. Default 0.5.
    pub log_sd: f64,
}

impl Default for DynamicsConfig {
    fn default() -> Self {
        DynamicsConfig {
            tau_s: 0.2,
            log_sd: 0.5,
        }
    }
}

/// Sneak-path ghosting of a passive row/column read-out (phase: signal,
/// before `piezo`, grid arrays). See the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct GhostingConfig {
    /// Share of the sneak-path current the read-out lets through, in [0, 1]
    /// (1 = floating lines). Default 0.2.
    pub sneak: f64,
}

impl Default for GhostingConfig {
    fn default() -> Self {
        GhostingConfig { sneak: 0.2 }
    }
}

/// The built `hysteresis` effect.
pub(crate) struct Hysteresis(pub HysteresisConfig);

struct HysteresisState {
    keep: f64,
    frac: f64,
    alpha: f64,
    z: Vec<f64>,
    started: bool,
}

impl SignalEffect for Hysteresis {
    fn kind(&self) -> &'static str {
        "hysteresis"
    }
    fn start<'a>(&'a self, info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        super::effects::log_event("run", "hysteresis");
        Box::new(HysteresisState {
            keep: 1.0 - self.0.fraction,
            frac: self.0.fraction,
            // Exact discretization of dz/dt = (x - z)/tau for x held over a sample.
            alpha: 1.0 - (-1.0 / (self.0.tau_s * info.sample_rate_hz)).exp(),
            z: vec![0.0; info.layout.len()],
            started: false,
        })
    }
}

impl SignalState for HysteresisState {
    fn process(&mut self, b: &mut Block<'_>) {
        let len = b.len;
        if len == 0 {
            return;
        }
        if !self.started {
            for (z, row) in self.z.iter_mut().zip(b.data.chunks_exact(len)) {
                *z = row[0];
            }
        }
        let (alpha, keep, frac) = (self.alpha, self.keep, self.frac);
        per_taxel_recurrence(b.data, len, &mut self.z, |_, z, x| {
            // Loading follows at once, unloading recovers with tau (a select,
            // not a branch: the same value either way).
            let relaxed = *z + alpha * (x - *z);
            *z = if x >= *z { x } else { relaxed };
            keep * x + frac * *z
        });
        self.started = true;
    }
}

/// Runs one first-order recurrence per taxel over a taxel-major block:
/// `x[i][k] <- step(i, &mut state[i], x[i][k])` for k in order. Each taxel's
/// recurrence is a chain of dependent operations (latency-bound, ~12 cycles
/// a sample); running 8 taxels' chains in lock step overlaps them, and
/// every taxel's values are computed by the same operations in the same
/// order as one taxel at a time, so the bits do not change.
fn per_taxel_recurrence(
    data: &mut [f64],
    len: usize,
    state: &mut [f64],
    step: impl Fn(usize, &mut f64, f64) -> f64,
) {
    const GROUP: usize = 8;
    if len == 0 {
        return;
    }
    let n = state.len().min(data.len() / len);
    let mut rows = data.chunks_exact_mut(len).take(n);
    let mut first = 0;
    while first + GROUP <= n {
        let mut group: [&mut [f64]; GROUP] = std::array::from_fn(|_| rows.next().unwrap_or_default());
        let st: &mut [f64; GROUP] = (&mut state[first..first + GROUP])
            .try_into()
            .unwrap_or_else(|_| unreachable!("a group of GROUP states"));
        for k in 0..len {
            for (j, row) in group.iter_mut().enumerate() {
                row[k] = step(first + j, &mut st[j], row[k]);
            }
        }
        first += GROUP;
    }
    for (j, row) in rows.enumerate() {
        let s = &mut state[first + j];
        for x in row.iter_mut() {
            *x = step(first + j, s, *x);
        }
    }
}

/// The built `dynamics` effect: one recurrence coefficient per taxel.
pub(crate) struct Dynamics {
    /// Per-taxel time constants, s.
    pub tau_s: Vec<f64>,
}

impl Dynamics {
    /// Draws the per-taxel time constants from the array's generator.
    pub fn draw(c: &DynamicsConfig, n_taxels: usize, rng: &mut ChaCha8Rng) -> Dynamics {
        Dynamics {
            tau_s: (0..n_taxels)
                .map(|_| c.tau_s * normal3(rng, c.log_sd).exp())
                .collect(),
        }
    }
}

struct DynamicsState {
    alpha: Vec<f64>,
    y: Vec<f64>,
    started: bool,
}

impl SignalEffect for Dynamics {
    fn kind(&self) -> &'static str {
        "dynamics"
    }
    fn start<'a>(&'a self, info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        super::effects::log_event("run", "dynamics");
        Box::new(DynamicsState {
            alpha: self
                .tau_s
                .iter()
                .map(|t| 1.0 - (-1.0 / (t * info.sample_rate_hz)).exp())
                .collect(),
            y: vec![0.0; info.layout.len()],
            started: false,
        })
    }
}

impl SignalState for DynamicsState {
    fn process(&mut self, b: &mut Block<'_>) {
        let len = b.len;
        if len == 0 {
            return;
        }
        if !self.started {
            for (y, row) in self.y.iter_mut().zip(b.data.chunks_exact(len)) {
                *y = row[0];
            }
        }
        let alpha = &self.alpha;
        per_taxel_recurrence(b.data, len, &mut self.y, |i, y, x| {
            *y += alpha[i] * (x - *y);
            *y
        });
        self.started = true;
    }
}

/// The built `ghosting` effect.
pub(crate) struct Ghosting {
    pub sneak: f64,
    pub rows: usize,
    pub cols: usize,
}

struct GhostingState<'a> {
    fx: &'a Ghosting,
    p: Vec<f64>,
}

impl SignalEffect for Ghosting {
    fn kind(&self) -> &'static str {
        "ghosting"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        super::effects::log_event("run", "ghosting");
        Box::new(GhostingState {
            fx: self,
            p: Vec::new(),
        })
    }
}

/// Three conductances in series; 0 when any is 0.
#[inline]
fn series(a: f64, b: f64, d: f64) -> f64 {
    let den = a * b + b * d + d * a;
    if den > 0.0 {
        a * b * d / den
    } else {
        0.0
    }
}

impl SignalState for GhostingState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        let Ghosting { sneak, rows, cols } = *self.fx;
        let len = b.len;
        let n = rows * cols;
        if len == 0 || b.data.len() < n * len {
            return;
        }
        // A clamped copy: every output reads its row's and column's inputs.
        self.p.clear();
        self.p.extend(b.data[..n * len].iter().map(|v| v.max(0.0)));
        let p = &self.p;
        let out = &mut b.data[..n * len];
        crate::wide::with_avx2(
            #[inline(always)]
            || ghost_all(p, out, rows, cols, len, sneak),
        );
    }
}

/// Samples per lane group: the sums of one output taxel's nine sneak paths
/// stay in registers across a group.
const GHOST_LANES: usize = 16;

/// `out[t] = p[t] + sneak * sum of series(p[r][c2], p[r2][c2], p[r2][c])`
/// over r2 != r, c2 != c, for every taxel t = (r, c), samples across lanes.
/// Each sample's sum runs in the same order as a sample-at-a-time loop and
/// `series` is the same expression, so the bits are those of the scalar
/// definition (tested against it) on any instruction set.
#[inline(always)]
fn ghost_all(p: &[f64], out: &mut [f64], rows: usize, cols: usize, len: usize, sneak: f64) {
    let at = |r: usize, c: usize| (r * cols + c) * len;
    for r in 0..rows {
        for c in 0..cols {
            let o = &mut out[at(r, c)..at(r, c) + len];
            let me = &p[at(r, c)..at(r, c) + len];
            let full = len - len % GHOST_LANES;
            for k0 in (0..full).step_by(GHOST_LANES) {
                let mut ghost = [0.0f64; GHOST_LANES];
                for r2 in (0..rows).filter(|&r2| r2 != r) {
                    for c2 in (0..cols).filter(|&c2| c2 != c) {
                        let a: &[f64; GHOST_LANES] = lanes(p, at(r, c2) + k0);
                        let b: &[f64; GHOST_LANES] = lanes(p, at(r2, c2) + k0);
                        let d: &[f64; GHOST_LANES] = lanes(p, at(r2, c) + k0);
                        for j in 0..GHOST_LANES {
                            ghost[j] += series_select(a[j], b[j], d[j]);
                        }
                    }
                }
                for j in 0..GHOST_LANES {
                    o[k0 + j] = me[k0 + j] + sneak * ghost[j];
                }
            }
            for k in full..len {
                let mut ghost = 0.0;
                for r2 in (0..rows).filter(|&r2| r2 != r) {
                    for c2 in (0..cols).filter(|&c2| c2 != c) {
                        ghost += series(p[at(r, c2) + k], p[at(r2, c2) + k], p[at(r2, c) + k]);
                    }
                }
                o[k] = me[k] + sneak * ghost;
            }
        }
    }
}

/// `GHOST_LANES` values of `p` from `at` (in bounds: `at` is a lane group's start).
#[inline(always)]
fn lanes(p: &[f64], at: usize) -> &[f64; GHOST_LANES] {
    p[at..at + GHOST_LANES]
        .try_into()
        .unwrap_or_else(|_| unreachable!("a lane group lies inside its taxel's block"))
}

/// [`series`] without a branch, so that it vectorises: the quotient is taken
/// for every lane (0/0 where `den` is 0, then discarded by the select).
#[inline(always)]
fn series_select(a: f64, b: f64, d: f64) -> f64 {
    let den = a * b + b * d + d * a;
    let q = a * b * d / den;
    if den > 0.0 {
        q
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// The definition, one sample at a time (the kernel's reference).
    fn ghosting_reference(fx: &Ghosting, data: &mut [f64], len: usize) {
        let Ghosting { sneak, rows, cols } = *fx;
        let n = rows * cols;
        let mut p = vec![0.0; n];
        for k in 0..len {
            for (i, p) in p.iter_mut().enumerate() {
                *p = data[i * len + k].max(0.0);
            }
            for r in 0..rows {
                for c in 0..cols {
                    let mut ghost = 0.0;
                    for r2 in (0..rows).filter(|&r2| r2 != r) {
                        for c2 in (0..cols).filter(|&c2| c2 != c) {
                            ghost += series(p[r * cols + c2], p[r2 * cols + c2], p[r2 * cols + c]);
                        }
                    }
                    data[(r * cols + c) * len + k] = p[r * cols + c] + sneak * ghost;
                }
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn lock_step_recurrences_have_one_taxel_at_a_times_bits(
            n in 1usize..20,
            len in 1usize..40,
            seed in 0u64..1000,
        ) {
            use rand::Rng;
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let data: Vec<f64> = (0..n * len).map(|_| rng.random_range(-1.0..2.0)).collect();
            let alpha: Vec<f64> = (0..n).map(|_| rng.random_range(0.0..1.0)).collect();
            // Hysteresis and dynamics, one taxel at a time, over two blocks.
            let (keep, frac, a) = (0.6, 0.4, alpha[0]);
            let mut want_h = data.clone();
            let mut want_d = data.clone();
            for i in 0..n {
                let (mut z, mut y) = (data[i * len], data[i * len]);
                for k in 0..len {
                    let x = want_h[i * len + k];
                    if x >= z { z = x } else { z += a * (x - z) }
                    want_h[i * len + k] = keep * x + frac * z;
                    y += alpha[i] * (want_d[i * len + k] - y);
                    want_d[i * len + k] = y;
                }
            }
            let mut h = HysteresisState { keep, frac, alpha: a, z: vec![0.0; n], started: false };
            let mut d = DynamicsState { alpha: alpha.clone(), y: vec![0.0; n], started: false };
            let half = len / 2;
            let (mut got_h, mut got_d) = (Vec::new(), Vec::new());
            for (st, out) in [(&mut h as &mut dyn SignalState, &mut got_h), (&mut d, &mut got_d)] {
                *out = vec![0.0; n * len];
                for (start, l) in [(0, half), (half, len - half)] {
                    let mut blk: Vec<f64> = (0..n)
                        .flat_map(|i| data[i * len + start..i * len + start + l].to_vec())
                        .collect();
                    st.process(&mut Block { data: &mut blk, len: l, start });
                    for i in 0..n {
                        out[i * len + start..i * len + start + l].copy_from_slice(&blk[i * l..(i + 1) * l]);
                    }
                }
            }
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            proptest::prop_assert_eq!(bits(&got_h), bits(&want_h));
            proptest::prop_assert_eq!(bits(&got_d), bits(&want_d));
        }

        #[test]
        fn ghosting_kernel_has_the_definitions_bits(
            rows in 1usize..5,
            cols in 1usize..5,
            len in 0usize..70,
            sneak in 0.0f64..1.0,
            seed in 0u64..1000,
            zeros in 0.0f64..0.6,
        ) {
            use rand::Rng;
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            // Zeros and negatives exercise the 0/0 lanes and the clamp.
            let data: Vec<f64> = (0..rows * cols * len)
                .map(|_| if rng.random::<f64>() < zeros { 0.0 } else { rng.random_range(-0.5..2.0) })
                .collect();
            let fx = Ghosting { sneak, rows, cols };
            let mut want = data.clone();
            ghosting_reference(&fx, &mut want, len);
            let mut got = data;
            let mut st = GhostingState { fx: &fx, p: Vec::new() };
            st.process(&mut Block { data: &mut got, len, start: 0 });
            let same = got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits());
            proptest::prop_assert!(same && got.iter().all(|v| v.is_finite()));
        }
    }

    fn run(fx: &dyn SignalEffect, layout: &TaxelLayout, rows: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
        let n = rows[0].len();
        let info = TrialInfo {
            sample_rate_hz: 1000.0,
            n_samples: n,
            layout,
        };
        let mut st = fx.start(&info, ChaCha8Rng::seed_from_u64(1));
        let mut data: Vec<f64> = rows.concat();
        // Two blocks, to exercise the carried state.
        let half = n / 2;
        let mut out = vec![Vec::new(); rows.len()];
        for (start, len) in [(0, half), (half, n - half)] {
            let mut blk: Vec<f64> = (0..rows.len())
                .flat_map(|i| data[i * n + start..i * n + start + len].to_vec())
                .collect();
            st.process(&mut Block {
                data: &mut blk,
                len,
                start,
            });
            for (i, o) in out.iter_mut().enumerate() {
                o.extend_from_slice(&blk[i * len..(i + 1) * len]);
            }
        }
        data.clear();
        out
    }

    fn one() -> TaxelLayout {
        TaxelLayout::Grid {
            rows: 1,
            cols: 1,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        }
    }

    #[test]
    fn hysteresis_loads_at_once_and_recovers_slowly() {
        let fx = Hysteresis(HysteresisConfig {
            fraction: 0.5,
            tau_s: 1.0,
        });
        // 1 s at 0, 1 s at 1 (loading), 2 s at 0 (unloading).
        let x: Vec<f64> = (0..4000)
            .map(|k| if (1000..2000).contains(&k) { 1.0 } else { 0.0 })
            .collect();
        let y = run(&fx, &one(), vec![x]).remove(0);
        assert_eq!(y[999], 0.0);
        assert_eq!(y[1000], 1.0, "loading is immediate");
        // Unloading: half drops at once, half decays with tau = 1 s.
        assert!((y[2000] - 0.5 * (-1e-3f64).exp()).abs() < 1e-9, "{}", y[2000]);
        let expect = 0.5 * (-1.0f64).exp();
        assert!((y[2999] - expect).abs() < 2e-3, "{} vs {expect}", y[2999]);
        // The loop: on the way down the reading exceeds the load.
        assert!(y[2500] > 0.0);
    }

    #[test]
    fn dynamics_give_each_taxel_its_own_lag() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let fx = Dynamics::draw(
            &DynamicsConfig {
                tau_s: 0.2,
                log_sd: 0.5,
            },
            16,
            &mut rng,
        );
        let taus = fx.tau_s.clone();
        assert!(taus
            .iter()
            .all(|t| *t > 0.2 * (-1.5f64).exp() - 1e-12 && *t < 0.2 * 1.5f64.exp() + 1e-12));
        assert!(taus.iter().any(|t| (t - taus[0]).abs() > 1e-3), "taxels differ");
        let x: Vec<f64> = (0..2000).map(|k| if k >= 500 { 1.0 } else { 0.0 }).collect();
        let y = run(&fx, &TaxelLayout::paper(), vec![x; 16]);
        for (row, tau) in y.iter().zip(&taus) {
            // The exact step response of the lag, sampled: the step enters at
            // sample 500, so sample 500 + m has seen m + 1 samples of it.
            for m in [0usize, 50, 200, 1000] {
                let expect = 1.0 - (-((m + 1) as f64) / (tau * 1000.0)).exp();
                assert!(
                    (row[500 + m] - expect).abs() < 1e-12,
                    "{} vs {expect}",
                    row[500 + m]
                );
            }
            assert_eq!(row[499], 0.0, "settled start");
        }
    }

    #[test]
    fn ghosting_follows_the_sneak_paths() {
        let l = TaxelLayout::Grid {
            rows: 2,
            cols: 2,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        };
        let fx = Ghosting {
            sneak: 1.0,
            rows: 2,
            cols: 2,
        };
        // Taxel 0 off the object, the other three at pressure 1: taxel 0 reads
        // their sneak path, 1/3; the others read 1 (their paths go through 0).
        let y = run(
            &fx,
            &l,
            vec![vec![0.0; 4], vec![1.0; 4], vec![1.0; 4], vec![1.0; 4]],
        );
        assert!((y[0][0] - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(y[1][0], 1.0);
        // All loaded: every taxel reads 1 + 1/3 (uniform).
        let y = run(&fx, &l, vec![vec![1.0; 4]; 4]);
        assert!(y.iter().all(|r| (r[0] - 4.0 / 3.0).abs() < 1e-12));
        // None loaded, or negative: 0, never NaN.
        let y = run(&fx, &l, vec![vec![-1.0; 4]; 4]);
        assert!(y.iter().all(|r| r[0] == 0.0));
    }

    #[test]
    fn sleeve_sticks_and_slips_within_its_limits() {
        let c = SleeveConfig::default();
        assert!((c.u_static() - 1.0 * 10.0 * 1.0 / 30.0).abs() < 1e-12);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let u = c.track(20_000, 2000, 18_000, 0.002, &mut rng);
        assert!(u[..2000].iter().all(|&v| v == 0.0), "no shear before the slide");
        assert!(u.iter().all(|&v| (0.0..=c.u_max() + 0.002).contains(&v)));
        let slips = u.windows(2).filter(|w| w[1] < w[0]).count();
        // Each cycle climbs from u_k to ~u_s: about travel / (u_s - u_k) slips.
        let expect = 32.0 / (c.u_static() - c.u_kinetic());
        assert!(
            (slips as f64) > 0.5 * expect && (slips as f64) < 2.0 * expect,
            "{slips} vs {expect}"
        );
        assert!(
            u[18_000..].iter().all(|&v| v == u[17_999]),
            "held after the slide"
        );
    }

    #[test]
    fn tilt_is_a_gradient_that_never_goes_negative() {
        let c = TiltConfig {
            mean_x_per_mm: 0.02,
            mean_y_per_mm: 0.0,
            sd_per_mm: 0.0,
        };
        let g = c.gains(&TaxelLayout::paper(), &mut ChaCha8Rng::seed_from_u64(1));
        assert!((g[3] - (1.0 + 0.02 * 4.5)).abs() < 1e-12);
        assert!((g[0] - (1.0 - 0.02 * 4.5)).abs() < 1e-12);
        let steep = TiltConfig {
            mean_x_per_mm: 1.0,
            ..c
        };
        let g = steep.gains(&TaxelLayout::paper(), &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(g[0], 0.0);
    }
}
