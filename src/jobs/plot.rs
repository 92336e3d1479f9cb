//! PNG plots (plotters, bitmap backend, text through fontconfig). One
//! generic x–y chart ([`chart`]) serves every figure; writes are atomic.
//!
//! A chart's legend sits in a column right of the plot area (never over the
//! data) and shows each series as drawn: solid or dashed, with its marker.
//! A log axis is labelled at every decade (and at 2 and 5 where the range
//! holds fewer than three decades), with light grid lines at 2…9 × each
//! decade.

use crate::error::Result;
use crate::forward::profile::ProfileDoc;
use plotters::prelude::*;
use std::path::Path;

/// How a series is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Style {
    Line,
    Dashed,
    Points,
}

/// One series of a chart: points (x, y) with optional ±error bars.
#[derive(Clone, Debug)]
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
    pub errors: Option<Vec<f64>>,
    pub style: Style,
    /// Index into the palette.
    pub color: usize,
    /// A line's points drawn as markers too, each with this text beside it
    /// (`None`: a plain line; empty strings: markers without text).
    pub marks: Option<Vec<String>>,
}

impl Series {
    pub fn line(label: impl Into<String>, points: Vec<(f64, f64)>, color: usize) -> Self {
        Series {
            label: label.into(),
            points,
            errors: None,
            style: Style::Line,
            color,
            marks: None,
        }
    }
    pub fn dashed(label: impl Into<String>, points: Vec<(f64, f64)>, color: usize) -> Self {
        Series {
            style: Style::Dashed,
            ..Self::line(label, points, color)
        }
    }
    pub fn points(
        label: impl Into<String>,
        points: Vec<(f64, f64)>,
        errors: Option<Vec<f64>>,
        color: usize,
    ) -> Self {
        Series {
            label: label.into(),
            points,
            errors,
            style: Style::Points,
            color,
            marks: None,
        }
    }

    /// The series with a marker at each point and `labels[k]` beside point
    /// k.
    pub fn marked(self, labels: Vec<String>) -> Self {
        Series {
            marks: Some(labels),
            ..self
        }
    }
}

/// Axes of a chart.
#[derive(Clone, Debug)]
pub struct Axes {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
}

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn range(v: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for x in v.filter(|x| x.is_finite() && (!log || *x > 0.0)) {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    if !lo.is_finite() {
        return (if log { 1e-3 } else { 0.0 }, 1.0);
    }
    if log {
        (lo / 1.5, hi * 1.5)
    } else {
        let pad = 0.05 * (hi - lo).max(1e-12);
        (lo - pad, hi + pad)
    }
}

/// The bold (labelled) and light grid values of a log axis over [lo, hi]:
/// every decade bold, 2…9 × each decade light; where fewer than three
/// decades lie inside, 2 and 5 × each decade are bold too.
pub fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>) {
    let (mut bold, mut light) = (Vec::new(), Vec::new());
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return (bold, light);
    }
    let (a, b) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    let inside = (a..=b)
        .filter(|&k| (lo..=hi).contains(&10f64.powi(k)))
        .count();
    for k in a..=b {
        let decade = 10f64.powi(k);
        for m in 1..10 {
            let v = m as f64 * decade;
            if !(lo..=hi).contains(&v) {
                continue;
            }
            if m == 1 || (inside < 3 && (m == 2 || m == 5)) {
                bold.push(v);
            } else {
                light.push(v);
            }
        }
    }
    (bold, light)
}

/// Grid lines: bold at the labelled values, light between.
const BOLD_GRID: RGBColor = RGBColor(200, 200, 200);
const LIGHT_GRID: RGBColor = RGBColor(236, 236, 236);

/// Width in pixels of the legend column for `series` (0 without labels).
fn legend_width(series: &[Series]) -> u32 {
    let chars = series
        .iter()
        .filter(|s| !s.label.is_empty())
        .map(|s| s.label.chars().count())
        .max();
    chars.map_or(0, |c| (c as u32 * 8 + 60).clamp(110, 300))
}

