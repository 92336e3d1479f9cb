//! `svkernel` command line: parses arguments and calls the library.

use anyhow::{Context, Result, bail};
use clap::builder::RangedU64ValueParser;
use clap::{Args, Parser, Subcommand};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Duration;
use svkernel::fit::meta::Components;
use svkernel::forward::kernel::{self, KernelConfig, KernelDoc, PairGrid};
use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::profile::{self, DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use svkernel::forward::runner::{RunOptions, Shard, chunk_range, shard_range};
use svkernel::forward::tally::RadialBins;
use svkernel::jobs::render::Target;
use svkernel::jobs::shipped::{Models, Shipped, cache_dir};
use svkernel::jobs::store::FileCheckpoint;
use svkernel::metamodel::basis::BasisModel;
use svkernel::metamodel::meta::MetaModelFile;
use svkernel::pair::VertexClass;
use svkernel::provenance::Provenance;
use svkernel::render::estimator::{Allocation, Sampling, Sequence};
use svkernel::render::svbssrdf::{
    AlbedoSpace, DensityKernel, DensityLaw, InteriorKernel, LastKernel, SPACE_BLUR, Split, StepEnds,
};

#[derive(Parser)]
#[command(
    name = "svkernel",
    version,
    about = "Learned aggregation kernels for spatially varying BSSRDFs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a forward Monte Carlo simulation.
    #[command(subcommand)]
    Simulate(Simulate),
    /// Add shards of one simulation into one document (exact).
    Merge {
        /// Shard documents written by `simulate … --shard k/N`.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        #[arg(long)]
        out: PathBuf,
    },
    /// Fit models to simulations.
    #[command(subcommand)]
    Fit(Fit),
    /// Query the basis profile: R_d, R₁, Rₘ and p(r), CDF at given radii.
    #[command(allow_negative_numbers = true)]
    Profile {
        #[arg(long)]
        albedo: f64,
        /// Comma-separated radii in MFP.
        #[arg(long, value_delimiter = ',', default_value = "0.01,0.1,1,10")]
        radii: Vec<f64>,
        /// Basis model file (default: $SVKERNEL_BASIS, else the built-in one).
        #[arg(long)]
        model: Option<PathBuf>,
        /// Print JSON (the only output format; kept for scripts).
        #[arg(long)]
        json: bool,
    },
    /// Query an aggregation kernel: the learned meta-model or the manual kernel.
    #[command(allow_negative_numbers = true)]
    Kernel {
        /// Pair distance |x_e − x_i| in MFP.
        #[arg(long)]
        d: f64,
        #[arg(long)]
        albedo: f64,
        #[arg(long, default_value_t = 1.0)]
        density: f64,
        /// Which scattering vertices the kernel describes.
        #[arg(long, value_enum, default_value = "all")]
        vertices: VertexClass,
        /// The fixed manual kernel (docs/design.md §4) instead of the meta-model.
        #[arg(long)]
        manual: bool,
        /// Meta-model file (default: $SVKERNEL_MODEL, else the built-in one).
        #[arg(long)]
        model: Option<PathBuf>,
        /// Print JSON (the only output format; kept for scripts).
        #[arg(long)]
        json: bool,
    },
    /// Render a scene with every method and the brute-force reference.
    Render(RenderArgs),
    /// Render the reference and every method, measure each against the
    /// reference, and draw error against wall time as budgets grow against
    /// a high-budget truth; writes compare.json, report.html (self-contained)
    /// and report.md.
    Compare {
        scene: PathBuf,
        /// Samples per pixel of the main render (default: the scene's).
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
        spp: Option<u32>,
        /// Reference paths of the main render (default: the scene's).
        #[arg(long, value_parser = parse_count)]
        paths: Option<u64>,
        /// Paths of the truth (independent seed).
        #[arg(long, default_value = "2e7", value_parser = parse_count)]
        truth_paths: u64,
        /// Samples per pixel of the model methods, one render each.
        #[arg(long, value_delimiter = ',', default_value = "4,16,64,256")]
        spp_list: Vec<u32>,
        /// Reference paths, one render each.
        #[arg(long, value_delimiter = ',', default_value = "1e5,1e6,1e7", value_parser = parse_count)]
        paths_list: Vec<u64>,
        /// Skip the error-vs-time curves.
        #[arg(long)]
        no_curves: bool,
        /// Render everything in full, even effects the scene does not call for.
        #[arg(long)]
        no_analysis: bool,
        /// How entry points x_i are sampled.
        #[arg(long, value_enum, default_value = "importance")]
        sampling: Sampling,
        /// The numbers samples are made of (as for `render`).
        #[arg(long, value_enum, default_value = "sobol")]
        sequence: Sequence,
        /// How the samples are shared among the pixels (as for `render`).
        #[arg(long, value_enum, default_value = "adaptive")]
        allocation: Allocation,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where `learned` takes α_t under the interior vertices' kernel
        /// (as for `render`).
        #[arg(long, value_enum, default_value = "auto", num_args = 0..=1, default_missing_value = "always")]
        interior: InteriorKernel,
        #[command(flatten)]
        models: ModelArgs,
        #[arg(long, default_value = "out/compare")]
        out: PathBuf,
    },
    /// The open experiments over the canonical scenes (density-scaled vs
    /// plain, vertex kernels vs point albedos, two passes, the interior
    /// kernel, sampling, learned
    /// vs manual, and error vs meta-model complexity with --models): tables
    /// in experiments.html (self-contained), experiments.md and .json.
    Experiments(ExperimentsArgs),
    /// End-to-end demo on shipped data.
    Demo {
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Paths of the demo simulation.
        #[arg(long, default_value = "2e6", value_parser = parse_count)]
        paths: u64,
        #[command(flatten)]
        models: ModelArgs,
    },
    /// Design the albedo map whose appearance after sub-surface scattering
    /// matches TARGET (a .png in sRGB, or a linear .exr or .npy of
    /// reflectances in [0, 1]): L-BFGS-B on the exact gradient of the
    /// model's appearance; writes albedo.npy/.png, naive.npy, predicted.npy,
    /// design.json and report.html into --out.
    Design(DesignArgs),
    /// Models for a medium (η, g): build them, or list the media that have
    /// them.
    #[command(subcommand)]
    Medium(MediumCmd),
    /// Print a built-in scene's TOML (a starting point for your own scene).
    Scene {
        /// stripes, checker, complex, color, density or features.
        #[arg(value_parser = clap::builder::PossibleValuesParser::new(["stripes", "checker", "complex", "color", "density", "features"]))]
        name: String,
    },
}

