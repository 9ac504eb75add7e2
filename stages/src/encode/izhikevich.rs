//! `izhikevich`: the Izhikevich (2003) neuron, one per taxel (paper eqs. 1-3).
//!
//! ```text
//! dv/dt = 0.04 v² + 5 v + 140 - u + I        (v in mV, t in ms)
//! du/dt = a (b v - u)
//! if v >= v_peak: v <- c, u <- u + d
//! ```
//!
//! Presets (Izhikevich 2003, Fig. 2): `fa_i` is the paper's FA-I neuron
//! (a = 0.02, b = 0.2, c = -65, d = 2); `regular_spiking` (0.02, 0.2, -65, 8),
//! `intrinsically_bursting` (0.02, 0.2, -55, 4), `chattering` (0.02, 0.2, -50, 2),
//! `fast_spiking` (0.1, 0.2, -65, 2), `low_threshold_spiking` (0.02, 0.25, -65, 2),
//! `thalamo_cortical` (0.02, 0.25, -65, 0.05), `resonator` (0.1, 0.26, -65, 2).
//! Explicit `a`, `b`, `c`, `d` override the preset's.
//!
//! Schemes (step `dt = dt_ms`):
//!
//! * `izhikevich` (default; Izhikevich's own code): `v` advances in two
//!   half-steps of `dt/2` with the same `u` and `I`, then
//!   `u += dt · a (b v - u)` with the new `v`.
//! * `euler`: forward Euler, `v += dt · f(v, u, I)` and
//!   `u += dt · a (b v_old - u)`.
//!
//! Numerical guards (the user guide's "Numerical hard cases"; they never act in the regime the
//! presets are meant for, and make every other input safe):
//!
//! * The spike is detected at (half-)step ends. Once `v` reaches `v_peak` in a
//!   (half-)step, the neuron has spiked: `v` is held at `v_peak` for the rest of
//!   the step (so the recovery update sees `v_peak`, not a numerical overshoot
//!   of the quadratic term that can reach 1e10 at large `dt`), then reset. So a
//!   neuron spikes at most once per step, and `u` gains at most `d` plus a
//!   bounded drift per step. (Izhikevich's code lets `v` overshoot into the `u`
//!   update; that differs only when `v` overshoots, by `a·b·(v - 30)·dt`.)
//! * `v` never falls below `min(c, v_rest) - 1000` mV: with a large `u` (after
//!   a burst of strong input) and a large `dt`, explicit integration of the
//!   quadratic can otherwise oscillate without bound.
//! * The currents are clamped to ±1e12 (see [`super`]), `a·dt <= 1` is required
//!   (so the `u` update is a convex combination, never unstable), and
//!   `c < v_peak`.
//!
//! With these, currents from 0 to 1e6 and steps from 0.01 to 2 ms give finite
//! `v`, `u` and spike times (tested by property tests below).
//!
//! Initial state: the resting point of the `I = 0` dynamics, `v_rest` the lower
//! root of `0.04 v² + (5 - b) v + 140 = 0` and `u = b v_rest` (-70 mV, -14 for
//! b = 0.2), so a silent input gives no onset spike. When `b` leaves no resting
//! point the neuron starts at `v = c`, `u = b c`.
//!
//! Rheobase (the smallest constant current that makes the neuron fire) of the
//! default scheme at dt = 0.5 ms, found numerically and tested below: about
//! 3.78 for `fa_i` and `regular_spiking` (b = 0.2: the saddle-node current
//! `(5 - b)²/0.16 - 140 = 4` less the transient from rest). Above it the rate
//! rises monotonically with the current.
//!
//! Speed: taxels run in blocks of [`LANES`] neurons in lock step; the hot loop
//! is branch-free except for the rare spike (see `benches/encode.rs`).

use super::{block_input, check_input_shape, fmax, fmin, sort_events, tiled, InputMode, StepInput, LANES};
use palpate_core::{
    check_range, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec, Item, Map, Payload,
    PayloadKind, SpikeEvent, SpikeTrain, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// A classic parameter set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// The paper's FA-I neuron: a = 0.02, b = 0.2, c = -65, d = 2.
    #[default]
    FaI,
    /// Regular spiking (RS): 0.02, 0.2, -65, 8.
    RegularSpiking,
    /// Intrinsically bursting (IB): 0.02, 0.2, -55, 4.
    IntrinsicallyBursting,
    /// Chattering (CH): 0.02, 0.2, -50, 2.
    Chattering,
    /// Fast spiking (FS): 0.1, 0.2, -65, 2.
    FastSpiking,
    /// Low-threshold spiking (LTS): 0.02, 0.25, -65, 2.
    LowThresholdSpiking,
    /// Thalamo-cortical (TC): 0.02, 0.25, -65, 0.05.
    ThalamoCortical,
    /// Resonator (RZ): 0.1, 0.26, -65, 2.
    Resonator,
}

