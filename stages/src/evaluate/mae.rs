//! The MAE sink: mean absolute error of orientation estimates, overall and per
//! class.
//!
//! For trial `n` with true angle `θ_n` and estimate `θ̂_n`, the absolute error is
//! `e_n = |θ̂_n - θ_n|` (degrees). Reported per estimator (one per input):
//!
//! * overall MAE `= mean_n e_n` and its SD `= sqrt(mean_n (e_n - MAE)^2)` (the
//!   population SD, as the paper's "MAE (±SD)" reads);
//! * per class (true angle): trials, mean estimate, MAE; the largest per-class MAE;
//! * "no edge" answers: counted, and left out of the MAE (an estimator that says
//!   "no edge" makes no angle error, but it did not answer, so the count stands
//!   beside the MAE in every table rather than being silently folded into it);
//! * trials without a true angle: counted, left out.
//!
//! Files: `<sink id>.json` in the run's output directory, written atomically.

use palpate_core::output::write_atomic;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, PayloadKind, Sink, SinkContext, SinkInput,
    SinkReport, Stage, StageConfig, StageError,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// Mean absolute error of orientation estimates, overall and per true angle; one
/// table per input estimator.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct MaeConfig {
    /// Print the per-class table (not only the summary line). Default true.
    #[serde(default = "yes")]
    pub per_class: bool,
}

fn yes() -> bool {
    true
}

#[typetag::serde(name = "mae")]
impl StageConfig for MaeConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::many(PayloadKind::Estimates)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Sink(Box::new(MaeSink {
            per_class: self.per_class,
        })))
    }
}
register_stage!("mae", MaeConfig);

struct MaeSink {
    per_class: bool,
}

/// Per-class statistics of one estimator.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ClassStats {
    /// True angle, degrees.
    pub angle_deg: f64,
    /// Trials of this class.
    pub trials: usize,
    /// Trials answered "no edge".
    pub no_edge: usize,
    /// Mean estimate over answered trials, degrees (NaN-free: `None` if none answered).
    pub mean_estimate_deg: Option<f64>,
    /// MAE over answered trials, degrees.
    pub mae_deg: Option<f64>,
}

/// MAE statistics of one estimator.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct MaeStats {
    /// The estimator's stage id.
    pub estimator: String,
    /// Overall MAE, degrees; `None` when no trial was answered.
    pub mae_deg: Option<f64>,
    /// Population SD of the absolute errors, degrees.
    pub sd_deg: Option<f64>,
    /// Largest per-class MAE, degrees.
    pub max_class_mae_deg: Option<f64>,
    /// Trials answered "no edge".
    pub no_edge: usize,
    /// Trials without a true angle (left out).
    pub unlabelled: usize,
    /// Trials in all.
    pub trials: usize,
    /// Per class, by true angle.
    pub classes: Vec<ClassStats>,
}

/// Computes MAE statistics over `(true angle, estimate)` pairs.
pub fn mae_stats(estimator: &str, pairs: &[(Option<f64>, Option<f64>)]) -> MaeStats {
    let mut by_class: BTreeMap<i64, (f64, Vec<Option<f64>>)> = BTreeMap::new();
    let mut stats = MaeStats {
        estimator: estimator.to_string(),
        trials: pairs.len(),
        ..MaeStats::default()
    };
    let mut errors = Vec::new();
    for &(truth, est) in pairs {
        let Some(truth) = truth else {
            stats.unlabelled += 1;
            continue;
        };
        // Classes keyed by the angle in micro-degrees, so 45.0 and 45.0000001 agree.
        let key = (truth * 1e6).round() as i64;
        by_class.entry(key).or_insert((truth, Vec::new())).1.push(est);
        match est {
            Some(e) => errors.push((e - truth).abs()),
            None => stats.no_edge += 1,
        }
    }
    if !errors.is_empty() {
        let mae = errors.iter().sum::<f64>() / errors.len() as f64;
        let var = errors.iter().map(|e| (e - mae).powi(2)).sum::<f64>() / errors.len() as f64;
        stats.mae_deg = Some(mae);
        stats.sd_deg = Some(var.sqrt());
    }
    for (_, (angle, ests)) in by_class {
        let answered: Vec<f64> = ests.iter().flatten().copied().collect();
        let n = answered.len() as f64;
        let c = ClassStats {
            angle_deg: angle,
            trials: ests.len(),
            no_edge: ests.len() - answered.len(),
            mean_estimate_deg: (!answered.is_empty()).then(|| answered.iter().sum::<f64>() / n),
            mae_deg: (!answered.is_empty())
                .then(|| answered.iter().map(|e| (e - angle).abs()).sum::<f64>() / n),
        };
        stats.classes.push(c);
    }
    stats.max_class_mae_deg = stats.classes.iter().filter_map(|c| c.mae_deg).reduce(f64::max);
    stats
}

fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.prec$}"))
}

/// Renders the statistics as a terminal table.
pub fn render(stats: &MaeStats, per_class: bool) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "estimator `{}`: {} trials", stats.estimator, stats.trials);
    if per_class {
        let _ = writeln!(
            s,
            "  {:>9}  {:>6}  {:>13}  {:>8}  {:>7}",
            "angle", "trials", "mean estimate", "MAE", "no edge"
        );
        for c in &stats.classes {
            let _ = writeln!(
                s,
                "  {:>8.1}°  {:>6}  {:>12}°  {:>7}°  {:>7}",
                c.angle_deg,
                c.trials,
                fmt_opt(c.mean_estimate_deg, 2),
                fmt_opt(c.mae_deg, 2),
                c.no_edge
            );
        }
    }
    let _ = writeln!(
        s,
        "  MAE {}° (SD {}°), largest per-class MAE {}°, no edge {}{}",
        fmt_opt(stats.mae_deg, 2),
        fmt_opt(stats.sd_deg, 2),
        fmt_opt(stats.max_class_mae_deg, 2),
        stats.no_edge,
        if stats.unlabelled > 0 {
            format!(", {} unlabelled trials left out", stats.unlabelled)
        } else {
            String::new()
        }
    );
    s
}

impl Sink for MaeSink {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        let mut all = Vec::new();
        for input in inputs {
            let mut pairs = Vec::with_capacity(input.items.len());
            for item in input.items {
                let est = item.payload.estimate()?;
                pairs.push((item.meta.label.angle_deg, est.angle_deg));
            }
            let stats = mae_stats(input.stage_id, &pairs);
            report.text.push_str(&render(&stats, self.per_class));
            let id = input.stage_id;
            if let Some(m) = stats.mae_deg {
                report.metrics.push((format!("{id}.mae_deg"), m));
            }
            if let Some(m) = stats.sd_deg {
                report.metrics.push((format!("{id}.sd_deg"), m));
            }
            if let Some(m) = stats.max_class_mae_deg {
                report.metrics.push((format!("{id}.max_class_mae_deg"), m));
            }
            report
                .metrics
                .push((format!("{id}.no_edge"), stats.no_edge as f64));
            all.push(stats);
        }
        let path = ctx.out_dir.join(format!("{}.json", ctx.stage_id));
        let json = serde_json::to_vec_pretty(&all).map_err(|e| StageError::new(e.to_string()))?;
        write_atomic(&path, &json)
            .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
        report.files.push(path);
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mae_sd_and_per_class() {
        let pairs = vec![
            (Some(10.0), Some(10.0)),
            (Some(10.0), Some(15.0)),
            (Some(20.0), Some(20.0)),
            (Some(20.0), None),
            (None, Some(3.0)),
        ];
        let s = mae_stats("w", &pairs);
        // Errors 0, 5, 0 -> MAE 5/3, SD sqrt(((5/3)^2*2 + (10/3)^2)/3).
        assert!((s.mae_deg.unwrap() - 5.0 / 3.0).abs() < 1e-12);
        let sd = ((2.0 * (5.0f64 / 3.0).powi(2) + (10.0f64 / 3.0).powi(2)) / 3.0).sqrt();
        assert!((s.sd_deg.unwrap() - sd).abs() < 1e-12);
        assert_eq!(s.no_edge, 1);
        assert_eq!(s.unlabelled, 1);
        assert_eq!(s.classes.len(), 2);
        assert_eq!(s.classes[0].mae_deg, Some(2.5));
        assert_eq!(s.classes[1].no_edge, 1);
        assert_eq!(s.max_class_mae_deg, Some(2.5));
        let text = render(&s, true);
        assert!(text.contains("MAE 1.67°"), "{text}");
    }

    #[test]
    fn all_no_edge_gives_no_nan() {
        let s = mae_stats("w", &[(Some(10.0), None)]);
        assert_eq!(s.mae_deg, None);
        assert!(!render(&s, true).contains("NaN"));
    }
}
