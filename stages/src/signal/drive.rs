//! `drive`: the input current of the spiking encoder, from a taxel's signal.
//!
//! * `fa_i` (fast-adapting, paper eq. 4): `I = G · |dV/dt|`, `dV/dt` per second
//!   by central differences (see [`super::derivative`]). Responds only while the
//!   signal changes, as FA-I afferents respond to changing indentation.
//! * `sa_i` (slowly adapting): `I = G · V`. Responds to sustained pressure.
//! * `direct`: the input signal is the current, unchanged (no gain), so the
//!   encoder can be compared with other simulators on identical input.
//!
//! The gain `G` is either fixed (`gain`) or set per trial from a target peak
//! current (`target_peak_current`): `G = target / P` where `D` is the drive
//! before gain (`|dV/dt|` or `V`) and, by default (`peak_of =
//! "median_taxel"`), `P = median_taxel max_t D(t)`: the median over taxels
//! of each taxel's peak (taxels with no drive left out). `peak_of = "max"`
//! takes `P = max_{taxel, t} D(t)`, the original rule, under which one taxel
//! whose drive is far above the others' (a dead taxel's stretched noise, a
//! clipped or glitching taxel) sets `G` and silences every real crossing
//!. With the median, fewer than half the taxels cannot move `P`;
//! an outlier taxel gets a current above the target (the encoder clamps
//! absurd currents) while the others keep theirs. A trial whose drive is 0
//! everywhere (nothing changes) gives `I = 0`, never NaN. A slope or current
//! larger than f64 holds (an absurd sample rate or gain, values near
//! `f64::MAX`) is clamped to `f64::MAX`, and is 0 under a zero gain, never
//! NaN; but when the slope that sets a per-trial gain overflows (the peak
//! `P` itself), the stage fails naming the taxel and sample, as
//! `derivative` does: `G = target / inf` would make every current 0, a
//! silent trial.
//!
//! Default, when neither key is set: `target_peak_current = 20`. Why: on the
//! ideal edge crossing (a taxel's normalized signal ramps 1 -> 0 over 1 s at
//! 2 mm/s) the FA-I current is a 20-unit plateau for that second and 0 before
//! and after. The FA-I neuron (a = 0.02, b = 0.2, c = -65, d = 2) is silent at
//! 0 and, at 20, fires tonically at about 120 Hz (Izhikevich scheme, dt =
//! 0.5 ms; tonic firing needs I > ~3.78, see the encoder's tests), i.e. about
//! 12 spikes per 100 ms image while the edge crosses the taxel and none
//! otherwise: a clear count image per frame, as in the paper's Fig. 3(c), with
//! enough counts per frame for the Pearson correlation of WSS to resolve the
//! crossing's time course. A per-trial target rather than a
//! fixed `G` keeps that true at every edge angle: the time a 2 mm taxel takes to
//! be crossed grows from 1 s at 90° to ~6.6 s at 10°, so the slope, and with a
//! fixed `G` the current, falls ~7-fold and would drop below the neuron's
//! rheobase (~3.8) at shallow angles. A fixed `gain` is the biologically
//! literal choice (faster indentation, more spikes) and is available.
//!
//! # Why the paper graphs set a fixed `gain = 30`
//!
//! The paper chose one `G` for every trial ("chosen empirically" so that the
//! spikes behave like FA-I afferents), and a live board cannot know a trial's
//! peak before it ends, so the per-trial rule cannot stream. It has a cost
//! too: on a shallow edge (10-20°) the peak slope is several times smaller,
//! so the per-trial `G` is several times larger and the sensor's noise fires
//! the neurons while the array slides, seconds before the edge (Fig. 5
//! statistic on the lab scene: spikes spread ±6.1 s around the crossing).
//! A fixed `G` has an FA-I window, measured on the lab scene with the
//! `spike_timing` sink (`palpate run graphs/paper/fig5.toml --set
//! stages.drive.gain=G`, with `--set stages.scene.file=../scenes/ideal.toml
//! --set stages.scene.angles=[10]` for the lower end):
//! * lower end, every crossing fires: the ideal scene's 10° crossing gives
//!   0 spikes at `G = 17.3` and 6,400 at `G = 22`;
//! * upper end, rest stays silent: the lab scene's spike-time skew is +0.90
//!   at `G = 30` and −1.82 at `G = 35` (noise firing before the crossing),
//!   −6.6 at `G = 40`.
//!
//! `G = 30` lies inside it and is also graphs/live.toml's `G`, so the offline
//! and live graphs run the same arithmetic.
//!
//! The window's lower end scales with 1 / speed (the slope does): at 2 mm/s
//! `G = 30` drives a 10° crossing to about 6, above the rheobase; at 1 mm/s
//! to about 3, and WSS still answers every lab trial (MAE 0.27 ± 0.13° over
//! 5 seeds); at 0.5 mm/s the shallowest edges stay silent (16 of 170 trials
//! "no edge", MAE 1.65 ± 0.43°; `palpate run graphs/paper/wss.toml --set
//! stages.scene.motion.speed_mm_s=S --set stages.wss.speed_mm_s=S`). Palpating
//! slower than about 1 mm/s needs a larger `G`, measured as above.

