//! Spiking encoders: analog taxel signals to spike events.
//!
//! An encoder reads [`Signals`] whose values are the input current of one
//! neuron per taxel (usually made by the `drive` stage) and gives a
//! [`palpate_core::SpikeTrain`] of time-sorted `(taxel, t_ms)` events whose `duration_ms` is
//! the trial's duration.
//!
//! | type | neuron |
//! |---|---|
//! | `izhikevich` | Izhikevich 2003 (paper eqs. 1-3), presets `fa_i`, `regular_spiking`, ... |
//! | `lif` | leaky integrate-and-fire with a refractory period |
//!
//! Shared conventions (this module):
//!
//! * The neuron is integrated at its own step `dt_ms`; step `n` covers
//!   `[n dt, (n+1) dt)` and the simulation runs while `n dt < duration`.
//! * The input current is sampled at the signal's rate. At step `n` the neuron
//!   sees `I(n dt)`, by default held from the last sample at or before `n dt`
//!   (`input = "hold"`: zero-order hold, causal, what a DAQ delivers), or
//!   linearly interpolated between the two samples around it
//!   (`input = "linear"`; looks ahead by less than one sample).
//! * Currents are clamped to `±1e12` before integration: far beyond any value at
//!   which a neuron already fires on every step, and it keeps every product
//!   finite (the user guide's "Numerical hard cases").
//! * A spike's time is interpolated linearly within the step (or half-step) in
//!   which the membrane crossed threshold, so spike times are not quantized to
//!   `dt`. A spike whose time would fall at or after the trial's end (possible
//!   only when `dt` does not divide the duration) is dropped.
//! * Encoders run the taxels in blocks of [`LANES`] neurons in lock step so that
//!   the independent membranes fill the CPU's pipelines and SIMD lanes: the
//!   block's currents are interleaved sample-major a tile of [`TILE`]
//!   samples at a time ([`tiled`]) so a step reads one contiguous
//!   `[f64; LANES]` from L1, the per-step update is
//!   branch-free (min/max/select), and spike bookkeeping runs only on steps
//!   where some lane crossed threshold. One trial runs on one core (trials run
//!   in parallel at the graph level). `benches/encode.rs` measures it.

pub mod izhikevich;
pub mod lif;

use palpate_core::{Signals, SpikeEvent, StageError};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Neurons integrated together in lock step. 16: the paper's array in one
/// block. Each membrane is a serial chain of dependent operations, so with 8
/// lanes the kernel waited on latency; 16 independent chains keep the vector
/// units busy (Izhikevich 16 x 40 s: 4.7 -> 3.0 ms, `cargo bench --bench
/// encode`). Smaller arrays pay for padding lanes, which are cheap.
pub const LANES: usize = crate::wide::LANES;

/// Largest input current magnitude an encoder uses; larger values are clamped.
pub const MAX_CURRENT: f64 = 1e12;

/// How the input current is sampled at the neuron's step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum InputMode {
    /// Zero-order hold: the last sample at or before the step's start (causal).
    #[default]
    Hold,
    /// Linear interpolation between the samples around the step's start.
    Linear,
}

/// Per-step input lookup for one trial: sample index and interpolation weight.
pub struct StepInput {
    /// Number of neuron steps.
    pub n_steps: usize,
    /// Step length, ms.
    pub dt_ms: f64,
    /// Trial duration, ms.
    pub duration_ms: f64,
    /// `idx[n]`: the sample at or before step `n`'s start.
    pub idx: Vec<u32>,
    /// `frac[n]`: weight of sample `idx[n] + 1` (empty for hold).
    pub frac: Vec<f64>,
}

