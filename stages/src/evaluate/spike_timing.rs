//! The spike-timing sink: per taxel, when spikes fire relative to the moment
//! the edge crosses that taxel's centre (Kumar et al. 2020, section 3.1 and
//! Fig. 5), pooled over every trial and orientation.
//!
//! # Ground truth: when the edge crosses a taxel's centre
//!
//! Core's geometry (`palpate_core::geometry`): the edge at `θ` has normal `n`,
//! its offset `s` falls at the normal speed `v sin θ` while the array slides,
//! and taxel `i` with centre `p_i` is crossed when `s = n·p_i = c_i`.
//!
//! * A trial that knows its crossing `[t₀, t₁]` (a simulated scene: the edge
//!   touches the first taxel at `t₀`, when `s = hi`, and leaves the last at
//!   `t₁`, when `s = lo - W`, with `(lo, hi)` the taxels' footprint along `n`
//!   and `W` the stimulus width, key `stimulus_width_mm`) has `s` linear in
//!   between, so the centre of the stimulus (`s + W/2`) meets `c_i` at
//!   `t_i = t₀ + (hi + W/2 - c_i) (t₁ - t₀) / (hi + W - lo)`.
//! * A recording without a crossing declares when the edge crosses the
//!   array's centre (`centre_crossing_ms`, the layout's origin) and the
//!   palpation speed `v` (`speed_mm_s`, else each trial's own declared
//!   speed, e.g. from its label file): `s(t) = -v sin θ (t - t_c)`, so
//!   `t_i = t_c - c_i / (v sin θ)`.
//!
//! Trials without a true angle, or without a crossing when no centre
//! crossing or no speed is declared, are skipped and counted.
//!
//! # Statistics, per taxel, of the relative times `d = t_spike - t_i` (s)
//!
//! * `n`, mean, SD (population), median, 5 % and 95 % quantiles (linear
//!   interpolation between order statistics), the half-width of the central
//!   90 %, `(q95 - q5) / 2`: the "± spread" the paper reads off Fig. 5;
//! * skew: the sample skewness `m₃ / m₂^{3/2}` (0 when every `d` is equal);
//! * peak offset: the centre of the fullest histogram bin (bins of `bin_ms`
//!   centred on 0, counted over `|d| ≤ range_ms`; ties to the bin nearest 0);
//! * overlap with neighbours: per trial, for each neighbour `j` of taxel `i`
//!   (centres no further apart than 1.01 × the layout's smallest centre
//!   distance: the 4-neighbours of a grid), the overlap coefficient of their
//!   spike-time histograms in absolute time, `Σ_b min(p_i(b), p_j(b))` with
//!   `p` each taxel's share of its spikes in bin `b` (1 = the two fire at the
//!   same moments, 0 = never in the same bin); averaged over trials and
//!   neighbours where both fired.
//!
//! Pooled over taxels (the run's metrics, `<id>.<name>`): `half_range_s` and
//! `sd_s` (means over taxels), `peak_abs_s` (mean `|peak offset|`),
//! `peak_off_zero` (share of taxels whose peak is not the zero bin),
//! `taxel_spread_cv` (SD over taxels of the half-range / its mean: how much
//! taxels differ), `skew` (mean), `overlap` (mean), `spikes` (total counted).
//!
//! Files, written atomically: `<id>.json`, `<id>.csv` (one row per taxel),
//! `<id>.md`, and `<id>.svg` (one histogram per taxel, laid out like the
//! array, with the zero line: the paper's Fig. 5).

use palpate_core::geometry::Edge;
use palpate_core::output::write_atomic;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, PayloadKind, Sink, SinkContext, SinkInput,
    SinkReport, Stage, StageConfig, StageError, TaxelLayout,
};
use plotters::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// Largest number of histogram bins per taxel (`2 range_ms / bin_ms`): a
/// config that asks for more is an error, not an allocation.
pub const MAX_BINS: f64 = 100_000.0;

