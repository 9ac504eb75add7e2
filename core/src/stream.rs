//! Streaming: per-trial stages fed one trial in blocks, as a DAQ delivers it.
//!
//! Beside its batch form (a [`crate::Map`] or an estimator's model, which sees
//! a whole trial), a stage type may register a *streaming form*: per trial it
//! opens a [`StreamState`], is pushed the trial block by block, emits what is
//! ready after each block, and emits the rest when the trial is flushed. State
//! (filter memories, membranes, open images) is kept between blocks.
//!
//! Blocks are ordinary [`Payload`]s of the stage's kinds, cut in time:
//!
//! | kind | one block holds |
//! |---|---|
//! | signals | the next samples of every taxel (`data[taxel]`, all of one length, possibly 0); rate, layout and unit as the trial's |
//! | spikes | the next events, time-sorted; `duration_ms` is the time up to which every event of the trial is known (the last block's is the trial's duration) |
//! | images | the next complete frames (`n_frames` of them, numbered on from the previous block's) |
//! | estimates | the running estimate after the images so far; the last one is the trial's |
//!
//! The contract, tested for every streamable stage with blocks of 1, 7 and
//! 1000 samples: [`concat()`] of a stage's output blocks equals its batch output
//! on the whole trial (bit for bit where the arithmetic is the same; each test
//! states its tolerance otherwise).
//!
//! A stage that cannot stream (a zero-phase filter, whole-trial normalization,
//! a gain set from the trial's peak, a crop by share of a crossing) says so
//! with [`StreamForm::Batch`], naming why and its causal alternative;
//! `palpate check --live GRAPH` lists them. Registration is by stage type name,
//! through `inventory`, like the stage registry: [`register_stream!`](crate::register_stream)
//! beside the stage's own registration, in a separate file, so the batch
//! stage's code is untouched.

use crate::payload::{Estimate, Payload, Signals, SpikeImages, SpikeTrain};
use crate::stage::{BuildContext, ConfigError, StageError, TrialContext};

/// One trial's running state of a streaming stage.
pub trait StreamState: Send {
    /// Pushes the next block of the stage's input; appends the output blocks
    /// that are ready (possibly none) to `out`.
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError>;
    /// Ends the trial: appends what is left (the last samples' look-ahead,
    /// the images that run past the end, the final estimate) to `out`.
    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError>;
}

/// The streaming form of a built stage: opens one state per trial.
pub trait StreamStage: Send + Sync {
    /// A fresh state for one trial (the seed of `ctx` is the batch form's).
    fn open(&self, ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError>;
}

/// Whether a configured stage can stream.
pub enum StreamForm {
    /// It can: its streaming form.
    Streams(Box<dyn StreamStage>),
    /// It cannot, with these settings.
    Batch {
        /// Why it needs the whole trial, e.g. "zero-phase filtering runs backwards from the trial's end".
        why: String,
        /// What to use instead in a live graph, e.g. "mode = \"causal\"".
        instead: String,
    },
}

impl StreamForm {
    /// A stage that cannot stream: why, and its causal alternative.
    pub fn batch(why: impl Into<String>, instead: impl Into<String>) -> Self {
        StreamForm::Batch {
            why: why.into(),
            instead: instead.into(),
        }
    }
}

/// A stage type's streaming form, found by its `type` name.
pub struct StreamRegistration {
    /// The `type` value in graph files.
    pub type_name: &'static str,
    /// Builds the streaming form from the stage's settings (its config
    /// serialized as `{type_name: {keys}}`, as typetag writes it).
    pub build: fn(&serde_json::Value, &BuildContext) -> Result<StreamForm, ConfigError>,
}

inventory::collect!(StreamRegistration);

/// Registers a stage type's streaming form: `register_stream!("lowpass",
/// LowpassConfig, lowpass_stream)` with `fn lowpass_stream(&LowpassConfig,
/// &BuildContext) -> Result<StreamForm, ConfigError>`.
#[macro_export]
macro_rules! register_stream {
    ($name:literal, $ty:ty, $build:path) => {
        $crate::__private::inventory::submit! {
            $crate::stream::StreamRegistration {
                type_name: $name,
                build: |settings, ctx| {
                    let inner = settings.get($name).cloned().unwrap_or_else(|| settings.clone());
                    let cfg: $ty = $crate::__private::serde_json::from_value(inner)
                        .map_err(|e| $crate::ConfigError::general(e.to_string()))?;
                    $build(&cfg, ctx)
                },
            }
        }
    };
}

/// The streaming registration of `type_name`, if it has one.
pub fn find(type_name: &str) -> Option<&'static StreamRegistration> {
    inventory::iter::<StreamRegistration>
        .into_iter()
        .find(|r| r.type_name == type_name)
}

/// The streaming form of a stage of type `type_name` with `settings` (its
/// serialized config); a type without a registration cannot stream.
pub fn form(
    type_name: &str,
    settings: &serde_json::Value,
    ctx: &BuildContext,
) -> Result<StreamForm, ConfigError> {
    match find(type_name) {
        Some(r) => (r.build)(settings, ctx),
        None => Ok(StreamForm::batch(
            format!("stage type `{type_name}` has no streaming form"),
            "a stage that streams, or run it offline",
        )),
    }
}

