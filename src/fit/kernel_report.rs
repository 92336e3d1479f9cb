//! `svkernel fit kernels`: per-configuration GMM fits, the joint meta-model
//! fits, and how good the kernels are where it matters — the **aggregation
//! error** (issue 5 §3).
//!
//! # Aggregation error
//! For cell (α, d) and a random albedo texture A (texel size τ, values
//! uniform in [0, 1], random offset and orientation relative to the pair
//! frame; seeded), the aggregated albedo under a kernel K is
//! α_t(K) = Σ_b m_b(K)·Ā_b / Σ_b m_b(K) over the histogram's grid, with m_b
//! the kernel's mass in bin b and Ā_b the texture averaged over bin b and
//! its mirror image in s (the histogram is folded in |s|), by 4 × 4
//! sub-samples per bin. The reference is the measured histogram; the error
//! of a kernel is the RMS over textures of α_t(K) − α_t(histogram). Off-grid
//! mass is left out of every method alike.

use super::gmm::{KernelHistogram, histogram_of};
use super::lm::FitReport;
use super::meta::{Cell, cells, fit_meta};
use crate::error::{Error, Result};
use crate::forward::kernel::{KernelDoc, VertexClass};
use crate::forward::rng::PathRng;
use crate::metamodel::kernel::{Gmm, manual_kernel};
use crate::metamodel::meta::{META_FORMAT, META_VERSION, MetaModel, MetaModelFile};
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;

/// Textures per cell in the aggregation-error measure.
pub const TEXTURES: u64 = 64;
/// Texel sizes (MFP) cycled through the textures.
pub const TEXEL_SIZES: [f64; 4] = [0.25, 0.5, 1.0, 2.0];

/// A seeded random texture: values in [0, 1] on a texel grid of size τ,
/// rotated by φ and offset, evaluated at pair-frame points.
struct Texture {
    tau: f64,
    cos: f64,
    sin: f64,
    offset: [f64; 2],
    seed: u64,
}

impl Texture {
    fn new(seed: u64, index: u64) -> Self {
        let mut rng = PathRng::new(seed, index);
        let phi = 2.0 * std::f64::consts::PI * rng.uniform();
        Texture {
            tau: TEXEL_SIZES[(index % TEXEL_SIZES.len() as u64) as usize],
            cos: phi.cos(),
            sin: phi.sin(),
            offset: [rng.uniform() * 100.0, rng.uniform() * 100.0],
            seed: seed ^ (index << 20),
        }
    }

    /// The albedo at pair-frame point (t, s): a hash of the texel index.
    fn at(&self, t: f64, s: f64) -> f64 {
        let x = self.cos * t - self.sin * s + self.offset[0];
        let y = self.sin * t + self.cos * s + self.offset[1];
        let (i, j) = ((x / self.tau).floor() as i64, (y / self.tau).floor() as i64);
        let key = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).rotate_left(32);
        PathRng::new(self.seed, key).uniform()
    }

    /// Mean over bin [t0, t1] × [s0, s1] and its mirror in s (4 × 4 samples).
    fn bin_mean(&self, t0: f64, t1: f64, s0: f64, s1: f64) -> f64 {
        let mut sum = 0.0;
        for a in 0..4 {
            let t = t0 + (t1 - t0) * (a as f64 + 0.5) / 4.0;
            for b in 0..4 {
                let s = s0 + (s1 - s0) * (b as f64 + 0.5) / 4.0;
                sum += self.at(t, s) + self.at(t, -s);
            }
        }
        sum / 32.0
    }
}

/// Per texture: the texture's bin means over the grid of `hists[0]` (one
/// evaluation shared by every kernel and by the noise estimate) and α_t of
/// each kernel histogram.
fn aggregated(hists: &[&KernelHistogram], seed: u64) -> Vec<(Vec<f64>, Vec<f64>)> {
    let grid = hists[0];
    let (te, se) = (&grid.t_edges, &grid.s_edges);
    (0..TEXTURES)
        .map(|k| {
            let tex = Texture::new(seed, k);
            let means: Vec<f64> = te
                .windows(2)
                .flat_map(|t| se.windows(2).map(move |s| (t[0], t[1], s[0], s[1])))
                .map(|(t0, t1, s0, s1)| tex.bin_mean(t0, t1, s0, s1))
                .collect();
            let at = hists
                .iter()
                .map(|h| {
                    let m: f64 = h.mass.iter().map(|v| v.max(0.0)).sum();
                    let a: f64 = h.mass.iter().zip(&means).map(|(v, a)| v.max(0.0) * a).sum();
                    if m > 0.0 { a / m } else { f64::NAN }
                })
                .collect();
            (means, at)
        })
        .collect()
}

