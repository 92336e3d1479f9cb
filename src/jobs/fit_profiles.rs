//! `svkernel fit profiles` and `svkernel fit check`: fit the basis from a
//! directory of profile documents, measure its accuracy against simulations
//! (training or fresh), compare with Christensen–Burley, write the report
//! and its plots.

use crate::error::{Error, Result};
use crate::fit::basis::{BasisFitOutcome, fit_basis};
use crate::fit::lm::{FitOptions, FitReport};
use crate::forward::medium::Observable;
use crate::forward::profile::ProfileDoc;
use crate::jobs::plot::{Axes, Series, chart, ring_points};
use crate::metamodel::basis::{BasisModel, ExpMixture, RadialProfile};
use crate::metamodel::burley;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The radial accuracy measure uses rings inside this range (MFP).
pub const RADIAL_RANGE: (f64, f64) = (0.01, 20.0);

/// Accuracy of a model at one simulated albedo.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AccuracyRow {
    pub alpha: f64,
    pub rd_sim: f64,
    pub rd_sim_stderr: f64,
    pub rd_model: f64,
    /// (model − sim)/sim.
    pub rd_rel_err: f64,
    /// sqrt(Σ_j (E_model,j − E_sim,j)²)/R_d over the rings in
    /// [`RADIAL_RANGE`], E_j the energy of ring j (single + multiple).
    pub radial_l2_model: f64,
    /// The same for Christensen–Burley with A = the simulated R_d.
    pub radial_l2_burley: f64,
    /// The same for the simulation's own noise: sqrt(Σ σ_j²)/R_d.
    pub radial_l2_noise: f64,
}

/// Loads every profile document (`format: svkernel.profile`) of `dir`.
pub fn load_profiles(dir: &Path) -> Result<Vec<ProfileDoc>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension().is_some_and(|x| x == "json")
                && !p
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'))
        })
        .collect();
    paths.sort();
    let docs = paths
        .iter()
        .map(|p| ProfileDoc::load(p))
        .collect::<Result<Vec<_>>>()?;
    if docs.is_empty() {
        return Err(Error::format(
            dir,
            "(directory)",
            "no profile documents (*.json) found",
        ));
    }
    Ok(docs)
}

fn ring_energy(m: &RadialProfile, lo: f64, hi: f64) -> f64 {
    m.cdf(hi) - m.cdf(lo)
}

/// Accuracy of `model` (and of Christensen–Burley) against one profile.
pub fn accuracy(model: &BasisModel, doc: &ProfileDoc) -> AccuracyRow {
    let alpha = doc.config.medium.alpha;
    let b = &doc.bins;
    let Some(o) = doc.observed(model.observable) else {
        panic!("a profile without the model's observable (fit_basis refuses it)")
    };
    let mix = model.profile(alpha);
    let cb = RadialProfile {
        parts: vec![burley::profile(doc.R_d)],
    };
    let (mut s_model, mut s_cb, mut s_noise) = (0.0, 0.0, 0.0);
    for k in 0..o.p_1.len() {
        let (lo, hi) = (b.edges[k], b.edges[k + 1]);
        if lo < RADIAL_RANGE.0 || hi > RADIAL_RANGE.1 {
            continue;
        }
        let w = hi - lo;
        let e_sim = (o.p_1[k] + o.p_m[k]) * w;
        let var = (o.p_1_stderr[k].powi(2) + o.p_m_stderr[k].powi(2)) * w * w;
        s_model += (ring_energy(&mix, lo, hi) - e_sim).powi(2);
        s_cb += (ring_energy(&cb, lo, hi) - e_sim).powi(2);
        s_noise += var;
    }
    let rd = o.total.value.max(1e-300);
    let rd_model = model.r_d(alpha);
    // Christensen–Burley is a profile of the exitance.
    let burley = match model.observable {
        Observable::Exitance => s_cb.sqrt() / rd,
        Observable::Radiance => f64::NAN,
    };
    AccuracyRow {
        alpha,
        rd_sim: o.total.value,
        rd_sim_stderr: o.total.stderr,
        rd_model,
        rd_rel_err: rd_model / rd - 1.0,
        radial_l2_model: s_model.sqrt() / rd,
        radial_l2_burley: burley,
        radial_l2_noise: s_noise.sqrt() / rd,
    }
}