impl Preset {
    /// `(a, b, c, d)`.
    pub fn params(self) -> [f64; 4] {
        match self {
            Preset::FaI => [0.02, 0.2, -65.0, 2.0],
            Preset::RegularSpiking => [0.02, 0.2, -65.0, 8.0],
            Preset::IntrinsicallyBursting => [0.02, 0.2, -55.0, 4.0],
            Preset::Chattering => [0.02, 0.2, -50.0, 2.0],
            Preset::FastSpiking => [0.1, 0.2, -65.0, 2.0],
            Preset::LowThresholdSpiking => [0.02, 0.25, -65.0, 2.0],
            Preset::ThalamoCortical => [0.02, 0.25, -65.0, 0.05],
            Preset::Resonator => [0.1, 0.26, -65.0, 2.0],
        }
    }
}

/// Integration scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Scheme {
    /// Izhikevich's: v in two half-steps of dt/2, then u with the new v.
    #[default]
    Izhikevich,
    /// Forward Euler at dt.
    Euler,
}

/// Izhikevich neuron per taxel (paper eqs. 1-3): input current to spikes; FA-I preset by default.
///
/// `dv/dt = 0.04v² + 5v + 140 - u + I`, `du/dt = a(bv - u)`; at `v >= v_peak`,
/// `v <- c`, `u <- u + d`. Guarded so that no input or step gives NaN, and a
/// neuron spikes at most once per step.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct IzhikevichConfig {
    /// Parameter set: `fa_i` (paper), `regular_spiking`, `intrinsically_bursting`, `chattering`,
    /// `fast_spiking`, `low_threshold_spiking`, `thalamo_cortical`, `resonator`. Default `fa_i`.
    pub preset: Preset,
    /// Recovery time scale, 1/ms; overrides the preset.
    pub a: Option<f64>,
    /// Sensitivity of u to v (dimensionless); overrides the preset.
    pub b: Option<f64>,
    /// Reset potential after a spike, mV; overrides the preset.
    pub c: Option<f64>,
    /// Recovery increment after a spike; overrides the preset.
    pub d: Option<f64>,
    /// Spike threshold (peak), mV. Default 30.
    pub v_peak: f64,
    /// Integration step, ms. Default 0.5; 1e-4 to 10 allowed, and steps
    /// over [`COARSE_DT_MS`] warn (see there).
    pub dt_ms: f64,
    /// `izhikevich` (two half-steps for v, then u) or `euler` (forward Euler). Default `izhikevich`.
    pub scheme: Scheme,
    /// Input sampling between signal samples: `hold` (zero-order hold) or `linear`. Default `hold`.
    pub input: InputMode,
}

impl Default for IzhikevichConfig {
    fn default() -> Self {
        IzhikevichConfig {
            preset: Preset::FaI,
            a: None,
            b: None,
            c: None,
            d: None,
            v_peak: 30.0,
            dt_ms: 0.5,
            scheme: Scheme::Izhikevich,
            input: InputMode::Hold,
        }
    }
}

/// Checked neuron parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IzhParams {
    /// Recovery time scale, 1/ms.
    pub a: f64,
    /// Sensitivity of u to v.
    pub b: f64,
    /// Reset, mV.
    pub c: f64,
    /// Recovery increment.
    pub d: f64,
    /// Threshold, mV.
    pub v_peak: f64,
}

impl IzhParams {
    /// A preset's parameters with threshold 30 mV.
    pub fn preset(p: Preset) -> Self {
        let [a, b, c, d] = p.params();
        IzhParams {
            a,
            b,
            c,
            d,
            v_peak: 30.0,
        }
    }

    /// The resting state `(v, u)` for zero input, or `(c, b c)` when there is none.
    pub fn rest(&self) -> (f64, f64) {
        let disc = (5.0 - self.b).powi(2) - 4.0 * 0.04 * 140.0;
        if disc >= 0.0 {
            let v = ((self.b - 5.0) - disc.sqrt()) / 0.08;
            (v, self.b * v)
        } else {
            (self.c, self.b * self.c)
        }
    }
}

impl IzhikevichConfig {
    /// The checked parameters, or an error naming the key.
    pub fn params(&self) -> Result<IzhParams, ConfigError> {
        let [pa, pb, pc, pd] = self.preset.params();
        let mut k = ConfigChecks::new();
        let a = k.take(check_range("a", self.a.unwrap_or(pa), 0.0, 10.0, "1/ms"));
        let b = k.take(check_range("b", self.b.unwrap_or(pb), -10.0, 10.0, ""));
        let c = k.take(check_range("c", self.c.unwrap_or(pc), -1000.0, 1000.0, "mV"));
        let d = k.take(check_range("d", self.d.unwrap_or(pd), -1000.0, 1000.0, ""));
        let v_peak = k.take(check_range("v_peak", self.v_peak, -1000.0, 1000.0, "mV"));
        let (Some(a), Some(b), Some(c), Some(d), Some(v_peak)) = (a, b, c, d, v_peak) else {
            return Err(k
                .finish()
                .err()
                .unwrap_or_else(|| ConfigError::general("bad parameters")));
        };
        let p = IzhParams { a, b, c, d, v_peak };
        if p.c >= p.v_peak {
            return Err(ConfigError::key(
                "c",
                format!("the reset c = {} mV must lie below v_peak = {} mV", p.c, p.v_peak),
            ));
        }
        Ok(p)
    }
}

