//! Shared SVG plotting in one house style ([`style`]): line charts (signals
//! over time, sweep curves), heatmaps (confusion matrices: square cells,
//! labels at the cells' centres, axis titles, a colour bar and the value in
//! every cell), small-multiples bar charts (a per-class metric of many
//! estimators, one panel each on shared axes), scatter charts with a Pareto
//! frontier (accuracy against time), and a sweep's declared figures
//! ([`line_plot`]: points joined over numeric x with error bars and dashed
//! reference series; [`bar_plot`]: grouped bars over categories). Plots are
//! written atomically like every report file.
//!
//! Heatmaps, small multiples, line plots and bar charts are written as SVG
//! text directly (rectangles, lines and text with a `class` naming each
//! element's role), so their structure can be checked by tests and no font is
//! needed to write them; line charts and frontier charts use `plotters`.

mod xy;
pub use xy::{bar_plot, bar_plot_svg, line_plot, line_plot_svg, BarPlot, Figure, PlotSeries, Point};

use palpate_core::output::write_atomic;
use plotters::prelude::*;
use std::fmt::Write as _;
use std::path::Path;

/// One named series of `(x, y)` points.
pub struct Series<'a> {
    /// Legend name.
    pub name: &'a str,
    /// Points, in x order.
    pub points: Vec<(f64, f64)>,
}

fn err<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> std::io::Error + '_ {
    move |e| std::io::Error::other(format!("plotting {}: {e}", path.display()))
}

fn bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 0.5, hi + 0.5);
    }
    let pad = (hi - lo) * 0.05;
    (lo - pad, hi + pad)
}

/// Writes a line chart as SVG.
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
) -> std::io::Result<()> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (800, 450)).into_drawing_area();
        root.fill(&WHITE).map_err(err(path))?;
        let (x0, x1) = bounds(series.iter().flat_map(|s| s.points.iter().map(|p| p.0)));
        let (y0, y1) = bounds(series.iter().flat_map(|s| s.points.iter().map(|p| p.1)));
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", style::TITLE))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err(path))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .draw()
            .map_err(err(path))?;
        for (k, s) in series.iter().enumerate() {
            let color = tab10(k);
            chart
                .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(2)))
                .map_err(err(path))?
                .label(s.name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
        }
        if series.len() > 1 {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(err(path))?;
        }
        root.present().map_err(err(path))?;
    }
    write_atomic(path, svg.as_bytes())
}

/// The house style shared by every plot palpate writes: one font family, the
/// same title, axis-title and tick sizes, and the Tableau-10 colours
/// (`tab10`), so that figures from different sinks sit together in a paper.
pub mod style {
    /// Font family of every text.
    pub const FONT: &str = "DejaVu Sans, Helvetica, Arial, sans-serif";
    /// Title size, px.
    pub const TITLE: u32 = 17;
    /// Axis-title size, px.
    pub const AXIS: u32 = 14;
    /// Tick-label size, px.
    pub const TICK: u32 = 12;
    /// Colour of axes, ticks and text.
    pub const INK: &str = "#222222";
    /// Colour of grid lines.
    pub const GRID: &str = "#dddddd";
}

/// Escapes text for SVG.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Opens an SVG document of `w` x `h` px on a white background.
fn svg_open(w: f64, h: f64) -> String {
    format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w:.0}" height="{h:.0}" viewBox="0 0 {w:.0} {h:.0}" font-family="{}" fill="{}">
<rect x="0" y="0" width="{w:.0}" height="{h:.0}" fill="#ffffff"/>
"##,
        style::FONT,
        style::INK
    )
}

/// One text element; `class` names its role (tests and style sheets find it).
#[allow(clippy::too_many_arguments)]
fn text(s: &mut String, class: &str, x: f64, y: f64, size: u32, anchor: &str, rotate: f64, body: &str) {
    let rot = if rotate == 0.0 {
        String::new()
    } else {
        format!(r#" transform="rotate({rotate} {x:.2} {y:.2})""#)
    };
    let _ = writeln!(
        s,
        r#"<text class="{class}" x="{x:.2}" y="{y:.2}" font-size="{size}" text-anchor="{anchor}"{rot}>{}</text>"#,
        esc(body)
    );
}

/// A "nice" tick step for a span of `span`: 1, 2 or 5 times a power of ten,
/// giving at most about `n` steps.
fn nice_step(span: f64, n: usize) -> f64 {
    let span = if span.is_finite() && span > 0.0 { span } else { 1.0 };
    let raw = span / n.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag)
}

/// "Nice" axis ticks from 0 to at least `max`: steps of 1, 2 or 5 times a
/// power of ten, at most about `n` of them. Returns `(ticks, top)`.
fn nice_ticks(max: f64, n: usize) -> (Vec<f64>, f64) {
    let (ticks, _, top) = nice_range(0.0, max, n);
    (ticks, top)
}

/// "Nice" ticks covering `[lo, hi]` (as [`nice_ticks`], from a multiple of
/// the step at or below `lo`). Returns `(ticks, bottom, top)`; a non-finite
/// or empty range gives 0 to 1.
fn nice_range(lo: f64, hi: f64, n: usize) -> (Vec<f64>, f64, f64) {
    let (lo, hi) = if lo.is_finite() && hi.is_finite() && hi > lo {
        (lo, hi)
    } else if lo.is_finite() && lo == hi && lo != 0.0 {
        (lo.min(0.0), lo.max(0.0))
    } else {
        (0.0, 1.0)
    };
    let step = nice_step(hi - lo, n);
    let first = (lo / step + 1e-9).floor() as i64;
    let last = ((hi / step - 1e-9).ceil() as i64).max(first + 1);
    let ticks = (first..=last).map(|i| i as f64 * step).collect();
    (ticks, first as f64 * step, last as f64 * step)
}