/// Per-taxel spike times relative to the edge crossing the taxel's centre
/// (the paper's Fig. 5): spread, skew, peak offset and overlap with
/// neighbours, as a table, CSV, JSON and an SVG of histograms.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SpikeTimingConfig {
    /// Histogram bin width, ms (the peak offset's resolution). Default 100.
    pub bin_ms: f64,
    /// Half-width of the histograms' window of relative times, ms: the peak is
    /// searched and plotted within ±range_ms (every spike still counts in the
    /// SD and quantiles). Default 4000.
    pub range_ms: f64,
    /// Width of the stimulus along its normal, mm: 0 for an edge, the bar's
    /// width for a ridge (its centre line is what "crosses"). Default 0.
    pub stimulus_width_mm: f64,
    /// Palpation speed, mm/s, for trials that carry no crossing (recordings);
    /// with `centre_crossing_ms`. Default none: each trial's own declared
    /// speed (a recording's `speed_mm_s` label); a trial with none is skipped.
    pub speed_mm_s: Option<f64>,
    /// When the edge crosses the array's centre, ms from each trial's start,
    /// for trials that carry no crossing. Default none (such trials are skipped).
    pub centre_crossing_ms: Option<f64>,
}

impl Default for SpikeTimingConfig {
    fn default() -> Self {
        SpikeTimingConfig {
            bin_ms: 100.0,
            range_ms: 4000.0,
            stimulus_width_mm: 0.0,
            speed_mm_s: None,
            centre_crossing_ms: None,
        }
    }
}

#[typetag::serde(name = "spike_timing")]
impl StageConfig for SpikeTimingConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        self.check()?;
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("spike_timing", SpikeTimingConfig);

impl SpikeTimingConfig {
    fn check(&self) -> Result<(), ConfigError> {
        let mut c = palpate_core::ConfigChecks::new();
        let bin = c.take(palpate_core::check_positive("bin_ms", self.bin_ms, "ms"));
        let range = c.take(palpate_core::check_positive("range_ms", self.range_ms, "ms"));
        if bin.is_some() && range.is_some() && 2.0 * self.range_ms / self.bin_ms > MAX_BINS {
            c.push(ConfigError::key(
                "bin_ms",
                format!(
                    "2 range_ms / bin_ms = {:.0} bins, more than the limit of {MAX_BINS:.0}",
                    2.0 * self.range_ms / self.bin_ms
                ),
            ));
        }
        c.take(palpate_core::check_range(
            "stimulus_width_mm",
            self.stimulus_width_mm,
            0.0,
            1e3,
            "mm",
        ));
        if let Some(v) = self.speed_mm_s {
            c.take(palpate_core::check_positive("speed_mm_s", v, "mm/s"));
        }
        match self.centre_crossing_ms {
            Some(t) => {
                c.take(palpate_core::check_range(
                    "centre_crossing_ms",
                    t,
                    -1e12,
                    1e12,
                    "ms",
                ));
            }
            // Without it a speed (the config's) could never be used.
            None if self.speed_mm_s.is_some() => c.push(ConfigError::key(
                "centre_crossing_ms",
                "needed with `speed_mm_s`: when the edge crosses the array's centre",
            )),
            None => {}
        }
        c.finish()
    }

    /// When the stimulus' centre line crosses each taxel's centre in this
    /// trial, ms from its start; `None` when the trial has no angle, or no
    /// crossing and no declared centre crossing or speed (the config's, else
    /// the trial's).
    pub fn crossing_times(
        &self,
        item_meta: &palpate_core::TrialMeta,
        layout: &TaxelLayout,
    ) -> Option<Vec<f64>> {
        let theta = item_meta.label.angle_deg?;
        if !(theta > 0.0 && theta < 180.0) {
            return None;
        }
        let edge = Edge::new(theta);
        let centres: Vec<f64> = layout.positions().iter().map(|&p| edge.offset(p)).collect();
        let w = self.stimulus_width_mm;
        if let Some([t0, t1]) = item_meta.crossing_ms {
            let (lo, hi) = edge.footprint(layout);
            let extent = hi + w - lo;
            if !(t1 > t0 && extent > 0.0 && t0.is_finite() && t1.is_finite()) {
                return None;
            }
            let ms_per_mm = (t1 - t0) / extent;
            return Some(
                centres
                    .iter()
                    .map(|c| t0 + (hi + w / 2.0 - c) * ms_per_mm)
                    .collect(),
            );
        }
        let tc = self.centre_crossing_ms?;
        let v = self.speed_mm_s.or(item_meta.speed_mm_s)?;
        if !(v.is_finite() && v > 0.0) {
            return None;
        }
        let vn = edge.normal_speed(v) / 1000.0; // mm per ms
        Some(centres.iter().map(|c| tc - c / vn).collect())
    }
}

