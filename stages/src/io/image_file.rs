//! The `image_file` source: spike images read back from the folder
//! `write_images` wrote, so that images round-trip (write, read, same counts,
//! same labels, same trial order), or from image files of another tool laid
//! out the same way.
//!
//! ## The folder
//!
//! `write_images` writes, into one folder:
//!
//! * one file per trial, named after the trial id: NPY float64 of shape
//!   `(frames, rows, cols)` for a grid or `(frames, taxels)` otherwise, or
//!   CSV with the header `frame, t_start_ms, taxel_0 .. taxel_{N-1}` and one
//!   row per frame (`frame` = 0, 1, ...; `t_start_ms` = `frame · hop_ms`);
//! * `labels.toml`: each trial's `angle_deg`, `stimulus` and `group` (the
//!   label sidecar every file source reads);
//! * `info.json`: `layout`, `window_ms`, `hop_ms`, `format` and `trials` (the
//!   trial files' stems in the order the run gave them).
//!
//! `image_file` reads `info.json` for the layout, window, hop, format and
//! order. The `layout`, `window_ms`, `hop_ms` and `format` keys supply what
//! `info.json` does not record (all four when the folder has none); a key
//! that `info.json` also records must agree with it, else it is an error
//! naming the key, both values and the `info.json`: the record says how the
//! files were written, and reading them with another hop or array (a 3 x 5
//! grid read as 5 x 3) gives wrong answers without a word. Without a
//! `trials` list the trials are the folder's files of that format in name
//! order. The labels come from `labels.toml` when present (or the `labels`
//! key); every trial must have an entry and every entry a trial, as for
//! `signal_file`.
//!
//! ## Checks
//!
//! Counts must be finite and not negative (a spike count); an NPY file's
//! shape must be `(frames, rows, cols)` or `(frames, taxels)` for the layout;
//! a CSV file's header must be `frame, t_start_ms, taxel_0 ..` with one column
//! per taxel, its frames numbered 0, 1, ... and `t_start_ms` equal to
//! `frame · hop_ms` (within 1e-9 ms relative), so that a file written with
//! another hop is not silently read on a wrong time base. Every error names
//! the file and the row or entry.

use super::arrays::{read_npy_plain, NdArray};
use super::common::{apply_sidecar, build_metas, describe_layout, read_sidecar, LayoutConfig, TrialLabels};
use palpate_core::{
    check_positive, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec, Inspection,
    OutputFacts, Payload, PayloadKind, Source, SpikeImages, Stage, StageConfig, StageError, TaxelLayout,
    TrialContext, TrialMeta,
};
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// File format of image files.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ImageFormat {
    /// As `info.json` says (`write_images`' own record).
    #[default]
    Auto,
    /// `frame, t_start_ms, taxel_0 ..` CSV.
    Csv,
    /// NumPy `.npy` float64.
    Npy,
}

impl ImageFormat {
    fn ext(self) -> Option<&'static str> {
        match self {
            ImageFormat::Auto => None,
            ImageFormat::Csv => Some("csv"),
            ImageFormat::Npy => Some("npy"),
        }
    }
}

/// Spike images read from a folder `write_images` wrote (one NPY or CSV file
/// per trial, `labels.toml`, `info.json`), so that images round-trip.
///
/// Format, checks and the order of trials: the user guide's "Sources" page and
/// the module docs of `palpate_stages::io::image_file`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ImageFileConfig {
    /// The folder, relative to the graph file's folder (e.g.
    /// "../out/quickstart/images"). Required.
    pub dir: String,
    /// `auto` (as `info.json` says), `csv` or `npy`; set, it must agree
    /// with `info.json`'s `format` when that records one. Default auto.
    pub format: ImageFormat,
    /// Frame length, ms; must agree with `info.json`'s `window_ms` when that
    /// records one. Default: `info.json`'s.
    pub window_ms: Option<f64>,
    /// Time between frame starts, ms; must agree with `info.json`'s
    /// `hop_ms` when that records one. Default: `info.json`'s.
    pub hop_ms: Option<f64>,
    /// Taxel layout; must agree with `info.json`'s `layout` when that
    /// records one. Default: `info.json`'s.
    /// (`kind = "grid"` or `"positions"` may be left out: `positions_mm` or
    /// `rows`/`cols` tell it.)
    #[serde(default, deserialize_with = "crate::io::common::layout_with_inferred_kind")]
    #[schemars(schema_with = "crate::io::common::layout_schema_kind_optional")]
    pub layout: Option<LayoutConfig>,
    /// Label sidecar (TOML, CSV or `trials.json`), relative to the graph
    /// file's folder; default: the folder's `labels.toml` when present.
    pub labels: Option<String>,
}

