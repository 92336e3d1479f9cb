//! PNG plots (plotters, bitmap backend, DejaVu via fontconfig).

use crate::error::{Error, Result};
use crate::forward::profile::ProfileDoc;
use plotters::prelude::*;
use std::path::Path;

/// Log-log plot of the radial density p(r) = 2πr·R(r) of a profile, split
/// into single (R₁) and multiple (Rₘ) scattering, with ±1 standard error bars.
/// Written atomically to `path`.
pub fn profile_plot(doc: &ProfileDoc, path: &Path) -> Result<()> {
    let b = &doc.bins;
    let mid = |k: usize| (b.edges[k] * b.edges[k + 1]).sqrt();
    let series = |v: &[f64], e: &[f64]| -> Vec<(f64, f64, f64)> {
        (1..v.len())
            .filter(|&k| v[k] > 0.0)
            .map(|k| (mid(k), v[k], e[k]))
            .collect()
    };
    let single = series(&b.p_1, &b.p_1_stderr);
    let multi = series(&b.p_m, &b.p_m_stderr);
    let all: Vec<f64> = single.iter().chain(&multi).map(|p| p.1).collect();
    let ymax = all.iter().cloned().fold(1e-12, f64::max) * 3.0;
    let ymin = all
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min)
        .max(ymax * 1e-9)
        / 3.0;
    let title = format!(
        "p(r) = 2πr·R(r): α = {}, g = {}, η = {}, {} paths",
        doc.config.medium.alpha, doc.config.medium.g, doc.config.medium.eta, doc.paths
    );
    let tmp = crate::io::temp_sibling(path);
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        let root = BitMapBackend::new(&tmp, (900, 600)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(
                (b.edges[1]..*b.edges.last().unwrap_or(&100.0)).log_scale(),
                (ymin..ymax).log_scale(),
            )?;
        chart
            .configure_mesh()
            .x_desc("r (MFP)")
            .y_desc("p(r) (1/MFP)")
            .x_label_formatter(&|x| format!("{x:.0e}"))
            .y_label_formatter(&|y| format!("{y:.0e}"))
            .draw()?;
        for (data, color, label) in [
            (&single, BLUE, "R₁ (single)"),
            (&multi, RED, "Rₘ (multiple)"),
        ] {
            chart
                .draw_series(LineSeries::new(
                    data.iter().map(|p| (p.0, p.1)),
                    color.stroke_width(2),
                ))?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            chart.draw_series(data.iter().filter(|p| p.1 > p.2).map(|p| {
                ErrorBar::new_vertical(p.0, p.1 - p.2, p.1, p.1 + p.2, color.filled(), 4)
            }))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::format(path, "(plot)", e)
    })?;
    crate::io::commit(&tmp, path)
}
