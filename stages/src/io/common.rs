//! Helpers shared by the file sources and sinks: the taxel-layout key, path
//! expansion (globs and lists), trial ids, label sidecars and the assignment of
//! cross-validation groups.
//!
//! ## Label sidecars
//!
//! A sidecar maps trial ids to labels; it is a small TOML or CSV file (chosen by
//! its extension), or the `trials.json` that `palpate simulate` writes (its
//! trials' `trial_id`, `label.angle_deg`, `label.stimulus` and `group`). Every trial the files hold must appear in it, and every entry
//! must name a trial the files hold (a typo would otherwise silently unlabel a
//! trial).
//!
//! TOML:
//!
//! ```toml
//! [trials.rec01]
//! angle_deg = 45.0        # optional
//! stimulus = "edge"       # optional: edge | ridge | unknown
//! group = 0               # optional: the cross-validation key
//! duration_ms = 9500.0    # optional; spike files only: the trial's length
//! ```
//!
//! CSV: a header row with `trial` and any of `angle_deg`, `stimulus`, `group`,
//! `duration_ms`; one row per trial; an empty cell means "not given".
//!
//! ## Label angles
//!
//! An `angle_deg` label, wherever it is read (a sidecar, a data file's column,
//! an NPZ or MAT `angle_deg` array, a `trials.json`), must lie strictly
//! between 0 and 180 degrees ([`check_label_angle`]): the rule the scene's
//! `angles` and WSS's class grid (10 to 170 by default) follow. 0 and 180 are
//! parallel to the motion and never crossed, and an angle outside the range
//! (400, -30, 1e300) names no edge an estimator could answer: it would be
//! scored as an error of hundreds of degrees, or an infinite one. Such a
//! label is an error naming the file and the trial (and the line, for CSV).
//!
//! ## The array's layout
//!
//! A TOML sidecar may also declare the taxel layout the files were recorded
//! with, in a `[layout]` table with the keys of a stage's `layout` key
//! (`kind = "grid"`, `rows`, `cols`, `pitch_mm`, `taxel_mm`, or `kind =
//! "positions"`, `positions_mm`, `taxel_mm`); a `trials.json` declares it in
//! its `layout` entry. `palpate simulate`, `write_signals` and `write_spikes`
//! write it, so files of a 3 x 3 array read back as a 3 x 3 array without a
//! second key. Which layout a file source uses ([`resolve_layout`]): its
//! `layout` key when set (a sidecar that declares another layout is then an
//! error naming both, not a silent choice), else the sidecar's, else the
//! paper's 4 x 4 grid.
//!
//! ## Precedence and groups
//!
//! A sidecar value wins over a value read from the data file. A trial with an
//! angle but no stimulus is an `edge`; one with neither is `unknown`. When no
//! `group` is given, a trial's group is its repetition number within its class
//! (same stimulus and angle), counted in trial order from 0, which is what
//! leave-one-trial-out cross-validation needs for recordings made as "10 trials
//! per angle".

use palpate_core::{ConfigError, Label, StageError, Stimulus, TaxelLayout, TrialMeta};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// Where the taxels are: a grid, or an explicit list of positions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum LayoutConfig {
    /// A `rows x cols` grid centred on the origin, row 0 on top; taxel `i` is row
    /// `i / cols`, column `i % cols`.
    Grid {
        /// Rows (along y).
        rows: usize,
        /// Columns (along x, the sliding direction).
        cols: usize,
        /// Centre-to-centre spacing, mm.
        pitch_mm: f64,
        /// Side of a square taxel, mm.
        taxel_mm: f64,
    },
    /// Explicit taxel centres `[x, y]` in mm, for skins that are not grids.
    Positions {
        /// Taxel centres `[x, y]`, mm, in taxel order.
        positions_mm: Vec<[f64; 2]>,
        /// Side of a square taxel, mm.
        taxel_mm: f64,
    },
}

/// Reads a source's `layout` key: a [`LayoutConfig`] whose `kind` may be
/// left out when its keys say it (`positions_mm`: positions; `rows` or
/// `cols`: a grid), as a scene's `layout` is written. Used with
/// `#[serde(default, deserialize_with = "...")]` on the sources' fields.
pub fn layout_with_inferred_kind<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<LayoutConfig>, D::Error> {
    use serde::de::Error;
    let mut v = serde_json::Value::deserialize(d)?;
    if let Some(m) = v.as_object_mut() {
        if !m.contains_key("kind") {
            let kind = if m.contains_key("positions_mm") {
                "positions"
            } else if m.contains_key("rows") || m.contains_key("cols") {
                "grid"
            } else {
                return Err(D::Error::custom(
                    "a layout needs `kind` (\"grid\" with rows, cols, pitch_mm, taxel_mm; \
                     or \"positions\" with positions_mm, taxel_mm)",
                ));
            };
            m.insert("kind".into(), kind.into());
        }
    }
    LayoutConfig::deserialize(v).map(Some).map_err(D::Error::custom)
}

/// The JSON schema of a source's `layout` key as [`layout_with_inferred_kind`]
/// reads it: [`LayoutConfig`]'s, with `kind` optional in each variant (the
/// variants' other required keys and `additionalProperties = false` still
/// tell them apart), so an editor checking a graph against
/// `graphs/palpate-graph.schema.json` accepts the layouts the sources accept.
/// Used with `#[schemars(schema_with = "...")]` on the sources' fields.
pub fn layout_schema_kind_optional(g: &mut schemars::SchemaGenerator) -> schemars::Schema {
    let mut schema = <LayoutConfig as JsonSchema>::json_schema(g);
    if let Some(variants) = schema.get_mut("oneOf").and_then(|v| v.as_array_mut()) {
        for v in variants {
            if let Some(req) = v.get_mut("required").and_then(|r| r.as_array_mut()) {
                req.retain(|k| k != "kind");
            }
        }
    }
    schema
}

impl Default for LayoutConfig {
    fn default() -> Self {
        LayoutConfig::Grid {
            rows: 4,
            cols: 4,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        }
    }
}

impl From<&TaxelLayout> for LayoutConfig {
    /// The key that describes `l` (the same fields).
    fn from(l: &TaxelLayout) -> Self {
        match l.clone() {
            TaxelLayout::Grid {
                rows,
                cols,
                pitch_mm,
                taxel_mm,
            } => LayoutConfig::Grid {
                rows,
                cols,
                pitch_mm,
                taxel_mm,
            },
            TaxelLayout::Positions {
                positions_mm,
                taxel_mm,
            } => LayoutConfig::Positions {
                positions_mm,
                taxel_mm,
            },
        }
    }
}

/// The array a source's `layout` key states, for [`OutputFacts::layout`]
/// (`None` when unset or invalid: `build` reports an invalid one).
///
/// [`OutputFacts::layout`]: palpate_core::OutputFacts
pub fn stated_layout(layout: &Option<LayoutConfig>) -> Option<TaxelLayout> {
    layout.as_ref().and_then(|l| l.to_layout("layout").ok())
}

/// The inspection of a file source whose only fact known before the run is
/// the array its `layout` key states.
pub fn layout_inspection(layout: &Option<LayoutConfig>) -> palpate_core::Inspection {
    palpate_core::Inspection {
        facts: palpate_core::OutputFacts {
            layout: stated_layout(layout),
            ..palpate_core::OutputFacts::default()
        },
        ..palpate_core::Inspection::default()
    }
}

