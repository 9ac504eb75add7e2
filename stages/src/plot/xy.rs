//! A sweep's declared figures: line plots over a numeric x axis (points
//! joined in x order, a ± SD error bar where a point has one, reference series
//! dashed with open markers) and grouped bar charts over categories (one bar
//! per series in each category's group, reference series as dashed outlines,
//! optional value labels, ± SD error bars).
//!
//! Both share one frame in the house style ([`super::style`]): the title
//! above, y grid lines at "nice" steps (1, 2 or 5 times a power of ten) with
//! 0 always on the axis, axis titles, and the legend outside the plot area on
//! the right, so that no entry hides data. Coordinates are linear:
//! `px = left + w · (x − x₀) / (x₁ − x₀)` and `py = top + h · (1 − (y − y₀) / (y₁ − y₀))`,
//! so a bar's height is proportional to its value. Non-finite values are left
//! out (a NaN or an infinity never reaches the SVG text).
//!
//! Elements carry a `class` naming their role (`plot-area`, `line`, `point`,
//! `errorbar`, `reference`, `bar`, `ref-bar`, `bar-value`, `legend-entry`,
//! ...), so tests can check the structure.

use super::{esc, nice_range, nice_step, style, svg_open, tab10_hex, text, tick_label};
use palpate_core::output::write_atomic;
use std::fmt::Write as _;
use std::path::Path;

/// One point of a [`PlotSeries`]: its position and, optionally, the SD drawn
/// as an error bar from `y − sd` to `y + sd`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point {
    /// x: a number on a line plot; the category's index on a bar chart.
    pub x: f64,
    /// y.
    pub y: f64,
    /// Spread of y (e.g. the SD over repeats); `None`, 0 or non-finite: no bar.
    pub sd: Option<f64>,
}

/// A named series of points.
#[derive(Clone, Debug, PartialEq)]
pub struct PlotSeries {
    /// Legend name.
    pub name: String,
    /// Points, in any order (a line plot joins them in x order).
    pub points: Vec<Point>,
}

/// What [`line_plot`] draws, and the common part of a [`BarPlot`].
pub struct Figure<'a> {
    /// Title above the plot.
    pub title: &'a str,
    /// Title of the x axis.
    pub x_title: &'a str,
    /// Title of the y axis.
    pub y_title: &'a str,
    /// Measured series, coloured in turn.
    pub series: &'a [PlotSeries],
    /// Reference series (e.g. published values): dashed with open markers on
    /// a line plot, dashed outlines after the measured bars on a bar chart.
    pub reference: &'a [PlotSeries],
}

/// What [`bar_plot`] draws: a [`Figure`] over categories, one bar per series
/// in each category's group.
pub struct BarPlot<'a> {
    /// Titles and series; a point's `x` is its category's index.
    pub figure: Figure<'a>,
    /// Category labels, left to right.
    pub categories: &'a [String],
    /// Write each bar's value above it.
    pub value_labels: bool,
}

/// The plot area and the legend's place, px.
struct Frame {
    left: f64,
    top: f64,
    w: f64,
    h: f64,
    /// Left edge of the legend (right of the plot area); `None`: no legend.
    legend_x: Option<f64>,
    width: f64,
    height: f64,
}

/// How a legend entry shows its series.
enum Swatch {
    /// A line sample with a marker; dashed (this pattern) and open for a
    /// reference.
    Line {
        color: String,
        dashed: Option<&'static str>,
    },
    /// A bar sample; outlined and dashed for a reference.
    Bar { color: String, reference: bool },
}

/// Dash pattern of reference series `k` (distinct for up to three).
fn dash(k: usize) -> &'static str {
    ["6 4", "2 3", "9 3 2 3"][k % 3]
}

/// Colour of reference series `k`: dark greys that no Tableau colour resembles.
fn ref_color(k: usize) -> String {
    ["#222222", "#777777", "#444444"][k % 3].to_string()
}

