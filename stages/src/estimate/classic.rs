//! Classical baselines from smartcore 0.4 on the same features as the ANN
//! (SPEC.md section 5): stage types `svm`, `random_forest`, `knn` and `logistic`.
//!
//! Design: one stage type per model (rather than one `classic` type with a
//! `model` key), so that each type's keys are exactly the ones that model has
//! and `palpate stages svm` documents them; the feature keys (`frames`, `step`,
//! `stride`, `min_spikes`, `max_train_frames`, `vote`, `save_model`) are the same
//! in all four and mean what they mean for `ann` (see [`super::features`]). Every
//! model classifies single feature vectors (default: 5 stacked images, the
//! ANN (ST) input), standardised per feature on the training vectors; a trial's
//! answer is the paper's winner-take-all vote over its active frames.
//!
//! * `svm`: RBF-kernel SVMs, `K(x, z) = exp(-γ‖x - z‖²)`, trained with
//!   smartcore's binary `SVC` (an approximate LaSVM solver) **one-vs-one**: one
//!   machine per pair of classes (K(K-1)/2 of them), each on that pair's vectors
//!   only, so each problem is small and balanced. A vector's class scores are
//!   its votes plus sklearn's tie-breaker, `votes_c + conf_c / (3 (max|conf| + 1))`
//!   with `conf_c` the summed decision values in favour of `c`, so confidences
//!   only order classes with equal votes; scores are divided by `K - 1`. The
//!   fitted machines (support vectors, coefficients, bias) are copied out of
//!   smartcore into [`OvoSvm`]: smartcore's `SVC` borrows its parameters and its
//!   deserialized form cannot predict, and evaluating the decision function
//!   ourselves lets it vectorise. `γ = 0` (auto) is `1 / dim` (sklearn's
//!   "scale" for standardised features).
//! * `random_forest`: smartcore's `RandomForestClassifier` (Gini, bootstrap,
//!   `m = sqrt(dim)` features per split by default); each vector votes for its
//!   predicted class (score 1).
//! * `knn`: smartcore's `KNNClassifier` (Euclidean, cover tree), class scores =
//!   its `predict_proba` (share of the `k` neighbours, optionally distance-weighted).
//! * `logistic`: smartcore's multinomial `LogisticRegression` (L-BFGS, L2 penalty
//!   `alpha`); the coefficients are copied into [`Softmax`], whose class scores
//!   are the softmax probabilities.
//!
//! Seeds: the SVM pairs and the forest take seeds from the fold's RNG; k-NN and
//! logistic regression are deterministic. The SVM pairs train in parallel and
//! are gathered in pair order, so 1 or N threads give the same bits.

use super::ann::{dot, softmax};
use super::features::{
    maybe_save, Classifier, FeatureKeys, FittedModel, Standardizer, TrainSet, TrainingLog, Vote, MODEL_FORMAT,
};
use palpate_core::{
    check_positive, check_range, register_stage, BuildContext, ConfigError, Estimator, FitContext, InputSpec,
    Item, Model, PayloadKind, Stage, StageConfig, StageError,
};
use rand::Rng;
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use smartcore::ensemble::random_forest_classifier::{
    RandomForestClassifier, RandomForestClassifierParameters,
};
use smartcore::linalg::basic::arrays::Array;
use smartcore::linalg::basic::matrix::DenseMatrix;
use smartcore::linear::logistic_regression::{LogisticRegression, LogisticRegressionParameters};
use smartcore::metrics::distance::euclidian::Euclidian;
use smartcore::neighbors::knn_classifier::{KNNClassifier, KNNClassifierParameters};
use smartcore::neighbors::KNNWeightFunction;
use smartcore::svm::svc::{SVCParameters, SVC};
use smartcore::svm::Kernels;
use std::path::PathBuf;

/// Standardised training rows of a fold, as a smartcore matrix with `i32` labels.
struct Design {
    x: DenseMatrix<f64>,
    rows: Vec<Vec<f64>>,
    y: Vec<i32>,
}

fn design(set: &TrainSet, scaler: &Standardizer) -> Result<Design, StageError> {
    let mut flat = Vec::with_capacity(set.x.len());
    let mut rows = Vec::with_capacity(set.len());
    for i in 0..set.len() {
        let mut r = set.row(i).to_vec();
        scaler.apply(&mut r);
        flat.extend_from_slice(&r);
        rows.push(r);
    }
    let x = DenseMatrix::new(set.len(), set.dim, flat, false).map_err(smart_err)?;
    let y = set.y.iter().map(|&c| c as i32).collect();
    Ok(Design { x, rows, y })
}

