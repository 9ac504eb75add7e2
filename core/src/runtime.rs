//! Running a validated graph.
//!
//! The per-trial part of a graph (sources, and the maps and model-based
//! estimators downstream of them before any trained estimator) runs
//! **depth-first**: one trial at a time through the whole chain, trials in
//! parallel on rayon's pool, keeping only the outputs a trained estimator or a
//! sink reads (see `chain`). Peak memory is then O(threads x one trial) plus
//! what trained estimators must hold (spike images) and the estimates, not
//! O(trials x samples) for every stage's output. Trained estimators and sinks,
//! which need every trial of their input, then run one at a time in
//! topological order. A stage's
//! output is computed once and shared by every stage that reads it, then
//! dropped as soon as its last reader is done.
//!
//! With a sweep [`Cache`], outputs are kept for later points (sources and
//! the maps below them trial by trial, see `runtime/items.rs`), and the run
//! is planned backwards from its sinks: each trial of each of those stages
//! is served from the cache, computed, or left out when nothing reads it.
//! A chain the run computes in full and whose outputs no announced run
//! still to come contains runs as without a cache (`chain`), keeping
//! nothing. A chain that later runs share (a sweep of a downstream key,
//! `palpate batch`'s graphs that start with the same trials) runs its
//! sources and maps trial by trial too (`item_chain`), offering the cache
//! what it wants as it goes; the stages below them (WSS, trained
//! estimators, sinks) then take the kept spike images. Either way peak
//! memory is about one run's, not a signal stage's output for every trial:
//! `graphs/paper/table2.toml`'s 5 seeds peaked at 203 MB on the 4 x 4 lab
//! scene and 576 MB on an 8 x 8 array (one run: 173 / 485 MB), and a
//! two-point sweep of a WSS key on the quickstart at 156 MB (4 x 4) and
//! 542 MB (8 x 8), where running shared chains stage at a time held 1.15 GB
//! and 7.2 GB (`/usr/bin/time -f %M`; tests/sweep_memory.rs checks the
//! bound).
//!
//! Determinism: every per-trial computation is a pure function of (config, input,
//! seed), seeds come from [`derive_seed`] over (graph seed, stage id, trial id or
//! fold), and results are gathered in trial order, so 1 and N threads give the
//! same bits. When several trials fail, the first in trial order is reported.
//!
//! Estimators run under the evaluation protocol: a model-based estimator fits
//! once on nothing and estimates every trial; a trained one, under
//! leave-one-trial-out, fits once per distinct `group` (fold `f` holds out the
//! `f`-th group of every class) and estimates only that fold's held-out trials.

use crate::graph::Graph;
use crate::payload::{Item, Payload, Provenance, TrialMeta};
use crate::protocol::folds;
use crate::stage::{
    derive_seed, settings_json, FitContext, SinkContext, SinkInput, SinkReport, Stage, TrialContext,
};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

mod chain;
mod item_chain;
mod items;

/// Receives progress while a graph runs (the CLI draws a bar with it).
pub trait Progress: Sync {
    /// A stage starts `total` units of work (trials, or folds).
    fn start(&self, stage: &str, total: usize);
    /// One unit of work is done.
    fn tick(&self);
    /// The stage is done.
    fn finish(&self, stage: &str);
    /// Whether the run should stop (a user's Ctrl-C): checked before each
    /// stage's work on each trial and before each fold's fit; the run then
    /// fails with a [`RunError`] whose message is [`INTERRUPTED`]. Default:
    /// never.
    fn cancelled(&self) -> bool {
        false
    }
}

/// The message of a run stopped by its [`Progress::cancelled`].
pub const INTERRUPTED: &str = "interrupted";

/// `Err` (naming stage `id`) once the run's progress says it is cancelled.
pub(crate) fn interrupted(opts: &RunOptions<'_>, id: &str) -> Result<(), RunError> {
    match opts.progress {
        Some(p) if p.cancelled() => Err(RunError::new(id, None, INTERRUPTED)),
        _ => Ok(()),
    }
}

/// Outputs kept across runs (the points of a sweep), keyed by a hash of each
/// stage's id, type, settings, seed and its inputs' keys: a stage whose config and
/// inputs did not change is not run again. Sinks always run. Valid for graphs
/// loaded from the same directory (relative paths in settings are not resolved
/// into the key).
///
/// A run under a cache is planned backwards from its sinks before anything
/// runs: a stage is computed only when a stage that must be computed reads it,
/// so once a downstream output is cached (an encoder's spikes), the stages
/// upstream of it (the scene, the filters) are neither computed nor fetched.
/// Sweeping a downstream key then simulates each seed's scene once, however
/// little of the scene's output fits in the cache.
///
/// Each output is kept with the [`StageTiming`] of the run that computed it, so
/// a run served from the cache still reports what the stage costs (marked
/// `cached`): a sweep's compute-time figures then do not depend on which point
/// happened to compute a shared stage first. A stage's timing (a few kB) is
/// kept beyond its output, so a stage skipped because its readers were cached
/// still reports its cost; under a sweep's announcements it is dropped with
/// the last run that needs it, so a long sweep's timings do not pile up
/// (without announcements they are kept for the cache's life).
///
/// The cache holds at most [`Cache::budget_bytes`] of payload data (default
/// [`DEFAULT_CACHE_BYTES`]), and an output larger than the whole budget is not
/// kept. When a new output would pass the budget, outputs are dropped by
/// GreedyDual-Size (Cao & Irani, 1997): each entry's priority is
/// `H = L + cost / bytes`, where `cost` is the wall time of the stage and all
/// its upstream stages (what dropping it may cost again) and `L` is the
/// priority of the last entry dropped (so entries not used for a while age
/// out); the lowest `H` goes first, ties to the least recently used.
/// Sources and the maps below them are kept one trial at a time, each trial
/// under its own key (`runtime/items.rs`): a sweep that changes one condition of a
/// scene (`graphs/shift/shift.toml` shifts its `test` condition and leaves
/// `train` alone) computes only that condition's trials at each point, and
/// the other's are served from the first point that computed them. A
/// computed trial no announced run will read is not kept (its readers'
/// trials will be served instead): under a sweep that leaves a chain of
/// signal stages alone, only the chain's last output is kept.
///
/// A sweep also tells the cache, before it starts, which runs will need
/// which outputs ([`Cache::expect`]): an output no later run needs is not
/// kept, and one whose last run has used it is dropped, so the budget goes
/// to what will be read again (the 14 points of an array-area sweep need a
/// seed's spike trains 14 times and each point's binned images once). Plain
/// least-recently-used eviction thrashed: a scene and three filters of
/// 600 MB each pushed out the 4 MB spike trains computed from them, so every
/// point re-simulated its scene. A sweep whose points share nothing (each
/// changes its scene, or draws new seeds) still runs in bounded memory
/// instead of keeping every point's signals to the end (a 6-point x 5-seed
/// sweep of 340-trial scenes reached 22 GB before this bound).
pub struct Cache {
    map: std::sync::Mutex<CacheMap>,
    hits: std::sync::atomic::AtomicUsize,
    misses: std::sync::atomic::AtomicUsize,
    budget: usize,
}

/// Most payload bytes a [`Cache`] keeps by default: 2 GiB.
pub const DEFAULT_CACHE_BYTES: usize = 2 << 30;

