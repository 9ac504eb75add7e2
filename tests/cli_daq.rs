//! The live path from the command line: `palpate daq run --emulate-scene`
//! (an alias of `palpate run graphs/live.toml --live` with the `daq` source
//! emulating one trial of the scene) estimates its edge as it streams.

/// `daq run` on a board emulating the lab scene's 60-degree trial, seed 3.
const DAQ_RUN_60: [&str; 8] = [
    "daq",
    "run",
    "--emulate-scene",
    "graphs/scenes/lab.toml",
    "--angle",
    "60",
    "--seed",
    "3",
];

#[test]
fn daq_run_on_an_emulated_board_finds_the_edge() {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .current_dir(root)
        .args(DAQ_RUN_60)
        .args(["--speed", "50", "--config", "graphs/live.toml"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    let finals: Vec<&str> = stdout.lines().filter(|l| l.contains("wss: final")).collect();
    assert_eq!(finals.len(), 1, "{stdout}\n{stderr}");
    assert!(
        finals[0].starts_with("edge-60deg-r00") && finals[0].contains("final 60.0 deg"),
        "{stdout}\n{stderr}"
    );
    // The estimate was printed as it changed, before the end.
    assert!(
        stdout.lines().filter(|l| l.contains("wss: now ")).count() >= 1,
        "{stdout}"
    );
}

/// `run --live` leaves a run record as a batch run does: the graph, seed,
/// metrics, and the live speed (blocks through the chain, their latency,
/// and each stage's share in `live_timing.md` / `.csv`).
#[test]
fn a_live_run_writes_its_run_record_with_block_latency() {
    let root = env!("CARGO_MANIFEST_DIR");
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .current_dir(root)
        .args(["run", "graphs/live.toml", "--live", "--out"])
        .arg(dir.path())
        .args([
            "--set",
            "stages.daq.angles=[30, 60]",
            "--set",
            "stages.daq.trials_per_angle=1",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("blocks through the chain"), "{stdout}");
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("run.json")).unwrap()).unwrap();
    assert_eq!(rec["graph"], "graphs/live.toml");
    assert_eq!(rec["run"]["seed"], 1);
    assert_eq!(rec["metrics"]["wss.mae_deg"], 0.0, "{rec}");
    let live = &rec["live"];
    assert_eq!(live["trials"], 2, "{live}");
    // One block per 1 kHz frame of the two trials' streams.
    let stream_s = live["stream_s"].as_f64().unwrap();
    let blocks = live["blocks"].as_u64().unwrap();
    assert!(stream_s > 10.0, "{live}");
    assert_eq!(blocks, (stream_s * 1000.0).round() as u64, "{live}");
    let us = &live["block_us"];
    let [median, p95, max] = ["median", "p95", "max"].map(|k| us[k].as_f64().unwrap());
    assert!(0.0 < median && median <= p95 && p95 <= max, "{us}");
    assert_eq!(rec["timing"].as_array().map(Vec::len), Some(0));
    // Per stage of the chain, in order: every block and each trial's flush
    // timed, the stage times within the chain's and their shares summing
    // to 100 %.
    let stages = live["stages"].as_array().expect("live.stages");
    let ids: Vec<&str> = stages.iter().map(|s| s["stage"].as_str().unwrap()).collect();
    assert_eq!(ids, ["filter", "norm", "drive", "enc", "bins", "wss"], "{live}");
    assert_eq!(stages[5]["type_name"], "wss");
    let chain_s = live["block_us"]["mean"].as_f64().unwrap() * blocks as f64 / 1e6;
    let mut total_s = 0.0;
    let mut share = 0.0;
    for s in stages {
        assert_eq!(s["blocks"].as_u64(), Some(blocks + 2), "{s}");
        let t = s["total_s"].as_f64().unwrap();
        assert!(t > 0.0, "{s}");
        total_s += t;
        share += s["share_pct"].as_f64().unwrap();
    }
    // The flushes are outside the chain's per-block time: a little slack.
    assert!(
        total_s <= chain_s * 1.05 + 0.05,
        "{total_s} s of stages, {chain_s} s of chain"
    );
    assert!((share - 100.0).abs() < 1e-6, "{share}");
    let csv = std::fs::read_to_string(dir.path().join("live_timing.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7, "{csv}");
    assert!(csv.lines().nth(6).unwrap().starts_with("wss,wss,"), "{csv}");
    let md = std::fs::read_to_string(dir.path().join("live_timing.md")).unwrap();
    assert!(md.contains("| enc | izhikevich |"), "{md}");
    assert!(stdout.contains("share"), "{stdout}");
}

/// Runs `palpate args...`, sends it SIGINT `after` a line containing
/// `marker` appears on its stdout (`on_stderr`: its stderr), and returns its
/// exit code, stdout and stderr (the watched stream's lines before the
/// signal included).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn interrupted_at(
    args: &[&str],
    on_stderr: bool,
    marker: &str,
    after: std::time::Duration,
) -> (Option<i32>, String, String) {
    use std::io::{BufRead, Read};
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let watched: Box<dyn Read> = if on_stderr {
        Box::new(child.stderr.take().unwrap())
    } else {
        Box::new(child.stdout.take().unwrap())
    };
    let mut lines = std::io::BufReader::new(watched).lines();
    let mut seen = Vec::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        let hit = line.contains(marker);
        seen.push(line);
        if hit {
            break;
        }
    }
    assert!(seen.last().is_some_and(|l| l.contains(marker)), "{seen:?}");
    std::thread::sleep(after);
    // SAFETY: signalling our own child process.
    let pid = i32::try_from(child.id()).unwrap();
    assert_eq!(unsafe { libc::kill(pid, libc::SIGINT) }, 0);
    seen.extend(lines.map(Result::unwrap));
    let out = child.wait_with_output().unwrap();
    let watched = seen.join("\n");
    let other = String::from_utf8_lossy(if on_stderr { &out.stdout } else { &out.stderr }).into_owned();
    let (stdout, stderr) = if on_stderr {
        (other, watched)
    } else {
        (watched, other)
    };
    (out.status.code(), stdout, stderr)
}

/// Ctrl-C ends a live session cleanly: the trial under way is dropped, the
/// reports and run record are written, and the exit code is 130. The board
/// is emulated at 5x real time (a 20 s trial takes 4 s), so the signal
/// lands mid-trial: at the first running estimate.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn ctrl_c_ends_a_live_session_with_its_reports() {
    let args = [&DAQ_RUN_60[..], &["--speed", "5", "--config", "graphs/live.toml"]].concat();
    let (code, text, stderr) = interrupted_at(&args, false, "wss: now ", std::time::Duration::ZERO);
    assert_eq!(code, Some(130), "{text}\n{stderr}");
    assert!(
        text.contains("stopped by Ctrl-C after 0 finished trials"),
        "{text}"
    );
    assert!(text.contains("run record and per-stage timing in"), "{text}");
    assert!(!text.contains("wss: final"), "{text}");
}