impl LayoutConfig {
    /// The checked layout, or an error naming `key`.
    pub fn to_layout(&self, key: &str) -> Result<TaxelLayout, ConfigError> {
        let l = match self.clone() {
            LayoutConfig::Grid {
                rows,
                cols,
                pitch_mm,
                taxel_mm,
            } => TaxelLayout::Grid {
                rows,
                cols,
                pitch_mm,
                taxel_mm,
            },
            LayoutConfig::Positions {
                positions_mm,
                taxel_mm,
            } => TaxelLayout::Positions {
                positions_mm,
                taxel_mm,
            },
        };
        l.validate().map_err(|m| ConfigError::key(key, m))?;
        Ok(l)
    }
}

/// `Ok` when `p` is a regular file; else an error on `key` saying what it is:
/// missing, a folder (with the glob that lists its files), or a device,
/// pipe or socket. Why the last: files are read whole, and `/dev/zero`
/// would never end.
pub fn check_regular_file(p: &Path, key: &str) -> Result<(), ConfigError> {
    if p.is_file() {
        Ok(())
    } else if p.is_dir() {
        Err(ConfigError::key(
            key,
            format!(
                "{} is a folder: give its files, e.g. the pattern `{}`",
                p.display(),
                p.join("*.csv").display()
            ),
        ))
    } else if p.exists() {
        Err(ConfigError::key(
            key,
            format!(
                "{} is not a regular file (a device, pipe or socket?)",
                p.display()
            ),
        ))
    } else {
        Err(ConfigError::key(key, format!("file {} not found", p.display())))
    }
}

/// Expands a list of paths, each resolved against the graph's directory; an
/// entry with a glob metacharacter (`*`, `?`, `[`) is a pattern whose matches are
/// taken in sorted order. Every literal path must exist, every pattern must match.
pub fn expand_paths(
    entries: &[String],
    resolve: impl Fn(&Path) -> PathBuf,
    key: &str,
) -> Result<Vec<PathBuf>, ConfigError> {
    if entries.is_empty() {
        return Err(ConfigError::key(key, "give at least one file or glob pattern"));
    }
    let mut out = Vec::new();
    for e in entries {
        let p = resolve(Path::new(e));
        if e.contains(['*', '?', '[']) {
            let pattern = p.to_string_lossy().into_owned();
            let matches = glob::glob(&pattern)
                .map_err(|err| ConfigError::key(key, format!("bad glob pattern `{e}`: {err}")))?;
            let mut found: Vec<PathBuf> = matches.filter_map(Result::ok).filter(|p| p.is_file()).collect();
            if found.is_empty() {
                return Err(ConfigError::key(
                    key,
                    format!("pattern `{pattern}` matched no file"),
                ));
            }
            found.sort();
            out.extend(found);
        } else {
            check_regular_file(&p, key)?;
            out.push(p);
        }
    }
    let mut seen = std::collections::HashSet::new();
    out.retain(|p| seen.insert(p.clone()));
    Ok(out)
}

/// A short, unique name for each file: its stem, or, when two files share a
/// stem, its path relative to the files' common directory without extension
/// (`/` replaced by `_`, so the name is still a file name).
pub fn file_ids(paths: &[PathBuf]) -> Vec<String> {
    let stems: Vec<String> = paths
        .iter()
        .map(|p| {
            p.file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default()
        })
        .collect();
    let mut counts: HashMap<&str, usize> = HashMap::new();
    for s in &stems {
        *counts.entry(s.as_str()).or_default() += 1;
    }
    if counts.values().all(|&c| c == 1) {
        return stems;
    }
    let common = common_dir(paths);
    paths
        .iter()
        .map(|p| {
            let rel = p.strip_prefix(&common).unwrap_or(p).with_extension("");
            rel.to_string_lossy().replace(['/', '\\'], "_")
        })
        .collect()
}

fn common_dir(paths: &[PathBuf]) -> PathBuf {
    let mut common: Option<PathBuf> = None;
    for p in paths {
        let dir = p.parent().map(Path::to_path_buf).unwrap_or_default();
        common = Some(match common {
            None => dir,
            Some(c) => c
                .components()
                .zip(dir.components())
                .take_while(|(a, b)| a == b)
                .map(|(a, _)| a)
                .collect(),
        });
    }
    common.unwrap_or_default()
}

/// Turns a trial id into a safe file stem: characters other than ASCII
/// letters, digits, `.`, `-` and `_` become `_`.
pub fn file_stem_for(trial_id: &str) -> String {
    let s: String = trial_id
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if s.is_empty() || s.starts_with('.') {
        format!("trial{s}")
    } else {
        s
    }
}

/// Labels of one trial as read from a file or a sidecar; `None` = not given.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrialLabels {
    /// True edge orientation, degrees.
    pub angle_deg: Option<f64>,
    /// Stimulus kind.
    #[serde(default, deserialize_with = "de_stimulus")]
    pub stimulus: Option<Stimulus>,
    /// Cross-validation key.
    pub group: Option<usize>,
    /// Trial length, ms (spike files).
    pub duration_ms: Option<f64>,
    /// The commanded sliding speed, mm/s (what WSS builds its templates for
    /// when its config sets no `speed_mm_s`). A condition `speed_mm_s` that
    /// reads as a number gives it too, when this key is absent.
    pub speed_mm_s: Option<f64>,
    /// Conditions the trial was recorded under (`conditions = { speed_mm_s =
    /// 1.5, skin = "thick" }`: strings, numbers or booleans), which the
    /// `leave_one_condition_out` and `train_test` protocols split on.
    #[serde(default, deserialize_with = "de_conditions")]
    pub conditions: BTreeMap<String, String>,
    /// When the edge first and last touched the array, `[first, last]` in ms
    /// from the trial's start (a simulated scene knows it; `palpate
    /// simulate`'s `trials.json` carries it). The `mae` sink counts decision
    /// times from the first, so trials read back from files are timed as
    /// the scene's were. Default none: timed from the trial's start.
    pub crossing_ms: Option<[f64; 2]>,
}

fn de_conditions<'de, D: serde::Deserializer<'de>>(d: D) -> Result<BTreeMap<String, String>, D::Error> {
    let raw = BTreeMap::<String, serde_json::Value>::deserialize(d)?;
    raw.into_iter()
        .map(|(k, v)| {
            let s = match v {
                serde_json::Value::String(s) => s,
                serde_json::Value::Number(n) => n.to_string(),
                serde_json::Value::Bool(b) => b.to_string(),
                other => {
                    return Err(serde::de::Error::custom(format!(
                        "condition `{k}` must be a string, number or boolean, got {other}"
                    )))
                }
            };
            Ok((k, s))
        })
        .collect()
}

fn de_stimulus<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Stimulus>, D::Error> {
    let s = String::deserialize(d)?;
    parse_stimulus(&s).map(Some).map_err(serde::de::Error::custom)
}

impl TrialLabels {
    /// `self` with every value `other` gives replacing this one.
    pub fn overridden_by(&self, other: &TrialLabels) -> TrialLabels {
        TrialLabels {
            angle_deg: other.angle_deg.or(self.angle_deg),
            stimulus: other.stimulus.or(self.stimulus),
            group: other.group.or(self.group),
            duration_ms: other.duration_ms.or(self.duration_ms),
            speed_mm_s: other.speed_mm_s.or(self.speed_mm_s),
            crossing_ms: other.crossing_ms.or(self.crossing_ms),
            conditions: {
                let mut c = self.conditions.clone();
                c.extend(other.conditions.clone());
                c
            },
        }
    }

    /// The label these values give (see the module docs for defaults).
    pub fn label(&self) -> Label {
        Label {
            stimulus: self.stimulus.unwrap_or(if self.angle_deg.is_some() {
                Stimulus::Edge
            } else {
                Stimulus::Unknown
            }),
            angle_deg: self.angle_deg,
        }
    }

