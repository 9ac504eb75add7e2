//! Memory of the batch and the streaming paths against input length, shared by
//! the `memory` bench (`benches/memory.rs`, release, 10 / 100 / 1000 s) and its
//! test (`tests/memory.rs`, debug, shorter lengths).
//!
//! **Counting.** [`Counting`] wraps the system allocator and keeps the bytes
//! currently allocated and their peak, process-wide (atomics, so rayon's
//! threads count too). Each binary installs it with
//! `#[global_allocator] static A: Counting = Counting;`. Allocation sizes are
//! deterministic, so the figures are exact and repeatable (unlike RSS: the
//! allocator's own overhead and free pages are not counted).
//!
//! **Input.** The lab scene's 45-degree trials (graphs/scenes/lab.toml: every
//! physical effect, 16 taxels at 1 kHz, ~19 s each: 2 s at rest on the
//! object, the slide off it at 2 mm/s, 2 s at rest), simulated with the
//! quickstart's seed, played back to back and cut to `T` seconds: a robot
//! palpating the same edge over and over. Between palpations the array, off
//! the object at the end of one, is lowered back onto it at the start
//! position: a 1 s linear ramp from each taxel's last reading to its next
//! first reading (a jump would be a 1.5 V step whose slope, ~50x any
//! crossing's, would set the batch drive's per-trial gain and silence every
//! crossing). A 10 s input is the first palpation's rest and the first half
//! of its crossing; 1000 s is ~44 palpations. Repeating real
//! palpations keeps the spike density, the images and the WSS work per second
//! what a real trial gives at every length, which a single slower crossing
//! would not (an FA-I afferent responds to the rate of change: at 0.02 mm/s
//! it hardly fires, and the templates are for 2 mm/s).
//!
//! **Batch** ([`batch_peak`]): the chain of `graphs/quickstart.toml` from the
//! scene's signals to the estimate (lowpass -> normalize -> drive ->
//! izhikevich -> bin -> wss), its stages built from that file and run as the
//! runtime runs them (each stage's output replaces its input, which is then
//! freed). Its peak includes the input signals, which a batch must hold.
//!
//! **Streaming** ([`stream_peak`]): the streaming plan of graphs/live.toml
//! (what `palpate run graphs/live.toml --live` and `palpate daq run` run),
//! built inside the measurement (WSS templates included) and fed the input as
//! one trial, one sample frame at a time, as the `daq` source hands it on; the
//! input is not counted (a DAQ delivers it frame by frame).

#![allow(dead_code)]

use palpate::core::{self, derive_seed, FitContext, Item, LoadOptions, RunOptions, Stage, TrialContext};
use palpate::core::{Estimate, Signals};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::Arc;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

/// The system allocator, counting live bytes and their peak.
pub struct Counting;

fn grow(n: usize) {
    let now = CURRENT.fetch_add(n, Relaxed) + n;
    PEAK.fetch_max(now, Relaxed);
}

fn shrink(n: usize) {
    CURRENT.fetch_sub(n, Relaxed);
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            grow(l.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(l) };
        if !p.is_null() {
            grow(l.size());
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        shrink(l.size());
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        let q = unsafe { System.realloc(p, l, new) };
        if !q.is_null() {
            if new >= l.size() {
                grow(new - l.size());
            } else {
                shrink(l.size() - new);
            }
        }
        q
    }
}

/// Bytes allocated now.
pub fn live_bytes() -> usize {
    CURRENT.load(Relaxed)
}

/// Restarts peak tracking from the current level; returns that level.
pub fn reset_peak() -> usize {
    let now = CURRENT.load(Relaxed);
    PEAK.store(now, Relaxed);
    now
}

/// Largest level since the last [`reset_peak`].
pub fn peak_bytes() -> usize {
    PEAK.load(Relaxed)
}

/// Runs `f` and returns its result with the peak level reached during it;
/// the overall peak still covers it.
pub fn with_peak<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let outer = peak_bytes();
    reset_peak();
    let v = f();
    let inner = peak_bytes();
    PEAK.fetch_max(outer, Relaxed);
    (v, inner)
}

pub const ANGLE: f64 = 45.0;
pub const FS: f64 = 1000.0;
pub const MIB: f64 = 1024.0 * 1024.0;

/// The worktree root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf()
}

