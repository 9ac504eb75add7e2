//! Loading and validating experiment graphs from TOML.
//!
//! A graph file has a `[run]` table of run-wide settings ([`RunSettings`]) and one
//! `[stages.<id>]` table per stage:
//!
//! ```toml
//! [run]
//! seed = 7
//!
//! [stages.scene]
//! type = "edge_scene"
//!
//! [stages.enc]
//! type = "izhikevich"
//! inputs = ["scene"]
//! dt_ms = 0.5
//! ```
//!
//! Loading follows Vector's `compile`: every problem is gathered before failing,
//! each a [`Diagnostic`] naming the file, line, stage and key. The checks, in
//! order: TOML syntax; unknown top-level tables; `[run]` keys; the `[sweep]`
//! table (its keys, series, and each `[[sweep.plot]]`'s file name, metric and
//! fields against the sweep's points); per stage, its
//! `type` (unknown types list close matches), unknown and missing keys (against
//! the config's schema), mistyped keys (serde's error, located by
//! `serde_path_to_error`), the config's own range checks (`build`: every wrong
//! key of a stage, each its own diagnostic); then the graph: unknown inputs,
//! input counts, payload-kind mismatches on edges, cycles (naming their
//! stages), the absence of a source, and (a warning) stages whose output
//! nobody reads; last, in data-flow order, each stage's
//! [`inspect`](crate::StageConfig::inspect) against what is known of its
//! inputs before anything runs (a low-pass cutoff at or above the Nyquist
//! frequency of a scene's sample rate is an error here, not at run time), with
//! its warnings (deprecated key spellings, a bin window shorter than its hop).
//! Nothing runs on a graph with an error.

use crate::registry;
use crate::stage::{BuildContext, ConfigError, InputSpec, OutputFacts, Stage, StageConfig};
use petgraph::graph::{DiGraph, NodeIndex};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

pub use crate::protocol::Protocol;

/// The schema of `[run] seed`: an integer, or a string of decimal digits.
#[derive(schemars::JsonSchema)]
#[serde(untagged)]
#[allow(dead_code)]
enum SeedSchema {
    /// 0 to 9223372036854775807 (TOML's integers).
    Int(u64),
    /// Decimal digits, up to 18446744073709551615.
    Digits(String),
}

/// Reads a seed: a non-negative integer, or a string of decimal digits (for
/// seeds above TOML's largest integer), with an error that says so.
fn seed_from_toml<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    struct V;
    const WHAT: &str = "a whole number from 0 to 18446744073709551615 (above \
                        9223372036854775807, TOML's largest integer, write it as a string: \
                        seed = \"18446744073709551615\")";
    impl serde::de::Visitor<'_> for V {
        type Value = u64;
        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str(WHAT)
        }
        fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<u64, E> {
            Ok(v)
        }
        fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<u64, E> {
            u64::try_from(v).map_err(|_| E::custom(format!("seed {v}: a seed is {WHAT}")))
        }
        fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<u64, E> {
            seed_from_digits(v).ok_or_else(|| E::custom(format!("seed \"{v}\": a seed is {WHAT}")))
        }
    }
    d.deserialize_any(V)
}

/// A seed written as a string: decimal digits only (spaces around them
/// allowed), at most 18446744073709551615; `None` otherwise.
pub fn seed_from_digits(v: &str) -> Option<u64> {
    let t = v.trim();
    (!t.is_empty() && t.bytes().all(|b| b.is_ascii_digit()))
        .then(|| t.parse().ok())
        .flatten()
}

/// `seed` as a `[run] seed` value: an integer, or above TOML's largest
/// integer the string of its digits (which the seed key reads alike).
pub fn seed_value(seed: u64) -> toml::Value {
    i64::try_from(seed).map_or_else(|_| toml::Value::String(seed.to_string()), toml::Value::Integer)
}

/// Run-wide settings: the graph file's `[run]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RunSettings {
    /// Seed of every random generator in the run (each stage and trial derives
    /// its own from it): a whole number from 0 to 18446744073709551615. TOML
    /// integers stop at 9223372036854775807; a larger seed is written as a
    /// string (`seed = "18446744073709551615"`). Default 0.
    #[serde(deserialize_with = "seed_from_toml")]
    #[schemars(with = "SeedSchema")]
    pub seed: u64,
    /// Evaluation protocol for trained estimators. Default "leave_one_trial_out".
    pub protocol: Protocol,
    /// Directory the run's reports go to, relative to the working directory.
    /// Default `out/<graph file name without .toml>`.
    pub out: Option<PathBuf>,
}

impl Default for RunSettings {
    fn default() -> Self {
        RunSettings {
            seed: 0,
            protocol: Protocol::LeaveOneTrialOut,
            out: None,
        }
    }
}

/// A sweep: the graph's `[sweep]` table. The graph runs once per point (and per
/// repeat); stages whose config and inputs did not change are not run again (see
/// [`crate::sweep`]).
///
/// Two forms: the single-key form (`key` and `values`: one point per value), or
/// `[[sweep.series]]` tables, each varying one key from the base graph (the
/// sweep is then the union of the series' points). A graph gives one form, not
/// both. A sweep of `repeats` alone runs the base graph at seeds `[run] seed`
/// to `seed + repeats - 1` (on the command line: `--set sweep.repeats=5`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SweepSettings {
    /// Single-key form: what to vary: `stages.<id>.<key>`, `run.<key>`, or
    /// `stages.<id>` with table values whose keys are merged into the stage (to
    /// vary several keys at once). Leave out with `series`.
    #[serde(default)]
    pub key: String,
    /// Single-key form: the values, in order; TOML values of the key's type.
    #[serde(default)]
    #[schemars(with = "Vec<serde_json::Value>")]
    pub values: Vec<toml::Value>,
    /// Runs per value, repeat `r` with seed `[run] seed + r`; alone (no key, values or series), the base graph's runs. Default 1.
    #[serde(default = "one")]
    pub repeats: usize,
    /// Metrics to tabulate and plot across the sweep (names as sinks report them,
    /// e.g. `wss.mae_deg`); default every metric.
    #[serde(default)]
    pub metrics: Vec<String>,
    /// Several series (`[[sweep.series]]`), each varying one key from the base
    /// graph; the sweep is their union. Point labels are `<series>/<value>` and
    /// each point reports into `<out>/<series>/<value>/`.
    #[serde(default)]
    pub series: Vec<SweepSeries>,
    /// Estimator stage ids to place on the accuracy-time frontier (each must
    /// feed an `mae` sink): MAE against compute time per trial and against
    /// decision time, written as `frontier.{md,csv,json}` and
    /// `frontier_{compute,decision}.svg` into the sweep's output directory.
    /// Default none.
    #[serde(default)]
    pub frontier: Vec<String>,
    /// Figures to draw across the sweep (`[[sweep.plot]]` tables), each an SVG
    /// in the sweep's output directory, in palpate's house style. Default none.
    #[serde(default, rename = "plot")]
    pub plots: Vec<SweepPlot>,
}

/// One figure of a sweep: a `[[sweep.plot]]` table. Every run gives one or more
/// `(series, x, y)` rows: `y` is the run's `metric`, `x` and the series come
/// from the run's point (see [`SweepPoint::field`]). Rows that share (series, x)
/// are averaged, over repeats and over the points that share them (e.g. the
/// placements of one array size); with repeats, the error bar is the SD over
/// repeats of each repeat's average.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(inline)]
pub struct SweepPlot {
    /// The SVG's file name, written into the sweep's output directory: a plain
    /// name (letters, digits, `-`, `_`, `.`) ending `.svg`, not starting
    /// `sweep_` or `frontier_` (palpate's own plots). Required.
    pub file: String,
    /// Title above the plot. Default `"<metric> across <x>"`.
    #[serde(default)]
    pub title: Option<String>,
    /// The metric on the y axis, as sinks name it (`wss.mae_deg`); one of the
    /// sweep's `metrics` when it lists any. Required.
    pub metric: String,
    /// What goes on the x axis: a key of the points' table values (`share` of
    /// `{ share = 0.6, truncate = false }`), `"value"` for the whole value,
    /// `"series"` for the series' name, or `"class"` for the metric per class
    /// (per true angle: the `mae` sink's `<id>.mae_deg`). Default "value".
    #[serde(default)]
    pub x: Option<String>,
    /// What splits the rows into series (legend entries), as `x` (`"series"`
    /// for a series sweep's series). Default none: one series.
    #[serde(default)]
    pub by: Option<String>,
    /// "line" (numeric x, points joined, repeat SD as error bars) or "bars"
    /// (grouped bars, one group per x value in sweep order). Default "line".
    #[serde(default)]
    pub kind: PlotKind,
    /// Title of the x axis. Default the `x` field's name.
    #[serde(default)]
    pub x_label: Option<String>,
    /// Title of the y axis. Default the metric's name.
    #[serde(default)]
    pub y_label: Option<String>,
    /// Legend names: a series' default name (the `by` value's label, e.g.
    /// `"edge"`; `"<by> = <value>"` for a key of table values; the metric's
    /// name when there is no `by`) mapped to the name to show. Default none.
    #[serde(default)]
    pub legend: std::collections::BTreeMap<String, String>,
    /// Bars only: write each bar's value above it. Default false.
    #[serde(default)]
    pub value_labels: bool,
    /// Reference values drawn beside the measured ones (e.g. a paper's):
    /// dashed with open markers on a line plot, outlined bars on a bar plot.
    /// Default none.
    #[serde(default)]
    pub reference: Vec<PlotReference>,
}

