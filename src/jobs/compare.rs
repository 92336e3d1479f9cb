//! What accuracy costs in time: for one scene, the
//! error of every method and of the brute-force reference as their sample
//! budgets grow, against a high-budget reference ("truth") rendered with an
//! independent seed.
//!
//! # Error
//! e = √(max(0, Σ(m − t)² − Σσ_t²)/Σt²) over all pixels and channels of the
//! first pass: the relative RMSE of image m against the truth t with the
//! truth's own variance σ_t² subtracted (so a noisy truth does not inflate
//! it), but *not* m's: the method's noise is part of what its time buys.
//! A model's curve falls like 1/√time until it meets its bias (the floor);
//! the reference's keeps falling, and where it crosses a model's curve is
//! how long brute force needs to match that model.
//!
//! # Time
//! A curve's time is the render time of each budget: a model's set-up (what
//! it prepares once per scene and material, such as the kernel methods'
//! pyramids) is recorded beside it
//! ([`CurvePoint::setup_s`]) and stated separately in the report, so time
//! grows with the budget; the reference has no set-up.

use super::render::{RenderDoc, RenderOptions, Target, render_scene, write_outputs};
use super::report::{Block, write_report};
use crate::error::{Error, Result};
use crate::provenance::Provenance;
use crate::render::analysis::{Effect, EffectKind, Plan, analyse};
use crate::render::estimator::Image;
use crate::render::scene::Scene;
use crate::render::svbssrdf::Method;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One point of a curve: the budget (samples per pixel, or reference
/// paths), the wall time it took (set-up included), the set-up part of it
/// and the error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    pub budget: u64,
    pub wall_s: f64,
    /// Set-up (pyramid builds) within `wall_s`; 0 for the reference.
    #[serde(default)]
    pub setup_s: f64,
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_rmse: f64,
    /// The smallest error the truth resolves at this point
    /// ([`resolution`]); below it `rel_rmse` is not a measurement, only
    /// `rel_rmse ≤ hypot(rel_rmse, resolution)` is.
    #[serde(default)]
    pub resolution: f64,
}

impl CurvePoint {
    /// The render time: `wall_s` less the set-up.
    pub fn render_s(&self) -> f64 {
        self.wall_s - self.setup_s
    }

    /// Whether the truth resolves this point's error (`rel_rmse` at or
    /// above [`CurvePoint::resolution`]).
    pub fn resolved(&self) -> bool {
        self.rel_rmse >= self.resolution
    }

    /// An upper bound on the error ([`super::render::error_bound`]).
    pub fn error_bound(&self) -> f64 {
        super::render::error_bound(self.rel_rmse, self.resolution)
    }
}

/// Error against time of one method (or the reference), in budget order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Curve {
    pub method: Target,
    pub points: Vec<CurvePoint>,
}

/// The truth-noise-subtracted relative RMSE of `m` against `t` (module docs).
pub fn rel_error(m: &Image, t: &Image) -> f64 {
    super::render::rel_rmse(m, t, false)
}

/// The smallest error the truth `t` resolves for `m`
/// ([`super::render::resolution`] with the truth's noise alone).
pub fn resolution(m: &Image, t: &Image) -> f64 {
    super::render::resolution(m, t, false)
}

/// Every budget of the curves must be ≥ 1 (checked before any work).
fn check_budgets(truth_paths: u64, spps: &[u32], paths: &[u64]) -> Result<()> {
    if spps.contains(&0) || paths.contains(&0) || truth_paths == 0 {
        return Err(Error::param("budgets", "0", "budgets >= 1"));
    }
    Ok(())
}

/// Renders the truth (`truth_paths`, seed `opts.seed + 1_000_003`), the
/// reference at each of `paths` and every model method of the scene at each
/// of `spps` (seed `opts.seed`), and returns the curves (first pass only)
/// and the truth's wall time.
pub fn error_vs_time(
    scene: &Scene,
    opts: &RenderOptions,
    truth_paths: u64,
    spps: &[u32],
    paths: &[u64],
) -> Result<(Vec<Curve>, f64)> {
    check_budgets(truth_paths, spps, paths)?;
    // The curves are of the first pass: render only that one (a density
    // sweep's other passes were rendered and thrown away).
    let mut one_pass = scene.clone();
    one_pass.density_sweep.truncate(1);
    let first = |o: &RenderOptions| -> Result<Vec<(Target, Image, f64, f64)>> {
        let first_pass = render_scene(&one_pass, o)?.swap_remove(0);
        Ok(first_pass
            .rendered
            .into_iter()
            .map(|r| (r.target, r.image, r.wall_s, r.setup_s))
            .collect())
    };
    let mut o = opts.clone();
    o.targets = vec![Target::Reference];
    o.reference_paths = Some(truth_paths);
    o.seed = opts.seed.wrapping_add(1_000_003);
    o.out = opts.out.join("truth");
    let truth = first(&o)?;
    let (_, truth_img, truth_s, _) = &truth[0];

    let mut curves: Vec<Curve> = Vec::new();
    let mut push =
        |method: Target, p: CurvePoint| match curves.iter_mut().find(|c| c.method == method) {
            Some(c) => c.points.push(p),
            None => curves.push(Curve {
                method,
                points: vec![p],
            }),
        };
    for &n in paths {
        let mut o = opts.clone();
        o.targets = vec![Target::Reference];
        o.reference_paths = Some(n);
        o.out = opts.out.join(format!("reference_{n}"));
        for (t, img, wall_s, setup_s) in first(&o)? {
            push(
                t,
                CurvePoint {
                    budget: n,
                    wall_s,
                    setup_s,
                    rel_rmse: rel_error(&img, truth_img),
                    resolution: resolution(&img, truth_img),
                },
            );
        }
    }
    let methods: Vec<Target> = scene.methods.iter().map(|&m| Target::Model(m)).collect();
    // (No model methods: nothing to add; empty targets would mean "the
    // scene's methods and the reference".)
    for &spp in spps.iter().filter(|_| !methods.is_empty()) {
        let mut o = opts.clone();
        o.targets = methods.clone();
        o.spp = Some(spp);
        for (t, img, wall_s, setup_s) in first(&o)? {
            push(
                t,
                CurvePoint {
                    budget: spp as u64,
                    wall_s,
                    setup_s,
                    rel_rmse: rel_error(&img, truth_img),
                    resolution: resolution(&img, truth_img),
                },
            );
        }
    }
    for c in &mut curves {
        c.points.sort_by_key(|p| p.budget);
    }
    Ok((curves, *truth_s))
}