/// What `write_images` records in `info.json`.
#[derive(Debug, Default, Deserialize)]
struct Info {
    layout: Option<TaxelLayout>,
    window_ms: Option<f64>,
    hop_ms: Option<f64>,
    format: Option<String>,
    trials: Option<Vec<String>>,
}

#[typetag::serde(name = "image_file")]
impl StageConfig for ImageFileConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Images)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Source(Box::new(self.source(ctx)?)))
    }
    /// The array when the `layout` key gives it (a union warns when its
    /// sources' arrays differ); unknown until the files are read otherwise.
    fn inspect(&self, _ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        super::common::layout_inspection(&self.layout)
    }
}
register_stage!("image_file", ImageFileConfig);

impl ImageFileConfig {
    /// Checks the keys against the folder and makes the (not yet loaded) source.
    fn source(&self, ctx: &BuildContext) -> Result<ImageFileSource, ConfigError> {
        if self.dir.is_empty() {
            return Err(ConfigError::key("dir", "name the folder `write_images` wrote"));
        }
        let dir = ctx.resolve(Path::new(&self.dir));
        if !dir.is_dir() {
            return Err(ConfigError::key(
                "dir",
                format!("folder {} not found", dir.display()),
            ));
        }
        let info_path = dir.join("info.json");
        let has_info = info_path.is_file();
        let info: Info = if has_info {
            let text = palpate_core::input::read_text(&info_path)
                .map_err(|e| ConfigError::key("dir", format!("cannot read {}: {e}", info_path.display())))?;
            serde_json::from_str(&text)
                .map_err(|e| ConfigError::key("dir", format!("{}: {e}", info_path.display())))?
        } else {
            Info::default()
        };
        let shown = info_path.display().to_string();
        let from_info = |what: &str| {
            if has_info {
                format!("not given, and {shown} gives no `{what}`")
            } else {
                format!(
                    "not given, and the folder has no info.json ({shown} is missing): it records the \
                     `layout`, `window_ms`, `hop_ms` and `format` the files were written with \
                     (`write_images` writes it); restore it, or set the `{what}` key"
                )
            }
        };
        // A key that disagrees with the record: named with both values.
        let disagrees = |key: &str, set: String, recorded: String| {
            ConfigError::key(
                key,
                format!(
                    "is {set} but {shown} records {recorded}, which the files were written with; \
                     remove the key (or correct info.json)"
                ),
            )
        };
        let mut c = ConfigChecks::new();
        let layout_recorded = info.layout.is_some();
        let recorded_layout = match info.layout {
            Some(l) => c.take(
                l.validate()
                    .map(|()| l)
                    .map_err(|m| ConfigError::key("layout", format!("{shown}: {m}"))),
            ),
            None => None,
        };
        let layout = match (&self.layout, recorded_layout) {
            (Some(l), recorded) => match (c.take(l.to_layout("layout")), recorded) {
                (Some(l), Some(r)) if l != r => {
                    c.push(disagrees("layout", describe_layout(&l), describe_layout(&r)));
                    None
                }
                (l, _) => l,
            },
            (None, Some(r)) => Some(r),
            (None, None) => {
                // A bad recorded layout was reported above.
                if !layout_recorded {
                    c.push(ConfigError::key("layout", from_info("layout")));
                }
                None
            }
        };
        let mut number = |key: &str, given: Option<f64>, recorded: Option<f64>| {
            let v = match (given, recorded) {
                // Equal to the record, to rounding (a hand-typed 0.1 + 0.2).
                (Some(g), Some(r)) if (g - r).abs() > 1e-9 * g.abs().max(r.abs()) => {
                    c.push(disagrees(key, format!("{g} ms"), format!("{r} ms")));
                    return None;
                }
                (Some(v), _) | (None, Some(v)) => v,
                (None, None) => {
                    c.push(ConfigError::key(key, from_info(key)));
                    return None;
                }
            };
            c.take(check_positive(key, v, "ms"))
        };
        let window_ms = number("window_ms", self.window_ms, info.window_ms);
        let hop_ms = number("hop_ms", self.hop_ms, info.hop_ms);
        let ext = match (self.format.ext(), info.format.as_deref()) {
            (Some(e), Some(r)) if (r == "csv" || r == "npy") && r != e => {
                c.push(disagrees("format", format!("\"{e}\""), format!("\"{r}\"")));
                None
            }
            (Some(e), _) => Some(e),
            (None, Some("csv")) => Some("csv"),
            (None, Some("npy")) => Some("npy"),
            (None, Some(other)) => {
                c.push(ConfigError::key(
                    "format",
                    format!("{shown} says format \"{other}\"; set `format` to csv or npy"),
                ));
                None
            }
            (None, None) => {
                c.push(ConfigError::key("format", from_info("format")));
                None
            }
        };
        let labels = match &self.labels {
            Some(l) => {
                let p = ctx.resolve(Path::new(l));
                c.take(super::common::check_regular_file(&p, "labels"));
                Some(p)
            }
            None => Some(dir.join("labels.toml")).filter(|p| p.is_file()),
        };
        c.finish()?;
        let (Some(layout), Some(window_ms), Some(hop_ms), Some(ext)) = (layout, window_ms, hop_ms, ext)
        else {
            return Err(ConfigError::key("dir", "incomplete image folder"));
        };
        let files = match info.trials {
            Some(stems) => {
                let files: Vec<PathBuf> = stems.iter().map(|s| dir.join(format!("{s}.{ext}"))).collect();
                if let Some(missing) = files.iter().find(|f| !f.is_file()) {
                    return Err(ConfigError::key(
                        "dir",
                        format!(
                            "{} lists trial file {}, which is missing",
                            info_path.display(),
                            missing.display()
                        ),
                    ));
                }
                files
            }
            None => {
                let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
                    .map_err(|e| ConfigError::key("dir", format!("cannot list {}: {e}", dir.display())))?
                    .filter_map(Result::ok)
                    .map(|e| e.path())
                    .filter(|p| p.is_file() && p.extension().and_then(|e| e.to_str()) == Some(ext))
                    .collect();
                files.sort();
                files
            }
        };
        if files.is_empty() {
            return Err(ConfigError::key(
                "dir",
                format!("{} holds no .{ext} image file", dir.display()),
            ));
        }
        Ok(ImageFileSource {
            layout,
            window_ms,
            hop_ms,
            files,
            labels,
            loaded: OnceLock::new(),
        })
    }
}

