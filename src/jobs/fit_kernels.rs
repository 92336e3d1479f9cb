//! `svkernel fit kernels`: per-configuration GMM fits, the joint meta-model
//! fits ([`crate::fit::meta::fit_metamodel`]), and how good the kernels are
//! where it matters — the aggregation error
//! ([`crate::fit::aggregation`]) — written as report.json and plots.

use crate::error::{Error, Result};
use crate::fit::aggregation::{AggregationRow, aggregation_row};
use crate::fit::gmm::histogram_of;
use crate::fit::lm::FitReport;
use crate::fit::meta::{
    Cell, Components, FitStart, MomentFit, PlaneMoments, StuckCell, fit_metamodel_with,
};
use crate::forward::kernel::{KernelDoc, VertexClass};
use crate::metamodel::kernel::{Gmm, manual_kernel};
use crate::metamodel::meta::MetaModelFile;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What `svkernel fit kernels` writes as report.json.
#[derive(Serialize, Deserialize)]
pub struct KernelReport {
    pub model_file: String,
    pub data_file: String,
    /// Tallies overlaid on `data_file`, in order: each replaces the cells
    /// at its albedos ([`KernelDoc::overlay`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub overlays: Vec<String>,
    pub components: Components,
    pub degree: (usize, usize),
    /// The first- and last-vertex grids' refinement the fit saw.
    #[serde(default)]
    pub vertex_refine: usize,
    /// The meta-model the joint fits started from
    /// ([`KernelFitOptions::start`]), if not the ladder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<String>,
    /// How the moment residuals were weighed ([`KernelFitOptions::moments`]).
    pub moments: MomentFit,
    pub joint: Vec<FitReport>,
    /// The cells found stuck and refitted with a width floor first, per
    /// class ([`crate::fit::meta::JointFit::stuck`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub stuck: Vec<(String, Vec<StuckCell>)>,
    /// Per-cell fit reports (or the error) per class.
    pub per_cell: Vec<(String, Vec<std::result::Result<FitReport, String>>)>,
    pub aggregation: Vec<AggregationRow>,
    pub wall_s: f64,
}

/// The polynomial degrees in ln d and √(1 − α) of a fit from the data alone
/// (the shipped model's).
pub const DEFAULT_DEGREE: (usize, usize) = (4, 3);

/// How `svkernel fit kernels` fits ([`fit_kernels`]).
#[derive(Clone, Debug)]
pub struct KernelFitOptions {
    /// Gaussian components of the all- and last-vertex kernels.
    pub components: Components,
    /// Polynomial degrees in ln d and √(1 − α). With `start`, `None` keeps
    /// the model's, and degrees as high or higher raise them.
    pub degree: Option<(usize, usize)>,
    /// Fit the first- and last-vertex histograms on a grid this many times
    /// finer than the all-vertex one, a divisor of the tally's own
    /// ([`KernelDoc::coarsen_vertices`]); `None`: the tally's grid.
    pub vertex_refine: Option<usize>,
    /// Start the joint fits from this fitted meta-model's coefficients, at
    /// its K and its degrees or `degree` (`components` is then not used): a
    /// refit of new data over the model's box
    /// ([`crate::fit::meta::FitStart::From`]). `None`: from the data alone.
    pub start: Option<std::path::PathBuf>,
    /// How the whole-plane moment residuals are weighed against the bins.
    pub moments: MomentFit,
}

