//! `union`: one source made of several named sources, so a graph can train on
//! one data set and test on another.
//!
//! Each entry of `sources` is a whole source stage's table (`type` and its
//! keys): a simulated `scene`, a recording read by `signal_file`, spikes from
//! `spike_file`... The union lists every source's trials in name order, each
//! with its id prefixed `<name>-` and the label `source = "<name>"` added to
//! its conditions, and produces a trial by asking the source it came from.
//! The protocols split on that label like on any other:
//!
//! ```toml
//! [run]
//! protocol = { train_test = { key = "source", train = ["sim"] } }   # fit on the simulation, score on the recording
//!
//! [stages.data]
//! type = "union"
//! sources.sim = { type = "scene", file = "scenes/lab.toml" }
//! sources.rec = { type = "signal_file", path = "recordings/", labels = "recordings/labels.toml" }
//! ```
//!
//! With `leave_one_condition_out = { key = "source" }` every source is tested
//! once with the estimators fitted on all the others.
//!
//! Every source must give the same payload kind (signals, spikes or images)
//! and, where it is known before the run, the same sample rate: the stages
//! after the union run once over all of them. Sources on different arrays
//! (where their configs say which) draw a warning, not an error: WSS matches
//! each trial against its own array's templates, but a trained estimator
//! learns one array's taxels. A trial's seed is the union's
//! (derived from the graph seed, the union's stage id and the prefixed trial
//! id), so a scene inside a union draws other noise than the same scene as a
//! stage of its own; results remain a pure function of graph and seed.

use super::common::other_array_warning;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Inspection, OutputFacts, Payload, PayloadKind,
    Source, Stage, StageConfig, StageError, TaxelLayout, TrialContext, TrialMeta,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::OnceLock;

/// The condition key every trial of a union carries: the name of its source.
pub const SOURCE_KEY: &str = "source";

/// Several named sources as one (see the module docs).
#[derive(Debug, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct UnionConfig {
    /// The sources, by name: each a table like a source stage's (`type` and
    /// its keys, relative paths against the graph file's directory), e.g.
    /// `sources.sim = { type = "scene", file = "scenes/lab.toml" }`. Trial ids
    /// become `<name>-<id>` and every trial carries the label `source =
    /// "<name>"`, which the `train_test` and `leave_one_condition_out`
    /// protocols split on. Names hold letters, digits, `_` and `-`. At least
    /// one source; every one must give the same payload kind. Required.
    #[schemars(with = "BTreeMap<String, serde_json::Value>")]
    #[serde(deserialize_with = "de_sources", serialize_with = "ser_sources")]
    pub sources: BTreeMap<String, Box<dyn StageConfig>>,
}

/// Reads each source table as the graph loader reads a stage: `type` names
/// the registered config, every other key is its own (no `inputs`).
fn de_sources<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<BTreeMap<String, Box<dyn StageConfig>>, D::Error> {
    use serde::de::Error;
    let raw: BTreeMap<String, toml::Table> = BTreeMap::deserialize(d)?;
    let mut out = BTreeMap::new();
    for (name, mut table) in raw {
        let ty = match table.remove("type") {
            Some(toml::Value::String(t)) => t,
            Some(_) => {
                return Err(D::Error::custom(format!(
                    "sources.{name}.type: must be a string naming a source stage type"
                )))
            }
            None => {
                return Err(D::Error::custom(format!(
                    "sources.{name}: missing key `type` (the source's stage type, e.g. \"scene\")"
                )))
            }
        };
        if table.contains_key("inputs") {
            return Err(D::Error::custom(format!(
                "sources.{name}.inputs: a source takes no inputs"
            )));
        }
        let mut tagged = toml::Table::new();
        tagged.insert(ty, toml::Value::Table(table));
        let cfg: Box<dyn StageConfig> = toml::Value::Table(tagged)
            .try_into()
            .map_err(|e: toml::de::Error| D::Error::custom(format!("sources.{name}: {}", e.message())))?;
        out.insert(name, cfg);
    }
    Ok(out)
}

/// Writes each source back as `{ type = "...", keys... }`, as it was read.
fn ser_sources<S: serde::Serializer>(
    sources: &BTreeMap<String, Box<dyn StageConfig>>,
    s: S,
) -> Result<S::Ok, S::Error> {
    use serde::ser::{Error, SerializeMap};
    let mut map = s.serialize_map(Some(sources.len()))?;
    for (name, cfg) in sources {
        let v = serde_json::to_value(cfg).map_err(S::Error::custom)?;
        let flat = match v {
            serde_json::Value::Object(o) if o.len() == 1 => {
                let (ty, keys) = o
                    .into_iter()
                    .next()
                    .ok_or_else(|| S::Error::custom("empty config"))?;
                let mut t = match keys {
                    serde_json::Value::Object(k) => k,
                    _ => serde_json::Map::new(),
                };
                t.insert("type".into(), serde_json::Value::String(ty));
                serde_json::Value::Object(t)
            }
            other => other,
        };
        map.serialize_entry(name, &flat)?;
    }
    map.end()
}

fn bad_name(name: &str) -> bool {
    name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-'))
}

impl UnionConfig {
    /// The one payload kind of every source, or an error naming the first
    /// source that differs (or is not a source at all).
    fn kind(&self) -> Result<PayloadKind, ConfigError> {
        let mut kind = None;
        if self.sources.is_empty() {
            return Err(ConfigError::key("sources", "lists no source; give at least one"));
        }
        for (name, cfg) in &self.sources {
            if bad_name(name) {
                return Err(ConfigError::key(
                    format!("sources.{name}"),
                    format!("source name `{name}`: use letters, digits, `_` and `-` (it starts trial ids)"),
                ));
            }
            let spec = cfg.inputs();
            let Some(k) = cfg.output().filter(|_| spec.min == 0 && spec.max == Some(0)) else {
                return Err(ConfigError::key(
                    format!("sources.{name}.type"),
                    "is not a source stage (it takes inputs or gives nothing)",
                ));
            };
            match kind {
                None => kind = Some(k),
                Some(first) if first != k => {
                    return Err(ConfigError::key(
                        format!("sources.{name}.type"),
                        format!(
                            "gives {k:?}, but the sources before it give {first:?}; a union needs one kind"
                        ),
                    ))
                }
                Some(_) => {}
            }
        }
        kind.ok_or_else(|| ConfigError::key("sources", "lists no source"))
    }