/// The report of `svkernel fit profiles` (written as report.json).
#[derive(Serialize, Deserialize)]
pub struct BasisReport {
    pub model_file: String,
    pub profiles_dir: String,
    pub components: usize,
    pub degree: usize,
    pub joint: FitReport,
    pub single: FitReport,
    pub per_profile: Vec<FitReport>,
    pub training_accuracy: Vec<AccuracyRow>,
    /// R_d(α = 1) of the model and its target 1 − R_sp.
    pub rd_at_one: (f64, f64),
    pub wall_s: f64,
}

/// Fits the basis to the profiles of `in_dir` and writes the model to `out`
/// and the report and plots to `report_dir`.
pub fn fit_profiles(
    in_dir: &Path,
    out: &Path,
    report_dir: &Path,
    k: usize,
    degree: usize,
    tol: f64,
    observable: Observable,
) -> Result<BasisReport> {
    let start = std::time::Instant::now();
    let docs = load_profiles(in_dir)?;
    let prov = serde_json::to_value(crate::provenance::Provenance::current()).unwrap_or_default();
    let provenance = serde_json::json!({
        "made_by": prov,
        "profiles_dir": in_dir.display().to_string(),
        "profiles": docs.iter().map(|d| serde_json::json!({"alpha": d.config.medium.alpha, "paths": d.paths, "seed": d.config.seed})).collect::<Vec<_>>(),
    });
    let BasisFitOutcome {
        model,
        joint,
        single,
        per_profile,
    } = fit_basis(
        &docs,
        observable,
        k,
        degree,
        &FitOptions {
            tol,
            ..FitOptions::default()
        },
        provenance,
    )?;
    crate::jobs::store::write_json_atomic(out, &model)?;
    let mut rows: Vec<AccuracyRow> = docs.iter().map(|d| accuracy(&model, d)).collect();
    rows.sort_by(|a, b| a.alpha.total_cmp(&b.alpha));
    let report = BasisReport {
        model_file: out.display().to_string(),
        profiles_dir: in_dir.display().to_string(),
        components: k,
        degree,
        joint,
        single,
        per_profile: per_profile.into_iter().map(|p| p.2).collect(),
        training_accuracy: rows,
        rd_at_one: (model.r_d(1.0), 1.0 - model.r_sp),
        wall_s: start.elapsed().as_secs_f64(),
    };
    crate::jobs::store::write_json_atomic(&report_dir.join("report.json"), &report)?;
    plots(&model, &docs, &report.training_accuracy, report_dir)?;
    Ok(report)
}

/// The multiple-scattering fit problem of one profile with LM's optimum, as
/// JSON for an independent optimiser (tools/nlopt_check.py). The tail bin has
/// `hi = null`; parameters are (ln A_k…, θ_k…) with B = rate_from_theta(θ).
pub fn export_problem(doc: &ProfileDoc, k: usize) -> Result<serde_json::Value> {
    use crate::fit::exp_mixture::{
        BinnedDensity, ExpMixtureFit, Order, fit_mixture, theta_from_rate,
    };
    use levenberg_marquardt::LeastSquaresProblem;
    let data = BinnedDensity::from_profile(doc, Order::Multi, Observable::Exitance);
    let (m, rep) = fit_mixture("export", &data, k, 1, &FitOptions::default())?;
    let theta: Vec<f64> =
        m.a.iter()
            .map(|a| a.ln())
            .chain(m.b.iter().map(|&b| theta_from_rate(b)))
            .collect();
    let p = ExpMixtureFit {
        data: &data,
        power: 1,
        theta: nalgebra::DVector::from_vec(theta.clone()),
    };
    let chi2 = p.residuals().map_or(f64::NAN, |r| r.norm_squared());
    Ok(serde_json::json!({
        "alpha": doc.config.medium.alpha,
        "power": 1,
        "components": k,
        "b_min": crate::metamodel::basis::B_MIN,
        "b_max": crate::metamodel::basis::B_MAX,
        "lo": data.lo,
        "hi": data.hi.iter().map(|h| if h.is_finite() { serde_json::json!(h) } else { serde_json::Value::Null }).collect::<Vec<_>>(),
        "y": data.y,
        "sigma": data.sigma,
        "theta": theta,
        "chi2": chi2,
        "report": rep,
    }))
}

