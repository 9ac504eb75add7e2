//! Stage configs and runtime stages.
//!
//! A stage is declared in a graph file as a table whose `type` names a registered
//! config struct. The config is plain data ([`StageConfig`], registered with
//! `#[typetag::serde(name = "...")]` plus [`crate::register_stage!`]); `build()`
//! checks it and turns it into a runtime [`Stage`], or returns a [`ConfigError`]
//! naming the key that is wrong (linfa's param-guard idea).
//!
//! Runtime stages come in four roles:
//!
//! * [`Source`]: lists its trials, then produces each one's payload;
//! * [`Map`]: a pure per-trial function of its inputs (same trial on every input);
//! * [`Estimator`]: sees all trials under the run's evaluation protocol; `fit`
//!   returns a separate fitted [`Model`] (linfa's `Fit` idea), which `predict`s
//!   one trial at a time;
//! * [`Sink`]: receives every trial of every input at the end and reports.
//!
//! Randomness: every stage gets its seed from [`derive_seed`] over (graph seed,
//! stage id, trial id or fold), so results never depend on thread scheduling.

use crate::payload::{Estimate, Item, Payload, PayloadKind, TaxelLayout, TrialMeta};
use rand_chacha::rand_core::SeedableRng;
use std::fmt;
use std::path::PathBuf;
use std::sync::Arc;

/// What a stage accepts on its inputs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InputSpec {
    /// Payload kinds accepted on every input.
    pub kinds: Vec<PayloadKind>,
    /// Fewest inputs.
    pub min: usize,
    /// Most inputs; `None` for any number.
    pub max: Option<usize>,
}

impl InputSpec {
    /// A source: no inputs.
    pub fn none() -> Self {
        InputSpec {
            kinds: vec![],
            min: 0,
            max: Some(0),
        }
    }

    /// Exactly one input of `kind`.
    pub fn one(kind: PayloadKind) -> Self {
        InputSpec {
            kinds: vec![kind],
            min: 1,
            max: Some(1),
        }
    }

    /// One or more inputs of `kind`.
    pub fn many(kind: PayloadKind) -> Self {
        InputSpec {
            kinds: vec![kind],
            min: 1,
            max: None,
        }
    }

    /// Describes the accepted kinds for error messages, e.g. "spike images".
    pub fn describe_kinds(&self) -> String {
        let names: Vec<String> = self.kinds.iter().map(|k| k.to_string()).collect();
        names.join(" or ")
    }
}

/// A problem with a stage's config, naming the key when there is one.
///
/// A config with several wrong keys reports them all in one error: the first
/// problem is `key` and `message`, every further one is in `more` (each with
/// its own key; gather them with [`ConfigChecks`]). `palpate check` prints
/// each problem as its own diagnostic, with its key's line.
#[derive(Clone, Debug, PartialEq)]
pub struct ConfigError {
    /// The offending key (a dotted path for nested keys), if any.
    pub key: Option<String>,
    /// What is wrong and what would be right.
    pub message: String,
    /// Further problems of the same config, found by the same check; empty
    /// when there is one problem.
    pub more: Vec<ConfigError>,
}

impl fmt::Display for ConfigError {
    /// Every problem, each as "key `k`: message", separated by "; ".
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, (key, message)) in self.problems().into_iter().enumerate() {
            if i > 0 {
                f.write_str("; ")?;
            }
            if let Some(k) = key {
                write!(f, "key `{k}`: ")?;
            }
            f.write_str(message)?;
        }
        Ok(())
    }
}

impl std::error::Error for ConfigError {}

impl ConfigError {
    /// A problem with `key`.
    pub fn key(key: impl Into<String>, message: impl Into<String>) -> Self {
        ConfigError {
            key: Some(key.into()),
            message: message.into(),
            more: Vec::new(),
        }
    }

    /// A problem with the config as a whole.
    pub fn general(message: impl Into<String>) -> Self {
        ConfigError {
            key: None,
            message: message.into(),
            more: Vec::new(),
        }
    }

