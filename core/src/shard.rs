//! Sweeps beyond one process: addressing points, running a subset of them (a
//! shard), resuming after a kill, and rebuilding the whole sweep from the point
//! folders so that any split gives the report a single process gives.
//!
//! * **Points.** A sweep's points are numbered from 0 in the order of
//!   [`SweepSettings::points`](crate::graph::SweepSettings::points) (the values
//!   of the single-key form, or each series' values in turn). A point's repeats
//!   always run together, in the same process.
//! * **Selections.** `--points 3,7-9` names points by number; `--shard K/N`
//!   (1-based `K`) takes the `K`-th of `N` contiguous blocks: point `p` of `P`
//!   belongs to shard `floor(p * N / P) + 1`. Contiguous blocks keep a series'
//!   neighbouring points (which usually share their upstream stages) in one
//!   process, where the sweep cache serves them once.
//! * **Seeds** come from the point and the repeat (`[run] seed + r`, see
//!   [`crate::sweep`]), never from the shard, so the results of a point do not
//!   depend on how points are spread.
//! * **Completion.** A finished (point, repeat) writes its reports into its own
//!   folder, then, last and atomically, `point.json` ([`PointRecord`]): the
//!   completion marker, holding every sink's text and metrics and every stage's
//!   timing. A kill at any moment leaves either no marker (the point runs again)
//!   or a whole one. Markers carry a [`fingerprint`] of the point's loaded graph
//!   (stage types, configs, wiring, run settings) and palpate's version, so a
//!   marker left by a different graph is never mistaken for this one's; files the
//!   graph only names (a scene file, a recording) are not covered: rerun with
//!   `--fresh` after editing them.
//! * **Manifest.** Every run of a sweep writes `sweep-manifest.json` to the
//!   sweep's output folder (the graph's text, file name, overrides and base
//!   directory): `palpate merge OUT` needs nothing else, and two shards write
//!   the same bytes, atomically.
//!
//! Metric values are stored by their bits, so a merged table is bit-identical
//! to a single run's, NaN included.

use crate::graph::{load_str, Diagnostic, Graph, LoadErrors, LoadOptions, Severity};
use crate::output::write_atomic;
use crate::runtime::{RunResult, StageTiming};
use crate::stage::{ClassMetric, SinkReport};
use crate::sweep::{point_dir, point_label};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Largest point number a `--points` list may name (a typo such as `1-999999999`
/// must not allocate a list of a billion numbers).
pub const MAX_POINTS: usize = 1_000_000;

/// Name of a point's completion marker.
pub const MARKER: &str = "point.json";
/// Name of the sweep's manifest in its output folder.
pub const MANIFEST: &str = "sweep-manifest.json";

/// Which points of a sweep to run.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub enum Selection {
    /// Every point.
    #[default]
    All,
    /// These point numbers (sorted, unique).
    Points(Vec<usize>),
    /// Shard `k` of `n` (1-based `k`).
    Shard {
        /// This shard, 1..=n.
        k: usize,
        /// Number of shards.
        n: usize,
    },
}

impl Selection {
    /// Parses a `--points` list: comma-separated numbers and inclusive ranges
    /// `a-b`, e.g. `3,7-9`.
    pub fn parse_points(s: &str) -> Result<Selection, String> {
        let mut out = Vec::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let num = |t: &str| {
                t.trim()
                    .parse::<usize>()
                    .map_err(|_| format!("`--points {s}`: `{t}` is not a point number (0, 1, 2, ...)"))
            };
            let (a, b) = match part.split_once('-') {
                Some((a, b)) => (num(a)?, num(b)?),
                None => {
                    let v = num(part)?;
                    (v, v)
                }
            };
            if a > b {
                return Err(format!("`--points {s}`: range `{part}` runs backwards"));
            }
            if b >= MAX_POINTS {
                return Err(format!(
                    "`--points {s}`: point {b} is beyond the limit of {MAX_POINTS} points"
                ));
            }
            out.extend(a..=b);
        }
        if out.is_empty() {
            return Err(format!("`--points {s}` names no point"));
        }
        out.sort_unstable();
        out.dedup();
        Ok(Selection::Points(out))
    }

    /// Parses a `--shard K/N`, 1 <= K <= N.
    pub fn parse_shard(s: &str) -> Result<Selection, String> {
        let bad = || format!("`--shard {s}` needs the form K/N with 1 <= K <= N, e.g. 2/4");
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let k: usize = k.trim().parse().map_err(|_| bad())?;
        let n: usize = n.trim().parse().map_err(|_| bad())?;
        if k == 0 || n == 0 || k > n {
            return Err(bad());
        }
        Ok(Selection::Shard { k, n })
    }

    /// Whether point `p` of `total` is selected.
    pub fn contains(&self, p: usize, total: usize) -> bool {
        match self {
            Selection::All => true,
            Selection::Points(list) => list.binary_search(&p).is_ok(),
            // p * n fits: p < total <= MAX sweep size, n <= total in practice;
            // saturate anyway so a huge n cannot overflow.
            Selection::Shard { k, n } => p.saturating_mul(*n) / total.max(1) + 1 == *k,
        }
    }

    /// Point numbers that a `--points` list names but the sweep lacks.
    pub fn out_of_range(&self, total: usize) -> Vec<usize> {
        match self {
            Selection::Points(list) => list.iter().copied().filter(|&p| p >= total).collect(),
            _ => Vec::new(),
        }
    }
}

