//! `palpate._palpate`: the compiled half of palpate's Python package.
//!
//! Everything here calls the same Rust code the graphs and the CLI run: a
//! graph is loaded by `palpate_core::load_str` and run by `palpate_core::run`;
//! a building block (an encoder, a filter, binning, WSS, a trained baseline) is
//! the registered stage of that type, deserialized from its config exactly as
//! the graph loader does (typetag), built, and called through its `Map`,
//! `Estimator` or `Source` role. So a Python call and a graph run give the same
//! bits.
//!
//! Data cross the boundary as "raw" dicts of NumPy arrays and plain values (see
//! `convert`); the pure-Python half (`palpate/__init__.py`) turns them into
//! the user-facing classes (tonic-convention event arrays among them).
//!
//! Errors: every failure becomes a Python exception of the `PalpateError`
//! family carrying the same message as the CLI, and the file, line, stage and
//! key where there are some. A Rust panic is caught at the boundary and raised
//! as `PalpateError` ("internal error"), never as a crash. Long calls (runs,
//! simulations, building blocks) release the GIL.

mod convert;
mod pystage;
mod run;

use pyo3::prelude::*;

pyo3::create_exception!(
    _palpate,
    PalpateError,
    pyo3::exceptions::PyException,
    "Base class of palpate's errors."
);
pyo3::create_exception!(
    _palpate,
    GraphError,
    PalpateError,
    "A graph did not load: `diagnostics` lists every problem (file, line, stage, key, message)."
);
pyo3::create_exception!(
    _palpate,
    ConfigError,
    PalpateError,
    "A stage's config is wrong: `stage` and `key` name where."
);
pyo3::create_exception!(
    _palpate,
    RunError,
    PalpateError,
    "A stage failed while running: `stage` and `trial` name where."
);

/// Runs `f`, turning a panic into a `PalpateError` (a bug, reported as such)
/// so that no Rust panic crosses into Python.
pub(crate) fn no_panic<T>(what: &str, f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PalpateError::new_err(format!(
                "{what}: internal error (a bug in palpate, please report it): {msg}"
            )))
        }
    }
}

/// Sets attributes on an exception's value.
pub(crate) fn with_attrs(py: Python<'_>, err: PyErr, attrs: &[(&str, Option<String>)]) -> PyErr {
    let v = err.value(py);
    for (k, val) in attrs {
        // Setting an attribute on a fresh exception instance cannot fail in
        // practice; if it did, the message alone still reaches the user.
        let _ = v.setattr(*k, val.clone());
    }
    err
}

/// Warnings the Rust core reported ([`palpate_core::warn`]) since the last
/// [`flushed`]: from any thread (a run's workers), without the GIL.
static PENDING_WARNINGS: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());

fn keep_warning(message: &str) {
    PENDING_WARNINGS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(message.to_string());
}

/// `r`, after raising the core's pending warnings as Python `UserWarning`s
/// (which `warnings` filters, records, and turns into errors: then that
/// error is raised, unless `r` is an error already). Nothing reaches stderr
/// twice: with the sink set, the core prints none of them.
pub(crate) fn flushed<T>(py: Python<'_>, r: PyResult<T>) -> PyResult<T> {
    let pending = std::mem::take(&mut *PENDING_WARNINGS.lock().unwrap_or_else(|e| e.into_inner()));
    let mut raised = Ok(());
    for m in pending {
        let m = m.strip_prefix("warning: ").unwrap_or(&m).replace('\0', " ");
        let msg = std::ffi::CString::new(m).unwrap_or_else(|_| c"palpate warning".into());
        if let Err(e) = PyErr::warn(py, &py.get_type::<pyo3::exceptions::PyUserWarning>(), &msg, 1) {
            raised = Err(e);
            break;
        }
    }
    let v = r?;
    raised.map(|_| v)
}

/// The version of the Rust crates this module was built from.
#[pyfunction]
fn version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

#[pymodule]
fn _palpate(m: &Bound<'_, PyModule>) -> PyResult<()> {
    palpate::link();
    palpate_core::set_warning_sink(keep_warning);
    let py = m.py();
    m.add("PalpateError", py.get_type::<PalpateError>())?;
    m.add("GraphError", py.get_type::<GraphError>())?;
    m.add("ConfigError", py.get_type::<ConfigError>())?;
    m.add("RunError", py.get_type::<RunError>())?;
    // Every attribute the docs declare is there on every instance (None, or
    // an empty `diagnostics`), also on one raised by the Python half or
    // built by hand: the class holds the defaults, a raise sets its own.
    for (ty, names) in [
        (py.get_type::<GraphError>(), &["file", "line", "stage", "key"][..]),
        (py.get_type::<ConfigError>(), &["stage", "key"][..]),
        (py.get_type::<RunError>(), &["file", "stage", "trial", "key"][..]),
    ] {
        for n in names {
            ty.setattr(*n, py.None())?;
        }
    }
    py.get_type::<GraphError>()
        .setattr("diagnostics", pyo3::types::PyTuple::empty(py))?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    m.add_function(wrap_pyfunction!(run::check, m)?)?;
    m.add_function(wrap_pyfunction!(run::run, m)?)?;
    m.add_function(wrap_pyfunction!(run::run_live, m)?)?;
    m.add_function(wrap_pyfunction!(run::stage_types, m)?)?;
    m.add_function(wrap_pyfunction!(run::apply, m)?)?;
    m.add_function(wrap_pyfunction!(run::fit, m)?)?;
    m.add_function(wrap_pyfunction!(run::simulate, m)?)?;
    m.add_function(wrap_pyfunction!(run::read_source, m)?)?;
    m.add_function(wrap_pyfunction!(pystage::register_stage, m)?)?;
    m.add_function(wrap_pyfunction!(pystage::unregister_stage, m)?)?;
    m.add_class::<run::Model>()?;
    Ok(())
}