    fn sub_context(ctx: &BuildContext, name: &str) -> BuildContext {
        BuildContext {
            stage_id: format!("{}.{name}", ctx.stage_id),
            ..ctx.clone()
        }
    }
}

#[typetag::serde(name = "union")]
impl StageConfig for UnionConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        // A union of mixed or no sources is refused at build(); until then,
        // say what the first source gives.
        self.kind()
            .ok()
            .or_else(|| self.sources.values().next().and_then(|c| c.output()))
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.kind()?;
        let mut parts = Vec::with_capacity(self.sources.len());
        let mut errors = Vec::new();
        for (name, cfg) in &self.sources {
            match cfg.build(&Self::sub_context(ctx, name)) {
                Ok(Stage::Source(s)) => parts.push((name.clone(), s)),
                Ok(_) => errors.push(ConfigError::key(
                    format!("sources.{name}.type"),
                    "is not a source stage",
                )),
                Err(e) => errors.push(e.within(&format!("sources.{name}"))),
            }
        }
        if let Some(e) = ConfigError::join(errors) {
            return Err(e);
        }
        Ok(Stage::Source(Box::new(UnionSource {
            parts,
            index: OnceLock::new(),
        })))
    }
    /// Every source's own inspection, keys prefixed; the sample rate when the
    /// sources that know theirs agree (an error when two differ); the array
    /// when every source states the same one (a warning when two differ:
    /// legal for WSS, wrong for a trained estimator).
    fn inspect(&self, ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        let mut out = Inspection::default();
        let mut rate: Option<(String, f64)> = None;
        // The first source stating its array, and that array: every later
        // one that states another is warned about.
        let mut layout: Option<(String, TaxelLayout)> = None;
        let mut one_array = true;
        for (name, cfg) in &self.sources {
            let sub = cfg.inspect(&Self::sub_context(ctx, name), &[]);
            match (&sub.facts.layout, &layout) {
                (None, _) => one_array = false,
                (Some(l), None) => layout = Some((name.clone(), l.clone())),
                (Some(l), Some((first, fl))) if l != fl => {
                    out.warnings.push(other_array_warning(
                        format!("sources.{name}"),
                        l,
                        "source",
                        first,
                        fl,
                    ));
                    one_array = false;
                }
                _ => {}
            }
            out.errors.extend(
                sub.errors
                    .into_iter()
                    .map(|e| e.within(&format!("sources.{name}"))),
            );
            out.warnings.extend(
                sub.warnings
                    .into_iter()
                    .map(|e| e.within(&format!("sources.{name}"))),
            );
            if let Some(r) = sub.facts.sample_rate_hz {
                match &rate {
                    Some((first, fr)) if *fr != r => out.errors.push(ConfigError::key(
                        format!("sources.{name}"),
                        format!(
                            "samples at {r} Hz but source `{first}` at {fr} Hz; the stages after a union run once \
                             over every source, so resample one of them"
                        ),
                    )),
                    Some(_) => {}
                    None => rate = Some((name.clone(), r)),
                }
            }
        }
        out.facts.sample_rate_hz = rate.map(|(_, r)| r);
        out.facts.layout = layout.filter(|_| one_array).map(|(_, l)| l);
        out
    }
}
register_stage!("union", UnionConfig);

/// The built union: each source, and (once listed) where each trial came from.
struct UnionSource {
    parts: Vec<(String, Box<dyn Source>)>,
    /// Per union trial: (part, the trial's metadata in its own source).
    index: OnceLock<Vec<(usize, TrialMeta)>>,
}

impl UnionSource {
    fn listing(&self) -> Result<&Vec<(usize, TrialMeta)>, StageError> {
        if let Some(ix) = self.index.get() {
            return Ok(ix);
        }
        let mut ix = Vec::new();
        for (p, (name, src)) in self.parts.iter().enumerate() {
            let metas = src
                .trials()
                .map_err(|e| StageError::new(format!("source `{name}`: {e}")))?;
            for (i, mut m) in metas.into_iter().enumerate() {
                m.index = i;
                ix.push((p, m));
            }
        }
        // Another thread may have listed first; both listings are equal.
        Ok(self.index.get_or_init(|| ix))
    }
}

impl Source for UnionSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        let ix = self.listing()?;
        Ok(ix
            .iter()
            .map(|(p, m)| {
                let name = &self.parts[*p].0;
                let mut u = m.clone();
                u.trial_id = format!("{name}-{}", m.trial_id);
                u.conditions.insert(SOURCE_KEY.to_string(), name.clone());
                u
            })
            .collect())
    }

    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let ix = self.listing()?;
        let Some((p, meta)) = ix.get(ctx.meta.index) else {
            return Err(StageError::new(format!(
                "trial {} is not one of the union's {} trials",
                ctx.meta.index,
                ix.len()
            )));
        };
        let (name, src) = &self.parts[*p];
        let sub = TrialContext {
            stage_id: ctx.stage_id,
            meta,
            seed: ctx.seed,
        };
        src.produce(&sub)
            .map_err(|e| StageError::new(format!("source `{name}`, trial {}: {e}", meta.trial_id)))
    }
}
