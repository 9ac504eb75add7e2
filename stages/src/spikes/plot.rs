//! Plots of spikes and spike images, as SVG sinks:
//!
//! * `raster_plot` (spikes): one row per taxel, a tick per spike, the trial's
//!   known crossing interval shaded; one file per selected trial.
//! * `image_strip` (images): a strip of a trial's binned images over time, like
//!   the paper's Fig. 3(c); darker = more spikes, one grey scale per strip.
//!
//! Trials: those listed in `trials` (by id; an unknown id is an error naming the
//! key), else the first `n_trials`. Files are `<sink id>-<trial id>.svg` in the
//! run's output directory, written atomically. The SVG is written directly
//! (rectangles, lines and text only), so no font or plotting backend is needed;
//! [`raster_svg`] and [`strip_svg`] give the text for other callers.

use palpate_core::output::write_atomic;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, PayloadKind, Sink, SinkContext, SinkInput,
    SinkReport, SpikeImages, SpikeTrain, Stage, StageConfig, StageError, TaxelLayout, TrialMeta,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// Which trials a plot sink draws.
fn select<'a>(items: &'a [Item], trials: &[String], n_trials: usize) -> Result<Vec<&'a Item>, StageError> {
    if trials.is_empty() {
        return Ok(items.iter().take(n_trials).collect());
    }
    trials
        .iter()
        .map(|id| {
            items.iter().find(|it| &it.meta.trial_id == id).ok_or_else(|| {
                StageError::new(format!(
                    "key `trials` lists `{id}`, which is not a trial of this run"
                ))
            })
        })
        .collect()
}

/// A trial id made safe for a file name.
fn file_stem(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

fn title(meta: &TrialMeta) -> String {
    match meta.label.angle_deg {
        Some(a) => format!("{} ({}, {a}°)", meta.trial_id, meta.label.stimulus),
        None => meta.trial_id.clone(),
    }
}

fn taxel_label(layout: &TaxelLayout, i: usize) -> String {
    match layout.row_col(i) {
        Some((r, c)) => format!("({r},{c})"),
        None => format!("{i}"),
    }
}

/// A "nice" tick step (1, 2 or 5 times a power of ten) giving about `n` ticks over `span`.
fn tick_step(span: f64, n: f64) -> f64 {
    if span.is_nan() || span <= 0.0 {
        return 1.0;
    }
    let raw = span / n;
    let p = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p)
}

/// The SVG text of a spike raster: one row per taxel.
pub fn raster_svg(train: &SpikeTrain, meta: &TrialMeta) -> String {
    let n = train.layout.len();
    let (left, top, width, row_h) = (70.0, 40.0, 820.0, 16.0);
    let height = top + n as f64 * row_h + 45.0;
    let dur = if train.duration_ms > 0.0 {
        train.duration_ms
    } else {
        1.0
    };
    let x = |t: f64| left + t / dur * width;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{height}" viewBox="0 0 {w} {height}" font-family="sans-serif" font-size="11">"#,
        w = left + width + 20.0
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{left}" y="22" font-size="15">Spike raster: {} — {} spikes</text>"#,
        esc(&title(meta)),
        train.events.len()
    );
    if let Some([a, b]) = meta.crossing_ms {
        let (a, b) = (a.clamp(0.0, dur), b.clamp(0.0, dur));
        let _ = writeln!(
            s,
            r##"<rect x="{:.2}" y="{top}" width="{:.2}" height="{:.2}" fill="#fde9c8"><title>edge crossing</title></rect>"##,
            x(a),
            (x(b) - x(a)).max(0.5),
            n as f64 * row_h
        );
    }
    for i in 0..n {
        let y = top + i as f64 * row_h;
        let _ = writeln!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text><line x1="{left}" x2="{:.1}" y1="{:.1}" y2="{:.1}" stroke="#eee"/>"##,
            left - 6.0,
            y + row_h * 0.75,
            taxel_label(&train.layout, i),
            left + width,
            y + row_h,
            y + row_h
        );
    }
    let _ = write!(s, r#"<path stroke="black" stroke-width="1" d=""#);
    for e in &train.events {
        let y = top + e.taxel as f64 * row_h;
        let _ = write!(s, "M{:.2} {:.1}v{:.1}", x(e.t_ms), y + 2.0, row_h - 4.0);
    }
    let _ = writeln!(s, r#""/>"#);
    let axis_y = top + n as f64 * row_h;
    let _ = writeln!(
        s,
        r#"<line x1="{left}" x2="{:.1}" y1="{axis_y}" y2="{axis_y}" stroke="black"/>"#,
        left + width
    );
    let step = tick_step(dur / 1000.0, 10.0);
    let mut k = 0.0;
    while k * step * 1000.0 <= dur + 1e-9 {
        let t = k * step * 1000.0;
        let _ = writeln!(
            s,
            r#"<line x1="{0:.2}" x2="{0:.2}" y1="{axis_y}" y2="{1}" stroke="black"/><text x="{0:.2}" y="{2}" text-anchor="middle">{3}</text>"#,
            x(t),
            axis_y + 4.0,
            axis_y + 16.0,
            format_num(k * step)
        );
        k += 1.0;
    }
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">time (s)</text>"#,
        left + width / 2.0,
        axis_y + 34.0
    );
    s.push_str("</svg>\n");
    s
}