    /// Every problem this error holds, first one first, as (key, message).
    pub fn problems(&self) -> Vec<(Option<&str>, &str)> {
        let mut out = vec![(self.key.as_deref(), self.message.as_str())];
        for m in &self.more {
            out.extend(m.problems());
        }
        out
    }

    /// One error holding every problem of `errors` (in order); `None` when
    /// there is none.
    pub fn join(errors: Vec<ConfigError>) -> Option<ConfigError> {
        let mut it = errors.into_iter();
        let mut first = it.next()?;
        first.more.extend(it);
        Some(first)
    }

    /// The same problems with every message prefixed by `what: ` (e.g. the
    /// file they were found in).
    pub fn context(mut self, what: &str) -> ConfigError {
        self.message = format!("{what}: {}", self.message);
        self.more = self.more.into_iter().map(|m| m.context(what)).collect();
        self
    }

    /// The same problems with every key prefixed by `prefix.` (a key of a
    /// nested table: `ridge` + `width_mm` gives `ridge.width_mm`).
    pub fn within(mut self, prefix: &str) -> ConfigError {
        self.key = Some(match self.key.take() {
            Some(k) if !k.is_empty() => format!("{prefix}.{k}"),
            _ => prefix.to_string(),
        });
        self.more = self.more.into_iter().map(|m| m.within(prefix)).collect();
        self
    }
}

/// Gathers every problem of a config, so that `build` reports them all at
/// once instead of stopping at the first:
///
/// ```
/// # use palpate_core::{check_positive, check_range, ConfigChecks, ConfigError};
/// fn check(order: f64, cutoff_hz: f64) -> Result<(), ConfigError> {
///     let mut c = ConfigChecks::new();
///     c.take(check_range("order", order, 1.0, 16.0, ""));
///     c.take(check_positive("cutoff_hz", cutoff_hz, "Hz"));
///     c.finish()
/// }
/// let e = check(0.0, -1.0).unwrap_err();
/// assert_eq!(e.problems().len(), 2);
/// ```
#[derive(Debug, Default)]
pub struct ConfigChecks {
    errors: Vec<ConfigError>,
}

impl ConfigChecks {
    /// No problem yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The value of a check that passed; a failed check's problem is kept
    /// (and `None` returned) so that the next checks still run.
    pub fn take<T>(&mut self, result: Result<T, ConfigError>) -> Option<T> {
        match result {
            Ok(v) => Some(v),
            Err(e) => {
                self.errors.push(e);
                None
            }
        }
    }

    /// Records a problem.
    pub fn push(&mut self, e: ConfigError) {
        self.errors.push(e);
    }

    /// True while no check failed.
    pub fn is_ok(&self) -> bool {
        self.errors.is_empty()
    }

    /// `Ok` when every check passed, else one error holding every problem.
    pub fn finish(self) -> Result<(), ConfigError> {
        match ConfigError::join(self.errors) {
            None => Ok(()),
            Some(e) => Err(e),
        }
    }
}

/// A number as messages print it: Rust's shortest round-trip form, or
/// exponent form when that would be long (magnitude at least 1e15 or below
/// 1e-6, so `f64::MAX` prints as `1.7976931348623157e308`, not 309 digits).
pub fn fmt_num(v: f64) -> String {
    let a = v.abs();
    if v.is_finite() && a != 0.0 && !(1e-6..1e15).contains(&a) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// Checks a number against a range, naming the key on failure. Used by configs'
/// `build` to turn out-of-range values into [`ConfigError`]s.
pub fn check_range(key: &str, value: f64, min: f64, max: f64, unit: &str) -> Result<f64, ConfigError> {
    if value.is_finite() && value >= min && value <= max {
        Ok(value)
    } else {
        // Bounds print readably: an open upper end (f64::MAX) is said in
        // words, and a huge bound in exponent form, never as 309 digits.
        let num = fmt_num;
        // A unitless key says no unit (no stray space before the comma).
        let unit = if unit.is_empty() {
            String::new()
        } else {
            format!(" {unit}")
        };
        let msg = if max == f64::MAX {
            format!(
                "must be a finite number of at least {}{unit}, got {}",
                num(min),
                num(value)
            )
        } else {
            format!(
                "must lie in [{}, {}]{unit}, got {}",
                num(min),
                num(max),
                num(value)
            )
        };
        Err(ConfigError::key(key, msg))
    }
}

/// Checks that a number is finite and strictly positive, naming the key on failure.
pub fn check_positive(key: &str, value: f64, unit: &str) -> Result<f64, ConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(ConfigError::key(
            key,
            format!(
                "must be a positive number{}, got {}",
                if unit.is_empty() {
                    String::new()
                } else {
                    format!(" of {unit}")
                },
                fmt_num(value)
            ),
        ))
    }
}

