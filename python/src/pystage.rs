//! `python`: a stage written in Python, usable in any graph run from Python.
//!
//! A Python class decorated with `@palpate.stage("name", inputs=..., output=...)`
//! is registered here under its name with its role and payload kinds, and its
//! name becomes a stage type (a [`palpate_core::registry::Alias`]); a graph
//! then uses it as
//!
//! ```toml
//! [stages.enc]
//! type = "threshold_encoder"        # the name it was registered under
//! inputs = ["drive"]
//! threshold = 0.5                   # the class's own keys
//! ```
//!
//! which the loader reads as the long form `type = "python"`, `stage =
//! "threshold_encoder"`, `config = { threshold = 0.5 }` (also accepted). A
//! name of a built-in type is refused.
//!
//! Building the stage calls the Python factory with `config` (the Python side
//! checks the keys against the class's declared ones and raises an error naming
//! the key); running it calls the adapter's `process` (a map), or `fit` then
//! `predict` (an estimator), taking the GIL for each call. Payloads cross as the
//! raw dicts of [`crate::convert`]. A Python exception becomes a stage error
//! with the Python message, so the run fails with the stage and trial named.

use crate::convert::{item_to_py, json_to_py, payload_from_py};
use palpate_core::{
    register_stage, BuildContext, ConfigError, Estimate, Estimator, FitContext, InputSpec, Item, Map, Model,
    Payload, PayloadKind, Stage, StageConfig, StageError, TrialContext,
};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

/// What a registered Python stage is.
struct Entry {
    /// `map` or `estimator`.
    role: String,
    inputs: Vec<PayloadKind>,
    min_inputs: usize,
    max_inputs: Option<usize>,
    output: PayloadKind,
    /// `factory(config: dict) -> adapter`.
    factory: PyObject,
}

fn registry() -> &'static Mutex<HashMap<String, Entry>> {
    static R: OnceLock<Mutex<HashMap<String, Entry>>> = OnceLock::new();
    R.get_or_init(|| Mutex::new(HashMap::new()))
}

fn kind(name: &str) -> PyResult<PayloadKind> {
    serde_json::from_value(serde_json::Value::String(name.to_string())).map_err(|_| {
        pyo3::exceptions::PyValueError::new_err(format!(
            "unknown payload kind `{name}`; expected signals, spikes, images or estimates"
        ))
    })
}

/// Registers (or replaces) a Python stage.
#[pyfunction]
#[pyo3(signature = (name, role, inputs, output, factory, min_inputs=1, max_inputs=Some(1)))]
pub fn register_stage(
    name: String,
    role: String,
    inputs: Vec<String>,
    output: String,
    factory: PyObject,
    min_inputs: usize,
    max_inputs: Option<usize>,
) -> PyResult<()> {
    if role != "map" && role != "estimator" {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "role must be `map` or `estimator`, got `{role}`"
        )));
    }
    let inputs = inputs.iter().map(|k| kind(k)).collect::<PyResult<Vec<_>>>()?;
    let output = kind(&output)?;
    if role == "estimator" && output != PayloadKind::Estimates {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "an estimator's output must be `estimates`",
        ));
    }
    // The name becomes a stage type of its own: `type = "<name>"` with the
    // class's keys beside it stands for `type = "python"`, `stage = "<name>"`,
    // `config = { .. }`.
    palpate_core::registry::register_alias(
        &name,
        palpate_core::registry::Alias {
            target: "python",
            name_key: "stage",
            keys_into: "config",
        },
    )
    .map_err(pyo3::exceptions::PyValueError::new_err)?;
    let mut r = registry()
        .lock()
        .map_err(|_| pyo3::exceptions::PyRuntimeError::new_err("stage registry poisoned"))?;
    r.insert(
        name,
        Entry {
            role,
            inputs,
            min_inputs,
            max_inputs,
            output,
            factory,
        },
    );
    Ok(())
}

/// Removes a Python stage; true if it was registered.
#[pyfunction]
pub fn unregister_stage(name: &str) -> bool {
    registry()
        .lock()
        .map(|mut r| r.remove(name).is_some())
        .unwrap_or(false)
}

/// A stage written in Python and registered with `@palpate.stage` (only in
/// graphs run from Python, where the class is defined).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PythonStageConfig {
    /// The name the Python class was registered under (`@palpate.stage("name")`).
    pub stage: String,
    /// The Python stage's own keys, checked against the keys its class declares.
    /// Default: none (every key takes the class's default).
    #[serde(default)]
    pub config: serde_json::Map<String, serde_json::Value>,
}