/// Statistics of one taxel's relative spike times.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct TaxelTiming {
    /// Taxel name (`r0c0`, ... for a grid; `t0`, ... otherwise).
    pub taxel: String,
    /// Spikes counted.
    pub n: usize,
    /// Mean relative time, s.
    pub mean_s: f64,
    /// Population SD, s.
    pub sd_s: f64,
    /// Median, s.
    pub median_s: f64,
    /// 5 % quantile, s.
    pub q05_s: f64,
    /// 95 % quantile, s.
    pub q95_s: f64,
    /// `(q95 - q05) / 2`, s.
    pub half_range_s: f64,
    /// Sample skewness.
    pub skew: f64,
    /// Centre of the fullest histogram bin, s.
    pub peak_s: f64,
    /// Mean overlap coefficient with the neighbours, in [0, 1]; `None` when no
    /// neighbour fired in the same trial.
    pub overlap: Option<f64>,
    /// Histogram counts over `[-range, range]`, bins of `bin_ms` centred on 0.
    #[serde(skip)]
    pub hist: Vec<usize>,
}

/// The sink's result.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Timing {
    /// Per taxel, in layout order.
    pub taxels: Vec<TaxelTiming>,
    /// Trials counted.
    pub trials: usize,
    /// Trials skipped (no angle, or no crossing and no declared speed).
    pub skipped: usize,
    /// Pooled statistics: `(name, value)`, see the module docs.
    pub pooled: Vec<(String, f64)>,
    /// Histogram bin, ms.
    pub bin_ms: f64,
    /// Histogram half-window, ms.
    pub range_ms: f64,
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let (i, f) = (pos.floor() as usize, pos - pos.floor());
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] + f * (sorted[j] - sorted[i])
}

/// Taxels whose centres lie within 1.01 x the smallest centre distance.
fn neighbours(layout: &TaxelLayout) -> Vec<Vec<usize>> {
    let p = layout.positions();
    let d = |a: usize, b: usize| (p[a][0] - p[b][0]).hypot(p[a][1] - p[b][1]);
    let mut min = f64::INFINITY;
    for a in 0..p.len() {
        for b in a + 1..p.len() {
            min = min.min(d(a, b));
        }
    }
    (0..p.len())
        .map(|a| {
            (0..p.len())
                .filter(|&b| b != a && d(a, b) <= 1.01 * min)
                .collect()
        })
        .collect()
}

