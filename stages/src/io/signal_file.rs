//! The `signal_file` source: analog taxel recordings from CSV, NPY, NPZ, MATLAB
//! `.mat` files and raw DAQ streams.
//!
//! Every sample must be finite: a NaN or infinite sample is an error naming the
//! file and the position (CSV: line and column; NPY/NPZ: the array and its
//! 0-based `[sample, taxel]` index; MAT: the variable and its 1-based MATLAB
//! subscripts). Nothing is silently dropped, filled or resampled.
//!
//! ## Formats
//!
//! **CSV** (`.csv`): a header row, then one row per sample. Columns:
//!
//! | column | meaning |
//! |---|---|
//! | `taxel_0` ... `taxel_{N-1}` | one per taxel of `layout` (any order); or the names listed in `columns`, in taxel order |
//! | `time_ms` or `time_s` | optional sample time; gives the sample rate (checked uniform to a quarter sample) |
//! | `trial` | optional trial name: rows with the same value form one trial (many trials per file) |
//! | `angle_deg`, `stimulus`, `group`, `speed_mm_s` | optional labels, constant within a trial |
//!
//! Any other column is an error (it would otherwise be silently ignored),
//! unless `ignore_columns` lists it. The delimiter is `,`, or `;` or a tab
//! when the header has no comma (spreadsheets in decimal-comma locales,
//! loggers writing TSV); numbers use a decimal point. A delimiter ending
//! the header line and every row (loggers printing `v,` per value) is no
//! column; a value after it is an error. The
//! file must end with a line end: a last line without one is taken as a file
//! cut while being written (its last number may have lost digits).
//! Lines starting with `#` are comments.
//!
//! **NPY** (`.npy`): one trial per file, a 2-D array `(samples, taxels)`; a 3-D
//! array `(trials, samples, taxels)` holds many trials. With
//! `taxel_major = true` the last two axes swap: `(taxels, samples)`.
//!
//! **NPZ** (`.npz`, `np.savez` or `np.savez_compressed`): reserved arrays
//! `sample_rate_hz` (one value), `angle_deg`, `group` and `speed_mm_s` (one
//! value per trial, in trial order); every other array (or only those named in `variables`) is
//! data: 2-D = one trial, 3-D = a stack of trials, shaped as for NPY.
//!
//! **MAT** (`.mat`, MATLAB v5/v7, and v7.3, which is HDF5: see [`super::arrays`]): the same
//! reserved variables (`fs` is accepted for `sample_rate_hz`); data variables
//! are `data(sample, taxel)` for one trial or `data(sample, taxel, trial)` for a
//! stack (MATLAB's natural order: trial last), transposed by `taxel_major`
//! like NPY.
//!
//! **DAQ** (`.daq`, `.bin`): a raw byte stream recorded by the DAQ acquisition
//! (see `docs/daq-protocol.md`), decoded frame by frame; one trial per file.
//! The sample rate comes from the frames' timestamps (median interval), which
//! must lie on a uniform grid (to a quarter sample, as a CSV time column;
//! a decrease, a rate change or alternating intervals are errors naming the
//! frame), and every frame must keep the first one's sample format. Lost
//! frames (sequence gaps) and CRC errors are an error naming their count,
//! unless `fill_gaps = true`, which holds each lost frame at the previous
//! frame's values (the gap count is still in the error-free report), for at
//! most as many lost frames as were received. A recording that ends inside a
//! frame is an error unless `allow_cut_end = true` (a live recording stopped
//! mid-frame); frames of another channel count and samples that are not
//! finite are always errors.
//!
//! ## Trials, ids, rates
//!
//! A file holding one trial gives the trial id `<file>` (its stem; when two
//! files share a stem, the path relative to their common folder). A file with
//! many gives `<file>-<name>`, where `<name>` is the CSV `trial` value, the
//! NPZ/MAT array name, or, within a stack, the 0-based index (`<file>-<array>-<k>`
//! when an archive has several stacks). Ids must be unique across all files.
//!
//! The sample rate is the `sample_rate_hz` key if given, else the one the
//! `labels` file declares (a top-level `sample_rate_hz`, which the
//! `labels.toml` of `palpate simulate` and `write_signals` and a
//! `trials.json` carry; a key and a label file that disagree are an error).
//! A file that carries its own rate (a time column, a `sample_rate_hz`
//! variable, DAQ timestamps) must agree with it (within 0.1 %). Without
//! either, every file must carry a rate and all must agree: mixing rates in
//! one source is an error, since downstream stages assume one rate.
//!
//! ## One recording, many palpations (`segment`)
//!
//! A continuous log of several palpations is cut into trials by the rules
//! the `daq` source applies to a live stream (`segment = "contact"`): with
//! `m_k` the lowest taxel of sample `k`, a trial starts at the first of
//! `N_in = round(enter_ms · fs / 1000)` consecutive samples with `m_k <=
//! contact_v` (those samples included) and ends before the first of `N_out
//! = round(exit_ms · fs / 1000)` consecutive samples with `m_k >=
//! release_v` (hysteresis: `release_v > contact_v`; the output falls with
//! pressure, as a piezoresistive divider's does). `segment = "fixed"` cuts
//! consecutive windows of `window_ms` instead (the last may be shorter).
//! Segment `j` (0-based) of a trial with id `<id>` gets the id `<id>-<j>`
//! and the file's labels, which a sidecar entry for `<id>-<j>` overrides, so
//! each palpation of one log can carry its own angle. A sensor whose output
//! rises with pressure sets `contact_polarity = "rises"`: the rules apply to
//! the highest taxel with the inequalities turned (`m_k >= contact_v` starts,
//! `m_k <= release_v < contact_v` ends, as the `daq` source does). A recording in which no contact segment starts is
//! an error that gives the range of its lowest (highest) taxel and its
//! longest run past `contact_v`, so the threshold can be set.

use super::arrays::{read_mat, read_npy_plain, read_npz, NdArray, NpyContent};
use super::common::{
    apply_sidecar, build_metas, expand_paths, file_ids, merge_consistent, number_error, read_sidecar,
    resolve_layout, set_label_cell, stated_layout, user_csv_reader, LayoutConfig, TrialLabels, LABEL_COLUMNS,
};
use super::daq::source::{Polarity, SegEvent, SegmentPlan, Segmenter};
use palpate_core::{
    check_positive, check_range, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec,
    Inspection, OutputFacts, Payload, PayloadKind, Signals, Source, Stage, StageConfig, StageError,
    TaxelLayout, TrialContext, TrialMeta,
};
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// File format of a recording.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SignalFormat {
    /// By extension: `.csv`, `.npy`, `.npz`, `.mat`, `.daq`/`.bin`.
    #[default]
    Auto,
    /// Comma-separated values with a header row.
    Csv,
    /// A NumPy array.
    Npy,
    /// A NumPy archive of arrays.
    Npz,
    /// A MATLAB v5/v7 file.
    Mat,
    /// A raw DAQ byte stream (docs/daq-protocol.md).
    Daq,
}

