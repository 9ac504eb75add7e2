//! The live path from the command line: an emulated DAQ plays a simulated trial
//! into a pseudo-terminal; `palpate daq run` estimates its edge as it streams.

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
    let last = stdout.lines().last().unwrap_or("");
    assert!(last.contains("final: 60.0 deg"), "{stdout}\n{stderr}");
    // The estimate was printed as it changed, before the end.
    assert!(
        stdout.lines().filter(|l| l.contains(" now: ")).count() >= 1,
        "{stdout}"
    );
}
