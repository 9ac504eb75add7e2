//! The MAE sink: mean absolute error of orientation estimates, overall and per
//! class.
//!
//! For trial `n` with true angle `θ_n` and estimate `θ̂_n`, the absolute error is
//! the angle between the two edge lines, `d = |θ̂_n - θ_n| mod 180`,
//! `e_n = min(d, 180 - d)` (degrees): orientations are lines, so an edge at
//! 170° is 20° from one at 10°, not 160° ([`angle_error`]). Within the paper's
//! 10..90 classes no two angles are over 90° apart and `e_n = |θ̂_n - θ_n|`
//! exactly. Reported per estimator (one per input):
//!
//! * overall MAE `= mean_n e_n` and its SD `= sqrt(mean_n (e_n - MAE)^2)` (the
//!   population SD, as the paper's "MAE (±SD)" reads);
//! * per class (true angle): trials, mean estimate, MAE; the largest per-class MAE;
//! * "no edge" answers: counted, and left out of the MAE (an estimator that says
//!   "no edge" makes no angle error, but it did not answer, so the count stands
//!   beside the MAE in every table rather than being silently folded into it);
//! * trials without a true angle: counted, left out;
//! * MAE at a coarser acuity `A` (key `acuity_deg`, default `[10]`): truth and
//!   estimate are both binned into classes `floor((θ - θ_min) / A)` of width `A`
//!   from the smallest true angle `θ_min`, and the error is the distance between
//!   the bins' lower edges; confusing 40° with 45° then costs nothing at 10°
//!   acuity, confusing 40° with 35° costs 10°. (The paper's "0 MAE at 10° acuity"
//!   is the other reading, a 9-class WSS on the 9 matching classes: that is a
//!   graph, graphs/paper/acuity.toml, not a metric.)
//!
//! * decision time (metric `<id>.decision_ms`): the median over trials of the
//!   palpation each answer needed, `decision_time_ms − t₀`, in ms. The
//!   estimator's `decision_time_ms` counts from the trial's start (see
//!   `estimate`'s module docs for how each estimator sets it); `t₀` is the
//!   edge's first contact with the array, the trial's `crossing_ms[0]`, when the
//!   source knows it (simulated scenes, or a label file's `crossing_ms`, as in
//!   the `trials.json` of `palpate simulate`), else 0 (the trial's start: a recording
//!   without a known crossing; such trials are counted in the report). Counted
//!   from first contact because the hold before it is the protocol's (the
//!   paper's robot waits 2 s at P1), the same for every estimator and no part of
//!   palpating the edge; and because `crop`'s share is defined on the crossing,
//!   so a crop to share `s` caps the decision time at `s · (t₁ − t₀)`. Every
//!   trial with a decision time counts, "no edge" answers included (the time
//!   was spent); an answer given before contact gives a negative time,
//!   kept in the median and counted in the report (such an answer rests on
//!   activity before the edge arrived: a mis-set front end or frames much
//!   longer than the crossing, not a fast decision). The
//!   median, not the mean, because crossing times grow like `1/sin θ` and a few
//!   shallow angles would dominate a mean.
//!
//! * true angles outside an estimator's classes (the angles its estimates
//!   score) by more than half the grid's step: counted in a note of the
//!   report, since the estimator answers within its classes and such a
//!   trial is wrong whatever it does (the usual cause: a scene or recording
//!   with angles above 90° against the paper's 10..90 grid).
//!
//! * accuracy: the share of labelled trials answered within
//!   `correct_within_deg` (default 0: the exact class) of the truth, and the
//!   count of the others ("wrong", "no edge" included). With classes 5° apart
//!   every miss costs at least 5°, so "4 of 170 wrong" says what an MAE of
//!   0.12° (SD 0.76°) hides. Exact-class accuracy cannot count right a true
//!   angle between the classes (a recording at 33.3°) nor an answer refined
//!   between them (WSS's `refine = "search"`): a note of the report counts
//!   those trials and suggests `correct_within_deg` (half the class step
//!   counts the nearest class right), so "0 of 8 right" is not read as
//!   failure.
//!
//! * uncertain answers (metric `<id>.uncertain`): trials whose estimate flags
//!   itself `uncertain` (each estimator documents its rule; WSS: a rival class
//!   scores nearly as well). Counted, and kept in the MAE like any answer: the
//!   count says how many of the errors the estimator warned about.
//!
//! * per-class metrics (for a sweep's `[[sweep.plot]]` with `x = "class"`):
//!   each class's MAE, named `<id>.mae_deg` like the overall one, keyed by the
//!   class's true angle.
//!
//! Files, in the run's output directory, written atomically: `<sink id>.json`,
//! `<sink id>.csv` (one row per estimator and class, numeric columns only),
//! `<sink id>_overall.csv` (one row per estimator), `<sink id>.md` (the table
//! as Markdown), `<sink id>_trials.csv` (one row per estimator and trial: truth,
//! answer, error, correct, decision time, uncertain) and `<sink id>_per_class.svg`
//! (per-class MAE bars, one panel per estimator on shared axes).

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
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MaeConfig {
    /// Print the per-class table (not only the summary line). Default true.
    #[serde(default = "yes")]
    pub per_class: bool,
    /// Coarser acuities to report the MAE at, degrees (see the module docs).
    /// Default `[10]`.
    #[serde(default = "ten")]
    pub acuity_deg: Vec<f64>,
    /// A trial counts as correct when its answer is within this many degrees
    /// of the truth (0: the exact class, up to 1e-6° of rounding), degrees.
    /// Default 0.
    #[serde(default)]
    pub correct_within_deg: f64,
}

