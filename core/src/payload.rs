//! Typed payloads that travel on the graph's edges, and the trial metadata that
//! travels with each of them.
//!
//! Four payload kinds exist, in the order data flows through a tactile pipeline:
//!
//! | kind | type | what it holds |
//! |---|---|---|
//! | [`PayloadKind::Signals`] | [`Signals`] | analog taxel signals, one sample vector per taxel, at a sample rate |
//! | [`PayloadKind::Spikes`] | [`SpikeTrain`] | time-sorted spike events `(taxel, t_ms)` |
//! | [`PayloadKind::Images`] | [`SpikeImages`] | spike counts binned into frames of `window_ms`, one every `hop_ms` |
//! | [`PayloadKind::Estimates`] | [`Estimate`] | an orientation estimate (or "no edge") with every class's score |
//!
//! Coordinates: millimetres, `x` along the array's horizontal axis (the sliding
//! direction), `y` perpendicular to it, pointing "up" (towards row 0). A grid's
//! centre is the origin; taxel `i` of a grid sits at row `i / cols`, column
//! `i % cols`.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::sync::Arc;

/// The kind of a payload: what an edge of the graph carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PayloadKind {
    /// Analog taxel signals ([`Signals`]).
    Signals,
    /// Spike events ([`SpikeTrain`]).
    Spikes,
    /// Binned spike images ([`SpikeImages`]).
    Images,
    /// Orientation estimates ([`Estimate`]).
    Estimates,
}

impl PayloadKind {
    /// Every kind, in data-flow order.
    pub const ALL: [PayloadKind; 4] = [
        PayloadKind::Signals,
        PayloadKind::Spikes,
        PayloadKind::Images,
        PayloadKind::Estimates,
    ];
}

impl fmt::Display for PayloadKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            PayloadKind::Signals => "analog signals",
            PayloadKind::Spikes => "spike events",
            PayloadKind::Images => "spike images",
            PayloadKind::Estimates => "orientation estimates",
        })
    }
}

/// Where the taxels of an array are.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TaxelLayout {
    /// A regular `rows x cols` grid with centre-to-centre spacing `pitch_mm` and
    /// square taxels of side `taxel_mm`, centred on the origin.
    Grid {
        /// Number of rows (along `y`).
        rows: usize,
        /// Number of columns (along `x`).
        cols: usize,
        /// Centre-to-centre spacing, mm.
        pitch_mm: f64,
        /// Side of a square taxel, mm.
        taxel_mm: f64,
    },
    /// An explicit list of taxel centres, mm, for skins that are not grids; each
    /// taxel is taken as a square of side `taxel_mm`.
    Positions {
        /// Taxel centres `[x, y]`, mm.
        positions_mm: Vec<[f64; 2]>,
        /// Side of a square taxel, mm.
        taxel_mm: f64,
    },
}

impl TaxelLayout {
    /// The paper's array: 4 x 4 taxels, 3 mm pitch, 2 mm taxels.
    pub fn paper() -> Self {
        TaxelLayout::Grid {
            rows: 4,
            cols: 4,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        }
    }

    /// Number of taxels.
    pub fn len(&self) -> usize {
        match self {
            // Saturating: a layout is validated (at most MAX_TAXELS) before use,
            // but `len` must not panic on one that was not.
            TaxelLayout::Grid { rows, cols, .. } => rows.saturating_mul(*cols),
            TaxelLayout::Positions { positions_mm, .. } => positions_mm.len(),
        }
    }

    /// True when the layout has no taxel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Side of a (square) taxel, mm.
    pub fn taxel_mm(&self) -> f64 {
        match self {
            TaxelLayout::Grid { taxel_mm, .. } | TaxelLayout::Positions { taxel_mm, .. } => *taxel_mm,
        }
    }

    /// `(rows, cols)` for a grid, `None` for an explicit list.
    pub fn grid(&self) -> Option<(usize, usize)> {
        match self {
            TaxelLayout::Grid { rows, cols, .. } => Some((*rows, *cols)),
            TaxelLayout::Positions { .. } => None,
        }
    }

