//! Conversions between palpate's payloads and "raw" Python dicts of NumPy
//! arrays, and between JSON values and Python objects.
//!
//! Raw payloads (`kind` says which; every one may carry `meta`):
//!
//! | kind | keys |
//! |---|---|
//! | `signals` | `data` float64 `(samples, taxels)`, `sample_rate_hz`, `unit`, `layout` |
//! | `spikes` | `taxel` uint32 `(n,)`, `t_ms` float64 `(n,)`, `duration_ms`, `layout` |
//! | `images` | `counts` float64 `(frames, taxels)`, `window_ms`, `hop_ms`, `layout` |
//! | `estimate` | `angle_deg`, `class_deg` (float or None), `class_angles`, `scores` float64 `(classes,)`, `best_frame`, `decision_time_ms`, `uncertain` (bool; absent: false) |
//!
//! `layout` is the JSON form of [`TaxelLayout`] as a dict (`{"kind": "grid",
//! "rows": 4, ...}`); `meta` is `{"trial_id", "index", "angle_deg", "stimulus",
//! "group", "crossing_ms", "speed_mm_s"}` (`speed_mm_s`: the commanded
//! sliding speed, which WSS uses when its config sets none). Sizes coming
//! from Python are checked (a signal's
//! rows must agree, a spike's taxel must exist, times must be finite) and a
//! violation is a `ValueError` naming the field.

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use palpate_core::{
    ClassScore, Estimate, Item, Label, Payload, Signals, SpikeEvent, SpikeImages, SpikeTrain, Stimulus,
    TaxelLayout, TrialMeta,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use std::sync::Arc;

/// A JSON value as a Python object.
pub fn json_to_py(py: Python<'_>, v: &serde_json::Value) -> PyResult<PyObject> {
    use serde_json::Value as V;
    Ok(match v {
        V::Null => py.None(),
        V::Bool(b) => PyBool::new(py, *b).to_owned().into_any().unbind(),
        V::Number(n) => match (n.as_i64(), n.as_u64()) {
            (Some(i), _) => i.into_pyobject(py)?.into_any().unbind(),
            (None, Some(u)) => u.into_pyobject(py)?.into_any().unbind(),
            _ => n
                .as_f64()
                .unwrap_or(f64::NAN)
                .into_pyobject(py)?
                .into_any()
                .unbind(),
        },
        V::String(s) => PyString::new(py, s).into_any().unbind(),
        V::Array(a) => {
            let items: Vec<PyObject> = a.iter().map(|x| json_to_py(py, x)).collect::<PyResult<_>>()?;
            PyList::new(py, items)?.into_any().unbind()
        }
        V::Object(o) => {
            let d = PyDict::new(py);
            for (k, x) in o {
                d.set_item(k, json_to_py(py, x)?)?;
            }
            d.into_any().unbind()
        }
    })
}

/// A Python object (dicts, lists, tuples, str, numbers, bool, None, NumPy
/// scalars and arrays) as a JSON value. `depth` guards against cycles.
pub fn py_to_json(obj: &Bound<'_, PyAny>) -> PyResult<serde_json::Value> {
    py_to_json_at(obj, 0)
}

fn py_to_json_at(obj: &Bound<'_, PyAny>, depth: usize) -> PyResult<serde_json::Value> {
    use serde_json::Value as V;
    if depth > 64 {
        return Err(PyValueError::new_err("value nested more than 64 levels deep"));
    }
    if obj.is_none() {
        return Ok(V::Null);
    }
    if obj.is_instance_of::<PyBool>() {
        return Ok(V::Bool(obj.extract()?));
    }
    if obj.is_instance_of::<PyInt>() {
        if let Ok(i) = obj.extract::<i64>() {
            return Ok(V::from(i));
        }
        // PyO3's own conversion raised a bare OverflowError.
        return obj.extract::<u64>().map(V::from).map_err(|_| {
            PyValueError::new_err(format!("{obj} is outside the 64-bit integers a key can hold"))
        });
    }
    if obj.is_instance_of::<PyFloat>() {
        let f: f64 = obj.extract()?;
        return serde_json::Number::from_f64(f)
            .map(V::Number)
            .ok_or_else(|| PyValueError::new_err(format!("{f} is not a finite number")));
    }
    if let Ok(s) = obj.downcast::<PyString>() {
        return Ok(V::String(s.extract::<String>()?));
    }
    if let Ok(d) = obj.downcast::<PyDict>() {
        let mut m = serde_json::Map::new();
        for (k, v) in d.iter() {
            let key: String = k
                .extract()
                .map_err(|_| PyTypeError::new_err(format!("dict keys must be strings, got {k}")))?;
            m.insert(key, py_to_json_at(&v, depth + 1)?);
        }
        return Ok(V::Object(m));
    }
    if obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>() {
        let mut a = Vec::new();
        for x in obj.try_iter()? {
            a.push(py_to_json_at(&x?, depth + 1)?);
        }
        return Ok(V::Array(a));
    }
    // NumPy arrays and scalars, pathlib paths: through their Python forms.
    if obj.hasattr("tolist")? {
        let l = obj.call_method0("tolist")?;
        if !l.is(obj) {
            return py_to_json_at(&l, depth + 1);
        }
    }
    if obj.hasattr("__fspath__")? {
        return Ok(V::String(obj.call_method0("__fspath__")?.extract()?));
    }
    Err(PyTypeError::new_err(format!(
        "cannot use a value of type {} in a config",
        obj.get_type().name()?
    )))
}

/// `err` (from converting the value of `what`) with `what` named at the head of
/// its message: a `TypeError` stays one, anything else (a bare `ValueError`,
/// PyO3's `OverflowError`) becomes a `ValueError`.
pub fn named(py: Python<'_>, what: &str, err: PyErr) -> PyErr {
    let msg = format!("{what}: {}", err.value(py));
    if err.is_instance_of::<PyTypeError>(py) {
        PyTypeError::new_err(msg)
    } else {
        PyValueError::new_err(msg)
    }
}

/// A stage's keys (a dict) as a JSON object, converted key by key so that an
/// error names the key (`` `cutoff_hz`: NaN is not a finite number ``).
pub fn config_to_json(py: Python<'_>, obj: &Bound<'_, PyAny>) -> PyResult<serde_json::Value> {
    let Ok(d) = obj.downcast::<PyDict>() else {
        return py_to_json(obj);
    };
    let mut m = serde_json::Map::new();
    for (k, v) in d.iter() {
        let key: String = k
            .extract()
            .map_err(|_| PyTypeError::new_err(format!("keys must be strings, got {k}")))?;
        let j = py_to_json(&v).map_err(|e| named(py, &format!("key `{key}`"), e))?;
        m.insert(key, j);
    }
    Ok(serde_json::Value::Object(m))
}

/// A Python value as a TOML value (`set=` of a graph), `what` naming it in
/// errors. NaN and infinities are TOML floats (the graph's checks then name
/// the stage and key, as for `--set key=nan`); None, and integers outside
/// TOML's 64 bits, are errors naming `what`. Integers from 2**63 to 2**64 - 1
/// (seeds) become their digits, which `run.seed` reads alike.
pub fn py_to_toml(obj: &Bound<'_, PyAny>, what: &str, depth: usize) -> PyResult<toml::Value> {
    use toml::Value as T;
    if depth > 64 {
        return Err(PyValueError::new_err(format!(
            "{what}: nested more than 64 levels deep"
        )));
    }
    if obj.is_none() {
        return Err(PyTypeError::new_err(format!(
            "{what} is None: TOML has no null; leave the key out"
        )));
    }
    if obj.is_instance_of::<PyBool>() {
        return Ok(T::Boolean(obj.extract()?));
    }
    if obj.is_instance_of::<PyInt>() {
        if let Ok(i) = obj.extract::<i64>() {
            return Ok(T::Integer(i));
        }
        if depth == 0 {
            if let Ok(u) = obj.extract::<u64>() {
                return Ok(T::String(u.to_string()));
            }
        }
        return Err(PyValueError::new_err(format!(
            "{what}: {obj} is outside TOML's integers (-2**63 to 2**63 - 1{})",
            if depth == 0 {
                "; a seed: up to 2**64 - 1"
            } else {
                ""
            }
        )));
    }
    if obj.is_instance_of::<PyFloat>() {
        return Ok(T::Float(obj.extract()?));
    }
    if let Ok(s) = obj.downcast::<PyString>() {
        return Ok(T::String(s.extract()?));
    }
    if let Ok(d) = obj.downcast::<PyDict>() {
        let mut t = toml::Table::new();
        for (k, v) in d.iter() {
            let key: String = k
                .extract()
                .map_err(|_| PyTypeError::new_err(format!("{what}: dict keys must be strings, got {k}")))?;
            let sub = format!("{what}.{key}");
            t.insert(key, py_to_toml(&v, &sub, depth + 1)?);
        }
        return Ok(T::Table(t));
    }
    if obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>() {
        let mut a = Vec::new();
        for x in obj.try_iter()? {
            a.push(py_to_toml(&x?, what, depth + 1)?);
        }
        return Ok(T::Array(a));
    }
    // NumPy arrays and scalars (np.bool_ included), pathlib paths.
    if obj.hasattr("tolist")? {
        let l = obj.call_method0("tolist")?;
        if !l.is(obj) {
            return py_to_toml(&l, what, depth);
        }
    }
    if obj.hasattr("__fspath__")? {
        return Ok(T::String(obj.call_method0("__fspath__")?.extract()?));
    }
    Err(PyTypeError::new_err(format!(
        "{what}: cannot use a value of type {} in a graph",
        obj.get_type().name()?
    )))
}

fn layout_to_py(py: Python<'_>, l: &TaxelLayout) -> PyResult<PyObject> {
    json_to_py(py, &serde_json::to_value(l).unwrap_or(serde_json::Value::Null))
}

fn layout_from_py(obj: &Bound<'_, PyAny>) -> PyResult<TaxelLayout> {
    let l: TaxelLayout = serde_json::from_value(py_to_json(obj)?)
        .map_err(|e| PyValueError::new_err(format!("`layout`: {e}")))?;
    l.validate()
        .map_err(|e| PyValueError::new_err(format!("`layout`: {e}")))?;
    Ok(l)
}

/// Trial metadata as a dict.
pub fn meta_to_py<'py>(py: Python<'py>, m: &TrialMeta) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("trial_id", &m.trial_id)?;
    d.set_item("index", m.index)?;
    d.set_item("angle_deg", m.label.angle_deg)?;
    d.set_item("stimulus", m.label.stimulus.to_string())?;
    d.set_item("group", m.group)?;
    d.set_item("crossing_ms", m.crossing_ms.map(|c| (c[0], c[1])))?;
    d.set_item("speed_mm_s", m.speed_mm_s)?;
    Ok(d)
}

