//! The `spike_file` source: spike events `(x, y, t[, p])` from CSV or NPY files,
//! in the layout neuromorphic event tools use, mapped to the taxels of a layout.
//!
//! ## Mapping
//!
//! For a grid, `x` is the column and `y` the row (row 0 on top), so the event
//! goes to taxel `y * cols + x`. For an explicit list of positions, `x` is the
//! taxel index and `y` must be 0. Coordinates must be whole numbers inside the
//! layout; anything else is an error naming the file and the row (CSV line or
//! NPY event index). `t` is in `time_unit` (`us` by default, as event cameras
//! and tonic/AEDAT tools store it; `ms`, `s`), converted to ms; with
//! `time_origin = "first_event"` times are shifted so the trial's first event
//! is at 0. Times must be finite and not negative. `p` (polarity) is optional;
//! `polarity = "on"` keeps events with `p > 0`, `"off"` those with `p <= 0`.
//!
//! The trial's duration is, in order of precedence: the sidecar's
//! `duration_ms`, the `duration_ms` key, or the last event's time plus 1 ms
//! (so every event lies in `[0, duration)`); an event at or after a given
//! duration is an error naming the latest event's CSV line or NPY index.
//! Events are sorted by time, then taxel.
//!
//! ## Formats
//!
//! **CSV**: a header row with `x`, `y`, `t`, optionally `p`, `trial` (many
//! trials per file, rows grouped by value, ids `<file>-<trial>`), `angle_deg`,
//! `stimulus`, `group`, `duration_ms` (labels, constant within a trial). Other
//! columns are an error. A header-only file is a trial without spikes (it
//! needs a duration).
//!
//! **NPY**: one trial per file; a 2-D array `(events, 3)` or `(events, 4)`
//! with columns `x, y, t[, p]`, or a 1-D structured array with numeric fields
//! `x`, `y`, `t` (or `ts`), optionally `p` (the dtype tonic and other event
//! tools save); other fields are an error.
//!
//! Trial ids, label sidecars and groups work as for `signal_file`.

use super::arrays::{read_npy, NpyContent};
use super::common::{
    apply_sidecar, build_metas, expand_paths, file_ids, merge_consistent, read_sidecar, resolve_layout,
    set_label_cell, LayoutConfig, TrialLabels, LABEL_COLUMNS,
};
use super::signal_file::{check_csv_complete, csv_error};
use palpate_core::{
    check_positive, register_stage, BuildContext, ConfigError, InputSpec, Inspection, OutputFacts, Payload,
    PayloadKind, Source, SpikeEvent, SpikeTrain, Stage, StageConfig, StageError, TaxelLayout, TrialContext,
    TrialMeta,
};
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// Unit of event times in a file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum TimeUnit {
    /// Microseconds.
    #[default]
    Us,
    /// Milliseconds.
    Ms,
    /// Seconds.
    S,
}

impl TimeUnit {
    /// Milliseconds per unit.
    pub fn to_ms(self) -> f64 {
        match self {
            TimeUnit::Us => 1e-3,
            TimeUnit::Ms => 1.0,
            TimeUnit::S => 1e3,
        }
    }
}

/// Where time 0 is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum TimeOrigin {
    /// Times are from the trial's start.
    #[default]
    Zero,
    /// The first event of each trial is at 0.
    FirstEvent,
}

/// Which polarities to keep.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// Every event.
    #[default]
    Both,
    /// Events with `p > 0`.
    On,
    /// Events with `p <= 0`.
    Off,
}

/// File format of an event file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SpikeFormat {
    /// By extension (`.csv`, `.npy`).
    #[default]
    Auto,
    /// CSV with a header row.
    Csv,
    /// NumPy array, plain or structured.
    Npy,
}