/// An error while a stage runs on data.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct StageError {
    /// What went wrong, naming the file, key or position where there is one.
    pub message: String,
}

impl StageError {
    /// An error with a message.
    pub fn new(message: impl Into<String>) -> Self {
        StageError {
            message: message.into(),
        }
    }

    pub(crate) fn wrong_kind(expected: PayloadKind, got: PayloadKind) -> Self {
        StageError::new(format!("expected {expected}, got {got}"))
    }
}

impl From<ConfigError> for StageError {
    fn from(e: ConfigError) -> Self {
        StageError::new(e.to_string())
    }
}

impl From<std::io::Error> for StageError {
    fn from(e: std::io::Error) -> Self {
        StageError::new(e.to_string())
    }
}

/// What a config's `build` may know about the graph it is in.
#[derive(Clone, Debug)]
pub struct BuildContext {
    /// The stage's id.
    pub stage_id: String,
    /// The run's seed.
    pub seed: u64,
    /// Where the run writes its reports.
    pub out_dir: PathBuf,
    /// Directory that relative paths in the graph (scene files, recordings)
    /// resolve against: the graph file's directory.
    pub base_dir: PathBuf,
}

impl BuildContext {
    /// Resolves a path from the graph against [`BuildContext::base_dir`].
    pub fn resolve(&self, path: &std::path::Path) -> PathBuf {
        if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.base_dir.join(path)
        }
    }
}

/// A stage's config: plain data deserialized from its graph table.
///
/// Register an implementation with `#[typetag::serde(name = "my_type")]` on the
/// `impl` and [`crate::register_stage!`]`("my_type", MyConfig)` beside it; the
/// struct's doc comments are the documentation `palpate stages my_type` shows.
#[typetag::serde]
pub trait StageConfig: Send + Sync + fmt::Debug {
    /// Payload kinds and number of inputs this stage accepts.
    fn inputs(&self) -> InputSpec;
    /// The payload kind this stage gives; `None` for a sink.
    fn output(&self) -> Option<PayloadKind>;
    /// Checks the config and builds the runtime stage. Must be cheap: heavy
    /// precomputation belongs in the first use, cached.
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError>;
    /// Checks the config against what is known of its inputs before anything
    /// runs (their sample rate, ...), says what is known of its own output,
    /// and gives warnings (deprecated spellings, settings that run but are
    /// probably not meant). The graph loader calls it after every stage
    /// built, in data-flow order; `inputs` holds one [`OutputFacts`] per
    /// declared input. Must be cheap, like `build`.
    ///
    /// The default checks nothing and passes the sample rate on when the
    /// stage turns signals into signals and its inputs agree on it.
    fn inspect(&self, _ctx: &BuildContext, inputs: &[OutputFacts]) -> Inspection {
        let mut out = Inspection::default();
        if self.output() == Some(PayloadKind::Signals) && self.inputs().kinds == [PayloadKind::Signals] {
            out.facts = OutputFacts::agreed(inputs);
        }
        out
    }
}

