//! `lowpass`: Butterworth low-pass filter of each taxel, designed here as
//! cascaded second-order sections (SOS).
//!
//! Design (order `N`, cutoff `fc`, sample rate `fs`):
//!
//! 1. Prewarp: `K = tan(π fc / fs)` (the bilinear transform maps the analog
//!    frequency `2 fs K` to exactly `fc`).
//! 2. Analog Butterworth prototype poles `s_k = exp(jπ(2k + N + 1) / 2N)`,
//!    `k = 0..N`; each conjugate pair gives a section `1 / (s² + q s + 1)` with
//!    `q = 2 sin(π(2k + 1) / 2N)`, `k = 0..N/2`, and odd `N` adds `1 / (s + 1)`.
//! 3. Bilinear transform `s = (1/K)(1 - z⁻¹)/(1 + z⁻¹)` of each section:
//!    `b = K²(1, 2, 1) / a0`, `a = (1, 2(K² - 1), 1 - qK + K²) / a0`,
//!    `a0 = 1 + qK + K²`; first order `b = K(1, 1)/(1 + K)`,
//!    `a = (1, (K - 1)/(1 + K))`. Every section has unit gain at DC.
//!
//! Sections run in transposed direct form II, which keeps rounding small for
//! low cutoffs.
//!
//! Modes:
//!
//! * `zero_phase` (offline, default): forward then backward (filtfilt). The
//!   magnitude is squared and the phase cancels, so there is no lag. So that
//!   `cutoff_hz` is still the -3 dB point of the whole stage, each pass is
//!   designed at `K' = K / (√2 - 1)^(1/2N)` (each pass is then -1.5 dB at
//!   `fc`: `(1 + (K/K')^2N)^-2 = 1/2`). Start-up: each end is extended by
//!   `P = max(3(2·sections + 1), ⌈fs/fc⌉)` samples (at most `n - 1`) of odd
//!   reflection, as scipy's `filtfilt` does, but about the *level of the
//!   signal's start*, not its first sample: a least-squares line
//!   `x[k] ≈ L + s·k` over the first `2P` samples (at most `n`) gives `L`,
//!   and the extension is `x[-i] = 2L - x[i]`, `i = 1..P` (the same at the
//!   end, from the last `2P` samples). The forward pass starts in the
//!   steady state of the line (value `L - s·P` at the extension's first
//!   sample, slope `s`; scipy starts from the steady state of the first
//!   padded sample, `lfilter_zi`, a constant), the backward pass in the
//!   steady state of the forward output's last sample with the end line's
//!   slope. A ramp `c + s k` leaves a section with DC delay `τ` as
//!   `c + s (k - τ)` (see [`dc_delay`]), which gives each section's state
//!   ([`ramp_state`]). Why: a
//!   zero-phase filter of a signal odd about `(0, x[0])` passes exactly
//!   through `x[0]`, so reflecting about a noisy first sample pins the
//!   output to that sample's noise and the output then relaxes to the true
//!   level within ~`1/fc`: on the lab scene (5 mV noise) that slope made
//!   every taxel's FA-I neuron fire ~3 ms into each trial. The fitted
//!   level's error is ~`2σ/√(2P)` (σ the noise), below the filtered noise
//!   itself, and a signal that starts or ends on a straight line (flat, or
//!   a ramp) continues it exactly, with no transient.
//! * `causal` (live): a single forward pass designed at `fc` exactly, starting
//!   in the steady state of the first sample (as if the signal had been at that
//!   value before the recording began).
//!
//! `cutoff_hz` must lie below the Nyquist frequency `fs/2`, and the
//! normalised cutoff `fc/fs` must be at least [`MIN_CUTOFF_RATIO`] = 1e-7.
//! Why the lower bound: a section's DC gain is `Σb / (1 + a1 + a2)` with
//! `1 + a1 + a2 = 4K²/a0`, a difference of coefficients near -2 and 1, so
//! rounding each coefficient to f64 (~1e-16) moves the section's gain,
//! cutoff and damping by ~`1e-16 / 4K²` (`K ≈ π fc/fs`). Measured on the
//! rounded coefficients with exact arithmetic, the worst over orders 1 to
//! 16 and both modes: 8e-6 at `fc/fs = 1e-6`, 8e-4 at 1e-7, 9% at 1e-8,
//! and from ~3e-9 down some section's pole rounds onto or outside the unit
//! circle (the output drifts without bound; at `fs` ≈ 1e50 Hz for a 10 Hz
//! cutoff every pole rounds to `z = 1` and the filter outputs NaN). Below
//! 1e-7 the stage refuses, naming `cutoff_hz`; it refuses any design whose
//! coefficients are not finite too.
//!
//! When the source states its sample rate in its config (a scene's
//! `motion.sample_rate_hz`, a file source's `sample_rate_hz`), `palpate
//! check` refuses a cutoff outside these bounds; otherwise the rate is known
//! only from the data, and the run stops with the same error naming the key.

use super::{check_shape, check_signals, non_finite_error};
use palpate_core::{
    check_positive, check_range, fmt_num, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec,
    Inspection, Item, Map, OutputFacts, Payload, PayloadKind, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Offline (zero-phase) or live (causal) filtering.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum FilterMode {
    /// Forward-backward: no lag, -3 dB at the cutoff overall (offline).
    #[default]
    ZeroPhase,
    /// One forward pass (live data); lags like any causal filter.
    Causal,
}

/// Butterworth low-pass of each taxel (cascaded second-order sections), zero-phase or causal.
///
/// `cutoff_hz` is the -3 dB point of the whole stage in both modes.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LowpassConfig {
    /// Filter order (poles per pass), 1 to 16. Default 2.
    pub order: usize,
    /// -3 dB cutoff frequency, Hz; must be below half the sample rate and at
    /// least 1e-7 of it (below, f64 cannot hold the design: see the module
    /// docs). Default 20.
    pub cutoff_hz: f64,
    /// `zero_phase` (forward-backward, offline) or `causal` (live). Default `zero_phase`.
    pub mode: FilterMode,
}

impl Default for LowpassConfig {
    fn default() -> Self {
        LowpassConfig {
            order: 2,
            cutoff_hz: 20.0,
            mode: FilterMode::ZeroPhase,
        }
    }
}

