//! The brute-force reference (design §4 table, `reference`): analog Monte
//! Carlo of the heterogeneous 2.5D half-space, no model.
//!
//! # What is simulated
//! Paths are launched from the scene's light disk (collimated normal beam or
//! diffuse, [`crate::forward::walk::launch`]) and walked through the albedo
//! and density maps with exact free flights through the texel columns
//! ([`crate::forward::walk::walk_tracked`]: regular tracking, so a density
//! contrast of 1e6 costs nothing extra, where delta tracking would take
//! ρ_max/ρ null steps per collision; the same step protocol as every walk). Channel c of path p uses stream (seed, p) for every c
//! (common random numbers across channels).
//!
//! # Estimators (per unit irradiance times E)
//! With Φ = E·πR² the incident power, w the entry weight (1 − R_sp for
//! collimated light, 1 for diffuse, whose entry Fresnel is sampled), N paths
//! and A_pix the pixel area:
//! * exitance: M_pix = Φ·w·n_pix/(N·A_pix), n_pix the exits in the pixel;
//!   stderr Φ·w·√(n_pix(1 − n_pix/N))/(N·A_pix) (binomial, exact).
//! * radiance along the normal (next-event estimation): every scattering
//!   vertex at (x, y, z) with arrival direction ω adds
//!   f_HG(ω·ẑ)·e^{−ρ(x,y)|z|}·T(1)/η² to the pixel above it — the vertical
//!   ray stays in its texel column (2.5D), so e^{−ρ|z|} is its exact
//!   transmittance, T(1) = 1 − F(1) and 1/η² the radiance change across the
//!   interface (L/n² is invariant). L_pix = Φ·w·Σ/(N·A_pix); stderr from
//!   the per-path sums.
//!
//! # Determinism, shards and checkpoints
//! Runs through [`crate::forward::runner`]: fixed chunks merged in chunk
//! order; counts are integers and radiance sums are fixed point (2⁻³²
//! units, u128), so results are bitwise identical for any thread count and
//! for shards merged with [`ReferenceTally::merge`].

use super::estimator::{Image, View};
use super::scene::{LightKind, Observable};
use crate::error::{Error, Result};
use crate::forward::fresnel::fresnel_dielectric;
use crate::forward::maps::{AlbedoMap, DensityMap, TexelMap};
use crate::forward::medium::{Medium, Source};
use crate::forward::rng::PathRng;
use crate::forward::runner::{Tally, chunk_paths};
use crate::forward::sampling::hg_pdf;
use crate::forward::walk::{Fate, entry_weight, launch, walk_tracked};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Format tag of reference tally documents.
pub const REFERENCE_FORMAT: &str = "svkernel.reference";
pub const REFERENCE_VERSION: u32 = 1;

/// Scatterings after which a path is stopped (counted as truncated).
pub const MAX_EVENTS: u32 = 1_000_000;

/// Fixed-point scale of the radiance sums.
const Q: f64 = 4_294_967_296.0;

/// The mergeable tally of a reference render.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceTally {
    pub resolution: usize,
    pub channels: usize,
    /// Paths launched (per channel).
    pub paths: u64,
    /// Scattering events, all channels.
    pub events: u64,
    /// Null-collision and wall steps are not counted; exits outside the window.
    pub outside: u64,
    pub absorbed: u64,
    pub truncated: u64,
    /// Exits per pixel, channel-major (`(c·N + i)·N + j`).
    pub exits: Vec<u64>,
    /// Radiance: per pixel Σ over paths of the path's fixed-point sum q, and
    /// Σ q² (empty unless the observable is radiance).
    pub radiance: Vec<u128>,
    pub radiance_sq: Vec<u128>,
}

impl ReferenceTally {
    pub fn new(resolution: usize, channels: usize, radiance: bool) -> Self {
        let n = resolution * resolution * channels;
        let r = if radiance { n } else { 0 };
        ReferenceTally {
            resolution,
            channels,
            paths: 0,
            events: 0,
            outside: 0,
            absorbed: 0,
            truncated: 0,
            exits: vec![0; n],
            radiance: vec![0; r],
            radiance_sq: vec![0; r],
        }
    }
}

impl Tally for ReferenceTally {
    fn merge(&mut self, o: &Self) {
        self.paths += o.paths;
        self.events += o.events;
        self.outside += o.outside;
        self.absorbed += o.absorbed;
        self.truncated += o.truncated;
        for (a, b) in self.exits.iter_mut().zip(&o.exits) {
            *a += b;
        }
        for (a, b) in self.radiance.iter_mut().zip(&o.radiance) {
            *a += b;
        }
        for (a, b) in self.radiance_sq.iter_mut().zip(&o.radiance_sq) {
            *a += b;
        }
    }
}

/// A scene prepared for the reference walk.
pub struct Reference {
    pub medium: Medium,
    pub albedo: Vec<AlbedoMap>,
    pub density: DensityMap,
    pub source: Source,
    pub view: View,
    pub observable: Observable,
    pub seed: u64,
    pub paths: u64,
}