/// The chart body on any plotters backend (`$root` a drawing area).
macro_rules! draw_chart {
    ($root:expr, $axes:expr, $series:expr, $ranges:expr) => {{
        let (root, axes, series) = ($root, $axes, $series);
        let (x0, x1, y0, y1): (f64, f64, f64, f64) = $ranges;
        let (w, _) = root.dim_in_pixel();
        let legend_w = legend_width(series);
        let (plot_area, legend_area) = root.split_horizontally(w - legend_w);
        let (x_bold, x_light) = log_ticks(x0, x1);
        let (y_bold, y_light) = log_ticks(y0, y1);
        macro_rules! builder {
            () => {
                ChartBuilder::on(&plot_area)
                    .caption(&axes.title, ("sans-serif", 20))
                    .margin(15)
                    .x_label_area_size(45)
                    .y_label_area_size(75)
            };
        }
        macro_rules! body {
            ($chart:expr) => {{
                let mut chart = $chart;
                chart
                    .configure_mesh()
                    .x_desc(axes.x_label.as_str())
                    .y_desc(axes.y_label.as_str())
                    .x_label_formatter(&|x| fmt_tick(*x, axes.log_x))
                    .y_label_formatter(&|y| fmt_tick(*y, axes.log_y))
                    .bold_line_style(BOLD_GRID)
                    .light_line_style(LIGHT_GRID)
                    .label_style(("sans-serif", 14))
                    .axis_desc_style(("sans-serif", 15))
                    .draw()?;
                for s in series {
                    let color = PALETTE[s.color % PALETTE.len()];
                    let visible = |p: &(f64, f64)| {
                        p.0.is_finite()
                            && p.1.is_finite()
                            && (!axes.log_x || p.0 > 0.0)
                            && (!axes.log_y || p.1 > 0.0)
                    };
                    let pts: Vec<(f64, f64)> = s.points.iter().cloned().filter(visible).collect();
                    match s.style {
                        Style::Line => {
                            chart
                                .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))?;
                        }
                        Style::Dashed => {
                            chart.draw_series(DashedLineSeries::new(
                                pts.clone(),
                                8,
                                5,
                                color.stroke_width(2),
                            ))?;
                        }
                        Style::Points => {
                            chart.draw_series(
                                pts.iter().map(|p| Circle::new(*p, 3, color.filled())),
                            )?;
                        }
                    }
                    if let Some(marks) = &s.marks {
                        // Solid lines' texts above right of their points,
                        // dashed lines' below left, so that two curves'
                        // texts part.
                        let (dx, dy) = if s.style == Style::Dashed {
                            (-28, 4)
                        } else {
                            (6, -17)
                        };
                        let marked = s.points.iter().zip(marks).filter(|(p, _)| visible(p));
                        chart.draw_series(marked.map(|(p, text)| {
                            EmptyElement::at(*p)
                                + Circle::new((0, 0), 4, color.filled())
                                + Text::new(text.clone(), (dx, dy), ("sans-serif", 13))
                        }))?;
                    }
                    if let Some(err) = &s.errors {
                        let bars = s.points.iter().zip(err).filter(|(p, e)| {
                            p.1.is_finite() && e.is_finite() && (!axes.log_y || p.1 - **e > 0.0)
                        });
                        chart.draw_series(bars.map(|(p, e)| {
                            ErrorBar::new_vertical(p.0, p.1 - e, p.1, p.1 + e, color.filled(), 4)
                        }))?;
                    }
                }
            }};
        }
        match (axes.log_x, axes.log_y) {
            (true, true) => body!(
                builder!().build_cartesian_2d(
                    (x0..x1)
                        .log_scale()
                        .with_key_points(x_bold)
                        .with_light_points(x_light),
                    (y0..y1)
                        .log_scale()
                        .with_key_points(y_bold)
                        .with_light_points(y_light),
                )?
            ),
            (true, false) => body!(
                builder!().build_cartesian_2d(
                    (x0..x1)
                        .log_scale()
                        .with_key_points(x_bold)
                        .with_light_points(x_light),
                    y0..y1
                )?
            ),
            (false, true) => body!(
                builder!().build_cartesian_2d(
                    x0..x1,
                    (y0..y1)
                        .log_scale()
                        .with_key_points(y_bold)
                        .with_light_points(y_light),
                )?
            ),
            (false, false) => body!(builder!().build_cartesian_2d(x0..x1, y0..y1)?),
        }
        // The legend: one row per labelled series, drawn as in the chart,
        // from the top of the plot area down.
        let mut y = 60;
        for s in series.iter().filter(|s| !s.label.is_empty()) {
            let color = PALETTE[s.color % PALETTE.len()];
            let stroke = color.stroke_width(2);
            match s.style {
                Style::Line => {
                    legend_area.draw(&PathElement::new(vec![(6, y), (40, y)], stroke))?;
                }
                Style::Dashed => {
                    for x in [6, 19, 32] {
                        legend_area.draw(&PathElement::new(vec![(x, y), (x + 8, y)], stroke))?;
                    }
                }
                Style::Points => {}
            }
            if s.marks.is_some() || s.style == Style::Points {
                legend_area.draw(&Circle::new((23, y), 4, color.filled()))?;
            }
            legend_area.draw(&Text::new(s.label.clone(), (48, y - 8), ("sans-serif", 15)))?;
            y += 24;
        }
        Ok(())
    }};
}