/// How a [`SweepPlot`] draws its series.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum PlotKind {
    /// Points joined by lines over a numeric x axis.
    #[default]
    Line,
    /// Grouped bars over categorical x.
    Bars,
}

/// A reference series of a [`SweepPlot`]: `{ name = "paper", points = [[0.6, 2.1]] }`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(inline)]
pub struct PlotReference {
    /// Its legend name. Required.
    pub name: String,
    /// Its `[x, y]` points; on a bar plot, `x` is matched to the category of
    /// that value (a category no point has is added after the others). Required.
    pub points: Vec<[f64; 2]>,
}

/// Most runs (values x repeats, over every series) one sweep may have: a
/// documented cap (docs/resource-policy.md), since every run's graph is loaded
/// before the first runs.
pub const MAX_SWEEP_RUNS: usize = 1000;

/// Stage ids a graph may not use (in any letter case, for case-insensitive
/// file systems): a sink names its reports after its id (`<id>.csv`,
/// `<id>.json`, `<id>.md`), and every run writes `run.json`, `timing.md` /
/// `timing.csv` and, live, `live_timing.md` / `.csv` into the same folder,
/// which would overwrite a sink called so without a word.
pub const RESERVED_STAGE_IDS: [&str; 3] = ["run", "timing", "live_timing"];

/// One series of a sweep: one key, its values, and constant overrides.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(inline)]
pub struct SweepSeries {
    /// The series' name: the prefix of its point labels and report
    /// directories, and its legend entry in plots. Letters, digits, `-` and `_`.
    pub name: String,
    /// What to vary, as the single-key form's `key`.
    pub key: String,
    /// The values, in order.
    #[schemars(with = "Vec<serde_json::Value>")]
    pub values: Vec<toml::Value>,
    /// Overrides applied to every point of this series before its key, each a
    /// quoted path as `--set` takes it (`"stages.bins.inputs" = ["crop"]`):
    /// for a setting that needs the graph wired differently. Default none.
    #[serde(default)]
    #[schemars(with = "std::collections::BTreeMap<String, serde_json::Value>")]
    pub set: toml::Table,
}

/// One point of a sweep: a key set to one value (plus a series' constants).
#[derive(Clone, Debug, PartialEq)]
pub struct SweepPoint {
    /// The series' name (`None` in the single-key form).
    pub series: Option<String>,
    /// The key varied.
    pub key: String,
    /// Its value here.
    pub value: toml::Value,
    /// Overrides applied before the key (a series' `set`).
    pub set: Vec<(String, toml::Value)>,
}

impl SweepPoint {
    /// The point's value of a plot field ([`SweepPlot::x`], [`SweepPlot::by`]):
    /// `"value"` is the whole value, `"series"` the series' name, any other
    /// name a key of a table value. `None` when the point has no such field
    /// (and for `"class"`, which is per class, not per point).
    pub fn field(&self, name: &str) -> Option<toml::Value> {
        match name {
            "value" => Some(self.value.clone()),
            "series" => self.series.clone().map(toml::Value::String),
            "class" => None,
            key => self.value.as_table().and_then(|t| t.get(key)).cloned(),
        }
    }
}

impl SweepPlot {
    /// The `x` field's name (`"value"` when not given).
    pub fn x_field(&self) -> &str {
        self.x.as_deref().unwrap_or("value")
    }

    /// A series' default legend name: the metric's name without `by`, the
    /// value's text for `by = "value"` or `"series"`, else `<by> = <value>`.
    pub fn default_series_name(&self, by_value: Option<&toml::Value>) -> String {
        match (self.by.as_deref(), by_value) {
            (None, _) | (_, None) => self.metric.clone(),
            (Some("value" | "series"), Some(v)) => value_text(v),
            (Some(by), Some(v)) => format!("{by} = {}", value_text(v)),
        }
    }

    /// A series' legend name: its default name mapped through `legend`.
    pub fn series_name(&self, by_value: Option<&toml::Value>) -> String {
        let name = self.default_series_name(by_value);
        self.legend.get(&name).cloned().unwrap_or(name)
    }
}

/// A value as plots label it: a string as it is, a whole number without a
/// decimal point (`4`, also for `4.0`, so that a float category matches an
/// integer reference), anything else as TOML writes it.
pub fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => s.clone(),
        toml::Value::Float(f) => crate::fmt_num(*f),
        other => other.to_string(),
    }
}

impl SweepSettings {
    /// Every point, in order: the values of the single-key form, or each
    /// series' values in turn.
    pub fn points(&self) -> Vec<SweepPoint> {
        if self.series.is_empty() {
            return self
                .values
                .iter()
                .map(|v| SweepPoint {
                    series: None,
                    key: self.key.clone(),
                    value: v.clone(),
                    set: Vec::new(),
                })
                .collect();
        }
        self.series
            .iter()
            .flat_map(|s| {
                s.values.iter().map(|v| SweepPoint {
                    series: Some(s.name.clone()),
                    key: s.key.clone(),
                    value: v.clone(),
                    set: s.set.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
                })
            })
            .collect()
    }

    /// How the sweep names what it varies: its key, or its series' names.
    pub fn describe(&self) -> String {
        if self.series.is_empty() {
            self.key.clone()
        } else {
            let names: Vec<&str> = self.series.iter().map(|s| s.name.as_str()).collect();
            format!("series {}", names.join(", "))
        }
    }
}

fn one() -> usize {
    1
}

/// How bad a diagnostic is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Severity {
    /// The graph cannot run.
    Error,
    /// The graph runs, but probably not as meant.
    Warning,
}

/// One problem found while loading a graph.
#[derive(Clone, Debug, PartialEq)]
pub struct Diagnostic {
    /// Error or warning.
    pub severity: Severity,
    /// The graph file's name as given.
    pub file: String,
    /// 1-based line, where the problem has one.
    pub line: Option<usize>,
    /// The stage concerned, if any.
    pub stage: Option<String>,
    /// The key concerned, if any.
    pub key: Option<String>,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        let sev = match self.severity {
            Severity::Error => "error",
            Severity::Warning => "warning",
        };
        write!(f, ": {sev}: ")?;
        if let Some(stage) = &self.stage {
            write!(f, "stage `{stage}`: ")?;
        }
        f.write_str(&self.message)
    }
}

/// All the errors (and warnings) that stopped a graph from loading.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadErrors(pub Vec<Diagnostic>);

impl LoadErrors {
    /// Only the errors.
    pub fn errors(&self) -> impl Iterator<Item = &Diagnostic> {
        self.0.iter().filter(|d| d.severity == Severity::Error)
    }
}

impl fmt::Display for LoadErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for d in &self.0 {
            writeln!(f, "{d}")?;
        }
        let n = self.errors().count();
        write!(
            f,
            "{n} error{} in the graph; nothing was run",
            if n == 1 { "" } else { "s" }
        )
    }
}

impl std::error::Error for LoadErrors {}

/// Options applied while loading.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Overrides: (`stages.<id>.<key>`, `stages.<id>` with a table value merged
    /// into the stage's keys, or `run.<key>`; value). Applied in order.
    pub overrides: Vec<(String, toml::Value)>,
    /// Output directory, overriding `[run] out`.
    pub out: Option<PathBuf>,
    /// Directory relative paths in the graph resolve against; default the graph
    /// file's directory ([`load_file`]) or the working directory ([`load_str`]).
    pub base_dir: Option<PathBuf>,
}