/// `graphs/quickstart.toml`, loaded (its stages built), reports to a temp dir.
pub fn quickstart() -> core::Graph {
    palpate::link();
    let out = std::env::temp_dir().join(format!("palpate-memory-{}", std::process::id()));
    core::load_file(
        &root().join("graphs/quickstart.toml"),
        &LoadOptions {
            out: Some(out),
            ..LoadOptions::default()
        },
    )
    .expect("graphs/quickstart.toml")
}

/// The lab scene's first `n` trials at 45 degrees, exactly as the quickstart
/// graph (same file, same seed) simulates them.
pub fn lab_trials(n: usize) -> Vec<Item> {
    palpate::link();
    let g = quickstart();
    let text = format!(
        "[run]\nseed = {}\n[stages.scene]\ntype = \"scene\"\nfile = \"scenes/lab.toml\"\nangles = [{ANGLE}]\n\
         trials_per_angle = {n}\n",
        g.run.seed
    );
    let opts = LoadOptions {
        base_dir: Some(root().join("graphs")),
        out: Some(std::env::temp_dir()),
        ..LoadOptions::default()
    };
    let g = core::load_str(&text, "scene.toml", "scene", &opts).expect("scene graph");
    let r = core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .expect("lab scene");
    r.outputs["scene"].as_ref().clone()
}

/// The lab scene's palpation speed (graphs/scenes/lab.toml), mm/s.
const LAB_SPEED_MM_S: f64 = 2.0;

/// Samples of the touch-down ramp between palpations (1 s at 1 kHz).
pub const RAMP: usize = 1000;

/// `trials` played back to back, cycled, joined by [`RAMP`]-sample linear
/// ramps (the array lowered back onto the object), cut to `seconds` (see the
/// module docs). Allocated once at its final size, so building it leaves no
/// slack.
pub fn long_input(trials: &[Item], seconds: f64) -> Item {
    let sigs: Vec<&Arc<Signals>> = trials
        .iter()
        .map(|t| t.payload.signals().expect("signals"))
        .collect();
    let first = sigs[0];
    assert_eq!(first.sample_rate_hz, FS);
    let n = (seconds * FS).round() as usize;
    let mut data: Vec<Vec<f64>> = (0..first.data.len()).map(|_| Vec::with_capacity(n)).collect();
    let mut r = 0;
    while data[0].len() < n {
        let s = sigs[r % sigs.len()];
        if r > 0 {
            // Lowering the array: from where the last palpation ended to
            // where this one starts, linearly over RAMP samples.
            for (d, xs) in data.iter_mut().zip(&s.data) {
                let (a, b) = (*d.last().expect("a sample"), xs[0]);
                let take = (n - d.len()).min(RAMP);
                d.extend((1..=take).map(|j| a + (b - a) * j as f64 / (RAMP + 1) as f64));
            }
        }
        let take = (n - data[0].len()).min(s.n_samples());
        for (d, xs) in data.iter_mut().zip(&s.data) {
            d.extend_from_slice(&xs[..take]);
        }
        r += 1;
    }
    let mut meta = (*trials[0].meta).clone();
    meta.crossing_ms = None;
    Item {
        meta: Arc::new(meta),
        payload: first.with_data(first.unit.clone(), data).into(),
    }
}

/// The quickstart's chain after the scene.
pub const CHAIN: [&str; 6] = ["filter", "norm", "drive", "enc", "bins", "wss"];

/// Runs `item` through the quickstart's stages `CHAIN` as the runtime does
/// (same per-trial seeds; each input dropped once its successor exists).
pub fn run_chain(g: &core::Graph, item: Item) -> Item {
    run_chain_peaks(g, item).0
}

