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