/// A budget in the plots and tables: spp as is, paths as `4e6` where that
/// is exact.
pub fn count(n: u64) -> String {
    let k = (n as f64).log10().floor() as u32;
    match 10u64.checked_pow(k) {
        Some(p) if n >= 10_000 && n.is_multiple_of(p) => format!("{}e{k}", n / p),
        _ => n.to_string(),
    }
}

/// The log-log error-vs-render-time plot (reference dashed, models in the
/// palette, every point marked with its budget) as PNG at `path` and as
/// SVG beside it (same stem, `.svg`).
pub fn plot_curves(path: &Path, scene: &str, curves: &[Curve]) -> Result<()> {
    use crate::jobs::plot::{Axes, Series, chart, chart_svg};
    let series: Vec<Series> = curves
        .iter()
        .enumerate()
        .map(|(k, c)| {
            // An unresolved error at its bound, so the point stays on the
            // log axis and says what it is.
            let pts = c
                .points
                .iter()
                .map(|p| (p.render_s(), p.error_bound()))
                .collect();
            let bound = |p: &CurvePoint, label: String| {
                if p.resolved() {
                    label
                } else {
                    format!("{label} (bound)")
                }
            };
            let (series, marks) = if c.method == Target::Reference {
                let marks = c.points.iter().map(|p| bound(p, count(p.budget))).collect();
                (Series::dashed("reference (paths)", pts, k), marks)
            } else {
                let marks = c
                    .points
                    .iter()
                    .map(|p| bound(p, p.budget.to_string()))
                    .collect();
                (
                    Series::line(format!("{} (spp)", c.method.name()), pts, k),
                    marks,
                )
            };
            series.marked(marks)
        })
        .collect();
    let axes = Axes {
        title: format!("{scene}: error vs render time"),
        x_label: "render time per budget [s] (set-up excluded)".into(),
        y_label: "relative RMSE vs truth (noise included)".into(),
        log_x: true,
        log_y: true,
    };
    chart(path, &axes, &series)?;
    chart_svg(&path.with_extension("svg"), &axes, &series)
}

/// A curve's (render time, error) points with both positive, by time.
fn time_error_points(curve: &Curve) -> Vec<(f64, f64)> {
    let mut pts: Vec<(f64, f64)> = curve
        .points
        .iter()
        .filter(|p| p.rel_rmse > 0.0 && p.render_s() > 0.0)
        .map(|p| (p.render_s(), p.rel_rmse))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    pts
}

/// The reference's render time to reach relative error `e`, read off its
/// curve: log-log interpolation between its points, and beyond them the
/// Monte Carlo law e ∝ t^(−1/2) from the nearest end point.
pub fn reference_time_for(reference: &Curve, e: f64) -> Option<f64> {
    let pts = time_error_points(reference);
    let (first, last) = (*pts.first()?, *pts.last()?);
    if e.is_nan() || e <= 0.0 {
        return None;
    }
    if e >= first.1 {
        return Some(first.0 * (first.1 / e).powi(2));
    }
    if e <= last.1 {
        return Some(last.0 * (last.1 / e).powi(2));
    }
    pts.windows(2).find_map(|w| {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        let between = (e1..=e0).contains(&e) || (e0..=e1).contains(&e);
        (between && e0 != e1).then(|| {
            let f = (e.ln() - e0.ln()) / (e1.ln() - e0.ln());
            (t0.ln() + f * (t1.ln() - t0.ln())).exp()
        })
    })
}

/// The reference's error after render time `t`, read off its curve: log-log
/// interpolation between its points, and beyond them e ∝ t^(−1/2) from the
/// nearest end point (the inverse of [`reference_time_for`]).
pub fn reference_error_at(reference: &Curve, t: f64) -> Option<f64> {
    let pts = time_error_points(reference);
    let (first, last) = (*pts.first()?, *pts.last()?);
    if t.is_nan() || t <= 0.0 {
        return None;
    }
    if t <= first.0 {
        return Some(first.1 * (first.0 / t).sqrt());
    }
    if t >= last.0 {
        return Some(last.1 * (last.0 / t).sqrt());
    }
    pts.windows(2).find_map(|w| {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        ((t0..=t1).contains(&t) && t0 != t1).then(|| {
            let f = (t.ln() - t0.ln()) / (t1.ln() - t0.ln());
            (e0.ln() + f * (e1.ln() - e0.ln())).exp()
        })
    })
}

/// How much faster a model is than brute force at the model's own error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Speedup {
    pub method: Target,
    /// The model point with the largest ratio: its budget (spp), wall time
    /// (set-up included), set-up and error (written inline).
    #[serde(flatten)]
    pub point: CurvePoint,
    /// Reference render time to the same error ([`reference_time_for`]),
    /// read at [`CurvePoint::error_bound`].
    pub reference_s: f64,
    /// `reference_s` over the model's render time (set-up excluded).
    pub ratio: f64,
    /// The truth does not resolve the point's error
    /// ([`CurvePoint::resolved`]): the error is read at its upper bound, so
    /// the ratios are lower bounds.
    #[serde(default)]
    pub lower_bound: bool,
    /// The model's lowest error over its budgets (its floor, bias-bound),
    /// an upper bound where the truth does not resolve it.
    #[serde(with = "crate::doc::nan_as_null")]
    pub floor: f64,
    /// `floor` is an upper bound ([`CurvePoint::error_bound`]).
    #[serde(default)]
    pub floor_bound: bool,
    /// At equal time: the reference's error after the model's render time
    /// at this budget ([`reference_error_at`]); over the model's error it
    /// is how many times lower the model's error is.
    #[serde(default = "f64_nan", with = "crate::doc::nan_as_null")]
    pub reference_error: f64,
}

fn f64_nan() -> f64 {
    f64::NAN
}

impl Speedup {
    /// The speed-up with the model's set-up counted: `reference_s / wall_s`.
    pub fn ratio_with_setup(&self) -> f64 {
        self.reference_s / self.point.wall_s.max(1e-9)
    }

    /// How many times lower the model's error is than the reference's in
    /// equal time (a lower bound with [`Speedup::lower_bound`]).
    pub fn error_ratio(&self) -> f64 {
        self.reference_error / self.point.error_bound()
    }

