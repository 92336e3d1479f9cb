//! `svkernel render`: a scene through every requested method and the
//! reference, with timings, images and a JSON sidecar.
//!
//! A scene with a `density_sweep` is rendered once per density (a *pass*
//! each, tagged `rho<ρ>`); otherwise there is one pass with the scene's
//! density map (or ρ = 1).
//!
//! # Outputs (in `--out DIR`, all atomic)
//! * `<pass>/<method>.exr` — channels Y (or R, G, B) and stderr.*;
//! * `<pass>/<method>.png` — tone-mapped preview ([`super::output`]), and
//!   `<pass>/<method>_diff.png` — signed difference to the reference;
//! * `<pass>/<method>_mean.npy`, `<pass>/<method>_stderr.npy` — `(N, N, C)`;
//! * `<pass>/reference.tally.json` — the mergeable reference tally;
//! * `<pass>/albedo.npy`, `<pass>/density.npy` — the material's texels;
//! * `<pass>/albedo.png`, and `<pass>/density.png` with a density map —
//!   previews of the input maps over the image window (linear: black 0,
//!   white albedo 1 or the map's largest density);
//! * `<pass>/row.png` — reference | each method (in render order), with the
//!   signed differences to the reference below (blue −, red +, ±25 % of
//!   the white point);
//! * `render.json` ([`RenderDoc`]) — scene, settings, per-method timings
//!   and errors against the reference, provenance.

use super::extend::{self, Extension};
use super::output;
use crate::error::{Error, Result};
use crate::forward::runner::{RunOptions, Shard, chunk_range, run};
use crate::jobs::shipped::Models;
use crate::provenance::Provenance;
use crate::render::analysis::analyse;
use crate::render::estimator::{self, Allocation, Image, Sampling, Sequence, Settings, View};
use crate::render::reference::{REFERENCE_FORMAT, REFERENCE_VERSION, Reference, ReferenceTally};
use crate::render::scene::{LightKind, Observable, Scene};
use crate::render::svbssrdf::{BasisTable, Density, Material, Method, SvBssrdf, Variant};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// One thing to render.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    Reference,
    Model(Method),
}

impl Target {
    pub fn name(self) -> &'static str {
        match self {
            Target::Reference => "reference",
            Target::Model(m) => m.name(),
        }
    }

    pub fn parse(s: &str) -> Result<Target> {
        if s == "reference" {
            Ok(Target::Reference)
        } else {
            Method::parse(s).map(Target::Model)
        }
    }
}

/// `--method`: the reference or one of the methods.
impl clap::ValueEnum for Target {
    fn value_variants<'a>() -> &'a [Self] {
        &[
            Target::Reference,
            Target::Model(Method::Point),
            Target::Model(Method::Factorized),
            Target::Model(Method::Line),
            Target::Model(Method::Ellipse),
            Target::Model(Method::Manual),
            Target::Model(Method::Learned),
        ]
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        Some(clap::builder::PossibleValue::new(self.name()))
    }
}

/// Written as its name ([`Target::name`]).
impl Serialize for Target {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Target {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        Target::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// How to render (the CLI's flags; `None` = the scene's value).
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Targets; empty = the scene's methods plus the reference.
    pub targets: Vec<Target>,
    pub spp: Option<u32>,
    pub sampling: Sampling,
    pub sequence: Sequence,
    pub allocation: Allocation,
    pub variant: Variant,
    pub seed: u64,
    pub reference_paths: Option<u64>,
    /// The basis models, the meta-model and its training configuration.
    pub models: Models,
    pub out: PathBuf,
    /// Reference: only this shard (the images are then partial).
    pub shard: Option<Shard>,
    /// Reference: checkpoint interval, resume and progress.
    pub run: RunOptions,
    /// Reference: checkpoints go to `<this>.<pass>.ckpt`; `None`: none.
    pub checkpoint: Option<PathBuf>,
    /// Use these merged reference tallies (one per pass, in pass order)
    /// instead of simulating.
    pub reference_tallies: Vec<PathBuf>,
    /// Skip the effects the scene does not call for ([`crate::render::analysis`]).
    pub analysis: bool,
    /// Where meta-model extensions for albedos outside the trained range
    /// are cached ([`super::extend`]); `None`: clamp there instead.
    pub cache: Option<PathBuf>,
    /// Materials already prepared (maps on one grid, pyramids, row sums),
    /// shared by every method of a pass and by the renders of every clone
    /// of these options (compare's budgets), keyed by scene content, pass
    /// and analysis.
    pub materials: Materials,
}

/// Prepared materials by (scene hash, pass, analysis on).
pub type Materials = Arc<std::sync::Mutex<std::collections::HashMap<String, Arc<Material>>>>;

impl RenderOptions {
    /// The defaults into `out` with `models`: the scene's targets, samples
    /// and reference paths, importance sampling, the default variant, seed
    /// 1, no shard, no checkpoint, no progress, extensions cached in
    /// [`crate::jobs::shipped::cache_dir`] (if the platform has one).
    pub fn new(out: PathBuf, models: Models) -> Self {
        RenderOptions {
            targets: Vec::new(),
            spp: None,
            sampling: Sampling::Importance,
            sequence: Sequence::default(),
            allocation: Allocation::default(),
            variant: Variant::default(),
            seed: 1,
            reference_paths: None,
            models,
            out,
            shard: None,
            run: RunOptions::default(),
            checkpoint: None,
            reference_tallies: Vec::new(),
            analysis: true,
            cache: crate::jobs::shipped::cache_dir(None).ok(),
            materials: Materials::default(),
        }
    }
}

/// A stored reference tally (mergeable; `svkernel merge`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReferenceDoc {
    pub format: String,
    pub version: u32,
    pub key: serde_json::Value,
    /// Chunk ranges this tally covers.
    pub chunks: Vec<(u64, u64)>,
    pub wall_s: f64,
    pub tally: ReferenceTally,
    pub provenance: Provenance,
}