/// Analog taxel signals read from recordings (CSV, NPY, NPZ, MATLAB .mat, raw
/// DAQ streams).
///
/// One trial per file or many per file; labels from the file or a sidecar; any
/// taxel layout; the formats and label files are in the user guide's "File
/// formats and label files" page (docs/guide/src/formats.md).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SignalFileConfig {
    /// A file or glob pattern (e.g. `recordings/*.csv`), relative to the graph
    /// file's folder. Default none; give `path`, `paths` or both.
    pub path: Option<String>,
    /// More files or glob patterns, read after `path`, in order. Default empty.
    pub paths: Vec<String>,
    /// File format: `auto` (by extension), `csv`, `npy`, `npz`, `mat`, `daq`. Default auto.
    pub format: SignalFormat,
    /// Sample rate, Hz. Required unless the `labels` file declares it (as
    /// `palpate simulate` and `write_signals` write it) or every file
    /// carries its own (a time column, a `sample_rate_hz` variable, DAQ
    /// timestamps). Default none.
    pub sample_rate_hz: Option<f64>,
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
    /// Unit of the samples, e.g. `V`. Default `V`.
    pub unit: String,
    /// Label sidecar (TOML, CSV, or a `trials.json` from `palpate simulate`)
    /// mapping trial id to angle, stimulus, group.
    /// Default none (labels from the files, if any).
    pub labels: Option<String>,
    /// CSV: names of the taxel columns in taxel order, instead of `taxel_0..`.
    /// Default empty.
    pub columns: Vec<String>,
    /// CSV: columns to skip, e.g. a force or trigger channel, or a time
    /// column stamped by a host clock that jitters (then set
    /// `sample_rate_hz`). Any other column the reader does not know is an
    /// error, so a misspelt or surplus taxel column is never dropped
    /// silently. Default empty.
    pub ignore_columns: Vec<String>,
    /// NPZ/MAT: names of the data arrays to read; empty = every array that is
    /// not a reserved label or rate variable. Default empty.
    pub variables: Vec<String>,
    /// NPY/NPZ/MAT: data arrays are `(taxels, samples)` rather than `(samples,
    /// taxels)`. Default false.
    pub taxel_major: bool,
    /// DAQ: hold the previous frame's values over lost frames instead of
    /// failing. Default false.
    pub fill_gaps: bool,
    /// DAQ: accept a recording whose last frame is incomplete (a live
    /// recording stopped mid-frame); that frame is dropped. Without it a cut
    /// last frame is an error, as a CSV cut mid-line is. Default false.
    pub allow_cut_end: bool,
    /// DAQ: decoded value = raw * `daq_scale` + `daq_offset` (e.g. volts per ADC
    /// count). Default 1.
    pub daq_scale: f64,
    /// DAQ: see `daq_scale`. Default 0.
    pub daq_offset: f64,
    /// Cut each recording into trials: `none` (each file, CSV `trial` or
    /// array is one trial), `contact` (a trial per stretch of contact, as
    /// the `daq` source cuts a live stream: `contact_v`, `release_v`,
    /// `enter_ms`, `exit_ms`), or `fixed` (windows of `window_ms`); see the
    /// module docs. Default none.
    pub segment: FileSegment,
    /// `segment = "contact"`: contact starts when the lowest taxel reads at
    /// most this, in the files' unit (V for the paper's divider). Default 3.0.
    pub contact_v: f64,
    /// `segment = "contact"`: contact ends when the lowest taxel reads at
    /// least this, in the files' unit; above `contact_v`. Default 3.2.
    pub release_v: f64,
    /// `segment = "contact"`: samples under `contact_v` needed to start a
    /// trial, as a duration, ms. Default 20.
    pub enter_ms: f64,
    /// `segment = "contact"`: samples over `release_v` needed to end it, ms. Default 200.
    pub exit_ms: f64,
    /// `segment = "fixed"`: the length of each trial, ms. Default none (required then).
    pub window_ms: Option<f64>,
    /// `segment = "contact"`: how the output moves with pressure: `falls`
    /// (a piezoresistive divider, as the paper's: contact at the lowest
    /// taxel <= `contact_v`, release at >= `release_v`) or `rises` (contact
    /// at the highest taxel >= `contact_v`, release at <= `release_v`, then
    /// below `contact_v`). Default falls.
    pub contact_polarity: Polarity,
}

/// How `signal_file` cuts a recording into trials (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum FileSegment {
    /// Each file (or CSV `trial`, or array) is a trial.
    #[default]
    None,
    /// A trial per stretch of contact.
    Contact,
    /// Consecutive windows of `window_ms`.
    Fixed,
}

impl Default for SignalFileConfig {
    fn default() -> Self {
        SignalFileConfig {
            path: None,
            paths: vec![],
            format: SignalFormat::Auto,
            sample_rate_hz: None,
            layout: None,
            unit: "V".into(),
            labels: None,
            columns: vec![],
            ignore_columns: vec![],
            variables: vec![],
            taxel_major: false,
            fill_gaps: false,
            allow_cut_end: false,
            daq_scale: 1.0,
            daq_offset: 0.0,
            segment: FileSegment::None,
            contact_v: 3.0,
            release_v: 3.2,
            enter_ms: 20.0,
            exit_ms: 200.0,
            window_ms: None,
            contact_polarity: Polarity::Falls,
        }
    }
}

#[typetag::serde(name = "signal_file")]
impl StageConfig for SignalFileConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Source(Box::new(self.source(ctx)?)))
    }
    /// The sample rate when the `sample_rate_hz` key gives it (the files
    /// must then agree with it), and the array when the `layout` key gives
    /// it; unknown until the files are read otherwise.
    fn inspect(&self, _ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        Inspection {
            facts: OutputFacts {
                sample_rate_hz: self.sample_rate_hz,
                layout: stated_layout(&self.layout),
            },
            ..Inspection::default()
        }
    }
}
register_stage!("signal_file", SignalFileConfig);