/// Computes every statistic of the module docs over `items` (spike trains).
pub fn analyse(cfg: &SpikeTimingConfig, items: &[Item]) -> Result<Timing, StageError> {
    let Some(first) = items.first() else {
        return Ok(Timing {
            bin_ms: cfg.bin_ms,
            range_ms: cfg.range_ms,
            ..Timing::default()
        });
    };
    let layout = first.payload.spikes()?.layout.clone();
    let n_tax = layout.len();
    let nb = neighbours(&layout);
    let half_bins = (cfg.range_ms / cfg.bin_ms - 0.5).ceil().max(0.0) as i64;
    let n_bins = (2 * half_bins + 1) as usize;
    let mut rel: Vec<Vec<f64>> = vec![Vec::new(); n_tax];
    let mut hist = vec![vec![0usize; n_bins]; n_tax];
    let mut overlap_sum = vec![0.0; n_tax];
    let mut overlap_n = vec![0usize; n_tax];
    let (mut trials, mut skipped) = (0, 0);
    for item in items {
        let spikes = item.payload.spikes()?;
        if spikes.layout != layout {
            return Err(StageError::new(format!(
                "trial `{}` has a different taxel layout from trial `{}`: one array per analysis",
                item.meta.trial_id, first.meta.trial_id
            )));
        }
        let Some(tc) = cfg.crossing_times(&item.meta, &layout) else {
            skipped += 1;
            continue;
        };
        trials += 1;
        // Absolute-time histograms of this trial, sparse: bin -> count.
        let mut abs: Vec<BTreeMap<i64, usize>> = vec![BTreeMap::new(); n_tax];
        let mut counts = vec![0usize; n_tax];
        for e in &spikes.events {
            let i = e.taxel as usize;
            if i >= n_tax || !e.t_ms.is_finite() {
                return Err(StageError::new(format!(
                    "trial `{}`: spike on taxel {i} at {} ms is outside the {n_tax}-taxel array or not finite",
                    item.meta.trial_id, e.t_ms
                )));
            }
            let d = e.t_ms - tc[i];
            rel[i].push(d / 1000.0);
            let b = (d / cfg.bin_ms).round();
            if b.abs() <= half_bins as f64 {
                hist[i][(b as i64 + half_bins) as usize] += 1;
            }
            *abs[i].entry((e.t_ms / cfg.bin_ms).floor() as i64).or_insert(0) += 1;
            counts[i] += 1;
        }
        for a in 0..n_tax {
            if counts[a] == 0 {
                continue;
            }
            for &b in &nb[a] {
                if counts[b] == 0 {
                    continue;
                }
                let ov: f64 = abs[a]
                    .iter()
                    .filter_map(|(k, &ca)| {
                        abs[b]
                            .get(k)
                            .map(|&cb| (ca as f64 / counts[a] as f64).min(cb as f64 / counts[b] as f64))
                    })
                    .sum();
                overlap_sum[a] += ov;
                overlap_n[a] += 1;
            }
        }
    }
    let names = crate::scene::taxel_names(&layout);
    let mut taxels = Vec::with_capacity(n_tax);
    for (i, mut d) in rel.into_iter().enumerate() {
        d.sort_by(f64::total_cmp);
        let n = d.len();
        let mut t = TaxelTiming {
            taxel: names[i].clone(),
            n,
            overlap: (overlap_n[i] > 0).then(|| overlap_sum[i] / overlap_n[i] as f64),
            ..TaxelTiming::default()
        };
        if n > 0 {
            let nf = n as f64;
            let mean = d.iter().sum::<f64>() / nf;
            let m2 = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / nf;
            let m3 = d.iter().map(|x| (x - mean).powi(3)).sum::<f64>() / nf;
            t.mean_s = mean;
            t.sd_s = m2.sqrt();
            // Below ~1e-12 s^2 the spread is rounding: no shape to speak of.
            t.skew = if m2 > 1e-24 { m3 / m2.powf(1.5) } else { 0.0 };
            t.median_s = quantile(&d, 0.5);
            t.q05_s = quantile(&d, 0.05);
            t.q95_s = quantile(&d, 0.95);
            t.half_range_s = (t.q95_s - t.q05_s) / 2.0;
            // Fullest bin; ties go to the bin nearest 0 (then the earlier).
            let best = (0..n_bins)
                .max_by(|&a, &b| {
                    hist[i][a]
                        .cmp(&hist[i][b])
                        .then((b as i64 - half_bins).abs().cmp(&(a as i64 - half_bins).abs()))
                        .then(b.cmp(&a))
                })
                .unwrap_or(half_bins as usize);
            if hist[i][best] > 0 {
                t.peak_s = (best as i64 - half_bins) as f64 * cfg.bin_ms / 1000.0;
            }
        }
        t.hist = std::mem::take(&mut hist[i]);
        taxels.push(t);
    }
    let fired: Vec<&TaxelTiming> = taxels.iter().filter(|t| t.n > 0).collect();
    let mean_of = |f: &dyn Fn(&TaxelTiming) -> f64| {
        if fired.is_empty() {
            0.0
        } else {
            fired.iter().map(|t| f(t)).sum::<f64>() / fired.len() as f64
        }
    };
    let hr = mean_of(&|t| t.half_range_s);
    let hr_sd = if fired.is_empty() {
        0.0
    } else {
        (fired.iter().map(|t| (t.half_range_s - hr).powi(2)).sum::<f64>() / fired.len() as f64).sqrt()
    };
    let with_overlap: Vec<f64> = taxels.iter().filter_map(|t| t.overlap).collect();
    let pooled = vec![
        ("half_range_s".to_string(), hr),
        ("sd_s".to_string(), mean_of(&|t| t.sd_s)),
        ("peak_abs_s".to_string(), mean_of(&|t| t.peak_s.abs())),
        (
            "peak_off_zero".to_string(),
            mean_of(&|t| if t.peak_s != 0.0 { 1.0 } else { 0.0 }),
        ),
        (
            "taxel_spread_cv".to_string(),
            if hr > 0.0 { hr_sd / hr } else { 0.0 },
        ),
        ("skew".to_string(), mean_of(&|t| t.skew)),
        (
            "overlap".to_string(),
            if with_overlap.is_empty() {
                0.0
            } else {
                with_overlap.iter().sum::<f64>() / with_overlap.len() as f64
            },
        ),
        (
            "spikes".to_string(),
            taxels.iter().map(|t| t.n).sum::<usize>() as f64,
        ),
    ];
    Ok(Timing {
        taxels,
        trials,
        skipped,
        pooled,
        bin_ms: cfg.bin_ms,
        range_ms: cfg.range_ms,
    })
}

