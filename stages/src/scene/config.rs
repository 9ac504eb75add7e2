//! The `scene` stage's keys, scene files, and their resolution into a checked
//! [`Scene`].
//!
//! Every key is optional in the config struct so that a scene file's keys can act
//! as defaults that inline keys override *key by key*: a graph may say
//! `file = "scenes/lab.toml"` and `motion = { speed_mm_s = 4 }` and keep the
//! file's holds and sample rate. Tables merge recursively; lists (`angles` as a
//! list, `effects`, `layout.positions_mm`) are replaced as a whole. Keys given
//! nowhere take the paper's values, stated in each key's doc comment.

use super::effects::EffectConfig;
use palpate_core::{check_positive, check_range, BuildContext, ConfigChecks, ConfigError, TaxelLayout};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest number of samples (taxels x samples) one trial may hold: 10^8
/// values, 800 MB of f64. An angle so close to 0 or 180 degrees that the edge
/// would take longer than this to cross is a config error, not an allocation
/// failure.
pub const MAX_TRIAL_VALUES: f64 = 1e8;

/// A simulated scene: a straight edge (or a ridge) at each listed angle crossing
/// a taxel array that slides over it, with optional physical effects.
///
/// The array is held on the object for `motion.hold_before_s`, slides `+x` at
/// `motion.speed_mm_s` until the stimulus is fully past (a margin beyond the
/// array's footprint), and holds for `motion.hold_after_s`. Each taxel reports
/// the contact pressure averaged exactly over its square area (unit
/// "pressure": 1 = full contact with a flat surface); the listed `effects` then
/// turn that ideal response into a plausible sensor signal. With no effects the
/// output is exactly the ideal contact fraction. See the module docs of
/// `palpate_stages::scene` for the geometry and every effect's physics.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SceneConfig {
    /// Path of a scene TOML file (e.g. "scenes/lab.toml") whose keys are the
    /// defaults of this stage; keys given inline override it, tables key by key.
    /// Relative to the graph file's directory. Default: none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
    /// What the array crosses: "edge" (an object's boundary; the array starts on
    /// the object and slides off it) or "ridge" (a raised bar on a flat surface).
    /// Default "edge".
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = "edge"))]
    pub stimulus: Option<StimulusKind>,
    /// The ridge's shape (used when `stimulus = "ridge"`): `width_mm` (default 2),
    /// `height_mm` (default 2), `indent_mm` (default 1).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = {"width_mm": 2.0, "height_mm": 2.0, "indent_mm": 1.0}))]
    pub ridge: Option<RidgeKeys>,
    /// Edge orientations, degrees from the array's horizontal axis, each in
    /// (0, 180): a list (`[30, 45]`) or a range (`{ from = 10, to = 90, step = 5 }`,
    /// `to` included; the old spelling `start`/`stop` is read with a
    /// deprecation warning). Default: the paper's 17 classes, 10 to 90 by 5.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = {"from": 10.0, "to": 90.0, "step": 5.0}))]
    pub angles: Option<Angles>,
    /// Repetitions of every angle (the cross-validation groups). Default 10.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = 10))]
    pub trials_per_angle: Option<usize>,
    /// A regular grid of square taxels: `rows` (default 4), `cols` (default 4),
    /// `pitch_mm` centre to centre (default 3), `taxel_mm` side (default 2): the
    /// paper's 13 x 13 mm array. Ignored when `layout` is given.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = {"rows": 4, "cols": 4, "pitch_mm": 3.0, "taxel_mm": 2.0}))]
    pub array: Option<ArrayKeys>,
    /// An explicit layout instead of a grid: `positions_mm` (taxel centres
    /// `[x, y]`, mm, origin at the array centre, x along the sliding direction)
    /// and `taxel_mm` (side of each square taxel, default 2). Default: none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub layout: Option<LayoutKeys>,
    /// The palpation: `speed_mm_s` (default 2), `hold_before_s` (default 2),
    /// `hold_after_s` (default 2), `sample_rate_hz` (default 1000), `margin_mm`
    /// (how far beyond the array's footprint the stimulus starts and ends,
    /// default 1; the spatial reach of the listed effects is added to it).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = {"speed_mm_s": 2.0, "hold_before_s": 2.0, "hold_after_s": 2.0, "sample_rate_hz": 1000.0, "margin_mm": 1.0}))]
    pub motion: Option<MotionKeys>,
    /// Physical effects, applied in the listed order, each a table with a `kind`
    /// (`variation`, `skin`, `stress`, `creep`, `piezo`, `mismatch`, `crosstalk`,
    /// `noise`, `hum`, `adc`, `dead`) and its own keys. Effects not listed are
    /// never simulated. Default: none (the ideal response).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = []))]
    pub effects: Option<Vec<EffectConfig>>,
    /// Changes to effects of the `effects` list, by kind: each entry is a
    /// table of that effect's keys, set on the one effect of that kind (the
    /// scene's own, or a condition's inherited list), e.g. `adjust = { skin =
    /// { sigma_mm = 1.0 } }` for a thicker skin. Unlike `effects`, which
    /// replaces the whole list, this reaches one key, so a sweep or a
    /// condition can shift one physical parameter
    /// (`--set stages.scene.conditions.test.adjust.skin.sigma_mm=1.0`). An
    /// error names the kind when the list holds no effect of it, or several.
    /// Default: none.
    // TOML values, not JSON ones: JSON has no NaN or infinity, so a
    // `sigma_mm = nan` read into JSON became `null` and was reported as a
    // type error that named no key.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(
        with = "Option<std::collections::BTreeMap<String, serde_json::Map<String, serde_json::Value>>>"
    )]
    pub adjust: Option<std::collections::BTreeMap<String, toml::Table>>,
    /// Which simulated copy of the array to draw: every copy has its own
    /// manufacturing draws (mismatch, dead taxels, per-taxel dynamics...), the
    /// same for every trial of the copy; copy 0 is the one the run seed gives.
    /// A condition with `array_copy = 1` is "a second array". Default 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("default" = 0))]
    pub array_copy: Option<u32>,
    /// Conditions to simulate, by name: each a table of this scene's keys that
    /// override the scene for that condition's trials (tables merged key by
    /// key; a list such as `effects` is replaced). Every condition gets every
    /// angle and repetition; its trial ids start with `<name>-` and its trials
    /// carry the label `condition = "<name>"`, which the `train_test` and
    /// `leave_one_condition_out` protocols split on. E.g. `conditions = { base
    /// = {}, fast = { motion = { speed_mm_s = 3.0 } } }`. Names hold letters,
    /// digits, `_` and `-` (so `--set stages.scene.conditions.<name>.<key>`
    /// can address them). Default: none (one condition, plain ids).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub conditions: Option<std::collections::BTreeMap<String, SceneConfig>>,
}

