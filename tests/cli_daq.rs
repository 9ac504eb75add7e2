//! The live path from the command line: `palpate daq run --emulate-scene`
//! (an alias of `palpate run graphs/live.toml --live` with the `daq` source
//! emulating one trial of the scene) estimates its edge as it streams.

#[test]
fn daq_run_on_an_emulated_board_finds_the_edge() {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .current_dir(root)
        .args([
            "daq",
            "run",
            "--emulate-scene",
            "graphs/scenes/lab.toml",
            "--angle",
            "60",
            "--seed",
            "3",
        ])
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
/// metrics, and the live speed (blocks through the chain, their latency).
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
}
