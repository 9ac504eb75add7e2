//! `signal_file`'s mat reader on arbitrary bytes: an error or trials, never
//! a panic, a hang or unbounded memory; every sample it returns is finite.
#![no_main]
use libfuzzer_sys::fuzz_target;
use palpate_stages::io::signal_file::{read_signal_bytes, SignalFileConfig, SignalFormat};

fuzz_target!(|data: &[u8]| {
    let cfg = SignalFileConfig {
        fill_gaps: true,
        ..Default::default()
    };
    if let Ok(trials) = read_signal_bytes(data, "fuzz.mat", "fuzz", SignalFormat::Mat, &cfg, 16) {
        for t in &trials {
            assert_eq!(t.data.len(), 16);
            assert!(t.data.iter().flatten().all(|v| v.is_finite()));
        }
    }
});
