//! The open experiments of the design, answered with numbers (
//! and the model-cost side of §2): `svkernel experiments`.
//!
//! Every scene's reference is rendered once; each experiment then renders
//! the model configurations it needs (a configuration shared by several
//! experiments is rendered once) and measures them against that reference:
//!
//! | experiment | scenes | configurations |
//! |---|---|---|
//! | methods | all | every method, default variant, importance sampling |
//! | density | `density`, `features` | learned, manual: density-scaled vs plain |
//! | vertex | all but `features` | learned: first/last-vertex kernels vs point albedos |
//! | two-pass | `stripes`, `checker`, `density` | learned: one pass vs α₀ = α_t |
//! | interior | all | learned: α_t under the interior kernel blended in, nowhere, everywhere |
//! | coarse variance | all | learned: the two-scale mean vs its coarse-variance term ([`COARSE_VARIANCE`]) |
//! | sampling | `stripes`, `checker`, `density` | learned: uniform, importance, MIS |
//! | models | `stripes`, `checker` | learned with each `--models` file (K, degrees) |
//! | bases | `stripes`, `checker` | learned with each `--bases` file (exponential terms) |
//!
//! Errors are [`super::render::metrics`] (both images' noise subtracted).
//! Sampling is compared at equal time by the relative noise an image would
//! have after one second, ν·√t, with ν = √(Σσ²/Σr²) its measured relative
//! noise and t its wall time (lower is better; the estimator's cost is the
//! same per sample up to the sampler itself).

use super::render::{RenderOptions, Target, metrics, render_scene};
use super::report::{Block, err, num, pct};
use crate::error::Result;
use crate::metamodel::meta::MetaModelFile;
use crate::provenance::Provenance;
use crate::render::estimator::{Image, Sampling};
use crate::render::scene::Scene;
use crate::render::svbssrdf::{COARSE_VARIANCE, InteriorKernel, Method, Variant};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// (x, y) points of a plotted series.
type Points = Vec<(f64, f64)>;

/// One model configuration.
#[derive(Clone, Debug, PartialEq)]
struct Config {
    method: Method,
    variant: Variant,
    sampling: Sampling,
    /// Meta-model file (`None`: the options' one).
    model: Option<PathBuf>,
    /// Basis model file (`None`: the options' one).
    basis: Option<PathBuf>,
}

/// The `format` of `experiments.json`.
pub const EXPERIMENTS_FORMAT: &str = "svkernel.experiments";
pub const EXPERIMENTS_VERSION: u32 = 1;

/// `experiments.json`: the budgets and every measured row.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExperimentsDoc {
    /// [`EXPERIMENTS_FORMAT`], [`EXPERIMENTS_VERSION`].
    pub format: String,
    pub version: u32,
    /// Samples per pixel of every model render, reference paths per pass.
    pub spp: u32,
    pub reference_paths: u64,
    pub rows: Vec<Row>,
    pub provenance: Provenance,
}

impl ExperimentsDoc {
    /// The document of `rows` measured at these budgets, made now.
    pub fn new(spp: u32, reference_paths: u64, rows: Vec<Row>) -> ExperimentsDoc {
        ExperimentsDoc {
            format: EXPERIMENTS_FORMAT.into(),
            version: EXPERIMENTS_VERSION,
            spp,
            reference_paths,
            rows,
            provenance: Provenance::current(),
        }
    }
}

impl crate::doc::Document for ExperimentsDoc {
    const FORMAT: &'static str = EXPERIMENTS_FORMAT;
    const VERSION: u32 = EXPERIMENTS_VERSION;
}

/// Every experiment's table as text (the report without its figure).
impl std::fmt::Display for ExperimentsDoc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&super::report::to_text(&sections(&self.rows).0))
    }
}

