//! The live path (`palpate_stages::io::live`): frame-by-frame equality with the
//! batch graph, end to end through a pseudo-terminal, corrupted streams, and
//! constant memory.

use palpate_core::{LoadOptions, RunOptions, Signals};
use palpate_stages::io::daq::{
    emulate_pty, encode_frame, AcquireOptions, EmulateOptions, SampleFormat, StopReason,
};
use palpate_stages::io::live::{
    run_live, run_live_serial, simulate_trial, wss_delay_line_bytes, wss_stream_bytes, LiveConfig, LiveEnd,
    LivePipeline, LiveUpdate,
};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Counts this thread's net allocated bytes (tests run on separate threads).
struct Counting;

thread_local! {
    static NET: Cell<i64> = const { Cell::new(0) };
}

fn count(d: i64) {
    let _ = NET.try_with(|n| n.set(n.get() + d));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        count(l.size() as i64);
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        count(-(l.size() as i64));
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        count(new as i64 - l.size() as i64);
        unsafe { System.realloc(p, l, new) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

fn net_bytes() -> i64 {
    NET.with(Cell::get)
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn lab_scene() -> PathBuf {
    root().join("graphs/scenes/lab.toml")
}

/// The shipped live config.
fn config() -> LiveConfig {
    LiveConfig::from_file(&root().join("graphs/live.toml")).unwrap()
}

const ANGLE: f64 = 60.0;
const SEED: u64 = 3;

fn trial() -> Signals {
    simulate_trial(&lab_scene(), ANGLE, SEED).unwrap()
}

fn feed(p: &mut LivePipeline, s: &Signals) {
    let mut frame = vec![0.0; s.data.len()];
    for k in 0..s.n_samples() {
        for (f, xs) in frame.iter_mut().zip(&s.data) {
            *f = xs[k];
        }
        p.push(&frame).unwrap();
    }
}

/// The DAQ byte stream of `s` (f32 frames, sequence from 0), one `Vec` per frame.
fn frames(s: &Signals) -> Vec<Vec<u8>> {
    (0..s.n_samples())
        .map(|k| {
            let raw: Vec<f64> = s.data.iter().map(|xs| xs[k]).collect();
            let mut b = Vec::new();
            encode_frame(&mut b, SampleFormat::F32, k as u32, k as u64 * 1000, &raw);
            b
        })
        .collect()
}

/// (a) Frame by frame through `LivePipeline` equals the batch graph with the
/// same causal settings: the same spike events bit for bit (causal filter,
/// causal normalization, fixed gain and the hold input make every sample's
/// current identical, and the streaming neuron step is the batch encoder's
/// arithmetic), hence the same per-taxel spike counts and number of images,
/// and the same estimate (class; scores to WssStream's rounding). The trial
/// also equals the graph's scene output, so `simulate_trial` reproduces the
/// graph's seeds.
#[test]
fn pipeline_equals_the_batch_graph_on_a_lab_trial() {
    let cfg = config();
    let (lp, nm, gain) = (&cfg.lowpass, &cfg.normalize, cfg.drive.gain.unwrap());
    let graph = format!(
        r#"
[run]
seed = {SEED}
[stages.scene]
type = "scene"
file = "{scene}"
angles = [{ANGLE}]
trials_per_angle = 1
[stages.filter]
type = "lowpass"
inputs = ["scene"]
mode = "causal"
order = {order}
cutoff_hz = {cutoff}
[stages.norm]
type = "normalize"
inputs = ["filter"]
mode = "causal"
baseline_ms = {baseline}
span = {span}
[stages.drive]
type = "drive"
inputs = ["norm"]
kind = "fa_i"
gain = {gain}
[stages.enc]
type = "izhikevich"
inputs = ["drive"]
dt_ms = {dt}
[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = {window}
hop_ms = {hop}
[stages.wss]
type = "wss"
inputs = ["bins"]
{wss}
[stages.mae]
type = "mae"
inputs = ["wss"]
"#,
        scene = lab_scene().display(),
        order = lp.order,
        cutoff = lp.cutoff_hz,
        baseline = nm.baseline_ms,
        span = nm.span.unwrap(),
        dt = cfg.encoder.dt_ms,
        window = cfg.bin.window_ms,
        hop = cfg.bin.hop_ms,
        // The live graph's WSS keys, so both sides use the same settings.
        wss = match toml::Value::try_from(&cfg.wss).unwrap() {
            toml::Value::Table(t) => t.iter().map(|(k, v)| format!("{k} = {v}\n")).collect::<String>(),
            other => panic!("WssConfig serialized as {other}"),
        },
    );
    palpate_stages::link();
    let dir = tempfile::tempdir().unwrap();
    let opts = LoadOptions {
        out: Some(dir.path().to_path_buf()),
        ..LoadOptions::default()
    };
    let g = palpate_core::load_str(&graph, "batch.toml", "batch", &opts).unwrap();
    let r = palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let sig = r.outputs["scene"][0].payload.signals().unwrap().clone();
    let spikes = r.outputs["enc"][0].payload.spikes().unwrap().clone();
    let images = r.outputs["bins"][0].payload.images().unwrap().clone();
    let batch = r.outputs["wss"][0].payload.estimate().unwrap().clone();

    let ours = trial();
    assert_eq!(
        ours.data, sig.data,
        "simulate_trial differs from the graph's trial"
    );

    let mut p = LivePipeline::new(&cfg).unwrap();
    p.keep_spikes(true);
    feed(&mut p, &sig);
    let fin = p.finish().unwrap();

    assert!(spikes.events.len() > 500, "{} spikes", spikes.events.len());
    assert_eq!(p.spike_events(), spikes.events, "spike trains differ");
    let mut per_taxel = vec![0u64; 16];
    for e in &spikes.events {
        per_taxel[e.taxel as usize] += 1;
    }
    assert_eq!(p.spike_counts(), per_taxel.as_slice());
    assert_eq!(p.frames(), images.n_frames);
    assert_eq!(p.samples() as usize, sig.n_samples());

    assert_eq!(fin.angle_deg, Some(ANGLE));
    assert_eq!(fin.class_deg, batch.class_deg);
    assert_eq!(fin.estimate.best_frame, batch.best_frame);
    for (a, b) in fin.estimate.scores.iter().zip(&batch.scores) {
        assert!((a.score - b.score).abs() < 1e-9, "{a:?} vs {b:?}");
    }
    assert!(fin.score > 0.5 && fin.margin > 0.0, "{fin:?}");

    // graphs/live.toml as a graph (its lab scene cut to this trial).
    let text = std::fs::read_to_string(root().join("graphs/live.toml")).unwrap();
    let mut doc: toml::Table = toml::from_str(&text).unwrap();
    let scene = doc["stages"]["scene"].as_table().unwrap().clone();
    let mut scene = scene;
    scene.insert("file".into(), lab_scene().display().to_string().into());
    scene.insert("angles".into(), toml::Value::Array(vec![ANGLE.into()]));
    scene.insert("trials_per_angle".into(), 1.into());
    doc["stages"]
        .as_table_mut()
        .unwrap()
        .insert("scene".into(), scene.into());
    doc["run"]
        .as_table_mut()
        .unwrap()
        .insert("seed".into(), (SEED as i64).into());
    let live = toml::to_string(&doc).unwrap();
    let g = palpate_core::load_str(&live, "live.toml", "live", &opts).unwrap();
    let r = palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    // graphs/live.toml is an ordinary graph of causal stages: its batch WSS
    // answers as the live pipeline did (scores to the stream's 1e-9).
    let offline = r.outputs["wss"][0].payload.estimate().unwrap().clone();
    assert_eq!(offline.angle_deg, fin.estimate.angle_deg);
    assert_eq!(offline.class_deg, fin.estimate.class_deg);
    for (a, b) in offline.scores.iter().zip(&fin.estimate.scores) {
        assert!((a.score - b.score).abs() < 1e-9, "{a:?} vs {b:?}");
    }
}

/// (b) End to end: `emulate_pty` plays the trial at 50x real time while
/// `run_live_serial` reads the pseudo-terminal's device; every frame sent is
/// received, none lost, and the final estimate is the true class.
#[test]
fn through_a_pseudo_terminal_at_50x() {
    let sig = trial();
    let n = sig.n_samples() as u64;
    let (tx, rx) = std::sync::mpsc::channel();
    let play = sig.clone();
    let player = std::thread::spawn(move || {
        emulate_pty(
            &play,
            &EmulateOptions {
                speed: 50.0,
                ..Default::default()
            },
            move |path| tx.send(path.to_string()).unwrap(),
        )
    });
    let path = rx.recv().unwrap();
    let cfg = config();
    let opts = AcquireOptions {
        max_frames: Some(n),
        give_up_after: Some(Duration::from_secs(10)),
        ..Default::default()
    };
    let mut updates = Vec::new();
    let report = run_live_serial(&path, 115_200, &cfg, &opts, None, |u| updates.push(u.clone())).unwrap();
    let sent = player.join().unwrap().unwrap();
    assert_eq!(sent.frames, n);
    assert_eq!(report.stats.frames, n, "{}", report.stats);
    assert_eq!(
        (report.stats.lost_frames, report.stats.crc_errors, report.held),
        (0, 0, 0)
    );
    assert_eq!(report.ended, LiveEnd::Acquisition(StopReason::MaxFrames));
    assert_eq!(report.final_estimate.angle_deg, Some(ANGLE));
    let rate = report.measured_rate_hz.unwrap();
    assert!((rate - 1000.0).abs() < 1e-6, "{rate}");
    // Updates: changes of the running answer, then the final one last.
    assert!(matches!(updates.last(), Some(LiveUpdate::Final(_))));
    let changes: Vec<_> = updates
        .iter()
        .filter_map(|u| match u {
            LiveUpdate::Estimate(e) => Some(e),
            _ => None,
        })
        .collect();
    assert!(!changes.is_empty());
    assert!(changes
        .windows(2)
        .all(|w| w[0].class_deg != w[1].class_deg && w[0].t_ms < w[1].t_ms));
}

/// (c) A corrupted stream: flipped bytes (CRC errors), dropped frames and
/// garbage between frames are counted, lost frames are held, and the run
/// still ends with the right estimate. A gap longer than `max_gap_ms` ends the
/// run with the estimate of what came before; a NaN sample is reported.
#[test]
fn corrupted_stream_is_counted_and_still_estimated() {
    let sig = trial();
    let fr = frames(&sig);
    let mut bytes = Vec::new();
    let (mut flipped, mut dropped) = (0u64, 0u64);
    for (k, f) in fr.iter().enumerate() {
        if k > 0 && k % 997 == 0 {
            dropped += 1;
            continue;
        }
        let mut f = f.clone();
        if k > 0 && k % 613 == 0 {
            f[20] ^= 0x5A; // a sample byte: the CRC fails
            flipped += 1;
        }
        if k % 1500 == 7 {
            bytes.extend_from_slice(&[0x00, 0xAA, 0x13, 0x55]); // garbage
        }
        bytes.extend_from_slice(&f);
    }
    let cfg = config();
    let mut updates = Vec::new();
    let report = run_live(Cursor::new(bytes), &cfg, &AcquireOptions::default(), |u| {
        updates.push(u.clone())
    })
    .unwrap();
    let s = &report.stats;
    assert!(flipped > 10 && dropped > 10);
    assert_eq!(s.crc_errors, flipped, "{s}");
    assert_eq!(s.lost_frames, flipped + dropped, "{s}");
    assert_eq!(report.held, flipped + dropped);
    assert_eq!(s.frames + report.held, sig.n_samples() as u64);
    assert!(s.garbage_bytes > 0);
    assert_eq!(report.ended, LiveEnd::Acquisition(StopReason::EndOfStream));
    let crc_updates = updates
        .iter()
        .filter(|u| matches!(u, LiveUpdate::CrcError { .. }))
        .count() as u64;
    assert_eq!(crc_updates, flipped);
    let held: u64 = updates
        .iter()
        .map(|u| match u {
            LiveUpdate::Lost {
                count, held: true, ..
            } => *count,
            _ => 0,
        })
        .sum();
    assert_eq!(held, flipped + dropped);
    assert_eq!(report.final_estimate.angle_deg, Some(ANGLE));

    // A 1.5 s gap after the crossing (in the final hold), and a NaN sample.
    let n = fr.len();
    let mut bytes = Vec::new();
    for (k, f) in fr.iter().enumerate() {
        if (n - 1800..n - 300).contains(&k) {
            continue;
        }
        if k == 100 {
            let mut raw: Vec<f64> = sig.data.iter().map(|xs| xs[k]).collect();
            raw[5] = f64::NAN;
            encode_frame(&mut bytes, SampleFormat::F32, k as u32, k as u64 * 1000, &raw);
            continue;
        }
        bytes.extend_from_slice(f);
    }
    let mut updates = Vec::new();
    let report = run_live(Cursor::new(bytes), &cfg, &AcquireOptions::default(), |u| {
        updates.push(u.clone())
    })
    .unwrap();
    assert_eq!(report.ended, LiveEnd::Gap(1500));
    assert!(report.error().unwrap().contains("1500 frames lost"));
    assert_eq!(report.non_finite, 1);
    assert!(updates.contains(&LiveUpdate::NonFinite { total: 1 }));
    assert_eq!(report.samples as usize, n - 1800);
    assert_eq!(report.final_estimate.angle_deg, Some(ANGLE));
}

/// (d) Memory is constant: what the pipeline holds beside the WSS stream
/// stays bounded (pending spikes, open images), the WSS stream reserves its
/// state when built (`wss_stream_bytes`: the frames its longest template
/// reads and its delay line, not a byte per image), and over a ~1.5 min
/// stream, long past the longest template (~37 s), nothing grows but the
/// stream's few kept alignments (48 B each). Before, the stream kept every
/// image's statistics (425 B per image: 170 kB over this stream).
#[test]
fn memory_is_constant() {
    let one = trial();
    let n = one.n_samples();
    let reps = 4;
    let cfg = config();
    let tpl = cfg.templates().unwrap();
    // The first pipeline builds the templates' streaming spectra (cached, shared).
    drop(LivePipeline::with_templates(&cfg, tpl.clone()).unwrap());
    let before = net_bytes();
    let mut p = LivePipeline::with_templates(&cfg, tpl.clone()).unwrap();
    let built = net_bytes() - before;
    let state = wss_stream_bytes(&tpl);
    assert!(state > wss_delay_line_bytes(&tpl));
    assert!(
        (built as usize) > state / 2 && (built as usize) < state + 128 * 1024,
        "built {built} B; the WSS stream's state {state} B"
    );
    let mut frame = vec![0.0; 16];
    let (mut max_pending, mut max_open) = (0, 0);
    let mut after_first = 0;
    for r in 0..reps {
        for k in 0..n {
            for (f, xs) in frame.iter_mut().zip(&one.data) {
                *f = xs[k];
            }
            p.push(&frame).unwrap();
            let (a, b) = p.buffered();
            max_pending = max_pending.max(a);
            max_open = max_open.max(b);
        }
        if r == 0 {
            after_first = net_bytes();
        }
    }
    let images = p.frames();
    assert!(images >= reps * n / 10 - 11, "{images}");
    let grown = net_bytes() - after_first;
    let kept = p.wss_candidates();
    assert!(kept <= 40 * 17, "{kept} alignments kept");
    assert!(
        grown < 16 * 1024 && net_bytes() - before < built + 32 * 1024,
        "grew {grown} B over {} images after the first trial ({kept} alignments kept)",
        images * (reps - 1) / reps
    );
    // Spikes wait at most one sample (16 taxels x 2 steps); images open at
    // most window/hop + 2.
    assert!(max_pending <= 32, "{max_pending}");
    assert!(max_open <= 12, "{max_open}");
    let fin = p.finish().unwrap();
    assert_eq!(fin.frames, (reps * n).div_ceil(10));
}

/// A stream that never changes: no spikes, "no edge", no NaN; the config
/// errors name their keys.
#[test]
fn silent_stream_and_config_errors() {
    let cfg = config();
    let mut p = LivePipeline::new(&cfg).unwrap();
    for k in 0..3000 {
        p.push(&[1.75 + if k % 2 == 0 { 0.0 } else { 1e-16 }; 16])
            .unwrap();
    }
    let e = p.finish().unwrap();
    assert_eq!(p.spike_counts().iter().sum::<u64>(), 0);
    assert_eq!(e.angle_deg, None);
    assert!(e.score.is_finite() && e.margin.is_finite());
    assert!(p.push(&[0.0; 16]).is_err());
    assert!(LivePipeline::new(&cfg).unwrap().push(&[0.0; 3]).is_err());

    let key = |c: LiveConfig| LivePipeline::new(&c).err().unwrap().key.unwrap();
    let mut c = cfg.clone();
    c.normalize.span = None;
    assert_eq!(key(c), "normalize.span");
    let mut c = cfg.clone();
    c.drive.gain = None;
    assert_eq!(key(c), "drive.gain");
    let mut c = cfg.clone();
    c.lowpass.cutoff_hz = 600.0;
    assert_eq!(key(c), "lowpass.cutoff_hz");
    let mut c = cfg.clone();
    c.encoder.input = palpate_stages::encode::InputMode::Linear;
    assert_eq!(key(c), "encoder.input");
    let mut c = cfg.clone();
    c.encoder.c = Some(40.0);
    assert_eq!(key(c), "encoder.c");
    let mut c = cfg.clone();
    c.stop_at_decision = true;
    assert_eq!(key(c), "stop_at_decision");
    // Every problem at once, not only the first.
    let mut c = cfg;
    c.normalize.span = None;
    c.drive.gain = None;
    c.lowpass.cutoff_hz = 600.0;
    c.bin.hop_ms = -1.0;
    let e = LivePipeline::new(&c).err().unwrap();
    let keys: Vec<_> = e
        .problems()
        .iter()
        .filter_map(|(k, _)| *k)
        .map(str::to_string)
        .collect();
    assert_eq!(
        keys,
        ["lowpass.cutoff_hz", "normalize.span", "drive.gain", "bin.hop_ms"],
        "{e}"
    );
    let e = LiveConfig::from_toml_str("[stages.a]\ntype = \"scene\"\n").unwrap_err();
    // An ordinary graph without the live chain's stages is refused by name.
    assert!(
        e.message.contains("exactly one stage") || e.message.contains("needs a `normalize` stage"),
        "{e}"
    );
    let e = LiveConfig::from_toml_str("sample_rate = 3\n").unwrap_err();
    assert!(e.message.contains("sample_rate"), "{e}");
}

fn shared_templates() -> std::sync::Arc<palpate_stages::estimate::wss::Templates> {
    static TPL: std::sync::OnceLock<std::sync::Arc<palpate_stages::estimate::wss::Templates>> =
        std::sync::OnceLock::new();
    TPL.get_or_init(|| config().templates().unwrap()).clone()
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(24))]
    /// Any stream (huge, tiny, constant, NaN or infinite samples, steps, lost
    /// frames) gives a finite answer without panicking: scores, margin and
    /// spike counts finite, and an edge only above the threshold.
    #[test]
    fn any_stream_gives_a_finite_answer(
        segs in proptest::collection::vec(
            (
                proptest::prop_oneof![
                    -1e12f64..1e12,
                    -1.0f64..1.0,
                    proptest::strategy::Just(f64::NAN),
                    proptest::strategy::Just(f64::INFINITY),
                    proptest::strategy::Just(0.0),
                ],
                1usize..600,
                0u64..40,
            ),
            1..8,
        ),
    ) {
        let cfg = config();
        let mut p = LivePipeline::with_templates(&cfg, shared_templates()).unwrap();
        for (v, len, lost) in segs {
            let frame: Vec<f64> = (0..16).map(|t| v * (1.0 + 0.1 * t as f64)).collect();
            for _ in 0..len {
                p.push(&frame).unwrap();
            }
            p.hold(lost).unwrap();
        }
        let e = p.finish().unwrap();
        proptest::prop_assert!(e.score.is_finite() && e.margin.is_finite());
        proptest::prop_assert!(e.estimate.scores.iter().all(|s| s.score.is_finite()));
        if e.angle_deg.is_some() {
            proptest::prop_assert!(e.score >= cfg.wss.threshold);
        }
        proptest::prop_assert_eq!(e.frames, (p.samples() as usize).div_ceil(10).max(1));
    }
}