use super::{
    check_shape, check_signals, derivative::differentiate, derivative::DiffScheme, first_non_finite,
    non_finite_error,
};
use palpate_core::{
    check_positive, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind,
    Signals, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Default target peak current when neither `gain` nor `target_peak_current` is set.
pub const DEFAULT_TARGET_PEAK_CURRENT: f64 = 20.0;

/// Which receptor's drive to compute.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum DriveKind {
    /// Fast adapting: `I = G |dV/dt|` (paper eq. 4).
    #[default]
    FaI,
    /// Slowly adapting: `I = G V`.
    SaI,
    /// The input is the current, unchanged.
    Direct,
}

/// Input current of the encoder: FA-I G*|dV/dt| (paper eq. 4), SA-I G*V, or the signal itself.
///
/// `G` is fixed (`gain`) or set per trial so that the median taxel's peak
/// current (or, `peak_of = "max"`, the trial's largest current) equals
/// `target_peak_current` (default 20 when neither is set).
/// A trial with no change gives zero current.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DriveConfig {
    /// `fa_i` (G*|dV/dt|, dV/dt per second), `sa_i` (G*V) or `direct` (input unchanged). Default `fa_i`.
    pub kind: DriveKind,
    /// Fixed gain G, current units per (signal unit per second) for `fa_i`, per signal unit for `sa_i`. Unset by default.
    pub gain: Option<f64>,
    /// Sets G per trial so the peak chosen by `peak_of` equals this, current units.
    /// Default 20 when `gain` is unset too.
    pub target_peak_current: Option<f64>,
    /// Which peak `target_peak_current` sets: `median_taxel` (the median over
    /// taxels of each one's peak drive) or `max` (the trial's largest drive).
    /// Default `median_taxel`.
    pub peak_of: PeakOf,
}

/// Which peak `target_peak_current` sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum PeakOf {
    /// The median over taxels of each taxel's peak (taxels with no drive at
    /// all left out): one taxel, dead, clipped or glitching, cannot set the gain.
    #[default]
    MedianTaxel,
    /// The largest drive of any taxel at any time (one outlier sets the gain).
    Max,
}

/// How the gain is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Gain {
    Fixed(f64),
    TargetPeak(f64, PeakOf),
    None,
}

#[typetag::serde(name = "drive")]
impl StageConfig for DriveConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let gain = match (self.kind, self.gain, self.target_peak_current) {
            (DriveKind::Direct, Some(_), _) => {
                return Err(ConfigError::key(
                    "gain",
                    "kind `direct` passes the signal unchanged; remove `gain`",
                ))
            }
            (DriveKind::Direct, None, Some(_)) => {
                return Err(ConfigError::key(
                    "target_peak_current",
                    "kind `direct` passes the signal unchanged; remove `target_peak_current`",
                ))
            }
            (DriveKind::Direct, None, None) => Gain::None,
            (_, Some(_), Some(_)) => {
                return Err(ConfigError::key(
                    "gain",
                    "set either `gain` (fixed) or `target_peak_current` (per trial), not both",
                ))
            }
            (_, Some(g), None) => {
                if !g.is_finite() || g < 0.0 {
                    return Err(ConfigError::key(
                        "gain",
                        format!("must be a finite number >= 0, got {}", palpate_core::fmt_num(g)),
                    ));
                }
                Gain::Fixed(g)
            }
            (_, None, t) => Gain::TargetPeak(
                check_positive(
                    "target_peak_current",
                    t.unwrap_or(DEFAULT_TARGET_PEAK_CURRENT),
                    "current units",
                )?,
                self.peak_of,
            ),
        };
        Ok(Stage::Map(Box::new(Drive {
            kind: self.kind,
            gain,
        })))
    }
}
register_stage!("drive", DriveConfig);

