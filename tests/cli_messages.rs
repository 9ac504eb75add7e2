//! What a researcher reads on the terminal: `check` lists every error of a
//! stage with file, line, stage and key, numbers print compactly, the live
//! DAQ commands work from any folder, report in sentences (no struct dumps),
//! and a normal end of playback is not an error.

use std::process::{Command, Stdio};
mod common;
use common::wait_or_kill;
use std::time::Duration;

fn palpate_in(dir: &std::path::Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_palpate"));
    c.current_dir(dir);
    c
}

fn repo() -> std::path::PathBuf {
    env!("CARGO_MANIFEST_DIR").into()
}

/// Text output ends with a newline, and holds no Rust struct dump.
fn assert_tidy(what: &str, text: &str) {
    assert!(
        text.is_empty() || text.ends_with('\n'),
        "{what} does not end with a newline: {text:?}"
    );
    for dump in ["Report {", "Stats {", "Some(", " { frames:", "elapsed:"] {
        assert!(!text.contains(dump), "{what} dumps a struct ({dump}): {text}");
    }
}

const GRAPH: &str = r#"[stages.scene]
type = "scene"
file = "SCENE"
trials_per_angle = 1

[stages.filter]
type = "lowpass"
inputs = ["scene"]
order = 0
cutoff_hz = -1.0

[stages.drive]
type = "drive"
inputs = ["filter"]
gain = -1.7976931348623157e308

[stages.out]
type = "write_signals"
inputs = ["drive"]
"#;