/// Fits the meta-model (all and last vertices) to the tally `data[0]`,
/// with each later tally of `data` overlaid on it ([`load_tally`]), writes
/// `out` and `dir/report.json` and the plots; `progress` reports the fit's
/// steps.
pub fn fit_kernels(
    data: &[PathBuf],
    out: &Path,
    dir: &Path,
    opts: &KernelFitOptions,
    progress: bool,
) -> Result<KernelReport> {
    let start = Instant::now();
    let doc = load_tally(data, opts.vertex_refine)?;
    if doc.config.density != 1.0 {
        return Err(Error::format(
            &data[0],
            "config.density",
            "the meta-model is trained at unit density (other densities follow by scaling)",
        ));
    }
    let start_file = opts.start.as_deref().map(MetaModelFile::load).transpose()?;
    let from = match &start_file {
        Some(f) => FitStart::From {
            model: f,
            degree: opts.degree,
        },
        None => FitStart::Ladder {
            components: opts.components,
            degree: opts.degree.unwrap_or(DEFAULT_DEGREE),
        },
    };
    let (file, fit) = fit_metamodel_with(&doc, &from, opts.moments, progress)?;
    let (k, degree) = (
        Components {
            all: file.all.k,
            last: file.last.k,
        },
        (file.all.deg_x, file.all.deg_y),
    );
    crate::jobs::store::write_json_atomic(out, &file)?;
    let report = KernelReport {
        model_file: out.display().to_string(),
        data_file: data[0].display().to_string(),
        overlays: data[1..].iter().map(|p| p.display().to_string()).collect(),
        components: k,
        degree,
        vertex_refine: doc.config.grid.vertex_refine,
        start: opts.start.as_ref().map(|p| p.display().to_string()),
        moments: opts.moments,
        joint: fit.joint,
        stuck: fit.stuck,
        per_cell: fit.per_cell,
        aggregation: fit.aggregation,
        wall_s: start.elapsed().as_secs_f64(),
    };
    crate::jobs::store::write_json_atomic(&dir.join("report.json"), &report)?;
    crate::jobs::store::write_atomic(
        &dir.join("aggregation.md"),
        aggregation_table(&report.aggregation, true).as_bytes(),
    )?;
    crate::progress::step(progress, "drawing the kernel plots", || {
        kernel_plots(&doc, &file, &report.aggregation, dir)
    })?;
    Ok(report)
}

/// The kernel tally `data[0]` with each later tally of `data` overlaid on
/// it in turn ([`KernelDoc::overlay`]: its cells replace those at its
/// albedos), every first- and last-vertex histogram summed onto
/// `vertex_refine` ([`KernelDoc::coarsen_vertices`]) if given.
pub fn load_tally(data: &[PathBuf], vertex_refine: Option<usize>) -> Result<KernelDoc> {
    let load = |path: &Path| -> Result<KernelDoc> {
        let mut doc = KernelDoc::load(path)?;
        if let Some(r) = vertex_refine {
            doc.coarsen_vertices(r)?;
        }
        Ok(doc)
    };
    let (first, rest) = data
        .split_first()
        .ok_or_else(|| Error::param("kernel tallies", "none", "at least one file"))?;
    let mut doc = load(first)?;
    for path in rest {
        doc.overlay(&load(path)?, path)?;
    }
    Ok(doc)
}

/// `svkernel fit outer`: writes to `out` the meta-model of `model` carrying
/// the one of `outer`, a fit over a wider box, for the queries outside its
/// own box ([`MetaModelFile::at`]). An outer model that does not hold the
/// box, or has one of its own, or is for another medium, is an error naming
/// `outer`; `model`'s own outer model, if any, is replaced.
pub fn attach_outer(model: &Path, outer: &Path, out: &Path) -> Result<MetaModelFile> {
    let mut file = MetaModelFile::load(model)?;
    let wide = MetaModelFile::load(outer)?;
    file.outer = Some(Box::new(wide));
    crate::doc::Document::validate(&file, outer)?;
    crate::jobs::store::write_json_atomic(out, &file)?;
    Ok(file)
}

/// `svkernel fit check-kernels`: the aggregation errors and whole-plane
/// moments of the meta-model `model` against the kernel tally `data[0]`
/// (with each later tally of `data` overlaid, as in [`load_tally`]), per
/// cell of at least [`crate::fit::meta::MIN_PATHS`] effective paths,
/// without fitting. Each cell is answered as the renderer asks
/// ([`MetaModelFile::eval`]): by the model's outer one outside its box.
/// `vertex_refine` sums the tally's vertex histograms first, as in
/// [`KernelFitOptions::vertex_refine`].
pub fn check_kernels(
    data: &[PathBuf],
    model: &MetaModelFile,
    vertex_refine: Option<usize>,
) -> Result<Vec<AggregationRow>> {
    let doc = load_tally(data, vertex_refine)?;
    use rayon::prelude::*;
    let mut rows = Vec::new();
    for class in [VertexClass::All, VertexClass::Last] {
        let cells = crate::fit::meta::cells(&doc, class);
        rows.par_extend(cells.par_iter().map(|c| {
            let q = model.eval(class, c.d, c.alpha, 1.0);
            crate::fit::aggregation::aggregation_row(class, c, None, &q.gmm)
        }));
    }
    Ok(rows)
}