#[typetag::serde(name = "lowpass")]
impl StageConfig for LowpassConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(check_range("order", self.order as f64, 1.0, 16.0, ""));
        c.take(check_positive("cutoff_hz", self.cutoff_hz, "Hz"));
        c.finish()?;
        Ok(Stage::Map(Box::new(Lowpass {
            order: self.order,
            cutoff_hz: self.cutoff_hz,
            mode: self.mode,
        })))
    }
    /// A cutoff at or above the Nyquist frequency of a sample rate known
    /// before the run (a scene's), or below [`MIN_CUTOFF_RATIO`] of it, is an
    /// error here, at check time.
    fn inspect(&self, _ctx: &BuildContext, inputs: &[OutputFacts]) -> Inspection {
        let facts = OutputFacts::agreed(inputs);
        let mut errors = Vec::new();
        if let Some(fs) = facts.sample_rate_hz {
            if let Some(problem) = cutoff_problem(self.cutoff_hz, fs) {
                errors.push(ConfigError::key("cutoff_hz", problem));
            }
        }
        Inspection {
            facts,
            errors,
            warnings: Vec::new(),
        }
    }
}
register_stage!("lowpass", LowpassConfig);

/// Smallest normalised cutoff `cutoff_hz / fs` the stage designs (see the
/// module docs: below it, rounding the coefficients to f64 moves the gain and
/// cutoff by more than 0.1%, and from ~3e-9 the filter is unstable).
pub const MIN_CUTOFF_RATIO: f64 = 1e-7;

/// Why `cutoff_hz` cannot be designed at sample rate `fs` (positive, finite),
/// as the rest of a sentence after the key; `None` when it can, and for a
/// cutoff that is not a positive number (the build's own check names it).
pub fn cutoff_problem(cutoff_hz: f64, fs: f64) -> Option<String> {
    if !(cutoff_hz > 0.0 && cutoff_hz.is_finite()) {
        return None;
    }
    if cutoff_hz >= fs / 2.0 {
        return Some(format!(
            "{} Hz must lie below the Nyquist frequency {} Hz (half the input's sample rate, {} Hz)",
            fmt_num(cutoff_hz),
            fmt_num(fs / 2.0),
            fmt_num(fs)
        ));
    }
    // Written as a product so that a ratio that underflows (1e-300 Hz at
    // 1e300 Hz) is still refused.
    if cutoff_hz < MIN_CUTOFF_RATIO * fs {
        return Some(format!(
            "{} Hz is {} of the input's sample rate ({} Hz), below the {} a Butterworth design in f64 \
             can hold (its coefficients round to a wrong or unstable filter); raise `cutoff_hz` to at \
             least {} Hz or resample the signals to a lower rate",
            fmt_num(cutoff_hz),
            fmt_num(cutoff_hz / fs),
            fmt_num(fs),
            fmt_num(MIN_CUTOFF_RATIO),
            fmt_num(MIN_CUTOFF_RATIO * fs)
        ));
    }
    None
}

/// One second-order section `b0 + b1 z⁻¹ + b2 z⁻²` over `1 + a1 z⁻¹ + a2 z⁻²`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Biquad {
    /// Numerator.
    pub b: [f64; 3],
    /// Denominator `a1, a2` (`a0 = 1`).
    pub a: [f64; 2],
}

impl Biquad {
    /// The section's complex gain at normalized angular frequency `w` (rad/sample).
    pub fn response(&self, w: f64) -> (f64, f64) {
        // H = (b0 + b1 e^-jw + b2 e^-2jw) / (1 + a1 e^-jw + a2 e^-2jw)
        let (c1, s1, c2, s2) = (w.cos(), -w.sin(), (2.0 * w).cos(), -(2.0 * w).sin());
        let (nr, ni) = (
            self.b[0] + self.b[1] * c1 + self.b[2] * c2,
            self.b[1] * s1 + self.b[2] * s2,
        );
        let (dr, di) = (
            1.0 + self.a[0] * c1 + self.a[1] * c2,
            self.a[0] * s1 + self.a[1] * s2,
        );
        let den = dr * dr + di * di;
        ((nr * dr + ni * di) / den, (ni * dr - nr * di) / den)
    }
}

/// Designs a Butterworth low-pass of `order` whose prewarped analog cutoff is
/// `k = tan(π fc / fs)`, as second-order sections (a first-order one last for
/// odd orders, stored with `b2 = a2 = 0`).
pub fn butterworth_sos(order: usize, k: f64) -> Vec<Biquad> {
    let n = order as f64;
    let mut sos = Vec::with_capacity(order.div_ceil(2));
    for i in 0..order / 2 {
        let q = 2.0 * (PI * (2.0 * i as f64 + 1.0) / (2.0 * n)).sin();
        let a0 = 1.0 + q * k + k * k;
        let kk = k * k / a0;
        sos.push(Biquad {
            b: [kk, 2.0 * kk, kk],
            a: [2.0 * (k * k - 1.0) / a0, (1.0 - q * k + k * k) / a0],
        });
    }
    if order % 2 == 1 {
        let g = k / (1.0 + k);
        sos.push(Biquad {
            b: [g, g, 0.0],
            a: [(k - 1.0) / (1.0 + k), 0.0],
        });
    }
    sos
}

/// Magnitude of a cascade at frequency `f` for sample rate `fs`.
pub fn magnitude(sos: &[Biquad], f: f64, fs: f64) -> f64 {
    let w = 2.0 * PI * f / fs;
    sos.iter()
        .map(|s| {
            let (re, im) = s.response(w);
            (re * re + im * im).sqrt()
        })
        .product()
}

/// Runs `xs` through the cascade in place, each section starting in the steady
/// state of `xs[0]` (every section has unit DC gain).
pub fn sosfilt(sos: &[Biquad], xs: &mut [f64]) {
    let Some(&x0) = xs.first() else { return };
    sosfilt_from(sos, xs, x0);
}

/// Runs `xs` through the cascade in place, each section starting in the
/// steady state of a constant input `x0` (before the first sample).
pub fn sosfilt_from(sos: &[Biquad], xs: &mut [f64], x0: f64) {
    for s in sos {
        let [b0, b1, b2] = s.b;
        let [a1, a2] = s.a;
        // Transposed DF-II steady state for constant input x0 and output x0.
        let mut z2 = (b2 - a2) * x0;
        let mut z1 = (b1 - a1) * x0 + z2;
        for x in xs.iter_mut() {
            let xi = *x;
            let y = b0 * xi + z1;
            z1 = b1 * xi - a1 * y + z2;
            z2 = b2 * xi - a2 * y;
            *x = y;
        }
    }
}

