//! The signal-levels sink: what a taxel reads on the object, what it reads off
//! it, and how long the change takes (Kumar et al. 2020, Fig. 3a: "around
//! 1.75 V" in full contact, rising as the array leaves the object, saturated
//! once it is off).
//!
//! # Statistics, per trial and taxel
//!
//! With `x` the taxel's samples and `R` samples in `rest_ms`:
//!
//! * start level `a`: the median of the first `R` samples (the array held on
//!   the object before it slides);
//! * end level `b`: the median of the last `R` samples (held past the edge);
//! * change `b - a`; a taxel whose `|b - a|` is below `min_change` (dead,
//!   or never crossed) is counted as flat and left out of the transition;
//! * transition (10-90 %): `t₉₀ - t₁₀`, where `t_f` is the first sample at
//!   which `x` has moved by at least `f (b - a)` from `a` in the direction of
//!   the change, `t₉₀` searched from `t₁₀` on; `t₁₀` itself is also reported
//!   relative to the trial's start;
//! * saturation: the share of the last `R` samples equal to the trial's
//!   largest sample of that taxel (an ADC ceiling reads as a run of equal
//!   maxima; a noisy, unclipped level almost never repeats its maximum).
//!
//! Pooled over (trial, taxel) pairs (the run's metrics, `<id>.<name>`):
//! `start` and `end` (means; in the signal's unit, volts after a `piezo`
//! effect), `start_sd` and `end_sd` (SDs), `transition_ms` and
//! `transition_sd_ms`, `saturated` (mean share), `flat` (count of flat
//! pairs) and `pairs`. Files, written atomically: `<id>.json` (pooled and
//! per-taxel means) and `<id>.md`.
//!
//! Every statistic is taken on whatever signals reach the sink (raw or
//! filtered); the paper's Fig. 3a shows the low-pass-filtered signal.

use palpate_core::output::write_atomic;
use palpate_core::{
    check_positive, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec, PayloadKind, Sink,
    SinkContext, SinkInput, SinkReport, Stage, StageConfig, StageError,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// Levels on and off the object and the transition between them (Fig. 3a).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SignalLevelsConfig {
    /// Length of the stretch at each end of a trial whose median is the
    /// level, ms. Default 1000 (the lab scene holds 2 s at each end).
    pub rest_ms: f64,
    /// Smallest change between the two levels for a taxel to count as
    /// crossed, in the signal's unit (V after `piezo`). Default 0.05.
    pub min_change: f64,
}

impl Default for SignalLevelsConfig {
    fn default() -> Self {
        SignalLevelsConfig {
            rest_ms: 1000.0,
            min_change: 0.05,
        }
    }
}

#[typetag::serde(name = "signal_levels")]
impl StageConfig for SignalLevelsConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(check_positive("rest_ms", self.rest_ms, "ms"));
        c.take(check_positive("min_change", self.min_change, "signal units"));
        c.finish()?;
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("signal_levels", SignalLevelsConfig);

/// One (trial, taxel) pair's statistics.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PairLevels {
    /// Start level (median of the first `rest_ms`).
    pub start: f64,
    /// End level (median of the last `rest_ms`).
    pub end: f64,
    /// 10-90 % transition, ms; `None` for a flat pair.
    pub transition_ms: Option<f64>,
    /// When the change reaches 10 %, ms from the trial's start; `None` if flat.
    pub t10_ms: Option<f64>,
    /// Share of the end stretch at the taxel's largest sample.
    pub saturated: f64,
}

fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        s[n / 2]
    } else {
        (s[n / 2 - 1] + s[n / 2]) / 2.0
    }
}

