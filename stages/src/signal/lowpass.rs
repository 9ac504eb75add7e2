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
//!   `fc`: `(1 + (K/K')^2N)^-2 = 1/2`). The ends are extended by odd
//!   reflection about the end samples (`max(3(2·sections + 1), fs/fc)`
//!   samples, at most `n - 1`) and each pass starts in its steady state for
//!   the first sample, so a signal that starts or ends flat has no transient.
//! * `causal` (live): a single forward pass designed at `fc` exactly, starting
//!   in the steady state of the first sample (as if the signal had been at that
//!   value before the recording began).
//!
//! `cutoff_hz` must lie below the Nyquist frequency `fs/2`; that is checked
//! when the sample rate is known (at run time), naming the key.

use super::check_signals;
use palpate_core::{
    check_positive, check_range, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload,
    PayloadKind, Stage, StageConfig, StageError, TrialContext,
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
    /// -3 dB cutoff frequency, Hz; must be below half the sample rate. Default 20.
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
        check_range("order", self.order as f64, 1.0, 16.0, "")?;
        check_positive("cutoff_hz", self.cutoff_hz, "Hz")?;
        Ok(Stage::Map(Box::new(Lowpass {
            order: self.order,
            cutoff_hz: self.cutoff_hz,
            mode: self.mode,
        })))
    }
}
register_stage!("lowpass", LowpassConfig);

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
    /// The sections of one pass for sample rate `fs`.
    pub fn design(&self, fs: f64) -> Result<Vec<Biquad>, StageError> {
        if self.cutoff_hz >= fs / 2.0 {
            return Err(StageError::new(format!(
                "lowpass: key `cutoff_hz` = {} Hz must lie below the Nyquist frequency {} Hz of these signals",
                self.cutoff_hz,
                fs / 2.0
            )));
        }
        let k = (PI * self.cutoff_hz / fs).tan();
        let k = match self.mode {
            FilterMode::Causal => k,
            // Each of the two passes at -1.5 dB so the product is -3 dB at fc.
            FilterMode::ZeroPhase => k / (2f64.sqrt() - 1.0).powf(1.0 / (2.0 * self.order as f64)),
        };
        Ok(butterworth_sos(self.order, k))
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
                if n < 2 {
                    return xs.to_vec();
                }
                let want = (3 * (2 * sos.len() + 1)).max((fs / self.cutoff_hz).ceil() as usize);
                let pad = want.min(n - 1);
                // Odd extension: 2 x[0] - x[pad..1], x, 2 x[n-1] - x[n-2..n-1-pad].
                let mut ext = Vec::with_capacity(n + 2 * pad);
                ext.extend((1..=pad).rev().map(|i| 2.0 * xs[0] - xs[i]));
                ext.extend_from_slice(xs);
                ext.extend((1..=pad).map(|i| 2.0 * xs[n - 1] - xs[n - 1 - i]));
                sosfilt(sos, &mut ext);
                ext.reverse();
                sosfilt(sos, &mut ext);
                ext.reverse();
                ext[pad..pad + n].to_vec()
            }
        }
    }
}

impl Map for Lowpass {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_signals("lowpass", s)?;
        let sos = self.design(s.sample_rate_hz)?;
        let data = s
            .data
            .iter()
            .map(|xs| self.filter(&sos, xs, s.sample_rate_hz))
            .collect();
        Ok(s.with_data(s.unit.clone(), data).into())
    }
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
