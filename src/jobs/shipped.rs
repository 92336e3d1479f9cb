//! What is built into the binary, so every command works from any folder
//! and after `cargo install`: the basis BSSRDF models (pencil and diffuse
//! incidence, each of the exitance and of the radiance along the normal),
//! the kernel meta-model, the configuration of the tallies the
//! meta-model was trained on, and the canonical scenes.
//!
//! A model is found in this order: the file given by the caller (a
//! command-line flag), the file named by the environment variable
//! (`SVKERNEL_BASIS`, `SVKERNEL_BASIS_DIFFUSE`, `SVKERNEL_BASIS_RADIANCE`,
//! `SVKERNEL_BASIS_RADIANCE_DIFFUSE`, `SVKERNEL_MODEL`), else the
//! built-in copy (the same bytes as `data/profiles/*.json`). The cache of
//! meta-model extensions is `--cache`, else `SVKERNEL_CACHE`, else the
//! platform's cache folder ([`dirs::cache_dir`]) + `svkernel`.

use crate::doc::Document;
use crate::error::{Error, Result};
use crate::forward::kernel::{KernelConfig, PairGrid};
use crate::metamodel::basis::BasisModel;
use crate::metamodel::meta::MetaModelFile;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A model that ships with svkernel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shipped {
    /// The basis BSSRDF fitted to pencil-beam profiles (collimated lights).
    Basis,
    /// The basis BSSRDF fitted to diffuse-incidence profiles.
    BasisDiffuse,
    /// The bases of the radiance along the normal (pencil, diffuse).
    BasisRadiance,
    BasisRadianceDiffuse,
    /// The kernel meta-model.
    Meta,
}

impl Shipped {
    /// The environment variable that overrides the built-in copy.
    pub fn env(self) -> &'static str {
        match self {
            Shipped::Basis => "SVKERNEL_BASIS",
            Shipped::BasisDiffuse => "SVKERNEL_BASIS_DIFFUSE",
            Shipped::BasisRadiance => "SVKERNEL_BASIS_RADIANCE",
            Shipped::BasisRadianceDiffuse => "SVKERNEL_BASIS_RADIANCE_DIFFUSE",
            Shipped::Meta => "SVKERNEL_MODEL",
        }
    }

    /// The built-in document.
    pub fn text(self) -> &'static str {
        match self {
            Shipped::Basis => include_str!("../../data/profiles/basis.json"),
            Shipped::BasisDiffuse => include_str!("../../data/profiles/basis_diffuse.json"),
            Shipped::BasisRadiance => include_str!("../../data/profiles/basis_radiance.json"),
            Shipped::BasisRadianceDiffuse => {
                include_str!("../../data/profiles/basis_radiance_diffuse.json")
            }
            Shipped::Meta => include_str!("../../data/profiles/metamodel.json"),
        }
    }

    /// The name errors give the built-in copy.
    pub fn origin(self) -> PathBuf {
        PathBuf::from(match self {
            Shipped::Basis => "(built-in basis.json)",
            Shipped::BasisDiffuse => "(built-in basis_diffuse.json)",
            Shipped::BasisRadiance => "(built-in basis_radiance.json)",
            Shipped::BasisRadianceDiffuse => "(built-in basis_radiance_diffuse.json)",
            Shipped::Meta => "(built-in metamodel.json)",
        })
    }

    /// Where the model comes from: `file`, else the environment variable,
    /// else `None` (the built-in copy).
    pub fn source(self, file: Option<&Path>) -> Option<PathBuf> {
        file.map(Path::to_path_buf).or_else(|| {
            std::env::var_os(self.env())
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        })
    }

    /// Loads the model (see [`Shipped::source`]); returns it with its origin.
    pub fn load<T: Document>(self, file: Option<&Path>) -> Result<(T, PathBuf)> {
        match self.source(file) {
            Some(path) => Ok((crate::jobs::store::load(&path)?, path)),
            None => {
                let origin = self.origin();
                Ok((crate::doc::from_json(self.text(), &origin)?, origin))
            }
        }
    }
}

