//! Estimating with a saved model: the `model_in` key of every trained
//! estimator (`ann`, `edbn`, `svm`, `random_forest`, `knn`, `logistic`).
//!
//! # What
//!
//! `model_in = "models/x.model.json"` names a model that an offline run
//! wrote with `save_model = true` (`<out>/<stage id>.fold<f>.model.json`),
//! relative to the graph file's directory like every path key. With it the
//! stage does not fit: the model is loaded (and checked) when the graph is
//! built, and every trial is a test trial, as for the model-based WSS: no
//! folds, no training trials, no labels needed. It predicts
//!
//! * in batch, each trial's images at once ([`FittedModel::predict_images`]);
//! * streaming (`palpate run --live`), frame by frame through
//!   [`FittedModel::stream`]: the stage's streaming form
//!   (`crate::stream`'s `trained` module) keeps the running vote and emits
//!   the estimate whenever its answer changes, then the trial's final one.
//!
//! Both give the same final estimate (the batch scores the frames a stream
//! uses in one batch and votes in the same order; the per-trial seed of
//! stochastic EDBN inference is the same, `derive_seed(run seed, [stage id,
//! trial id])`), tested with blocks of 1, 7 and 1000 samples in
//! `stages/tests/stream_blocks.rs`.
//!
//! The model keeps its own feature spec (images stacked, step, stride,
//! `min_spikes`) and vote: the stage's training and feature keys are unused
//! when `model_in` is set. `save_model = true` together with `model_in` is an
//! error (nothing is fitted, so nothing would be saved).
//!
//! # Why
//!
//! A trained estimator fits once per fold on whole labelled trials, which a
//! live stream does not have: it sees one unlabelled trial at a time, as it
//! comes. Fitting offline and loading the result is the only way a trained
//! estimator can run live, and it lets a graph score new recordings with a
//! model fitted once rather than re-fitting per run.
//!
//! # Checks
//!
//! When the graph is built (so `palpate check` reports them), each naming the
//! key `model_in` and the file (the loader adds the stage): a missing or
//! unreadable file, a file that is not a palpate model (bad JSON, another
//! format version), a model fitted by another stage type (an `edbn` model in
//! an `ann` stage), and a model whose classes, feature spec or classifier
//! shape disagree with each other ([`FittedModel::check`]). When a trial
//! comes, naming the key and file too: images whose taxel count, frame
//! window or hop differ from the model's training images, or whose taxels
//! are arranged otherwise ([`same_arrangement`]: the same grid at another
//! pitch passes, a 2 x 8 strip for a 4 x 4 grid does not; a model saved
//! before models recorded their array is checked on the count alone).

