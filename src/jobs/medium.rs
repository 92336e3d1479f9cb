//! Models for any medium (η, g), built on demand and cached.
//!
//! The shipped models are for one medium (η = 1.5, g = 0.3). For another,
//! [`ensure`] runs the whole pipeline once and caches the result under a
//! content hash of (medium, [`BuildConfig`], [`BUILD_VERSION`]):
//!
//! 1. profiles of a homogeneous half-space at [`BuildConfig::profile_albedos`]
//!    under a pencil beam and under diffuse incidence (the lane engine);
//! 2. the basis BSSRDF of each incidence, fitted to them
//!    ([`crate::fit::basis::fit_basis`]);
//! 3. kernel tallies at the training grid of albedos and pair distances,
//!    and the kernel meta-model fitted to them
//!    ([`crate::fit::meta::fit_metamodel`]);
//! 4. the models' accuracy: R_d and the radial error of each basis against
//!    *fresh* simulations at albedos between the training ones (another
//!    seed), and every cell's aggregation error of the meta-model and of the
//!    manual kernel.
//!
//! Every finished simulation is written to the medium's folder before the
//! next starts, and a simulation in progress checkpoints every
//! [`BuildOptions::checkpoint_every`]: a build killed at any point resumes
//! where it stopped and loses at most one checkpoint interval. The manifest
//! `medium.json` is written last; a folder without it is an unfinished
//! build. A shard of a build (`--shard k/N`, into a folder all shards
//! share) runs that slice of every simulation and stops before the fits;
//! a build without `--shard` over the folder then merges each complete set
//! of slices and fits.
//!
//! Presets are media whose models ship with svkernel
//! ([`crate::jobs::shipped::PRESETS`]); they were made by this build.

use crate::error::{Error, Result};
use crate::fit::aggregation::AggregationRow;
use crate::fit::basis::fit_basis;
use crate::fit::lm::{FitOptions, FitReport};
use crate::forward::kernel::{KernelConfig, KernelDoc, PairGrid};
use crate::forward::medium::{Medium, Observable, Source};
use crate::forward::profile::{DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use crate::forward::runner::{RunOptions, Shard, chunk_range};
use crate::forward::tally::RadialBins;
use crate::jobs::fit_profiles::{AccuracyRow, accuracy};
use crate::jobs::store::{
    FileCheckpoint, content_hash, write_json_atomic, write_json_compact_atomic,
};
use crate::metamodel::basis::BasisModel;
use crate::metamodel::meta::MetaModelFile;
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The format tag of `medium.json`.
pub const MEDIUM_FORMAT: &str = "svkernel.medium";
/// Bumped whenever the build's algorithm changes what it produces (part of
/// the cache key).
pub const BUILD_VERSION: u32 = 1;

/// Everything that determines a medium's models.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BuildConfig {
    /// n_inside / n_outside.
    pub eta: f64,
    /// Henyey–Greenstein g.
    pub g: f64,
    /// Albedos of the profiles the bases are fitted to.
    pub profile_albedos: Vec<f64>,
    /// Pilot paths of each profile; the profile is then simulated with as
    /// many paths as reach `profile_precision` (at least the pilot's, at
    /// most `max_profile_paths`).
    pub profile_paths: u64,
    /// Relative standard error of R_d wanted of every profile.
    pub profile_precision: f64,
    pub max_profile_paths: u64,
    pub seed: u64,
    /// Basis: exponentials per profile and polynomial degree in √(1 − α).
    pub basis_components: usize,
    pub basis_degree: usize,
    /// The kernel tallies (η and g are this medium's).
    pub kernels: KernelConfig,
    /// Meta-model: Gaussians, and polynomial degrees in (ln d, √(1 − α)).
    pub meta_components: usize,
    pub meta_degrees: (usize, usize),
    /// Effective contributing paths wanted in every kernel cell
    /// ([`KernelConfig::plan`]), and the most paths of one planned run.
    pub kernel_target: f64,
    pub kernel_max_paths: u64,
    /// Fresh simulations of the accuracy check (pilot paths; the same
    /// precision as the training profiles).
    pub check_albedos: Vec<f64>,
    pub check_paths: u64,
}

/// Relative tolerance of the basis fits.
pub const FIT_TOL: f64 = 1e-9;

