//! File sinks: signals, spikes, images and estimates as NPY or CSV, so Python
//! (`np.load`, `pandas.read_csv`) and MATLAB (`readmatrix`, `readtable`, or
//! `readNPY` from npy-matlab) load them directly.
//!
//! Every file is written atomically (a temporary file renamed over the target)
//! into `<run out>/<dir>/`, where `dir` defaults to the sink's id. Numbers in
//! CSV are written in Rust's shortest round-trip form, so reading them back
//! gives the same `f64` bits; NPY files are `<f8` (float64), C order, except
//! spike events, which by default use the structured dtype of tonic and other
//! event-camera tools (see below).
//!
//! | sink | files | NPY array | CSV columns |
//! |---|---|---|---|
//! | `write_signals` | one per trial, `<trial>.npy`/`.csv` | `(samples, taxels)` | `time_ms, taxel_0 .. taxel_{N-1}` |
//! | `write_spikes` | one per trial | structured `(events,)`: `x, y` int16, `t` int64, `p` bool (tonic's dtype; `npy_layout = "float"`: `(events, 4)` float64) | `x, y, t, p` |
//! | `write_images` | one per trial | `(frames, rows, cols)` for a grid, else `(frames, taxels)` | `frame, t_start_ms, taxel_0 ..` |
//! | `write_estimates` | one per run, `estimates.npy`/`.csv` | `(rows, 6 + classes)`, see below | see below |
//!
//! Per-trial files are named after the trial id (characters other than
//! letters, digits, `.`, `-`, `_` become `_`), and beside them `labels.toml`
//! gives each trial's `angle_deg`, `stimulus`, `group` (plus `duration_ms` for
//! spikes) in the label-sidecar format `signal_file` and `spike_file` read, keyed
//! by the ids those sources will give the files. So writing then reading back
//! gives the same data and labels. `info.json` records the rest (sample rate,
//! unit and layout of signals; layout, window, hop and the trials' order of
//! images, which `image_file` reads back).
//!
//! Spikes are written the way `spike_file` reads them: `x` = column, `y` = row
//! for a grid (`x` = taxel index, `y` = 0 otherwise), `t` in `time_unit`
//! (µs by default), `p` = 1. Their NPY default is tonic's event dtype
//! `[('x', '<i2'), ('y', '<i2'), ('t', '<i8'), ('p', '|b1')]` (`|b1` is NumPy's bool), a 1-D structured
//! array that `tonic.transforms` take as it is; `t` is then rounded to a whole
//! number of `time_unit` (µs by default: tonic's convention), so a spike at
//! 12.3456 ms reads back at 12.346 ms. `npy_layout = "float"` writes the older
//! `(events, 4)` float64 array with unrounded times instead.
//!
//! Estimates: one row per (input estimator, trial). CSV columns `source, trial,
//! stimulus, true_angle_deg, group, angle_deg, class_deg, best_frame,
//! decision_time_ms, score_<angle> ...` (one score column per class angle seen
//! in any input; an empty cell is "none": "no edge", no score). The NPY array
//! holds the numeric columns `true_angle_deg, group, angle_deg, class_deg,
//! best_frame, decision_time_ms, scores...` with NaN for "none";
//! `estimates_rows.csv` names each row's source and trial, and
//! `estimates_classes.npy` the score columns' angles.

use super::arrays::npy_bytes;
use super::common::{file_stem_for, sidecar_toml};
use super::spike_file::TimeUnit;
use palpate_core::output::write_atomic;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, Payload, PayloadKind, Signals, Sink,
    SinkContext, SinkInput, SinkReport, Stage, StageConfig, StageError, TaxelLayout, TrialMeta,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::PathBuf;

/// Output file format.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OutFormat {
    /// Comma-separated values with a header row.
    #[default]
    Csv,
    /// NumPy `.npy` (float64).
    Npy,
}

impl OutFormat {
    fn ext(self) -> &'static str {
        match self {
            OutFormat::Csv => "csv",
            OutFormat::Npy => "npy",
        }
    }
}

fn check_dir(dir: &Option<String>) -> Result<(), ConfigError> {
    if let Some(d) = dir {
        let p = std::path::Path::new(d);
        if d.is_empty()
            || p.is_absolute()
            || p.components()
                .any(|c| matches!(c, std::path::Component::ParentDir))
        {
            return Err(ConfigError::key(
                "dir",
                format!("must be a folder name inside the run's output folder, got `{d}`"),
            ));
        }
    }
    Ok(())
}