/// Joins a stage's output blocks into the payload its batch form gives on the
/// whole trial (see the module docs); `None` for no blocks or mixed kinds.
pub fn concat(blocks: &[Payload]) -> Option<Payload> {
    let first = blocks.first()?;
    match first {
        Payload::Signals(s0) => {
            let mut data: Vec<Vec<f64>> = vec![Vec::new(); s0.data.len()];
            for b in blocks {
                let s = b.signals().ok()?;
                if s.data.len() != data.len() {
                    return None;
                }
                for (d, x) in data.iter_mut().zip(&s.data) {
                    d.extend_from_slice(x);
                }
            }
            Some(s0.with_data(s0.unit.clone(), data).into())
        }
        Payload::Spikes(t0) => {
            let mut events = Vec::new();
            let mut duration_ms = t0.duration_ms;
            for b in blocks {
                let t = b.spikes().ok()?;
                events.extend_from_slice(&t.events);
                duration_ms = t.duration_ms;
            }
            Some(
                SpikeTrain {
                    layout: t0.layout.clone(),
                    duration_ms,
                    events,
                }
                .into(),
            )
        }
        Payload::Images(i0) => {
            let mut counts = Vec::new();
            let mut n_frames = 0usize;
            for b in blocks {
                let i = b.images().ok()?;
                counts.extend_from_slice(&i.counts);
                n_frames = n_frames.checked_add(i.n_frames)?;
            }
            Some(
                SpikeImages {
                    layout: i0.layout.clone(),
                    window_ms: i0.window_ms,
                    hop_ms: i0.hop_ms,
                    n_frames,
                    counts,
                }
                .into(),
            )
        }
        Payload::Estimate(_) => {
            let last: &Estimate = blocks.last()?.estimate().ok()?;
            blocks
                .iter()
                .all(|b| b.estimate().is_ok())
                .then(|| last.clone().into())
        }
    }
}

/// Cuts a trial's signals into blocks of `block` samples (the last may be
/// shorter; `block` 0 is taken as 1), as a stream would deliver them.
pub fn signal_blocks(s: &Signals, block: usize) -> Vec<Payload> {
    let n = s.n_samples();
    let block = block.max(1);
    (0..n)
        .step_by(block)
        .map(|a| {
            let b = (a + block).min(n);
            s.with_data(s.unit.clone(), s.data.iter().map(|x| x[a..b].to_vec()).collect())
                .into()
        })
        .collect()
}

/// Pushes `blocks` through a fresh state of `stage` and flushes it: every
/// output block, in order. What tests and replays use.
pub fn run_blocks(
    stage: &dyn StreamStage,
    blocks: &[Payload],
    ctx: &TrialContext<'_>,
) -> Result<Vec<Payload>, StageError> {
    let mut state = stage.open(ctx)?;
    let mut out = Vec::new();
    for b in blocks {
        state.push(b, &mut out)?;
    }
    state.flush(&mut out)?;
    Ok(out)
}

/// A stage of a graph that cannot stream, for `palpate check --live`.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveProblem {
    /// The stage's id.
    pub stage: String,
    /// Its type.
    pub type_name: String,
    /// Why it cannot stream.
    pub why: String,
    /// Its causal alternative.
    pub instead: String,
}

impl std::fmt::Display for LiveProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.stage.is_empty() {
            // A problem of the graph as a whole, not of one stage.
            return write!(
                f,
                "the graph cannot run live: {}; instead: {}",
                self.why, self.instead
            );
        }
        write!(
            f,
            "stage `{}` ({}) cannot stream: {}; instead: {}",
            self.stage, self.type_name, self.why, self.instead
        )
    }
}

/// A graph's streaming plan: its one source, and the streaming form of every
/// stage between it and the sinks (in execution order).
pub struct LivePlan {
    /// The source's node index.
    pub source: usize,
    /// (node index, streaming form), in the graph's execution order.
    pub stages: Vec<(usize, Box<dyn StreamStage>)>,
}