/// The runtime `drive` stage.
pub struct Drive {
    kind: DriveKind,
    gain: Gain,
}

impl Drive {
    /// Computes the current of every taxel of one trial: the slopes
    /// (`fa_i`), then the gain in place: two simple loops, which vectorize
    /// (a single loop fusing the guarded product into the slope did not).
    /// Same operations, in the same order, as `differentiate` (central),
    /// then `|.|`, then the guarded gain.
    fn currents(&self, data: &[Vec<f64>], fs: f64) -> Vec<Vec<f64>> {
        match self.kind {
            DriveKind::Direct => data.to_vec(),
            DriveKind::SaI => self.scale(data.to_vec(), None),
            DriveKind::FaI => {
                let (raw, peaks) = data.iter().map(|xs| slope_and_peak(xs, fs)).unzip();
                self.scale(raw, Some(peaks))
            }
        }
    }

    /// [`Self::currents`] of checked signals: the shape, and every sample
    /// finite (else the error names the first taxel and sample that is
    /// not, as [`check_signals`]).
    ///
    /// Why per taxel: for `fa_i` each taxel is checked and differentiated
    /// in turn, while its samples are in L2 (172 kB for a 21 s lab trial at
    /// 1 kHz); checking the whole trial first, then differentiating it,
    /// read the trial twice from memory (2.8 MB for that trial, more than
    /// L2). A per-trial gain reads the trial once more, for the peaks, and
    /// writes it once: the fewest passes a gain set by every taxel allows.
    fn checked_currents(&self, s: &Signals) -> Result<Vec<Vec<f64>>, StageError> {
        if self.kind != DriveKind::FaI {
            check_signals("drive", s)?;
            return Ok(self.currents(&s.data, s.sample_rate_hz));
        }
        check_shape("drive", s)?;
        let fs = s.sample_rate_hz;
        // The gain is applied as each slope is written: one pass over the
        // trial instead of the slopes' and then the gain's (the trial's
        // 2.8 MB is more than L2, so the second pass went to memory). The
        // same operations on every sample: `scaled(|slope|, g)`.
        let g = match self.gain {
            Gain::Fixed(g) => g,
            Gain::None => 1.0,
            Gain::TargetPeak(target, of) => {
                // A per-trial gain: every taxel's peak slope first, read
                // only, then the scaled slopes in one pass as for a fixed
                // gain. The slopes were written, then read and written again
                // by the gain: a write stream of the whole trial (2.8 MB for
                // a lab trial, more than L2) saved. The same operations on
                // every value (tested against the two-pass `currents`).
                let mut peaks = Vec::with_capacity(s.data.len());
                for xs in &s.data {
                    let (p, all_finite) = crate::wide::with_avx2(
                        #[inline(always)]
                        || slope_peak(xs, fs),
                    );
                    // A non-finite slope comes from a non-finite sample or
                    // from an overflow of finite ones (clamped, unless it
                    // sets the gain: below).
                    if !all_finite && first_non_finite(xs).is_some() {
                        return Err(non_finite_error("drive", s));
                    }
                    peaks.push(p);
                }
                let peak = peak_of(peaks.iter().copied(), of);
                if peak == f64::INFINITY {
                    // The reference peak itself overflowed: `target / inf`
                    // would be a zero gain and a silent trial (every
                    // current 0). Named as `derivative` names it.
                    let t = peaks.iter().position(|p| *p == f64::INFINITY).unwrap_or(0);
                    let i = abs_slope(&s.data[t], fs)
                        .iter()
                        .position(|v| !v.is_finite())
                        .unwrap_or(0);
                    return Err(super::derivative::overflow_error("drive", t, i, fs));
                }
                // No change anywhere: zero current (not target/0).
                if peak > 0.0 && peak.is_finite() {
                    target / peak
                } else {
                    0.0
                }
            }
        };
        let fixed = !matches!(self.gain, Gain::TargetPeak(..));
        let mut raw = Vec::with_capacity(s.data.len());
        for xs in &s.data {
            // (A per-trial gain's pass above has checked every taxel.)
            if fixed && first_non_finite(xs).is_some() {
                return Err(non_finite_error("drive", s));
            }
            raw.push(crate::wide::with_avx2(
                #[inline(always)]
                || abs_slope_map(xs, fs, |v| scaled(v, g)),
            ));
        }
        Ok(raw)
    }