/// `svkernel medium`.
#[derive(Subcommand)]
enum MediumCmd {
    /// Simulate and fit the models of a medium: profiles under collimated
    /// and diffuse light, both bases, kernel tallies and the meta-model;
    /// then print their accuracy against fresh simulations. Resumable: run
    /// it again after an interruption.
    Build {
        #[arg(long)]
        eta: f64,
        #[arg(long, allow_negative_numbers = true)]
        g: f64,
        /// Where to build [default: the cache, where renders find it].
        #[arg(long)]
        out: Option<PathBuf>,
        /// The cache [default: $SVKERNEL_CACHE, else the platform's cache
        /// folder, e.g. ~/.cache/svkernel].
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Run only this slice k/N of every simulation (into the same
        /// --out for all N); a build without --shard then merges and fits.
        #[arg(long)]
        shard: Option<String>,
        /// Seconds between checkpoints of a simulation in progress.
        #[arg(long, default_value_t = 30.0)]
        checkpoint_every: f64,
        /// A small build (seconds; rough models) to try the pipeline.
        #[arg(long)]
        quick: bool,
    },
    /// List the media with models: built in, presets and cached.
    List {
        #[arg(long)]
        cache: Option<PathBuf>,
    },
}

/// `svkernel medium`.
fn medium(cmd: MediumCmd) -> Result<()> {
    use svkernel::jobs::medium::{self, BuildConfig, BuildOptions};
    use svkernel::jobs::shipped::PRESETS;
    match cmd {
        MediumCmd::Build {
            eta,
            g,
            out,
            cache,
            shard,
            checkpoint_every,
            quick,
        } => {
            let config = if quick {
                BuildConfig::quick(eta, g)
            } else {
                BuildConfig::standard(eta, g)
            };
            config.validate()?;
            let opts = BuildOptions {
                progress: true,
                checkpoint_every: checkpoint_interval(checkpoint_every)?,
                shard: shard.as_deref().map(Shard::parse).transpose()?,
            };
            let built = match out {
                Some(dir) => medium::build(&config, &dir, &opts)?,
                None => medium::ensure(&config, &cache_dir(cache.as_deref())?, &opts)?,
            };
            let d = &built.doc;
            println!(
                "medium η = {}, g = {}: {} ({})",
                d.eta,
                d.g,
                built.dir.display(),
                if built.cached {
                    format!("already built, in {:.0} s", d.wall_s)
                } else {
                    format!("built in {:.0} s", d.wall_s)
                }
            );
            let parts: Vec<String> = d
                .stages
                .iter()
                .map(|(n, t)| format!("{n} {t:.0} s"))
                .collect();
            println!("stages: {}\n", parts.join(", "));
            println!("{}", d.accuracy.markdown());
        }
        MediumCmd::List { cache } => {
            let models = Models::builtin()?;
            println!("{:<22} {:>5} {:>5}  where", "medium", "η", "g");
            println!(
                "{:<22} {:>5} {:>5}  built in",
                "default", models.basis.eta, models.basis.g
            );
            for p in PRESETS {
                println!(
                    "{:<22} {:>5} {:>5}  built in: {}",
                    format!("preset {}", p.name),
                    p.eta,
                    p.g,
                    p.description
                );
            }
            let dir = cache_dir(cache.as_deref())?;
            for b in medium::cached(&dir)? {
                let (rd, l2) = b.doc.accuracy.worst_profile();
                println!(
                    "{:<22} {:>5} {:>5}  {} (worst R_d error {:.2} %, radial L2 {:.2} %)",
                    "cached",
                    b.doc.eta,
                    b.doc.g,
                    b.dir.display(),
                    100.0 * rd,
                    100.0 * l2
                );
            }
        }
    }
    Ok(())
}

/// `svkernel design`.
#[derive(Args)]
struct DesignArgs {
    /// The target appearance: .png (sRGB), .exr or .npy ((ny, nx) or (ny, nx, 3)).
    target: PathBuf,
    #[arg(long, required_unless_present = "export_check")]
    out: Option<PathBuf>,
    /// Instead of designing, write the appearance problem of the target's
    /// first channel at its naive map (grid, offsets, basis coefficients,
    /// blur levels, kernel reads, M and its exact gradient) to this JSON
    /// file, for tools/design_grad_check.py.
    #[arg(long)]
    export_check: Option<PathBuf>,
    /// Texel size in MFP.
    #[arg(long, default_value_t = 0.05)]
    texel: f64,
    /// The printable albedo range LO,HI.
    #[arg(long, default_value = "0.2,0.99", value_parser = parse_pair::<f64>)]
    albedo_range: [f64; 2],
    /// uniform, or disk:R (a disk of radius R MFP at the texture's centre).
    #[arg(long, default_value = "uniform")]
    illumination: String,
    /// Projected fixed-point steps u ← clip(u + β(target − M(u))) before
    /// L-BFGS-B, at most (a step that raises the objective halves β; they
    /// stop when β < 0.2 or a step gains < 0.5 %).
    #[arg(long, default_value_t = svkernel::design::Settings::default().warm_start)]
    warm_start: usize,
    /// L-BFGS-B iterations per channel.
    #[arg(long, default_value_t = svkernel::design::Settings::default().iterations as u64,
          value_parser = clap::value_parser!(u64).range(1..))]
    iterations: u64,
    /// L-BFGS-B rounds (learned): the kernel shapes are anchored at the
    /// current map before each.
    #[arg(long, default_value_t = svkernel::design::Settings::default().rounds as u64,
          value_parser = clap::value_parser!(u64).range(1..))]
    rounds: u64,
    /// Weight W of the smoothness term W·mean((α_e − α_e')²) over adjacent texels.
    #[arg(long, default_value_t = 0.0)]
    smoothness: f64,
    /// Forward model: learned, factorized or point.
    #[arg(long, default_value = "learned")]
    method: String,
    /// Quadrature rings and angles per ring of the appearance estimate.
    #[arg(long, default_value = "12,2", value_parser = parse_pair::<usize>)]
    quadrature: [usize; 2],
    /// Forward model learned: the space in which α_t averages albedo
    /// variation coarser than --space-blur, as in `render`.
    #[arg(long, value_enum, default_value_t = AlbedoSpace::Transport)]
    albedo_space: AlbedoSpace,
    /// Forward model learned: the scale b (MFP) that splits fine from
    /// coarse albedo variation for --albedo-space, as in `render`.
    #[arg(long, default_value_t = SPACE_BLUR)]
    space_blur: f64,
    /// Forward model learned: the kernel of that split, as in `render`
    /// (its darker regime's everywhere: below an endpoint albedo of 0.95,
    /// where `render` uses it).
    #[arg(long, value_enum, default_value_t = Split::Regimes)]
    split: Split,
    /// Forward model learned: α_t under the interior vertices' kernel, as
    /// `render --interior`.
    #[arg(long)]
    interior: bool,
    /// Validate by brute force with this many reference paths per map (e.g.
    /// 5e7): the naive map and the maps designed with learned, factorized
    /// and point, against the target.
    #[arg(long, value_parser = parse_count)]
    validate: Option<u64>,
    /// Pixels per side of the validation images.
    #[arg(long, default_value_t = 64)]
    validate_resolution: usize,
    /// Calibrate the forward model by brute force with this many reference
    /// paths (e.g. 1e8): one render of the design, the model's bias per
    /// albedo measured from it, and the design again for the target
    /// corrected by that bias (on the validation's pixel grid).
    #[arg(long, value_parser = parse_count)]
    calibrate: Option<u64>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(flatten)]
    models: ModelArgs,
}

/// `svkernel design`.
fn design(a: DesignArgs) -> Result<()> {
    use svkernel::design::Settings;
    use svkernel::design::appearance::{Illumination, Quadrature};
    use svkernel::jobs::design::{DesignOptions, run};
    let settings = Settings {
        method: svkernel::render::svbssrdf::Method::parse(&a.method)?,
        texel: a.texel,
        albedo_range: a.albedo_range,
        illumination: Illumination::parse(&a.illumination)?,
        warm_start: a.warm_start,
        iterations: a.iterations as usize,
        rounds: a.rounds as usize,
        smoothness: a.smoothness,
        quadrature: Quadrature {
            rings: a.quadrature[0],
            angles: a.quadrature[1],
        },
        albedo_space: a.albedo_space,
        space_blur: a.space_blur,
        split: a.split,
        interior_kernel: a.interior,
    };
    let opts = DesignOptions {
        target: a.target,
        out: a.out.clone().unwrap_or_default(),
        settings,
        validate: a.validate,
        validate_resolution: a.validate_resolution,
        calibrate: a.calibrate,
        seed: a.seed,
        models: a.models.load()?,
        progress: true,
    };
    if let Some(file) = &a.export_check {
        svkernel::jobs::design::export_check(&opts, file)?;
        println!("wrote {}", file.display());
        return Ok(());
    }
    let doc = run(&opts)?;
    println!(
        "designed {}×{}×{} in {:.1} s ({} evaluations; set-up {:.1} s); model error against the target: naive {:.2} %, designed {:.2} %",
        doc.shape[0],
        doc.shape[1],
        doc.shape[2],
        doc.solve_s,
        doc.evaluations,
        doc.setup_s,
        100.0 * doc.model_naive_rel_rmse,
        100.0 * doc.model_designed_rel_rmse
    );
    if let Some(c) = &doc.calibration {
        println!(
            "calibrated by brute force ({} paths); brute force ÷ model per albedo bin:",
            c.paths
        );
        for (k, t) in c.channels.iter().enumerate() {
            let bins: Vec<String> = t
                .albedo
                .iter()
                .zip(&t.ratio)
                .map(|(a, r)| format!("{a:.3}: {r:.3}"))
                .collect();
            println!("  channel {k}: {}", bins.join(", "));
        }
    }
    if let Some(v) = &doc.validation {
        println!(
            "brute force ({} paths per map, {}² pixels, reference noise {:.1} %):",
            v.paths,
            v.resolution,
            100.0 * v.reference_noise
        );
        println!(
            "  naive                  rel RMSE {:6.2} %  mean ΔE00 {:.2}",
            100.0 * v.naive.rel_rmse,
            v.naive.delta_e00
        );
        for r in &v.rows {
            println!(
                "  designed ({:10})  rel RMSE {:6.2} %  mean ΔE00 {:.2}",
                r.method,
                100.0 * r.designed.rel_rmse,
                r.designed.delta_e00
            );
        }
        match v.improvement {
            Some(x) => println!(
                "  {}'s design is {x:.1}× closer to the target than the naive map",
                v.rows[0].method
            ),
            None => println!(
                "  {}'s design is within the reference's noise of the target: more paths resolve the ratio",
                v.rows[0].method
            ),
        }
    }
    println!(
        "wrote {0}/albedo.npy, albedo.png, naive.npy, predicted.npy, design.json, report.html",
        opts.out.display()
    );
    Ok(())
}

/// Where the models come from: a flag, else its environment variable, else
/// the copy built into svkernel.
#[derive(Args, Clone, Debug)]
struct ModelArgs {
    /// Basis BSSRDF for collimated lights [default: $SVKERNEL_BASIS, else built in].
    #[arg(long)]
    basis: Option<PathBuf>,
    /// Basis BSSRDF for diffuse lights [default: $SVKERNEL_BASIS_DIFFUSE, else built in].
    #[arg(long)]
    basis_diffuse: Option<PathBuf>,
    /// Basis of the radiance along the normal for collimated lights
    /// [default: $SVKERNEL_BASIS_RADIANCE, else built in].
    #[arg(long)]
    basis_radiance: Option<PathBuf>,
    /// Basis of the radiance along the normal for diffuse lights
    /// [default: $SVKERNEL_BASIS_RADIANCE_DIFFUSE, else built in].
    #[arg(long)]
    basis_radiance_diffuse: Option<PathBuf>,
    /// Kernel meta-model [default: $SVKERNEL_MODEL, else built in].
    #[arg(long)]
    model: Option<PathBuf>,
    /// Cache of meta-model extensions [default: $SVKERNEL_CACHE, else the
    /// platform's cache folder, e.g. ~/.cache/svkernel].
    #[arg(long)]
    cache: Option<PathBuf>,
}

impl ModelArgs {
    fn load(&self) -> Result<Models> {
        Ok(Models::find(
            [
                self.basis.as_deref(),
                self.basis_diffuse.as_deref(),
                self.basis_radiance.as_deref(),
                self.basis_radiance_diffuse.as_deref(),
            ],
            self.model.as_deref(),
        )?)
    }
}

/// `svkernel experiments`.
#[derive(Args)]
struct ExperimentsArgs {
    /// Scene files (default: the six canonical scenes).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "stripes,checker,complex,color,density,features"
    )]
    scenes: Vec<PathBuf>,
    /// Samples per pixel of every model render.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..))]
    spp: u32,
    /// Reference paths per scene and pass.
    #[arg(long, default_value = "1e7", value_parser = parse_count)]
    paths: u64,
    /// Meta-model files rendered with `learned` on stripes and checker
    /// (error vs K and polynomial degrees; tools/kernel_complexity.sh).
    #[arg(long, value_delimiter = ',')]
    models: Vec<PathBuf>,
    /// Basis model files rendered with `learned` on stripes and checker
    /// (error vs exponential terms; tools/kernel_complexity.sh).
    #[arg(long, value_delimiter = ',')]
    bases: Vec<PathBuf>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(flatten)]
    model_args: ModelArgs,
    #[arg(long, default_value = "out/experiments")]
    out: PathBuf,
}