/// The statistics of one taxel's samples (see the module docs); `None` when
/// the trial is shorter than twice `rest` samples or holds a non-finite
/// sample (the signal stages refuse those before a sink sees them).
pub fn pair_levels(x: &[f64], rate_hz: f64, rest_ms: f64, min_change: f64) -> Option<PairLevels> {
    let r = ((rest_ms * rate_hz / 1e3).round() as usize).max(1);
    if x.len() < 2 * r || x.iter().any(|v| !v.is_finite()) || !rate_hz.is_finite() || rate_hz <= 0.0 {
        return None;
    }
    let start = median(&x[..r]);
    let end = median(&x[x.len() - r..]);
    let max = x.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let saturated = x[x.len() - r..].iter().filter(|&&v| v == max).count() as f64 / r as f64;
    let change = end - start;
    let (mut transition_ms, mut t10_ms) = (None, None);
    if change.abs() >= min_change {
        let moved = |v: f64| (v - start) * change.signum();
        let reach = |from: usize, f: f64| (from..x.len()).find(|&k| moved(x[k]) >= f * change.abs());
        if let Some(k10) = reach(0, 0.1) {
            if let Some(k90) = reach(k10, 0.9) {
                transition_ms = Some((k90 - k10) as f64 * 1e3 / rate_hz);
                t10_ms = Some(k10 as f64 * 1e3 / rate_hz);
            }
        }
    }
    Some(PairLevels {
        start,
        end,
        transition_ms,
        t10_ms,
        saturated,
    })
}

/// Population mean and SD; NaN when nothing was measured (core's `mean_sd`
/// gives 0 there, which would read as a measured level).
fn mean_sd(v: &[f64]) -> (f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    palpate_core::sweep::mean_sd(v)
}

impl Sink for SignalLevelsConfig {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        let Some(input) = inputs.first() else {
            return Ok(report);
        };
        let mut pairs: Vec<(usize, PairLevels)> = Vec::new();
        let mut short = 0usize;
        for item in input.items {
            let s = item.payload.signals()?;
            for (taxel, x) in s.data.iter().enumerate() {
                match pair_levels(x, s.sample_rate_hz, self.rest_ms, self.min_change) {
                    Some(p) => pairs.push((taxel, p)),
                    None => short += 1,
                }
            }
        }
        let col = |f: &dyn Fn(&PairLevels) -> Option<f64>| -> Vec<f64> {
            pairs.iter().filter_map(|(_, p)| f(p)).collect()
        };
        let (start, start_sd) = mean_sd(&col(&|p| Some(p.start)));
        let (end, end_sd) = mean_sd(&col(&|p| Some(p.end)));
        let (tr, tr_sd) = mean_sd(&col(&|p| p.transition_ms));
        let (sat, _) = mean_sd(&col(&|p| Some(p.saturated)));
        let flat = pairs.iter().filter(|(_, p)| p.transition_ms.is_none()).count();
        let pooled = [
            ("start", start),
            ("start_sd", start_sd),
            ("end", end),
            ("end_sd", end_sd),
            ("transition_ms", tr),
            ("transition_sd_ms", tr_sd),
            ("saturated", sat),
            ("flat", flat as f64),
            ("pairs", pairs.len() as f64),
        ];
        let taxels = pairs.iter().map(|(t, _)| t + 1).max().unwrap_or(0);
        let per_taxel: Vec<serde_json::Value> = (0..taxels)
            .map(|t| {
                let own: Vec<&PairLevels> = pairs.iter().filter(|(k, _)| *k == t).map(|(_, p)| p).collect();
                let m = |f: &dyn Fn(&PairLevels) -> Option<f64>| {
                    let v: Vec<f64> = own.iter().filter_map(|p| f(p)).collect();
                    if v.is_empty() {
                        serde_json::Value::Null
                    } else {
                        serde_json::json!(mean_sd(&v).0)
                    }
                };
                serde_json::json!({
                    "taxel": t,
                    "start": m(&|p| Some(p.start)),
                    "end": m(&|p| Some(p.end)),
                    "transition_ms": m(&|p| p.transition_ms),
                    "saturated": m(&|p| Some(p.saturated)),
                })
            })
            .collect();
        let mut md = String::new();
        let _ = writeln!(
            md,
            "signal levels of `{}`: {} (trial, taxel) pairs, {flat} flat (change < {}), {short} too short",
            input.stage_id,
            pairs.len(),
            self.min_change
        );
        let _ = writeln!(md, "\n| statistic | mean | SD |\n| --- | --- | --- |");
        let _ = writeln!(md, "| start level (on the object) | {start:.3} | {start_sd:.3} |");
        let _ = writeln!(md, "| end level (off the object) | {end:.3} | {end_sd:.3} |");
        let _ = writeln!(md, "| transition 10-90 %, ms | {tr:.0} | {tr_sd:.0} |");
        let _ = writeln!(
            md,
            "| end stretch at the taxel's maximum (saturation) | {sat:.2} | |"
        );
        report.text = md.clone();
        for (name, v) in pooled {
            if v.is_finite() {
                report.metrics.push((format!("{}.{name}", ctx.stage_id), v));
            }
        }
        let json = serde_json::to_vec_pretty(&serde_json::json!({
            "source": input.stage_id,
            "rest_ms": self.rest_ms,
            "min_change": self.min_change,
            "too_short": short,
            "pooled": pooled.iter().map(|(k, v)| (k.to_string(), if v.is_finite() { serde_json::json!(v) } else { serde_json::Value::Null })).collect::<serde_json::Map<_, _>>(),
            "taxels": per_taxel,
        }))
        .map_err(|e| StageError::new(e.to_string()))?;
        let base = ctx.out_dir.join(ctx.stage_id);
        for (ext, bytes) in [("json", json), ("md", md.into_bytes())] {
            let p = base.with_extension(ext);
            write_atomic(&p, &bytes).map_err(|e| StageError::new(format!("writing {}: {e}", p.display())))?;
            report.files.push(p);
        }
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_ramp_between_two_levels_gives_its_levels_and_its_10_90_time() {
        // 1 kHz: 1.75 for 2 s, a linear rise to 3.3 over 1 s, 3.3 for 2 s.
        let mut x = vec![1.75; 2000];
        x.extend((0..1000).map(|k| 1.75 + 1.55 * k as f64 / 1000.0));
        x.extend(vec![3.3; 2000]);
        let p = pair_levels(&x, 1000.0, 1000.0, 0.05).unwrap();
        assert_eq!((p.start, p.end), (1.75, 3.3));
        // 10 % at sample 2100, 90 % at 2900 (to rounding of the ramp's steps).
        let tr = p.transition_ms.unwrap();
        assert!((tr - 800.0).abs() <= 1.0, "{tr}");
        assert!((p.t10_ms.unwrap() - 2100.0).abs() <= 1.0);
        // The end stretch sits at the maximum: saturated.
        assert_eq!(p.saturated, 1.0);
        // A falling signal (pressure rising) is measured the same way.
        let y: Vec<f64> = x.iter().map(|v| 5.0 - v).collect();
        let q = pair_levels(&y, 1000.0, 1000.0, 0.05).unwrap();
        assert!((q.transition_ms.unwrap() - tr).abs() <= 1.0);
        assert_eq!(q.saturated, 0.0);
    }

