//! Stages defined outside palpate-stages, registered and run exactly like the
//! built-in ones: proof that a test (or a plugin crate) can extend palpate.

#![allow(dead_code)]

use palpate_core::*;
use rand::Rng;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

/// Test source: `classes` x `reps` trials of random signals.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TSource {
    /// Number of classes.
    #[serde(default = "three")]
    pub classes: usize,
    /// Repetitions per class.
    #[serde(default = "three")]
    pub reps: usize,
    /// Samples per trial (required: tests the missing-key error).
    pub samples: usize,
}
fn three() -> usize {
    3
}

#[typetag::serde(name = "t_source")]
impl StageConfig for TSource {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        if self.samples == 0 {
            return Err(ConfigError::key("samples", "must be at least 1"));
        }
        Ok(Stage::Source(Box::new(self.clone())))
    }
}
register_stage!("t_source", TSource);

impl Source for TSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        let mut v = Vec::new();
        for c in 0..self.classes {
            for r in 0..self.reps {
                v.push(TrialMeta {
                    trial_id: format!("c{c}-r{r}"),
                    label: Label {
                        stimulus: Stimulus::Edge,
                        angle_deg: Some(10.0 * (c + 1) as f64),
                    },
                    group: r,
                    ..TrialMeta::default()
                });
            }
        }
        Ok(v)
    }
    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let mut rng = ctx.rng();
        let data = (0..4)
            .map(|_| (0..self.samples).map(|_| rng.random::<f64>()).collect())
            .collect();
        Ok(Signals {
            sample_rate_hz: 1000.0,
            layout: TaxelLayout::Grid {
                rows: 2,
                cols: 2,
                pitch_mm: 3.0,
                taxel_mm: 2.0,
            },
            unit: "V".into(),
            data,
        }
        .into())
    }
}

/// Test map: scales signals, counting how often it runs.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TScale {
    /// Factor, dimensionless. Default 2.
    pub factor: f64,
    /// Ignored: lets a test change the stage's settings (and so its cache
    /// key) without changing its output. Default empty.
    pub note: String,
    /// A trial id on which the stage fails. Default none.
    pub fail_on: Option<String>,
}
impl Default for TScale {
    fn default() -> Self {
        TScale {
            factor: 2.0,
            note: String::new(),
            fail_on: None,
        }
    }
}
/// Tests that read the counters take this lock: tests of one binary run in parallel.
pub static SERIAL: Mutex<()> = Mutex::new(());
pub static SCALE_CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
/// `(note, trial id)` of each `t_scale` call whose `note` starts with
/// `order`, in call order: how a run interleaved its stages.
pub static ORDER: Mutex<Vec<(String, String)>> = Mutex::new(Vec::new());

#[typetag::serde(name = "t_scale")]
impl StageConfig for TScale {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_positive("factor", self.factor, "")?;
        Ok(Stage::Map(Box::new(self.clone())))
    }
}
register_stage!("t_scale", TScale);

impl Map for TScale {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        SCALE_CALLS.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        if self.note.starts_with("order") {
            if let Ok(mut o) = ORDER.lock() {
                o.push((self.note.clone(), inputs[0].meta.trial_id.clone()));
            }
        }
        if self.fail_on.as_deref() == Some(inputs[0].meta.trial_id.as_str()) {
            return Err(StageError::new("t_scale fails here"));
        }
        let s = inputs[0].payload.signals()?;
        let data = s
            .data
            .iter()
            .map(|ch| ch.iter().map(|x| x * self.factor).collect())
            .collect();
        Ok(s.with_data(s.unit.clone(), data).into())
    }
}

/// Test spike maker: one spike per sample above 0.5 on each taxel.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TSpikes {}

#[typetag::serde(name = "t_spikes")]
impl StageConfig for TSpikes {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Map(Box::new(self.clone())))
    }
}
register_stage!("t_spikes", TSpikes);

impl Map for TSpikes {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        let mut events = Vec::new();
        for (t, ch) in s.data.iter().enumerate() {
            for (k, v) in ch.iter().enumerate() {
                if *v > 0.5 {
                    events.push(SpikeEvent {
                        taxel: t as u32,
                        t_ms: k as f64,
                    });
                }
            }
        }
        let mut train = SpikeTrain {
            layout: s.layout.clone(),
            duration_ms: s.duration_ms(),
            events,
        };
        train.sort();
        Ok(train.into())
    }
}

/// Test estimator: nearest class mean of the signals' overall mean; records
/// which trials it was trained on.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TEstimator {
    /// Pretend fitting has effects (as saving a model does). Default false.
    pub effects: bool,
}

pub static TRAINED_ON: Mutex<Vec<(usize, Vec<String>)>> = Mutex::new(Vec::new());

#[typetag::serde(name = "t_estimator")]
impl StageConfig for TEstimator {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Estimator(Box::new(self.clone())))
    }
}
register_stage!("t_estimator", TEstimator);

fn mean(s: &Signals) -> f64 {
    let n = s.data.iter().map(Vec::len).sum::<usize>().max(1);
    s.data.iter().flatten().sum::<f64>() / n as f64
}

struct TModel {
    classes: Vec<(f64, f64)>,
}