fn smart_err(e: smartcore::error::Failed) -> StageError {
    StageError::new(format!("smartcore: {e}"))
}

/// Shared fit: features, standardisation, the model-specific part, packaging.
fn fit_classic(
    keys: &FeatureKeys,
    vote: Vote,
    stage_type: &str,
    train: &[&Item],
    ctx: &FitContext<'_>,
    fit: impl FnOnce(&TrainSet, Design, Standardizer, u64) -> Result<Classifier, StageError>,
) -> Result<FittedModel, StageError> {
    keys.check()?;
    let set = TrainSet::build(train, keys)?;
    let all: Vec<usize> = (0..set.len()).collect();
    let scaler = Standardizer::fit(&set, &all);
    let d = design(&set, &scaler)?;
    let seed = ctx.rng().random::<u64>();
    let classifier = fit(&set, d, scaler, seed)?;
    Ok(FittedModel {
        format: MODEL_FORMAT,
        stage_type: stage_type.into(),
        log: TrainingLog {
            n_train: set.len(),
            ..TrainingLog::default()
        },
        classes: set.classes,
        features: set.spec,
        vote,
        classifier,
    })
}

macro_rules! estimator {
    ($cfg:ty, $est:ident) => {
        struct $est {
            config: $cfg,
            out_dir: PathBuf,
        }
        impl Estimator for $est {
            fn trained(&self) -> bool {
                true
            }
            fn fit(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
                let m = self.config.fit_model(train, ctx)?;
                maybe_save(&m, self.config.save_model, &self.out_dir, ctx)?;
                Ok(Box::new(m))
            }
        }
    };
}

// ---------------------------------------------------------------- SVM

/// Multi-class RBF SVM (one-vs-one over smartcore's binary SVC) on spike-image features.
///
/// Per-frame votes are combined by the paper's winner-take-all over the trial.
/// Input: spike images; output: orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SvmConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 40.
    pub max_train_frames: usize,
    /// Soft-margin penalty C. Default 10.
    pub c: f64,
    /// RBF width γ of `exp(-γ‖x-z‖²)` on standardised features; 0 = auto (1 / dim). Default 0.
    pub gamma: f64,
    /// Passes of the LaSVM solver over each pair's data. Default 2.
    pub epochs: usize,
    /// Solver tolerance. Default 1e-3.
    pub tol: f64,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
}

impl Default for SvmConfig {
    fn default() -> Self {
        SvmConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 40,
            c: 10.0,
            gamma: 0.0,
            epochs: 2,
            tol: 1e-3,
            vote: Vote::Winner,
            save_model: false,
        }
    }
}

/// One binary machine of [`OvoSvm`]: positive decision = class `b`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BinarySvm {
    /// Class index on the negative side.
    pub a: usize,
    /// Class index on the positive side.
    pub b: usize,
    /// Support vectors, row-major.
    pub sv: Vec<f64>,
    /// Their coefficients.
    pub coef: Vec<f64>,
    /// Bias.
    pub bias: f64,
}

/// A fitted one-vs-one RBF SVM.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OvoSvm {
    /// Input size.
    pub dim: usize,
    /// Number of classes.
    pub classes: usize,
    /// RBF γ.
    pub gamma: f64,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// One machine per class pair, in pair order.
    pub machines: Vec<BinarySvm>,
}

impl OvoSvm {
    /// Decision value of machine `m` at standardised `x`.
    pub fn decision(&self, m: &BinarySvm, x: &[f64]) -> f64 {
        let mut f = m.bias;
        for (sv, c) in m.sv.chunks_exact(self.dim).zip(&m.coef) {
            let mut d2 = 0.0;
            for (a, b) in sv.iter().zip(x) {
                d2 += (a - b) * (a - b);
            }
            f += c * (-self.gamma * d2).exp();
        }
        f
    }

    /// Vote shares (with the confidence tie-breaker) of a normalised vector.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        let mut z = x.to_vec();
        self.scaler.apply(&mut z);
        let mut votes = vec![0.0; self.classes];
        let mut conf = vec![0.0; self.classes];
        for m in &self.machines {
            let f = self.decision(m, &z);
            if f > 0.0 {
                votes[m.b] += 1.0;
            } else {
                votes[m.a] += 1.0;
            }
            conf[m.b] += f;
            conf[m.a] -= f;
        }
        let cmax = conf.iter().fold(0.0f64, |a, c| a.max(c.abs()));
        let norm = 1.0 / (self.classes.max(2) - 1) as f64;
        for c in 0..self.classes {
            let s = votes[c] + conf[c] / (3.0 * (cmax + 1.0));
            out[c] = (s * norm).max(0.0);
        }
    }
}