impl LoadOptions {
    /// Parses `path=value` (from `--set`) into an override; a value that does not
    /// parse as a TOML value is taken as a string, so `--set stages.s.mode=trial` works,
    /// except one that starts as an array, a table or a quoted string does
    /// (`[`, `{`, `"`, `'`): that is an error saying why it does not parse.
    pub fn parse_set(arg: &str) -> Result<(String, toml::Value), String> {
        let (k, v) = arg
            .split_once('=')
            .ok_or_else(|| format!("`--set {arg}` needs the form stages.<id>.<key>=<value>"))?;
        let v = v.trim();
        // A bare word is a string (`mode=trial`), but an array, a table or a
        // quoted string was meant as TOML: say why it does not parse rather
        // than pass its text on as a string.
        if v.starts_with(['[', '{', '"', '\'']) {
            if let Err(e) = toml::from_str::<toml::Table>(&format!("v = {v}")) {
                return Err(format!(
                    "`--set {arg}`: `{v}` is not a TOML value ({})",
                    first_line(e.message())
                ));
            }
        }
        Ok((k.trim().to_string(), parse_value(v)))
    }
}

/// One stage of a loaded graph.
pub struct StageNode {
    /// The stage's id (its table name).
    pub id: String,
    /// Its registered type.
    pub type_name: String,
    /// Ids of the stages it reads, in order.
    pub inputs: Vec<String>,
    /// Its config.
    pub config: Box<dyn StageConfig>,
    /// The built runtime stage.
    pub stage: Stage,
    /// Line of its table in the file.
    pub line: Option<usize>,
}

impl fmt::Debug for StageNode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("StageNode")
            .field("id", &self.id)
            .field("type_name", &self.type_name)
            .field("inputs", &self.inputs)
            .field("role", &self.stage.role())
            .finish()
    }
}

/// A validated graph, ready to run.
#[derive(Debug)]
pub struct Graph {
    /// The file it came from, as given.
    pub file: String,
    /// Run-wide settings (after overrides).
    pub run: RunSettings,
    /// Where reports go.
    pub out_dir: PathBuf,
    /// Directory that relative paths in the graph resolve against (the
    /// graph file's directory, or [`LoadOptions::base_dir`]): what every
    /// stage was built with, kept so that a stage's streaming form resolves
    /// its paths (`model_in`, a scene file) the same way.
    pub base_dir: PathBuf,
    /// Stages in file order.
    pub nodes: Vec<StageNode>,
    /// Indices into `nodes`, in an order where every stage follows its inputs.
    pub order: Vec<usize>,
    /// For each node, the indices of its inputs.
    pub input_index: Vec<Vec<usize>>,
    /// Warnings found while loading.
    pub warnings: Vec<Diagnostic>,
    /// The `[sweep]` table, if any.
    pub sweep: Option<SweepSettings>,
}

impl Graph {
    /// Index of the stage with `id`.
    pub fn index_of(&self, id: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.id == id)
    }

    /// The graph in Graphviz dot.
    pub fn to_dot(&self) -> String {
        let mut s = String::from("digraph palpate {\n  rankdir=LR;\n");
        for n in &self.nodes {
            s.push_str(&format!(
                "  \"{}\" [label=\"{}\\n({})\" shape={}];\n",
                n.id,
                n.id,
                n.type_name,
                match n.stage {
                    Stage::Source(_) => "invhouse",
                    Stage::Sink(_) => "house",
                    Stage::Estimator(_) => "box3d",
                    Stage::Map(_) => "box",
                }
            ));
        }
        for (i, n) in self.nodes.iter().enumerate() {
            for &j in &self.input_index[i] {
                let kind = self.nodes[j]
                    .config
                    .output()
                    .map(|k| k.to_string())
                    .unwrap_or_default();
                s.push_str(&format!(
                    "  \"{}\" -> \"{}\" [label=\"{}\"];\n",
                    self.nodes[j].id, n.id, kind
                ));
            }
        }
        s.push_str("}\n");
        s
    }

    /// The graph as a Mermaid flowchart.
    pub fn to_mermaid(&self) -> String {
        let mut s = String::from("flowchart LR\n");
        let safe = |id: &str| id.replace(|c: char| !c.is_ascii_alphanumeric() && c != '_', "_");
        for n in &self.nodes {
            s.push_str(&format!(
                "  {}[\"{}<br/>({})\"]\n",
                safe(&n.id),
                n.id,
                n.type_name
            ));
        }
        for (i, n) in self.nodes.iter().enumerate() {
            for &j in &self.input_index[i] {
                let kind = self.nodes[j]
                    .config
                    .output()
                    .map(|k| k.to_string())
                    .unwrap_or_default();
                s.push_str(&format!(
                    "  {} -->|{}| {}\n",
                    safe(&self.nodes[j].id),
                    kind,
                    safe(&n.id)
                ));
            }
        }
        s
    }
}

/// Loads and validates a graph file.
pub fn load_file(path: &Path, opts: &LoadOptions) -> Result<Graph, LoadErrors> {
    let file = path.display().to_string();
    let text = crate::input::read_text(path).map_err(|e| {
        LoadErrors(vec![Diagnostic {
            severity: Severity::Error,
            file: file.clone(),
            line: None,
            stage: None,
            key: None,
            message: format!("cannot read the graph file: {e}"),
        }])
    })?;
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("graph");
    let mut opts = opts.clone();
    if opts.base_dir.is_none() {
        opts.base_dir = Some(path.parent().map(Path::to_path_buf).unwrap_or_default());
    }
    load_str(&text, &file, stem, &opts)
}

/// Loads and validates a graph from text. `file` names it in messages; `stem`
/// names the default output directory `out/<stem>`.
pub fn load_str(text: &str, file: &str, stem: &str, opts: &LoadOptions) -> Result<Graph, LoadErrors> {
    Loader {
        file: file.to_string(),
        text,
        diags: Vec::new(),
    }
    .load(stem, opts)
}

struct Loader<'t> {
    file: String,
    text: &'t str,
    diags: Vec<Diagnostic>,
}

/// Lines of the tables and keys of a graph file.
#[derive(Default)]
struct Lines {
    top: HashMap<String, usize>,
    run: HashMap<String, usize>,
    stages: HashMap<String, usize>,
    keys: HashMap<(String, String), usize>,
}

/// What the passes produced, for [`Loader::assemble`].
struct Assembly {
    pending: Vec<Pending>,
    run: RunSettings,
    sweep: Option<SweepSettings>,
    out_dir: PathBuf,
    base_dir: PathBuf,
    order: Vec<usize>,
    input_index: Vec<Vec<usize>>,
}

struct Pending {
    id: String,
    type_name: String,
    inputs: Vec<String>,
    config: Box<dyn StageConfig>,
    /// `None` when `build` refused the config (its errors are reported); the
    /// stage is still wired and inspected, so that every error shows at once.
    stage: Option<Stage>,
    line: Option<usize>,
}

impl<'t> Loader<'t> {
    fn line_of(&self, offset: usize) -> usize {
        self.text[..offset.min(self.text.len())].matches('\n').count() + 1
    }

    fn error(&mut self, line: Option<usize>, stage: Option<&str>, key: Option<&str>, message: String) {
        self.diags.push(Diagnostic {
            severity: Severity::Error,
            file: self.file.clone(),
            line,
            stage: stage.map(str::to_string),
            key: key.map(str::to_string),
            message,
        });
    }

    /// The line of every key of a stage's table `t`, nested tables' keys
    /// as dotted paths (`motion.speed_mm_s`, `sources.b`), so a problem in a
    /// nested key points at its own line. Depth-capped: a hostile file's
    /// deep nesting costs nothing.
    fn key_lines(&self, lines: &mut Lines, id: &str, prefix: &str, t: &toml::de::DeTable, depth: usize) {
        for (key, v) in t.iter() {
            let path = format!("{prefix}{}", key.get_ref());
            lines
                .keys
                .entry((id.to_string(), path.clone()))
                .or_insert_with(|| self.line_of(key.span().start));
            if let (toml::de::DeValue::Table(sub), true) = (v.get_ref(), depth < 4) {
                self.key_lines(lines, id, &format!("{path}."), sub, depth + 1);
            }
        }
    }

    fn lines(&self) -> Lines {
        let mut lines = Lines::default();
        let Ok(doc) = toml::de::DeTable::parse(self.text) else {
            return lines;
        };
        for (k, v) in doc.get_ref().iter() {
            lines
                .top
                .insert(k.get_ref().to_string(), self.line_of(k.span().start));
            let toml::de::DeValue::Table(t) = v.get_ref() else {
                continue;
            };
            match k.get_ref().as_ref() {
                "run" => {
                    for (rk, _) in t.iter() {
                        lines
                            .run
                            .insert(rk.get_ref().to_string(), self.line_of(rk.span().start));
                    }
                }
                "stages" => {
                    for (sid, sv) in t.iter() {
                        let id = sid.get_ref().to_string();
                        lines.stages.insert(id.clone(), self.line_of(sid.span().start));
                        if let toml::de::DeValue::Table(st) = sv.get_ref() {
                            self.key_lines(&mut lines, &id, "", st, 0);
                        }
                    }
                }
                _ => {}
            }
        }
        lines
    }