impl Timing {
    /// The per-taxel table as Markdown.
    pub fn to_markdown(&self) -> String {
        let mut s = String::from(
            "| taxel | spikes | mean (s) | SD (s) | 5-95 % (s) | ± half 90 % (s) | skew | peak (s) | overlap |\n|---|---|---|---|---|---|---|---|---|\n",
        );
        for t in &self.taxels {
            let _ = writeln!(
                s,
                "| {} | {} | {:+.2} | {:.2} | {:+.2} to {:+.2} | {:.2} | {:+.2} | {:+.2} | {} |",
                t.taxel,
                t.n,
                t.mean_s,
                t.sd_s,
                t.q05_s,
                t.q95_s,
                t.half_range_s,
                t.skew,
                t.peak_s,
                t.overlap.map_or("-".into(), |o| format!("{o:.2}"))
            );
        }
        s
    }

    /// The per-taxel table as CSV.
    pub fn to_csv(&self) -> String {
        let mut s =
            String::from("taxel,spikes,mean_s,sd_s,median_s,q05_s,q95_s,half_range_s,skew,peak_s,overlap\n");
        for t in &self.taxels {
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{},{},{},{},{}",
                t.taxel,
                t.n,
                t.mean_s,
                t.sd_s,
                t.median_s,
                t.q05_s,
                t.q95_s,
                t.half_range_s,
                t.skew,
                t.peak_s,
                t.overlap.map_or(String::new(), |o| o.to_string())
            );
        }
        s
    }

    fn pooled(&self, name: &str) -> f64 {
        self.pooled.iter().find(|(n, _)| n == name).map_or(0.0, |p| p.1)
    }

    /// The terminal summary.
    pub fn summary(&self) -> String {
        format!(
            "{} trials ({} skipped), {:.0} spikes: spread ±{:.2} s (half of the central 90 %, mean over taxels; SD {:.2} s), |peak| {:.2} s, {:.0} % of taxels peak off zero, taxel-to-taxel CV of the spread {:.2}, skew {:+.2}, overlap with neighbours {:.2}\n",
            self.trials,
            self.skipped,
            self.pooled("spikes"),
            self.pooled("half_range_s"),
            self.pooled("sd_s"),
            self.pooled("peak_abs_s"),
            self.pooled("peak_off_zero") * 100.0,
            self.pooled("taxel_spread_cv"),
            self.pooled("skew"),
            self.pooled("overlap"),
        )
    }
}

