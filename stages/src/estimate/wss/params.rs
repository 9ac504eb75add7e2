//! WSS parameters: the checked, plain-data form of the `wss` stage's keys, shared
//! by the stage, the pure-Rust API ([`super::wss_batch`], [`super::WssStream`])
//! and the benches.

use palpate_core::{check_positive, check_range, ConfigError};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The weight `w` of each observed frame in eq. 5, from its spike rate
/// `SR = frame count / max frame count of the trial` (`SR` in `[0, 1]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Weighting {
    /// `w = 1`: a plain mean of the correlations. The default: exact on the
    /// ideal scene and at least as good as `1 - SR` on the lab scene.
    #[default]
    Constant,
    /// `w = 1 - SR`: the paper's best; the busiest frames count least, and a
    /// spike-free frame (correlation 0) counts most.
    OneMinusSr,
    /// `w = 1 + SR`: the busiest frames count most.
    OnePlusSr,
}

/// How to turn the best grid class into a continuous angle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Refine {
    /// The answer is the best class of the grid (the paper's behaviour).
    #[default]
    None,
    /// Vertex of the parabola through the best class's score and its two
    /// neighbours' (clamped to the neighbours; the grid's end classes stay put).
    /// Free: it uses scores already computed.
    Parabola,
    /// Golden-section search of `max_k WSS_θ(k)` over `θ` between the best
    /// class's neighbours, with templates built for each probed angle, to
    /// `refine_tol_deg`. Costs about 12 extra classes per trial.
    Search,
    /// The angle of the arrival-time plane ([`super::timing`]): when each
    /// taxel fires, fitted as `t = a + b·x + c·y`, gives `θ = atan2(−b, c)`
    /// without the declared speed. WSS still decides edge or no edge and the
    /// class (`class_deg`); the answer is flagged uncertain when the two
    /// disagree by more than 1.5 grid steps, and stays the class when no
    /// plane fits (fewer than 3 taxels fired, or all on one line).
    Timing,
}

/// What the sum of eq. 5 does with template indices `i` that would pair with a
/// frame before the trial's start (`k - i < 0`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum BeforeStart {
    /// Left out of both sums: `WSS_θ(k)` is the weighted mean over the
    /// `min(k, k(θ)) + 1` frames that exist. Early `k` then average few frames,
    /// so a burst of 1 to 8 frames at a trial's start can score up to 1 and win
    /// (seen on simulated lab trials: errors of 40 to 165 degrees).
    Exclude,
    /// Counted as spike-free frames: correlation 0 (zero variance) with the
    /// weight of a spike-free frame (`SR = 0`: 1 for every weighting), so a short
    /// run of frames at the trial's start cannot reach a high score alone: a
    /// window of `m` real frames scores at most `m / k(θ)` of a full one. The
    /// default.
    #[default]
    Silent,
}

/// Where eq. 6's distance `d` is measured from: the taxel's centre, or every
/// point of its area (the taxel then reports the mean of `exp(−d²/σ²)` over its
/// area, as a pressure sensor integrates the load over its surface).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Distance {
    /// `d` from the taxel's centre to the line (eq. 6 read literally). The
    /// default.
    #[default]
    Centre,
    /// `exp(−d²/σ²)` averaged over the taxel's square area: the template then
    /// follows the shape of a real taxel's response, whose width across the
    /// line grows from `a` at 90 degrees to `a·√2` at 45 (`a` the taxel's side),
    /// which a centre distance with one `σ` cannot follow. (Measured: it does
    /// not change the ideal scene's refinement bias, see the module docs.)
    Area,
}

/// The class grid: a list of angles or an inclusive range.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(untagged)]
pub enum AngleGrid {
    /// Explicit angles, degrees, strictly increasing, each in (0, 180).
    List(Vec<f64>),
    /// `from, from + step, ...` up to `to` (inclusive, within 1e-9 of a step).
    Range {
        /// First angle, degrees.
        from: f64,
        /// Last angle, degrees.
        to: f64,
        /// Spacing, degrees.
        step: f64,
    },
}

impl Default for AngleGrid {
    /// 33 classes, 10, 15, ..., 170 degrees: the paper's 5-degree step over
    /// both halves of the circle of orientations, so that an edge leaning the
    /// other way (91 to 170 degrees) is not forced onto the paper's 17 classes
    /// (10 to 90). Graphs that reproduce the paper set its 17 classes.
    fn default() -> Self {
        AngleGrid::Range {
            from: 10.0,
            to: 170.0,
            step: 5.0,
        }
    }
}

