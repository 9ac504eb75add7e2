//! Simulated scenes: an edge or a ridge crossing a taxel array (the paper's
//! protocol, and the effects a lab scene may call for). No recordings of the paper's sensor are public, so most
//! experiments draw their data from here; the simulator is exact where it can
//! be, and says what it models where it cannot.
//!
//! # What is simulated
//!
//! * **Geometry** ([`sim`]): core's edge convention; the array rests on the
//!   object, slides `+x` at constant speed until the stimulus is fully past, and
//!   rests again. Trials are listed angle by angle, `trials_per_angle` each:
//!   trial id `edge-45deg-r03`, label `{stimulus, angle}`, group = repetition
//!   (0-based; the cross-validation key), `crossing_ms` = when the stimulus
//!   touches some taxel, from the geometry.
//! * **Ideal response** ([`field`]): each taxel reports the contact pressure
//!   averaged over its square area, in closed form (never a point sample at the
//!   centre). For an edge that is the contact fraction in `[0, 1]`; for a ridge,
//!   `1` (the flat surface) plus the bar's extra pressure `height / indent`
//!   times the fraction of the taxel over it. Unit "pressure".
//! * **Effects** ([`effects`]): skin spreading, stress concentration,
//!   piezoresistive read-out, gain/offset mismatch, row/column crosstalk,
//!   viscoelastic creep, white noise, mains hum, ADC quantization, trial
//!   variation and dead taxels, and ([`sensor`]) the soft sleeve's thickness
//!   and stick-slip shear, end-effector tilt, loading/unloading hysteresis
//!   with slow recovery, per-taxel time constants and passive-matrix
//!   ghosting — each a separate component, constructed and computed only when
//!   a scene lists it, applied in the listed order.
//!
//! # Reproducibility
//!
//! A trial is a pure function of (scene, graph seed, stage id, trial id): per
//! trial draws come from `ctx.seed`, the array's fixed properties from
//! `derive_seed(graph seed, [stage id, "array"])`. Same seed, same bits, on any
//! number of threads.
//!
//! # Scene files
//!
//! `file = "scenes/lab.toml"` takes a scene's keys as defaults (see
//! [`config`]); `graphs/scenes/ideal.toml` and `graphs/scenes/lab.toml` are the
//! shipped scenes. [`simulate_to_dir`] writes a scene's trials for `palpate
//! simulate` as `signal_file` reads them back (the files `write_signals`
//! writes: NPY `(samples, taxels)` by default, or CSV `time_ms, taxel_0 ..`),
//! with a `labels.toml` label file, a `trials.json` of the trials' metadata
//! (also accepted as a label file) and a plot of one taxel.

pub mod config;
pub mod effects;
pub mod field;
pub mod gauss;
pub mod sensor;
pub mod sim;
pub mod special;

#[cfg(test)]
mod tests;

pub use config::{SceneConfig, StimulusKind};
pub use sim::Simulator;

use palpate_core::output::write_atomic;
use palpate_core::{
    derive_seed, register_stage, BuildContext, ConfigError, InputSpec, Inspection, Label, OutputFacts,
    Payload, PayloadKind, Source, Stage, StageConfig, StageError, Stimulus, TrialContext, TrialMeta,
};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[typetag::serde(name = "scene")]
impl StageConfig for SceneConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut sims = Vec::new();
        let mut fingerprints = Vec::new();
        for (name, cfg, scene) in self.resolve_conditions(ctx)?.0 {
            let seed = array_seed(ctx, cfg.array_copy.unwrap_or(0));
            // The condition's merged config (scene file, base keys and the
            // condition's own) and its array draw: all a trial of it reads.
            fingerprints.push(serde_json::json!([cfg, seed.to_string()]).to_string());
            let sim = Simulator::new(scene, seed)?;
            sims.push((name, Arc::new(sim)));
        }
        Ok(Stage::Source(Box::new(SceneSource { sims, fingerprints })))
    }
    /// The sample rate (`motion.sample_rate_hz`), for the stages downstream
    /// (a low-pass checks its cutoff against it), the array when every
    /// condition has the same, and the deprecation warnings of the scene's
    /// keys and file.
    ///
    /// Conditions on different arrays draw a warning, as a union's sources
    /// do (legal for WSS, wrong for a trained estimator), at each condition
    /// whose array differs from the first condition's.
    fn inspect(&self, ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        let Ok((conditions, mut warnings)) = self.resolve_conditions(ctx) else {
            // `build` reported it already.
            return Inspection::default();
        };
        if let Some(((Some(first), _, s0), rest)) = conditions.split_first() {
            for (name, _, s) in rest.iter().filter(|(_, _, s)| s.layout != s0.layout) {
                warnings.push(crate::io::common::other_array_warning(
                    format!("conditions.{}", name.as_deref().unwrap_or_default()),
                    &s.layout,
                    "condition",
                    first,
                    &s0.layout,
                ));
            }
        }
        Inspection {
            facts: OutputFacts {
                // One rate when every condition samples alike.
                sample_rate_hz: conditions
                    .iter()
                    .map(|(_, _, scene)| scene.motion.sample_rate_hz)
                    .reduce(|a, b| if a == b { a } else { f64::NAN })
                    .filter(|r| r.is_finite()),
                // One array when every condition uses the same (warned
                // above when they differ).
                layout: OutputFacts::one(conditions.iter().map(|(_, _, s)| &s.layout)).cloned(),
            },
            errors: Vec::new(),
            warnings,
        }
    }
}
register_stage!("scene", SceneConfig);