/// One measured configuration on one pass of one scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    pub scene: String,
    pub pass: String,
    pub method: Method,
    /// "" for the default variant.
    pub variant: String,
    pub sampling: Sampling,
    pub model: Option<PathBuf>,
    pub basis: Option<PathBuf>,
    /// The shape of `model` (absent in older files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_shape: Option<ModelShape>,
    /// The shape of `basis` (absent in older files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub basis_shape: Option<BasisShape>,
    pub spp: u32,
    pub wall_s: f64,
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_rmse: f64,
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_bias: f64,
    /// √(Σσ²/Σr²): the image's relative noise.
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_noise: f64,
    /// The smallest rel RMSE this comparison resolves
    /// ([`super::render::resolution`], both images' noise).
    #[serde(with = "crate::doc::nan_as_null")]
    pub resolution: f64,
}

/// A meta-model's size (the `models` experiment).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelShape {
    /// Gaussian components K of the all-vertex kernel.
    pub k: usize,
    /// Polynomial degrees in ln d and √(1 − α).
    pub degrees: [usize; 2],
    /// Every polynomial coefficient of the all- and last-vertex models.
    pub coefficients: usize,
}

impl ModelShape {
    pub fn of(m: &MetaModelFile) -> ModelShape {
        ModelShape {
            k: m.all.k,
            degrees: [m.all.deg_x, m.all.deg_y],
            coefficients: [&m.all, &m.last]
                .iter()
                .flat_map(|c| c.coeffs.iter().map(Vec::len))
                .sum(),
        }
    }
}

/// A basis model's size (the `bases` experiment).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BasisShape {
    /// Exponential terms of the multiple-scattering mixture.
    pub terms: usize,
    /// Polynomial degree in the albedo coordinate.
    pub degree: usize,
}

/// What to run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Scene files (their `name` decides which experiments include them).
    pub scenes: Vec<PathBuf>,
    /// Meta-model files for the `models` experiment (may be empty).
    pub models: Vec<PathBuf>,
    /// Basis model files for the `bases` experiment (may be empty).
    pub bases: Vec<PathBuf>,
}

/// The configurations scene `name` takes part in (module docs).
fn configs(name: &str, settings: &Settings) -> Vec<Config> {
    let base = |method| Config {
        method,
        variant: Variant::default(),
        sampling: Sampling::Importance,
        model: None,
        basis: None,
    };
    let mut c: Vec<Config> = Method::ALL.into_iter().map(base).collect();
    let with = |method, f: &dyn Fn(&mut Config)| {
        let mut k = base(method);
        f(&mut k);
        k
    };
    if matches!(name, "density" | "features") {
        for m in [Method::Manual, Method::Learned] {
            c.push(with(m, &|k| k.variant.plain = true));
        }
    }
    if name != "features" {
        c.push(with(Method::Learned, &|k| k.variant.vertex_kernels = false));
    }
    c.push(with(Method::Learned, &|k| {
        k.variant.interior = InteriorKernel::Never
    }));
    c.push(with(Method::Learned, &|k| {
        k.variant.interior = InteriorKernel::Always
    }));
    c.push(with(Method::Learned, &|k| {
        k.variant.coarse_variance = COARSE_VARIANCE
    }));
    if matches!(name, "stripes" | "checker" | "density") {
        // Manual's kernel does not depend on α₀: a second pass changes nothing.
        c.push(with(Method::Learned, &|k| k.variant.two_pass = true));
        for s in [Sampling::Uniform, Sampling::Profile, Sampling::Mis] {
            c.push(with(Method::Learned, &|k| k.sampling = s));
        }
    }
    if matches!(name, "stripes" | "checker") {
        for m in &settings.models {
            c.push(with(Method::Learned, &|k| k.model = Some(m.clone())));
        }
        for b in &settings.bases {
            c.push(with(Method::Learned, &|k| k.basis = Some(b.clone())));
        }
    }
    c
}

/// √(Σσ²/Σr²) of `img` against the reference means `r`.
fn rel_noise(img: &Image, r: &Image) -> f64 {
    let var: f64 = img.stderr.iter().map(|s| s * s).sum();
    let norm: f64 = r.mean.iter().map(|v| v * v).sum();
    (var / norm).sqrt()
}

