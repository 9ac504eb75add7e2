//! `normalize`: each taxel's signal to `[0, 1]` (paper section 2.4).
//!
//! Two modes:
//!
//! * `trial` (offline, the paper's): `V(t) = (x(t) - min x) / (max x - min x)`
//!   over the whole trial, so the taxel's lowest value maps to 0 and its highest
//!   to 1. The piezoresistive output rises as pressure falls, so an edge scene
//!   gives 0 in contact and 1 off the object.
//! * `causal` (live data): the rest level `r` is the mean of the first
//!   `baseline_ms` of the trial and `span` is the expected full-scale change in
//!   input units (a calibration value: live data cannot know its future
//!   maximum). `V(t) = clamp(|x(t) - r| / span, 0, 1)`: the deviation from rest,
//!   whichever way the sensor moves. During the baseline window itself the
//!   output is 0 (the rest level is not yet known), so the output at `t` depends
//!   only on samples up to `t`.
//!
//! A taxel whose signal never changes (its span `max - min` is at most
//! `min_span`, or below `1e-12` of its magnitude, where only rounding noise
//! could live) normalizes to 0 everywhere, never NaN, so it fires nothing
//! downstream. `min_span` doubles as a noise floor: a taxel that only sees noise
//! smaller than it stays at 0 rather than having its noise stretched to `[0, 1]`.
//!
//! Dead taxels (`trial` mode): a taxel whose span is below `dead_fraction`
//! times the **median span of the trial's taxels** normalizes to 0 too. Why: a
//! broken taxel reads a constant plus noise, hum and its neighbours' crosstalk
//! (on the lab scene 0.05-0.2 V, against ~1.5 V for a taxel the edge crosses);
//! stretched to `[0, 1]`, that wobble has the steepest slopes of the trial, so
//! it fires like a crossing and takes over the drive's per-trial auto-gain,
//! silencing the real crossings ( one dead taxel made 33 of 170 lab
//! trials answer "no edge"). The median is a robust statistic across taxels:
//! fewer than half the taxels being dead cannot move it, and no fixed volt
//! threshold has to match the sensor. Taxels with no real change at all
//! (flat, by the rule above) are left out of the median.

use super::{check_shape, check_signals, non_finite_error};
use palpate_core::{
    check_positive, check_range, fmt_num, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec,
    Item, Map, Payload, PayloadKind, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// How the range of each taxel is found.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum NormalizeMode {
    /// Over the whole trial: min maps to 0, max to 1 (offline, the paper's).
    #[default]
    Trial,
    /// From a baseline window at the start and a known span (live data).
    Causal,
}

/// Normalizes each taxel's signal to [0, 1], over the trial or causally from a baseline.
///
/// `trial`: `V = (x - min) / (max - min)` per taxel over the whole trial.
/// `causal`: `V = clamp(|x - r| / span, 0, 1)` with `r` the mean of the first
/// `baseline_ms` (output 0 during that window). A taxel whose signal never
/// changes normalizes to 0, never NaN.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct NormalizeConfig {
    /// `trial` (whole-trial min..max, offline) or `causal` (baseline + span, live). Default `trial`.
    pub mode: NormalizeMode,
    /// Causal mode: length of the baseline window at the start of the trial, ms. Default 500.
    pub baseline_ms: f64,
    /// Causal mode: expected full-scale change of the signal from rest, in input
    /// units (e.g. V); required in causal mode.
    pub span: Option<f64>,
    /// Noise floor, input units: a taxel whose change never exceeds it normalizes to 0. Default 0.
    pub min_span: f64,
    /// Trial mode: a taxel whose span (max - min) is below this fraction of
    /// the median span of the trial's taxels is dead and normalizes to 0
    /// (dimensionless, in [0, 1]; 0 turns the rule off). Default 0.25.
    pub dead_fraction: f64,
}

/// Default [`NormalizeConfig::dead_fraction`].
pub const DEFAULT_DEAD_FRACTION: f64 = 0.25;