/// The data ranges of a chart.
fn chart_ranges(axes: &Axes, series: &[Series]) -> (f64, f64, f64, f64) {
    let xs = series.iter().flat_map(|s| s.points.iter().map(|p| p.0));
    let ys = series.iter().flat_map(|s| s.points.iter().map(|p| p.1));
    let (x0, x1) = range(xs, axes.log_x);
    let (y0, y1) = range(ys, axes.log_y);
    (x0, x1, y0, y1)
}

/// The size of a chart: 900 × 600 pixels and the legend column.
fn chart_size(series: &[Series]) -> (u32, u32) {
    (900 + legend_width(series), 600)
}

/// Draws an x–y chart to `path` (PNG, sized by `chart_size`).
pub fn chart(path: &Path, axes: &Axes, series: &[Series]) -> Result<()> {
    let r = chart_ranges(axes, series);
    png(path, chart_size(series), |root| {
        draw_chart!(root, axes, series, r)
    })
}

/// [`chart`] as SVG, written atomically.
pub fn chart_svg(path: &Path, axes: &Axes, series: &[Series]) -> Result<()> {
    let r = chart_ranges(axes, series);
    atomic(path, |tmp| {
        let root = SVGBackend::new(tmp, chart_size(series)).into_drawing_area();
        root.fill(&WHITE)?;
        let drawn: DrawResult = draw_chart!(&root, axes, series, r);
        drawn?;
        root.present()?;
        Ok(())
    })
}

/// What a drawing closure returns.
type DrawResult = std::result::Result<(), Box<dyn std::error::Error>>;

/// Runs `draw` on a temporary sibling of `path` and renames it into place,
/// so a failure leaves nothing behind (the error names the file).
fn atomic(path: &Path, draw: impl FnOnce(&Path) -> DrawResult) -> Result<()> {
    crate::jobs::store::write_atomic_path(path, draw)
}

/// Draws a PNG of `size` pixels to `path`: `draw` paints on a white root
/// area, written atomically ([`atomic`]).
fn png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> DrawResult,
) -> Result<()> {
    atomic(path, |tmp| {
        let root = BitMapBackend::new(tmp, size).into_drawing_area();
        root.fill(&WHITE)?;
        draw(&root)?;
        root.present()?;
        Ok(())
    })
}