/// Every trial, read once and shared.
type Loaded = Vec<(TrialMeta, Arc<SpikeImages>)>;

struct ImageFileSource {
    layout: TaxelLayout,
    window_ms: f64,
    hop_ms: f64,
    files: Vec<PathBuf>,
    labels: Option<PathBuf>,
    loaded: OnceLock<Result<Loaded, StageError>>,
}

impl ImageFileSource {
    fn load(&self) -> Result<Loaded, StageError> {
        let images: Vec<Result<SpikeImages, String>> = self.files.par_iter().map(|f| self.read(f)).collect();
        let images: Vec<SpikeImages> = images
            .into_iter()
            .collect::<Result<_, _>>()
            .map_err(StageError::new)?;
        let mut labelled: Vec<(String, TrialLabels)> = self
            .files
            .iter()
            .map(|f| {
                let id = f
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                (id, TrialLabels::default())
            })
            .collect();
        if let Some(p) = &self.labels {
            let side = read_sidecar(p)?;
            apply_sidecar(&mut labelled, &side, p)?;
        }
        let origins: Vec<String> = self.files.iter().map(|f| f.display().to_string()).collect();
        let metas = build_metas(&labelled, &origins)?;
        Ok(metas.into_iter().zip(images.into_iter().map(Arc::new)).collect())
    }