/// Accuracy of a model file against the profiles of a directory.
pub fn check(model: &BasisModel, in_dir: &Path) -> Result<Vec<AccuracyRow>> {
    let docs = load_profiles(in_dir)?;
    let mut rows: Vec<AccuracyRow> = docs.iter().map(|d| accuracy(model, d)).collect();
    rows.sort_by(|a, b| a.alpha.total_cmp(&b.alpha));
    Ok(rows)
}

/// The total a profile of `observable` integrates to: R_d, or ∫L dA of the
/// radiance along the normal.
fn total_name(observable: Observable) -> &'static str {
    match observable {
        Observable::Exitance => "R_d",
        Observable::Radiance => "∫L dA",
    }
}

/// Markdown table of accuracy rows.
pub fn markdown_table(rows: &[AccuracyRow], observable: Observable) -> String {
    let total = total_name(observable);
    let mut s = format!(
        "| α | {total} sim | {total} model | rel. err | radial L2 model | radial L2 C–B | radial L2 MC noise |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        // No Christensen–Burley profile exists of the normal radiance.
        let burley = if r.radial_l2_burley.is_nan() {
            "—".to_string()
        } else {
            format!("{:.4}", r.radial_l2_burley)
        };
        s += &format!(
            "| {:.6} | {:.5} ± {:.5} | {:.5} | {:+.3} % | {:.4} | {burley} | {:.4} |\n",
            r.alpha,
            r.rd_sim,
            r.rd_sim_stderr,
            r.rd_model,
            100.0 * r.rd_rel_err,
            r.radial_l2_model,
            r.radial_l2_noise
        );
    }
    s
}