/// The kind of stimulus a scene presents.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum StimulusKind {
    /// The boundary edge of a flat object: contact on one side, none on the other.
    #[default]
    Edge,
    /// A raised bar on a flat surface (paper section 3.6).
    Ridge,
}

/// A ridge's shape.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RidgeKeys {
    /// Width of the bar across its length, mm. Default 2 (the paper's ridges).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub width_mm: Option<f64>,
    /// Height of the bar above the surface, mm. Default 2 (the paper's ridges).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_mm: Option<f64>,
    /// How deep the skin is pressed into the flat surface, mm. With the skin as a
    /// Winkler bed (pressure proportional to indentation), the bar's top carries
    /// `(indent + height) / indent` times the flat's pressure. Default 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub indent_mm: Option<f64>,
}

/// Angles as a list or a range.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(untagged)]
pub enum Angles {
    /// Explicit angles, degrees.
    List(Vec<f64>),
    /// `from`, `from + step`, ... up to and including `to`, degrees.
    Range(AngleRange),
}

/// A range of angles, `{ from, to, step }` as in every stage that takes a
/// range (`wss`'s `angles` too).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AngleRange {
    /// First angle, degrees. Default 10.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub from: Option<f64>,
    /// Last angle (included when the steps land on it), degrees. Default 90.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub to: Option<f64>,
    /// Step, degrees. Default 5.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step: Option<f64>,
    /// Deprecated spelling of `from`, degrees: read with a warning. Default unset.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("deprecated" = true))]
    pub start: Option<f64>,
    /// Deprecated spelling of `to`, degrees: read with a warning. Default unset.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schemars(extend("deprecated" = true))]
    pub stop: Option<f64>,
}