/// One row of the aggregation-error table.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AggregationRow {
    pub class: VertexClass,
    pub alpha: f64,
    pub d: f64,
    pub paths: u64,
    /// RMS over textures of α_t − α_t(histogram) for the per-configuration
    /// GMM (None if its fit failed), the meta-model, the manual kernel.
    pub per_config: Option<f64>,
    pub meta: f64,
    pub manual: f64,
    /// The histogram's own statistical noise on α_t (RMS over textures of
    /// the standard error, from the bins' standard errors).
    pub noise: f64,
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    (s / n.max(1) as f64).sqrt()
}

/// The aggregation errors of one cell.
pub fn aggregation_row(
    class: VertexClass,
    cell: &Cell,
    per_config: Option<&Gmm>,
    meta: &Gmm,
) -> AggregationRow {
    let h = &cell.hist;
    let manual = histogram_of(&manual_kernel(cell.d), h);
    let meta_h = histogram_of(meta, h);
    let pc = per_config.map(|g| histogram_of(g, h));
    let mut list = vec![h, &meta_h, &manual];
    if let Some(p) = &pc {
        list.push(p);
    }
    let seed = 0xA66 ^ (cell.alpha.to_bits() >> 3) ^ cell.d.to_bits();
    let at = aggregated(&list, seed);
    let err = |k: usize| rms(at.iter().map(|(_, r)| r[k] - r[0]));
    // Noise: α_t = Σ m A / Σ m; first order σ² = Σ σ_b² (A_b − α_t)² / (Σm)².
    let m: f64 = h.mass.iter().map(|v| v.max(0.0)).sum();
    let noise = rms(at.iter().take(8).map(|(means, r)| {
        let s2: f64 = h
            .sigma
            .iter()
            .zip(means)
            .map(|(s, a)| (s * (a - r[0])).powi(2))
            .sum();
        s2.sqrt() / m.max(1e-300)
    }));
    AggregationRow {
        class,
        alpha: cell.alpha,
        d: cell.d,
        paths: h.paths,
        per_config: pc.map(|_| err(3)),
        meta: err(1),
        manual: err(2),
        noise,
    }
}

/// What `svkernel fit kernels` writes as report.json.
#[derive(Serialize, Deserialize)]
pub struct KernelReport {
    pub model_file: String,
    pub data_file: String,
    pub components: usize,
    pub degree: (usize, usize),
    pub joint: Vec<FitReport>,
    /// Per-cell fit reports (or the error) per class.
    pub per_cell: Vec<(String, Vec<std::result::Result<FitReport, String>>)>,
    pub aggregation: Vec<AggregationRow>,
    pub wall_s: f64,
}

/// Fits the meta-model (all and last vertices) to `data`, writes `out` and
/// `dir/report.json`, and measures the aggregation errors.
pub fn fit_kernels(
    data: &Path,
    out: &Path,
    dir: &Path,
    k: usize,
    degree: (usize, usize),
) -> Result<KernelReport> {
    let start = Instant::now();
    let doc = KernelDoc::load(data)?;
    if doc.config.density != 1.0 {
        return Err(Error::format(
            data,
            "config.density",
            "the meta-model is trained at unit density (other densities follow by scaling)",
        ));
    }
    // The two classes are independent fits: run them side by side (the QR
    // inside LM is single-threaded).
    let fit_class = |class: VertexClass| {
        let cs = cells(&doc, class);
        let what = format!("meta-model ({} vertices)", class.name());
        fit_meta(&cs, k, degree, &what).map(|r| (class, cs, r))
    };
    let (a, l) = rayon::join(
        || fit_class(VertexClass::All),
        || fit_class(VertexClass::Last),
    );
    let mut models: Vec<MetaModel> = Vec::new();
    let mut joint = Vec::new();
    let mut per_cell = Vec::new();
    let mut aggregation = Vec::new();
    for r in [a, l] {
        let (class, cs, (m, rep, fits)) = r?;
        use rayon::prelude::*;
        aggregation.extend(
            cs.par_iter()
                .zip(&fits)
                .map(|(c, f)| {
                    let q = m.eval(c.d, c.alpha, 1.0);
                    aggregation_row(class, c, f.as_ref().ok().map(|x| &x.0), &q.gmm)
                })
                .collect::<Vec<_>>(),
        );
        per_cell.push((
            format!("{class:?}"),
            fits.into_iter()
                .map(|f| f.map(|x| x.1).map_err(|e| e.to_string()))
                .collect(),
        ));
        joint.push(rep);
        models.push(m);
    }
    let last = models.pop().expect("two models");
    let all = models.pop().expect("two models");
    let file = MetaModelFile {
        format: META_FORMAT.into(),
        version: META_VERSION,
        all,
        first: None,
        last,
        g: doc.config.g,
        eta: doc.config.eta,
        provenance: Provenance::current(),
    };
    crate::io::write_json_atomic(out, &file)?;
    let report = KernelReport {
        model_file: out.display().to_string(),
        data_file: data.display().to_string(),
        components: k,
        degree,
        joint,
        per_cell,
        aggregation,
        wall_s: start.elapsed().as_secs_f64(),
    };
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    crate::io::write_json_atomic(&dir.join("report.json"), &report)?;
    kernel_plots(&doc, &file, &report.aggregation, dir)?;
    Ok(report)
}