/// Files to write, relative to the sink's folder.
struct Files {
    dir: PathBuf,
    list: Vec<(String, Vec<u8>)>,
}

impl Files {
    fn new(ctx: &SinkContext<'_>, dir: &Option<String>) -> Self {
        Files {
            dir: ctx.out_dir.join(dir.as_deref().unwrap_or(ctx.stage_id)),
            list: vec![],
        }
    }

    fn add(&mut self, name: String, bytes: Vec<u8>) -> Result<(), StageError> {
        if self.list.iter().any(|(n, _)| *n == name) {
            return Err(StageError::new(format!(
                "two trials would be written to the same file `{name}` (their ids differ only in \
                 characters that are not safe in file names)"
            )));
        }
        self.list.push((name, bytes));
        Ok(())
    }

    fn write(self, what: &str) -> Result<SinkReport, StageError> {
        let mut files = Vec::new();
        for (name, bytes) in &self.list {
            let p = self.dir.join(name);
            write_atomic(&p, bytes)
                .map_err(|e| StageError::new(format!("cannot write {}: {e}", p.display())))?;
            files.push(p);
        }
        Ok(SinkReport {
            text: format!(
                "wrote {what} to {} ({} file{})\n",
                self.dir.display(),
                files.len(),
                if files.len() == 1 { "" } else { "s" }
            ),
            metrics: vec![("files".into(), files.len() as f64)],
            files,
            class_metrics: Vec::new(),
        })
    }
}

fn npy(shape: &[usize], data: &[f64]) -> Result<Vec<u8>, StageError> {
    npy_bytes(shape, data).map_err(|e| StageError::new(format!("cannot encode NPY: {e}")))
}

fn taxel_header(n: usize) -> String {
    (0..n).map(|i| format!("taxel_{i}")).collect::<Vec<_>>().join(",")
}

fn json(v: &serde_json::Value) -> Vec<u8> {
    serde_json::to_vec_pretty(v).unwrap_or_default()
}

