//! `svkernel demo`: the end-to-end job on shipped data. It simulates one
//! profile of the default medium, checks R_d against the adding-doubling
//! oracle and plots p(r); compares the shipped basis BSSRDF with that
//! simulation and prints the learned aggregation kernel next to the manual
//! one; then compares the `stripes` and `checker` scenes — every method
//! against a quick reference, with error-vs-time curves — and writes one
//! self-contained report, `out/demo/index.html` ([`compare_scenes`]).

use crate::error::Result;
use crate::forward::medium::{Medium, Source};
use crate::forward::profile::{DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use crate::forward::runner::{RunOptions, chunk_range};
use crate::forward::tally::RadialBins;
use crate::jobs::shipped::Models;
use crate::provenance::Provenance;
use std::path::{Path, PathBuf};

/// What the demo produced.
pub struct DemoReport {
    pub doc: ProfileDoc,
    pub oracle: f64,
    pub oracle_accuracy: f64,
    pub plot: PathBuf,
    pub json: PathBuf,
    /// The shipped basis model's (R_d, R₁, Rₘ) at the demo's albedo.
    pub basis: (f64, f64, f64),
    /// The learned (all-vertex) and the manual kernel at d = 1 MFP.
    pub learned: crate::metamodel::kernel::Gmm,
    pub manual: crate::metamodel::kernel::Gmm,
}

/// The albedo of the demo's profile.
pub const DEMO_ALBEDO: f64 = 0.9;

/// Simulates `paths` paths of the default medium (η = 1.5, g = 0.3) at
/// α = 0.9 with a pencil beam and writes `profile.json` and `profile.png`
/// to `out`; compares `models` with it.
pub fn run(out: &Path, paths: u64, models: &Models, progress: bool) -> Result<DemoReport> {
    let alpha = DEMO_ALBEDO;
    let config = ProfileConfig {
        medium: Medium::default_with_albedo(alpha)?,
        source: Source::Pencil,
        paths,
        seed: 1,
        max_events: DEFAULT_MAX_EVENTS,
        bins: RadialBins::default(),
        engine: Engine::Lanes,
        radiance: false,
    };
    let opts = RunOptions {
        progress,
        ..Default::default()
    };
    let (tally, wall_s) = config.run(None, &opts)?;
    let chunks = vec![chunk_range(paths, None)];
    let doc = ProfileDoc::new(config, None, chunks, tally, wall_s, Provenance::current());
    let json = out.join("profile.json");
    let plot = out.join("profile.png");
    crate::jobs::store::write_json_atomic(&json, &doc)?;
    crate::jobs::plot::profile_plot(&doc, &plot)?;
    let oracle = crate::oracles::lookup(&crate::oracles::RD_ETA15_G03, alpha).unwrap_or(f64::NAN);
    let (r1, rm) = models.basis.r_1_m(alpha);
    let meta = &models.meta;
    Ok(DemoReport {
        doc,
        oracle,
        oracle_accuracy: crate::oracles::accuracy(false, alpha),
        plot,
        json,
        basis: (r1 + rm, r1, rm),
        learned: meta
            .eval(crate::pair::VertexClass::All, 1.0, alpha, 1.0)
            .gmm,
        manual: crate::metamodel::kernel::manual_kernel(1.0),
    })
}

/// The scenes the demo renders, the reference paths and samples per pixel.
pub const DEMO_SCENES: [&str; 3] = ["stripes", "checker", "marble"];

const DEMO_REFERENCE_PATHS: u64 = 4_000_000;
const DEMO_SPP: u32 = 64;
/// Error-vs-time budgets of the demo: truth paths, model spp, reference paths.
const DEMO_TRUTH_PATHS: u64 = 10_000_000;
const DEMO_SPP_LIST: [u32; 4] = [4, 16, 64, 256];
const DEMO_PATHS_LIST: [u64; 3] = [100_000, 1_000_000, 4_000_000];

/// Compares [`DEMO_SCENES`] (reference and every method, importance
/// sampling, 64 spp, 4e6 reference paths, error-vs-time curves) into
/// `out/<scene>/` and writes `out/index.html` and `out/index.md` with all
/// of them; returns each scene's name and comparison.
pub fn compare_scenes(
    out: &Path,
    models: &Models,
    progress: bool,
) -> Result<Vec<(String, crate::jobs::compare::Comparison)>> {
    use crate::jobs::compare::{CompareSettings, compare_scene};
    use crate::jobs::render::RenderOptions;
    use crate::jobs::report::{Block, write_report};
    let settings = CompareSettings {
        curves: Some((
            DEMO_TRUTH_PATHS,
            DEMO_SPP_LIST.to_vec(),
            DEMO_PATHS_LIST.to_vec(),
        )),
        measure_savings: true,
    };
    let mut done = Vec::new();
    let names: Vec<String> = DEMO_SCENES
        .iter()
        .map(|p| {
            let stem = Path::new(p).file_stem().map(|s| s.to_string_lossy());
            format!("`{}`", stem.unwrap_or_default())
        })
        .collect();
    let mut blocks = vec![
        Block::Para(format!(
            "The end-to-end demo on the shipped data: the basis BSSRDF and the kernel \
             meta-model built into svkernel (the same as `data/profiles/basis.json` and \
             `metamodel.json`) render the {} scenes with every method; the brute-force \
             reference (the heterogeneous walk) is the ground truth. Produced by \
             `svkernel demo`; one scene alone: `svkernel compare {}`.",
            crate::render::analysis::list_names(&names),
            DEMO_SCENES[0]
        )),
        Block::Figure {
            caption: format!(
                "the demo's profile check: p(r) = 2πr·R(r) at α = {DEMO_ALBEDO}, single (R₁) \
                 and multiple (Rₘ) scattering"
            ),
            path: out.join("profile.png"),
        },
    ];
    for path in DEMO_SCENES {
        let scene = crate::render::scene::Scene::find(Path::new(path))?;
        let opts = RenderOptions {
            spp: Some(DEMO_SPP),
            reference_paths: Some(DEMO_REFERENCE_PATHS),
            run: RunOptions {
                progress,
                ..Default::default()
            },
            ..RenderOptions::new(out.join(&scene.name), models.clone())
        };
        let c = compare_scene(&scene, &opts, &settings)?;
        blocks.extend(c.blocks.iter().cloned());
        done.push((scene.name.clone(), c));
    }
    blocks.extend(crate::jobs::compare::glossary());
    write_report(out, "index", "svkernel demo", &blocks)?;
    Ok(done)
}