    /// `(row, col)` of taxel `i` in a grid.
    pub fn row_col(&self, i: usize) -> Option<(usize, usize)> {
        self.grid().map(|(_, cols)| (i / cols, i % cols))
    }

    /// Centre of taxel `i`, `[x, y]` in mm.
    ///
    /// Panics if `i >= self.len()` (an internal invariant: callers index taxels
    /// of this layout).
    pub fn position(&self, i: usize) -> [f64; 2] {
        match self {
            TaxelLayout::Grid {
                rows, cols, pitch_mm, ..
            } => {
                let (r, c) = (i / cols, i % cols);
                assert!(r < *rows, "taxel {i} outside a {rows}x{cols} grid");
                let x = (c as f64 - (*cols as f64 - 1.0) / 2.0) * pitch_mm;
                let y = ((*rows as f64 - 1.0) / 2.0 - r as f64) * pitch_mm;
                [x, y]
            }
            TaxelLayout::Positions { positions_mm, .. } => positions_mm[i],
        }
    }

    /// Every taxel centre, in taxel order.
    pub fn positions(&self) -> Vec<[f64; 2]> {
        (0..self.len()).map(|i| self.position(i)).collect()
    }

    /// Most taxels a layout may have (the paper's array has 16; a DAQ frame
    /// carries at most 1024 channels): a documented cap, so that sizes derived
    /// from the layout cannot overflow or exhaust memory.
    pub const MAX_TAXELS: usize = 1 << 16;

    /// Checks that the layout describes at least one and at most
    /// [`TaxelLayout::MAX_TAXELS`] taxels of positive, finite size.
    pub fn validate(&self) -> Result<(), String> {
        let n = match self {
            TaxelLayout::Grid { rows, cols, .. } => rows.checked_mul(*cols),
            TaxelLayout::Positions { positions_mm, .. } => Some(positions_mm.len()),
        };
        if n.is_none_or(|n| n > Self::MAX_TAXELS) {
            return Err(format!(
                "{} taxels is over the cap of {}",
                n.map_or_else(|| "more than 2^64".to_string(), |n| n.to_string()),
                Self::MAX_TAXELS
            ));
        }
        let t = self.taxel_mm();
        if !(t.is_finite() && t > 0.0) {
            return Err(format!(
                "taxel size must be a positive number of mm, got {}",
                crate::fmt_num(t)
            ));
        }
        match self {
            TaxelLayout::Grid {
                rows, cols, pitch_mm, ..
            } => {
                if *rows == 0 || *cols == 0 {
                    return Err(format!(
                        "a grid needs at least one row and one column, got {rows}x{cols}"
                    ));
                }
                if !(pitch_mm.is_finite() && *pitch_mm > 0.0) {
                    return Err(format!(
                        "pitch must be a positive number of mm, got {}",
                        crate::fmt_num(*pitch_mm)
                    ));
                }
            }
            TaxelLayout::Positions { positions_mm, .. } => {
                if positions_mm.is_empty() {
                    return Err("an explicit layout needs at least one taxel position".into());
                }
                if let Some(p) = positions_mm
                    .iter()
                    .find(|p| !(p[0].is_finite() && p[1].is_finite()))
                {
                    return Err(format!("taxel position {p:?} is not finite"));
                }
                // Two taxels at one point cannot be told apart by anything
                // spatial (a pasted line, most likely): refused, naming both.
                let mut order: Vec<usize> = (0..positions_mm.len()).collect();
                order.sort_by(|&a, &b| {
                    // `+ 0.0` makes −0 and 0 one key, as `==` sees them.
                    let (p, q) = (positions_mm[a], positions_mm[b]);
                    (p[0] + 0.0)
                        .total_cmp(&(q[0] + 0.0))
                        .then((p[1] + 0.0).total_cmp(&(q[1] + 0.0)))
                        .then(a.cmp(&b))
                });
                if let Some(w) = order
                    .windows(2)
                    .find(|w| positions_mm[w[0]] == positions_mm[w[1]])
                {
                    let p = positions_mm[w[0]];
                    return Err(format!(
                        "taxels {} and {} share the position [{}, {}] mm: every taxel needs its own",
                        w[0],
                        w[1],
                        crate::fmt_num(p[0] + 0.0),
                        crate::fmt_num(p[1] + 0.0)
                    ));
                }
            }
        }
        Ok(())
    }
}