/// The configuration of the kernel tallies the shipped meta-model was
/// fitted to (`data/kernels/eta1.5_g0.3_pencil.json`: medium, grid, albedos,
/// distances, seed) as an analog simulation; the shipped tallies themselves
/// are planned per cell (their `runs`). Extensions of the trained albedo
/// range simulate with it, analog, at other albedos.
pub fn training_config() -> KernelConfig {
    KernelConfig {
        g: 0.3,
        eta: 1.5,
        density: 1.0,
        albedos: vec![0.2, 0.4, 0.6, 0.75, 0.85, 0.92, 0.96, 0.99],
        distances: vec![0.1, 0.2, 0.35, 0.6, 1.0, 1.6, 2.5, 4.0, 6.5, 10.0],
        rel_width: 0.1,
        min_order: 2,
        paths: 20_000_000,
        seed: 3000,
        max_events: 1_000_000,
        grid: PairGrid {
            nu: 32,
            nv: 16,
            extent: 4.0,
            vertex_refine: 4,
            tail: Some(crate::forward::kernel::Tail {
                bins: 8,
                extent: 16.0,
            }),
        },
        runs: Vec::new(),
    }
}

/// The models a render uses, loaded once and shared.
#[derive(Clone, Debug)]
pub struct Models {
    /// Basis BSSRDF for collimated lights, and where it came from.
    pub basis: Arc<BasisModel>,
    pub basis_origin: PathBuf,
    /// Basis BSSRDF for diffuse lights.
    pub basis_diffuse: Arc<BasisModel>,
    pub basis_diffuse_origin: PathBuf,
    /// Bases of the radiance along the normal: collimated and diffuse
    /// lights, each with where it came from.
    pub basis_radiance: [(Arc<BasisModel>, PathBuf); 2],
    /// The kernel meta-model (`learned`).
    pub meta: Arc<MetaModelFile>,
    pub meta_origin: PathBuf,
    /// The configuration of the meta-model's training tallies.
    pub training: KernelConfig,
}

impl Models {
    /// The built-in models (environment variables are not read).
    pub fn builtin() -> Result<Models> {
        fn builtin<T: Document>(s: Shipped) -> Result<(T, PathBuf)> {
            let o = s.origin();
            Ok((crate::doc::from_json(s.text(), &o)?, o))
        }
        Ok(Models::from_parts(
            [
                builtin(Shipped::Basis)?,
                builtin(Shipped::BasisDiffuse)?,
                builtin(Shipped::BasisRadiance)?,
                builtin(Shipped::BasisRadianceDiffuse)?,
            ],
            builtin(Shipped::Meta)?,
        ))
    }

    /// Each model from its file if given, else its environment variable,
    /// else the built-in copy.
    /// The bases are, in order, of the exitance under collimated and
    /// diffuse lights and of the radiance along the normal under the same.
    pub fn find(bases: [Option<&Path>; 4], meta: Option<&Path>) -> Result<Models> {
        let [b, d, r, rd] = bases;
        Ok(Models::from_parts(
            [
                Shipped::Basis.load(b)?,
                Shipped::BasisDiffuse.load(d)?,
                Shipped::BasisRadiance.load(r)?,
                Shipped::BasisRadianceDiffuse.load(rd)?,
            ],
            Shipped::Meta.load(meta)?,
        ))
    }

    fn from_parts(
        [(b, bo), (d, dox), (r, ro), (rd, rdo)]: [(BasisModel, PathBuf); 4],
        (m, mo): (MetaModelFile, PathBuf),
    ) -> Models {
        Models {
            basis: Arc::new(b),
            basis_origin: bo,
            basis_diffuse: Arc::new(d),
            basis_diffuse_origin: dox,
            basis_radiance: [(Arc::new(r), ro), (Arc::new(rd), rdo)],
            meta: Arc::new(m),
            meta_origin: mo,
            training: training_config(),
        }
    }

    /// The basis of `incidence` and `observable`, and where it came from.
    pub fn basis_for(
        &self,
        incidence: crate::forward::medium::Incidence,
        observable: crate::forward::medium::Observable,
    ) -> (&Arc<BasisModel>, &Path) {
        use crate::forward::medium::{Incidence, Observable};
        match (observable, incidence) {
            (Observable::Exitance, Incidence::Pencil) => (&self.basis, &self.basis_origin),
            (Observable::Exitance, Incidence::Diffuse) => {
                (&self.basis_diffuse, &self.basis_diffuse_origin)
            }
            (Observable::Radiance, i) => {
                let (b, o) = &self.basis_radiance[usize::from(i == Incidence::Diffuse)];
                (b, o)
            }
        }
    }