/// The runtime `lowpass` stage.
pub struct Lowpass {
    order: usize,
    cutoff_hz: f64,
    mode: FilterMode,
}

impl Lowpass {
    /// A low-pass of `order` with its -3 dB point at `cutoff_hz` (checked at
    /// build and run time by the stage; see [`LowpassConfig`]).
    pub fn new(order: usize, cutoff_hz: f64, mode: FilterMode) -> Lowpass {
        Lowpass {
            order,
            cutoff_hz,
            mode,
        }
    }

    /// The sections of one pass for sample rate `fs`; an error naming the
    /// stage and `cutoff_hz` when `fs` cannot hold the design (see
    /// [`cutoff_problem`]) or its coefficients are not finite.
    pub fn design(&self, fs: f64) -> Result<Vec<Biquad>, StageError> {
        if !(self.cutoff_hz > 0.0 && self.cutoff_hz.is_finite()) {
            return Err(StageError::new(format!(
                "lowpass: key `cutoff_hz` = {} must be a positive number of Hz",
                fmt_num(self.cutoff_hz)
            )));
        }
        // The run-time wording of the Nyquist error (the user guide quotes it).
        if self.cutoff_hz >= fs / 2.0 {
            return Err(StageError::new(format!(
                "lowpass: key `cutoff_hz` = {} Hz must lie below the Nyquist frequency {} Hz of these signals",
                fmt_num(self.cutoff_hz),
                fmt_num(fs / 2.0)
            )));
        }
        if let Some(problem) = cutoff_problem(self.cutoff_hz, fs) {
            return Err(StageError::new(format!("lowpass: key `cutoff_hz` = {problem}")));
        }
        let k = (PI * self.cutoff_hz / fs).tan();
        let k = match self.mode {
            FilterMode::Causal => k,
            // Each of the two passes at -1.5 dB so the product is -3 dB at fc.
            FilterMode::ZeroPhase => k / (2f64.sqrt() - 1.0).powf(1.0 / (2.0 * self.order as f64)),
        };
        let sos = butterworth_sos(self.order, k);
        // The bounds above keep every coefficient finite; this keeps a NaN
        // from reaching the next stage if they ever do not.
        if sos.iter().any(|q| !q.b.iter().chain(&q.a).all(|c| c.is_finite())) {
            return Err(StageError::new(format!(
                "lowpass: key `cutoff_hz` = {} Hz at a sample rate of {} Hz gives non-finite filter coefficients",
                fmt_num(self.cutoff_hz),
                fmt_num(fs)
            )));
        }
        Ok(sos)
    }

    /// Filters one taxel.
    pub fn filter(&self, sos: &[Biquad], xs: &[f64], fs: f64) -> Vec<f64> {
        let n = xs.len();
        match self.mode {
            FilterMode::Causal => {
                let mut y = xs.to_vec();
                sosfilt(sos, &mut y);
                y
            }
            FilterMode::ZeroPhase => {
                let (pad, fit) = self.edges(sos.len(), fs, n);
                filtfilt(sos, xs, pad, fit)
            }
        }
    }

    /// Zero-phase edge handling for `n` samples: the length of each odd
    /// extension and of the window the start and end levels are fitted on.
    pub fn edges(&self, sections: usize, fs: f64, n: usize) -> (usize, usize) {
        // At least scipy's 3 (2 sections + 1) and one period of the cutoff
        // (the filter's memory); the level is fitted over two such periods.
        let want = (3 * (2 * sections + 1)).max((fs / self.cutoff_hz).ceil().min(1e9) as usize);
        (want.min(n.saturating_sub(1)), want.saturating_mul(2).min(n))
    }
}

/// Least-squares line through `ys[0], ys[1], ...` (index as abscissa):
/// `(value at index 0, slope per sample)`. One sample: `(ys[0], 0)`.
pub fn edge_line(ys: impl ExactSizeIterator<Item = f64> + Clone) -> (f64, f64) {
    let m = ys.len();
    if m < 2 {
        return (ys.clone().next().unwrap_or(0.0), 0.0);
    }
    let kbar = (m - 1) as f64 / 2.0;
    let mean = ys.clone().sum::<f64>() / m as f64;
    // sum (k - kbar)^2 = m (m^2 - 1) / 12
    let skk = m as f64 * ((m * m) as f64 - 1.0) / 12.0;
    let sky: f64 = ys.enumerate().map(|(k, y)| (k as f64 - kbar) * (y - mean)).sum();
    let slope = sky / skk;
    (mean - slope * kbar, slope)
}

/// [`edge_line`] of `ys` with a fallback to `(end, 0)` where the sums
/// overflow (values near `f64::MAX`) or the line's run over `pad` samples does.
pub fn edge_fit(ys: impl ExactSizeIterator<Item = f64> + Clone, end: f64, pad: usize) -> (f64, f64) {
    let (l, s) = edge_line(ys);
    if l.is_finite() && (s * pad as f64).is_finite() {
        (l, s)
    } else {
        (end, 0.0)
    }
}

/// Delay at DC of a section with unit DC gain, samples: its steady response
/// to a ramp `c + s k` is `c + s (k - τ)`, with
/// `τ = (b1 + 2 b2 - a1 - 2 a2) / (1 + a1 + a2)` (from the difference equation).
pub fn dc_delay(q: &Biquad) -> f64 {
    ((q.b[1] + 2.0 * q.b[2]) - (q.a[0] + 2.0 * q.a[1])) / (1.0 + q.a[0] + q.a[1])
}

/// The state `(z1, z2)` of every section in the steady state of a ramp whose
/// next input is `v` and which changes by `s` a sample (`s = 0`: a constant):
/// the past inputs `x[-1] = v - s`, `x[-2] = v - 2s` and the outputs they
/// left, `x[-j] - s τ`. Each section passes the ramp on delayed by its own τ.
/// Falls back to the constant `v` if the ramp's numbers are not finite.
pub fn ramp_state(sos: &[Biquad], v: f64, s: f64) -> Vec<(f64, f64)> {
    let mut v_in = v;
    let st: Vec<(f64, f64)> = sos
        .iter()
        .map(|q| {
            let tau = dc_delay(q);
            let (x1, x2) = (v_in - s, v_in - 2.0 * s);
            let (y1, y2) = (x1 - s * tau, x2 - s * tau);
            let z2_before = q.b[2] * x2 - q.a[1] * y2;
            let z2 = q.b[2] * x1 - q.a[1] * y1;
            let z1 = q.b[1] * x1 - q.a[0] * y1 + z2_before;
            v_in -= s * tau;
            (z1, z2)
        })
        .collect();
    if s != 0.0 && st.iter().any(|(a, b)| !(a.is_finite() && b.is_finite())) {
        return ramp_state(sos, v, 0.0);
    }
    st
}