fn ten() -> Vec<f64> {
    vec![10.0]
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
        let mut c = palpate_core::ConfigChecks::new();
        for a in &self.acuity_deg {
            c.take(palpate_core::check_positive("acuity_deg", *a, "degrees"));
        }
        if !(self.correct_within_deg.is_finite() && self.correct_within_deg >= 0.0) {
            c.push(ConfigError::key(
                "correct_within_deg",
                format!(
                    "must be a finite number of degrees >= 0, got {}",
                    palpate_core::fmt_num(self.correct_within_deg)
                ),
            ));
        }
        c.finish()?;
        Ok(Stage::Sink(Box::new(MaeSink {
            per_class: self.per_class,
            acuity_deg: self.acuity_deg.clone(),
            correct_within_deg: self.correct_within_deg,
        })))
    }
}
register_stage!("mae", MaeConfig);

struct MaeSink {
    per_class: bool,
    acuity_deg: Vec<f64>,
    correct_within_deg: f64,
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
    /// Trials whose estimate flags itself uncertain (kept in the MAE).
    pub uncertain: usize,
    /// Trials without a true angle (left out).
    pub unlabelled: usize,
    /// Trials in all.
    pub trials: usize,
    /// Per class, by true angle.
    pub classes: Vec<ClassStats>,
    /// (acuity, MAE at that acuity), degrees.
    pub coarse: Vec<(f64, Option<f64>)>,
    /// Median decision time, ms of palpation from first contact (see the
    /// module docs); `None` when no trial has one.
    pub decision_ms: Option<f64>,
    /// Trials with a decision time.
    pub decision_trials: usize,
    /// Of those, trials timed from their start (no known crossing).
    pub decision_from_start: usize,
    /// Of those timed from first contact, trials whose answer came before
    /// it (a negative time: the answer rests on activity before the edge
    /// reached the array, e.g. frames far longer than the crossing).
    pub decision_before_contact: usize,
    /// Trials with a true angle.
    pub labelled: usize,
    /// Labelled trials answered within the tolerance of the truth (see
    /// [`with_accuracy`]).
    pub correct: usize,
    /// `correct / labelled`; `None` without a labelled trial.
    pub accuracy: Option<f64>,
}

/// Whether an answer is correct: an angle within `tolerance` degrees of the
/// truth (plus 1e-6° for rounding); "no edge" is never correct.
pub fn is_correct(truth: f64, estimate: Option<f64>, tolerance: f64) -> bool {
    estimate.is_some_and(|e| angle_error(e, truth) <= tolerance + 1e-6)
}

/// The error of an orientation estimate, degrees: the angle between the two
/// lines, `d = |θ̂ − θ| mod 180` folded to `min(d, 180 − d)`. An edge at
/// 170° is the line at −10°, 20° from one at 10°, not 160°. Equal to
/// `|θ̂ − θ|`, bit for bit, whenever that is at most 90° (every pair of
/// angles within 0..90, as the paper's classes are).
pub fn angle_error(estimate: f64, truth: f64) -> f64 {
    let d = (estimate - truth).abs() % 180.0;
    d.min(180.0 - d)
}

/// Adds accuracy: the share of labelled trials answered within `tolerance`
/// degrees ([`is_correct`]); the rest, "no edge" included, are wrong.
pub fn with_accuracy(mut stats: MaeStats, pairs: &[(Option<f64>, Option<f64>)], tolerance: f64) -> MaeStats {
    let labelled: Vec<(f64, Option<f64>)> = pairs.iter().filter_map(|&(t, e)| Some((t?, e))).collect();
    stats.labelled = labelled.len();
    stats.correct = labelled
        .iter()
        .filter(|(t, e)| is_correct(*t, *e, tolerance))
        .count();
    stats.accuracy = (stats.labelled > 0).then(|| stats.correct as f64 / stats.labelled as f64);
    stats
}

/// One row per trial as CSV: `estimator, trial, true_angle_deg, estimate_deg,
/// abs_error_deg, correct, decision_ms, uncertain` (empty cell: not known, or
/// "no edge"; `decision_ms` from first contact as in the summary; `uncertain`
/// true or false).
pub fn trials_csv(rows: &[TrialRow]) -> String {
    let mut s = String::from(
        "estimator,trial,true_angle_deg,estimate_deg,abs_error_deg,correct,decision_ms,uncertain\n",
    );
    let f = |v: Option<f64>| v.map_or(String::new(), |x| format!("{x}"));
    for r in rows {
        let err = r.truth.zip(r.estimate).map(|(t, e)| angle_error(e, t));
        let correct = r.truth.map_or(String::new(), |t| {
            is_correct(t, r.estimate, r.tolerance).to_string()
        });
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{}",
            csv_field(&r.estimator),
            csv_field(&r.trial),
            f(r.truth),
            f(r.estimate),
            f(err),
            correct,
            f(r.decision_ms),
            r.uncertain
        );
    }
    s
}

