//! Shared SVG plotting: line charts (signals over time, sweep curves), spike
//! rasters and heatmaps (confusion matrices, spike images). Plots are written
//! atomically like every report file.

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
        // Empty and constant data must not panic.
        line_chart(&p, "t", "x", "y", &[]).unwrap();
        heatmap(&h, "c", &[], &[], &[]).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