/// Ctrl-C ends a live session with nothing in contact: the board streams
/// frames but no trial and no estimate comes (here a contact threshold it
/// never reaches, the scene played in real time, ~25 s), so a stop that
/// waited for the next estimate never came; it is now seen at the next
/// frame. Signalled once the session says it is streaming.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn ctrl_c_ends_a_live_session_with_nothing_in_contact() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let args = [
        "run",
        "graphs/live.toml",
        "--live",
        "--out",
        out,
        "--set",
        "stages.daq.angles=[60]",
        "--set",
        "stages.daq.trials_per_angle=1",
        "--set",
        "stages.daq.contact_v=0.5",
        "--set",
        "stages.daq.release_v=0.6",
        "--set",
        "stages.daq.speed=1.0",
    ];
    // Half a second in, so the board has sent frames (at 1 kHz) to diagnose.
    let (code, stdout, stderr) = interrupted_at(
        &args,
        true,
        "streaming live; Ctrl-C stops",
        std::time::Duration::from_millis(500),
    );
    let text = format!("{stdout}\n{stderr}");
    assert_eq!(code, Some(130), "{text}");
    assert!(
        stdout.contains("stopped by Ctrl-C after 0 finished trials"),
        "{text}"
    );
    // No trial began: said in words, not latencies and a stage table of zeros.
    assert!(
        stdout.contains("no trial began: no block went through the chain")
            && stdout.contains("estimator `wss`: no trial to score")
            && !stdout.contains("median us"),
        "{text}"
    );
    // ... and why: the board's levels against the threshold, on the stop too.
    assert!(
        stderr.contains("daq `daq`: no contact in ")
            && stderr.contains("never at or under `contact_v` = 0.5"),
        "{text}"
    );
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("run.json")).unwrap()).unwrap();
    assert_eq!(rec["live"]["stopped"], true, "{rec}");
    assert_eq!(rec["live"]["trials"], 0, "{rec}");
}