/// Per vertex class: cells, the mean and worst aggregation error of the
/// meta-model and of the manual kernel, the cells where the meta-model is
/// the better of the two (α_t errors in albedo units); then what the tally
/// window holds and how far the meta-model's whole-plane moments are from
/// the measured vertices'.
pub fn aggregation_summary(rows: &[AggregationRow]) -> String {
    let mut s = String::from(
        "vertices  cells  meta-model mean / worst   manual mean / worst   meta-model better\n",
    );
    let classes = [VertexClass::All, VertexClass::Last];
    let of = |class: VertexClass| -> Vec<&AggregationRow> {
        rows.iter().filter(|r| r.class == class).collect()
    };
    for class in classes {
        let r = of(class);
        if r.is_empty() {
            continue;
        }
        let n = r.len() as f64;
        let mean = |f: &dyn Fn(&AggregationRow) -> f64| r.iter().map(|x| f(x)).sum::<f64>() / n;
        let worst = |f: &dyn Fn(&AggregationRow) -> f64| r.iter().map(|x| f(x)).fold(0.0, f64::max);
        let better = r.iter().filter(|x| x.meta < x.manual).count();
        s += &format!(
            "{:<9} {:>5}  {:>10.4} / {:<10.4}   {:>7.4} / {:<8.4}   {better} of {}\n",
            class.name(),
            r.len(),
            mean(&|x| x.meta),
            worst(&|x| x.meta),
            mean(&|x| x.manual),
            worst(&|x| x.manual),
            r.len()
        );
    }
    s += "vertices  window holds (worst cell)           below 99 %   whole plane: |Δ mean t| worst   rms s meta/data   within the targets (or 2 se of the data): mean t, rms s\n";
    for class in classes {
        let r = of(class);
        let Some(w) = r.iter().min_by(|a, b| a.window.total_cmp(&b.window)) else {
            continue;
        };
        let planes: Vec<_> = r.iter().filter_map(|x| x.plane.map(|p| (x.d, p))).collect();
        let dt = planes
            .iter()
            .map(|(_, [data, meta])| (meta.mean_t - data.mean_t).abs())
            .fold(0.0, f64::max);
        let (lo, hi) = planes
            .iter()
            .map(|(_, [data, meta])| meta.rms_s / data.rms_s.max(1e-300))
            .fold((f64::INFINITY, 0.0f64), |(lo, hi), m| {
                (lo.min(m), hi.max(m))
            });
        // Cells within the targets, with or without the data's error.
        let within = |i: usize, with_se: bool| {
            planes
                .iter()
                .filter(|(d, [data, meta])| {
                    let se = data.se.filter(|_| with_se).unwrap_or([0.0; 2]);
                    moment_within(*d, data, meta, se)[i]
                })
                .count()
        };
        let short = r.iter().filter(|x| x.window < WINDOW_SHARE).count();
        s += &format!(
            "{:<9} {:>6.2} % (α = {}, d = {} MFP)  {short:>4} of {:<4}   {:>8.3} MFP               {lo:.2}–{hi:.2}         {} ({}), {} ({}) of {}\n",
            class.name(),
            100.0 * w.window,
            w.alpha,
            w.d,
            r.len(),
            dt,
            within(0, false),
            within(0, true),
            within(1, false),
            within(1, true),
            planes.len()
        );
    }
    s
}

/// The share of a cell's vertex weight its window should hold: the fit
/// sees the bins, and beyond them only the overflow's mass and the
/// whole-plane moments.
pub const WINDOW_SHARE: f64 = 0.99;

/// Whether the meta-model's whole-plane moments meet the targets against
/// the data's ([`crate::fit::gmm::moment_tolerances`]: |Δ mean t| within
/// 0.05·d (+ 0.01λ), rms s within 10 %), each target widened by twice the
/// data's standard error `se` (MFP; 0 for the targets alone).
pub fn moment_within(d: f64, data: &PlaneMoments, meta: &PlaneMoments, se: [f64; 2]) -> [bool; 2] {
    let (tol_t, tol_s) = crate::fit::gmm::moment_tolerances(d);
    let rms = data.rms_s.max(1e-300);
    [
        (meta.mean_t - data.mean_t).abs() <= tol_t + 2.0 * se[0],
        (meta.rms_s / rms).ln().abs() <= tol_s + 2.0 * se[1] / rms,
    ]
}