/// What kind of stimulus a trial palpates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Stimulus {
    /// The boundary edge of an object (the paper's main experiment).
    #[default]
    Edge,
    /// A ridge on a flat surface (paper section 3.6).
    Ridge,
    /// Not known (e.g. a recording without a label).
    Unknown,
}

impl fmt::Display for Stimulus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Stimulus::Edge => "edge",
            Stimulus::Ridge => "ridge",
            Stimulus::Unknown => "unknown",
        })
    }
}

/// The ground truth of a trial, where known.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Label {
    /// Stimulus kind.
    pub stimulus: Stimulus,
    /// True orientation of the edge, degrees from the array's horizontal axis;
    /// `None` when unknown or when the trial has no edge.
    pub angle_deg: Option<f64>,
}

/// One step of a payload's provenance: which stage made it, with which settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// The stage's id in the graph.
    pub stage: String,
    /// The stage's registered type.
    pub type_name: String,
    /// The stage's settings, as the JSON of its config (shared by every trial).
    pub settings: Arc<serde_json::Value>,
}

/// Metadata that travels with every payload of a trial.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct TrialMeta {
    /// Unique id of the trial within its source, e.g. `edge-45deg-r03`.
    pub trial_id: String,
    /// Position of the trial in its source's order.
    pub index: usize,
    /// Ground truth.
    pub label: Label,
    /// The key cross-validation groups by: the repetition number of the trial
    /// within its class. Leave-one-trial-out fold `f` tests every trial whose
    /// group is the `f`-th distinct group.
    pub group: usize,
    /// When the edge crosses the array, `[start, end]` in ms from the trial's
    /// start, if the source knows it (simulated scenes do).
    pub crossing_ms: Option<[f64; 2]>,
    /// The sliding speed the trial was palpated at, mm/s, as commanded (what
    /// a robot knows beforehand, not a measurement), if the source knows it:
    /// a scene's `motion.speed_mm_s` (of the trial's condition), a recording's
    /// `speed_mm_s` label (or condition). Model-based estimators that need the
    /// speed (WSS) take it from here unless their own config sets one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_mm_s: Option<f64>,
    /// The conditions the trial was recorded under, by name, e.g.
    /// `condition = "fast"` for a scene's `conditions` table, or a label
    /// file's extra keys (`speed_mm_s = "1.5"`): what
    /// `leave_one_condition_out` and `train_test` protocols split on. Empty
    /// by default.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub conditions: std::collections::BTreeMap<String, String>,
    /// Which stages made this payload, source first.
    pub provenance: Vec<Provenance>,
}

impl TrialMeta {
    /// Everything but provenance (which names the settings of every stage
    /// upstream, and so differs between sweep points that produce the same
    /// trial): what content and cache keys hash of a trial's metadata.
    pub(crate) fn identity(&self) -> serde_json::Value {
        serde_json::json!([
            self.trial_id,
            self.index,
            self.label,
            self.group,
            self.crossing_ms,
            self.conditions,
            self.speed_mm_s
        ])
    }
}

/// Analog taxel signals of one trial.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Signals {
    /// Samples per second of every taxel, Hz.
    pub sample_rate_hz: f64,
    /// Where the taxels are.
    pub layout: TaxelLayout,
    /// What the values measure, e.g. `"V"`, `"pressure (normalized)"`, `"current"`.
    pub unit: String,
    /// `data[taxel][sample]`; every taxel has the same number of samples.
    pub data: Vec<Vec<f64>>,
}

impl Signals {
    /// Number of samples per taxel.
    pub fn n_samples(&self) -> usize {
        self.data.first().map_or(0, Vec::len)
    }

    /// Duration of the trial, ms.
    pub fn duration_ms(&self) -> f64 {
        self.n_samples() as f64 * 1000.0 / self.sample_rate_hz
    }

    /// A copy of these signals' frame (rate, layout) with new data and unit.
    pub fn with_data(&self, unit: impl Into<String>, data: Vec<Vec<f64>>) -> Signals {
        Signals {
            sample_rate_hz: self.sample_rate_hz,
            layout: self.layout.clone(),
            unit: unit.into(),
            data,
        }
    }
}