/// Trial metadata from a dict (missing keys take neutral values); `index`
/// is the trial's position when the dict has none.
pub fn meta_from_py(obj: Option<&Bound<'_, PyAny>>, index: usize) -> PyResult<TrialMeta> {
    let mut m = TrialMeta {
        trial_id: format!("trial{index}"),
        index,
        ..TrialMeta::default()
    };
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(m);
    };
    let d = obj
        .downcast::<PyDict>()
        .map_err(|_| PyTypeError::new_err("`meta` must be a dict"))?;
    if let Some(v) = d.get_item("trial_id")? {
        m.trial_id = v.str()?.to_string();
    }
    if let Some(v) = d.get_item("angle_deg")?.filter(|v| !v.is_none()) {
        let a: f64 = v.extract()?;
        m.label = Label {
            stimulus: Stimulus::Edge,
            angle_deg: a.is_finite().then_some(a),
        };
    }
    if let Some(v) = d.get_item("stimulus")?.filter(|v| !v.is_none()) {
        m.label.stimulus = serde_json::from_value(serde_json::Value::String(v.str()?.to_string()))
            .map_err(|e| PyValueError::new_err(format!("`stimulus`: {e}")))?;
    }
    if let Some(v) = d.get_item("group")?.filter(|v| !v.is_none()) {
        m.group = v.extract()?;
    }
    if let Some(v) = d.get_item("crossing_ms")?.filter(|v| !v.is_none()) {
        let (a, b): (f64, f64) = v.extract()?;
        m.crossing_ms = Some([a, b]);
    }
    if let Some(v) = d.get_item("speed_mm_s")?.filter(|v| !v.is_none()) {
        let v: f64 = v.extract()?;
        if !(v.is_finite() && v > 0.0) {
            return Err(PyValueError::new_err(format!(
                "`speed_mm_s`: must be a positive number of mm/s, got {v}"
            )));
        }
        m.speed_mm_s = Some(v);
    }
    Ok(m)
}