/// `n` albedos from `lo` to `hi`, evenly spaced in √(1 − α), to 6 decimals.
fn albedo_ladder(n: usize, lo: f64, hi: f64) -> Vec<f64> {
    let (x0, x1) = ((1.0 - lo).sqrt(), (1.0 - hi).sqrt());
    (0..n)
        .map(|k| {
            let x = x0 + (x1 - x0) * k as f64 / (n - 1) as f64;
            ((1.0 - x * x) * 1e6).round() / 1e6
        })
        .collect()
}

/// The midpoints (in √(1 − α)) of consecutive albedos, every `step`-th.
fn between(albedos: &[f64], step: usize) -> Vec<f64> {
    albedos
        .windows(2)
        .step_by(step)
        .map(|w| {
            let x = ((1.0 - w[0]).sqrt() + (1.0 - w[1]).sqrt()) / 2.0;
            ((1.0 - x * x) * 1e6).round() / 1e6
        })
        .collect()
}

impl BuildConfig {
    /// The build `svkernel medium build` runs: 16 profile albedos from 0.01
    /// to 0.999, each simulated to 0.2 % relative error of R_d after a
    /// pilot of 1e6 paths (basis 6 × degree 5, as shipped), the shipped
    /// kernel grid (8 albedos × 10 distances) planned to 2000 effective
    /// contributing paths per cell, a meta-model of 4 Gaussians and degrees
    /// (3, 3), and checks at 5 albedos between the training ones.
    pub fn standard(eta: f64, g: f64) -> Self {
        let profile_albedos = albedo_ladder(16, 0.01, 0.999);
        BuildConfig {
            eta,
            g,
            check_albedos: between(&profile_albedos, 3),
            profile_albedos,
            profile_paths: 1_000_000,
            profile_precision: 0.002,
            max_profile_paths: 1_000_000_000,
            seed: 5000,
            basis_components: 6,
            basis_degree: 5,
            kernels: KernelConfig {
                eta,
                g,
                paths: 10_000_000,
                seed: 6000,
                // The presets were built on one grid for every vertex
                // class, without a tail; a build on the refined last-vertex
                // grid and the tail of the default medium's model has not
                // been measured.
                grid: PairGrid {
                    vertex_refine: 1,
                    tail: None,
                    ..crate::jobs::shipped::training_config().grid
                },
                ..crate::jobs::shipped::training_config()
            },
            meta_components: 4,
            meta_degrees: (3, 3),
            kernel_target: 2000.0,
            kernel_max_paths: 20_000_000,
            check_paths: 1_000_000,
        }
    }

    /// A small build for tests (seconds, not minutes; its models are rough).
    pub fn quick(eta: f64, g: f64) -> Self {
        let profile_albedos = albedo_ladder(7, 0.05, 0.99);
        BuildConfig {
            check_albedos: vec![between(&profile_albedos, 1)[3]],
            profile_albedos,
            profile_paths: 200_000,
            profile_precision: 0.01,
            max_profile_paths: 2_000_000,
            basis_components: 4,
            basis_degree: 3,
            kernels: KernelConfig {
                albedos: vec![0.6, 0.8, 0.9, 0.95],
                distances: vec![0.25, 0.5, 1.0, 2.0],
                paths: 2_000_000,
                ..Self::standard(eta, g).kernels
            },
            meta_components: 2,
            meta_degrees: (1, 1),
            kernel_target: 1500.0,
            kernel_max_paths: 2_000_000,
            check_paths: 200_000,
            ..Self::standard(eta, g)
        }
    }

    /// Refuses a medium outside the simulator's domain, naming the key
    /// (`eta`, `g`), and an unusable configuration.
    pub fn validate(&self) -> Result<()> {
        Medium::new(0.5, self.g, self.eta, 1.0, None)?;
        if self.profile_albedos.len() <= self.basis_degree {
            return Err(Error::param(
                "profile_albedos",
                self.profile_albedos.len(),
                "more than the basis degree",
            ));
        }
        if self.kernel_target < crate::fit::meta::MIN_PATHS as f64 {
            return Err(Error::param(
                "kernel_target",
                self.kernel_target,
                ">= 1000 contributing paths per cell (cells with fewer are not fitted)",
            ));
        }
        if self.profile_paths == 0 || self.check_paths == 0 {
            return Err(Error::param("paths", 0, ">= 1"));
        }
        if (self.kernels.eta, self.kernels.g) != (self.eta, self.g) {
            return Err(Error::param(
                "kernels.eta/g",
                format!("{}/{}", self.kernels.eta, self.kernels.g),
                "the medium's η and g",
            ));
        }
        self.kernels.validate()
    }