/// `svkernel render SCENE.toml`.
#[derive(Args)]
struct RenderArgs {
    /// Scene file (TOML; schema in docs/scenes.md), or a built-in scene's name.
    scene: PathBuf,
    /// Methods to render (comma-separated or repeated): reference, point,
    /// factorized, line, ellipse, manual, learned. Default: the scene's
    /// methods and the reference.
    #[arg(long = "method", value_enum, value_delimiter = ',')]
    methods: Vec<Target>,
    /// Light samples per pixel of the model methods (default: the scene's `samples`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    spp: Option<u32>,
    /// Image resolution N (N × N; default: the scene's `image.resolution`).
    #[arg(long, value_parser = RangedU64ValueParser::<usize>::new().range(1..=4096))]
    resolution: Option<usize>,
    /// How entry points x_i are sampled.
    #[arg(long, value_enum, default_value = "importance")]
    sampling: Sampling,
    /// The numbers samples are made of: Owen-scrambled Sobol' points
    /// (randomised QMC) or independent ones.
    #[arg(long, value_enum, default_value = "sobol")]
    sequence: Sequence,
    /// How the samples are shared among the pixels: the same number in
    /// every pixel, or spp on average with each pixel's share growing as
    /// its value in a pilot render to the power 0.75.
    #[arg(long, value_enum, default_value = "adaptive")]
    allocation: Allocation,
    /// Render everything in full, even effects the scene does not call
    /// for (grey RGB as three channels, a constant density map through a
    /// pyramid, a homogeneous material through every method's machinery).
    #[arg(long)]
    no_analysis: bool,
    /// Clamp `learned` outside the meta-model's trained albedo range
    /// instead of simulating and fitting the missing range; refuse a medium
    /// without models instead of building them.
    #[arg(long)]
    no_extend: bool,
    /// Kernel-method variant: not density-scaled aggregation.
    #[arg(long)]
    plain: bool,
    /// Kernel-method variant: point albedos in the local terms instead of the
    /// first/last-vertex kernels (the default).
    #[arg(long)]
    point_albedos: bool,
    /// Kernel-method variant: a second pass with α₀ = α_t.
    #[arg(long)]
    two_pass: bool,
    /// Kernel-method variant (learned): where α_t is taken under the
    /// interior vertices' kernel, without the first and last vertices that
    /// the local terms already count: blended in where the paths see an
    /// albedo above 0.95 (auto), everywhere (always; `--interior` alone) or
    /// nowhere (never). docs/design.md §4.
    #[arg(long, value_enum, default_value = "auto", num_args = 0..=1, default_missing_value = "always")]
    interior: InteriorKernel,
    /// Kernel-method variant: the space in which α_t averages albedo
    /// variation coarser than --space-blur (linear: α; transport: √(1 − α);
    /// log: ln α; absorption: ln(1 − α)); finer variation is averaged linearly.
    #[arg(long, value_enum, default_value_t = AlbedoSpace::Transport)]
    albedo_space: AlbedoSpace,
    /// Kernel-method variant: the scale b (MFP) that splits fine from coarse
    /// albedo variation for --albedo-space.
    #[arg(long, default_value_t = SPACE_BLUR)]
    space_blur: f64,
    /// Kernel-method variant: the kernel of that split (regimes: below an
    /// endpoint albedo of 0.95, a point of weight 0.2 and a Gaussian of
    /// σ = --space-blur, above 0.98 the one-flight kernel of mean length
    /// 0.5 MFP, blended between; gaussian: the Gaussian of σ = --space-blur
    /// everywhere). docs/design.md §4.
    #[arg(long, value_enum, default_value_t = Split::Regimes)]
    split: Split,
    /// Kernel-method variant, transport space: the weight c of the coarse
    /// albedo's variance within each kernel component, less its part along
    /// the pair's axis, which moves the two-scale mean y = ⟨√(1 − ᾱ)⟩ to
    /// y − c·Var/y (the albedo blurred over 1 MFP). 0 (the default) turns it
    /// off; 0.25 is the measured weight for albedo steps coarser than a mean
    /// free path, at about 50 % more time per evaluation. docs/design.md §4.
    #[arg(long, default_value_t = 0.0)]
    coarse_variance: f64,
    /// Kernel-method variant: the density that scales the profile where the
    /// density varies (endpoints: the geometric mean of the profiles at the
    /// entry's and the exit's density; kernel: the mean density under the
    /// kernel).
    #[arg(long, value_enum, default_value_t = DensityLaw::Endpoints)]
    density_law: DensityLaw,
    /// Kernel-method variant: how the kernels are placed where the density
    /// varies (scaled: at the endpoints' mean density, weighted by the
    /// density across the mixture; warp: the optical warp along the pair,
    /// weighted within each component).
    #[arg(long, value_enum, default_value_t = DensityKernel::Warp)]
    density_kernel: DensityKernel,
    /// Kernel-method variant (learned): a pair whose ends lie on the two
    /// sides of a coarse albedo step (their albedos averaged over 1 MFP
    /// differ) has its ends counted once in α_t and their albedos read in
    /// the two-scale space (correlated), or is treated as any other pair
    /// (independent). docs/design.md §4.
    #[arg(long, value_enum, default_value_t = StepEnds::Correlated)]
    step_ends: StepEnds,
    /// Kernel-method variant (learned, exitance): the albedo at which the
    /// last-vertex kernel that gives α_e is queried: l_e, the albedo its
    /// vertex sees (exit), or the pair's mean albedo α₀ (pair).
    /// docs/design.md §4.
    #[arg(long, value_enum, default_value_t = LastKernel::Exit)]
    last_kernel: LastKernel,
    /// Paths of the reference (default: the scene's `reference_paths`; 1e7 notation).
    #[arg(long, value_parser = parse_count)]
    paths: Option<u64>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Reference: run only the k-th of N slices (0-based); merge the
    /// `reference.tally.json` files with `svkernel merge`.
    #[arg(long)]
    shard: Option<String>,
    /// Reference: use merged tallies (one per pass) instead of simulating.
    #[arg(long = "reference-tally", value_delimiter = ',')]
    reference_tallies: Vec<PathBuf>,
    /// Seconds between reference checkpoints (OUT/reference.<pass>.ckpt).
    #[arg(long, default_value_t = 30.0)]
    checkpoint_every: f64,
    /// Continue the reference from its checkpoint.
    #[arg(long)]
    resume: bool,
    #[command(flatten)]
    models: ModelArgs,
    /// Output directory.
    #[arg(long, default_value = "out/render")]
    out: PathBuf,
}

/// The profiles of the default medium in a checkout of the repository.
const DEFAULT_PROFILES: &str = "data/profiles/eta1.5_g0.3_pencil";
/// The kernel tallies the shipped meta-model was fitted to (in a checkout).
const DEFAULT_KERNELS: &str = "data/kernels/eta1.5_g0.3_pencil.json";