/// The sequential colour scale of heatmaps, `t` in `[0, 1]` from white to dark
/// blue (the "Blues" ramp: light cells read as "few", the eye finds the dark
/// diagonal).
fn blues(t: f64) -> (u8, u8, u8) {
    const STOPS: [(u8, u8, u8); 5] = [
        (247, 251, 255),
        (198, 219, 239),
        (107, 174, 214),
        (33, 113, 181),
        (8, 48, 107),
    ];
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 0.0 };
    let x = t * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let mix = |a: u8, b: u8| (a as f64 + (b as f64 - a as f64) * f).round() as u8;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    (mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

fn hex((r, g, b): (u8, u8, u8)) -> String {
    format!("#{r:02x}{g:02x}{b:02x}")
}

/// What [`heatmap`] draws: a matrix of cells `values[row][col]` coloured on one
/// scale from 0 to `v_max`, with row and column labels at the cells' centres,
/// axis titles, a colour bar and (optionally) a text in every cell.
pub struct Heatmap<'a> {
    /// Title above the matrix.
    pub title: &'a str,
    /// Title of the x axis (the columns), below the labels.
    pub x_title: &'a str,
    /// Title of the y axis (the rows), left of the labels.
    pub y_title: &'a str,
    /// Label of each row, top to bottom.
    pub row_labels: &'a [String],
    /// Label of each column, left to right.
    pub col_labels: &'a [String],
    /// `values[row][col]`; a non-finite value is drawn as an empty (grey) cell.
    pub values: &'a [Vec<f64>],
    /// Text written in each cell (same shape as `values`; an empty string or a
    /// missing row writes nothing).
    pub cell_text: &'a [Vec<String>],
    /// Top of the colour scale (`None`: the largest finite value, or 1).
    pub v_max: Option<f64>,
    /// Title of the colour bar.
    pub scale_title: &'a str,
    /// Tick labels of the colour bar are `value * scale_factor` (e.g. 100 for
    /// shares shown as percent).
    pub scale_factor: f64,
}

/// Pixel geometry of a [`Heatmap`]: where cell `(r, c)` is. Exposed so tests
/// (and callers overlaying marks) agree with the drawing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeatmapGeometry {
    /// Left edge of the matrix, px.
    pub left: f64,
    /// Top edge of the matrix, px.
    pub top: f64,
    /// Side of one (square) cell, px.
    pub cell: f64,
}

impl HeatmapGeometry {
    /// Centre of column `c`, px.
    pub fn col_centre(&self, c: usize) -> f64 {
        self.left + (c as f64 + 0.5) * self.cell
    }
    /// Centre of row `r`, px.
    pub fn row_centre(&self, r: usize) -> f64 {
        self.top + (r as f64 + 0.5) * self.cell
    }
}

/// The geometry [`heatmap_svg`] uses for `rows` x `cols` cells: square cells of
/// 14 to 44 px, the matrix at most about 560 px on its longer side.
pub fn heatmap_geometry(rows: usize, cols: usize, row_labels: &[String]) -> HeatmapGeometry {
    let n = rows.max(cols).max(1) as f64;
    let cell = (560.0 / n).clamp(14.0, 44.0).floor();
    let label_w =
        row_labels.iter().map(|l| l.chars().count()).max().unwrap_or(1) as f64 * 0.62 * style::TICK as f64;
    HeatmapGeometry {
        left: 40.0 + label_w + 12.0,
        top: 48.0,
        cell,
    }
}