    /// The content hash the cache files the models under.
    pub fn key(&self) -> Result<String> {
        let json =
            serde_json::to_vec(self).map_err(|e| Error::format("(medium build)", "config", e))?;
        Ok(content_hash([
            format!("svkernel medium v{BUILD_VERSION}").as_bytes(),
            json.as_slice(),
        ]))
    }
}

/// The folder name of a medium in the cache: `eta<η>_g<g>_<key>`.
pub fn folder_name(config: &BuildConfig) -> Result<String> {
    Ok(format!(
        "eta{}_g{}_{}",
        config.eta,
        config.g,
        &config.key()?[..16]
    ))
}

/// How a build runs.
#[derive(Clone, Debug)]
pub struct BuildOptions {
    pub progress: bool,
    /// Checkpoint interval of a simulation in progress.
    pub checkpoint_every: Duration,
    /// Only this slice of every simulation (no fits).
    pub shard: Option<Shard>,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            progress: false,
            checkpoint_every: Duration::from_secs(30),
            shard: None,
        }
    }
}

/// The accuracy of a medium's models.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Accuracy {
    /// Each basis against fresh simulations: (incidence, rows).
    pub profiles: Vec<(String, Vec<AccuracyRow>)>,
    /// Every cell's aggregation error (meta-model and manual kernel).
    pub aggregation: Vec<AggregationRow>,
}

impl Accuracy {
    /// The largest |R_d error| and radial L2 of the bases over the checks.
    pub fn worst_profile(&self) -> (f64, f64) {
        self.profiles
            .iter()
            .flat_map(|(_, rows)| rows)
            .fold((0.0f64, 0.0f64), |(a, b), r| {
                (a.max(r.rd_rel_err.abs()), b.max(r.radial_l2_model))
            })
    }

    /// Cells where the meta-model aggregates no better than the manual
    /// kernel.
    pub fn cells_not_beating_manual(&self) -> usize {
        self.aggregation
            .iter()
            .filter(|r| r.meta >= r.manual)
            .count()
    }

    /// A Markdown table: per incidence and checked albedo, R_d of the
    /// simulation and its error, and the radial L2; then the aggregation
    /// summary.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| incidence | α | R_d (fresh sim.) | basis R_d error | radial L2 | noise L2 |\n|---|---|---|---|---|---|\n",
        );
        for (inc, rows) in &self.profiles {
            for r in rows {
                s += &format!(
                    "| {inc} | {:.4} | {:.5} ± {:.5} | {:+.3} % | {:.2} % | {:.2} % |\n",
                    r.alpha,
                    r.rd_sim,
                    r.rd_sim_stderr,
                    100.0 * r.rd_rel_err,
                    100.0 * r.radial_l2_model,
                    100.0 * r.radial_l2_noise
                );
            }
        }
        let worst =
            |f: fn(&AggregationRow) -> f64| self.aggregation.iter().map(f).fold(0.0f64, f64::max);
        s += &format!(
            "\nAggregation error over {} cells (albedo units): meta-model worst {:.4}, \
             manual kernel worst {:.4}; cells where the meta-model is not below the manual kernel: {}.\n",
            self.aggregation.len(),
            worst(|r| r.meta),
            worst(|r| r.manual),
            self.cells_not_beating_manual()
        );
        s
    }
}

/// `medium.json`: what was built, how, and how accurate it is.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MediumDoc {
    pub format: String,
    pub version: u32,
    pub eta: f64,
    pub g: f64,
    pub key: String,
    pub config: BuildConfig,
    pub accuracy: Accuracy,
    /// The joint fits: the pencil and diffuse bases, the meta-model's
    /// classes (termination, evaluations, χ²/dof).
    pub fits: Vec<FitReport>,
    /// Seconds of this build's simulations and fits (not counting time
    /// before a resume).
    pub wall_s: f64,
    /// Seconds per stage: profiles, kernel tallies, basis fits, the
    /// meta-model fit and the checks (together).
    pub stages: Vec<(String, f64)>,
    pub provenance: Provenance,
}