impl Reference {
    /// Prepares the walk: albedo channels in [0, 1], density > 0 (a constant
    /// density is a 1×1 map).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        eta: f64,
        g: f64,
        albedo: &[TexelMap],
        density: Option<&TexelMap>,
        constant_density: f64,
        light: &LightKind,
        view: View,
        observable: Observable,
        seed: u64,
        paths: u64,
    ) -> Result<Self> {
        let medium = Medium::new(0.5, g, eta, 1.0, None)?;
        let albedo = albedo
            .iter()
            .map(|m| AlbedoMap::new(m.clone()))
            .collect::<Result<Vec<_>>>()?;
        let density = match density {
            Some(m) => DensityMap::new(m.clone())?,
            None => DensityMap::new(TexelMap::new(1, 1, 1.0, vec![constant_density])?)?,
        };
        let source = match light {
            LightKind::Collimated => Source::Collimated {
                radius: view.light_radius,
            },
            LightKind::Diffuse => Source::Diffuse {
                radius: view.light_radius,
            },
        };
        if paths == 0 {
            return Err(Error::param("--paths", 0, ">= 1"));
        }
        Ok(Reference {
            medium,
            albedo,
            density,
            source,
            view,
            observable,
            seed,
            paths,
        })
    }

    /// A key identifying this simulation (for checkpoints and merges).
    pub fn key(&self, scene_hash: &str) -> serde_json::Value {
        serde_json::json!({
            "scene": scene_hash,
            "seed": self.seed,
            "paths": self.paths,
            "resolution": self.view.resolution,
            "observable": format!("{:?}", self.observable),
        })
    }

    /// An empty tally of the right shape.
    pub fn empty(&self) -> ReferenceTally {
        ReferenceTally::new(
            self.view.resolution,
            self.albedo.len(),
            self.observable == Observable::Radiance,
        )
    }

    /// Simulates chunk `c` ([`crate::forward::runner`]).
    pub fn chunk(&self, c: u64) -> ReferenceTally {
        let (first, count) = chunk_paths(self.paths, c);
        let mut t = self.empty();
        t.paths = count;
        let n = self.view.resolution;
        let radiance = self.observable == Observable::Radiance;
        let g = self.medium.g;
        // T(1)/η²: radiance across the interface along the normal.
        let t_normal = (1.0 - fresnel_dielectric(1.0, 1.0 / self.medium.eta))
            / (self.medium.eta * self.medium.eta);
        let mut contrib: Vec<(usize, f64)> = Vec::new();
        for (ch, albedo) in self.albedo.iter().enumerate() {
            for path in first..first + count {
                let mut rng = PathRng::new(self.seed, path);
                let Some(start) = launch(&self.source, self.medium.eta, &mut rng) else {
                    continue;
                };
                contrib.clear();
                let view = &self.view;
                let density = &self.density;
                let (fate, events) = walk_tracked(
                    &self.medium,
                    albedo,
                    &density.map,
                    MAX_EVENTS,
                    start,
                    &mut rng,
                    |v, w| {
                        if radiance && let Some((i, j)) = view.pixel_of(v[0], v[1]) {
                            let tr = (-density.map.at(v[0], v[1]) * v[2].abs()).exp();
                            contrib.push((i * n + j, hg_pdf(g, w[2]) * tr * t_normal));
                        }
                    },
                );
                t.events += events as u64;
                match fate {
                    Fate::Exit { x, y } => match view.pixel_of(x, y) {
                        Some((i, j)) => t.exits[(ch * n + i) * n + j] += 1,
                        None => t.outside += 1,
                    },
                    Fate::Absorbed => t.absorbed += 1,
                    Fate::Truncated => t.truncated += 1,
                    Fate::Transmitted => {}
                }
                if radiance && !contrib.is_empty() {
                    contrib.sort_by_key(|c| c.0);
                    let mut k = 0;
                    while k < contrib.len() {
                        let pix = contrib[k].0;
                        let mut s = 0.0;
                        while k < contrib.len() && contrib[k].0 == pix {
                            s += contrib[k].1;
                            k += 1;
                        }
                        let q = (s * Q).round() as u128;
                        t.radiance[ch * n * n + pix] += q;
                        t.radiance_sq[ch * n * n + pix] += q * q;
                    }
                }
            }
        }
        t
    }

    /// The image of a finished tally (module docs), times the irradiance.
    pub fn image(&self, tally: &ReferenceTally, irradiance: f64) -> Image {
        let n = self.view.resolution;
        let r = self.view.light_radius;
        let h = 2.0 * self.view.half_width / n as f64;
        let big_n = tally.paths as f64;
        let scale =
            irradiance * PI * r * r * entry_weight(&self.source, self.medium.eta) / (big_n * h * h);
        let mut img = Image::zeros(n, tally.channels);
        for k in 0..img.mean.len() {
            if tally.radiance.is_empty() {
                let c = tally.exits[k] as f64;
                img.mean[k] = scale * c;
                img.stderr[k] = scale * (c * (1.0 - c / big_n)).max(0.0).sqrt();
            } else {
                let s = tally.radiance[k] as f64 / Q;
                let sq = tally.radiance_sq[k] as f64 / (Q * Q);
                let mean = s / big_n;
                img.mean[k] = scale * s;
                img.stderr[k] = scale * ((sq - big_n * mean * mean).max(0.0)).sqrt();
            }
        }
        img
    }
}