    /// The declared speed: the `speed_mm_s` key, else a `speed_mm_s`
    /// condition that reads as a number. `what` names the trial for errors:
    /// a speed that is not a positive number is refused, not ignored, since
    /// WSS would otherwise build its templates for the wrong speed.
    pub fn speed(&self, what: &str) -> Result<Option<f64>, String> {
        let v = match (self.speed_mm_s, self.conditions.get("speed_mm_s")) {
            (Some(v), _) => v,
            (None, Some(s)) => s
                .trim()
                .parse::<f64>()
                .map_err(|_| format!("{what}: condition `speed_mm_s` = {s:?} is not a number of mm/s"))?,
            (None, None) => return Ok(None),
        };
        if v.is_finite() && v > 0.0 {
            Ok(Some(v))
        } else {
            Err(format!(
                "{what}: `speed_mm_s` must be a positive number of mm/s, got {v}"
            ))
        }
    }
}

/// The field delimiter of a user's CSV file, sniffed from its header (the
/// first line that is not a `#` comment): `,` if the header has one, else a
/// tab, else `;`, else `,`. Why: spreadsheets in locales with a decimal
/// comma save `;`-separated files, and many loggers (LabVIEW among them)
/// write tab-separated ones; read as `,`-separated, such a header is one
/// long unknown column.
pub fn sniff_delimiter(bytes: &[u8]) -> u8 {
    let header = bytes
        .split(|&b| b == b'\n')
        .find(|l| !l.starts_with(b"#"))
        .unwrap_or(&[]);
    if header.contains(&b',') {
        b','
    } else if header.contains(&b'\t') {
        b'\t'
    } else if header.contains(&b';') {
        b';'
    } else {
        b','
    }
}

/// A reader for a user's CSV file: fields trimmed, lines starting with `#`
/// skipped, the delimiter [sniffed](sniff_delimiter) from the header.
pub fn user_csv_reader(bytes: &[u8]) -> csv::Reader<&[u8]> {
    csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .delimiter(sniff_delimiter(bytes))
        .from_reader(bytes)
}

/// The trailing empty column of a header that ends with the delimiter
/// (`taxel_0,...,taxel_15,`), as loggers that print a delimiter after every
/// value write their lines: the reader sees one more column, unnamed, whose
/// cells must be empty ([`check_trailing`]). `None` otherwise (an empty
/// header name elsewhere stays an unknown column).
pub fn trailing_column(headers: &csv::StringRecord) -> Option<usize> {
    (headers.len() > 1 && headers.iter().next_back() == Some("")).then(|| headers.len() - 1)
}

/// An error when `rec` holds a value in the [trailing](trailing_column)
/// column `col`: no value is dropped silently. `at`: the file and line.
pub fn check_trailing(rec: &csv::StringRecord, col: Option<usize>, at: &str) -> Result<(), String> {
    match col.and_then(|c| rec.get(c)) {
        Some(v) if !v.is_empty() => Err(format!(
            "{at}: a value `{v}` in the last column, whose header is empty (the header line ends \
             with a delimiter): name that column, or end the rows as the header ends"
        )),
        _ => Ok(()),
    }
}

/// The error for a cell that is not a number (`noun`, e.g. "a number" or
/// "a time"), with a hint when the cell is one written with a decimal comma
/// (`1,75`), as `;`-separated files from such locales hold.
pub fn number_error(what: &str, cell: &str, noun: &str) -> String {
    let comma = cell.contains(',') && cell.replacen(',', ".", 1).parse::<f64>().is_ok();
    format!(
        "{what}: cannot read `{cell}` as {noun}{}",
        if comma {
            " (a decimal comma? palpate reads numbers written with a decimal point)"
        } else {
            ""
        }
    )
}

/// Reads `edge`, `ridge` or `unknown` (any case).
pub fn parse_stimulus(s: &str) -> Result<Stimulus, String> {
    match s.trim().to_ascii_lowercase().as_str() {
        "edge" => Ok(Stimulus::Edge),
        "ridge" => Ok(Stimulus::Ridge),
        "unknown" | "" => Ok(Stimulus::Unknown),
        other => Err(format!(
            "unknown stimulus `{other}` (expected edge, ridge or unknown)"
        )),
    }
}

/// The label-column names a data file or sidecar may carry.
pub const LABEL_COLUMNS: [&str; 5] = ["angle_deg", "stimulus", "group", "duration_ms", "speed_mm_s"];

/// Reads one label cell of a CSV file into `labels`; `what` names the place for
/// errors. Empty cells are "not given".
pub fn set_label_cell(labels: &mut TrialLabels, column: &str, cell: &str, what: &str) -> Result<(), String> {
    let cell = cell.trim();
    if cell.is_empty() {
        return Ok(());
    }
    match column {
        "angle_deg" | "duration_ms" | "speed_mm_s" => {
            let v: f64 = cell.parse().map_err(|_| number_error(what, cell, "a number"))?;
            if !v.is_finite() {
                return Err(format!("{what}: `{cell}` is not a finite number"));
            }
            if column == "angle_deg" {
                check_label_angle(v).map_err(|m| format!("{what}: {m}"))?;
                labels.angle_deg = Some(v);
            } else if v <= 0.0 {
                return Err(format!("{what}: `{column}` must be positive, got {v}"));
            } else if column == "speed_mm_s" {
                labels.speed_mm_s = Some(v);
            } else {
                labels.duration_ms = Some(v);
            }
        }
        "stimulus" => labels.stimulus = Some(parse_stimulus(cell).map_err(|e| format!("{what}: {e}"))?),
        "group" => {
            let v: f64 = cell
                .parse()
                .map_err(|_| number_error(what, cell, "a group number"))?;
            if !(v.is_finite() && v >= 0.0 && v.fract() == 0.0) {
                return Err(format!("{what}: group must be a whole number >= 0, got `{cell}`"));
            }
            labels.group = Some(v as usize);
        }
        _ => return Err(format!("{what}: `{column}` is not a label column")),
    }
    Ok(())
}

/// The range of a label's edge angle (module docs, "Label angles"):
/// strictly between 0 and 180 degrees, as the scene's `angles` and WSS's
/// class grid are; anything else (a non-finite value included) is an error.
pub fn check_label_angle(a: f64) -> Result<(), String> {
    if a.is_finite() && a > 0.0 && a < 180.0 {
        Ok(())
    } else {
        Err(format!(
            "angle_deg = {} must lie strictly between 0 and 180 degrees (0 and 180 are \
             parallel to the motion and never crossed; a scene's `angles` and WSS's classes \
             follow the same rule)",
            palpate_core::fmt_num(a)
        ))
    }
}

/// Checks the numbers of labels read from a typed source (a TOML sidecar, a
/// `trials.json`): an angle must be finite and in range
/// ([`check_label_angle`]), a duration and a speed finite and positive.
pub fn check_label_numbers(l: &TrialLabels) -> Result<(), String> {
    if let Some(a) = l.angle_deg.filter(|a| !a.is_finite()) {
        return Err(format!("angle_deg = {a} is not a finite number"));
    }
    if let Some(a) = l.angle_deg {
        check_label_angle(a)?;
    }
    if let Some(d) = l.duration_ms.filter(|d| !(d.is_finite() && *d > 0.0)) {
        return Err(format!(
            "duration_ms = {d} must be a finite, positive number of ms"
        ));
    }
    if let Some(v) = l.speed_mm_s.filter(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(format!(
            "speed_mm_s = {v} must be a finite, positive number of mm/s"
        ));
    }
    if let Some([a, b]) = l.crossing_ms {
        if !(a.is_finite() && b.is_finite() && 0.0 <= a && a <= b) {
            return Err(format!(
                "crossing_ms = [{a}, {b}] must be two finite times in ms, 0 <= first <= last"
            ));
        }
    }
    Ok(())
}