/// The seed of the array's manufacturing draws: copy 0 is the run seed's own
/// (as before copies existed), copy `c` another independent draw.
fn array_seed(ctx: &BuildContext, copy: u32) -> u64 {
    if copy == 0 {
        derive_seed(ctx.seed, &[&ctx.stage_id, "array"])
    } else {
        derive_seed(ctx.seed, &[&ctx.stage_id, "array", &copy.to_string()])
    }
}

/// The runtime `scene` source: one simulator per condition.
pub struct SceneSource {
    sims: Vec<(Option<String>, Arc<Simulator>)>,
    /// Per condition (same order as `sims`): what its trials depend on, for
    /// [`Source::trial_fingerprint`].
    fingerprints: Vec<String>,
}

impl SceneSource {
    /// The simulator behind the source (the first condition's).
    pub fn simulator(&self) -> &Simulator {
        &self.sims[0].1
    }
    /// The position in `sims` of the condition `meta` names.
    fn condition_of(&self, meta: &TrialMeta) -> Result<usize, StageError> {
        let want = meta.conditions.get("condition");
        self.sims
            .iter()
            .position(|(name, _)| name.as_ref() == want || self.sims.len() == 1 && name.is_none())
            .ok_or_else(|| {
                StageError::new(format!(
                    "trial `{}` names condition {want:?}, which this scene does not simulate",
                    meta.trial_id
                ))
            })
    }
}

/// The trial id of repetition `rep` at `angle`: `edge-45deg-r03`.
pub fn trial_id(stimulus: StimulusKind, angle: f64, rep: usize) -> String {
    let s = match stimulus {
        StimulusKind::Edge => "edge",
        StimulusKind::Ridge => "ridge",
    };
    format!("{s}-{}deg-r{rep:02}", config::angle_id(angle))
}

impl Source for SceneSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        let mut out = Vec::new();
        for (name, sim) in &self.sims {
            let sc = &sim.scene;
            let conditions: std::collections::BTreeMap<String, String> = name
                .iter()
                .map(|n| ("condition".to_string(), n.clone()))
                .collect();
            let prefix = name.as_ref().map(|n| format!("{n}-")).unwrap_or_default();
            for &angle in &sc.angles {
                let plan = sim.plan(angle)?;
                let crossing = sim.crossing_ms(&plan);
                for rep in 0..sc.trials_per_angle {
                    out.push(TrialMeta {
                        trial_id: format!("{prefix}{}", trial_id(sc.stimulus, angle, rep)),
                        index: out.len(),
                        label: Label {
                            stimulus: match sc.stimulus {
                                StimulusKind::Edge => Stimulus::Edge,
                                StimulusKind::Ridge => Stimulus::Ridge,
                            },
                            angle_deg: Some(angle),
                        },
                        group: rep,
                        crossing_ms: Some(crossing),
                        // The commanded speed, before `variation`'s tracking error.
                        speed_mm_s: Some(sc.motion.speed_mm_s),
                        conditions: conditions.clone(),
                        provenance: Vec::new(),
                    });
                }
            }
        }
        Ok(out)
    }

    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let angle = ctx.meta.label.angle_deg.ok_or_else(|| {
            StageError::new(format!(
                "trial `{}` has no angle: not a trial of this scene",
                ctx.meta.trial_id
            ))
        })?;
        let sim = &self.sims[self.condition_of(ctx.meta)?].1;
        Ok(sim.simulate(angle, ctx.seed)?.into())
    }

    /// The trial's condition's merged config and array seed: a sweep that
    /// shifts one condition reuses the other conditions' trials.
    fn trial_fingerprint(&self, meta: &TrialMeta) -> Option<String> {
        self.condition_of(meta)
            .ok()
            .and_then(|c| self.fingerprints.get(c).cloned())
    }
}