impl SignalFileConfig {
    /// Checks the config and makes the (not yet loaded) source.
    fn source(&self, ctx: &BuildContext) -> Result<SignalFileSource, ConfigError> {
        let mut c = ConfigChecks::new();
        if let Some(r) = self.sample_rate_hz {
            c.take(check_positive("sample_rate_hz", r, "Hz"));
        }
        if !(self.daq_scale.is_finite() && self.daq_scale != 0.0 && self.daq_offset.is_finite()) {
            c.push(ConfigError::key(
                "daq_scale",
                "scale must be finite and non-zero, offset finite",
            ));
        }
        match self.segment {
            FileSegment::None => {}
            FileSegment::Contact => {
                self.contact_polarity
                    .check_thresholds(&mut c, self.contact_v, self.release_v, "file units");
                c.take(check_range("enter_ms", self.enter_ms, 0.0, 3.6e6, "ms"));
                c.take(check_range("exit_ms", self.exit_ms, 0.0, 3.6e6, "ms"));
            }
            FileSegment::Fixed => match self.window_ms {
                Some(w) => {
                    c.take(check_range("window_ms", w, 1e-3, 3.6e6, "ms"));
                }
                None => c.push(ConfigError::key(
                    "window_ms",
                    "required with segment = \"fixed\": the length of each trial, ms",
                )),
            },
        }
        let entries: Vec<String> = self.path.iter().chain(&self.paths).cloned().collect();
        let key = if self.path.is_some() { "path" } else { "paths" };
        let files = c
            .take(expand_paths(&entries, |p| ctx.resolve(p), key))
            .unwrap_or_default();
        // One message for the format, however many files it cannot tell.
        if let Some(m) = files.iter().find_map(|f| format_of(self.format, f).err()) {
            c.push(ConfigError::key("format", m));
        }
        let labels = self.labels.as_ref().map(|l| ctx.resolve(Path::new(l)));
        if let Some(l) = &labels {
            c.take(super::common::check_regular_file(l, "labels"));
        }
        // A signal file's column count checks the layout: no default to flag.
        let layout = c
            .take(resolve_layout("layout", self.layout.as_ref(), labels.as_deref()))
            .map(|(l, _)| l);
        let n_taxels = layout.as_ref().map_or(self.columns.len(), TaxelLayout::len);
        if !self.columns.is_empty() && self.columns.len() != n_taxels {
            c.push(ConfigError::key(
                "columns",
                format!(
                    "lists {} names but the layout has {} taxels",
                    self.columns.len(),
                    n_taxels
                ),
            ));
        }
        c.finish()?;
        let layout = layout.ok_or_else(|| ConfigError::key("layout", "not a layout"))?;
        Ok(SignalFileSource {
            cfg: self.clone(),
            layout,
            files,
            labels,
            loaded: OnceLock::new(),
        })
    }
}

/// Reads every trial `cfg` names, outside a graph (e.g. the CLI's
/// `palpate daq emulate <recording>`): relative paths resolve against
/// `base_dir`. Same checks and errors as the `signal_file` stage.
pub fn read_signal_files(
    cfg: &SignalFileConfig,
    base_dir: &Path,
) -> Result<Vec<(TrialMeta, Arc<Signals>)>, StageError> {
    let ctx = BuildContext {
        stage_id: "signal_file".into(),
        seed: 0,
        out_dir: base_dir.to_path_buf(),
        base_dir: base_dir.to_path_buf(),
    };
    cfg.source(&ctx)?.load()
}

/// Appended to a taxel-count mismatch: where the layout comes from.
const LAYOUT_HINT: &str =
    "; the stage's `layout` key, or a `[layout]` table in the label sidecar, declares the recorded array";