/// Writes the per-taxel histograms as one SVG, panels laid out like the array.
pub fn plot(path: &Path, title: &str, timing: &Timing, layout: &TaxelLayout) -> std::io::Result<()> {
    let err = |e: &dyn std::fmt::Display| std::io::Error::other(format!("plotting {}: {e}", path.display()));
    let n = timing.taxels.len().max(1);
    let (rows, cols) = layout.grid().unwrap_or_else(|| {
        let c = (n as f64).sqrt().ceil() as usize;
        (n.div_ceil(c), c)
    });
    let r = timing.range_ms / 1000.0;
    let half = (timing.taxels.first().map_or(1, |t| t.hist.len()) / 2) as f64;
    let bin_s = timing.bin_ms / 1000.0;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (240 * cols as u32 + 20, 180 * rows as u32 + 50))
            .into_drawing_area();
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let root = root.titled(title, ("sans-serif", 18)).map_err(|e| err(&e))?;
        let panels = root.split_evenly((rows, cols));
        for (t, area) in timing.taxels.iter().zip(panels.iter()) {
            let total = t.n.max(1) as f64;
            let ymax = t.hist.iter().copied().max().unwrap_or(0) as f64 / total;
            let mut chart = ChartBuilder::on(area)
                .caption(
                    format!("{}: ±{:.2} s, peak {:+.1} s", t.taxel, t.half_range_s, t.peak_s),
                    ("sans-serif", 12),
                )
                .margin(4)
                .x_label_area_size(18)
                .y_label_area_size(28)
                .build_cartesian_2d(-r..r, 0.0..(ymax * 1.1).max(1e-3))
                .map_err(|e| err(&e))?;
            chart
                .configure_mesh()
                .disable_mesh()
                .x_labels(5)
                .y_labels(3)
                .label_style(("sans-serif", 9))
                .draw()
                .map_err(|e| err(&e))?;
            chart
                .draw_series(t.hist.iter().enumerate().filter(|(_, &c)| c > 0).map(|(b, &c)| {
                    let x = (b as f64 - half) * bin_s;
                    Rectangle::new(
                        [(x - bin_s / 2.0, 0.0), (x + bin_s / 2.0, c as f64 / total)],
                        RGBColor(70, 110, 200).filled(),
                    )
                }))
                .map_err(|e| err(&e))?;
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(0.0, 0.0), (0.0, ymax * 1.1)],
                    RED.stroke_width(1),
                )))
                .map_err(|e| err(&e))?;
        }
        root.present().map_err(|e| err(&e))?;
    }
    write_atomic(path, svg.as_bytes())
}

impl Sink for SpikeTimingConfig {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        let Some(input) = inputs.first() else {
            return Ok(report);
        };
        let timing = analyse(self, input.items)?;
        report.text = timing.summary();
        report.text.push_str(&timing.to_markdown());
        for (name, v) in &timing.pooled {
            report.metrics.push((format!("{}.{name}", ctx.stage_id), *v));
        }
        let base = ctx.out_dir.join(ctx.stage_id);
        let io = |p: &Path| {
            let p = p.display().to_string();
            move |e: std::io::Error| StageError::new(format!("writing {p}: {e}"))
        };
        let json = serde_json::to_vec_pretty(&serde_json::json!({
            "source": input.stage_id,
            "trials": timing.trials,
            "skipped": timing.skipped,
            "bin_ms": timing.bin_ms,
            "range_ms": timing.range_ms,
            "pooled": timing.pooled.iter().cloned().collect::<BTreeMap<_, _>>(),
            "taxels": timing.taxels,
        }))
        .map_err(|e| StageError::new(e.to_string()))?;
        for (ext, bytes) in [
            ("json", json),
            ("csv", timing.to_csv().into_bytes()),
            ("md", timing.to_markdown().into_bytes()),
        ] {
            let p = base.with_extension(ext);
            write_atomic(&p, &bytes).map_err(io(&p))?;
            report.files.push(p);
        }
        if let Some(first) = input.items.first() {
            let layout = &first.payload.spikes()?.layout;
            let p = base.with_extension("svg");
            plot(
                &p,
                &format!(
                    "Spike times relative to the edge crossing each taxel's centre ({})",
                    input.stage_id
                ),
                &timing,
                layout,
            )
            .map_err(io(&p))?;
            report.files.push(p);
        }
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::{Label, Payload, SpikeEvent, SpikeTrain, Stimulus, TrialMeta};
    use proptest::prelude::*;
    use std::sync::Arc;

    fn item(angle: f64, crossing: Option<[f64; 2]>, events: Vec<SpikeEvent>) -> Item {
        Item {
            meta: Arc::new(TrialMeta {
                trial_id: format!("t{angle}"),
                label: Label {
                    stimulus: Stimulus::Edge,
                    angle_deg: Some(angle),
                },
                crossing_ms: crossing,
                ..TrialMeta::default()
            }),
            payload: Payload::from(SpikeTrain {
                layout: TaxelLayout::paper(),
                duration_ms: 1e6,
                events,
            }),
        }
    }