    /// Loads a graph as a sequence of passes, each reporting into the same
    /// diagnostics so that every error of a file shows at once:
    ///
    /// 1. `parse`: the TOML (a syntax error stops here);
    /// 2. `apply_overrides`: `--set key=value` into the document;
    /// 3. `check_top_level`: only `[run]`, `[sweep]` and `[stages.*]`;
    /// 4. `load_run` and 5. `load_sweep`: the run and sweep settings;
    /// 6. `load_stages`: each stage's config deserialised and built;
    /// 7. `check_graph`: edges, payload kinds, cycles, sources (the order);
    /// 8. `inspect`: each config checked against what its inputs produce;
    /// 9. `check_frontier`: the sweep's frontier names scored estimators;
    /// 10. `assemble`: the graph, when no pass reported an error.
    fn load(mut self, stem: &str, opts: &LoadOptions) -> Result<Graph, LoadErrors> {
        let Some(mut doc) = self.parse() else {
            return Err(LoadErrors(self.diags));
        };
        let lines = self.lines();
        self.apply_overrides(&mut doc, &opts.overrides);
        self.check_top_level(&doc, &lines);
        let run = self.load_run(doc.get("run"), &lines);
        let sweep = self.load_sweep(doc.get("sweep"), &lines, &doc, run.seed);
        let out_dir = opts
            .out
            .clone()
            .or_else(|| run.out.clone())
            .unwrap_or_else(|| PathBuf::from("out").join(stem));
        let base_dir = opts.base_dir.clone().unwrap_or_default();
        let pending = self.load_stages(&doc, &lines, &run, &out_dir, &base_dir);
        let (order, input_index) =
            self.check_graph(&pending, &lines, stages_declared(&doc), &inputs_declared(&doc));
        let ctx = BuildContext {
            stage_id: String::new(),
            seed: run.seed,
            out_dir: out_dir.clone(),
            base_dir: base_dir.clone(),
        };
        self.inspect(&pending, &order, &input_index, &ctx, &lines);
        if let Some(sweep) = &sweep {
            self.check_frontier(sweep, &pending, &lines);
        }
        self.assemble(Assembly {
            pending,
            run,
            sweep,
            out_dir,
            base_dir,
            order,
            input_index,
        })
    }

    /// Pass 1: the document, or `None` after reporting a TOML syntax error.
    fn parse(&mut self) -> Option<toml::Table> {
        match toml::from_str(self.text) {
            Ok(t) => Some(t),
            Err(e) => {
                let line = e.span().map(|s| self.line_of(s.start));
                self.error(line, None, None, format!("not valid TOML: {}", e.message()));
                None
            }
        }
    }

    /// Pass 3: a graph has `[run]`, `[sweep]` and `[stages.<id>]` tables only.
    fn check_top_level(&mut self, doc: &toml::Table, lines: &Lines) {
        for key in doc.keys() {
            if key != "run" && key != "stages" && key != "sweep" {
                let line = lines.top.get(key).copied();
                self.error(
                    line,
                    None,
                    Some(key),
                    format!(
                        "unknown top-level table `{key}`; a graph has `[run]` and `[stages.<id>]` tables"
                    ),
                );
            }
        }
    }

    /// Pass 6: every `[stages.<id>]` table deserialised and built (a stage
    /// whose build failed is kept, unbuilt, so later passes still check it).
    fn load_stages(
        &mut self,
        doc: &toml::Table,
        lines: &Lines,
        run: &RunSettings,
        out_dir: &Path,
        base_dir: &Path,
    ) -> Vec<Pending> {
        let mut pending = Vec::new();
        match doc.get("stages") {
            None => self.error(
                None,
                None,
                None,
                "the graph declares no stages: add `[stages.<id>]` tables".into(),
            ),
            Some(toml::Value::Table(stages)) => {
                for (id, value) in stages {
                    if let Some(p) = self.load_stage(id, value, lines, run, out_dir, base_dir) {
                        pending.push(p);
                    }
                }
            }
            Some(_) => {
                let line = lines.top.get("stages").copied();
                self.error(
                    line,
                    None,
                    None,
                    "`stages` must be a table of `[stages.<id>]` tables".into(),
                );
            }
        }
        pending
    }

    /// Pass 10: the diagnostics in file order and, when none is an error,
    /// the graph.
    fn assemble(mut self, a: Assembly) -> Result<Graph, LoadErrors> {
        // In file order, so that a reader goes down the file once; those
        // without a line (overrides, the graph as a whole) first.
        self.diags.sort_by_key(|d| d.line.unwrap_or(0));
        if self.diags.iter().any(|d| d.severity == Severity::Error) {
            return Err(LoadErrors(self.diags));
        }
        let mut nodes = Vec::with_capacity(a.pending.len());
        for p in a.pending {
            let Some(stage) = p.stage else {
                // Unreachable: a refused build reported an error above.
                return Err(LoadErrors(self.diags));
            };
            nodes.push(StageNode {
                id: p.id,
                type_name: p.type_name,
                inputs: p.inputs,
                config: p.config,
                stage,
                line: p.line,
            });
        }
        Ok(Graph {
            file: self.file,
            run: a.run,
            out_dir: a.out_dir,
            base_dir: a.base_dir,
            nodes,
            order: a.order,
            input_index: a.input_index,
            warnings: self.diags,
            sweep: a.sweep,
        })
    }