/// Builds the streaming plan of a graph, or names every stage that cannot
/// stream (with why, and what to use instead). A live graph has one source;
/// every other stage but the sinks reads one input and has a streaming form.
pub fn plan(graph: &crate::Graph) -> Result<LivePlan, Vec<LiveProblem>> {
    use crate::stage::Stage;
    let mut problems = Vec::new();
    let mut source = None;
    let mut stages = Vec::new();
    for &i in &graph.order {
        let node = &graph.nodes[i];
        let problem = |why: String, instead: &str| LiveProblem {
            stage: node.id.clone(),
            type_name: node.type_name.clone(),
            why,
            instead: instead.to_string(),
        };
        match &node.stage {
            Stage::Sink(_) => continue,
            Stage::Source(_) => {
                if source.is_some() {
                    problems.push(problem(
                        "a live graph has one source (the DAQ or the recording it replays)".into(),
                        "one source stage",
                    ));
                }
                source = Some(i);
                continue;
            }
            Stage::Map(_) | Stage::Estimator(_) => {}
        }
        if graph.input_index[i].len() != 1 {
            problems.push(problem(
                "a stage of several inputs does not stream yet".into(),
                "a chain of one-input stages",
            ));
            continue;
        }
        let ctx = build_context(graph, i);
        let settings = serde_json::to_value(node.config.as_ref()).unwrap_or(serde_json::Value::Null);
        match form(&node.type_name, &settings, &ctx) {
            Ok(StreamForm::Streams(s)) => stages.push((i, s)),
            Ok(StreamForm::Batch { why, instead }) => problems.push(problem(why, &instead)),
            Err(e) => problems.push(problem(e.to_string(), "a valid setting")),
        }
    }
    // A live run scores every trial as it streams, and runs one graph.
    let whole = |why: String, instead: &str| LiveProblem {
        stage: String::new(),
        type_name: String::new(),
        why,
        instead: instead.to_string(),
    };
    if graph.run.protocol.scores_a_subset() {
        problems.push(whole(
            format!(
                "[run] protocol `{}` scores a held-out subset of the trials, chosen from the whole \
                 trial list, which a live stream does not have before it ends",
                graph.run.protocol.name()
            ),
            "no protocol (a live run scores every trial), or run without --live",
        ));
    }
    if graph.sweep.is_some() {
        problems.push(whole(
            "a live run streams one graph, and this one has a [sweep] table".into(),
            "run the sweep without --live, or remove [sweep] to stream the base graph",
        ));
    }
    match (source, problems.is_empty()) {
        (Some(source), true) => Ok(LivePlan { source, stages }),
        (None, _) => {
            problems.push(whole(
                "the graph has no source".into(),
                "a source stage (a scene, a recording, the DAQ)",
            ));
            Err(problems)
        }
        (_, false) => Err(problems),
    }
}

impl LivePlan {
    /// Opens every stage's state for one trial: push the source's blocks
    /// into the returned [`TrialStream`] as they come, then finish it.
    /// `keep`: keep every node's output blocks (tests), else only each
    /// node's last block (the estimators' running answers).
    pub fn start_trial<'p>(
        &'p self,
        graph: &'p crate::Graph,
        meta: &crate::TrialMeta,
        keep: bool,
    ) -> Result<TrialStream<'p>, crate::RunError> {
        let mut states = Vec::with_capacity(self.stages.len());
        for (i, s) in &self.stages {
            let id = graph.nodes[*i].id.as_str();
            let ctx = TrialContext {
                stage_id: id,
                meta,
                seed: crate::derive_seed(graph.run.seed, &[id, &meta.trial_id]),
            };
            states.push(s.open(&ctx).map_err(|e| run_error(graph, *i, meta, e))?);
        }
        let n = graph.nodes.len();
        Ok(TrialStream {
            plan: self,
            graph,
            meta: meta.clone(),
            keep,
            states,
            kept: vec![Vec::new(); n],
            pending: vec![Vec::new(); n],
            timing: None,
        })
    }

    /// Streams one trial: pushes `blocks` of the source's output through every
    /// stage's fresh state, then flushes them in order. `on_block(node, block)`
    /// sees every output block as it is produced (a live display shows the
    /// estimates). Returns every node's output blocks when `keep` is set
    /// (tests), else only the estimators' and maps' last blocks.
    pub fn run_trial(
        &self,
        graph: &crate::Graph,
        meta: &crate::TrialMeta,
        blocks: impl IntoIterator<Item = Payload>,
        keep: bool,
        mut on_block: impl FnMut(usize, &Payload),
    ) -> Result<Vec<(usize, Vec<Payload>)>, crate::RunError> {
        let mut t = self.start_trial(graph, meta, keep)?;
        for b in blocks {
            t.push(b, &mut on_block)?;
        }
        t.finish(&mut on_block)
    }
}

fn run_error(graph: &crate::Graph, i: usize, meta: &crate::TrialMeta, e: StageError) -> crate::RunError {
    crate::RunError {
        stage: graph.nodes[i].id.clone(),
        trial: Some(meta.trial_id.clone()),
        message: e.message,
    }
}

/// The output blocks a trial's stream kept, per node that produced any
/// (see [`LivePlan::run_trial`]).
pub type KeptBlocks = Vec<(usize, Vec<Payload>)>;

/// One trial being streamed through a [`LivePlan`] (see [`LivePlan::start_trial`]).
pub struct TrialStream<'p> {
    plan: &'p LivePlan,
    graph: &'p crate::Graph,
    meta: crate::TrialMeta,
    keep: bool,
    states: Vec<Box<dyn StreamState>>,
    kept: Vec<Vec<Payload>>,
    pending: Vec<Vec<Payload>>,
    /// Per stage of the plan, the wall time of its share of each step
    /// ([`TrialStream::time_stages`]); `None`: not timed.
    timing: Option<Vec<BlockLatency>>,
}

