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