/// The SVG text of a heatmap (see [`Heatmap`]).
pub fn heatmap_svg(h: &Heatmap<'_>) -> String {
    let rows = h.values.len();
    let cols = h.values.iter().map(Vec::len).max().unwrap_or(0);
    let g = heatmap_geometry(rows, cols, h.row_labels);
    let finite_max = h
        .values
        .iter()
        .flatten()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0_f64, f64::max);
    let v_max = h
        .v_max
        .filter(|v| v.is_finite() && *v > 0.0)
        .unwrap_or(if finite_max > 0.0 { finite_max } else { 1.0 });
    let (mw, mh) = (cols as f64 * g.cell, rows as f64 * g.cell);
    let rotate_x = g.cell < 34.0 || h.col_labels.iter().any(|l| l.chars().count() > 4);
    let x_label_h = if rotate_x {
        h.col_labels.iter().map(|l| l.chars().count()).max().unwrap_or(1) as f64 * 0.5 * style::TICK as f64
            + 16.0
    } else {
        22.0
    };
    let bar_x = g.left + mw + 24.0;
    let width = bar_x + 16.0 + 80.0;
    let height = g.top + mh + x_label_h + 34.0;
    let mut s = svg_open(width.max(320.0), height);
    text(
        &mut s,
        "title",
        (g.left + mw / 2.0).max(160.0),
        28.0,
        style::TITLE,
        "middle",
        0.0,
        h.title,
    );
    // Cells, then their texts (white on dark cells).
    for (r, row) in h.values.iter().enumerate() {
        for c in 0..cols {
            let v = row.get(c).copied().unwrap_or(f64::NAN);
            let (x, y) = (g.left + c as f64 * g.cell, g.top + r as f64 * g.cell);
            let t = v / v_max;
            let fill = if v.is_finite() {
                hex(blues(t))
            } else {
                "#eeeeee".into()
            };
            let _ = writeln!(
                s,
                r##"<rect class="cell" data-row="{r}" data-col="{c}" x="{x:.2}" y="{y:.2}" width="{w:.2}" height="{w:.2}" fill="{fill}" stroke="#ffffff" stroke-width="1"/>"##,
                w = g.cell
            );
            let body = h
                .cell_text
                .get(r)
                .and_then(|t| t.get(c))
                .map_or("", String::as_str);
            if !body.is_empty() {
                let size = ((g.cell * 0.36).floor() as u32).clamp(7, 13);
                let color = if v.is_finite() && t > 0.55 {
                    "#ffffff"
                } else {
                    style::INK
                };
                let _ = writeln!(
                    s,
                    r#"<text class="cell-value" x="{:.2}" y="{:.2}" font-size="{size}" text-anchor="middle" dominant-baseline="central" fill="{color}">{}</text>"#,
                    g.col_centre(c),
                    g.row_centre(r),
                    esc(body)
                );
            }
        }
    }
    let _ = writeln!(
        s,
        r#"<rect x="{:.2}" y="{:.2}" width="{mw:.2}" height="{mh:.2}" fill="none" stroke="{}" stroke-width="1"/>"#,
        g.left,
        g.top,
        style::INK
    );
    // One tick and one label per row and per column, at the cell's centre.
    for (r, label) in h.row_labels.iter().enumerate().take(rows) {
        let y = g.row_centre(r);
        let _ = writeln!(
            s,
            r#"<line class="tick-y" x1="{:.2}" y1="{y:.2}" x2="{:.2}" y2="{y:.2}" stroke="{}"/>"#,
            g.left - 4.0,
            g.left,
            style::INK
        );
        let _ = writeln!(
            s,
            r#"<text class="label-y" x="{:.2}" y="{y:.2}" font-size="{}" text-anchor="end" dominant-baseline="central">{}</text>"#,
            g.left - 7.0,
            style::TICK,
            esc(label)
        );
    }
    let y_ticks = g.top + mh;
    for (c, label) in h.col_labels.iter().enumerate().take(cols) {
        let x = g.col_centre(c);
        let _ = writeln!(
            s,
            r#"<line class="tick-x" x1="{x:.2}" y1="{y_ticks:.2}" x2="{x:.2}" y2="{:.2}" stroke="{}"/>"#,
            y_ticks + 4.0,
            style::INK
        );
        if rotate_x {
            let y = y_ticks + 8.0;
            let _ = writeln!(
                s,
                r#"<text class="label-x" x="{x:.2}" y="{y:.2}" font-size="{}" text-anchor="end" dominant-baseline="central" transform="rotate(-60 {x:.2} {y:.2})">{}</text>"#,
                style::TICK,
                esc(label)
            );
        } else {
            text(
                &mut s,
                "label-x",
                x,
                y_ticks + 18.0,
                style::TICK,
                "middle",
                0.0,
                label,
            );
        }
    }
    text(
        &mut s,
        "axis-title-x",
        g.left + mw / 2.0,
        y_ticks + x_label_h + 20.0,
        style::AXIS,
        "middle",
        0.0,
        h.x_title,
    );
    text(
        &mut s,
        "axis-title-y",
        18.0,
        g.top + mh / 2.0,
        style::AXIS,
        "middle",
        -90.0,
        h.y_title,
    );
    // The colour bar: a vertical gradient from 0 (bottom) to v_max (top).
    let _ = writeln!(
        s,
        r#"<defs><linearGradient id="scale" x1="0" y1="1" x2="0" y2="0">"#
    );
    for k in 0..=8 {
        let t = k as f64 / 8.0;
        let _ = writeln!(s, r#"<stop offset="{t:.3}" stop-color="{}"/>"#, hex(blues(t)));
    }
    let _ = writeln!(s, "</linearGradient></defs>");
    let bar_h = mh.max(60.0);
    let _ = writeln!(
        s,
        r#"<rect class="colorbar" x="{bar_x:.2}" y="{:.2}" width="16" height="{bar_h:.2}" fill="url(#scale)" stroke="{}" stroke-width="0.5"/>"#,
        g.top,
        style::INK
    );
    for k in 0..=4 {
        let t = k as f64 / 4.0;
        let y = g.top + bar_h * (1.0 - t);
        let _ = writeln!(
            s,
            r#"<line x1="{:.2}" y1="{y:.2}" x2="{:.2}" y2="{y:.2}" stroke="{}"/>"#,
            bar_x + 16.0,
            bar_x + 20.0,
            style::INK
        );
        let label = tick_label(t * v_max * h.scale_factor);
        let _ = writeln!(
            s,
            r#"<text class="colorbar-tick" x="{:.2}" y="{y:.2}" font-size="{}" dominant-baseline="central">{label}</text>"#,
            bar_x + 23.0,
            style::TICK
        );
    }
    text(
        &mut s,
        "colorbar-title",
        bar_x + 8.0,
        g.top - 10.0,
        style::TICK,
        "middle",
        0.0,
        h.scale_title,
    );
    s.push_str("</svg>\n");
    s
}

/// Writes a heatmap (see [`Heatmap`]) as SVG, atomically.
pub fn heatmap(path: &Path, h: &Heatmap<'_>) -> std::io::Result<()> {
    write_atomic(path, heatmap_svg(h).as_bytes())
}

/// What [`small_multiples`] draws: one small bar chart (a panel) per series,
/// all on the same axes, so that many estimators stay readable side by side
/// (grouped bars of 8 series become slivers).
pub struct SmallMultiples<'a> {
    /// Title above the panels.
    pub title: &'a str,
    /// x axis title (under the bottom row of panels).
    pub x_title: &'a str,
    /// y axis title (left of the left column of panels).
    pub y_title: &'a str,
    /// Category of each bar, left to right (the same in every panel).
    pub categories: &'a [String],
    /// Per panel: its name and one value per category (non-finite: no value,
    /// marked by a small grey cross on the axis).
    pub series: &'a [(&'a str, Vec<f64>)],
    /// Per panel, a note after its name (e.g. its overall value); may be empty.
    pub notes: &'a [String],
}

