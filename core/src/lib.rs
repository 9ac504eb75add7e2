//! palpate-core: the skeleton every palpate stage plugs into.
//!
//! * [`payload`]: the typed data on the graph's edges (analog signals, spike
//!   events, spike images, orientation estimates) and the trial metadata that
//!   travels with each;
//! * [`stage`]: stage configs (serde + typetag), the runtime roles (source, map,
//!   estimator, sink) and seed derivation;
//! * [`registry`]: every registered stage type with its schema (keys, defaults,
//!   units, docs);
//! * [`graph`]: loading a TOML graph, gathering every error with its line;
//! * [`protocol`]: evaluation protocols (leave-one-trial-out, k-fold,
//!   hold-out, leave-one-condition-out) as train/test folds;
//! * [`runtime`]: running a graph, in parallel and deterministically;
//! * [`sweep`]: running a graph across the values of one key (or several series
//!   of keys), with a cache;
//! * [`shard`]: sweeps beyond one process (points by number, shards,
//!   completion markers, the manifest `palpate merge` reads);
//! * [`stream`]: the streaming forms of per-trial stages (a trial in blocks);
//! * [`output`]: atomic report files.
//!
//! `core` knows no stage by name: stages register themselves, and the CLI finds
//! them through the registry.

pub mod geometry;
pub mod graph;
pub mod input;
pub mod output;
pub mod payload;
pub mod protocol;
pub mod registry;
pub mod runtime;
pub mod shard;
pub mod stage;
pub mod stream;
pub mod sweep;

pub use graph::{
    load_file, load_str, Diagnostic, Graph, LoadErrors, LoadOptions, PlotKind, PlotReference, Protocol,
    RunSettings, Severity, SweepPlot, SweepPoint, SweepSeries, SweepSettings,
};
pub use payload::{
    ClassScore, Estimate, Item, Label, Payload, PayloadKind, Provenance, Signals, SpikeEvent, SpikeImages,
    SpikeTrain, Stimulus, TaxelLayout, TrialMeta,
};
pub use runtime::{
    run, thread_pool, Cache, Progress, RunError, RunOptions, RunResult, StageTiming, INTERRUPTED, MAX_THREADS,
};
pub use stage::{
    check_positive, check_range, derive_seed, fmt_num, BuildContext, ClassMetric, ConfigChecks, ConfigError,
    Estimator, FitContext, InputSpec, Inspection, Map, Model, OutputFacts, Sink, SinkContext, SinkInput,
    SinkReport, Source, Stage, StageConfig, StageError, TrialContext,
};

/// Re-exports used by [`register_stage!`]; not part of the public API.
#[doc(hidden)]
pub mod __private {
    pub use inventory;
    pub use schemars;
    pub use serde_json;
}

/// Where a stage's run-time warnings go (WSS's "taxels all lie on one line"
/// and "no palpation speed", a spike file's unused edges, `simulate_to_dir`'s
/// scene warnings): standard error, unless a host has set a sink
/// ([`set_warning_sink`]; the Python package raises them as Python
/// warnings). The DAQ source's device messages (dropped frames, stalls)
/// still print directly: they are a live session's log, not a result's caveat.
static WARNING_SINK: std::sync::RwLock<Option<fn(&str)>> = std::sync::RwLock::new(None);

/// Reports a run-time warning: to the sink if one is set, else to standard
/// error as it is.
pub fn warn(message: &str) {
    let sink = *WARNING_SINK.read().unwrap_or_else(|e| e.into_inner());
    match sink {
        Some(f) => f(message),
        None => eprintln!("{message}"),
    }
}

/// Sends every later [`warn`] to `sink` instead of standard error.
pub fn set_warning_sink(sink: fn(&str)) {
    *WARNING_SINK.write().unwrap_or_else(|e| e.into_inner()) = Some(sink);
}