fn format_num(v: f64) -> String {
    let r = (v * 1000.0).round() / 1000.0;
    if r.fract() == 0.0 {
        format!("{r:.0}")
    } else {
        format!("{r}")
    }
}

/// The frames a strip shows: from the first to the last frame with spikes
/// (all frames if none has any), evenly thinned to at most `max_frames`.
pub fn strip_frames(images: &SpikeImages, max_frames: usize) -> Vec<usize> {
    let busy = |k: &usize| images.frame(*k).iter().any(|&c| c > 0.0);
    let first = (0..images.n_frames).find(busy);
    let last = (0..images.n_frames).rev().find(busy);
    let (a, b) = match (first, last) {
        (Some(a), Some(b)) => (a, b),
        _ => (0, images.n_frames.saturating_sub(1)),
    };
    let len = b + 1 - a;
    let m = max_frames.max(1).min(len);
    if images.n_frames == 0 {
        return vec![];
    }
    if m == 1 {
        return vec![a];
    }
    (0..m)
        .map(|j| a + (j as f64 * (len - 1) as f64 / (m - 1) as f64).round() as usize)
        .collect()
}

/// The SVG text of a strip of binned images (paper Fig. 3(c)).
pub fn strip_svg(images: &SpikeImages, meta: &TrialMeta, max_frames: usize, per_row: usize) -> String {
    let frames = strip_frames(images, max_frames);
    let (rows, cols) = images.layout.grid().unwrap_or((1, images.n_taxels()));
    let cell = (60.0 / rows.max(cols) as f64).clamp(3.0, 14.0);
    let (iw, ih) = (cols as f64 * cell, rows as f64 * cell);
    let per_row = per_row.max(1);
    // Room for a "1234 ms" label under small images.
    let (gap, label_h, top, left) = ((48.0 - iw).max(10.0), 16.0, 40.0, 15.0);
    let lines = frames.len().div_ceil(per_row).max(1);
    // Wide enough for the title line too.
    let w = (left * 2.0 + per_row.min(frames.len().max(1)) as f64 * (iw + gap)).max(640.0);
    let h = top + lines as f64 * (ih + label_h + gap) + 10.0;
    let max = frames
        .iter()
        .flat_map(|&k| images.frame(k).iter().copied())
        .fold(0.0_f64, f64::max);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w:.0}" height="{h:.0}" viewBox="0 0 {w:.0} {h:.0}" font-family="sans-serif" font-size="10">"#
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{left}" y="22" font-size="13">Spike images: {} — window {} ms, hop {} ms, black = {} spikes</text>"#,
        esc(&title(meta)),
        images.window_ms,
        images.hop_ms,
        max
    );
    for (j, &k) in frames.iter().enumerate() {
        let x0 = left + (j % per_row) as f64 * (iw + gap);
        let y0 = top + (j / per_row) as f64 * (ih + label_h + gap);
        for (i, &c) in images.frame(k).iter().enumerate() {
            let (r, cc) = images.layout.row_col(i).unwrap_or((0, i));
            let t = if max > 0.0 { c / max } else { 0.0 };
            let g = (255.0 * (1.0 - t)).round() as u8;
            let _ = writeln!(
                s,
                r#"<rect x="{:.1}" y="{:.1}" width="{cell:.1}" height="{cell:.1}" fill="rgb({g},{g},{g})"><title>frame {k}, taxel {i}: {c}</title></rect>"#,
                x0 + cc as f64 * cell,
                y0 + r as f64 * cell
            );
        }
        let _ = writeln!(
            s,
            r##"<rect x="{x0:.1}" y="{y0:.1}" width="{iw:.1}" height="{ih:.1}" fill="none" stroke="#888"/><text x="{:.1}" y="{:.1}" text-anchor="middle">{} ms</text>"##,
            x0 + iw / 2.0,
            y0 + ih + 12.0,
            format_num(k as f64 * images.hop_ms)
        );
    }
    s.push_str("</svg>\n");
    s
}

/// Spike raster (one row per taxel) of the first N trials or listed trial ids, as SVG files.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RasterPlotConfig {
    /// Trial ids to plot; empty = the first `n_trials`. Default empty.
    pub trials: Vec<String>,
    /// Number of trials plotted when `trials` is empty. Default 3.
    pub n_trials: usize,
}