fn one_input<'a>(inputs: &'a [SinkInput<'a>]) -> Result<&'a [Item], StageError> {
    inputs
        .first()
        .map(|i| i.items)
        .ok_or_else(|| StageError::new("no input"))
}

macro_rules! simple_sink_config {
    ($(#[$doc:meta])* $name:ident, $type:literal, $kind:expr, $sink:ident) => {
        $(#[$doc])*
        #[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
        #[serde(deny_unknown_fields, default)]
        pub struct $name {
            /// `csv` or `npy`. Default csv.
            pub format: OutFormat,
            /// Folder inside the run's output folder. Default: the sink's id.
            pub dir: Option<String>,
        }

        #[typetag::serde(name = $type)]
        impl StageConfig for $name {
            fn inputs(&self) -> InputSpec {
                InputSpec::one($kind)
            }
            fn output(&self) -> Option<PayloadKind> {
                None
            }
            fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
                check_dir(&self.dir)?;
                Ok(Stage::Sink(Box::new($sink {
                    format: self.format,
                    dir: self.dir.clone(),
                })))
            }
        }
        register_stage!($type, $name);
    };
}

simple_sink_config!(
    /// Writes analog signals, one NPY `(samples, taxels)` or CSV
    /// (`time_ms, taxel_0..`) file per trial, with a `labels.toml` label sidecar
    /// that `signal_file` reads back.
    WriteSignalsConfig,
    "write_signals",
    PayloadKind::Signals,
    SignalsSink
);

simple_sink_config!(
    /// Writes spike images, one NPY `(frames, rows, cols)` or CSV
    /// (`frame, t_start_ms, taxel_0..`) file per trial, with `labels.toml` and
    /// `info.json`, which `image_file` reads back.
    WriteImagesConfig,
    "write_images",
    PayloadKind::Images,
    ImagesSink
);

struct SignalsSink {
    format: OutFormat,
    dir: Option<String>,
}

impl Sink for SignalsSink {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let items = one_input(inputs)?;
        let mut files = Files::new(ctx, &self.dir);
        let mut rows = Vec::new();
        let mut info = None;
        for it in items {
            let s = it.payload.signals()?;
            let stem = file_stem_for(&it.meta.trial_id);
            let bytes = match self.format {
                OutFormat::Npy => signals_npy(s)?,
                OutFormat::Csv => signals_csv(s).into_bytes(),
            };
            files.add(format!("{stem}.{}", self.format.ext()), bytes)?;
            rows.push((stem, &*it.meta, None));
            info.get_or_insert_with(|| {
                serde_json::json!({
                    "sample_rate_hz": s.sample_rate_hz,
                    "unit": s.unit,
                    "layout": s.layout,
                    "format": self.format.ext(),
                })
            });
        }
        let layout = items.first().and_then(|it| payload_layout(&it.payload));
        // The rate goes into labels.toml too, so that `signal_file` reads
        // NPY files back without a `sample_rate_hz` key (when every trial
        // has the same rate; one source has one rate).
        let rate = super::common::shared_rate(
            items
                .iter()
                .filter_map(|it| it.payload.signals().ok().map(|s| s.sample_rate_hz)),
        );
        finish_with_sidecar(files, &rows, info, layout, rate, "signals")
    }
}

/// One trial's signals as NPY bytes: float64 `(samples, taxels)`.
pub fn signals_npy(s: &Signals) -> Result<Vec<u8>, StageError> {
    let (n, m) = (s.data.len(), s.n_samples());
    let mut flat = Vec::with_capacity(n * m);
    for k in 0..m {
        flat.extend(s.data.iter().map(|col| col[k]));
    }
    npy(&[m, n], &flat)
}

/// One trial's signals as CSV text: `time_ms, taxel_0 .. taxel_{N-1}`, one row
/// per sample, numbers in round-trip form (what `signal_file` reads).
pub fn signals_csv(s: &Signals) -> String {
    let mut out = format!("time_ms,{}\n", taxel_header(s.data.len()));
    for k in 0..s.n_samples() {
        let _ = write!(out, "{}", k as f64 * 1000.0 / s.sample_rate_hz);
        for col in &s.data {
            let _ = write!(out, ",{}", col[k]);
        }
        out.push('\n');
    }
    out
}

/// The layout a signals, spikes or images payload carries (estimates carry none).
fn payload_layout(p: &Payload) -> Option<&TaxelLayout> {
    match p {
        Payload::Signals(s) => Some(&s.layout),
        Payload::Spikes(s) => Some(&s.layout),
        Payload::Images(im) => Some(&im.layout),
        Payload::Estimate(_) => None,
    }
}

fn finish_with_sidecar(
    mut files: Files,
    rows: &[(String, &TrialMeta, Option<f64>)],
    info: Option<serde_json::Value>,
    layout: Option<&TaxelLayout>,
    sample_rate_hz: Option<f64>,
    what: &str,
) -> Result<SinkReport, StageError> {
    files.add(
        "labels.toml".into(),
        sidecar_toml(rows, layout, sample_rate_hz).into_bytes(),
    )?;
    if let Some(info) = info {
        files.add("info.json".into(), json(&info))?;
    }
    let n = rows.len();
    files.write(&format!("{n} trial{} of {what}", if n == 1 { "" } else { "s" }))
}

struct ImagesSink {
    format: OutFormat,
    dir: Option<String>,
}

impl Sink for ImagesSink {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let items = one_input(inputs)?;
        let mut files = Files::new(ctx, &self.dir);
        let mut rows = Vec::new();
        let mut info = None;
        for it in items {
            let im = it.payload.images()?;
            let n = im.n_taxels();
            let stem = file_stem_for(&it.meta.trial_id);
            let bytes = match self.format {
                OutFormat::Npy => {
                    let shape = match im.layout.grid() {
                        Some((r, c)) => vec![im.n_frames, r, c],
                        None => vec![im.n_frames, n],
                    };
                    npy(&shape, &im.counts)?
                }
                OutFormat::Csv => {
                    let mut out = format!("frame,t_start_ms,{}\n", taxel_header(n));
                    for k in 0..im.n_frames {
                        let _ = write!(out, "{k},{}", k as f64 * im.hop_ms);
                        for v in im.frame(k) {
                            let _ = write!(out, ",{v}");
                        }
                        out.push('\n');
                    }
                    out.into_bytes()
                }
            };
            files.add(format!("{stem}.{}", self.format.ext()), bytes)?;
            rows.push((stem, &*it.meta, None));
            info.get_or_insert_with(|| {
                serde_json::json!({
                    "layout": im.layout,
                    "window_ms": im.window_ms,
                    "hop_ms": im.hop_ms,
                    "format": self.format.ext(),
                })
            });
        }
        // The trials' order, so that `image_file` gives them back in it.
        if let Some(serde_json::Value::Object(o)) = info.as_mut() {
            let stems: Vec<&str> = rows.iter().map(|(s, _, _)| s.as_str()).collect();
            o.insert("trials".into(), serde_json::json!(stems));
        }
        let layout = items.first().and_then(|it| payload_layout(&it.payload));
        finish_with_sidecar(files, &rows, info, layout, None, "spike images")
    }
}

