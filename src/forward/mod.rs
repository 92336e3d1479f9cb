//! Forward Monte Carlo simulation of sub-surface transport (docs/design.md §3 step 1).
//!
//! Physics only: the medium and sources ([`medium`]), Fresnel ([`fresnel`]),
//! pure samplers ([`sampling`]), per-path random streams ([`rng`]), the walk
//! ([`walk`], scalar f64; [`simd`], eight f32 lanes), integer tallies
//! ([`tally`]) and their deterministic, shardable execution ([`runner`],
//! [`profile`]); the path-density estimator of aggregation kernels
//! ([`kernel`]) and piecewise-constant material maps ([`maps`]).
//!
//! ```
//! use svkernel::forward::{medium::{Medium, Source}, profile::*, runner::RunOptions, tally::RadialBins};
//! use svkernel::provenance::Provenance;
//! // 2e4 paths, index-matched isotropic medium at α = 0.9: R_d = 1 − H(1)·sqrt(0.1) = 0.41495.
//! let config = ProfileConfig {
//!     medium: Medium::new(0.9, 0.0, 1.0, 1.0, None).unwrap(),
//!     source: Source::Pencil,
//!     paths: 20_000,
//!     seed: 1,
//!     max_events: DEFAULT_MAX_EVENTS,
//!     bins: RadialBins::default(),
//!     engine: Engine::Lanes,
//!     radiance: false,
//! };
//! let (tally, wall_s) = config.run(None, &RunOptions::default()).unwrap();
//! let doc = ProfileDoc::new(config, None, vec![(0, 2)], tally, wall_s, Provenance::current());
//! assert!((doc.R_d - 0.41495).abs() < 4.0 * doc.R_d_stderr + 1e-4);
//! ```

pub mod fresnel;
pub mod kernel;
pub mod maps;
pub mod medium;
pub mod profile;
pub mod rng;
pub mod runner;
pub mod sampling;
pub mod simd;
pub mod tally;
pub mod walk;