#[typetag::serde(name = "python")]
impl StageConfig for PythonStageConfig {
    fn inputs(&self) -> InputSpec {
        registry()
            .lock()
            .ok()
            .and_then(|r| {
                r.get(&self.stage).map(|e| InputSpec {
                    kinds: e.inputs.clone(),
                    min: e.min_inputs,
                    max: e.max_inputs,
                })
            })
            .unwrap_or_else(|| InputSpec::many(PayloadKind::Signals))
    }
    fn output(&self) -> Option<PayloadKind> {
        registry()
            .lock()
            .ok()
            .and_then(|r| r.get(&self.stage).map(|e| e.output))
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Python::with_gil(|py| {
            let (role, output, factory) = {
                let r = registry()
                    .lock()
                    .map_err(|_| ConfigError::general("the Python stage registry is poisoned"))?;
                match r.get(&self.stage) {
                    Some(e) => (e.role.clone(), e.output, e.factory.clone_ref(py)),
                    None => {
                        let mut names: Vec<&String> = r.keys().collect();
                        names.sort();
                        let known = if names.is_empty() {
                            "none is registered (define it with @palpate.stage in the Python process that runs the graph)".to_string()
                        } else {
                            format!(
                                "registered: {}",
                                names
                                    .iter()
                                    .map(|n| format!("`{n}`"))
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            )
                        };
                        return Err(ConfigError::key(
                            "stage",
                            format!("no Python stage `{}`; {known}", self.stage),
                        ));
                    }
                }
            };
            let cfg = json_to_py(py, &serde_json::Value::Object(self.config.clone()))
                .map_err(|e| ConfigError::key("config", e.to_string()))?;
            let adapter = factory.call1(py, (cfg,)).map_err(|e| {
                // The Python side names the offending key in `e.key`.
                let key = e
                    .value(py)
                    .getattr("key")
                    .ok()
                    .and_then(|k| k.extract::<String>().ok())
                    .map(|k| format!("config.{k}"));
                let msg = e.value(py).to_string();
                match key {
                    Some(k) => ConfigError::key(k, msg),
                    None => ConfigError::key("config", msg),
                }
            })?;
            let stage = PyStage {
                name: self.stage.clone(),
                output,
                adapter,
            };
            Ok(if role == "map" {
                Stage::Map(Box::new(stage))
            } else {
                Stage::Estimator(Box::new(stage))
            })
        })
    }
}
register_stage!("python", PythonStageConfig);

struct PyStage {
    name: String,
    /// The kind the class declared (`output=`): what `process` must return.
    output: PayloadKind,
    adapter: PyObject,
}

/// The name `@palpate.stage(output=...)` takes for a kind.
fn kind_name(k: PayloadKind) -> String {
    serde_json::to_value(k)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| k.to_string())
}

/// A Python exception as a stage error: its type, message and the last line
/// of its traceback.
fn py_err(py: Python<'_>, name: &str, what: &str, e: &PyErr) -> StageError {
    let tb = e.traceback(py).and_then(|t| t.format().ok()).and_then(|s| {
        s.lines()
            .rev()
            .find(|l| l.trim_start().starts_with("File"))
            .map(|l| l.trim().to_string())
    });
    StageError::new(format!(
        "Python stage `{name}` {what}: {}{}",
        e.value(py),
        tb.map(|t| format!(" ({t})")).unwrap_or_default()
    ))
}

fn ctx_dict<'py>(
    py: Python<'py>,
    stage_id: &str,
    trial: Option<&str>,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("stage_id", stage_id)?;
    d.set_item("trial_id", trial)?;
    d.set_item("seed", seed)?;
    Ok(d)
}

fn to_payload(py: Python<'_>, name: &str, what: &str, obj: &Bound<'_, PyAny>) -> Result<Payload, StageError> {
    payload_from_py(obj).map_err(|e| py_err(py, name, what, &e))
}

impl Map for PyStage {
    fn process(&self, inputs: &[&Item], ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        Python::with_gil(|py| {
            let go = || -> PyResult<PyObject> {
                let l = PyList::empty(py);
                for it in inputs {
                    l.append(item_to_py(py, it)?)?;
                }
                let c = ctx_dict(py, ctx.stage_id, Some(&ctx.meta.trial_id), ctx.seed)?;
                self.adapter.call_method1(py, "process", (l, c))
            };
            let out = go().map_err(|e| py_err(py, &self.name, "failed", &e))?;
            let p = to_payload(py, &self.name, "returned a bad payload", out.bind(py))?;
            // Unchecked, the next stage failed, blaming itself ("expected
            // spike events, got analog signals").
            if p.kind() != self.output {
                return Err(StageError::new(format!(
                    "Python stage `{}` declares output=\"{}\" ({}) but its `process` returned {} ({})",
                    self.name,
                    kind_name(self.output),
                    self.output,
                    kind_name(p.kind()),
                    p.kind()
                )));
            }
            Ok(p)
        })
    }
}

impl Estimator for PyStage {
    fn trained(&self) -> bool {
        Python::with_gil(|py| {
            self.adapter
                .getattr(py, "trained")
                .and_then(|t| t.extract::<bool>(py))
                .unwrap_or(true)
        })
    }
    fn fit(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        Python::with_gil(|py| {
            let go = || -> PyResult<PyObject> {
                let l = PyList::empty(py);
                for it in train {
                    l.append(item_to_py(py, it)?)?;
                }
                let c = ctx_dict(py, ctx.stage_id, None, ctx.seed)?;
                c.set_item("fold", ctx.fold)?;
                self.adapter.call_method1(py, "fit", (l, c))
            };
            let model = go().map_err(|e| py_err(py, &self.name, "failed to fit", &e))?;
            Ok(Box::new(PyModel {
                name: self.name.clone(),
                model,
            }) as Box<dyn Model>)
        })
    }
}

struct PyModel {
    name: String,
    model: PyObject,
}

impl Model for PyModel {
    fn predict(&self, item: &Item, ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        Python::with_gil(|py| {
            let go = || -> PyResult<PyObject> {
                let c = ctx_dict(py, ctx.stage_id, Some(&ctx.meta.trial_id), ctx.seed)?;
                self.model.call_method1(py, "predict", (item_to_py(py, item)?, c))
            };
            let out = go().map_err(|e| py_err(py, &self.name, "failed to predict", &e))?;
            match to_payload(py, &self.name, "returned a bad estimate", out.bind(py))? {
                Payload::Estimate(e) => Ok((*e).clone()),
                other => Err(StageError::new(format!(
                    "Python stage `{}` returned {} from predict, not an estimate",
                    self.name,
                    other.kind()
                ))),
            }
        })
    }
}