/// Panel layout of [`small_multiples`]: `(columns, rows)` for `n` panels.
pub fn panel_grid(n: usize) -> (usize, usize) {
    let cols = match n {
        0 | 1 => 1,
        2..=4 => 2,
        5 | 6 => 3,
        _ => 4,
    };
    (cols, n.max(1).div_ceil(cols))
}

/// The SVG text of a small-multiples bar chart (see [`SmallMultiples`]).
pub fn small_multiples_svg(m: &SmallMultiples<'_>) -> String {
    let n = m.series.len();
    let (gc, gr) = panel_grid(n);
    let n_cat = m.categories.len().max(1);
    let (pw, ph) = if gc == 1 { (640.0, 280.0) } else { (300.0, 190.0) };
    let (left, top, gap_x, gap_y) = (70.0, 64.0, 28.0, 58.0);
    let width = left + gc as f64 * pw + (gc - 1) as f64 * gap_x + 20.0;
    let height = top + gr as f64 * ph + (gr - 1) as f64 * gap_y + 78.0;
    let max = m
        .series
        .iter()
        .flat_map(|s| s.1.iter())
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0_f64, f64::max);
    let (ticks, top_v) = nice_ticks(max, 4);
    let mut s = svg_open(width, height);
    text(
        &mut s,
        "title",
        width / 2.0,
        26.0,
        style::TITLE,
        "middle",
        0.0,
        m.title,
    );
    // Every label when there is room, else every other one (the ticks stay).
    let slot = pw / n_cat as f64;
    let longest = m.categories.iter().map(|c| c.chars().count()).max().unwrap_or(1) as f64;
    let every = if slot >= longest * 0.62 * style::TICK as f64 + 3.0 {
        1
    } else {
        2
    };
    for (k, (name, values)) in m.series.iter().enumerate() {
        let (col, row) = (k % gc, k / gc);
        let x0 = left + col as f64 * (pw + gap_x);
        let y0 = top + row as f64 * (ph + gap_y);
        let y_of = |v: f64| y0 + ph * (1.0 - v / top_v);
        let _ = writeln!(s, r#"<g class="panel" data-series="{}">"#, esc(name));
        for &t in &ticks {
            let y = y_of(t);
            let _ = writeln!(
                s,
                r#"<line x1="{x0:.2}" y1="{y:.2}" x2="{:.2}" y2="{y:.2}" stroke="{}" stroke-width="1"/>"#,
                x0 + pw,
                style::GRID
            );
            if col == 0 {
                text(
                    &mut s,
                    "label-y",
                    x0 - 6.0,
                    y + 4.0,
                    style::TICK,
                    "end",
                    0.0,
                    &tick_label(t),
                );
            }
        }
        let fill = tab10_hex(k);
        for (i, &v) in values.iter().enumerate().take(n_cat) {
            let cx = x0 + (i as f64 + 0.5) * slot;
            let bw = (slot * 0.7).max(1.0);
            if v.is_finite() {
                let v = v.max(0.0);
                // A zero is drawn as a hairline on the axis, so "no error"
                // reads differently from "no value" (the cross).
                let h = (ph * v / top_v).max(1.5);
                let y = y0 + ph - h;
                let _ = writeln!(
                    s,
                    r#"<rect class="bar" data-cat="{i}" x="{:.2}" y="{y:.2}" width="{bw:.2}" height="{h:.2}" fill="{fill}"><title>{}: {}</title></rect>"#,
                    cx - bw / 2.0,
                    esc(m.categories.get(i).map_or("", String::as_str)),
                    tick_label(v)
                );
            } else {
                let (y, d) = (y0 + ph - 4.0, 3.0);
                let _ = writeln!(
                    s,
                    r##"<path class="missing" d="M{:.2} {:.2}L{:.2} {:.2}M{:.2} {:.2}L{:.2} {:.2}" stroke="#999999" stroke-width="1.2"/>"##,
                    cx - d,
                    y - d,
                    cx + d,
                    y + d,
                    cx - d,
                    y + d,
                    cx + d,
                    y - d
                );
            }
        }
        // Axes, one tick per category at its slot's centre.
        let yb = y0 + ph;
        let _ = writeln!(
            s,
            r#"<path d="M{x0:.2} {y0:.2}L{x0:.2} {yb:.2}L{:.2} {yb:.2}" fill="none" stroke="{}"/>"#,
            x0 + pw,
            style::INK
        );
        for (i, category) in m.categories.iter().enumerate() {
            let cx = x0 + (i as f64 + 0.5) * slot;
            let _ = writeln!(
                s,
                r#"<line class="tick-x" x1="{cx:.2}" y1="{yb:.2}" x2="{cx:.2}" y2="{:.2}" stroke="{}"/>"#,
                yb + 4.0,
                style::INK
            );
            if i % every == 0 {
                text(
                    &mut s,
                    "label-x",
                    cx,
                    yb + 16.0,
                    style::TICK,
                    "middle",
                    0.0,
                    category,
                );
            }
        }
        let note = m.notes.get(k).filter(|n| !n.is_empty());
        let head = match note {
            Some(n) => format!("{name} — {n}"),
            None => name.to_string(),
        };
        text(
            &mut s,
            "panel-title",
            x0 + pw / 2.0,
            y0 - 8.0,
            style::AXIS,
            "middle",
            0.0,
            &head,
        );
        s.push_str("</g>\n");
    }
    let grid_w = gc as f64 * pw + (gc - 1) as f64 * gap_x;
    let grid_h = gr as f64 * ph + (gr - 1) as f64 * gap_y;
    text(
        &mut s,
        "axis-title-x",
        left + grid_w / 2.0,
        top + grid_h + 44.0,
        style::AXIS,
        "middle",
        0.0,
        m.x_title,
    );
    text(
        &mut s,
        "axis-title-y",
        20.0,
        top + grid_h / 2.0,
        style::AXIS,
        "middle",
        -90.0,
        m.y_title,
    );
    s.push_str("</svg>\n");
    s
}

