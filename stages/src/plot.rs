//! Shared SVG plotting: line charts (signals over time, sweep curves), spike
//! rasters and heatmaps (confusion matrices, spike images), grouped bars, and
//! scatter charts with a Pareto frontier (accuracy against time). Plots are
//! written atomically like every report file.

use palpate_core::output::write_atomic;
use plotters::prelude::*;
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
            .caption(title, ("sans-serif", 20))
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
            let color = Palette99::pick(k).to_rgba();
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

/// Writes a heatmap of `values[row][col]` as SVG, with row and column labels.
pub fn heatmap(
    path: &Path,
    title: &str,
    row_labels: &[String],
    col_labels: &[String],
    values: &[Vec<f64>],
) -> std::io::Result<()> {
    let rows = values.len();
    let cols = values.first().map_or(0, Vec::len);
    let max = values
        .iter()
        .flatten()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0_f64, f64::max);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (700, 640)).into_drawing_area();
        root.fill(&WHITE).map_err(err(path))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(50)
            .y_label_area_size(60)
            .build_cartesian_2d(0..cols, 0..rows)
            .map_err(err(path))?;
        let xl = |c: &usize| col_labels.get(*c).cloned().unwrap_or_default();
        let yl = |r: &usize| {
            row_labels
                .get(rows.saturating_sub(1 + *r))
                .cloned()
                .unwrap_or_default()
        };
        chart
            .configure_mesh()
            .disable_mesh()
            .x_labels(cols.max(1))
            .y_labels(rows.max(1))
            .x_label_formatter(&xl)
            .y_label_formatter(&yl)
            .draw()
            .map_err(err(path))?;
        chart
            .draw_series(values.iter().enumerate().flat_map(|(r, row)| {
                row.iter().enumerate().map(move |(c, &v)| {
                    let t = if max > 0.0 && v.is_finite() { v / max } else { 0.0 };
                    let shade = (255.0 * (1.0 - t)) as u8;
                    let y = rows - 1 - r;
                    Rectangle::new([(c, y), (c + 1, y + 1)], RGBColor(shade, shade, 255).filled())
                })
            }))
            .map_err(err(path))?;
        root.present().map_err(err(path))?;
    }
    write_atomic(path, svg.as_bytes())
}

/// Writes a grouped bar chart as SVG: one group per category, one bar per series.
pub fn bar_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    categories: &[String],
    series: &[(&str, Vec<f64>)],
) -> std::io::Result<()> {
    let n_cat = categories.len().max(1);
    let n_ser = series.len().max(1);
    let y_max = series
        .iter()
        .flat_map(|s| s.1.iter())
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0_f64, f64::max);
    let y_max = if y_max > 0.0 { y_max * 1.1 } else { 1.0 };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 450)).into_drawing_area();
        root.fill(&WHITE).map_err(err(path))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..n_cat as f64, 0.0..y_max)
            .map_err(err(path))?;
        let label = |x: &f64| {
            let i = x.floor() as usize;
            if (x - i as f64 - 0.5).abs() < 1e-6 {
                categories.get(i).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        };
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(2 * n_cat + 1)
            .x_label_formatter(&label)
            .x_desc(x_label)
            .y_desc(y_label)
            .draw()
            .map_err(err(path))?;
        let width = 0.8 / n_ser as f64;
        for (k, (name, values)) in series.iter().enumerate() {
            let color = Palette99::pick(k).to_rgba();
            chart
                .draw_series(
                    values
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| v.is_finite())
                        .map(|(i, &v)| {
                            let x0 = i as f64 + 0.1 + k as f64 * width;
                            Rectangle::new([(x0, 0.0), (x0 + width, v)], color.filled())
                        }),
                )
                .map_err(err(path))?
                .label(*name)
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], color.filled()));
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
            b.caption(c.title, ("sans-serif", 20))
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
    fn line_chart_and_heatmap_write_svg() {
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
        let h = dir.join("heat.svg");
        heatmap(
            &h,
            "c",
            &["a".into(), "b".into()],
            &["x".into(), "y".into()],
            &[vec![1.0, 0.0], vec![0.0, 0.0]],
        )
        .unwrap();
        assert!(std::fs::read_to_string(&h).unwrap().contains("<rect"));
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
        heatmap(&h, "c", &[], &[], &[]).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