/// What an entry keeps: a stage's whole output, or one trial's payload of
/// an item-level stage (see [`items`]).
enum Held {
    Stage(Arc<Vec<Item>>),
    Item(Payload),
}

/// One kept output.
struct Entry {
    held: Held,
    bytes: usize,
    /// Seconds to recompute it (its stage and everything upstream).
    cost: f64,
    /// GreedyDual-Size priority.
    h: f64,
    /// Last use, for ties.
    used: u64,
}

#[derive(Default)]
struct CacheMap {
    entries: HashMap<u64, Entry>,
    timings: HashMap<u64, StageTiming>,
    /// Each computed trial's time by item key, kept beyond its payload like
    /// `timings` (16 bytes a trial).
    item_times: HashMap<u64, Duration>,
    bytes: usize,
    clock: u64,
    /// GreedyDual-Size's inflation value `L`.
    floor: f64,
    /// Runs still to come that contain each key, for keys announced by
    /// [`Cache::expect`].
    future: HashMap<u64, usize>,
    /// Per trained estimator family (its type, settings, id and the graph's
    /// seed): runs announced in all, and runs still to come.
    families: HashMap<u64, (usize, usize)>,
    /// Fitted models by fit key (family, fold seed, training items'
    /// contents): the model, its fit time, its family.
    models: HashMap<u64, (Arc<dyn crate::stage::Model>, Duration, u64)>,
}

/// GreedyDual-Size priority `H = L + cost / bytes`.
fn priority(floor: f64, cost: f64, bytes: usize) -> f64 {
    floor + cost / bytes.max(1) as f64
}

impl Default for Cache {
    fn default() -> Self {
        Cache::with_budget(DEFAULT_CACHE_BYTES)
    }
}

/// A cached output with the timing of the run that computed it.
type Cached = (Arc<Vec<Item>>, StageTiming);

impl Cache {
    /// A cache keeping at most `bytes` of payload data.
    pub fn with_budget(bytes: usize) -> Self {
        Cache {
            map: std::sync::Mutex::new(CacheMap::default()),
            hits: Default::default(),
            misses: Default::default(),
            budget: bytes,
        }
    }
    /// The most payload bytes this cache keeps.
    pub fn budget_bytes(&self) -> usize {
        self.budget
    }
    /// Payload bytes held now.
    pub fn held_bytes(&self) -> usize {
        self.map.lock().map_or(0, |m| m.bytes)
    }
    /// Stage runs served from the cache.
    pub fn hits(&self) -> usize {
        self.hits.load(std::sync::atomic::Ordering::Relaxed)
    }
    /// Stage outputs looked up and not found (each was then computed).
    pub fn misses(&self) -> usize {
        self.misses.load(std::sync::atomic::Ordering::Relaxed)
    }
    fn get(&self, key: u64) -> Option<Cached> {
        let hit = {
            let mut m = self.map.lock().ok()?;
            m.clock += 1;
            let (now, floor) = (m.clock, m.floor);
            let timing = m.timings.get(&key).cloned();
            m.entries.get_mut(&key).and_then(|e| {
                let Held::Stage(items) = &e.held else {
                    return None;
                };
                e.used = now;
                e.h = priority(floor, e.cost, e.bytes);
                Some((items.clone(), timing?))
            })
        };
        let counter = if hit.is_some() { &self.hits } else { &self.misses };
        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        hit
    }
    /// Announces a run of `graph` to come: outputs it shares with earlier
    /// runs are kept for it, and outputs no announced run still needs are
    /// dropped. Without announcements every output may be reused and the
    /// budget alone bounds the cache.
    pub fn expect(&self, graph: &Graph) {
        let keys = stage_keys(graph);
        // A graph whose trials cannot be listed fails when it runs; its
        // trials are then not announced (the budget alone bounds them).
        let plans = items::plans(graph, &keys, &key_context(graph)).unwrap_or_default();
        if let Ok(mut m) = self.map.lock() {
            for (i, k) in keys.into_iter().enumerate() {
                if !always_runs(&graph.nodes[i].stage) {
                    *m.future.entry(k).or_default() += 1;
                }
            }
            for p in plans.iter().flatten() {
                for &k in &p.keys {
                    *m.future.entry(k).or_default() += 1;
                }
            }
            for f in fit_families(graph).into_iter().flatten() {
                let e = m.families.entry(f).or_default();
                e.0 += 1;
                e.1 += 1;
            }
        }
    }
    /// A run of these keys and estimator families has started (its hits are
    /// already fetched): one run fewer needs each, and an output no announced
    /// run needs any more is dropped.
    fn started(&self, keys: &[u64], families: &[u64]) {
        let Ok(mut m) = self.map.lock() else {
            return;
        };
        for k in keys {
            if let Some(left) = m.future.get_mut(k) {
                *left = left.saturating_sub(1);
                if *left == 0 {
                    if let Some(e) = m.entries.remove(k) {
                        m.bytes -= e.bytes;
                    }
                    m.timings.remove(k);
                    m.item_times.remove(k);
                }
            }
        }
        for f in families {
            if let Some((_, left)) = m.families.get_mut(f) {
                *left = left.saturating_sub(1);
            }
        }
    }
    /// A run of these estimator families has ended: the models of a family
    /// no announced run still has are dropped (not at the run's start: its
    /// folds look them up as they go).
    fn finished(&self, families: &[u64]) {
        if let Ok(mut m) = self.map.lock() {
            for f in families {
                if m.families.get(f).is_some_and(|&(_, left)| left == 0) {
                    m.models.retain(|_, (_, _, fam)| fam != f);
                }
            }
        }
    }
    /// Whether runs announced to this cache share the estimator family `f`
    /// (only then are its models looked up and kept).
    fn shares_fits(&self, f: u64) -> bool {
        self.map
            .lock()
            .is_ok_and(|m| m.families.get(&f).is_some_and(|&(all, _)| all > 1))
    }
    fn model(&self, key: u64) -> Option<(Arc<dyn crate::stage::Model>, Duration)> {
        let m = self.map.lock().ok()?;
        m.models.get(&key).map(|(model, t, _)| (model.clone(), *t))
    }
    /// Keeps a fitted model while a later announced run has its family.
    fn put_model(&self, key: u64, family: u64, model: Arc<dyn crate::stage::Model>, fit: Duration) {
        if let Ok(mut m) = self.map.lock() {
            if m.families.get(&family).is_some_and(|&(_, left)| left > 0) {
                m.models.insert(key, (model, fit, family));
            }
        }
    }
    /// The timing of the run that computed `key`'s output, kept even after
    /// the output itself was dropped.
    fn timing(&self, key: u64) -> Option<StageTiming> {
        self.map.lock().ok()?.timings.get(&key).cloned()
    }
    /// Keeps `items` under `key`; `cost` is what recomputing them would take.
    fn put(&self, key: u64, items: Arc<Vec<Item>>, timing: StageTiming, cost: Duration) {
        let size: usize = items.iter().map(|it| it.payload.approx_bytes()).sum();
        let Ok(mut m) = self.map.lock() else {
            return;
        };
        if m.future.get(&key) == Some(&0) {
            // No announced run needs this output (or its timing) again.
            return;
        }
        m.timings.insert(key, timing);
        if size > self.budget {
            return;
        }
        if let Some(old) = m.entries.remove(&key) {
            m.bytes -= old.bytes;
        }
        let mut victims = Victims::default();
        if victims.make_room(&mut m, size, self.budget) {
            m.insert(key, Held::Stage(items), size, cost);
        }
    }