    /// Applies the gain (fixed, or set from the trial's peak) in place.
    /// `peaks`: each row's [`max_abs`] when the caller has them.
    fn scale(&self, mut raw: Vec<Vec<f64>>, peaks: Option<Vec<f64>>) -> Vec<Vec<f64>> {
        let g = match self.gain {
            Gain::Fixed(g) => g,
            Gain::TargetPeak(target, of) => {
                let peak = match peaks {
                    Some(p) => peak_of(p.into_iter(), of),
                    None => reference_peak(&raw, of),
                };
                // No change anywhere: zero current (not target/0).
                if peak > 0.0 && peak.is_finite() {
                    target / peak
                } else {
                    0.0
                }
            }
            Gain::None => 1.0,
        };
        // Row by row: a flattened iterator checks for the end of the
        // inner row at every element.
        for row in raw.iter_mut() {
            row.iter_mut().for_each(|v| *v = scaled(*v, g));
        }
        raw
    }
}

/// One taxel's [`abs_slope`] and its [`max_abs`], the peak taken while the
/// slopes are still in cache.
fn slope_and_peak(xs: &[f64], fs: f64) -> (Vec<f64>, f64) {
    let d = abs_slope(xs, fs);
    let p = max_abs(&d);
    (d, p)
}

/// `v · g`, guarded: the product of finite values may overflow for an
/// absurd fixed gain (clamped to `±f64::MAX`), and a slope that overflowed
/// (`v = inf`: a change times an absurd sample rate) times a zero gain is 0,
/// not NaN (whose sign bit made it `-f64::MAX`).
#[inline(always)]
pub(crate) fn scaled(v: f64, g: f64) -> f64 {
    let x = v * g;
    if x.is_finite() {
        x
    } else if x.is_nan() {
        0.0
    } else {
        f64::MAX.copysign(x)
    }
}

/// `|dx/dt|` of one taxel by central differences (one-sided at the ends):
/// the arithmetic of [`differentiate`] with [`DiffScheme::Central`].
#[inline]
fn abs_slope(xs: &[f64], fs: f64) -> Vec<f64> {
    abs_slope_map(xs, fs, |v| v)
}

/// `f(|dx/dt|)` of one taxel: [`abs_slope`] with `f` applied to each value
/// as it is written.
#[inline(always)]
fn abs_slope_map(xs: &[f64], fs: f64, f: impl Fn(f64) -> f64) -> Vec<f64> {
    let n = xs.len();
    if n < 3 {
        return differentiate(xs, fs, DiffScheme::Central)
            .into_iter()
            .map(|v| f(v.abs()))
            .collect();
    }
    let half = 0.5 * fs;
    let mut d = Vec::with_capacity(n);
    d.push(f(((xs[1] - xs[0]) * fs).abs()));
    // Sample i + 1 minus sample i - 1, as two shifted slices (vectorizes).
    d.extend(
        xs[2..]
            .iter()
            .zip(&xs[..n - 2])
            .map(|(a, b)| f(((a - b) * half).abs())),
    );
    d.push(f(((xs[n - 1] - xs[n - 2]) * fs).abs()));
    d
}

