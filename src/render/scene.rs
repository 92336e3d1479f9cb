//! The scene a renderer evaluates: medium, material maps, light, image and
//! methods. Scene files (TOML) are read by the job layer
//! ([`crate::jobs::scene`], schema there and in `docs/scenes.md`); this
//! module holds only the loaded, validated values.

use crate::forward::maps::TexelMap;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The light of a scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LightKind {
    Collimated,
    Diffuse,
}

impl LightKind {
    /// The incidence of this light (the basis profile it needs).
    pub fn incidence(&self) -> crate::forward::medium::Incidence {
        match self {
            LightKind::Collimated => crate::forward::medium::Incidence::Pencil,
            LightKind::Diffuse => crate::forward::medium::Incidence::Diffuse,
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            LightKind::Collimated => "collimated",
            LightKind::Diffuse => "diffuse",
        }
    }
}

pub use crate::forward::medium::Observable;

/// A loaded, validated scene.
#[derive(Clone, Debug)]
pub struct Scene {
    pub name: String,
    /// The file it was read from (or the name of a built-in scene).
    pub path: PathBuf,
    /// The scene's TOML text (part of its content hash).
    pub source: String,
    pub eta: f64,
    pub g: f64,
    pub texel: f64,
    /// One map per channel: 1 (grey) or 3 (RGB).
    pub albedo: Vec<TexelMap>,
    /// Density map (one channel); `None` = constant 1.
    pub density: Option<TexelMap>,
    pub light: LightKind,
    pub light_radius: f64,
    pub irradiance: f64,
    pub resolution: usize,
    pub half_width: f64,
    pub observable: Observable,
    pub methods: Vec<crate::render::svbssrdf::Method>,
    pub samples: u32,
    pub reference_paths: u64,
    /// Render the scene once per constant density in this list (the
    /// `features` scene); empty: once, with `density`.
    pub density_sweep: Vec<f64>,
}
