//! The brute-force reference (docs/design.md §4 table, `reference`): analog Monte
//! Carlo of the heterogeneous 2.5D half-space, no model.
//!
//! # What is simulated
//! Paths are launched from the scene's light disk (collimated normal beam or
//! diffuse, [`crate::forward::walk::launch`]) and walked through the albedo
//! and density maps with exact free flights
//! ([`crate::forward::walk::walk_grid`]): regular tracking through the cells
//! of a majorant grid and delta tracking within them. One texel per cell is
//! plain regular tracking (a density contrast of 1e6 costs nothing extra),
//! one cell for the map plain delta tracking against ρ_max (the texel size
//! costs nothing); [`Tracking::for_density`] picks the cell size it expects
//! to be cheapest for the map. Every cell size is unbiased and uses the step
//! protocol of every walk (tested to
//! agree pixel by pixel). Channel c of path p uses stream (seed, p) for
//! every c (common random numbers across channels).
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
use crate::forward::maps::{AlbedoMap, DensityMap, MajorantGrid, TexelMap, steps_per_collision};
use crate::forward::medium::{Medium, Source};
use crate::forward::rng::PathRng;
use crate::forward::runner::{Tally, chunk_paths};
use crate::forward::sampling::hg_pdf;
use crate::forward::walk::{Fate, entry_weight, launch, normal_exit_factor, walk_grid};
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

/// How the reference samples free flights through the density map: on a
/// [`MajorantGrid`] of square cells of `cell_texels` texels (regular
/// tracking through the cells, delta tracking within; exact for every cell
/// size, tested to agree pixel by pixel). One texel per cell is regular
/// tracking, [`Tracking::DELTA`] one cell for the whole map (delta tracking
/// against ρ_max), which [`Tracking::for_density`] picks for a constant
/// density: then the walk is the homogeneous one (no nulls, no faces).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tracking {
    /// Cell edge in texels (clamped to the map: any value ≥ max(nx, ny) is
    /// one cell).
    pub cell_texels: usize,
}

/// Cost of one tracking step (a tentative collision: three random numbers,
/// a logarithm, a map read, the collision itself) in cell-face crossings of
/// [`crate::forward::walk::track_flight`] (a few comparisons and a
/// multiply-add each), and the extra set-up of a flight on a grid of more
/// than one cell (its first cell, the face distances). Fitted to the
/// reference walk on α = 0.9 with the density ramp 0.5…4 (τ = 0.05 MFP,
/// 320² texels) at cells of 1, 2, 4, …, 256 and 320 texels (`cargo bench
/// --bench render -- walk/reference_a0.9_density_ramp`): ≈ 8.5 ns per
/// crossing, ≈ 68 ns per step, ≈ 25 ns per grid set-up.
pub const STEP_IN_CROSSINGS: f64 = 8.0;
/// The set-up of a flight on a multi-cell grid, in crossings (see
/// [`STEP_IN_CROSSINGS`]).
pub const GRID_SETUP_IN_CROSSINGS: f64 = 3.0;

impl Tracking {
    /// Regular tracking through the texels (no null collisions).
    pub const REGULAR: Tracking = Tracking { cell_texels: 1 };
    /// Delta tracking against the map's largest density (no crossings).
    pub const DELTA: Tracking = Tracking {
        cell_texels: usize::MAX,
    };