    #[test]
    fn crossing_times_follow_the_geometry() {
        let cfg = SpikeTimingConfig::default();
        let l = TaxelLayout::paper();
        // At 90 degrees the footprint is x in [-5.5, 5.5] and the edge falls
        // from 5.5 to -5.5 over [1000, 12000] ms (1 mm/s): column c's centre
        // x = -4.5 + 3c is crossed at 1000 + (5.5 - x) * 1000.
        let m = item(90.0, Some([1000.0, 12000.0]), vec![]).meta;
        let t = cfg.crossing_times(&m, &l).unwrap();
        for (i, ti) in t.iter().enumerate() {
            let x = -4.5 + 3.0 * (i % 4) as f64;
            assert!((ti - (1000.0 + (5.5 - x) * 1000.0)).abs() < 1e-9, "{i}: {ti}");
        }
        // A recording: declared speed 2 mm/s and the centre crossed at 5 s.
        let rec = SpikeTimingConfig {
            speed_mm_s: Some(2.0),
            centre_crossing_ms: Some(5000.0),
            ..SpikeTimingConfig::default()
        };
        let m = item(90.0, None, vec![]).meta;
        let t = rec.crossing_times(&m, &l).unwrap();
        // Column 3 (x = 4.5) leaves the object first: 2.25 s before the centre.
        assert!((t[3] - 2750.0).abs() < 1e-9);
        assert!((t[0] - 7250.0).abs() < 1e-9);
        assert!(
            cfg.crossing_times(&m, &l).is_none(),
            "no crossing, no speed: skipped"
        );
        // The trial's own declared speed when the config gives none.
        let own = SpikeTimingConfig {
            centre_crossing_ms: Some(5000.0),
            ..SpikeTimingConfig::default()
        };
        assert!(own.crossing_times(&m, &l).is_none(), "no speed anywhere");
        let mut declared = (*m).clone();
        declared.speed_mm_s = Some(2.0);
        assert_eq!(own.crossing_times(&declared, &l), Some(t.clone()));
        // At a declared 4 mm/s the offsets from the centre crossing halve ...
        declared.speed_mm_s = Some(4.0);
        let half = own.crossing_times(&declared, &l).unwrap();
        assert!((half[3] - (5000.0 - 2250.0 / 2.0)).abs() < 1e-9, "{half:?}");
        // ... unless the config gives a speed (rec's 2 mm/s), which wins.
        assert_eq!(rec.crossing_times(&declared, &l), Some(t));
    }

    #[test]
    fn spikes_at_the_crossing_give_zero_spread_and_peak() {
        let cfg = SpikeTimingConfig::default();
        let l = TaxelLayout::paper();
        let mut items = Vec::new();
        for a in [30.0, 60.0, 90.0] {
            let m = item(a, Some([2000.0, 9000.0]), vec![]).meta;
            let t = cfg.crossing_times(&m, &l).unwrap();
            let mut ev: Vec<SpikeEvent> = t
                .iter()
                .enumerate()
                .map(|(i, &t)| SpikeEvent {
                    taxel: i as u32,
                    t_ms: t,
                })
                .collect();
            ev.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
            items.push(item(a, Some([2000.0, 9000.0]), ev));
        }
        let r = analyse(&cfg, &items).unwrap();
        assert_eq!(r.trials, 3);
        for t in &r.taxels {
            assert_eq!(t.n, 3);
            assert!(t.sd_s.abs() < 1e-9 && t.half_range_s.abs() < 1e-9 && t.peak_s == 0.0);
            assert_eq!(t.skew, 0.0);
        }
    }