    /// Looks up, where `look` is set, the trials of an item-level stage: each
    /// hit's payload and the time computing it took.
    fn get_items(&self, keys: &[u64], look: &[bool]) -> Vec<Option<(Payload, Duration)>> {
        let Ok(mut m) = self.map.lock() else {
            return vec![None; keys.len()];
        };
        let m = &mut *m;
        let floor = m.floor;
        keys.iter()
            .zip(look)
            .map(|(k, &look)| {
                if !look {
                    return None;
                }
                let dt = *m.item_times.get(k)?;
                let e = m.entries.get_mut(k)?;
                let Held::Item(p) = &e.held else {
                    return None;
                };
                m.clock += 1;
                e.used = m.clock;
                e.h = priority(floor, e.cost, e.bytes);
                Some((p.clone(), dt))
            })
            .collect()
    }
    /// The time each trial took when it was computed, where known.
    fn item_times(&self, keys: &[u64]) -> Vec<Option<Duration>> {
        match self.map.lock() {
            Ok(m) => keys.iter().map(|k| m.item_times.get(k).copied()).collect(),
            Err(_) => vec![None; keys.len()],
        }
    }
    /// Keeps computed trials of an item-level stage: `(key, payload, its
    /// time, the time to recompute it with everything upstream)`. Trials no
    /// announced run needs are not kept; room is made by GreedyDual-Size as
    /// in [`Cache::put`], never by dropping a trial of the same batch.
    /// A `None` payload keeps the time alone.
    fn put_items(&self, batch: Vec<(u64, Option<Payload>, Duration, Duration)>) {
        let Ok(mut m) = self.map.lock() else {
            return;
        };
        let mut victims = Victims::default();
        for (key, payload, dt, cost) in batch {
            if m.future.get(&key) == Some(&0) {
                continue;
            }
            m.item_times.insert(key, dt);
            let Some(payload) = payload else {
                continue;
            };
            let size = payload.approx_bytes();
            if size > self.budget {
                continue;
            }
            if let Some(old) = m.entries.remove(&key) {
                m.bytes -= old.bytes;
            }
            if victims.make_room(&mut m, size, self.budget) {
                m.insert(key, Held::Item(payload), size, cost);
            }
        }
    }
    /// Whether some announced run still to come contains one of `keys` (a
    /// key never announced counts as needed: without announcements any
    /// output may be reused).
    fn needed_later(&self, keys: &[u64]) -> bool {
        let Ok(m) = self.map.lock() else {
            return true;
        };
        keys.iter().any(|k| m.future.get(k) != Some(&0))
    }
    /// For each trial of an item-level stage (`own` keys), whether every
    /// announced run still to come that has it also has the same trial of
    /// each of the stage's readers (`readers`, item-level, by reader): then
    /// no later run reads it (the readers' trials are served instead), and
    /// keeping it only crowds out what will be read. A scene's signals under
    /// a sweep that shifts a downstream key are read again; under one that
    /// leaves the whole chain alone, only the last per-trial output is.
    fn covered(&self, own: &[u64], readers: &[&[u64]]) -> Vec<bool> {
        let Ok(m) = self.map.lock() else {
            return vec![false; own.len()];
        };
        own.iter()
            .enumerate()
            .map(|(t, k)| {
                let Some(left) = m.future.get(k) else {
                    return false;
                };
                !readers.is_empty()
                    && readers
                        .iter()
                        .all(|r| r.get(t).is_some_and(|rk| m.future.get(rk) == Some(left)))
            })
            .collect()
    }
    /// Keeps the timing of an item-level stage computed in full (a later run
    /// served wholly from trials reports it).
    fn put_timing(&self, key: u64, timing: StageTiming) {
        if let Ok(mut m) = self.map.lock() {
            if m.future.get(&key) != Some(&0) {
                m.timings.insert(key, timing);
            }
        }
    }
    /// Counts a stage served from the cache (`hit`) or computed.
    fn count(&self, hit: bool) {
        let counter = if hit { &self.hits } else { &self.misses };
        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }
}

impl CacheMap {
    /// Inserts an entry (room already made).
    fn insert(&mut self, key: u64, held: Held, bytes: usize, cost: Duration) {
        self.clock += 1;
        let cost = cost.as_secs_f64();
        let entry = Entry {
            held,
            bytes,
            cost,
            h: priority(self.floor, cost, bytes),
            used: self.clock,
        };
        self.entries.insert(key, entry);
        self.bytes += bytes;
    }
}

/// Eviction candidates, lowest GreedyDual-Size priority first (ties to the
/// least recently used), listed once per batch of insertions: entries
/// inserted after the listing are not candidates.
#[derive(Default)]
struct Victims {
    order: Option<std::vec::IntoIter<u64>>,
    /// The cache's clock at the listing: an entry used or inserted since is
    /// spared.
    listed_at: u64,
}

impl Victims {
    /// Drops entries until `size` more bytes fit in `budget`; false when
    /// they cannot (no candidate left).
    fn make_room(&mut self, m: &mut CacheMap, size: usize, budget: usize) -> bool {
        while m.bytes + size > budget {
            if self.order.is_none() {
                self.listed_at = m.clock;
            }
            let order = self.order.get_or_insert_with(|| {
                let mut v: Vec<(f64, u64, u64)> = m.entries.iter().map(|(&k, e)| (e.h, e.used, k)).collect();
                v.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                v.into_iter().map(|(.., k)| k).collect::<Vec<_>>().into_iter()
            });
            let Some(victim) = order.next() else {
                return false;
            };
            if m.entries.get(&victim).is_some_and(|e| e.used > self.listed_at) {
                continue;
            }
            if let Some(e) = m.entries.remove(&victim) {
                m.bytes -= e.bytes;
                m.floor = m.floor.max(e.h);
            }
        }
        true
    }
}

/// Options for [`run`].
#[derive(Default)]
pub struct RunOptions<'a> {
    /// Progress receiver.
    pub progress: Option<&'a dyn Progress>,
    /// Outputs shared across runs (sweeps); `None` computes everything.
    pub cache: Option<&'a Cache>,
    /// Keep every stage's output in the result (tests and tools use it);
    /// otherwise outputs are dropped once read.
    pub keep_outputs: bool,
}

/// Wall time a stage spent.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageTiming {
    /// The stage's id.
    pub id: String,
    /// Its type.
    pub type_name: String,
    /// Its role (source, map, estimator, sink).
    pub role: &'static str,
    /// Per trial the stage ran on, in trial order: producing, processing or
    /// predicting it (under a hold-out or train/test protocol an estimator
    /// runs on the held-out trials only).
    pub per_trial: Vec<Duration>,
    /// Per fold: fitting (trained estimators), or the single fit of a model-based one.
    pub fits: Vec<Duration>,
    /// Wall time of the whole stage.
    pub total: Duration,
    /// True when the output came from the sweep cache: nothing was computed in
    /// this run, and the times above are those of the run that computed it.
    pub cached: bool,
}

