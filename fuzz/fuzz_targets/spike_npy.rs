//! `spike_file`'s NPY reader on arbitrary bytes: an error or events, never a
//! panic, a hang or unbounded memory; every event is on a taxel and finite.
#![no_main]
use libfuzzer_sys::fuzz_target;
use palpate_core::TaxelLayout;
use palpate_stages::io::spike_file::{read_spike_bytes, SpikeFileConfig, SpikeFormat};

fuzz_target!(|data: &[u8]| {
    let cfg = SpikeFileConfig::default();
    let layout = TaxelLayout::paper();
    if let Ok(trials) = read_spike_bytes(data, "fuzz.npy", "fuzz", SpikeFormat::Npy, &cfg, &layout) {
        for (_, _, events, _) in &trials {
            assert!(events.iter().all(|&(x, t)| (x as usize) < 16 && t.is_finite()));
        }
    }
});