    /// These models with the meta-model replaced by the one at `path`.
    pub fn with_meta(&self, path: &Path) -> Result<Models> {
        Ok(Models {
            meta: Arc::new(MetaModelFile::load(path)?),
            meta_origin: path.to_path_buf(),
            ..self.clone()
        })
    }

    /// These models with the collimated-light basis replaced by the one at
    /// `path`.
    pub fn with_basis(&self, path: &Path) -> Result<Models> {
        Ok(Models {
            basis: Arc::new(BasisModel::load(path)?),
            basis_origin: path.to_path_buf(),
            ..self.clone()
        })
    }
}

impl Models {
    /// The models of the medium (η, g): these if they are for it, else a
    /// preset's ([`PRESETS`]), else the medium's models from `cache`, built
    /// there first if absent ([`crate::jobs::medium::ensure`]; progress on
    /// stderr if `progress`). `None` for `cache` refuses a medium without
    /// models. Bases of the radiance along the normal exist for the
    /// built-in medium only; other media keep the built-in ones, which the
    /// render refuses for them by name.
    pub fn for_medium(
        &self,
        eta: f64,
        g: f64,
        cache: Option<&Path>,
        progress: bool,
    ) -> Result<Models> {
        if same_medium((self.basis.eta, self.basis.g), (eta, g)) {
            return Ok(self.clone());
        }
        if let Some(p) = PRESETS.iter().find(|p| same_medium((p.eta, p.g), (eta, g))) {
            return p.models(self);
        }
        let Some(cache) = cache else {
            return Err(Error::param(
                "medium",
                format!("eta = {eta}, g = {g}"),
                "a medium with models (the built-in one, a preset, or one built into the cache: \
                 `svkernel medium build`)",
            ));
        };
        let config = crate::jobs::medium::BuildConfig::standard(eta, g);
        let opts = crate::jobs::medium::BuildOptions {
            progress,
            ..Default::default()
        };
        let built = crate::jobs::medium::ensure(&config, cache, &opts)?;
        Ok(self.with_medium(built.basis, built.basis_diffuse, built.meta, &built.dir))
    }

    /// These models with the exitance bases and the meta-model of another
    /// medium, from `dir`.
    fn with_medium(
        &self,
        basis: BasisModel,
        basis_diffuse: BasisModel,
        meta: MetaModelFile,
        dir: &Path,
    ) -> Models {
        Models {
            basis: Arc::new(basis),
            basis_origin: dir.join("basis.json"),
            basis_diffuse: Arc::new(basis_diffuse),
            basis_diffuse_origin: dir.join("basis_diffuse.json"),
            training: meta_training(&meta, &self.training),
            meta: Arc::new(meta),
            meta_origin: dir.join("metamodel.json"),
            ..self.clone()
        }
    }
}

/// The training configuration of another medium's meta-model: the
/// built-in one with that medium's η and g (the extension of its albedo
/// range simulates with it).
fn meta_training(meta: &MetaModelFile, base: &KernelConfig) -> KernelConfig {
    KernelConfig {
        eta: meta.eta,
        g: meta.g,
        ..base.clone()
    }
}

/// Whether two (η, g) are the same medium (to 1e-9).
pub fn same_medium(a: (f64, f64), b: (f64, f64)) -> bool {
    (a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9
}

/// A medium whose models ship with svkernel, built by
/// [`crate::jobs::medium::build`] with [`crate::jobs::medium::BuildConfig::standard`]
/// (`tools/make_presets.sh`); `data/media/<name>/` holds them and their
/// accuracy.
#[derive(Clone, Copy, Debug)]
pub struct Preset {
    pub name: &'static str,
    pub description: &'static str,
    pub eta: f64,
    pub g: f64,
    basis: &'static str,
    basis_diffuse: &'static str,
    meta: &'static str,
    /// `medium.json`: the build and its accuracy.
    pub manifest: &'static str,
}

impl Preset {
    /// The preset's models (radiance bases: `base`'s).
    pub fn models(&self, base: &Models) -> Result<Models> {
        let dir = PathBuf::from(format!("(built-in preset {})", self.name));
        let origin = |f: &str| dir.join(f);
        let basis: BasisModel = crate::doc::from_json(self.basis, &origin("basis.json"))?;
        let diffuse: BasisModel =
            crate::doc::from_json(self.basis_diffuse, &origin("basis_diffuse.json"))?;
        let meta: MetaModelFile = crate::doc::from_json(self.meta, &origin("metamodel.json"))?;
        Ok(base.with_medium(basis, diffuse, meta, &dir))
    }
}

macro_rules! preset {
    ($name:literal, $description:literal, $eta:expr, $g:expr) => {
        Preset {
            name: $name,
            description: $description,
            eta: $eta,
            g: $g,
            basis: include_str!(concat!("../../data/media/", $name, "/basis.json")),
            basis_diffuse: include_str!(concat!("../../data/media/", $name, "/basis_diffuse.json")),
            meta: include_str!(concat!("../../data/media/", $name, "/metamodel.json")),
            manifest: include_str!(concat!("../../data/media/", $name, "/medium.json")),
        }
    };
}

/// The preset media.
pub const PRESETS: &[Preset] = &[
    preset!(
        "skin",
        "forward-scattering, skin- or milk-like (η = 1.4, g = 0.8)",
        1.4,
        0.8
    ),
    preset!(
        "index-matched",
        "isotropic and index-matched (η = 1, g = 0), the exact oracles' medium",
        1.0,
        0.0
    ),
];

/// The preset called `name`.
pub fn preset(name: &str) -> Option<&'static Preset> {
    PRESETS.iter().find(|p| p.name == name)
}

