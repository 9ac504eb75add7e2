//! Hostile command-line values: duration flags that used to panic
//! inside `Duration::from_secs_f64`, and a live run whose emulator outlives the
//! reader (it used to hang forever).

use std::process::{Command, Stdio};
mod common;
use common::wait_or_kill;
use std::time::Duration;

fn palpate() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_palpate"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

#[test]
fn duration_flags_refuse_nan_infinite_and_huge_values() {
    for (cmd, flag, v) in [
        ("run", "--seconds", "nan"),
        ("run", "--seconds", "inf"),
        ("run", "--seconds", "1e20"),
        ("run", "--seconds", "-1"),
        ("emulate", "--delay", "inf"),
        ("emulate", "--delay", "nan"),
    ] {
        let mut c = palpate();
        // `--flag=value`: clap would read a bare `-1` as a flag of its own.
        c.args(["daq", cmd, &format!("{flag}={v}")]);
        if cmd == "run" {
            c.arg("/dev/null-no-such-port");
        } else {
            c.args(["--scene", "graphs/scenes/lab.toml"]);
        }
        let out = c.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        // clap's usage error (2), not a panic (101).
        assert_eq!(out.status.code(), Some(2), "{cmd} {flag} {v}: {err}");
        assert!(err.contains(flag) && err.contains("seconds"), "{err}");
    }
}

/// Runs `palpate args`, killing it (and failing) if it outlives `limit`.
fn run_within(args: &[&str], limit: Duration) -> std::process::Output {
    let child = palpate()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_or_kill(child, limit)
}

#[test]
fn a_live_run_that_stops_before_its_emulator_exits() {
    // The emulator gives up 10 s after the reader stops taking bytes.
    let out = run_within(
        &[
            "daq",
            "run",
            "--emulate-scene",
            "graphs/scenes/lab.toml",
            "--speed",
            "1000",
            "--seconds",
            "0.01",
            "--config",
            "graphs/live.toml",
        ],
        Duration::from_secs(120),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
}

/// A mistyped thread count (`--threads 99999999999`) used to hang while the
/// pool tried to start that many threads; now it is refused before any work.
#[test]
fn a_thread_count_over_the_cap_is_refused_at_once() {
    for args in [
        vec!["run", "graphs/quickstart.toml", "--threads", "99999999999"],
        vec!["run", "graphs/quickstart.toml", "--threads", "4097"],
    ] {
        let out = run_within(&args, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(
            err.contains("--threads") && err.contains("over the cap of 4096"),
            "{err}"
        );
    }
}

/// `daq emulate --sample-rate-hz` sets a recording's rate; beside a scene it
/// would change nothing, so it is refused rather than ignored.
#[test]
fn a_sample_rate_for_an_emulated_scene_is_refused() {
    let out = palpate()
        .args([
            "daq",
            "emulate",
            "--scene",
            "graphs/scenes/lab.toml",
            "--sample-rate-hz",
            "500",
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--recording"), "{err}");
}