/// Runs every experiment (module docs) with `opts`' budgets and returns
/// the rows; progress lines on stderr if `opts.run.progress`.
pub fn run(settings: &Settings, opts: &RenderOptions) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    for path in &settings.scenes {
        let scene = Scene::find(path)?;
        let out = opts.out.join(&scene.name);
        let reference = render_scene(
            &scene,
            &RenderOptions {
                targets: vec![Target::Reference],
                out: out.clone(),
                ..opts.clone()
            },
        )?;
        for config in configs(&scene.name, settings) {
            let mut models = opts.models.clone();
            if let Some(p) = &config.model {
                models = models.with_meta(p)?;
            }
            if let Some(p) = &config.basis {
                models = models.with_basis(p)?;
            }
            let model_shape = config.model.as_ref().map(|_| ModelShape::of(&models.meta));
            let basis_shape = config.basis.as_ref().map(|_| BasisShape {
                terms: models.basis.ln_a.len(),
                degree: models.basis.degree,
            });
            let o = RenderOptions {
                targets: vec![Target::Model(config.method)],
                variant: config.variant,
                sampling: config.sampling,
                models,
                out: out.clone(),
                ..opts.clone()
            };
            for (pass, r) in render_scene(&scene, &o)?.iter().zip(&reference) {
                let img = &pass.rendered[0];
                let reference = &r.rendered[0].image;
                let m = metrics(&img.image, reference);
                rows.push(Row {
                    scene: scene.name.clone(),
                    pass: super::render::tag_or(&pass.tag).to_string(),
                    method: config.method,
                    variant: config.variant.tag(),
                    sampling: config.sampling,
                    model: config.model.clone(),
                    basis: config.basis.clone(),
                    model_shape: model_shape.clone(),
                    basis_shape: basis_shape.clone(),
                    spp: opts.spp.unwrap_or(scene.samples),
                    wall_s: img.wall_s,
                    rel_rmse: m.rel_rmse,
                    rel_bias: m.rel_bias,
                    rel_noise: rel_noise(&img.image, reference),
                    resolution: m.resolution,
                });
            }
        }
    }
    Ok(rows)
}

/// The row of (scene, pass, method, variant, sampling, model).
fn find<'a>(
    rows: &'a [Row],
    key: (&str, &str),
    method: Method,
    variant: &str,
    sampling: Sampling,
    model: Option<&Path>,
) -> Option<&'a Row> {
    rows.iter().find(|r| {
        (r.scene.as_str(), r.pass.as_str()) == key
            && r.method == method
            && r.variant == variant
            && r.sampling == sampling
            && r.model.as_deref() == model
            && r.basis.is_none()
    })
}