#[derive(Subcommand)]
enum Fit {
    /// Fit the smooth basis BSSRDF to a directory of profile documents.
    Profiles {
        #[arg(long = "in", default_value = DEFAULT_PROFILES)]
        input: PathBuf,
        /// The fitted model (the shipped one is never replaced unless named here).
        #[arg(long, default_value = "out/fit/basis.json")]
        out: PathBuf,
        /// Directory for report.json and the plots (default: OUT's directory/basis_report).
        #[arg(long)]
        report: Option<PathBuf>,
        /// Exponentials in the multiple-scattering mixture.
        #[arg(long, default_value_t = 6)]
        components: usize,
        /// Polynomial degree in sqrt(1 − α).
        #[arg(long, default_value_t = 5)]
        degree: usize,
        /// Relative tolerance of LM's ftol/xtol (convergence criterion).
        #[arg(long, default_value_t = 1e-12)]
        tol: f64,
        /// The profile to fit: the exitance, or the radiance along the
        /// normal (profiles simulated with --radiance)
        #[arg(long, value_enum, default_value = "exitance")]
        observable: svkernel::forward::medium::Observable,
    },
    /// Export one profile's multiple-scattering fit problem and LM's optimum
    /// (for tools/nlopt_check.py).
    Export {
        #[arg(long)]
        albedo: f64,
        #[arg(long = "in", default_value = DEFAULT_PROFILES)]
        input: PathBuf,
        #[arg(long, default_value_t = 6)]
        components: usize,
        #[arg(long)]
        out: PathBuf,
    },
    /// Fit the kernel meta-model (all and last vertices) to a kernel document.
    Kernels {
        /// The kernel tally. Given again, each later tally is overlaid on
        /// the first: its cells replace those at its albedos (same medium,
        /// distances, window and grid).
        #[arg(long = "in", default_value = DEFAULT_KERNELS, action = clap::ArgAction::Append)]
        input: Vec<PathBuf>,
        /// The fitted meta-model (the shipped one is never replaced unless named here).
        #[arg(long, default_value = "out/fit/metamodel.json")]
        out: PathBuf,
        /// Directory for report.json (default: OUT's directory/metamodel_report)
        #[arg(long)]
        report: Option<PathBuf>,
        /// Gaussian components K of the all-vertex and of the last-vertex
        /// kernels, e.g. 4,5 (one number: the same K for both).
        #[arg(long, value_delimiter = ',', default_value = "4,5",
              value_parser = RangedU64ValueParser::<usize>::new().range(1..=5))]
        components: Vec<usize>,
        /// Polynomial degrees in ln d and sqrt(1 − α), e.g. 3,3 [default:
        /// 4,3]. With --from: raise the model's degrees to these (the new
        /// coefficients start at zero).
        #[arg(long, value_delimiter = ',')]
        degree: Option<Vec<usize>>,
        /// Fit the first- and last-vertex histograms summed onto a grid this
        /// many times finer than the all-vertex one (a divisor of the tally's
        /// own; exact, one vertex of each per path): fewer bins, a faster fit.
        #[arg(long)]
        vertex_refine: Option<usize>,
        /// Start the joint fits from this fitted meta-model's coefficients,
        /// at its K and its degrees (or --degree), instead of climbing from
        /// per-cell fits: a refit of a new tally over the model's box (its
        /// box, g and η must be the tally's).
        #[arg(long, conflicts_with = "components")]
        from: Option<PathBuf>,
        /// Let the whole-plane moment residuals allow for the data's own
        /// standard errors (each tolerance τ becomes sqrt(τ² + se²)): for
        /// tallies whose moments are noisier than the tolerances.
        #[arg(long)]
        moment_errors: bool,
        /// The weight W of the whole-plane moment residuals against the
        /// bins: a miss by the tolerance (5 % of d in mean t, 10 % in rms s)
        /// costs W² in χ².
        #[arg(long, default_value_t = svkernel::fit::gmm::MOMENT_WEIGHT)]
        moment_weight: f64,
    },
    /// Make a fitted meta-model carry a fit over a wider box (d, α), which
    /// answers the kernel queries outside its own box (the shipped model
    /// carries data/profiles/metamodel_wide.json).
    Outer {
        /// The fitted meta-model.
        #[arg(long)]
        model: PathBuf,
        /// The meta-model of the wider box.
        #[arg(long)]
        outer: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
    /// The aggregation errors and whole-plane moments of a meta-model
    /// against a kernel tally, cell by cell, without fitting (queries
    /// outside the model's box go to its outer model, as in `render`).
    CheckKernels {
        /// The kernel tally; given again, overlaid as in `fit kernels`.
        #[arg(long = "in", default_value = DEFAULT_KERNELS, action = clap::ArgAction::Append)]
        input: Vec<PathBuf>,
        /// Meta-model [default: $SVKERNEL_MODEL, else built in].
        #[arg(long)]
        model: Option<PathBuf>,
        /// Sum the tally's first- and last-vertex histograms onto this
        /// refinement first (as `fit kernels --vertex-refine`).
        #[arg(long)]
        vertex_refine: Option<usize>,
        /// Also write the per-cell table (Markdown).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Export a few cells of the meta-model fit (residuals, Jᵀr, Jacobian
    /// columns) and one per-configuration GMM fit, for tools/jax_check.py
    /// and tools/nlopt_check.py --gmm.
    ExportKernels {
        #[arg(long = "in", default_value = DEFAULT_KERNELS)]
        input: PathBuf,
        /// Meta-model [default: $SVKERNEL_MODEL, else built in].
        #[arg(long)]
        model: Option<PathBuf>,
        /// all or last (the first-vertex kernel is exact: no fit).
        #[arg(long, value_enum, default_value = "all")]
        vertices: VertexClass,
        /// Cells to export (spread over the training set).
        #[arg(long, default_value_t = 6)]
        cells: usize,
        #[arg(long)]
        out: PathBuf,
    },
    /// Kernels across a density step (ρ = 1 | 4, a vertical plane halfway
    /// between x_i and x_e), measured with delta tracking, against the
    /// density-scaled homogeneous meta-model kernel.
    DensityStep {
        /// Meta-model [default: $SVKERNEL_MODEL, else built in].
        #[arg(long)]
        model: Option<PathBuf>,
        #[arg(long, value_delimiter = ',', default_value = "0.6,0.9,0.99")]
        albedos: Vec<f64>,
        #[arg(long, value_delimiter = ',', default_value = "0.5,1,2,4")]
        distances: Vec<f64>,
        #[arg(long, default_value = "1e7", value_parser = parse_count)]
        paths: u64,
        #[arg(long, default_value_t = 11)]
        seed: u64,
        /// Also write the rows as JSON.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Accuracy of a basis model against a directory of (fresh) profiles.
    Check {
        /// Basis model [default: $SVKERNEL_BASIS, else built in].
        #[arg(long)]
        model: Option<PathBuf>,
        #[arg(long = "in")]
        input: PathBuf,
        /// Also write the rows as JSON.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
enum Simulate {
    /// Radial profile R(r) = R₁ + Rₘ of a homogeneous half-space or slab.
    #[command(allow_negative_numbers = true)]
    Profile(ProfileArgs),
    /// Path densities (aggregation kernels) of a homogeneous half-space under
    /// a pencil beam: first, last and all scattering vertices of the paths
    /// that exit at each distance, for each albedo.
    #[command(allow_negative_numbers = true)]
    Kernels(KernelArgs),
}

/// The medium flags shared by the simulate commands.
#[derive(Args)]
struct MediumArgs {
    /// Relative index of refraction n_inside/n_outside, in [1, 3].
    #[arg(long, default_value_t = 1.5)]
    eta: f64,
    /// Henyey–Greenstein g in (−1, 1); g > 0 scatters forward.
    #[arg(long, default_value_t = 0.3)]
    g: f64,
    /// Density ρ > 0 (σ_t = ρ per MFP).
    #[arg(long, default_value_t = 1.0)]
    density: f64,
}

/// How a simulation runs: size, streams, shard, checkpoints, output.
#[derive(Args)]
struct RunArgs {
    /// Number of paths (accepts 1e7 notation; kernels walk each once per albedo).
    #[arg(long, default_value = "1e6", value_parser = parse_count)]
    paths: u64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Run only the k-th of N slices (0-based), for `merge` later.
    #[arg(long)]
    shard: Option<String>,
    /// Stop a path after this many scattering events (counted as truncated).
    #[arg(long, default_value_t = DEFAULT_MAX_EVENTS)]
    max_events: u32,
    /// Seconds between checkpoints (written to OUT.ckpt).
    #[arg(long, default_value_t = 30.0)]
    checkpoint_every: f64,
    /// Continue from OUT.ckpt if it exists.
    #[arg(long)]
    resume: bool,
    /// Output JSON document.
    #[arg(long)]
    out: PathBuf,
}

impl RunArgs {
    /// The parsed shard and the runner's options (validates the interval).
    fn options(&self) -> Result<(Option<Shard>, RunOptions)> {
        let shard = self.shard.as_deref().map(Shard::parse).transpose()?;
        let opts = RunOptions {
            checkpoint: Some(FileCheckpoint::arc(checkpoint_path(&self.out))),
            checkpoint_every: checkpoint_interval(self.checkpoint_every)?,
            resume: self.resume,
            progress: std::io::stderr().is_terminal(),
        };
        Ok((shard, opts))
    }
}

#[derive(Args)]
struct KernelArgs {
    /// Comma-separated albedos in [0, 1].
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.3,0.6,0.8,0.9,0.95,0.99"
    )]
    albedos: Vec<f64>,
    /// Comma-separated pair distances d in MFP (bins d·(1 ± rel-width) must not overlap).
    #[arg(long, value_delimiter = ',', default_value = "0.1,0.25,0.5,1,2,4,8")]
    distances: Vec<f64>,
    /// Relative half-width w of the distance bins.
    #[arg(long, default_value_t = 0.1)]
    rel_width: f64,
    /// Minimum scattering order of a contributing path (2: multiple scattering).
    #[arg(long, default_value_t = 2)]
    min_order: u32,
    #[command(flatten)]
    medium: MediumArgs,
    /// Histogram bins along the axis and across it, and the extent in units of λ = d/2 + 1/ρ.
    #[arg(long, default_value_t = PairGrid::default().nu)]
    nu: usize,
    #[arg(long, default_value_t = PairGrid::default().nv)]
    nv: usize,
    #[arg(long, default_value_t = PairGrid::default().extent)]
    extent: f64,
    /// The first- and last-vertex histograms have this many times as many
    /// bins along each axis (one vertex's core is narrower than a bin of
    /// the all-vertex grid).
    #[arg(long, default_value_t = PairGrid::default().vertex_refine)]
    vertex_refine: usize,
    /// Log-spaced all-vertex bins beyond the core (each side along the
    /// axis, and outward across it), out to `--tail-extent` (λ units): the
    /// window that holds the far vertices of high albedos. Default: none.
    #[arg(long, requires = "tail_extent")]
    tail_bins: Option<usize>,
    /// The tail's far edge in units of λ (beyond `--extent`).
    #[arg(long, requires = "tail_bins")]
    tail_extent: Option<f64>,
    /// Plan the simulation so that every cell gets at least this many
    /// effective contributing paths: pilot walks choose per cell a flight
    /// stretch and a path count (then `--paths` is the most paths of one run).
    #[arg(long)]
    min_paths: Option<f64>,
    /// With --min-paths: at most this many top-up rounds after the plan,
    /// each sized from the tally so far for the cells still short.
    #[arg(long, default_value_t = 3)]
    top_ups: usize,
    /// With --min-paths: also offer the pilots exponential transforms with
    /// angular biasing at these fractions of the albedo's bias bound (e.g.
    /// 0.9,0.97), for far cells at low albedo.
    #[arg(long, value_delimiter = ',')]
    angular: Vec<f64>,
    /// With --min-paths: a top-up round pilots again the albedos of the
    /// cells still short. A cell whose runs delivered less than half the
    /// effective paths per unit of work that their sampling's pilot
    /// promised moves to another flight sampling whose pilot promises twice
    /// what they delivered (its tally from them is then dropped).
    #[arg(long)]
    replan: bool,
    /// With --min-paths: top up this finished tally instead of planning a
    /// new one. Its configuration (medium, cells, grid, seed and runs) and
    /// paths are kept, and only the cells below --min-paths get more paths,
    /// from streams that continue the tally's own; the configuration flags
    /// are not read.
    #[arg(long, requires = "min_paths", conflicts_with = "shard")]
    from: Option<PathBuf>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Args)]
struct ProfileArgs {
    /// Single-scattering albedo α in [0, 1].
    #[arg(long)]
    albedo: f64,
    #[command(flatten)]
    medium: MediumArgs,
    /// Slab thickness in MFP (default: half-space).
    #[arg(long)]
    thickness: Option<f64>,
    /// pencil | collimated:R | diffuse:R (R in MFP).
    #[arg(long, default_value = "pencil")]
    source: String,
    /// lanes (8-wide f32 SIMD) or scalar (plain f64) [default: lanes, or
    /// scalar with --radiance]
    #[arg(long, value_enum)]
    engine: Option<Engine>,
    /// Also tally the radiance leaving along the normal (next-event
    /// estimation at every scattering vertex; scalar engine), for a basis of
    /// the radiance observable (`fit profiles --observable radiance`)
    #[arg(long)]
    radiance: bool,
    /// Also write the per-bin arrays as OUT.npy.
    #[arg(long)]
    npy: bool,
    #[command(flatten)]
    run: RunArgs,
}

/// Parses a count such as `1000000`, `1e6` or `2.5e7`.
/// `A,B` (two values of one type).
fn parse_pair<T: std::str::FromStr>(s: &str) -> std::result::Result<[T; 2], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [a, b] = parts.as_slice() else {
        return Err(format!("'{s}' is not two comma-separated values"));
    };
    let parse = |v: &str| {
        v.parse::<T>()
            .map_err(|_| format!("'{v}' in '{s}' is not a number"))
    };
    Ok([parse(a)?, parse(b)?])
}