/// Chunk ranges as `0..4, 8..12`.
fn chunk_list(chunks: &[(u64, u64)]) -> String {
    let parts: Vec<String> = chunks.iter().map(|(a, b)| format!("{a}..{b}")).collect();
    parts.join(", ")
}

impl crate::doc::Document for ReferenceDoc {
    const FORMAT: &'static str = REFERENCE_FORMAT;
    const VERSION: u32 = REFERENCE_VERSION;

    /// Checks that the tally is whole: its shape against its key
    /// (resolution, channels), and its path count against the chunks it
    /// claims. Errors name the file.
    fn validate(&self, path: &Path) -> Result<()> {
        let doc = self;
        let t = &doc.tally;
        let key_usize = |k: &str| doc.key.get(k).and_then(|v| v.as_u64());
        let cells = t.resolution * t.resolution * t.channels;
        let shape_ok = key_usize("resolution") == Some(t.resolution as u64)
            && key_usize("channels") == Some(t.channels as u64)
            && t.exits.len() == cells
            && [t.radiance.len(), t.radiance_sq.len()]
                .iter()
                .all(|&l| l == 0 || l == cells)
            && t.radiance.len() == t.radiance_sq.len();
        if !shape_ok {
            return Err(Error::format(
                path,
                "tally",
                "shape does not match the key (resolution × resolution × channels)",
            ));
        }
        let claimed = key_usize("paths")
            .map(|p| crate::forward::runner::paths_in(p, &doc.chunks))
            .ok_or_else(|| Error::format(path, "key.paths", "missing"))?;
        if t.paths != claimed {
            return Err(Error::format(
                path,
                "tally.paths",
                format!(
                    "{} paths, but its chunks {} hold {claimed}",
                    t.paths,
                    chunk_list(&doc.chunks)
                ),
            ));
        }
        Ok(())
    }
}

/// One rendered image and what it cost.
#[derive(Clone, Debug)]
pub struct Rendered {
    pub target: Target,
    pub image: Image,
    /// Wall time of the render itself (set-up such as pyramids included).
    pub wall_s: f64,
    /// Set-up part of `wall_s` (pyramid builds).
    pub setup_s: f64,
}

/// The images of one pass.
#[derive(Clone, Debug)]
pub struct Pass {
    /// "" for a single pass, else `rho<ρ>`.
    pub tag: String,
    pub density: Option<f64>,
    pub rendered: Vec<Rendered>,
    /// Reference events per second (scatterings), if simulated here.
    pub reference_events_per_s: Option<f64>,
    /// The meta-model extension `learned` used, if the scene's albedos
    /// left the trained range ([`super::extend`]).
    pub extension: Option<Extension>,
}

/// Errors of a method image against the reference, over all channels and
/// per channel (NaN, written `null`, against a black reference).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// √(max(0, Σ(m − r)² − Σ(σ_m² + σ_r²))/Σ r²): relative RMSE with both
    /// images' own noise subtracted.
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_rmse: f64,
    /// Σ(m − r)/Σ r: mean relative bias.
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_bias: f64,
    /// The smallest `rel_rmse` the two images' noise resolves
    /// ([`resolution`]); below it the error is only bounded.
    #[serde(default, with = "crate::doc::nan_as_null")]
    pub resolution: f64,
    /// The same numbers per channel (Y, or R, G, B).
    pub channels: Vec<ChannelMetrics>,
}

/// [`Metrics`] of one channel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChannelMetrics {
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_rmse: f64,
    #[serde(with = "crate::doc::nan_as_null")]
    pub rel_bias: f64,
    #[serde(default, with = "crate::doc::nan_as_null")]
    pub resolution: f64,
}

/// How many standard deviations of the noise [`resolution`] spans: two, a
/// one-sided confidence of 97.7 % that an unresolved error lies below its
/// bound.
pub const RESOLUTION_Z: f64 = 2.0;

/// Sums over the pixels of channels `cs` of `m` against `r`: squared error,
/// noise variance v (σ_r², plus σ_m² if `own`), Σr², Σ(m − r), Σr, and
/// for [`resolution`] Σ4(d² − v)v and Σ2v².
fn error_sums(m: &Image, r: &Image, own: bool, cs: std::ops::Range<usize>) -> [f64; 7] {
    let n2 = r.resolution * r.resolution;
    let mut s = [0.0; 7];
    for k in cs.start * n2..cs.end * n2 {
        let d = m.mean[k] - r.mean[k];
        let v = r.stderr[k].powi(2) + if own { m.stderr[k].powi(2) } else { 0.0 };
        s[0] += d * d;
        s[1] += v;
        s[2] += r.mean[k] * r.mean[k];
        s[3] += d;
        s[4] += r.mean[k];
        s[5] += 4.0 * (d * d - v) * v;
        s[6] += 2.0 * v * v;
    }
    s
}

/// (relative RMSE, relative bias, resolution) from [`error_sums`].
fn from_sums([se, noise, norm, diff, sum, cross, quad]: [f64; 7]) -> ChannelMetrics {
    ChannelMetrics {
        rel_rmse: ((se - noise).max(0.0) / norm).sqrt(),
        rel_bias: diff / sum,
        resolution: (RESOLUTION_Z * (cross.max(0.0) + quad).sqrt() / norm).sqrt(),
    }
}