    /// "≥ " before a ratio that is a lower bound, else nothing.
    pub fn at_least(&self) -> &'static str {
        if self.lower_bound { "≥ " } else { "" }
    }

    /// The model's error as a percentage: "< x %" at its upper bound where
    /// the truth does not resolve it.
    pub fn error_text(&self) -> String {
        super::report::err(Some(self.point.rel_rmse), self.point.resolution)
    }

    /// The floor as a percentage, "< x %" where it is an upper bound.
    pub fn floor_text(&self) -> String {
        let p = super::report::pct(Some(self.floor));
        if self.floor_bound {
            format!("< {p}")
        } else {
            p
        }
    }
}

/// Per model curve: the point where it beats brute force by the most (at
/// render time; the set-up is stated beside it).
pub fn speedups(curves: &[Curve]) -> Vec<Speedup> {
    let Some(reference) = curves.iter().find(|c| c.method == Target::Reference) else {
        return Vec::new();
    };
    curves
        .iter()
        .filter(|c| c.method != Target::Reference)
        .filter_map(|c| {
            let lowest = c
                .points
                .iter()
                .min_by(|a, b| a.error_bound().total_cmp(&b.error_bound()))?;
            let (floor, floor_bound) = (lowest.error_bound(), !lowest.resolved());
            c.points
                .iter()
                .filter_map(|p| {
                    let t = reference_time_for(reference, p.error_bound())?;
                    Some(Speedup {
                        method: c.method,
                        point: p.clone(),
                        reference_s: t,
                        ratio: t / p.render_s().max(1e-9),
                        lower_bound: !p.resolved(),
                        floor,
                        floor_bound,
                        reference_error: reference_error_at(reference, p.render_s())
                            .unwrap_or(f64::NAN),
                    })
                })
                .max_by(|a, b| a.ratio.total_cmp(&b.ratio))
        })
        .collect()
}

/// What `compare` does besides the main render.
#[derive(Clone, Debug)]
pub struct CompareSettings {
    /// Error-vs-time curves: truth paths, model spp list, reference paths
    /// list; `None` skips them.
    pub curves: Option<(u64, Vec<u32>, Vec<u64>)>,
    /// Measure what the analysis's skips saved (a second render with the
    /// analysis off), when it skipped anything.
    pub measure_savings: bool,
}

/// The `format` of `compare.json`.
pub const COMPARE_FORMAT: &str = "svkernel.compare";
pub const COMPARE_VERSION: u32 = 1;

/// `compare.json`: the scene analysis, what its skips saved, the main
/// render ([`RenderDoc`]) and the error-vs-time curves.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CompareDoc {
    /// [`COMPARE_FORMAT`], [`COMPARE_VERSION`].
    pub format: String,
    pub version: u32,
    pub scene: PathBuf,
    pub scene_name: String,
    /// The scene analysis, with the meta-model range effect for `learned`.
    pub analysis: Plan,
    /// The effects skipped (`analysis.effects` not needed).
    pub skipped: Vec<EffectKind>,
    /// What the skips saved, measured (`None`: nothing to measure, or not
    /// asked).
    pub savings: Option<Savings>,
    pub render: RenderDoc,
    pub curves: CurvesDoc,
    pub provenance: Provenance,
}

/// What the scene analysis's skips saved: the same render with the
/// analysis off.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Savings {
    /// How it was measured.
    pub how: String,
    /// In all, over the targets.
    pub saved_s: f64,
    pub targets: Vec<TargetSavings>,
}

/// [`Savings`] of one target.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetSavings {
    pub method: Target,
    pub with_skips_s: f64,
    pub without_skips_s: f64,
    pub saved_s: f64,
}

/// The error-vs-time curves of [`CompareDoc`] (empty without them).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvesDoc {
    /// The truth's paths and wall time.
    pub truth_paths: Option<u64>,
    pub truth_wall_s: Option<f64>,
    /// What the error is, in words.
    pub error: String,
    pub curves: Vec<Curve>,
    pub speedups: Vec<Speedup>,
}

impl crate::doc::Document for CompareDoc {
    const FORMAT: &'static str = COMPARE_FORMAT;
    const VERSION: u32 = COMPARE_VERSION;
}

/// One line of the speed-up summary.
impl std::fmt::Display for Speedup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:<11} {:>5} spp {:>7.3} s (+{:.3} s set-up)  error {:>8}  reference needs \
             {:>7.3} s  ({a}{:.2}×; {a}{:.2}× with set-up); in equal time it errs {:.2} % \
             ({a}{:.2}×)",
            self.method.name(),
            self.point.budget,
            self.point.render_s(),
            self.point.setup_s,
            self.error_text(),
            self.reference_s,
            self.ratio,
            self.ratio_with_setup(),
            100.0 * self.reference_error,
            self.error_ratio(),
            a = self.at_least(),
        )
    }
}

/// The terminal summary: method table per pass, skipped effects, measured
/// savings, error-vs-time speed-ups.
impl std::fmt::Display for CompareDoc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for pass in &self.render.passes {
            writeln!(f, "scene {}, pass {}:", self.scene_name, pass.tag)?;
            write!(f, "{pass}")?;
        }
        let skipped: Vec<&str> = self.skipped.iter().map(|e| e.name()).collect();
        writeln!(f, "  skipped: {}", skipped.join(", "))?;
        if let Some(s) = &self.savings {
            writeln!(f, "  the skips saved {:.2} s (measured)", s.saved_s)?;
        }
        for p in &self.curves.speedups {
            writeln!(f, "  {p}")?;
        }
        Ok(())
    }
}

/// A finished comparison: the `compare.json` document and the report's
/// blocks (the demo gathers several into one page).
pub struct Comparison {
    pub doc: CompareDoc,
    pub blocks: Vec<Block>,
}