impl TrialStream<'_> {
    /// Pushes the source's next block through every stage.
    pub fn push(
        &mut self,
        block: Payload,
        on_block: &mut dyn FnMut(usize, &Payload),
    ) -> Result<(), crate::RunError> {
        if self.keep {
            self.kept[self.plan.source].push(block.clone());
        }
        self.pending[self.plan.source].push(block);
        self.step(false, on_block)
    }

    /// Flushes every stage, in order; returns the kept blocks of every node
    /// that produced any (see [`LivePlan::run_trial`]).
    pub fn finish(
        self,
        on_block: &mut dyn FnMut(usize, &Payload),
    ) -> Result<Vec<(usize, Vec<Payload>)>, crate::RunError> {
        self.finish_timed(on_block).map(|(kept, _)| kept)
    }

    /// Times every stage from now on: `acc` (one accumulator per stage of
    /// the plan, in plan order; missing ones are added) records, for each
    /// block pushed and for the final flush, the wall time each stage spent
    /// on it (its pushes and flush, not `on_block` nor the copies kept).
    /// Two clock reads per stage and block; with them the chain's mean time
    /// per block did not move beyond run-to-run noise (`palpate run
    /// graphs/live.toml --live`, 170 trials, binaries without and with them
    /// alternated: 6.5 and 5.9 against 6.0 and 6.4 µs).
    /// [`TrialStream::finish_timed`] hands them back.
    pub fn time_stages(&mut self, mut acc: Vec<BlockLatency>) {
        acc.resize_with(self.plan.stages.len(), BlockLatency::default);
        self.timing = Some(acc);
    }

    /// [`TrialStream::finish`], also handing back the accumulators given to
    /// [`TrialStream::time_stages`] (`None` if it was not called).
    pub fn finish_timed(
        mut self,
        on_block: &mut dyn FnMut(usize, &Payload),
    ) -> Result<(KeptBlocks, Option<Vec<BlockLatency>>), crate::RunError> {
        self.step(true, on_block)?;
        let kept = std::mem::take(&mut self.kept)
            .into_iter()
            .enumerate()
            .filter(|(_, v)| !v.is_empty())
            .collect();
        Ok((kept, self.timing.take()))
    }

    fn step(
        &mut self,
        flush: bool,
        on_block: &mut dyn FnMut(usize, &Payload),
    ) -> Result<(), crate::RunError> {
        let graph = self.graph;
        for (p, (i, _)) in self.plan.stages.iter().enumerate() {
            let input = graph.input_index[*i][0];
            let mut out = Vec::new();
            let t0 = self.timing.is_some().then(std::time::Instant::now);
            for b in &self.pending[input] {
                self.states[p]
                    .push(b, &mut out)
                    .map_err(|e| run_error(graph, *i, &self.meta, e))?;
            }
            if flush {
                self.states[p]
                    .flush(&mut out)
                    .map_err(|e| run_error(graph, *i, &self.meta, e))?;
            }
            if let (Some(t0), Some(acc)) = (t0, self.timing.as_mut()) {
                acc[p].add(u64::try_from(t0.elapsed().as_nanos()).unwrap_or(u64::MAX));
            }
            for b in &out {
                on_block(*i, b);
            }
            if self.keep {
                self.kept[*i].extend(out.iter().cloned());
            } else if let Some(last) = out.last() {
                self.kept[*i] = vec![last.clone()];
            }
            self.pending[*i] = out;
        }
        for v in self.pending.iter_mut() {
            v.clear();
        }
        Ok(())
    }
}

/// What a streaming source (a DAQ) hands a live run, in stream order.
#[derive(Clone, Debug)]
pub enum SourceEvent {
    /// A trial begins (its metadata; `index` is filled in by the run).
    Start(crate::TrialMeta),
    /// The trial's next block (signals of the source's kind).
    Block(Payload),
    /// The trial ends.
    End,
    /// Nothing for the run to stream, but the source is alive: a frame
    /// arrived outside any trial (a board with nothing in contact), or a
    /// wait for data elapsed (a silent board). A live run checks here
    /// whether its caller wants to stop ([`replay_polled`]); without these
    /// a session with nothing in contact could not be stopped.
    Tick,
}

/// A source that produces its trials as they happen (a DAQ), for live runs:
/// instead of [`crate::Source::trials`] then `produce`, a live run calls
/// [`LiveSource::stream`] once and follows its events. A source offers it
/// through [`crate::Source::live`].
pub trait LiveSource: Send + Sync {
    /// Runs the stream to its end, handing every event to `on` as it comes;
    /// an error from `on` stops the stream and is returned.
    fn stream(
        &self,
        on: &mut dyn FnMut(SourceEvent) -> Result<(), crate::RunError>,
    ) -> Result<(), crate::RunError>;
}