/// The smallest relative error that a comparison of `m` against `r`
/// resolves, as a relative RMSE; the noise is σ_r², plus σ_m² if
/// `subtract_own_noise` (as in [`rel_rmse`]).
///
/// Per pixel and channel the difference is d = δ + ε with δ the error and
/// ε ~ N(0, v) the noise, so S = Σd² − Σv estimates Σδ² with variance
/// Var S = Σ(4δ²v + 2v²), its first sum estimated without bias by
/// Σ4(d² − v)v (at least 0). The resolution is √(z·√(Var S)/Σr²) with
/// z = [`RESOLUTION_Z`]: an error below it is indistinguishable from zero,
/// and the error lies below hypot([`rel_rmse`], resolution) with that
/// confidence. Where the noise is concentrated in a few pixels (near a
/// light) √(Σv²) approaches Σv, and the resolution approaches the noise's
/// own relative RMSE.
pub fn resolution(m: &Image, r: &Image, subtract_own_noise: bool) -> f64 {
    let m = broadcast(m, r.channels);
    from_sums(error_sums(&m, r, subtract_own_noise, 0..r.channels)).resolution
}

/// The upper bound on an error `rel_rmse` of resolution `resolution`:
/// `rel_rmse` itself where it is resolved, else hypot(rel_rmse,
/// resolution) ([`resolution`]).
pub fn error_bound(rel_rmse: f64, resolution: f64) -> f64 {
    if rel_rmse >= resolution {
        rel_rmse
    } else {
        rel_rmse.hypot(resolution)
    }
}

/// Relative RMSE and bias of `m` against `r`, overall and per channel
/// (both images' noise subtracted). A one-channel image against a
/// three-channel reference (a grey render) is compared with each channel.
pub fn metrics(m: &Image, r: &Image) -> Metrics {
    let m = broadcast(m, r.channels);
    let all = from_sums(error_sums(&m, r, true, 0..r.channels));
    Metrics {
        rel_rmse: all.rel_rmse,
        rel_bias: all.rel_bias,
        resolution: all.resolution,
        channels: (0..r.channels)
            .map(|c| from_sums(error_sums(&m, r, true, c..c + 1)))
            .collect(),
    }
}

/// `m` with its single channel repeated to `channels` (a grey render
/// compared with an RGB one); `m` itself otherwise.
pub fn broadcast(m: &Image, channels: usize) -> std::borrow::Cow<'_, Image> {
    if m.channels == channels || m.channels != 1 {
        return std::borrow::Cow::Borrowed(m);
    }
    let mut out = Image::zeros(m.resolution, channels);
    for c in 0..channels {
        let n2 = m.resolution * m.resolution;
        out.mean[c * n2..(c + 1) * n2].copy_from_slice(&m.mean);
        out.stderr[c * n2..(c + 1) * n2].copy_from_slice(&m.stderr);
    }
    std::borrow::Cow::Owned(out)
}

/// √(max(0, Σ(m − r)² − noise)/Σr²) over all pixels and channels, the noise
/// being Σσ_r² plus, if `subtract_own_noise`, Σσ_m².
pub fn rel_rmse(m: &Image, r: &Image, subtract_own_noise: bool) -> f64 {
    let m = broadcast(m, r.channels);
    from_sums(error_sums(&m, r, subtract_own_noise, 0..r.channels)).rel_rmse
}

/// A content hash of the scene ([`crate::jobs::store::content_hash`]): the scene file's
/// bytes, then every loaded map (shape, texel size and values, bit for bit).
/// It identifies a reference simulation for checkpoints, merges and
/// `--reference-tally`, so an edited texture file (`.npy`, `.exr`, `.png`)
/// that the unchanged TOML points to is a different scene.
pub fn scene_hash(scene: &Scene) -> Result<String> {
    let mut parts = vec![scene.source.as_bytes().to_vec()];
    for m in scene.albedo.iter().chain(&scene.density) {
        let mut b = Vec::with_capacity(24 + 8 * m.values.len());
        b.extend((m.nx as u64).to_le_bytes());
        b.extend((m.ny as u64).to_le_bytes());
        b.extend(m.texel.to_le_bytes());
        for v in &m.values {
            b.extend(v.to_le_bytes());
        }
        parts.push(b);
    }
    Ok(crate::jobs::store::content_hash(
        parts.iter().map(|p| p.as_slice()),
    ))
}

/// The passes of a scene: (tag, constant density or None for the map).
fn passes(scene: &Scene) -> Vec<(String, Option<f64>)> {
    if scene.density_sweep.is_empty() {
        vec![(String::new(), None)]
    } else {
        scene
            .density_sweep
            .iter()
            .map(|r| (format!("rho{r}"), Some(*r)))
            .collect()
    }
}

/// What a render of `scene` under `opts` draws: `opts.targets`, else the
/// reference and the scene's methods.
fn targets_of(scene: &Scene, opts: &RenderOptions) -> Vec<Target> {
    if opts.targets.is_empty() {
        let mut t: Vec<Target> = scene.methods.iter().map(|&m| Target::Model(m)).collect();
        t.insert(0, Target::Reference);
        t
    } else {
        opts.targets.clone()
    }
}

/// `opts` with the models of the scene's medium, if its targets use a
/// model: the given ones, a preset's, or built on demand into the cache
/// ([`super::medium`]). A caller that renders one scene many times
/// resolves them once with this.
pub fn with_scene_models(scene: &Scene, opts: &RenderOptions) -> Result<RenderOptions> {
    let needs_model = targets_of(scene, opts)
        .iter()
        .any(|t| matches!(t, Target::Model(_)));
    Ok(RenderOptions {
        models: scene_models(scene, opts, needs_model)?,
        ..opts.clone()
    })
}