/// `svkernel compare` on one scene into `opts.out`: the reference and every
/// method with metrics and images ([`super::render`]), the error-vs-time
/// curves, the scene analysis and what its skips saved; writes
/// `compare.json`, `report.html` (self-contained) and `report.md`.
pub fn compare_scene(
    scene: &Scene,
    opts: &RenderOptions,
    settings: &CompareSettings,
) -> Result<Comparison> {
    if let Some((truth, spps, paths)) = &settings.curves {
        check_budgets(*truth, spps, paths)?;
    }
    // The scene medium's models, found (or built) once for every render
    // below.
    let opts = &super::render::with_scene_models(scene, opts)?;
    let mut plan = analyse(scene, opts.analysis);
    let passes = render_scene(scene, opts)?;
    let render = write_outputs(scene, opts, &passes)?;
    super::output::write_colorbar(&opts.out.join("colorbar.png"), 256, 12)?;
    let (curves, truth_s) = match &settings.curves {
        Some((truth, spps, paths)) => {
            let mut o = opts.clone();
            o.out = opts.out.join("curves");
            let (c, t) = error_vs_time(scene, &o, *truth, spps, paths)?;
            plot_curves(&opts.out.join("error_time.png"), &scene.name, &c)?;
            (c, Some(t))
        }
        None => (Vec::new(), None),
    };
    let savings = if settings.measure_savings && plan.skips_work() {
        Some(measure_savings(scene, opts)?)
    } else {
        None
    };
    let extension = passes.first().and_then(|p| p.extension.as_ref());
    if let Some(effect) = range_effect(scene, &plan, opts, extension)? {
        plan.effects.push(effect);
    }
    let skipped = plan.skipped().map(|e| e.name).collect();
    let doc = CompareDoc {
        format: COMPARE_FORMAT.into(),
        version: COMPARE_VERSION,
        scene: scene.path.clone(),
        scene_name: scene.name.clone(),
        analysis: plan,
        skipped,
        savings,
        render,
        curves: CurvesDoc {
            truth_paths: settings.curves.as_ref().map(|c| c.0),
            truth_wall_s: truth_s,
            error: "relative RMSE against the truth (independent seed), the truth's variance \
                    subtracted, the method's noise included"
                .into(),
            speedups: speedups(&curves),
            curves,
        },
        provenance: Provenance::current(),
    };
    crate::jobs::store::write_json_atomic(&opts.out.join("compare.json"), &doc)?;
    let blocks = report_blocks(&doc, &opts.out);
    let mut page = blocks.clone();
    page.extend(glossary());
    write_report(
        &opts.out,
        "report",
        &format!("svkernel compare: {}", scene.name),
        &page,
    )?;
    Ok(Comparison { doc, blocks })
}

/// The kernel meta-model's albedo range against the scene's, for
/// `learned`: nothing to simulate, or what the extension did.
fn range_effect(
    scene: &Scene,
    plan: &crate::render::analysis::Plan,
    opts: &RenderOptions,
    extension: Option<&super::extend::Extension>,
) -> Result<Option<Effect>> {
    if !scene.methods.contains(&Method::Learned) {
        return Ok(None);
    }
    let [lo, hi] = plan.albedo_range;
    // Albedos to three decimals in the text.
    let r = |v: f64| (v * 1e3).round() / 1e3;
    let (lo, hi) = (r(lo), r(hi));
    // The scene medium's meta-model (`compare_scene` resolved the models).
    // Its outer model's box, where it has one.
    let model = &opts.models.meta;
    let trained = model.alpha_range();
    let effect = range_albedo_effect(plan, opts, extension, (lo, hi), trained, r);
    // The other axis of the range: the optical pair distances the image can
    // ask for, against the trained ones (beyond, the kernel keeps the
    // normalised shape of the largest trained distance, scaled with λ).
    let d_max = model.d_range()[1];
    let reach = plan.max_optical_distance;
    Ok(Some(Effect {
        detail: format!(
            "{}; optical pair distances reach ρd ≈ {:.3} MFP, trained up to {:.3}{}",
            effect.detail,
            reach,
            d_max,
            if reach > d_max {
                ": beyond it the kernel keeps the shape of the largest trained distance, \
                 scaled with λ = ρd/2 + 1"
            } else {
                ""
            }
        ),
        ..effect
    }))
}

/// The albedo half of [`range_effect`].
fn range_albedo_effect(
    plan: &crate::render::analysis::Plan,
    opts: &RenderOptions,
    extension: Option<&super::extend::Extension>,
    (lo, hi): (f64, f64),
    trained: [f64; 2],
    r: impl Fn(f64) -> f64,
) -> Effect {
    match extension {
        None if plan.homogeneous => Effect {
            name: EffectKind::KernelSimulation,
            needed: false,
            detail: format!(
                "the material is homogeneous (α = {lo}): learned is the profile, no kernel to \
                 simulate or fit"
            ),
        },
        None if opts.cache.is_none()
            && super::extend::missing(plan.albedo_range, trained).is_some() =>
        {
            Effect {
                name: EffectKind::KernelSimulation,
                needed: false,
                detail: format!(
                    "the scene's α ∈ [{lo}, {hi}] leaves the trained [{}, {}], but extension is \
                     off: learned clamps there",
                    trained[0], trained[1]
                ),
            }
        }
        None => Effect {
            name: EffectKind::KernelSimulation,
            needed: false,
            detail: format!(
                "the scene's α ∈ [{lo}, {hi}] lies inside the meta-model's trained [{}, {}]: \
                 nothing to simulate or fit",
                trained[0], trained[1]
            ),
        },
        Some(e) => Effect {
            name: EffectKind::KernelSimulation,
            needed: true,
            detail: if e.cached {
                format!(
                    "α ∈ [{}, {}] lies outside the trained [{}, {}]: extension reused from the \
                     cache ({}), no simulation",
                    r(e.missing[0]),
                    r(e.missing[1]),
                    trained[0],
                    trained[1],
                    e.model.display()
                )
            } else {
                format!(
                    "α ∈ [{}, {}] lies outside the trained [{}, {}]: simulated {} paths at α = \
                     {:?} and fitted in {:.1} s, only that range (cached as {})",
                    r(e.missing[0]),
                    r(e.missing[1]),
                    trained[0],
                    trained[1],
                    e.paths,
                    e.albedos,
                    e.wall_s,
                    e.model.display()
                )
            },
        },
    }
}

