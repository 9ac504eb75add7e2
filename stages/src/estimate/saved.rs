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
//! window or hop differ from the model's training images.

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
        self.model
            .features
            .check_images(images, what)
            .map_err(|e| self.error(e))
    }

    /// `e`, naming the key and the file.
    pub fn error(&self, e: StageError) -> StageError {
        StageError::new(format!("key `model_in` ({}): {}", self.file.display(), e.message))
    }
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