/// What the graph loader knows of a stage's output before anything runs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OutputFacts {
    /// Samples per second of the signals, Hz, when the source knows it from
    /// its config (a scene's `motion.sample_rate_hz`, a file source's
    /// `sample_rate_hz`); `None` when it is known only from the data.
    pub sample_rate_hz: Option<f64>,
    /// The taxel array of every trial, when the source's config says it (a
    /// scene's `array` or `layout`, a file source's `layout` key) and every
    /// trial has the same one; `None` when it is known only from the data
    /// (a file source reading its layout from a sidecar) or trials differ.
    /// Why: a `union` of sources on different arrays is legal (WSS matches
    /// each trial against its own array's templates) but a trained estimator
    /// would learn one array's taxels and score another's, so `check` warns.
    pub layout: Option<TaxelLayout>,
}

impl OutputFacts {
    /// The facts every input agrees on (an unknown input makes them unknown).
    pub fn agreed(inputs: &[OutputFacts]) -> OutputFacts {
        OutputFacts {
            sample_rate_hz: Self::one(inputs.iter().map(|f| f.sample_rate_hz)).flatten(),
            layout: Self::one(inputs.iter().map(|f| f.layout.as_ref()))
                .flatten()
                .cloned(),
        }
    }

    /// The value every item has; `None` when two differ or there is none
    /// (how a source with several conditions agrees its own facts).
    pub fn one<T: PartialEq>(mut items: impl Iterator<Item = T>) -> Option<T> {
        let first = items.next()?;
        items.all(|x| x == first).then_some(first)
    }
}

/// What [`StageConfig::inspect`] found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Inspection {
    /// What is known of the stage's output.
    pub facts: OutputFacts,
    /// Problems that stop the graph from running (each names its key).
    pub errors: Vec<ConfigError>,
    /// Problems `check` and `run` print without stopping.
    pub warnings: Vec<ConfigError>,
}

/// A runtime stage, by role.
pub enum Stage {
    /// Produces trials.
    Source(Box<dyn Source>),
    /// Transforms one trial at a time.
    Map(Box<dyn Map>),
    /// Fits on training trials and estimates test trials.
    Estimator(Box<dyn Estimator>),
    /// Receives every trial at the end.
    Sink(Box<dyn Sink>),
}

impl Stage {
    /// The role's name, for messages.
    pub fn role(&self) -> &'static str {
        match self {
            Stage::Source(_) => "source",
            Stage::Map(_) => "map",
            Stage::Estimator(_) => "estimator",
            Stage::Sink(_) => "sink",
        }
    }
}

/// Per-trial context: which stage and trial, and the seed for that pair.
#[derive(Clone, Debug)]
pub struct TrialContext<'a> {
    /// The stage's id.
    pub stage_id: &'a str,
    /// The trial's metadata.
    pub meta: &'a TrialMeta,
    /// Seed derived from (graph seed, stage id, trial id).
    pub seed: u64,
}

impl TrialContext<'_> {
    /// A fresh generator seeded for this (stage, trial).
    pub fn rng(&self) -> rand_chacha::ChaCha8Rng {
        rand_chacha::ChaCha8Rng::seed_from_u64(self.seed)
    }
}

/// A source of trials.
pub trait Source: Send + Sync {
    /// Every trial's metadata, in order; `index` is filled in by the runtime.
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError>;
    /// The payload of one trial: a pure function of (config, metadata, seed).
    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError>;
    /// What one trial's payload depends on besides the stage's id and type,
    /// the graph's seed and the trial's metadata, as text to hash: a sweep's
    /// cache reuses a trial's payload (and everything computed from it)
    /// across points whose fingerprints and metadata agree. `None` (the
    /// default) stands for the stage's whole settings, so a trial is reused
    /// only when nothing in the stage's config changed. A source whose config
    /// has parts only some trials read (a scene's conditions) returns what
    /// this trial reads, so that a sweep shifting one condition does not
    /// recompute the other's trials. It must cover everything `produce`
    /// reads besides `ctx.meta` and `ctx.seed`, or a stale payload is served.
    fn trial_fingerprint(&self, _meta: &TrialMeta) -> Option<String> {
        None
    }
    /// Its live form, for a source that produces trials as they happen (a
    /// DAQ): `palpate run --live` follows it instead of `trials`/`produce`.
    fn live(&self) -> Option<&dyn crate::stream::LiveSource> {
        None
    }
}