    /// The cheapest cell size for `density` among 1, 2, 4, … and the whole
    /// map, by the expected work per real collision:
    /// ([`STEP_IN_CROSSINGS`] + [`GRID_SETUP_IN_CROSSINGS`])·n_steps + n_cross
    /// (the set-up only when the grid has more than one cell), with n_steps =
    /// [`steps_per_collision`] and n_cross = 1/(ρ̄Mτ) the face
    /// crossings along the mean free path 1/ρ̄ (its surface projection
    /// crosses ≈ its length in faces of x and y together); ρ̄ the map's mean.
    pub fn for_density(density: &DensityMap) -> Tracking {
        let m = &density.map;
        let n = m.nx.max(m.ny);
        if m.values.iter().all(|&v| v == m.values[0]) {
            return Tracking::DELTA; // one cell, no null collisions
        }
        let mean = m.values.iter().sum::<f64>() / m.values.len() as f64;
        let mut best = (f64::INFINITY, Tracking::DELTA);
        let mut cell = 1usize;
        loop {
            let majorant = MajorantGrid::majorants(density, cell);
            let steps = steps_per_collision(m, &majorant);
            let cost = if majorant.values.len() == 1 {
                STEP_IN_CROSSINGS * steps
            } else {
                (STEP_IN_CROSSINGS + GRID_SETUP_IN_CROSSINGS) * steps
                    + 1.0 / (mean * cell as f64 * m.texel)
            };
            if cost < best.0 {
                best = (cost, Tracking { cell_texels: cell });
            }
            if cell >= n {
                return best.1;
            }
            cell *= 2;
        }
    }
}