/// The format of `path` under setting `f`.
pub fn format_of(f: SignalFormat, path: &Path) -> Result<SignalFormat, String> {
    if f != SignalFormat::Auto {
        return Ok(f);
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    Ok(match ext.as_str() {
        "csv" | "txt" => SignalFormat::Csv,
        "npy" => SignalFormat::Npy,
        "npz" => SignalFormat::Npz,
        "mat" => SignalFormat::Mat,
        "daq" | "bin" => SignalFormat::Daq,
        _ => {
            return Err(format!(
                "cannot tell the format of {} from its extension; set `format`",
                path.display()
            ))
        }
    })
}

/// Every trial, read once and shared.
type Loaded = Vec<(TrialMeta, Arc<Signals>)>;

struct SignalFileSource {
    cfg: SignalFileConfig,
    layout: TaxelLayout,
    files: Vec<PathBuf>,
    labels: Option<PathBuf>,
    loaded: OnceLock<Result<Loaded, StageError>>,
}

/// One trial as read from a file, before labels and rates are settled.
#[derive(Clone, Debug)]
pub struct RawTrial {
    /// Trial id.
    pub id: String,
    /// Labels the file gives.
    pub labels: TrialLabels,
    /// `data[taxel][sample]`.
    pub data: Vec<Vec<f64>>,
    /// Sample rate the file carries, Hz.
    pub rate_hz: Option<f64>,
    /// Where the trial came from, for messages.
    pub origin: String,
}

impl SignalFileSource {
    fn load(&self) -> Result<Loaded, StageError> {
        let ids = file_ids(&self.files);
        let per_file: Vec<Result<Vec<RawTrial>, String>> = self
            .files
            .par_iter()
            .zip(ids.par_iter())
            .map(|(f, id)| read_signal_file(f, id, &self.cfg, self.layout.len()))
            .collect();
        let mut raw = Vec::new();
        for r in per_file {
            raw.extend(r.map_err(StageError::new)?);
        }
        // Settle the sample rate: the key, else the label file's (as
        // `palpate simulate` and `write_signals` write it), else the files'.
        let tol = |a: f64, b: f64| (a - b).abs() <= 1e-3 * a.abs().max(b.abs());
        let side = match &self.labels {
            Some(p) => super::common::read_sidecar_rate(p)
                .map_err(StageError::new)?
                .map(|r| (r, format!("the label file {}", p.display()))),
            None => None,
        };
        let declared = match (self.cfg.sample_rate_hz, side) {
            // Like the layout: a key and a label file that disagree describe
            // two recordings; neither is chosen silently.
            (Some(r), Some((sr, from))) if !tol(r, sr) => {
                return Err(StageError::new(format!(
                    "`sample_rate_hz` is {r} Hz but {from} declares {sr} Hz; remove the key or correct it"
                )))
            }
            (Some(r), _) => Some((r, "`sample_rate_hz`".to_string())),
            (None, side) => side,
        };
        let rate = match declared {
            Some((r, from)) => {
                if let Some(t) = raw.iter().find(|t| t.rate_hz.is_some_and(|fr| !tol(fr, r))) {
                    return Err(StageError::new(format!(
                        "{} has a sample rate of {} Hz but {from} says {r} Hz",
                        t.origin,
                        t.rate_hz.unwrap_or(f64::NAN)
                    )));
                }
                r
            }
            None => {
                if let Some(t) = raw.iter().find(|t| t.rate_hz.is_none()) {
                    return Err(StageError::new(format!(
                        "{} carries no sample rate; set `sample_rate_hz` (or give `labels` a label \
                         file that declares it, as `palpate simulate` and `write_signals` write)",
                        t.origin
                    )));
                }
                let first = &raw[0];
                let r0 = first.rate_hz.unwrap_or(f64::NAN);
                if let Some(t) = raw.iter().find(|t| !tol(t.rate_hz.unwrap_or(f64::NAN), r0)) {
                    return Err(StageError::new(format!(
                        "mismatched sample rates: {} is at {r0} Hz but {} is at {} Hz; \
                         one source must have one rate (resample, or use two sources)",
                        first.origin,
                        t.origin,
                        t.rate_hz.unwrap_or(f64::NAN)
                    )));
                }
                r0
            }
        };
        let raw = match self.plan(rate) {
            Some(plan) => segment_trials(raw, plan, &self.cfg).map_err(StageError::new)?,
            None => raw,
        };
        let mut labelled: Vec<(String, TrialLabels)> =
            raw.iter().map(|t| (t.id.clone(), t.labels.clone())).collect();
        if let Some(p) = &self.labels {
            let side = read_sidecar(p)?;
            apply_sidecar(&mut labelled, &side, p)?;
        }
        let origins: Vec<String> = raw.iter().map(|t| t.origin.clone()).collect();
        let metas = build_metas(&labelled, &origins)?;
        Ok(metas
            .into_iter()
            .zip(raw)
            .map(|(m, t)| {
                let s = Signals {
                    sample_rate_hz: rate,
                    layout: self.layout.clone(),
                    unit: self.cfg.unit.clone(),
                    data: t.data,
                };
                (m, Arc::new(s))
            })
            .collect())
    }

    /// The segmentation at `fs` Hz, if the config asks for one.
    fn plan(&self, fs: f64) -> Option<SegmentPlan> {
        let frames = |ms: f64| ((ms * fs / 1000.0).round() as usize).max(1);
        match self.cfg.segment {
            FileSegment::None => None,
            FileSegment::Contact => Some(SegmentPlan::Contact {
                contact: self.cfg.contact_v,
                release: self.cfg.release_v,
                rises: self.cfg.contact_polarity == Polarity::Rises,
                enter: frames(self.cfg.enter_ms),
                exit: frames(self.cfg.exit_ms),
            }),
            FileSegment::Fixed => Some(SegmentPlan::Fixed(frames(self.cfg.window_ms.unwrap_or(0.0)))),
        }
    }

    fn loaded(&self) -> Result<&Loaded, StageError> {
        self.loaded
            .get_or_init(|| self.load())
            .as_ref()
            .map_err(Clone::clone)
    }
}

impl Source for SignalFileSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        Ok(self.loaded()?.iter().map(|(m, _)| m.clone()).collect())
    }
    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let trial = crate::io::common::loaded_trial(self.loaded()?, ctx.meta, "files")?;
        Ok(Payload::Signals(trial))
    }
}

/// Cuts every trial of `raw` by `plan` (module docs): segment `j` of trial
/// `<id>` becomes trial `<id>-<j>` with its labels. A trial in which no
/// segment starts is an error that says what the samples looked like.
fn segment_trials(
    raw: Vec<RawTrial>,
    plan: SegmentPlan,
    cfg: &SignalFileConfig,
) -> Result<Vec<RawTrial>, String> {
    let mut out = Vec::new();
    for t in raw {
        let n = t.data.len();
        let samples = t.data.first().map_or(0, Vec::len);
        let mut seg = Segmenter::new(plan);
        let mut parts: Vec<Vec<Vec<f64>>> = Vec::new();
        let mut on = |e: SegEvent<'_>| -> Result<(), std::convert::Infallible> {
            match e {
                SegEvent::Start => parts.push(vec![Vec::new(); n]),
                SegEvent::Frame(f) => {
                    if let Some(p) = parts.last_mut() {
                        p.iter_mut().zip(f).for_each(|(col, &v)| col.push(v));
                    }
                }
                SegEvent::End => {}
            }
            Ok(())
        };
        let mut frame = vec![0.0; n];
        for k in 0..samples {
            frame.iter_mut().zip(&t.data).for_each(|(v, col)| *v = col[k]);
            let Ok(()) = seg.push(&frame, &mut on);
        }
        let Ok(()) = seg.finish(&mut on);
        if parts.is_empty() {
            let seen = seg.levels().map_or(String::new(), |l| {
                let rises = matches!(plan, SegmentPlan::Contact { rises: true, .. });
                let (which, past) = if rises { ("highest", "over") } else { ("lowest", "under") };
                let (a, b) = l.low_range;
                format!(
                    ": its {which} taxel ranged {} to {} {}, and stayed at or {past} contact_v = {} for at most {} samples (enter_ms = {} needs {})",
                    round4(a.min(b)),
                    round4(a.max(b)),
                    cfg.unit,
                    cfg.contact_v,
                    l.longest_under,
                    cfg.enter_ms,
                    match plan {
                        SegmentPlan::Contact { enter, .. } => enter,
                        SegmentPlan::Fixed(_) => 0,
                    }
                )
            });
            // Fixed windows cut a trial from any sample: none means no samples.
            let hint = match plan {
                SegmentPlan::Contact { .. } => "; set `contact_v` and `release_v` to the recording's levels",
                SegmentPlan::Fixed(_) => "",
            };
            return Err(format!(
                "{}: `segment` found no trial in {samples} samples{seen}{hint}",
                t.origin
            ));
        }
        for (j, data) in parts.into_iter().enumerate() {
            out.push(RawTrial {
                id: format!("{}-{j}", t.id),
                labels: t.labels.clone(),
                data,
                rate_hz: t.rate_hz,
                origin: format!("{}, segment {j}", t.origin),
            });
        }
    }
    Ok(out)
}