impl AngleGrid {
    /// The angles, checked: non-empty, finite, strictly increasing, each in
    /// (0, 180). Errors name the key `angles`.
    pub fn resolve(&self) -> Result<Vec<f64>, ConfigError> {
        let bad = |m: String| ConfigError::key("angles", m);
        let v = match self {
            AngleGrid::List(v) => v.clone(),
            AngleGrid::Range { from, to, step } => {
                if !(step.is_finite() && *step > 0.0) {
                    return Err(ConfigError::key(
                        "angles.step",
                        format!("must be a positive number of degrees, got {step}"),
                    ));
                }
                if !(from.is_finite() && to.is_finite() && from <= to) {
                    return Err(bad(format!("range needs finite from <= to, got {from}..{to}")));
                }
                let n = ((to - from) / step + 1e-9).floor() + 1.0;
                if n > 100_000.0 {
                    return Err(bad(format!("range gives {n} classes; at most 100000")));
                }
                (0..n as usize).map(|j| from + j as f64 * step).collect()
            }
        };
        if v.is_empty() {
            return Err(bad("needs at least one angle".into()));
        }
        for (j, a) in v.iter().enumerate() {
            if !(a.is_finite() && *a > 0.0 && *a < 180.0) {
                return Err(bad(format!(
                    "angle {a} (entry {j}) must lie strictly between 0 and 180 degrees: 0 and 180 \
                     are parallel to the motion and never cross the array"
                )));
            }
            if j > 0 && *a <= v[j - 1] {
                return Err(bad(format!(
                    "angles must be strictly increasing, got {} then {a}",
                    v[j - 1]
                )));
            }
        }
        Ok(v)
    }
}

/// Weighted spatiotemporal similarity (WSS) edge-orientation estimator (model-based, no training).
///
/// Matches a trial's spike images against simulated templates of a line
/// crossing the array at each class angle (paper eqs. 5 to 7) and answers the
/// best class, optionally refined to a continuous angle, or "no edge".
/// Templates follow the images' layout and hop, and are built once per run.
//
// One struct for the keys as written (`WssConfig`, angles as a list or a
// range) and their checked form (`WssParams`, angles resolved, every value
// validated by `WssConfig::params`), so that the keys and their docs exist
// once. (A comment, not a doc: the doc is the stage's description in the schema.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(
    deny_unknown_fields,
    default,
    bound(
        serialize = "A: Serialize",
        deserialize = "A: Deserialize<'de> + DefaultAngles"
    )
)]
#[schemars(bound = "A: JsonSchema + DefaultAngles + Serialize")]
pub struct WssSettings<A> {
    /// Sliding speed the templates assume, mm/s ("known beforehand"). Default:
    /// each trial's own declared speed (a scene's `motion.speed_mm_s`, a
    /// recording's `speed_mm_s` label), else 2 mm/s (the paper's). A live
    /// board's trials declare none: set the arm's speed here. Set, it
    /// overrides every trial's (to study a wrong declared speed, say).
    pub speed_mm_s: Option<f64>,
    /// Spread `σ` of eq. 6, mm, in [0.01, 1000]. Default 1 (half the
    /// paper's 2 mm taxel). Outside that range every template is flat (every
    /// taxel near 1) or empty (every taxel off the line at 0) on any real
    /// array, its correlation 0, and every trial would answer "no edge".
    pub sigma_mm: f64,
    /// Width of the simulated line, mm, in [0, 1000]. Default 0.2 (the paper's).
    pub line_width_mm: f64,
    // In `WssParams`: the resolved, strictly increasing list.
    /// Class angles, degrees in (0, 180): a list `[10, 20, 30]` or a range
    /// `{ from = 10, to = 90, step = 5 }` (inclusive). Default 10 to 170 by 5
    /// (33 classes: the paper's 17, 10 to 90, and their mirror images).
    pub angles: A,
    /// Frame weighting `w` of eq. 5: `constant`, `one_minus_sr` or
    /// `one_plus_sr`. Default `constant`: exact on the ideal scene with four
    /// rows or more (on two or three rows some classes go one step towards 90
    /// degrees: the module docs), where `one_minus_sr`
    /// (the paper's best) misses classes, and as good or better on the lab
    /// scene (RESULTS.md); the paper graphs set `one_minus_sr`.
    pub weighting: Weighting,
    /// Best score (a weighted mean correlation, in [-1, 1]) under which the
    /// answer is "no edge". Default 0.1.
    pub threshold: f64,
    /// Continuous angle: `none` (the grid class), `parabola`, `search` (of
    /// the WSS score over the angle) or `timing` (the arrival-time plane of
    /// the taxels' spikes: unbiased and speed-free, see the module docs).
    /// Default `none`.
    pub refine: Refine,
    /// Angle tolerance of `refine = "search"`, degrees. Default 0.05.
    pub refine_tol_deg: f64,
    /// For `refine = "timing"`: a taxel's arrival time is the centroid of its
    /// spikes within this many ms of its busiest frame. Default 3000.
    pub timing_window_ms: f64,
    /// Longest template, s of palpation (crossings near 0 or 180 degrees are
    /// long); a longer crossing keeps its last part. Default 120.
    pub max_template_s: f64,
    /// Frames before the trial's start: `silent` (spike-free frames:
    /// correlation 0, weight 1, so a partial window at the trial's start cannot
    /// win) or `exclude` (not part of the sums). Default `silent`.
    pub before_start: BeforeStart,
    /// Stop early, frame by frame, once the best class's score leads the
    /// second best by this margin (and passes `threshold`); `decision_time_ms`
    /// then tells how much palpation was used (ms from the trial's start, to
    /// the end of the stopping frame). Default: none (whole trial).
    pub stop_margin: Option<f64>,
    /// Where eq. 6's distance `d` is measured from: `centre` (the taxel's
    /// centre, eq. 6 read literally) or `area` (every point of the taxel's
    /// square, `exp(−d²/σ²)` averaged over it). Default `centre`.
    pub distance: Distance,
    /// Relative error of `speed_mm_s` to allow for, estimating the speed
    /// jointly with the angle: templates are built at `speed_steps` speeds
    /// over `speed_mm_s · (1 ± speed_tolerance)`, every class scores its best
    /// speed, and `refine = "search"` refines the speed too. Costs
    /// `speed_steps` times the classes. Batch only (not with `stop_margin`).
    /// In [0, 0.9]; default 0 (the speed is known, as in the paper).
    pub speed_tolerance: f64,
    /// Speeds of the grid searched when `speed_tolerance > 0`, 2 to 41.
    /// Default 5 (steps of 10 % at a tolerance of 20 %).
    pub speed_steps: usize,
    /// The answer is flagged `uncertain` when a class that is not the best
    /// class's grid neighbour scores within this much of the best score
    /// (scores are weighted mean correlations; the margin is their
    /// difference, no unit). 0 never flags. Default 0.05 (see the module docs).
    pub uncertain_margin: f64,
}