/// Simulates every trial of a scene file and writes, into `out` (created):
///
/// * `<trial_id>.npy`: float64, shape `(samples, taxels)`, C order; or, with
///   `csv`, `<trial_id>.csv`: header `time_ms,taxel_0,..`, one row per sample
///   (the formats of `write_signals`, which `signal_file` reads);
/// * `labels.toml`: each trial's angle, stimulus and group, the label file
///   `signal_file`'s `labels` key reads;
/// * `trials.json`: every trial's metadata, sample rate, unit and layout
///   (`signal_file` also accepts it as a label file);
/// * `<first trial>-<taxel>.svg`: one taxel's signal over the first trial, like
///   the paper's Fig. 3(a) (taxel `r1c1` of a grid: an inner taxel; else taxel 0).
///
/// Trials are exactly those a graph with a `scene` stage of id `"scene"`,
/// `file = <scene_file>` and `[run] seed = <seed>` produces. Returns the paths
/// written, in that order (per trial NPY then CSV, then the JSON and the plot).
pub fn simulate_to_dir(
    scene_file: &Path,
    out: &Path,
    seed: u64,
    csv: bool,
) -> Result<Vec<PathBuf>, StageError> {
    let config = SceneConfig {
        file: Some(scene_file.to_path_buf()),
        ..SceneConfig::default()
    };
    let ctx = BuildContext {
        stage_id: "scene".into(),
        seed,
        out_dir: out.to_path_buf(),
        base_dir: PathBuf::from("."),
    };
    // The same simulators a graph's `scene` stage builds, every condition included.
    let mut sims = Vec::new();
    let (conditions, warnings) = config
        .resolve_conditions(&ctx)
        .map_err(|e| StageError::new(e.to_string()))?;
    // Deprecated spellings in the scene file: said, as `check` says them.
    for w in &warnings {
        palpate_core::warn(&format!("warning: {w}"));
    }
    for (name, cfg, scene) in conditions {
        let sim = Simulator::new(scene, array_seed(&ctx, cfg.array_copy.unwrap_or(0)))
            .map_err(|e| StageError::new(format!("scene file {}: {e}", scene_file.display())))?;
        sims.push((name, Arc::new(sim)));
    }
    let source = SceneSource {
        sims,
        fingerprints: Vec::new(),
    };
    let metas = source.trials()?;
    std::fs::create_dir_all(out).map_err(|e| StageError::new(format!("creating {}: {e}", out.display())))?;
    let names = taxel_names(&source.simulator().scene.layout);
    // The files `write_signals` writes, so `signal_file` reads them back:
    // NPY `(samples, taxels)`, or CSV `time_ms, taxel_0 ..`; one per trial,
    // named after the trial id (scene ids are safe file names).
    let written: Vec<(PathBuf, f64)> = metas
        .par_iter()
        .map(|meta| {
            let ctx = TrialContext {
                stage_id: "scene",
                meta,
                seed: derive_seed(seed, &["scene", &meta.trial_id]),
            };
            let payload = source.produce(&ctx)?;
            let sig = payload.signals()?;
            let (path, bytes) = if csv {
                let path = out.join(format!("{}.csv", meta.trial_id));
                (path, crate::io::sinks::signals_csv(sig).into_bytes())
            } else {
                let path = out.join(format!("{}.npy", meta.trial_id));
                (path, crate::io::sinks::signals_npy(sig)?)
            };
            write_file(&path, &bytes)?;
            Ok((path, sig.sample_rate_hz))
        })
        .collect::<Result<_, StageError>>()?;
    // One rate for every trial (a condition may set its own): labels.toml
    // declares it, so the NPY files read back without a `sample_rate_hz` key.
    let one_rate = crate::io::common::shared_rate(written.iter().map(|w| w.1));
    let mut files: Vec<PathBuf> = written.into_iter().map(|w| w.0).collect();
    let rows: Vec<(String, &TrialMeta, Option<f64>)> =
        metas.iter().map(|m| (m.trial_id.clone(), m, None)).collect();
    let labels = out.join("labels.toml");
    let layout = &source.simulator().scene.layout;
    write_file(
        &labels,
        crate::io::common::sidecar_toml(&rows, Some(layout), one_rate).as_bytes(),
    )?;
    files.push(labels);

    let sc = &source.simulator().scene;
    let json = serde_json::json!({
        "scene_file": scene_file.display().to_string(),
        "seed": seed,
        "sample_rate_hz": sc.motion.sample_rate_hz,
        "unit": source.simulator().unit,
        "layout": sc.layout,
        "taxels": names,
        "columns": (0..names.len()).map(|i| format!("taxel_{i}")).collect::<Vec<_>>(),
        "trials": metas,
    });
    let path = out.join("trials.json");
    let text = serde_json::to_vec_pretty(&json).map_err(|e| StageError::new(e.to_string()))?;
    write_file(&path, &text)?;
    files.push(path);

    if let Some(meta) = metas.first() {
        let ctx = TrialContext {
            stage_id: "scene",
            meta,
            seed: derive_seed(seed, &["scene", &meta.trial_id]),
        };
        let payload = source.produce(&ctx)?;
        let sig = payload.signals()?;
        let taxel = if sc.layout.grid().is_some_and(|(r, c)| r > 1 && c > 1) {
            sc.layout.grid().map_or(0, |(_, c)| c + 1)
        } else {
            0
        };
        let dt = 1000.0 / sig.sample_rate_hz;
        let points = sig.data[taxel]
            .iter()
            .enumerate()
            .map(|(k, &v)| (k as f64 * dt / 1000.0, v))
            .collect();
        let path = out.join(format!("{}-{}.svg", meta.trial_id, names[taxel]));
        crate::plot::line_chart(
            &path,
            &format!("{}: taxel {}", meta.trial_id, names[taxel]),
            "time (s)",
            &format!("taxel output ({})", sig.unit),
            &[crate::plot::Series {
                name: &names[taxel],
                points,
            }],
        )
        .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
        files.push(path);
    }
    if let Some(w) = stale_recordings(out, &files) {
        palpate_core::warn(&format!("warning: {w}"));
    }
    Ok(files)
}