impl AngleRange {
    /// Moves the deprecated `start`/`stop` to `from`/`to`, returning one
    /// warning per old name; both spellings of one bound is an error.
    pub fn normalize_spelling(&mut self) -> Result<Vec<ConfigError>, ConfigError> {
        let mut warnings = Vec::new();
        let mut c = ConfigChecks::new();
        for (old, new, old_v, new_v) in [
            ("start", "from", &mut self.start, &mut self.from),
            ("stop", "to", &mut self.stop, &mut self.to),
        ] {
            let Some(v) = old_v.take() else { continue };
            if new_v.is_some() {
                c.push(ConfigError::key(
                    format!("angles.{old}"),
                    format!("give `{new}` (or its deprecated spelling `{old}`), not both"),
                ));
            } else {
                *new_v = Some(v);
                warnings.push(ConfigError::key(
                    format!("angles.{old}"),
                    format!("`{old}` is deprecated: write `{new}` (ranges are `{{ from, to, step }}` in every stage)"),
                ));
            }
        }
        c.finish().map(|()| warnings)
    }
}

/// A regular grid array.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ArrayKeys {
    /// Rows of taxels (along y). Default 4.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rows: Option<usize>,
    /// Columns of taxels (along x, the sliding direction). Default 4.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cols: Option<usize>,
    /// Centre-to-centre spacing, mm. Default 3 (2 mm traces, 1 mm gaps).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pitch_mm: Option<f64>,
    /// Side of a square taxel, mm. Default 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub taxel_mm: Option<f64>,
}

/// An explicit layout.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LayoutKeys {
    /// `positions`, or unset: accepted so that a layout table written for a
    /// file source (`layout = { kind = "positions", ... }`) reads here too;
    /// a grid is the `array` table. Default unset.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kind: Option<String>,
    /// Taxel centres `[x, y]`, mm. Required when `layout` is given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub positions_mm: Option<Vec<[f64; 2]>>,
    /// Side of each square taxel, mm. Default 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub taxel_mm: Option<f64>,
}

/// The palpation's motion and sampling.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct MotionKeys {
    /// Sliding speed along +x, mm/s. Default 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_mm_s: Option<f64>,
    /// Time held still on the object before sliding, s. Default 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold_before_s: Option<f64>,
    /// Time held still after sliding, s. Default 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold_after_s: Option<f64>,
    /// Samples per second of every taxel, Hz. Default 1000.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sample_rate_hz: Option<f64>,
    /// Distance between the array's footprint and the stimulus at the start and
    /// at the end of the slide, mm, before the effects' reach is added. Default 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub margin_mm: Option<f64>,
    /// Mean normal force relative to the one the scene describes (which
    /// scales the contact pressure, like `variation`'s per-trial draw):
    /// 1.3 presses 30 % harder. Unitless, in [0.01, 100]. Default 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub force_rel: Option<f64>,
}

/// The palpation, resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    /// mm/s.
    pub speed_mm_s: f64,
    /// s.
    pub hold_before_s: f64,
    /// s.
    pub hold_after_s: f64,
    /// Hz.
    pub sample_rate_hz: f64,
    /// mm.
    pub margin_mm: f64,
    /// Mean normal force relative to the scene's, unitless.
    pub force_rel: f64,
}

/// A ridge, resolved.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ridge {
    /// mm.
    pub width_mm: f64,
    /// mm.
    pub height_mm: f64,
    /// mm.
    pub indent_mm: f64,
}

impl Ridge {
    /// Extra pressure on the bar's top relative to the flat (Winkler bed).
    pub fn extra_pressure(&self) -> f64 {
        self.height_mm / self.indent_mm
    }
}

/// A checked scene: every key resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// Edge or ridge.
    pub stimulus: StimulusKind,
    /// The ridge's shape (unused for edges).
    pub ridge: Ridge,
    /// Angles, degrees, in order.
    pub angles: Vec<f64>,
    /// Repetitions per angle.
    pub trials_per_angle: usize,
    /// The array.
    pub layout: TaxelLayout,
    /// The palpation.
    pub motion: Motion,
    /// Effects, in order.
    pub effects: Vec<EffectConfig>,
}