    fn load_sweep(
        &mut self,
        value: Option<&toml::Value>,
        lines: &Lines,
        doc: &toml::Table,
        seed: u64,
    ) -> Option<SweepSettings> {
        let value = value?;
        let line = lines.top.get("sweep").copied();
        let mut sweep: SweepSettings = match serde_path_to_error::deserialize(value.clone()) {
            Ok(s) => s,
            Err(e) => {
                let path = e.path().to_string();
                let key = if path.starts_with("plot") {
                    // Inside a [[sweep.plot]] table: its index and key.
                    let mut k = format!("sweep.{path}");
                    match unknown_field(e.inner().message()) {
                        Some(f) if !k.ends_with(&format!(".{f}")) => k = format!("{k}.{f}"),
                        _ => {}
                    }
                    Some(k)
                } else {
                    e.path()
                        .iter()
                        .next()
                        .map(|s| s.to_string())
                        .or_else(|| unknown_field(e.inner().message()))
                };
                let at = match &key {
                    Some(k) if k.starts_with("sweep.") => format!("`{k}`: "),
                    _ => String::new(),
                };
                self.error(
                    line,
                    None,
                    key.as_deref(),
                    format!("in [sweep]: {at}{}", first_line(e.inner().message())),
                );
                return None;
            }
        };
        let key_ok = |key: &str| {
            let parts: Vec<&str> = key.split('.').collect();
            match parts.as_slice() {
                ["run", _, ..] => true,
                ["stages", id, ..] => doc.get("stages").and_then(|s| s.get(*id)).is_some(),
                _ => false,
            }
        };
        let key_msg = |key: &str| {
            format!("must name run.<key> or a declared stage: stages.<id>[.<key>], not \"{key}\"")
        };
        // Repeats only (no key, values nor series): the base graph is the
        // one point, run at seeds `seed`, `seed + 1`, ..., as if the sweep
        // were `key = "run.seed"`, `values = [seed]` (the form
        // graphs/paper/table2.toml spells out).
        if sweep.series.is_empty() && sweep.key.is_empty() && sweep.values.is_empty() {
            sweep.key = "run.seed".into();
            sweep.values = vec![i64::try_from(seed)
                .map(toml::Value::Integer)
                .unwrap_or_else(|_| toml::Value::String(seed.to_string()))];
        }
        if sweep.series.is_empty() {
            if !key_ok(&sweep.key) {
                self.error(
                    line,
                    None,
                    Some("key"),
                    format!("in [sweep]: `key` {}", key_msg(&sweep.key)),
                );
            }
            if sweep.values.is_empty() {
                self.error(
                    line,
                    None,
                    Some("values"),
                    "in [sweep]: `values` lists no value (or give [[sweep.series]] tables)".into(),
                );
            }
        } else if !sweep.key.is_empty() || !sweep.values.is_empty() {
            self.error(
                line,
                None,
                Some("series"),
                "in [sweep]: give either `key` and `values` or [[sweep.series]] tables, not both".into(),
            );
        }
        // Two values with one label would share a point folder: the second
        // overwrites the first, and the sweep never counts as complete. Two
        // numbers of one value (`10` and `10.0`) get two folders but run
        // one setting twice: the same mistake.
        let repeated = |values: &[toml::Value]| -> Option<String> {
            let labels: Vec<String> = values.iter().map(crate::sweep::label).collect();
            let number = |v: &toml::Value| v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
            let same = |a: usize, b: usize| {
                labels[a] == labels[b]
                    || matches!((number(&values[a]), number(&values[b])), (Some(x), Some(y)) if x == y)
            };
            (0..values.len())
                .find_map(|i| (0..i).find(|&j| same(i, j)).map(|j| (j, i)))
                .map(|(j, i)| {
                    if labels[i] == labels[j] {
                        format!(
                            "`values` lists {} twice (each value is one point, reported in its own folder)",
                            labels[i]
                        )
                    } else {
                        format!(
                            "`values` lists {} and {}, one number: the same setting would run twice",
                            labels[j], labels[i]
                        )
                    }
                })
        };
        if let Some(msg) = repeated(&sweep.values) {
            self.error(line, None, Some("values"), format!("in [sweep]: {msg}"));
        }
        let mut names: Vec<&str> = Vec::new();
        for s in &sweep.series {
            let what = format!("in [sweep] series `{}`", s.name);
            if let Some(msg) = repeated(&s.values) {
                self.error(line, None, Some("values"), format!("{what}: {msg}"));
            }
            let name_ok = !s.name.is_empty()
                && s.name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_".contains(c));
            if !name_ok {
                self.error(
                    line,
                    None,
                    Some("name"),
                    format!("{what}: `name` must be letters, digits, `-` and `_` (it names a directory)"),
                );
            }
            if names.contains(&s.name.as_str()) {
                self.error(
                    line,
                    None,
                    Some("name"),
                    format!("{what}: two series share this name"),
                );
            }
            names.push(&s.name);
            if !key_ok(&s.key) {
                self.error(
                    line,
                    None,
                    Some("key"),
                    format!("{what}: `key` {}", key_msg(&s.key)),
                );
            }
            if s.values.is_empty() {
                self.error(
                    line,
                    None,
                    Some("values"),
                    format!("{what}: `values` lists no value"),
                );
            }
            for k in s.set.keys() {
                if !key_ok(k) {
                    self.error(
                        line,
                        None,
                        Some("set"),
                        format!("{what}: `set` key {}", key_msg(k)),
                    );
                }
            }
        }
        for id in &sweep.frontier {
            if doc.get("stages").and_then(|s| s.get(id)).is_none() {
                self.error(
                    line,
                    None,
                    Some("frontier"),
                    format!("in [sweep]: `frontier` names `{id}`, which is not a declared stage"),
                );
            }
        }
        self.check_plots(&sweep, line);
        if sweep.repeats == 0 {
            self.error(
                line,
                None,
                Some("repeats"),
                "in [sweep]: `repeats` must be at least 1".into(),
            );
        }
        // Every run of a sweep is loaded (and kept) before any runs, each load
        // parsing the whole file with all its values: cost grows with the
        // square of the sweep (4,000 values took 6.4 s and 1.3 GB to check).
        let points = if sweep.series.is_empty() {
            sweep.values.len()
        } else {
            sweep.series.iter().map(|s| s.values.len()).sum()
        };
        let runs = points.saturating_mul(sweep.repeats);
        if runs > MAX_SWEEP_RUNS {
            self.error(
                line,
                None,
                Some("values"),
                format!(
                    "in [sweep]: {points} values x {} repeats = {runs} runs, over the cap of {MAX_SWEEP_RUNS}; \
                     split the sweep into several files",
                    sweep.repeats
                ),
            );
        }
        Some(sweep)
    }

    /// Checks every `[[sweep.plot]]` against the sweep's points and metrics;
    /// each problem names `sweep.plot[i].<key>`.
    fn check_plots(&mut self, sweep: &SweepSettings, line: Option<usize>) {
        let points = sweep.points();
        let mut files: Vec<&str> = Vec::new();
        for (i, plot) in sweep.plots.iter().enumerate() {
            let diag = |me: &mut Self, severity: Severity, key: &str, msg: String| {
                let key = format!("sweep.plot[{i}].{key}");
                me.diags.push(Diagnostic {
                    severity,
                    file: me.file.clone(),
                    line,
                    stage: None,
                    message: format!("in [sweep]: `{key}` {msg}"),
                    key: Some(key),
                });
            };
            let bad = |me: &mut Self, key: &str, msg: String| diag(me, Severity::Error, key, msg);
            let f = plot.file.as_str();
            let plain = f.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
            if !plain || f.len() <= 4 || !f.ends_with(".svg") || f.starts_with('.') {
                bad(
                    self,
                    "file",
                    format!(
                        "must be a plain file name ending .svg (letters, digits, `-`, `_`, `.`; \
                         it is written into the sweep's output directory), not \"{f}\""
                    ),
                );
            } else if f.starts_with("sweep_") || f.starts_with("frontier_") {
                bad(
                    self,
                    "file",
                    format!("\"{f}\": names starting `sweep_` or `frontier_` are palpate's own plots"),
                );
            } else if files.contains(&f) {
                bad(self, "file", format!("\"{f}\": another plot writes this file"));
            }
            files.push(f);
            if plot.metric.is_empty() {
                bad(self, "metric", "names no metric (e.g. \"wss.mae_deg\")".into());
            } else if !sweep.metrics.is_empty() && !sweep.metrics.contains(&plot.metric) {
                let listed: Vec<String> = sweep.metrics.iter().map(|m| format!("`{m}`")).collect();
                bad(
                    self,
                    "metric",
                    format!(
                        "names `{}`, which is not among the sweep's `metrics` ({})",
                        plot.metric,
                        listed.join(", ")
                    ),
                );
            }
            // Each field must be given by every point (a typo would otherwise
            // leave every point out of the plot, found only after the run).
            let fields = [("x", Some(plot.x_field())), ("by", plot.by.as_deref())];
            for (key, field) in fields {
                let Some(field) = field else { continue };
                if field == "class" {
                    continue;
                }
                if field == "series" && sweep.series.is_empty() {
                    bad(
                        self,
                        key,
                        "is \"series\", but the sweep has no [[sweep.series]] tables".into(),
                    );
                    continue;
                }
                if let Some(p) = points.iter().find(|p| p.field(field).is_none()) {
                    bad(
                        self,
                        key,
                        format!(
                            "names `{field}`, which point `{}` does not give: use \"value\", \"series\", \
                             \"class\" or a key of the points' table values",
                            crate::sweep::point_label(p)
                        ),
                    );
                    continue;
                }
                let numeric = |v: Option<toml::Value>| {
                    matches!(v, Some(toml::Value::Integer(_) | toml::Value::Float(_)))
                };
                if key == "x" && plot.kind == PlotKind::Line {
                    if let Some(p) = points.iter().find(|p| !numeric(p.field(field))) {
                        bad(
                            self,
                            "x",
                            format!(
                                "a line plot needs numbers on x, but `{field}` of point `{}` is not one; \
                                 use kind = \"bars\"",
                                crate::sweep::point_label(p)
                            ),
                        );
                    }
                }
            }
            if plot.by.as_deref() == Some(plot.x_field()) {
                bad(self, "by", "is the same field as `x`".into());
            }
            if plot.by.as_deref() != Some("class") {
                let by = plot.by.as_deref();
                let mut names: Vec<String> = Vec::new();
                for p in &points {
                    let n = plot.default_series_name(by.and_then(|b| p.field(b)).as_ref());
                    if !names.contains(&n) {
                        names.push(n);
                    }
                }
                // A warning, not an error: a `--set` or a cut-down sweep may
                // leave a series out, and its legend name with it.
                for k in plot.legend.keys().filter(|k| !names.contains(k)) {
                    let known: Vec<String> = names.iter().map(|n| format!("\"{n}\"")).collect();
                    diag(
                        self,
                        Severity::Warning,
                        "legend",
                        format!(
                            "renames \"{k}\", which is no series of this plot (its series: {})",
                            known.join(", ")
                        ),
                    );
                }
            }
            for (r, reference) in plot.reference.iter().enumerate() {
                if reference.name.is_empty() {
                    bad(self, &format!("reference[{r}].name"), "is empty".into());
                }
                if reference.points.iter().flatten().any(|v| !v.is_finite()) {
                    bad(
                        self,
                        &format!("reference[{r}].points"),
                        "must hold finite numbers".into(),
                    );
                }
            }
        }
    }