/// A stream that ends without contact says why: the range of each frame's
/// lowest taxel against `contact_v` (here the emulated board's open 3.3 V and
/// contact ~1.7 V against a threshold of 0.5 V), and the keys to set. A
/// threshold met, but not for `enter_ms`, says for how many frames it was.
/// An emulated scene ends on its own: no trial in it is a failure, live as
/// in a batch run (only a session the user stops is not, above).
#[test]
fn a_live_stream_without_contact_says_which_levels_it_saw() {
    let dir = tempfile::tempdir().unwrap();
    let run = |contact: &str, release: &str, enter: &str, ok: bool| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args(["run", "graphs/live.toml", "--live", "--out"])
            .arg(dir.path())
            .args([
                "--set",
                "stages.daq.angles=[60]",
                "--set",
                "stages.daq.trials_per_angle=1",
            ])
            .args(["--set", &format!("stages.daq.contact_v={contact}")])
            .args(["--set", &format!("stages.daq.release_v={release}")])
            .args(["--set", &format!("stages.daq.enter_ms={enter}")])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr).to_string();
        assert_eq!(out.status.success(), ok, "{stderr}");
        if !ok {
            assert!(
                stderr.contains(
                    "live run failed: stage `daq`: the stream held no trial (no contact: is `contact_v` right"
                ),
                "{stderr}"
            );
        }
        stderr
    };
    let e = run("0.5", "0.6", "20", false);
    let line = e
        .lines()
        .find(|l| l.contains("no contact in"))
        .unwrap_or_else(|| panic!("{e}"));
    assert!(
        line.contains("to 3.3 V, never at or under `contact_v` = 0.5")
            && line.contains("after 20 frames")
            && line.contains("`scale`"),
        "{line}"
    );
    // The trial's contact lasts seconds: an `enter_ms` longer than the
    // whole stream finds it, but never long enough.
    let e = run("3.0", "3.2", "60000", false);
    let line = e
        .lines()
        .find(|l| l.contains("no contact in"))
        .unwrap_or_else(|| panic!("{e}"));
    assert!(
        line.contains("at or under `contact_v` = 3 for at most "),
        "{line}"
    );
    // With contact, nothing to explain.
    assert!(!run("3.0", "3.2", "20", true).contains("no contact"));
}

/// The lab scene's trial at `angle` (seed 3) played as DAQ frames (f32),
/// then a second off the object (3.3 V), as `daq run --record` writes it.
fn lab_recording(angle: f64) -> Vec<u8> {
    use palpate::stages::io::daq::{emulate, simulate_trial, EmulateOptions};
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut s = simulate_trial(&root.join("graphs/scenes/lab.toml"), angle, 3).unwrap();
    for col in &mut s.data {
        col.extend(std::iter::repeat_n(3.3, 1000));
    }
    let mut out = Vec::new();
    let opts = EmulateOptions {
        speed: f64::INFINITY,
        ..EmulateOptions::default()
    };
    emulate(&s, &mut out, &opts).unwrap();
    out
}