/// The largest [`abs_slope`] of a taxel (0 when empty) without writing the
/// slopes, and whether every slope was finite (not NaN, not inf). The
/// maximum of a set does not depend on the order it is taken in, so this is
/// the bits of [`max_abs`] of [`abs_slope`].
#[inline(always)]
fn slope_peak(xs: &[f64], fs: f64) -> (f64, bool) {
    let n = xs.len();
    if n < 3 {
        let d = abs_slope(xs, fs);
        return (max_abs(&d), d.iter().all(|v| v.abs() <= f64::MAX));
    }
    let half = 0.5 * fs;
    let (first, last) = (((xs[1] - xs[0]) * fs).abs(), ((xs[n - 1] - xs[n - 2]) * fs).abs());
    let mut m = [0.0_f64; 8];
    // `a <= MAX` fails for NaN and inf; kept per lane so the loop vectorizes.
    let mut ok = [true; 8];
    let (a, b) = (&xs[2..], &xs[..n - 2]);
    let whole = a.len() / 8 * 8;
    for (ca, cb) in a[..whole].chunks_exact(8).zip(b[..whole].chunks_exact(8)) {
        for j in 0..8 {
            let v = ((ca[j] - cb[j]) * half).abs();
            m[j] = if v > m[j] { v } else { m[j] };
            ok[j] &= v <= f64::MAX;
        }
    }
    let mut peak = m.iter().fold(first.max(last), |p, &v| p.max(v));
    let mut finite = ok.iter().all(|&o| o) && first <= f64::MAX && last <= f64::MAX;
    for (x, y) in a[whole..].iter().zip(&b[whole..]) {
        let v = ((x - y) * half).abs();
        finite &= v <= f64::MAX;
        peak = peak.max(v);
    }
    (peak, finite)
}

/// Largest `|x|` of a taxel (0 when empty). Inputs are finite or infinite
/// (an overflowing slope), never NaN: compare-and-select over eight running
/// maxima vectorizes where `f64::max`'s NaN rule would not.
fn max_abs(xs: &[f64]) -> f64 {
    let mut m = [0.0_f64; 8];
    let chunks = xs.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for j in 0..8 {
            let a = c[j].abs();
            m[j] = if a > m[j] { a } else { m[j] };
        }
    }
    m.iter().chain(rest).fold(0.0_f64, |a, &x| a.max(x.abs()))
}

/// The peak a per-trial gain maps to its target: see [`PeakOf`]. 0 when no
/// taxel has any drive.
pub fn reference_peak(raw: &[Vec<f64>], of: PeakOf) -> f64 {
    peak_of(raw.iter().map(|xs| max_abs(xs)), of)
}

/// [`reference_peak`] from each taxel's [`max_abs`].
fn peak_of(peaks: impl Iterator<Item = f64>, of: PeakOf) -> f64 {
    match of {
        PeakOf::Max => peaks.fold(0.0, f64::max),
        PeakOf::MedianTaxel => {
            let mut p: Vec<f64> = peaks.filter(|&p| p > 0.0).collect();
            if p.is_empty() {
                return 0.0;
            }
            p.sort_by(f64::total_cmp);
            let m = p.len();
            if m % 2 == 1 {
                p[m / 2]
            } else {
                p[m / 2 - 1] / 2.0 + p[m / 2] / 2.0
            }
        }
    }
}

