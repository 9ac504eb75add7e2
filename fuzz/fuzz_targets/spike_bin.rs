//! The `bin` stage on arbitrary settings and spike trains: an error or images
//! of the stated size (under the cap) whose counts add up.
#![no_main]
use arbitrary::Arbitrary;
use libfuzzer_sys::fuzz_target;
use palpate_core::{SpikeEvent, SpikeTrain, TaxelLayout};
use palpate_stages::spikes::bin::{Binner, MAX_IMAGE_CELLS};

#[derive(Arbitrary, Debug)]
struct Input {
    window_ms: f64,
    hop_ms: f64,
    duration_ms: f64,
    events: Vec<(u8, f64)>,
}

fuzz_target!(|inp: Input| {
    if !(inp.window_ms > 0.0 && inp.hop_ms > 0.0 && inp.window_ms.is_finite() && inp.hop_ms.is_finite()) {
        return; // the stage's config check refuses these
    }
    let train = SpikeTrain {
        layout: TaxelLayout::paper(),
        duration_ms: inp.duration_ms,
        events: inp
            .events
            .iter()
            .map(|&(x, t_ms)| SpikeEvent {
                taxel: u32::from(x % 17),
                t_ms,
            })
            .collect(),
    };
    let b = Binner::new(inp.window_ms, inp.hop_ms);
    if let Ok(im) = b.bin(&train) {
        assert_eq!(im.counts.len(), im.n_frames * 16);
        assert!(im.counts.len() <= MAX_IMAGE_CELLS);
        assert!(im.counts.iter().all(|c| c.is_finite() && *c >= 0.0));
    }
});