/// graphs/live.toml with its `daq` source reading `recording` (written to
/// `dir`) instead of emulating the scene, plus `keys`; returns the graph.
fn recording_graph(dir: &std::path::Path, name: &str, bytes: &[u8], keys: &str) -> std::path::PathBuf {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("graphs/live.toml")).unwrap();
    let rec = dir.join(format!("{name}.daq"));
    std::fs::write(&rec, bytes).unwrap();
    let line = format!("recording = {:?}\n{keys}", rec.display().to_string());
    assert!(text.contains("scene = \"scenes/lab.toml\"\n"));
    let text = text.replacen("scene = \"scenes/lab.toml\"\n", &format!("{line}\n"), 1);
    let graph = dir.join(format!("{name}.toml"));
    std::fs::write(&graph, text).unwrap();
    graph
}

/// `palpate run GRAPH [--live]` into `out`: success, stdout, stderr.
fn run_graph(graph: &std::path::Path, live: bool, out: &std::path::Path) -> (bool, String, String) {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"));
    cmd.current_dir(env!("CARGO_MANIFEST_DIR")).arg("run").arg(graph);
    if live {
        cmd.arg("--live");
    }
    let o = cmd.arg("--out").arg(out).output().unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// What a failed run said after "run failed: " (batch) or "live run failed: ".
fn failure(stderr: &str) -> &str {
    stderr
        .lines()
        .find_map(|l| l.split_once("run failed: ").map(|(_, m)| m))
        .unwrap_or_else(|| panic!("no failure in:\n{stderr}"))
}

/// A recording cut inside a frame (half of it, in contact; or its last 7
/// bytes) is refused by the `daq` source, batch and live, naming the file,
/// the byte and `allow_cut_end`, before any trial is scored. With
/// `allow_cut_end = true` the cut frame is dropped, and a recording that
/// ends in contact warns that its trial was cut short, and scores it.
#[test]
fn a_daq_recording_cut_inside_a_frame_is_refused_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let full = lab_recording(60.0);
    let half = &full[..full.len() / 2];
    let short = &full[..full.len() - 7];
    for (name, bytes) in [("half", half), ("short", short)] {
        let graph = recording_graph(dir.path(), name, bytes, "");
        for live in [false, true] {
            let (ok, stdout, stderr) = run_graph(&graph, live, &dir.path().join("o"));
            assert!(!ok, "{name} live={live}: {stdout}\n{stderr}");
            let m = failure(&stderr);
            assert!(
                m.starts_with("stage `daq`: ")
                    && m.contains(&format!("{name}.daq: the recording ends inside a frame ("))
                    && m.contains("Set `allow_cut_end = true`"),
                "{name} live={live}: {m}"
            );
            // Refused before anything streamed or was scored.
            assert!(!stdout.contains("wss: "), "{stdout}");
        }
        let allowed = recording_graph(dir.path(), name, bytes, "allow_cut_end = true");
        for live in [false, true] {
            let (ok, stdout, stderr) = run_graph(&allowed, live, &dir.path().join("o"));
            assert!(ok, "{name} live={live}: {stdout}\n{stderr}");
            assert!(
                stderr.contains("ends inside a frame") && stderr.contains("dropped it"),
                "{stderr}"
            );
            let cut = stderr.lines().find(|l| l.contains("cut short"));
            if name == "half" {
                let w = cut.unwrap_or_else(|| panic!("{stderr}"));
                assert!(
                    w.contains("half.daq ends in contact, inside trial `daq-0000`")
                        && w.contains("still scored"),
                    "{w}"
                );
            } else {
                // The whole trial and its release are in: nothing was cut short.
                assert_eq!(cut, None, "{stderr}");
            }
            if live {
                assert!(
                    stdout.contains("daq-0000") && stdout.contains("wss: final"),
                    "{stdout}"
                );
            }
        }
    }
}