/// Renders the scene twice at the same settings, with the analysis on and
/// off (reference at ≤ 1e6 paths, its times scaled to the full count), and
/// returns each target's measured saving.
fn measure_savings(scene: &Scene, opts: &RenderOptions) -> Result<Savings> {
    let paths = opts.reference_paths.unwrap_or(scene.reference_paths);
    let probe = paths.min(1_000_000);
    let dir = opts.out.join("savings");
    let mut times: Vec<Vec<(Target, f64)>> = Vec::new();
    for analysis in [true, false] {
        let o = RenderOptions {
            analysis,
            reference_paths: Some(probe),
            out: dir.clone(),
            run: Default::default(),
            reference_tallies: Vec::new(),
            shard: None,
            ..opts.clone()
        };
        let t = render_scene(scene, &o)?
            .iter()
            .flat_map(|p| p.rendered.iter().map(|r| (r.target, r.wall_s)))
            .fold(Vec::<(Target, f64)>::new(), |mut acc, (t, s)| {
                match acc.iter_mut().find(|(u, _)| *u == t) {
                    Some((_, v)) => *v += s,
                    None => acc.push((t, s)),
                }
                acc
            });
        times.push(t);
    }
    let _ = std::fs::remove_dir_all(&dir);
    let scale = paths as f64 / probe as f64;
    let mut total = 0.0;
    let targets: Vec<TargetSavings> = times[0]
        .iter()
        .zip(&times[1])
        .map(|(&(t, on), &(_, off))| {
            let k = if t == Target::Reference { scale } else { 1.0 };
            total += k * (off - on);
            TargetSavings {
                method: t,
                with_skips_s: k * on,
                without_skips_s: k * off,
                saved_s: k * (off - on),
            }
        })
        .collect();
    Ok(Savings {
        how: format!(
            "the same render with the analysis off; reference timed at {} paths and scaled to \
             {}",
            count(probe),
            count(paths)
        ),
        saved_s: total,
        targets,
    })
}

/// The report of one comparison (module docs of [`super::report`]): a
/// verdict, the scene, its input maps, what the analysis skipped, every
/// pass's images and errors, and what accuracy costs in time. The terms are
/// explained by [`glossary`], which the caller appends (once per page).
pub fn report_blocks(doc: &CompareDoc, out: &Path) -> Vec<Block> {
    use super::report::{num, pct};
    let render = &doc.render;
    let mut b = vec![
        Block::Heading(2, format!("Scene `{}`", doc.scene_name)),
        Block::Para(format!("Verdict: {}", verdict(doc))),
        Block::Para(scene_text(doc)),
    ];
    if let Some(first) = render.passes.first() {
        let dir = out.join(&first.tag);
        let mut inputs = vec![Some((albedo_caption(doc), dir.join("albedo.png")))];
        let density = dir.join("density.png");
        if let Some(super::render::DensitySource::Map { range }) =
            render.material.as_ref().map(|m| &m.density)
            && density.exists()
        {
            inputs.push(Some((
                format!(
                    "density (input): {}; black 0, white {}",
                    interval("ρ", *range),
                    short(range[1])
                ),
                density,
            )));
        }
        inputs.retain(|c| c.as_ref().is_some_and(|(_, p)| p.exists()));
        if !inputs.is_empty() {
            let maps = if inputs.len() > 1 { "maps" } else { "map" };
            b.push(Block::Heading(3, "Input".into()));
            b.push(Block::Grid {
                rows: vec![inputs],
                width: 160,
            });
            let rgb = render
                .material
                .as_ref()
                .is_some_and(|m| m.albedo_channels == 3);
            b.push(Block::Para(format!(
                "The input {} over the image window (half-width {} MFP), in linear levels{}; \
                 the renders below show the same window.",
                maps,
                render.half_width,
                if rgb {
                    " (per channel for the RGB albedo)"
                } else {
                    ""
                }
            )));
        }
    }
    b.push(Block::Heading(3, "What the scene calls for".into()));
    b.push(Block::table(
        &["effect", "simulated", "why"],
        doc.analysis
            .effects
            .iter()
            .map(|e| {
                vec![
                    e.name.to_string(),
                    if e.needed { "yes" } else { "skipped" }.into(),
                    e.detail.clone(),
                ]
            })
            .collect(),
    ));
    match &doc.savings {
        Some(sv) => {
            b.push(Block::Para(format!(
                "The skips saved {:.2} s in all (measured: {}).",
                sv.saved_s, sv.how
            )));
            b.push(Block::table(
                &["target", "with skips [s]", "without [s]", "saved [s]"],
                sv.targets
                    .iter()
                    .map(|t| {
                        vec![
                            t.method.name().to_string(),
                            num(Some(t.with_skips_s)),
                            num(Some(t.without_skips_s)),
                            num(Some(t.saved_s)),
                        ]
                    })
                    .collect(),
            ));
        }
        None => b.push(Block::Para(no_savings_text(doc))),
    }
    for pass in &render.passes {
        b.extend(pass_blocks(pass, out));
    }
    let curves = &doc.curves;
    if !curves.curves.is_empty() {
        let first = render.passes.first();
        b.push(Block::Heading(
            3,
            match first.and_then(|p| p.density.map(|r| (p, r))) {
                Some((p, r)) if render.passes.len() > 1 => {
                    format!("What accuracy costs in time (pass `{}`, ρ = {r})", p.tag)
                }
                _ => "What accuracy costs in time".into(),
            },
        ));
        b.push(Block::Figure {
            caption: format!(
                "relative RMSE against a truth of {} reference paths ({:.2} s, independent \
                 seed), each image's own noise included, against the render time of each \
                 budget (set-up excluded); the reference dashed; each marker is labelled with \
                 its budget: spp for the models, paths for the reference; \"(bound)\": an error \
                 the truth does not resolve, drawn at its upper bound",
                count(curves.truth_paths.unwrap_or(0)),
                curves.truth_wall_s.unwrap_or(0.0)
            ),
            path: out.join("error_time.png"),
        });
        b.push(Block::Para(setup_text(&curves.curves)));
        b.push(Block::table(
            &[
                "method",
                "spp",
                "render [s]",
                "set-up [s]",
                "rel RMSE (noise included)",
                "reference render time to same error [s]",
                "speed-up",
                "speed-up with set-up",
                "reference error in equal time",
                "error ratio in equal time",
                "error floor",
            ],
            curves
                .speedups
                .iter()
                .map(|p| {
                    vec![
                        p.method.name().to_string(),
                        p.point.budget.to_string(),
                        num(Some(p.point.render_s())),
                        num(Some(p.point.setup_s)),
                        p.error_text(),
                        num(Some(p.reference_s)),
                        format!("{}{:.2}×", p.at_least(), p.ratio),
                        format!("{}{:.2}×", p.at_least(), p.ratio_with_setup()),
                        pct(Some(p.reference_error)),
                        format!("{}{:.2}×", p.at_least(), p.error_ratio()),
                        p.floor_text(),
                    ]
                })
                .collect(),
        ));
        b.push(Block::Para(
            "Per model: the budget where it beats brute force by the most at render time. The \
             reference's time to the same error is read off its curve (log-log interpolation; \
             beyond its points, e ∝ t^(−1/2)); a speed-up below 1× means the reference is \
             faster at that error. In equal time: the reference's error after the model's \
             render time, read off the same curve, and how many times the model's error it is. \
             The floor is the model's lowest error over its budgets. An error written \"< x\" \
             is one the truth does not resolve: it is read at its upper bound x (two standard \
             deviations of the truth's noise), and the ratios beside it, marked ≥, are lower \
             bounds."
                .into(),
        ));
    }
    b
}

