//! # svkernel — learned aggregation kernels for spatially varying BSSRDFs
//!
//! The pipeline (design §3): [`forward`] simulates sub-surface transport in a
//! homogeneous half-space (or slab) by analog Monte Carlo and tallies radial
//! profiles; later stages fit, learn kernels and render.
//!
//! # Conventions (design §2 — everything in this crate relies on them)
//!
//! * **Units.** Lengths are in mean free paths (MFP) of the reference medium,
//!   σ_t0 = 1. A density ρ > 0 scales extinction: σ_t = ρ·σ_t0, so a free flight
//!   in a medium of density ρ is `-ln(u)/ρ` MFP.
//! * **Geometry.** Flat half-space: the surface is the plane z = 0 and the
//!   medium occupies z < 0 (a slab of thickness L occupies −L < z < 0).
//! * **Index of refraction.** `eta` = n_inside / n_outside (default 1.5). η = 1
//!   is index-matched: no Fresnel reflection and no refraction at all.
//! * **Directions are propagation directions.** A photon entering at normal
//!   incidence travels along (0, 0, −1). The Henyey–Greenstein phase function
//!   is written in the angle θ between the incoming and outgoing *propagation*
//!   directions, cos θ = `dot(dir_in, dir_out)`, with the textbook
//!   p(cos θ) = (1 − g²) / (4π (1 + g² − 2g cos θ)^{3/2}); g > 0 scatters
//!   forward (pinned by a test in [`forward::sampling`]).
//! * **Observable.** Radiant exitance per unit incident power (pencil beam) or
//!   per unit incident irradiance (disk lights). `R(r)` is the exitance at
//!   distance r, and the radial density is p(r) = 2πr·R(r) (finite at r = 0);
//!   the diffuse reflectance is R_d = ∫ p(r) dr. R_d never includes the
//!   specular reflection at the surface (R_sp = ((η−1)/(η+1))²), as in
//!   `shared/oracles.md`.
//! * **Scattering order.** R = R₁ + Rₘ: paths with exactly one scattering
//!   vertex, and with two or more.
//! * **Randomness.** Every random number of path `i` comes from its own stream,
//!   a pure function of `(seed, i)` ([`forward::rng`]); results never depend on
//!   the thread count or on sharding.

pub mod demo;
pub mod error;
pub mod fastmath;
pub mod fit;
pub mod forward;
pub mod io;
pub mod metamodel;
pub mod oracles;
pub mod pair;
pub mod plot;
pub mod provenance;
pub mod render;
pub mod testing;

pub use error::{Error, Result};