/// One spike: which taxel fired, and when.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpikeEvent {
    /// Taxel index in the layout.
    pub taxel: u32,
    /// Time from the trial's start, ms.
    pub t_ms: f64,
}

/// The spike events of one trial, sorted by time (ties by taxel).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpikeTrain {
    /// Where the taxels are.
    pub layout: TaxelLayout,
    /// Length of the trial, ms; every event lies in `[0, duration_ms)`.
    pub duration_ms: f64,
    /// Events, time-sorted.
    pub events: Vec<SpikeEvent>,
}

impl SpikeTrain {
    /// Sorts events by time, then taxel (a total order: times are finite).
    pub fn sort(&mut self) {
        self.events
            .sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms).then(a.taxel.cmp(&b.taxel)));
    }

    /// True when events are sorted by time.
    pub fn is_sorted(&self) -> bool {
        self.events.windows(2).all(|w| w[0].t_ms <= w[1].t_ms)
    }
}

/// Spike counts binned into frames: frame `k` covers `[k*hop_ms, k*hop_ms + window_ms)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpikeImages {
    /// Where the taxels are.
    pub layout: TaxelLayout,
    /// Frame length, ms.
    pub window_ms: f64,
    /// Time between frame starts, ms.
    pub hop_ms: f64,
    /// Number of frames.
    pub n_frames: usize,
    /// `counts[k * n_taxels + taxel]`: spikes of `taxel` in frame `k`.
    pub counts: Vec<f64>,
}

impl SpikeImages {
    /// Number of taxels per frame.
    pub fn n_taxels(&self) -> usize {
        self.layout.len()
    }

    /// The counts of frame `k`, one per taxel.
    pub fn frame(&self, k: usize) -> &[f64] {
        let n = self.n_taxels();
        &self.counts[k * n..(k + 1) * n]
    }
}

/// One class's score in an estimate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClassScore {
    /// The class's orientation, degrees.
    pub angle_deg: f64,
    /// The estimator's score for it (higher is more likely).
    pub score: f64,
}

/// An estimator's answer for one trial.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Estimate {
    /// Estimated orientation, degrees; `None` means "no edge".
    pub angle_deg: Option<f64>,
    /// The best class of the estimator's grid (equals `angle_deg` unless the
    /// estimator refines between classes); `None` means "no edge".
    pub class_deg: Option<f64>,
    /// Every class's score, in the estimator's class order.
    pub scores: Vec<ClassScore>,
    /// Frame at which the best score was reached, if the estimator is frame-based.
    pub best_frame: Option<usize>,
    /// How much palpation the answer needed, ms from the trial's start.
    pub decision_time_ms: Option<f64>,
    /// The estimator flags its answer as unreliable (each estimator documents
    /// its rule; WSS: a class that is not the best's grid neighbour scores
    /// nearly as well, or the answer's crossing is longer than its templates).
    /// An uncertain answer is still an answer: sinks count it, never drop it.
    /// Absent in older files: false.
    #[serde(default)]
    pub uncertain: bool,
}

/// A payload of any kind. Large payloads are shared, never copied, between the
/// stages that read them.
#[derive(Clone, Debug)]
pub enum Payload {
    /// Analog signals.
    Signals(Arc<Signals>),
    /// Spike events.
    Spikes(Arc<SpikeTrain>),
    /// Spike images.
    Images(Arc<SpikeImages>),
    /// An estimate.
    Estimate(Arc<Estimate>),
}

impl Payload {
    /// Heap bytes the payload's data hold, approximately (samples, events,
    /// counts, scores; small fixed parts and metadata left out): what a cache
    /// of outputs budgets by.
    pub fn approx_bytes(&self) -> usize {
        match self {
            Payload::Signals(s) => s.data.iter().map(|t| t.len() * 8 + 24).sum(),
            Payload::Spikes(s) => s.events.len() * std::mem::size_of::<SpikeEvent>(),
            Payload::Images(i) => i.counts.len() * 8,
            Payload::Estimate(e) => e.scores.len() * std::mem::size_of::<ClassScore>() + 64,
        }
    }