/// One pass's images, difference images and error table.
fn pass_blocks(pass: &super::render::PassDoc, out: &Path) -> Vec<Block> {
    use super::report::{err, num, pct};
    let dir = out.join(&pass.tag);
    let white = pass.white_point;
    let mut b = vec![Block::Heading(
        3,
        match pass.density {
            Some(r) => format!("Pass `{}` (ρ = {r})", pass.tag),
            None => "Images".into(),
        },
    )];
    let image = |name: String, file: String| {
        let path = dir.join(file);
        path.exists().then_some((name, path))
    };
    let top: Vec<_> = pass
        .methods
        .iter()
        .map(|m| image(m.method.name().into(), format!("{}.png", m.method.name())))
        .collect();
    // Each difference under its method; the reference's cell stays empty.
    let diffs: Vec<_> = pass
        .methods
        .iter()
        .map(|m| match m.method {
            Target::Reference => None,
            Target::Model(_) => {
                let n = m.method.name();
                image(format!("{n} − reference"), format!("{n}_diff.png"))
            }
        })
        .collect();
    let any_diff = diffs.iter().any(Option::is_some);
    let mut rows = vec![top];
    if any_diff {
        rows.push(diffs);
    }
    b.push(Block::Grid { rows, width: 160 });
    if any_diff {
        b.push(Block::Figure {
            caption: format!(
                "signed difference to the reference, channel mean: blue −{0:.4} … white 0 … red \
                 +{0:.4} (±25 % of the white point {1:.4}); images tone-mapped to the white \
                 point (the reference's 99.5th percentile)",
                0.25 * white,
                white
            ),
            path: out.join("colorbar.png"),
        });
    }
    let channels = pass
        .methods
        .iter()
        .find_map(|m| m.metrics.as_ref().map(|m| m.channels.len()))
        .unwrap_or(0);
    let mut header: Vec<String> = [
        "method",
        "time [s]",
        "of it set-up [s]",
        "rel RMSE (noise subtracted)",
        "rel bias",
    ]
    .map(String::from)
    .into();
    if channels == 3 {
        header.extend(["R", "G", "B"].iter().map(|c| format!("rel RMSE {c}")));
    }
    b.push(Block::Table {
        header,
        rows: pass
            .methods
            .iter()
            .map(|m| {
                let mt = m.metrics.as_ref();
                let mut row = vec![
                    m.method.name().to_string(),
                    num(Some(m.wall_s)),
                    num(Some(m.setup_s)),
                    err(mt.map(|x| x.rel_rmse), mt.map_or(0.0, |x| x.resolution)),
                    pct(mt.map(|x| x.rel_bias)),
                ];
                if channels == 3 {
                    row.extend((0..channels).map(|c| {
                        let x = mt.and_then(|x| x.channels.get(c));
                        err(x.map(|x| x.rel_rmse), x.map_or(0.0, |x| x.resolution))
                    }));
                }
                row
            })
            .collect(),
    });
    b
}

/// `v` to three decimals (a texel value in the text).
fn short(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}

/// "α ∈ [lo, hi]", or "α = v" for a single value (three decimals).
fn interval(name: &str, [lo, hi]: [f64; 2]) -> String {
    let (lo, hi) = (short(lo), short(hi));
    if lo == hi {
        format!("{name} = {lo}")
    } else {
        format!("{name} ∈ [{lo}, {hi}]")
    }
}

/// The albedo preview's caption.
fn albedo_caption(doc: &CompareDoc) -> String {
    match &doc.render.material {
        Some(m) => format!(
            "albedo (input{}): {}; black 0, white 1",
            match (m.albedo_channels, m.grey) {
                (1, _) => ", grey",
                (_, true) => ", RGB, three identical channels",
                _ => ", RGB",
            },
            interval("α", m.albedo_range)
        ),
        None => "albedo α (input); black 0, white 1".into(),
    }
}

/// The scene in one paragraph, every phrase from the documents.
fn scene_text(doc: &CompareDoc) -> String {
    let r = &doc.render;
    let light = match r.light.kind {
        crate::render::scene::LightKind::Collimated => "collimated (normal incidence)",
        crate::render::scene::LightKind::Diffuse => "diffuse",
    };
    let material = match &r.material {
        Some(m) => {
            let albedo = match (m.albedo_channels, m.grey) {
                (1, _) => "a grey albedo (one channel)".to_string(),
                (_, true) => "an RGB albedo of three identical channels (grey)".to_string(),
                _ => "an RGB albedo (three different channels)".to_string(),
            };
            let range = interval("α", m.albedo_range);
            let density = match &m.density {
                super::render::DensitySource::Unit => "no density map (ρ = 1)".to_string(),
                super::render::DensitySource::Map { range } if range[0] == range[1] => {
                    format!("a constant density map ({})", interval("ρ", *range))
                }
                super::render::DensitySource::Map { range } => {
                    format!("a density map with {}", interval("ρ", *range))
                }
                super::render::DensitySource::Sweep { values } => format!(
                    "a density sweep, ρ = {} (one pass each)",
                    crate::render::analysis::list(values)
                ),
            };
            format!(" Material: {albedo} with {range}; {density}.")
        }
        None => String::new(),
    };
    format!(
        "Scene file `{}`: {}² pixels over a window of half-width {} MFP; a {light} disk light of \
         radius {} MFP; observable {}.{material} Main render: {} spp per model ({}), {} \
         sampling, variant `{}`; reference {} paths; seed {}. Commit `{}`.",
        r.scene.display(),
        r.resolution,
        r.half_width,
        r.light.radius,
        match r.observable {
            crate::render::scene::Observable::Exitance => "exitance",
            crate::render::scene::Observable::Radiance => "radiance",
        },
        r.spp,
        match r.allocation {
            crate::render::estimator::Allocation::Uniform => "in every pixel",
            crate::render::estimator::Allocation::Adaptive => {
                "on average, shared by a pilot render"
            }
        },
        r.sampling.name(),
        match r.variant.as_str() {
            "" => format!(
                "default: density-scaled, vertex kernels, one pass, interior kernel above α {}, \
                 two-scale √(1 − α) mean split at b = {} MFP (split kernel: regimes)",
                crate::render::svbssrdf::INTERIOR_RAMP[0],
                crate::render::svbssrdf::SPACE_BLUR
            ),
            v => v.trim_start_matches('+').to_string(),
        },
        count(r.reference_paths),
        r.seed,
        r.provenance.git_commit.as_deref().unwrap_or("unknown"),
    )
}

