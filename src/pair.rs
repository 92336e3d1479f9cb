//! The pair frame shared by the forward estimator, the fits and the models
//! (docs/design.md §2, "Frames for kernels"): for entry x_i and exit x_e at distance
//! d, t runs along the axis from x_i (t = 0) to x_e (t = d) and s across it;
//! kernels are symmetric in s. Lengths in MFP.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Which scattering vertices a histogram holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum VertexClass {
    All,
    First,
    Last,
}

impl VertexClass {
    pub const ALL: [VertexClass; 3] = [VertexClass::All, VertexClass::First, VertexClass::Last];

    /// Index of the class in per-class arrays (all, first, last).
    pub fn slot(self) -> usize {
        self as usize
    }

    /// `all`, `first` or `last` (as [`Self::parse`] reads it).
    pub fn name(self) -> &'static str {
        match self {
            VertexClass::All => "all",
            VertexClass::First => "first",
            VertexClass::Last => "last",
        }
    }

    /// Parses `all|first|last`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "all" => Ok(VertexClass::All),
            "first" => Ok(VertexClass::First),
            "last" => Ok(VertexClass::Last),
            _ => Err(Error::param("vertices", s, "all, first or last")),
        }
    }
}