/// Writes spike events, one NPY or CSV file per trial with fields `x, y, t, p`
/// (x = column, y = row, t in `time_unit`), as `spike_file` reads them. NPY
/// holds tonic's structured event dtype by default.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct WriteSpikesConfig {
    /// `csv` or `npy`. Default csv.
    pub format: OutFormat,
    /// Folder inside the run's output folder. Default: the sink's id.
    pub dir: Option<String>,
    /// Unit of `t`: `us`, `ms` or `s`. Default us (tonic's convention).
    pub time_unit: TimeUnit,
    /// Layout of NPY files: `structured` (tonic's dtype: `x`, `y` int16, `t`
    /// int64 rounded to whole `time_unit`s, `p` bool; one record per event) or
    /// `float` (an `(events, 4)` float64 array, times unrounded). Default
    /// structured. Ignored for CSV.
    pub npy_layout: NpyLayout,
}

/// How `write_spikes` lays out NPY files.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum NpyLayout {
    /// tonic's structured event dtype `[x <i2, y <i2, t <i8, p ?]`.
    #[default]
    Structured,
    /// A plain `(events, 4)` float64 array.
    Float,
}

/// tonic's event dtype, as an NPY `descr`.
pub const TONIC_DESCR: &str = "[('x', '<i2'), ('y', '<i2'), ('t', '<i8'), ('p', '|b1')]";

/// Encodes events as a 1-D structured NPY array of tonic's dtype ([`TONIC_DESCR`]);
/// `events` are `(x, y, t, p)` with `t` already in the file's unit. Fails, naming
/// the value, when a coordinate does not fit int16 or a time does not fit int64.
pub fn tonic_npy(events: &[(f64, f64, f64, bool)]) -> Result<Vec<u8>, StageError> {
    let header = format!(
        "{{'descr': {TONIC_DESCR}, 'fortran_order': False, 'shape': ({},), }}",
        events.len()
    );
    // Magic (6) + version (2) + header length (2) + header + '\n', padded with
    // spaces to a multiple of 64 bytes, as NPY 1.0 asks.
    let unpadded = 10 + header.len() + 1;
    let pad = (64 - unpadded % 64) % 64;
    let hlen = u16::try_from(header.len() + pad + 1)
        .map_err(|_| StageError::new("cannot encode NPY: header too long"))?;
    let mut out = Vec::with_capacity(unpadded + pad + events.len() * 13);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&hlen.to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend(std::iter::repeat_n(b' ', pad));
    out.push(b'\n');
    for &(x, y, t, p) in events {
        let coord = |v: f64, name: &str| -> Result<i16, StageError> {
            if v.fract() == 0.0 && v >= f64::from(i16::MIN) && v <= f64::from(i16::MAX) {
                Ok(v as i16)
            } else {
                Err(StageError::new(format!(
                    "cannot write `{name}` = {v} as int16 (tonic's dtype); use npy_layout = \"float\""
                )))
            }
        };
        let t = t.round();
        // 2^63 is exactly representable; anything at or above it (or NaN) does not fit.
        if !(-9.223_372_036_854_776e18..9.223_372_036_854_776e18).contains(&t) {
            return Err(StageError::new(format!("cannot write time {t} as int64")));
        }
        out.extend_from_slice(&coord(x, "x")?.to_le_bytes());
        out.extend_from_slice(&coord(y, "y")?.to_le_bytes());
        out.extend_from_slice(&(t as i64).to_le_bytes());
        out.push(u8::from(p));
    }
    Ok(out)
}

#[typetag::serde(name = "write_spikes")]
impl StageConfig for WriteSpikesConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_dir(&self.dir)?;
        Ok(Stage::Sink(Box::new(SpikesSink { cfg: self.clone() })))
    }
}
register_stage!("write_spikes", WriteSpikesConfig);