fn fmt_tick(v: f64, log: bool) -> String {
    if log && (1e-3..1e4).contains(&v) {
        // Decimals enough for one significant figure: 0.002, 0.1, 5, 100.
        let decimals = (-v.log10().floor()).max(0.0) as usize;
        format!("{v:.decimals$}")
    } else if log || (v != 0.0 && (v.abs() < 1e-2 || v.abs() >= 1e4)) {
        format!("{v:.0e}")
    } else {
        format!("{v:.3}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_string()
    }
}

/// Geometric bin centres and the points of a ring-average array (inner disk
/// and empty bins skipped).
pub fn ring_points(edges: &[f64], v: &[f64], e: &[f64]) -> (Vec<(f64, f64)>, Vec<f64>) {
    (1..v.len())
        .filter(|&k| v[k] > 0.0)
        .map(|k| (((edges[k] * edges[k + 1]).sqrt(), v[k]), e[k]))
        .unzip()
}

/// Log-log plot of the radial density p(r) = 2πr·R(r) of a profile, split
/// into single (R₁) and multiple (Rₘ) scattering, with ±1 standard errors.
pub fn profile_plot(doc: &ProfileDoc, path: &Path) -> Result<()> {
    let b = &doc.bins;
    let (p1, e1) = ring_points(&b.edges, &b.p_1, &b.p_1_stderr);
    let (pm, em) = ring_points(&b.edges, &b.p_m, &b.p_m_stderr);
    let m = &doc.config.medium;
    let axes = Axes {
        title: format!(
            "p(r) = 2πr·R(r): α = {}, g = {}, η = {}, {} paths",
            m.alpha, m.g, m.eta, doc.paths
        ),
        x_label: "r (MFP)".into(),
        y_label: "p(r) (1/MFP)".into(),
        log_x: true,
        log_y: true,
    };
    chart(
        path,
        &axes,
        &[
            Series::points("R₁ (single)", p1, Some(e1), 0),
            Series::points("Rₘ (multiple)", pm, Some(em), 1),
        ],
    )
}

/// One panel of a heat-map grid: `values[i * ny + j]` over an nx × ny grid
/// (i along x, j along y, y drawn upward).
pub struct Panel {
    pub title: String,
    pub nx: usize,
    pub ny: usize,
    pub values: Vec<f64>,
}

/// Draws panels in a grid of `cols` columns (PNG), each with its own colour
/// scale: a perceptual ramp (dark blue → yellow) of sqrt(value / max).
pub fn heatmaps(path: &Path, title: &str, panels: &[Panel], cols: usize) -> Result<()> {
    let cols = cols.max(1);
    let rows = panels.len().div_ceil(cols);
    let (pw, ph) = (220u32, 170u32);
    png(path, (pw * cols as u32, ph * rows as u32 + 40), |root| {
        let (head, body) = root.split_vertically(40);
        head.titled(title, ("sans-serif", 20))?;
        let areas = body.split_evenly((rows, cols));
        for (p, area) in panels.iter().zip(areas) {
            let (cap, plot) = area.split_vertically(20);
            cap.titled(&p.title, ("sans-serif", 13))?;
            let plot = plot.margin(2, 6, 6, 6);
            let (w, h) = plot.dim_in_pixel();
            let max = p.values.iter().copied().fold(0.0f64, f64::max).max(1e-300);
            for i in 0..p.nx {
                for j in 0..p.ny {
                    let v = (p.values[i * p.ny + j].max(0.0) / max).sqrt();
                    let x0 = (i as u32 * w / p.nx as u32) as i32;
                    let x1 = ((i as u32 + 1) * w / p.nx as u32) as i32;
                    let y1 = (h - j as u32 * h / p.ny as u32) as i32;
                    let y0 = (h - (j as u32 + 1) * h / p.ny as u32) as i32;
                    plot.draw(&Rectangle::new([(x0, y0), (x1, y1)], ramp(v).filled()))?;
                }
            }
        }
        Ok(())
    })
}

/// Colour ramp for v ∈ [0, 1]: dark blue → teal → yellow (viridis-like).
fn ramp(v: f64) -> RGBColor {
    let stops = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let x = v.clamp(0.0, 1.0) * (stops.len() - 1) as f64;
    let k = (x.floor() as usize).min(stops.len() - 2);
    let f = x - k as f64;
    let (a, b) = (stops[k], stops[k + 1]);
    let mix = |p: f64, q: f64| (p + (q - p) * f).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_axes_are_labelled_at_every_decade() {
        let (bold, light) = log_ticks(0.004, 3.0);
        assert_eq!(bold, [0.01, 0.1, 1.0]);
        let has = |v: f64| light.iter().any(|l| (l - v).abs() < 1e-12);
        assert!(has(0.005) && has(3.0) && !has(0.003));
        assert_eq!(light.len(), 6 + 8 + 8 + 2);
        // Under three decades: 2 and 5 are labelled too.
        let (bold, _) = log_ticks(0.08, 1.5);
        assert_eq!(bold, [0.1, 0.2, 0.5, 1.0]);
        assert_eq!(fmt_tick(0.002, true), "0.002");
        assert_eq!(fmt_tick(200.0, true), "200");
        assert_eq!(fmt_tick(1e-5, true), "1e-5");
    }

    #[test]
    fn a_chart_is_drawn_with_its_legend_beside_the_plot() {
        let dir = std::env::temp_dir().join(format!("svk-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let series = [
            Series::dashed("reference (paths)", vec![(0.01, 0.3), (0.1, 0.1)], 0)
                .marked(vec!["1e5".into(), "1e6".into()]),
            Series::line("learned (spp)", vec![(0.02, 0.2), (0.08, 0.05)], 1)
                .marked(vec!["4".into(), "16".into()]),
        ];
        let axes = Axes {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            log_x: true,
            log_y: true,
        };
        chart(&dir.join("c.png"), &axes, &series).unwrap();
        chart_svg(&dir.join("c.svg"), &axes, &series).unwrap();
        let svg = std::fs::read_to_string(dir.join("c.svg")).unwrap();
        let (w, _) = chart_size(&series);
        assert!(w > 900 && svg.contains(&format!("width=\"{w}\"")), "{w}");
        // (Text nodes may be written on lines of their own.)
        let compact: String = svg.split_whitespace().collect();
        assert!(
            svg.contains("reference (paths)") && compact.contains(">1e6<"),
            "{svg}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