/// The models of the scene's medium ([`with_scene_models`]); `opts.models`
/// themselves if no model is needed. A medium without models is an error
/// naming the scene and `medium`.
fn scene_models(scene: &Scene, opts: &RenderOptions, needs_model: bool) -> Result<Models> {
    if !needs_model {
        return Ok(opts.models.clone());
    }
    opts.models
        .for_medium(scene.eta, scene.g, opts.cache.as_deref(), opts.run.progress)
        .map_err(|e| match e {
            Error::Param {
                name: "medium",
                value,
                allowed,
            } => Error::format(
                &scene.path,
                "medium",
                format!("{value}: no models for this medium: {allowed}"),
            ),
            e => e,
        })
}

/// Renders every pass of `scene` (module docs). Progress lines go to stderr
/// when `opts.run.progress` is set.
pub fn render_scene(scene: &Scene, opts: &RenderOptions) -> Result<Vec<Pass>> {
    let targets = targets_of(scene, opts);
    let needs_model = targets.iter().any(|t| matches!(t, Target::Model(_)));
    let models = scene_models(scene, opts, needs_model)?;
    let basis = if needs_model {
        let m = &models;
        let want = scene.light.incidence();
        let (model, path) = m.basis_for(want, scene.observable);
        if model.observable != scene.observable {
            return Err(Error::format(
                path,
                "observable",
                format!(
                    "'{}', but the scene renders the {}",
                    model.observable.name(),
                    scene.observable.name()
                ),
            ));
        }
        if model.incidence != want {
            return Err(Error::format(
                path,
                "incidence",
                format!(
                    "'{}', but the scene's {} light needs a basis fitted to '{}' profiles",
                    model.incidence.name(),
                    scene.light.name(),
                    want.name()
                ),
            ));
        }
        if (model.eta - scene.eta).abs() > 1e-9 || (model.g - scene.g).abs() > 1e-9 {
            return Err(Error::format(
                path,
                "eta/g",
                format!(
                    "basis is for η = {}, g = {} but the scene {} has η = {}, g = {}{}",
                    model.eta,
                    model.g,
                    scene.path.display(),
                    scene.eta,
                    scene.g,
                    if scene.observable == crate::forward::medium::Observable::Radiance {
                        " (the radiance along the normal is modelled for the built-in medium only)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        Some(Arc::new(BasisTable::new(model)))
    } else {
        None
    };
    let meta = if targets.contains(&Target::Model(Method::Learned)) {
        Some(models.meta.clone())
    } else {
        None
    };
    let plan = analyse(scene, opts.analysis);
    // Albedos outside the trained range: simulate and fit only those (not
    // for a homogeneous material, whose every method is the profile).
    let (extension, extension_model) = match (&meta, &opts.cache) {
        (Some(m), Some(cache)) if !plan.homogeneous => {
            match extend::missing(plan.albedo_range, m.alpha_range()) {
                Some(missing) => {
                    let (done, model) =
                        extend::ensure(m, &models.training, missing, cache, opts.run.progress)?;
                    (Some(done), Some(Arc::new(model)))
                }
                None => (None, None),
            }
        }
        _ => (None, None),
    };
    let view = View {
        light_radius: scene.light_radius,
        irradiance: scene.irradiance,
        resolution: scene.resolution,
        half_width: scene.half_width,
    };
    let settings = Settings {
        spp: opts.spp.unwrap_or(scene.samples),
        sampling: opts.sampling,
        sequence: opts.sequence,
        allocation: opts.allocation,
        seed: opts.seed,
    };
    if targets.iter().any(|t| matches!(t, Target::Model(_))) {
        settings.validate()?;
    }
    let hash = scene_hash(scene)?;
    let albedo = plan.albedo(scene);
    let mut out = Vec::new();
    let all_passes = passes(scene);
    let tallies = opts.reference_tallies.len();
    if tallies > 0 && tallies != all_passes.len() {
        return Err(Error::param(
            "reference_tallies",
            format!("{tallies} files for {} passes", all_passes.len()),
            "one tally per pass, in the scene's order (its density sweep)",
        ));
    }
    for (pass_index, (tag, rho)) in all_passes.into_iter().enumerate() {
        let density_map = if rho.is_some() {
            None
        } else {
            plan.density_map(scene)
        };
        let constant = rho.or(plan.constant_density).unwrap_or(1.0);
        let mut rendered = Vec::new();
        let mut events_per_s = None;
        for &target in &targets {
            let t0 = Instant::now();
            match target {
                Target::Reference => {
                    let paths = opts.reference_paths.unwrap_or(scene.reference_paths);
                    let reference = Reference::new(
                        scene.eta,
                        scene.g,
                        &albedo,
                        density_map,
                        constant,
                        &scene.light,
                        view,
                        scene.observable,
                        opts.seed,
                        paths,
                    )?;
                    let key = reference.key(&format!("{hash}/{tag}"));
                    let (tally, wall_s) = match opts.reference_tallies.get(pass_index) {
                        Some(path) => {
                            let doc = ReferenceDoc::load(path)?;
                            if doc.key != key {
                                return Err(Error::format(
                                    path,
                                    "key",
                                    "tally belongs to a different scene, pass or setting",
                                ));
                            }
                            let all = chunk_range(paths, None);
                            if doc.chunks != [all] {
                                return Err(Error::format(
                                    path,
                                    "chunks",
                                    format!(
                                        "covers chunks {} of 0..{}: merge every shard \
                                         first (`svkernel merge`)",
                                        chunk_list(&doc.chunks),
                                        all.1
                                    ),
                                ));
                            }
                            (doc.tally, doc.wall_s)
                        }
                        None => {
                            let range = chunk_range(paths, opts.shard);
                            if range.0 == range.1 {
                                let s = opts.shard.map_or(String::new(), |s| {
                                    format!(
                                        "{}/{} of {} chunks",
                                        s.index,
                                        s.count,
                                        chunk_range(paths, None).1
                                    )
                                });
                                return Err(Error::param(
                                    "shard",
                                    s,
                                    "a shard that holds chunks: at most as many shards \
                                     as chunks",
                                ));
                            }
                            let mut run_opts = opts.run.clone();
                            run_opts.checkpoint = opts.checkpoint.as_ref().map(|p| {
                                crate::jobs::store::FileCheckpoint::arc(
                                    p.with_extension(format!("{}.ckpt", tag_or(&tag))),
                                )
                            });
                            let r = run(
                                &key,
                                range,
                                reference.empty(),
                                |c| reference.chunk(c),
                                &run_opts,
                            )?;
                            events_per_s = Some(r.tally.events as f64 / r.wall_s.max(1e-9));
                            let doc = ReferenceDoc {
                                format: REFERENCE_FORMAT.into(),
                                version: REFERENCE_VERSION,
                                key: key.clone(),
                                chunks: vec![range],
                                wall_s: r.wall_s,
                                tally: r.tally.clone(),
                                provenance: Provenance::current(),
                            };
                            let dir = opts.out.join(tag_or(&tag));
                            crate::jobs::store::write_json_compact_atomic(
                                &dir.join("reference.tally.json"),
                                &doc,
                            )?;
                            if let Some(ck) = &run_opts.checkpoint {
                                ck.clear()?;
                            }
                            (r.tally, r.wall_s)
                        }
                    };
                    rendered.push(Rendered {
                        target,
                        image: reference.image(&tally, scene.irradiance),
                        wall_s,
                        setup_s: 0.0,
                    });
                }
                Target::Model(method) => {
                    let density = match density_map {
                        Some(m) => Density::Map(m.clone()),
                        None => Density::Constant(constant),
                    };
                    // A homogeneous material: every method is the profile.
                    let evaluated = if plan.homogeneous {
                        Method::Point
                    } else {
                        method
                    };
                    let key = format!("{hash}/{tag}/{}", opts.analysis);
                    let material = {
                        let mut cache = opts.materials.lock().unwrap_or_else(|e| e.into_inner());
                        match cache.get(&key) {
                            Some(m) => m.clone(),
                            None => {
                                let m = Arc::new(Material::new(albedo.clone(), density)?);
                                cache.insert(key, m.clone());
                                m
                            }
                        }
                    };
                    let sv = SvBssrdf::on(
                        evaluated,
                        opts.variant,
                        basis.clone().expect("loaded for model targets"),
                        meta.clone(),
                        material,
                    )?;
                    let sv = match (&extension_model, method) {
                        (Some(ext), Method::Learned) => sv.with_extension(ext.clone()),
                        _ => sv,
                    };
                    let setup_s = t0.elapsed().as_secs_f64();
                    let image = estimator::render(&sv, &view, &settings);
                    rendered.push(Rendered {
                        target,
                        image,
                        wall_s: t0.elapsed().as_secs_f64(),
                        setup_s,
                    });
                }
            }
            if opts.run.progress {
                let r = rendered.last().expect("just pushed");
                eprintln!("  {} {:<10} {:>8.2} s", scene.name, target.name(), r.wall_s);
            }
        }
        out.push(Pass {
            tag,
            density: rho,
            rendered,
            reference_events_per_s: events_per_s,
            extension: extension.clone(),
        });
    }
    Ok(out)
}

/// The directory name of a pass ("main" for the single pass).
pub fn tag_or(tag: &str) -> &str {
    if tag.is_empty() { "main" } else { tag }
}

/// The albedo channels on one texel grid (the scene's, unless the channels
/// differ in shape: then the exact common grid of
/// [`crate::render::svbssrdf::common_grid`], whose texel may be τ/2).
fn albedo_grid(scene: &Scene) -> Result<Vec<crate::forward::maps::TexelMap>> {
    let maps: Vec<_> = scene.albedo.iter().collect();
    crate::render::svbssrdf::common_grid(&maps).map_err(|e| Error::format(&scene.path, "albedo", e))
}

/// Writes the pass's material as texel arrays for external renderers
/// (`tools/mitsuba_check.py`): the albedo channels `a` ([`albedo_grid`]) as
/// `albedo.npy` `(ny, nx)` or `(ny, nx, 3)` and
/// `density.npy` `(ny, nx)` (a constant density as a 1 × 1 array), row 0 at
/// +y, column 0 at −x, texel sizes (`texel`, and `albedo_texel` for the
/// albedo array) and conventions in `render.json`.
fn write_maps(
    scene: &Scene,
    a: &[crate::forward::maps::TexelMap],
    pass: &Pass,
    dir: &Path,
) -> Result<()> {
    let (nx, ny) = (a[0].nx, a[0].ny);
    let albedo =
        ndarray::Array3::from_shape_fn((ny, nx, a.len()), |(i, j, c)| a[c].values[i * nx + j]);
    crate::jobs::store::write_npy_atomic(&dir.join("albedo.npy"), &albedo)?;
    let density = match (pass.density, &scene.density) {
        (None, Some(m)) => ndarray::Array2::from_shape_vec((m.ny, m.nx), m.values.clone())
            .map_err(|e| Error::format(&scene.path, "density", e))?,
        (r, _) => ndarray::Array2::from_elem((1, 1), r.unwrap_or(1.0)),
    };
    crate::jobs::store::write_npy_atomic(&dir.join("density.npy"), &density)
}

/// The `format` of `render.json`.
pub const RENDER_FORMAT: &str = "svkernel.render";
pub const RENDER_VERSION: u32 = 1;

/// `render.json`: the scene, the settings, every pass's methods with their
/// timings and errors against the reference, and provenance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderDoc {
    /// [`RENDER_FORMAT`], [`RENDER_VERSION`].
    pub format: String,
    pub version: u32,
    /// The scene file, its name and [`scene_hash`].
    pub scene: PathBuf,
    pub scene_name: String,
    pub scene_hash: String,
    /// N (N × N pixels) and the half-width W of the image window (MFP).
    pub resolution: usize,
    pub half_width: f64,
    pub observable: Observable,
    pub eta: f64,
    pub g: f64,
    /// Texel size of the scene's maps, and of `albedo.npy` (MFP).
    pub texel: f64,
    pub albedo_texel: f64,
    pub light: LightDoc,
    /// How maps and pixels sit in the plane (for external renderers).
    pub conventions: String,
    /// Samples per pixel of the model methods.
    pub spp: u32,
    pub sampling: Sampling,
    /// The numbers the samples are made of (documents written before it
    /// existed read as `independent`).
    #[serde(default = "independent")]
    pub sequence: Sequence,
    /// How the samples are shared among the pixels (documents written
    /// before it existed read as `uniform`).
    #[serde(default = "uniform")]
    pub allocation: Allocation,
    /// [`Variant::tag`]: "" for the default.
    pub variant: String,
    pub seed: u64,
    pub reference_paths: u64,
    /// "k/N" for a shard of the reference.
    pub shard: Option<String>,
    /// How the PNG previews are tone-mapped.
    pub tone_map: String,
    /// What the material is (absent in older files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<MaterialSummary>,
    pub passes: Vec<PassDoc>,
    pub provenance: Provenance,
}

/// The light of [`RenderDoc`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LightDoc {
    pub kind: LightKind,
    /// Radius of the light disk (MFP).
    pub radius: f64,
    pub irradiance: f64,
}

/// The scene's material, as the report describes it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialSummary {
    /// Albedo channels as written: 1 or 3 (R, G, B).
    pub albedo_channels: usize,
    /// One channel, or three identical ones.
    pub grey: bool,
    /// The albedo's range over all channels and texels.
    pub albedo_range: [f64; 2],
    pub density: DensitySource,
}

/// Where the density comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum DensitySource {
    /// No density map: ρ = 1 everywhere.
    Unit,
    /// A density map, with its range.
    Map { range: [f64; 2] },
    /// A sweep: one pass per constant density.
    Sweep { values: Vec<f64> },
}

impl MaterialSummary {
    /// The material of `scene`.
    pub fn of(scene: &Scene) -> MaterialSummary {
        let range = |m: &mut dyn Iterator<Item = f64>| {
            m.fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], v| {
                [lo.min(v), hi.max(v)]
            })
        };
        MaterialSummary {
            albedo_channels: scene.albedo.len(),
            grey: scene.is_grey(),
            albedo_range: range(&mut scene.albedo.iter().flat_map(|m| m.values.iter().copied())),
            density: match (&scene.density, scene.density_sweep.is_empty()) {
                (Some(m), _) => DensitySource::Map {
                    range: range(&mut m.values.iter().copied()),
                },
                (None, false) => DensitySource::Sweep {
                    values: scene.density_sweep.clone(),
                },
                (None, true) => DensitySource::Unit,
            },
        }
    }
}

