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
}

impl CurvePoint {
    /// The render time: `wall_s` less the set-up.
    pub fn render_s(&self) -> f64 {
        self.wall_s - self.setup_s
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
                },
            );
        }
    }
    for c in &mut curves {
        c.points.sort_by_key(|p| p.budget);
    }
    Ok((curves, *truth_s))
}

/// The log-log error-vs-time plot (reference dashed, models in the palette)
/// as PNG at `path` and as SVG beside it (same stem, `.svg`).
pub fn plot_curves(path: &Path, scene: &str, curves: &[Curve]) -> Result<()> {
    use crate::jobs::plot::{Axes, Series, chart, chart_svg};
    let series: Vec<Series> = curves
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let pts = c.points.iter().map(|p| (p.wall_s, p.rel_rmse)).collect();
            if c.method == Target::Reference {
                Series::dashed(c.method.name(), pts, k)
            } else {
                Series::line(c.method.name(), pts, k)
            }
        })
        .collect();
    let axes = Axes {
        title: format!("{scene}: error vs time (reference dashed)"),
        x_label: "wall time [s]".into(),
        y_label: "relative RMSE vs truth".into(),
        log_x: true,
        log_y: true,
    };
    chart(path, &axes, &series)?;
    chart_svg(&path.with_extension("svg"), &axes, &series)
}

/// The reference's wall time to reach relative error `e`, read off its
/// curve: log-log interpolation between its points, and beyond them the
/// Monte Carlo law e ∝ t^(−1/2) from the nearest end point.
pub fn reference_time_for(reference: &Curve, e: f64) -> Option<f64> {
    let mut pts: Vec<(f64, f64)> = reference
        .points
        .iter()
        .filter(|p| p.rel_rmse > 0.0 && p.wall_s > 0.0)
        .map(|p| (p.wall_s, p.rel_rmse))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
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

/// How much faster a model is than brute force at the model's own error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Speedup {
    pub method: Target,
    /// The model point with the largest ratio: its budget (spp), time and
    /// error.
    pub budget: u64,
    pub wall_s: f64,
    pub rel_rmse: f64,
    /// Reference time to the same error ([`reference_time_for`]).
    pub reference_s: f64,
    /// `reference_s / wall_s`.
    pub ratio: f64,
    /// The model's lowest error over its budgets (its floor, bias-bound).
    #[serde(with = "crate::doc::nan_as_null")]
    pub floor: f64,
}