/// What a run produced.
#[derive(Debug, Default)]
pub struct RunResult {
    /// Each sink's report, in execution order.
    pub reports: Vec<(String, SinkReport)>,
    /// Each stage's timing, in execution order.
    pub timings: Vec<StageTiming>,
    /// Every stage's output, when [`RunOptions::keep_outputs`] was set.
    pub outputs: HashMap<String, Arc<Vec<Item>>>,
}

/// A failure while running, naming the stage and (where there is one) the trial.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("stage `{stage}`{}: {message}", trial.as_ref().map(|t| format!(", trial `{t}`")).unwrap_or_default())]
pub struct RunError {
    /// The failing stage.
    pub stage: String,
    /// The failing trial, if the failure is per trial.
    pub trial: Option<String>,
    /// What went wrong.
    pub message: String,
}

impl RunError {
    fn new(stage: &str, trial: Option<&str>, message: impl Into<String>) -> Self {
        RunError {
            stage: stage.to_string(),
            trial: trial.map(str::to_string),
            message: message.into(),
        }
    }
}

type Timed<T> = (T, Duration);
/// A fold's fit time and its (trial index, estimate, predict time) list.
type FoldOutcome = Result<(Duration, Vec<(usize, Timed<Item>)>), RunError>;

fn timed<T>(f: impl FnOnce() -> T) -> Timed<T> {
    let t0 = Instant::now();
    let v = f();
    (v, t0.elapsed())
}

/// Most worker threads one pool starts (`palpate run --threads`, a batch's
/// threads per job, Python's `run(threads=)`): far above any machine's core
/// count, so that a mistyped count (an extra digit or two) is an error
/// rather than a pool of billions of threads that never finishes starting.
pub const MAX_THREADS: usize = 4096;

/// A pool of `threads` worker threads (0: one per core), or an error naming
/// `what` (the flag or argument) when the count is over [`MAX_THREADS`] or
/// the threads cannot be started.
pub fn thread_pool(threads: usize, what: &str) -> Result<rayon::ThreadPool, String> {
    if threads > MAX_THREADS {
        return Err(format!(
            "{what} {threads} is over the cap of {MAX_THREADS} worker threads (0 or none: one per core)"
        ));
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| format!("cannot start {threads} worker threads ({what}): {e}"))
}