/// One pass of [`RenderDoc`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassDoc {
    /// The pass's directory: "main", or `rho<ρ>` of a density sweep.
    pub tag: String,
    /// The sweep's constant density (`None`: the scene's map, or 1).
    pub density: Option<f64>,
    /// White point of the previews ([`output::white_point`]).
    pub white_point: f64,
    /// Reference scattering events per second, if simulated here.
    pub reference_events_per_s: Option<f64>,
    /// The meta-model extension `learned` used ([`super::extend`]).
    pub metamodel_extension: Option<Extension>,
    pub methods: Vec<MethodDoc>,
}

/// One rendered target of a pass.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MethodDoc {
    pub method: Target,
    /// Wall time, set-up included, and the set-up part (pyramid builds).
    pub wall_s: f64,
    pub setup_s: f64,
    /// Against the reference (`None` for the reference itself, or without
    /// one).
    pub metrics: Option<Metrics>,
    /// Mean pixel value over all channels.
    #[serde(with = "crate::doc::nan_as_null")]
    pub mean: f64,
}

impl crate::doc::Document for RenderDoc {
    const FORMAT: &'static str = RENDER_FORMAT;
    const VERSION: u32 = RENDER_VERSION;
}

/// The header of [`MethodDoc`]'s rows.
pub struct MethodHeader;