/// Runs `xs` through the cascade in place from the given state of each section.
pub fn sosfilt_state(sos: &[Biquad], xs: &mut [f64], state: Vec<(f64, f64)>) {
    for (q, (mut z1, mut z2)) in sos.iter().zip(state) {
        let [b0, b1, b2] = q.b;
        let [a1, a2] = q.a;
        for x in xs.iter_mut() {
            let xi = *x;
            let y = b0 * xi + z1;
            z1 = b1 * xi - a1 * y + z2;
            z2 = b2 * xi - a2 * y;
            *x = y;
        }
    }
}

/// Zero-phase (forward-backward) filtering of one taxel: the scalar
/// reference of the stage's `zero_phase` mode (see the module docs).
///
/// The ends are extended by `pad` samples of odd reflection about the level a
/// least-squares line over the first (last) `fit` samples gives at the first
/// (last) sample, and the forward pass starts in the steady state of that
/// line's value at the extension's first sample; the backward pass starts in
/// the steady state of the forward output's last sample.
pub fn filtfilt(sos: &[Biquad], xs: &[f64], pad: usize, fit: usize) -> Vec<f64> {
    let n = xs.len();
    if n < 2 {
        return xs.to_vec();
    }
    let pad = pad.min(n - 1);
    let fit = fit.clamp(1, n);
    let (l0, s0) = edge_fit(xs[..fit].iter().copied(), xs[0], pad);
    let (l1, s1) = edge_fit(xs[n - fit..].iter().rev().copied(), xs[n - 1], pad);
    // Odd extension about (0, l0) and (n - 1, l1): 2 l0 - x[pad..1], x,
    // 2 l1 - x[n-2..n-1-pad]. A line through the start stays that line.
    let mut ext = Vec::with_capacity(n + 2 * pad);
    ext.extend((1..=pad).rev().map(|i| 2.0 * l0 - xs[i]));
    ext.extend_from_slice(xs);
    ext.extend((1..=pad).map(|i| 2.0 * l1 - xs[n - 1 - i]));
    sosfilt_state(sos, &mut ext, ramp_state(sos, l0 - s0 * pad as f64, s0));
    ext.reverse();
    // Reversed, the end's line `x[n-1-j] = l1 + s1 j` rises by s1 a step.
    let y_end = ext[0];
    sosfilt_state(sos, &mut ext, ramp_state(sos, y_end, s1));
    ext.reverse();
    ext[pad..pad + n].to_vec()
}

/// Taxels filtered in lock step by [`filtfilt_taxels`]: 16 lanes (four AVX2
/// vectors), as many as a 4x4 array has, so each time step of the recursion
/// runs four independent vector chains instead of one scalar chain.
pub const LANES: usize = crate::wide::LANES;

/// Zero-phase filtering of every taxel, [`LANES`] at a time in lock step:
/// the same arithmetic as [`filtfilt`] per taxel, in the same order (every
/// IEEE operation rounds the same at any vector width), so the same bits.
///
/// Why it is faster: a biquad is a recursion whose each step waits for the
/// last (~10 cycles of add-multiply-add latency per sample and section in
/// one taxel), so one taxel at a time is latency-bound; 16 independent taxels
/// fill the pipeline. The block's samples are gathered once into one
/// sample-major buffer (tiled, [`crate::wide::gather_lanes`]), both passes run
/// in place over it with every section's state in registers (the section
/// count is a compile-time constant up to 8, order 16), and the result is
/// scattered back tile by tile: three sequential sweeps of memory in all.
pub fn filtfilt_taxels(sos: &[Biquad], data: &[Vec<f64>], pad: usize, fit: usize) -> Vec<Vec<f64>> {
    filtfilt_taxels_finite(sos, data, pad, fit).0
}

/// [`filtfilt_taxels`], also telling whether every input sample was finite
/// (noted while the input is transposed, so the stage reads it once).
pub fn filtfilt_taxels_finite(
    sos: &[Biquad],
    data: &[Vec<f64>],
    pad: usize,
    fit: usize,
) -> (Vec<Vec<f64>>, bool) {
    let n = data.first().map_or(0, Vec::len);
    if n < 2 || sos.is_empty() || data.iter().any(|xs| xs.len() != n) {
        let finite = data.iter().all(|xs| super::first_non_finite(xs).is_none());
        return (
            data.iter().map(|xs| filtfilt(sos, xs, pad, fit)).collect(),
            finite,
        );
    }
    // Allocated, not zeroed: every sample is written by the backward
    // sweep's scatter (see `crate::wide::scatter_lanes_uninit`).
    let mut out: Vec<Vec<f64>> = data.iter().map(|_| Vec::with_capacity(n)).collect();
    let mut finite = true;
    crate::wide::with_scratch(|buf| {
        for (chunk, outs) in data.chunks(LANES).zip(out.chunks_mut(LANES)) {
            // Both inlined into the wide function, or the loops stay SSE2.
            finite &= crate::wide::with_avx2(
                #[inline(always)]
                || filtfilt_block(sos, chunk, outs, pad, fit, buf),
            );
            for row in outs.iter_mut() {
                // SAFETY: `filtfilt_block` scattered its tiles, which cover
                // samples `0..n`, into every row of `outs` (all of them
                // lanes of this block), so all `n` samples are written; the
                // capacity is `n`.
                unsafe { row.set_len(n) };
            }
        }
    });
    (out, finite)
}

/// The cascade's state: `z1`, `z2` of each section, per lane.
type State = Vec<([f64; LANES], [f64; LANES])>;

/// Every section in the steady state of a ramp (per lane: next input `v`,
/// slope `s`), by [`ramp_state`] lane by lane (the same bits).
fn steady(sos: &[Biquad], v: &[f64; LANES], s: &[f64; LANES]) -> State {
    let mut st: State = vec![([0.0; LANES], [0.0; LANES]); sos.len()];
    for l in 0..LANES {
        for (k, (z1, z2)) in ramp_state(sos, v[l], s[l]).into_iter().enumerate() {
            st[k].0[l] = z1;
            st[k].1[l] = z2;
        }
    }
    st
}