impl Estimator for TEstimator {
    fn trained(&self) -> bool {
        true
    }
    fn reusable(&self) -> bool {
        !self.effects
    }
    fn fit(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        TRAINED_ON
            .lock()
            .unwrap()
            .push((ctx.fold, train.iter().map(|i| i.meta.trial_id.clone()).collect()));
        let mut sums: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
        for it in train {
            let a = it.meta.label.angle_deg.unwrap_or(0.0);
            let e = sums.entry(a as i64).or_insert((a, 0.0, 0));
            e.1 += mean(it.payload.signals()?);
            e.2 += 1;
        }
        Ok(Box::new(TModel {
            classes: sums.values().map(|(a, s, n)| (*a, s / *n as f64)).collect(),
        }))
    }
}

impl Model for TModel {
    fn predict(&self, item: &Item, _ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        self.predict_value(mean(item.payload.signals()?))
    }
}

/// Test sink: reports the number of items per input and their estimates.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TSink {}

#[typetag::serde(name = "t_sink")]
impl StageConfig for TSink {
    fn inputs(&self) -> InputSpec {
        InputSpec::many(PayloadKind::Estimates)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("t_sink", TSink);

impl Sink for TSink {
    fn consume(&self, inputs: &[SinkInput<'_>], _ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut r = SinkReport::default();
        for i in inputs {
            r.metrics
                .push((format!("{}.n", i.stage_id), i.items.len() as f64));
            for it in i.items {
                let e = it.payload.estimate()?;
                r.text
                    .push_str(&format!("{} {:?}\n", it.meta.trial_id, e.angle_deg));
            }
        }
        Ok(r)
    }
}

pub fn load(text: &str) -> Result<Graph, LoadErrors> {
    let opts = LoadOptions {
        out: Some(std::env::temp_dir().join(format!("palpate-core-test-{}", std::process::id()))),
        ..LoadOptions::default()
    };
    load_str(text, "test.toml", "test", &opts)
}

/// A trial's answer: its id, angle and every class score's bits.
pub type Answer = (String, Option<f64>, Vec<u64>);

/// Each estimate's [`Answer`], in order.
pub fn answers_of(items: &[Item]) -> Vec<Answer> {
    items
        .iter()
        .map(|i| {
            let e = i.payload.estimate().unwrap();
            (
                i.meta.trial_id.clone(),
                e.angle_deg,
                e.scores.iter().map(|s| s.score.to_bits()).collect(),
            )
        })
        .collect()
}

pub fn outputs(graph: &Graph) -> Arc<Vec<Item>> {
    let r = run(
        graph,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap();
    r.outputs["est"].clone()
}

/// Test map standing for stages defined at run time (as Python's are): a
/// `stage` name and that stage's own keys in `config`; scales signals by
/// `config.factor` (default 1).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TDynamic {
    /// The run-time stage's name.
    pub stage: String,
    /// Its keys. Default empty.
    #[serde(default)]
    pub config: std::collections::BTreeMap<String, f64>,
}

#[typetag::serde(name = "t_dynamic")]
impl StageConfig for TDynamic {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        if let Some(k) = self.config.keys().find(|k| k.as_str() != "factor") {
            return Err(ConfigError::key(
                format!("config.{k}"),
                format!("`{}` has no key `{k}`", self.stage),
            ));
        }
        Ok(Stage::Map(Box::new(TScale {
            factor: self.config.get("factor").copied().unwrap_or(1.0),
            ..TScale::default()
        })))
    }
}
register_stage!("t_dynamic", TDynamic);

/// Test model-based estimator: fits on nothing; answers the class (10, 20,
/// 30 or 40 degrees) nearest 50 x the signals' overall mean (random signals
/// in [0, 1): 25 on average), scoring every class.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TFixed {
    /// A trial id on which predicting fails. Default none.
    pub fail_on: Option<String>,
}

#[typetag::serde(name = "t_fixed")]
impl StageConfig for TFixed {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Estimator(Box::new(self.clone())))
    }
}
register_stage!("t_fixed", TFixed);

impl Estimator for TFixed {
    fn trained(&self) -> bool {
        false
    }
    fn fit(&self, _train: &[&Item], _ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        Ok(Box::new(self.clone()))
    }
}

impl Model for TFixed {
    fn predict(&self, item: &Item, _ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        if self.fail_on.as_deref() == Some(item.meta.trial_id.as_str()) {
            return Err(StageError::new("t_fixed fails here"));
        }
        let m = 50.0 * mean(item.payload.signals()?);
        TModel {
            classes: (1..=4).map(|c| (10.0 * c as f64, 10.0 * c as f64)).collect(),
        }
        .predict_value(m)
    }
}

impl TModel {
    fn predict_value(&self, m: f64) -> Result<Estimate, StageError> {
        let best = self
            .classes
            .iter()
            .min_by(|a, b| (a.1 - m).abs().total_cmp(&(b.1 - m).abs()))
            .map(|c| c.0);
        Ok(Estimate {
            angle_deg: best,
            class_deg: best,
            scores: self
                .classes
                .iter()
                .map(|c| ClassScore {
                    angle_deg: c.0,
                    score: -(c.1 - m).abs(),
                })
                .collect(),
            ..Estimate::default()
        })
    }
}