fn parse_count(s: &str) -> std::result::Result<u64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a number"))?;
    if !((1.0..=1e15).contains(&v) && v.fract() == 0.0) {
        return Err(format!("'{s}' must be an integer in [1, 1e15]"));
    }
    Ok(v as u64)
}

fn checkpoint_path(out: &std::path::Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".ckpt");
    PathBuf::from(s)
}

/// Removes the checkpoint of a finished run.
fn remove_checkpoint(out: &std::path::Path) -> Result<()> {
    let ckpt = checkpoint_path(out);
    if ckpt.exists() {
        std::fs::remove_file(&ckpt).with_context(|| format!("removing {}", ckpt.display()))?;
    }
    Ok(())
}

fn simulate_kernels(a: KernelArgs) -> Result<()> {
    let (shard, opts) = a.run.options()?;
    let config = KernelConfig {
        g: a.medium.g,
        eta: a.medium.eta,
        density: a.medium.density,
        albedos: a.albedos,
        distances: a.distances,
        rel_width: a.rel_width,
        min_order: a.min_order,
        paths: a.run.paths,
        seed: a.run.seed,
        max_events: a.run.max_events,
        grid: PairGrid {
            nu: a.nu,
            nv: a.nv,
            extent: a.extent,
            vertex_refine: a.vertex_refine,
            tail: a
                .tail_bins
                .zip(a.tail_extent)
                .map(|(bins, extent)| kernel::Tail { bins, extent }),
        },
        runs: Vec::new(),
    };
    config.validate()?;
    let plan = |target| kernel::PlanOptions {
        target,
        max_paths: a.run.paths,
        angular_fractions: a.angular.clone(),
        replan: a.replan,
        ..Default::default()
    };
    let (config, tally, wall_s) = match (a.min_paths, &a.from) {
        (Some(target), Some(from)) => {
            let doc = KernelDoc::load(from)?;
            if doc.shard.is_some() {
                bail!(
                    "{}: key 'shard': a shard of a tally (merge the shards with `svkernel merge` first)",
                    from.display()
                );
            }
            let start = Rounds::finished(doc.config, doc.tally, doc.wall_s);
            run_with_top_ups(start, &plan(target), a.top_ups, &a.run.out, &opts)?
        }
        (None, _) => {
            let (tally, wall_s) = config.run(shard, &opts)?;
            (config, tally, wall_s)
        }
        (Some(target), None) => {
            let plan = plan(target);
            let (planned, cells) = config.plan(&plan, opts.progress)?;
            print_plan(&planned, &cells);
            if shard.is_some() {
                // Top-ups need the whole tally: a shard runs the plan as is.
                let (tally, wall_s) = planned.run(shard, &opts)?;
                (planned, tally, wall_s)
            } else {
                let start = Rounds::planned(planned);
                run_with_top_ups(start, &plan, a.top_ups, &a.run.out, &opts)?
            }
        }
    };
    let chunks = vec![shard_range(config.chunks(), shard)];
    let doc = KernelDoc::new(config, shard, chunks, tally, wall_s, Provenance::current());
    svkernel::jobs::store::write_json_compact_atomic(&a.run.out, &doc)?;
    remove_checkpoint(&a.run.out)?;
    print_kernel_summary(&doc);
    Ok(())
}

/// The state of a planned simulation between top-up rounds, kept in
/// `OUT.rounds` so that `--resume` after a kill loses at most the running
/// round's last checkpoint interval.
#[derive(serde::Serialize, serde::Deserialize)]
struct Rounds {
    /// The configuration the rounds started from (a plan, or a finished
    /// tally's): a kept state resumes only the same start.
    plan: KernelConfig,
    config: KernelConfig,
    /// `None` until the plan itself has run.
    tally: Option<kernel::KernelTally>,
    wall_s: f64,
    round: usize,
}

impl Rounds {
    /// A plan that has not run yet.
    fn planned(config: KernelConfig) -> Self {
        Rounds {
            plan: config.clone(),
            config,
            tally: None,
            wall_s: 0.0,
            round: 0,
        }
    }

    /// A finished tally, before any top-up round of its own.
    fn finished(config: KernelConfig, tally: kernel::KernelTally, wall_s: f64) -> Self {
        Rounds {
            plan: config.clone(),
            config,
            tally: Some(tally),
            wall_s,
            round: 0,
        }
    }
}

/// Runs the start's configuration unless its tally is already there, then
/// up to `top_ups` rounds of [`KernelConfig::top_up`] where cells fell
/// short. Each finished round is kept in `OUT.rounds`.
fn run_with_top_ups(
    start: Rounds,
    plan: &kernel::PlanOptions,
    top_ups: usize,
    out: &std::path::Path,
    opts: &RunOptions,
) -> Result<(KernelConfig, kernel::KernelTally, f64)> {
    let rounds_path = {
        let mut s = out.as_os_str().to_owned();
        s.push(".rounds");
        PathBuf::from(s)
    };
    let kept: Option<Rounds> = if opts.resume && rounds_path.exists() {
        let r: Rounds = svkernel::jobs::store::read_json(&rounds_path)?;
        (r.plan == start.plan && r.tally.is_some()).then_some(r)
    } else {
        None
    };
    let mut state = kept.unwrap_or(start);
    if state.tally.is_none() {
        let (tally, wall_s) = state.config.run(None, opts)?;
        state.tally = Some(tally);
        state.wall_s += wall_s;
    }
    while state.round < top_ups {
        // The finished round is kept; its chunk checkpoint is spent.
        svkernel::jobs::store::write_json_compact_atomic(&rounds_path, &state)?;
        remove_checkpoint(out)?;
        let tally = state.tally.as_mut().expect("the start has run");
        let Some(grown) = state.config.top_up(tally, plan)? else {
            break;
        };
        let range = (state.config.chunks(), grown.chunks());
        let new_runs = &grown.runs[state.config.runs.len()..];
        let moved = (0..grown.albedos.len())
            .flat_map(|ia| (0..grown.distances.len()).map(move |id| (ia, id)))
            .filter(|&(ia, id)| {
                grown.run_of(ia, id).map(|r| r.flights)
                    != state.config.run_of(ia, id).map(|r| r.flights)
            })
            .count();
        eprintln!(
            "top-up {}: {} more paths for {} cells below {} effective paths{}",
            state.round + 1,
            grown.paths - state.config.paths,
            new_runs.iter().map(|r| r.distances.len()).sum::<usize>(),
            plan.target,
            if moved > 0 {
                format!(" ({moved} moved to another flight sampling)")
            } else {
                String::new()
            }
        );
        let (extra, wall_s) = grown.run_chunks(range, opts)?;
        use svkernel::forward::runner::Tally as _;
        tally.merge(&extra);
        state.wall_s += wall_s;
        state.config = grown;
        state.round += 1;
    }
    if rounds_path.exists() {
        std::fs::remove_file(&rounds_path)
            .with_context(|| format!("removing {}", rounds_path.display()))?;
    }
    let tally = state.tally.expect("the start has run");
    Ok((state.config, tally, state.wall_s))
}

fn print_plan(config: &KernelConfig, cells: &[kernel::PlannedCell]) {
    use std::io::Write;
    let mut text = format!(
        "plan: {} runs, {:.3e} paths\n   α        d   stretch  bias forced angular   pilot paths → contributing   expected effective   run paths\n",
        config.runs.len(),
        config.paths as f64
    );
    for c in cells {
        let run_paths = config
            .albedos
            .iter()
            .position(|&a| a == c.albedo)
            .zip(config.distances.iter().position(|&d| d == c.d))
            .map_or(0, |(ia, id)| config.launched_for(ia, id));
        text += &format!(
            "{:6.4} {:8.3} {:9.3} {:5.2} {:6} {:7} {:13} → {:12} {:20.0} {:11.3e}\n",
            c.albedo,
            c.d,
            c.flights.stretch,
            c.flights.bias,
            c.flights.forced,
            if c.flights.angular { "yes" } else { "no" },
            c.pilot_paths,
            c.pilot_contributing,
            c.expected,
            run_paths as f64
        );
    }
    let _ = std::io::stderr().lock().write_all(text.as_bytes());
}