/// `daq emulate --recording` refuses a recording cut inside a frame with a
/// hint this command can follow (`--allow-cut-end`, not a graph key), and
/// plays it without the cut frame when given the flag.
#[test]
fn daq_emulate_refuses_a_cut_recording_unless_its_flag_allows_it() {
    let dir = tempfile::tempdir().unwrap();
    let full = lab_recording(60.0);
    // Ten whole frames (86 bytes each: 16 f32 taxels) and half of one.
    let rec = dir.path().join("cut.daq");
    std::fs::write(&rec, &full[..10 * 86 + 40]).unwrap();
    let emulate = |flag: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
            .args(["daq", "emulate", "--delay", "0", "--speed", "100", "--recording"])
            .arg(&rec)
            .args(flag)
            .output()
            .unwrap();
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let (ok, _, stderr) = emulate(&[]);
    assert!(!ok, "{stderr}");
    assert!(
        stderr.contains("ends inside a frame")
            && stderr.contains("Pass --allow-cut-end")
            && !stderr.contains("allow_cut_end"),
        "{stderr}"
    );
    let (ok, stdout, stderr) = emulate(&["--allow-cut-end"]);
    assert!(ok, "{stdout}\n{stderr}");
    assert!(stdout.contains("played 10 frames"), "{stdout}");
}

/// A recording that holds no trial (empty, random bytes, one frame's header
/// alone) fails a live run as it fails a batch run, with the same message
/// naming the file and what it held; a live run used to end "no trial
/// began" with exit 0.
#[test]
fn a_recording_without_a_trial_fails_live_as_in_batch() {
    let dir = tempfile::tempdir().unwrap();
    // Noise from a fixed generator (xorshift), so the test is repeatable.
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let random: Vec<u8> = (0..5000)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 24) as u8
        })
        .collect();
    let full = lab_recording(60.0);
    for (name, bytes) in [
        ("empty", &[][..]),
        ("random", &random[..]),
        ("header", &full[..18]),
    ] {
        let graph = recording_graph(dir.path(), name, bytes, "");
        let (ok, _, batch) = run_graph(&graph, false, &dir.path().join("o"));
        assert!(!ok, "{batch}");
        let (ok, stdout, live) = run_graph(&graph, true, &dir.path().join("o"));
        assert!(!ok, "{stdout}\n{live}");
        assert_eq!(failure(&live), failure(&batch), "{name}");
        let m = failure(&live);
        assert!(
            m.starts_with(&format!(
                "stage `daq`: the recording {}",
                dir.path().join(name).display()
            )) && m.contains(".daq held no trial: no valid DAQ frame")
                && m.contains(&format!("({} bytes)", bytes.len())),
            "{m}"
        );
        assert!(!stdout.contains("no trial began"), "{stdout}");
    }
}

/// `daq run --emulate-scene` plays the trial `daq emulate --scene` plays
/// (and `palpate simulate`) for the same scene, angle and seed: the raw
/// stream it records begins with that trial's samples, to the f32 bit. It
/// used to draw them keyed by the graph's `daq` stage id instead.
#[test]
fn daq_run_and_daq_emulate_play_the_same_trial() {
    use palpate::stages::io::daq::{decode_recording, simulate_trial};
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("r30.daq");
    let scene = root.join("graphs/scenes/lab.toml");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .current_dir(dir.path())
        .args(["daq", "run", "--emulate-scene"])
        .arg(&scene)
        .args(["--angle", "30", "--seed", "0", "--speed", "0", "--record"])
        .arg(&rec)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let played = decode_recording(&std::fs::read(&rec).unwrap(), 1.0, 0.0, false).unwrap();
    let want = simulate_trial(&scene, 30.0, 0).unwrap();
    let n = want.n_samples();
    assert!(played.data[0].len() > n, "{} frames", played.data[0].len());
    for (ch, (got, want)) in played.data.iter().zip(&want.data).enumerate() {
        let want: Vec<f64> = want.iter().map(|&v| f64::from(v as f32)).collect();
        assert!(
            got[..n] == want[..],
            "taxel {ch}: {:?} vs {:?}",
            &got[..3],
            &want[..3]
        );
    }
}