impl std::fmt::Display for MethodHeader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:<11} {:>9} {:>10} {:>10} {:>10}",
            "method", "time [s]", "set-up [s]", "rel RMSE", "rel bias"
        )
    }
}

/// A row under [`MethodHeader`]: name, time, set-up, relative RMSE and bias
/// against the reference ("—" for the reference itself).
impl std::fmt::Display for MethodDoc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use super::report::{err, pct};
        let m = self.metrics.as_ref();
        write!(
            f,
            "{:<11} {:>9.2} {:>10.2} {:>10} {:>10}",
            self.method.name(),
            self.wall_s,
            self.setup_s,
            err(m.map(|m| m.rel_rmse), m.map_or(0.0, |m| m.resolution)),
            pct(m.map(|m| m.rel_bias))
        )
    }
}

/// The method table of a pass, indented by two spaces, and the reference's
/// speed.
impl std::fmt::Display for PassDoc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "  {MethodHeader}")?;
        for m in &self.methods {
            writeln!(f, "  {m}")?;
        }
        if let Some(e) = self.reference_events_per_s {
            writeln!(f, "  reference: {e:.3e} scattering events/s")?;
        }
        Ok(())
    }
}

/// Every pass's table.
impl std::fmt::Display for RenderDoc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for pass in &self.passes {
            writeln!(f, "pass {}:", pass.tag)?;
            write!(f, "{pass}")?;
        }
        Ok(())
    }
}