impl StepInput {
    /// Plans the steps for `n_samples` samples at `fs` Hz.
    pub fn new(n_samples: usize, fs: f64, dt_ms: f64, mode: InputMode) -> Self {
        let duration_ms = n_samples as f64 * 1000.0 / fs;
        // Steps while n dt < duration; the 1e-9 guards 1000/0.5-style quotients
        // that land a hair above an integer.
        let n_steps = if n_samples == 0 {
            0
        } else {
            (duration_ms / dt_ms - 1e-9).ceil().max(1.0) as usize
        };
        let samples_per_step = dt_ms * fs / 1000.0;
        let last = n_samples.saturating_sub(1);
        let mut idx = Vec::with_capacity(n_steps);
        let mut frac = Vec::with_capacity(if mode == InputMode::Linear { n_steps } else { 0 });
        // In the AVX2 function: there `floor` is one rounding instruction;
        // in baseline x86-64 (no SSE4.1) it is a call into a software
        // floor (`perf` on `palpate run graphs/quickstart.toml --threads
        // 1`: this plan was 8 % of the encoder's samples, the floor calls
        // about a third of it). `floor` is exact either way, so the same
        // indices.
        //
        // The indices are one `extend` of a counted map, which vectorizes
        // (a `push` per step, with the fractions' branch beside it, did
        // not: the plan was 6.6 % of the encoder's samples in the same
        // profile, at 2 steps a sample); the fractions follow from them.
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                idx.extend((0..n_steps).map(|n| {
                    let pos = n as f64 * samples_per_step;
                    ((pos + 1e-9).floor() as usize).min(last) as u32
                }));
                if mode == InputMode::Linear {
                    frac.extend(idx.iter().enumerate().map(|(n, &i)| {
                        let (pos, i) = (n as f64 * samples_per_step, i as usize);
                        if i < last {
                            (pos - i as f64).clamp(0.0, 1.0)
                        } else {
                            0.0
                        }
                    }));
                }
            },
        );
        StepInput {
            n_steps,
            dt_ms,
            duration_ms,
            idx,
            frac,
        }
    }

    /// The current of `xs` at step `n`.
    #[inline(always)]
    pub fn at(&self, xs: &[f64], n: usize) -> f64 {
        let i = self.idx[n] as usize;
        let x = if self.frac.is_empty() {
            xs[i]
        } else {
            let f = self.frac[n];
            if f > 0.0 {
                xs[i] + f * (xs[i + 1] - xs[i])
            } else {
                xs[i]
            }
        };
        x.clamp(-MAX_CURRENT, MAX_CURRENT)
    }
}

/// Samples a tile of [`tiled`] interleaves at a time: 256 samples x 16
/// lanes x 8 bytes = 32 KiB, so a tile is written, then read by the
/// kernel, while it is still in the L1 data cache.
pub const TILE: usize = 256;

/// Runs an encoder's kernel over one block of up to [`LANES`] taxels tile
/// by tile: each tile of [`TILE`] samples is interleaved ([`interleave`]'s
/// layout and clamp) into `data`, then `run(data, steps, first)` integrates
/// the steps whose sample (`plan.idx`) falls in the tile, `data[0]` being
/// sample `first`. `data` also holds the sample after the tile, where one
/// exists, for linear interpolation's look-ahead. Steps go to `run` in
/// order and each exactly once, so a kernel that carries its state from
/// call to call gives the bits of one pass over the whole trial.
///
/// Why tiles: interleaving the whole trial first wrote a sample-major copy
/// as large as the trial (2.8 MB for a 21 s lab trial, more than L2), read
/// back by the kernel from memory; the transpose and that round trip were
/// about a third of the encoder (`perf` on `palpate run
/// graphs/quickstart.toml --threads 1`). A tile stays in L1.
///
/// Returns whether every current read was finite (as [`interleave`]).
/// Ragged rows (shorter than `n_samples`) take [`interleave`]'s safe path:
/// one tile of the whole trial.
pub fn tiled(
    chunk: &[Vec<f64>],
    n_samples: usize,
    plan: &StepInput,
    data: &mut Vec<[f64; LANES]>,
    mut run: impl FnMut(&[[f64; LANES]], std::ops::Range<usize>, usize),
) -> bool {
    if !chunk.iter().all(|xs| xs.len() >= n_samples) {
        let finite = interleave(chunk, n_samples, data);
        run(data, 0..plan.n_steps, 0);
        return finite;
    }
    let mut finite = true;
    let mut n = 0;
    let mut t0 = 0;
    while t0 < n_samples {
        let t1 = (t0 + TILE).min(n_samples);
        data.clear();
        finite &= crate::wide::gather_lanes(chunk, t0..(t1 + 1).min(n_samples), data, Some(MAX_CURRENT));
        let start = n;
        // `idx` never decreases, so a tile's steps are contiguous.
        while n < plan.n_steps && (plan.idx[n] as usize) < t1 {
            n += 1;
        }
        if n > start {
            run(data, start..n, t0);
        }
        t0 = t1;
    }
    // Every step's sample is below `n_samples` (`StepInput::new`), so the
    // tiles took them all.
    debug_assert_eq!(n, plan.n_steps);
    finite
}