fn build_context(graph: &crate::Graph, node: usize) -> BuildContext {
    BuildContext {
        stage_id: graph.nodes[node].id.clone(),
        seed: graph.run.seed,
        out_dir: graph.out_dir.clone(),
        // The batch build's base directory: `LoadOptions::base_dir` may
        // differ from the graph file's directory.
        base_dir: graph.base_dir.clone(),
    }
}

/// A running estimate, as `palpate run --live` prints it.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveUpdate {
    /// The trial being streamed.
    pub trial_id: String,
    /// The estimator stage that answered.
    pub stage: String,
    /// Stream time: samples pushed so far over the rate, ms.
    pub t_ms: f64,
    /// The estimate.
    pub estimate: Estimate,
    /// True for the trial's final estimate (after the flush).
    pub last: bool,
}

/// Wall time of each block's trip through a live chain (the stages' pushes,
/// not the caller's `on_update`), summarised in constant memory whatever the
/// number of blocks: an exact count, mean and maximum, and quantiles from a
/// histogram of 8 bins per octave of nanoseconds (a quantile is its bin's
/// upper edge, capped at the maximum: at most 12.5 % above the exact value,
/// never below it).
#[derive(Clone, Debug, PartialEq)]
pub struct BlockLatency {
    /// Blocks per bin (see [`BlockLatency::bin`]).
    counts: Box<[u64; LATENCY_BINS]>,
    blocks: u64,
    sum_ns: u128,
    max_ns: u64,
}

/// Bins of [`BlockLatency`]: 16 one-nanosecond bins, then 8 per octave up to 2^64 ns.
const LATENCY_BINS: usize = 16 + 60 * 8;

impl Default for BlockLatency {
    fn default() -> Self {
        BlockLatency {
            counts: Box::new([0; LATENCY_BINS]),
            blocks: 0,
            sum_ns: 0,
            max_ns: 0,
        }
    }
}

impl BlockLatency {
    /// The bin of `ns`: `ns` itself below 16, else 8 bins per octave.
    fn bin(ns: u64) -> usize {
        if ns < 16 {
            return ns as usize;
        }
        let e = ns.ilog2() as usize; // 4..=63
        let sub = ((ns >> (e - 3)) & 7) as usize;
        16 + (e - 4) * 8 + sub
    }

    /// The largest value of bin `b`.
    fn upper(b: usize) -> u64 {
        if b < 16 {
            return b as u64;
        }
        let (e, sub) = ((b - 16) / 8 + 4, ((b - 16) % 8) as u64);
        // Bin (e, sub) holds [2^e + sub 2^(e-3), 2^e + (sub + 1) 2^(e-3)).
        let lo = (1u64 << e) + (sub << (e - 3));
        lo.saturating_add((1u64 << (e - 3)) - 1)
    }

    /// Records one block that took `ns` nanoseconds.
    pub fn add(&mut self, ns: u64) {
        self.counts[Self::bin(ns)] += 1;
        self.blocks += 1;
        self.sum_ns += u128::from(ns);
        self.max_ns = self.max_ns.max(ns);
    }

    /// Adds every block `other` recorded.
    pub fn merge(&mut self, other: &BlockLatency) {
        self.counts
            .iter_mut()
            .zip(other.counts.iter())
            .for_each(|(a, b)| *a += b);
        self.blocks += other.blocks;
        self.sum_ns += other.sum_ns;
        self.max_ns = self.max_ns.max(other.max_ns);
    }

    /// Total nanoseconds recorded.
    pub fn total_ns(&self) -> u128 {
        self.sum_ns
    }

    /// Blocks recorded.
    pub fn blocks(&self) -> u64 {
        self.blocks
    }

    /// Mean nanoseconds per block (0 for none).
    pub fn mean_ns(&self) -> f64 {
        if self.blocks == 0 {
            return 0.0;
        }
        self.sum_ns as f64 / self.blocks as f64
    }

    /// The slowest block, ns.
    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }

    /// The `q`-quantile (`q` in `[0, 1]`, clamped) in ns: the upper edge of
    /// the bin holding the `ceil(q · blocks)`-th fastest block (at least the
    /// first), capped at the maximum; 0 for no block.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.blocks == 0 {
            return 0;
        }
        let q = if q.is_nan() { 1.0 } else { q.clamp(0.0, 1.0) };
        let rank = ((q * self.blocks as f64).ceil() as u64).clamp(1, self.blocks);
        let mut seen = 0u64;
        for (b, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Self::upper(b).min(self.max_ns);
            }
        }
        self.max_ns
    }
}

/// What a live replay gives: the sinks' reports, the estimators' final answers, and
/// how fast the chain (and each of its stages) ran.
#[derive(Clone, Debug)]
pub struct LiveRun {
    /// Each sink's report, in graph order.
    pub reports: Vec<(String, crate::SinkReport)>,
    /// Trials streamed.
    pub trials: usize,
    /// Stream time fed (samples over their rate, summed over trials), s.
    pub stream_s: f64,
    /// Wall time per block through the chain.
    pub latency: BlockLatency,
    /// Per stage of the chain (stage id, in the plan's order): the wall time
    /// it spent on each block (and on each trial's final flush). The sum
    /// over stages is the chain's time less the run's bookkeeping.
    pub stages: Vec<(String, BlockLatency)>,
    /// Per estimator (stage id, in the plan's order): its final estimate of
    /// every trial, in stream order, as the sinks got them.
    pub estimates: Vec<(String, Vec<crate::Item>)>,
    /// The caller stopped the stream ([`replay_until`]); `trials` counts the
    /// trials finished before.
    pub stopped: bool,
}