/// A payload as a raw dict (with its trial's `meta`).
pub fn item_to_py<'py>(py: Python<'py>, item: &Item) -> PyResult<Bound<'py, PyDict>> {
    let d = payload_to_py(py, &item.payload)?;
    d.set_item("meta", meta_to_py(py, &item.meta)?)?;
    Ok(d)
}

/// A payload as a raw dict.
pub fn payload_to_py<'py>(py: Python<'py>, p: &Payload) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    match p {
        Payload::Signals(s) => {
            let (n, m) = (s.data.len(), s.n_samples());
            let mut flat = Vec::with_capacity(n * m);
            for k in 0..m {
                flat.extend(s.data.iter().map(|row| row[k]));
            }
            d.set_item("kind", "signals")?;
            d.set_item("data", PyArray1::from_vec(py, flat).reshape([m, n])?)?;
            d.set_item("sample_rate_hz", s.sample_rate_hz)?;
            d.set_item("unit", &s.unit)?;
            d.set_item("layout", layout_to_py(py, &s.layout)?)?;
        }
        Payload::Spikes(s) => {
            d.set_item("kind", "spikes")?;
            d.set_item(
                "taxel",
                PyArray1::from_vec(py, s.events.iter().map(|e| e.taxel).collect()),
            )?;
            d.set_item(
                "t_ms",
                PyArray1::from_vec(py, s.events.iter().map(|e| e.t_ms).collect()),
            )?;
            d.set_item("duration_ms", s.duration_ms)?;
            d.set_item("layout", layout_to_py(py, &s.layout)?)?;
        }
        Payload::Images(im) => {
            d.set_item("kind", "images")?;
            d.set_item(
                "counts",
                PyArray1::from_vec(py, im.counts.clone()).reshape([im.n_frames, im.n_taxels()])?,
            )?;
            d.set_item("window_ms", im.window_ms)?;
            d.set_item("hop_ms", im.hop_ms)?;
            d.set_item("layout", layout_to_py(py, &im.layout)?)?;
        }
        Payload::Estimate(e) => {
            d.set_item("kind", "estimate")?;
            d.set_item("angle_deg", e.angle_deg)?;
            d.set_item("class_deg", e.class_deg)?;
            d.set_item(
                "class_angles",
                PyArray1::from_vec(py, e.scores.iter().map(|s| s.angle_deg).collect()),
            )?;
            d.set_item(
                "scores",
                PyArray1::from_vec(py, e.scores.iter().map(|s| s.score).collect()),
            )?;
            d.set_item("best_frame", e.best_frame)?;
            d.set_item("decision_time_ms", e.decision_time_ms)?;
            d.set_item("uncertain", e.uncertain)?;
        }
    }
    Ok(d)
}