/// The `wss` stage's keys as written in a graph.
pub type WssConfig = WssSettings<AngleGrid>;

/// Checked WSS parameters, shared by the stage, the pure-Rust API
/// ([`super::wss_batch`], [`super::WssStream`]) and the benches.
pub type WssParams = WssSettings<Vec<f64>>;

impl<A> WssSettings<A> {
    /// The same settings with other angles.
    fn with_angles<B>(self, angles: B) -> WssSettings<B> {
        WssSettings {
            angles,
            speed_mm_s: self.speed_mm_s,
            sigma_mm: self.sigma_mm,
            line_width_mm: self.line_width_mm,
            weighting: self.weighting,
            threshold: self.threshold,
            refine: self.refine,
            refine_tol_deg: self.refine_tol_deg,
            timing_window_ms: self.timing_window_ms,
            max_template_s: self.max_template_s,
            before_start: self.before_start,
            stop_margin: self.stop_margin,
            distance: self.distance,
            speed_tolerance: self.speed_tolerance,
            speed_steps: self.speed_steps,
            uncertain_margin: self.uncertain_margin,
        }
    }
}

/// The class angles a default [`WssSettings`] has: 10 to 170 degrees by 5.
pub trait DefaultAngles {
    /// The default angles in this form.
    fn default_angles() -> Self;
}

impl DefaultAngles for AngleGrid {
    fn default_angles() -> Self {
        AngleGrid::default()
    }
}

impl DefaultAngles for Vec<f64> {
    fn default_angles() -> Self {
        AngleGrid::default().resolve().unwrap_or_default()
    }
}