/// Fields of smartcore's serialized `SVC` we read back.
#[derive(Deserialize)]
struct SvcParts {
    instances: Option<Vec<Vec<f64>>>,
    w: Option<Vec<f64>>,
    b: Option<f64>,
}

impl SvmConfig {
    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        self.keys().check()?;
        check_positive("c", self.c, "")?;
        check_range("gamma", self.gamma, 0.0, 1e6, "")?;
        check_positive("tol", self.tol, "")?;
        if self.epochs == 0 {
            return Err(ConfigError::key("epochs", "must be at least 1"));
        }
        Ok(())
    }

    /// Fits the one-vs-one SVM on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic(
            &self.keys(),
            self.vote,
            "svm",
            train,
            ctx,
            |set, d, scaler, seed| {
                let k = set.classes.len();
                let gamma = if self.gamma > 0.0 {
                    self.gamma
                } else {
                    1.0 / set.dim as f64
                };
                let pairs: Vec<(usize, usize)> =
                    (0..k).flat_map(|a| (a + 1..k).map(move |b| (a, b))).collect();
                let machines: Vec<Result<BinarySvm, StageError>> = pairs
                    .par_iter()
                    .enumerate()
                    .map(|(p, &(a, b))| {
                        let idx: Vec<usize> = (0..d.y.len())
                            .filter(|&i| set.y[i] == a || set.y[i] == b)
                            .collect();
                        let mut flat = Vec::with_capacity(idx.len() * set.dim);
                        idx.iter().for_each(|&i| flat.extend_from_slice(&d.rows[i]));
                        let x = DenseMatrix::new(idx.len(), set.dim, flat, false).map_err(smart_err)?;
                        let y: Vec<i32> = idx.iter().map(|&i| i32::from(set.y[i] == b)).collect();
                        let params = SVCParameters::default()
                            .with_c(self.c)
                            .with_epoch(self.epochs)
                            .with_tol(self.tol)
                            .with_kernel(Kernels::rbf().with_gamma(gamma))
                            .with_seed(Some(seed ^ (p as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)));
                        let svc = SVC::fit(&x, &y, &params).map_err(smart_err)?;
                        let parts: SvcParts = serde_json::to_value(&svc)
                            .and_then(serde_json::from_value)
                            .map_err(|e| StageError::new(format!("reading smartcore's SVC: {e}")))?;
                        let (Some(inst), Some(w), Some(bias)) = (parts.instances, parts.w, parts.b) else {
                            return Err(StageError::new(
                                "smartcore's SVC came back without support vectors",
                            ));
                        };
                        let mut sv = Vec::with_capacity(inst.len() * set.dim);
                        for v in &inst {
                            if v.len() != set.dim {
                                return Err(StageError::new(
                                    "smartcore's SVC returned a support vector of the wrong size",
                                ));
                            }
                            sv.extend_from_slice(v);
                        }
                        Ok(BinarySvm {
                            a,
                            b,
                            sv,
                            coef: w,
                            bias,
                        })
                    })
                    .collect();
                let machines = machines.into_iter().collect::<Result<Vec<_>, _>>()?;
                Ok(Classifier::Svm(OvoSvm {
                    dim: set.dim,
                    classes: k,
                    gamma,
                    scaler,
                    machines,
                }))
            },
        )
    }
}

#[typetag::serde(name = "svm")]
impl StageConfig for SvmConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.check()?;
        Ok(Stage::Estimator(Box::new(SvmEstimator {
            config: self.clone(),
            out_dir: ctx.out_dir.clone(),
        })))
    }
}
register_stage!("svm", SvmConfig);
estimator!(SvmConfig, SvmEstimator);

// ---------------------------------------------------------------- random forest

/// Random forest (smartcore) on spike-image features, winner-take-all over the trial.
///
/// Each active frame votes for its predicted class. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RandomForestConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 100.
    pub max_train_frames: usize,
    /// Trees. Default 100.
    pub n_trees: u16,
    /// Largest tree depth; 0 = unlimited. Default 0.
    pub max_depth: u16,
    /// Fewest vectors in a leaf. Default 1.
    pub min_samples_leaf: usize,
    /// Features tried per split; 0 = auto (sqrt of the vector length). Default 0.
    pub m: usize,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
}

