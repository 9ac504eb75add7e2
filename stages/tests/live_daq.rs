//! The live path end to end: the `daq` source stage reading frames that an
//! emulator writes into a pseudo-terminal, streamed through a graph
//! (`palpate_core::stream::replay`, what `palpate run --live` runs) with (a)
//! Izhikevich + WSS, (b) LIF + WSS, (c) LIF + a trained ANN and (d)
//! Izhikevich + a trained EDBN, each model fitted offline in the test on the
//! emulated lab scene, saved (`save_model`) and loaded (`model_in`); the
//! shipped graphs/live_ann.toml with its shipped model; a corrupted raw
//! recording read offline; an emulated scene's trials cut at
//! contact; bad settings.

mod common;

use palpate_core::stream::{self, LiveUpdate};
use palpate_core::{LoadOptions, RunOptions, Signals};
use palpate_stages::io::daq::{emulate_pty, encode_frame, simulate_trial, EmulateOptions, SampleFormat};
use std::path::{Path, PathBuf};

const ANGLE: f64 = 60.0;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn lab_scene() -> PathBuf {
    root().join("graphs/scenes/lab.toml")
}

/// The lab scene's 60-degree trial (seed 3), as a board would stream it.
fn trial() -> Signals {
    simulate_trial(&lab_scene(), ANGLE, 3).unwrap()
}