/// The aggregation-error table as Markdown (α_t errors in albedo units),
/// with the window's share of the vertices and the whole-plane moments
/// (mean t, rms s in MFP) of the measured vertices and of the meta-model.
/// A row without a per-configuration GMM shows "failed" after a fit
/// (`fitted`) and "—" after [`check_kernels`], which fits none.
pub fn aggregation_table(rows: &[AggregationRow], fitted: bool) -> String {
    let mut s = String::from(
        "| vertices | α | d | paths | per-config GMM | meta-model | manual | histogram noise | window holds | mean t data / meta | rms s data / meta |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let (t, sd) = match r.plane {
            Some([data, meta]) => {
                // "± error" where the data has one.
                let pm = |i: usize| data.se.map_or(String::new(), |e| format!(" ± {:.3}", e[i]));
                (
                    format!("{:+.3}{} / {:+.3}", data.mean_t, pm(0), meta.mean_t),
                    format!("{:.3}{} / {:.3}", data.rms_s, pm(1), meta.rms_s),
                )
            }
            None => ("—".into(), "—".into()),
        };
        s += &format!(
            "| {} | {} | {} | {} | {} | {:.4} | {:.4} | {:.4} | {:.2} % | {t} | {sd} |\n",
            r.class.name(),
            r.alpha,
            r.d,
            r.paths,
            r.per_config
                .map_or(if fitted { "failed" } else { "—" }.into(), |v| format!(
                    "{v:.4}"
                )),
            r.meta,
            r.manual,
            r.noise,
            100.0 * r.window
        );
    }
    s
}

/// A curve coloured by component; albedos alternate solid and dashed lines.
fn styled(
    label: String,
    points: Vec<(f64, f64)>,
    albedo_index: usize,
    k: usize,
) -> crate::jobs::plot::Series {
    let color = k + 3 * (albedo_index / 2);
    if albedo_index.is_multiple_of(2) {
        crate::jobs::plot::Series::line(label, points, color)
    } else {
        crate::jobs::plot::Series::dashed(label, points, color)
    }
}

/// Albedos and distances shown in the report's plots.
const PLOT_ALPHAS: [f64; 3] = [0.6, 0.92, 0.99];
const PLOT_DISTANCES: [f64; 3] = [0.35, 1.6, 6.5];