/// Merges two label readings of the same trial (e.g. two rows of a CSV trial),
/// failing when they disagree.
pub fn merge_consistent(into: &mut TrialLabels, other: &TrialLabels, what: &str) -> Result<(), String> {
    fn one<T: PartialEq + Copy + std::fmt::Debug>(
        a: &mut Option<T>,
        b: Option<T>,
        name: &str,
        what: &str,
    ) -> Result<(), String> {
        match (*a, b) {
            (Some(x), Some(y)) if x != y => Err(format!(
                "{what}: column `{name}` changes within a trial ({x:?} then {y:?})"
            )),
            (None, Some(y)) => {
                *a = Some(y);
                Ok(())
            }
            _ => Ok(()),
        }
    }
    one(&mut into.angle_deg, other.angle_deg, "angle_deg", what)?;
    one(&mut into.stimulus, other.stimulus, "stimulus", what)?;
    one(&mut into.group, other.group, "group", what)?;
    one(&mut into.duration_ms, other.duration_ms, "duration_ms", what)?;
    one(&mut into.speed_mm_s, other.speed_mm_s, "speed_mm_s", what)?;
    Ok(())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TomlSidecar {
    trials: BTreeMap<String, TrialLabels>,
    /// The array the files were recorded with: accepted here so that
    /// `deny_unknown_fields` lets it through, read and checked by
    /// [`read_sidecar_layout`].
    #[serde(default)]
    #[allow(dead_code)]
    layout: Option<TaxelLayout>,
    /// The files' sample rate: read by [`read_sidecar_rate`].
    #[serde(default)]
    #[allow(dead_code)]
    sample_rate_hz: Option<f64>,
}

/// The part of a sidecar (TOML or `trials.json`) that declares the layout;
/// every other entry is ignored here and checked by [`parse_sidecar`].
#[derive(Deserialize)]
struct SidecarLayout {
    #[serde(default)]
    layout: Option<TaxelLayout>,
    #[serde(default)]
    sample_rate_hz: Option<f64>,
}

/// The sample rate a label sidecar declares (a top-level `sample_rate_hz`:
/// `palpate simulate`'s `labels.toml` and `trials.json`, `write_signals`'
/// `labels.toml`), checked finite and positive; `None` when it declares
/// none (a CSV sidecar never does).
pub fn read_sidecar_rate(path: &Path) -> Result<Option<f64>, String> {
    let Some((text, ext)) = sidecar_text(path)? else {
        return Ok(None);
    };
    let shown = path.display();
    let parsed: SidecarLayout = match ext.as_str() {
        "toml" => toml::from_str(&text).map_err(|e| format!("{shown}: {e}"))?,
        _ => serde_json::from_str(&text).map_err(|e| format!("{shown}: {e}"))?,
    };
    match parsed.sample_rate_hz {
        Some(r) if !(r.is_finite() && r > 0.0) => Err(format!(
            "{shown}: `sample_rate_hz` must be a positive number of Hz, not {r}"
        )),
        r => Ok(r),
    }
}

/// The one sample rate of `rates` (`None` when they differ, or there are
/// none): what a `labels.toml` declares for the files written beside it.
pub fn shared_rate(rates: impl IntoIterator<Item = f64>) -> Option<f64> {
    let mut rates = rates.into_iter();
    let first = rates.next()?;
    rates.all(|r| r == first).then_some(first)
}

/// A TOML or JSON sidecar's text and extension (lower case); `None` for any
/// other kind of file (a CSV sidecar declares no layout or rate).
fn sidecar_text(path: &Path) -> Result<Option<(String, String)>, String> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if ext != "toml" && ext != "json" {
        return Ok(None);
    }
    let text =
        palpate_core::input::read_text(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    Ok(Some((text, ext)))
}

/// The taxel layout a label sidecar declares (its `[layout]` table, or a
/// `trials.json`'s `layout`), checked; `None` when it declares none (a CSV
/// sidecar never does).
pub fn read_sidecar_layout(path: &Path) -> Result<Option<TaxelLayout>, String> {
    match sidecar_text(path)? {
        Some((text, ext)) => parse_sidecar_layout(&text, &ext, &path.display().to_string()),
        None => Ok(None),
    }
}

/// [`read_sidecar_layout`] on a sidecar's text: `ext` (`toml` or `json`;
/// anything else declares none) picks the syntax and `shown` names the file.
pub fn parse_sidecar_layout(text: &str, ext: &str, shown: &str) -> Result<Option<TaxelLayout>, String> {
    let parsed: SidecarLayout = match ext {
        "toml" => toml::from_str(text).map_err(|e| format!("{shown}: {e}"))?,
        "json" => serde_json::from_str(text).map_err(|e| format!("{shown}: {e}"))?,
        _ => return Ok(None),
    };
    match parsed.layout {
        Some(l) => {
            l.validate().map_err(|m| format!("{shown}: `layout`: {m}"))?;
            Ok(Some(l))
        }
        None => Ok(None),
    }
}

/// The layout a file source reads its files with: its `layout` key (`key`,
/// when set), else the one the label sidecar `sidecar` declares, else the
/// paper's 4 x 4 grid. A key and a sidecar that disagree are an error on the
/// key naming the sidecar: one of them describes another array. The flag is
/// true when the layout was declared (key or sidecar), false for the default.
pub fn resolve_layout(
    key: &str,
    set: Option<&LayoutConfig>,
    sidecar: Option<&Path>,
) -> Result<(TaxelLayout, bool), ConfigError> {
    match resolve_declared(key, set, sidecar)? {
        Some(l) => Ok((l, true)),
        None => Ok((LayoutConfig::default().to_layout(key)?, false)),
    }
}

/// [`resolve_layout`] without the default: `None` when neither the key nor
/// the sidecar declares a layout.
fn resolve_declared(
    key: &str,
    set: Option<&LayoutConfig>,
    sidecar: Option<&Path>,
) -> Result<Option<TaxelLayout>, ConfigError> {
    let declared = match sidecar {
        Some(p) if p.is_file() => read_sidecar_layout(p).map_err(|m| ConfigError::key("labels", m))?,
        _ => None,
    };
    match (set, declared) {
        (Some(c), Some(d)) => {
            let l = c.to_layout(key)?;
            if l != d {
                return Err(ConfigError::key(
                    key,
                    format!(
                        "{} but the label sidecar {} declares {}; remove the key or correct the sidecar",
                        describe_layout(&l),
                        sidecar.map_or(String::new(), |p| p.display().to_string()),
                        describe_layout(&d)
                    ),
                ));
            }
            Ok(Some(l))
        }
        (Some(c), None) => c.to_layout(key).map(Some),
        (None, Some(d)) => Ok(Some(d)),
        (None, None) => Ok(None),
    }
}

/// A layout in a few words, for errors.
pub fn describe_layout(l: &TaxelLayout) -> String {
    match l {
        TaxelLayout::Grid {
            rows,
            cols,
            pitch_mm,
            taxel_mm,
        } => format!("a {rows} x {cols} grid ({pitch_mm} mm pitch, {taxel_mm} mm taxels)"),
        TaxelLayout::Positions {
            positions_mm,
            taxel_mm,
            ..
        } => format!(
            "{} taxels at given positions ({taxel_mm} mm taxels)",
            positions_mm.len()
        ),
    }
}

/// The warning for one part of a run (a union's source, a scene's
/// condition: `what`) on another array than an earlier part `first`: legal
/// for WSS, wrong for a trained estimator. Keyed `key`.
pub fn other_array_warning(
    key: String,
    l: &TaxelLayout,
    what: &str,
    first: &str,
    fl: &TaxelLayout,
) -> ConfigError {
    ConfigError::key(
        key,
        format!(
            "its array is {} but {what} `{first}`'s is {}; WSS matches each trial against its own \
             array, but a trained estimator fitted on one array cannot score the other's trials \
             (a different taxel count stops the run; the same count with another geometry mixes \
             taxels silently)",
            describe_layout(l),
            describe_layout(fl)
        ),
    )
}

/// Reads a label sidecar (TOML, CSV, or the `trials.json` of `palpate
/// simulate`, by extension): trial id -> labels.
pub fn read_sidecar(path: &Path) -> Result<BTreeMap<String, TrialLabels>, StageError> {
    let shown = path.display();
    let text = palpate_core::input::read_text(path)
        .map_err(|e| StageError::new(format!("cannot read label sidecar {shown}: {e}")))?;
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    parse_sidecar(&text, &ext, &shown.to_string())
}

/// Parses a label sidecar's text; `ext` (`toml` or `csv`) picks the syntax and
/// `shown` names the file in errors.
pub fn parse_sidecar(
    text: &str,
    ext: &str,
    shown: &str,
) -> Result<BTreeMap<String, TrialLabels>, StageError> {
    match ext {
        "toml" => {
            let s: TomlSidecar =
                toml::from_str(text).map_err(|e| StageError::new(format!("label sidecar {shown}: {e}")))?;
            // TOML has `nan` and `inf`: hold its numbers to the CSV rules.
            for (id, l) in &s.trials {
                check_label_numbers(l)
                    .map_err(|m| StageError::new(format!("label sidecar {shown}, trial `{id}`: {m}")))?;
            }
            Ok(s.trials)
        }
        "csv" => {
            let mut rdr = user_csv_reader(text.as_bytes());
            let headers = rdr
                .headers()
                .map_err(|e| StageError::new(format!("label sidecar {shown}: {e}")))?
                .clone();
            let mut trial_col = None;
            let trailing = trailing_column(&headers);
            let mut seen = std::collections::HashSet::new();
            for (i, h) in headers.iter().enumerate() {
                if Some(i) == trailing {
                    continue;
                }
                if !seen.insert(h) {
                    return Err(StageError::new(format!(
                        "label sidecar {shown}: column `{h}` appears twice in the header"
                    )));
                }
                if h == "trial" {
                    trial_col = Some(i);
                } else if !LABEL_COLUMNS.contains(&h) {
                    return Err(StageError::new(format!(
                        "label sidecar {shown}: unknown column `{h}` (expected trial, {})",
                        LABEL_COLUMNS.join(", ")
                    )));
                }
            }
            let trial_col = trial_col
                .ok_or_else(|| StageError::new(format!("label sidecar {shown}: no `trial` column")))?;
            let mut out = BTreeMap::new();
            for (r, rec) in rdr.records().enumerate() {
                let line = r + 2;
                let rec =
                    rec.map_err(|e| StageError::new(format!("label sidecar {shown}, line {line}: {e}")))?;
                check_trailing(&rec, trailing, &format!("label sidecar {shown}, line {line}"))
                    .map_err(StageError::new)?;
                let id = rec.get(trial_col).unwrap_or("").to_string();
                if id.is_empty() {
                    return Err(StageError::new(format!(
                        "label sidecar {shown}, line {line}: empty trial id"
                    )));
                }
                let mut l = TrialLabels::default();
                for (i, h) in headers.iter().enumerate() {
                    if i != trial_col && Some(i) != trailing {
                        set_label_cell(
                            &mut l,
                            h,
                            rec.get(i).unwrap_or(""),
                            &format!("label sidecar {shown}, line {line}, trial `{id}`"),
                        )
                        .map_err(StageError::new)?;
                    }
                }
                if out.insert(id.clone(), l).is_some() {
                    return Err(StageError::new(format!(
                        "label sidecar {shown}, line {line}: trial `{id}` appears twice"
                    )));
                }
            }
            Ok(out)
        }
        "json" => read_trials_json(text).map_err(|e| StageError::new(format!("label sidecar {shown}: {e}"))),
        _ => Err(StageError::new(format!(
            "label sidecar {shown}: unknown extension (use .toml, .csv, or the trials.json `palpate simulate` writes)"
        ))),
    }
}

/// One trial of a `trials.json` (what `palpate simulate` writes): the parts of
/// its metadata that are labels.
#[derive(Deserialize)]
struct JsonTrial {
    trial_id: String,
    label: JsonLabel,
    #[serde(default)]
    group: Option<usize>,
    #[serde(default, deserialize_with = "de_conditions")]
    conditions: BTreeMap<String, String>,
    #[serde(default)]
    speed_mm_s: Option<f64>,
    #[serde(default)]
    crossing_ms: Option<[f64; 2]>,
}

#[derive(Deserialize)]
struct JsonLabel {
    #[serde(default, deserialize_with = "de_stimulus")]
    stimulus: Option<Stimulus>,
    #[serde(default)]
    angle_deg: Option<f64>,
}

#[derive(Deserialize)]
struct TrialsJson {
    trials: Vec<JsonTrial>,
}

/// Reads the labels of a `trials.json`: `{"trials": [{"trial_id": ..., "label":
/// {"stimulus": ..., "angle_deg": ...}, "group": ..., "speed_mm_s": ..., "crossing_ms": [t0, t1]}, ...]}` (other keys are
/// ignored: they are metadata, not labels).
fn read_trials_json(text: &str) -> Result<BTreeMap<String, TrialLabels>, String> {
    let parsed: TrialsJson = serde_json::from_str(text).map_err(|e| e.to_string())?;
    let mut out = BTreeMap::new();
    for t in parsed.trials {
        let labels = TrialLabels {
            angle_deg: t.label.angle_deg,
            stimulus: t.label.stimulus,
            group: t.group,
            duration_ms: None,
            speed_mm_s: t.speed_mm_s,
            conditions: t.conditions,
            crossing_ms: t.crossing_ms,
        };
        // JSON has no NaN, but an angle of 400 or a speed of -1 is as wrong
        // here as in a TOML sidecar.
        check_label_numbers(&labels).map_err(|m| format!("trial `{}`: {m}", t.trial_id))?;
        if out.insert(t.trial_id.clone(), labels).is_some() {
            return Err(format!("trial `{}` appears twice", t.trial_id));
        }
    }
    Ok(out)
}

/// Applies a sidecar to trials read from files: every trial must have an entry
/// and every entry a trial. An entry may name a one-trial file's trial by the
/// file's name (`trial01.csv` for the trial `trial01`).
pub fn apply_sidecar(
    trials: &mut [(String, TrialLabels)],
    sidecar: &BTreeMap<String, TrialLabels>,
    path: &Path,
) -> Result<(), StageError> {
    let known: std::collections::HashSet<&str> = trials.iter().map(|(id, _)| id.as_str()).collect();
    // Each entry under the trial id it names: its key, or the key less a data
    // file's extension when the key itself is no trial's id.
    let mut by_id: BTreeMap<&str, (&str, &TrialLabels)> = BTreeMap::new();
    for (k, l) in sidecar {
        let id = if known.contains(k.as_str()) {
            k.as_str()
        } else {
            sidecar_key_id(k)
        };
        if let Some((first, _)) = by_id.insert(id, (k.as_str(), l)) {
            return Err(StageError::new(format!(
                "label sidecar {} names trial `{id}` twice (as `{first}` and as `{k}`)",
                path.display()
            )));
        }
    }
    let missing: Vec<&str> = trials
        .iter()
        .filter(|(id, _)| !by_id.contains_key(id.as_str()))
        .map(|(id, _)| id.as_str())
        .collect();
    if !missing.is_empty() {
        return Err(StageError::new(format!(
            "label sidecar {} has no entry for trial(s) {}",
            path.display(),
            preview(&missing)
        )));
    }
    let extra: Vec<&str> = by_id
        .iter()
        .filter(|(id, _)| !known.contains(*id))
        .map(|(_, (k, _))| *k)
        .collect();
    if !extra.is_empty() {
        return Err(StageError::new(format!(
            "label sidecar {} names trial(s) the files do not hold: {} (the files hold {})",
            path.display(),
            preview(&extra),
            preview(&trials.iter().map(|(id, _)| id.as_str()).collect::<Vec<_>>())
        )));
    }
    for (id, labels) in trials.iter_mut() {
        *labels = labels.overridden_by(by_id[id.as_str()].1);
    }
    Ok(())
}

/// Extensions of the data files a label sidecar may name its trials by.
const DATA_EXTENSIONS: [&str; 6] = ["csv", "npy", "npz", "mat", "daq", "bin"];

/// The trial id a sidecar key names: the key, less a data file's extension
/// (`trial01.csv` -> `trial01`). Why: a file's trial id is its name without
/// the extension, and a label file written by hand often lists the names.
fn sidecar_key_id(key: &str) -> &str {
    match key.rsplit_once('.') {
        Some((stem, ext))
            if !stem.is_empty() && DATA_EXTENSIONS.iter().any(|e| e.eq_ignore_ascii_case(ext)) =>
        {
            stem
        }
        _ => key,
    }
}

/// At most five items of a list, for messages.
pub fn preview(items: &[&str]) -> String {
    let mut s: Vec<String> = items.iter().take(5).map(|i| format!("`{i}`")).collect();
    if items.len() > 5 {
        s.push(format!("... ({} in all)", items.len()));
    }
    s.join(", ")
}

/// Builds trial metadata: labels, and groups (given, or the repetition number
/// within the class). Fails on duplicate trial ids, naming where each came from.
pub fn build_metas(
    trials: &[(String, TrialLabels)],
    origins: &[String],
) -> Result<Vec<TrialMeta>, StageError> {
    let mut seen: HashMap<&str, usize> = HashMap::new();
    for (k, (id, _)) in trials.iter().enumerate() {
        if let Some(&j) = seen.get(id.as_str()) {
            return Err(StageError::new(format!(
                "two trials share the id `{id}` ({} and {}); trial ids must be unique",
                origins[j], origins[k]
            )));
        }
        seen.insert(id, k);
    }
    let mut reps: HashMap<(Stimulus, Option<i64>), usize> = HashMap::new();
    trials
        .iter()
        .enumerate()
        .map(|(index, (id, l))| {
            let label = l.label();
            let key = (label.stimulus, label.angle_deg.map(|a| (a * 1e6).round() as i64));
            let rep = reps.entry(key).or_default();
            let group = l.group.unwrap_or(*rep);
            *rep += 1;
            let speed_mm_s = l
                .speed(&format!(
                    "trial `{id}` ({})",
                    origins.get(index).map_or("?", String::as_str)
                ))
                .map_err(StageError::new)?;
            Ok(TrialMeta {
                trial_id: id.clone(),
                index,
                label,
                group,
                crossing_ms: l.crossing_ms,
                speed_mm_s,
                conditions: l.conditions.clone(),
                provenance: vec![],
            })
        })
        .collect()
}

/// The loaded trial `meta` names: looked up at its index first (the runtime
/// asks in source order), else by id; `what` names the files in the error.
pub fn loaded_trial<T>(
    all: &[(TrialMeta, std::sync::Arc<T>)],
    meta: &TrialMeta,
    what: &str,
) -> Result<std::sync::Arc<T>, StageError> {
    all.get(meta.index)
        .filter(|(m, _)| m.trial_id == meta.trial_id)
        .or_else(|| all.iter().find(|(m, _)| m.trial_id == meta.trial_id))
        .map(|(_, x)| x.clone())
        .ok_or_else(|| StageError::new(format!("no trial `{}` in the {what}", meta.trial_id)))
}

/// Writes the label sidecar (TOML) the sources read: one `[trials."<id>"]`
/// table per trial with `angle_deg` (when known), `stimulus`, `group`,
/// `speed_mm_s` and `crossing_ms` (when known), for spikes `duration_ms`,
/// and first the array's `[layout]` when given (what
/// the file sources read the files with, see the module docs). TOML rather
/// than CSV so that a `*.csv` glob over the data files does not pick the
/// sidecar up. Numbers use Rust's round-trip form.
pub fn sidecar_toml(
    rows: &[(String, &TrialMeta, Option<f64>)],
    layout: Option<&TaxelLayout>,
    sample_rate_hz: Option<f64>,
) -> String {
    let mut s = String::from("# Labels of the trials in this folder (palpate label sidecar).\n");
    if let Some(r) = sample_rate_hz {
        s.push_str(&format!(
            "# The files' sample rate (NPY and MAT files carry none).\nsample_rate_hz = {r:?}\n"
        ));
    }
    if let Some(l) = layout {
        #[derive(Serialize)]
        struct L<'a> {
            layout: &'a TaxelLayout,
        }
        // A layout always serialises (numbers and a tag); an error would
        // only drop the table, and the sources then fall back to their key.
        if let Ok(t) = toml::to_string(&L { layout: l }) {
            s.push_str("# The array these files were recorded with.\n");
            s.push_str(&t);
        }
    }
    for (id, m, d) in rows {
        let id = id.replace('\\', "\\\\").replace('"', "\\\"");
        s.push_str(&format!("\n[trials.\"{id}\"]\n"));
        if let Some(a) = m.label.angle_deg {
            s.push_str(&format!("angle_deg = {a:?}\n"));
        }
        s.push_str(&format!(
            "stimulus = \"{}\"\ngroup = {}\n",
            m.label.stimulus, m.group
        ));
        if let Some(d) = d {
            s.push_str(&format!("duration_ms = {d:?}\n"));
        }
        if let Some(v) = m.speed_mm_s {
            s.push_str(&format!("speed_mm_s = {v:?}\n"));
        }
        // When the edge touched the array: decision times are counted from
        // it, so trials read back are timed as the scene timed them.
        if let Some([a, b]) = m.crossing_ms.filter(|c| c.iter().all(|t| t.is_finite())) {
            s.push_str(&format!("crossing_ms = [{a:?}, {b:?}]\n"));
        }
        if !m.conditions.is_empty() {
            let q = |x: &str| format!("\"{}\"", x.replace('\\', "\\\\").replace('"', "\\\""));
            let items: Vec<String> = m
                .conditions
                .iter()
                .map(|(k, v)| format!("{} = {}", q(k), q(v)))
                .collect();
            s.push_str(&format!("conditions = {{ {} }}\n", items.join(", ")));
        }
    }
    s
}