    /// Reads one trial's file.
    fn read(&self, path: &Path) -> Result<SpikeImages, String> {
        let shown = path.display().to_string();
        let n = self.layout.len();
        let (n_frames, counts) = if path.extension().and_then(|e| e.to_str()) == Some("npy") {
            let bytes =
                palpate_core::input::read_data(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
            let NdArray { shape, data } = read_npy_plain(&bytes, &shown)?;
            let frames_of = |shape: &[usize]| -> Option<usize> {
                match (shape, self.layout.grid()) {
                    ([f, r, c], Some((rows, cols))) if *r == rows && *c == cols => Some(*f),
                    ([f, t], _) if *t == n => Some(*f),
                    _ => None,
                }
            };
            let f = frames_of(&shape).ok_or_else(|| {
                format!(
                    "{shown}: shape {shape:?} does not fit the layout: expected (frames, {}){}",
                    n,
                    self.layout
                        .grid()
                        .map(|(r, c)| format!(" or (frames, {r}, {c})"))
                        .unwrap_or_default()
                )
            })?;
            (f, data)
        } else {
            self.read_csv(path, &shown)?
        };
        if let Some(k) = counts.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(format!(
                "{shown}: frame {}, taxel {}: {} is not a spike count (finite, >= 0)",
                k / n.max(1),
                k % n.max(1),
                counts[k]
            ));
        }
        Ok(SpikeImages {
            layout: self.layout.clone(),
            window_ms: self.window_ms,
            hop_ms: self.hop_ms,
            n_frames,
            counts,
        })
    }