/// Writes a small-multiples bar chart (see [`SmallMultiples`]) as SVG, atomically.
pub fn small_multiples(path: &Path, m: &SmallMultiples<'_>) -> std::io::Result<()> {
    write_atomic(path, small_multiples_svg(m).as_bytes())
}

/// One point of a [`frontier_chart`]: its position, its colour group (e.g. the
/// estimator) and its marker group (e.g. the sweep series).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScatterPoint {
    /// x (must be positive on a log axis; other points are left out).
    pub x: f64,
    /// y.
    pub y: f64,
    /// Index into [`FrontierChart::colors`].
    pub color: usize,
    /// Index into [`FrontierChart::markers`].
    pub marker: usize,
}

/// What [`frontier_chart`] draws.
pub struct FrontierChart<'a> {
    /// Caption.
    pub title: &'a str,
    /// x axis description.
    pub x_label: &'a str,
    /// y axis description.
    pub y_label: &'a str,
    /// Logarithmic x axis (base 10).
    pub log_x: bool,
    /// Legend name of each colour group.
    pub colors: &'a [&'a str],
    /// Legend name of each marker group (drawn in black in the legend).
    pub markers: &'a [&'a str],
    /// The points.
    pub points: &'a [ScatterPoint],
    /// The frontier's points, drawn ringed and joined as a step line in x
    /// order (any order is accepted).
    pub frontier: &'a [(f64, f64)],
    /// Per colour group, that group's own frontier, drawn as a dashed step
    /// line in its colour (empty: none).
    pub own_frontiers: &'a [Vec<(f64, f64)>],
    /// Legend name of one more marker group, drawn as a star (e.g. the base
    /// configuration): points whose `marker` is `markers.len()`.
    pub base: Option<&'a str>,
}

type Xy = (f64, f64);

/// The step line through frontier points: sorted by x, from each point right
/// to the next one's x, then to its y (the best y reachable at each x).
fn step_line(points: &[(f64, f64)], ok: impl Fn(f64, f64) -> bool) -> (Vec<Xy>, Vec<Xy>) {
    let mut front: Vec<(f64, f64)> = points.iter().copied().filter(|p| ok(p.0, p.1)).collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let mut steps = Vec::with_capacity(2 * front.len());
    for (k, &(x, y)) in front.iter().enumerate() {
        if k > 0 {
            steps.push((x, front[k - 1].1));
        }
        steps.push((x, y));
    }
    (front, steps)
}

/// Marker shapes, cycled by marker group: filled circle, triangle, square,
/// diamond; cross, plus; open circle, triangle, square, diamond. The base
/// group ([`FrontierChart::base`]) is a star.
const MARKERS: usize = 10;
const STAR: usize = usize::MAX;

/// Colour `k` of the frontier chart: the ten "Tableau 10" colours, which stay
/// distinct on white (plotters' palette starts with a pale yellow).
fn tab10(k: usize) -> RGBAColor {
    const C: [(u8, u8, u8); 10] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = C[k % C.len()];
    RGBColor(r, g, b).to_rgba()
}

/// Colour `k` of [`tab10`] as `#rrggbb`, for plots written as SVG text.
fn tab10_hex(k: usize) -> String {
    let c = tab10(k);
    format!("#{:02x}{:02x}{:02x}", c.0, c.1, c.2)
}

/// Draws marker `kind` centred at pixel `at` of `area`.
fn marker<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    kind: usize,
    at: (i32, i32),
    color: RGBAColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (x, y) = at;
    let fill = color.filled();
    let line = color.stroke_width(2);
    let tri = vec![(x, y - 6), (x + 6, y + 4), (x - 6, y + 4)];
    let dia = vec![(x, y - 6), (x + 6, y), (x, y + 6), (x - 6, y)];
    let sq = [(x - 5, y - 5), (x + 5, y + 5)];
    let closed = |mut v: Vec<(i32, i32)>| {
        v.push(v[0]);
        v
    };
    if kind == STAR {
        let star: Vec<(i32, i32)> = (0..10)
            .map(|k| {
                let r = if k % 2 == 0 { 8.0 } else { 3.5 };
                let a = std::f64::consts::PI * (k as f64 / 5.0 - 0.5);
                (x + (r * a.cos()).round() as i32, y + (r * a.sin()).round() as i32)
            })
            .collect();
        return area.draw(&Polygon::new(star, fill));
    }
    match kind % MARKERS {
        0 => area.draw(&Circle::new(at, 5, fill)),
        1 => area.draw(&Polygon::new(tri, fill)),
        2 => area.draw(&Rectangle::new(sq, fill)),
        3 => area.draw(&Polygon::new(dia, fill)),
        4 => {
            area.draw(&PathElement::new(vec![(x - 5, y - 5), (x + 5, y + 5)], line))?;
            area.draw(&PathElement::new(vec![(x - 5, y + 5), (x + 5, y - 5)], line))
        }
        5 => {
            area.draw(&PathElement::new(vec![(x - 6, y), (x + 6, y)], line))?;
            area.draw(&PathElement::new(vec![(x, y - 6), (x, y + 6)], line))
        }
        6 => area.draw(&Circle::new(at, 5, line)),
        7 => area.draw(&PathElement::new(closed(tri), line)),
        8 => area.draw(&Rectangle::new(sq, line)),
        _ => area.draw(&PathElement::new(closed(dia), line)),
    }
}