/// Streams every trial of a graph's source through its [`LivePlan`], trial
/// after trial; `on_update` sees every estimate as it changes. Then the sinks
/// get each estimator's final estimates, as after a batch run. Each block's
/// wall time through the stages (the `on_update` calls left out) is
/// recorded in the result's [`BlockLatency`].
///
/// A source with a live form ([`LiveSource`], e.g. the DAQ) is followed as
/// it produces its blocks (a board: frame by frame, as they arrive; `block`
/// is unused). Any other source produces a trial at a time, cut into blocks
/// of `block` samples (1 = frame by frame, as a board delivers them). Memory:
/// the stages' states and, for a non-live source, one trial's payload.
pub fn replay(
    graph: &crate::Graph,
    plan: &LivePlan,
    block: usize,
    mut on_update: impl FnMut(&LiveUpdate),
) -> Result<LiveRun, crate::RunError> {
    replay_until(graph, plan, block, |u| {
        on_update(u);
        std::ops::ControlFlow::Continue(())
    })
}

/// [`replay`] that the caller can stop (a user ending a live session on a
/// board that would stream forever): when `on_update` returns `Break`, no
/// further update is passed and the stream stops after the block or trial
/// end being handled. A trial under way is dropped (its answers are not
/// final), the sinks report the trials finished before, and the result's
/// `stopped` is set.
pub fn replay_until(
    graph: &crate::Graph,
    plan: &LivePlan,
    block: usize,
    on_update: impl FnMut(&LiveUpdate) -> std::ops::ControlFlow<()>,
) -> Result<LiveRun, crate::RunError> {
    replay_polled(graph, plan, block, on_update, || false)
}

/// The message of the error a live source's `on` callback returns once the
/// caller of [`replay_polled`] stopped the stream: a source that reports on
/// its way out (e.g. why no trial began) can tell a stop from a failure.
pub const STOPPED: &str = "stopped by the caller";