/// Runs a graph to the end.
pub fn run(graph: &Graph, opts: &RunOptions<'_>) -> Result<RunResult, RunError> {
    let n = graph.nodes.len();
    let mut readers = vec![0usize; n];
    for inputs in &graph.input_index {
        for &j in inputs {
            readers[j] += 1;
        }
    }
    let mut outputs: Vec<Option<Arc<Vec<Item>>>> = vec![None; n];
    let mut result = RunResult::default();
    let seed = graph.run.seed;
    let mut keys = vec![0u64; n];
    // Depth-first per-trial chains (under a sweep cache only those no other
    // run shares, below): their kept outputs and timings, by node.
    let mut depth_first: Vec<Option<StageTiming>> = vec![None; n];
    if opts.cache.is_none() {
        let keep = chain::kept(graph, opts.keep_outputs);
        for c in chain::chains(graph) {
            let out = chain::run_chain(graph, &c, &keep, opts)?;
            for ((&i, items), timing) in c.nodes.iter().zip(out.items).zip(out.timings) {
                outputs[i] = items.map(Arc::new);
                depth_first[i] = Some(timing);
            }
        }
    }

    // Under a cache: every stage's key (its config and its inputs' keys, no
    // data), then the plan, backwards from the sinks.
    let mut hit: Vec<Option<Cached>> = vec![None; n];
    let mut skipped: Vec<Option<StageTiming>> = vec![None; n];
    let mut families: Vec<Option<u64>> = vec![None; n];
    // Item-level stages under a cache: each trial's hit, its known time and
    // whether it is computed (the plan's), then what running them gave.
    let mut item_hits: Vec<Vec<Option<(Payload, Duration)>>> = vec![Vec::new(); n];
    let mut item_times: Vec<Vec<Option<Duration>>> = vec![Vec::new(); n];
    let mut compute: Vec<Vec<bool>> = vec![Vec::new(); n];
    let mut item_done: Vec<Option<item_chain::ItemDone>> = (0..n).map(|_| None).collect();
    if let Some(c) = opts.cache {
        keys = stage_keys(graph);
        let item_plans = items::plans(graph, &keys, &key_context(graph))?;
        plan(
            graph,
            c,
            &keys,
            &item_plans,
            opts.keep_outputs,
            &mut hit,
            &mut skipped,
            &mut item_hits,
            &mut item_times,
            &mut compute,
        );
        let mut cacheable: Vec<u64> = (0..n)
            .filter(|&i| !always_runs(&graph.nodes[i].stage))
            .map(|i| keys[i])
            .collect();
        for p in item_plans.iter().flatten() {
            cacheable.extend_from_slice(&p.keys);
        }
        families = fit_families(graph);
        let own: Vec<u64> = families.iter().flatten().copied().collect();
        c.started(&cacheable, &own);
        // A chain this run computes in full and no later run shares runs
        // as without a cache (its model-based estimators inside it, each
        // trial's estimate made while its images are warm), offering the
        // cache nothing: nothing would read it.
        let keep = chain::kept(graph, opts.keep_outputs);
        for ch in chain::chains(graph) {
            let unshared = ch.nodes.iter().all(|&i| match &item_plans[i] {
                Some(p) => {
                    compute[i].len() == p.keys.len()
                        && compute[i].iter().all(|&x| x)
                        && !c.needed_later(&p.keys)
                        && !c.needed_later(&[p.stage_key])
                }
                None => hit[i].is_none() && skipped[i].is_none() && !c.needed_later(&[keys[i]]),
            });
            if !unshared {
                continue;
            }
            let out = chain::run_chain(graph, &ch, &keep, opts)?;
            for ((&i, items), timing) in ch.nodes.iter().zip(out.items).zip(out.timings) {
                outputs[i] = items.map(Arc::new);
                depth_first[i] = Some(timing);
            }
        }
        // The other item-level stages: trial by trial through each
        // connected component, as the plan says (served, computed or left
        // out), keeping for the cache what it wants (`item_chain`).
        let member: Vec<bool> = (0..n)
            .map(|i| item_plans[i].is_some() && depth_first[i].is_none())
            .collect();
        let mut metas_of: Vec<Option<Arc<Vec<Arc<TrialMeta>>>>> = vec![None; n];
        for comp in chain::components(graph, &member) {
            let mut nodes = Vec::with_capacity(comp.nodes.len());
            for &i in &comp.nodes {
                let (Some(p), node) = (&item_plans[i], &graph.nodes[i]) else {
                    continue;
                };
                let id = node.id.as_str();
                let prov = Provenance {
                    stage: node.id.clone(),
                    type_name: node.type_name.clone(),
                    settings: settings_json(node.config.as_ref()),
                };
                let with_stage = |m: &TrialMeta| meta_with(m, &prov);
                // A source's trials as listed, or the first input's metadata.
                let metas: Arc<Vec<Arc<TrialMeta>>> = Arc::new(match &node.stage {
                    Stage::Source(_) => p.listed.iter().map(&with_stage).collect(),
                    _ => graph.input_index[i]
                        .first()
                        .and_then(|&j| metas_of[j].as_ref())
                        .ok_or_else(|| {
                            RunError::new(id, None, "an input has no trials (internal planning error)")
                        })?
                        .iter()
                        .map(|m| with_stage(m))
                        .collect(),
                });
                metas_of[i] = Some(metas.clone());
                let reader_nodes: Vec<usize> =
                    (0..n).filter(|&j| graph.input_index[j].contains(&i)).collect();
                // The same trials of the stages reading this one, when all are item-level.
                let readers: Vec<&[u64]> = reader_nodes
                    .iter()
                    .map(|&j| item_plans[j].as_ref().map(|r| r.keys.as_slice()))
                    .collect::<Option<_>>()
                    .unwrap_or_default();
                let keep = opts.keep_outputs || reader_nodes.iter().any(|&j| !member[j]);
                nodes.push(item_chain::ItemNode {
                    node: i,
                    plan: p,
                    metas,
                    hits: std::mem::take(&mut item_hits[i]),
                    known: std::mem::take(&mut item_times[i]),
                    stored: skipped[i].take(),
                    compute: std::mem::take(&mut compute[i]),
                    readers,
                    keep,
                });
            }
            let done = item_chain::run_component(graph, nodes, c, opts)?;
            for (&i, d) in comp.nodes.iter().zip(done) {
                item_done[i] = Some(d);
            }
        }
    }
    // Content keys of an estimator input's items, computed once per run for
    // every estimator that may reuse a model (by input node).
    let mut content: HashMap<usize, Arc<Vec<u64>>> = HashMap::new();
    // Seconds to recompute each stage with everything upstream (the cache's
    // eviction weighs it against the bytes kept).
    let mut upstream_cost = vec![Duration::ZERO; n];

    for &i in &graph.order {
        let node = &graph.nodes[i];
        let id = node.id.as_str();
        let inputs_cost: Duration = graph.input_index[i].iter().map(|&j| upstream_cost[j]).sum();
        if let Some(timing) = depth_first[i].take() {
            upstream_cost[i] = inputs_cost + timing.total;
            if let (true, Some(items)) = (opts.keep_outputs, &outputs[i]) {
                result.outputs.insert(node.id.clone(), items.clone());
            }
            result.timings.push(timing);
            release_inputs(graph, i, &mut readers, &mut outputs);
            continue;
        }
        if let Some(done) = item_done[i].take() {
            upstream_cost[i] = inputs_cost + done.timing.total;
            if let Some(items) = done.items.filter(|v| v.iter().all(Option::is_some)) {
                let full: Arc<Vec<Item>> = Arc::new(items.into_iter().flatten().collect());
                if opts.keep_outputs {
                    result.outputs.insert(node.id.clone(), full.clone());
                }
                outputs[i] = Some(full);
            }
            result.timings.push(done.timing);
            release_inputs(graph, i, &mut readers, &mut outputs);
            continue;
        }
        let prov = Provenance {
            stage: node.id.clone(),
            type_name: node.type_name.clone(),
            settings: settings_json(node.config.as_ref()),
        };
        // Served from the cache: its output (a hit), or only its timing (a
        // stage whose readers were all hits).
        let served = hit[i]
            .take()
            .map(|(items, t)| (Some(items), t))
            .or_else(|| skipped[i].take().map(|t| (None, t)));
        if let Some((items, computed)) = served {
            upstream_cost[i] = inputs_cost + computed.total;
            result.timings.push(StageTiming {
                id: node.id.clone(),
                type_name: node.type_name.clone(),
                role: node.stage.role(),
                cached: true,
                ..computed
            });
            if let (true, Some(items)) = (opts.keep_outputs, &items) {
                result.outputs.insert(node.id.clone(), items.clone());
            }
            outputs[i] = items;
            release_inputs(graph, i, &mut readers, &mut outputs);
            continue;
        }
        let inputs: Vec<Arc<Vec<Item>>> = graph.input_index[i]
            .iter()
            .map(|&j| {
                outputs[j].clone().ok_or_else(|| {
                    RunError::new(
                        id,
                        None,
                        format!(
                            "input `{}` has no output (internal ordering error)",
                            graph.nodes[j].id
                        ),
                    )
                })
            })
            .collect::<Result<_, _>>()?;
        let mut timing = StageTiming {
            id: node.id.clone(),
            type_name: node.type_name.clone(),
            role: node.stage.role(),
            ..StageTiming::default()
        };
        let t_stage = Instant::now();
        let produced: Option<Vec<Item>> = match &node.stage {
            Stage::Source(src) => {
                let mut metas = src.trials().map_err(|e| RunError::new(id, None, e.message))?;
                for (k, m) in metas.iter_mut().enumerate() {
                    m.index = k;
                }
                check_unique_ids(id, &metas)?;
                start(opts, id, metas.len());
                let done: Vec<Result<Timed<Item>, RunError>> = metas
                    .into_par_iter()
                    .map(|meta| {
                        interrupted(opts, id)?;
                        let ctx = TrialContext {
                            stage_id: id,
                            meta: &meta,
                            seed: derive_seed(seed, &[id, &meta.trial_id]),
                        };
                        let (payload, dt) = timed(|| src.produce(&ctx));
                        tick(opts);
                        let payload =
                            payload.map_err(|e| RunError::new(id, Some(&meta.trial_id), e.message))?;
                        Ok((with_provenance(&meta, &prov, payload), dt))
                    })
                    .collect();
                Some(unzip_timed(done, &mut timing.per_trial)?)
            }
            Stage::Map(map) => {
                let trials = aligned_len(id, graph, i, &inputs)?;
                start(opts, id, trials);
                let done: Vec<Result<Timed<Item>, RunError>> = (0..trials)
                    .into_par_iter()
                    .map(|t| {
                        interrupted(opts, id)?;
                        let items: Vec<&Item> = inputs.iter().map(|v| &v[t]).collect();
                        let meta = &items[0].meta;
                        let ctx = TrialContext {
                            stage_id: id,
                            meta,
                            seed: derive_seed(seed, &[id, &meta.trial_id]),
                        };
                        let (payload, dt) = timed(|| map.process(&items, &ctx));
                        tick(opts);
                        let payload =
                            payload.map_err(|e| RunError::new(id, Some(&meta.trial_id), e.message))?;
                        Ok((with_provenance(meta, &prov, payload), dt))
                    })
                    .collect();
                Some(unzip_timed(done, &mut timing.per_trial)?)
            }
            Stage::Estimator(est) => {
                let items = &inputs[0];
                let folds = folds(est.trained(), &graph.run.protocol, items)
                    .map_err(|e| RunError::new(id, None, e))?;
                // A hold-out or train/test split is one fold by design; every
                // other protocol needs two.
                let hold_out = graph.run.protocol.scores_a_subset();
                if est.trained() && folds.len() < 2 && !hold_out {
                    let why = match &graph.run.protocol {
                        crate::Protocol::LeaveOneConditionOut { key } => format!(
                            "protocol leave_one_condition_out needs at least two values of `{key}` (one to test, the rest to train on), and every trial has the same one"
                        ),
                        _ => "a trained estimator needs at least two repetitions (groups) of its classes for leave-one-trial-out".to_string(),
                    };
                    return Err(RunError::new(id, None, why));
                }
                // Progress counts folds, each a fit plus its test trials: a
                // fit dominates a fold's time, so counting trials (ticked
                // only after each fit) made the first ETA many times too long.
                start(opts, id, folds.len());
                // Under a sweep whose runs share this estimator: a model
                // fitted on the same training items (by content) with the
                // same fold seed is reused, reporting the fit time of the run
                // that fitted it.
                let reuse = match (opts.cache, families[i]) {
                    (Some(c), Some(f)) if c.shares_fits(f) => {
                        let j = graph.input_index[i][0];
                        let keys = content
                            .entry(j)
                            .or_insert_with(|| Arc::new(items.par_iter().map(Item::content_key).collect()))
                            .clone();
                        Some((c, f, keys))
                    }
                    _ => None,
                };
                // Only the trials a fold tests are timed: under a hold-out the
                // others are not estimated, and a zero for each of them made
                // the median and the estimates per second wrong.
                let mut per_trial: Vec<Option<Duration>> = vec![None; items.len()];
                let mut estimates: Vec<Option<Item>> = vec![None; items.len()];
                let fold_results: Vec<FoldOutcome> = folds
                    .par_iter()
                    .enumerate()
                    .map(|(f, (train, test))| {
                        interrupted(opts, id)?;
                        let fold_name = format!("fold{f}");
                        let fctx = FitContext {
                            stage_id: id,
                            fold: f,
                            seed: derive_seed(seed, &[id, &fold_name]),
                        };
                        let fit_key = reuse.as_ref().map(|(_, family, keys)| {
                            use std::hash::Hasher;
                            let mut h = std::hash::DefaultHasher::new();
                            h.write_u64(*family);
                            h.write_u64(fctx.seed);
                            for &t in train.iter() {
                                h.write_u64(keys[t]);
                            }
                            h.finish()
                        });
                        let reused = reuse.as_ref().zip(fit_key).and_then(|((c, ..), k)| c.model(k));
                        let (model, fit_time) = match reused {
                            Some(m) => m,
                            None => {
                                let train_items: Vec<&Item> = train.iter().map(|&t| &items[t]).collect();
                                let (model, fit_time) = timed(|| est.fit(&train_items, &fctx));
                                let model: Arc<dyn crate::stage::Model> = Arc::from(model.map_err(|e| {
                                    RunError::new(id, None, format!("fitting fold {f}: {}", e.message))
                                })?);
                                if let (Some((c, family, _)), Some(k)) = (&reuse, fit_key) {
                                    c.put_model(k, *family, model.clone(), fit_time);
                                }
                                (model, fit_time)
                            }
                        };
                        let preds: Vec<Result<(usize, Timed<Item>), RunError>> = test
                            .par_iter()
                            .map(|&t| {
                                let item = &items[t];
                                let ctx = TrialContext {
                                    stage_id: id,
                                    meta: &item.meta,
                                    seed: derive_seed(seed, &[id, &item.meta.trial_id]),
                                };
                                let (est, dt) = timed(|| model.predict(item, &ctx));
                                let est =
                                    est.map_err(|e| RunError::new(id, Some(&item.meta.trial_id), e.message))?;
                                Ok((t, (with_provenance(&item.meta, &prov, Payload::from(est)), dt)))
                            })
                            .collect();
                        let preds = preds.into_iter().collect::<Result<Vec<_>, _>>()?;
                        tick(opts);
                        Ok((fit_time, preds))
                    })
                    .collect();
                for r in fold_results {
                    let (fit_time, preds) = r?;
                    timing.fits.push(fit_time);
                    for (t, (item, dt)) in preds {
                        per_trial[t] = Some(dt);
                        estimates[t] = Some(item);
                    }
                }
                timing.per_trial = per_trial.into_iter().flatten().collect();
                let mut out = Vec::with_capacity(estimates.len());
                for (t, e) in estimates.into_iter().enumerate() {
                    // Under a hold-out only the held-out trials are scored.
                    if e.is_none() && hold_out {
                        continue;
                    }
                    out.push(e.ok_or_else(|| {
                        RunError::new(
                            id,
                            Some(&items[t].meta.trial_id),
                            "no fold tested this trial (internal protocol error)",
                        )
                    })?);
                }
                Some(out)
            }
            Stage::Sink(sink) => {
                std::fs::create_dir_all(&graph.out_dir).map_err(|e| {
                    RunError::new(
                        id,
                        None,
                        format!(
                            "cannot create the output directory {}: {e}",
                            graph.out_dir.display()
                        ),
                    )
                })?;
                start(opts, id, 1);
                let sink_inputs: Vec<SinkInput<'_>> = graph.input_index[i]
                    .iter()
                    .zip(&inputs)
                    .map(|(&j, items)| SinkInput {
                        stage_id: &graph.nodes[j].id,
                        items,
                    })
                    .collect();
                let ctx = SinkContext {
                    stage_id: id,
                    out_dir: &graph.out_dir,
                };
                let report = sink
                    .consume(&sink_inputs, &ctx)
                    .map_err(|e| RunError::new(id, None, e.message))?;
                crate::stage::check_sink_files(&result.reports, id, &report)
                    .map_err(|e| RunError::new(id, None, e))?;
                tick(opts);
                result.reports.push((node.id.clone(), report));
                None
            }
        };
        timing.total = t_stage.elapsed();
        if let Some(p) = opts.progress {
            p.finish(id);
        }
        if let Some(items) = produced {
            let items = Arc::new(items);
            if opts.keep_outputs {
                result.outputs.insert(node.id.clone(), items.clone());
            }
            upstream_cost[i] = inputs_cost + timing.total;
            if let (Some(c), false) = (opts.cache, always_runs(&node.stage)) {
                c.put(keys[i], items.clone(), timing.clone(), upstream_cost[i]);
            }
            outputs[i] = Some(items);
        }
        result.timings.push(timing);
        release_inputs(graph, i, &mut readers, &mut outputs);
    }
    if let Some(c) = opts.cache {
        let own: Vec<u64> = families.iter().flatten().copied().collect();
        c.finished(&own);
    }
    Ok(result)
}