/// A CSV field, quoted when it holds a comma, a quote or a line end.
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// One trial of the per-trial table.
#[derive(Clone, Debug, PartialEq)]
pub struct TrialRow {
    /// The estimator's stage id.
    pub estimator: String,
    /// The trial's id.
    pub trial: String,
    /// True angle, degrees.
    pub truth: Option<f64>,
    /// The answer, degrees (`None`: no edge).
    pub estimate: Option<f64>,
    /// Decision time from first contact, ms.
    pub decision_ms: Option<f64>,
    /// The tolerance of "correct", degrees.
    pub tolerance: f64,
    /// The estimate flags itself uncertain.
    pub uncertain: bool,
}

/// One trial's decision time from first contact: `(ms, timed from the start?)`,
/// or `None` when the estimate has no decision time.
pub fn decision_from_contact(
    decision_time_ms: Option<f64>,
    crossing_ms: Option<[f64; 2]>,
) -> Option<(f64, bool)> {
    let t = decision_time_ms.filter(|t| t.is_finite())?;
    match crossing_ms {
        Some([t0, _]) if t0.is_finite() => Some((t - t0, false)),
        _ => Some((t, true)),
    }
}

/// Median of finite values (`None` when there is none): the mean of the two
/// middle values for an even count.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    })
}

/// Adds the decision-time statistics from each trial's `(ms, timed from the
/// start?)` (see [`decision_from_contact`]).
pub fn with_decision(mut stats: MaeStats, times: &[(f64, bool)]) -> MaeStats {
    let ms: Vec<f64> = times.iter().map(|t| t.0).collect();
    stats.decision_ms = median(&ms);
    stats.decision_trials = times.len();
    stats.decision_from_start = times.iter().filter(|t| t.1).count();
    stats.decision_before_contact = times.iter().filter(|t| !t.1 && t.0 < 0.0).count();
    stats
}

/// MAE after binning truth and estimate into classes of width `acuity` from `origin`.
pub fn coarse_mae(pairs: &[(Option<f64>, Option<f64>)], acuity: f64, origin: f64) -> Option<f64> {
    let bin = |a: f64| ((a - origin) / acuity + 1e-9).floor();
    let errs: Vec<f64> = pairs
        .iter()
        .filter_map(|&(t, e)| {
            let d = (bin(t?) - bin(e?)).abs() * acuity;
            // Folded as [`angle_error`] folds: lines 180° apart are one.
            Some(d.min((180.0 - d).abs()))
        })
        .collect();
    (!errs.is_empty()).then(|| errs.iter().sum::<f64>() / errs.len() as f64)
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
            Some(e) => errors.push(angle_error(e, truth)),
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
                .then(|| answered.iter().map(|&e| angle_error(e, angle)).sum::<f64>() / n),
        };
        stats.classes.push(c);
    }
    stats.max_class_mae_deg = stats.classes.iter().filter_map(|c| c.mae_deg).reduce(f64::max);
    stats
}

/// Adds the MAE at each coarser acuity.
pub fn with_coarse(mut stats: MaeStats, pairs: &[(Option<f64>, Option<f64>)], acuities: &[f64]) -> MaeStats {
    let origin = pairs.iter().filter_map(|p| p.0).fold(f64::INFINITY, f64::min);
    if origin.is_finite() {
        stats.coarse = acuities
            .iter()
            .map(|&a| (a, coarse_mae(pairs, a, origin)))
            .collect();
    }
    stats
}

/// The per-class statistics of several estimators as CSV: one row per estimator
/// and class, every column after `estimator` numeric (an empty cell where a class
/// has no answered trial), so that `numpy.loadtxt`/pandas read it as numbers.
/// The overall figures are in [`to_overall_csv`].
pub fn to_csv(all: &[MaeStats]) -> String {
    let mut s = String::from("estimator,angle_deg,trials,no_edge,mean_estimate_deg,mae_deg\n");
    for st in all {
        for c in &st.classes {
            let _ = writeln!(
                s,
                "{},{},{},{},{},{}",
                st.estimator,
                c.angle_deg,
                c.trials,
                c.no_edge,
                csv_num(c.mean_estimate_deg),
                csv_num(c.mae_deg)
            );
        }
    }
    s
}

/// The overall statistics of several estimators as CSV (`<sink id>_overall.csv`):
/// one row per estimator, every column after `estimator` numeric.
pub fn to_overall_csv(all: &[MaeStats]) -> String {
    let mut s = String::from(
        "estimator,trials,no_edge,unlabelled,mae_deg,sd_deg,max_class_mae_deg,decision_ms,uncertain\n",
    );
    for st in all {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{}",
            st.estimator,
            st.trials,
            st.no_edge,
            st.unlabelled,
            csv_num(st.mae_deg),
            csv_num(st.sd_deg),
            csv_num(st.max_class_mae_deg),
            csv_num(st.decision_ms),
            st.uncertain
        );
    }
    s
}

/// A CSV cell: the number, or empty when there is none.
fn csv_num(v: Option<f64>) -> String {
    v.map_or(String::new(), |x| format!("{x}"))
}