impl Map for Drive {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        let data = self.checked_currents(s)?;
        let unit = match self.kind {
            DriveKind::Direct => s.unit.clone(),
            _ => "current".to_string(),
        };
        Ok(s.with_data(unit, data).into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::testdata::ramps;

    fn drive(kind: DriveKind, gain: Gain) -> Drive {
        Drive { kind, gain }
    }

    #[test]
    fn fa_i_is_gain_times_abs_slope() {
        let s = ramps(1000.0, 0.5, 1.0, 0.0, 2.0);
        let i = drive(DriveKind::FaI, Gain::Fixed(7.0)).currents(&s.data, 1000.0);
        // Mid-ramp the slope is -1/s, so I = 7; on the holds I = 0.
        assert!((i[0][1000] - 7.0).abs() < 1e-9);
        assert_eq!(i[0][100], 0.0);
        assert_eq!(i[0][1800], 0.0);
    }

    #[test]
    fn target_peak_sets_the_largest_current() {
        let mut s = ramps(1000.0, 0.5, 1.0, 0.0, 2.0);
        // Taxel 1 ramps twice as fast: it sets the peak.
        s.data[1] = s.data[1].iter().map(|v| (2.0 * v - 1.0).max(0.0)).collect();
        let i = drive(DriveKind::FaI, Gain::TargetPeak(20.0, PeakOf::Max)).currents(&s.data, 1000.0);
        let peak = i.iter().flatten().fold(0.0_f64, |m, &v| m.max(v));
        assert!((peak - 20.0).abs() < 1e-9);
        assert!((i[0][1000] - 10.0).abs() < 1e-6, "{}", i[0][1000]);
        let sa = drive(DriveKind::SaI, Gain::TargetPeak(4.0, PeakOf::Max)).currents(&s.data, 1000.0);
        assert!((sa[0][0] - 4.0).abs() < 1e-12);
    }

    /// Issue 15: one taxel whose drive is far above the others' (a dead
    /// taxel's stretched wobble, a clipped or glitching one) no longer sets
    /// the gain: the median taxel's peak does, so the others keep the target.
    #[test]
    fn one_outlier_taxel_does_not_set_the_gain() {
        let mut s = ramps(1000.0, 0.5, 1.0, 0.0, 2.0);
        // Taxel 3 changes 10 times faster (a 0.1 s ramp).
        s.data[3] = (0..2000)
            .map(|k| (1.0 - (k as f64 - 500.0) / 100.0).clamp(0.0, 1.0))
            .collect();
        let med =
            drive(DriveKind::FaI, Gain::TargetPeak(20.0, PeakOf::MedianTaxel)).currents(&s.data, 1000.0);
        assert!((med[0][1000] - 20.0).abs() < 1e-9, "{}", med[0][1000]);
        assert!((med[3][550] - 200.0).abs() < 1e-6, "{}", med[3][550]);
        let max = drive(DriveKind::FaI, Gain::TargetPeak(20.0, PeakOf::Max)).currents(&s.data, 1000.0);
        assert!((max[0][1000] - 2.0).abs() < 1e-9, "{}", max[0][1000]);
        // Taxels with no drive are left out of the median; none at all gives 0.
        let mut d = vec![vec![0.0; 10]; 16];
        d[2][4] = 3.0;
        assert_eq!(reference_peak(&d, PeakOf::MedianTaxel), 3.0);
        d[7][1] = -5.0;
        assert_eq!(reference_peak(&d, PeakOf::MedianTaxel), 4.0);
        assert_eq!(reference_peak(&vec![vec![0.0; 10]; 16], PeakOf::MedianTaxel), 0.0);
        assert_eq!(DriveConfig::default().peak_of, PeakOf::MedianTaxel);
    }

    #[test]
    fn no_change_gives_zero_current_not_nan() {
        let data = vec![vec![1.75; 100]; 16];
        let i = drive(DriveKind::FaI, Gain::TargetPeak(20.0, PeakOf::Max)).currents(&data, 1000.0);
        assert!(i.iter().flatten().all(|&v| v == 0.0));
        let zeros = vec![vec![0.0; 100]; 16];
        let i = drive(DriveKind::SaI, Gain::TargetPeak(20.0, PeakOf::Max)).currents(&zeros, 1000.0);
        assert!(i.iter().flatten().all(|&v| v == 0.0));
    }

    proptest::proptest! {
        /// The stage's one-pass path for a gain known in advance (fixed,
        /// absurd enough to overflow, or none), and its peaks-then-one-pass
        /// path for a per-trial gain, give the bits of slopes, then the gain
        /// in a second pass; on any values and lengths (including the one-
        /// and two-sample ends, and slopes that overflow at scale 1e300).
        #[test]
        fn a_fixed_gain_in_the_slope_pass_is_the_bits_of_two_passes(
            n in 0usize..40,
            scale in proptest::prop_oneof![proptest::strategy::Just(1.0), proptest::strategy::Just(1e300), proptest::strategy::Just(1.7e308)],
            seed in 0u64..1000,
            g in proptest::prop_oneof![
                proptest::strategy::Just(None),
                proptest::strategy::Just(Some(30.0)),
                proptest::strategy::Just(Some(1e308)),
                proptest::strategy::Just(Some(0.0)),
                // The per-trial gains (peaks first, then one scaled pass).
                proptest::strategy::Just(Some(-1.0)),
                proptest::strategy::Just(Some(-2.0)),
            ],
        ) {
            let mut s = ramps(1000.0, 0.01, 0.01, 0.0, 0.04);
            for (t, row) in s.data.iter_mut().enumerate() {
                *row = (0..n)
                    .map(|i| {
                        let h = (seed ^ (t as u64 * 7919) ^ (i as u64 * 104_729)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
                        ((h >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * scale
                    })
                    .collect();
            }
            let gain = match g {
                None => Gain::None,
                Some(-1.0) => Gain::TargetPeak(20.0, PeakOf::MedianTaxel),
                Some(-2.0) => Gain::TargetPeak(20.0, PeakOf::Max),
                Some(g) => Gain::Fixed(g),
            };
            let d = drive(DriveKind::FaI, gain);
            let one = match d.checked_currents(&s) {
                Ok(one) => one,
                Err(e) => {
                    // Only a per-trial gain whose reference peak overflowed.
                    proptest::prop_assert!(matches!(gain, Gain::TargetPeak(..)) && e.message.contains("larger than f64 holds"), "{e}");
                    return Ok(());
                }
            };
            let two = d.currents(&s.data, s.sample_rate_hz);
            let bits = |v: &[Vec<f64>]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
            proptest::prop_assert_eq!(bits(&one), bits(&two));
        }
    }

    /// At an absurd sample rate a slope overflows f64: the current is
    /// clamped (a positive gain) or 0 (a zero gain), never NaN or negative;
    /// a per-trial gain whose reference peak overflowed is an error naming
    /// the taxel and sample (it gave every current 0: a silent trial).
    #[test]
    fn overflowing_slopes_give_finite_non_negative_currents() {
        let mut s = ramps(f64::MAX, 0.0, 0.0, 0.0, 0.0);
        s.data = vec![vec![0.0, 2.0, 0.0, 0.0, 1e-300, 0.0]; 16];
        for gain in [
            Gain::TargetPeak(20.0, PeakOf::Max),
            Gain::TargetPeak(20.0, PeakOf::MedianTaxel),
        ] {
            let e = drive(DriveKind::FaI, gain).checked_currents(&s).unwrap_err();
            assert!(
                e.message.contains("taxel 0, sample 0") && e.message.contains("larger than f64 holds"),
                "{gain:?}: {e}"
            );
        }
        // One taxel's overflow does not set the median taxel's peak: the
        // others' currents stand, that taxel's is clamped.
        let mut one = ramps(1000.0, 0.0, 0.0, 0.0, 0.0);
        one.data = vec![vec![0.0, 0.5, 1.0, 0.5, 0.0]; 16];
        one.data[3] = vec![0.0, f64::MAX, -f64::MAX, 0.0, 0.0];
        let i = drive(DriveKind::FaI, Gain::TargetPeak(20.0, PeakOf::MedianTaxel))
            .checked_currents(&one)
            .unwrap();
        assert_eq!(i[0].iter().copied().fold(0.0, f64::max), 20.0);
        assert_eq!(i[3].iter().copied().fold(0.0, f64::max), f64::MAX);
        for gain in [Gain::Fixed(0.0), Gain::Fixed(30.0)] {
            let i = drive(DriveKind::FaI, gain).checked_currents(&s).unwrap();
            assert!(
                i.iter().flatten().all(|v| v.is_finite() && *v >= 0.0),
                "{gain:?}: {:?}",
                i[0]
            );
            // Where the slope is 1e-300 x MAX / 2 (finite) a fixed gain scales it.
            if let Gain::Fixed(g) = gain {
                assert_eq!(i[0][3], scaled(1e-300 * (0.5 * f64::MAX), g), "{gain:?}");
                assert_eq!(i[0][0], if g > 0.0 { f64::MAX } else { 0.0 });
            }
        }
    }

    #[test]
    fn direct_is_unchanged() {
        let data = vec![vec![1.0, -2.0, 3.5]];
        assert_eq!(drive(DriveKind::Direct, Gain::None).currents(&data, 10.0), data);
    }

    #[test]
    fn config_rejects_conflicting_keys() {
        let ctx = BuildContext {
            stage_id: "d".into(),
            seed: 0,
            out_dir: ".".into(),
            base_dir: ".".into(),
        };
        let both = DriveConfig {
            gain: Some(1.0),
            target_peak_current: Some(2.0),
            ..Default::default()
        };
        assert_eq!(both.build(&ctx).err().unwrap().key.as_deref(), Some("gain"));
        let direct = DriveConfig {
            kind: DriveKind::Direct,
            target_peak_current: Some(2.0),
            ..Default::default()
        };
        assert_eq!(
            direct.build(&ctx).err().unwrap().key.as_deref(),
            Some("target_peak_current")
        );
        let neg = DriveConfig {
            target_peak_current: Some(-1.0),
            ..Default::default()
        };
        assert!(neg.build(&ctx).is_err());
    }
}