/// The cache folder: `dir` if given, else `SVKERNEL_CACHE`, else the
/// platform's cache folder + `svkernel` (e.g. `~/.cache/svkernel`).
pub fn cache_dir(dir: Option<&Path>) -> Result<PathBuf> {
    if let Some(d) = dir {
        return Ok(d.to_path_buf());
    }
    if let Some(d) = std::env::var_os("SVKERNEL_CACHE").filter(|v| !v.is_empty()) {
        return Ok(PathBuf::from(d));
    }
    dirs::cache_dir()
        .map(|d| d.join("svkernel"))
        .ok_or_else(|| {
            Error::format(
                "(cache)",
                "cache",
                "no cache folder on this platform: give --cache DIR or set SVKERNEL_CACHE",
            )
        })
}

/// The canonical scenes, by name, as TOML (the last three translucent).
pub const SCENES: &[(&str, &str)] = &[
    ("stripes", include_str!("../../scenes/stripes.toml")),
    ("checker", include_str!("../../scenes/checker.toml")),
    ("complex", include_str!("../../scenes/complex.toml")),
    ("color", include_str!("../../scenes/color.toml")),
    ("density", include_str!("../../scenes/density.toml")),
    ("features", include_str!("../../scenes/features.toml")),
    ("marble", include_str!("../../scenes/marble.toml")),
    ("skin", include_str!("../../scenes/skin.toml")),
    ("milk", include_str!("../../scenes/milk.toml")),
];

/// The built-in scene called `name`.
pub fn scene_text(name: &str) -> Option<&'static str> {
    SCENES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_models_parse_and_match_the_data_folder() {
        let m = Models::builtin().unwrap();
        let on_disk = BasisModel::load(Path::new("data/profiles/basis.json")).unwrap();
        assert_eq!(
            serde_json::to_value(&*m.basis).unwrap(),
            serde_json::to_value(&on_disk).unwrap()
        );
        use crate::forward::medium::{Incidence, Observable};
        for i in [Incidence::Pencil, Incidence::Diffuse] {
            for o in [Observable::Exitance, Observable::Radiance] {
                let (b, _) = m.basis_for(i, o);
                assert_eq!((b.incidence, b.observable), (i, o));
            }
        }
        assert!(m.meta.all.alpha_range[0] < m.meta.all.alpha_range[1]);
    }

    #[test]
    fn training_config_is_the_shipped_tallies_one() {
        let doc = crate::forward::kernel::KernelDoc::load(Path::new(
            "data/kernels/eta1.5_g0.3_pencil.json",
        ))
        .unwrap();
        // Everything but the plan and its path count.
        let analog = crate::forward::kernel::KernelConfig {
            paths: training_config().paths,
            runs: Vec::new(),
            ..doc.config.clone()
        };
        assert!(
            !doc.config.runs.is_empty(),
            "the shipped tallies are planned"
        );
        assert_eq!(
            serde_json::to_value(&analog).unwrap(),
            serde_json::to_value(training_config()).unwrap()
        );
    }

    #[test]
    fn every_scene_is_built_in() {
        for (name, text) in SCENES {
            assert!(text.contains(&format!("name = \"{name}\"")), "{name}");
        }
        assert!(scene_text("stripes").is_some() && scene_text("nope").is_none());
    }
}