/// Every stage's cache key, by node: a hash of its id, type, settings, the
/// graph's seed and its inputs' keys (so it follows every change upstream
/// without reading data). The id is in it because stages draw their random
/// numbers from seeds derived from their ids: two stages alike but for
/// their ids may differ. So are the folder relative paths in settings
/// resolve against (a scene `file`) and the evaluation protocol (which
/// splits a trained estimator's folds): a cache shared by several graphs
/// (`palpate batch`) must not serve one graph's `../scenes/lab.toml` or
/// folds to another whose differ.
fn stage_keys(graph: &Graph) -> Vec<u64> {
    let mut keys = vec![0u64; graph.nodes.len()];
    let context = key_context(graph);
    for &i in &graph.order {
        let node = &graph.nodes[i];
        let settings = settings_json(node.config.as_ref()).to_string();
        let input_keys: Vec<String> = graph.input_index[i]
            .iter()
            .map(|&j| keys[j].to_string())
            .collect();
        let mut labels: Vec<&str> = vec![&node.id, &node.type_name, &settings, &context];
        labels.extend(input_keys.iter().map(String::as_str));
        keys[i] = derive_seed(graph.run.seed, &labels);
    }
    keys
}

/// What every key of a graph covers besides its stages: the folder relative
/// paths resolve against and the evaluation protocol (see [`stage_keys`]).
fn key_context(graph: &Graph) -> String {
    let base = std::path::absolute(&graph.base_dir).unwrap_or_else(|_| graph.base_dir.clone());
    serde_json::json!([base.to_string_lossy(), graph.run.protocol]).to_string()
}