fn print_kernel_summary(doc: &KernelDoc) {
    use std::io::Write;
    let mut text = format!(
        "{} paths × {} albedos in {:.2} s\n   α        d   contributing  effective stretch  bias   mean n   mean u (all/first/last)\n",
        doc.paths,
        doc.config.albedos.len(),
        doc.wall_s
    );
    for c in &doc.summary {
        text += &format!(
            "{:6.4} {:8.3} {:13} {:10.0} {:7.3} {:5.2} {:8.1}   {:+.3} / {:+.3} / {:+.3}\n",
            c.albedo,
            c.d,
            c.paths,
            c.effective_paths,
            c.flights.stretch,
            c.flights.bias,
            c.mean_vertices,
            c.mean_u[0],
            c.mean_u[1],
            c.mean_u[2]
        );
    }
    let _ = std::io::stdout().lock().write_all(text.as_bytes());
}

fn simulate_profile(a: ProfileArgs) -> Result<()> {
    let m = &a.medium;
    let medium = Medium::new(a.albedo, m.g, m.eta, m.density, a.thickness)?;
    let source = Source::parse(&a.source)?;
    let (shard, opts) = a.run.options()?;
    let engine = a.engine.unwrap_or(if a.radiance {
        Engine::Scalar
    } else {
        Engine::Lanes
    });
    let config = ProfileConfig {
        medium,
        source,
        paths: a.run.paths,
        seed: a.run.seed,
        max_events: a.run.max_events,
        bins: RadialBins::default(),
        engine,
        radiance: a.radiance,
    };
    config.validate()?;
    let (tally, wall_s) = config.run(shard, &opts)?;
    let chunks = vec![chunk_range(config.paths, shard)];
    let doc = ProfileDoc::new(config, shard, chunks, tally, wall_s, Provenance::current());
    write_doc(&doc, &a.run.out, a.npy)?;
    remove_checkpoint(&a.run.out)?;
    print_summary(&doc);
    Ok(())
}

fn write_doc(doc: &ProfileDoc, out: &std::path::Path, npy: bool) -> Result<()> {
    if npy {
        let b = &doc.bins;
        let rings = b.p_1.len();
        let cols = [&b.p_1, &b.p_1_stderr, &b.p_m, &b.p_m_stderr, &b.r_1, &b.r_m];
        let arr = ndarray::Array2::from_shape_fn((rings, 8), |(k, j)| match j {
            0 => b.edges[k],
            1 => b.edges[k + 1],
            _ => cols[j - 2][k],
        });
        svkernel::jobs::store::write_npy_atomic(&out.with_extension("npy"), &arr)?;
    }
    svkernel::jobs::store::write_json_atomic(out, doc)?;
    Ok(())
}

/// Prints the summary of a written profile. A closed stdout (e.g. `| head -1`)
/// is not an error: the result is already on disk.
fn print_summary(doc: &ProfileDoc) {
    use std::io::Write;
    let text = format!(
        "R_d = {:.6} ± {:.6}   R_1 = {:.6} ± {:.6}   R_m = {:.6} ± {:.6}\n\
         energy balance: R_d {:.6} + R_sp {:.6} + absorbed {:.6} + transmitted {:.6} + truncated {:.2e} = {:.9}\n\
         {} paths, {} scattering events ({:.1} per path), {:.2} s, {:.3e} events/s\n",
        doc.R_d,
        doc.R_d_stderr,
        doc.R_1,
        doc.R_1_stderr,
        doc.R_m,
        doc.R_m_stderr,
        doc.R_d,
        doc.R_sp,
        doc.absorbed,
        doc.transmitted,
        doc.truncated,
        doc.energy_balance,
        doc.paths,
        doc.events,
        doc.mean_events,
        doc.wall_s,
        doc.events as f64 / doc.wall_s.max(1e-9)
    );
    let radiance = doc.radiance.as_ref().map_or(String::new(), |r| {
        format!(
            "normal radiance ∫L dA: L_1 = {:.6} ± {:.6} /sr   L_m = {:.6} ± {:.6} /sr\n",
            r.single.value, r.single.stderr, r.multi.value, r.multi.stderr
        )
    });
    let _ = std::io::stdout()
        .lock()
        .write_all((text + &radiance).as_bytes());
}

/// Merges profile or kernel shards (the format of the first input decides).
fn merge(inputs: Vec<PathBuf>, out: PathBuf) -> Result<()> {
    let format = svkernel::jobs::store::read_format(&inputs[0])?;
    if format.as_deref() == Some(svkernel::render::reference::REFERENCE_FORMAT) {
        svkernel::jobs::render::merge_reference(&inputs, &out)?;
        println!(
            "merged {} reference tallies into {}",
            inputs.len(),
            out.display()
        );
        return Ok(());
    }
    if format.as_deref() == Some(kernel::KERNEL_FORMAT) {
        let docs = inputs
            .into_iter()
            .map(|p| KernelDoc::load(&p).map(|d| (p, d)))
            .collect::<svkernel::Result<Vec<_>>>()?;
        let doc = kernel::merge(&docs, Provenance::current())?;
        svkernel::jobs::store::write_json_compact_atomic(&out, &doc)?;
        print_kernel_summary(&doc);
        return Ok(());
    }
    if format.as_deref() != Some(profile::PROFILE_FORMAT) {
        let found = format.map_or("not an svkernel document (no format tag)".into(), |f| {
            format!("a `{f}` document")
        });
        bail!(
            "{}: format: {found}; merge adds shards of `{}`, `{}` or `{}` documents",
            inputs[0].display(),
            profile::PROFILE_FORMAT,
            kernel::KERNEL_FORMAT,
            svkernel::render::reference::REFERENCE_FORMAT
        );
    }
    let docs = inputs
        .into_iter()
        .map(|p| ProfileDoc::load(&p).map(|d| (p, d)))
        .collect::<svkernel::Result<Vec<_>>>()?;
    let doc = profile::merge(&docs, Provenance::current())?;
    write_doc(&doc, &out, false)?;
    print_summary(&doc);
    Ok(())
}

fn demo(out: PathBuf, paths: u64, models: ModelArgs) -> Result<()> {
    let models = models.load()?;
    let r = svkernel::jobs::demo::run(&out, paths, &models, true)?;
    let d = &r.doc;
    println!("svkernel demo — default medium (η = 1.5, g = 0.3), α = 0.9, pencil beam");
    print_summary(d);
    let z = (d.R_d - r.oracle) / (d.R_d_stderr.powi(2) + r.oracle_accuracy.powi(2)).sqrt();
    println!(
        "R_d = {:.5} ± {:.5} vs adding-doubling oracle {:.5} ± {:.4}: difference {:+.5} ({:+.2} σ combined)",
        d.R_d,
        d.R_d_stderr,
        r.oracle,
        r.oracle_accuracy,
        d.R_d - r.oracle,
        z
    );
    let (rd, r1, rm) = r.basis;
    println!(
        "shipped basis BSSRDF at α = 0.9: R_d = {rd:.5} (simulation {:.5}, {:+.2} %), R_1 = {r1:.5}, R_m = {rm:.5}",
        d.R_d,
        100.0 * (rd / d.R_d - 1.0)
    );
    println!(
        "aggregation kernel at d = 1 MFP, α = 0.9 (all vertices; t from x_i toward x_e, MFP):"
    );
    println!("  learned: {}", r.learned);
    println!("  manual : {}", r.manual);
    println!("wrote {} and {}", r.json.display(), r.plot.display());
    println!(
        "comparing {} (64 spp importance sampling on Sobol' points, reference 4e6 paths, 64² pixels, error-vs-time curves):",
        svkernel::jobs::demo::DEMO_SCENES.join(", ")
    );
    let scenes = svkernel::jobs::demo::compare_scenes(&out, &models, true)?;
    for (_, c) in &scenes {
        print!("{}", c.doc);
    }
    println!(
        "wrote {0}/index.html (self-contained report), {0}/index.md, and per scene {0}/<scene>/report.html",
        out.display()
    );
    Ok(())
}

