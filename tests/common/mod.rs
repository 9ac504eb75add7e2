//! Helpers shared by the CLI's integration tests.

use std::time::{Duration, Instant};

/// Waits for a child, failing (and killing it) after `limit`: a hang
/// detector, not a timing.
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