/// A stable 64-bit fingerprint of a loaded graph: palpate's version, the run
/// settings other than the output folder, and every stage's id, type, inputs and
/// config (as JSON). FNV-1a, so it is stable across Rust versions and platforms.
pub fn fingerprint(graph: &Graph) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut feed = |bytes: &[u8]| {
        for &b in bytes.iter().chain(std::iter::once(&0xffu8)) {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    feed(env!("CARGO_PKG_VERSION").as_bytes());
    let mut run = graph.run.clone();
    run.out = None;
    feed(serde_json::to_string(&run).unwrap_or_default().as_bytes());
    for (node, inputs) in graph.nodes.iter().zip(&graph.input_index) {
        feed(node.id.as_bytes());
        feed(node.type_name.as_bytes());
        for &i in inputs {
            feed(graph.nodes.get(i).map_or(&b""[..], |n| n.id.as_bytes()));
        }
        feed(serde_json::to_string(&node.config).unwrap_or_default().as_bytes());
    }
    format!("{h:016x}")
}

/// A metric as stored: its name, its value for readers, and its exact bits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MetricRecord {
    /// The metric's name (e.g. `wss.mae_deg`).
    pub name: String,
    /// Its value (`null` when not finite), for people and other tools.
    pub value: Option<f64>,
    /// `f64::to_bits` of the value: what palpate reads back.
    pub bits: u64,
}

/// A sink's report as stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReportRecord {
    /// The sink's stage id.
    pub id: String,
    /// Its terminal text.
    pub text: String,
    /// Files it wrote.
    pub files: Vec<PathBuf>,
    /// Its metrics.
    pub metrics: Vec<MetricRecord>,
    /// Its per-class metrics (absent in markers written before they existed).
    #[serde(default)]
    pub class_metrics: Vec<ClassMetricRecord>,
}

/// A per-class metric as stored: as [`MetricRecord`], with its class.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClassMetricRecord {
    /// The metric's name (e.g. `wss.mae_deg`).
    pub name: String,
    /// The class (true angle, degrees), by its bits.
    pub class_bits: u64,
    /// Its value (`null` when not finite), for people and other tools.
    pub value: Option<f64>,
    /// `f64::to_bits` of the value: what palpate reads back.
    pub bits: u64,
}

/// A stage's timing as stored, in nanoseconds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TimingRecord {
    /// The stage's id.
    pub id: String,
    /// Its type.
    pub type_name: String,
    /// Its role: source, map, estimator or sink.
    pub role: String,
    /// Per trial, ns.
    pub per_trial_ns: Vec<u64>,
    /// Per fit, ns.
    pub fits_ns: Vec<u64>,
    /// The whole stage, ns.
    pub total_ns: u64,
    /// Served from the sweep cache.
    pub cached: bool,
}

/// A finished (point, repeat): the completion marker `point.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointRecord {
    /// Format version of this record.
    pub format: u32,
    /// [`fingerprint`] of the point's graph.
    pub fingerprint: String,
    /// Point number.
    pub point: usize,
    /// Repeat number.
    pub repeat: usize,
    /// The point's label.
    pub label: String,
    /// The seed the run used.
    pub seed: u64,
    /// Every sink's report.
    pub reports: Vec<ReportRecord>,
    /// Every stage's timing.
    pub timings: Vec<TimingRecord>,
}

const FORMAT: u32 = 1;

fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

fn role(s: &str) -> &'static str {
    match s {
        "source" => "source",
        "map" => "map",
        "estimator" => "estimator",
        "sink" => "sink",
        _ => "stage",
    }
}

