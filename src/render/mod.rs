//! Rendering (design §3 step 4 and §4): the SV-BSSRDF evaluation and what it
//! needs, starting with the Gaussian pyramid that aggregates a material map
//! under an isotropic Gaussian in O(1) ([`pyramid`]).

pub mod pyramid;
pub mod scene;
