//! A long live stream keeps its memory flat: 12 minutes of DAQ frames (the lab
//! scene's 60-degree trial played 40 times back to back, one unbroken
//! contact, so one 12-minute trial) written into a pseudo-terminal as fast as
//! the graph reads them, through the `daq` source and graphs/live.toml's causal
//! chain to WSS. The bytes allocated process-wide (a counting allocator; its
//! own test binary so nothing else runs beside it) are sampled every 20 ms
//! of wall time: after the first tenth of the run they do not grow.
//!
//! Two checks, because one buffer may fill for a reason other than a leak:
//! the reader's queue of raw bytes ahead of the decoder
//! ([`READ_AHEAD_BYTES`], 1 MiB) fills whenever the graph lags the player,
//! which writes as fast as it can, and it does on a loaded machine. So the
//! peak may exceed the start by that queue plus jitter, and the median of
//! the last quarter of the run (a leak's growth, which a transient fill
//! does not move) may exceed the median of the first quarter by jitter only.

use palpate_core::stream;
use palpate_core::LoadOptions;
use palpate_stages::io::daq::{emulate_pty, simulate_trial, EmulateOptions, READ_AHEAD_BYTES};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicI64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

struct Counting;

static LIVE: AtomicI64 = AtomicI64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        LIVE.fetch_add(l.size() as i64, Relaxed);
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        LIVE.fetch_sub(l.size() as i64, Relaxed);
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        LIVE.fetch_add(new as i64 - l.size() as i64, Relaxed);
        unsafe { System.realloc(p, l, new) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

#[test]
fn twelve_minutes_of_frames_keep_memory_flat() {
    palpate_stages::link();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let sig = simulate_trial(&root.join("graphs/scenes/lab.toml"), 60.0, 3).unwrap();
    let repeat = 40;
    let frames = sig.n_samples() as u64 * repeat as u64;
    let (tx, rx) = std::sync::mpsc::channel();
    let player = std::thread::spawn(move || {
        let opts = EmulateOptions {
            speed: f64::INFINITY,
            repeat,
            ..Default::default()
        };
        emulate_pty(&sig, &opts, move |path| tx.send(path.to_string()).unwrap())
    });
    let port = rx.recv().unwrap();
    let opts = LoadOptions {
        overrides: vec![("stages.daq.port".into(), port.into())],
        out: Some(std::env::temp_dir().join("palpate-live-memory")),
        base_dir: None,
    };
    let g = palpate_core::load_file(&root.join("graphs/live.toml"), &opts).unwrap();
    let plan = stream::plan(&g).unwrap_or_else(|p| panic!("{p:?}"));
    // (wall time s, live bytes) every 20 ms while the stream runs.
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let t0 = Instant::now();
            let mut samples: Vec<(f64, i64)> = Vec::with_capacity(1 << 16);
            while !stop.load(Relaxed) {
                samples.push((t0.elapsed().as_secs_f64(), LIVE.load(Relaxed)));
                std::thread::sleep(Duration::from_millis(20));
            }
            samples
        })
    };
    let mut streamed_ms = 0.0;
    stream::replay(&g, &plan, 1, |u| streamed_ms = u.t_ms).unwrap_or_else(|e| panic!("{e}"));
    stop.store(true, Relaxed);
    let samples = sampler.join().unwrap();
    assert_eq!(player.join().unwrap().unwrap().frames, frames);
    assert!(streamed_ms > 700e3, "streamed {streamed_ms} ms");
    let wall = samples.last().unwrap().0;
    let late: Vec<i64> = samples
        .iter()
        .filter(|(t, _)| *t >= 0.1 * wall)
        .map(|s| s.1)
        .collect();
    assert!(late.len() > 10, "{} samples", late.len());
    let (first, most) = (late[0], *late.iter().max().unwrap());
    let quarter = late.len() / 4;
    let (early, end) = (median(&late[..quarter]), median(&late[late.len() - quarter..]));
    eprintln!(
        "{:.0} s of frames in {wall:.1} s; live bytes after a tenth of the run {first}, largest after {most}; \
         median of the first quarter {early}, of the last {end}",
        streamed_ms / 1e3
    );
    // Jitter: the WSS stream's kept alignments, frames in flight between
    // threads. A leak of 1 KiB a second of frames would add ~500 KiB
    // between the two quarters' medians, twice this.
    let jitter = 256 * 1024;
    assert!(end - early <= jitter, "the median grew by {} B", end - early);
    assert!(
        most - first <= READ_AHEAD_BYTES as i64 + jitter,
        "the peak grew by {} B, more than the read-ahead queue ({READ_AHEAD_BYTES} B) and jitter",
        most - first
    );
}

fn median(v: &[i64]) -> i64 {
    let mut v = v.to_vec();
    v.sort_unstable();
    v[v.len() / 2]
}
