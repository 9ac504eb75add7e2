//! Streaming trained estimators (`ann`, `edbn`, `svm`, `random_forest`,
//! `knn`, `logistic`) with a model saved by an offline run (`model_in`; see
//! [`crate::estimate::saved`]).
//!
//! Each trial's state is a [`Streamer`] over the shared loaded model, seeded
//! like the batch prediction of the trial: every image is pushed as it comes,
//! the running vote is kept, and an estimate block is emitted whenever the
//! answer (class or "no edge") changes. The flush emits the trial's final
//! estimate, its decision time capped at what the images cover, as the batch
//! model does, so it is the batch estimate.
//!
//! Without `model_in` the stage cannot stream: it fits per fold on whole
//! labelled trials, which a live stream does not have. `palpate check --live`
//! says so and names `model_in` as the alternative.

use crate::estimate::ann::AnnConfig;
use crate::estimate::classic::{KnnConfig, LogisticConfig, RandomForestConfig, SvmConfig};
use crate::estimate::edbn::EdbnConfig;
use crate::estimate::features::{FittedModel, Streamer};
use crate::estimate::saved::{self, ModelIn};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{register_stream, BuildContext, ConfigError, Payload, StageError, TrialContext};
use std::sync::Arc;

/// The streaming form of a trained estimator of type `stage_type`: streams
/// the model `model_in` names, or says (naming `model_in`) that a fitting
/// stage cannot stream. A plugin's trained estimator registers its own with
/// `register_stream!` and a function that calls this one.
pub fn form(
    stage_type: &str,
    model_in: Option<&str>,
    save_model: bool,
    ctx: &BuildContext,
) -> Result<StreamForm, ConfigError> {
    match saved::load_model_in(stage_type, model_in, save_model, ctx)? {
        Some(m) => Ok(StreamForm::Streams(Box::new(TrainedStream(m)))),
        None => Ok(StreamForm::batch(
            "a trained estimator fits per fold on whole labelled trials, which a live stream does not have",
            "model_in = \"<file>\": a model saved by an offline run of this stage with save_model = true",
        )),
    }
}

macro_rules! trained_stream {
    ($name:literal, $ty:ty, $f:ident) => {
        fn $f(cfg: &$ty, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
            form($name, cfg.model_in.as_deref(), cfg.save_model, ctx)
        }
        register_stream!($name, $ty, $f);
    };
}

trained_stream!("ann", AnnConfig, ann_stream);
trained_stream!("edbn", EdbnConfig, edbn_stream);
trained_stream!("svm", SvmConfig, svm_stream);
trained_stream!("random_forest", RandomForestConfig, random_forest_stream);
trained_stream!("knn", KnnConfig, knn_stream);
trained_stream!("logistic", LogisticConfig, logistic_stream);

struct TrainedStream(ModelIn);

impl StreamStage for TrainedStream {
    fn open(&self, ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(TrainedState {
            model: self.0.clone(),
            streamer: FittedModel::stream_shared(self.0.model.clone(), ctx.seed),
            last: None,
        }))
    }
}

struct TrainedState {
    model: ModelIn,
    streamer: Streamer<Arc<FittedModel>>,
    /// The last emitted answer: (angle, class) bits.
    last: Option<(Option<u64>, Option<u64>)>,
}

impl StreamState for TrainedState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let images = block.images()?;
        let what = format!("images from frame {}", self.streamer.frames_seen());
        self.model.check_images(images, &what)?;
        let mut changed = None;
        for k in 0..images.n_frames {
            let used = self
                .streamer
                .push(images.frame(k))
                .map_err(|e| self.model.error(e))?
                .is_some();
            if used {
                let e = self.streamer.estimate();
                let key = (e.angle_deg.map(f64::to_bits), e.class_deg.map(f64::to_bits));
                if self.last != Some(key) {
                    self.last = Some(key);
                    changed = Some(e);
                }
            }
        }
        if let Some(e) = changed {
            out.push(e.into());
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let mut e = self.streamer.estimate();
        // What the batch model does (`cap_decision_time`): the images of a
        // trial of n frames cover (n - 1)·hop ms.
        let end = self.streamer.frames_seen().saturating_sub(1) as f64 * self.model.model.features.hop_ms;
        e.decision_time_ms = e.decision_time_ms.map(|t| t.min(end));
        out.push(e.into());
        Ok(())
    }
}