/// Fills `data` with one block of up to [`LANES`] taxels' currents, interleaved sample-major
/// (`data[sample][lane]`) and clamped to [`MAX_CURRENT`], so a step reads one
/// contiguous `[f64; LANES]` (one bounds check, one cache line pair) instead of
/// `LANES` scattered slices. Missing lanes of the last block hold 0.
///
/// Returns whether every current read was finite (noted during the
/// transpose, so an encoder stage reads its input once).
pub fn interleave(chunk: &[Vec<f64>], n_samples: usize, data: &mut Vec<[f64; LANES]>) -> bool {
    data.clear();
    data.reserve(n_samples);
    if chunk.iter().all(|xs| xs.len() >= n_samples) {
        crate::wide::gather_lanes(chunk, 0..n_samples, data, Some(MAX_CURRENT))
    } else {
        let finite = chunk
            .iter()
            .all(|xs| crate::signal::first_non_finite(xs).is_none());
        // Ragged rows (callers check lengths; kept safe): short rows read 0.
        data.resize(n_samples, [0.0; LANES]);
        for (l, xs) in chunk.iter().take(LANES).enumerate() {
            for (row, &x) in data.iter_mut().zip(xs) {
                row[l] = x.clamp(-MAX_CURRENT, MAX_CURRENT);
            }
        }
        finite
    }
}

/// The currents of a block at step `n` whose sample index is `i`: held, or
/// (`LINEAR`) interpolated towards the next sample.
#[inline(always)]
pub fn block_input<const LINEAR: bool>(
    data: &[[f64; LANES]],
    plan: &StepInput,
    n: usize,
    i: usize,
) -> [f64; LANES] {
    let a = data[i];
    if !LINEAR {
        return a;
    }
    let f = plan.frac[n];
    if f > 0.0 {
        // frac > 0 only when i + 1 is a sample (see StepInput::new).
        let b = data[i + 1];
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            out[l] = a[l] + f * (b[l] - a[l]);
        }
        out
    } else {
        a
    }
}