    #[test]
    fn flat_short_and_non_finite_taxels_are_not_measured() {
        let flat = vec![0.5; 5000];
        let p = pair_levels(&flat, 1000.0, 1000.0, 0.05).unwrap();
        assert_eq!(p.transition_ms, None);
        assert!(pair_levels(&[1.0; 1500], 1000.0, 1000.0, 0.05).is_none());
        let mut bad = vec![1.0; 5000];
        bad[10] = f64::NAN;
        assert!(pair_levels(&bad, 1000.0, 1000.0, 0.05).is_none());
        assert!(pair_levels(&flat, 0.0, 1000.0, 0.05).is_none());
    }

    proptest! {
        #[test]
        fn levels_are_finite_and_the_transition_fits_in_the_trial(
            x in proptest::collection::vec(-10.0f64..10.0, 2..3000),
            rate in 10.0f64..5000.0,
            rest in 0.1f64..2000.0,
        ) {
            if let Some(p) = pair_levels(&x, rate, rest, 0.05) {
                prop_assert!(p.start.is_finite() && p.end.is_finite());
                prop_assert!((0.0..=1.0).contains(&p.saturated));
                if let Some(t) = p.transition_ms {
                    prop_assert!(t >= 0.0 && t <= x.len() as f64 * 1e3 / rate);
                }
            }
        }
    }
}