    /// Reads `frame, t_start_ms, taxel_0 ..` CSV.
    fn read_csv(&self, path: &Path, shown: &str) -> Result<(usize, Vec<f64>), String> {
        let n = self.layout.len();
        let bytes = palpate_core::input::read_data(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
        let mut rdr = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .from_reader(bytes.as_slice());
        let headers = rdr.headers().map_err(|e| format!("{shown}: {e}"))?.clone();
        let expected: Vec<String> = ["frame".to_string(), "t_start_ms".to_string()]
            .into_iter()
            .chain((0..n).map(|i| format!("taxel_{i}")))
            .collect();
        if headers.iter().ne(expected.iter().map(String::as_str)) {
            return Err(format!(
                "{shown}: the header must be `frame, t_start_ms, taxel_0 .. taxel_{}` ({} columns for the layout's {n} taxels), got {} columns starting `{}`",
                n.saturating_sub(1),
                n + 2,
                headers.len(),
                headers.iter().take(3).collect::<Vec<_>>().join(", ")
            ));
        }
        let mut counts = Vec::new();
        let mut frames = 0usize;
        for (r, rec) in rdr.records().enumerate() {
            let line = r + 2;
            let rec = rec.map_err(|e| format!("{shown}, line {line}: {e}"))?;
            let cell = |i: usize| -> Result<f64, String> {
                let c = rec.get(i).unwrap_or("");
                c.parse::<f64>().map_err(|_| {
                    format!(
                        "{shown}, line {line}, column `{}`: cannot read `{c}` as a number",
                        expected[i]
                    )
                })
            };
            let frame = cell(0)?;
            if frame != frames as f64 {
                return Err(format!(
                    "{shown}, line {line}: frame {frame}, expected {frames} (frames numbered 0, 1, ... in order)"
                ));
            }
            let t = cell(1)?;
            let want = frames as f64 * self.hop_ms;
            if (t - want).abs() > 1e-9 * want.abs().max(1.0) {
                return Err(format!(
                    "{shown}, line {line}: t_start_ms = {t}, but frame {frames} at a hop of {} ms starts at {want} ms (a file written with another hop_ms?)",
                    self.hop_ms
                ));
            }
            for i in 2..n + 2 {
                counts.push(cell(i)?);
            }
            frames += 1;
        }
        Ok((frames, counts))
    }

    fn loaded(&self) -> Result<&Loaded, StageError> {
        self.loaded
            .get_or_init(|| self.load())
            .as_ref()
            .map_err(Clone::clone)
    }
}

impl Source for ImageFileSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        Ok(self.loaded()?.iter().map(|(m, _)| m.clone()).collect())
    }
    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let trial = crate::io::common::loaded_trial(self.loaded()?, ctx.meta, "image files")?;
        Ok(Payload::Images(trial))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 x 5 grid folder of one CSV trial, written at a hop of 10 ms and a
    /// window of 30 ms; `info` is info.json's text (none when `None`).
    fn folder(info: Option<&str>) -> tempfile::TempDir {
        let d = tempfile::tempdir().unwrap();
        let cols: Vec<String> = (0..15).map(|i| format!("taxel_{i}")).collect();
        let mut csv = format!("frame,t_start_ms,{}\n", cols.join(","));
        for k in 0..4 {
            let counts: Vec<String> = (0..15).map(|i| ((i + k) % 3).to_string()).collect();
            csv.push_str(&format!("{k},{},{}\n", k as f64 * 10.0, counts.join(",")));
        }
        std::fs::write(d.path().join("t0.csv"), csv).unwrap();
        if let Some(info) = info {
            std::fs::write(d.path().join("info.json"), info).unwrap();
        }
        d
    }

    const GRID_3X5: &str =
        r#""layout": {"kind": "grid", "rows": 3, "cols": 5, "pitch_mm": 3.0, "taxel_mm": 2.0}"#;

    fn full_info() -> String {
        format!(r#"{{{GRID_3X5}, "window_ms": 30.0, "hop_ms": 10.0, "format": "csv", "trials": ["t0"]}}"#)
    }

    /// Builds the source from `keys` (TOML, `dir` added) over folder `d`.
    fn build(d: &tempfile::TempDir, keys: &str) -> Result<ImageFileSource, String> {
        let cfg: ImageFileConfig = toml::from_str(&format!("dir = \".\"\n{keys}")).unwrap();
        let ctx = BuildContext {
            stage_id: "img".into(),
            seed: 0,
            out_dir: d.path().to_path_buf(),
            base_dir: d.path().to_path_buf(),
        };
        cfg.source(&ctx).map_err(|e| e.to_string())
    }

    /// A key that info.json also records must agree with it: a 3 x 5 folder
    /// read as 5 x 3, or at another hop, window or format, is refused with
    /// the key, both values and the info.json named; agreeing keys pass.
    #[test]
    fn keys_that_disagree_with_info_json_are_refused_naming_both_values() {
        let d = folder(Some(&full_info()));
        for (keys, key, set, recorded) in [
            (
                "layout = { rows = 5, cols = 3, pitch_mm = 3.0, taxel_mm = 2.0 }",
                "layout",
                "5 x 3",
                "3 x 5",
            ),
            ("hop_ms = 20.0", "hop_ms", "20 ms", "10 ms"),
            ("window_ms = 25.0", "window_ms", "25 ms", "30 ms"),
            ("format = \"npy\"", "format", "\"npy\"", "\"csv\""),
        ] {
            let e = build(&d, keys)
                .err()
                .unwrap_or_else(|| panic!("{keys}: accepted"));
            assert!(
                e.contains(&format!("`{key}`"))
                    && e.contains(set)
                    && e.contains(recorded)
                    && e.contains("info.json"),
                "{keys}: {e}"
            );
        }
        let same = "layout = { rows = 3, cols = 5, pitch_mm = 3.0, taxel_mm = 2.0 }\n\
                    hop_ms = 10.0\nwindow_ms = 30.0\nformat = \"csv\"";
        let src = build(&d, same).unwrap();
        assert_eq!(
            (src.layout.grid(), src.hop_ms, src.window_ms),
            (Some((3, 5)), 10.0, 30.0)
        );
        let trials = src.trials().unwrap();
        assert_eq!(trials.len(), 1);
    }

    /// Keys supply what info.json does not record, and then the CSV's
    /// `t_start_ms` column still catches a hop the files were not written at.
    #[test]
    fn keys_supply_what_info_json_does_not_record() {
        let d = folder(Some(&format!(r#"{{{GRID_3X5}, "format": "csv"}}"#)));
        let e = build(&d, "").err().unwrap();
        assert!(e.contains("`hop_ms`") && e.contains("gives no `hop_ms`"), "{e}");
        let src = build(&d, "hop_ms = 10.0\nwindow_ms = 30.0").unwrap();
        assert_eq!(src.trials().unwrap().len(), 1);
        let src = build(&d, "hop_ms = 5.0\nwindow_ms = 30.0").unwrap();
        let e = src.trials().unwrap_err().message;
        assert!(e.contains("t_start_ms") && e.contains("t0.csv"), "{e}");
    }

    /// A folder without info.json says the file is missing and what it
    /// holds, and the keys can stand in for it.
    #[test]
    fn a_folder_without_info_json_says_it_is_missing() {
        let d = folder(None);
        let e = build(&d, "").err().unwrap();
        assert!(
            e.contains("info.json") && e.contains("is missing") && !e.contains("gives no"),
            "{e}"
        );
        for key in ["layout", "window_ms", "hop_ms", "format"] {
            assert!(e.contains(&format!("`{key}`")), "{key}: {e}");
        }
        let keys = "layout = { rows = 3, cols = 5, pitch_mm = 3.0, taxel_mm = 2.0 }\n\
                    hop_ms = 10.0\nwindow_ms = 30.0\nformat = \"csv\"";
        assert_eq!(build(&d, keys).unwrap().trials().unwrap().len(), 1);
    }
}