/// `v` to 4 decimals, for messages (`1638` rather than `1638.0000`).
fn round4(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// Reads one recording into trials; `file_id` is the file's short name.
pub fn read_signal_file(
    path: &Path,
    file_id: &str,
    cfg: &SignalFileConfig,
    n_taxels: usize,
) -> Result<Vec<RawTrial>, String> {
    let shown = path.display().to_string();
    let fmt = format_of(cfg.format, path)?;
    let bytes = palpate_core::input::read_data(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    read_signal_bytes(&bytes, &shown, file_id, fmt, cfg, n_taxels)
}

/// Reads one recording's bytes (format `fmt`, not `auto`) into trials;
/// `shown` names the file in errors. What [`read_signal_file`] does after
/// reading the file; public so that fuzzing and tests reach every reader
/// without the file system.
pub fn read_signal_bytes(
    bytes: &[u8],
    shown: &str,
    file_id: &str,
    fmt: SignalFormat,
    cfg: &SignalFileConfig,
    n_taxels: usize,
) -> Result<Vec<RawTrial>, String> {
    let shown = shown.to_string();
    let trials = match fmt {
        SignalFormat::Csv => read_csv_signals(bytes, &shown, file_id, cfg, n_taxels)?,
        SignalFormat::Npy => {
            let a = read_npy_plain(bytes, &shown)?;
            arrays_to_trials(
                vec![(String::new(), a)],
                &shown,
                file_id,
                cfg,
                n_taxels,
                false,
                TrialLabels::default(),
                None,
            )?
        }
        SignalFormat::Npz => {
            let arrays = read_npz(bytes, &shown)?
                .into_iter()
                .map(|(n, c)| match c {
                    NpyContent::Plain(a) => Ok((n, a)),
                    NpyContent::Record(_) => Err(format!("{shown}: array `{n}` is structured, not numeric")),
                })
                .collect::<Result<Vec<_>, _>>()?;
            named_arrays_to_trials(arrays, &shown, file_id, cfg, n_taxels, false)?
        }
        SignalFormat::Mat => {
            let arrays = read_mat(bytes, &shown)?;
            named_arrays_to_trials(arrays, &shown, file_id, cfg, n_taxels, true)?
        }
        SignalFormat::Daq => {
            let rec = super::daq::decode_recording(bytes, cfg.daq_scale, cfg.daq_offset, cfg.fill_gaps)
                .map_err(|e| format!("{shown}: {e}"))?;
            if rec.data.len() != n_taxels {
                return Err(format!(
                    "{shown}: channel mismatch: the frames carry {} channels but the layout has {n_taxels} taxels{LAYOUT_HINT}",
                    rec.data.len()
                ));
            }
            if rec.trailing_bytes > 0 && !cfg.allow_cut_end {
                return Err(super::daq::cut_end_error(
                    &shown,
                    rec.trailing_bytes,
                    (bytes.len() - rec.trailing_bytes) as u64,
                ));
            }
            vec![RawTrial {
                id: file_id.to_string(),
                labels: TrialLabels::default(),
                data: rec.data,
                rate_hz: rec.sample_rate_hz,
                origin: shown.clone(),
            }]
        }
        SignalFormat::Auto => return Err(format!("{shown}: the format must be resolved before reading")),
    };
    if trials.is_empty() {
        return Err(format!("{shown} holds no trial"));
    }
    for t in &trials {
        if t.data.first().is_none_or(Vec::is_empty) {
            return Err(format!("{}: no samples (empty or truncated file?)", t.origin));
        }
    }
    Ok(trials)
}

const RESERVED: [&str; 5] = ["sample_rate_hz", "fs", "angle_deg", "group", "speed_mm_s"];

fn named_arrays_to_trials(
    arrays: Vec<(String, NdArray)>,
    shown: &str,
    file_id: &str,
    cfg: &SignalFileConfig,
    n_taxels: usize,
    matlab: bool,
) -> Result<Vec<RawTrial>, String> {
    let mut rate = None;
    let mut angles = None;
    let mut groups = None;
    let mut speeds = None;
    let mut data = Vec::new();
    for (name, a) in arrays {
        match name.as_str() {
            "sample_rate_hz" | "fs" => {
                if a.data.len() != 1 {
                    return Err(format!(
                        "{shown}: `{name}` must hold one value, has shape {:?}",
                        a.shape
                    ));
                }
                let r = a.data[0];
                if !(r.is_finite() && r > 0.0) {
                    return Err(format!("{shown}: `{name}` must be a positive rate, got {r}"));
                }
                rate = Some(r);
            }
            "angle_deg" => angles = Some(a.data),
            "group" => groups = Some(a.data),
            "speed_mm_s" => speeds = Some(a.data),
            _ => {
                if cfg.variables.is_empty() || cfg.variables.contains(&name) {
                    data.push((name, a));
                }
            }
        }
    }
    for v in &cfg.variables {
        if !data.iter().any(|(n, _)| n == v) {
            let have: Vec<&str> = data.iter().map(|(n, _)| n.as_str()).collect();
            return Err(format!(
                "{shown}: no data variable `{v}` (found: {})",
                have.join(", ")
            ));
        }
    }
    if data.is_empty() {
        return Err(format!(
            "{shown}: no data array (only reserved names {} found)",
            RESERVED.join(", ")
        ));
    }
    let mut trials = arrays_to_trials(
        data,
        shown,
        file_id,
        cfg,
        n_taxels,
        matlab,
        TrialLabels::default(),
        rate,
    )?;
    for (name, vals) in [
        ("angle_deg", &angles),
        ("group", &groups),
        ("speed_mm_s", &speeds),
    ] {
        if let Some(v) = vals {
            if v.len() != trials.len() {
                return Err(format!(
                    "{shown}: `{name}` has {} values but the file holds {} trials",
                    v.len(),
                    trials.len()
                ));
            }
            for (t, &x) in trials.iter_mut().zip(v.iter()) {
                let what = format!("{shown}, `{name}` of trial `{}`", t.id);
                set_label_cell(&mut t.labels, name, &x.to_string(), &what)?;
            }
        }
    }
    Ok(trials)
}

#[allow(clippy::too_many_arguments)]
fn arrays_to_trials(
    arrays: Vec<(String, NdArray)>,
    shown: &str,
    file_id: &str,
    cfg: &SignalFileConfig,
    n_taxels: usize,
    matlab: bool,
    labels: TrialLabels,
    rate_hz: Option<f64>,
) -> Result<Vec<RawTrial>, String> {
    let single = arrays.len() == 1;
    let mut out = Vec::new();
    for (name, a) in arrays {
        let what = if name.is_empty() {
            shown.to_string()
        } else {
            format!("{shown}, array `{name}`")
        };
        // (trial axis, sample axis, taxel axis) in the array's C-order shape.
        let (n_trials, axes) = match (a.shape.len(), matlab) {
            (1, _) if n_taxels == 1 => (1, None),
            (2, _) => (1, Some((None, if cfg.taxel_major { (1, 0) } else { (0, 1) }))),
            (3, false) => (
                a.shape[0],
                Some((Some(0), if cfg.taxel_major { (2, 1) } else { (1, 2) })),
            ),
            (3, true) => (
                a.shape[2],
                Some((Some(2), if cfg.taxel_major { (1, 0) } else { (0, 1) })),
            ),
            _ => {
                return Err(format!(
                    "{what}: wrong shape {:?}; expected {} with {n_taxels} taxels",
                    a.shape,
                    expected_shape(matlab, cfg.taxel_major)
                ))
            }
        };
        let (n_samples, strides) = match axes {
            None => (a.shape[0], (0, 1, 0)),
            Some((trial_ax, (s_ax, x_ax))) => {
                if a.shape[x_ax] != n_taxels {
                    // The two axes the other way round is the usual cause:
                    // say which key fixes it.
                    let hint = if a.shape[s_ax] == n_taxels {
                        format!(
                            " (the other axis has {n_taxels} entries: set `taxel_major = {}` if the array is {})",
                            !cfg.taxel_major,
                            expected_shape(matlab, !cfg.taxel_major)
                        )
                    } else {
                        LAYOUT_HINT.to_string()
                    };
                    return Err(format!(
                        "{what}: wrong shape {:?}: the taxel axis has {} entries but the layout has {n_taxels} taxels; expected {}{hint}",
                        a.shape,
                        a.shape[x_ax],
                        expected_shape(matlab, cfg.taxel_major)
                    ));
                }
                let st = c_strides(&a.shape);
                (a.shape[s_ax], (trial_ax.map_or(0, |t| st[t]), st[s_ax], st[x_ax]))
            }
        };
        let (st_trial, st_sample, st_taxel) = strides;
        if a.data.is_empty() {
            // Checked before the loop: a shape like (2^40, 0, 16) holds no data
            // but would otherwise make 2^40 empty trials.
            return Err(format!(
                "{what}: shape {:?} holds no samples (empty or truncated file?)",
                a.shape
            ));
        }
        for k in 0..n_trials {
            let mut data = vec![Vec::with_capacity(n_samples); n_taxels];
            for (x, row) in data.iter_mut().enumerate() {
                for s in 0..n_samples {
                    let v = a.data[k * st_trial + s * st_sample + x * st_taxel];
                    if !v.is_finite() {
                        let mut idx = vec![0; a.shape.len()];
                        if let Some((t_ax, (s_ax, x_ax))) = axes {
                            if let Some(t) = t_ax {
                                idx[t] = k;
                            }
                            idx[s_ax] = s;
                            idx[x_ax] = x;
                        } else {
                            idx[0] = s;
                        }
                        let pos = if matlab {
                            let subs: Vec<String> = idx.iter().map(|i| (i + 1).to_string()).collect();
                            format!(
                                "{}({})",
                                if name.is_empty() { "data" } else { &name },
                                subs.join(", ")
                            )
                        } else {
                            format!("index {idx:?}")
                        };
                        return Err(format!(
                            "{what}: sample {v} at {pos} (sample {s}, taxel {x}) is not finite"
                        ));
                    }
                    row.push(v);
                }
            }
            let id = match (single, n_trials) {
                (true, 1) => file_id.to_string(),
                (true, _) => format!("{file_id}-{k}"),
                (false, 1) => format!("{file_id}-{name}"),
                (false, _) => format!("{file_id}-{name}-{k}"),
            };
            let origin = if n_trials > 1 {
                format!("{what}, trial {k}")
            } else {
                what.clone()
            };
            out.push(RawTrial {
                id,
                labels: labels.clone(),
                data,
                rate_hz,
                origin,
            });
        }
    }
    Ok(out)
}

fn expected_shape(matlab: bool, taxel_major: bool) -> &'static str {
    match (matlab, taxel_major) {
        (false, false) => "(samples, taxels) or (trials, samples, taxels)",
        (false, true) => "(taxels, samples) or (trials, taxels, samples)",
        (true, false) => "data(sample, taxel) or data(sample, taxel, trial)",
        (true, true) => "data(taxel, sample) or data(taxel, sample, trial)",
    }
}

fn c_strides(shape: &[usize]) -> Vec<usize> {
    let mut st = vec![1; shape.len()];
    for d in (0..shape.len().saturating_sub(1)).rev() {
        st[d] = st[d + 1] * shape[d + 1];
    }
    st
}

/// Maps a csv crate error to a message with the file and line.
pub fn csv_error(shown: &str, e: &csv::Error) -> String {
    match e.kind() {
        csv::ErrorKind::UnequalLengths {
            pos,
            expected_len,
            len,
        } => format!(
            "{shown}, line {}: expected {expected_len} fields, found {len} (truncated or malformed row)",
            pos.as_ref().map_or(0, |p| p.line())
        ),
        _ => format!("{shown}: {e}"),
    }
}

/// A CSV whose last line has no line end was most likely cut while being
/// written: its last number may be short by digits, which no parser can see.
/// So it is an error (add the newline if the file is complete).
pub fn check_csv_complete(bytes: &[u8], shown: &str) -> Result<(), String> {
    if bytes.last().is_some_and(|&b| b != b'\n' && b != b'\r') {
        let line = bytes.iter().filter(|&&b| b == b'\n').count() + 1;
        return Err(format!(
            "{shown}, line {line}: the last line has no line end, so the file looks truncated \
             (if it is complete, end it with a newline)"
        ));
    }
    Ok(())
}

struct CsvTrial {
    name: String,
    labels: TrialLabels,
    data: Vec<Vec<f64>>,
    times_ms: Vec<(u64, f64)>,
}

fn read_csv_signals(
    bytes: &[u8],
    shown: &str,
    file_id: &str,
    cfg: &SignalFileConfig,
    n_taxels: usize,
) -> Result<Vec<RawTrial>, String> {
    check_csv_complete(bytes, shown)?;
    let mut rdr = user_csv_reader(bytes);
    let headers = rdr.headers().map_err(|e| csv_error(shown, &e))?.clone();
    let names: Vec<String> = if cfg.columns.is_empty() {
        (0..n_taxels).map(|i| format!("taxel_{i}")).collect()
    } else {
        cfg.columns.clone()
    };
    #[derive(Clone, Copy)]
    enum Col {
        Taxel(usize),
        TimeMs(f64),
        Trial,
        Label,
        Ignored,
        /// The unnamed column after a delimiter ending the header line.
        Trailing,
    }
    // Hash lookups: a layout of 160k taxels made matching quadratic (32 s).
    let by_name: std::collections::HashMap<&str, usize> =
        names.iter().enumerate().map(|(i, n)| (n.as_str(), i)).collect();
    let mut seen = std::collections::HashSet::new();
    let mut cols = Vec::new();
    let trailing = super::common::trailing_column(&headers);
    for (k, h) in headers.iter().enumerate() {
        if Some(k) == trailing {
            cols.push(Col::Trailing);
            continue;
        }
        if !seen.insert(h) {
            return Err(format!(
                "{shown}: column `{h}` appears twice in the header (column {} is a repeat)",
                k + 1
            ));
        }
        let ignored = cfg.ignore_columns.iter().any(|c| c == h);
        let c = if let Some(&i) = by_name.get(h) {
            if ignored {
                return Err(format!(
                    "{shown}: column `{h}` is taxel {i} of the layout and is listed in `ignore_columns`"
                ));
            }
            Col::Taxel(i)
        } else if ignored {
            Col::Ignored
        } else {
            match h {
                "time_ms" => Col::TimeMs(1.0),
                "time_s" => Col::TimeMs(1000.0),
                "trial" => Col::Trial,
                // A signal's duration is its samples over its rate, so
                // `duration_ms` (a spike file's column) is not one of them.
                h if h != "duration_ms" && LABEL_COLUMNS.contains(&h) => Col::Label,
                // A taxel column past the layout's last: the file's array is
                // larger, which `ignore_columns` must not be suggested for.
                h if cfg.columns.is_empty()
                    && h.strip_prefix("taxel_")
                        .is_some_and(|i| i.parse::<usize>().is_ok()) =>
                {
                    return Err(format!(
                        "{shown}: column `{h}` is past the layout's {n_taxels} taxels (taxel_0 .. taxel_{}): \
                         the file holds a larger array{LAYOUT_HINT}",
                        n_taxels.saturating_sub(1)
                    ));
                }
                _ => {
                    return Err(format!(
                        "{shown}: unknown column `{h}`; expected {} (the layout has {n_taxels} taxels), \
                         optionally time_ms or time_s, trial, angle_deg, stimulus, group, speed_mm_s \
                         (set `columns` to name the taxel columns, `ignore_columns` to skip others)",
                        if cfg.columns.is_empty() {
                            format!("taxel_0 .. taxel_{}", n_taxels.saturating_sub(1))
                        } else {
                            cfg.columns.join(", ")
                        }
                    ))
                }
            }
        };
        cols.push(c);
    }
    let mut present = vec![false; names.len()];
    for c in &cols {
        if let Col::Taxel(j) = c {
            present[*j] = true;
        }
    }
    for (i, n) in names.iter().enumerate() {
        if !present[i] {
            return Err(format!(
                "{shown}: missing taxel column `{n}` (taxel {i} of the layout's {n_taxels}){LAYOUT_HINT}"
            ));
        }
    }
    let mut trials: Vec<CsvTrial> = Vec::new();
    // Trial name -> index in `trials` (a linear search was quadratic in trials).
    let mut trial_index: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    let trial_col = cols.iter().position(|c| matches!(c, Col::Trial));
    for rec in rdr.records() {
        let rec = rec.map_err(|e| csv_error(shown, &e))?;
        let line = rec.position().map_or(0, |p| p.line());
        let trial_name = trial_col
            .map(|i| rec.get(i).unwrap_or("").to_string())
            .unwrap_or_default();
        let k = match trial_index.get(&trial_name) {
            Some(&k) => k,
            None => {
                trial_index.insert(trial_name.clone(), trials.len());
                trials.push(CsvTrial {
                    name: trial_name,
                    labels: TrialLabels::default(),
                    data: vec![Vec::new(); n_taxels],
                    times_ms: Vec::new(),
                });
                trials.len() - 1
            }
        };
        let t = &mut trials[k];
        let mut row_labels = TrialLabels::default();
        for (i, (c, cell)) in cols.iter().zip(rec.iter()).enumerate() {
            let what = || format!("{shown}, line {line}, column `{}`", &headers[i]);
            match *c {
                Col::Taxel(x) => {
                    let v: f64 = cell
                        .parse()
                        .map_err(|_| number_error(&what(), cell, "a number"))?;
                    if !v.is_finite() {
                        return Err(format!(
                            "{}: sample `{cell}` is not finite (NaN or infinite)",
                            what()
                        ));
                    }
                    t.data[x].push(v);
                }
                Col::TimeMs(scale) => {
                    let v: f64 = cell.parse().map_err(|_| number_error(&what(), cell, "a time"))?;
                    if !v.is_finite() {
                        return Err(format!("{}: time `{cell}` is not finite", what()));
                    }
                    t.times_ms.push((line, v * scale));
                }
                Col::Trial | Col::Ignored => {}
                Col::Trailing => {
                    super::common::check_trailing(&rec, Some(i), &format!("{shown}, line {line}"))?
                }
                Col::Label => {
                    // A label belongs to the trial: name it when the file holds several.
                    let at = match trial_col {
                        Some(_) => format!("{}, trial `{}`", what(), t.name),
                        None => what(),
                    };
                    set_label_cell(&mut row_labels, &headers[i], cell, &at)?
                }
            }
        }
        merge_consistent(&mut t.labels, &row_labels, &format!("{shown}, line {line}"))?;
    }
    let many = trials.len() > 1 || trials.first().is_some_and(|t| !t.name.is_empty());
    trials
        .into_iter()
        .map(|t| {
            let origin = if many {
                format!("{shown}, trial `{}`", t.name)
            } else {
                shown.to_string()
            };
            let rate_hz = rate_from_times(&t.times_ms, &origin)?;
            Ok(RawTrial {
                id: if many {
                    format!("{file_id}-{}", t.name)
                } else {
                    file_id.to_string()
                },
                labels: t.labels,
                data: t.data,
                rate_hz,
                origin,
            })
        })
        .collect()
}

/// The sample rate a time column gives, checking that samples are uniformly
/// spaced (each within [a quarter sample](super::common::GRID_TOLERANCE) of
/// the grid through the first and last time), so a missing row is caught.
/// The line named is the first that leaves the grid of the lines before it
/// ([`TimeGrid`](super::common::TimeGrid)), so a rate that changes part way
/// is named where it changes, not where the overall fit first misses.
fn rate_from_times(times: &[(u64, f64)], origin: &str) -> Result<Option<f64>, String> {
    use super::common::{off_grid, GridBreak, TimeGrid};
    if times.len() < 2 {
        return Ok(None);
    }
    let n = times.len();
    let dt = (times[n - 1].1 - times[0].1) / (n - 1) as f64;
    let uniform = dt.is_finite()
        && dt > 0.0
        && times
            .iter()
            .enumerate()
            .all(|(k, &(_, t))| !off_grid(t, times[0].1, k as f64, dt));
    if uniform {
        return Ok(Some(1000.0 / dt));
    }
    let way_out = "(a missing or repeated row? if the times only jitter, e.g. stamped by the \
                   host, give the rate in `sample_rate_hz` and list the time column in \
                   `ignore_columns`)";
    // Times as messages print numbers: 1e300 in exponent form, not 301 digits.
    let n_ = palpate_core::fmt_num;
    let mut grid = TimeGrid::default();
    for &(line, t) in times {
        match grid.push(t, 1) {
            Ok(()) => {}
            Err(GridBreak::NotIncreasing { before }) => {
                return Err(format!(
                    "{origin}, line {line}: the time column does not increase: {} ms after {} ms",
                    n_(t),
                    n_(before)
                ))
            }
            Err(GridBreak::Off { step, interval }) => {
                return Err(format!(
                    "{origin}, line {line}: time {} ms is off the uniform grid of {} ms of the \
                     lines before it ({} ms after the line before) {way_out}",
                    n_(t),
                    n_(step),
                    n_(interval)
                ))
            }
        }
    }
    // Every line on the grid of those before it, but not on the overall
    // one (a slow drift): the first line the overall fit misses.
    if !(dt.is_finite() && dt > 0.0) {
        return Err(format!("{origin}: the time column does not increase"));
    }
    let (line, t) = times
        .iter()
        .enumerate()
        .find(|&(k, &(_, t))| off_grid(t, times[0].1, k as f64, dt))
        .map_or((0, f64::NAN), |(_, &lt)| lt);
    Err(format!(
        "{origin}, line {line}: time {} ms is off the uniform grid of {} ms {way_out}",
        n_(t),
        n_(dt)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::daq::{encode_frame, SampleFormat};

    fn csv_cfg() -> SignalFileConfig {
        SignalFileConfig::default()
    }

    /// A label angle outside (0, 180) in a data file is refused naming the
    /// file, line and trial (CSV) or the file, array and trial (NPZ/MAT).
    #[test]
    fn label_angles_outside_0_to_180_in_data_files_are_refused() {
        let csv = "trial,angle_deg,taxel_0\na,40,1.0\na,40,1.5\nb,400,1.0\nb,400,1.2\n";
        let e = read_signal_bytes(csv.as_bytes(), "rec.csv", "rec", SignalFormat::Csv, &csv_cfg(), 1)
            .unwrap_err();
        assert!(
            e.contains("rec.csv, line 4") && e.contains("trial `b`") && e.contains("between 0 and 180"),
            "{e}"
        );
        let arrays = |angles: Vec<f64>| {
            vec![
                (
                    "data".to_string(),
                    NdArray {
                        shape: vec![2, 3, 1],
                        data: vec![1.0; 6],
                    },
                ),
                (
                    "angle_deg".to_string(),
                    NdArray {
                        shape: vec![2],
                        data: angles,
                    },
                ),
            ]
        };
        let e = named_arrays_to_trials(arrays(vec![30.0, -30.0]), "rec.npz", "rec", &csv_cfg(), 1, false)
            .unwrap_err();
        assert!(
            e.contains("rec.npz") && e.contains("trial `rec-1`") && e.contains("between 0 and 180"),
            "{e}"
        );
        let ok = named_arrays_to_trials(arrays(vec![30.0, 150.0]), "rec.npz", "rec", &csv_cfg(), 1, false)
            .unwrap();
        assert_eq!(ok[1].labels.angle_deg, Some(150.0));
    }

    /// A time column whose rate changes part way (100 Hz, then 200 Hz from
    /// line 703) is refused at the line where it changes, with the step of
    /// the lines before it, not at line 3 with the overall fit's step.
    #[test]
    fn a_rate_change_in_a_time_column_is_named_where_it_happens() {
        let times: Vec<(u64, f64)> = (0..1400u64)
            .map(|k| {
                let t = if k <= 700 {
                    k as f64 * 10.0
                } else {
                    7000.0 + (k - 700) as f64 * 5.0
                };
                (k + 2, t)
            })
            .collect();
        let e = rate_from_times(&times, "rec.csv").unwrap_err();
        assert!(
            e.contains("rec.csv, line 703") && e.contains("grid of 10 ms") && e.contains("5 ms after"),
            "{e}"
        );
        // Uniform times still give their rate; times that go back are named.
        let uniform: Vec<(u64, f64)> = (0..50u64).map(|k| (k + 2, k as f64 * 2.5)).collect();
        assert_eq!(rate_from_times(&uniform, "u.csv").unwrap(), Some(400.0));
        let mut back = uniform.clone();
        back[30].1 = 10.0;
        let e = rate_from_times(&back, "b.csv").unwrap_err();
        assert!(
            e.contains("b.csv, line 32") && e.contains("does not increase"),
            "{e}"
        );
    }

    /// A DAQ recording whose timestamps decrease says so at the frame,
    /// rather than that it carries no sample rate.
    #[test]
    fn a_daq_recording_with_decreasing_timestamps_names_the_frame() {
        let mut b = Vec::new();
        for (seq, ts) in [(0u32, 3000u64), (1, 2000), (2, 1000), (3, 0)] {
            encode_frame(&mut b, SampleFormat::F32, seq, ts, &[1.0]);
        }
        let e = read_signal_bytes(&b, "r.daq", "r", SignalFormat::Daq, &csv_cfg(), 1).unwrap_err();
        assert!(
            e.contains("r.daq") && e.contains("frame 1 (sequence 1)") && e.contains("decrease"),
            "{e}"
        );
        assert!(!e.contains("no sample rate"), "{e}");
    }
}