/// Spike events `(x, y, t[, p])` read from CSV or NPY files, mapped to taxels.
///
/// x = column, y = row of a grid (or x = taxel index for an explicit layout);
/// t in `time_unit`. Formats: the user guide's "File formats and label files"
/// page (docs/guide/src/formats.md).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SpikeFileConfig {
    /// A file or glob pattern, relative to the graph file's folder. Default none.
    pub path: Option<String>,
    /// More files or glob patterns. Default empty.
    pub paths: Vec<String>,
    /// `auto` (by extension), `csv` or `npy`. Default auto.
    pub format: SpikeFormat,
    /// Unit of `t`: `us`, `ms` or `s`. Default us.
    pub time_unit: TimeUnit,
    /// `zero` (times from the trial start) or `first_event`. Default zero.
    pub time_origin: TimeOrigin,
    /// Polarities kept: `both`, `on` (p > 0), `off` (p <= 0). Default both.
    pub polarity: Polarity,
    /// Trial length, ms; default none: the last event + 1 ms (a sidecar's
    /// `duration_ms` wins).
    pub duration_ms: Option<f64>,
    /// Taxel layout; its taxel count must match the files'. Default: the one
    /// the label sidecar declares (its `[layout]` table, or a `trials.json`'s
    /// `layout`: `palpate simulate`, `write_signals` and `write_spikes` write
    /// it), else the paper's 4 x 4 grid, 3 mm pitch, 2 mm taxels. Set and
    /// unlike the sidecar's, an error.
    /// (`kind = "grid"` or `"positions"` may be left out: `positions_mm` or
    /// `rows`/`cols` tell it.)
    #[serde(default, deserialize_with = "crate::io::common::layout_with_inferred_kind")]
    #[schemars(schema_with = "crate::io::common::layout_schema_kind_optional")]
    pub layout: Option<LayoutConfig>,
    /// Label sidecar (TOML, CSV, or a `trials.json` from `palpate simulate`).
    /// Default none.
    pub labels: Option<String>,
}

impl Default for SpikeFileConfig {
    fn default() -> Self {
        SpikeFileConfig {
            path: None,
            paths: vec![],
            format: SpikeFormat::Auto,
            time_unit: TimeUnit::Us,
            time_origin: TimeOrigin::Zero,
            polarity: Polarity::Both,
            duration_ms: None,
            layout: None,
            labels: None,
        }
    }
}

#[typetag::serde(name = "spike_file")]
impl StageConfig for SpikeFileConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = palpate_core::ConfigChecks::new();
        if let Some(d) = self.duration_ms {
            c.take(check_positive("duration_ms", d, "ms"));
        }
        let entries: Vec<String> = self.path.iter().chain(&self.paths).cloned().collect();
        let key = if self.path.is_some() { "path" } else { "paths" };
        let files = c
            .take(expand_paths(&entries, |p| ctx.resolve(p), key))
            .unwrap_or_default();
        // One message for the format, however many files it cannot tell.
        if let Some(m) = files.iter().find_map(|f| spike_format_of(self.format, f).err()) {
            c.push(ConfigError::key("format", m));
        }
        let labels = self.labels.as_ref().map(|l| ctx.resolve(Path::new(l)));
        if let Some(l) = &labels {
            c.take(super::common::check_regular_file(l, "labels"));
        }
        let layout = c.take(resolve_layout("layout", self.layout.as_ref(), labels.as_deref()));
        c.finish()?;
        let (layout, declared) = layout.ok_or_else(|| ConfigError::key("layout", "not a layout"))?;
        Ok(Stage::Source(Box::new(SpikeFileSource {
            cfg: self.clone(),
            layout,
            assumed: (!declared).then(|| ctx.stage_id.clone()),
            files,
            labels,
            loaded: OnceLock::new(),
        })))
    }
    /// The array when the `layout` key gives it (a union warns when its
    /// sources' arrays differ); unknown until the files are read otherwise.
    fn inspect(&self, _ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        super::common::layout_inspection(&self.layout)
    }
}
register_stage!("spike_file", SpikeFileConfig);