/// [`replay_until`] that also asks `stop` whether to stop, after every
/// block and at every [`SourceEvent::Tick`] of a live source (each frame a
/// board sends outside a trial, each wait for a silent one): a stop asked
/// for (Ctrl-C) is then seen within a block or a wait even when no
/// estimate comes, as on a board with nothing in contact. `stop` returning
/// true stops the stream as a `Break` from `on_update` does.
pub fn replay_polled(
    graph: &crate::Graph,
    plan: &LivePlan,
    block: usize,
    mut on_update: impl FnMut(&LiveUpdate) -> std::ops::ControlFlow<()>,
    mut stop: impl FnMut() -> bool,
) -> Result<LiveRun, crate::RunError> {
    use crate::stage::Stage;
    let stopped = std::cell::Cell::new(false);
    let mut on_update = |u: &LiveUpdate| {
        if !stopped.get() && on_update(u).is_break() {
            stopped.set(true);
        }
    };
    // Whether to stop now: stopped already, or the caller's `stop` says so.
    let mut poll = || {
        if !stopped.get() && stop() {
            stopped.set(true);
        }
        stopped.get()
    };
    let src_id = graph.nodes[plan.source].id.as_str();
    let Stage::Source(src) = &graph.nodes[plan.source].stage else {
        return Err(crate::RunError {
            stage: src_id.to_string(),
            trial: None,
            message: "not a source (internal error)".into(),
        });
    };
    let rerr = |stage: &str, trial: Option<&str>, e: StageError| crate::RunError {
        stage: stage.to_string(),
        trial: trial.map(str::to_string),
        message: e.message,
    };
    let estimators: Vec<usize> = plan
        .stages
        .iter()
        .map(|(i, _)| *i)
        .filter(|&i| matches!(graph.nodes[i].stage, Stage::Estimator(_)))
        .collect();
    let mut finals: Vec<Vec<crate::Item>> = vec![Vec::new(); graph.nodes.len()];
    let live = src.live();
    // One trial: its stream, the samples fed so far and their rate.
    struct Open<'p> {
        stream: TrialStream<'p>,
        meta: crate::TrialMeta,
        fed: usize,
        fs: f64,
    }
    // Filled as trials stream; the sinks' reports are added at the end.
    let mut run = LiveRun {
        reports: Vec::new(),
        trials: 0,
        stream_s: 0.0,
        latency: BlockLatency::default(),
        stages: plan
            .stages
            .iter()
            .map(|(i, _)| (graph.nodes[*i].id.clone(), BlockLatency::default()))
            .collect(),
        estimates: Vec::new(),
        stopped: false,
    };
    let push = |open: &mut Open<'_>,
                b: Payload,
                run: &mut LiveRun,
                on_update: &mut dyn FnMut(&LiveUpdate)|
     -> Result<(), crate::RunError> {
        if let Ok(s) = b.signals() {
            open.fed += s.n_samples();
            open.fs = s.sample_rate_hz;
        }
        let t_ms = open.fed as f64 * 1000.0 / open.fs;
        let meta = &open.meta;
        let t0 = std::time::Instant::now();
        // The caller's time (printing the estimate) is not the chain's.
        let mut theirs = std::time::Duration::ZERO;
        let r = open.stream.push(b, &mut |node, out| {
            if let (true, Ok(e)) = (estimators.contains(&node), out.estimate()) {
                let u0 = std::time::Instant::now();
                on_update(&LiveUpdate {
                    trial_id: meta.trial_id.clone(),
                    stage: graph.nodes[node].id.clone(),
                    t_ms,
                    estimate: (**e).clone(),
                    last: false,
                });
                theirs += u0.elapsed();
            }
        });
        let ns = t0.elapsed().saturating_sub(theirs).as_nanos();
        run.latency.add(u64::try_from(ns).unwrap_or(u64::MAX));
        r
    };
    let finish = |open: Open<'_>,
                  finals: &mut Vec<Vec<crate::Item>>,
                  run: &mut LiveRun,
                  on_update: &mut dyn FnMut(&LiveUpdate)|
     -> Result<(), crate::RunError> {
        let t_ms = if open.fs > 0.0 {
            open.fed as f64 * 1000.0 / open.fs
        } else {
            0.0
        };
        run.trials += 1;
        run.stream_s += t_ms / 1000.0;
        let (kept, timing) = open.stream.finish_timed(&mut |_, _| {})?;
        for ((_, total), trial) in run.stages.iter_mut().zip(timing.iter().flatten()) {
            total.merge(trial);
        }
        for (node, blocks) in kept {
            if let (true, Some(last)) = (estimators.contains(&node), blocks.last()) {
                if let Ok(e) = last.estimate() {
                    on_update(&LiveUpdate {
                        trial_id: open.meta.trial_id.clone(),
                        stage: graph.nodes[node].id.clone(),
                        t_ms,
                        estimate: (**e).clone(),
                        last: true,
                    });
                }
                finals[node].push(crate::Item {
                    meta: std::sync::Arc::new(open.meta.clone()),
                    payload: last.clone(),
                });
            }
        }
        Ok(())
    };
    match live {
        Some(live) => {
            let mut open: Option<Open<'_>> = None;
            let mut index = 0usize;
            let stop_err = || crate::RunError {
                stage: src_id.to_string(),
                trial: None,
                message: STOPPED.into(),
            };
            let r = live.stream(&mut |ev| match ev {
                _ if stopped.get() => Err(stop_err()),
                SourceEvent::Start(mut meta) => {
                    if let Some(o) = open.take() {
                        finish(o, &mut finals, &mut run, &mut on_update)?;
                        if stopped.get() {
                            return Err(stop_err());
                        }
                    }
                    meta.index = index;
                    index += 1;
                    let mut stream = plan.start_trial(graph, &meta, false)?;
                    stream.time_stages(Vec::new());
                    open = Some(Open {
                        stream,
                        meta,
                        fed: 0,
                        fs: 0.0,
                    });
                    Ok(())
                }
                SourceEvent::Block(b) => match open.as_mut() {
                    Some(o) => {
                        push(o, b, &mut run, &mut on_update)?;
                        if poll() {
                            return Err(stop_err());
                        }
                        Ok(())
                    }
                    None => Err(crate::RunError {
                        stage: src_id.to_string(),
                        trial: None,
                        message: "a block came before its trial began (internal error)".into(),
                    }),
                },
                SourceEvent::End => match open.take() {
                    Some(o) => finish(o, &mut finals, &mut run, &mut on_update),
                    None => Ok(()),
                },
                SourceEvent::Tick if poll() => Err(stop_err()),
                SourceEvent::Tick => Ok(()),
            });
            match r {
                // The trial under way, if any, is dropped.
                Err(e) if stopped.get() && e.message == STOPPED => {}
                Err(e) => return Err(e),
                Ok(()) => {
                    if let Some(o) = open.take() {
                        finish(o, &mut finals, &mut run, &mut on_update)?;
                    }
                }
            }
        }
        None => {
            let mut metas = src.trials().map_err(|e| rerr(src_id, None, e))?;
            for (k, m) in metas.iter_mut().enumerate() {
                m.index = k;
            }
            for meta in &metas {
                if poll() {
                    break;
                }
                let ctx = TrialContext {
                    stage_id: src_id,
                    meta,
                    seed: crate::derive_seed(graph.run.seed, &[src_id, &meta.trial_id]),
                };
                let payload = src
                    .produce(&ctx)
                    .map_err(|e| rerr(src_id, Some(&meta.trial_id), e))?;
                let signals = payload
                    .signals()
                    .map_err(|e| rerr(src_id, Some(&meta.trial_id), e))?;
                let mut stream = plan.start_trial(graph, meta, false)?;
                stream.time_stages(Vec::new());
                let mut open = Open {
                    stream,
                    meta: meta.clone(),
                    fed: 0,
                    fs: signals.sample_rate_hz,
                };
                for b in signal_blocks(signals, block) {
                    push(&mut open, b, &mut run, &mut on_update)?;
                    if poll() {
                        break;
                    }
                }
                if stopped.get() {
                    // The trial under way is dropped.
                    break;
                }
                finish(open, &mut finals, &mut run, &mut on_update)?;
                if stopped.get() {
                    break;
                }
            }
        }
    }
    run.stopped = stopped.get();
    // Sinks, as after a batch run, on the estimators' final answers.
    for &i in &graph.order {
        let node = &graph.nodes[i];
        let Stage::Sink(sink) = &node.stage else { continue };
        if !graph.input_index[i].iter().all(|j| estimators.contains(j)) {
            continue;
        }
        std::fs::create_dir_all(&graph.out_dir).map_err(|e| {
            rerr(
                &node.id,
                None,
                StageError::new(format!("cannot create {}: {e}", graph.out_dir.display())),
            )
        })?;
        let inputs: Vec<crate::SinkInput<'_>> = graph.input_index[i]
            .iter()
            .map(|&j| crate::SinkInput {
                stage_id: &graph.nodes[j].id,
                items: &finals[j],
            })
            .collect();
        let ctx = crate::SinkContext {
            stage_id: &node.id,
            out_dir: &graph.out_dir,
        };
        let report = sink.consume(&inputs, &ctx).map_err(|e| rerr(&node.id, None, e))?;
        crate::stage::check_sink_files(&run.reports, &node.id, &report)
            .map_err(|e| rerr(&node.id, None, StageError::new(e)))?;
        run.reports.push((node.id.clone(), report));
    }
    run.estimates = estimators
        .iter()
        .map(|&i| (graph.nodes[i].id.clone(), std::mem::take(&mut finals[i])))
        .collect();
    Ok(run)
}