/// The report's plots: kernel heat maps (measured | meta-model | manual) on
/// an (α, d) grid in the pair frame, the meta-model's parameters against d,
/// and the aggregation errors against d.
pub fn kernel_plots(
    doc: &KernelDoc,
    file: &MetaModelFile,
    rows: &[AggregationRow],
    dir: &Path,
) -> Result<()> {
    use crate::jobs::plot::{Axes, Panel, Series, chart, heatmaps};
    let find = |v: &[f64], x: f64| v.iter().position(|y| (y - x).abs() < 1e-9);
    for class in [VertexClass::All, VertexClass::Last] {
        let mut panels = Vec::new();
        for a in PLOT_ALPHAS {
            for d in PLOT_DISTANCES {
                let (Some(ia), Some(id)) =
                    (find(&doc.config.albedos, a), find(&doc.config.distances, d))
                else {
                    continue;
                };
                let h = crate::fit::meta::histogram_from_doc(doc, ia, id, class);
                let meta = file.eval(class, d, a, 1.0).gmm;
                let manual = manual_kernel(d);
                // The core's bins only: a tail's wider bins would show their
                // mass, not the density, on equal cells.
                let tail = doc.config.grid.for_class(class).tail.map_or(0, |t| t.bins);
                let (nt, ns) = (h.nt() - 2 * tail, h.ns() - tail);
                // Unfold |s| into s ∈ (−S, S): rows j < ns mirror the upper half.
                let unfold = |m: &[f64]| -> Vec<f64> {
                    let mut out = Vec::with_capacity(nt * 2 * ns);
                    for i in 0..nt {
                        for j in 0..2 * ns {
                            let jj = if j < ns { ns - 1 - j } else { j - ns };
                            out.push(m[(i + tail) * (ns + tail) + jj]);
                        }
                    }
                    out
                };
                for (name, g) in [
                    ("measured", None),
                    ("meta-model", Some(&meta)),
                    ("manual", Some(&manual)),
                ] {
                    let m = match g {
                        None => h.mass.clone(),
                        Some(g) => histogram_of(g, &h).mass,
                    };
                    panels.push(Panel {
                        title: format!("{name} α={a} d={d}"),
                        nx: nt,
                        ny: 2 * ns,
                        values: unfold(&m),
                    });
                }
            }
        }
        heatmaps(
            &dir.join(format!("kernels_{class:?}.png").to_lowercase()),
            &format!(
                "{class:?} vertices: measured | meta-model | manual, t → (x_i left of centre, x_e right), s ↑, the window's core, sqrt colour scale"
            ),
            &panels,
            9,
        )?;
    }
    // Parameters of the "all" meta-model against d, per albedo.
    let ds: Vec<f64> = (0..60)
        .map(|i| 0.1 * 100f64.powf(i as f64 / 59.0))
        .collect();
    let m = &file.all;
    let mut w = Vec::new();
    let mut t = Vec::new();
    let mut s = Vec::new();
    for (ci, a) in PLOT_ALPHAS.iter().enumerate() {
        for k in 0..m.k {
            let pick = |f: &dyn Fn(&crate::metamodel::kernel::Gmm, f64) -> f64| {
                ds.iter()
                    .map(|&d| (d, f(&m.eval(d, *a, 1.0).gmm, d)))
                    .collect::<Vec<_>>()
            };
            let label = format!("α={a} k={k}");
            // Centres and widths in units of λ = d/2 + 1 (the meta-model's
            // own coordinates: bounded from near to far field).
            let lam = |d: f64| 0.5 * d + 1.0;
            w.push(styled(
                label.clone(),
                pick(&|g, _| g.components[k].weight),
                ci,
                k,
            ));
            t.push(styled(
                label.clone(),
                pick(&|g, d| (g.components[k].t - 0.5 * d) / lam(d)),
                ci,
                k,
            ));
            s.push(styled(
                label,
                pick(&|g, d| g.components[k].sigma / lam(d)),
                ci,
                k,
            ));
        }
    }
    let axes = |title: &str, y: &str, log_y: bool| Axes {
        title: title.into(),
        x_label: "d (MFP)".into(),
        y_label: y.into(),
        log_x: true,
        log_y,
    };
    chart(
        &dir.join("weights.png"),
        &axes("meta-model (all vertices): weights", "w_k", false),
        &w,
    )?;
    chart(
        &dir.join("centres.png"),
        &axes(
            "meta-model (all vertices): centres (t_k − d/2)/λ, λ = d/2 + 1",
            "μ_k",
            false,
        ),
        &t,
    )?;
    chart(
        &dir.join("widths.png"),
        &axes("meta-model (all vertices): widths σ_k/λ", "σ_k / λ", true),
        &s,
    )?;
    // Aggregation errors against d.
    for class in [VertexClass::All, VertexClass::Last] {
        let mut series = Vec::new();
        for (ci, a) in PLOT_ALPHAS.iter().enumerate() {
            let sel: Vec<&AggregationRow> = rows
                .iter()
                .filter(|r| r.class == class && (r.alpha - a).abs() < 1e-9)
                .collect();
            series.push(Series::line(
                format!("meta-model α={a}"),
                sel.iter().map(|r| (r.d, r.meta)).collect(),
                ci,
            ));
            series.push(Series::dashed(
                format!("manual α={a}"),
                sel.iter().map(|r| (r.d, r.manual)).collect(),
                ci,
            ));
        }
        chart(
            &dir.join(format!("aggregation_{class:?}.png").to_lowercase()),
            &axes(
                &format!("aggregation error RMS(α_t − α_t[measured]), {class:?} vertices"),
                "RMS error (albedo units)",
                true,
            ),
            &series,
        )?;
    }
    Ok(())
}

/// A density step: ρ = `left` for x < x_step, `right` beyond (2.5D, a
/// vertical plane), for [`crate::forward::kernel::DirectedKernel`].
pub struct DensityStep {
    pub x_step: f64,
    pub left: f64,
    pub right: f64,
}

impl crate::forward::walk::DensityField for DensityStep {
    fn density(&self, x: f64, _y: f64) -> f64 {
        if x < self.x_step {
            self.left
        } else {
            self.right
        }
    }
    fn majorant(&self) -> f64 {
        self.left.max(self.right)
    }
}

/// One row of the density-step experiment: aggregation errors (RMS of α_t
/// over random textures, against the measured kernel) of the homogeneous
/// meta-model kernel evaluated at several effective densities ρ̄, of the
/// renderer's density-weighted rule, and of the optical warp.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepRow {
    pub alpha: f64,
    pub d: f64,
    pub paths: u64,
    /// (label, ρ̄, aggregation error); ρ̄ is the density at which the
    /// homogeneous kernel was evaluated (1 for the warps, which evaluate it
    /// at the optical distance and unit density).
    pub predictions: Vec<(String, f64, f64)>,
    pub noise: f64,
}

/// The optical coordinate across a [`DensityStep`] on the pair axis:
/// τ(t) = ∫₀ᵗ ρ (MFP at unit density), x_i at t = 0.
struct StepAxis<'a>(&'a DensityStep);

