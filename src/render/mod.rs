//! Rendering (design §3 step 4 and §4): scenes, the SV-BSSRDF of every
//! method ([`svbssrdf`]) with O(1) aggregation ([`pyramid`]), one estimator
//! for all of them ([`estimator`]), the brute-force reference
//! ([`reference`](mod@reference)), image output ([`output`]), the `render` job ([`job`])
//! error against time ([`compare`]), the scene analysis ([`analysis`]) and
//! the comparison report ([`report`]) and the open experiments
//! ([`experiments`]).

pub mod analysis;
pub mod compare;
pub mod estimator;
pub mod experiments;
pub mod extend;
pub mod job;
pub mod output;
pub mod pyramid;
pub mod reference;
pub mod report;
pub mod scene;
pub mod svbssrdf;