/// A built (or cached) medium's models.
#[derive(Clone, Debug)]
pub struct BuiltMedium {
    pub dir: PathBuf,
    pub doc: MediumDoc,
    pub basis: BasisModel,
    pub basis_diffuse: BasisModel,
    pub meta: MetaModelFile,
    /// True if nothing was simulated or fitted (the folder was complete).
    pub cached: bool,
}

const BASIS: &str = "basis.json";
const BASIS_DIFFUSE: &str = "basis_diffuse.json";
const META: &str = "metamodel.json";
const MANIFEST: &str = "medium.json";

/// The models of `config`'s medium in `cache/media/`: a complete build of
/// `config` if there is one, else of any configuration for the same (η, g)
/// (`svkernel medium build --quick`, for one), else `config` built there
/// (module docs). A damaged complete entry is an error naming the file.
pub fn ensure(config: &BuildConfig, cache: &Path, opts: &BuildOptions) -> Result<BuiltMedium> {
    let dir = cache.join("media").join(folder_name(config)?);
    if !dir.join(MANIFEST).exists()
        && opts.shard.is_none()
        && let Some((found, _)) = manifests(cache)?
            .into_iter()
            .find(|(_, d)| crate::jobs::shipped::same_medium((d.eta, d.g), (config.eta, config.g)))
    {
        return load(&found, None);
    }
    build(config, &dir, opts)
}