/// One time step of one section for every lane (transposed direct form II).
#[inline(always)]
fn section(q: &Biquad, z1: &mut [f64; LANES], z2: &mut [f64; LANES], v: &mut [f64; LANES]) {
    let [b0, b1, b2] = q.b;
    let [a1, a2] = q.a;
    for l in 0..LANES {
        let xi = v[l];
        let y = b0 * xi + z1[l];
        z1[l] = b1 * xi - a1 * y + z2[l];
        z2[l] = b2 * xi - a2 * y;
        v[l] = y;
    }
}

/// Runs the cascade of `S` sections in place over `buf` (forwards, or
/// backwards in time), from state `st`, leaving in `st` the state after the
/// last sample, so that a long signal can be swept a tile at a time. The
/// state lives in local arrays across the tile so that it stays in
/// registers.
#[inline(always)]
fn sweep<const S: usize>(sos: &[Biquad], st: &mut State, buf: &mut [[f64; LANES]], backward: bool) {
    let mut q = [Biquad {
        b: [0.0; 3],
        a: [0.0; 2],
    }; S];
    q.copy_from_slice(&sos[..S]);
    let mut z1 = [[0.0; LANES]; S];
    let mut z2 = [[0.0; LANES]; S];
    for k in 0..S {
        (z1[k], z2[k]) = st[k];
    }
    let mut step = |v: &mut [f64; LANES]| {
        for k in 0..S {
            section(&q[k], &mut z1[k], &mut z2[k], v);
        }
    };
    if backward {
        buf.iter_mut().rev().for_each(&mut step);
    } else {
        buf.iter_mut().for_each(&mut step);
    }
    for k in 0..S {
        st[k] = (z1[k], z2[k]);
    }
}

/// [`sweep`] for any number of sections (1 to 8 compiled each; more, which
/// the stage's order cap excludes, run section by section over the tile).
#[inline(always)]
fn sweep_any(sos: &[Biquad], st: &mut State, buf: &mut [[f64; LANES]], backward: bool) {
    match sos.len() {
        1 => sweep::<1>(sos, st, buf, backward),
        2 => sweep::<2>(sos, st, buf, backward),
        3 => sweep::<3>(sos, st, buf, backward),
        4 => sweep::<4>(sos, st, buf, backward),
        5 => sweep::<5>(sos, st, buf, backward),
        6 => sweep::<6>(sos, st, buf, backward),
        7 => sweep::<7>(sos, st, buf, backward),
        8 => sweep::<8>(sos, st, buf, backward),
        _ => {
            // Section after section over the whole tile: the same
            // operations on each sample in the same order.
            for (q, (z1, z2)) in sos.iter().zip(st.iter_mut()) {
                let mut step = |v: &mut [f64; LANES]| section(q, z1, z2, v);
                if backward {
                    buf.iter_mut().rev().for_each(&mut step);
                } else {
                    buf.iter_mut().for_each(&mut step);
                }
            }
        }
    }
}

/// Samples per tile of the fused passes: 128 x 16 lanes is 16 kB, so a
/// tile is swept while it is still in L1.
const TILE: usize = 128;

/// [`filtfilt_taxels`] for one block of up to [`LANES`] taxels of `n >= 2`
/// samples each; missing lanes compute zeros and are dropped. Returns
/// whether the block's samples were finite.
///
/// Passes over memory: the forward sweep runs over each tile as soon as it
/// is transposed in, and the backward sweep over each tile just before it
/// is transposed out, so the trial is read once, the sample-major buffer
/// written once and read once, and the output written once. (The backward
/// sweep stops at the first sample: the start extension's outputs are never
/// used.)
#[inline(always)]
#[allow(clippy::needless_range_loop)] // lanes x samples: indexing both reads clearer than zipped iterators
fn filtfilt_block(
    sos: &[Biquad],
    chunk: &[Vec<f64>],
    outs: &mut [Vec<f64>],
    pad: usize,
    fit: usize,
    buf: &mut Vec<[f64; LANES]>,
) -> bool {
    let n = chunk[0].len();
    let pad = pad.min(n - 1);
    let fit = fit.clamp(1, n);
    let w = chunk.len().min(LANES);
    // Per lane as in `filtfilt`: the start and end levels and the
    // forward pass's starting value.
    let (mut l0, mut l1, mut x0) = ([0.0; LANES], [0.0; LANES], [0.0; LANES]);
    let (mut s0, mut s1) = ([0.0; LANES], [0.0; LANES]);
    for (l, xs) in chunk.iter().enumerate().take(w) {
        (l0[l], s0[l]) = edge_fit(xs[..fit].iter().copied(), xs[0], pad);
        (l1[l], s1[l]) = edge_fit(xs[n - fit..].iter().rev().copied(), xs[n - 1], pad);
        x0[l] = l0[l] - s0[l] * pad as f64;
    }
    let len = n + 2 * pad;
    buf.clear();
    buf.reserve(len);
    let mut st = steady(sos, &x0, &s0);
    // Forward over the extended input `2 l0 - x[pad..1]`, `x`,
    // `2 l1 - x[n-2..n-1-pad]`.
    let mut x = [0.0; LANES];
    for i in (1..=pad).rev() {
        for l in 0..w {
            x[l] = 2.0 * l0[l] - chunk[l][i];
        }
        buf.push(x);
    }
    sweep_any(sos, &mut st, &mut buf[..pad], false);
    let mut finite = true;
    for t0 in (0..n).step_by(TILE) {
        let t1 = (t0 + TILE).min(n);
        finite &= crate::wide::gather_lanes(chunk, t0..t1, buf, None);
        sweep_any(sos, &mut st, &mut buf[pad + t0..pad + t1], false);
    }
    for i in 1..=pad {
        for l in 0..w {
            x[l] = 2.0 * l1[l] - chunk[l][n - 1 - i];
        }
        buf.push(x);
    }
    sweep_any(sos, &mut st, &mut buf[pad + n..], false);
    debug_assert_eq!(buf.len(), len);
    // Backward from the steady state of the forward output's last sample.
    let mut st = steady(sos, &buf[len - 1], &s1);
    sweep_any(sos, &mut st, &mut buf[pad + n..], true);
    let tiles = n.div_ceil(TILE);
    for j in (0..tiles).rev() {
        let (t0, t1) = (j * TILE, ((j + 1) * TILE).min(n));
        let tile = &mut buf[pad + t0..pad + t1];
        sweep_any(sos, &mut st, tile, true);
        crate::wide::scatter_lanes_uninit(tile, outs, t0);
    }
    finite
}