    #[test]
    fn a_late_skewed_taxel_is_reported_as_such() {
        let cfg = SpikeTimingConfig::default();
        let l = TaxelLayout::paper();
        let m = item(90.0, Some([1000.0, 12000.0]), vec![]).meta;
        let t = cfg.crossing_times(&m, &l).unwrap();
        // Taxel 5 fires 0.5 s late mostly, with a tail to 3 s late.
        let mut ev = vec![];
        for k in 0..20 {
            ev.push(SpikeEvent {
                taxel: 5,
                t_ms: t[5] + 500.0 + k as f64,
            });
        }
        for k in 0..5 {
            ev.push(SpikeEvent {
                taxel: 5,
                t_ms: t[5] + 1000.0 + 500.0 * k as f64,
            });
        }
        ev.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
        let r = analyse(&cfg, &[item(90.0, Some([1000.0, 12000.0]), ev)]).unwrap();
        let x = &r.taxels[5];
        assert_eq!(x.n, 25);
        assert!((x.peak_s - 0.5).abs() < 1e-9, "{}", x.peak_s);
        assert!(x.skew > 1.0, "{}", x.skew);
        assert!(x.mean_s > x.median_s);
        assert_eq!(r.taxels[0].n, 0);
    }

    #[test]
    fn overlap_is_one_for_twins_and_zero_for_strangers() {
        let cfg = SpikeTimingConfig::default();
        // Taxels 0 and 1 (row neighbours) fire together; 2 fires much later.
        let mut ev = vec![];
        for k in 0..10 {
            let t = 3000.0 + 10.0 * k as f64;
            ev.push(SpikeEvent { taxel: 0, t_ms: t });
            ev.push(SpikeEvent { taxel: 1, t_ms: t });
            ev.push(SpikeEvent {
                taxel: 2,
                t_ms: t + 5000.0,
            });
        }
        ev.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
        let r = analyse(&cfg, &[item(90.0, Some([1000.0, 12000.0]), ev)]).unwrap();
        assert!((r.taxels[0].overlap.unwrap() - 1.0).abs() < 1e-12);
        // Taxel 1's neighbours: 0 (overlap 1) and 2 (0) and 5 (silent).
        assert!((r.taxels[1].overlap.unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(r.taxels[2].overlap, Some(0.0));
        assert_eq!(r.taxels[15].overlap, None);
    }

    #[test]
    fn hostile_config_and_input_are_errors_not_panics() {
        let bad = SpikeTimingConfig {
            bin_ms: 1e-9,
            ..SpikeTimingConfig::default()
        };
        assert_eq!(bad.check().unwrap_err().key.as_deref(), Some("bin_ms"));
        let bad = SpikeTimingConfig {
            speed_mm_s: Some(2.0),
            ..SpikeTimingConfig::default()
        };
        assert_eq!(
            bad.check().unwrap_err().key.as_deref(),
            Some("centre_crossing_ms")
        );
        let cfg = SpikeTimingConfig::default();
        let ev = vec![SpikeEvent { taxel: 99, t_ms: 1.0 }];
        let e = analyse(&cfg, &[item(90.0, Some([1000.0, 12000.0]), ev)]).unwrap_err();
        assert!(e.message.contains("taxel 99"), "{}", e.message);
        // No trials: empty, not NaN.
        let r = analyse(&cfg, &[]).unwrap();
        assert!(r.taxels.is_empty());
    }

    proptest! {
        #[test]
        fn statistics_are_finite_and_ordered(
            times in proptest::collection::vec((0u32..16, -1e6f64..1e6), 0..200),
            angle in 1.0f64..179.0,
        ) {
            let mut ev: Vec<SpikeEvent> = times.iter().map(|&(taxel, t_ms)| SpikeEvent { taxel, t_ms }).collect();
            ev.sort_by(|a, b| a.t_ms.total_cmp(&b.t_ms));
            let cfg = SpikeTimingConfig::default();
            let r = analyse(&cfg, &[item(angle, Some([100.0, 20000.0]), ev)]).unwrap();
            for t in &r.taxels {
                prop_assert!(t.sd_s.is_finite() && t.skew.is_finite() && t.half_range_s >= 0.0);
                prop_assert!(t.q05_s <= t.median_s + 1e-9 && t.median_s <= t.q95_s + 1e-9);
                prop_assert!(t.peak_s.abs() <= cfg.range_ms / 1000.0 + 1e-9);
                if let Some(o) = t.overlap { prop_assert!((0.0..=1.0 + 1e-9).contains(&o)); }
            }
            for (_, v) in &r.pooled { prop_assert!(v.is_finite()); }
        }
    }
}