impl Default for RasterPlotConfig {
    fn default() -> Self {
        RasterPlotConfig {
            trials: vec![],
            n_trials: 3,
        }
    }
}

#[typetag::serde(name = "raster_plot")]
impl StageConfig for RasterPlotConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("raster_plot", RasterPlotConfig);

impl Sink for RasterPlotConfig {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        for item in select(inputs[0].items, &self.trials, self.n_trials)? {
            let svg = raster_svg(item.payload.spikes()?, &item.meta);
            let path = ctx
                .out_dir
                .join(format!("{}-{}.svg", ctx.stage_id, file_stem(&item.meta.trial_id)));
            write_atomic(&path, svg.as_bytes())
                .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
            report.files.push(path);
        }
        report.text = format!("{} spike raster(s) written\n", report.files.len());
        Ok(report)
    }
}

/// Strip of a trial's binned spike images over time (paper Fig. 3(c)), as SVG files.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ImageStripConfig {
    /// Trial ids to plot; empty = the first `n_trials`. Default empty.
    pub trials: Vec<String>,
    /// Number of trials plotted when `trials` is empty. Default 1.
    pub n_trials: usize,
    /// Most frames shown, evenly spread from the first to the last frame with spikes. Default 24.
    pub max_frames: usize,
    /// Frames per line of the strip. Default 12.
    pub per_row: usize,
}

impl Default for ImageStripConfig {
    fn default() -> Self {
        ImageStripConfig {
            trials: vec![],
            n_trials: 1,
            max_frames: 24,
            per_row: 12,
        }
    }
}

#[typetag::serde(name = "image_strip")]
impl StageConfig for ImageStripConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = palpate_core::ConfigChecks::new();
        if self.max_frames == 0 {
            c.push(ConfigError::key("max_frames", "must be at least 1"));
        }
        if self.per_row == 0 {
            c.push(ConfigError::key("per_row", "must be at least 1"));
        }
        c.finish()?;
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("image_strip", ImageStripConfig);

impl Sink for ImageStripConfig {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        for item in select(inputs[0].items, &self.trials, self.n_trials)? {
            let svg = strip_svg(item.payload.images()?, &item.meta, self.max_frames, self.per_row);
            let path = ctx
                .out_dir
                .join(format!("{}-{}.svg", ctx.stage_id, file_stem(&item.meta.trial_id)));
            write_atomic(&path, svg.as_bytes())
                .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
            report.files.push(path);
        }
        report.text = format!("{} image strip(s) written\n", report.files.len());
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::SpikeEvent;

    fn images(n_frames: usize, busy: &[(usize, usize, f64)]) -> SpikeImages {
        let mut counts = vec![0.0; n_frames * 16];
        for &(k, t, c) in busy {
            counts[k * 16 + t] = c;
        }
        SpikeImages {
            layout: TaxelLayout::paper(),
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames,
            counts,
        }
    }

    #[test]
    fn strip_frames_span_the_active_part() {
        let im = images(100, &[(20, 0, 1.0), (60, 3, 2.0)]);
        let f = strip_frames(&im, 5);
        assert_eq!(f, vec![20, 30, 40, 50, 60]);
        assert_eq!(strip_frames(&im, 100).len(), 41);
        // No spikes at all: the whole trial, thinned.
        assert_eq!(strip_frames(&images(10, &[]), 3), vec![0, 5, 9]);
        assert_eq!(strip_frames(&images(10, &[(4, 0, 1.0)]), 3), vec![4]);
    }

    #[test]
    fn svgs_hold_the_data() {
        let meta = TrialMeta {
            trial_id: "edge<45>".into(),
            crossing_ms: Some([10.0, 50.0]),
            ..TrialMeta::default()
        };
        let train = SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms: 100.0,
            events: vec![
                SpikeEvent { taxel: 2, t_ms: 25.0 },
                SpikeEvent { taxel: 2, t_ms: 26.0 },
            ],
        };
        let r = raster_svg(&train, &meta);
        assert!(r.starts_with("<svg") && r.ends_with("</svg>\n"));
        assert_eq!(r.matches("v12.0").count(), 2);
        assert!(r.contains("edge&lt;45&gt;") && r.contains("edge crossing"));
        let s = strip_svg(&images(30, &[(5, 1, 3.0)]), &meta, 24, 12);
        assert!(s.contains("rgb(0,0,0)"), "the busiest cell is black");
        assert!(s.contains("black = 3 spikes"));
        // Empty data does not panic and gives no NaN.
        let empty = SpikeTrain {
            events: vec![],
            duration_ms: 0.0,
            ..train
        };
        assert!(!raster_svg(&empty, &meta).contains("NaN"));
        assert!(!strip_svg(&images(1, &[]), &meta, 24, 12).contains("NaN"));
        assert_eq!(file_stem("a/b c"), "a_b_c");
        assert_eq!(tick_step(40.0, 10.0), 5.0);
    }
}