/// [`run_chain`], also returning each stage's peak heap level (bytes, all
/// live data included: its input, its output, its working memory).
pub fn run_chain_peaks(g: &core::Graph, mut item: Item) -> (Item, Vec<(&'static str, usize)>) {
    let mut peaks = Vec::new();
    for id in CHAIN {
        let node = &g.nodes[g.index_of(id).expect("quickstart stage")];
        let ctx = TrialContext {
            stage_id: id,
            meta: &item.meta,
            seed: derive_seed(g.run.seed, &[id, &item.meta.trial_id]),
        };
        let (payload, peak) = with_peak(|| match &node.stage {
            Stage::Map(m) => m.process(&[&item], &ctx),
            Stage::Estimator(e) => {
                assert!(!e.trained(), "{id}: the chain has no trained estimator");
                let fctx = FitContext {
                    stage_id: id,
                    fold: 0,
                    seed: derive_seed(g.run.seed, &[id, "fold0"]),
                };
                e.fit(&[], &fctx)
                    .and_then(|m| m.predict(&item, &ctx).map(Into::into))
            }
            _ => panic!("{id}: not a map or estimator"),
        });
        let payload = payload.unwrap_or_else(|e| panic!("{id}: {}", e.message));
        peaks.push((id, peak));
        item = Item {
            meta: item.meta.clone(),
            payload,
        };
    }
    (item, peaks)
}

/// What one measurement found.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Row {
    /// Input length, s.
    pub seconds: f64,
    /// Bytes of the input signals (16 taxels x samples x 8 B).
    pub input_bytes: usize,
    /// Peak bytes of the batch chain, input included.
    pub batch_peak_bytes: usize,
    /// Each batch stage's peak (same origin).
    pub batch_stage_peak_bytes: Vec<(&'static str, usize)>,
    /// Peak bytes of the streaming path (input excluded).
    pub stream_peak_bytes: usize,
    /// Bytes the streaming path held once built, before the first frame.
    pub stream_built_bytes: usize,
    /// Bytes the streaming path held at the end of the stream, before `finish`.
    pub stream_end_bytes: usize,
    /// Spike images the stream pushed into WSS.
    pub stream_images: usize,
    /// Batch estimate, degrees (None = no edge).
    pub batch_angle_deg: Option<f64>,
    /// Streaming final estimate, degrees.
    pub stream_angle_deg: Option<f64>,
    /// Wall time of the batch chain, s (information only).
    pub batch_wall_s: f64,
    /// Wall time of the stream, s (information only).
    pub stream_wall_s: f64,
}

/// What the batch chain used.
pub struct BatchMemory {
    /// Peak bytes, counted from before the input was made.
    pub peak: usize,
    /// Each stage's peak, same origin.
    pub stages: Vec<(&'static str, usize)>,
    pub estimate: Estimate,
}

/// Runs the batch chain on `input` (which it consumes; `input_bytes` its size).
pub fn batch_peak(g: &core::Graph, input: Item, input_bytes: usize) -> BatchMemory {
    let base = reset_peak() - input_bytes;
    let (out, stages) = run_chain_peaks(g, input);
    let peak = peak_bytes() - base;
    BatchMemory {
        peak,
        stages: stages.into_iter().map(|(id, p)| (id, p - base)).collect(),
        estimate: out.payload.estimate().expect("estimate").as_ref().clone(),
    }
}

/// What the streaming path used.
pub struct StreamMemory {
    /// Peak bytes.
    pub peak: usize,
    /// Bytes held once built, before the first frame.
    pub built: usize,
    /// Bytes held after the last frame, before the flush.
    pub end: usize,
    /// Spike images the stream made.
    pub images: usize,
    /// The final estimate.
    pub estimate: Estimate,
}

/// One sample frame of `sig` as a block.
fn frame_block(sig: &Signals, k: usize) -> core::Payload {
    Signals {
        sample_rate_hz: sig.sample_rate_hz,
        layout: sig.layout.clone(),
        unit: sig.unit.clone(),
        data: sig.data.iter().map(|xs| vec![xs[k]]).collect(),
    }
    .into()
}

/// Runs the streaming plan of `live` on `sig` as one trial, frame by frame.
pub fn stream_peak(live: &core::Graph, sig: &Signals) -> StreamMemory {
    let base = reset_peak();
    let plan = core::stream::plan(live).expect("graphs/live.toml streams");
    let meta = core::TrialMeta {
        trial_id: "long".into(),
        // The lab scene's palpation speed, as its trials declare it (WSS
        // warns once, allocating, when a trial declares none).
        speed_mm_s: Some(LAB_SPEED_MM_S),
        ..core::TrialMeta::default()
    };
    let mut t = plan.start_trial(live, &meta, false).expect("open");
    let built = live_bytes() - base;
    let mut images = 0usize;
    let mut count = |_: usize, b: &core::Payload| {
        if let Ok(i) = b.images() {
            images += i.n_frames;
        }
    };
    for k in 0..sig.n_samples() {
        t.push(frame_block(sig, k), &mut count).expect("push");
    }
    let end = live_bytes() - base;
    let kept = t.finish(&mut count).expect("finish");
    let estimate = kept
        .iter()
        .rev()
        .find_map(|(_, b)| {
            b.last()
                .and_then(|p| p.estimate().ok())
                .map(|e| e.as_ref().clone())
        })
        .expect("an estimate");
    StreamMemory {
        peak: peak_bytes() - base,
        built,
        end,
        images,
        estimate,
    }
}

/// Splits what the built streaming path holds: (the plan: WSS templates with
/// their spectra, built once per graph and shared by every trial; one trial's
/// own state, reserved when the trial opens).
pub fn stream_split(live: &core::Graph) -> (usize, usize) {
    let base = live_bytes();
    let plan = core::stream::plan(live).expect("graphs/live.toml streams");
    let meta = core::TrialMeta {
        speed_mm_s: Some(LAB_SPEED_MM_S),
        ..core::TrialMeta::default()
    };
    // The first trial builds the templates' streaming spectra (cached).
    drop(plan.start_trial(live, &meta, false).expect("open"));
    let templates = live_bytes() - base;
    let t = plan.start_trial(live, &meta, false).expect("open");
    let state = live_bytes() - base - templates;
    drop(t);
    (templates, state)
}

/// Measures both paths on `seconds` of input made from `trials`.
pub fn measure(g: &core::Graph, live: &core::Graph, trials: &[Item], seconds: f64) -> Row {
    let before = live_bytes();
    let input = long_input(trials, seconds);
    let input_bytes = live_bytes() - before;
    let sig = input.payload.signals().expect("signals").clone();
    let t0 = std::time::Instant::now();
    let stream = stream_peak(live, &sig);
    let stream_wall_s = t0.elapsed().as_secs_f64();
    drop(sig);
    let t0 = std::time::Instant::now();
    let batch = batch_peak(g, input, input_bytes);
    let batch_wall_s = t0.elapsed().as_secs_f64();
    Row {
        seconds,
        input_bytes,
        batch_peak_bytes: batch.peak,
        batch_stage_peak_bytes: batch.stages,
        stream_peak_bytes: stream.peak,
        stream_built_bytes: stream.built,
        stream_end_bytes: stream.end,
        stream_images: stream.images,
        batch_angle_deg: batch.estimate.angle_deg,
        stream_angle_deg: stream.estimate.angle_deg,
        batch_wall_s,
        stream_wall_s,
    }
}

/// graphs/live.toml, what `palpate daq run` streams.
pub fn live_graph() -> core::Graph {
    palpate::link();
    let out = std::env::temp_dir().join(format!("palpate-memory-live-{}", std::process::id()));
    core::load_file(
        &root().join("graphs/live.toml"),
        &LoadOptions {
            out: Some(out),
            ..LoadOptions::default()
        },
    )
    .expect("graphs/live.toml")
}

/// The table the bench prints.
pub fn table(rows: &[Row]) -> String {
    let mut s = String::from(
        "| input s | input MiB | batch peak MiB | batch B per input s | streaming peak MiB | \
         streaming built MiB | streaming at end MiB | images | batch / stream angle |\n\
         | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |\n",
    );
    let deg = |a: Option<f64>| a.map_or("none".to_string(), |a| format!("{a:.1}"));
    for r in rows {
        s += &format!(
            "| {} | {:.2} | {:.2} | {:.0} | {:.3} | {:.3} | {:.3} | {} | {} / {} |\n",
            r.seconds,
            r.input_bytes as f64 / MIB,
            r.batch_peak_bytes as f64 / MIB,
            r.batch_peak_bytes as f64 / r.seconds,
            r.stream_peak_bytes as f64 / MIB,
            r.stream_built_bytes as f64 / MIB,
            r.stream_end_bytes as f64 / MIB,
            r.stream_images,
            deg(r.batch_angle_deg),
            deg(r.stream_angle_deg),
        );
    }
    s
}

/// Each batch stage's peak, MiB, one row per length.
pub fn stage_table(rows: &[Row]) -> String {
    let mut s = String::from("| input s |");
    for id in CHAIN {
        s += &format!(" {id} |");
    }
    s += "\n| ---: |";
    s += &" ---: |".repeat(CHAIN.len());
    s += "\n";
    for r in rows {
        s += &format!("| {} |", r.seconds);
        for (_, b) in &r.batch_stage_peak_bytes {
            s += &format!(" {:.2} |", *b as f64 / MIB);
        }
        s += "\n";
    }
    s
}