/// A per-trial transformation.
pub trait Map: Send + Sync {
    /// Transforms one trial; `inputs` are this trial's items, one per declared
    /// input, in declaration order.
    fn process(&self, inputs: &[&Item], ctx: &TrialContext<'_>) -> Result<Payload, StageError>;
}

/// Context for fitting an estimator on one fold.
#[derive(Clone, Debug)]
pub struct FitContext<'a> {
    /// The stage's id.
    pub stage_id: &'a str,
    /// The fold's number (0 for a model-based estimator's single fit).
    pub fold: usize,
    /// Seed derived from (graph seed, stage id, fold).
    pub seed: u64,
}

impl FitContext<'_> {
    /// A fresh generator seeded for this (stage, fold).
    pub fn rng(&self) -> rand_chacha::ChaCha8Rng {
        rand_chacha::ChaCha8Rng::seed_from_u64(self.seed)
    }
}

/// An estimator: trained (fits on the training trials of each fold) or
/// model-based (fits once, on nothing, and estimates every trial).
pub trait Estimator: Send + Sync {
    /// True when the estimator learns from training trials.
    fn trained(&self) -> bool;
    /// Fits a model. A model-based estimator gets no training items.
    ///
    /// A sweep may reuse a model fitted at an earlier point, for the same
    /// stage (id, type, settings), seed and fold, when the training items'
    /// payloads and metadata other than provenance are unchanged
    /// ([`Item::content_key`]): a fit must depend on nothing else.
    fn fit(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError>;
    /// False when fitting has effects beyond the model it returns (writing
    /// the model into the run's directory): a sweep then runs the stage at
    /// every point, reusing neither its output nor its models, so every
    /// point gets its files. Default true.
    fn reusable(&self) -> bool {
        true
    }
}

/// A fitted model.
pub trait Model: Send + Sync {
    /// Estimates one trial.
    fn predict(&self, item: &Item, ctx: &TrialContext<'_>) -> Result<Estimate, StageError>;
    /// The model as the bytes of a model file (the file a trained stage's
    /// `save_model = true` writes and `model_in` reads), or `None` for a model
    /// that is not saved that way (WSS, built from its config; a Python
    /// stage's). The Python package's `Model.save` and pickling use it.
    fn saved_bytes(&self) -> Option<Result<Vec<u8>, StageError>> {
        None
    }
}

/// Every trial of one input of a sink.
#[derive(Clone, Copy, Debug)]
pub struct SinkInput<'a> {
    /// The id of the stage that made these items.
    pub stage_id: &'a str,
    /// The items, in trial order.
    pub items: &'a [Item],
}

/// Context for a sink.
#[derive(Clone, Debug)]
pub struct SinkContext<'a> {
    /// The sink's id.
    pub stage_id: &'a str,
    /// Where the run writes its reports (created by the runtime).
    pub out_dir: &'a std::path::Path,
}

/// What a sink reports.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SinkReport {
    /// Text for the terminal (a table, usually).
    pub text: String,
    /// Files the sink wrote.
    pub files: Vec<PathBuf>,
    /// Named numbers the sink measured (e.g. `wss.mae_deg`), for tests, sweeps
    /// and the run record.
    pub metrics: Vec<(String, f64)>,
    /// A metric's value per class (e.g. `wss.mae_deg` of the trials whose true
    /// angle is 45°), for a sweep's `[[sweep.plot]]` with `x = "class"`. Named
    /// like the overall metric it breaks down. Default none.
    pub class_metrics: Vec<ClassMetric>,
}