impl Default for NormalizeConfig {
    fn default() -> Self {
        NormalizeConfig {
            mode: NormalizeMode::Trial,
            baseline_ms: 500.0,
            span: None,
            min_span: 0.0,
            dead_fraction: DEFAULT_DEAD_FRACTION,
        }
    }
}

#[typetag::serde(name = "normalize")]
impl StageConfig for NormalizeConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(check_range(
            "min_span",
            self.min_span,
            0.0,
            f64::MAX,
            "input units",
        ));
        c.take(check_range("dead_fraction", self.dead_fraction, 0.0, 1.0, ""));
        let span = match self.mode {
            NormalizeMode::Trial => 0.0,
            NormalizeMode::Causal => {
                c.take(check_positive("baseline_ms", self.baseline_ms, "ms"));
                match self.span {
                    Some(s) => c.take(check_positive("span", s, "input units")).unwrap_or(0.0),
                    None => {
                        c.push(ConfigError::key(
                            "span",
                            "causal mode needs the expected full-scale change of the signal \
                             (input units, from calibration); live data cannot know its maximum",
                        ));
                        0.0
                    }
                }
            }
        };
        c.finish()?;
        Ok(Stage::Map(Box::new(Normalizer {
            mode: self.mode,
            baseline_ms: self.baseline_ms,
            span,
            min_span: self.min_span,
            dead_fraction: self.dead_fraction,
        })))
    }
}
register_stage!("normalize", NormalizeConfig);

/// The runtime `normalize` stage.
pub struct Normalizer {
    mode: NormalizeMode,
    baseline_ms: f64,
    span: f64,
    min_span: f64,
    dead_fraction: f64,
}

/// True when a range `[lo, hi]` holds no real change: at most `min_span`, or
/// within rounding of the values' magnitude.
fn is_flat(lo: f64, hi: f64, min_span: f64) -> bool {
    let d = hi - lo;
    !(d > min_span && d > 1e-12 * lo.abs().max(hi.abs()))
}

/// `(min, max)` of a taxel (`(inf, -inf)` when empty). Inputs are finite
/// (the stage checks), so the min and max are exact in any order: eight
/// running minima and maxima by compare-and-select vectorize where
/// `f64::min`'s NaN rule would not.
pub fn range(xs: &[f64]) -> (f64, f64) {
    let (lo, hi, _) = range_finite(xs);
    (lo, hi)
}

/// [`range`], also telling whether every sample is finite (the same pass;
/// with a NaN or an infinity the range is not meaningful).
pub fn range_finite(xs: &[f64]) -> (f64, f64, bool) {
    let mut lo = [f64::INFINITY; 8];
    let mut hi = [f64::NEG_INFINITY; 8];
    let mut ok = true;
    let chunks = xs.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for j in 0..8 {
            ok &= super::finite(c[j]);
            lo[j] = if c[j] < lo[j] { c[j] } else { lo[j] };
            hi[j] = if c[j] > hi[j] { c[j] } else { hi[j] };
        }
    }
    let (mut l, mut h) = (f64::INFINITY, f64::NEG_INFINITY);
    for j in 0..8 {
        l = l.min(lo[j]);
        h = h.max(hi[j]);
    }
    for &x in rest {
        ok &= super::finite(x);
        l = l.min(x);
        h = h.max(x);
    }
    (l, h, ok)
}

/// Normalizes one taxel over the whole trial: min -> 0, max -> 1; flat -> 0.
pub fn normalize_trial(xs: &[f64], min_span: f64) -> Vec<f64> {
    let (lo, hi) = range(xs);
    if xs.is_empty() || is_flat(lo, hi, min_span) {
        return vec![0.0; xs.len()];
    }
    map_range(xs, lo, hi)
}