#[test]
fn check_lists_every_wrong_key_with_its_line_and_compact_numbers() {
    let d = tempfile::tempdir().unwrap();
    let scene = repo().join("graphs/scenes/lab.toml");
    let g = d.path().join("g.toml");
    std::fs::write(&g, GRAPH.replace("SCENE", &scene.display().to_string())).unwrap();
    let out = palpate_in(d.path()).args(["check", "g.toml"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("g.toml:9: error: stage `filter`: key `order`: must lie in [1, 16], got 0\n"),
        "{err}"
    );
    assert!(
        err.contains(
            "g.toml:10: error: stage `filter`: key `cutoff_hz`: must be a positive number of Hz, got -1\n"
        ),
        "{err}"
    );
    assert!(err.contains("g.toml:15: error: stage `drive`: key `gain`: must be a finite number >= 0, got -1.7976931348623157e308\n"), "{err}");
    assert!(err.contains("3 errors in the graph; nothing was run\n"), "{err}");
    // No number is printed digit by digit (f64::MAX has 309).
    assert!(
        !err.chars()
            .collect::<Vec<_>>()
            .windows(40)
            .any(|w| w.iter().all(char::is_ascii_digit)),
        "{err}"
    );
    assert_tidy("check's stderr", &err);
}

#[test]
fn check_refuses_a_cutoff_above_nyquist_and_warns_about_old_range_names() {
    let d = tempfile::tempdir().unwrap();
    let g = d.path().join("g.toml");
    std::fs::write(
        &g,
        "[stages.scene]\ntype = \"scene\"\nangles = { start = 30, stop = 60, step = 30 }\n\
         motion = { sample_rate_hz = 200.0 }\n\n[stages.filter]\ntype = \"lowpass\"\ninputs = [\"scene\"]\ncutoff_hz = 150.0\n\n\
         [stages.out]\ntype = \"write_signals\"\ninputs = [\"filter\"]\n",
    )
    .unwrap();
    let out = palpate_in(d.path()).args(["check", "g.toml"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("g.toml:9: error: stage `filter`: key `cutoff_hz`: 150 Hz must lie below the Nyquist frequency 100 Hz"), "{err}");
    assert!(
        err.contains(
            "g.toml:3: warning: stage `scene`: key `angles.start`: `start` is deprecated: write `from`"
        ),
        "{err}"
    );
    assert!(err.contains("key `angles.stop`"), "{err}");
    assert_tidy("check's stderr", &err);
}

#[test]
fn simulate_warns_about_old_range_names_in_a_scene_file() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("s.toml"),
        "angles = { start = 30, stop = 60, step = 30 }\ntrials_per_angle = 1\neffects = []\n\
         [motion]\nspeed_mm_s = 10.0\nhold_before_s = 0.2\nhold_after_s = 0.2\nsample_rate_hz = 200.0\n",
    )
    .unwrap();
    let out = palpate_in(d.path())
        .args(["simulate", "s.toml", "--out", "sim"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("warning:") && err.contains("`start` is deprecated: write `from`"),
        "{err}"
    );
    assert!(err.contains("`stop` is deprecated: write `to`"), "{err}");
    // The old spelling still means the same range: two trials, 30 and 60.
    let labels = std::fs::read_to_string(d.path().join("sim/labels.toml")).unwrap();
    assert!(
        labels.contains("angle_deg = 30.0") && labels.contains("angle_deg = 60.0"),
        "{labels}"
    );
    assert_tidy("simulate's stderr", &err);
}

#[test]
fn daq_run_emulate_scene_works_outside_the_repository() {
    let d = tempfile::tempdir().unwrap();
    let scene = repo().join("graphs/scenes/lab.toml");
    // No --config: the built-in graphs/live.toml, whatever the folder.
    let out = palpate_in(d.path())
        .args(["daq", "run", "--emulate-scene"])
        .arg(&scene)
        .args(["--angle", "60", "--seed", "3", "--speed", "50"])
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.lines().any(|l| l.contains("wss: final 60.0 deg")),
        "{stdout}"
    );
    assert_tidy("stdout", &stdout);
    assert_tidy("stderr", &stderr);
    // A config that does not exist is named.
    let out = palpate_in(d.path())
        .args(["daq", "run", "--emulate-scene"])
        .arg(&scene)
        .args(["--config", "nope.toml"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("nope.toml"), "{err}");
}

#[test]
fn an_emulated_recording_plays_the_array_its_label_file_declares() {
    let d = tempfile::tempdir().unwrap();
    let mut csv = String::from("time_ms");
    for i in 0..9 {
        csv.push_str(&format!(",taxel_{i}"));
    }
    csv.push('\n');
    for k in 0..200 {
        csv.push_str(&format!("{k}"));
        for i in 0..9 {
            csv.push_str(&format!(",{}", 1.75 + 0.01 * i as f64));
        }
        csv.push('\n');
    }
    std::fs::write(d.path().join("t0.csv"), csv).unwrap();
    let emulate = || {
        palpate_in(d.path())
            .args([
                "daq",
                "emulate",
                "--recording",
                "t0.csv",
                "--speed",
                "100",
                "--delay",
                "0",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    // Without a label file: read as the default 4 x 4, the 9 columns are an
    // error that says where the layout is declared.
    let out = emulate().wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("[layout]"), "{err}");
    std::fs::write(
        d.path().join("labels.toml"),
        "[layout]\nkind = \"grid\"\nrows = 3\ncols = 3\npitch_mm = 3.0\ntaxel_mm = 2.0\n[trials.t0]\nangle_deg = 30.0\n",
    )
    .unwrap();
    let mut emu = emulate();
    let mut first = String::new();
    {
        use std::io::BufRead;
        let stdout = emu.stdout.as_mut().unwrap();
        std::io::BufReader::new(stdout).read_line(&mut first).unwrap();
    }
    let _ = emu.kill();
    let _ = emu.wait();
    assert!(first.contains("(9 taxels"), "{first}");
}

#[test]
fn the_end_of_an_emulators_playback_is_not_an_error() {
    let d = tempfile::tempdir().unwrap();
    let scene = repo().join("graphs/scenes/lab.toml");
    let mut emu = palpate_in(d.path())
        .args(["daq", "emulate", "--scene"])
        .arg(&scene)
        .args(["--speed", "100", "--delay", "1"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The first line names the device.
    let mut first = String::new();
    {
        use std::io::BufRead;
        let stdout = emu.stdout.as_mut().unwrap();
        std::io::BufReader::new(stdout).read_line(&mut first).unwrap();
    }
    let port = first
        .split_whitespace()
        .find(|w| w.starts_with("/dev/"))
        .unwrap_or_else(|| panic!("no device in {first:?}"))
        .to_string();
    let run = palpate_in(d.path())
        .args(["daq", "run", &port])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let run = wait_or_kill(run, Duration::from_secs(120));
    let emu = wait_or_kill(emu, Duration::from_secs(120));
    let (stdout, stderr) = (
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr),
    );
    assert!(run.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.lines().any(|l| l.contains("wss: final 45.0 deg")),
        "{stdout}"
    );
    assert!(
        !stderr.contains("Broken pipe") && !stderr.contains("stopped answering"),
        "{stderr}"
    );
    assert!(stderr.contains("end of playback after "), "{stderr}");
    assert_tidy("daq run's stderr", &stderr);
    let emu_out = String::from_utf8_lossy(&emu.stdout);
    assert!(
        emu.status.success(),
        "{emu_out}\n{}",
        String::from_utf8_lossy(&emu.stderr)
    );
    assert!(
        emu_out.starts_with("played ") && emu_out.contains(" frames ("),
        "{emu_out}"
    );
    assert_tidy("the emulator's stdout", &emu_out);
}