/// Deep-merges `over` into `base`: tables merge key by key, anything else in
/// `over` replaces `base`.
///
/// The merge works on TOML values, the form the keys were written in: a
/// JSON intermediate (the first version) turned a NaN or an infinity into
/// `null`, which then read as "not set", so `speed_mm_s = nan` over a scene
/// file ran at the file's speed without a word. In TOML the value stays a
/// float and the checks refuse it, naming the key.
fn merge_toml(base: &mut toml::Value, over: toml::Value) {
    match (base, over) {
        (toml::Value::Table(b), toml::Value::Table(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge_toml(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

impl SceneConfig {
    /// Reads a scene file: the same keys as the stage, without `type`, `inputs`
    /// or `file`. Errors name the file and the offending key.
    pub fn from_file(path: &Path) -> Result<SceneConfig, ConfigError> {
        let text = palpate_core::input::read_text(path).map_err(|e| {
            ConfigError::key("file", format!("cannot read scene file {}: {e}", path.display()))
        })?;
        Self::from_toml_str(&text, path)
    }

    /// Parses scene-file text; `path` names it in errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<SceneConfig, ConfigError> {
        let cfg: SceneConfig = toml::from_str(text).map_err(|e| {
            let msg = e.message().trim().to_string();
            // serde names an unknown key in the message; a mistyped value's key is
            // the text at the start of the offending line.
            let line_no = e
                .span()
                .map(|s| text[..s.start.min(text.len())].lines().count().max(1));
            let line_text = e
                .span()
                .and_then(|s| {
                    text[..s.start.min(text.len())]
                        .rsplit('\n')
                        .next()
                        .map(|h| (h, s))
                })
                .map(|(head, s)| {
                    format!(
                        "{head}{}",
                        text[s.start.min(text.len())..].lines().next().unwrap_or("")
                    )
                })
                .map(|l| l.trim().to_string())
                .unwrap_or_default();
            let key = if msg.starts_with("unknown field") {
                msg.split('`').nth(1).map(str::to_string)
            } else {
                line_text
                    .split('=')
                    .next()
                    .map(|k| k.trim().trim_matches(['[', ']', '{', ' ']).to_string())
                    .filter(|k| !k.is_empty() && !k.contains(' '))
            };
            ConfigError::key(
                "file",
                format!(
                    "scene file {}{}: {}{msg}{}",
                    path.display(),
                    line_no.map(|l| format!(", line {l}")).unwrap_or_default(),
                    key.map(|k| format!("key `{k}`: ")).unwrap_or_default(),
                    if line_text.is_empty() {
                        String::new()
                    } else {
                        format!(" (in `{line_text}`)")
                    },
                ),
            )
        })?;
        if cfg.file.is_some() {
            return Err(ConfigError::key(
                "file",
                format!(
                    "scene file {}: a scene file cannot name another `file`",
                    path.display()
                ),
            ));
        }
        Ok(cfg)
    }

    /// A warning when both `array` and `layout` are given (after merging a
    /// file and a condition): the explicit layout wins, and a grid key set
    /// beside it (`--set stages.scene.array.rows=8` on a scene with a
    /// `layout`) would otherwise change nothing without a word.
    fn grid_ignored(&self) -> Option<ConfigError> {
        (self.array.is_some() && self.layout.is_some()).then(|| {
            ConfigError::key(
                "array",
                "is ignored: `layout` is given, and an explicit layout replaces the grid (give one of them)",
            )
        })
    }

    /// Moves deprecated key spellings to the current ones (see
    /// [`AngleRange::normalize_spelling`]), returning their warnings.
    pub fn normalize_spelling(&mut self) -> Result<Vec<ConfigError>, ConfigError> {
        match &mut self.angles {
            Some(Angles::Range(r)) => r.normalize_spelling(),
            _ => Ok(Vec::new()),
        }
    }

    /// This config with `base`'s keys as defaults (this config's keys win,
    /// tables merged key by key).
    pub fn over(&self, base: &SceneConfig) -> Result<SceneConfig, ConfigError> {
        let to = |c: &SceneConfig| {
            toml::Value::try_from(c).map_err(|e| ConfigError::general(format!("merging scene keys: {e}")))
        };
        let mut merged = to(base)?;
        merge_toml(&mut merged, to(self)?);
        let mut merged: SceneConfig = merged
            .try_into()
            .map_err(|e| ConfigError::general(format!("merging scene keys: {e}")))?;
        // A layout given here replaces the base's grid (as an explicit layout
        // replaces a grid in one table): the base's `array` is then no key
        // the user set beside the layout, and warning that it is ignored
        // (`grid_ignored`) would only be noise.
        if self.layout.is_some() && self.array.is_none() {
            merged.array = None;
        }
        Ok(merged)
    }

    /// Resolves the file (if any) and every default, and checks every value.
    pub fn resolve(&self, ctx: &BuildContext) -> Result<Scene, ConfigError> {
        self.resolve_with_warnings(ctx).map(|(scene, _)| scene)
    }

    /// [`SceneConfig::resolve`], with the warnings found on the way
    /// (deprecated spellings, in the graph or in the scene file).
    pub fn resolve_with_warnings(
        &self,
        ctx: &BuildContext,
    ) -> Result<(Scene, Vec<ConfigError>), ConfigError> {
        let (merged, warnings) = self.merged_with_warnings(ctx)?;
        Ok((merged.check()?, warnings))
    }

    /// This config over its file's keys (if any), spellings normalized,
    /// unchecked; with the deprecation warnings found on the way.
    pub fn merged_with_warnings(
        &self,
        ctx: &BuildContext,
    ) -> Result<(SceneConfig, Vec<ConfigError>), ConfigError> {
        let mut inline = self.clone();
        let mut warnings = inline.normalize_spelling()?;
        let merged = match &self.file {
            Some(f) => {
                let path = ctx.resolve(f);
                let mut base = SceneConfig::from_file(&path)?;
                let what = format!("scene file {}", path.display());
                let file_warnings = base.normalize_spelling().map_err(|e| e.context(&what))?;
                warnings.extend(file_warnings.into_iter().map(|w| w.context(&what)));
                inline.file = None;
                inline.over(&base)?
            }
            None => inline,
        };
        let mut merged = merged;
        merged.apply_adjust()?;
        Ok((merged, warnings))
    }

    /// Applies and clears `adjust`: each listed kind's keys are merged into
    /// the single effect of that kind in `effects`.
    pub fn apply_adjust(&mut self) -> Result<(), ConfigError> {
        let Some(adjust) = self.adjust.take() else {
            return Ok(());
        };
        let effects = self.effects.take().unwrap_or_default();
        let mut list = match toml::Value::try_from(&effects) {
            Ok(toml::Value::Array(a)) => a,
            _ => return Err(ConfigError::key("adjust", "cannot read the effects list")),
        };
        let mut c = ConfigChecks::new();
        for (kind, keys) in adjust {
            let at: Vec<usize> = list
                .iter()
                .enumerate()
                .filter(|(_, e)| e.get("kind").and_then(|k| k.as_str()) == Some(kind.as_str()))
                .map(|(i, _)| i)
                .collect();
            let key = format!("adjust.{kind}");
            match at.as_slice() {
                [i] => {
                    if keys.contains_key("kind") {
                        c.push(ConfigError::key(key, "cannot change an effect's `kind`"));
                        continue;
                    }
                    merge_toml(&mut list[*i], toml::Value::Table(keys));
                }
                [] => c.push(ConfigError::key(
                    key,
                    format!("the scene lists no `{kind}` effect to adjust (list it under `effects`)"),
                )),
                _ => c.push(ConfigError::key(
                    key,
                    format!(
                        "the scene lists {} `{kind}` effects; adjust needs exactly one",
                        at.len()
                    ),
                )),
            }
        }
        c.finish()?;
        let effects: Vec<EffectConfig> = list
            .into_iter()
            .map(|e| {
                let kind = e.get("kind").and_then(|k| k.as_str()).unwrap_or("?").to_string();
                e.try_into().map_err(|err: toml::de::Error| {
                    ConfigError::key(format!("adjust.{kind}"), err.message().to_string())
                })
            })
            .collect::<Result<_, _>>()?;
        self.effects = Some(effects);
        Ok(())
    }

    /// The scene of every condition, resolved and checked: `(name, scene
    /// config, scene)` in name order, or one unnamed entry without
    /// `conditions`; and the warnings found on the way. Errors name
    /// `conditions.<name>.<key>`.
    #[allow(clippy::type_complexity)]
    pub fn resolve_conditions(
        &self,
        ctx: &BuildContext,
    ) -> Result<(Vec<(Option<String>, SceneConfig, Scene)>, Vec<ConfigError>), ConfigError> {
        let (mut merged, mut warnings) = self.merged_with_warnings(ctx)?;
        let base_warned = merged.grid_ignored().map(|w| warnings.push(w)).is_some();
        let Some(conditions) = merged.conditions.take() else {
            let scene = merged.check()?;
            return Ok((vec![(None, merged, scene)], warnings));
        };
        if conditions.is_empty() {
            return Err(ConfigError::key(
                "conditions",
                "an empty table; leave `conditions` out for a single condition",
            ));
        }
        let mut out = Vec::with_capacity(conditions.len());
        for (name, mut cond) in conditions {
            let key = |k: &str| format!("conditions.{name}{}{k}", if k.is_empty() { "" } else { "." });
            let prefix = |e: ConfigError| e.within(&format!("conditions.{name}"));
            if name.is_empty()
                || !name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-'))
            {
                return Err(ConfigError::key(
                    key(""),
                    format!(
                        "condition name `{name}`: use letters, digits, `_` and `-` (it starts trial ids)"
                    ),
                ));
            }
            if cond.file.is_some() {
                return Err(ConfigError::key(
                    key("file"),
                    "a condition cannot name a scene `file`",
                ));
            }
            if cond.conditions.is_some() {
                return Err(ConfigError::key(key("conditions"), "conditions cannot nest"));
            }
            warnings.extend(cond.normalize_spelling().map_err(prefix)?.into_iter().map(prefix));
            let mut cfg = cond.over(&merged)?;
            if !base_warned {
                warnings.extend(cfg.grid_ignored().map(prefix));
            }
            cfg.apply_adjust().map_err(prefix)?;
            let scene = cfg.check().map_err(prefix)?;
            out.push((Some(name), cfg, scene));
        }
        Ok((out, warnings))
    }

    /// Fills defaults and checks values (no file handling). Every wrong key
    /// is reported, not only the first.
    pub fn check(&self) -> Result<Scene, ConfigError> {
        let mut c = ConfigChecks::new();
        let stimulus = self.stimulus.unwrap_or_default();
        let r = self.ridge.clone().unwrap_or_default();
        let ridge = Ridge {
            width_mm: c
                .take(check_positive("ridge.width_mm", r.width_mm.unwrap_or(2.0), "mm"))
                .unwrap_or(2.0),
            height_mm: c
                .take(check_range(
                    "ridge.height_mm",
                    r.height_mm.unwrap_or(2.0),
                    0.0,
                    1e3,
                    "mm",
                ))
                .unwrap_or(2.0),
            indent_mm: c
                .take(check_positive(
                    "ridge.indent_mm",
                    r.indent_mm.unwrap_or(1.0),
                    "mm",
                ))
                .unwrap_or(1.0),
        };
        let angles = c.take(resolve_angles(self.angles.as_ref())).unwrap_or_default();
        let trials_per_angle = self.trials_per_angle.unwrap_or(10);
        if trials_per_angle == 0 {
            c.push(ConfigError::key("trials_per_angle", "must be at least 1"));
        }
        // A documented cap (docs/resource-policy.md): 1e8 passed check, then
        // the trial list alone aborted the run.
        if angles.len().saturating_mul(trials_per_angle) > MAX_SCENE_TRIALS {
            c.push(ConfigError::key(
                "trials_per_angle",
                format!(
                    "{} angles x {trials_per_angle} trials is over the cap of {MAX_SCENE_TRIALS} trials per scene",
                    angles.len()
                ),
            ));
        }
        if let Some(k) = self.layout.as_ref().and_then(|l| l.kind.as_deref()) {
            if k != "positions" {
                c.push(ConfigError::key(
                    "layout.kind",
                    format!(
                        "a scene's `layout` lists taxel positions (`kind = \"positions\"`, or no `kind`); \
                         got `{k}`: a grid is the `array` table (rows, cols, pitch_mm, taxel_mm)"
                    ),
                ));
            }
        }
        let layout = match &self.layout {
            Some(l) => match l.positions_mm.clone() {
                None => {
                    c.push(ConfigError::key(
                        "layout.positions_mm",
                        "an explicit layout needs its taxel positions",
                    ));
                    None
                }
                Some(positions_mm) => {
                    let layout = TaxelLayout::Positions {
                        positions_mm,
                        taxel_mm: l.taxel_mm.unwrap_or(2.0),
                    };
                    c.take(layout.validate().map_err(|e| ConfigError::key("layout", e)))
                        .map(|()| layout)
                }
            },
            None => {
                let a = self.array.clone().unwrap_or_default();
                let layout = TaxelLayout::Grid {
                    rows: a.rows.unwrap_or(4),
                    cols: a.cols.unwrap_or(4),
                    pitch_mm: a.pitch_mm.unwrap_or(3.0),
                    taxel_mm: a.taxel_mm.unwrap_or(2.0),
                };
                c.take(layout.validate().map_err(|e| ConfigError::key("array", e)))
                    .map(|()| layout)
            }
        };
        let m = self.motion.clone().unwrap_or_default();
        let motion = Motion {
            speed_mm_s: c
                .take(check_positive(
                    "motion.speed_mm_s",
                    m.speed_mm_s.unwrap_or(2.0),
                    "mm/s",
                ))
                .unwrap_or(2.0),
            hold_before_s: c
                .take(check_range(
                    "motion.hold_before_s",
                    m.hold_before_s.unwrap_or(2.0),
                    0.0,
                    3600.0,
                    "s",
                ))
                .unwrap_or(2.0),
            hold_after_s: c
                .take(check_range(
                    "motion.hold_after_s",
                    m.hold_after_s.unwrap_or(2.0),
                    0.0,
                    3600.0,
                    "s",
                ))
                .unwrap_or(2.0),
            sample_rate_hz: c
                .take(check_range(
                    "motion.sample_rate_hz",
                    m.sample_rate_hz.unwrap_or(1000.0),
                    1e-3,
                    1e7,
                    "Hz",
                ))
                .unwrap_or(1000.0),
            margin_mm: c
                .take(check_range(
                    "motion.margin_mm",
                    m.margin_mm.unwrap_or(1.0),
                    0.0,
                    1e3,
                    "mm",
                ))
                .unwrap_or(1.0),
            force_rel: c
                .take(check_range(
                    "motion.force_rel",
                    m.force_rel.unwrap_or(1.0),
                    0.01,
                    100.0,
                    "",
                ))
                .unwrap_or(1.0),
        };
        c.finish()?;
        Ok(Scene {
            stimulus,
            ridge,
            angles,
            trials_per_angle,
            // Present whenever every check passed.
            layout: layout.ok_or_else(|| ConfigError::key("array", "no layout"))?,
            motion,
            effects: self.effects.clone().unwrap_or_default(),
        })
    }
}

/// Most trials (angles x trials per angle) one scene may list.
pub const MAX_SCENE_TRIALS: usize = 1_000_000;

/// Expands and checks the angles: each in (0, 180), no repeats.
fn resolve_angles(angles: Option<&Angles>) -> Result<Vec<f64>, ConfigError> {
    let list = match angles {
        Some(Angles::List(v)) => v.clone(),
        None => range(10.0, 90.0, 5.0)?,
        Some(Angles::Range(r)) => range(
            r.from.or(r.start).unwrap_or(10.0),
            r.to.or(r.stop).unwrap_or(90.0),
            r.step.unwrap_or(5.0),
        )?,
    };
    if list.is_empty() {
        return Err(ConfigError::key("angles", "needs at least one angle"));
    }
    // Repeats by hash (a pairwise check took 11.6 s on 10,000 angles).
    let mut seen = std::collections::HashSet::new();
    for &a in &list {
        if !(a.is_finite() && a > 0.0 && a < 180.0) {
            return Err(ConfigError::key(
                "angles",
                format!(
                    "every angle must lie strictly between 0 and 180 degrees (0 and 180 are parallel to the motion and never crossed), got {}",
                    palpate_core::fmt_num(a)
                ),
            ));
        }
        if !seen.insert(angle_id(a)) {
            return Err(ConfigError::key("angles", format!("angle {a} is listed twice")));
        }
    }
    Ok(list)
}

fn range(start: f64, stop: f64, step: f64) -> Result<Vec<f64>, ConfigError> {
    check_positive("angles.step", step, "degrees")?;
    if !(start.is_finite() && stop.is_finite()) || stop < start {
        return Err(ConfigError::key(
            "angles",
            format!("a range needs finite from <= to, got from {start}, to {stop}"),
        ));
    }
    let n = ((stop - start) / step + 1e-9).floor();
    if n > 1e5 {
        return Err(ConfigError::key(
            "angles.step",
            format!("{n} angles is too many; use a larger step"),
        ));
    }
    // Multiply rather than accumulate, and round to 1e-9 degree, so that
    // `10 + 3 * 0.1` gives the angle 10.3 and not 10.300000000000001.
    Ok((0..=n as usize)
        .map(|i| ((start + i as f64 * step) * 1e9).round() / 1e9)
        .collect())
}

/// The angle as it appears in trial ids: `45`, `22.5`, `10.125`.
pub fn angle_id(a: f64) -> String {
    let s = format!("{:.6}", a);
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}