/// `(x - lo) / (hi - lo)` clamped to [0, 1], for a range that is not flat.
fn map_range(xs: &[f64], lo: f64, hi: f64) -> Vec<f64> {
    if !(hi - lo).is_finite() {
        // A span wider than f64::MAX: halve everything first (else inf * 0 = NaN).
        let (lo2, inv) = (lo / 2.0, 1.0 / (hi / 2.0 - lo / 2.0));
        return xs
            .iter()
            .map(|&x| ((x / 2.0 - lo2) * inv).clamp(0.0, 1.0))
            .collect();
    }
    let inv = 1.0 / (hi - lo);
    if !inv.is_finite() {
        // A span below 1 / f64::MAX (subnormal values): its reciprocal is
        // inf and the minimum's `0 * inf` NaN, so divide instead (exact
        // enough there, and only there: the usual path keeps its bits).
        let d = hi - lo;
        return xs.iter().map(|&x| ((x - lo) / d).clamp(0.0, 1.0)).collect();
    }
    xs.iter().map(|&x| ((x - lo) * inv).clamp(0.0, 1.0)).collect()
}

/// Which taxels of a trial are live, given each one's `(min, max)`: not flat
/// (span above `min_span` and rounding) and, when `dead_fraction > 0`, a span
/// of at least `dead_fraction` times the median span of the non-flat taxels.
pub fn live_taxels(ranges: &[(f64, f64)], min_span: f64, dead_fraction: f64) -> Vec<bool> {
    let mut live: Vec<bool> = ranges
        .iter()
        .map(|&(lo, hi)| !is_flat(lo, hi, min_span))
        .collect();
    let mut spans: Vec<f64> = ranges
        .iter()
        .zip(&live)
        .filter(|(_, &l)| l)
        .map(|(&(lo, hi), _)| hi - lo)
        .collect();
    if dead_fraction > 0.0 && !spans.is_empty() {
        spans.sort_by(f64::total_cmp);
        let m = spans.len();
        // The median; an even count takes the mean of the middle two (halved
        // first: the sum of two spans near f64::MAX would overflow).
        let median = if m % 2 == 1 {
            spans[m / 2]
        } else {
            spans[m / 2 - 1] / 2.0 + spans[m / 2] / 2.0
        };
        for (l, &(lo, hi)) in live.iter_mut().zip(ranges) {
            *l = *l && hi - lo >= dead_fraction * median;
        }
    }
    live
}

/// Normalizes every taxel of a trial (`trial` mode): live taxels (see
/// [`live_taxels`]) map min -> 0 and max -> 1, the others to 0.
pub fn normalize_trial_taxels(data: &[Vec<f64>], min_span: f64, dead_fraction: f64) -> Vec<Vec<f64>> {
    let ranges: Vec<(f64, f64)> = data.iter().map(|xs| range(xs)).collect();
    map_taxels(data, &ranges, min_span, dead_fraction)
}

/// [`normalize_trial_taxels`], or `None` when a sample is not finite (found
/// by the pass that takes the ranges, so the stage reads its input once
/// before writing).
pub fn normalize_trial_taxels_finite(
    data: &[Vec<f64>],
    min_span: f64,
    dead_fraction: f64,
) -> Option<Vec<Vec<f64>>> {
    // Each taxel is mapped right after its range is taken, while its
    // samples are still in L2 (172 kB for a 21 s lab trial; the whole
    // trial, 2.8 MB, is not), so the trial is read from memory once, not
    // twice. Whether a taxel is dead by `dead_fraction` needs every span
    // first: the few it finds are zeroed afterwards, which gives the
    // values `map_taxels` gives (a flat taxel is never mapped).
    let mut ranges = Vec::with_capacity(data.len());
    let mut out = Vec::with_capacity(data.len());
    for xs in data {
        let (lo, hi, finite) = range_finite(xs);
        if !finite {
            return None;
        }
        ranges.push((lo, hi));
        out.push(if is_flat(lo, hi, min_span) {
            vec![0.0; xs.len()]
        } else {
            map_range(xs, lo, hi)
        });
    }
    for (row, live) in out.iter_mut().zip(live_taxels(&ranges, min_span, dead_fraction)) {
        if !live {
            row.iter_mut().for_each(|x| *x = 0.0);
        }
    }
    Some(out)
}