fn fit(f: Fit) -> Result<()> {
    use svkernel::jobs::fit_profiles as report;
    match f {
        Fit::Profiles {
            input,
            out,
            report: dir,
            components,
            degree,
            tol,
            observable,
        } => {
            if !(tol > 0.0 && tol < 1.0) {
                bail!("invalid --tol = {tol}: must be in (0, 1)");
            }
            if !(1..=12).contains(&components) {
                bail!("invalid components = {components}: must be in 1..=12");
            }
            if degree > 10 {
                bail!("invalid degree = {degree}: must be <= 10");
            }
            let dir = dir.unwrap_or_else(|| {
                out.parent()
                    .unwrap_or(std::path::Path::new("."))
                    .join("basis_report")
            });
            let r = report::fit_profiles(&input, &out, &dir, components, degree, tol, observable)?;
            println!(
                "{}",
                report::markdown_table(&r.training_accuracy, observable)
            );
            // The α = 1 energy law holds for the exitance only.
            let energy = match observable {
                svkernel::forward::medium::Observable::Exitance => format!(
                    "; R_d(α=1) = {:.5} (target {:.5})",
                    r.rd_at_one.0, r.rd_at_one.1
                ),
                svkernel::forward::medium::Observable::Radiance => String::new(),
            };
            println!(
                "joint fit: {} after {} evaluations, χ²/dof = {:.3}{energy}; {:.1} s",
                r.joint.termination, r.joint.evaluations, r.joint.chi2_per_dof, r.wall_s
            );
            println!(
                "wrote {} and {}/report.json + plots",
                out.display(),
                dir.display()
            );
        }
        Fit::Export {
            albedo,
            input,
            components,
            out,
        } => {
            let docs = report::load_profiles(&input)?;
            let Some(doc) = docs.iter().min_by(|a, b| {
                (a.config.medium.alpha - albedo)
                    .abs()
                    .total_cmp(&(b.config.medium.alpha - albedo).abs())
            }) else {
                bail!("no profiles in {}", input.display());
            };
            let v = report::export_problem(doc, components)?;
            svkernel::jobs::store::write_json_atomic(&out, &v)?;
            println!(
                "exported α = {} ({} bins, χ² = {}) to {}",
                doc.config.medium.alpha,
                v["y"].as_array().map_or(0, |a| a.len()),
                v["chi2"],
                out.display()
            );
        }
        Fit::Outer { model, outer, out } => {
            let m = svkernel::jobs::fit_kernels::attach_outer(&model, &outer, &out)?;
            let [a0, a1] = m.alpha_range();
            let [d0, d1] = m.d_range();
            println!(
                "wrote {}: the model of {} (d ∈ [{:.3}, {:.3}] MFP, α ∈ [{}, {}]), and outside it \
                 the one of {} (d ∈ [{d0:.3}, {d1:.3}] MFP, α ∈ [{a0}, {a1}])",
                out.display(),
                model.display(),
                m.all.ln_d_range[0].exp(),
                m.all.ln_d_range[1].exp(),
                m.all.alpha_range[0],
                m.all.alpha_range[1],
                outer.display()
            );
        }
        Fit::Kernels {
            input,
            out,
            report: dir,
            components,
            degree,
            vertex_refine,
            from,
            moment_errors,
            moment_weight,
        } => {
            use svkernel::jobs::fit_kernels;
            let components = match components[..] {
                [k] => Components::from(k),
                [all, last] => Components { all, last },
                _ => bail!("invalid --components: give K or K_ALL,K_LAST, e.g. 4,5"),
            };
            let degree = match degree.as_deref() {
                None => None,
                Some(&[dx, dy]) if dx <= 7 && dy <= 7 => Some((dx, dy)),
                Some(&[dx, dy]) => bail!("invalid --degree {dx},{dy}: each must be <= 7"),
                Some(_) => bail!("invalid --degree: give two degrees, e.g. 3,3"),
            };
            if !(moment_weight.is_finite() && moment_weight >= 0.0) {
                bail!("invalid --moment-weight {moment_weight}: give a finite weight >= 0");
            }
            let dir = dir.unwrap_or_else(|| {
                out.parent()
                    .unwrap_or(std::path::Path::new("."))
                    .join("metamodel_report")
            });
            let r = fit_kernels::fit_kernels(
                &input,
                &out,
                &dir,
                &fit_kernels::KernelFitOptions {
                    components,
                    degree,
                    vertex_refine,
                    start: from.clone(),
                    moments: svkernel::fit::meta::MomentFit {
                        weight: moment_weight,
                        errors: moment_errors,
                    },
                },
                true,
            );
            // The starting model is the one input a library error does not name.
            let r = match &from {
                Some(m) => {
                    r.with_context(|| format!("refitting {} from {}", shown(&input), m.display()))?
                }
                None => r?,
            };
            print!("{}", fit_kernels::aggregation_summary(&r.aggregation));
            for (class, cells) in &r.stuck {
                let list: Vec<String> = cells
                    .iter()
                    .map(|c| {
                        format!(
                            "α = {}, d = {} (χ² {:.0}, its own fit's {:.0})",
                            c.alpha, c.d, c.chi2, c.own_chi2
                        )
                    })
                    .collect();
                println!(
                    "{class}: {} stuck cell(s) refitted with a width floor first: {}",
                    cells.len(),
                    list.join("; ")
                );
            }
            for j in &r.joint {
                println!(
                    "{}: {} after {} evaluations, χ²/dof = {:.3}, {:.1} s",
                    j.what, j.termination, j.evaluations, j.chi2_per_dof, j.wall_s
                );
            }
            println!(
                "wrote {} and {}/report.json (every cell: {}/aggregation.md) in {:.1} s",
                out.display(),
                dir.display(),
                dir.display(),
                r.wall_s
            );
        }
        Fit::CheckKernels {
            input,
            model,
            vertex_refine,
            out,
        } => {
            use svkernel::jobs::fit_kernels;
            let (f, origin): (MetaModelFile, _) = Shipped::Meta.load(model.as_deref())?;
            let rows = fit_kernels::check_kernels(&input, &f, vertex_refine)?;
            println!("{} against {}:", origin.display(), shown(&input));
            print!("{}", fit_kernels::aggregation_summary(&rows));
            if let Some(out) = out {
                svkernel::jobs::store::write_atomic(
                    &out,
                    fit_kernels::aggregation_table(&rows, false).as_bytes(),
                )?;
            }
        }
        Fit::ExportKernels {
            input,
            model,
            vertices,
            cells,
            out,
        } => {
            use svkernel::forward::kernel::{KernelDoc, VertexClass};
            let class = vertices;
            if class == VertexClass::First {
                bail!("invalid --vertices first: the first-vertex kernel is exact (no fit)");
            }
            let doc = KernelDoc::load(&input)?;
            let (f, _): (MetaModelFile, _) = Shipped::Meta.load(model.as_deref())?;
            let all = svkernel::fit::meta::cells(&doc, class);
            let step = (all.len() / cells.max(1)).max(1);
            let picked: Vec<_> = all.into_iter().step_by(step).take(cells.max(1)).collect();
            let m = if class == VertexClass::All {
                &f.all
            } else {
                &f.last
            };
            let v = svkernel::fit::meta::export_problem(&picked, m, 8)?;
            svkernel::jobs::store::write_json_compact_atomic(&out, &v)?;
            println!(
                "exported {} cells ({} residuals, χ² = {}) to {}",
                picked.len(),
                v["residuals"].as_array().map_or(0, |a| a.len()),
                v["chi2"],
                out.display()
            );
        }
        Fit::DensityStep {
            model,
            albedos,
            distances,
            paths,
            seed,
            out,
        } => {
            use svkernel::jobs::fit_kernels::density_step_experiment;
            for a in &albedos {
                Medium::default_with_albedo(*a).map_err(|e| param_as(e, "albedo", "albedos"))?;
            }
            if let Some(d) = distances.iter().find(|d| !(**d > 0.0 && d.is_finite())) {
                bail!("invalid --distances: {d} must be finite and > 0");
            }
            let (f, _): (MetaModelFile, _) = Shipped::Meta.load(model.as_deref())?;
            let start = std::time::Instant::now();
            let rows = density_step_experiment(&f, &albedos, &distances, paths, seed);
            if let Some(first) = rows.first() {
                let labels: Vec<&str> = first.predictions.iter().map(|p| p.0.as_str()).collect();
                println!("| α | d | paths | {} | noise |", labels.join(" | "));
                println!("|---|---|---|{}---|", "---|".repeat(labels.len()));
            }
            for r in &rows {
                let cells: Vec<String> = r
                    .predictions
                    .iter()
                    .map(|p| format!("{:.4}", p.2))
                    .collect();
                println!(
                    "| {} | {} | {} | {} | {:.4} |",
                    r.alpha,
                    r.d,
                    r.paths,
                    cells.join(" | "),
                    r.noise
                );
            }
            println!("{:.1} s", start.elapsed().as_secs_f64());
            if let Some(out) = out {
                svkernel::jobs::store::write_json_atomic(&out, &rows)?;
            }
        }
        Fit::Check { model, input, out } => {
            let (m, _): (BasisModel, _) = Shipped::Basis.load(model.as_deref())?;
            let rows = report::check(&m, &input)?;
            println!(
                "{}",
                report::markdown_table(&rows, svkernel::forward::medium::Observable::Exitance)
            );
            if let Some(out) = out {
                svkernel::jobs::store::write_json_atomic(&out, &rows)?;
            }
        }
    }
    Ok(())
}