/// Writes every image and the sidecar `render.json`; returns the sidecar.
pub fn write_outputs(scene: &Scene, opts: &RenderOptions, passes: &[Pass]) -> Result<RenderDoc> {
    // The albedo as external renderers get it: the same for every pass.
    let albedo = albedo_grid(scene)?;
    let mut pass_docs = Vec::new();
    for pass in passes {
        let dir = opts.out.join(tag_or(&pass.tag));
        write_maps(scene, &albedo, pass, &dir)?;
        let channels: Vec<_> = scene.albedo.iter().collect();
        output::write_map_png(
            &dir.join("albedo.png"),
            &channels,
            scene.resolution,
            scene.half_width,
            1.0,
        )?;
        if let (None, Some(m)) = (pass.density, &scene.density) {
            let max = m.values.iter().copied().fold(0.0, f64::max);
            output::write_map_png(
                &dir.join("density.png"),
                &[m],
                scene.resolution,
                scene.half_width,
                if max > 0.0 { max } else { 1.0 },
            )?;
        }
        let reference = pass
            .rendered
            .iter()
            .find(|r| r.target == Target::Reference)
            .map(|r| &r.image);
        let white = output::white_point(reference.unwrap_or(&pass.rendered[0].image));
        let mut methods = Vec::new();
        for r in &pass.rendered {
            let name = r.target.name();
            output::write_exr(&dir.join(format!("{name}.exr")), &r.image, name)?;
            output::write_png(&dir.join(format!("{name}.png")), &r.image, white)?;
            output::write_npy(
                &dir.join(format!("{name}_mean.npy")),
                &dir.join(format!("{name}_stderr.npy")),
                &r.image,
            )?;
            let m = match (reference, r.target) {
                (Some(reference), Target::Model(_)) => {
                    output::write_diff_png(
                        &dir.join(format!("{name}_diff.png")),
                        &r.image,
                        reference,
                        0.25 * white,
                    )?;
                    Some(metrics(&r.image, reference))
                }
                _ => None,
            };
            methods.push(MethodDoc {
                method: r.target,
                wall_s: r.wall_s,
                setup_s: r.setup_s,
                metrics: m,
                mean: r.image.mean.iter().sum::<f64>() / r.image.mean.len() as f64,
            });
        }
        if let Some(reference) = reference {
            let mut row = vec![reference];
            row.extend(
                pass.rendered
                    .iter()
                    .filter(|r| r.target != Target::Reference)
                    .map(|r| &r.image),
            );
            output::write_row_png(&dir.join("row.png"), &row, white, 0.25 * white)?;
        }
        pass_docs.push(PassDoc {
            tag: tag_or(&pass.tag).to_string(),
            density: pass.density,
            white_point: white,
            reference_events_per_s: pass.reference_events_per_s,
            metamodel_extension: pass.extension.clone(),
            methods,
        });
    }
    let doc = RenderDoc {
        format: RENDER_FORMAT.into(),
        version: RENDER_VERSION,
        scene: scene.path.clone(),
        scene_name: scene.name.clone(),
        scene_hash: scene_hash(scene)?,
        resolution: scene.resolution,
        half_width: scene.half_width,
        observable: scene.observable,
        eta: scene.eta,
        g: scene.g,
        texel: scene.texel,
        albedo_texel: albedo[0].texel,
        light: LightDoc {
            kind: scene.light.clone(),
            radius: scene.light_radius,
            irradiance: scene.irradiance,
        },
        conventions: "maps: centred on the origin, row 0 = +y, column 0 = -x, nearest-neighbour, edge texels extend to infinity; pixel (i, j) covers x in -W + [j, j+1]*2W/N, y in W - [i+1, i]*2W/N; z < 0 is the medium (half-space)".into(),
        spp: opts.spp.unwrap_or(scene.samples),
        sampling: opts.sampling,
        sequence: opts.sequence,
        allocation: opts.allocation,
        variant: opts.variant.tag(),
        seed: opts.seed,
        reference_paths: opts.reference_paths.unwrap_or(scene.reference_paths),
        shard: opts.shard.map(|s| format!("{}/{}", s.index, s.count)),
        tone_map: "sRGB OETF of clamp(v / white_point, 0, 1); white_point = 99.5th percentile of the reference, or of the pass's first image without one".into(),
        material: Some(MaterialSummary::of(scene)),
        passes: pass_docs,
        provenance: Provenance::current(),
    };
    crate::jobs::store::write_json_atomic(&opts.out.join("render.json"), &doc)?;
    Ok(doc)
}