/// The (scene, pass) keys of the rows, in order of appearance.
fn passes(rows: &[Row]) -> Vec<(String, String)> {
    let mut keys: Vec<(String, String)> = Vec::new();
    for r in rows {
        let k = (r.scene.clone(), r.pass.clone());
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    keys
}

fn label((scene, pass): &(String, String)) -> String {
    if pass == "main" {
        scene.clone()
    } else {
        format!("{scene} {pass}")
    }
}

/// A two-way comparison table: per pass and method, the default variant's
/// error against `variant`'s, and which wins; plus how often `variant` won.
fn variant_table(
    rows: &[Row],
    methods: &[Method],
    variant: &str,
    names: [&str; 2],
) -> (Block, String) {
    let mut table = Vec::new();
    let (mut wins, mut n) = (0, 0);
    for key in passes(rows) {
        let k = (key.0.as_str(), key.1.as_str());
        for &m in methods {
            let (Some(a), Some(b)) = (
                find(rows, k, m, "", Sampling::Importance, None),
                find(rows, k, m, variant, Sampling::Importance, None),
            ) else {
                continue;
            };
            // Within 2 % of each other (relative) is a tie; an undefined
            // error (a black reference) is no comparison and is not counted.
            let comparable = a.rel_rmse.is_finite() && b.rel_rmse.is_finite();
            n += usize::from(comparable);
            // Both within their noise is a tie too.
            let unresolved = |r: &Row| r.rel_rmse < r.resolution;
            let better = if !comparable {
                "—"
            } else if (a.rel_rmse - b.rel_rmse).abs() <= 0.02 * a.rel_rmse.max(b.rel_rmse)
                || (unresolved(a) && unresolved(b))
            {
                "tie"
            } else if b.rel_rmse < a.rel_rmse {
                wins += 1;
                names[1]
            } else {
                names[0]
            };
            table.push(vec![
                label(&key),
                m.name().to_string(),
                err(Some(a.rel_rmse), a.resolution),
                err(Some(b.rel_rmse), b.resolution),
                pct(Some(a.rel_bias)),
                pct(Some(b.rel_bias)),
                better.to_string(),
            ]);
        }
    }
    let header = vec![
        "scene".into(),
        "method".into(),
        format!("rel RMSE, {}", names[0]),
        format!("rel RMSE, {}", names[1]),
        format!("bias, {}", names[0]),
        format!("bias, {}", names[1]),
        "lower error".into(),
    ];
    (
        Block::Table {
            header,
            rows: table,
        },
        format!(
            "{} has the lower error in {wins} of {n} cases (a tie: within 2 % of each other).",
            names[1]
        ),
    )
}

/// The report's blocks: what was run (`doc`'s command line), one section
/// per experiment and, if the `models` experiment ran, its
/// error-vs-complexity plot at `plot` (PNG + SVG).
pub fn report(doc: &ExperimentsDoc, plot: &Path) -> Result<Vec<Block>> {
    let mut b = vec![
        Block::Para(
            "Every number below is measured by the command that follows, against each scene's \
             brute-force reference; rel RMSE has both images' noise subtracted (\"< x\": \
             the method's bias is below what the budgets resolve, and at most x)."
                .into(),
        ),
        Block::Code(doc.provenance.command_line.join(" ")),
    ];
    let (sections, complexity) = sections(&doc.rows);
    let at = b.len();
    b.extend(sections);
    if let Some((k, plotted)) = complexity {
        use crate::jobs::plot::{Axes, chart, chart_svg};
        let axes = Axes {
            title: "learned: error vs Gaussian components K (degrees 3, 3)".into(),
            x_label: "K".into(),
            y_label: "relative RMSE vs reference".into(),
            log_x: false,
            log_y: true,
        };
        chart(plot, &axes, &plotted)?;
        chart_svg(&plot.with_extension("svg"), &axes, &plotted)?;
        b.insert(
            at + k,
            Block::Figure {
                caption: "learned's error against K (solid; a point on the dashed line of its \
                          scene is below what the comparison resolves)"
                    .into(),
                path: plot.to_path_buf(),
            },
        );
    }
    Ok(b)
}

/// One section per experiment, and for the `models` experiment the index in
/// the sections where its plot belongs and the plot's series.
fn sections(rows: &[Row]) -> (Vec<Block>, Option<(usize, Vec<crate::jobs::plot::Series>)>) {
    let mut b = vec![Block::Heading(
        2,
        "Learned vs manual vs the baselines".into(),
    )];
    let methods = Method::ALL;
    let mut header = vec!["scene".to_string()];
    header.extend(methods.iter().map(|m| m.name().to_string()));
    header.push("resolvable (learned)".into());
    let mut table = Vec::new();
    let (mut learned_wins, mut manual_wins, mut n) = (0, 0, 0);
    for key in passes(rows) {
        let k = (key.0.as_str(), key.1.as_str());
        let found: Vec<Option<&Row>> = methods
            .iter()
            .map(|&m| find(rows, k, m, "", Sampling::Importance, None))
            .collect();
        let e: Vec<Option<f64>> = found.iter().map(|r| r.map(|r| r.rel_rmse)).collect();
        let mut row = vec![label(&key)];
        row.extend(
            found
                .iter()
                .map(|r| err(r.map(|r| r.rel_rmse), r.map_or(0.0, |r| r.resolution))),
        );
        row.push(pct(find(
            rows,
            k,
            Method::Learned,
            "",
            Sampling::Importance,
            None,
        )
        .map(|r| r.resolution)));
        table.push(row);
        if let [Some(p), Some(f), Some(l), Some(el), Some(ma), Some(le)] = e[..] {
            n += 1;
            learned_wins += usize::from(le < ma);
            manual_wins += usize::from(ma < p.min(f).min(l).min(el));
        }
    }
    b.push(Block::Table {
        header,
        rows: table,
    });
    b.push(Block::Para(format!(
        "learned is below manual on {learned_wins} of {n} scenes/passes; manual is below the \
         best of point/factorized/line/ellipse on {manual_wins} of {n}."
    )));
    let coarse = Variant {
        coarse_variance: COARSE_VARIANCE,
        ..Variant::default()
    }
    .tag();
    let sections: [(&str, &[Method], &str, [&str; 2]); 6] = [
        (
            "Density-scaled vs plain aggregation",
            &[Method::Manual, Method::Learned],
            "+plain",
            ["density-scaled", "plain"],
        ),
        (
            "First/last-vertex kernels vs point albedos in the local terms",
            &[Method::Learned],
            "+point-albedos",
            ["vertex kernels", "point albedos"],
        ),
        (
            "One extra pass with α₀ = α_t (learned; manual's kernel does not depend on α₀)",
            &[Method::Learned],
            "+2pass",
            ["one pass", "two passes"],
        ),
        (
            "α_t under the interior vertices' kernel where the paths see a high albedo \
             (the default) vs the all-vertex kernel everywhere (learned)",
            &[Method::Learned],
            "+no-interior",
            ["blended", "all vertices"],
        ),
        (
            "α_t under the interior vertices' kernel where the paths see a high albedo \
             (the default) vs everywhere (learned)",
            &[Method::Learned],
            "+interior",
            ["blended", "interior"],
        ),
        (
            "The two-scale mean (the default) vs its coarse-variance term, c = 0.25 (learned)",
            &[Method::Learned],
            &coarse,
            ["two-scale", "coarse variance"],
        ),
    ];
    for (title, ms, variant, names) in sections {
        let (table, summary) = variant_table(rows, ms, variant, names);
        b.push(Block::Heading(2, title.into()));
        b.push(table);
        b.push(Block::Para(summary));
    }
    b.push(Block::Heading(
        2,
        "Uniform vs profile vs importance vs MIS sampling (learned)".into(),
    ));
    let mut table = Vec::new();
    for key in passes(rows) {
        let k = (key.0.as_str(), key.1.as_str());
        let cells: Vec<Option<&Row>> = [
            Sampling::Uniform,
            Sampling::Profile,
            Sampling::Importance,
            Sampling::Mis,
        ]
        .into_iter()
        .map(|s| find(rows, k, Method::Learned, "", s, None))
        .collect();
        if cells[0].is_none() {
            continue;
        }
        let mut row = vec![label(&key)];
        for c in &cells {
            row.push(pct(c.map(|r| r.rel_noise * r.wall_s.sqrt())));
        }
        for c in &cells {
            row.push(err(c.map(|r| r.rel_rmse), c.map_or(0.0, |r| r.resolution)));
        }
        table.push(row);
    }
    b.push(Block::table(
        &[
            "scene",
            "noise at 1 s, uniform",
            "profile",
            "importance",
            "MIS",
            "rel RMSE, uniform",
            "profile",
            "importance",
            "MIS",
        ],
        table,
    ));
    b.push(Block::Para(
        "Noise at equal time: ν·√t, the relative noise an image would have after one second \
         (lower is better). `profile` draws r from the homogeneous profile and φ uniformly on \
         the arc inside the light; `importance` also guides φ by the albedo along the arc. \
         Uniform disk sampling has unbounded variance here (R(r) ~ 1/r at \
         the pixel: ∫(1/r)² r dr diverges), so its measured noise is itself unreliable."
            .into(),
    ));
    let model_rows: Vec<&Row> = rows.iter().filter(|r| r.model.is_some()).collect();
    let mut complexity = None;
    if !model_rows.is_empty() {
        b.push(Block::Heading(
            2,
            "Error vs kernel complexity and meta-model size".into(),
        ));
        let mut table = Vec::new();
        // Per scene: error vs K at degrees (3, 3), and the resolution floor.
        let mut series: Vec<(String, Points, Points)> = Vec::new();
        for r in &model_rows {
            let path = r.model.as_deref().expect("filtered");
            let shape = r.model_shape.as_ref();
            table.push(vec![
                label(&(r.scene.clone(), r.pass.clone())),
                path.display().to_string(),
                shape.map_or("—".into(), |m| m.k.to_string()),
                shape.map_or("—".into(), |m| {
                    format!("{}, {}", m.degrees[0], m.degrees[1])
                }),
                shape.map_or("—".into(), |m| m.coefficients.to_string()),
                num(Some(r.wall_s)),
                err(Some(r.rel_rmse), r.resolution),
                pct(Some(r.resolution)),
                pct(Some(r.rel_bias)),
            ]);
            if let Some(m) = shape.filter(|m| m.degrees == [3, 3]) {
                let k = m.k as f64;
                let (e, f) = (r.rel_rmse.max(r.resolution), r.resolution);
                match series.iter_mut().find(|(s, _, _)| *s == r.scene) {
                    Some((_, v, w)) => {
                        v.push((k, e));
                        w.push((k, f));
                    }
                    None => series.push((r.scene.clone(), vec![(k, e)], vec![(k, f)])),
                }
            }
        }
        b.push(Block::table(
            &[
                "scene",
                "meta-model",
                "K",
                "degrees (ln d, √(1−α))",
                "coefficients",
                "time [s]",
                "rel RMSE",
                "resolvable",
                "rel bias",
            ],
            table,
        ));
        b.push(Block::Para(
            "resolvable: the smallest rel RMSE the comparison can tell from the two images' \
             noise, two standard deviations of the noise-subtracted squared error; \"< x\" rows lie below it, with x the error's upper bound."
                .into(),
        ));
        use crate::jobs::plot::Series;
        let mut plotted: Vec<Series> = Vec::new();
        for (k, (name, mut e, mut f)) in series.into_iter().enumerate() {
            e.sort_by(|a, b| a.0.total_cmp(&b.0));
            f.sort_by(|a, b| a.0.total_cmp(&b.0));
            plotted.push(Series::line(name.clone(), e, k));
            plotted.push(Series::dashed(format!("{name}: resolvable"), f, k));
        }
        complexity = Some((b.len(), plotted));
    }
    let basis_rows: Vec<&Row> = rows.iter().filter(|r| r.basis.is_some()).collect();
    if !basis_rows.is_empty() {
        b.push(Block::Heading(2, "Error vs basis terms".into()));
        let mut table = Vec::new();
        for r in basis_rows {
            let path = r.basis.as_deref().expect("filtered");
            let shape = r.basis_shape.as_ref();
            table.push(vec![
                label(&(r.scene.clone(), r.pass.clone())),
                path.display().to_string(),
                shape.map_or("—".into(), |m| m.terms.to_string()),
                shape.map_or("—".into(), |m| m.degree.to_string()),
                num(Some(r.wall_s)),
                err(Some(r.rel_rmse), r.resolution),
                pct(Some(r.resolution)),
                pct(Some(r.rel_bias)),
            ]);
        }
        b.push(Block::table(
            &[
                "scene",
                "basis",
                "exponential terms",
                "degree in albedo",
                "time [s]",
                "rel RMSE",
                "resolvable",
                "rel bias",
            ],
            table,
        ));
    }
    (b, complexity)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(variant: &str, rel_rmse: f64) -> Row {
        Row {
            scene: "s".into(),
            pass: "main".into(),
            method: Method::Learned,
            variant: variant.into(),
            sampling: Sampling::Importance,
            model: None,
            basis: None,
            model_shape: None,
            basis_shape: None,
            spp: 4,
            wall_s: 1.0,
            rel_rmse,
            rel_bias: 0.0,
            rel_noise: 0.01,
            resolution: 0.01,
        }
    }

    #[test]
    fn an_undefined_error_is_no_comparison() {
        // A black reference makes the relative error NaN: not a win for
        // either variant, and not counted.
        let rows = [row("", f64::NAN), row("+x", 0.1)];
        let (Block::Table { rows: table, .. }, summary) =
            variant_table(&rows, &[Method::Learned], "+x", ["default", "x"])
        else {
            panic!("a table")
        };
        assert_eq!(table[0].last().unwrap(), "—");
        assert!(summary.contains("0 of 0"), "{summary}");
    }
}