#[typetag::serde(name = "izhikevich")]
impl StageConfig for IzhikevichConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut k = ConfigChecks::new();
        let params = k.take(self.params());
        let dt = k.take(check_range("dt_ms", self.dt_ms, 1e-4, 10.0, "ms"));
        k.finish()?;
        let (Some(params), Some(_)) = (params, dt) else {
            return Err(ConfigError::general("bad parameters"));
        };
        if params.a * self.dt_ms > 1.0 {
            return Err(ConfigError::key(
                "dt_ms",
                format!(
                    "a * dt_ms = {} must be at most 1 for a stable recovery update; use a smaller step",
                    params.a * self.dt_ms
                ),
            ));
        }
        Ok(Stage::Map(Box::new(Izhikevich {
            params,
            dt_ms: self.dt_ms,
            scheme: self.scheme,
            input: self.input,
        })))
    }
    fn inspect(
        &self,
        _ctx: &BuildContext,
        _inputs: &[palpate_core::OutputFacts],
    ) -> palpate_core::Inspection {
        let mut out = palpate_core::Inspection::default();
        if self.dt_ms > COARSE_DT_MS {
            out.warnings.push(ConfigError::key(
                "dt_ms",
                format!(
                    "a step of {} ms is coarse for the Izhikevich neuron (its spike's upstroke lasts about a \
                     millisecond): spikes come late or not at all, and estimates degrade (quickstart: MAE 0.06 \
                     degrees up to 2 ms, 1.6 at 5 ms, 33 at 10 ms); {COARSE_DT_MS} ms or less is safe",
                    palpate_core::fmt_num(self.dt_ms)
                ),
            ));
        }
        out
    }
}
register_stage!("izhikevich", IzhikevichConfig);

/// The longest `dt_ms` that runs without a warning. The neuron's spike
/// upstroke (from the knee near −55 mV to `v_peak`) takes about a
/// millisecond, so a longer step jumps over it and the spike times (and
/// whether a weak input fires at all) shift. Measured on
/// `palpate run graphs/quickstart.toml --set stages.enc.dt_ms=<dt>`
/// (seed 1, 2026-12-07): MAE 0.06 degrees at 0.5, 1 and 2 ms, 0.09 at 3,
/// 1.59 at 5 (four trials flagged uncertain), 33.3 at 10 (15 of 170 trials
/// no edge).
pub const COARSE_DT_MS: f64 = 2.0;

/// The runtime `izhikevich` encoder.
#[derive(Clone, Debug)]
pub struct Izhikevich {
    /// Neuron parameters.
    pub params: IzhParams,
    /// Step, ms.
    pub dt_ms: f64,
    /// Scheme.
    pub scheme: Scheme,
    /// Input sampling.
    pub input: InputMode,
}

impl Izhikevich {
    /// Encodes currents `currents[taxel][sample]` at `fs` Hz into time-sorted
    /// spike events. `currents` must be finite (callers check).
    pub fn encode(&self, currents: &[Vec<f64>], fs: f64) -> Vec<SpikeEvent> {
        self.encode_with_state(currents, fs).0
    }

    /// [`Izhikevich::encode`], also giving every neuron's final `(v, u)`.
    pub fn encode_with_state(&self, currents: &[Vec<f64>], fs: f64) -> (Vec<SpikeEvent>, Vec<(f64, f64)>) {
        let (events, state, _) = self.encode_finite(currents, fs);
        (events, state)
    }

    /// [`Izhikevich::encode_with_state`], also telling whether every
    /// current was finite (noted while the input is transposed).
    fn encode_finite(&self, currents: &[Vec<f64>], fs: f64) -> (Vec<SpikeEvent>, Vec<(f64, f64)>, bool) {
        let mut finite = true;
        let mut state = Vec::with_capacity(currents.len());
        let n_samples = currents.first().map_or(0, Vec::len);
        let plan = StepInput::new(n_samples, fs, self.dt_ms, self.input);
        let mut events = Vec::new();
        // One reused buffer per thread (see `with_scratch`).
        crate::wide::with_scratch(|data| {
            for (block, chunk) in currents.chunks(LANES).enumerate() {
                let first = (block * LANES) as u32;
                let (p, live, ev) = (&self.params, chunk.len(), &mut events);
                let (v0, u0) = p.rest();
                let mut vu = ([v0; LANES], [u0; LANES]);
                finite &= tiled(chunk, n_samples, &plan, data, |data, steps, off| {
                    let at = (steps, off, live, first);
                    // The lanes' arithmetic in 256-bit vectors where the CPU has them
                    // (no FMA: the same bits either way, tested).
                    vu = crate::wide::with_avx2(
                        #[inline(always)]
                        || match (self.scheme, self.input) {
                            (Scheme::Izhikevich, InputMode::Hold) => {
                                run_block::<true, false>(p, &plan, data, vu, at, ev)
                            }
                            (Scheme::Izhikevich, InputMode::Linear) => {
                                run_block::<true, true>(p, &plan, data, vu, at, ev)
                            }
                            (Scheme::Euler, InputMode::Hold) => {
                                run_block::<false, false>(p, &plan, data, vu, at, ev)
                            }
                            (Scheme::Euler, InputMode::Linear) => {
                                run_block::<false, true>(p, &plan, data, vu, at, ev)
                            }
                        },
                    );
                });
                let (v, u) = vu;
                state.extend((0..chunk.len()).map(|l| (v[l], u[l])));
            }
        });
        sort_events(&mut events);
        (events, state, finite)
    }
}

