//! Least-squares fitting (docs/design.md §3 step 2): the Levenberg–Marquardt layer
//! ([`lm`]), per-profile exponential mixtures ([`exp_mixture`]) and the
//! smooth-in-albedo basis BSSRDF ([`basis`]), per-configuration Gaussian
//! mixtures of the kernel histograms ([`gmm`]) and the joint kernel
//! meta-model ([`meta`]). Every fit is pure: it takes loaded documents and
//! returns the model and its report; the jobs ([`crate::jobs`]) read and
//! write the files.
//!
//! A fit goes residual → exact Jacobian → derivative check → solve → report:
//!
//! ```
//! use svkernel::fit::exp_mixture::{BinnedDensity, fit_mixture};
//! use svkernel::fit::lm::FitOptions;
//! use svkernel::metamodel::basis::ExpMixture;
//! // Ring averages of a known two-term density, 1 % errors.
//! let truth = ExpMixture { a: vec![0.2, 0.01], b: vec![10.0, 0.5], power: 0 };
//! let edges: Vec<f64> = (0..=40).map(|k| 1e-3 * 10f64.powf(k as f64 / 8.0)).collect();
//! let mut d = BinnedDensity { lo: vec![], hi: vec![], y: vec![], sigma: vec![] };
//! for w in edges.windows(2) {
//!     let y = truth.bin_mean(w[0], w[1]);
//!     d.lo.push(w[0]); d.hi.push(w[1]); d.y.push(y); d.sigma.push(0.01 * y + 1e-12);
//! }
//! let (fit, report) = fit_mixture("doc example", &d, 2, 0, &FitOptions::default()).unwrap();
//! assert!(report.success && report.chi2_per_dof < 1e-6);
//! assert!((fit.energy() / truth.energy() - 1.0).abs() < 1e-6);
//! ```

pub mod aggregation;
pub mod basis;
pub mod exp_mixture;
pub mod gmm;
pub mod lm;
pub mod meta;