use super::features::{load_model, FittedModel};
use palpate_core::{
    BuildContext, ConfigError, Estimate, Estimator, FitContext, Item, Model, SpikeImages, Stage, StageError,
    TrialContext,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A model loaded from `model_in`, with the file it came from.
#[derive(Clone, Debug)]
pub struct ModelIn {
    /// The checked model.
    pub model: Arc<FittedModel>,
    /// The resolved file.
    pub file: PathBuf,
}

impl ModelIn {
    /// Loads and checks the model `path` names (resolved against the graph's
    /// directory) for a stage of type `stage_type`. Errors name the key
    /// `model_in` and the file.
    pub fn load(stage_type: &str, path: &str, ctx: &BuildContext) -> Result<ModelIn, ConfigError> {
        if path.trim().is_empty() {
            return Err(ConfigError::key(
                "model_in",
                "is empty: name a model file written by `save_model = true`",
            ));
        }
        let file = ctx.resolve(Path::new(path));
        if !file.is_file() {
            return Err(ConfigError::key(
                "model_in",
                format!(
                    "{}: no such file (write one with `save_model = true` in an offline run: `<out>/<stage id>.fold<f>.model.json`)",
                    file.display()
                ),
            ));
        }
        let model = load_model(&file).map_err(|e| ConfigError::key("model_in", e.message))?;
        model
            .check(stage_type)
            .map_err(|e| ConfigError::key("model_in", format!("{}: {e}", file.display())))?;
        Ok(ModelIn {
            model: Arc::new(model),
            file,
        })
    }

    /// Checks that `images` fit the model (taxels, window, hop), naming the
    /// key and file.
    pub fn check_images(&self, images: &SpikeImages, what: &str) -> Result<(), StageError> {
        let f = &self.model.features;
        f.check_images(images, what).map_err(|e| self.error(e))?;
        match &f.layout {
            Some(l) if *l != images.layout && !same_arrangement(l, &images.layout) => {
                Err(self.error(StageError::new(format!(
                    "{what}: images come from {}, the model was trained on {}: its inputs are taxels by \
                 index, so another arrangement mixes them (retrain on this array)",
                    crate::io::common::describe_layout(&images.layout),
                    crate::io::common::describe_layout(l)
                ))))
            }
            _ => Ok(()),
        }
    }

    /// `e`, naming the key and the file.
    pub fn error(&self, e: StageError) -> StageError {
        StageError::new(format!("key `model_in` ({}): {}", self.file.display(), e.message))
    }
}

/// Whether two layouts place their taxels alike up to a uniform scale and a
/// shift: taxel `i` of one sits where taxel `i` of the other does once each
/// array's positions are centred and divided by their largest distance from
/// the centre (within 1e-6). So a model transfers to the same arrangement at
/// another pitch (whether it then works is for the user to measure), but
/// not to a transposed grid, a 2 x 8 strip, or renumbered taxels.
pub fn same_arrangement(a: &palpate_core::TaxelLayout, b: &palpate_core::TaxelLayout) -> bool {
    let norm = |l: &palpate_core::TaxelLayout| -> Vec<[f64; 2]> {
        let p = l.positions();
        let n = p.len().max(1) as f64;
        let c = p
            .iter()
            .fold([0.0, 0.0], |s, q| [s[0] + q[0] / n, s[1] + q[1] / n]);
        let r = p
            .iter()
            .map(|q| (q[0] - c[0]).hypot(q[1] - c[1]))
            .fold(0.0, f64::max);
        let r = if r > 0.0 { r } else { 1.0 };
        p.iter().map(|q| [(q[0] - c[0]) / r, (q[1] - c[1]) / r]).collect()
    };
    let (pa, pb) = (norm(a), norm(b));
    pa.len() == pb.len()
        && pa
            .iter()
            .zip(&pb)
            .all(|(x, y)| (x[0] - y[0]).abs() <= 1e-6 && (x[1] - y[1]).abs() <= 1e-6)
}

/// The model a trained estimator's `model_in` names, or `None` without it;
/// `save_model` with `model_in` is refused. Shared by the batch stage and its
/// streaming form, so both accept and refuse the same configs.
pub fn load_model_in(
    stage_type: &str,
    model_in: Option<&str>,
    save_model: bool,
    ctx: &BuildContext,
) -> Result<Option<ModelIn>, ConfigError> {
    let Some(path) = model_in else {
        return Ok(None);
    };
    if save_model {
        return Err(ConfigError::key(
            "save_model",
            "cannot be true with `model_in`: a loaded model is not fitted, so there is nothing new to save",
        ));
    }
    ModelIn::load(stage_type, path, ctx).map(Some)
}

/// The stage of a trained estimator given `model_in`, or `None` without it.
pub fn stage(
    stage_type: &str,
    model_in: Option<&str>,
    save_model: bool,
    ctx: &BuildContext,
) -> Result<Option<Stage>, ConfigError> {
    Ok(load_model_in(stage_type, model_in, save_model, ctx)?
        .map(|m| Stage::Estimator(Box::new(SavedEstimator(m)) as Box<dyn Estimator>)))
}

/// A trained estimator's stage with a loaded model: model-based (no fit).
struct SavedEstimator(ModelIn);

impl Estimator for SavedEstimator {
    fn trained(&self) -> bool {
        false
    }
    fn fit(&self, _train: &[&Item], _ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        Ok(Box::new(SavedModel(self.0.clone())))
    }
}

struct SavedModel(ModelIn);

impl Model for SavedModel {
    fn predict(&self, item: &Item, ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        let images = item.payload.images()?;
        let what = format!("trial `{}`", item.meta.trial_id);
        self.0.check_images(images, &what)?;
        self.0.model.predict(item, ctx).map_err(|e| self.0.error(e))
    }
    fn saved_bytes(&self) -> Option<Result<Vec<u8>, StageError>> {
        self.0.model.saved_bytes()
    }
}