/// One neuron's membrane `(v, u)` carried between calls to
/// [`Izhikevich::step`], for streaming (the live path advances each taxel's
/// neuron by one DAQ frame at a time, never re-encoding the past).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeuronState {
    /// Membrane potential, mV.
    pub v: f64,
    /// Recovery variable.
    pub u: f64,
}

impl Izhikevich {
    /// The state a neuron starts in (see the module docs: rest, or `(c, b c)`).
    pub fn initial_state(&self) -> NeuronState {
        let (v, u) = self.params.rest();
        NeuronState { v, u }
    }

    /// Advances one neuron by one step of `dt_ms` under current `i` (clamped
    /// to ±[`super::MAX_CURRENT`]). Returns the spike's position within the
    /// step as a fraction in `[0, 1]` when it fired (the spike time is
    /// `(n + frac) · dt` for step `n`).
    ///
    /// The arithmetic is that of one lane of [`Izhikevich::encode`], operation
    /// for operation, so a stream of steps gives bit-identical spike times to
    /// the batch encoder on the same currents (tested below).
    #[inline]
    pub fn step(&self, s: &mut NeuronState, i: f64) -> Option<f64> {
        let p = &self.params;
        let il = i.clamp(-super::MAX_CURRENT, super::MAX_CURRENT);
        let (v0, _) = p.rest();
        let dt = self.dt_ms;
        let half = self.scheme == Scheme::Izhikevich;
        let h = if half { 0.5 * dt } else { dt };
        let adt = p.a * dt;
        let (b, c, d, vp) = (p.b, p.c, p.d, p.v_peak);
        let floor = c.min(v0) - 1000.0;
        let (vl, ul) = (s.v, s.u);
        let a1 = fmax(vl + h * ((0.04 * vl + 5.0) * vl + 140.0 - ul + il), floor);
        let (x, y);
        if half {
            let m = fmin(a1, vp);
            let a2 = fmax(m + h * ((0.04 * m + 5.0) * m + 140.0 - ul + il), floor);
            x = if a1 >= vp { vp } else { fmin(a2, vp) };
            y = ul + adt * (b * x - ul);
        } else {
            x = fmin(a1, vp);
            y = ul + adt * (b * vl - ul);
        }
        if x < vp {
            s.v = x;
            s.u = y;
            return None;
        }
        let frac = spike_frac(half, (vl, ul, il), a1, (h, floor, vp));
        s.v = c;
        s.u = y + d;
        Some(frac)
    }
}

/// Integrates one block of lanes over the steps `steps` from the state
/// `(v, u)`, `data[0]` holding sample `off` (one tile of
/// [`super::tiled`]). `HALF`: Izhikevich's two half-steps; otherwise
/// forward Euler. `LINEAR`: interpolated input. Inlined so that it is
/// compiled inside [`crate::wide::with_avx2`].
#[inline(always)]
fn run_block<const HALF: bool, const LINEAR: bool>(
    p: &IzhParams,
    plan: &StepInput,
    data: &[[f64; LANES]],
    (mut v, mut u): ([f64; LANES], [f64; LANES]),
    (steps, off, live, first_taxel): (std::ops::Range<usize>, usize, usize, u32),
    events: &mut Vec<SpikeEvent>,
) -> ([f64; LANES], [f64; LANES]) {
    let (v0, _) = p.rest();
    let dt = plan.dt_ms;
    let h = if HALF { 0.5 * dt } else { dt };
    let adt = p.a * dt;
    let (b, c, vp) = (p.b, p.c, p.v_peak);
    let floor = c.min(v0) - 1000.0;
    let start = steps.start;
    for (n, &i) in plan.idx[steps].iter().enumerate() {
        let n = start + n;
        let cur = block_input::<LINEAR>(data, plan, n, i as usize - off);
        let mut vn = [0.0; LANES];
        let mut un = [0.0; LANES];
        let mut any = false;
        // Hot path: branch-free over the lanes (min/max/select only), so it
        // compiles to packed SIMD. Spike bookkeeping is in the rare path below.
        for l in 0..LANES {
            let (vl, ul, il) = (v[l], u[l], cur[l]);
            let a1 = fmax(vl + h * ((0.04 * vl + 5.0) * vl + 140.0 - ul + il), floor);
            let (x, y);
            if HALF {
                let m = fmin(a1, vp);
                let a2 = fmax(m + h * ((0.04 * m + 5.0) * m + 140.0 - ul + il), floor);
                // Once v has reached the peak in the first half, it stays there.
                x = if a1 >= vp { vp } else { fmin(a2, vp) };
                y = ul + adt * (b * x - ul);
            } else {
                x = fmin(a1, vp);
                y = ul + adt * (b * vl - ul);
            }
            any |= x >= vp;
            vn[l] = x;
            un[l] = y;
        }
        if any {
            // The rare path works on copies: indexing the hot arrays by a
            // run-time lane would pin them to memory, and every step would
            // then carry `v` and `u` through a store and a load.
            (vn, un) = spikes::<HALF>(p, plan, [v, u, cur], [vn, un], n, (live, first_taxel), events);
        }
        v = vn;
        u = un;
    }
    (v, u)
}