struct SpikesSink {
    cfg: WriteSpikesConfig,
}

/// `(x, y)` of a taxel as event tools number it.
fn event_xy(layout: &TaxelLayout, taxel: u32) -> (f64, f64) {
    match layout.grid() {
        Some((_, cols)) => ((taxel as usize % cols) as f64, (taxel as usize / cols) as f64),
        None => (f64::from(taxel), 0.0),
    }
}

impl Sink for SpikesSink {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let items = one_input(inputs)?;
        let mut files = Files::new(ctx, &self.cfg.dir);
        let mut rows = Vec::new();
        let per_ms = 1.0 / self.cfg.time_unit.to_ms();
        for it in items {
            let s = it.payload.spikes()?;
            let stem = file_stem_for(&it.meta.trial_id);
            let bytes = match self.cfg.format {
                OutFormat::Npy if self.cfg.npy_layout == NpyLayout::Structured => {
                    let events: Vec<(f64, f64, f64, bool)> = s
                        .events
                        .iter()
                        .map(|e| {
                            let (x, y) = event_xy(&s.layout, e.taxel);
                            (x, y, e.t_ms * per_ms, true)
                        })
                        .collect();
                    tonic_npy(&events)
                        .map_err(|e| StageError::new(format!("trial `{}`: {e}", it.meta.trial_id)))?
                }
                OutFormat::Npy => {
                    let mut flat = Vec::with_capacity(s.events.len() * 4);
                    for e in &s.events {
                        let (x, y) = event_xy(&s.layout, e.taxel);
                        flat.extend([x, y, e.t_ms * per_ms, 1.0]);
                    }
                    npy(&[s.events.len(), 4], &flat)?
                }
                OutFormat::Csv => {
                    let mut out = String::from("x,y,t,p\n");
                    for e in &s.events {
                        let (x, y) = event_xy(&s.layout, e.taxel);
                        let _ = writeln!(out, "{x},{y},{},1", e.t_ms * per_ms);
                    }
                    out.into_bytes()
                }
            };
            files.add(format!("{stem}.{}", self.cfg.format.ext()), bytes)?;
            rows.push((stem, &*it.meta, Some(s.duration_ms)));
        }
        let info = items.first().map(|it| {
            let layout = it.payload.spikes().map(|s| s.layout.clone()).ok();
            serde_json::json!({
                "layout": layout,
                "time_unit": self.cfg.time_unit,
                "format": self.cfg.format.ext(),
                "npy_layout": self.cfg.npy_layout,
            })
        });
        let layout = items.first().and_then(|it| payload_layout(&it.payload));
        finish_with_sidecar(files, &rows, info, layout, None, "spikes")
    }
}

/// Writes orientation estimates of every input estimator, one table per run
/// (`estimates.csv` or `estimates.npy`), with true labels and every class score.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct WriteEstimatesConfig {
    /// `csv` or `npy`. Default csv.
    pub format: OutFormat,
    /// Folder inside the run's output folder. Default: the sink's id.
    pub dir: Option<String>,
}

#[typetag::serde(name = "write_estimates")]
impl StageConfig for WriteEstimatesConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::many(PayloadKind::Estimates)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_dir(&self.dir)?;
        Ok(Stage::Sink(Box::new(EstimatesSink { cfg: self.clone() })))
    }
}
register_stage!("write_estimates", WriteEstimatesConfig);

struct EstimatesSink {
    cfg: WriteEstimatesConfig,
}

fn cell(v: Option<f64>) -> String {
    v.map(|x| x.to_string()).unwrap_or_default()
}