fn spike_format_of(f: SpikeFormat, path: &Path) -> Result<SpikeFormat, String> {
    if f != SpikeFormat::Auto {
        return Ok(f);
    }
    match path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .as_deref()
    {
        Some("csv" | "txt") => Ok(SpikeFormat::Csv),
        Some("npy") => Ok(SpikeFormat::Npy),
        _ => Err(format!(
            "cannot tell the format of {} from its extension; set `format`",
            path.display()
        )),
    }
}

/// Every trial, read once and shared.
type Loaded = Vec<(TrialMeta, Arc<SpikeTrain>)>;
/// A CSV trial being read: name, labels, `(taxel, t_ms)` events, and the
/// latest event's time and line.
type CsvEvents = (String, TrialLabels, Vec<(u32, f64)>, Latest);

struct SpikeFileSource {
    cfg: SpikeFileConfig,
    layout: TaxelLayout,
    /// The stage's id when the layout is the default 4 x 4 (neither the key
    /// nor the label file declared one): [`unused_edges`] is then reported.
    assumed: Option<String>,
    files: Vec<PathBuf>,
    labels: Option<PathBuf>,
    loaded: OnceLock<Result<Loaded, StageError>>,
}

/// Events of a smaller array read with a larger grid land on its first rows
/// and columns and leave the others silent, with no error. So when the grid
/// was assumed rather than declared and no event at all lies in its last
/// row or last column, say so (a warning, not an error: a real 4 x 4 array
/// may have a dead edge row).
fn unused_edges<'a>(layout: &TaxelLayout, events: impl Iterator<Item = &'a (u32, f64)>) -> Option<String> {
    let (rows, cols) = layout.grid()?;
    let (mut last_row, mut last_col, mut any) = (false, false, false);
    for &(taxel, _) in events {
        any = true;
        let t = taxel as usize;
        last_row |= t / cols.max(1) == rows - 1;
        last_col |= t % cols.max(1) == cols - 1;
    }
    (any && !(last_row && last_col)).then(|| {
        format!(
            "no event in the last {} of the default {rows} x {cols} grid: if the array is smaller, \
             declare it (the `layout` key, or a `[layout]` table in the label file)",
            match (last_row, last_col) {
                (false, false) => "row or column",
                (false, true) => "row",
                _ => "column",
            }
        )
    })
}

/// Events of one trial as read, before durations and labels are settled.
struct RawEvents {
    id: String,
    labels: TrialLabels,
    /// `(taxel, t_ms)`, unsorted, origin not yet applied.
    events: Vec<(u32, f64)>,
    origin: String,
    /// Where the latest event is in the file (`line 7`, `event 3`), for the
    /// error when it lies past the trial's duration.
    latest_at: Option<String>,
}

/// The latest event seen so far of a trial being read: its time and where
/// it is (the CSV line or NPY event index). First of equal times wins.
#[derive(Clone, Copy, Default)]
struct Latest(Option<(f64, u64)>);

impl Latest {
    fn see(&mut self, t_ms: f64, pos: u64) {
        if self.0.is_none_or(|(t, _)| t_ms > t) {
            self.0 = Some((t_ms, pos));
        }
    }
    fn at(self, what: &str) -> Option<String> {
        self.0.map(|(_, p)| format!("{what} {p}"))
    }
}