/// How far a time may lie from its point on a uniform grid, in steps: a
/// quarter sample, so that a missing or repeated sample (a whole step) is
/// never within it. The CSV time column and the DAQ timestamps are held to it.
pub const GRID_TOLERANCE: f64 = 0.25;

/// Whether time `t` lies off the uniform grid `t0 + k·dt` by more than
/// [`GRID_TOLERANCE`] steps.
pub fn off_grid(t: f64, t0: f64, k: f64, dt: f64) -> bool {
    (t - t0 - k * dt).abs() > GRID_TOLERANCE * dt
}

/// Checks times one after another against a uniform grid, in constant
/// memory (a live stream is checked as it arrives, whatever its length).
///
/// The step is the span of the times taken so far over their steps (the
/// CSV reader's fit through the first and last time, over what has come),
/// and each new time must lie [on its grid point](off_grid), so the first
/// time that leaves the grid of the ones before it is the one named. A
/// [`restart`](Self::restart) (after a sequence gap, whose length the caller
/// judges by other means) anchors the grid at the next time and keeps the
/// step learnt so far.
#[derive(Clone, Debug, Default)]
pub struct TimeGrid {
    /// The current run: its first time, its last, and the steps between them.
    run: Option<(f64, f64, u64)>,
    /// Time spanned and steps taken by the runs before the current one.
    before: (f64, u64),
}