    fn apply_overrides(&mut self, doc: &mut toml::Table, overrides: &[(String, toml::Value)]) {
        for (path, value) in overrides {
            let value = value.clone();
            let parts: Vec<&str> = path.split('.').collect();
            let target = match parts.as_slice() {
                ["stages", id] if value.is_table() => {
                    match doc.get_mut("stages").and_then(|s| s.as_table_mut()) {
                        Some(t) if t.contains_key(*id) => Some((t, vec![*id])),
                        _ => {
                            self.error(
                                None,
                                Some(id),
                                None,
                                format!("`{path}` names a stage the graph does not declare"),
                            );
                            None
                        }
                    }
                }
                ["stages", id, key @ ..] if !key.is_empty() => {
                    match doc
                        .get_mut("stages")
                        .and_then(|s| s.get_mut(*id))
                        .and_then(|s| s.as_table_mut())
                    {
                        Some(t) => Some((t, key.to_vec())),
                        None => {
                            self.error(
                                None,
                                Some(id),
                                None,
                                format!("`{path}` names a stage the graph does not declare"),
                            );
                            None
                        }
                    }
                }
                ["run", key @ ..] if !key.is_empty() => {
                    let run = doc
                        .entry("run")
                        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                    // A protocol is one of several kinds, so a new one
                    // replaces the old rather than merging into it: merged,
                    // `{ k_fold = { k = 5 } }` over a hold-out was two
                    // protocols at once, and one of the same kind kept the
                    // old one's other keys (its seed).
                    run.as_table_mut().map(|t| {
                        if key == ["protocol"] {
                            t.remove("protocol");
                        }
                        (t, key.to_vec())
                    })
                }
                // A graph without a sweep gains one: `--set sweep.repeats=5`
                // runs it over 5 seeds (see `load_sweep`).
                ["sweep", key @ ..] if !key.is_empty() => doc
                    .entry("sweep")
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                    .as_table_mut()
                    .map(|t| (t, key.to_vec())),
                _ => {
                    self.error(
                        None,
                        None,
                        None,
                        format!(
                            "override `{path}`: the path must be stages.<id>.<key>, run.<key> or sweep.<key>"
                        ),
                    );
                    None
                }
            };
            if let Some((table, keys)) = target {
                set_path(table, &keys, value);
            }
        }
    }

    fn load_run(&mut self, value: Option<&toml::Value>, lines: &Lines) -> RunSettings {
        let Some(value) = value else {
            return RunSettings::default();
        };
        match serde_path_to_error::deserialize::<_, RunSettings>(value.clone()) {
            Ok(r) => {
                // The protocol's values (k, test_share, an empty key) are
                // checked here, so `palpate check` reports them, not only
                // the run that reaches the first trained estimator.
                if let Err(msg) = r.protocol.check() {
                    let line = lines
                        .run
                        .get("protocol")
                        .copied()
                        .or(lines.top.get("run").copied());
                    self.error(line, None, Some("protocol"), format!("in [run]: {msg}"));
                }
                r
            }
            Err(e) => {
                let key = e
                    .path()
                    .iter()
                    .next()
                    .map(|s| s.to_string())
                    .or_else(|| unknown_field(e.inner().message()));
                let line = key
                    .as_ref()
                    .and_then(|k| lines.run.get(k))
                    .copied()
                    .or(lines.top.get("run").copied());
                let msg = format!("in [run]: {}", first_line(e.inner().message()));
                self.error(line, None, key.as_deref(), msg);
                RunSettings::default()
            }
        }
    }

    fn load_stage(
        &mut self,
        id: &str,
        value: &toml::Value,
        lines: &Lines,
        run: &RunSettings,
        out_dir: &Path,
        base_dir: &Path,
    ) -> Option<Pending> {
        let line = lines.stages.get(id).copied();
        let key_line = |k: &str| lines.keys.get(&(id.to_string(), k.to_string())).copied().or(line);
        if id.is_empty()
            || !id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            self.error(
                line,
                Some(id),
                None,
                "a stage id may hold only letters, digits, `_` and `-`".into(),
            );
        }
        if let Some(r) = RESERVED_STAGE_IDS.iter().find(|r| r.eq_ignore_ascii_case(id)) {
            self.error(
                line,
                Some(id),
                None,
                format!(
                    "`{r}` is reserved: a sink's reports are named after its id, and the run writes                      its own {r}.* files beside them (rename the stage)"
                ),
            );
        }
        let Some(table) = value.as_table() else {
            self.error(
                line,
                Some(id),
                None,
                "a stage must be a table with at least a `type` key".into(),
            );
            return None;
        };
        let type_name = match table.get("type") {
            None => {
                self.error(
                    line,
                    Some(id),
                    Some("type"),
                    "missing key `type`: which kind of stage this is".into(),
                );
                return None;
            }
            Some(toml::Value::String(s)) => s.clone(),
            Some(other) => {
                self.error(
                    key_line("type"),
                    Some(id),
                    Some("type"),
                    format!("`type` must be a string, got {}", other.type_str()),
                );
                return None;
            }
        };
        // A type defined at run time (a Python stage) stands for a table of a
        // registered type.
        let aliased;
        let (type_name, table) = match registry::find(&type_name) {
            Some(_) => (type_name, table),
            None => match registry::rewrite_alias(&type_name, table) {
                Some((target, t)) => {
                    aliased = t;
                    (target, &aliased)
                }
                None => (type_name, table),
            },
        };
        let Some(reg) = registry::find(&type_name) else {
            let close = registry::close_matches(&type_name);
            let hint = if close.is_empty() {
                "; `palpate stages` lists every type".to_string()
            } else {
                format!(
                    "; did you mean {}?",
                    close
                        .iter()
                        .map(|c| format!("`{c}`"))
                        .collect::<Vec<_>>()
                        .join(" or ")
                )
            };
            self.error(
                key_line("type"),
                Some(id),
                Some("type"),
                format!("unknown stage type `{type_name}`{hint}"),
            );
            return None;
        };
        let inputs: Vec<String> = match table.get("inputs") {
            None => Vec::new(),
            Some(toml::Value::Array(a)) => {
                let mut v = Vec::new();
                for x in a {
                    match x.as_str() {
                        Some(s) => v.push(s.to_string()),
                        None => self.error(
                            key_line("inputs"),
                            Some(id),
                            Some("inputs"),
                            format!("`inputs` must list stage ids as strings, got {}", x.type_str()),
                        ),
                    }
                }
                v
            }
            Some(other) => {
                self.error(
                    key_line("inputs"),
                    Some(id),
                    Some("inputs"),
                    format!("`inputs` must be an array of stage ids, got {}", other.type_str()),
                );
                Vec::new()
            }
        };