/// A summary row's name and how to fill its cell for one estimator.
type SummaryCell = (&'static str, fn(&MaeStats) -> String);

/// The per-class MAE of several estimators side by side as a Markdown table, with
/// summary rows.
pub fn to_markdown(all: &[MaeStats]) -> String {
    let mut angles: Vec<f64> = all
        .iter()
        .flat_map(|s| s.classes.iter().map(|c| c.angle_deg))
        .collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let mut s = String::from("| angle |");
    for st in all {
        let _ = write!(s, " {} MAE (°) |", st.estimator);
    }
    s.push_str("\n|---|");
    s.push_str(&"---|".repeat(all.len()));
    s.push('\n');
    for a in &angles {
        let _ = write!(s, "| {a}° |");
        for st in all {
            let v = st
                .classes
                .iter()
                .find(|c| (c.angle_deg - a).abs() < 1e-9)
                .and_then(|c| c.mae_deg);
            let _ = write!(s, " {} |", fmt_opt(v, 2));
        }
        s.push('\n');
    }
    let rows: [SummaryCell; 7] = [
        ("accuracy (wrong trials)", |st| match st.accuracy {
            Some(a) => format!("{:.1}% ({})", a * 100.0, st.labelled - st.correct),
            None => "-".to_string(),
        }),
        ("overall MAE (SD)", |st| {
            format!("{} ({})", fmt_opt(st.mae_deg, 2), fmt_opt(st.sd_deg, 2))
        }),
        ("largest per-class MAE", |st| fmt_opt(st.max_class_mae_deg, 2)),
        ("no edge", |st| st.no_edge.to_string()),
        ("uncertain (flagged by the estimator)", |st| {
            st.uncertain.to_string()
        }),
        ("decision time, median ms from contact", |st| {
            fmt_opt(st.decision_ms, 0)
        }),
        ("coarse acuity MAE", |st| {
            st.coarse
                .iter()
                .map(|(a, m)| format!("{a}°: {}", fmt_opt(*m, 2)))
                .collect::<Vec<_>>()
                .join(", ")
        }),
    ];
    for (name, f) in rows {
        let _ = write!(s, "| **{name}** |");
        for st in all {
            let _ = write!(s, " {} |", f(st));
        }
        s.push('\n');
    }
    s
}

fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.prec$}"))
}

/// Renders the statistics as a terminal table.
pub fn render(stats: &MaeStats, per_class: bool) -> String {
    // A class's angle with one decimal, or every digit it needs when one
    // decimal would round it (30.0001 and 30 are two rows, both "30.0").
    let class_label = |a: f64| {
        let one = format!("{a:.1}");
        if one.parse::<f64>() == Ok(a) {
            one
        } else {
            palpate_core::fmt_num(a)
        }
    };
    let mut s = String::new();
    if stats.trials == 0 {
        // A live session stopped before its first trial ended: say so
        // rather than an empty table and a row of dashes.
        let _ = writeln!(s, "estimator `{}`: no trial to score", stats.estimator);
        return s;
    }
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
                "  {:>8}°  {:>6}  {:>12}°  {:>7}°  {:>7}",
                class_label(c.angle_deg),
                c.trials,
                fmt_opt(c.mean_estimate_deg, 2),
                fmt_opt(c.mae_deg, 2),
                c.no_edge
            );
        }
    }
    if let Some(a) = stats.accuracy {
        let _ = writeln!(
            s,
            "  accuracy {:.1}% ({} of {} trials wrong, {} of them no edge)",
            a * 100.0,
            stats.labelled - stats.correct,
            stats.labelled,
            stats.no_edge
        );
    }
    let _ = writeln!(
        s,
        "  MAE {}° (SD {}°), largest per-class MAE {}°, no edge {}, uncertain {}{}",
        fmt_opt(stats.mae_deg, 2),
        fmt_opt(stats.sd_deg, 2),
        fmt_opt(stats.max_class_mae_deg, 2),
        stats.no_edge,
        stats.uncertain,
        if stats.unlabelled > 0 {
            format!(", {} unlabelled trials left out", stats.unlabelled)
        } else {
            String::new()
        }
    );
    if stats.trials > 0 && stats.no_edge == stats.trials {
        // The usual cause on a recording is the front end, not the estimator:
        // say where to look (the guide's troubleshooting page says more).
        // An estimator that cannot work on the input (WSS on one taxel or on
        // one line along the slide) warns at the start of the run; this sink
        // cannot see that warning, so it points at it first.
        let _ = writeln!(
            s,
            "  every trial came out \"no edge\": unless a warning above gives the reason (an array WSS \
             cannot read), check the front end -- `normalize`'s `min_span` is in the signal's unit (0.1 \
             for volts, 100 for millivolts) and the encoder must fire (a `raster_plot` stage shows its \
             spikes)"
        );
    }
    if let Some(d) = stats.decision_ms {
        let _ = writeln!(
            s,
            "  decision time: median {d:.0} ms of palpation from first contact ({} trials{}{})",
            stats.decision_trials,
            if stats.decision_from_start > 0 {
                format!(
                    "; {} without a known crossing timed from their start",
                    stats.decision_from_start
                )
            } else {
                String::new()
            },
            if stats.decision_before_contact > 0 {
                format!(
                    "; {} answered before first contact, with negative times: their answers rest on \
                     activity before the edge arrived (frames much longer than the crossing?)",
                    stats.decision_before_contact
                )
            } else {
                String::new()
            }
        );
    }
    s
}