impl StepAxis<'_> {
    fn rho(&self, t: f64) -> f64 {
        if t < self.0.x_step {
            self.0.left
        } else {
            self.0.right
        }
    }
    fn tau(&self, t: f64) -> f64 {
        let s = self.0;
        if t < s.x_step {
            s.left * t
        } else {
            s.left * s.x_step + s.right * (t - s.x_step)
        }
    }
    fn inverse(&self, tau: f64) -> f64 {
        let s = self.0;
        let at_step = s.left * s.x_step;
        if tau < at_step {
            tau / s.left
        } else {
            s.x_step + (tau - at_step) / s.right
        }
    }
    /// The share of [t0, t1] left of the step.
    fn left_share(&self, t0: f64, t1: f64) -> f64 {
        ((self.0.x_step - t0) / (t1 - t0)).clamp(0.0, 1.0)
    }
    /// The mean density over [t0, t1].
    fn mean_rho(&self, t0: f64, t1: f64) -> f64 {
        let f = self.left_share(t0, t1);
        f * self.0.left + (1.0 - f) * self.0.right
    }
}

/// The bin masses of `kernel` on `template`'s grid, each weighted by the
/// mean density of its t-range (`per_component`: each component's
/// weighted masses rescaled to its weight), for the rule α_t = ∫Kρα/∫Kρ.
fn density_weighted_masses(
    kernel: &Gmm,
    template: &crate::fit::gmm::KernelHistogram,
    axis: &StepAxis,
    per_component: bool,
) -> crate::fit::gmm::KernelHistogram {
    // Zero masses on the template's grid, to be summed into.
    let mut out = histogram_of(&Gmm::default(), template);
    let ns = template.s_edges.len() - 1;
    for c in &kernel.components {
        let one = histogram_of(
            &Gmm {
                components: vec![c.clone()],
            },
            template,
        );
        let weighted: Vec<f64> = one
            .mass
            .iter()
            .enumerate()
            .map(|(b, m)| {
                let it = b / ns;
                m * axis.mean_rho(template.t_edges[it], template.t_edges[it + 1])
            })
            .collect();
        let total: f64 = weighted.iter().sum();
        let scale = if per_component {
            c.weight / total.max(1e-300)
        } else {
            1.0
        };
        for (o, m) in out.mass.iter_mut().zip(&weighted) {
            *o += m * scale;
        }
    }
    out
}

/// The optical warp of the unit-density kernel `opt` (queried at the
/// optical distance τ(d)) onto `template`'s grid, exactly: along t the
/// warp τ(t) = ∫₀ᵗρ, across it s scaled by the local ρ, so that
/// K(t, s) = ρ(t)²·K_opt(τ(t), ρ(t)s), and a bin's mass is the mixture's
/// mass over its image, piece by piece on either side of the step.
fn warped_masses(
    opt: &Gmm,
    template: &crate::fit::gmm::KernelHistogram,
    axis: &StepAxis,
) -> crate::fit::gmm::KernelHistogram {
    let mut out = histogram_of(opt, template);
    let ns = template.s_edges.len() - 1;
    let x = axis.0.x_step;
    for (it, t) in template.t_edges.windows(2).enumerate() {
        let pieces = [(t[0], t[1].min(x)), (t[0].max(x), t[1])];
        for (is, s) in template.s_edges.windows(2).enumerate() {
            out.mass[it * ns + is] = pieces
                .iter()
                .filter(|(a, b)| b > a)
                .map(|&(a, b)| {
                    let r = axis.rho(0.5 * (a + b));
                    opt.mass_in_fold(axis.tau(a), axis.tau(b), r * s[0], r * s[1])
                })
                .sum();
        }
    }
    // What the warped grid leaves out (not the unwarped grid's).
    out.overflow = (opt.total_weight() - out.mass.iter().sum::<f64>()).max(0.0);
    out
}