/// Builds `config`'s models into `dir`, resuming what a previous build of
/// the same configuration left there; a complete folder is loaded.
pub fn build(config: &BuildConfig, dir: &Path, opts: &BuildOptions) -> Result<BuiltMedium> {
    config.validate()?;
    let key = config.key()?;
    if dir.join(MANIFEST).exists() {
        return load(dir, Some(&key));
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let start = Instant::now();
    let say = |msg: String| {
        if opts.progress {
            eprintln!("{msg}");
        }
    };
    say(format!(
        "building the models of the medium η = {}, g = {} in {}",
        config.eta,
        config.g,
        dir.display()
    ));
    let shard_tag = opts
        .shard
        .map(|s| format!(".shard{}of{}", s.index, s.count))
        .unwrap_or_default();
    let mut stages = Vec::new();
    let mut lap = Instant::now();
    let mut stage = |name: &str| {
        stages.push((name.to_string(), lap.elapsed().as_secs_f64()));
        lap = Instant::now();
    };
    let mut bases = Vec::new();
    for name in ["pencil", "diffuse"] {
        let source = Source::parse(name)?;
        let mut docs = Vec::new();
        for (k, &alpha) in config.profile_albedos.iter().enumerate() {
            let file = dir
                .join(format!("profiles_{name}"))
                .join(format!("a{alpha:.6}{shard_tag}.json"));
            let seed = config.seed + 100 * u64::from(name == "diffuse") + k as u64;
            say(format!(
                "  profile {name} α = {alpha} ({}/{})",
                k + 1,
                config.profile_albedos.len()
            ));
            docs.push(profile(
                config,
                alpha,
                source,
                config.profile_paths,
                seed,
                &file,
                opts,
            )?);
        }
        bases.push((name, docs));
    }
    stage("profiles");
    let kernels_file = dir.join(format!("kernels{shard_tag}.json"));
    say("  kernel tallies".into());
    let kernels = kernel_tally(config, &kernels_file, opts)?;
    stage("kernel tallies");
    if let Some(s) = opts.shard {
        // The fits need every slice: a later build without --shard over
        // this folder merges the N slices and fits.
        say(format!(
            "  shard {}/{} simulated; run the other shards into {}, then build without --shard",
            s.index,
            s.count,
            dir.display()
        ));
        return Err(Error::Merge {
            path: dir.to_path_buf(),
            msg: format!(
                "shard {}/{} done: the models need every shard (build again without --shard)",
                s.index, s.count
            ),
        });
    }
    // Fits.
    // The fits stop at a relative tolerance of 1e-9 or after their budget
    // (the report says which): the accuracy against fresh simulations
    // below is the check that counts.
    let fit_opts = FitOptions {
        tol: FIT_TOL,
        patience: 60,
        allow_nonconvergence: true,
    };
    let mut models = Vec::new();
    let mut fits = Vec::new();
    for (name, docs) in &bases {
        say(format!("  fitting the {name} basis"));
        let provenance = serde_json::json!({
            "made_by": serde_json::to_value(Provenance::current()).unwrap_or_default(),
            "medium_build": key,
            "incidence": name,
        });
        let out = fit_basis(
            docs,
            Observable::Exitance,
            config.basis_components,
            config.basis_degree,
            &fit_opts,
            provenance,
        )?;
        fits.push(out.joint);
        models.push(out.model);
    }
    stage("basis fits");
    // The meta-model fit (two classes, one thread each, of unequal
    // length) and the checks' fresh simulations share the cores.
    say("  fitting the kernel meta-model; simulating the checks".into());
    let check = || -> Result<Vec<(String, Vec<AccuracyRow>)>> {
        let mut profiles = Vec::new();
        for ((name, _), model) in bases.iter().zip(&models) {
            let source = Source::parse(name)?;
            let mut rows = Vec::new();
            for (k, &alpha) in config.check_albedos.iter().enumerate() {
                let file = dir
                    .join(format!("check_{name}"))
                    .join(format!("a{alpha:.6}.json"));
                let seed = config.seed + 500 + 100 * u64::from(*name == "diffuse") + k as u64;
                let quiet = BuildOptions {
                    progress: false,
                    ..opts.clone()
                };
                let doc = profile(
                    config,
                    alpha,
                    source,
                    config.check_paths,
                    seed,
                    &file,
                    &quiet,
                )?;
                rows.push(accuracy(model, &doc));
            }
            profiles.push((name.to_string(), rows));
        }
        Ok(profiles)
    };
    let (fitted, checked) = rayon::join(
        || {
            crate::fit::meta::fit_metamodel(
                &kernels,
                config.meta_components,
                config.meta_degrees,
                opts.progress,
            )
        },
        check,
    );
    let (meta, fit) = fitted?;
    let profiles = checked?;
    fits.extend(fit.joint.iter().cloned());
    stage("meta-model fit and checks");
    let [basis, basis_diffuse]: [BasisModel; 2] = models
        .try_into()
        .map_err(|_| Error::format(dir, "bases", "two bases expected"))?;
    write_json_atomic(&dir.join(BASIS), &basis)?;
    write_json_atomic(&dir.join(BASIS_DIFFUSE), &basis_diffuse)?;
    write_json_atomic(&dir.join(META), &meta)?;
    let doc = MediumDoc {
        format: MEDIUM_FORMAT.into(),
        version: BUILD_VERSION,
        eta: config.eta,
        g: config.g,
        key,
        config: config.clone(),
        accuracy: Accuracy {
            profiles,
            aggregation: fit.aggregation,
        },
        fits,
        wall_s: start.elapsed().as_secs_f64(),
        stages,
        provenance: Provenance::current(),
    };
    write_json_atomic(&dir.join(MANIFEST), &doc)?;
    say(format!("  done in {:.0} s", doc.wall_s));
    Ok(BuiltMedium {
        dir: dir.to_path_buf(),
        doc,
        basis,
        basis_diffuse,
        meta,
        cached: false,
    })
}

/// The manifest of the medium folder `dir`.
fn read_manifest(dir: &Path) -> Result<MediumDoc> {
    let manifest = dir.join(MANIFEST);
    let text = std::fs::read_to_string(&manifest).map_err(|e| Error::io(&manifest, e))?;
    let doc: MediumDoc =
        serde_json::from_str(&text).map_err(|e| crate::doc::json_error(&manifest, e))?;
    if doc.format != MEDIUM_FORMAT {
        return Err(Error::format(
            &manifest,
            "format",
            format!("'{}', expected '{MEDIUM_FORMAT}'", doc.format),
        ));
    }
    Ok(doc)
}

/// Loads a complete medium folder; with `key`, refuses one built from
/// another configuration.
pub fn load(dir: &Path, key: Option<&str>) -> Result<BuiltMedium> {
    let manifest = dir.join(MANIFEST);
    let doc = read_manifest(dir)?;
    if let Some(k) = key
        && doc.key != k
    {
        return Err(Error::format(
            &manifest,
            "key",
            format!(
                "{} was built from another configuration ({k} expected)",
                doc.key
            ),
        ));
    }
    Ok(BuiltMedium {
        dir: dir.to_path_buf(),
        basis: BasisModel::load(&dir.join(BASIS))?,
        basis_diffuse: BasisModel::load(&dir.join(BASIS_DIFFUSE))?,
        meta: MetaModelFile::load(&dir.join(META))?,
        doc,
        cached: true,
    })
}

/// One profile simulation, or its document if `file` holds it already
/// (resumed from `file`'s checkpoint if one was left).
fn profile(
    config: &BuildConfig,
    alpha: f64,
    source: Source,
    paths: u64,
    seed: u64,
    file: &Path,
    opts: &BuildOptions,
) -> Result<ProfileDoc> {
    if let Some(doc) = existing(file, opts, crate::forward::profile::merge)? {
        return Ok(doc);
    }
    if let Some(parent) = file.parent() {
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }
    let mut pc = ProfileConfig {
        medium: Medium::new(alpha, config.g, config.eta, 1.0, None)?,
        source,
        paths,
        seed,
        max_events: DEFAULT_MAX_EVENTS,
        bins: RadialBins::default(),
        engine: Engine::Lanes,
        radiance: false,
    };
    pc.validate()?;
    // The pilot (whole, in every shard: the same number everywhere) sets
    // the paths: N = N_pilot·(rel. error / wanted)², within the bounds.
    let (pilot, pilot_s) = pc.run(None, &RunOptions::default())?;
    let pilot = ProfileDoc::new(
        pc.clone(),
        None,
        vec![chunk_range(paths, None)],
        pilot,
        pilot_s,
        Provenance::current(),
    );
    let rel = pilot.R_d_stderr / pilot.R_d.max(1e-300);
    let want = (paths as f64 * (rel / config.profile_precision).powi(2)).ceil();
    pc.paths = (want as u64).clamp(paths, config.max_profile_paths.max(paths));
    if pc.paths == paths && opts.shard.is_none() {
        write_json_atomic(file, &pilot)?;
        return Ok(pilot);
    }
    let (ckpt, run) = run_options(file, opts);
    let (tally, wall_s) = pc.run(opts.shard, &run)?;
    let chunks = vec![chunk_range(pc.paths, opts.shard)];
    let doc = ProfileDoc::new(pc, opts.shard, chunks, tally, wall_s, Provenance::current());
    write_json_atomic(file, &doc)?;
    remove(&ckpt)?;
    Ok(doc)
}

/// The checkpoint beside `file` and how to run the simulation that writes
/// `file`: resuming from that checkpoint.
fn run_options(file: &Path, opts: &BuildOptions) -> (PathBuf, RunOptions) {
    let ckpt = checkpoint_of(file);
    let run = RunOptions {
        checkpoint: Some(FileCheckpoint::arc(&ckpt)),
        checkpoint_every: opts.checkpoint_every,
        resume: true,
        progress: opts.progress,
    };
    (ckpt, run)
}

/// The kernel tallies, or their document if `file` holds it already.
fn kernel_tally(config: &BuildConfig, file: &Path, opts: &BuildOptions) -> Result<KernelDoc> {
    if let Some(doc) = existing(file, opts, crate::forward::kernel::merge)? {
        return Ok(doc);
    }
    // Paths where each cell needs them (pilots choose every run's flight
    // sampling and length; deterministic).
    let plan = crate::forward::kernel::PlanOptions {
        target: config.kernel_target,
        max_paths: config.kernel_max_paths,
        ..Default::default()
    };
    let (kc, _) = config.kernels.plan(&plan, false)?;
    let (ckpt, run) = run_options(file, opts);
    let (tally, wall_s) = kc.run(opts.shard, &run)?;
    let chunks = vec![crate::forward::runner::shard_range(kc.chunks(), opts.shard)];
    let doc = KernelDoc::new(kc, opts.shard, chunks, tally, wall_s, Provenance::current());
    write_json_compact_atomic(file, &doc)?;
    remove(&ckpt)?;
    Ok(doc)
}

/// How the shard documents of one simulation merge into one.
type Merge<T> = fn(&[(PathBuf, T)], Provenance) -> Result<T>;

/// The document `file` holds, or (unsharded builds) the merge of a complete
/// set of shard documents beside it (`<stem>.shard<k>of<N>.json`, every k),
/// which is then written to `file`; `None` if neither exists.
fn existing<T: crate::doc::Document>(
    file: &Path,
    opts: &BuildOptions,
    merge: Merge<T>,
) -> Result<Option<T>> {
    let read = |f: &Path| -> Result<T> {
        let text = std::fs::read_to_string(f).map_err(|e| Error::io(f, e))?;
        crate::doc::from_json(&text, f)
    };
    if file.exists() {
        return read(file).map(Some);
    }
    let (Some(dir), Some(stem), None) = (
        file.parent(),
        file.file_stem().and_then(|s| s.to_str()),
        opts.shard,
    ) else {
        return Ok(None);
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(None);
    };
    let prefix = format!("{stem}.shard");
    let mut count = None;
    let mut shards = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some((k, n)) = name
            .strip_prefix(&prefix)
            .and_then(|r| r.strip_suffix(".json"))
            .and_then(|r| r.split_once("of"))
            .and_then(|(k, n)| Some((k.parse::<u64>().ok()?, n.parse::<u64>().ok()?)))
        else {
            continue;
        };
        count = Some(n);
        shards.push((k, e.path()));
    }
    let Some(n) = count else {
        return Ok(None);
    };
    shards.sort();
    if shards.len() as u64 != n || shards.iter().enumerate().any(|(i, (k, _))| *k != i as u64) {
        return Ok(None); // not all shards there yet: simulate the whole
    }
    let docs = shards
        .into_iter()
        .map(|(_, p)| Ok((p.clone(), read(&p)?)))
        .collect::<Result<Vec<_>>>()?;
    let doc = merge(&docs, Provenance::current())?;
    write_json_compact_atomic(file, &doc)?;
    Ok(Some(doc))
}