fn get<'py>(d: &Bound<'py, PyDict>, key: &str, kind: &str) -> PyResult<Bound<'py, PyAny>> {
    d.get_item(key)?
        .ok_or_else(|| PyValueError::new_err(format!("{kind} payload: missing `{key}`")))
}

fn finite(v: f64, what: &str) -> PyResult<f64> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(PyValueError::new_err(format!("{what} must be finite, got {v}")))
    }
}

fn opt_f64(d: &Bound<'_, PyDict>, key: &str) -> PyResult<Option<f64>> {
    match d.get_item(key)? {
        Some(v) if !v.is_none() => Ok(Some(v.extract::<f64>()?).filter(|x| x.is_finite())),
        _ => Ok(None),
    }
}

/// A payload from a raw dict; every size and value is checked.
pub fn payload_from_py(obj: &Bound<'_, PyAny>) -> PyResult<Payload> {
    let d = obj
        .downcast::<PyDict>()
        .map_err(|_| PyTypeError::new_err("a payload must be a dict with a `kind`"))?;
    let kind: String = get(d, "kind", "a")?.extract()?;
    match kind.as_str() {
        "signals" => {
            let arr: PyReadonlyArray2<'_, f64> = get(d, "data", "signals")?.extract()?;
            let a = arr.as_array();
            let n = a.shape()[1];
            let layout = layout_from_py(&get(d, "layout", "signals")?)?;
            if layout.len() != n {
                return Err(PyValueError::new_err(format!(
                    "signals: `data` has {n} columns (taxels) but the layout has {} taxels",
                    layout.len()
                )));
            }
            let data: Vec<Vec<f64>> = (0..n).map(|t| a.column(t).to_vec()).collect();
            let fs = finite(get(d, "sample_rate_hz", "signals")?.extract()?, "sample_rate_hz")?;
            if fs <= 0.0 {
                return Err(PyValueError::new_err(format!(
                    "sample_rate_hz must be positive, got {fs}"
                )));
            }
            let unit: String = match d.get_item("unit")? {
                Some(u) if !u.is_none() => u.extract()?,
                _ => String::new(),
            };
            Ok(Payload::from(Signals {
                sample_rate_hz: fs,
                layout,
                unit,
                data,
            }))
        }
        "spikes" => {
            let taxel: PyReadonlyArray1<'_, i64> = get(d, "taxel", "spikes")?
                .call_method1("astype", ("int64",))?
                .extract()?;
            let t: PyReadonlyArray1<'_, f64> = get(d, "t_ms", "spikes")?
                .call_method1("astype", ("float64",))?
                .extract()?;
            let (taxel, t) = (taxel.as_array(), t.as_array());
            if taxel.len() != t.len() {
                return Err(PyValueError::new_err(format!(
                    "spikes: {} taxels but {} times",
                    taxel.len(),
                    t.len()
                )));
            }
            let layout = layout_from_py(&get(d, "layout", "spikes")?)?;
            let duration_ms = finite(get(d, "duration_ms", "spikes")?.extract()?, "duration_ms")?;
            if duration_ms < 0.0 {
                // Binned into a 1-frame image without a word.
                return Err(PyValueError::new_err(format!(
                    "spikes: `duration_ms` must be >= 0, got {duration_ms}"
                )));
            }
            let n = layout.len() as i64;
            let mut events = Vec::with_capacity(t.len());
            for (&k, &tm) in taxel.iter().zip(t.iter()) {
                if k < 0 || k >= n {
                    return Err(PyValueError::new_err(format!(
                        "spikes: taxel {k} outside the layout's {n} taxels"
                    )));
                }
                if !(tm.is_finite() && tm >= 0.0 && tm < duration_ms) {
                    return Err(PyValueError::new_err(format!(
                        "spikes: time {tm} ms outside [0, {duration_ms}) ms (the trial's duration)"
                    )));
                }
                events.push(SpikeEvent {
                    taxel: k as u32,
                    t_ms: tm,
                });
            }
            let mut s = SpikeTrain {
                layout,
                duration_ms,
                events,
            };
            if !s.is_sorted() {
                s.sort();
            }
            Ok(Payload::from(s))
        }
        "images" => {
            let arr: PyReadonlyArray2<'_, f64> = get(d, "counts", "images")?.extract()?;
            let a = arr.as_array();
            let (frames, n) = (a.shape()[0], a.shape()[1]);
            let layout = layout_from_py(&get(d, "layout", "images")?)?;
            if layout.len() != n {
                return Err(PyValueError::new_err(format!(
                    "images: `counts` has {n} columns (taxels) but the layout has {} taxels",
                    layout.len()
                )));
            }
            let counts: Vec<f64> = a.iter().copied().collect();
            if let Some(c) = counts.iter().find(|c| !c.is_finite()) {
                return Err(PyValueError::new_err(format!("images: count {c} is not finite")));
            }
            let window_ms = finite(get(d, "window_ms", "images")?.extract()?, "window_ms")?;
            let hop_ms = finite(get(d, "hop_ms", "images")?.extract()?, "hop_ms")?;
            if window_ms <= 0.0 || hop_ms <= 0.0 {
                return Err(PyValueError::new_err(
                    "images: window_ms and hop_ms must be positive",
                ));
            }
            Ok(Payload::from(SpikeImages {
                layout,
                window_ms,
                hop_ms,
                n_frames: frames,
                counts,
            }))
        }
        "estimate" => {
            let angles: PyReadonlyArray1<'_, f64> = get(d, "class_angles", "estimate")?
                .call_method1("astype", ("float64",))?
                .extract()?;
            let scores: PyReadonlyArray1<'_, f64> = get(d, "scores", "estimate")?
                .call_method1("astype", ("float64",))?
                .extract()?;
            if angles.len() != scores.len() {
                return Err(PyValueError::new_err(
                    "estimate: `class_angles` and `scores` differ in length",
                ));
            }
            let scores = angles
                .as_array()
                .iter()
                .zip(scores.as_array().iter())
                .map(|(&a, &s)| ClassScore {
                    angle_deg: a,
                    score: s,
                })
                .collect();
            let best_frame = match d.get_item("best_frame")? {
                Some(v) if !v.is_none() => Some(v.extract::<usize>()?),
                _ => None,
            };
            Ok(Payload::from(Estimate {
                angle_deg: opt_f64(d, "angle_deg")?,
                class_deg: opt_f64(d, "class_deg")?,
                scores,
                best_frame,
                decision_time_ms: opt_f64(d, "decision_time_ms")?,
                uncertain: match d.get_item("uncertain")? {
                    Some(v) if !v.is_none() => v.extract::<bool>()?,
                    _ => false,
                },
            }))
        }
        other => Err(PyValueError::new_err(format!(
            "unknown payload kind `{other}`; expected signals, spikes, images or estimate"
        ))),
    }
}

/// An item from a raw dict: its payload and its `meta` (or neutral metadata).
pub fn item_from_py(obj: &Bound<'_, PyAny>, index: usize) -> PyResult<Item> {
    let payload = payload_from_py(obj)?;
    let meta = match obj.downcast::<PyDict>() {
        Ok(d) => meta_from_py(d.get_item("meta")?.as_ref(), index)?,
        Err(_) => meta_from_py(None, index)?,
    };
    Ok(Item {
        meta: Arc::new(meta),
        payload,
    })
}