impl SpikeFileSource {
    fn load(&self) -> Result<Loaded, StageError> {
        let ids = file_ids(&self.files);
        let per_file: Vec<Result<Vec<RawEvents>, String>> = self
            .files
            .par_iter()
            .zip(ids.par_iter())
            .map(|(f, id)| read_spike_file(f, id, &self.cfg, &self.layout))
            .collect();
        let mut raw = Vec::new();
        for r in per_file {
            raw.extend(r.map_err(StageError::new)?);
        }
        if let Some(id) = &self.assumed {
            if let Some(m) = unused_edges(&self.layout, raw.iter().flat_map(|t| &t.events)) {
                palpate_core::warn(&format!("warning: spike_file `{id}`: {m}"));
            }
        }
        let mut labelled: Vec<(String, TrialLabels)> =
            raw.iter().map(|t| (t.id.clone(), t.labels.clone())).collect();
        if let Some(p) = &self.labels {
            let side = read_sidecar(p)?;
            apply_sidecar(&mut labelled, &side, p)?;
        }
        let origins: Vec<String> = raw.iter().map(|t| t.origin.clone()).collect();
        let metas = build_metas(&labelled, &origins)?;
        metas
            .into_iter()
            .zip(raw)
            .zip(labelled)
            .map(|((m, t), (_, l))| {
                let shift = match self.cfg.time_origin {
                    TimeOrigin::Zero => 0.0,
                    TimeOrigin::FirstEvent => t.events.iter().map(|e| e.1).fold(f64::INFINITY, f64::min),
                };
                let shift = if shift.is_finite() { shift } else { 0.0 };
                let mut events: Vec<SpikeEvent> = t
                    .events
                    .iter()
                    .map(|&(taxel, tm)| SpikeEvent { taxel, t_ms: tm - shift })
                    .collect();
                let last = events.iter().map(|e| e.t_ms).fold(f64::NEG_INFINITY, f64::max);
                let duration_ms = match l.duration_ms.or(self.cfg.duration_ms) {
                    Some(d) => {
                        if last >= d {
                            return Err(StageError::new(format!(
                                "{}{}: an event at {last:?} ms lies at or after the trial's duration of {d:?} ms",
                                t.origin,
                                t.latest_at.as_deref().map(|a| format!(", {a}")).unwrap_or_default()
                            )));
                        }
                        d
                    }
                    None if events.is_empty() => {
                        return Err(StageError::new(format!(
                            "{}: no events, so the duration is unknown; set `duration_ms` (or a sidecar's duration_ms)",
                            t.origin
                        )))
                    }
                    None => last + 1.0,
                };
                let mut train = SpikeTrain {
                    layout: self.layout.clone(),
                    duration_ms,
                    events: std::mem::take(&mut events),
                };
                train.sort();
                Ok((m, Arc::new(train)))
            })
            .collect()
    }

    fn loaded(&self) -> Result<&Loaded, StageError> {
        self.loaded
            .get_or_init(|| self.load())
            .as_ref()
            .map_err(Clone::clone)
    }
}

impl Source for SpikeFileSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        Ok(self.loaded()?.iter().map(|(m, _)| m.clone()).collect())
    }
    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let trial = crate::io::common::loaded_trial(self.loaded()?, ctx.meta, "files")?;
        Ok(Payload::Spikes(trial))
    }
}

/// Maps one event to a taxel and a time in ms, or explains what is wrong.
struct Mapper<'a> {
    layout: &'a TaxelLayout,
    cfg: &'a SpikeFileConfig,
}

impl Mapper<'_> {
    /// `None` when the event's polarity is filtered out.
    fn map(&self, x: f64, y: f64, t: f64, p: Option<f64>, what: &str) -> Result<Option<(u32, f64)>, String> {
        for (name, v) in [("x", x), ("y", y), ("t", t)] {
            if !v.is_finite() {
                return Err(format!("{what}: `{name}` = {v:?} is not finite"));
            }
        }
        if x.fract() != 0.0 || y.fract() != 0.0 {
            return Err(format!(
                "{what}: coordinates must be whole numbers, got x = {x:?}, y = {y:?}"
            ));
        }
        let taxel = match self.layout.grid() {
            Some((rows, cols)) => {
                if x < 0.0 || y < 0.0 || x >= cols as f64 || y >= rows as f64 {
                    return Err(format!(
                        "{what}: event at x = {x:?}, y = {y:?} lies outside the {rows} x {cols} grid \
                         (x is the column, y the row)"
                    ));
                }
                y as usize * cols + x as usize
            }
            None => {
                let n = self.layout.len();
                if x < 0.0 || x >= n as f64 || y != 0.0 {
                    return Err(format!(
                        "{what}: event at x = {x:?}, y = {y:?}: for an explicit layout x is the taxel index \
                         (0..{n}) and y must be 0"
                    ));
                }
                x as usize
            }
        };
        let t_ms = t * self.cfg.time_unit.to_ms();
        if t_ms < 0.0 && self.cfg.time_origin == TimeOrigin::Zero {
            return Err(format!(
                "{what}: negative time {t:?} (set time_origin = \"first_event\"?)"
            ));
        }
        let keep = match (self.cfg.polarity, p) {
            (Polarity::Both, _) => true,
            (Polarity::On, Some(p)) => p > 0.0,
            (Polarity::Off, Some(p)) => p <= 0.0,
            (_, None) => {
                return Err(format!(
                    "{what}: `polarity` filters by `p` but the file has no `p`"
                ))
            }
        };
        if let Some(p) = p.filter(|p| !p.is_finite()) {
            return Err(format!("{what}: `p` = {p} is not finite"));
        }
        Ok(keep.then_some((taxel as u32, t_ms)))
    }
}