        // Keys against the schema: every unknown and missing key at once.
        let doc = registry::stage_doc(reg);
        let known = doc.key_names();
        let mut keys_ok = true;
        for key in table.keys() {
            if key == "type" || key == "inputs" || known.contains(&key.as_str()) {
                continue;
            }
            keys_ok = false;
            let close: Vec<&str> = known
                .iter()
                .copied()
                .filter(|k| registry::is_close(key, k))
                .collect();
            let hint = match close.first() {
                Some(c) => format!("; did you mean `{c}`?"),
                None if known.is_empty() => "; this type has no keys".to_string(),
                None => format!(
                    "; its keys are {}",
                    known
                        .iter()
                        .map(|k| format!("`{k}`"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            };
            self.error(
                key_line(key),
                Some(id),
                Some(key),
                format!("unknown key `{key}` for type `{type_name}`{hint}"),
            );
        }
        for k in &doc.keys {
            if k.default.is_none() && !table.contains_key(&k.name) {
                keys_ok = false;
                self.error(
                    line,
                    Some(id),
                    Some(&k.name),
                    format!(
                        "missing key `{}` ({})",
                        k.name,
                        k.doc.lines().next().unwrap_or("")
                    ),
                );
            }
        }
        if !keys_ok {
            return None;
        }

        // The config as typetag reads it: `{ <type> = { keys but type and inputs } }`.
        let tagged = || {
            let mut inner = table.clone();
            inner.remove("type");
            inner.remove("inputs");
            toml::Table::from_iter([(type_name.clone(), toml::Value::Table(inner))])
        };
        let config: Box<dyn StageConfig> =
            match serde_path_to_error::deserialize(toml::Value::Table(tagged())) {
                Ok(c) => c,
                Err(e) => {
                    let segments: Vec<serde_path_to_error::Segment> = e.path().iter().cloned().collect();
                    // Keys joined by dots, indices appended as written in TOML
                    // paths elsewhere in the messages: `effects[0].kind`.
                    let mut path = String::new();
                    for seg in e.path().iter().skip(1) {
                        let seg = seg.to_string();
                        if !path.is_empty() && !seg.starts_with('[') {
                            path.push('.');
                        }
                        path.push_str(&seg);
                    }
                    let key = if path.is_empty() {
                        unknown_field(e.inner().message())
                    } else {
                        Some(path)
                    };
                    let first = key
                        .as_deref()
                        .map(|k| k.split(['.', '[']).next().unwrap_or(k).to_string());
                    let l = first.as_deref().map(key_line).unwrap_or(line);
                    let text = first_line(e.inner().message()).to_string();
                    let text = if text.starts_with("invalid type: unit variant")
                        || (text.starts_with("invalid type:")
                            && text.ends_with("expected variant identifier"))
                    {
                        names_expected(&tagged(), &segments).unwrap_or(text)
                    } else if text.starts_with("data did not match any variant of untagged enum") {
                        angles_expected(&tagged(), &segments).unwrap_or(text)
                    } else {
                        too_large_integer(&text).unwrap_or(text)
                    };
                    let msg = match &key {
                        Some(k) => format!("key `{k}`: {text}"),
                        None => text,
                    };
                    self.error(l, Some(id), key.as_deref(), msg);
                    return None;
                }
            };
        let ctx = BuildContext {
            stage_id: id.to_string(),
            seed: run.seed,
            out_dir: out_dir.to_path_buf(),
            base_dir: base_dir.to_path_buf(),
        };
        let stage = match config.build(&ctx) {
            Ok(stage) => Some(stage),
            Err(e) => {
                self.config_problems(Severity::Error, &e, id, lines);
                None
            }
        };
        Some(Pending {
            id: id.to_string(),
            type_name,
            inputs,
            config,
            stage,
            line,
        })
    }

    /// One diagnostic per problem a config reported, each at its key's line.
    fn config_problems(&mut self, severity: Severity, e: &ConfigError, id: &str, lines: &Lines) {
        for (key, message) in e.problems() {
            // The longest prefix of the key's path that has a line of its
            // own (`a.b[2].c` tries `a.b[2].c`, `a.b`, `a`).
            let line = key
                .and_then(|k| {
                    let cuts = k.match_indices(['.', '[']).map(|(i, _)| i).rev();
                    std::iter::once(k.len())
                        .chain(cuts)
                        .find_map(|i| lines.keys.get(&(id.to_string(), k[..i].to_string())))
                })
                .or_else(|| lines.stages.get(id))
                .copied();
            self.diags.push(Diagnostic {
                severity,
                file: self.file.clone(),
                line,
                stage: Some(id.to_string()),
                key: key.map(str::to_string),
                message: match key {
                    Some(k) => format!("key `{k}`: {message}"),
                    None => message.to_string(),
                },
            });
        }
    }

    /// Runs every stage's [`StageConfig::inspect`] in data-flow order, each
    /// with what is known of its inputs (their sample rate, ...), and reports
    /// its errors and warnings.
    fn inspect(
        &mut self,
        nodes: &[Pending],
        order: &[usize],
        input_index: &[Vec<usize>],
        ctx: &BuildContext,
        lines: &Lines,
    ) {
        let mut facts: Vec<OutputFacts> = vec![OutputFacts::default(); nodes.len()];
        for &i in order {
            let n = &nodes[i];
            let inputs: Vec<OutputFacts> = input_index[i].iter().map(|&j| facts[j].clone()).collect();
            let ctx = BuildContext {
                stage_id: n.id.clone(),
                ..ctx.clone()
            };
            let found = n.config.inspect(&ctx, &inputs);
            for (severity, list) in [
                (Severity::Error, &found.errors),
                (Severity::Warning, &found.warnings),
            ] {
                if let Some(e) = ConfigError::join(list.clone()) {
                    self.config_problems(severity, &e, &n.id, lines);
                }
            }
            facts[i] = found.facts;
        }
    }

    /// `[sweep] frontier`: each id must be an estimator that a sink scoring
    /// estimates ([`crate::stage::Sink::scores_estimates`], e.g. `mae`) reads, since the
    /// frontier's rows are that sink's metrics. (Ids that name no stage were
    /// reported by `load_sweep`; stages whose build failed were reported too.)
    fn check_frontier(&mut self, sweep: &SweepSettings, nodes: &[Pending], lines: &Lines) {
        let line = lines.top.get("sweep").copied();
        for id in &sweep.frontier {
            let Some(node) = nodes.iter().find(|n| &n.id == id) else {
                continue;
            };
            let Some(stage) = &node.stage else {
                continue;
            };
            if !matches!(stage, Stage::Estimator(_)) {
                self.error(
                    line,
                    None,
                    Some("frontier"),
                    format!(
                        "in [sweep]: `frontier` names `{id}`, a {} stage ({}), not an estimator",
                        stage.role(),
                        node.type_name
                    ),
                );
                continue;
            }
            let scored = nodes.iter().any(|n| {
                matches!(&n.stage, Some(Stage::Sink(s)) if s.scores_estimates()) && n.inputs.contains(id)
            });
            if !scored {
                self.error(
                    line,
                    None,
                    Some("frontier"),
                    format!(
                        "in [sweep]: `frontier` names estimator `{id}`, which feeds no sink that scores \
                         estimates; add it to an `mae` sink's inputs"
                    ),
                );
            }
        }
    }

    /// Checks edges, kinds, cycles and sources. Returns (topological order, input indices).
    fn check_graph(
        &mut self,
        nodes: &[Pending],
        lines: &Lines,
        declared: Vec<String>,
        referenced: &[String],
    ) -> (Vec<usize>, Vec<Vec<usize>>) {
        let index: HashMap<&str, usize> = nodes
            .iter()
            .enumerate()
            .map(|(i, n)| (n.id.as_str(), i))
            .collect();
        let mut g: DiGraph<usize, ()> = DiGraph::new();
        let ids: Vec<NodeIndex> = (0..nodes.len()).map(|i| g.add_node(i)).collect();
        let mut input_index = vec![Vec::new(); nodes.len()];
        let mut read = vec![false; nodes.len()];

        for (i, n) in nodes.iter().enumerate() {
            let spec: InputSpec = n.config.inputs();
            let inputs_line = lines
                .keys
                .get(&(n.id.clone(), "inputs".to_string()))
                .copied()
                .or(n.line);
            if spec.max == Some(0) && !n.inputs.is_empty() {
                self.error(
                    inputs_line,
                    Some(&n.id),
                    Some("inputs"),
                    format!("`{}` is a source and takes no inputs", n.type_name),
                );
                continue;
            }
            if n.inputs.len() < spec.min || spec.max.is_some_and(|m| n.inputs.len() > m) {
                let want = match spec.max {
                    Some(m) if m == spec.min => format!("exactly {m}"),
                    Some(m) => format!("{} to {m}", spec.min),
                    None => format!("at least {}", spec.min),
                };
                self.error(
                    inputs_line,
                    Some(&n.id),
                    Some("inputs"),
                    format!(
                        "`{}` takes {want} input(s) of {}, got {}",
                        n.type_name,
                        spec.describe_kinds(),
                        n.inputs.len()
                    ),
                );
            }
            for input in &n.inputs {
                let Some(&j) = index.get(input.as_str()) else {
                    if declared.contains(input) {
                        continue; // declared but failed to load: already reported
                    }
                    let close: Vec<String> = nodes
                        .iter()
                        .map(|m| m.id.clone())
                        .chain(declared.iter().cloned())
                        .filter(|m| registry::is_close(input, m))
                        .take(1)
                        .collect();
                    let hint = close
                        .first()
                        .map(|c| format!("; did you mean `{c}`?"))
                        .unwrap_or_default();
                    self.error(
                        inputs_line,
                        Some(&n.id),
                        Some("inputs"),
                        format!("unknown input `{input}`: no stage has that id{hint}"),
                    );
                    continue;
                };
                read[j] = true;
                input_index[i].push(j);
                g.add_edge(ids[j], ids[i], ());
                match nodes[j].config.output() {
                    None => self.error(
                        inputs_line,
                        Some(&n.id),
                        Some("inputs"),
                        format!("input `{}` is a sink and gives nothing to read", nodes[j].id),
                    ),
                    Some(kind) if !spec.kinds.contains(&kind) => self.error(
                        inputs_line,
                        Some(&n.id),
                        Some("inputs"),
                        format!(
                            "stage `{}` takes {} but `{}` gives {}",
                            n.id,
                            spec.describe_kinds(),
                            nodes[j].id,
                            kind
                        ),
                    ),
                    Some(_) => {}
                }
            }
        }

        for scc in petgraph::algo::tarjan_scc(&g) {
            let is_cycle = scc.len() > 1 || g.contains_edge(scc[0], scc[0]);
            if is_cycle {
                let mut members: Vec<usize> = scc.iter().map(|&ix| g[ix]).collect();
                members.sort_unstable();
                let names: Vec<String> = members.iter().map(|&m| format!("`{}`", nodes[m].id)).collect();
                let first = &nodes[members[0]];
                self.error(
                    first.line,
                    Some(&first.id),
                    Some("inputs"),
                    format!(
                        "cycle through stages {}: data must flow one way",
                        names.join(" -> ")
                    ),
                );
            }
        }

        // Only when every declared stage loaded can we tell there is no source.
        let has_source = nodes.iter().any(|n| n.config.inputs().max == Some(0));
        if !has_source && !nodes.is_empty() && nodes.len() == declared.len() {
            self.error(
                None,
                None,
                None,
                "the graph has no source stage (a scene, file or DAQ source)".into(),
            );
        }

        for (i, n) in nodes.iter().enumerate() {
            // A stage that failed to load still reads its inputs: no false warning.
            if !read[i] && !referenced.contains(&n.id) && n.config.output().is_some() {
                self.diags.push(Diagnostic {
                    severity: Severity::Warning,
                    file: self.file.clone(),
                    line: n.line,
                    stage: Some(n.id.clone()),
                    key: None,
                    message: format!(
                        "the output of `{}` ({}) is read by no stage",
                        n.id,
                        n.config.output().map(|k| k.to_string()).unwrap_or_default()
                    ),
                });
            }
        }

        let order = match petgraph::algo::toposort(&g, None) {
            Ok(o) => o.into_iter().map(|ix| g[ix]).collect(),
            Err(_) => Vec::new(),
        };
        (order, input_index)
    }
}

/// A better message for a choice key given a value that is not a string
/// (`weighting = 3.5`, `kind = 3`), where serde's TOML deserializer says
/// only "invalid type: unit variant, expected string only" (or "expected
/// variant identifier"), naming neither the value nor the choices: the config is deserialized
/// again with a string no choice has at that `path`, whose "unknown
/// variant" error lists the choices. `None` when that does not work out.
fn names_expected(tagged: &toml::Table, path: &[serde_path_to_error::Segment]) -> Option<String> {
    use serde_path_to_error::Segment;
    const PROBE: &str = "\u{1}";
    let mut probe = toml::Value::Table(tagged.clone());
    let mut at = &mut probe;
    for seg in path {
        at = match (seg, at) {
            (Segment::Map { key }, toml::Value::Table(t)) => t.get_mut(key)?,
            (Segment::Seq { index }, toml::Value::Array(a)) => a.get_mut(*index)?,
            _ => return None,
        };
    }
    let given = at.to_string();
    *at = toml::Value::String(PROBE.into());
    let e = serde_path_to_error::deserialize::<_, Box<dyn StageConfig>>(probe).err()?;
    let m = first_line(e.inner().message()).to_string();
    let (_, choices) = m.split_once(&format!("unknown variant `{PROBE}`, "))?;
    Some(format!("{given} is not a choice: {choices} (a string)"))
}

/// The value at `path` in `tagged` (`None` when the path leads nowhere).
fn value_at<'a>(tagged: &'a toml::Table, path: &[serde_path_to_error::Segment]) -> Option<&'a toml::Value> {
    use serde_path_to_error::Segment;
    let mut at: Option<&toml::Value> = None;
    for seg in path {
        let next = match (seg, at) {
            (Segment::Map { key }, None) => tagged.get(key),
            (Segment::Map { key }, Some(toml::Value::Table(t))) => t.get(key),
            (Segment::Seq { index }, Some(toml::Value::Array(a))) => a.get(*index),
            _ => None,
        };
        at = Some(next?);
    }
    at
}