impl Sink for EstimatesSink {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        // Score columns: every class angle any input uses, in order of first use.
        let mut classes: Vec<f64> = Vec::new();
        let mut col_of: HashMap<u64, usize> = HashMap::new();
        for inp in inputs {
            for it in inp.items {
                for s in &it.payload.estimate()?.scores {
                    col_of.entry(s.angle_deg.to_bits()).or_insert_with(|| {
                        classes.push(s.angle_deg);
                        classes.len() - 1
                    });
                }
            }
        }
        let mut files = Files::new(ctx, &self.cfg.dir);
        let mut n_rows = 0;
        let mut csv = String::from(
            "source,trial,stimulus,true_angle_deg,group,angle_deg,class_deg,best_frame,decision_time_ms",
        );
        for c in &classes {
            let _ = write!(csv, ",score_{c}");
        }
        csv.push('\n');
        let mut rows_csv = String::from("row,source,trial,stimulus\n");
        let width = 6 + classes.len();
        let mut flat = Vec::new();
        for inp in inputs {
            for it in inp.items {
                let e = it.payload.estimate()?;
                let m = &it.meta;
                let mut scores = vec![None; classes.len()];
                for s in &e.scores {
                    scores[col_of[&s.angle_deg.to_bits()]] = Some(s.score);
                }
                let best = e.best_frame.map(|b| b as f64);
                let _ = write!(
                    csv,
                    "{},{},{},{},{},{},{},{},{}",
                    inp.stage_id,
                    m.trial_id,
                    m.label.stimulus,
                    cell(m.label.angle_deg),
                    m.group,
                    cell(e.angle_deg),
                    cell(e.class_deg),
                    cell(best),
                    cell(e.decision_time_ms)
                );
                for s in &scores {
                    let _ = write!(csv, ",{}", cell(*s));
                }
                csv.push('\n');
                let _ = writeln!(
                    rows_csv,
                    "{n_rows},{},{},{}",
                    inp.stage_id, m.trial_id, m.label.stimulus
                );
                let nan = f64::NAN;
                flat.extend([
                    m.label.angle_deg.unwrap_or(nan),
                    m.group as f64,
                    e.angle_deg.unwrap_or(nan),
                    e.class_deg.unwrap_or(nan),
                    best.unwrap_or(nan),
                    e.decision_time_ms.unwrap_or(nan),
                ]);
                flat.extend(scores.iter().map(|s| s.unwrap_or(nan)));
                n_rows += 1;
            }
        }
        match self.cfg.format {
            OutFormat::Csv => files.add("estimates.csv".into(), csv.into_bytes())?,
            OutFormat::Npy => {
                files.add("estimates.npy".into(), npy(&[n_rows, width], &flat)?)?;
                files.add("estimates_rows.csv".into(), rows_csv.into_bytes())?;
                files.add("estimates_classes.npy".into(), npy(&[classes.len()], &classes)?)?;
            }
        }
        files.write(&format!("{n_rows} estimates"))
    }
}

#[cfg(test)]
mod tests {
    use super::super::arrays::{read_npy, NpyContent};
    use super::*;

    #[test]
    fn tonic_npy_reads_back_as_its_structured_dtype() {
        let events = [
            (0.0, 3.0, 250.0, true),
            (3.0, 0.0, 1_000_000.4, true),
            (1.0, 2.0, 7.6, false),
        ];
        let bytes = tonic_npy(&events).unwrap();
        // NPY 1.0: the data starts on a 64-byte boundary, 13 bytes per record.
        let hlen = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
        assert_eq!((10 + hlen) % 64, 0);
        assert_eq!(bytes.len(), 10 + hlen + 3 * 13);
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(
            header.contains(TONIC_DESCR) && header.contains("'shape': (3,)"),
            "{header}"
        );
        let NpyContent::Record(cols) = read_npy(&bytes, "e.npy").unwrap() else {
            panic!("not a structured array")
        };
        let names: Vec<&str> = cols.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["x", "y", "t", "p"]);
        assert_eq!(cols[0].1, vec![0.0, 3.0, 1.0]);
        assert_eq!(cols[1].1, vec![3.0, 0.0, 2.0]);
        // Times are rounded to whole units.
        assert_eq!(cols[2].1, vec![250.0, 1_000_000.0, 8.0]);
        assert_eq!(cols[3].1, vec![1.0, 1.0, 0.0]);
        assert_eq!(tonic_npy(&[]).unwrap().len(), 10 + hlen);
    }

    #[test]
    fn tonic_npy_refuses_what_its_dtype_cannot_hold() {
        for bad in [
            (40_000.0, 0.0, 0.0, true),
            (0.5, 0.0, 0.0, true),
            (0.0, -40_000.0, 0.0, true),
            (0.0, 0.0, f64::NAN, true),
            (0.0, 0.0, 1e19, true),
            (0.0, 0.0, f64::INFINITY, true),
        ] {
            assert!(tonic_npy(&[bad]).is_err(), "{bad:?}");
        }
    }
}