/// Tick values for a log axis over `[lo, hi]`: 1, 2 and 5 times powers of ten
/// (every integer multiple when that gives fewer than three).
fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return Vec::new();
    }
    let (e0, e1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    let pick = |mults: &[f64]| -> Vec<f64> {
        (e0..=e1)
            .flat_map(|e| mults.iter().map(move |m| m * 10f64.powi(e)))
            .filter(|v| *v >= lo && *v <= hi)
            .collect()
    };
    let ticks = pick(&[1.0, 2.0, 5.0]);
    if ticks.len() >= 3 {
        ticks
    } else {
        pick(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0])
    }
}

/// A tick label without trailing zeros.
fn tick_label(v: f64) -> String {
    let s = if v.abs() >= 100.0 || v == v.round() {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    };
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Writes a scatter chart with its Pareto frontier as SVG: points coloured by
/// colour group with a marker per marker group, the frontier ringed and joined
/// by a step line (from each frontier point, right to the next one's x, then
/// down to its y: the best y reachable at each x), each colour group's own
/// frontier dashed in its colour, and the legend beside the plot. Non-finite
/// points (and, on a log axis, non-positive x) are left out; y starts at 0.
pub fn frontier_chart(path: &Path, c: &FrontierChart<'_>) -> std::io::Result<()> {
    let ok = |x: f64, y: f64| x.is_finite() && y.is_finite() && (!c.log_x || x > 0.0);
    let points: Vec<ScatterPoint> = c.points.iter().copied().filter(|p| ok(p.x, p.y)).collect();
    let (front, steps) = step_line(c.frontier, ok);
    let own: Vec<Vec<(f64, f64)>> = c.own_frontiers.iter().map(|f| step_line(f, ok).1).collect();
    let y_max = points.iter().map(|p| p.y).fold(0.0_f64, f64::max);
    let y_max = if y_max > 0.0 { y_max * 1.08 } else { 1.0 };
    let (x0, x1) = if c.log_x {
        let lo = points.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
        let hi = points.iter().map(|p| p.x).fold(0.0_f64, f64::max);
        if lo.is_finite() && hi > 0.0 {
            (lo / 1.25, hi * 1.25)
        } else {
            (0.1, 10.0)
        }
    } else {
        let (lo, hi) = bounds(points.iter().map(|p| p.x));
        (lo.min(0.0), hi)
    };
    let base_name = c.base;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (1040, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(err(path))?;
        let (plot, legend) = root.split_horizontally(820);
        let builder = |area| {
            let mut b = ChartBuilder::on(area);
            b.caption(c.title, ("sans-serif", style::TITLE))
                .margin(12)
                .x_label_area_size(45)
                .y_label_area_size(60);
            b
        };
        // The same drawing on a log or a linear x axis (two coordinate types);
        // gives the pixels of the points and of the frontier's rings.
        macro_rules! draw {
            ($chart:expr) => {{
                let mut chart = $chart.map_err(err(path))?;
                chart
                    .configure_mesh()
                    .x_desc(c.x_label)
                    .y_desc(c.y_label)
                    .x_label_formatter(&|v: &f64| tick_label(*v))
                    .draw()
                    .map_err(err(path))?;
                for (k, line) in own.iter().enumerate().filter(|(_, l)| l.len() > 1) {
                    let color = tab10(k);
                    chart
                        .draw_series(DashedLineSeries::new(
                            line.iter().copied(),
                            6,
                            4,
                            color.stroke_width(1),
                        ))
                        .map_err(err(path))?;
                }
                if !steps.is_empty() {
                    chart
                        .draw_series(LineSeries::new(
                            steps.iter().copied(),
                            BLACK.stroke_width(2),
                        ))
                        .map_err(err(path))?;
                }
                let px: Vec<(i32, i32)> = points
                    .iter()
                    .map(|p| chart.backend_coord(&(p.x, p.y)))
                    .collect();
                let rings: Vec<(i32, i32)> = front.iter().map(|p| chart.backend_coord(p)).collect();
                (px, rings)
            }};
        }
        let (px, rings) = if c.log_x {
            let ticks = log_ticks(x0, x1);
            if ticks.is_empty() {
                draw!(builder(&plot).build_cartesian_2d((x0..x1).log_scale(), 0.0..y_max))
            } else {
                draw!(builder(&plot)
                    .build_cartesian_2d((x0..x1).log_scale().with_key_points(ticks), 0.0..y_max))
            }
        } else {
            draw!(builder(&plot).build_cartesian_2d(x0..x1, 0.0..y_max))
        };
        for (p, at) in points.iter().zip(px) {
            let kind = if base_name.is_some() && p.marker == c.markers.len() {
                STAR
            } else {
                p.marker
            };
            marker(&root, kind, at, tab10(p.color)).map_err(err(path))?;
        }
        for at in rings {
            root.draw(&Circle::new(at, 10, BLACK.stroke_width(1)))
                .map_err(err(path))?;
        }
        // The legend, beside the plot: colours, markers, lines.
        let font = ("sans-serif", 14).into_font();
        let mut y = 50;
        let entry = |text: &str, y: i32| {
            legend
                .draw(&Text::new(text.to_string(), (40, y - 7), font.clone()))
                .map_err(err(path))
        };
        for (k, name) in c.colors.iter().enumerate() {
            let color = tab10(k);
            legend
                .draw(&Rectangle::new([(12, y - 6), (24, y + 6)], color.filled()))
                .map_err(err(path))?;
            entry(name, y)?;
            y += 22;
        }
        y += 8;
        let groups = c.markers.iter().enumerate().map(|(k, n)| (k, *n));
        for (k, name) in groups.chain(base_name.map(|n| (STAR, n))) {
            marker(&legend, k, (18, y), BLACK.to_rgba()).map_err(err(path))?;
            entry(name, y)?;
            y += 22;
        }
        y += 8;
        if !steps.is_empty() {
            legend
                .draw(&PathElement::new(vec![(6, y), (30, y)], BLACK.stroke_width(2)))
                .map_err(err(path))?;
            legend
                .draw(&Circle::new((18, y), 10, BLACK.stroke_width(1)))
                .map_err(err(path))?;
            entry("overall frontier", y)?;
            y += 24;
        }
        if own.iter().any(|l| l.len() > 1) {
            for x in [6, 16, 26] {
                legend
                    .draw(&PathElement::new(vec![(x, y), (x + 6, y)], BLACK.stroke_width(1)))
                    .map_err(err(path))?;
            }
            entry("own frontier (colour)", y)?;
        }
        root.present().map_err(err(path))?;
    }
    write_atomic(path, svg.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_and_frontier_charts_write_svg() {
        let dir = std::env::temp_dir().join(format!("palpate-plot-{}", std::process::id()));
        let p = dir.join("line.svg");
        line_chart(
            &p,
            "t",
            "x",
            "y",
            &[
                Series {
                    name: "a",
                    points: vec![(0.0, 1.0), (1.0, 2.0)],
                },
                Series {
                    name: "b",
                    points: vec![(0.0, 0.0), (1.0, f64::NAN)],
                },
            ],
        )
        .unwrap();
        let s = std::fs::read_to_string(&p).unwrap();
        assert!(
            s.starts_with("<svg") && s.contains("polyline"),
            "{}",
            &s[..200.min(s.len())]
        );
        let f = dir.join("frontier.svg");
        let pts: Vec<ScatterPoint> = (0..8)
            .map(|k| ScatterPoint {
                x: 0.5 * (k + 1) as f64,
                y: 8.0 - k as f64,
                color: k % 3,
                marker: k,
            })
            .chain([ScatterPoint {
                x: f64::NAN,
                y: 1.0,
                color: 0,
                marker: 0,
            }])
            .collect();
        for log_x in [true, false] {
            frontier_chart(
                &f,
                &FrontierChart {
                    title: "t",
                    x_label: "ms",
                    y_label: "MAE",
                    log_x,
                    colors: &["a", "b", "c"],
                    markers: &["m0", "m1", "m2", "m3", "m4", "m5", "m6", "m7"],
                    points: &pts,
                    frontier: &[(4.0, 1.0), (0.5, 8.0), (1.0, 7.0)],
                    own_frontiers: &[vec![(0.5, 8.0), (2.0, 5.0)], vec![], vec![(f64::NAN, 1.0)]],
                    base: Some("base"),
                },
            )
            .unwrap();
            let s = std::fs::read_to_string(&f).unwrap();
            assert!(
                s.contains("overall frontier") && s.contains("polyline"),
                "log {log_x}"
            );
            assert!(s.contains("m5") && s.contains("m0"), "legend missing");
        }
        // Nothing to draw, or only points a log axis cannot show: no panic.
        let bad = [ScatterPoint {
            x: -1.0,
            y: 1.0,
            color: 0,
            marker: 0,
        }];
        for points in [&[][..], &bad[..]] {
            frontier_chart(
                &f,
                &FrontierChart {
                    title: "t",
                    x_label: "x",
                    y_label: "y",
                    log_x: true,
                    colors: &[],
                    markers: &[],
                    points,
                    frontier: &[],
                    own_frontiers: &[],
                    base: None,
                },
            )
            .unwrap();
        }
        // Empty and constant data must not panic.
        line_chart(&p, "t", "x", "y", &[]).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The numeric attribute `name` of an SVG element's text.
    fn attr(el: &str, name: &str) -> f64 {
        let key = format!(" {name}=\"");
        let i = el.find(&key).unwrap_or_else(|| panic!("no {name} in {el}")) + key.len();
        let j = el[i..].find('"').unwrap() + i;
        el[i..j].parse().unwrap()
    }

    /// Every element of class `class`, as its text.
    fn elements<'s>(svg: &'s str, class: &str) -> Vec<&'s str> {
        let key = format!("class=\"{class}\"");
        svg.lines().filter(|l| l.contains(&key)).collect()
    }

    /// The text of a `<text>` element.
    fn body(el: &str) -> &str {
        let i = el.find('>').unwrap() + 1;
        &el[i..el.rfind("</text>").unwrap()]
    }

    fn labels(n: usize) -> Vec<String> {
        (0..n).map(|k| format!("{}", 10 + 5 * k)).collect()
    }

    #[test]
    fn heatmap_labels_sit_at_cell_centres_one_per_row_and_column() {
        for n in [1, 3, 17, 40] {
            let rows = labels(n);
            let mut cols = labels(n);
            cols.push("no edge".into());
            let values: Vec<Vec<f64>> = (0..n)
                .map(|r| (0..=n).map(|c| if r == c { 1.0 } else { 0.0 }).collect())
                .collect();
            let text: Vec<Vec<String>> = values
                .iter()
                .map(|row| row.iter().map(|v| format!("{:.0}", v * 100.0)).collect())
                .collect();
            let svg = heatmap_svg(&Heatmap {
                title: "t",
                x_title: "estimated angle (°)",
                y_title: "true angle (°)",
                row_labels: &rows,
                col_labels: &cols,
                values: &values,
                cell_text: &text,
                v_max: Some(1.0),
                scale_title: "% of row",
                scale_factor: 100.0,
            });
            let g = heatmap_geometry(n, n + 1, &rows);
            let cells = elements(&svg, "cell");
            assert_eq!(cells.len(), n * (n + 1), "n {n}");
            for cell in &cells {
                assert!(
                    (attr(cell, "width") - attr(cell, "height")).abs() < 1e-9,
                    "square cells"
                );
            }
            // One label per row and column, each at its cell's centre, in order.
            let ly = elements(&svg, "label-y");
            let lx = elements(&svg, "label-x");
            assert_eq!((ly.len(), lx.len()), (n, n + 1), "n {n}");
            assert_eq!(elements(&svg, "tick-x").len(), n + 1);
            assert_eq!(elements(&svg, "tick-y").len(), n);
            for (r, el) in ly.iter().enumerate() {
                assert!((attr(el, "y") - g.row_centre(r)).abs() < 0.01, "row {r}: {el}");
                assert_eq!(body(el), rows[r]);
            }
            for (c, el) in lx.iter().enumerate() {
                assert!((attr(el, "x") - g.col_centre(c)).abs() < 0.01, "col {c}: {el}");
                assert_eq!(body(el), cols[c]);
            }
            // Labels are unique: no class appears twice.
            let mut seen: Vec<&str> = ly.iter().map(|e| body(e)).collect();
            seen.sort_unstable();
            seen.dedup();
            assert_eq!(seen.len(), n);
            // Axis titles, colour bar, a value in every cell.
            assert_eq!(elements(&svg, "axis-title-x").len(), 1);
            assert_eq!(elements(&svg, "axis-title-y").len(), 1);
            assert_eq!(elements(&svg, "colorbar").len(), 1);
            let ticks: Vec<&str> = elements(&svg, "colorbar-tick").into_iter().map(body).collect();
            assert_eq!(ticks, ["0", "25", "50", "75", "100"]);
            assert_eq!(elements(&svg, "cell-value").len(), n * (n + 1));
            // The diagonal is the darkest colour, the rest white.
            let dark = hex(blues(1.0));
            for cell in &cells {
                let (r, c) = (attr(cell, "data-row"), attr(cell, "data-col"));
                assert_eq!(cell.contains(&dark), r == c, "{cell}");
            }
        }
    }

    #[test]
    fn heatmap_of_nothing_or_nan_is_valid_svg() {
        for values in [vec![], vec![vec![f64::NAN, f64::INFINITY]], vec![vec![0.0; 3]; 2]] {
            let svg = heatmap_svg(&Heatmap {
                title: "<&>",
                x_title: "x",
                y_title: "y",
                row_labels: &[],
                col_labels: &[],
                values: &values,
                cell_text: &[],
                v_max: None,
                scale_title: "",
                scale_factor: 1.0,
            });
            assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
            assert!(!svg.contains("NaN") && !svg.contains("inf") && svg.contains("&lt;&amp;&gt;"));
        }
    }

    #[test]
    fn small_multiples_give_one_panel_per_series_on_shared_axes() {
        let cats = labels(17);
        let names: Vec<String> = (0..8).map(|k| format!("est{k}")).collect();
        let series: Vec<(&str, Vec<f64>)> = names
            .iter()
            .enumerate()
            .map(|(k, n)| {
                let v = (0..17)
                    .map(|i| {
                        if i == 3 && k == 2 {
                            f64::NAN
                        } else {
                            (k + i) as f64 * 0.5
                        }
                    })
                    .collect();
                (n.as_str(), v)
            })
            .collect();
        let notes: Vec<String> = (0..8).map(|k| format!("MAE {k}")).collect();
        let svg = small_multiples_svg(&SmallMultiples {
            title: "MAE per class",
            x_title: "true angle (°)",
            y_title: "MAE (°)",
            categories: &cats,
            series: &series,
            notes: &notes,
        });
        assert_eq!(svg.matches(r#"<g class="panel""#).count(), 8);
        assert_eq!(elements(&svg, "panel-title").len(), 8);
        // One tick per class in every panel, the bars centred on them.
        let ticks = elements(&svg, "tick-x");
        assert_eq!(ticks.len(), 8 * 17);
        let bars = elements(&svg, "bar");
        assert_eq!(bars.len(), 8 * 17 - 1, "the NaN is not a bar");
        assert_eq!(elements(&svg, "missing").len(), 1);
        for (bar, tick) in bars.iter().zip(ticks.iter()).take(17) {
            let centre = attr(bar, "x") + attr(bar, "width") / 2.0;
            assert!((centre - attr(tick, "x1")).abs() < 0.01);
            assert!(attr(bar, "width") > 5.0, "bars are not slivers: {bar}");
        }
        // Shared y axis: equal values give equal bar heights in any panel.
        // Panels 0, 1 have 17 bars, panel 2 has 16 (its NaN), panel 3 has 17.
        let h = |i: usize| attr(bars[i], "height");
        assert!((h(4) - h(67)).abs() < 1e-9, "est0 at 30° = est4 at 10° = 2.0");
        assert!(
            (h(bars.len() - 1) / h(4) - 11.5 / 2.0).abs() < 0.01,
            "heights to 0.01 px"
        );
        assert_eq!(h(0), 1.5, "a zero is a visible hairline, not nothing");
        assert_eq!(panel_grid(8), (4, 2));
        assert_eq!(panel_grid(1), (1, 1));
        assert_eq!(panel_grid(0), (1, 1));
        assert!(svg.contains("est7 — MAE 7"));
        // Nothing to draw: still a valid document.
        let empty = small_multiples_svg(&SmallMultiples {
            title: "t",
            x_title: "x",
            y_title: "y",
            categories: &[],
            series: &[],
            notes: &[],
        });
        assert!(empty.trim_end().ends_with("</svg>") && !empty.contains("NaN"));
    }

    #[test]
    fn nice_ticks_cover_the_maximum() {
        assert_eq!(nice_ticks(0.0, 4), (vec![0.0, 0.5, 1.0], 1.0));
        let (t, top) = nice_ticks(7.3, 4);
        assert_eq!(t, vec![0.0, 2.0, 4.0, 6.0, 8.0]);
        assert_eq!(top, 8.0);
        let (t, top) = nice_ticks(f64::NAN, 4);
        assert!(top >= 1.0 && t[0] == 0.0);
    }
}