#[cfg(test)]
mod tests {
    use super::BlockLatency;
    use proptest::prelude::*;

    /// The exact `q`-quantile as [`BlockLatency::quantile_ns`] defines its rank.
    fn exact(sorted: &[u64], q: f64) -> u64 {
        let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
        sorted[rank - 1]
    }

    #[test]
    fn bins_cover_every_value_in_order() {
        let mut last = 0;
        for ns in (0..4096u64).chain([u64::MAX / 3, u64::MAX - 1, u64::MAX]) {
            let b = BlockLatency::bin(ns);
            assert!(b >= last && b < super::LATENCY_BINS, "{ns}");
            assert!(BlockLatency::upper(b) >= ns, "{ns} above its bin's edge");
            last = b;
        }
        assert_eq!(BlockLatency::upper(BlockLatency::bin(u64::MAX)), u64::MAX);
    }

    #[test]
    fn no_block_gives_zeros() {
        let l = BlockLatency::default();
        assert_eq!((l.blocks(), l.quantile_ns(0.5), l.max_ns()), (0, 0, 0));
        assert_eq!(l.mean_ns(), 0.0);
    }

    proptest! {
        /// A quantile is never below the exact one and at most 12.5 % above
        /// it; the mean and maximum are exact.
        #[test]
        fn quantiles_bound_the_exact_ones(
            mut v in proptest::collection::vec(0u64..50_000_000_000, 1..300),
            q in 0.0f64..=1.0,
        ) {
            let mut l = BlockLatency::default();
            v.iter().for_each(|&x| l.add(x));
            v.sort_unstable();
            let (got, want) = (l.quantile_ns(q), exact(&v, q));
            prop_assert!(got >= want, "{got} < {want}");
            prop_assert!(got as f64 <= want as f64 * 1.125 + 1.0, "{got} vs {want}");
            prop_assert_eq!(l.max_ns(), *v.last().unwrap_or(&0));
            prop_assert_eq!(l.quantile_ns(1.0), l.max_ns());
            let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
            prop_assert!((l.mean_ns() - mean).abs() <= 1e-9 * mean.max(1.0));
        }

        /// Merging two records is recording both: the per-trial stage
        /// timings of a live run add up to one record.
        #[test]
        fn a_merge_is_the_record_of_both(
            a in proptest::collection::vec(0u64..u64::MAX, 0..100),
            b in proptest::collection::vec(0u64..u64::MAX, 0..100),
        ) {
            let (mut la, mut lb, mut both) =
                (BlockLatency::default(), BlockLatency::default(), BlockLatency::default());
            a.iter().for_each(|&x| { la.add(x); both.add(x) });
            b.iter().for_each(|&x| { lb.add(x); both.add(x) });
            la.merge(&lb);
            prop_assert_eq!(&la, &both);
            prop_assert_eq!(la.total_ns(), a.iter().chain(&b).map(|&x| u128::from(x)).sum::<u128>());
        }
    }
}