impl Default for RandomForestConfig {
    fn default() -> Self {
        RandomForestConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 100,
            n_trees: 100,
            max_depth: 0,
            min_samples_leaf: 1,
            m: 0,
            vote: Vote::Winner,
            save_model: false,
        }
    }
}

/// A fitted random forest.
#[derive(Debug, Serialize, Deserialize)]
pub struct Forest {
    /// Number of classes.
    pub classes: usize,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// smartcore's forest (labels are class indices).
    pub forest: RandomForestClassifier<f64, i32, DenseMatrix<f64>, Vec<i32>>,
}

impl Forest {
    /// One vote (score 1) for the predicted class.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|o| *o = 0.0);
        let mut z = x.to_vec();
        self.scaler.apply(&mut z);
        let n = z.len();
        let Ok(m) = DenseMatrix::new(1, n, z, false) else {
            return;
        };
        if let Ok(p) = self.forest.predict(&m) {
            if let Some(&c) = p.first() {
                if let Some(o) = usize::try_from(c).ok().and_then(|c| out.get_mut(c)) {
                    *o = 1.0;
                }
            }
        }
    }
}

impl RandomForestConfig {
    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        self.keys().check()?;
        if self.n_trees == 0 {
            return Err(ConfigError::key("n_trees", "must be at least 1"));
        }
        if self.min_samples_leaf == 0 {
            return Err(ConfigError::key("min_samples_leaf", "must be at least 1"));
        }
        Ok(())
    }

    /// Fits the forest on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic(
            &self.keys(),
            self.vote,
            "random_forest",
            train,
            ctx,
            |set, d, scaler, seed| {
                let mut p = RandomForestClassifierParameters::default()
                    .with_n_trees(self.n_trees)
                    .with_min_samples_leaf(self.min_samples_leaf)
                    .with_seed(seed);
                if self.max_depth > 0 {
                    p = p.with_max_depth(self.max_depth);
                }
                if self.m > 0 {
                    p = p.with_m(self.m.min(set.dim));
                }
                let forest = RandomForestClassifier::fit(&d.x, &d.y, p).map_err(smart_err)?;
                Ok(Classifier::RandomForest(Forest {
                    classes: set.classes.len(),
                    scaler,
                    forest,
                }))
            },
        )
    }
}

#[typetag::serde(name = "random_forest")]
impl StageConfig for RandomForestConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.check()?;
        Ok(Stage::Estimator(Box::new(ForestEstimator {
            config: self.clone(),
            out_dir: ctx.out_dir.clone(),
        })))
    }
}
register_stage!("random_forest", RandomForestConfig);
estimator!(RandomForestConfig, ForestEstimator);

// ---------------------------------------------------------------- k-NN

/// How the k nearest neighbours are weighted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum KnnWeight {
    /// Every neighbour counts the same.
    Uniform,
    /// Neighbours count by inverse distance.
    Distance,
}

/// k nearest neighbours (smartcore) on spike-image features, winner-take-all over the trial.
///
/// Class scores per frame are the neighbours' shares. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct KnnConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 100.
    pub max_train_frames: usize,
    /// Neighbours. Default 10.
    pub k: usize,
    /// `uniform` or `distance`. Default `uniform`.
    pub weight: KnnWeight,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
}

impl Default for KnnConfig {
    fn default() -> Self {
        KnnConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 100,
            k: 10,
            weight: KnnWeight::Uniform,
            vote: Vote::Winner,
            save_model: false,
        }
    }
}

/// A fitted k-NN classifier.
#[derive(Debug, Serialize, Deserialize)]
pub struct Knn {
    /// Number of classes.
    pub classes: usize,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// smartcore's classifier (labels are class indices).
    pub knn: KNNClassifier<f64, i32, DenseMatrix<f64>, Vec<i32>, Euclidian<f64>>,
}

impl Knn {
    /// Neighbour shares per class.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|o| *o = 0.0);
        let mut z = x.to_vec();
        self.scaler.apply(&mut z);
        let n = z.len();
        let Ok(m) = DenseMatrix::new(1, n, z, false) else {
            return;
        };
        if let Ok(p) = self.knn.predict_proba(&m) {
            if let Some(row) = p.first() {
                out.iter_mut()
                    .zip(row)
                    .for_each(|(o, v)| *o = if v.is_finite() { *v } else { 0.0 });
            }
        }
    }
}