/// Maps every taxel by its range (live taxels) or to 0.
fn map_taxels(data: &[Vec<f64>], ranges: &[(f64, f64)], min_span: f64, dead_fraction: f64) -> Vec<Vec<f64>> {
    let live = live_taxels(ranges, min_span, dead_fraction);
    data.iter()
        .zip(ranges.iter().zip(&live))
        .map(|(xs, (&(lo, hi), &l))| {
            if l {
                map_range(xs, lo, hi)
            } else {
                vec![0.0; xs.len()]
            }
        })
        .collect()
}

/// Normalizes one taxel causally: deviation from the mean of the first
/// `n_baseline` samples, over `span`, clamped to [0, 1]; 0 during the baseline.
pub fn normalize_causal(xs: &[f64], n_baseline: usize, span: f64, min_span: f64) -> Vec<f64> {
    let nb = n_baseline.clamp(1, xs.len().max(1)).min(xs.len());
    if nb == 0 {
        return Vec::new();
    }
    let rest = xs[..nb].iter().sum::<f64>() / nb as f64;
    let mut out = vec![0.0; xs.len()];
    for (o, &x) in out.iter_mut().zip(xs).skip(nb) {
        let dev = (x - rest).abs();
        if dev > min_span {
            *o = (dev / span).clamp(0.0, 1.0);
        }
    }
    out
}

