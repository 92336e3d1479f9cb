//! Simulate and fit only the missing range: when a scene's
//! albedos reach outside the albedo range the kernel meta-model was trained
//! on, `learned` would clamp there. Instead, [`ensure`] simulates path
//! densities at a few albedos spanning just the missing interval (plus an
//! overlap into the trained range), fits a meta-model to them in memory,
//! and caches the model and its tally under a content hash, so the next render with the same model and
//! the same missing interval reuses them.
//!
//! The extension model is used for kernel queries whose albedo α₀ lies
//! outside the main model's range ([`crate::render::svbssrdf::SvBssrdf::with_extension`]);
//! inside it nothing changes.
//!
//! The shipped model carries an outer model over α ∈ [0.05, 0.999] and
//! d ∈ [0.05, 20] MFP ([`MetaModelFile::at`]); the range to extend is then
//! the part of the scene's albedos outside the outer model's
//! ([`MetaModelFile::alpha_range`]), which leaves albedos below 0.05.
//! Distances are not extended: beyond the covered range the kernel keeps
//! the shape of its largest distance, stretched with d (the meta-model
//! clamps ln d and says so). How much light that concerns goes like the
//! diffusion falloff e^{−σ_tr·d}, σ_tr = √(3σ_a σ_t′): at 20 MFP ≈ 0.01 %
//! of the d = 0 level at α = 0.9, ≈ 5 % at α = 0.99.
//!
//! The basis profiles cover α ∈ [0.01, 0.999] (32 simulated albedos); a
//! scene outside that range gets a clear clamp rather than an extension.

use crate::error::{Error, Result};
use crate::forward::kernel::{KernelConfig, KernelDoc};
use crate::forward::runner::RunOptions;
use crate::metamodel::meta::MetaModelFile;
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Paths walked per extension simulation (all albedos share them): below
/// the trained range few paths scatter twice and exit at a given distance
/// (at α = 0.15, 5e7 paths give ≈ 1000 contributing paths per distance up
/// to 2.5 MFP, ≈ 6 s); above it paths are long but nearly all contribute.
pub fn extension_paths(missing: [f64; 2], trained: [f64; 2]) -> u64 {
    if missing[0] < trained[0] {
        50_000_000
    } else {
        10_000_000
    }
}
/// Albedos simulated across the missing interval.
const EXTENSION_ALBEDOS: usize = 4;
/// How far into the trained range the extension reaches (in √(1 − α)),
/// so the two models meet on common ground.
const OVERLAP: f64 = 0.05;
/// The largest albedo an extension simulates (paths grow like 1/(1 − α)).
const MAX_ALBEDO: f64 = 0.995;

/// What [`ensure`] did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Extension {
    /// The scene's albedo interval outside the main model's range.
    pub missing: [f64; 2],
    /// The albedos simulated and the paths walked.
    pub albedos: Vec<f64>,
    pub paths: u64,
    /// The extension meta-model and its kernel tallies.
    pub model: PathBuf,
    pub kernels: PathBuf,
    /// True if both came from the cache (no simulation, no fit).
    pub cached: bool,
    /// Simulation and fit time of this call (0 when cached).
    pub wall_s: f64,
}

/// The part of `scene_range` outside `trained` (the larger side if both;
/// `None` if it lies inside). Above a trained range that already reaches
/// 0.995, the largest albedo an extension simulates, an extension has
/// nothing to add: the model clamps there.
pub fn missing(scene_range: [f64; 2], trained: [f64; 2]) -> Option<[f64; 2]> {
    let below = scene_range[0] < trained[0];
    let above = scene_range[1] > trained[1] && trained[1] < MAX_ALBEDO;
    match (below, above) {
        (false, false) => None,
        (true, false) => Some([scene_range[0], trained[0]]),
        (false, true) => Some([trained[1], scene_range[1]]),
        (true, true) => {
            // One extension per render: the wider side (the other clamps).
            let lo = trained[0] - scene_range[0];
            let hi = scene_range[1] - trained[1];
            Some(if lo >= hi {
                [scene_range[0], trained[0]]
            } else {
                [trained[1], scene_range[1]]
            })
        }
    }
}

/// The albedos that cover `missing` and reach [`OVERLAP`] into `trained`,
/// evenly spaced in √(1 − α).
fn albedos(missing: [f64; 2], trained: [f64; 2]) -> Vec<f64> {
    let x = |a: f64| (1.0 - a).max(0.0).sqrt();
    let (x0, x1) = if missing[0] < trained[0] {
        // Below: from the scene's lowest albedo to inside the range.
        (x(missing[0].max(0.0)), x(trained[0]) - OVERLAP)
    } else {
        (x(trained[1]) + OVERLAP, x(missing[1].min(MAX_ALBEDO)))
    };
    (0..EXTENSION_ALBEDOS)
        .map(|k| {
            let t = k as f64 / (EXTENSION_ALBEDOS - 1) as f64;
            let xv = x0 + t * (x1 - x0);
            // Round to 4 decimals: stable names and hashes.
            ((1.0 - xv * xv) * 1e4).round() / 1e4
        })
        .collect()
}