impl<A: DefaultAngles> Default for WssSettings<A> {
    fn default() -> Self {
        WssSettings {
            speed_mm_s: None,
            sigma_mm: 1.0,
            line_width_mm: 0.2,
            angles: A::default_angles(),
            weighting: Weighting::Constant,
            threshold: 0.1,
            refine: Refine::None,
            refine_tol_deg: 0.05,
            timing_window_ms: 3000.0,
            max_template_s: 120.0,
            before_start: BeforeStart::Silent,
            stop_margin: None,
            distance: Distance::Centre,
            speed_tolerance: 0.0,
            speed_steps: 5,
            uncertain_margin: 0.05,
        }
    }
}

impl WssConfig {
    /// The checked parameters, or an error naming the key.
    pub fn params(&self) -> Result<WssParams, ConfigError> {
        let angles = self.angles.resolve()?;
        let p = self.clone().with_angles(angles);
        p.validate()?;
        if let Some(m) = p.stop_margin {
            palpate_core::check_range("stop_margin", m, 0.0, 2.0, "")?;
            if p.speed_tolerance > 0.0 {
                return Err(ConfigError::key(
                    "speed_tolerance",
                    "the joint speed search is batch only: it cannot be combined with stop_margin",
                ));
            }
        }
        Ok(p)
    }
}

/// The speed WSS assumes when neither its config nor the trial gives one,
/// mm/s: the paper's.
pub const DEFAULT_SPEED_MM_S: f64 = 2.0;

