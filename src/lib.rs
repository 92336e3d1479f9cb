//! # svkernel — learned aggregation kernels for spatially varying BSSRDFs
//!
//! The pipeline (`docs/design.md` §3), in layers that import only downwards:
//!
//! * the library, which opens no files: [`forward`] simulates sub-surface
//!   transport by analog Monte Carlo (radial profiles, and the path
//!   densities between an entry and an exit point); [`fit`] fits the basis
//!   BSSRDF and the kernel meta-model to them; [`metamodel`] evaluates
//!   those models; [`render`] is the SV-BSSRDF of every aggregation method,
//!   its estimator and the brute-force reference;
//! * [`jobs`]: the commands' work with files — scenes, the document store,
//!   the shipped models, reports and plots;
//! * the `svkernel` binary, a thin command line over the jobs.
//!
//! ```
//! use svkernel::prelude::*;
//! use std::sync::Arc;
//! // The built-in models, and a two-texel albedo map (0.3 | 0.9, τ = 1 MFP).
//! let models = Models::builtin()?;
//! let albedo = TexelMap::new(2, 1, 1.0, vec![0.3, 0.9])?;
//! let s = SvBssrdf::new(
//!     Method::Learned,
//!     Variant::default(),
//!     Arc::new(BasisTable::new(&models.basis)),
//!     Some(models.meta.clone()),
//!     vec![albedo],
//!     Density::Constant(1.0),
//! )?;
//! // S(x_i, x_e) for channel 0 (1/MFP²), and an importance-sampled x_i.
//! let mut scratch = Scratch::default();
//! let xe = [0.5, 0.0];
//! let value = s.eval(0, [-0.5, 0.0], xe, &mut scratch);
//! let e = s.sample_entry(xe, [0.3, 0.7]);
//! assert!(value > 0.0 && e.pdf > 0.0);
//! # Ok::<(), svkernel::Error>(())
//! ```
//!
//! # Conventions (`docs/design.md` §2 — everything in this crate relies on them)
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
//!   the oracle values of [`oracles`].
//! * **Scattering order.** R = R₁ + Rₘ: paths with exactly one scattering
//!   vertex, and with two or more.
//! * **Randomness.** Every random number of path `i` comes from its own stream,
//!   a pure function of `(seed, i)` ([`forward::rng`]); results never depend on
//!   the thread count or on sharding.

pub mod design;
pub mod doc;
pub mod error;
pub mod fastmath;
pub mod fit;
pub mod forward;
pub mod jobs;
pub mod metamodel;
pub mod oracles;
pub mod pair;
pub mod progress;
pub mod provenance;
pub mod render;
pub mod testing;

pub use error::{Error, Result};

/// The types a renderer or a script needs, in one import:
/// `use svkernel::prelude::*;`.
pub mod prelude {
    pub use crate::doc::Document;
    pub use crate::error::{Error, Result};
    pub use crate::fit::meta::{MetaModelFit, fit_metamodel};
    pub use crate::forward::kernel::{KernelConfig, KernelDoc, PairGrid};
    pub use crate::forward::maps::TexelMap;
    pub use crate::forward::medium::{Medium, Source};
    pub use crate::forward::profile::{Engine, ProfileConfig, ProfileDoc};
    pub use crate::forward::runner::RunOptions;
    pub use crate::jobs::shipped::Models;
    pub use crate::metamodel::basis::BasisModel;
    pub use crate::metamodel::kernel::{Component, Gmm, manual_kernel};
    pub use crate::metamodel::meta::MetaModelFile;
    pub use crate::pair::VertexClass;
    pub use crate::render::estimator::{EntrySample, EntrySampler, Sampling};
    pub use crate::render::scene::Scene;
    pub use crate::render::svbssrdf::{BasisTable, Density, Method, Scratch, SvBssrdf, Variant};
}