/// A report line when labelled trials lie outside an estimator's classes
/// (the angles its estimates score, sorted), by more than half the grid's
/// step: it answers within its classes, so such a trial is wrong however
/// well it works (an edge at 3 degrees against a 10..170 grid may come out
/// at the grid's far end, where the edge's orientation is nearly the same).
/// `None` when every true angle is covered or there is no grid.
fn outside_note(id: &str, classes: &[f64], pairs: &[(Option<f64>, Option<f64>)]) -> Option<String> {
    let grid = Grid::of(classes)?;
    let (lo, hi) = (grid.lo, grid.hi);
    let outside: Vec<f64> = pairs
        .iter()
        .filter_map(|(t, _)| *t)
        .filter(|t| !grid.covers(*t))
        .collect();
    if outside.is_empty() {
        return None;
    }
    let mut shown: Vec<f64> = Vec::new();
    for a in &outside {
        if !shown.contains(a) && shown.len() < 5 {
            shown.push(*a);
        }
    }
    Some(format!(
        "  note: {} trial{} with a true angle outside `{id}`'s classes ({}° to {}°), e.g. {}: it answers \
         within its classes; cover them (wss: its `angles`; a trained estimator: training trials at \
         those angles)\n",
        outside.len(),
        if outside.len() == 1 { "" } else { "s" },
        palpate_core::fmt_num(lo),
        palpate_core::fmt_num(hi),
        shown
            .iter()
            .map(|a| format!("{}°", palpate_core::fmt_num(*a)))
            .collect::<Vec<_>>()
            .join(", ")
    ))
}

/// An estimator's classes, sorted (finite ones), with their range and half
/// the smallest step between two of them (0 for a single class).
struct Grid {
    classes: Vec<f64>,
    lo: f64,
    hi: f64,
    half: f64,
}

impl Grid {
    /// `None` without classes (estimates that score none).
    fn of(classes: &[f64]) -> Option<Grid> {
        let mut grid: Vec<f64> = classes.iter().copied().filter(|a| a.is_finite()).collect();
        grid.sort_by(f64::total_cmp);
        let (&lo, &hi) = (grid.first()?, grid.last()?);
        let step = grid
            .windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| *d > 0.0)
            .fold(f64::INFINITY, f64::min);
        let half = if step.is_finite() { step / 2.0 } else { 0.0 };
        Some(Grid {
            classes: grid,
            lo,
            hi,
            half,
        })
    }

    /// Whether a true angle `t` lies within half a step of the grid's ends
    /// (its nearest class can answer it).
    fn covers(&self, t: f64) -> bool {
        t >= self.lo - self.half - 1e-9 && t <= self.hi + self.half + 1e-9
    }

    /// Whether `a` is one of the classes (to the 1e-6° exact-class accuracy allows).
    fn has(&self, a: f64) -> bool {
        self.classes.iter().any(|c| (c - a).abs() <= 1e-6)
    }
}

/// A report line when exact-class accuracy (`correct_within_deg = 0`)
/// counts trials wrong only because the truth or the answer lies between the
/// estimator's classes: a true angle off the grid (a scene or recording at
/// 33.3° against classes 5° apart) can never be answered exactly, and an
/// estimator that refines its answer (`refine = "search"`) answers between
/// classes, so "0 of 8 right" says nothing of how close they came. Truths
/// beyond the grid's ends are [`outside_note`]'s. `None` when accuracy has
/// a tolerance, there is no grid, or no such trial.
fn between_note(
    id: &str,
    classes: &[f64],
    pairs: &[(Option<f64>, Option<f64>)],
    tolerance: f64,
) -> Option<String> {
    if tolerance > 0.0 {
        return None;
    }
    let grid = Grid::of(classes)?;
    let (mut truths, mut answers) = (Vec::new(), Vec::new());
    for &(t, e) in pairs {
        let Some(t) = t.filter(|t| grid.covers(*t)) else {
            continue;
        };
        if !grid.has(t) {
            truths.push(t);
        } else if let Some(e) = e.filter(|e| !grid.has(*e)) {
            answers.push(e);
        }
    }
    let deg = |v: f64| format!("{}°", palpate_core::fmt_num(v));
    let trials = |n: usize| format!("{n} trial{}", if n == 1 { "" } else { "s" });
    let mut parts = Vec::new();
    if let Some(&t) = truths.first() {
        parts.push(format!(
            "{} with a true angle between `{id}`'s classes (e.g. {})",
            trials(truths.len()),
            deg(t)
        ));
    }
    if let Some(&e) = answers.first() {
        parts.push(format!(
            "{} on a class answered between classes (e.g. {e:.2}°)",
            trials(answers.len())
        ));
    }
    if parts.is_empty() {
        return None;
    }
    let hint = if grid.half > 0.0 {
        format!(
            " ({} is half the classes' {} step: the nearest class counts right)",
            deg(grid.half),
            deg(2.0 * grid.half)
        )
    } else {
        String::new()
    };
    Some(format!(
        "  note: accuracy is exact-class (`correct_within_deg = 0`): {} count wrong however close; the MAE \
         says how close, or set the mae sink's `correct_within_deg`{hint}\n",
        parts.join(" and ")
    ))
}

