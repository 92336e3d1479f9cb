//! Rendering physics (docs/design.md §3 step 4 and §4): the loaded scene
//! ([`scene`]), the SV-BSSRDF of every method ([`svbssrdf`]) with O(1)
//! aggregation ([`pyramid`]), one estimator for all of them ([`estimator`]),
//! the brute-force reference ([`reference`](mod@reference)) and the scene
//! analysis of what a scene calls for ([`analysis`]). Nothing here opens a
//! file: the jobs above ([`crate::jobs`]) load scenes and models and write
//! images and reports.

pub mod analysis;
pub mod estimator;
pub mod pyramid;
pub mod reference;
pub mod scene;
pub mod svbssrdf;