/// A time that breaks a [`TimeGrid`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GridBreak {
    /// The time is not after the one before (`before`).
    NotIncreasing {
        /// The time before it.
        before: f64,
    },
    /// The time lies off the grid.
    Off {
        /// The grid's step so far.
        step: f64,
        /// The interval the time came after, per step.
        interval: f64,
    },
}

impl TimeGrid {
    /// The step learnt so far; `None` before the first interval.
    pub fn step(&self) -> Option<f64> {
        let (span, steps) = self.before;
        let (span, steps) = match self.run {
            Some((first, last, n)) => (span + (last - first), steps + n),
            None => (span, steps),
        };
        (steps > 0).then(|| span / steps as f64)
    }

    /// Takes time `t`, `steps` grid steps after the last one taken (1 for
    /// consecutive samples); refused, and not taken, when it is not after
    /// the last or lies off the grid.
    pub fn push(&mut self, t: f64, steps: u64) -> Result<(), GridBreak> {
        let Some((first, last, n)) = self.run else {
            self.run = Some((t, t, 0));
            return Ok(());
        };
        if t <= last || t.is_nan() {
            return Err(GridBreak::NotIncreasing { before: last });
        }
        if let Some(dt) = self.step() {
            if off_grid(t, first, (n + steps) as f64, dt) {
                return Err(GridBreak::Off {
                    step: dt,
                    interval: (t - last) / steps as f64,
                });
            }
        }
        self.run = Some((first, t, n + steps));
        Ok(())
    }