/// Kernels across a density step (ρ = 1 | ρ = 4 across the plane halfway
/// between x_i and x_e) measured with delta tracking, against:
///
/// * the density-scaled homogeneous kernel K(d, α, ρ̄) for ρ̄ = 1 (plain),
///   4, the mean of the endpoint densities, and the kernel-weighted density
///   ρ̄ = ∫Kρ/∫K (iterated to a fixed point), each taken as the vertex
///   distribution itself;
/// * the renderer's rule: K(d, α, ρ₀) at the endpoints' mean density with
///   the vertices weighted by the density, α_t = ∫Kρα/∫Kρ;
/// * the optical warp: the unit-density kernel at the
///   optical distance D = ∫ρ along the pair, mapped back through τ(t);
/// * the warp as the renderer places it (`--density-kernel warp`): each
///   component's centre mapped back through τ, its width σ·d/D,
///   density-weighted within the component.
pub fn density_step_experiment(
    file: &MetaModelFile,
    alphas: &[f64],
    distances: &[f64],
    paths: u64,
    seed: u64,
) -> Vec<StepRow> {
    use crate::fit::aggregation::aggregation_row_of;
    use crate::forward::kernel::{DirectedKernel, PairGrid};
    use crate::forward::medium::Medium;
    use crate::forward::walk::UniformAlbedo;
    let (left, right) = (1.0, 4.0);
    let all = VertexClass::All;
    let mut rows = Vec::new();
    for &alpha in alphas {
        for &d in distances {
            let step = DensityStep {
                x_step: 0.5 * d,
                left,
                right,
            };
            let axis = StepAxis(&step);
            let albedo = UniformAlbedo(crate::forward::rng::threshold_u32(alpha));
            let grid = PairGrid::default();
            let lambda = PairGrid::scale(d, 1.0);
            let k = DirectedKernel {
                medium: Medium::new(alpha, 0.3, 1.5, 1.0, None).expect("valid medium"),
                albedo: &albedo,
                density: &step,
                d,
                rel_width: 0.1,
                wedge: 0.3,
                min_order: 2,
                lambda,
                grid,
                paths,
                seed,
                max_events: 1_000_000,
            };
            let cell_tally = k.run();
            let h = cell_tally.normalized(&grid, all, alpha, d, lambda);
            let cell = Cell::measured(alpha, h);
            // Kernel-weighted density: mass on each side of the step.
            let weighted = |g: &Gmm| {
                let w_left: f64 = g
                    .components
                    .iter()
                    .map(|c| {
                        c.weight
                            * crate::metamodel::kernel::gauss_interval(
                                f64::NEG_INFINITY,
                                0.5 * d,
                                c.t,
                                c.sigma,
                            )
                    })
                    .sum();
                w_left * left + (1.0 - w_left) * right
            };
            let rho0 = 0.5 * (left + right);
            let mut rho_k = rho0;
            for _ in 0..20 {
                rho_k = weighted(&file.eval(all, d, alpha, rho_k).gmm);
            }
            let mut predictions = Vec::new();
            let mut noise = 0.0;
            for (label, rho) in [
                ("plain (ρ̄ = 1)", left),
                ("ρ̄ = 4", right),
                ("endpoint mean", rho0),
                ("kernel-weighted", rho_k),
            ] {
                let g = file.eval(all, d, alpha, rho).gmm;
                let row = aggregation_row(all, &cell, None, &g);
                noise = row.noise;
                predictions.push((label.to_string(), rho, row.meta));
            }
            let at_rho0 = file.eval(all, d, alpha, rho0).gmm;
            let renderer = density_weighted_masses(&at_rho0, &cell.hist, &axis, false);
            let row = aggregation_row_of(all, &cell, None, &renderer);
            predictions.push(("renderer: ρ-weighted".to_string(), rho0, row.meta));
            let big_d = axis.tau(d);
            let opt = file.eval(all, big_d, alpha, 1.0).gmm;
            let row = aggregation_row_of(all, &cell, None, &warped_masses(&opt, &cell.hist, &axis));
            predictions.push(("optical warp".to_string(), 1.0, row.meta));
            let placed = Gmm {
                components: opt
                    .components
                    .iter()
                    .map(|c| crate::metamodel::kernel::Component {
                        t: axis.inverse(c.t),
                        sigma: c.sigma * d / big_d,
                        ..c.clone()
                    })
                    .collect(),
            };
            let placed = density_weighted_masses(&placed, &cell.hist, &axis, true);
            let row = aggregation_row_of(all, &cell, None, &placed);
            predictions.push(("warp, placed".to_string(), 1.0, row.meta));
            rows.push(StepRow {
                alpha,
                d,
                paths: cell.hist.paths,
                predictions,
                noise,
            });
        }
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::gmm::KernelHistogram;

    #[test]
    fn moments_within_the_targets_or_twice_the_data_error() {
        let data = PlaneMoments {
            mean_t: 0.5,
            rms_s: 1.0,
            se: Some([0.02, 0.05]),
        };
        // d = 1: τ_t = 0.05 + 0.015; rms s within 10 % (ln 1.1).
        let meta = PlaneMoments {
            mean_t: 0.58,
            rms_s: 0.85,
            se: None,
        };
        assert_eq!(moment_within(1.0, &data, &meta, [0.0; 2]), [false, false]);
        assert_eq!(moment_within(1.0, &data, &meta, [0.02, 0.05]), [true, true]);
        let near = PlaneMoments {
            mean_t: 0.55,
            rms_s: 0.95,
            se: None,
        };
        assert_eq!(moment_within(1.0, &data, &near, [0.0; 2]), [true, true]);
    }

    fn template(d: f64) -> KernelHistogram {
        let lambda = 0.5 * d + 1.0;
        KernelHistogram {
            d,
            t_edges: (0..=32)
                .map(|i| lambda * (-4.0 + 0.25 * i as f64))
                .collect(),
            s_edges: (0..=16).map(|i| lambda * 0.25 * i as f64).collect(),
            mass: vec![0.0; 32 * 16],
            sigma: vec![0.0; 32 * 16],
            overflow: 0.0,
            overflow_sigma: 0.0,
            paths: 1,
            plane: None,
        }
    }

    /// Without a step (equal densities on both sides) the optical warp is
    /// the density law itself, and the density weighting changes nothing.
    #[test]
    fn warp_without_a_step_is_the_density_law() {
        let (file, _) = crate::jobs::shipped::Shipped::Meta
            .load::<MetaModelFile>(None)
            .expect("built-in model");
        for (alpha, d, rho) in [(0.6, 0.5, 2.5), (0.95, 2.0, 0.5), (0.3, 1.0, 4.0)] {
            let step = DensityStep {
                x_step: 0.5 * d,
                left: rho,
                right: rho,
            };
            let axis = StepAxis(&step);
            let h = template(d);
            let scaled = histogram_of(&file.eval(VertexClass::All, d, alpha, rho).gmm, &h);
            let opt = file.eval(VertexClass::All, rho * d, alpha, 1.0).gmm;
            let warped = warped_masses(&opt, &h, &axis);
            let weighted = density_weighted_masses(
                &file.eval(VertexClass::All, d, alpha, rho).gmm,
                &h,
                &axis,
                false,
            );
            for ((a, b), c) in scaled.mass.iter().zip(&warped.mass).zip(&weighted.mass) {
                assert!((a - b).abs() <= 1e-12 + 1e-9 * a, "warp {b} vs scaled {a}");
                let c = c / rho;
                assert!(
                    (a - c).abs() <= 1e-12 + 1e-9 * a,
                    "weighted {c} vs scaled {a}"
                );
            }
            assert!(scaled.mass.iter().sum::<f64>() > 0.5);
        }
    }

    /// Across a step the warp keeps the kernel's mass, and it moves mass
    /// toward the thin side (where a unit of optical length is longer).
    #[test]
    fn warp_across_a_step_keeps_mass_and_stretches_the_thin_side() {
        let (file, _) = crate::jobs::shipped::Shipped::Meta
            .load::<MetaModelFile>(None)
            .expect("built-in model");
        let d = 1.0;
        let step = DensityStep {
            x_step: 0.5,
            left: 1.0,
            right: 4.0,
        };
        let axis = StepAxis(&step);
        assert_eq!(axis.tau(d), 2.5);
        assert!((axis.inverse(axis.tau(0.8)) - 0.8).abs() < 1e-12);
        let mut h = template(d);
        h.t_edges = (0..=400).map(|i| -20.0 + 0.1 * i as f64).collect();
        h.s_edges = (0..=200).map(|i| 0.1 * i as f64).collect();
        h.mass = vec![0.0; 400 * 200];
        let opt = file.eval(VertexClass::All, axis.tau(d), 0.8, 1.0).gmm;
        let w = warped_masses(&opt, &h, &axis);
        let total: f64 = w.mass.iter().sum();
        assert!((total - opt.total_weight()).abs() < 1e-6, "{total}");
        let left: f64 = (0..400)
            .filter(|&i| h.t_edges[i + 1] <= 0.5)
            .map(|i| w.mass[i * 200..(i + 1) * 200].iter().sum::<f64>())
            .sum();
        // Optical mass left of τ = 0.5 (the step's image) in the unit kernel.
        let expect: f64 = opt
            .components
            .iter()
            .map(|c| {
                c.weight
                    * crate::metamodel::kernel::gauss_interval(f64::NEG_INFINITY, 0.5, c.t, c.sigma)
            })
            .sum();
        assert!((left - expect).abs() < 1e-6, "{left} vs {expect}");
    }
}