/// The frame of a plot area `w` x `h` px with a legend of `names` (drawn only
/// when there is more than one entry).
fn frame(w: f64, h: f64, names: &[&str]) -> Frame {
    let (left, top) = (78.0, 52.0);
    let legend_w =
        names.iter().map(|n| n.chars().count()).max().unwrap_or(0) as f64 * 0.6 * style::TICK as f64 + 44.0;
    let legend_x = (names.len() > 1).then_some(left + w + 22.0);
    let width = legend_x.map_or(left + w + 24.0, |x| x + legend_w + 8.0);
    Frame {
        left,
        top,
        w,
        h,
        legend_x,
        width,
        height: top + h + 70.0,
    }
}

/// Opens the document and draws the title, the y grid and tick labels, the
/// axes and both axis titles. `y_of` maps a value to its pixel row.
fn open(
    f: &Frame,
    title: &str,
    x_title: &str,
    y_title: &str,
    y_ticks: &[f64],
    y_of: &dyn Fn(f64) -> f64,
) -> String {
    let mut s = svg_open(f.width, f.height);
    text(
        &mut s,
        "title",
        f.left + f.w / 2.0,
        28.0,
        style::TITLE,
        "middle",
        0.0,
        title,
    );
    for &t in y_ticks {
        let y = y_of(t);
        let _ = writeln!(
            s,
            r#"<line class="grid-y" x1="{:.2}" y1="{y:.2}" x2="{:.2}" y2="{y:.2}" stroke="{}" stroke-width="1"/>"#,
            f.left,
            f.left + f.w,
            style::GRID
        );
        text(
            &mut s,
            "label-y",
            f.left - 7.0,
            y + 4.0,
            style::TICK,
            "end",
            0.0,
            &tick_label(t),
        );
    }
    let _ = writeln!(
        s,
        r#"<rect class="plot-area" x="{:.2}" y="{:.2}" width="{:.2}" height="{:.2}" fill="none" stroke="none"/>"#,
        f.left, f.top, f.w, f.h
    );
    let bottom = f.top + f.h;
    let _ = writeln!(
        s,
        r#"<path class="axes" d="M{:.2} {:.2}L{:.2} {bottom:.2}L{:.2} {bottom:.2}" fill="none" stroke="{}"/>"#,
        f.left,
        f.top,
        f.left,
        f.left + f.w,
        style::INK
    );
    text(
        &mut s,
        "axis-title-x",
        f.left + f.w / 2.0,
        bottom + 50.0,
        style::AXIS,
        "middle",
        0.0,
        x_title,
    );
    text(
        &mut s,
        "axis-title-y",
        20.0,
        f.top + f.h / 2.0,
        style::AXIS,
        "middle",
        -90.0,
        y_title,
    );
    s
}