/// A scene prepared for the reference walk.
pub struct Reference {
    pub medium: Medium,
    pub albedo: Vec<AlbedoMap>,
    /// The density map with its majorant grid (cells chosen by
    /// [`Tracking::for_density`], or [`Reference::set_tracking`]).
    grid: MajorantGrid,
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
            return Err(Error::param("paths", 0, ">= 1"));
        }
        let tracking = Tracking::for_density(&density);
        Ok(Reference {
            medium,
            albedo,
            grid: MajorantGrid::new(&density, tracking.cell_texels),
            source,
            view,
            observable,
            seed,
            paths,
        })
    }

    /// Tracks on cells of `tracking.cell_texels` texels instead (same
    /// result in distribution; benchmarks and tests).
    pub fn set_tracking(&mut self, tracking: Tracking) {
        self.grid = MajorantGrid::new(&self.grid.density, tracking.cell_texels);
    }

    /// A key identifying this simulation (for checkpoints and merges).
    pub fn key(&self, scene_hash: &str) -> serde_json::Value {
        serde_json::json!({
            "scene": scene_hash,
            "seed": self.seed,
            "paths": self.paths,
            "resolution": self.view.resolution,
            "channels": self.albedo.len(),
            "observable": format!("{:?}", self.observable),
            "tracking_cell_texels": self.grid.cell_texels,
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
        let t_normal = normal_exit_factor(self.medium.eta);
        let mut contrib: Vec<(usize, f64)> = Vec::new();
        for (ch, albedo) in self.albedo.iter().enumerate() {
            for path in first..first + count {
                let mut rng = PathRng::new(self.seed, path);
                let Some(start) = launch(&self.source, self.medium.eta, &mut rng) else {
                    continue;
                };
                contrib.clear();
                let view = &self.view;
                let density = &self.grid.density;
                let visit = |v: [f64; 3], w: [f64; 3]| {
                    if radiance && let Some((i, j)) = view.pixel_of(v[0], v[1]) {
                        let tr = (-density.map.at(v[0], v[1]) * v[2].abs()).exp();
                        contrib.push((i * n + j, hg_pdf(g, w[2]) * tr * t_normal));
                    }
                };
                let (fate, events) = walk_grid(
                    &self.medium,
                    albedo,
                    &self.grid,
                    MAX_EVENTS,
                    start,
                    &mut rng,
                    visit,
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

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(n: usize, tau: f64, lo: f64, hi: f64) -> TexelMap {
        let v = (0..n * n)
            .map(|k| lo + (hi - lo) * (k % n) as f64 / (n - 1) as f64)
            .collect();
        TexelMap::new(n, n, tau, v).unwrap()
    }

    #[test]
    fn tracking_follows_the_cost_model() {
        let pick = |m: TexelMap| Tracking::for_density(&DensityMap::new(m).unwrap());
        // The canonical density ramp on fine texels: a grid between the
        // extremes (regular ≈ 9 crossings per collision, delta ρ_max/ρ̄ = 1.8
        // steps; cells of a few texels keep both low).
        let t = pick(ramp(160, 0.05, 0.5, 4.0));
        assert!((2..160).contains(&t.cell_texels), "{t:?}");
        // Coarse texels (one crossing per several flights): regular.
        assert_eq!(pick(ramp(16, 2.0, 0.5, 4.0)), Tracking::REGULAR);
        // A checker of 1e-3 | 1e3 on fine texels: every cell of two or more
        // texels has the majorant 1e3, doubling the steps; regular tracking
        // crosses 1/(ρ̄τ) ≈ 0.04 faces per collision.
        let checker = (0..64 * 64)
            .map(|k| {
                if (k / 64 + k % 64) % 2 == 0 {
                    1e-3
                } else {
                    1e3
                }
            })
            .collect();
        assert_eq!(
            pick(TexelMap::new(64, 64, 0.05, checker).unwrap()),
            Tracking::REGULAR
        );
        // A ramp of smooth, low density on very fine texels: one cell.
        assert_eq!(pick(ramp(64, 0.001, 1.0, 1.1)).cell_texels, 64);
        // A constant density is one exact cell: the homogeneous walk.
        for m in [
            TexelMap::new(1, 1, 0.05, vec![2.0]).unwrap(),
            TexelMap::new(5, 3, 0.05, vec![2.0; 15]).unwrap(),
        ] {
            let t = pick(m.clone());
            assert_eq!(t, Tracking::DELTA);
            assert!(MajorantGrid::new(&DensityMap::new(m).unwrap(), t.cell_texels).is_exact());
        }
    }

    /// Regular tracking, delta tracking and a majorant grid between sample
    /// the same transport: every pixel's exit count agrees within the runs'
    /// binomial noise (independent streams), and so do the totals.
    #[test]
    fn every_tracking_agrees_pixel_by_pixel() {
        let albedo = TexelMap::new(
            16,
            16,
            0.25,
            (0..256)
                .map(|k| if (k / 2) % 2 == 0 { 0.3 } else { 0.95 })
                .collect(),
        )
        .unwrap();
        let density = ramp(16, 0.25, 0.5, 3.0);
        let view = View {
            light_radius: 1.0,
            irradiance: 1.0,
            resolution: 4,
            half_width: 2.0,
        };
        let run = |tracking: Tracking, seed: u64| {
            let mut r = Reference::new(
                1.5,
                0.3,
                std::slice::from_ref(&albedo),
                Some(&density),
                1.0,
                &LightKind::Collimated,
                view,
                Observable::Exitance,
                seed,
                1_000_000,
            )
            .unwrap();
            r.set_tracking(tracking);
            let (lo, hi) = crate::forward::runner::chunk_range(r.paths, None);
            let mut t = r.empty();
            for c in lo..hi {
                t.merge(&r.chunk(c));
            }
            t
        };
        let a = run(Tracking::REGULAR, 1);
        let n = a.paths as f64;
        let z = |x: u64, y: u64| {
            let (p, q) = (x as f64 / n, y as f64 / n);
            (p - q) / ((p * (1.0 - p) + q * (1.0 - q)) / n).sqrt().max(1e-12)
        };
        let total = |t: &ReferenceTally| t.exits.iter().sum::<u64>() + t.outside;
        for (tracking, seed) in [(Tracking::DELTA, 2), (Tracking { cell_texels: 4 }, 3)] {
            let b = run(tracking, seed);
            let worst = a
                .exits
                .iter()
                .zip(&b.exits)
                .map(|(x, y)| z(*x, *y).abs())
                .fold(0.0, f64::max);
            println!(
                "{tracking:?}: exits {} vs {}, absorbed {} vs {}, worst pixel z = {worst:.2}",
                a.exits.iter().sum::<u64>(),
                b.exits.iter().sum::<u64>(),
                a.absorbed,
                b.absorbed
            );
            assert!(worst < 4.5, "{tracking:?}: worst pixel z = {worst:.2}");
            assert!(z(total(&a), total(&b)).abs() < 4.0);
            assert!(z(a.absorbed, b.absorbed).abs() < 4.0);
        }
    }
}