fn plots(model: &BasisModel, docs: &[ProfileDoc], rows: &[AccuracyRow], dir: &Path) -> Result<()> {
    // A few albedos across the range.
    let mut sorted: Vec<&ProfileDoc> = docs.iter().collect();
    sorted.sort_by(|a, b| a.config.medium.alpha.total_cmp(&b.config.medium.alpha));
    let picks: Vec<&ProfileDoc> = [0.0, 0.5, 0.8, 1.0]
        .iter()
        .map(|f| sorted[((sorted.len() - 1) as f64 * f).round() as usize])
        .collect();
    let rs: Vec<f64> = (0..=120)
        .map(|i| 1e-3 * 10f64.powf(i as f64 / 24.0))
        .collect();
    let mut series = Vec::new();
    let mut resid = Vec::new();
    for (c, d) in picks.iter().enumerate() {
        let a = d.config.medium.alpha;
        let b = &d.bins;
        let Some(o) = d.observed(model.observable) else {
            continue;
        };
        let total: Vec<f64> = o.p_1.iter().zip(o.p_m).map(|(x, y)| x + y).collect();
        let err: Vec<f64> = o
            .p_1_stderr
            .iter()
            .zip(o.p_m_stderr)
            .map(|(x, y)| (x * x + y * y).sqrt())
            .collect();
        let (pts, e) = ring_points(&b.edges, &total, &err);
        // Draw the model only where the simulation has signal.
        let floor = pts.iter().map(|p| p.1).fold(f64::INFINITY, f64::min) / 10.0;
        let r_last = pts.last().map_or(100.0, |p| p.0);
        series.push(Series::points(format!("sim α = {a:.4}"), pts, Some(e), c));
        series.push(Series::line(
            "",
            rs.iter()
                .filter(|&&r| r <= r_last)
                .map(|&r| (r, model.density(r, a)))
                .filter(|p| p.1 >= floor)
                .collect(),
            c,
        ));
        let mix = model.profile(a);
        let rel: Vec<(f64, f64)> = (1..total.len())
            .filter(|&k| {
                total[k] > 0.0 && b.edges[k] >= RADIAL_RANGE.0 && b.edges[k + 1] <= RADIAL_RANGE.1
            })
            .map(|k| {
                (
                    (b.edges[k] * b.edges[k + 1]).sqrt(),
                    mix.bin_mean(b.edges[k], b.edges[k + 1]) / total[k] - 1.0,
                )
            })
            .collect();
        resid.push(Series::line(format!("α = {a:.4}"), rel, c));
    }
    let ax = |title: &str, x: &str, y: &str, lx: bool, ly: bool| Axes {
        title: title.into(),
        x_label: x.into(),
        y_label: y.into(),
        log_x: lx,
        log_y: ly,
    };
    chart(
        &dir.join("profiles.png"),
        &ax(
            "p(r; α): simulation (points, ±1σ) vs smooth model (lines)",
            "r (MFP)",
            "p(r) (1/MFP)",
            true,
            true,
        ),
        &series,
    )?;
    chart(
        &dir.join("residuals.png"),
        &ax(
            "relative residual of the model per ring, r ∈ [0.01, 20]",
            "r (MFP)",
            "model/sim − 1",
            true,
            false,
        ),
        &resid,
    )?;
    let alphas: Vec<f64> = (0..=400).map(|i| i as f64 / 400.0).collect();
    let total = total_name(model.observable);
    chart(
        &dir.join("rd.png"),
        &ax(
            &format!("{total}(α): smooth model vs simulation"),
            "α",
            total,
            false,
            false,
        ),
        &[
            Series::line(
                "model",
                alphas.iter().map(|&a| (a, model.r_d(a))).collect(),
                0,
            ),
            Series::points(
                "simulation",
                rows.iter().map(|r| (r.alpha, r.rd_sim)).collect(),
                Some(rows.iter().map(|r| r.rd_sim_stderr).collect()),
                1,
            ),
        ],
    )?;
    let mut errors = vec![
        Series::points(
            format!("{total} rel. error"),
            rows.iter().map(|r| (r.alpha, r.rd_rel_err)).collect(),
            Some(rows.iter().map(|r| r.rd_sim_stderr / r.rd_sim).collect()),
            0,
        ),
        Series::line(
            "radial L2 model",
            rows.iter().map(|r| (r.alpha, r.radial_l2_model)).collect(),
            1,
        ),
    ];
    // Christensen–Burley is a profile of the exitance only.
    if model.observable == Observable::Exitance {
        errors.push(Series::dashed(
            "radial L2 Christensen–Burley",
            rows.iter().map(|r| (r.alpha, r.radial_l2_burley)).collect(),
            2,
        ));
    }
    chart(
        &dir.join("rd_error.png"),
        &ax(
            &format!("{total} relative error (model/sim − 1) and radial L2 error"),
            "α",
            "",
            false,
            false,
        ),
        &errors,
    )?;
    let k = model.components();
    let per = |f: &dyn Fn(&ExpMixture, usize) -> f64| -> Vec<Series> {
        (0..k)
            .map(|i| {
                Series::line(
                    format!("k = {}", i + 1),
                    alphas
                        .iter()
                        .filter(|&&a| a > 0.0)
                        .map(|&a| (a, f(&model.multi(a), i)))
                        .collect(),
                    i,
                )
            })
            .collect()
    };
    chart(
        &dir.join("amplitudes.png"),
        &ax(
            "A_k(α) of the multiple-scattering mixture",
            "α",
            "A_k (1/MFP)",
            false,
            true,
        ),
        &per(&|m, i| m.a[i]),
    )?;
    chart(
        &dir.join("rates.png"),
        &ax(
            "B_k(α) of the multiple-scattering mixture",
            "α",
            "B_k (1/MFP)",
            false,
            true,
        ),
        &per(&|m, i| m.b[i]),
    )?;
    Ok(())
}