impl KnnConfig {
    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        self.keys().check()?;
        if self.k == 0 {
            return Err(ConfigError::key("k", "must be at least 1"));
        }
        Ok(())
    }

    /// Fits k-NN on a fold's training trials (`k` is capped at the vectors available).
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic(&self.keys(), self.vote, "knn", train, ctx, |set, d, scaler, _| {
            let p = KNNClassifierParameters::default()
                .with_k(self.k.min(set.len()))
                .with_weight(match self.weight {
                    KnnWeight::Uniform => KNNWeightFunction::Uniform,
                    KnnWeight::Distance => KNNWeightFunction::Distance,
                });
            let knn = KNNClassifier::fit(&d.x, &d.y, p).map_err(smart_err)?;
            Ok(Classifier::Knn(Knn {
                classes: set.classes.len(),
                scaler,
                knn,
            }))
        })
    }
}

#[typetag::serde(name = "knn")]
impl StageConfig for KnnConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.check()?;
        Ok(Stage::Estimator(Box::new(KnnEstimator {
            config: self.clone(),
            out_dir: ctx.out_dir.clone(),
        })))
    }
}
register_stage!("knn", KnnConfig);
estimator!(KnnConfig, KnnEstimator);

// ---------------------------------------------------------------- logistic

/// Multinomial logistic regression (smartcore, L-BFGS) on spike-image features, winner-take-all over the trial.
///
/// Class scores per frame are softmax probabilities. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LogisticConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 100.
    pub max_train_frames: usize,
    /// L2 penalty on the coefficients. Default 1.
    pub alpha: f64,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
}

impl Default for LogisticConfig {
    fn default() -> Self {
        LogisticConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 100,
            alpha: 1.0,
            vote: Vote::Winner,
            save_model: false,
        }
    }
}

/// A fitted multinomial logistic regression: `p = softmax(W x + b)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Softmax {
    /// Input size.
    pub dim: usize,
    /// Number of classes.
    pub classes: usize,
    /// `W`, classes x dim, row-major.
    pub w: Vec<f64>,
    /// `b`, one per class.
    pub b: Vec<f64>,
    /// Input standardisation.
    pub scaler: Standardizer,
}

impl Softmax {
    /// Class probabilities.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        let mut z = x.to_vec();
        self.scaler.apply(&mut z);
        for (c, o) in out.iter_mut().enumerate().take(self.classes) {
            *o = dot(&self.w[c * self.dim..(c + 1) * self.dim], &z) + self.b[c];
        }
        softmax(&mut out[..self.classes]);
    }
}

impl LogisticConfig {
    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        self.keys().check()?;
        check_range("alpha", self.alpha, 0.0, 1e9, "")?;
        Ok(())
    }

    /// Fits logistic regression on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic(
            &self.keys(),
            self.vote,
            "logistic",
            train,
            ctx,
            |set, d, scaler, _| {
                let p = LogisticRegressionParameters::default().with_alpha(self.alpha);
                let lr = LogisticRegression::fit(&d.x, &d.y, p).map_err(smart_err)?;
                let k = set.classes.len();
                let (coef, icpt) = (lr.coefficients(), lr.intercept());
                let mut w = vec![0.0; k * set.dim];
                let mut b = vec![0.0; k];
                if k == 2 {
                    // smartcore's binary model has one row, for class 1: softmax over
                    // (0, z) is exactly sigmoid(z).
                    for j in 0..set.dim {
                        w[set.dim + j] = *coef.get((0, j));
                    }
                    b[1] = *icpt.get((0, 0));
                } else {
                    for c in 0..k {
                        for j in 0..set.dim {
                            w[c * set.dim + j] = *coef.get((c, j));
                        }
                        b[c] = *icpt.get((c, 0));
                    }
                }
                if w.iter().chain(&b).any(|v| !v.is_finite()) {
                    return Err(StageError::new(
                        "logistic regression diverged (non-finite coefficients); raise `alpha`",
                    ));
                }
                Ok(Classifier::Logistic(Softmax {
                    dim: set.dim,
                    classes: k,
                    w,
                    b,
                    scaler,
                }))
            },
        )
    }
}

#[typetag::serde(name = "logistic")]
impl StageConfig for LogisticConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.check()?;
        Ok(Stage::Estimator(Box::new(LogisticEstimator {
            config: self.clone(),
            out_dir: ctx.out_dir.clone(),
        })))
    }
}
register_stage!("logistic", LogisticConfig);
estimator!(LogisticConfig, LogisticEstimator);
