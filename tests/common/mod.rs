//! Helpers shared by the CLI's integration tests.

use std::process::{Command, Output};
use std::time::{Duration, Instant};

/// Runs the palpate binary with `args` from the repository's root.
#[allow(dead_code)] // not every test binary that shares this module calls it
pub fn palpate(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_palpate"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("palpate runs")
}

/// A finished run's stdout then stderr, as one text.
#[allow(dead_code)]
pub fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Waits for a child, failing (and killing it) after `limit`: a hang
/// detector, not a timing.
#[allow(dead_code)]
pub fn wait_or_kill(mut child: std::process::Child, limit: Duration) -> std::process::Output {
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("still running after {limit:?}: hung");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}