impl Map for Lowpass {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_shape("lowpass", s)?;
        let sos = self.design(s.sample_rate_hz)?;
        let data = match self.mode {
            FilterMode::ZeroPhase => {
                // Finiteness is noted while the input is transposed.
                let (pad, fit) = self.edges(sos.len(), s.sample_rate_hz, s.n_samples());
                let (data, finite) = filtfilt_taxels_finite(&sos, &s.data, pad, fit);
                if !finite {
                    return Err(non_finite_error("lowpass", s));
                }
                data
            }
            FilterMode::Causal => {
                check_signals("lowpass", s)?;
                s.data
                    .iter()
                    .map(|xs| self.filter(&sos, xs, s.sample_rate_hz))
                    .collect()
            }
        };
        if let Some(t) = data.iter().position(|ys| !ends_finite(ys)) {
            return Err(overflow_error(t, &s.data[t]));
        }
        Ok(s.with_data(s.unit.clone(), data).into())
    }
}

/// Whether a filtered taxel's first and last samples are finite, which
/// holds only if every sample is: the sections are recursions, and a value
/// that overflowed to ±inf makes every later state and output ±inf or NaN
/// (inf never returns to a finite number). The causal pass computes the last
/// sample last, the zero-phase backward pass the first, and both passes'
/// padding feeds those recursions, so two reads per taxel check the whole
/// trial, where a scan of the output would cost a pass over memory.
pub(crate) fn ends_finite(ys: &[f64]) -> bool {
    ys.first().is_none_or(|v| v.is_finite()) && ys.last().is_none_or(|v| v.is_finite())
}