/// WSS as the graph's estimator (stage id `wss`).
const WSS: &str = "[stages.wss]
type = \"wss\"
inputs = [\"bins\"]
weighting = \"one_minus_sr\"
sigma_mm = 1.0
threshold = 0.1";

/// A live graph: `source` keys for the `daq` stage, then the causal chain of
/// graphs/live.toml with `encoder` (a stage table's keys) and WSS.
fn graph(source: &str, encoder: &str) -> palpate_core::Graph {
    graph_with(source, encoder, WSS, "palpate-live-daq")
}

/// [`graph`] with `estimator` (a whole stage table reading `bins`) instead of
/// WSS, its reports in the temporary folder `out`.
fn graph_with(source: &str, encoder: &str, estimator: &str, out: &str) -> palpate_core::Graph {
    palpate_stages::link();
    let front = common::causal_front_end("daq");
    let text = format!(
        r#"
[run]
seed = 1

[stages.daq]
type = "daq"
{source}

{front}
[stages.enc]
inputs = ["drive"]
{encoder}

[stages.bins]
type = "bin"
inputs = ["enc"]

{estimator}
"#
    );
    let opts = LoadOptions {
        out: Some(std::env::temp_dir().join(out)),
        base_dir: Some(root().join("graphs")),
        ..LoadOptions::default()
    };
    palpate_core::load_str(&text, "live_daq.toml", "live_daq", &opts).unwrap_or_else(|e| panic!("{e}"))
}

const IZHIKEVICH: &str = "type = \"izhikevich\"\npreset = \"fa_i\"\ninput = \"hold\"";
const LIF: &str = "type = \"lif\"";

/// Streams `g` live; every update, in order.
fn live(g: &palpate_core::Graph) -> Vec<LiveUpdate> {
    let plan = stream::plan(g).unwrap_or_else(|p| panic!("{p:?}"));
    let mut updates = Vec::new();
    stream::replay(g, &plan, 1, |u| updates.push(u.clone())).unwrap_or_else(|e| panic!("{e}"));
    updates
}

/// Plays `sig` into a pseudo-terminal as fast as the graph reads, streams a
/// graph whose `daq` source reads that port, and checks the answer.
fn through_a_pty(encoder: &str) -> Vec<LiveUpdate> {
    through_a_pty_with(encoder, WSS)
}

/// [`through_a_pty`] with `estimator` (a stage table) instead of WSS.
fn through_a_pty_with(encoder: &str, estimator: &str) -> Vec<LiveUpdate> {
    let sig = trial();
    let n = sig.n_samples() as u64;
    let (tx, rx) = std::sync::mpsc::channel();
    let play = sig.clone();
    let player = std::thread::spawn(move || {
        let opts = EmulateOptions {
            speed: f64::INFINITY,
            ..Default::default()
        };
        emulate_pty(&play, &opts, move |path| tx.send(path.to_string()).unwrap())
    });
    let port = rx.recv().unwrap();
    let g = graph_with(
        &format!("port = \"{port}\""),
        encoder,
        estimator,
        "palpate-live-daq",
    );
    let updates = live(&g);
    assert_eq!(player.join().unwrap().unwrap().frames, n);
    // One trial (the stream is one contact), the whole of it streamed.
    let last = updates.last().expect("an estimate");
    assert!(last.last, "the final estimate comes last");
    assert_eq!(last.trial_id, "daq-0000");
    assert!(updates.iter().all(|u| u.trial_id == "daq-0000"));
    assert!(
        (last.t_ms - sig.duration_ms()).abs() < 1e-6,
        "{} ms streamed of {} ms",
        last.t_ms,
        sig.duration_ms()
    );
    // The estimate changed as the frames came, before the end.
    let running: Vec<&LiveUpdate> = updates.iter().filter(|u| !u.last).collect();
    assert!(!running.is_empty());
    assert!(running.windows(2).all(|w| w[0].t_ms <= w[1].t_ms));
    assert!(running.iter().any(|u| u.t_ms < last.t_ms));
    updates
}

#[test]
fn izhikevich_and_wss_through_a_pseudo_terminal() {
    let updates = through_a_pty(IZHIKEVICH);
    assert_eq!(updates.last().unwrap().estimate.angle_deg, Some(ANGLE));
}

#[test]
fn lif_and_wss_through_a_pseudo_terminal() {
    let updates = through_a_pty(LIF);
    let e = &updates.last().unwrap().estimate;
    let a = e.angle_deg.expect("an edge");
    assert!((a - ANGLE).abs() <= 5.0, "LIF + WSS answered {a} deg");
}

/// Fits `estimator` (a trained stage's type and keys) offline on the
/// emulated lab scene (5 trials at each of 30, 60 and 90 degrees, run seed 1,
/// so none is the live trial) through the live chain with `encoder`, saving
/// each fold's model; returns fold 0's (fitted on 4 trials per class).
fn fit_offline(name: &str, encoder: &str, estimator: &str) -> PathBuf {
    let out = format!("palpate-live-daq-fit-{name}-{}", std::process::id());
    let source = "scene = \"scenes/lab.toml\"\nangles = [30.0, 60.0, 90.0]\ntrials_per_angle = 5";
    let table = format!("[stages.est]\ninputs = [\"bins\"]\n{estimator}\nsave_model = true");
    let g = graph_with(source, encoder, &table, &out);
    palpate_core::run(&g, &RunOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let model = std::env::temp_dir().join(&out).join("est.fold0.model.json");
    assert!(model.is_file(), "{} was not saved", model.display());
    model
}

/// The trial of [`trial`] as a raw recording (f32 frames, as the emulator
/// plays them into the pseudo-terminal).
fn recording(name: &str) -> PathBuf {
    let sig = trial();
    let mut bytes = Vec::new();
    let mut frame = vec![0.0; sig.data.len()];
    for k in 0..sig.n_samples() {
        for (f, xs) in frame.iter_mut().zip(&sig.data) {
            *f = xs[k];
        }
        encode_frame(&mut bytes, SampleFormat::F32, k as u32, k as u64 * 1000, &frame);
    }
    let dir = std::env::temp_dir().join("palpate-live-daq");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{name}-{}.daq", std::process::id()));
    std::fs::write(&path, &bytes).unwrap();
    path
}

/// A trained estimator fitted offline, then loaded with `model_in` and run
/// live through a pseudo-terminal: its final live estimate is the offline
/// (batch) estimate of the same trial read from a recording, bit for bit,
/// and it is the true angle.
fn trained_through_a_pty(name: &str, encoder: &str, estimator: &str) {
    let model = fit_offline(name, encoder, estimator);
    let kind = estimator.lines().next().unwrap_or_default();
    let table = format!(
        "[stages.est]\ninputs = [\"bins\"]\n{kind}\nmodel_in = {:?}",
        model.display().to_string()
    );
    let updates = through_a_pty_with(encoder, &table);
    let live_e = &updates.last().unwrap().estimate;
    let rec = recording(name);
    let g = graph_with(
        &format!("recording = {:?}", rec.display().to_string()),
        encoder,
        &table,
        "palpate-live-daq",
    );
    let out = palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let batch_e = out.outputs["est"][0].payload.estimate().unwrap();
    assert_eq!(live_e, batch_e.as_ref(), "{name}: live vs offline");
    assert_eq!(live_e.angle_deg, Some(ANGLE), "{name}: {live_e:?}");
    let _ = std::fs::remove_file(rec);
}

#[test]
fn lif_and_a_saved_ann_through_a_pseudo_terminal() {
    trained_through_a_pty(
        "ann",
        LIF,
        "type = \"ann\"\nhidden = 12\nmax_epochs = 40\nval_fraction = 0.0",
    );
}

#[test]
fn izhikevich_and_a_saved_edbn_through_a_pseudo_terminal() {
    trained_through_a_pty("edbn", IZHIKEVICH, "type = \"edbn\"");
}

/// The shipped graphs/live_ann.toml streams with its shipped model: on two
/// emulated trials it answers their angles live, as its batch run does.
#[test]
fn the_shipped_live_ann_graph_streams_its_saved_model() {
    palpate_stages::link();
    let text = std::fs::read_to_string(root().join("graphs/live_ann.toml"))
        .unwrap()
        .replace(
            "trials_per_angle = 2",
            "trials_per_angle = 1\nangles = [25.0, 80.0]",
        );
    let opts = LoadOptions {
        out: Some(std::env::temp_dir().join("palpate-live-daq-shipped")),
        base_dir: Some(root().join("graphs")),
        ..LoadOptions::default()
    };
    let g =
        palpate_core::load_str(&text, "live_ann.toml", "live_ann", &opts).unwrap_or_else(|e| panic!("{e}"));
    let finals: Vec<LiveUpdate> = live(&g).into_iter().filter(|u| u.last).collect();
    let answers: Vec<Option<f64>> = finals.iter().map(|u| u.estimate.angle_deg).collect();
    assert_eq!(answers, [Some(25.0), Some(80.0)]);
    assert!(finals.iter().all(|u| u.stage == "ann"));
    let out = palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    for (u, it) in finals.iter().zip(out.outputs["ann"].iter()) {
        assert_eq!(
            &u.estimate,
            it.payload.estimate().unwrap().as_ref(),
            "{}",
            u.trial_id
        );
    }
}

/// Offline and live, a recording with corrupted frames: a flipped byte (a
/// CRC error, so one frame lost), two frames dropped and garbage between
/// frames. Lost frames are held, so the trial keeps its length, and the
/// answer is the clean stream's.
#[test]
fn a_corrupted_recording_is_held_over_and_still_estimated() {
    let sig = trial();
    let n = sig.n_samples();
    let mut bytes = Vec::new();
    let mut frame = vec![0.0; sig.data.len()];
    for k in 0..n {
        if k == 3000 || k == 3001 {
            continue;
        }
        for (f, xs) in frame.iter_mut().zip(&sig.data) {
            *f = xs[k];
        }
        let start = bytes.len();
        encode_frame(&mut bytes, SampleFormat::F32, k as u32, k as u64 * 1000, &frame);
        if k == 5000 {
            bytes[start + 30] ^= 0x40;
        }
        if k == 7000 {
            bytes.extend_from_slice(b"noise\xAA\x55 noise");
        }
    }
    let dir = std::env::temp_dir().join("palpate-live-daq");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("corrupt.daq");
    std::fs::write(&path, &bytes).unwrap();
    let g = graph(
        &format!("recording = {:?}", path.display().to_string()),
        IZHIKEVICH,
    );
    let updates = live(&g);
    let last = updates.last().unwrap();
    assert_eq!(last.estimate.angle_deg, Some(ANGLE));
    assert!((last.t_ms - sig.duration_ms()).abs() < 1e-6, "{}", last.t_ms);
    // Offline, the same trial.
    let out = palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap();
    let s = out.outputs["daq"][0].payload.signals().unwrap().clone();
    assert_eq!(s.n_samples(), n);
    // Held: the dropped frames repeat frame 2999, the corrupted one 4999.
    assert_eq!(s.data[5][3000], s.data[5][2999]);
    assert_eq!(s.data[5][5000], s.data[5][4999]);
    assert_eq!(s.data[5][4000], sig.data[5][4000] as f32 as f64);
    let e = out.outputs["wss"][0].payload.estimate().unwrap().clone();
    assert_eq!(e.angle_deg, Some(ANGLE));
}

/// An emulated scene is cut at contact into exactly its trials (the gaps
/// between them read open), each equal to the scene's trial to f32 (the
/// frames' format) and carrying its label; `fixed` windows cut the same
/// stream every `window_ms`.
#[test]
fn an_emulated_scene_is_cut_into_its_trials() {
    let keys = "scene = \"scenes/lab.toml\"\nangles = [30.0, 75.0]\ntrials_per_angle = 1";
    let g = graph(keys, IZHIKEVICH);
    let opts = RunOptions {
        keep_outputs: true,
        ..RunOptions::default()
    };
    let out = palpate_core::run(&g, &opts).unwrap();
    let daq = &out.outputs["daq"];
    assert_eq!(daq.len(), 2);
    // The same trials from the scene itself (same stage id, so same seeds).
    let scene_text = format!(
        "[run]\nseed = 1\n[stages.daq]\ntype = \"scene\"\nfile = {:?}\nangles = [30.0, 75.0]\ntrials_per_angle = 1\n[stages.w]\ntype = \"write_signals\"\ninputs = [\"daq\"]\n",
        lab_scene().display().to_string()
    );
    let sg = palpate_core::load_str(
        &scene_text,
        "scene.toml",
        "scene",
        &LoadOptions {
            out: Some(std::env::temp_dir().join("palpate-live-daq-scene")),
            ..LoadOptions::default()
        },
    )
    .unwrap();
    let want = palpate_core::run(&sg, &opts).unwrap();
    for (got, want) in daq.iter().zip(want.outputs["daq"].iter()) {
        assert_eq!(got.meta.trial_id, want.meta.trial_id);
        assert_eq!(got.meta.label.angle_deg, want.meta.label.angle_deg);
        let (a, b) = (got.payload.signals().unwrap(), want.payload.signals().unwrap());
        assert_eq!(a.n_samples(), b.n_samples(), "{}", got.meta.trial_id);
        for (x, y) in a.data.iter().zip(&b.data) {
            assert!(x.iter().zip(y).all(|(x, y)| *x == *y as f32 as f64));
        }
    }
    for (it, want) in out.outputs["wss"].iter().zip([30.0, 75.0]) {
        assert_eq!(it.payload.estimate().unwrap().angle_deg, Some(want));
    }
    // Fixed windows of 5 s over the same stream (two trials and two 1 s gaps).
    let total: usize = daq
        .iter()
        .map(|t| t.payload.signals().unwrap().n_samples() + 1000)
        .sum();
    let g = graph(
        &format!("{keys}\nsegment = \"fixed\"\nwindow_ms = 5000.0"),
        IZHIKEVICH,
    );
    let out = palpate_core::run(&g, &opts).unwrap();
    let lens: Vec<usize> = out.outputs["daq"]
        .iter()
        .map(|t| t.payload.signals().unwrap().n_samples())
        .collect();
    assert_eq!(lens.iter().sum::<usize>(), total);
    assert!(lens[..lens.len() - 1].iter().all(|&l| l == 5000), "{lens:?}");
    assert_eq!(out.outputs["daq"][1].meta.trial_id, "daq-0001");
}

#[test]
fn bad_settings_name_their_key_and_a_missing_port_its_path() {
    palpate_stages::link();
    let load = |keys: &str| {
        let text = format!("[stages.daq]\ntype = \"daq\"\n{keys}\n[stages.w]\ntype = \"write_signals\"\ninputs = [\"daq\"]\n");
        palpate_core::load_str(&text, "bad.toml", "bad", &LoadOptions::default())
    };
    let e = load("port = \"/dev/x\"\nsegment = \"fixed\"")
        .unwrap_err()
        .to_string();
    assert!(e.contains("window_ms"), "{e}");
    let e = load("port = \"/dev/x\"\ncontact_v = 3.0\nrelease_v = 2.0")
        .unwrap_err()
        .to_string();
    assert!(e.contains("release_v"), "{e}");
    let e = load("port = \"/dev/x\"\nbuad = 9600").unwrap_err().to_string();
    assert!(e.contains("buad"), "{e}");
    let e = load("").unwrap_err().to_string();
    assert!(
        e.contains("`port`") && e.contains("`recording`") && e.contains("`scene`"),
        "{e}"
    );
    let g = load("port = \"/dev/palpate-no-such-port\"").unwrap();
    let e = palpate_core::run(&g, &RunOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("/dev/palpate-no-such-port"), "{e}");
}

/// `replay_until` and `replay_polled`: the caller stops the stream
/// (Python's `run_live` on an exception or Ctrl-C). Stopped at a trial's final answer, that trial
/// counts and the rest are not streamed; stopped mid-trial, the trial is
/// dropped. The same from a live source (the `daq` stage simulating the
/// scene) and from a batch source cut into blocks (the `scene` stage).
#[test]
fn a_caller_can_stop_a_live_stream() {
    use std::ops::ControlFlow;
    let scene = format!(
        "[stages.scene]\ntype = \"scene\"\nfile = \"{}\"\nangles = [30.0, 60.0]\ntrials_per_angle = 1\n{}",
        lab_scene().display(),
        common::causal_front_end("scene")
    );
    let daq = graph_with(
        &format!(
            "scene = \"{}\"\nangles = [30.0, 60.0]\ntrials_per_angle = 1",
            lab_scene().display()
        ),
        IZHIKEVICH,
        &format!("{WSS}\n\n[stages.mae]\ntype = \"mae\"\ninputs = [\"wss\"]"),
        "palpate-live-stop-daq",
    );
    let batch = {
        let text = format!(
            "[run]\nseed = 1\n{scene}\n[stages.enc]\ninputs = [\"drive\"]\n{IZHIKEVICH}\n\n\
             [stages.bins]\ntype = \"bin\"\ninputs = [\"enc\"]\n\n{WSS}\n\n\
             [stages.mae]\ntype = \"mae\"\ninputs = [\"wss\"]\n"
        );
        let opts = LoadOptions {
            out: Some(std::env::temp_dir().join("palpate-live-stop-scene")),
            base_dir: Some(root().join("graphs")),
            ..LoadOptions::default()
        };
        palpate_core::load_str(&text, "stop.toml", "stop", &opts).unwrap_or_else(|e| panic!("{e}"))
    };
    for g in [&daq, &batch] {
        let plan = stream::plan(g).unwrap_or_else(|p| panic!("{p:?}"));
        // Not stopped: both trials.
        let all = stream::replay(g, &plan, 10, |_| {}).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((all.trials, all.stopped), (2, false));
        assert_eq!(all.estimates[0].1.len(), 2);
        // Stopped at the first trial's final answer.
        let mut seen = Vec::new();
        let run = stream::replay_until(g, &plan, 10, |u| {
            seen.push(u.clone());
            if u.last {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((run.trials, run.stopped), (1, true), "{}", g.file);
        assert_eq!(run.estimates.len(), 1);
        let (id, finals) = &run.estimates[0];
        assert_eq!((id.as_str(), finals.len()), ("wss", 1));
        assert_eq!(finals[0].meta.trial_id, all.estimates[0].1[0].meta.trial_id);
        // Nothing after the stop, and the sinks saw the one trial.
        assert!(seen.last().is_some_and(|u| u.last));
        assert_eq!(seen.iter().filter(|u| u.last).count(), 1);
        let text = &run.reports[0].1.text;
        assert!(text.contains("of 1 trials"), "{text}");
        // Stopped at the first update, mid-trial: that trial is dropped.
        let mut calls = 0;
        let run = stream::replay_until(g, &plan, 10, |_| {
            calls += 1;
            ControlFlow::Break(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((run.trials, run.stopped, calls), (0, true, 1), "{}", g.file);
        assert!(run.estimates[0].1.is_empty());
        // Stopped by the poll (asked after each block, and at each frame
        // outside a trial), at its 50th answer: in the first trial, or
        // before it began.
        let mut polls = 0;
        let run = stream::replay_polled(
            g,
            &plan,
            10,
            |_| ControlFlow::Continue(()),
            || {
                polls += 1;
                polls == 50
            },
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((run.trials, run.stopped, polls), (0, true, 50), "{}", g.file);
        assert!(run.estimates[0].1.is_empty());
    }
}

/// `replay_polled`: a stop asked for while nothing is in contact is seen at
/// once. The `daq` stage emulates the lab scene with a contact threshold
/// the board never reaches (0.5 V; it reads 1.75 V in contact), so it
/// streams frames but never a trial and no estimate comes: before
/// `SourceEvent::Tick`, Ctrl-C on such a session waited for an estimate
/// that never came. Here the poll is asked at every frame and the stream
/// stops at its 200th answer; not stopped, the stream runs to its end with
/// no trial.
#[test]
fn a_session_with_nothing_in_contact_can_be_stopped() {
    let g = graph_with(
        &format!(
            "scene = \"{}\"\nangles = [60.0]\ntrials_per_angle = 1\ncontact_v = 0.5\nrelease_v = 0.6",
            lab_scene().display()
        ),
        IZHIKEVICH,
        &format!("{WSS}\n\n[stages.mae]\ntype = \"mae\"\ninputs = [\"wss\"]"),
        "palpate-live-stop-no-contact",
    );
    let plan = stream::plan(&g).unwrap_or_else(|p| panic!("{p:?}"));
    let mut polls = 0usize;
    let mut updates = 0usize;
    let run = stream::replay_polled(
        &g,
        &plan,
        1,
        |_| {
            updates += 1;
            std::ops::ControlFlow::Continue(())
        },
        || {
            polls += 1;
            polls == 200
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((run.trials, run.stopped, updates), (0, true, 0));
    // Not asked again once stopped.
    assert_eq!(polls, 200);
    // Never stopped: the whole stream, one poll per frame, and no trial. A
    // stream that ended by itself without a trial is an error, live or not
    // (the `daq` stage's docs): only a stop by the user is not.
    let mut polls = 0usize;
    let err = match stream::replay_polled(
        &g,
        &plan,
        1,
        |_| std::ops::ControlFlow::Continue(()),
        || {
            polls += 1;
            false
        },
    ) {
        Ok(run) => panic!("a stream without contact gave {} trials and no error", run.trials),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("held no trial"), "{err}");
    assert!(polls > 10_000, "{polls} polls");
}