/// (warning kind, stage id) pairs already warned.
static WARNED: std::sync::Mutex<Vec<(&'static str, String)>> = std::sync::Mutex::new(Vec::new());

/// Prints `message()` the first time warning `kind` concerns `stage_id`;
/// returns whether it printed (for the tests).
pub(super) fn warn_once(kind: &'static str, stage_id: &str, message: impl FnOnce() -> String) -> bool {
    let mut w = WARNED.lock().unwrap_or_else(|e| e.into_inner());
    if w.iter().any(|(k, s)| *k == kind && s == stage_id) {
        return false;
    }
    w.push((kind, stage_id.to_string()));
    palpate_core::warn(&message());
    true
}

/// Warns, the first time for `stage_id`, that a trial declared no speed
/// ([`default_speed_message`]). Returns whether it warned (for the tests).
fn warn_default_speed(stage_id: &str, tolerance: f64) -> bool {
    warn_once("speed", stage_id, || default_speed_message(stage_id, tolerance))
}

/// Why WSS cannot tell orientations apart on `layout`, if it cannot: fewer
/// than two taxels (a correlation over one taxel is undefined, taken as 0,
/// so every trial answers "no edge"), or every taxel on one line along the
/// slide (`x`). An edge at `θ` reaches the taxel at `(x, y)` at `t = (x − y
/// cot θ) / v` plus a constant, so on a line of one `y` the order and the
/// timing of the activity are the same at every angle: the answers are
/// near chance (a 1 x 16 array gave 12.5° MAE, every answer uncertain). A
/// line across the slide, or any other line, keeps `cot θ` in the timing.
pub fn blind_layout(layout: &palpate_core::TaxelLayout) -> Option<String> {
    let n = layout.len();
    if n < 2 {
        return Some(format!(
            "the images have {n} taxel{}: a correlation over fewer than two taxels is undefined (taken \
             as 0), so every trial answers \"no edge\"; WSS needs two or more taxels, not all on one \
             line along the slide",
            if n == 1 { "" } else { "s" }
        ));
    }
    let y0 = layout.position(0)[1];
    // A thousandth of a micrometre: positions read from files may round.
    let along = (1..n).all(|i| (layout.position(i)[1] - y0).abs() <= 1e-6);
    along.then(|| {
        format!(
            "the array's {n} taxels all lie on one line along the slide (y = {} mm): an edge's \
             orientation changes neither the order nor the timing of their activity, so WSS cannot \
             tell the angles apart (expect answers near chance, flagged uncertain); an array needs \
             taxels across the slide (more than one row) to see orientation",
            palpate_core::fmt_num(y0)
        )
    })
}

/// The warning for a trial without a declared speed, under the stage's
/// `speed_tolerance`: with none, the two ways out (the speed, or a search
/// for it, which recovers a speed 50 % off: the lab scene at 3 mm/s scored
/// at 2 mm/s gives 16.82° MAE, 0.12° with `speed_tolerance = 0.5`; the
/// guide's recording page has the commands); with one, the range searched.
fn default_speed_message(stage_id: &str, tolerance: f64) -> String {
    let range = |e: f64| {
        format!(
            "{} to {} mm/s",
            palpate_core::fmt_num(DEFAULT_SPEED_MM_S * (1.0 - e)),
            palpate_core::fmt_num(DEFAULT_SPEED_MM_S * (1.0 + e))
        )
    };
    let head = format!(
        "warning: wss `{stage_id}`: a trial declares no palpation speed (a recording whose labels \
         omit `speed_mm_s`?); "
    );
    if tolerance > 0.0 {
        format!(
            "{head}its templates search speeds around {DEFAULT_SPEED_MM_S} mm/s (`speed_tolerance` = {}: {}). \
             Set the stage's `speed_mm_s` if the speed is known.",
            palpate_core::fmt_num(tolerance),
            range(tolerance)
        )
    } else {
        format!(
            "{head}its templates assume {DEFAULT_SPEED_MM_S} mm/s. Set the stage's `speed_mm_s` to the \
             speed the array slid at, or, in a batch run, `speed_tolerance` to search for it with the \
             angle (e.g. 0.5: {}).",
            range(0.5)
        )
    }
}

impl WssParams {
    /// The speed the templates are built for, mm/s: `speed_mm_s`, else
    /// [`DEFAULT_SPEED_MM_S`].
    pub fn speed(&self) -> f64 {
        self.speed_mm_s.unwrap_or(DEFAULT_SPEED_MM_S)
    }

    /// These parameters for a trial whose declared speed is `declared`: the
    /// configured speed when there is one (it overrides the trial's), else
    /// the trial's, else the default. Always with a speed set.
    ///
    /// Falling back to the default warns on stderr, once per stage id in a
    /// process: templates for the wrong speed cost tens of degrees (module
    /// docs), and a recording whose labels omit `speed_mm_s` would
    /// otherwise be scored at 2 mm/s without a word.
    pub fn for_trial(&self, declared: Option<f64>, stage_id: &str) -> WssParams {
        let speed = match self.speed_mm_s.or(declared) {
            Some(v) => v,
            None => {
                warn_default_speed(stage_id, self.speed_tolerance);
                DEFAULT_SPEED_MM_S
            }
        };
        WssParams {
            speed_mm_s: Some(speed),
            ..self.clone()
        }
    }

    /// The coarse speed grid as factors of `speed_mm_s`: `[1]` when the speed
    /// is known (`speed_tolerance = 0`), else `speed_steps` factors evenly
    /// spaced over `1 ± speed_tolerance`.
    pub fn speed_factors(&self) -> Vec<f64> {
        if self.speed_tolerance == 0.0 {
            return vec![1.0];
        }
        let n = self.speed_steps.max(2);
        (0..n)
            .map(|j| 1.0 - self.speed_tolerance + 2.0 * self.speed_tolerance * j as f64 / (n - 1) as f64)
            .collect()
    }

    /// These parameters with the speed scaled by `factor` and known.
    pub fn at_speed(&self, factor: f64) -> WssParams {
        WssParams {
            speed_mm_s: Some(self.speed() * factor),
            speed_tolerance: 0.0,
            ..self.clone()
        }
    }

    /// Checks every value, naming the key of the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if let Some(v) = self.speed_mm_s {
            check_positive("speed_mm_s", v, "mm/s")?;
        }
        check_range("sigma_mm", self.sigma_mm, 0.01, 1000.0, "mm")?;
        check_range("line_width_mm", self.line_width_mm, 0.0, 1000.0, "mm")?;
        AngleGrid::List(self.angles.clone()).resolve()?;
        if !(self.threshold.is_finite() && (-1.0..=1.0).contains(&self.threshold)) {
            return Err(ConfigError::key(
                "threshold",
                format!(
                    "must lie in [-1, 1] (WSS is a weighted mean of correlations), got {}",
                    self.threshold
                ),
            ));
        }
        check_positive("refine_tol_deg", self.refine_tol_deg, "degrees")?;
        check_positive("timing_window_ms", self.timing_window_ms, "ms")?;
        if !(self.speed_tolerance.is_finite() && (0.0..=0.9).contains(&self.speed_tolerance)) {
            return Err(ConfigError::key(
                "speed_tolerance",
                format!(
                    "must lie in [0, 0.9] (a relative error of speed_mm_s), got {}",
                    self.speed_tolerance
                ),
            ));
        }
        if !(2..=41).contains(&self.speed_steps) {
            return Err(ConfigError::key(
                "speed_steps",
                format!("must lie in 2..=41, got {}", self.speed_steps),
            ));
        }
        if !(self.uncertain_margin.is_finite() && (0.0..=2.0).contains(&self.uncertain_margin)) {
            return Err(ConfigError::key(
                "uncertain_margin",
                format!(
                    "must lie in [0, 2] (a difference of scores in [-1, 1]), got {}",
                    self.uncertain_margin
                ),
            ));
        }
        check_positive("max_template_s", self.max_template_s, "s")?;
        if self.max_template_s > 3600.0 {
            return Err(ConfigError::key(
                "max_template_s",
                format!("at most 3600 s, got {}", self.max_template_s),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod speed_tests {
    use super::*;

    #[test]
    fn the_default_speed_is_used_and_warned_once_per_stage_only_when_nothing_declares_one() {
        let p = WssParams {
            speed_mm_s: None,
            ..WssParams::default()
        };
        // A declared speed: used, no warning (the id is still unwarned after).
        assert_eq!(p.for_trial(Some(3.0), "wss-declared").speed_mm_s, Some(3.0));
        assert!(warn_default_speed("wss-declared", 0.0));
        // A configured speed overrides the trial's, without a warning.
        let fixed = WssParams {
            speed_mm_s: Some(1.5),
            ..WssParams::default()
        };
        assert_eq!(fixed.for_trial(None, "wss-fixed").speed_mm_s, Some(1.5));
        assert_eq!(fixed.for_trial(Some(3.0), "wss-fixed").speed_mm_s, Some(1.5));
        assert!(warn_default_speed("wss-fixed", 0.0));
        // Neither: the default, warned at the first trial only.
        assert_eq!(p.for_trial(None, "wss-none").speed_mm_s, Some(DEFAULT_SPEED_MM_S));
        assert!(!warn_default_speed("wss-none", 0.0));
    }

    #[test]
    fn the_missing_speed_warning_names_the_search_or_its_range() {
        let known = default_speed_message("wss", 0.0);
        assert!(
            known.contains("assume 2 mm/s")
                && known.contains("`speed_tolerance`")
                && known.contains("1 to 3 mm/s"),
            "{known}"
        );
        let searched = default_speed_message("wss", 0.25);
        assert!(
            searched.contains("search speeds around 2 mm/s")
                && searched.contains("`speed_tolerance` = 0.25: 1.5 to 2.5 mm/s"),
            "{searched}"
        );
    }

    #[test]
    fn a_template_spread_or_line_width_that_flattens_every_template_is_refused() {
        let with = |sigma_mm: f64, line_width_mm: f64| {
            WssParams {
                sigma_mm,
                line_width_mm,
                ..WssParams::default()
            }
            .validate()
            .err()
            .and_then(|e| e.key)
        };
        assert_eq!(with(1.0, 0.2), None);
        assert_eq!(with(0.01, 0.0), None);
        for bad in [1e-300, 0.0, -1.0, 1e300, f64::NAN, f64::INFINITY] {
            assert_eq!(with(bad, 0.2).as_deref(), Some("sigma_mm"), "{bad}");
        }
        for bad in [-0.1, 1e300, f64::NAN] {
            assert_eq!(with(1.0, bad).as_deref(), Some("line_width_mm"), "{bad}");
        }
    }

    #[test]
    fn a_layout_blind_to_orientation_is_named_and_warned_once_per_stage() {
        use palpate_core::TaxelLayout;
        let grid = |rows, cols| TaxelLayout::Grid {
            rows,
            cols,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        };
        let at = |positions_mm: Vec<[f64; 2]>| TaxelLayout::Positions {
            positions_mm,
            taxel_mm: 2.0,
        };
        let row = blind_layout(&grid(1, 16)).expect("a row along the slide is blind");
        assert!(
            row.contains("16 taxels") && row.contains("along the slide"),
            "{row}"
        );
        assert!(blind_layout(&grid(1, 1)).is_some_and(|m| m.contains("1 taxel:")));
        assert!(blind_layout(&at(vec![[0.0, 2.0], [3.0, 2.0], [9.0, 2.0]])).is_some());
        // Across the slide, on a diagonal, or a grid: timing keeps cot θ.
        for ok in [
            grid(16, 1),
            grid(4, 4),
            grid(2, 2),
            at(vec![[0.0, 0.0], [3.0, 3.0]]),
        ] {
            assert_eq!(blind_layout(&ok), None, "{ok:?}");
        }
        assert!(warn_once("layout", "wss-blind", || "warning: test".into()));
        assert!(!warn_once("layout", "wss-blind", || "warning: test".into()));
        assert!(warn_once("speed", "wss-blind", || "warning: test".into()));
    }
}