impl PointRecord {
    /// The record of a finished run of `graph` as point `point`, repeat `repeat`.
    pub fn new(graph: &Graph, point: usize, repeat: usize, label: &str, result: &RunResult) -> Self {
        PointRecord {
            format: FORMAT,
            fingerprint: fingerprint(graph),
            point,
            repeat,
            label: label.to_string(),
            seed: graph.run.seed,
            reports: result
                .reports
                .iter()
                .map(|(id, r)| ReportRecord {
                    id: id.clone(),
                    text: r.text.clone(),
                    files: r.files.clone(),
                    metrics: r
                        .metrics
                        .iter()
                        .map(|(name, v)| MetricRecord {
                            name: name.clone(),
                            value: v.is_finite().then_some(*v),
                            bits: v.to_bits(),
                        })
                        .collect(),
                    class_metrics: r
                        .class_metrics
                        .iter()
                        .map(|c| ClassMetricRecord {
                            name: c.name.clone(),
                            class_bits: c.class.to_bits(),
                            value: c.value.is_finite().then_some(c.value),
                            bits: c.value.to_bits(),
                        })
                        .collect(),
                })
                .collect(),
            timings: result
                .timings
                .iter()
                .map(|t| TimingRecord {
                    id: t.id.clone(),
                    type_name: t.type_name.clone(),
                    role: t.role.to_string(),
                    per_trial_ns: t.per_trial.iter().copied().map(nanos).collect(),
                    fits_ns: t.fits.iter().copied().map(nanos).collect(),
                    total_ns: nanos(t.total),
                    cached: t.cached,
                })
                .collect(),
        }
    }

    /// The run result this record stands for (no stage outputs).
    pub fn to_result(&self) -> RunResult {
        RunResult {
            reports: self
                .reports
                .iter()
                .map(|r| {
                    (
                        r.id.clone(),
                        SinkReport {
                            text: r.text.clone(),
                            files: r.files.clone(),
                            metrics: r
                                .metrics
                                .iter()
                                .map(|m| (m.name.clone(), f64::from_bits(m.bits)))
                                .collect(),
                            class_metrics: r
                                .class_metrics
                                .iter()
                                .map(|c| ClassMetric {
                                    name: c.name.clone(),
                                    class: f64::from_bits(c.class_bits),
                                    value: f64::from_bits(c.bits),
                                })
                                .collect(),
                        },
                    )
                })
                .collect(),
            timings: self
                .timings
                .iter()
                .map(|t| StageTiming {
                    id: t.id.clone(),
                    type_name: t.type_name.clone(),
                    role: role(&t.role),
                    per_trial: t.per_trial_ns.iter().copied().map(Duration::from_nanos).collect(),
                    fits: t.fits_ns.iter().copied().map(Duration::from_nanos).collect(),
                    total: Duration::from_nanos(t.total_ns),
                    cached: t.cached,
                })
                .collect(),
            outputs: Default::default(),
        }
    }

    /// Writes the record as `dir/point.json`, atomically: the last file a point
    /// writes.
    pub fn write(&self, dir: &Path) -> Result<(), String> {
        let path = dir.join(MARKER);
        let json =
            serde_json::to_vec_pretty(self).map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
        write_atomic(&path, &json).map_err(|e| format!("cannot write {}: {e}", path.display()))
    }

    /// Reads `dir/point.json` if it is there, whole, and stands for `graph` as
    /// point `point`, repeat `repeat`; `None` otherwise (the point must run).
    pub fn read_matching(dir: &Path, graph: &Graph, point: usize, repeat: usize) -> Option<PointRecord> {
        let bytes = crate::input::read_capped(&dir.join(MARKER), crate::input::MAX_TEXT_FILE_BYTES).ok()?;
        let rec: PointRecord = serde_json::from_slice(&bytes).ok()?;
        (rec.format == FORMAT
            && rec.point == point
            && rec.repeat == repeat
            && rec.fingerprint == fingerprint(graph))
        .then_some(rec)
    }
}

/// What `palpate merge` needs to rebuild a sweep: the graph as it was run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Format version.
    pub format: u32,
    /// The graph file's name as given on the command line.
    pub file: String,
    /// Its text.
    pub text: String,
    /// The directory its relative paths resolve against.
    pub base_dir: PathBuf,
    /// `--set` overrides, as `key = value` TOML lines.
    pub overrides: Vec<(String, String)>,
    /// Number of points.
    pub points: usize,
    /// Repeats per point.
    pub repeats: usize,
}