    /// This payload's kind.
    pub fn kind(&self) -> PayloadKind {
        match self {
            Payload::Signals(_) => PayloadKind::Signals,
            Payload::Spikes(_) => PayloadKind::Spikes,
            Payload::Images(_) => PayloadKind::Images,
            Payload::Estimate(_) => PayloadKind::Estimates,
        }
    }

    /// The signals, or an error naming the kind actually present.
    pub fn signals(&self) -> Result<&Arc<Signals>, crate::StageError> {
        match self {
            Payload::Signals(s) => Ok(s),
            other => Err(crate::StageError::wrong_kind(PayloadKind::Signals, other.kind())),
        }
    }

    /// The spikes, or an error naming the kind actually present.
    pub fn spikes(&self) -> Result<&Arc<SpikeTrain>, crate::StageError> {
        match self {
            Payload::Spikes(s) => Ok(s),
            other => Err(crate::StageError::wrong_kind(PayloadKind::Spikes, other.kind())),
        }
    }

    /// The images, or an error naming the kind actually present.
    pub fn images(&self) -> Result<&Arc<SpikeImages>, crate::StageError> {
        match self {
            Payload::Images(s) => Ok(s),
            other => Err(crate::StageError::wrong_kind(PayloadKind::Images, other.kind())),
        }
    }

    /// The estimate, or an error naming the kind actually present.
    pub fn estimate(&self) -> Result<&Arc<Estimate>, crate::StageError> {
        match self {
            Payload::Estimate(s) => Ok(s),
            other => Err(crate::StageError::wrong_kind(
                PayloadKind::Estimates,
                other.kind(),
            )),
        }
    }
}

impl From<Signals> for Payload {
    fn from(v: Signals) -> Self {
        Payload::Signals(Arc::new(v))
    }
}
impl From<SpikeTrain> for Payload {
    fn from(v: SpikeTrain) -> Self {
        Payload::Spikes(Arc::new(v))
    }
}
impl From<SpikeImages> for Payload {
    fn from(v: SpikeImages) -> Self {
        Payload::Images(Arc::new(v))
    }
}
impl From<Estimate> for Payload {
    fn from(v: Estimate) -> Self {
        Payload::Estimate(Arc::new(v))
    }
}

/// A payload together with its trial's metadata: what flows along an edge.
#[derive(Clone, Debug)]
pub struct Item {
    /// The trial's metadata, including provenance up to and including the stage
    /// that made `payload`.
    pub meta: Arc<TrialMeta>,
    /// The data.
    pub payload: Payload,
}

impl Item {
    /// A 64-bit hash of everything a trained estimator may read of this item:
    /// the payload's data and the metadata other than provenance (which names
    /// the settings of every stage upstream, and so differs between sweep
    /// points that produce the same trial). Equal keys mean equal items (up
    /// to hash collisions, ~1 in 2^64 per pair); a sweep's cache reuses a
    /// fitted model when its training items' keys are unchanged.
    ///
    /// XXH3 (64-bit) over the values' bits, fed in blocks: a fingerprint hash
    /// with full-width avalanche. It replaced `SipHash` fed one word at a
    /// time, which cost a run of the shift graph 73 ms (340 items), charged
    /// to its first trained estimator's time: 28.0 -> 4.2-4.8 ms for 170 lab
    /// trials (`cargo bench --bench io -- content_keys`). The keys
    /// live only in memory (a run's cache), so they need not be stable across
    /// versions or platforms.
    pub fn content_key(&self) -> u64 {
        let mut h = Words::default();
        h.json(&self.meta.identity());
        // Destructured in full: a new field is a compile error here until it
        // is hashed.
        match &self.payload {
            Payload::Signals(s) => {
                let Signals {
                    sample_rate_hz,
                    layout,
                    unit,
                    data,
                } = &**s;
                h.json(&serde_json::json!([
                    "signals",
                    sample_rate_hz,
                    layout,
                    unit,
                    data.len()
                ]));
                for row in data {
                    h.word(row.len() as u64);
                    h.f64s(row);
                }
            }
            Payload::Spikes(t) => {
                let SpikeTrain {
                    layout,
                    duration_ms,
                    events,
                } = &**t;
                h.json(&serde_json::json!(["spikes", layout, duration_ms, events.len()]));
                for e in events {
                    h.word(u64::from(e.taxel));
                    h.word(e.t_ms.to_bits());
                }
            }
            Payload::Images(i) => {
                let SpikeImages {
                    layout,
                    window_ms,
                    hop_ms,
                    n_frames,
                    counts,
                } = &**i;
                h.json(&serde_json::json!([
                    "images",
                    layout,
                    window_ms,
                    hop_ms,
                    n_frames,
                    counts.len()
                ]));
                h.f64s(counts);
            }
            Payload::Estimate(e) => h.json(&serde_json::json!(["estimate", e])),
        }
        h.finish()
    }
}