fn checkpoint_of(file: &Path) -> PathBuf {
    let mut s = file.as_os_str().to_owned();
    s.push(".ckpt");
    PathBuf::from(s)
}

fn remove(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(path, e)),
        _ => Ok(()),
    }
}

/// A medium that `svkernel medium list` shows.
#[derive(Clone, Debug, Serialize)]
pub struct Listed {
    /// `built-in`, `preset <name>` or `cached`.
    pub kind: String,
    pub eta: f64,
    pub g: f64,
    /// Where its models are.
    pub location: String,
    /// Worst basis R_d error and radial L2 over the checks, if known.
    pub worst_profile: Option<(f64, f64)>,
}

/// The complete medium folders of `cache` with their manifests, ordered
/// by (η, g).
fn manifests(cache: &Path) -> Result<Vec<(PathBuf, MediumDoc)>> {
    let dir = cache.join("media");
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return Ok(Vec::new());
    };
    let mut out = Vec::new();
    for e in entries {
        let path = e.map_err(|e| Error::io(&dir, e))?.path();
        if path.join(MANIFEST).exists() {
            let doc = read_manifest(&path)?;
            out.push((path, doc));
        }
    }
    out.sort_by(|a, b| (a.1.eta, a.1.g).partial_cmp(&(b.1.eta, b.1.g)).unwrap());
    Ok(out)
}