/// Why no second render was timed, from what was skipped and why.
fn no_savings_text(doc: &CompareDoc) -> String {
    if doc.analysis.skips_work() {
        return "What the skips save was not measured here (no second render with the analysis \
                off was asked for)."
            .into();
    }
    let material = doc.render.material.as_ref();
    let mut facts = Vec::new();
    for e in doc.analysis.skipped() {
        match e.name {
            EffectKind::RgbChannels => facts.push("a one-channel albedo".to_string()),
            EffectKind::DensityPyramid => facts.push(
                match material.map(|m| &m.density) {
                    Some(super::render::DensitySource::Sweep { .. }) => {
                        "a constant density per pass (a sweep)"
                    }
                    _ => "no density map",
                }
                .to_string(),
            ),
            EffectKind::CollimatedProfile | EffectKind::DiffuseProfile => facts.push(format!(
                "a {} light, so one basis",
                doc.render.light.kind.name()
            )),
            EffectKind::AlbedoAggregation | EffectKind::KernelSimulation => {}
        }
    }
    if facts.is_empty() {
        "The analysis skips nothing the full renderer would do here, so no second render was \
         timed."
            .into()
    } else {
        format!(
            "Each skip of the analysis above follows from how the scene is written ({}): the \
             full renderer would do the same work, so no second render was timed.",
            facts.join(", ")
        )
    }
}

/// A duration in words: "0.25 ms", "6.3 ms", "34 ms", "1.25 s".
fn secs(s: f64) -> String {
    if !s.is_finite() {
        "—".into()
    } else if s < 0.001 {
        format!("{:.2} ms", 1e3 * s)
    } else if s < 0.01 {
        format!("{:.1} ms", 1e3 * s)
    } else if s < 1.0 {
        format!("{:.0} ms", 1e3 * s)
    } else {
        format!("{s:.2} s")
    }
}

/// The middle value of `v` (the mean of the middle two).
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// The models' set-up times, which the plotted times leave out.
fn setup_text(curves: &[Curve]) -> String {
    let setups: Vec<String> = curves
        .iter()
        .filter(|c| c.method != Target::Reference)
        .map(|c| {
            let s = median(c.points.iter().map(|p| p.setup_s).collect());
            format!("{} {}", c.method.name(), secs(s))
        })
        .collect();
    if setups.is_empty() {
        return "Times are the reference's render times (it has no set-up).".into();
    }
    format!(
        "Set-up time, not in the plotted times (what a model prepares once per scene and \
         material before its first sample, such as the kernel methods' pyramids; median over \
         the budgets): {}. The reference has no set-up.",
        setups.join(", ")
    )
}

/// The one-line verdict: the most accurate method of each pass against the
/// reference, and learned's speed-up over the reference at equal error.
pub fn verdict(doc: &CompareDoc) -> String {
    use super::report::{err, pct};
    // (name, rel RMSE, bias, resolution): the methods within the noise
    // first, then by error.
    let within = |m: &(&str, f64, f64, f64)| m.1 < m.3 || m.1 == 0.0;
    let best = |pass: &super::render::PassDoc| {
        let mut ranked: Vec<(&str, f64, f64, f64)> = pass
            .methods
            .iter()
            .filter_map(|m| {
                let x = m.metrics.as_ref()?;
                x.rel_rmse.is_finite().then_some((
                    m.method.name(),
                    x.rel_rmse,
                    x.rel_bias,
                    x.resolution,
                ))
            })
            .collect();
        ranked.sort_by(|a, b| within(b).cmp(&within(a)).then(a.1.total_cmp(&b.1)));
        ranked
    };
    let passes = &doc.render.passes;
    let ranked: Vec<_> = passes.iter().map(best).collect();
    let mut text = match ranked.first() {
        None => "no model method was measured against the reference".to_string(),
        Some(r) if r.is_empty() => "no model method was measured against the reference".into(),
        Some(_) if passes.len() > 1 => {
            let winners: Vec<&str> = ranked
                .iter()
                .filter_map(|r| r.first().map(|w| w.0))
                .collect();
            if winners.iter().all(|w| *w == winners[0]) {
                let errors: Vec<String> = ranked
                    .iter()
                    .zip(passes)
                    .filter_map(|(r, p)| {
                        let w = r.first()?;
                        Some(format!(
                            "{} at ρ = {}",
                            err(Some(w.1), w.3),
                            p.density.map_or("the map".into(), |d| d.to_string())
                        ))
                    })
                    .collect();
                format!(
                    "{} is the most accurate against the reference in all {} passes (rel RMSE \
                     {})",
                    winners[0],
                    passes.len(),
                    errors.join(", ")
                )
            } else {
                let each: Vec<String> = ranked
                    .iter()
                    .zip(passes)
                    .filter_map(|(r, p)| {
                        let w = r.first()?;
                        Some(format!(
                            "{} at ρ = {} ({})",
                            w.0,
                            p.density.map_or("the map".into(), |d| d.to_string()),
                            err(Some(w.1), w.3)
                        ))
                    })
                    .collect();
                format!(
                    "the most accurate against the reference: {}",
                    each.join(", ")
                )
            }
        }
        Some(r) => {
            let tied: Vec<&str> = r.iter().filter(|m| within(m)).map(|m| m.0).collect();
            let head = if tied.len() > 1 {
                format!(
                    "{} agree with the reference to within its noise",
                    crate::render::analysis::list_names(&tied)
                )
            } else {
                format!(
                    "{} is the most accurate against the reference (rel RMSE {}, bias {})",
                    r[0].0,
                    err(Some(r[0].1), r[0].3),
                    pct(Some(r[0].2))
                )
            };
            match r.get(tied.len().max(1)) {
                Some(next) => format!("{head}; next {} ({})", next.0, err(Some(next.1), next.3)),
                None => head,
            }
        }
    };
    let learned = doc
        .curves
        .speedups
        .iter()
        .find(|s| s.method == Target::Model(Method::Learned));
    if let Some(s) = learned {
        let how = |ratio: f64| {
            if ratio >= 1.0 {
                format!(
                    "{}{ratio:.1}× faster",
                    if s.lower_bound { "at least " } else { "" }
                )
            } else {
                format!("{:.1}× slower", 1.0 / ratio)
            }
        };
        let pass = match passes.first() {
            Some(p) if passes.len() > 1 => format!(" (pass `{}`)", p.tag),
            _ => String::new(),
        };
        text.push_str(&format!(
            ". At equal error{pass} learned renders {} than the reference ({} error at {} spp: \
             {} against the reference's {}; with its {} set-up counted, {}). In equal time \
             the reference errs {}, {}{:.1}× as much",
            how(s.ratio),
            s.error_text(),
            s.point.budget,
            secs(s.point.render_s()),
            secs(s.reference_s),
            secs(s.point.setup_s),
            how(s.ratio_with_setup()),
            pct(Some(s.reference_error)),
            if s.lower_bound { "at least " } else { "" },
            s.error_ratio(),
        ));
    }
    text.push('.');
    text
}