fn kernel_query(
    d: f64,
    albedo: f64,
    density: f64,
    vertices: VertexClass,
    manual: bool,
    model: Option<&std::path::Path>,
) -> Result<()> {
    if !(d >= 0.0 && d.is_finite()) {
        bail!("invalid --d = {d}: must be finite and >= 0");
    }
    if !(0.0..=1.0).contains(&albedo) {
        bail!("invalid --albedo = {albedo}: must be in [0, 1]");
    }
    if !(density > 0.0 && density.is_finite()) {
        bail!("invalid --density = {density}: must be finite and > 0");
    }
    let class = vertices;
    let (gmm, clamped, source) = if manual {
        use svkernel::metamodel::kernel::{manual_kernel, optical_distance, scale_for_density};
        (
            // The density law, as the renderer applies it.
            scale_for_density(&manual_kernel(optical_distance(d, density)), density),
            false,
            "manual".to_string(),
        )
    } else {
        let (f, origin): (MetaModelFile, _) = Shipped::Meta.load(model)?;
        let q = f.eval(class, d, albedo, density);
        (q.gmm, q.clamped, origin.display().to_string())
    };
    let v = serde_json::json!({
        "d": d,
        "albedo": albedo,
        "density": density,
        "vertices": vertices,
        "model": source,
        "clamped": clamped,
        "components": gmm.components,
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

fn profile_query(albedo: f64, radii: &[f64], model: Option<&std::path::Path>) -> Result<()> {
    if !(0.0..=1.0).contains(&albedo) {
        bail!("invalid --albedo = {albedo}: must be in [0, 1]");
    }
    if let Some(r) = radii.iter().find(|r| !(**r >= 0.0 && r.is_finite())) {
        bail!("invalid radii: {r} must be finite and >= 0");
    }
    let (m, origin): (BasisModel, _) = Shipped::Basis.load(model)?;
    let (r1, rm) = m.r_1_m(albedo);
    let v = serde_json::json!({
        "albedo": albedo,
        "R_d": r1 + rm,
        "R_1": r1,
        "R_m": rm,
        "radii": radii,
        "density": radii.iter().map(|&r| m.density(r, albedo)).collect::<Vec<_>>(),
        "cdf": radii.iter().map(|&r| m.cdf(r, albedo)).collect::<Vec<_>>(),
        "model": origin.display().to_string(),
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

/// `svkernel compare` (flags of [`Command::Compare`]).
struct CompareArgs {
    scene: PathBuf,
    spp: Option<u32>,
    paths: Option<u64>,
    curves: Option<(u64, Vec<u32>, Vec<u64>)>,
    analysis: bool,
    sampling: Sampling,
    sequence: Sequence,
    allocation: Allocation,
    seed: u64,
    interior: InteriorKernel,
    models: ModelArgs,
    out: PathBuf,
}

/// `svkernel compare`: metrics, images, curves and the report.
fn compare(a: CompareArgs) -> Result<()> {
    use svkernel::jobs::compare::{CompareSettings, compare_scene};
    use svkernel::jobs::render::RenderOptions;
    use svkernel::render::svbssrdf::Variant;
    let scene = svkernel::render::scene::Scene::find(&a.scene)?;
    let opts = RenderOptions {
        sampling: a.sampling,
        sequence: a.sequence,
        allocation: a.allocation,
        seed: a.seed,
        spp: a.spp,
        reference_paths: a.paths,
        analysis: a.analysis,
        variant: Variant {
            interior: a.interior,
            ..Variant::default()
        },
        run: RunOptions {
            progress: true,
            ..Default::default()
        },
        cache: Some(cache_dir(a.models.cache.as_deref())?),
        ..RenderOptions::new(a.out.clone(), a.models.load()?)
    };
    let settings = CompareSettings {
        curves: a.curves,
        measure_savings: true,
    };
    let c = compare_scene(&scene, &opts, &settings)?;
    print!("{}", c.doc);
    println!(
        "wrote {0}/report.html (self-contained), {0}/report.md, {0}/compare.json",
        a.out.display()
    );
    Ok(())
}

/// `svkernel experiments`.
fn experiments(a: ExperimentsArgs) -> Result<()> {
    let ExperimentsArgs {
        scenes,
        spp,
        paths,
        models,
        bases,
        seed,
        model_args,
        out,
    } = a;
    use svkernel::jobs::experiments::{ExperimentsDoc, Settings, report, run};
    use svkernel::jobs::render::RenderOptions;
    let opts = RenderOptions {
        spp: Some(spp),
        reference_paths: Some(paths),
        seed,
        run: RunOptions {
            progress: true,
            ..Default::default()
        },
        cache: Some(cache_dir(model_args.cache.as_deref())?),
        ..RenderOptions::new(out.clone(), model_args.load()?)
    };
    let rows = run(
        &Settings {
            scenes,
            models,
            bases,
        },
        &opts,
    )?;
    let doc = ExperimentsDoc::new(spp, paths, rows);
    let blocks = report(&doc, &out.join("complexity.png"))?;
    svkernel::jobs::store::write_json_atomic(&out.join("experiments.json"), &doc)?;
    let html = svkernel::jobs::report::write_report(
        &out,
        "experiments",
        "svkernel: the open experiments",
        &blocks,
    )?;
    print!("{doc}");
    println!(
        "wrote {} (self-contained), experiments.md, experiments.json",
        html.display()
    );
    Ok(())
}

/// `--checkpoint-every` as a duration (≥ 0 seconds).
fn checkpoint_interval(every: f64) -> Result<Duration> {
    if !(every >= 0.0 && every.is_finite()) {
        bail!("invalid --checkpoint-every = {every}: must be >= 0 seconds");
    }
    Ok(Duration::from_secs_f64(every))
}

/// `svkernel render`.
fn render(a: RenderArgs) -> Result<()> {
    use svkernel::jobs::render::{RenderOptions, render_scene, write_outputs};
    use svkernel::render::scene::Scene;
    use svkernel::render::svbssrdf::Variant;
    let mut scene = Scene::find(&a.scene)?;
    if let Some(n) = a.resolution {
        scene.resolution = n;
    }
    let targets = a.methods.clone();
    let opts = RenderOptions {
        targets,
        spp: a.spp,
        sampling: a.sampling,
        sequence: a.sequence,
        allocation: a.allocation,
        variant: Variant {
            plain: a.plain,
            vertex_kernels: !a.point_albedos,
            two_pass: a.two_pass,
            interior: a.interior,
            space: a.albedo_space,
            space_blur: a.space_blur,
            split: a.split,
            coarse_variance: a.coarse_variance,
            density_law: a.density_law,
            density_kernel: a.density_kernel,
            step_ends: a.step_ends,
            last_kernel: a.last_kernel,
        },
        seed: a.seed,
        reference_paths: a.paths,
        models: a.models.load()?,
        shard: a.shard.as_deref().map(Shard::parse).transpose()?,
        run: RunOptions {
            checkpoint: None,
            checkpoint_every: checkpoint_interval(a.checkpoint_every)?,
            resume: a.resume,
            progress: true,
        },
        checkpoint: Some(a.out.join("reference")),
        reference_tallies: a.reference_tallies,
        analysis: !a.no_analysis,
        cache: if a.no_extend {
            None
        } else {
            Some(cache_dir(a.models.cache.as_deref())?)
        },
        out: a.out.clone(),
        materials: Default::default(),
    };
    let passes = render_scene(&scene, &opts)?;
    let doc = write_outputs(&scene, &opts, &passes)?;
    println!("scene {} → {}", scene.name, a.out.display());
    print!("{doc}");
    Ok(())
}

/// The flag that sets each parameter the library names in its errors
/// ([`svkernel::Error::Param`]); names not listed print as they are.
const FLAGS: &[(&str, &str)] = &[
    ("albedo", "--albedo"),
    ("albedos", "--albedos"),
    ("eta", "--eta"),
    ("g", "--g"),
    ("density", "--density"),
    ("thickness", "--thickness"),
    ("source", "--source"),
    ("paths", "--paths"),
    ("shard", "--shard"),
    ("max_events", "--max-events"),
    ("distances", "--distances"),
    ("rel_width", "--rel-width"),
    ("grid", "--nu/--nv/--extent"),
    ("grid.tail", "--tail-bins/--tail-extent"),
    ("vertices", "--vertices"),
    ("meta_model", "--model"),
    ("method", "--method"),
    ("sampling", "--sampling"),
    ("spp", "--spp (or the scene's samples)"),
    ("reference_tallies", "--reference-tally"),
    ("budgets", "--spp-list/--paths-list/--truth-paths"),
];

/// A library error about a parameter, named by the flag that set it
/// (`albedo` → `--albedo`); other errors as they are.
fn named_by_flag(e: anyhow::Error) -> anyhow::Error {
    // `downcast` sees through contexts and returns the error without them:
    // keep their messages to put back around the renamed one.
    let contexts: Vec<String> = e
        .chain()
        .take_while(|c| !c.is::<svkernel::Error>())
        .map(|c| c.to_string())
        .collect();
    let renamed = match e.downcast::<svkernel::Error>() {
        Ok(svkernel::Error::Param {
            name,
            value,
            allowed,
        }) => svkernel::Error::Param {
            name: FLAGS
                .iter()
                .find(|(p, _)| *p == name)
                .map_or(name, |(_, flag)| flag),
            value,
            allowed,
        }
        .into(),
        Ok(other) => other.into(),
        Err(e) => return e,
    };
    contexts
        .iter()
        .rev()
        .fold(renamed, |e, c| e.context(c.clone()))
}

/// `e`'s parameter `from` renamed `to` (a library parameter that a
/// command sets through another flag).
fn param_as(e: svkernel::Error, from: &str, to: &'static str) -> svkernel::Error {
    match e {
        svkernel::Error::Param {
            name,
            value,
            allowed,
        } if name == from => svkernel::Error::Param {
            name: to,
            value,
            allowed,
        },
        e => e,
    }
}

fn main() -> std::process::ExitCode {
    // A closed stdout (`svkernel kernel … | head -1`) ends the program
    // quietly, as for other Unix tools, instead of a panic in `println!`;
    // every result file is already complete when its summary is printed.
    #[cfg(unix)]
    // SAFETY: restoring the default action of a signal before any thread
    // is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Simulate(Simulate::Profile(a)) => simulate_profile(a),
        Command::Simulate(Simulate::Kernels(a)) => simulate_kernels(a),
        Command::Merge { inputs, out } => merge(inputs, out),
        Command::Render(a) => render(a),
        Command::Compare {
            scene,
            spp,
            paths,
            truth_paths,
            spp_list,
            paths_list,
            no_curves,
            no_analysis,
            sampling,
            sequence,
            allocation,
            seed,
            interior,
            models,
            out,
        } => compare(CompareArgs {
            scene,
            spp,
            paths,
            curves: (!no_curves).then_some((truth_paths, spp_list, paths_list)),
            analysis: !no_analysis,
            sampling,
            sequence,
            allocation,
            seed,
            interior,
            models,
            out,
        }),
        Command::Demo { out, paths, models } => demo(out, paths, models),
        Command::Design(a) => design(a),
        Command::Medium(m) => medium(m),
        Command::Scene { name } => {
            print!(
                "{}",
                svkernel::jobs::shipped::scene_text(&name).unwrap_or_default()
            );
            Ok(())
        }
        Command::Experiments(a) => experiments(a),
        Command::Fit(f) => fit(f),
        Command::Profile {
            albedo,
            radii,
            model,
            json: _,
        } => profile_query(albedo, &radii, model.as_deref()),
        Command::Kernel {
            d,
            albedo,
            density,
            vertices,
            manual,
            model,
            json: _,
        } => kernel_query(d, albedo, density, vertices, manual, model.as_deref()),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let e = named_by_flag(e);
            // The chain of causes, each once: a library error's message
            // often already holds its source's (a file's "No such file").
            let mut msg = e.to_string();
            for cause in e.chain().skip(1).map(|c| c.to_string()) {
                if !msg.contains(&cause) {
                    msg = format!("{msg}: {cause}");
                }
            }
            eprintln!("error: {msg}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Kernel tallies as `fit kernels --in` lists them: the first, then each
/// one overlaid on it (`a + b`).
fn shown(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(" + ")
}