/// A warning when `out` holds recordings (`.npy`, `.csv`) this run did not
/// write: trials of an earlier `simulate` into the same folder, which the
/// new `labels.toml` does not list, so the `path = "<out>/*.npy"` it
/// suggests would fail on them. Kept, not deleted: they are the user's.
fn stale_recordings(out: &Path, written: &[PathBuf]) -> Option<String> {
    let mut stale: Vec<String> = std::fs::read_dir(out)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .is_some_and(|x| x.eq_ignore_ascii_case("npy") || x.eq_ignore_ascii_case("csv"))
                && !written.contains(p)
        })
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    if stale.is_empty() {
        return None;
    }
    stale.sort();
    let n = stale.len();
    let shown = stale.iter().take(3).cloned().collect::<Vec<_>>().join(", ");
    Some(format!(
        "{} holds {n} recording{} this run did not write ({shown}{}), not in its new labels.toml: a \
         `path = \"{}/*\"` pattern would take them too; remove them or simulate into an empty folder",
        out.display(),
        if n == 1 { "" } else { "s" },
        if n > 3 { ", ..." } else { "" },
        out.display()
    ))
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), StageError> {
    write_atomic(path, bytes).map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))
}

/// Column names of the taxels: `r0c0`, `r0c1`, ... for a grid, `t0`, ... otherwise.
pub fn taxel_names(layout: &palpate_core::TaxelLayout) -> Vec<String> {
    (0..layout.len())
        .map(|i| match layout.row_col(i) {
            Some((r, c)) => format!("r{r}c{c}"),
            None => format!("t{i}"),
        })
        .collect()
}