    /// Ends the current run: the next time taken anchors a new one.
    pub fn restart(&mut self) {
        if let Some((first, last, n)) = self.run.take() {
            self.before.0 += last - first;
            self.before.1 += n;
        }
    }
}

#[cfg(test)]
mod tests {
    /// The incremental grid names the first time that leaves the grid of
    /// the times before it, and learns its step across restarts.
    #[test]
    fn a_time_grid_names_the_first_time_off_the_grid_of_those_before_it() {
        use super::{GridBreak, TimeGrid};
        let mut g = TimeGrid::default();
        // 100 Hz for 700 samples, then 200 Hz: the 701st interval is the break.
        for k in 0..=700 {
            g.push(k as f64 * 10.0, 1).unwrap();
        }
        assert_eq!(g.step(), Some(10.0));
        assert_eq!(
            g.push(7005.0, 1),
            Err(GridBreak::Off {
                step: 10.0,
                interval: 5.0
            })
        );
        // Intervals alternating 13 and 7 (a mean of 10) break at the second.
        let mut g = TimeGrid::default();
        g.push(0.0, 1).unwrap();
        g.push(13.0, 1).unwrap();
        assert!(matches!(g.push(20.0, 1), Err(GridBreak::Off { .. })));
        // A time that does not advance; one 3 steps on, within a quarter step.
        let mut g = TimeGrid::default();
        g.push(0.0, 1).unwrap();
        g.push(10.0, 1).unwrap();
        assert_eq!(g.push(10.0, 1), Err(GridBreak::NotIncreasing { before: 10.0 }));
        g.push(42.0, 3).unwrap();
        // A restart keeps the step (10.5 from 42 over 4) and re-anchors.
        g.restart();
        g.push(1000.0, 1).unwrap();
        assert_eq!(g.step(), Some(10.5));
        g.push(1010.0, 1).unwrap();
        assert!(matches!(g.push(1030.0, 1), Err(GridBreak::Off { .. })));
    }

    #[test]
    fn a_source_layout_without_kind_is_read_from_its_keys() {
        use crate::io::signal_file::SignalFileConfig;
        let read = |t: &str| toml::from_str::<SignalFileConfig>(t).map(|c| c.layout);
        let positions = read("layout = { positions_mm = [[0.0, 0.0], [3, 0]], taxel_mm = 2.0 }").unwrap();
        assert_eq!(
            positions,
            Some(super::LayoutConfig::Positions {
                positions_mm: vec![[0.0, 0.0], [3.0, 0.0]],
                taxel_mm: 2.0
            })
        );
        let grid = read("layout = { rows = 2, cols = 3, pitch_mm = 3.0, taxel_mm = 2.0 }").unwrap();
        let tagged =
            read("layout = { kind = \"grid\", rows = 2, cols = 3, pitch_mm = 3.0, taxel_mm = 2.0 }").unwrap();
        assert_eq!(grid, tagged);
        assert!(matches!(
            grid,
            Some(super::LayoutConfig::Grid { rows: 2, cols: 3, .. })
        ));
        assert_eq!(read("path = \"x.csv\"").unwrap(), None);
        // Neither kind nor keys that tell it; an unknown key still refused.
        let e = read("layout = { taxel_mm = 2.0 }").unwrap_err().to_string();
        assert!(e.contains("a layout needs `kind`"), "{e}");
        let e = read("layout = { positions_mm = [[0.0, 0.0]], taxel_mm = 2.0, pitch = 1 }")
            .unwrap_err()
            .to_string();
        assert!(e.contains("pitch"), "{e}");
    }

    /// The sources' `layout` schema lets `kind` out, as their reader does,
    /// and keeps every other required key; the DAQ's (plain) one keeps it.
    #[test]
    fn the_sources_layout_schema_leaves_kind_optional() {
        let mut g = schemars::SchemaGenerator::default();
        let required = |s: &schemars::Schema| -> Vec<Vec<String>> {
            s.get("oneOf")
                .and_then(|v| v.as_array())
                .expect("a oneOf of the two kinds")
                .iter()
                .map(|v| {
                    v["required"]
                        .as_array()
                        .expect("required keys")
                        .iter()
                        .map(|k| k.as_str().unwrap_or_default().to_string())
                        .collect()
                })
                .collect()
        };
        let sources = required(&layout_schema_kind_optional(&mut g));
        assert_eq!(
            sources,
            [
                vec!["rows", "cols", "pitch_mm", "taxel_mm"],
                vec!["positions_mm", "taxel_mm"]
            ]
        );
        let plain = required(&<LayoutConfig as JsonSchema>::json_schema(&mut g));
        assert!(plain
            .iter()
            .all(|r| r.first().map(String::as_str) == Some("kind")));
    }

    use super::*;