/// A better message for an angle key (`angles` of `scene` and `wss`, a list
/// or a `{ from, to, step }` range) given neither form, where serde says
/// only "data did not match any variant of untagged enum Angles": the forms,
/// and the first element that is not a number.
fn angles_expected(tagged: &toml::Table, path: &[serde_path_to_error::Segment]) -> Option<String> {
    let forms = "expected a list of angles in degrees (`[30, 45, 60]`) or a range (`{ from = 10, to = 90, step = 5 }`)";
    let v = value_at(tagged, path)?;
    let number = |x: &toml::Value| x.is_integer() || x.is_float();
    Some(match v {
        toml::Value::Array(items) => match items.iter().enumerate().find(|(_, x)| !number(x)) {
            Some((i, x)) => format!("{forms}; element [{i}] is {x}, a {}, not a number", x.type_str()),
            None => forms.to_string(),
        },
        toml::Value::Table(t) => match t.iter().find(|(_, x)| !number(x)) {
            Some((k, x)) => format!("{forms}; `{k}` is {x}, a {}, not a number", x.type_str()),
            None => format!("{forms}; a range takes only `from`, `to` and `step`"),
        },
        other => format!("{forms}, got {other}, a {}", other.type_str()),
    })
}

/// A better message for a whole number beyond TOML's integers: `--set k=<digits>`
/// and a value the TOML parser cannot hold become strings, and serde then
/// says "invalid type: string \"99999999999999999999\", expected usize".
fn too_large_integer(text: &str) -> Option<String> {
    let rest = text.strip_prefix("invalid type: string \"")?;
    let (digits, expected) = rest.split_once("\", expected ")?;
    let plain = digits.strip_prefix('-').unwrap_or(digits);
    if plain.is_empty() || !plain.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let expected = match expected {
        "usize" | "u64" | "u32" | "u16" | "u8" => "a whole number from 0",
        "isize" | "i64" | "i32" | "i16" | "i8" => "a whole number",
        "f64" | "f32" => "a number",
        other => other,
    };
    Some(format!(
        "{digits} is out of range: TOML's whole numbers go from -9223372036854775808 to \
         9223372036854775807 (this key takes {expected})"
    ))
}

/// toml's messages append a location ("in `key`") after a blank line; we give our own.
fn first_line(message: &str) -> &str {
    message.lines().next().unwrap_or(message).trim_end()
}

/// Every id named in any declared stage's `inputs`, loaded or not.
fn inputs_declared(doc: &toml::Table) -> Vec<String> {
    let Some(stages) = doc.get("stages").and_then(|s| s.as_table()) else {
        return Vec::new();
    };
    stages
        .values()
        .filter_map(|st| st.get("inputs").and_then(|i| i.as_array()))
        .flatten()
        .filter_map(|v| v.as_str().map(str::to_string))
        .collect()
}

fn stages_declared(doc: &toml::Table) -> Vec<String> {
    doc.get("stages")
        .and_then(|s| s.as_table())
        .map(|t| t.keys().cloned().collect())
        .unwrap_or_default()
}

/// serde reports an unknown field at the struct's level; take its name from the message.
fn unknown_field(message: &str) -> Option<String> {
    let rest = message
        .strip_prefix("unknown field `")
        .or_else(|| message.strip_prefix("missing field `"))?;
    rest.split('`').next().map(str::to_string)
}

/// Parses a TOML value from text; text that is not a TOML value is a string.
pub fn parse_value(raw: &str) -> toml::Value {
    match toml::from_str::<toml::Table>(&format!("v = {raw}")) {
        Ok(mut t) => t
            .remove("v")
            .unwrap_or_else(|| toml::Value::String(raw.to_string())),
        Err(_) => toml::Value::String(raw.to_string()),
    }
}

/// Sets `keys` to `value`; a table value is merged into an existing table.
fn set_path(table: &mut toml::Table, keys: &[&str], value: toml::Value) {
    match keys {
        [] => {}
        [last] => match (table.get_mut(*last), value) {
            (Some(toml::Value::Table(existing)), toml::Value::Table(new)) => {
                for (k, v) in new {
                    set_path(existing, &[k.as_str()], v);
                }
            }
            (_, value) => {
                table.insert((*last).to_string(), value);
            }
        },
        [first, rest @ ..] => {
            let entry = table
                .entry((*first).to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            if !entry.is_table() {
                *entry = toml::Value::Table(toml::Table::new());
            }
            if let Some(t) = entry.as_table_mut() {
                set_path(t, rest, value);
            }
        }
    }
}