impl Sink for MaeSink {
    fn scores_estimates(&self) -> bool {
        true
    }

    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        let mut all = Vec::new();
        let mut trial_rows = Vec::new();
        for input in inputs {
            let mut pairs = Vec::with_capacity(input.items.len());
            let mut times = Vec::with_capacity(input.items.len());
            let mut uncertain = 0;
            let mut classes: Vec<f64> = Vec::new();
            for item in input.items {
                let est = item.payload.estimate()?;
                for c in &est.scores {
                    if !classes.contains(&c.angle_deg) {
                        classes.push(c.angle_deg);
                    }
                }
                pairs.push((item.meta.label.angle_deg, est.angle_deg));
                let time = decision_from_contact(est.decision_time_ms, item.meta.crossing_ms);
                times.extend(time);
                uncertain += usize::from(est.uncertain);
                trial_rows.push(TrialRow {
                    estimator: input.stage_id.to_string(),
                    trial: item.meta.trial_id.clone(),
                    truth: item.meta.label.angle_deg,
                    estimate: est.angle_deg,
                    decision_ms: time.map(|t| t.0),
                    tolerance: self.correct_within_deg,
                    uncertain: est.uncertain,
                });
            }
            let stats = with_coarse(mae_stats(input.stage_id, &pairs), &pairs, &self.acuity_deg);
            let stats = with_decision(stats, &times);
            let mut stats = with_accuracy(stats, &pairs, self.correct_within_deg);
            stats.uncertain = uncertain;
            report.text.push_str(&render(&stats, self.per_class));
            let id = input.stage_id;
            if let Some(note) = outside_note(id, &classes, &pairs) {
                report.text.push_str(&note);
            }
            if let Some(note) = between_note(id, &classes, &pairs, self.correct_within_deg) {
                report.text.push_str(&note);
            }
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
            report
                .metrics
                .push((format!("{id}.uncertain"), stats.uncertain as f64));
            if let Some(a) = stats.accuracy {
                report.metrics.push((format!("{id}.accuracy"), a));
                report
                    .metrics
                    .push((format!("{id}.wrong"), (stats.labelled - stats.correct) as f64));
            }
            for (a, m) in &stats.coarse {
                if let Some(m) = m {
                    report.metrics.push((format!("{id}.mae_at_{a}deg"), *m));
                }
            }
            if let Some(d) = stats.decision_ms {
                report.metrics.push((format!("{id}.decision_ms"), d));
            }
            // Each class's MAE under the overall metric's name, for sweep plots
            // with `x = "class"` (a class whose every answer was "no edge" has none).
            for c in &stats.classes {
                if let Some(m) = c.mae_deg {
                    report.class_metrics.push(palpate_core::ClassMetric {
                        name: format!("{id}.mae_deg"),
                        class: c.angle_deg,
                        value: m,
                    });
                }
            }
            all.push(stats);
        }
        let out = |ext: &str| ctx.out_dir.join(format!("{}{ext}", ctx.stage_id));
        let json = serde_json::to_vec_pretty(&all).map_err(|e| StageError::new(e.to_string()))?;
        let files: [(std::path::PathBuf, Vec<u8>); 5] = [
            (out(".json"), json),
            (out(".csv"), to_csv(&all).into_bytes()),
            (out("_overall.csv"), to_overall_csv(&all).into_bytes()),
            (out(".md"), to_markdown(&all).into_bytes()),
            (out("_trials.csv"), trials_csv(&trial_rows).into_bytes()),
        ];
        for (path, bytes) in files {
            write_atomic(&path, &bytes)
                .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
            report.files.push(path);
        }
        let mut angles: Vec<f64> = all
            .iter()
            .flat_map(|s| s.classes.iter().map(|c| c.angle_deg))
            .collect();
        angles.sort_by(f64::total_cmp);
        angles.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        let class_mae = |st: &MaeStats, a: f64| {
            st.classes
                .iter()
                .find(|c| (c.angle_deg - a).abs() < 1e-9)
                .and_then(|c| c.mae_deg)
                .unwrap_or(f64::NAN)
        };
        let series: Vec<(&str, Vec<f64>)> = all
            .iter()
            .map(|st| {
                (
                    st.estimator.as_str(),
                    angles.iter().map(|&a| class_mae(st, a)).collect(),
                )
            })
            .collect();
        let svg = out("_per_class.svg");
        let cats: Vec<String> = angles.iter().map(|a| format!("{a}")).collect();
        let notes: Vec<String> = all
            .iter()
            .map(|st| format!("MAE {}°", fmt_opt(st.mae_deg, 2)))
            .collect();
        crate::plot::small_multiples(
            &svg,
            &crate::plot::SmallMultiples {
                title: "MAE per class",
                x_title: "true angle (degrees)",
                y_title: "MAE (degrees)",
                categories: &cats,
                series: &series,
                notes: &notes,
            },
        )
        .map_err(|e| StageError::new(format!("writing {}: {e}", svg.display())))?;
        report.files.push(svg);
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
        assert!(text.contains("    10.0°"), "{text}");
    }

    /// Orientations are lines: 10° answered 170° is 20° off, not 160°, in
    /// the MAE, the per-class MAE, the per-trial table and accuracy; within
    /// 90° the error is the plain difference, bit for bit.
    #[test]
    fn errors_are_angles_between_lines() {
        assert_eq!(angle_error(170.0, 10.0), 20.0);
        assert_eq!(angle_error(10.0, 170.0), 20.0);
        assert_eq!(angle_error(95.0, 5.0), 90.0);
        for (e, t) in [(45.3, 10.1), (10.1, 90.0), (0.1, 90.1), (33.3, 33.3)] {
            assert_eq!(angle_error(e, t).to_bits(), (e - t).abs().to_bits());
        }
        let pairs = vec![(Some(10.0), Some(170.0)), (Some(170.0), Some(170.0))];
        let s = mae_stats("w", &pairs);
        assert_eq!(s.mae_deg, Some(10.0));
        assert_eq!(s.classes[0].mae_deg, Some(20.0));
        assert!(is_correct(179.0, Some(1.0), 2.5));
        assert!(!is_correct(179.0, Some(5.0), 2.5));
    }

    /// Classes one decimal would round together are printed with every
    /// digit they need: 30 and 30.0001 are two rows, not two "30.0°".
    #[test]
    fn class_rows_keep_the_digits_that_tell_classes_apart() {
        let pairs = vec![
            (Some(30.0), Some(30.0)),
            (Some(30.0001), Some(30.0)),
            (Some(45.25), Some(45.0)),
        ];
        let text = render(&mae_stats("w", &pairs), true);
        for row in ["    30.0°", "30.0001°", "45.25°"] {
            assert!(text.contains(row), "{row}: {text}");
        }
    }

    /// No trial (a live session stopped before its first ended): one line
    /// saying so, not a table header over nothing and a row of dashes.
    #[test]
    fn no_trial_is_said_in_words() {
        let s = mae_stats("w", &[]);
        for per_class in [true, false] {
            let text = render(&s, per_class);
            assert_eq!(text, "estimator `w`: no trial to score\n");
        }
    }

    #[test]
    fn coarse_acuity_forgives_confusions_within_a_bin() {
        let pairs = vec![
            (Some(40.0), Some(45.0)),
            (Some(40.0), Some(35.0)),
            (Some(10.0), Some(10.0)),
        ];
        // Bins of 10 from 10: 40 and 45 share [40, 50); 35 lies in [30, 40).
        assert_eq!(coarse_mae(&pairs, 10.0, 10.0), Some(10.0 / 3.0));
        assert_eq!(coarse_mae(&pairs, 5.0, 10.0), Some(10.0 / 3.0));
        assert_eq!(coarse_mae(&[(Some(1.0), None)], 10.0, 1.0), None);
        let s = with_coarse(mae_stats("w", &pairs), &pairs, &[10.0]);
        assert_eq!(s.coarse, vec![(10.0, Some(10.0 / 3.0))]);
        let md = to_markdown(&[s.clone(), s.clone()]);
        assert!(md.contains("| 40° | 5.00 | 5.00 |"), "{md}");
        let csv = to_csv(std::slice::from_ref(&s));
        assert_eq!(csv.lines().count(), 3, "{csv}"); // header + 2 classes; the overall row is in _overall.csv
                                                     // Every cell after the estimator's name is a number or empty.
        for line in csv.lines().skip(1) {
            for cell in line.split(',').skip(1) {
                assert!(cell.is_empty() || cell.parse::<f64>().is_ok(), "{line}");
            }
        }
        assert_eq!(to_overall_csv(&[s]).lines().count(), 2);
    }

    #[test]
    fn decision_time_counts_from_first_contact_and_takes_the_median() {
        assert_eq!(
            decision_from_contact(Some(2500.0), Some([2000.0, 5000.0])),
            Some((500.0, false))
        );
        assert_eq!(decision_from_contact(Some(2500.0), None), Some((2500.0, true)));
        assert_eq!(
            decision_from_contact(Some(2500.0), Some([f64::NAN, 1.0])),
            Some((2500.0, true))
        );
        assert_eq!(decision_from_contact(None, Some([0.0, 1.0])), None);
        assert_eq!(decision_from_contact(Some(f64::NAN), None), None);
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&[f64::NAN, 1.0]), Some(1.0));
        let s = with_decision(
            mae_stats("w", &[(Some(30.0), Some(30.0)); 3]),
            &[(100.0, false), (300.0, true), (200.0, false)],
        );
        assert_eq!(s.decision_ms, Some(200.0));
        assert_eq!((s.decision_trials, s.decision_from_start), (3, 1));
        let text = render(&s, false);
        assert!(
            text.contains("median 200 ms") && text.contains("1 without a known crossing"),
            "{text}"
        );
        assert!(to_overall_csv(&[s]).lines().nth(1).unwrap().ends_with(",200,0"));
        // An answer before first contact is counted and said.
        let s = with_decision(
            mae_stats("w", &[(Some(30.0), Some(30.0)); 3]),
            &[(-100.0, false), (300.0, false), (-50.0, true)],
        );
        assert_eq!(s.decision_before_contact, 1);
        let text = render(&s, false);
        assert!(text.contains("1 answered before first contact"), "{text}");
    }

    #[test]
    fn all_no_edge_gives_no_nan() {
        let s = mae_stats("w", &[(Some(10.0), None)]);
        assert_eq!(s.mae_deg, None);
        let text = render(&s, true);
        assert!(!text.contains("NaN"));
        // Every trial without an edge: the report says where to look.
        assert!(text.contains("min_span"), "{text}");
        let some = mae_stats("w", &[(Some(10.0), None), (Some(20.0), Some(20.0))]);
        assert!(!render(&some, true).contains("min_span"));
    }

    #[test]
    fn accuracy_counts_wrong_trials_and_no_edge_as_wrong() {
        let pairs = vec![
            (Some(10.0), Some(10.0)),
            (Some(10.0), Some(15.0)),
            (Some(20.0), Some(20.0 + 1e-9)),
            (Some(20.0), None),
            (None, Some(3.0)),
        ];
        let s = with_accuracy(mae_stats("w", &pairs), &pairs, 0.0);
        assert_eq!((s.labelled, s.correct), (4, 2));
        assert_eq!(s.accuracy, Some(0.5));
        let text = render(&s, false);
        assert!(
            text.contains("accuracy 50.0% (2 of 4 trials wrong, 1 of them no edge)"),
            "{text}"
        );
        // A tolerance of 5 degrees forgives the 10 -> 15 miss, never "no edge".
        let s = with_accuracy(mae_stats("w", &pairs), &pairs, 5.0);
        assert_eq!(s.correct, 3);
        assert!(to_markdown(&[s]).contains("| **accuracy (wrong trials)** | 75.0% (1) |"));
        let none = with_accuracy(mae_stats("w", &[(None, Some(1.0))]), &[(None, Some(1.0))], 0.0);
        assert_eq!(none.accuracy, None);
        assert!(!render(&none, true).contains("accuracy"));
    }

    #[test]
    fn per_trial_table_has_one_row_per_trial() {
        let row = |trial: &str, truth, estimate, uncertain| TrialRow {
            estimator: "wss".into(),
            trial: trial.into(),
            truth,
            estimate,
            decision_ms: Some(1500.0),
            tolerance: 0.0,
            uncertain,
        };
        let csv = trials_csv(&[
            row("a", Some(45.0), Some(50.0), false),
            row("b,c", Some(45.0), None, false),
            row("d", None, Some(30.0), true),
        ]);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 4);
        assert!(lines[0].ends_with(",decision_ms,uncertain"));
        assert_eq!(lines[1], "wss,a,45,50,5,false,1500,false");
        assert_eq!(lines[2], "wss,\"b,c\",45,,,false,1500,false");
        assert_eq!(lines[3], "wss,d,,30,,,1500,true");
    }

    #[test]
    fn true_angles_outside_the_classes_are_noted() {
        let grid = [30.0, 10.0, 20.0];
        // Within half a step of the grid's ends: covered (the nearest class).
        let covered = [
            (Some(5.0), Some(10.0)),
            (Some(34.9), Some(30.0)),
            (None, Some(20.0)),
        ];
        assert_eq!(outside_note("wss", &grid, &covered), None);
        let far = [
            (Some(40.0), Some(30.0)),
            (Some(2.0), Some(10.0)),
            (Some(40.0), None),
        ];
        let note = outside_note("wss", &grid, &far).unwrap();
        assert!(
            note.contains("3 trials") && note.contains("(10° to 30°)") && note.contains("e.g. 40°, 2°"),
            "{note}"
        );
        // No grid (estimates without class scores): nothing to say.
        assert_eq!(outside_note("x", &[], &far), None);
    }

    #[test]
    fn exact_class_accuracy_notes_truths_and_answers_between_classes() {
        let grid = [30.0, 10.0, 20.0];
        // Class answers to class truths, truths beyond the ends (the other
        // note's), no-edge answers: nothing to say.
        let exact = [
            (Some(10.0), Some(10.0)),
            (Some(20.0), Some(30.0)),
            (Some(30.0), None),
            (Some(50.0), Some(30.0)),
            (None, Some(12.5)),
        ];
        assert_eq!(between_note("wss", &grid, &exact, 0.0), None);
        let off = [
            (Some(12.5), Some(10.0)),
            (Some(22.0), Some(20.0)),
            (Some(20.0), Some(20.7)),
            (Some(20.0), Some(20.0)),
            (Some(50.0), Some(31.0)),
        ];
        let note = between_note("wss", &grid, &off, 0.0).unwrap();
        assert!(
            note.contains("2 trials with a true angle between `wss`'s classes (e.g. 12.5°)")
                && note.contains("1 trial on a class answered between classes (e.g. 20.70°)")
                && note.contains("5° is half the classes' 10° step"),
            "{note}"
        );
        // With a tolerance, accuracy already says it; without a grid, nothing.
        assert_eq!(between_note("wss", &grid, &off, 2.5), None);
        assert_eq!(between_note("x", &[], &off, 0.0), None);
        // One class: no step to suggest half of.
        let note = between_note("wss", &[45.0], &[(Some(45.0), Some(44.0))], 0.0).unwrap();
        assert!(
            note.contains("1 trial on a class") && !note.contains("half"),
            "{note}"
        );
    }
}