    #[test]
    fn groups_count_repetitions_per_class_unless_given() {
        let t = |id: &str, a: Option<f64>, g: Option<usize>| {
            (
                id.to_string(),
                TrialLabels {
                    angle_deg: a,
                    group: g,
                    ..Default::default()
                },
            )
        };
        let trials = vec![
            t("a", Some(45.0), None),
            t("b", Some(30.0), None),
            t("c", Some(45.0), None),
            t("d", Some(45.0), Some(7)),
            t("e", None, None),
        ];
        let origins = vec!["x".to_string(); 5];
        let m = build_metas(&trials, &origins).unwrap();
        let groups: Vec<usize> = m.iter().map(|m| m.group).collect();
        assert_eq!(groups, vec![0, 0, 1, 7, 0]);
        assert_eq!(m[4].label.stimulus, Stimulus::Unknown);
        assert_eq!(m[0].label.stimulus, Stimulus::Edge);
        let dup = vec![t("a", None, None), t("a", None, None)];
        let e = build_metas(&dup, &["f1".into(), "f2".into()]).unwrap_err();
        assert!(e.message.contains("`a`") && e.message.contains("f1") && e.message.contains("f2"));
    }

    #[test]
    fn a_sidecar_declares_the_layout_and_a_key_must_agree_with_it() {
        let d = tempfile::tempdir().unwrap();
        let toml = d.path().join("labels.toml");
        let grid = TaxelLayout::Grid {
            rows: 3,
            cols: 2,
            pitch_mm: 2.5,
            taxel_mm: 2.0,
        };
        let meta = TrialMeta {
            trial_id: "t0".into(),
            ..TrialMeta::default()
        };
        std::fs::write(
            &toml,
            sidecar_toml(&[("t0".into(), &meta, None)], Some(&grid), None),
        )
        .unwrap();
        // The sidecar the writer makes parses as labels and declares the grid.
        assert_eq!(read_sidecar(&toml).unwrap().len(), 1);
        assert_eq!(read_sidecar_layout(&toml).unwrap(), Some(grid.clone()));
        assert_eq!(
            resolve_layout("layout", None, Some(&toml)).unwrap(),
            (grid.clone(), true)
        );
        let other = LayoutConfig::default();
        let e = resolve_layout("layout", Some(&other), Some(&toml))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("labels.toml") && e.contains("3 x 2") && e.contains("4 x 4"),
            "{e}"
        );
        // No sidecar, or one without a layout (CSV never has one): the key, else 4 x 4.
        let csv = d.path().join("labels.csv");
        std::fs::write(&csv, "trial,angle_deg\nt0,30\n").unwrap();
        let (l, declared) = resolve_layout("layout", None, Some(&csv)).unwrap();
        assert_eq!((l.len(), declared), (16, false));
        let (l, declared) = resolve_layout("layout", Some(&LayoutConfig::default()), None).unwrap();
        assert_eq!((l.len(), declared), (16, true));
        // trials.json's `layout`, and a bad one named with its file.
        let json = d.path().join("trials.json");
        std::fs::write(&json, r#"{"layout": {"kind": "grid", "rows": 1, "cols": 5, "pitch_mm": 3.0, "taxel_mm": 2.0}, "trials": []}"#).unwrap();
        assert_eq!(resolve_layout("layout", None, Some(&json)).unwrap().0.len(), 5);
        std::fs::write(
            &toml,
            "[layout]\nkind = \"grid\"\nrows = 0\ncols = 4\npitch_mm = 3.0\ntaxel_mm = 2.0\n[trials.t0]\n",
        )
        .unwrap();
        let e = resolve_layout("layout", None, Some(&toml))
            .unwrap_err()
            .to_string();
        assert!(e.contains("labels.toml") && e.contains("labels"), "{e}");
    }

    /// A label angle outside (0, 180), from any sidecar kind, is refused
    /// naming the file and the trial (and the CSV line); in-range angles,
    /// near the ends too, pass.
    #[test]
    fn label_angles_outside_0_to_180_are_refused_naming_file_and_trial() {
        for bad in ["400", "-30", "0", "180", "1e300"] {
            let csv = format!("trial,angle_deg,speed_mm_s\ntrial01,40,2\ntrial02,{bad},2\n");
            let e = parse_sidecar(&csv, "csv", "labels.csv").unwrap_err().message;
            assert!(
                e.contains("labels.csv, line 3")
                    && e.contains("trial `trial02`")
                    && e.contains("between 0 and 180"),
                "{bad}: {e}"
            );
            let toml = format!("[trials.t1]\nangle_deg = {bad}.0\n").replace("e300.0", ".0e300");
            let e = parse_sidecar(&toml, "toml", "labels.toml").unwrap_err().message;
            assert!(
                e.contains("labels.toml") && e.contains("trial `t1`") && e.contains("between 0 and 180"),
                "{bad}: {e}"
            );
            let json = format!(r#"{{"trials": [{{"trial_id": "r7", "label": {{"angle_deg": {bad}}}}}]}}"#);
            let e = parse_sidecar(&json, "json", "trials.json").unwrap_err().message;
            assert!(
                e.contains("trials.json") && e.contains("trial `r7`") && e.contains("between 0 and 180"),
                "{bad}: {e}"
            );
        }
        let ok = parse_sidecar("trial,angle_deg\na,0.001\nb,179.999\nc,\n", "csv", "l.csv").unwrap();
        assert_eq!(ok["a"].angle_deg, Some(0.001));
        assert_eq!(ok["c"].angle_deg, None);
    }

    /// A sidecar's `crossing_ms` (TOML, or `trials.json` as `palpate
    /// simulate` writes it) reaches the trial's metadata, where the `mae`
    /// sink times decisions from it; a reversed or negative one is refused.
    #[test]
    fn crossing_times_are_read_and_checked() {
        let json =
            r#"{"trials": [{"trial_id": "r7", "label": {"angle_deg": 45}, "crossing_ms": [2000.5, 9000]}]}"#;
        let l = parse_sidecar(json, "json", "trials.json").unwrap();
        assert_eq!(l["r7"].crossing_ms, Some([2000.5, 9000.0]));
        let l = parse_sidecar("[trials.t1]\ncrossing_ms = [100, 200]\n", "toml", "labels.toml").unwrap();
        let metas = build_metas(&[("t1".to_string(), l["t1"].clone())], &["t1.csv".to_string()]).unwrap();
        assert_eq!(metas[0].crossing_ms, Some([100.0, 200.0]));
        // The sidecar the writers make (`palpate simulate`'s labels.toml,
        // the write_* sinks') carries it back.
        let meta = TrialMeta {
            trial_id: "t2".into(),
            crossing_ms: Some([1234.5, 6789.25]),
            ..TrialMeta::default()
        };
        let text = sidecar_toml(&[("t2".into(), &meta, None)], None, None);
        let l = parse_sidecar(&text, "toml", "labels.toml").unwrap();
        assert_eq!(l["t2"].crossing_ms, Some([1234.5, 6789.25]), "{text}");
        for bad in ["[200, 100]", "[-1, 5]"] {
            let e = parse_sidecar(
                &format!("[trials.t1]\ncrossing_ms = {bad}\n"),
                "toml",
                "labels.toml",
            )
            .unwrap_err()
            .message;
            assert!(
                e.contains("trial `t1`") && e.contains("crossing_ms"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn file_ids_disambiguate_equal_stems() {
        let p = vec![PathBuf::from("/d/s1/rec.csv"), PathBuf::from("/d/s2/rec.csv")];
        assert_eq!(file_ids(&p), vec!["s1_rec", "s2_rec"]);
        let p = vec![PathBuf::from("/d/a.csv"), PathBuf::from("/d/b.npy")];
        assert_eq!(file_ids(&p), vec!["a", "b"]);
    }

    #[test]
    fn file_stems_are_safe() {
        assert_eq!(file_stem_for("edge-45deg-r03"), "edge-45deg-r03");
        assert_eq!(file_stem_for("a/b c"), "a_b_c");
        assert_eq!(file_stem_for(".."), "trial..");
    }
}