/// The terms of the compare reports, once per page.
pub fn glossary() -> Vec<Block> {
    let rows = [
        (
            "rel RMSE (noise subtracted)",
            "√(max(0, Σ(m − r)² − Σ(σ_m² + σ_r²)) / Σr²) over the pixels and channels of a \
             method's image m against the reference r, with σ² each pixel's estimated variance: \
             both images' own noise is subtracted, so it measures the method's bias pattern, \
             not its noise.",
        ),
        (
            "\"< x\"",
            "an error below what the two images' noise resolves (two standard deviations of \
             the noise-subtracted squared error): the images differ by no more than their noise \
             explains, and the error is at most x; more samples and reference paths would \
             resolve a smaller one.",
        ),
        (
            "rel bias",
            "Σ(m − r) / Σr: the mean relative offset of the method's image (positive: brighter \
             than the reference).",
        ),
        (
            "rel RMSE (noise included)",
            "in the error-vs-time curves: against a truth (the reference at a high budget, \
             independent seed) with only the truth's variance subtracted; the method's own noise \
             stays in, since that is what its time buys.",
        ),
        (
            "spp",
            "samples per pixel: the light samples a model method takes per pixel, on \
             average over the image with the adaptive allocation, which gives each pixel a \
             share that follows its value in a pilot render at half the resolution (the \
             reference's budget is its number of paths).",
        ),
        (
            "set-up time",
            "what a model prepares once per scene and material before its first sample (the \
             kernel methods build their albedo and density pyramids); the tables give it beside \
             the time, the curves leave it out. The material is shared: `manual` and `learned` \
             read the same pyramids, built by whichever renders first, and the budgets of the \
             curves reuse them.",
        ),
        (
            "speed-up at equal error",
            "the reference's render time to reach a model's error (read off the reference's \
             curve) over the model's render time at that error; above 1× the model is faster. \
             \"with set-up\" adds the model's set-up to its time.",
        ),
        (
            "error floor",
            "a model's lowest error over its budgets: where more samples stop helping (its bias).",
        ),
        (
            "≥ in the curves",
            "a speed-up or error ratio read at the upper bound of an error that the truth does \
             not resolve (\"< x\"): a lower bound.",
        ),
    ];
    vec![
        Block::Heading(2, "Terms".into()),
        Block::table(
            &["term", "meaning"],
            rows.iter()
                .map(|(t, m)| vec![t.to_string(), m.to_string()])
                .collect(),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve(name: &str, pts: &[(f64, f64)]) -> Curve {
        Curve {
            method: Target::parse(name).unwrap(),
            points: pts
                .iter()
                .map(|&(wall_s, rel_rmse)| CurvePoint {
                    budget: 1,
                    wall_s,
                    setup_s: 0.0,
                    rel_rmse,
                    resolution: 0.0,
                })
                .collect(),
        }
    }

    #[test]
    fn an_unresolved_error_gives_a_lower_bound_on_the_speed_up() {
        let r = curve("reference", &[(1.0, 0.1), (100.0, 0.01)]);
        let mut m = curve("learned", &[(0.5, 0.05), (2.0, 0.0)]);
        m.points[1].resolution = 0.005;
        let s = &speedups(&[r, m])[0];
        // 0.005 costs the reference 400 s: at least 200× at 2 s, where the
        // resolved point gives 8×.
        assert!(s.lower_bound && s.floor_bound, "{s:?}");
        assert!((s.ratio - 200.0).abs() < 1e-9, "{s:?}");
        assert_eq!(
            (s.at_least(), s.error_text()),
            ("≥ ", "< 0.5 %".to_string())
        );
    }

    #[test]
    fn budgets_read_as_counts() {
        assert_eq!(count(4_000_000), "4e6");
        assert_eq!(count(10_000), "1e4");
        assert_eq!(count(2_500_000), "2500000");
        assert_eq!((count(64), count(0)), ("64".into(), "0".into()));
    }

    #[test]
    fn reference_time_interpolates_and_extrapolates_like_monte_carlo() {
        let r = curve("reference", &[(1.0, 0.1), (100.0, 0.01)]);
        // Inside: log-log interpolation (this curve is exactly e = 0.1/√t).
        let t = reference_time_for(&r, 0.1 / 10f64.sqrt()).unwrap();
        assert!((t - 10.0).abs() < 1e-9, "{t}");
        // Below its best error: e ∝ t^(−1/2) from the last point.
        assert!((reference_time_for(&r, 0.001).unwrap() - 1e4).abs() < 1e-6);
        // Above its worst: the same law from the first point.
        assert!((reference_time_for(&r, 1.0).unwrap() - 0.01).abs() < 1e-12);
        let m = curve("learned", &[(0.5, 0.05), (2.0, 0.02)]);
        let s = &speedups(&[r.clone(), m])[0];
        // 0.02 costs the reference 25 s: 12.5× at 2 s (4 s at 0.05: 8×).
        assert!((s.ratio - 12.5).abs() < 1e-9 && s.floor == 0.02, "{s:?}");
        // In equal time (2 s) the reference errs 0.1/√2; the inverse reading
        // agrees with the forward one everywhere, inside and beyond.
        assert!(
            (s.reference_error - 0.1 / 2f64.sqrt()).abs() < 1e-12,
            "{s:?}"
        );
        for t in [0.01, 1.0, 10.0, 100.0, 1e4] {
            let e = reference_error_at(&r, t).unwrap();
            assert!(
                (reference_time_for(&r, e).unwrap() / t - 1.0).abs() < 1e-9,
                "{t}"
            );
        }
    }
}