/// [`Item::content_key`]'s hasher: 64-bit words gathered into a block and
/// handed to XXH3 a block at a time (one `update` per word costs several
/// times the hashing).
struct Words {
    xxh: xxhash_rust::xxh3::Xxh3,
    buf: [u8; Words::BLOCK],
    len: usize,
}

impl Default for Words {
    fn default() -> Self {
        Words {
            xxh: xxhash_rust::xxh3::Xxh3::new(),
            buf: [0; Words::BLOCK],
            len: 0,
        }
    }
}

impl Words {
    /// Bytes gathered per `update`: 256 words.
    const BLOCK: usize = 2048;

    /// Free bytes in the block, handing a full one to XXH3 first.
    fn room(&mut self) -> usize {
        if self.len == Self::BLOCK {
            self.xxh.update(&self.buf);
            self.len = 0;
        }
        Self::BLOCK - self.len
    }

    /// Appends `b`, then zeros to the next whole word: the block's length
    /// stays a multiple of 8, which [`Self::f64s`] relies on.
    fn bytes(&mut self, mut b: &[u8]) {
        while !b.is_empty() {
            let n = b.len().min(self.room());
            self.buf[self.len..self.len + n].copy_from_slice(&b[..n]);
            self.len += n;
            b = &b[n..];
        }
        let pad = self.len.next_multiple_of(8) - self.len;
        self.buf[self.len..self.len + pad].fill(0);
        self.len += pad;
    }

    fn word(&mut self, w: u64) {
        self.bytes(&w.to_le_bytes());
    }

    /// The values' bits, written straight into the block (a loop the
    /// compiler turns into copies; a `word` per value was 1.7x slower).
    fn f64s(&mut self, mut v: &[f64]) {
        while !v.is_empty() {
            let (now, rest) = v.split_at(v.len().min(self.room() / 8));
            let dst = &mut self.buf[self.len..self.len + 8 * now.len()];
            for (d, x) in dst.chunks_exact_mut(8).zip(now) {
                d.copy_from_slice(&x.to_bits().to_le_bytes());
            }
            self.len += 8 * now.len();
            v = rest;
        }
    }

    /// A JSON value's text, after its length (so no text can run into the
    /// words that follow it).
    fn json(&mut self, v: &serde_json::Value) {
        let text = v.to_string();
        self.word(text.len() as u64);
        self.bytes(text.as_bytes());
    }