/// `max` without NaN handling (a single instruction; inputs are never NaN here).
#[inline(always)]
pub(crate) fn fmax(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

/// `min` without NaN handling (a single instruction; inputs are never NaN here).
#[inline(always)]
pub(crate) fn fmin(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// Checks an encoder's input: finite samples, one vector per taxel, and
/// at most [`MAX_NEURON_STEPS`] at `dt_ms`.
pub fn check_input(what: &str, s: &Signals, dt_ms: f64) -> Result<(), StageError> {
    crate::signal::check_signals(what, s)?;
    check_input_shape(what, s, dt_ms)
}

/// [`check_input`] without the scan for non-finite samples, which the
/// encoders make while transposing their input ([`interleave`]).
pub fn check_input_shape(what: &str, s: &Signals, dt_ms: f64) -> Result<(), StageError> {
    crate::signal::check_shape(what, s)?;
    if s.layout.len() > u32::MAX as usize {
        return Err(StageError::new(format!("{what}: too many taxels")));
    }
    check_steps(
        what,
        s.n_samples() as u64,
        s.sample_rate_hz,
        s.layout.len(),
        dt_ms,
    )
}

/// Most neuron steps (taxels x steps of `dt_ms`) an encoder runs for one
/// trial: 2^28 = 268 435 456, e.g. 16 taxels for 4.6 hours at `dt_ms = 0.5`
/// (a 21 s lab trial takes 0.69 million).
///
/// Why: the batch encoder's step plan holds 4 to 12 bytes a step, and a
/// neuron may fire on every step (16 bytes a spike), so a trial whose
/// duration is absurd for its sample rate (a rate in kHz given as Hz, 10
/// samples declared at 10^-6 Hz) asked for tens of gigabytes and aborted the
/// process, where it must fail the trial with a message. The streaming form
/// stops at the same count, so the live path refuses the same trials.
pub const MAX_NEURON_STEPS: u64 = 1 << 28;

/// The [`MAX_NEURON_STEPS`] check for a trial of `n_samples` at `fs` Hz
/// over `n_taxels` neurons stepped every `dt_ms`.
pub fn check_steps(
    what: &str,
    n_samples: u64,
    fs: f64,
    n_taxels: usize,
    dt_ms: f64,
) -> Result<(), StageError> {
    let duration_ms = n_samples as f64 * 1000.0 / fs;
    let steps = (duration_ms / dt_ms).ceil();
    let total = steps * n_taxels.max(1) as f64;
    if total <= MAX_NEURON_STEPS as f64 {
        return Ok(());
    }
    Err(StageError::new(format!(
        "{what}: {n_samples} samples at {} Hz last {} s, {} steps of dt_ms = {} for each of {n_taxels} \
         taxels: over the cap of {MAX_NEURON_STEPS} neuron steps a trial (is the sample rate right? a \
         rate in kHz given as Hz makes a trial 1000 times longer)",
        palpate_core::fmt_num(fs),
        palpate_core::fmt_num(duration_ms / 1000.0),
        palpate_core::fmt_num(steps),
        palpate_core::fmt_num(dt_ms),
    )))
}

/// Sorts events by time, then taxel (stably).
///
/// Why an insertion sort first: the encoders emit a block's events step
/// after step, so they arrive sorted but for the spikes of one step, which
/// come in lane order rather than time order. Insertion sort puts those
/// right in one pass (the library's sort took 4.8 % of the encoder's
/// samples on `palpate run graphs/quickstart.toml --threads 1`). Once it
/// has moved events `len` places in all (several lane blocks, or input in
/// any order) it hands over to the library's stable sort, which gives the
/// same order: both are stable sorts by one comparison.
pub fn sort_events(events: &mut [SpikeEvent]) {
    let cmp = |a: &SpikeEvent, b: &SpikeEvent| a.t_ms.total_cmp(&b.t_ms).then(a.taxel.cmp(&b.taxel));
    let mut budget = events.len();
    for i in 1..events.len() {
        let mut j = i;
        while j > 0 && cmp(&events[j], &events[j - 1]).is_lt() {
            if budget == 0 {
                events.sort_by(cmp);
                return;
            }
            events.swap(j, j - 1);
            budget -= 1;
            j -= 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    proptest::proptest! {
        /// The insertion-first sort gives the library sort's order, on
        /// nearly sorted input (within-step disorder), on several sorted
        /// blocks one after another, and on any order; equal times tie on
        /// the taxel, and equal events keep their order.
        #[test]
        fn sort_events_orders_as_the_library_sort(
            raw in proptest::collection::vec((0u32..40, 0u32..6, 0u8..4), 0..300),
            shape in 0u8..3,
        ) {
            let mut ev: Vec<SpikeEvent> = raw
                .iter()
                .map(|&(t, taxel, f)| SpikeEvent { taxel, t_ms: t as f64 * 0.5 + f as f64 * 0.125 })
                .collect();
            match shape {
                // Sorted but for small local swaps, as one lane block emits.
                0 => {
                    ev.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
                    for i in (1..ev.len()).step_by(3) {
                        ev.swap(i, i - 1);
                    }
                }
                // Two sorted blocks one after the other.
                1 => {
                    let h = ev.len() / 2;
                    ev[..h].sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
                    ev[h..].sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
                }
                _ => {}
            }
            let mut want = ev.clone();
            want.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms).then(a.taxel.cmp(&b.taxel)));
            sort_events(&mut ev);
            let bits = |v: &[SpikeEvent]| v.iter().map(|e| (e.t_ms.to_bits(), e.taxel)).collect::<Vec<_>>();
            proptest::prop_assert_eq!(bits(&ev), bits(&want));
        }
    }

    #[test]
    fn the_plan_is_the_baseline_floor_of_each_step() {
        // The plan is computed inside the AVX2 function; the same
        // expression here runs in baseline code (a software floor).
        for (n_samples, fs, dt) in [
            (21_580, 1000.0, 0.5),
            (997, 333.3, 0.25),
            (4_001, 2048.0, 1.0),
            (7, 1e4, 0.05),
        ] {
            for mode in [InputMode::Hold, InputMode::Linear] {
                let p = StepInput::new(n_samples, fs, dt, mode);
                let sps = dt * fs / 1000.0;
                let last = n_samples - 1;
                for n in 0..p.n_steps {
                    let pos = std::hint::black_box(n as f64 * sps);
                    let i = ((pos + 1e-9).floor() as usize).min(last);
                    assert_eq!(
                        p.idx[n] as usize, i,
                        "{n_samples} samples at {fs} Hz, dt {dt}, step {n}"
                    );
                    if mode == InputMode::Linear {
                        let f = if i < last {
                            (pos - i as f64).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        assert_eq!(p.frac[n].to_bits(), f.to_bits());
                    }
                }
            }
        }
    }

    #[test]
    fn tiles_give_each_step_once_in_order_with_its_samples() {
        // Lengths around the tile size, and steps that take every sample,
        // skip samples (dt 2 ms at 1 kHz) or fall between them (0.3 ms).
        for n_samples in [0, 1, 5, TILE - 1, TILE, TILE + 1, 3 * TILE + 7] {
            let rows: Vec<Vec<f64>> = (0..3)
                .map(|l| (0..n_samples).map(|k| (k * 10 + l) as f64).collect())
                .collect();
            for (dt, mode) in [
                (1.0, InputMode::Hold),
                (2.0, InputMode::Linear),
                (0.3, InputMode::Linear),
            ] {
                let plan = StepInput::new(n_samples, 1000.0, dt, mode);
                let mut seen = Vec::new();
                let finite = tiled(&rows, n_samples, &plan, &mut Vec::new(), |data, steps, off| {
                    for n in steps {
                        let i = plan.idx[n] as usize;
                        assert_eq!(
                            data[i - off][..4],
                            [i as f64 * 10.0, i as f64 * 10.0 + 1.0, i as f64 * 10.0 + 2.0, 0.0]
                        );
                        if mode == InputMode::Linear && plan.frac[n] > 0.0 {
                            assert_eq!(
                                data[i + 1 - off][0],
                                (i + 1) as f64 * 10.0,
                                "look-ahead at step {n}"
                            );
                        }
                        seen.push(n);
                    }
                });
                assert!(finite);
                assert_eq!(
                    seen,
                    (0..plan.n_steps).collect::<Vec<_>>(),
                    "{n_samples} samples, dt {dt}"
                );
            }
        }
        // A non-finite sample in the last tile is still reported.
        let mut rows = vec![vec![1.0; 2 * TILE + 3]; 2];
        rows[1][2 * TILE + 2] = f64::NAN;
        let plan = StepInput::new(2 * TILE + 3, 1000.0, 0.5, InputMode::Hold);
        assert!(!tiled(&rows, 2 * TILE + 3, &plan, &mut Vec::new(), |_, _, _| {}));
    }

    #[test]
    fn steps_cover_the_trial_and_hold_the_last_sample() {
        let p = StepInput::new(1000, 1000.0, 0.5, InputMode::Hold);
        assert_eq!(p.n_steps, 2000);
        assert_eq!((p.idx[0], p.idx[1], p.idx[2], p.idx[1999]), (0, 0, 1, 999));
        let p = StepInput::new(1000, 1000.0, 2.0, InputMode::Hold);
        assert_eq!(p.n_steps, 500);
        assert_eq!(p.idx[499], 998);
        // dt that does not divide the duration: one partial step at the end.
        let p = StepInput::new(10, 1000.0, 3.0, InputMode::Hold);
        assert_eq!(p.n_steps, 4);
        assert_eq!(StepInput::new(0, 1000.0, 0.5, InputMode::Hold).n_steps, 0);
    }

    #[test]
    fn linear_interpolates_between_samples() {
        let xs = [0.0, 10.0, 20.0];
        let p = StepInput::new(3, 1000.0, 0.25, InputMode::Linear);
        assert_eq!(p.at(&xs, 1), 2.5);
        assert_eq!(p.at(&xs, 4), 10.0);
        assert_eq!(p.at(&xs, 11), 20.0); // past the last sample: held
        let h = StepInput::new(3, 1000.0, 0.25, InputMode::Hold);
        assert_eq!(h.at(&xs, 3), 0.0);
        assert_eq!(h.at(&[1e300], 0), MAX_CURRENT);
    }
}