/// The aggregation-error table as Markdown (α_t errors in albedo units).
pub fn aggregation_table(rows: &[AggregationRow]) -> String {
    let mut s = String::from(
        "| vertices | α | d | paths | per-config GMM | meta-model | manual | histogram noise |\n|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s += &format!(
            "| {:?} | {} | {} | {} | {} | {:.4} | {:.4} | {:.4} |\n",
            r.class,
            r.alpha,
            r.d,
            r.paths,
            r.per_config.map_or("failed".into(), |v| format!("{v:.4}")),
            r.meta,
            r.manual,
            r.noise
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
) -> crate::plot::Series {
    let color = k + 3 * (albedo_index / 2);
    if albedo_index.is_multiple_of(2) {
        crate::plot::Series::line(label, points, color)
    } else {
        crate::plot::Series::dashed(label, points, color)
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
    use crate::plot::{Axes, Panel, Series, chart, heatmaps};
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
                let h = super::meta::histogram_from_doc(doc, ia, id, class);
                let meta = file.eval(class, d, a, 1.0).gmm;
                let manual = manual_kernel(d);
                let (nt, ns) = (h.t_edges.len() - 1, h.s_edges.len() - 1);
                // Unfold |s| into s ∈ (−S, S): rows j < ns mirror the upper half.
                let unfold = |m: &[f64]| -> Vec<f64> {
                    let mut out = Vec::with_capacity(nt * 2 * ns);
                    for i in 0..nt {
                        for j in 0..2 * ns {
                            let jj = if j < ns { ns - 1 - j } else { j - ns };
                            out.push(m[i * ns + jj]);
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
                "{class:?} vertices: measured | meta-model | manual, t → (x_i left of centre, x_e right), s ↑, sqrt colour scale"
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
/// meta-model kernel evaluated at several effective densities ρ̄.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepRow {
    pub alpha: f64,
    pub d: f64,
    pub paths: u64,
    /// (label, ρ̄, aggregation error).
    pub predictions: Vec<(String, f64, f64)>,
    pub noise: f64,
}

/// Kernels across a density step (ρ = 1 | ρ = 4 across the plane halfway
/// between x_i and x_e) measured with delta tracking, against the
/// density-scaled homogeneous kernel K(d, α, ρ̄) for ρ̄ = 1 (plain), 4, the
/// mean of the endpoint densities, and the kernel-weighted density
/// ρ̄ = ∫Kρ/∫K (iterated to a fixed point) — the renderer's density scaling.
pub fn density_step_experiment(
    file: &MetaModelFile,
    alphas: &[f64],
    distances: &[f64],
    paths: u64,
    seed: u64,
) -> Vec<StepRow> {
    use crate::forward::kernel::{DirectedKernel, PairGrid};
    use crate::forward::medium::Medium;
    use crate::forward::walk::UniformAlbedo;
    let (left, right) = (1.0, 4.0);
    let mut rows = Vec::new();
    for &alpha in alphas {
        for &d in distances {
            let step = DensityStep {
                x_step: 0.5 * d,
                left,
                right,
            };
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
            let h = cell_tally.normalized(&grid, VertexClass::All, alpha, d, lambda);
            let hist = super::meta::fit_histogram(h);
            let cell = Cell { alpha, d, hist };
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
            let mut rho_k = 0.5 * (left + right);
            for _ in 0..20 {
                rho_k = weighted(&file.eval(VertexClass::All, d, alpha, rho_k).gmm);
            }
            let mut predictions = Vec::new();
            let mut noise = 0.0;
            for (label, rho) in [
                ("plain (ρ̄ = 1)", left),
                ("ρ̄ = 4", right),
                ("endpoint mean", 0.5 * (left + right)),
                ("kernel-weighted", rho_k),
            ] {
                let g = file.eval(VertexClass::All, d, alpha, rho).gmm;
                let row = aggregation_row(VertexClass::All, &cell, None, &g);
                noise = row.noise;
                predictions.push((label.to_string(), rho, row.meta));
            }
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