/// Stages that run at every run, served from nothing a cache holds: sinks,
/// and estimators whose fits have effects ([`crate::stage::Estimator::reusable`]).
fn always_runs(stage: &Stage) -> bool {
    match stage {
        Stage::Sink(_) => true,
        Stage::Estimator(e) => !e.reusable(),
        _ => false,
    }
}

/// Each trained estimator's fit family, by node (`None` for other stages): a
/// hash of its type, settings and id with the graph's seed, which with the
/// fold fixes its fit's seed; runs of one sweep that share a family may share
/// fitted models.
fn fit_families(graph: &Graph) -> Vec<Option<u64>> {
    graph
        .nodes
        .iter()
        .map(|node| match &node.stage {
            Stage::Estimator(e) if e.trained() && e.reusable() => {
                let settings = settings_json(node.config.as_ref()).to_string();
                Some(derive_seed(
                    graph.run.seed,
                    &["fit", &node.type_name, &settings, &node.id],
                ))
            }
            _ => None,
        })
        .collect()
}

/// Plans a run under a cache, from the sinks back to the sources: a stage's
/// output is wanted when a sink or a stage to be computed reads it (or when
/// every output is to be kept). A wanted stage is fetched from the cache
/// (`hit`) or computed, which wants its inputs in turn; a stage nobody wants
/// is `skipped`, reporting the timing of the run that computed it. A stage
/// the cache has never seen is computed even when nobody wants it (a stage
/// without readers), so that every stage has a timing to report.
///
/// Fetching the hits here, before anything runs, pins them: the outputs this
/// run computes cannot evict a hit the plan relies on.
///
/// An item-level stage ([`items`]) is planned trial by trial: a trial is
/// wanted when a reader computes that trial (every trial, for a reader that
/// is not item-level); a wanted trial is fetched or computed, and a trial
/// nobody wants is computed only when the cache has never seen it.
#[allow(clippy::too_many_arguments)]
fn plan(
    graph: &Graph,
    cache: &Cache,
    keys: &[u64],
    item_plans: &[Option<items::ItemPlan>],
    keep_outputs: bool,
    hit: &mut [Option<Cached>],
    skipped: &mut [Option<StageTiming>],
    item_hits: &mut [Vec<Option<(Payload, Duration)>>],
    item_times: &mut [Vec<Option<Duration>>],
    compute: &mut [Vec<bool>],
) {
    let mut wanted = vec![false; graph.nodes.len()];
    let mut wanted_trials: Vec<Vec<bool>> = item_plans
        .iter()
        .map(|p| vec![false; p.as_ref().map_or(0, |p| p.keys.len())])
        .collect();
    for &i in graph.order.iter().rev() {
        if let Some(p) = &item_plans[i] {
            let known = cache.item_times(&p.keys);
            // Fetched now: a run's start drops what no later run needs.
            skipped[i] = cache.timing(keys[i]);
            let look: Vec<bool> = (0..p.keys.len())
                .map(|t| wanted[i] || keep_outputs || wanted_trials[i][t] || known[t].is_none())
                .collect();
            item_hits[i] = cache.get_items(&p.keys, &look);
            compute[i] = look
                .iter()
                .zip(&item_hits[i])
                .map(|(&l, h)| l && h.is_none())
                .collect();
            item_times[i] = known;
            if look.iter().any(|&l| l) {
                cache.count(!compute[i].iter().any(|&c| c));
            }
            for (t, _) in compute[i].iter().enumerate().filter(|(_, &c)| c) {
                for &j in &graph.input_index[i] {
                    if let Some(w) = wanted_trials[j].get_mut(t) {
                        *w = true;
                    }
                }
            }
            continue;
        }
        let computed = if always_runs(&graph.nodes[i].stage) {
            true
        } else if wanted[i] || keep_outputs {
            hit[i] = cache.get(keys[i]);
            hit[i].is_none()
        } else if let Some(t) = cache.timing(keys[i]) {
            skipped[i] = Some(t);
            false
        } else {
            hit[i] = cache.get(keys[i]);
            hit[i].is_none()
        };
        if computed {
            for &j in &graph.input_index[i] {
                wanted[j] = true;
            }
        }
    }
}

/// Drops an input's output once its last reader is done.
fn release_inputs(graph: &Graph, i: usize, readers: &mut [usize], outputs: &mut [Option<Arc<Vec<Item>>>]) {
    for &j in &graph.input_index[i] {
        readers[j] -= 1;
        if readers[j] == 0 {
            outputs[j] = None;
        }
    }
}

fn start(opts: &RunOptions<'_>, id: &str, total: usize) {
    if let Some(p) = opts.progress {
        p.start(id, total);
    }
}

fn tick(opts: &RunOptions<'_>) {
    if let Some(p) = opts.progress {
        p.tick();
    }
}

fn with_provenance(meta: &TrialMeta, prov: &Provenance, payload: Payload) -> Item {
    Item {
        meta: meta_with(meta, prov),
        payload,
    }
}

/// `meta` with `prov` appended to its provenance.
fn meta_with(meta: &TrialMeta, prov: &Provenance) -> Arc<TrialMeta> {
    let mut m = meta.clone();
    m.provenance.push(prov.clone());
    Arc::new(m)
}

fn unzip_timed(
    done: Vec<Result<Timed<Item>, RunError>>,
    times: &mut Vec<Duration>,
) -> Result<Vec<Item>, RunError> {
    let mut items = Vec::with_capacity(done.len());
    for r in done {
        let (item, dt) = r?;
        items.push(item);
        times.push(dt);
    }
    Ok(items)
}

fn check_unique_ids(id: &str, metas: &[TrialMeta]) -> Result<(), RunError> {
    let mut seen = std::collections::HashSet::new();
    for m in metas {
        if !seen.insert(m.trial_id.as_str()) {
            return Err(RunError::new(
                id,
                Some(&m.trial_id),
                "two trials share this id; trial ids must be unique",
            ));
        }
    }
    Ok(())
}

/// Every input of a per-trial stage must carry the same trials in the same order.
fn aligned_len(id: &str, graph: &Graph, i: usize, inputs: &[Arc<Vec<Item>>]) -> Result<usize, RunError> {
    let first = &inputs[0];
    for (k, other) in inputs.iter().enumerate().skip(1) {
        let same = other.len() == first.len()
            && other
                .iter()
                .zip(first.iter())
                .all(|(a, b)| a.meta.trial_id == b.meta.trial_id);
        if !same {
            return Err(mixed_trials(graph, id, i, k));
        }
    }
    Ok(first.len())
}

/// Per-stage timing summary: (median, p95) of per-trial times.
pub fn median_p95(times: &[Duration]) -> (Duration, Duration) {
    if times.is_empty() {
        return (Duration::ZERO, Duration::ZERO);
    }
    let mut v = times.to_vec();
    v.sort_unstable();
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    (q(0.5), q(0.95))
}