/// The spike bookkeeping of one step of [`run_block`] (some lane reached
/// the peak): spike times, resets, events. Kept out of line.
/// (Arrays pass by value: a reference would let them escape, and the hot
/// loop would keep them in memory.)
#[inline(never)]
fn spikes<const HALF: bool>(
    p: &IzhParams,
    plan: &StepInput,
    [v, u, cur]: [[f64; LANES]; 3],
    [mut vn, mut un]: [[f64; LANES]; 2],
    n: usize,
    (live, first_taxel): (usize, u32),
    events: &mut Vec<SpikeEvent>,
) -> ([f64; LANES], [f64; LANES]) {
    let (v0, _) = p.rest();
    let dt = plan.dt_ms;
    let h = if HALF { 0.5 * dt } else { dt };
    let (c, d, vp) = (p.c, p.d, p.v_peak);
    let floor = c.min(v0) - 1000.0;
    for l in 0..LANES {
        if vn[l] < vp {
            continue;
        }
        // Crossing time, linear within the (half-)step that crossed,
        // from the unclamped membrane recomputed from the step's start.
        let (vl, ul, il) = (v[l], u[l], cur[l]);
        let a1 = fmax(vl + h * ((0.04 * vl + 5.0) * vl + 140.0 - ul + il), floor);
        let frac = spike_frac(HALF, (vl, ul, il), a1, (h, floor, vp));
        // Reset, then record (padding lanes never count).
        vn[l] = c;
        un[l] += d;
        let t = (n as f64 + frac) * dt;
        if l < live && t < plan.duration_ms {
            events.push(SpikeEvent {
                taxel: first_taxel + l as u32,
                t_ms: t,
            });
        }
    }
    (vn, un)
}

/// Where within a step that spiked the membrane crossed the peak, as a
/// fraction of the step: linear within the (half-)step that crossed, from
/// the unclamped membrane `a1` after the first (half-)step, recomputing the
/// second half-step from the step's start `(v, u, I)`. Shared by the batch
/// kernel and [`Izhikevich::step`], so both give the same bits.
#[inline(always)]
fn spike_frac(half: bool, (vl, ul, il): (f64, f64, f64), a1: f64, (h, floor, vp): (f64, f64, f64)) -> f64 {
    if !half {
        crossing(vl, a1, vp)
    } else if a1 >= vp {
        0.5 * crossing(vl, a1, vp)
    } else {
        let a2 = fmax(a1 + h * ((0.04 * a1 + 5.0) * a1 + 140.0 - ul + il), floor);
        0.5 + 0.5 * crossing(a1, a2, vp)
    }
}

/// Fraction of a step at which a line from `v0` (below `vp`) to `v1` (at or
/// above it) crosses `vp`, in `[0, 1]`; 1 for a degenerate segment.
#[inline]
fn crossing(v0: f64, v1: f64, vp: f64) -> f64 {
    let f = (vp - v0) / (v1 - v0);
    if f.is_finite() {
        f.clamp(0.0, 1.0)
    } else {
        1.0
    }
}