/// The cached media of `cache` (complete folders only).
pub fn cached(cache: &Path) -> Result<Vec<BuiltMedium>> {
    manifests(cache)?
        .into_iter()
        .map(|(dir, _)| load(&dir, None))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_medium_outside_the_domain_is_refused_naming_the_key() {
        let key = |c: BuildConfig| match c.validate() {
            Err(Error::Param { name, .. }) => name,
            other => panic!("{other:?}"),
        };
        assert_eq!(key(BuildConfig::standard(0.5, 0.3)), "eta");
        assert_eq!(key(BuildConfig::standard(1.4, 1.0)), "g");
        assert_eq!(key(BuildConfig::quick(1.4, f64::NAN)), "g");
        BuildConfig::standard(1.0, 0.0).validate().unwrap();
        BuildConfig::standard(1.4, -0.5).validate().unwrap();
    }

    #[test]
    fn albedo_ladders_and_checks_lie_between_training_albedos() {
        let a = albedo_ladder(16, 0.01, 0.999);
        assert_eq!((a[0], a[15]), (0.01, 0.999));
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        let c = BuildConfig::standard(1.4, 0.8).check_albedos;
        assert_eq!(c.len(), 5);
        for x in &c {
            assert!(!a.contains(x), "{x} is a training albedo");
        }
        // Keys differ by medium and by configuration.
        let k = |c: BuildConfig| c.key().unwrap();
        assert_ne!(
            k(BuildConfig::quick(1.4, 0.8)),
            k(BuildConfig::quick(1.4, 0.7))
        );
        assert_ne!(
            k(BuildConfig::quick(1.4, 0.8)),
            k(BuildConfig::standard(1.4, 0.8))
        );
        assert_eq!(
            k(BuildConfig::quick(1.4, 0.8)),
            k(BuildConfig::quick(1.4, 0.8))
        );
    }

    /// The build end to end on the small configuration: models of the
    /// medium asked for, accuracy measured, a second call loads the cache
    /// without simulating, and a build whose last steps were lost redoes only
    /// those (bitwise the same models).
    #[test]
    fn on_demand_build_is_cached_and_resumes() {
        let cache = tempfile::tempdir().unwrap();
        let config = BuildConfig::quick(1.3, 0.5);
        let opts = BuildOptions::default();
        let first = ensure(&config, cache.path(), &opts).unwrap();
        assert!(!first.cached);
        assert_eq!((first.basis.eta, first.basis.g), (1.3, 0.5));
        assert_eq!((first.basis_diffuse.eta, first.meta.g), (1.3, 0.5));
        assert_eq!(first.doc.accuracy.profiles.len(), 2);
        assert!(!first.doc.accuracy.aggregation.is_empty());
        let (rd, l2) = first.doc.accuracy.worst_profile();
        assert!(rd < 0.1 && l2 < 0.1, "{rd} {l2}");
        // The models, less their provenance (which records when they were made).
        let json = |b: &BuiltMedium| {
            let mut v = serde_json::to_value((&b.basis, &b.basis_diffuse, &b.meta)).unwrap();
            for m in v.as_array_mut().unwrap() {
                m.as_object_mut().unwrap().remove("provenance");
            }
            v.to_string()
        };

        let second = ensure(&config, cache.path(), &opts).unwrap();
        assert!(second.cached);
        assert_eq!(json(&second), json(&first));
        // Another configuration of the same medium finds it too.
        let standard = ensure(&BuildConfig::standard(1.3, 0.5), cache.path(), &opts).unwrap();
        assert!(standard.cached && standard.dir == first.dir);

        // Lose the fits and one profile: only those are redone.
        let dir = &first.dir;
        let kept = dir
            .join("profiles_pencil")
            .join(format!("a{:.6}.json", config.profile_albedos[0]));
        let lost = dir
            .join("profiles_diffuse")
            .join(format!("a{:.6}.json", config.profile_albedos[2]));
        let before = std::fs::metadata(&kept).unwrap().modified().unwrap();
        for f in [MANIFEST, BASIS, META] {
            std::fs::remove_file(dir.join(f)).unwrap();
        }
        std::fs::remove_file(&lost).unwrap();
        let again = build(&config, dir, &opts).unwrap();
        assert!(!again.cached && lost.exists());
        assert_eq!(
            std::fs::metadata(&kept).unwrap().modified().unwrap(),
            before
        );
        assert_eq!(json(&again), json(&first));
    }

    /// Shards into one folder, then an unsharded build merges them: the same
    /// models as an unsharded build.
    #[test]
    fn sharded_build_merges_to_the_unsharded_models() {
        let config = BuildConfig::quick(1.2, 0.2);
        let whole = tempfile::tempdir().unwrap();
        let sharded = tempfile::tempdir().unwrap();
        let a = build(&config, whole.path(), &BuildOptions::default()).unwrap();
        for index in 0..2 {
            let opts = BuildOptions {
                shard: Some(Shard { index, count: 2 }),
                ..Default::default()
            };
            let r = build(&config, sharded.path(), &opts);
            assert!(matches!(r, Err(Error::Merge { .. })), "{r:?}");
        }
        let b = build(&config, sharded.path(), &BuildOptions::default()).unwrap();
        for alpha in [0.1, 0.5, 0.8, 0.99] {
            assert_eq!(a.basis.r_d(alpha), b.basis.r_d(alpha));
            assert_eq!(a.basis_diffuse.r_d(alpha), b.basis_diffuse.r_d(alpha));
        }
        assert_eq!(
            serde_json::to_string(&a.meta.all).unwrap(),
            serde_json::to_string(&b.meta.all).unwrap()
        );
    }
}