/// Makes sure an extension of `meta` over `missing` exists in `cache`
/// (module docs): simulates with the configuration of the training tallies
/// `training` at new albedos, fits in memory, and stores the model and its
/// tally under a content hash of (model, configuration); returns what was
/// done and the extension model.
pub fn ensure(
    meta: &MetaModelFile,
    training: &KernelConfig,
    missing: [f64; 2],
    cache: &Path,
    progress: bool,
) -> Result<(Extension, MetaModelFile)> {
    let trained = meta.alpha_range();
    let albedos = albedos(missing, trained);
    let config = KernelConfig {
        albedos: albedos.clone(),
        paths: extension_paths(missing, trained),
        runs: Vec::new(),
        ..training.clone()
    };
    config.validate()?;
    let origin = Path::new("(meta-model extension)");
    let meta_json = serde_json::to_vec(meta).map_err(|e| Error::format(origin, "model", e))?;
    let config_json =
        serde_json::to_vec(&config).map_err(|e| Error::format(origin, "config", e))?;
    let key = crate::jobs::store::content_hash([
        b"svkernel extension v2".as_slice(),
        &meta_json,
        &config_json,
    ]);
    let model = cache.join(format!("metamodel_ext_{key}.json"));
    let kernels = cache.join(format!("kernels_ext_{key}.json"));
    // A cached entry is reused; a damaged one is an error naming the file
    // (from the load below), not a silent refit.
    let cached = model.exists();
    let (paths, t0) = (config.paths, Instant::now());
    let loaded = if cached {
        MetaModelFile::load(&model)?
    } else {
        if progress {
            eprintln!(
                "albedos {:.3}–{:.3} lie outside the meta-model's trained range {:.3}–{:.3}: \
                 simulating {:.1e} paths at {} albedos and fitting an extension",
                missing[0],
                missing[1],
                trained[0],
                trained[1],
                config.paths as f64,
                albedos.len()
            );
        }
        let opts = RunOptions {
            progress,
            ..Default::default()
        };
        let (tally, wall_s) = config.run(None, &opts)?;
        let chunks = vec![(0, config.chunks())];
        let doc = KernelDoc::new(config, None, chunks, tally, wall_s, Provenance::current());
        let degree = (meta.all.deg_x, meta.all.deg_y.min(EXTENSION_ALBEDOS - 2));
        let (file, _) = crate::fit::meta::fit_metamodel(
            &doc,
            crate::fit::meta::Components {
                all: meta.all.k,
                last: meta.last.k,
            },
            degree,
            progress,
        )?;
        crate::jobs::store::write_json_compact_atomic(&kernels, &doc)?;
        crate::jobs::store::write_json_atomic(&model, &file)?;
        file
    };
    let done = Extension {
        missing,
        albedos,
        paths,
        model,
        kernels,
        cached,
        wall_s: if cached {
            0.0
        } else {
            t0.elapsed().as_secs_f64()
        },
    };
    Ok((done, loaded))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_interval_and_its_albedos() {
        let trained = [0.2, 0.99];
        assert_eq!(missing([0.3, 0.95], trained), None);
        assert_eq!(missing([0.15, 0.9], trained), Some([0.15, 0.2]));
        assert_eq!(missing([0.3, 0.999], trained), Some([0.99, 0.999]));
        assert_eq!(missing([0.1, 0.995], trained), Some([0.1, 0.2]));
        // A range that reaches the largest albedo an extension simulates
        // (an outer model's) is extended below only.
        let wide = [0.05, 0.999];
        assert_eq!(missing([0.1, 0.9995], wide), None);
        assert_eq!(missing([0.02, 0.9995], wide), Some([0.02, 0.05]));
        let a = albedos([0.15, 0.2], trained);
        assert_eq!(a.len(), EXTENSION_ALBEDOS);
        assert_eq!(a[0], 0.15);
        // Increasing, ending inside the trained range.
        assert!(
            a.windows(2).all(|w| w[0] < w[1]) && a[3] > 0.2 && a[3] < 0.3,
            "{a:?}"
        );
        let b = albedos([0.99, 0.999], trained);
        assert!(b[0] < 0.99 && b[3] == 0.995, "{b:?}");
    }
}