impl Map for Normalizer {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_shape("normalize", s)?;
        let data = match self.mode {
            // Finiteness is noted by the pass that takes the ranges.
            NormalizeMode::Trial => normalize_trial_taxels_finite(&s.data, self.min_span, self.dead_fraction)
                .ok_or_else(|| non_finite_error("normalize", s))?,
            NormalizeMode::Causal => {
                check_signals("normalize", s)?;
                let nb = (self.baseline_ms * s.sample_rate_hz / 1000.0).round() as usize;
                if nb >= s.n_samples() && s.n_samples() > 0 {
                    return Err(StageError::new(format!(
                        "normalize: key `baseline_ms` = {} ms covers the whole trial ({} ms at {} Hz)",
                        fmt_num(self.baseline_ms),
                        super::fmt_ms(s.duration_ms()),
                        fmt_num(s.sample_rate_hz)
                    )));
                }
                s.data
                    .iter()
                    .map(|xs| normalize_causal(xs, nb, self.span, self.min_span))
                    .collect()
            }
        };
        Ok(s.with_data("normalized", data).into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn trial_mode_maps_min_to_0_and_max_to_1() {
        let v = normalize_trial(&[1.75, 2.0, 2.5, 1.75], 0.0);
        assert_eq!(v, vec![0.0, 1.0 / 3.0, 1.0, 0.0]);
    }

    #[test]
    fn flat_taxel_is_zero_not_nan() {
        assert_eq!(normalize_trial(&[1.75; 10], 0.0), vec![0.0; 10]);
        // Rounding-level wobble on a large value is still flat.
        let wobble: Vec<f64> = (0..10).map(|i| 1.75 + (i % 2) as f64 * 1e-15).collect();
        assert_eq!(normalize_trial(&wobble, 0.0), vec![0.0; 10]);
        // Noise below the floor stays 0; above it, it is stretched.
        let noisy: Vec<f64> = (0..10).map(|i| 1.0 + (i % 2) as f64 * 1e-3).collect();
        assert_eq!(normalize_trial(&noisy, 1e-2), vec![0.0; 10]);
        assert_eq!(normalize_trial(&noisy, 0.0)[1], 1.0);
        assert!(normalize_trial(&[], 0.0).is_empty());
    }

    /// A taxel whose values are subnormal (a span below 1 / f64::MAX, whose
    /// reciprocal is inf) maps to [0, 1], not NaN: `0 * inf` gave NaN at
    /// the minimum (the hammer of the Python building blocks found it).
    #[test]
    fn a_subnormal_span_maps_to_0_1_not_nan() {
        let tiny = f64::from_bits(1); // 5e-324
        let xs = [0.0, tiny, 0.0, 3.0 * tiny, 2.0 * tiny];
        let v = normalize_trial(&xs, 0.0);
        assert_eq!(v, vec![0.0, 1.0 / 3.0, 0.0, 1.0, 2.0 / 3.0]);
        let v = normalize_trial(&[-1e-310, 1e-310], 0.0);
        assert_eq!(v, vec![0.0, 1.0]);
        let out =
            normalize_trial_taxels_finite(&[xs.to_vec(), vec![1.0, 2.0, 1.5, 1.0, 2.0]], 0.0, 0.0).unwrap();
        assert!(out.iter().flatten().all(|x| x.is_finite()));
    }

    #[test]
    fn causal_mode_uses_only_the_past() {
        let xs: Vec<f64> = (0..100)
            .map(|i| if i < 50 { 2.0 } else { 2.0 - (i - 50) as f64 * 0.01 })
            .collect();
        let v = normalize_causal(&xs, 20, 0.25, 0.0);
        assert!(v[..50].iter().all(|&x| x == 0.0));
        assert!((v[75] - 0.25 / 0.25).abs() < 1e-12);
        assert_eq!(v[99], 1.0); // clamped
                                // Causality: changing the future never changes the past.
        let mut ys = xs.clone();
        ys[80] = 100.0;
        let w = normalize_causal(&ys, 20, 0.25, 0.0);
        assert_eq!(v[..80], w[..80]);
    }

    /// Issue 15's failing case in miniature: 15 taxels swing 1.5 V, a dead
    /// one 0.15 V of crosstalk and noise near the 3.3 V rail. The dead taxel
    /// normalizes to 0 (with the rule off it is stretched to [0, 1], whose
    /// steep wobble took over the drive's gain).
    #[test]
    fn a_dead_taxel_normalizes_to_zero() {
        let mut data: Vec<Vec<f64>> = (0..16)
            .map(|t| {
                (0..100)
                    .map(|k| 1.75 + 1.5 * (k as f64 / 99.0) + 0.01 * t as f64)
                    .collect()
            })
            .collect();
        data[5] = (0..100)
            .map(|k| 3.3 - 0.15 * (k as f64 * 0.3).sin().abs())
            .collect();
        let v = normalize_trial_taxels(&data, 0.0, DEFAULT_DEAD_FRACTION);
        assert!(v[5].iter().all(|&x| x == 0.0));
        for t in (0..16).filter(|&t| t != 5) {
            assert_eq!((v[t][0], v[t][99]), (0.0, 1.0), "taxel {t}");
            assert_eq!(v[t], normalize_trial(&data[t], 0.0));
        }
        let old = normalize_trial_taxels(&data, 0.0, 0.0);
        assert_eq!(old[5].iter().fold(0.0_f64, |m, &x| m.max(x)), 1.0);
    }

    #[test]
    fn live_taxels_use_the_median_span_of_the_non_flat_ones() {
        assert!(live_taxels(&[], 0.0, 0.25).is_empty());
        assert_eq!(live_taxels(&[(1.0, 1.0); 4], 0.0, 0.25), vec![false; 4]);
        // Spans 1, 2, 0.1, 0.5: median 0.75, so 0.1 < 0.1875 is dead.
        let r = [(0.0, 1.0), (0.0, 2.0), (0.0, 0.1), (0.0, 0.5)];
        assert_eq!(live_taxels(&r, 0.0, 0.25), vec![true, true, false, true]);
        assert_eq!(live_taxels(&r, 0.0, 0.0), vec![true; 4]);
        // Flat taxels do not pull the median down: spans 1, 1, 0.3 and two flat.
        let r = [(0.0, 1.0), (0.0, 1.0), (0.0, 0.3), (2.0, 2.0), (2.0, 2.0)];
        assert_eq!(live_taxels(&r, 0.0, 0.25), vec![true, true, true, false, false]);
        // Spans that overflow stay live and produce no NaN.
        let r = [(-1e308, 1e308), (0.0, 1.0), (0.0, f64::MAX)];
        assert_eq!(live_taxels(&r, 0.0, 0.25), vec![true, false, true]);
        let v = normalize_trial_taxels(&[vec![-1e308, 1e308], vec![0.0, 1.0]], 0.0, 0.25);
        assert!(v.iter().flatten().all(|x| (0.0..=1.0).contains(x)));
    }

    /// Absurd sample rates: the causal baseline covers every sample (a
    /// named error in short numbers) or a single one (finite output).
    #[test]
    fn causal_mode_at_absurd_rates_refuses_or_stays_finite() {
        let meta = palpate_core::TrialMeta::default();
        let ctx = TrialContext {
            stage_id: "n",
            meta: &meta,
            seed: 0,
        };
        let n = Normalizer {
            mode: NormalizeMode::Causal,
            baseline_ms: 500.0,
            span: 1.0,
            min_span: 0.0,
            dead_fraction: 0.0,
        };
        let mut s = crate::signal::testdata::ramps(1000.0, 0.01, 0.01, 0.0, 0.05);
        let run = |s: &palpate_core::Signals| {
            let item = Item {
                meta: std::sync::Arc::new(meta.clone()),
                payload: s.clone().into(),
            };
            n.process(&[&item], &ctx)
        };
        s.sample_rate_hz = 1e300;
        let e = run(&s).err().unwrap().message;
        assert!(
            e.starts_with("normalize: key `baseline_ms`") && e.contains("at 1e300 Hz") && e.len() < 120,
            "{e}"
        );
        s.sample_rate_hz = 1e-297;
        let out = run(&s).unwrap();
        assert!(out
            .signals()
            .unwrap()
            .data
            .iter()
            .flatten()
            .all(|v| v.is_finite()));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The stage's path (each taxel mapped while in cache, dead ones
        /// zeroed after) gives the bits of ranges first, then the map: with
        /// flat, dead-by-fraction, huge-span and empty taxels.
        #[test]
        fn mapping_each_taxel_at_once_is_the_bits_of_two_passes(
            spans in proptest::collection::vec(
                proptest::prop_oneof![
                    proptest::strategy::Just(0.0),
                    proptest::strategy::Just(0.01),
                    proptest::strategy::Just(1.0),
                    proptest::strategy::Just(1e308),
                    0.0f64..3.0,
                ],
                1..20,
            ),
            n in 0usize..30,
            min_span in proptest::prop_oneof![proptest::strategy::Just(0.0), proptest::strategy::Just(0.1)],
            dead_fraction in proptest::prop_oneof![proptest::strategy::Just(0.0), proptest::strategy::Just(0.25), 0.0f64..1.0],
        ) {
            let data: Vec<Vec<f64>> = spans
                .iter()
                .enumerate()
                .map(|(t, &sp)| (0..n).map(|i| 0.5 + sp * (((i * 7 + t * 3) % 11) as f64 / 10.0 - 0.5)).collect())
                .collect();
            let one = normalize_trial_taxels_finite(&data, min_span, dead_fraction).unwrap();
            let two = normalize_trial_taxels(&data, min_span, dead_fraction);
            let bits = |v: &[Vec<f64>]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
            prop_assert_eq!(bits(&one), bits(&two));
            prop_assert_eq!(one.len(), two.len());
        }

        #[test]
        fn always_in_unit_interval(xs in proptest::collection::vec(-1e12f64..1e12, 0..64), floor in 0.0f64..1.0) {
            for v in normalize_trial(&xs, floor).into_iter().chain(normalize_causal(&xs, 5, 3.0, floor)) {
                prop_assert!((0.0..=1.0).contains(&v));
            }
        }
    }
}