/// The error for a per-trial stage whose inputs `0` and `k` carry different
/// trials (shared by the runners of `chain` and `item_chain`).
pub(crate) fn mixed_trials(graph: &Graph, id: &str, i: usize, k: usize) -> RunError {
    RunError::new(
        id,
        None,
        format!(
            "inputs `{}` and `{}` carry different trials; a per-trial stage needs inputs from the same source",
            graph.nodes[graph.input_index[i][0]].id,
            graph.nodes[graph.input_index[i][k]].id
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles() {
        let t: Vec<Duration> = (1..=100).map(Duration::from_millis).collect();
        let (m, p) = median_p95(&t);
        assert!(m >= Duration::from_millis(50) && m <= Duration::from_millis(51));
        assert_eq!(p, Duration::from_millis(95));
        assert_eq!(median_p95(&[]), (Duration::ZERO, Duration::ZERO));
    }

    fn images(cells: usize) -> Arc<Vec<Item>> {
        let im = crate::payload::SpikeImages {
            layout: crate::payload::TaxelLayout::paper(),
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames: cells / 16,
            counts: vec![0.0; cells],
        };
        Arc::new(vec![Item {
            meta: Arc::new(crate::payload::TrialMeta::default()),
            payload: im.into(),
        }])
    }

    #[test]
    fn the_cache_stays_within_its_budget_dropping_the_least_recently_used() {
        // Budget: 3 outputs of 1,600 counts (12,800 bytes each).
        let c = Cache::with_budget(3 * 12_800);
        for k in 0..3 {
            c.put(k, images(1600), StageTiming::default(), Duration::ZERO);
        }
        assert_eq!(c.held_bytes(), 3 * 12_800);
        assert!(c.get(0).is_some()); // 0 is now the most recently used
        c.put(3, images(1600), StageTiming::default(), Duration::ZERO);
        assert!(c.held_bytes() <= c.budget_bytes());
        assert!(c.get(1).is_none(), "the least recently used output is dropped");
        assert!(c.get(0).is_some() && c.get(2).is_some() && c.get(3).is_some());
        // An output larger than the whole budget is not kept and evicts nothing.
        c.put(9, images(16_000), StageTiming::default(), Duration::ZERO);
        assert!(c.get(9).is_none());
        assert_eq!(c.held_bytes(), 3 * 12_800);
        // Replacing a key does not count it twice.
        c.put(3, images(1600), StageTiming::default(), Duration::ZERO);
        assert_eq!(c.held_bytes(), 3 * 12_800);
        assert_eq!((c.hits(), c.misses()), (4, 2));
    }

    proptest::proptest! {
        /// Any sequence of puts, gets and announced runs keeps the byte
        /// count exact and within the budget, and never panics.
        #[test]
        fn the_cache_accounting_holds_under_any_sequence(
            ops in proptest::collection::vec((0u8..7, 0u64..12, 1usize..40, 0u64..50), 1..200),
            budget_cells in 16usize..200,
        ) {
            let c = Cache::with_budget(budget_cells * 8);
            for (op, key, cells, cost) in ops {
                match op {
                    0 | 1 => c.put(key, images(cells * 16), StageTiming::default(), Duration::from_millis(cost)),
                    2 => {
                        let _ = c.get(key);
                    }
                    4 => {
                        // A batch of trials, some keeping their time alone.
                        let batch = (0..cells % 5)
                            .map(|b| {
                                let payload = images(cells * 16 / (b + 1))[0].payload.clone();
                                let kept = !(b as u64 + cost).is_multiple_of(3);
                                (key + b as u64, kept.then_some(payload), Duration::from_millis(cost), Duration::from_millis(cost))
                            })
                            .collect();
                        c.put_items(batch);
                    }
                    5 => {
                        let keys: Vec<u64> = (key..key + 4).collect();
                        let got = c.get_items(&keys, &[true, false, true, true]);
                        proptest::prop_assert!(got[1].is_none());
                        // A trial served has its time.
                        let times = c.item_times(&keys);
                        for (g, t) in got.iter().zip(&times) {
                            proptest::prop_assert!(g.is_none() || t.is_some());
                        }
                    }
                    3 => {
                        // A run announced once, now started: its output goes.
                        c.map.lock().unwrap_or_else(|e| e.into_inner()).future.insert(key, 1);
                        c.started(&[key], &[key]);
                        proptest::prop_assert!(c.get(key).is_none());
                        c.map.lock().unwrap_or_else(|e| e.into_inner()).future.remove(&key);
                    }
                    _ => {
                        let _ = c.get_items(&[key], &[true]);
                        let _ = c.covered(&[key], &[&[key + 1]]);
                    }
                }
                let m = c.map.lock().unwrap_or_else(|e| e.into_inner());
                let sum: usize = m.entries.values().map(|e| e.bytes).sum();
                proptest::prop_assert_eq!(sum, m.bytes);
                proptest::prop_assert!(m.bytes <= c.budget_bytes());
            }
        }
    }

    #[test]
    fn a_trial_is_covered_only_when_every_later_run_has_its_readers_trial() {
        let c = Cache::default();
        {
            let mut m = c.map.lock().unwrap();
            m.future.extend([(1, 3), (2, 3), (3, 1), (4, 3)]);
        }
        // Key 1 is in 3 later runs, and so is its reader's trial 2.
        assert_eq!(c.covered(&[1], &[&[2]]), [true]);
        // A reader whose trial is in 1 later run of 3: two runs read key 1.
        assert_eq!(c.covered(&[1], &[&[2], &[3]]), [false]);
        assert_eq!(c.covered(&[1, 4], &[&[2, 3]]), [true, false]);
        // No readers, or nothing announced: kept.
        assert_eq!(c.covered(&[1], &[]), [false]);
        assert_eq!(c.covered(&[9], &[&[2]]), [false]);
        // A covered trial keeps its time, not its payload.
        c.put_items(vec![(1, None, Duration::from_millis(5), Duration::ZERO)]);
        assert_eq!(c.item_times(&[1]), [Some(Duration::from_millis(5))]);
        assert!(c.get_items(&[1], &[true])[0].is_none());
        assert_eq!(c.held_bytes(), 0);
    }

    #[test]
    fn eviction_keeps_what_costs_most_to_recompute_per_byte() {
        let c = Cache::with_budget(3 * 12_800);
        let ms = Duration::from_millis;
        c.put(0, images(1600), StageTiming::default(), ms(1000));
        c.put(1, images(1600), StageTiming::default(), ms(1));
        c.put(2, images(1600), StageTiming::default(), ms(2));
        c.put(3, images(1600), StageTiming::default(), ms(1));
        assert!(c.get(1).is_none(), "the cheapest output goes first");
        assert!(c.get(0).is_some(), "not the oldest, costly one");
        // Equal cost: the larger output goes first (it frees more per second lost).
        let c = Cache::with_budget(3 * 12_800 + 6_400);
        c.put(0, images(1600), StageTiming::default(), ms(10));
        c.put(1, images(3200), StageTiming::default(), ms(10));
        c.put(2, images(1600), StageTiming::default(), ms(10));
        assert!(c.get(1).is_none() && c.get(0).is_some() && c.get(2).is_some());
    }
}