/// The error of a filtered taxel that overflowed f64: the input's largest
/// magnitude, near `f64::MAX`, times a section's gain (a higher order's
/// resonant sections, or the zero-phase pass's reflected padding `2 l - x`)
/// went past it. Refused rather than passed on as inf or NaN for the next
/// stage to be blamed for.
pub(crate) fn overflow_error(taxel: usize, xs: &[f64]) -> StageError {
    let peak = xs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    StageError::new(format!(
        "lowpass: taxel {taxel}: the filtered signal overflows f64: its input reaches {}, too near \
         f64's largest number ({:e}) for the filter's sections; scale the input down (another unit)",
        fmt_num(peak),
        f64::MAX
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lp(order: usize, fc: f64, mode: FilterMode) -> Lowpass {
        Lowpass {
            order,
            cutoff_hz: fc,
            mode,
        }
    }

    const DB3: f64 = std::f64::consts::FRAC_1_SQRT_2;

    #[test]
    fn design_is_minus_3db_at_cutoff_and_unit_at_dc() {
        let fs = 1000.0;
        for order in 1..=8 {
            for fc in [5.0, 20.0, 100.0, 400.0] {
                let c = lp(order, fc, FilterMode::Causal).design(fs).unwrap();
                assert!((magnitude(&c, 0.0, fs) - 1.0).abs() < 1e-12);
                assert!(
                    (magnitude(&c, fc, fs) - DB3).abs() < 1e-9,
                    "order {order} fc {fc}"
                );
                // Zero-phase: two passes, squared magnitude, still -3 dB at fc.
                let z = lp(order, fc, FilterMode::ZeroPhase).design(fs).unwrap();
                assert!((magnitude(&z, fc, fs).powi(2) - DB3).abs() < 1e-9);
                // Monotone fall above the cutoff (Butterworth has no ripple).
                assert!(magnitude(&c, fc * 1.2, fs) < magnitude(&c, fc, fs));
                assert!(magnitude(&c, fs * 0.499, fs) < 0.5);
            }
        }
    }

    #[test]
    fn roll_off_is_6n_db_per_octave() {
        let fs = 10_000.0;
        let c = lp(4, 10.0, FilterMode::Causal).design(fs).unwrap();
        let ratio = magnitude(&c, 80.0, fs) / magnitude(&c, 160.0, fs);
        // ~24 dB per octave for order 4: a factor 2^4 = 16.
        assert!((ratio - 16.0).abs() < 0.5, "{ratio}");
    }

    /// Amplitude of the steady-state response to a sine at `f`.
    fn sine_gain(f: &Lowpass, freq: f64, fs: f64) -> f64 {
        let n = 8000;
        let xs: Vec<f64> = (0..n).map(|i| (2.0 * PI * freq * i as f64 / fs).sin()).collect();
        let sos = f.design(fs).unwrap();
        let y = f.filter(&sos, &xs, fs);
        y[2000..6000].iter().fold(0.0_f64, |m, v| m.max(v.abs()))
    }

    #[test]
    fn filtered_sine_at_cutoff_is_minus_3db() {
        let fs = 1000.0;
        for mode in [FilterMode::Causal, FilterMode::ZeroPhase] {
            let g = sine_gain(&lp(3, 25.0, mode), 25.0, fs);
            assert!((g - DB3).abs() < 5e-3, "{mode:?}: {g}");
        }
    }

    /// Time (in samples, fractional) at which `ys` first falls through 0.5.
    fn crossing(ys: &[f64]) -> f64 {
        let i = ys.iter().position(|&y| y < 0.5).unwrap();
        (i - 1) as f64 + (ys[i - 1] - 0.5) / (ys[i - 1] - ys[i])
    }

    #[test]
    fn zero_phase_has_no_lag_and_causal_lags() {
        let fs = 1000.0;
        // A 1 s ramp 1 -> 0 after a 2 s hold: the midpoint is at sample 2500.
        let xs: Vec<f64> = (0..5000)
            .map(|i| (1.0 - (i as f64 - 2000.0) / 1000.0).clamp(0.0, 1.0))
            .collect();
        let z = lp(4, 5.0, FilterMode::ZeroPhase);
        let y = z.filter(&z.design(fs).unwrap(), &xs, fs);
        assert!((crossing(&y) - 2500.0).abs() < 0.5, "{}", crossing(&y));
        // Symmetric pulse: the peak does not move.
        let pulse: Vec<f64> = (0..2001)
            .map(|i| (-((i as f64 - 1000.0) / 30.0).powi(2)).exp())
            .collect();
        let yp = z.filter(&z.design(fs).unwrap(), &pulse, fs);
        let peak = yp.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
        assert_eq!(peak, 1000);
        let c = lp(4, 5.0, FilterMode::Causal);
        let yc = c.filter(&c.design(fs).unwrap(), &xs, fs);
        assert!(crossing(&yc) - 2500.0 > 20.0, "{}", crossing(&yc));
        // Flat starts and ends stay flat: no startup transient.
        assert!((y[0] - 1.0).abs() < 1e-9 && y[4999].abs() < 1e-9);
        assert!((yc[0] - 1.0).abs() < 1e-12);
    }

    /// Seeded white Gaussian noise of SD `sigma` around `level`.
    fn noisy(n: usize, level: f64, sigma: f64, seed: u64) -> Vec<f64> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let d = Normal::new(level, sigma).unwrap();
        (0..n).map(|_| d.sample(&mut rng)).collect()
    }

    /// The old start-up (the failing case): odd reflection about the
    /// first and last samples, each pass from the steady state of its first
    /// sample (scipy's `filtfilt` with `padtype = "odd"`).
    fn filtfilt_pinned(sos: &[Biquad], xs: &[f64], pad: usize) -> Vec<f64> {
        let n = xs.len();
        let mut ext: Vec<f64> = (1..=pad).rev().map(|i| 2.0 * xs[0] - xs[i]).collect();
        ext.extend_from_slice(xs);
        ext.extend((1..=pad).map(|i| 2.0 * xs[n - 1] - xs[n - 1 - i]));
        sosfilt(sos, &mut ext);
        ext.reverse();
        sosfilt(sos, &mut ext);
        ext.reverse();
        ext[pad..pad + n].to_vec()
    }

    /// Largest |slope| of `y` over `range`, per sample.
    fn max_slope(y: &[f64], range: std::ops::Range<usize>) -> f64 {
        y[range].windows(2).fold(0.0, |m, w| m.max((w[1] - w[0]).abs()))
    }

    /// Issue 15: on a flat rest level with the lab scene's 5 mV of noise, the
    /// zero-phase output must not move faster in its first and last 50 ms than
    /// the filtered noise moves anywhere else (reflecting about the noisy first
    /// sample made it relax from that sample: every taxel fired ~3 ms in).
    #[test]
    fn noisy_flat_start_has_no_transient() {
        let fs = 1000.0;
        let f = lp(2, 10.0, FilterMode::ZeroPhase);
        let sos = f.design(fs).unwrap();
        let (n, e) = (6000, 50);
        let (mut new_worst, mut old_median) = (0.0_f64, Vec::new());
        for seed in 0..40 {
            let xs = noisy(n, 3.3, 0.005, seed);
            let interior = max_slope(&f.filter(&sos, &xs, fs), 500..n - 500);
            let ratio = |y: &[f64]| max_slope(y, 0..e).max(max_slope(y, n - e..n)) / interior;
            new_worst = new_worst.max(ratio(&f.filter(&sos, &xs, fs)));
            let (pad, _) = f.edges(sos.len(), fs, n);
            old_median.push(ratio(&filtfilt_pinned(&sos, &xs, pad)));
        }
        old_median.sort_by(f64::total_cmp);
        // The old start-up fails this in most trials (the median is printed);
        // the new one in none.
        let old = old_median[old_median.len() / 2];
        assert!(old > 1.5, "the old start-up's median ratio {old}");
        assert!(
            new_worst < 1.2,
            "new start-up: edge slope / interior slope {new_worst}"
        );
    }

    /// A signal that starts and ends on a straight line (a ramp already
    /// under way, any slope) continues it through the extension: no
    /// transient at either end.
    #[test]
    fn ramps_at_the_ends_pass_unchanged() {
        let fs = 1000.0;
        let f = lp(4, 10.0, FilterMode::ZeroPhase);
        let sos = f.design(fs).unwrap();
        let xs: Vec<f64> = (0..3000).map(|k| 2.0 - 0.0005 * k as f64).collect();
        let y = f.filter(&sos, &xs, fs);
        for (a, b) in y.iter().zip(&xs) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // Very short signals: the fit covers what there is.
        for n in 2..6 {
            let y = f.filter(&sos, &xs[..n], fs);
            assert!(y.iter().zip(&xs).all(|(a, b)| (a - b).abs() < 1e-9), "{n}: {y:?}");
        }
    }

    #[test]
    fn edge_line_fits_exactly_and_degrades_gracefully() {
        let (l, s) = edge_line([3.0, 5.0, 7.0, 9.0].into_iter());
        assert!((l - 3.0).abs() < 1e-12 && (s - 2.0).abs() < 1e-12);
        assert_eq!(edge_line([4.0].into_iter()), (4.0, 0.0));
        assert_eq!(edge_line(std::iter::empty::<f64>()), (0.0, 0.0));
        // Values near f64::MAX: finite output (the stage falls back to the end sample).
        let f = lp(2, 10.0, FilterMode::ZeroPhase);
        let sos = f.design(1000.0).unwrap();
        let big = vec![1e307; 300];
        assert!(f.filter(&sos, &big, 1000.0).iter().all(|v| v.is_finite()));
    }

    /// The lock-step kernel against the scalar reference, bit for bit, with
    /// and without AVX2, at every taxel count (partial blocks too), order,
    /// and length (extensions longer than the signal included).
    #[test]
    fn lock_step_kernel_equals_the_scalar_reference() {
        let fs = 1000.0;
        for (case, &taxels) in [1usize, 3, 16, 17, 35].iter().enumerate() {
            for order in [1, 2, 3, 6] {
                for n in [2usize, 3, 7, 40, 150, 1200] {
                    let f = lp(order, 10.0 + case as f64, FilterMode::ZeroPhase);
                    let sos = f.design(fs).unwrap();
                    let (pad, fit) = f.edges(sos.len(), fs, n);
                    let data: Vec<Vec<f64>> = (0..taxels)
                        .map(|t| {
                            let mut xs = noisy(n, t as f64, 0.3, (case * 1000 + t * 10 + order) as u64);
                            // A ramp and a step so the ends are not only noise.
                            xs.iter_mut()
                                .enumerate()
                                .for_each(|(k, x)| *x += 0.01 * k as f64 + if k > n / 2 { 1.0 } else { 0.0 });
                            xs
                        })
                        .collect();
                    let want: Vec<Vec<f64>> = data.iter().map(|xs| filtfilt(&sos, xs, pad, fit)).collect();
                    let wide = filtfilt_taxels(&sos, &data, pad, fit);
                    let base = crate::wide::baseline_only(|| filtfilt_taxels(&sos, &data, pad, fit));
                    for (t, w) in want.iter().enumerate() {
                        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        assert_eq!(
                            bits(w),
                            bits(&wide[t]),
                            "{taxels} taxels, order {order}, n {n}, taxel {t}"
                        );
                        assert_eq!(bits(w), bits(&base[t]), "baseline: {taxels}, {order}, {n}, {t}");
                    }
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Hostile values (huge, tiny, mixed signs) and lengths: finite
        /// output, the same bits as the scalar reference.
        #[test]
        fn kernel_is_finite_and_equal_on_any_input(
            xs in proptest::collection::vec(-1e300f64..1e300, 2..80),
            taxels in 1usize..20,
            order in 1usize..5,
        ) {
            let f = lp(order, 50.0, FilterMode::ZeroPhase);
            let sos = f.design(1000.0).unwrap();
            let (pad, fit) = f.edges(sos.len(), 1000.0, xs.len());
            let data: Vec<Vec<f64>> = (0..taxels).map(|t| xs.iter().map(|x| x / (t + 1) as f64).collect()).collect();
            let got = filtfilt_taxels(&sos, &data, pad, fit);
            for (t, xs) in data.iter().enumerate() {
                let want = filtfilt(&sos, xs, pad, fit);
                proptest::prop_assert!(got[t].iter().all(|v| v.is_finite()));
                proptest::prop_assert!(want.iter().zip(&got[t]).all(|(a, b)| a.to_bits() == b.to_bits()));
            }
        }
    }

    /// The bound of the module docs: at `fc/fs` = [`MIN_CUTOFF_RATIO`] every
    /// section of every order and mode keeps its DC gain within 1e-3 (the
    /// sum `1 + a1 + a2` is exact in f64 here: Sterbenz), and far enough
    /// below it some design is unstable (`1 + a1 + a2 <= 0`, a real pole at
    /// or outside `z = 1`), so a lower bound is needed at all.
    #[test]
    fn designs_hold_at_the_bound_and_fail_below_it() {
        let fs = 1.0;
        let dc_error = |order, ratio, mode| {
            let sos = butterworth_sos(order, design_k(order, ratio, mode));
            sos.iter()
                .map(|q| (magnitude(&[*q], 0.0, fs) - 1.0).abs())
                .fold(0.0, f64::max)
        };
        let unstable = |order, ratio, mode| {
            butterworth_sos(order, design_k(order, ratio, mode))
                .iter()
                .any(|q| 1.0 + q.a[0] + q.a[1] <= 0.0)
        };
        let mut worst = 0.0_f64;
        let mut any_unstable = false;
        for order in 1..=16 {
            for mode in [FilterMode::Causal, FilterMode::ZeroPhase] {
                worst = worst.max(dc_error(order, MIN_CUTOFF_RATIO, mode));
                any_unstable |= unstable(order, 1e-10, mode);
                assert!(!unstable(order, MIN_CUTOFF_RATIO, mode));
            }
        }
        assert!(worst < 1e-3, "DC gain error {worst} at the bound");
        assert!(
            any_unstable,
            "no design unstable at 1e-10: the bound could be lower"
        );
    }

    /// The prewarped `K` the stage designs at `fc/fs = ratio`.
    fn design_k(order: usize, ratio: f64, mode: FilterMode) -> f64 {
        let k = (PI * ratio).tan();
        match mode {
            FilterMode::Causal => k,
            FilterMode::ZeroPhase => k / (2f64.sqrt() - 1.0).powf(1.0 / (2.0 * order as f64)),
        }
    }

    /// Sample rates whose normalised cutoff is below the bound (at 1e50 Hz
    /// the old design gave NaN) are named errors at run time and at check
    /// time; the bound itself and above design finite sections.
    #[test]
    fn a_cutoff_too_small_for_the_rate_is_a_named_error() {
        for order in [1, 2, 3, 16] {
            for mode in [FilterMode::Causal, FilterMode::ZeroPhase] {
                let f = lp(order, 10.0, mode);
                for fs in [1.01e8, 1e12, 1e50, 1e300, f64::MAX] {
                    let e = f.design(fs).unwrap_err().message;
                    assert!(
                        e.starts_with("lowpass: key `cutoff_hz` = 10 Hz is ") && e.contains("1e-7"),
                        "{e}"
                    );
                    assert!(e.len() < 400, "{e}");
                }
                for fs in [1e8, 1e3, 20.5] {
                    let sos = f.design(fs).unwrap();
                    assert!(sos.iter().all(|q| q.b.iter().chain(&q.a).all(|c| c.is_finite())));
                }
            }
        }
        // A ratio that underflows to 0 is refused too.
        assert!(cutoff_problem(1e-300, 1e300).is_some());
        assert!(cutoff_problem(10.0, 1e8).is_none());
        // At check time, from a rate the source states.
        let cfg = LowpassConfig::default();
        let ctx = BuildContext {
            stage_id: "filter".into(),
            seed: 0,
            out_dir: ".".into(),
            base_dir: ".".into(),
        };
        let facts = |fs: f64| OutputFacts {
            sample_rate_hz: Some(fs),
            layout: None,
        };
        let i = cfg.inspect(&ctx, &[facts(1e300)]);
        assert_eq!(i.errors.len(), 1);
        assert_eq!(i.errors[0].key.as_deref(), Some("cutoff_hz"));
        assert!(cfg.inspect(&ctx, &[facts(1000.0)]).errors.is_empty());
        // A tiny rate's Nyquist frequency prints in exponent form.
        let e = lp(2, 10.0, FilterMode::Causal)
            .design(1e-297)
            .unwrap_err()
            .message;
        assert!(e.contains("Nyquist frequency 5e-298 Hz"), "{e}");
    }

    #[test]
    fn nyquist_is_a_named_error_and_short_signals_pass() {
        assert!(lp(2, 500.0, FilterMode::Causal)
            .design(1000.0)
            .unwrap_err()
            .message
            .contains("cutoff_hz"));
        let f = lp(2, 10.0, FilterMode::ZeroPhase);
        let sos = f.design(1000.0).unwrap();
        assert_eq!(f.filter(&sos, &[3.0], 1000.0), vec![3.0]);
        assert_eq!(f.filter(&sos, &[], 1000.0), Vec::<f64>::new());
        let y = f.filter(&sos, &[1.0, 2.0, 3.0], 1000.0);
        assert!(y.iter().all(|v| v.is_finite()));
    }
}