/// Per model curve: the point where it beats brute force by the most.
pub fn speedups(curves: &[Curve]) -> Vec<Speedup> {
    let Some(reference) = curves.iter().find(|c| c.method == Target::Reference) else {
        return Vec::new();
    };
    curves
        .iter()
        .filter(|c| c.method != Target::Reference)
        .filter_map(|c| {
            let floor = c
                .points
                .iter()
                .map(|p| p.rel_rmse)
                .fold(f64::INFINITY, f64::min);
            c.points
                .iter()
                .filter_map(|p| {
                    let t = reference_time_for(reference, p.rel_rmse)?;
                    Some(Speedup {
                        method: c.method,
                        budget: p.budget,
                        wall_s: p.wall_s,
                        rel_rmse: p.rel_rmse,
                        reference_s: t,
                        ratio: t / p.wall_s.max(1e-9),
                        floor,
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

impl CompareDoc {
    /// Reads `compare.json`, checking its format and version.
    pub fn load(path: &Path) -> Result<CompareDoc> {
        crate::jobs::store::load(path)
    }
}

impl crate::doc::Document for CompareDoc {
    const FORMAT: &'static str = COMPARE_FORMAT;
    const VERSION: u32 = COMPARE_VERSION;

    fn validate(&self, _origin: &Path) -> Result<()> {
        Ok(())
    }
}

/// One line of the speed-up summary.
impl std::fmt::Display for Speedup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:<11} {:>5} spp {:>7.2} s  error {:>6.2} %  reference needs {:>8.2} s  ({:.1}×)",
            self.method.name(),
            self.budget,
            self.wall_s,
            100.0 * self.rel_rmse,
            self.reference_s,
            self.ratio,
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
    write_report(
        &opts.out,
        "report",
        &format!("svkernel compare: {}", scene.name),
        &blocks,
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
    let model = opts.models.meta.all.clone();
    let trained = model.alpha_range;
    let effect = range_albedo_effect(plan, opts, extension, (lo, hi), trained, r);
    // The other axis of the range: the optical pair distances the image can
    // ask for, against the trained ones (beyond, the kernel keeps the
    // normalised shape of the largest trained distance, scaled with λ).
    let d_max = model.ln_d_range[1].exp();
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
            "the same render with the analysis off; reference timed at {probe} paths and \
             scaled to {paths}"
        ),
        saved_s: total,
        targets,
    })
}

/// The report of one comparison (module docs of [`super::report`]).
pub fn report_blocks(doc: &CompareDoc, out: &Path) -> Vec<Block> {
    use super::report::{err, num, pct};
    let render = &doc.render;
    let mut b = vec![
        Block::Heading(2, format!("Scene `{}`", doc.scene_name)),
        Block::Para(format!(
            "Scene file `{}`; {}² pixels, half-width {} MFP; {} light of radius {} MFP; \
             observable {}; {} spp, {} sampling, variant `{}`; reference {} paths, seed {}. \
             Commit `{}`.",
            render.scene.display(),
            render.resolution,
            render.half_width,
            light_name(&render.light.kind),
            render.light.radius,
            observable_name(render.observable),
            render.spp,
            render.sampling.name(),
            match render.variant.as_str() {
                "" => "default: density-scaled, vertex kernels, one pass".to_string(),
                v => v.trim_start_matches('+').to_string(),
            },
            render.reference_paths,
            render.seed,
            render.provenance.git_commit.as_deref().unwrap_or(""),
        )),
        Block::Heading(3, "What the scene calls for".into()),
        Block::table(
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
        ),
    ];
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
        None => b.push(Block::Para(
            "The skips above are already implied by how the scene is written (a grey map, no \
             density map, one light kind): the renderer avoids no further work here, so no \
             second render was timed."
                .into(),
        )),
    }
    for pass in &render.passes {
        let tag = &pass.tag;
        let dir = out.join(tag);
        let names: Vec<&str> = pass.methods.iter().map(|m| m.method.name()).collect();
        let white = pass.white_point;
        b.push(Block::Heading(
            3,
            match pass.density {
                Some(r) => format!("Pass `{tag}` (ρ = {r})"),
                None => "Images".into(),
            },
        ));
        b.push(Block::Images {
            items: names
                .iter()
                .map(|n| (n.to_string(), dir.join(format!("{n}.png"))))
                .collect(),
            width: 160,
        });
        let diffs: Vec<(String, PathBuf)> = names
            .iter()
            .filter(|n| **n != "reference" && dir.join(format!("{n}_diff.png")).exists())
            .map(|n| {
                (
                    format!("{n} − reference"),
                    dir.join(format!("{n}_diff.png")),
                )
            })
            .collect();
        if !diffs.is_empty() {
            b.push(Block::Images {
                items: diffs,
                width: 160,
            });
            b.push(Block::Figure {
                caption: format!(
                    "signed difference, channel mean: blue −{0:.4} … white 0 … red +{0:.4} \
                     (±25 % of the white point {1:.4})",
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
        let names_c: Vec<&str> = if channels == 3 {
            vec!["R", "G", "B"]
        } else {
            vec!["Y"]
        };
        let mut header: Vec<String> = ["method", "time [s]", "set-up [s]", "rel RMSE", "rel bias"]
            .map(String::from)
            .into();
        if channels > 1 {
            header.extend(names_c.iter().map(|c| format!("RMSE {c}")));
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
                        err(mt.map(|x| x.rel_rmse)),
                        pct(mt.map(|x| x.rel_bias)),
                    ];
                    if channels > 1 {
                        row.extend(
                            (0..channels).map(|c| {
                                err(mt.and_then(|x| x.channels.get(c)).map(|x| x.rel_rmse))
                            }),
                        );
                    }
                    row
                })
                .collect(),
        });
    }
    b.push(Block::Para(
        "rel RMSE = √(max(0, Σ(m − r)² − Σ(σ_m² + σ_r²)) / Σr²) over pixels (and channels): \
         both images' own noise subtracted, so it measures the method's bias pattern \
         (\"< noise\": below what the two images' noise can resolve; render more samples and \
         reference paths to resolve it). rel bias = Σ(m − r)/Σr."
            .into(),
    ));
    let curves = &doc.curves;
    if !curves.curves.is_empty() {
        b.push(Block::Heading(3, "What accuracy costs in time".into()));
        b.push(Block::Figure {
            caption: format!(
                "error vs wall time against a truth of {} paths ({:.1} s); reference dashed",
                curves.truth_paths.unwrap_or(0),
                curves.truth_wall_s.unwrap_or(0.0)
            ),
            path: out.join("error_time.png"),
        });
        b.push(Block::table(
            &[
                "method",
                "spp",
                "time [s]",
                "rel RMSE (noise included)",
                "reference time to same error [s]",
                "speed-up",
                "error floor",
            ],
            curves
                .speedups
                .iter()
                .map(|p| {
                    vec![
                        p.method.name().to_string(),
                        p.budget.to_string(),
                        num(Some(p.wall_s)),
                        pct(Some(p.rel_rmse)),
                        num(Some(p.reference_s)),
                        format!("{:.1}×", p.ratio),
                        pct(Some(p.floor)),
                    ]
                })
                .collect(),
        ));
        b.push(Block::Para(
            "Per model: the budget where it beats brute force by the most. The reference's time \
             to the same error is read off its curve (log-log interpolation; beyond its points, \
             e ∝ t^(−1/2)). Errors here include each image's own noise (that is what its time \
             buys); the floor is the model's lowest error over its budgets."
                .into(),
        ));
    }
    b
}

/// The light's kind in words.
fn light_name(kind: &crate::render::scene::LightKind) -> &'static str {
    match kind {
        crate::render::scene::LightKind::Collimated => "collimated",
        crate::render::scene::LightKind::Diffuse => "diffuse",
    }
}

/// The observable in words.
fn observable_name(o: crate::render::scene::Observable) -> &'static str {
    match o {
        crate::render::scene::Observable::Exitance => "exitance",
        crate::render::scene::Observable::Radiance => "radiance",
    }
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
                })
                .collect(),
        }
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
        let s = &speedups(&[r, m])[0];
        // 0.02 costs the reference 25 s: 12.5× at 2 s (4 s at 0.05: 8×).
        assert!((s.ratio - 12.5).abs() < 1e-9 && s.floor == 0.02, "{s:?}");
    }
}