    fn finish(mut self) -> u64 {
        self.xxh.update(&self.buf[..self.len]);
        self.xxh.digest()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keyed(meta: TrialMeta, payload: Payload) -> u64 {
        Item {
            meta: Arc::new(meta),
            payload,
        }
        .content_key()
    }

    fn images(counts: Vec<f64>) -> Payload {
        Payload::from(SpikeImages {
            layout: TaxelLayout::paper(),
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames: counts.len() / 16,
            counts,
        })
    }

    #[test]
    fn content_keys_see_every_value_and_no_provenance() {
        // Long enough to span several of the hasher's blocks (256 words).
        let counts: Vec<f64> = (0..16 * 100).map(|k| f64::from(k % 7)).collect();
        let meta = TrialMeta {
            trial_id: "edge-45deg-r00".into(),
            ..TrialMeta::default()
        };
        let base = keyed(meta.clone(), images(counts.clone()));
        assert_eq!(base, keyed(meta.clone(), images(counts.clone())));
        // Any one value, early, on a block boundary or last, changes the key.
        for k in [0, 255, 256, counts.len() - 1] {
            let mut c = counts.clone();
            c[k] += 1.0;
            assert_ne!(base, keyed(meta.clone(), images(c)), "count {k}");
        }
        // So do -0.0 against 0.0 (different bits a model may read) ...
        let mut c = counts.clone();
        c[0] = -0.0;
        assert_eq!(counts[0], 0.0);
        assert_ne!(base, keyed(meta.clone(), images(c)));
        // ... and the metadata a model may read ...
        let other = TrialMeta {
            group: 1,
            ..meta.clone()
        };
        assert_ne!(base, keyed(other, images(counts.clone())));
        // ... but not which stages made the payload.
        let traced = TrialMeta {
            provenance: vec![Provenance {
                stage: "bins".into(),
                type_name: "bin".into(),
                settings: Arc::new(serde_json::json!({"hop_ms": 10.0})),
            }],
            ..meta.clone()
        };
        assert_eq!(base, keyed(traced, images(counts)));
        // Signals split into rows differently are different items.
        let signals = |data: Vec<Vec<f64>>| {
            Payload::from(Signals {
                sample_rate_hz: 1000.0,
                layout: TaxelLayout::paper(),
                unit: "V".into(),
                data,
            })
        };
        assert_ne!(
            keyed(meta.clone(), signals(vec![vec![1.0, 2.0], vec![3.0]])),
            keyed(meta.clone(), signals(vec![vec![1.0], vec![2.0, 3.0]]))
        );
        // Spikes: which taxel fired matters, not only when.
        let spikes = |taxel: u32| {
            Payload::from(SpikeTrain {
                layout: TaxelLayout::paper(),
                duration_ms: 10.0,
                events: vec![SpikeEvent { taxel, t_ms: 1.0 }],
            })
        };
        assert_ne!(keyed(meta.clone(), spikes(0)), keyed(meta, spikes(1)));
    }

    #[test]
    fn grid_positions_are_centred_and_row0_on_top() {
        let l = TaxelLayout::paper();
        assert_eq!(l.len(), 16);
        assert_eq!(l.position(0), [-4.5, 4.5]);
        assert_eq!(l.position(3), [4.5, 4.5]);
        assert_eq!(l.position(15), [4.5, -4.5]);
        assert_eq!(l.row_col(6), Some((1, 2)));
        let sum: [f64; 2] = l
            .positions()
            .iter()
            .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
        assert_eq!(sum, [0.0, 0.0]);
    }

    #[test]
    fn layout_validation_names_the_problem() {
        let bad = TaxelLayout::Grid {
            rows: 0,
            cols: 4,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        };
        assert!(bad.validate().unwrap_err().contains("row"));
        let bad = TaxelLayout::Positions {
            positions_mm: vec![[0.0, f64::NAN]],
            taxel_mm: 1.0,
        };
        assert!(bad.validate().unwrap_err().contains("not finite"));
        // Two taxels at one point (−0 and 0 are one point), named.
        let bad = TaxelLayout::Positions {
            positions_mm: vec![[1.0, 2.0], [-0.0, 5.0], [-0.0, 7.0], [0.0, 5.0]],
            taxel_mm: 1.0,
        };
        let e = bad.validate().unwrap_err();
        assert!(e.contains("taxels 1 and 3 share the position [0, 5] mm"), "{e}");
        let ok = TaxelLayout::Positions {
            positions_mm: vec![[0.0, 5.0], [5.0, 0.0]],
            taxel_mm: 1.0,
        };
        assert!(ok.validate().is_ok());
        assert!(TaxelLayout::paper().validate().is_ok());
    }

    #[test]
    fn spike_sort_is_by_time_then_taxel() {
        let mut s = SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms: 10.0,
            events: vec![
                SpikeEvent { taxel: 3, t_ms: 2.0 },
                SpikeEvent { taxel: 1, t_ms: 2.0 },
                SpikeEvent { taxel: 0, t_ms: 1.0 },
            ],
        };
        assert!(!s.is_sorted());
        s.sort();
        assert!(s.is_sorted());
        assert_eq!(s.events[1].taxel, 1);
    }
}