/// Merges reference tally documents of one simulation (shards) in chunk
/// order; errors name the file.
pub fn merge_reference(inputs: &[PathBuf], out: &Path) -> Result<()> {
    let mut docs: Vec<(PathBuf, ReferenceDoc)> = Vec::new();
    for p in inputs {
        let doc = ReferenceDoc::load(p)?;
        if let Some((_, first)) = docs.first()
            && first.key != doc.key
        {
            return Err(Error::Merge {
                path: p.clone(),
                msg: "a different reference simulation (key differs)".into(),
            });
        }
        docs.push((p.clone(), doc));
    }
    let chunks = crate::forward::runner::join_chunks(
        docs.iter().map(|(p, d)| (p.as_path(), d.chunks.as_slice())),
    )?;
    docs.sort_by_key(|(_, d)| d.chunks.first().copied());
    let (_, first) = docs.first().ok_or_else(|| Error::Merge {
        path: out.to_path_buf(),
        msg: "no inputs".into(),
    })?;
    let mut total = ReferenceTally::new(
        first.tally.resolution,
        first.tally.channels,
        !first.tally.radiance.is_empty(),
    );
    let mut wall_s = 0.0;
    for (_, d) in &docs {
        crate::forward::runner::Tally::merge(&mut total, &d.tally);
        wall_s += d.wall_s;
    }
    let doc = ReferenceDoc {
        format: REFERENCE_FORMAT.into(),
        version: REFERENCE_VERSION,
        key: first.key.clone(),
        chunks,
        wall_s,
        tally: total,
        provenance: Provenance::current(),
    };
    crate::jobs::store::write_json_compact_atomic(out, &doc)
}

/// The sequence of documents written before [`RenderDoc::sequence`].
fn independent() -> Sequence {
    Sequence::Independent
}

fn uniform() -> Allocation {
    Allocation::Uniform
}

#[cfg(test)]
mod tests {
    use super::*;

    /// References drawn with known noise around an exact image, and a
    /// method off it by a known error, noiseless or noisy itself: the error
    /// lies below its bound, an exact method reads below the resolution,
    /// and the resolution is well below the noise's own relative RMSE
    /// (what the subtraction buys on a uniform noise).
    #[test]
    fn the_resolution_bounds_the_error_under_the_noise() {
        use crate::forward::rng::PathRng;
        use crate::testing::standard_normal;
        let (n, sigma, trials) = (32, 0.05, 200);
        let exact: Vec<f64> = (0..n * n).map(|k| 1.0 + 0.5 * ((k % 7) as f64)).collect();
        let norm: f64 = exact.iter().map(|v| v * v).sum();
        let noise = ((n * n) as f64 * sigma * sigma / norm).sqrt();
        for own in [false, true] {
            let (mut covered, mut exact_below) = (0, 0);
            for trial in 0..trials {
                let mut rng = PathRng::new(11, trial);
                let mut draw = |scale: f64, noisy: bool| {
                    let mut img = Image::zeros(n, 1);
                    for (k, v) in exact.iter().enumerate() {
                        let s = if noisy { sigma } else { 0.0 };
                        img.mean[k] = v * scale + s * standard_normal(&mut rng);
                        img.stderr[k] = s;
                    }
                    img
                };
                let reference = draw(1.0, true);
                let (off, on) = (draw(1.003, own), draw(1.0, own));
                let (e, res) = (
                    rel_rmse(&off, &reference, own),
                    resolution(&off, &reference, own),
                );
                covered += usize::from(0.003 <= error_bound(e, res));
                assert!(res < 0.5 * noise, "{res} against {noise}");
                let (e, res) = (
                    rel_rmse(&on, &reference, own),
                    resolution(&on, &reference, own),
                );
                exact_below += usize::from(e < res);
                if own {
                    let m = metrics(&on, &reference);
                    assert_eq!((m.rel_rmse, m.resolution), (e, res));
                }
            }
            // 97.7 % each in expectation; 90 % of 200 fails with p < 1e-4.
            assert!(
                covered >= 180 && exact_below >= 180,
                "{own}: {covered} {exact_below}"
            );
        }
    }

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("svk-job-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn the_scene_hash_covers_the_texture_files() {
        let d = dir("hash");
        let toml = d.join("s.toml");
        std::fs::write(&toml, "texel = 0.5\nalbedo = { file = \"a.npy\" }\n").unwrap();
        let hash_with = |v: f64| {
            let a = ndarray::Array2::from_elem((3, 4), v);
            ndarray_npy::write_npy(d.join("a.npy"), &a).unwrap();
            scene_hash(&Scene::load(&toml).unwrap()).unwrap()
        };
        let (h1, h1_again, h2) = (hash_with(0.5), hash_with(0.5), hash_with(0.6));
        assert_eq!(h1, h1_again);
        assert_ne!(
            h1, h2,
            "an edited texture with the same TOML is another scene"
        );
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn albedo_channels_of_different_shapes_share_one_exact_grid() {
        let d = dir("grid");
        let toml = d.join("s.toml");
        std::fs::write(
            &toml,
            "texel = 0.25\nalbedo = { channels = [\
             { pattern = \"stripes\", values = [0.3, 0.95], width = 0.5, size = [9, 6] }, \
             { constant = 0.5 }, { constant = 0.8 }] }\n",
        )
        .unwrap();
        let scene = Scene::load(&toml).unwrap();
        assert_ne!(
            (scene.albedo[0].nx, scene.albedo[0].ny),
            (scene.albedo[1].nx, scene.albedo[1].ny)
        );
        let g = albedo_grid(&scene).unwrap();
        let (nx, ny, h) = (g[0].nx, g[0].ny, g[0].texel);
        for (c, m) in g.iter().enumerate() {
            assert_eq!((m.nx, m.ny, m.texel), (nx, ny, h));
            // Every grid texel centre reads what the scene's channel reads.
            for i in 0..ny {
                for j in 0..nx {
                    let x = -0.5 * nx as f64 * h + (j as f64 + 0.5) * h;
                    let y = 0.5 * ny as f64 * h - (i as f64 + 0.5) * h;
                    assert_eq!(
                        m.values[i * nx + j],
                        scene.albedo[c].at(x, y),
                        "{c} {i} {j}"
                    );
                }
            }
        }
        std::fs::remove_dir_all(&d).unwrap();
    }
}