/// Fails when `report` (sink `id`'s) lists a file an earlier sink of the
/// same run also wrote: sinks name their files after their ids (`mae` writes
/// `mae_trials.csv`, so a second sink called `mae_trials` writes over it), and
/// the one written first is lost. The error names both sinks and the file.
pub fn check_sink_files(
    earlier: &[(String, SinkReport)],
    id: &str,
    report: &SinkReport,
) -> Result<(), String> {
    for f in &report.files {
        if let Some((other, _)) = earlier.iter().find(|(_, r)| r.files.contains(f)) {
            return Err(format!(
                "sinks `{other}` and `{id}` both write {}: the second overwrote the first's; rename one of \
                 them (a sink's files are named after its id)",
                f.display()
            ));
        }
    }
    Ok(())
}

/// One class's value of a metric: see [`SinkReport::class_metrics`].
#[derive(Clone, Debug, PartialEq)]
pub struct ClassMetric {
    /// The metric's name, as the overall metric's (`wss.mae_deg`).
    pub name: String,
    /// The class: its true angle, degrees.
    pub class: f64,
    /// The metric over that class's trials.
    pub value: f64,
}

/// A sink: receives every trial of every input once all trials are done.
pub trait Sink: Send + Sync {
    /// Consumes the inputs, in declaration order.
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError>;

    /// Whether this sink reports, for each estimator it reads, the metrics the
    /// accuracy-time frontier reads: `<id>.mae_deg`, `<id>.sd_deg`,
    /// `<id>.no_edge` and `<id>.decision_ms`. The graph loader accepts an
    /// estimator in `[sweep] frontier` only when such a sink reads it, so a
    /// sink of a plugin can score estimates too. Default: no.
    fn scores_estimates(&self) -> bool {
        false
    }
}

/// Derives a 64-bit seed from the graph's seed and a list of labels (stage id,
/// trial id, fold). FNV-1a over the bytes, finished by SplitMix64, so that the
/// value is stable across Rust versions and platforms (unlike `DefaultHasher`).
pub fn derive_seed(seed: u64, labels: &[&str]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325 ^ seed;
    for label in labels {
        for b in label.bytes().chain(std::iter::once(0xff)) {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    splitmix64(h ^ seed.rotate_left(17))
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Shared, immutable settings JSON of a stage, for provenance.
pub(crate) fn settings_json(config: &dyn StageConfig) -> Arc<serde_json::Value> {
    Arc::new(serde_json::to_value(config).unwrap_or(serde_json::Value::Null))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_errors_print_bounds_readably() {
        let e = check_range("min_span", -1.0, 0.0, f64::MAX, "V").unwrap_err();
        assert!(e.message.contains("at least 0 V, got -1"), "{}", e.message);
        assert!(e.message.len() < 80, "{}", e.message);
        let e = check_range("x", 2e300, 0.0, 1e20, "ms").unwrap_err();
        assert!(e.message.contains("[0, 1e20] ms, got 2e300"), "{}", e.message);
        assert_eq!(check_range("x", 1.0, 0.0, f64::MAX, "ms").unwrap(), 1.0);
    }

    #[test]
    fn seeds_differ_by_every_label_and_are_stable() {
        let a = derive_seed(1, &["enc", "t1"]);
        assert_eq!(a, derive_seed(1, &["enc", "t1"]));
        assert_ne!(a, derive_seed(2, &["enc", "t1"]));
        assert_ne!(a, derive_seed(1, &["enc", "t2"]));
        assert_ne!(a, derive_seed(1, &["enct", "1"]));
    }

    #[test]
    fn range_checks_name_the_key() {
        let e = check_range("share", 1.5, 0.0, 1.0, "").unwrap_err();
        assert_eq!(e.key.as_deref(), Some("share"));
        assert!(check_positive("window_ms", 0.0, "ms").is_err());
        assert!(check_positive("window_ms", f64::NAN, "ms").is_err());
        assert_eq!(check_positive("window_ms", 3.0, "ms"), Ok(3.0));
    }
}