impl Map for Izhikevich {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_input_shape("izhikevich", s, self.dt_ms)?;
        let (events, _, finite) = self.encode_finite(&s.data, s.sample_rate_hz);
        if !finite {
            return Err(crate::signal::non_finite_error("izhikevich", s));
        }
        Ok(SpikeTrain {
            layout: s.layout.clone(),
            duration_ms: s.duration_ms(),
            events,
        }
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn neuron(preset: Preset, scheme: Scheme, dt_ms: f64) -> Izhikevich {
        Izhikevich {
            params: IzhParams::preset(preset),
            dt_ms,
            scheme,
            input: InputMode::Hold,
        }
    }

    /// Spikes of one neuron under a constant current for `ms` at 1 kHz: (all, after the first 1000 ms).
    fn constant(n: &Izhikevich, i: f64, ms: usize) -> (usize, usize) {
        let ev = n.encode(&[vec![i; ms]], 1000.0);
        (ev.len(), ev.iter().filter(|e| e.t_ms >= 1000.0).count())
    }

    #[test]
    fn silent_input_stays_silent_at_rest() {
        for preset in [
            Preset::FaI,
            Preset::RegularSpiking,
            Preset::FastSpiking,
            Preset::LowThresholdSpiking,
        ] {
            for scheme in [Scheme::Izhikevich, Scheme::Euler] {
                let n = neuron(preset, scheme, 0.5);
                let (ev, st) = n.encode_with_state(&[vec![0.0; 3000]], 1000.0);
                assert!(ev.is_empty(), "{preset:?} {scheme:?}");
                let (v, u) = n.params.rest();
                assert!((st[0].0 - v).abs() < 1e-9 && (st[0].1 - u).abs() < 1e-9);
            }
        }
        let (v, u) = IzhParams::preset(Preset::FaI).rest();
        assert!((v + 70.0).abs() < 1e-9 && (u + 14.0).abs() < 1e-9);
    }

    /// Izhikevich 2003: RS is silent below rheobase and its tonic rate rises with
    /// the current. Numerically (scheme `izhikevich`, dt = 0.5 ms), a step from
    /// rest gives one transient spike from I ~ 2.71 and tonic firing from
    /// I ~ 3.776 (the saddle-node current of the v-nullcline is 4; the limit cycle
    /// appears slightly below it).
    #[test]
    fn regular_spiking_rheobase_and_rate() {
        let rs = neuron(Preset::RegularSpiking, Scheme::Izhikevich, 0.5);
        assert_eq!(constant(&rs, 2.6, 3000), (0, 0));
        // I = 3: a single onset spike, then silence.
        let (all, late) = constant(&rs, 3.0, 3000);
        assert_eq!((all, late), (1, 0));
        assert_eq!(constant(&rs, 3.75, 3000).1, 0);
        assert!(constant(&rs, 3.8, 3000).1 > 0);
        // I = 5 fires tonically; the rate rises with the current.
        let rates: Vec<usize> = [5.0, 7.0, 10.0, 15.0, 20.0, 40.0]
            .iter()
            .map(|&i| constant(&rs, i, 2000).1)
            .collect();
        assert!(rates[0] >= 8, "{rates:?}");
        assert!(rates.windows(2).all(|w| w[1] > w[0]), "{rates:?}");
        // RS adapts (d = 8): fewer late than early spikes per second at I = 10.
        let ev = rs.encode(&[vec![10.0; 2000]], 1000.0);
        let early = ev.iter().filter(|e| e.t_ms < 200.0).count() * 5;
        let late = ev.iter().filter(|e| e.t_ms >= 1000.0).count();
        assert!(early > late, "early {early}/s, late {late}/s");
        // The FA-I neuron (d = 2) adapts less, so fires faster than RS.
        let fa = neuron(Preset::FaI, Scheme::Izhikevich, 0.5);
        assert!(constant(&fa, 10.0, 2000).1 > constant(&rs, 10.0, 2000).1);
        // The rheobase barely depends on the scheme and step.
        for (scheme, dt) in [
            (Scheme::Euler, 0.1),
            (Scheme::Euler, 0.5),
            (Scheme::Izhikevich, 1.0),
        ] {
            let n = neuron(Preset::RegularSpiking, scheme, dt);
            assert_eq!(constant(&n, 3.7, 3000).1, 0, "{scheme:?} {dt}");
            assert!(constant(&n, 3.85, 3000).1 > 0, "{scheme:?} {dt}");
        }
    }

    #[test]
    fn fast_spiking_fires_faster_than_regular_spiking() {
        let fs = neuron(Preset::FastSpiking, Scheme::Izhikevich, 0.5);
        let rs = neuron(Preset::RegularSpiking, Scheme::Izhikevich, 0.5);
        assert!(constant(&fs, 10.0, 2000).1 > 2 * constant(&rs, 10.0, 2000).1);
    }

    #[test]
    fn schemes_agree_at_small_steps() {
        let a = neuron(Preset::FaI, Scheme::Izhikevich, 0.05).encode(&[vec![10.0; 1000]], 1000.0);
        let b = neuron(Preset::FaI, Scheme::Euler, 0.05).encode(&[vec![10.0; 1000]], 1000.0);
        assert_eq!(a.len(), b.len());
        assert!((a[0].t_ms - b[0].t_ms).abs() < 0.2, "{} {}", a[0].t_ms, b[0].t_ms);
    }

    #[test]
    fn spike_times_are_sorted_and_interpolated() {
        let n = neuron(Preset::FaI, Scheme::Euler, 1.0);
        let mut currents = vec![vec![0.0; 500]; 11];
        for (k, c) in currents.iter_mut().enumerate() {
            c.iter_mut().for_each(|x| *x = 5.0 + k as f64);
        }
        let ev = n.encode(&currents, 1000.0);
        assert!(ev.windows(2).all(|w| w[0].t_ms <= w[1].t_ms));
        assert!(ev.iter().all(|e| e.taxel < 11 && (0.0..500.0).contains(&e.t_ms)));
        // Crossing times fall between step boundaries, not on them.
        assert!(ev.iter().any(|e| e.t_ms.fract() > 0.01 && e.t_ms.fract() < 0.99));
        // Lanes are independent: taxel 9 alone gives the same spikes.
        let alone = n.encode(&currents[9..10], 1000.0);
        let t9: Vec<f64> = ev.iter().filter(|e| e.taxel == 9).map(|e| e.t_ms).collect();
        let ta: Vec<f64> = alone.iter().map(|e| e.t_ms).collect();
        assert_eq!(t9, ta);
    }

    #[test]
    fn hold_and_linear_inputs_differ_only_between_samples() {
        let mut n = neuron(Preset::FaI, Scheme::Izhikevich, 0.25);
        let xs: Vec<f64> = (0..1000).map(|k| if k < 300 { 0.0 } else { 12.0 }).collect();
        let hold = n.encode(std::slice::from_ref(&xs), 1000.0);
        n.input = InputMode::Linear;
        let lin = n.encode(&[xs], 1000.0);
        assert_eq!(hold.len(), lin.len());
        // The linear ramp from sample 299 to 300 reaches the neuron earlier.
        assert!(lin[0].t_ms < hold[0].t_ms && hold[0].t_ms - lin[0].t_ms < 1.0);
    }

    #[test]
    fn extreme_currents_fire_once_per_step() {
        for dt in [0.01, 0.1, 0.5, 1.0, 2.0] {
            for scheme in [Scheme::Izhikevich, Scheme::Euler] {
                let n = neuron(Preset::FaI, scheme, dt);
                let (ev, st) =
                    n.encode_with_state(&[vec![1e6; 100], vec![-1e6; 100], vec![1e300; 100]], 1000.0);
                let steps = (100.0 / dt).round() as usize;
                let c0 = ev.iter().filter(|e| e.taxel == 0).count();
                assert_eq!(c0, steps, "dt {dt} {scheme:?}");
                assert_eq!(ev.iter().filter(|e| e.taxel == 1).count(), 0);
                assert!(st.iter().all(|(v, u)| v.is_finite() && u.is_finite()), "{st:?}");
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Piecewise-constant currents from 0 to 1e6 (log-spread, including bursts
        /// followed by silence), steps 0.01..2 ms, either scheme: state and spike
        /// times finite, times inside the trial, and at most one spike per step.
        #[test]
        fn never_nan_and_at_most_one_spike_per_step(
            segs in proptest::collection::vec((-1.0f64..6.0, 1usize..40), 1..8),
            dt in 0.01f64..2.0,
            euler in any::<bool>(),
            preset in 0usize..3,
        ) {
            let preset = [Preset::FaI, Preset::RegularSpiking, Preset::FastSpiking][preset];
            let scheme = if euler { Scheme::Euler } else { Scheme::Izhikevich };
            let mut xs = Vec::new();
            for (lg, len) in segs {
                let i = if lg < 0.0 { 0.0 } else { 10f64.powf(lg) };
                xs.extend(std::iter::repeat_n(i, len));
            }
            let n = neuron(preset, scheme, dt);
            let dur = xs.len() as f64;
            let (ev, st) = n.encode_with_state(&[xs], 1000.0);
            prop_assert!(st[0].0.is_finite() && st[0].1.is_finite());
            prop_assert!(st[0].0 <= n.params.v_peak);
            let steps = (dur / dt - 1e-9).ceil() as usize;
            prop_assert!(ev.len() <= steps);
            for e in &ev {
                prop_assert!(e.t_ms.is_finite() && e.t_ms >= 0.0 && e.t_ms < dur);
            }
            for w in ev.windows(2) {
                prop_assert!(w[1].t_ms > w[0].t_ms);
            }
            // Two spikes apart lie in steps at least two apart.
            for w in ev.windows(3) {
                prop_assert!(w[2].t_ms - w[0].t_ms > dt * (1.0 - 1e-9));
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// A taxel whose signal never changes normalizes to 0, drives no
        /// current and fires nothing, whatever its level.
        #[test]
        fn unchanging_taxel_fires_nothing(level in -1e9f64..1e9, n in 1usize..3000) {
            use crate::signal::{derivative::{differentiate, DiffScheme}, normalize::normalize_trial};
            let v = normalize_trial(&vec![level; n], 0.0);
            prop_assert!(v.iter().all(|&x| x == 0.0));
            let i: Vec<f64> = differentiate(&v, 1000.0, DiffScheme::Central).iter().map(|d| 20.0 * d.abs()).collect();
            let ev = neuron(Preset::FaI, Scheme::Izhikevich, 0.5).encode(&[i], 1000.0);
            prop_assert!(ev.is_empty());
        }
    }

    /// The streaming step reproduces the batch encoder bit for bit, in both
    /// schemes and at steps that do and do not divide the sample period.
    #[test]
    fn streaming_step_matches_batch_encoder() {
        let xs: Vec<f64> = (0..3000)
            .map(|k| {
                let t = k as f64 / 1000.0;
                (25.0 * (t * 7.0).sin()).max(0.0) + if k % 97 == 0 { 1e5 } else { 0.0 }
            })
            .collect();
        for (scheme, dt) in [
            (Scheme::Izhikevich, 0.5),
            (Scheme::Euler, 0.25),
            (Scheme::Izhikevich, 1.0),
            (Scheme::Izhikevich, 0.3),
        ] {
            // Both input modes: the batch encoder runs in tiles of
            // `super::super::TILE` samples (3000 samples: 11 whole tiles and
            // a partial one), and linear input looks across tile edges.
            for input in [InputMode::Hold, InputMode::Linear] {
                let mut n = neuron(Preset::FaI, scheme, dt);
                n.input = input;
                let (batch, st) = n.encode_with_state(std::slice::from_ref(&xs), 1000.0);
                let plan = StepInput::new(xs.len(), 1000.0, dt, input);
                let mut s = n.initial_state();
                let mut times = Vec::new();
                for k in 0..plan.n_steps {
                    if let Some(f) = n.step(&mut s, plan.at(&xs, k)) {
                        let t = (k as f64 + f) * dt;
                        if t < plan.duration_ms {
                            times.push(t);
                        }
                    }
                }
                let bt: Vec<f64> = batch.iter().map(|e| e.t_ms).collect();
                assert!(!bt.is_empty());
                assert_eq!(times, bt, "{scheme:?} {dt} {input:?}");
                assert_eq!((s.v, s.u), st[0], "{scheme:?} {dt} {input:?}");
            }
        }
    }

    #[test]
    fn the_avx2_and_baseline_kernels_give_the_same_bits() {
        // A ramp through threshold and a noisy drive on 11 taxels (a full and
        // a partial block of lanes), both schemes and input modes.
        let currents: Vec<Vec<f64>> = (0..11)
            .map(|k| {
                (0..4000)
                    .map(|j| 2.0 * k as f64 + 0.01 * j as f64 + 5.0 * ((j * (k + 3)) as f64 * 0.37).sin())
                    .collect()
            })
            .collect();
        for scheme in [Scheme::Izhikevich, Scheme::Euler] {
            for input in [InputMode::Hold, InputMode::Linear] {
                let mut n = neuron(Preset::FaI, scheme, 0.5);
                n.input = input;
                let fast = n.encode_with_state(&currents, 1000.0);
                let slow = crate::wide::baseline_only(|| n.encode_with_state(&currents, 1000.0));
                assert!(!fast.0.is_empty());
                let bits = |r: &(Vec<SpikeEvent>, Vec<(f64, f64)>)| {
                    let ev: Vec<(u32, u64)> = r.0.iter().map(|e| (e.taxel, e.t_ms.to_bits())).collect();
                    let st: Vec<(u64, u64)> = r.1.iter().map(|&(v, u)| (v.to_bits(), u.to_bits())).collect();
                    (ev, st)
                };
                assert_eq!(bits(&fast), bits(&slow), "{scheme:?} {input:?}");
            }
        }
    }

    #[test]
    fn config_checks_name_the_key() {
        let ctx = BuildContext {
            stage_id: "e".into(),
            seed: 0,
            out_dir: ".".into(),
            base_dir: ".".into(),
        };
        let bad = |c: IzhikevichConfig| c.build(&ctx).err().unwrap().key;
        assert_eq!(
            bad(IzhikevichConfig {
                c: Some(40.0),
                ..Default::default()
            })
            .as_deref(),
            Some("c")
        );
        assert_eq!(
            bad(IzhikevichConfig {
                dt_ms: 0.0,
                ..Default::default()
            })
            .as_deref(),
            Some("dt_ms")
        );
        assert_eq!(
            bad(IzhikevichConfig {
                a: Some(1.0),
                dt_ms: 2.0,
                ..Default::default()
            })
            .as_deref(),
            Some("dt_ms")
        );
        // Explicit keys override the preset.
        let c = IzhikevichConfig {
            preset: Preset::RegularSpiking,
            d: Some(2.0),
            ..Default::default()
        };
        assert_eq!(c.params().unwrap(), IzhParams::preset(Preset::FaI));
    }

    /// A step over `COARSE_DT_MS` runs but warns, naming `dt_ms`; the
    /// default and the threshold itself do not.
    #[test]
    fn coarse_steps_warn() {
        let ctx = BuildContext {
            stage_id: "e".into(),
            seed: 0,
            out_dir: ".".into(),
            base_dir: ".".into(),
        };
        let warnings = |dt_ms: f64| {
            let c = IzhikevichConfig {
                dt_ms,
                ..Default::default()
            };
            assert!(c.build(&ctx).is_ok());
            c.inspect(&ctx, &[]).warnings
        };
        assert!(warnings(0.5).is_empty());
        assert!(warnings(COARSE_DT_MS).is_empty());
        let w = warnings(5.0);
        assert_eq!(w.len(), 1);
        assert_eq!(w[0].key.as_deref(), Some("dt_ms"));
        assert!(w[0].message.contains("5 ms"), "{}", w[0].message);
    }
}