fn read_spike_file(
    path: &Path,
    file_id: &str,
    cfg: &SpikeFileConfig,
    layout: &TaxelLayout,
) -> Result<Vec<RawEvents>, String> {
    let shown = path.display().to_string();
    let fmt = spike_format_of(cfg.format, path)?;
    let bytes = palpate_core::input::read_data(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    read_spike_raw(&bytes, &shown, file_id, fmt, cfg, layout)
}

/// One trial's events as read from bytes: `(id, labels, (taxel, t_ms) events
/// unsorted and before the time origin is applied, origin for messages)`.
pub type SpikeBytesTrial = (String, TrialLabels, Vec<(u32, f64)>, String);

/// Reads one event file's bytes (format `fmt`, not `auto`); `shown` names the
/// file in errors. Public so that fuzzing reaches the readers without files.
pub fn read_spike_bytes(
    bytes: &[u8],
    shown: &str,
    file_id: &str,
    fmt: SpikeFormat,
    cfg: &SpikeFileConfig,
    layout: &TaxelLayout,
) -> Result<Vec<SpikeBytesTrial>, String> {
    Ok(read_spike_raw(bytes, shown, file_id, fmt, cfg, layout)?
        .into_iter()
        .map(|r| (r.id, r.labels, r.events, r.origin))
        .collect())
}

/// [`read_spike_bytes`], each trial with where its latest event is.
fn read_spike_raw(
    bytes: &[u8],
    shown: &str,
    file_id: &str,
    fmt: SpikeFormat,
    cfg: &SpikeFileConfig,
    layout: &TaxelLayout,
) -> Result<Vec<RawEvents>, String> {
    let shown = shown.to_string();
    let mapper = Mapper { layout, cfg };
    let raw = match fmt {
        SpikeFormat::Csv => read_csv_events(bytes, &shown, file_id, &mapper),
        SpikeFormat::Npy => {
            let cols: Vec<(String, Vec<f64>)> = match read_npy(bytes, &shown)? {
                NpyContent::Plain(a) => {
                    let ok = a.shape.len() == 2 && (a.shape[1] == 3 || a.shape[1] == 4);
                    if !ok {
                        return Err(format!(
                            "{shown}: wrong shape {:?}; expected (events, 3) or (events, 4) with columns x, y, t[, p], \
                             or a structured array with fields x, y, t[, p]",
                            a.shape
                        ));
                    }
                    let (n, w) = (a.shape[0], a.shape[1]);
                    ["x", "y", "t", "p"][..w]
                        .iter()
                        .enumerate()
                        .map(|(j, name)| (name.to_string(), (0..n).map(|i| a.data[i * w + j]).collect()))
                        .collect()
                }
                NpyContent::Record(fields) => fields
                    .into_iter()
                    .map(|(n, v)| (if n == "ts" { "t".to_string() } else { n }, v))
                    .collect(),
            };
            let get = |name: &str| cols.iter().find(|(n, _)| n == name).map(|(_, v)| v);
            for (n, _) in &cols {
                if !["x", "y", "t", "p"].contains(&n.as_str()) {
                    return Err(format!(
                        "{shown}: unknown field `{n}` (expected x, y, t or ts, p)"
                    ));
                }
            }
            let (Some(x), Some(y), Some(t)) = (get("x"), get("y"), get("t")) else {
                return Err(format!("{shown}: needs fields x, y and t (or ts)"));
            };
            let p = get("p");
            let mut events = Vec::with_capacity(x.len());
            let mut latest = Latest::default();
            for i in 0..x.len() {
                if let Some(e) =
                    mapper.map(x[i], y[i], t[i], p.map(|p| p[i]), &format!("{shown}, event {i}"))?
                {
                    latest.see(e.1, i as u64);
                    events.push(e);
                }
            }
            Ok(vec![RawEvents {
                id: file_id.to_string(),
                labels: TrialLabels::default(),
                events,
                origin: shown,
                latest_at: latest.at("event"),
            }])
        }
        SpikeFormat::Auto => Err(format!("{shown}: the format must be resolved before reading")),
    }?;
    Ok(raw)
}

fn read_csv_events(
    bytes: &[u8],
    shown: &str,
    file_id: &str,
    mapper: &Mapper<'_>,
) -> Result<Vec<RawEvents>, String> {
    check_csv_complete(bytes, shown)?;
    let mut rdr = super::common::user_csv_reader(bytes);
    let headers = rdr.headers().map_err(|e| csv_error(shown, &e))?.clone();
    let find = |n: &str| headers.iter().position(|h| h == n);
    let trailing = super::common::trailing_column(&headers);
    let mut seen = std::collections::HashSet::new();
    for (i, h) in headers.iter().enumerate() {
        if Some(i) == trailing {
            continue;
        }
        if !seen.insert(h) {
            return Err(format!("{shown}: column `{h}` appears twice in the header"));
        }
        if !["x", "y", "t", "p", "trial"].contains(&h) && !LABEL_COLUMNS.contains(&h) {
            return Err(format!(
                "{shown}: unknown column `{h}` (expected x, y, t, optionally p, trial, {})",
                LABEL_COLUMNS.join(", ")
            ));
        }
    }
    let (Some(cx), Some(cy), Some(ct)) = (find("x"), find("y"), find("t")) else {
        return Err(format!("{shown}: needs columns x, y and t"));
    };
    let cp = find("p");
    let ctrial = find("trial");
    let mut trials: Vec<CsvEvents> = Vec::new();
    // Trial name -> index in `trials` (a linear search was quadratic in trials).
    let mut trial_index: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    let label_cols: Vec<(usize, &str)> = headers
        .iter()
        .enumerate()
        .filter(|(_, h)| LABEL_COLUMNS.contains(h))
        .collect();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| csv_error(shown, &e))?;
        let line = rec.position().map_or(0, |p| p.line());
        let what = format!("{shown}, line {line}");
        super::common::check_trailing(&rec, trailing, &what)?;
        let num = |i: usize| -> Result<f64, String> {
            let cell = rec.get(i).unwrap_or("");
            cell.parse::<f64>().map_err(|_| {
                super::common::number_error(&format!("{what}, column `{}`", &headers[i]), cell, "a number")
            })
        };
        let name = ctrial
            .map(|i| rec.get(i).unwrap_or("").to_string())
            .unwrap_or_default();
        let k = match trial_index.get(&name) {
            Some(&k) => k,
            None => {
                trial_index.insert(name.clone(), trials.len());
                trials.push((name, TrialLabels::default(), Vec::new(), Latest::default()));
                trials.len() - 1
            }
        };
        let mut row_labels = TrialLabels::default();
        for &(i, h) in &label_cols {
            // A label belongs to the trial: name it when the file holds several.
            let trial = match ctrial {
                Some(_) => format!(", trial `{}`", trials[k].0),
                None => String::new(),
            };
            set_label_cell(
                &mut row_labels,
                h,
                rec.get(i).unwrap_or(""),
                &format!("{what}, column `{h}`{trial}"),
            )?;
        }
        merge_consistent(&mut trials[k].1, &row_labels, &what)?;
        let p = cp.map(num).transpose()?;
        if let Some(e) = mapper.map(num(cx)?, num(cy)?, num(ct)?, p, &what)? {
            trials[k].3.see(e.1, line);
            trials[k].2.push(e);
        }
    }
    if trials.is_empty() {
        // A header-only file: one trial without spikes.
        trials.push((
            String::new(),
            TrialLabels::default(),
            Vec::new(),
            Latest::default(),
        ));
    }
    let many = trials.len() > 1 || !trials[0].0.is_empty();
    Ok(trials
        .into_iter()
        .map(|(name, labels, events, latest)| RawEvents {
            latest_at: latest.at("line"),
            id: if many {
                format!("{file_id}-{name}")
            } else {
                file_id.to_string()
            },
            labels,
            events,
            origin: if many {
                format!("{shown}, trial `{name}`")
            } else {
                shown.to_string()
            },
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An event at or after the trial's duration is named with its line
    /// (CSV) or index (NPY), the latest event's where several are.
    #[test]
    fn an_event_past_the_duration_names_its_line() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(
            d.path().join("ev.csv"),
            "x,y,t\n0,0,1.0\n1,0,7.5\n2,1,9.0\n3,3,2.0\n",
        )
        .unwrap();
        let ctx = BuildContext {
            stage_id: "sp".into(),
            seed: 0,
            out_dir: d.path().to_path_buf(),
            base_dir: d.path().to_path_buf(),
        };
        let source = |keys: &str| -> Box<dyn Source> {
            let cfg: SpikeFileConfig = toml::from_str(keys).unwrap();
            match cfg.build(&ctx).unwrap() {
                Stage::Source(s) => s,
                _ => panic!("not a source"),
            }
        };
        let e = source("path = \"ev.csv\"\ntime_unit = \"ms\"\nduration_ms = 8.0")
            .trials()
            .unwrap_err()
            .message;
        assert!(e.contains("ev.csv, line 4") && e.contains("9.0 ms"), "{e}");
        assert!(
            source("path = \"ev.csv\"\ntime_unit = \"ms\"\nduration_ms = 10.0")
                .trials()
                .is_ok()
        );
    }

    #[test]
    fn events_of_a_smaller_array_on_the_default_grid_are_flagged() {
        let grid = LayoutConfig::default().to_layout("layout").unwrap();
        let ev = |xy: &[(u32, u32)]| xy.iter().map(|&(x, y)| (y * 4 + x, 1.0)).collect::<Vec<_>>();
        // A 3 x 3 array's events (x, y < 3): neither the last row nor column.
        let small = ev(&[(0, 0), (2, 2), (1, 2)]);
        let m = unused_edges(&grid, small.iter()).unwrap();
        assert!(m.contains("row or column") && m.contains("`layout`"), "{m}");
        // 4 rows, 3 columns: only the last column is silent.
        assert!(unused_edges(&grid, ev(&[(0, 3), (2, 0)]).iter())
            .unwrap()
            .contains("last column"));
        // Both edges reached (in different events), or no events at all: nothing to say.
        assert_eq!(unused_edges(&grid, ev(&[(3, 0), (0, 3)]).iter()), None);
        assert_eq!(unused_edges(&grid, std::iter::empty()), None);
        // Explicit positions have no rows and columns.
        let pos = TaxelLayout::Positions {
            positions_mm: vec![[0.0, 0.0], [3.0, 0.0]],
            taxel_mm: 2.0,
        };
        assert_eq!(unused_edges(&pos, ev(&[(0, 0)]).iter()), None);
    }
}