impl Manifest {
    /// Writes the manifest into `out` (atomically; shards write the same bytes).
    pub fn write(&self, out: &Path) -> Result<(), String> {
        let path = out.join(MANIFEST);
        let json =
            serde_json::to_vec_pretty(self).map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
        write_atomic(&path, &json).map_err(|e| format!("cannot write {}: {e}", path.display()))
    }

    /// Reads `out/sweep-manifest.json`.
    pub fn read(out: &Path) -> Result<Manifest, String> {
        let path = out.join(MANIFEST);
        let bytes = crate::input::read_capped(&path, crate::input::MAX_TEXT_FILE_BYTES).map_err(|e| {
            format!(
                "cannot read {}: {e} (is {} the output folder of a sweep run by `palpate run`?)",
                path.display(),
                out.display()
            )
        })?;
        let m: Manifest = serde_json::from_slice(&bytes)
            .map_err(|e| format!("{}: not a sweep manifest: {e}", path.display()))?;
        if m.format != FORMAT {
            return Err(format!(
                "{}: manifest format {} (this palpate reads {FORMAT})",
                path.display(),
                m.format
            ));
        }
        Ok(m)
    }

    /// The overrides as load options, with `out` as the output folder.
    pub fn load_options(&self, out: &Path) -> Result<LoadOptions, String> {
        let mut overrides = Vec::with_capacity(self.overrides.len());
        for (k, v) in &self.overrides {
            let value = toml::from_str::<toml::Table>(&format!("v = {v}"))
                .ok()
                .and_then(|mut t| t.remove("v"))
                .ok_or_else(|| format!("{MANIFEST}: override `{k} = {v}` is not a TOML value"))?;
            overrides.push((k.clone(), value));
        }
        Ok(LoadOptions {
            overrides,
            out: Some(out.to_path_buf()),
            base_dir: Some(self.base_dir.clone()),
        })
    }

    /// Loads the base graph the manifest describes.
    pub fn load(&self, out: &Path) -> Result<(Graph, LoadOptions), LoadErrors> {
        let opts = self.load_options(out).map_err(|message| {
            LoadErrors(vec![Diagnostic {
                severity: Severity::Error,
                file: out.join(MANIFEST).display().to_string(),
                line: None,
                stage: None,
                key: None,
                message,
            }])
        })?;
        let g = load_str(&self.text, &self.file, &stem(&self.file), &opts)?;
        Ok((g, opts))
    }
}

/// A graph file's stem, as the loader names its default output folder.
pub fn stem(file: &str) -> String {
    Path::new(file)
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("graph")
        .to_string()
}

/// Where the (point, repeat) of a sweep with `repeats` repeats reports.
pub fn record_dir(out: &Path, point: &crate::graph::SweepPoint, repeats: usize, repeat: usize) -> PathBuf {
    point_dir(out, &point_label(point), (repeats > 1).then_some(repeat))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_lists_and_ranges() {
        assert_eq!(
            Selection::parse_points("3,7-9").unwrap(),
            Selection::Points(vec![3, 7, 8, 9])
        );
        assert_eq!(
            Selection::parse_points(" 9-9 , 1,1 ").unwrap(),
            Selection::Points(vec![1, 9])
        );
        assert!(Selection::parse_points("9-3").unwrap_err().contains("backwards"));
        assert!(Selection::parse_points("x").unwrap_err().contains("`x`"));
        assert!(Selection::parse_points("").is_err());
        assert!(Selection::parse_points("0-18446744073709551615")
            .unwrap_err()
            .contains("limit"));
        let s = Selection::parse_points("1,5").unwrap();
        assert_eq!(s.out_of_range(3), vec![5]);
    }

    #[test]
    fn shards_partition_every_point_once() {
        for total in [1usize, 2, 3, 7, 16, 29] {
            for n in 1..=total + 2 {
                let mut owner = vec![0usize; total];
                for k in 1..=n {
                    let s = Selection::parse_shard(&format!("{k}/{n}")).unwrap();
                    for (p, o) in owner.iter_mut().enumerate() {
                        if s.contains(p, total) {
                            *o += 1;
                        }
                    }
                }
                assert!(owner.iter().all(|&c| c == 1), "total {total}, n {n}: {owner:?}");
            }
        }
        assert!(Selection::parse_shard("0/4").is_err());
        assert!(Selection::parse_shard("5/4").is_err());
        assert!(Selection::parse_shard("1-4").is_err());
    }

    #[test]
    fn shards_are_contiguous_blocks() {
        let s = Selection::parse_shard("2/3").unwrap();
        let got: Vec<usize> = (0..9).filter(|&p| s.contains(p, 9)).collect();
        assert_eq!(got, vec![3, 4, 5]);
    }
}