/// The legend, right of the plot area: one entry per series.
fn legend(s: &mut String, f: &Frame, entries: &[(&str, Swatch)]) {
    let Some(x) = f.legend_x else { return };
    let _ = writeln!(s, r#"<g class="legend">"#);
    for (k, (name, swatch)) in entries.iter().enumerate() {
        let y = f.top + 10.0 + 22.0 * k as f64;
        match swatch {
            Swatch::Line { color, dashed } => {
                let d = dashed.map_or(String::new(), |p| format!(r#" stroke-dasharray="{p}""#));
                let _ = writeln!(
                    s,
                    r#"<line x1="{x:.2}" y1="{y:.2}" x2="{:.2}" y2="{y:.2}" stroke="{color}" stroke-width="2"{d}/>"#,
                    x + 26.0
                );
                marker(s, "legend-marker", x + 13.0, y, color, dashed.is_some());
            }
            Swatch::Bar { color, reference } => {
                let paint = if *reference {
                    format!(r##"fill="#ffffff" stroke="{color}" stroke-width="1.5" stroke-dasharray="4 2""##)
                } else {
                    format!(r#"fill="{color}""#)
                };
                let _ = writeln!(
                    s,
                    r#"<rect x="{:.2}" y="{:.2}" width="16" height="12" {paint}/>"#,
                    x + 5.0,
                    y - 6.0
                );
            }
        }
        text(
            s,
            "legend-entry",
            x + 34.0,
            y + 4.0,
            style::TICK,
            "start",
            0.0,
            name,
        );
    }
    let _ = writeln!(s, "</g>");
}

/// A point's marker: a filled circle, or an open square for a reference.
fn marker(s: &mut String, class: &str, x: f64, y: f64, color: &str, reference: bool) {
    if reference {
        let _ = writeln!(
            s,
            r##"<rect class="{class}" x="{:.2}" y="{:.2}" width="8" height="8" fill="#ffffff" stroke="{color}" stroke-width="1.5"/>"##,
            x - 4.0,
            y - 4.0
        );
    } else {
        let _ = writeln!(
            s,
            r#"<circle class="{class}" cx="{x:.2}" cy="{y:.2}" r="3.5" fill="{color}"/>"#
        );
    }
}

/// A tick on the x axis (at pixel row `bottom`) at column `x`, with its label.
fn x_tick(s: &mut String, x: f64, bottom: f64, label: Option<&str>) {
    let _ = writeln!(
        s,
        r#"<line class="tick-x" x1="{x:.2}" y1="{bottom:.2}" x2="{x:.2}" y2="{:.2}" stroke="{}"/>"#,
        bottom + 4.0,
        style::INK
    );
    if let Some(label) = label {
        text(s, "label-x", x, bottom + 18.0, style::TICK, "middle", 0.0, label);
    }
}

/// An error bar from `lo` to `hi` (pixel rows) at column `x`, with caps.
fn error_bar(s: &mut String, x: f64, lo: f64, hi: f64, color: &str) {
    let c = 4.0;
    let _ = writeln!(
        s,
        r#"<path class="errorbar" d="M{x:.2} {lo:.2}L{x:.2} {hi:.2}M{:.2} {lo:.2}L{:.2} {lo:.2}M{:.2} {hi:.2}L{:.2} {hi:.2}" fill="none" stroke="{color}" stroke-width="1.2"/>"#,
        x - c,
        x + c,
        x - c,
        x + c
    );
}

/// Finite points only; a non-finite or non-positive SD is no SD.
fn clean(points: &[Point]) -> Vec<Point> {
    points
        .iter()
        .filter(|p| p.x.is_finite() && p.y.is_finite())
        .map(|p| Point {
            sd: p.sd.filter(|d| d.is_finite() && *d > 0.0),
            ..*p
        })
        .collect()
}

/// The y range of every point, with 0 always inside: up to the top of the
/// error bars, down to the lowest value only (an error bar of a positive
/// value stops at 0, so that an MAE's axis never shows negative degrees).
fn y_range<'p>(points: impl Iterator<Item = &'p Point>) -> (Vec<f64>, f64, f64) {
    let (mut lo, mut hi) = (0.0_f64, 0.0_f64);
    for p in points {
        lo = lo.min(p.y);
        hi = hi.max(p.y + p.sd.unwrap_or(0.0));
    }
    nice_range(lo, hi, 5)
}

/// The SVG text of a line plot (see [`Figure`]).
pub fn line_plot_svg(p: &Figure<'_>) -> String {
    let series: Vec<Vec<Point>> = p.series.iter().map(|s| clean(&s.points)).collect();
    let refs: Vec<Vec<Point>> = p.reference.iter().map(|s| clean(&s.points)).collect();
    let all = || series.iter().chain(&refs).flatten();
    let names: Vec<&str> = p
        .series
        .iter()
        .chain(p.reference)
        .map(|s| s.name.as_str())
        .collect();
    let f = frame(560.0, 320.0, &names);
    let (y_ticks, y0, y1) = y_range(all());
    let y_of = |v: f64| f.top + f.h * (1.0 - (v - y0) / (y1 - y0));
    // x: the data's range padded by 4 % each side, so no marker sits on the axis.
    let (lo, hi) = all().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), q| {
        (lo.min(q.x), hi.max(q.x))
    });
    let (x0, x1) = if !lo.is_finite() {
        (0.0, 1.0)
    } else if hi - lo < 1e-12 {
        (lo - 1.0, hi + 1.0)
    } else {
        let pad = 0.04 * (hi - lo);
        (lo - pad, hi + pad)
    };
    let x_of = |v: f64| f.left + f.w * (v - x0) / (x1 - x0);
    let mut s = open(&f, p.title, p.x_title, p.y_title, &y_ticks, &y_of);
    let step = nice_step(x1 - x0, 7);
    let bottom = f.top + f.h;
    let first = (x0 / step).ceil() as i64;
    let last = (x1 / step).floor() as i64;
    for i in first..=last.min(first + 40) {
        let t = i as f64 * step;
        x_tick(&mut s, x_of(t), bottom, Some(&tick_label(t)));
    }
    let mut entries = Vec::new();
    for (k, (pts, reference)) in series
        .iter()
        .map(|p| (p, false))
        .chain(refs.iter().map(|p| (p, true)))
        .enumerate()
    {
        let r = k.saturating_sub(series.len());
        let color = if reference { ref_color(r) } else { tab10_hex(k) };
        let mut sorted = pts.clone();
        sorted.sort_by(|a, b| a.x.total_cmp(&b.x));
        let class = if reference { "reference" } else { "line" };
        let _ = writeln!(s, r#"<g class="series" data-series="{}">"#, esc(names[k]));
        if sorted.len() > 1 {
            let at: Vec<String> = sorted
                .iter()
                .map(|q| format!("{:.2},{:.2}", x_of(q.x), y_of(q.y)))
                .collect();
            let d = if reference {
                format!(r#" stroke-dasharray="{}""#, dash(r))
            } else {
                String::new()
            };
            let _ = writeln!(
                s,
                r#"<polyline class="{class}" points="{}" fill="none" stroke="{color}" stroke-width="2"{d}/>"#,
                at.join(" ")
            );
        }
        for q in &sorted {
            if let Some(sd) = q.sd {
                error_bar(
                    &mut s,
                    x_of(q.x),
                    y_of((q.y - sd).max(y0)),
                    y_of(q.y + sd),
                    &color,
                );
            }
            let mark = if reference { "ref-point" } else { "point" };
            marker(&mut s, mark, x_of(q.x), y_of(q.y), &color, reference);
        }
        let _ = writeln!(s, "</g>");
        let dashed = reference.then(|| dash(r));
        entries.push((names[k], Swatch::Line { color, dashed }));
    }
    legend(&mut s, &f, &entries);
    s.push_str("</svg>\n");
    s
}

/// Writes a line plot (see [`Figure`]) as SVG, atomically.
pub fn line_plot(path: &Path, p: &Figure<'_>) -> std::io::Result<()> {
    write_atomic(path, line_plot_svg(p).as_bytes())
}

/// The SVG text of a grouped bar chart (see [`BarPlot`]).
pub fn bar_plot_svg(b: &BarPlot<'_>) -> String {
    let p = &b.figure;
    let n_cat = b.categories.len().max(1);
    let all: Vec<(&PlotSeries, bool)> = p
        .series
        .iter()
        .map(|s| (s, false))
        .chain(p.reference.iter().map(|s| (s, true)))
        .collect();
    let cleaned: Vec<Vec<Point>> = all
        .iter()
        .map(|(s, _)| {
            clean(&s.points)
                .into_iter()
                .filter(|q| q.x >= 0.0 && (q.x as usize) < n_cat && q.x.fract() == 0.0)
                .collect()
        })
        .collect();
    let names: Vec<&str> = all.iter().map(|(s, _)| s.name.as_str()).collect();
    // Each group holds one bar per series: at least 12 px a bar, 600 px in all.
    let bars = all.len().max(1) as f64;
    let group = (bars * 14.0 + 12.0).max(600.0 / n_cat as f64);
    let f = frame((group * n_cat as f64).min(1100.0), 320.0, &names);
    let slot = f.w / n_cat as f64;
    let bw = slot * 0.8 / bars;
    let (y_ticks, y0, y1) = y_range(cleaned.iter().flatten());
    let y_of = |v: f64| f.top + f.h * (1.0 - (v - y0) / (y1 - y0));
    let mut s = open(&f, p.title, p.x_title, p.y_title, &y_ticks, &y_of);
    let bottom = f.top + f.h;
    let longest = b.categories.iter().map(|c| c.chars().count()).max().unwrap_or(1) as f64;
    let every = if slot >= longest * 0.62 * style::TICK as f64 + 3.0 {
        1
    } else {
        2
    };
    for (c, label) in b.categories.iter().enumerate() {
        let x = f.left + (c as f64 + 0.5) * slot;
        x_tick(&mut s, x, bottom, (c % every == 0).then_some(label.as_str()));
    }
    let zero = y_of(0.0);
    let mut entries = Vec::new();
    for (k, ((series, reference), pts)) in all.iter().zip(&cleaned).enumerate() {
        let r = k.saturating_sub(p.series.len());
        let color = if *reference { ref_color(r) } else { tab10_hex(k) };
        let (class, paint) = if *reference {
            (
                "ref-bar",
                format!(r##"fill="#ffffff" stroke="{color}" stroke-width="1.5" stroke-dasharray="4 2""##),
            )
        } else {
            ("bar", format!(r#"fill="{color}""#))
        };
        let _ = writeln!(s, r#"<g class="series" data-series="{}">"#, esc(&series.name));
        for q in pts {
            let c = q.x as usize;
            let x = f.left + c as f64 * slot + slot * 0.1 + k as f64 * bw;
            let top = y_of(q.y);
            // A zero is a hairline on the axis, so it reads as "0", not "missing".
            let (y, h) = if (top - zero).abs() < 1.0 {
                (zero - 1.0, 1.0)
            } else {
                (top.min(zero), (top - zero).abs())
            };
            let _ = writeln!(
                s,
                r#"<rect class="{class}" data-cat="{c}" x="{x:.2}" y="{y:.2}" width="{bw:.2}" height="{h:.2}" {paint}><title>{}: {}</title></rect>"#,
                esc(&series.name),
                tick_label(q.y)
            );
            let cx = x + bw / 2.0;
            let mut label_y = top.min(zero) - 4.0;
            if let Some(sd) = q.sd {
                error_bar(&mut s, cx, y_of((q.y - sd).max(y0)), y_of(q.y + sd), style::INK);
                label_y = label_y.min(y_of(q.y + sd) - 4.0);
            }
            if b.value_labels {
                let _ = writeln!(
                    s,
                    r#"<text class="bar-value" x="{cx:.2}" y="{label_y:.2}" font-size="{}" text-anchor="middle">{:.2}</text>"#,
                    style::TICK - 2,
                    q.y
                );
            }
        }
        let _ = writeln!(s, "</g>");
        entries.push((
            names[k],
            Swatch::Bar {
                color,
                reference: *reference,
            },
        ));
    }
    legend(&mut s, &f, &entries);
    s.push_str("</svg>\n");
    s
}

/// Writes a grouped bar chart (see [`BarPlot`]) as SVG, atomically.
pub fn bar_plot(path: &Path, p: &BarPlot<'_>) -> std::io::Result<()> {
    write_atomic(path, bar_plot_svg(p).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The numeric attribute `name` of an SVG element's text.
    fn attr(el: &str, name: &str) -> f64 {
        let key = format!(" {name}=\"");
        let i = el.find(&key).unwrap_or_else(|| panic!("no {name} in {el}")) + key.len();
        let j = el[i..].find('"').unwrap() + i;
        el[i..j].parse().unwrap()
    }

    /// Every element whose class is exactly `class`.
    fn elements<'s>(svg: &'s str, class: &str) -> Vec<&'s str> {
        let key = format!("class=\"{class}\"");
        svg.lines().filter(|l| l.contains(&key)).collect()
    }

    fn pt(x: f64, y: f64, sd: Option<f64>) -> Point {
        Point { x, y, sd }
    }

    fn fig<'a>(series: &'a [PlotSeries], reference: &'a [PlotSeries]) -> Figure<'a> {
        Figure {
            title: "MAE",
            x_title: "x",
            y_title: "MAE (°)",
            series,
            reference,
        }
    }

    fn series(name: &str, points: Vec<Point>) -> PlotSeries {
        PlotSeries {
            name: name.into(),
            points,
        }
    }

    /// The legend's entries all sit right of the plot area.
    fn legend_clear_of_plot(svg: &str, entries: usize) {
        let area = elements(svg, "plot-area");
        assert_eq!(area.len(), 1);
        let right = attr(area[0], "x") + attr(area[0], "width");
        let legend = elements(svg, "legend-entry");
        assert_eq!(legend.len(), entries);
        for e in legend {
            assert!(attr(e, "x") > right + 20.0, "legend over the plot: {e}");
        }
        let width = attr(svg.lines().next().unwrap(), "width");
        assert!(width > right + 60.0, "legend inside the document");
    }

    #[test]
    fn bar_plot_gives_one_bar_per_series_and_category_heights_proportional() {
        let cats: Vec<String> = ["4x4", "3x3", "2x2"].iter().map(|s| s.to_string()).collect();
        let ours = series(
            "ours",
            vec![pt(0.0, 1.0, None), pt(1.0, 2.0, None), pt(2.0, 4.0, Some(0.5))],
        );
        let other = series(
            "other",
            vec![pt(0.0, 3.0, None), pt(1.0, 0.5, None), pt(2.0, 1.5, None)],
        );
        let paper = series("paper", vec![pt(0.0, 1.67, None), pt(2.0, 5.88, None)]);
        let svg = bar_plot_svg(&BarPlot {
            figure: fig(&[ours, other], &[paper]),
            categories: &cats,
            value_labels: true,
        });
        let bars = elements(&svg, "bar");
        assert_eq!(bars.len(), 2 * 3, "one bar per series and category");
        let refs = elements(&svg, "ref-bar");
        assert_eq!(refs.len(), 2);
        assert!(refs.iter().all(|r| r.contains("stroke-dasharray")));
        // Heights proportional to the values (y starts at 0).
        let h: Vec<f64> = bars.iter().map(|b| attr(b, "height")).collect();
        assert!(
            (h[1] / h[0] - 2.0).abs() < 1e-3 && (h[2] / h[0] - 4.0).abs() < 1e-3,
            "{h:?}"
        );
        assert!((h[3] / h[0] - 3.0).abs() < 1e-3);
        assert!((attr(refs[1], "height") / h[0] - 5.88).abs() < 1e-2);
        // Bars stand on the same baseline.
        let base = attr(bars[0], "y") + h[0];
        for b in bars.iter().chain(&refs) {
            assert!((attr(b, "y") + attr(b, "height") - base).abs() < 0.02, "{b}");
        }
        // Each group's bars sit side by side in series order, inside the
        // slot of the category's tick (ticks are a slot apart).
        let ticks = elements(&svg, "tick-x");
        assert_eq!(ticks.len(), 3);
        let slot = attr(ticks[1], "x1") - attr(ticks[0], "x1");
        for (c, tick) in ticks.iter().enumerate() {
            let mut group: Vec<&&str> = bars
                .iter()
                .chain(&refs)
                .filter(|b| attr(b, "data-cat") == c as f64)
                .collect();
            group.sort_by(|a, b| attr(a, "x").total_cmp(&attr(b, "x")));
            for w in group.windows(2) {
                assert!(attr(w[0], "x") + attr(w[0], "width") <= attr(w[1], "x") + 0.01);
            }
            let tick = attr(tick, "x1");
            for b in group {
                let (x, w) = (attr(b, "x"), attr(b, "width"));
                assert!(x >= tick - slot / 2.0 && x + w <= tick + slot / 2.0, "{b}");
            }
        }
        assert_eq!(elements(&svg, "errorbar").len(), 1, "the one SD given");
        // An SD larger than the value stops at the axis: no negative MAE.
        let wide = series("wide", vec![pt(0.0, 0.5, Some(2.0))]);
        let clipped = bar_plot_svg(&BarPlot {
            figure: fig(&[wide], &[]),
            categories: &cats[..1],
            value_labels: false,
        });
        assert!(!clipped.contains(">-"), "no negative tick: {clipped}");
        let err = elements(&clipped, "errorbar")[0];
        let bar = elements(&clipped, "bar")[0];
        let axis = attr(bar, "y") + attr(bar, "height");
        assert!(
            err.contains(&format!(" {axis:.2}L")),
            "{err} should start at {axis:.2}"
        );
        assert_eq!(elements(&svg, "bar-value").len(), 8);
        assert!(svg.contains(">5.88</text>"));
        legend_clear_of_plot(&svg, 3);
    }

    #[test]
    fn line_plot_draws_error_bars_and_a_dashed_reference() {
        let ours = series(
            "ours",
            vec![
                pt(10.0, 3.0, Some(0.2)),
                pt(0.0, 1.7, Some(0.1)),
                pt(1.0, 1.9, None),
            ],
        );
        let paper = series(
            "paper",
            vec![pt(0.0, 1.67, None), pt(1.0, 1.9, None), pt(10.0, 3.0, None)],
        );
        let svg = line_plot_svg(&fig(&[ours], &[paper]));
        assert_eq!(elements(&svg, "line").len(), 1);
        assert_eq!(elements(&svg, "point").len(), 3);
        assert_eq!(
            elements(&svg, "errorbar").len(),
            2,
            "the SDs given, none for None"
        );
        let reference = elements(&svg, "reference");
        assert_eq!(reference.len(), 1);
        assert!(reference[0].contains("stroke-dasharray"));
        assert_eq!(elements(&svg, "ref-point").len(), 3);
        // Points are joined in x order; an error bar spans y ± sd.
        let line = elements(&svg, "line")[0];
        let xs: Vec<f64> = line
            .split("points=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap()
            .split(' ')
            .map(|p| p.split(',').next().unwrap().parse().unwrap())
            .collect();
        assert!(xs.windows(2).all(|w| w[0] < w[1]), "{xs:?}");
        let points = elements(&svg, "point");
        let cy = |i: usize| attr(points[i], "cy");
        // 1.7 -> 3.0 spans 1.3 units; the 0.2 SD bar spans 0.4 units.
        let unit = (cy(0) - cy(2)) / 1.3;
        let bar = elements(&svg, "errorbar")[1];
        let ys: Vec<f64> = bar
            .split("d=\"M")
            .nth(1)
            .unwrap()
            .split('L')
            .take(2)
            .map(|p| {
                p.split(' ')
                    .nth(1)
                    .unwrap()
                    .split('M')
                    .next()
                    .unwrap()
                    .parse()
                    .unwrap()
            })
            .collect();
        assert!(
            ((ys[0] - ys[1]).abs() / unit - 0.4).abs() < 1e-2,
            "{ys:?} unit {unit}"
        );
        legend_clear_of_plot(&svg, 2);
        // One series and no reference: no legend, no error bars without SDs.
        let plain = series("a", vec![pt(0.0, 1.0, None), pt(1.0, 2.0, None)]);
        let svg = line_plot_svg(&fig(&[plain], &[]));
        assert!(elements(&svg, "legend-entry").is_empty());
        assert!(elements(&svg, "errorbar").is_empty());
    }

    #[test]
    fn non_finite_inputs_give_no_nan_in_the_svg() {
        let bad = series(
            "<bad & worse>",
            vec![
                pt(f64::NAN, 1.0, None),
                pt(1.0, f64::INFINITY, Some(1.0)),
                pt(2.0, 1.0, Some(f64::NAN)),
                pt(3.0, f64::NEG_INFINITY, None),
            ],
        );
        let empty = series("empty", vec![]);
        for refs in [vec![], vec![bad.clone()]] {
            for s in [vec![bad.clone()], vec![empty.clone()], vec![]] {
                let line = line_plot_svg(&fig(&s, &refs));
                let cats = vec!["a".to_string(), "b".to_string()];
                let bars = bar_plot_svg(&BarPlot {
                    figure: fig(&s, &refs),
                    categories: &cats,
                    value_labels: true,
                });
                for svg in [line, bars] {
                    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
                    let lower = svg.to_lowercase();
                    assert!(!lower.contains("nan") && !lower.contains("inf"), "{svg}");
                    assert!(!svg.contains("<bad"), "names are escaped");
                }
            }
        }
        // The one finite point of the bar series is drawn, without an SD.
        let cats: Vec<String> = (0..4).map(|c| c.to_string()).collect();
        let svg = bar_plot_svg(&BarPlot {
            figure: fig(&[bad], &[]),
            categories: &cats,
            value_labels: false,
        });
        assert_eq!(elements(&svg, "bar").len(), 1);
        assert!(elements(&svg, "errorbar").is_empty());
    }

    #[test]
    fn nice_range_covers_negative_and_positive_values() {
        let (t, lo, hi) = nice_range(-1.2, 3.7, 5);
        assert_eq!((lo, hi), (-2.0, 4.0));
        assert_eq!(t, vec![-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0]);
        let (_, lo, hi) = nice_range(f64::NAN, 1.0, 5);
        assert_eq!((lo, hi), (0.0, 1.0));
        let (_, lo, hi) = nice_range(2.0, 2.0, 5);
        assert!(lo <= 0.0 && hi >= 2.0);
    }
}
