//! Piecewise-constant 2.5D material maps (design §2): a texture of `nx × ny`
//! texels of size τ (MFP), extruded in depth, looked up nearest-neighbour
//! with the edge texel extending outside.
//!
//! # Conventions (fixed so that external tools can match them)
//! The texture is centred on the origin; row 0 is +y, column 0 is −x; texel
//! (i, j) covers x ∈ [−nx·τ/2 + jτ, −nx·τ/2 + (j+1)τ) and
//! y ∈ (ny·τ/2 − (i+1)τ, ny·τ/2 − iτ].

use super::rng::threshold_u32;
use super::walk::{AlbedoField, DensityField};
use crate::error::{Error, Result};

/// A scalar map over the surface (one channel).
#[derive(Clone, Debug, PartialEq)]
pub struct TexelMap {
    pub nx: usize,
    pub ny: usize,
    /// Texel size τ in MFP.
    pub texel: f64,
    /// Row-major values, `values[i * nx + j]` for row i (from +y), column j (from −x).
    pub values: Vec<f64>,
}

impl TexelMap {
    /// A map with validated shape and texel size (values are not checked here;
    /// see [`AlbedoMap::new`]).
    pub fn new(nx: usize, ny: usize, texel: f64, values: Vec<f64>) -> Result<Self> {
        if nx == 0 || ny == 0 || values.len() != nx * ny {
            return Err(Error::param(
                "map shape",
                format!("{nx}x{ny} with {} values", values.len()),
                "nx, ny >= 1 and nx*ny values",
            ));
        }
        if !(texel > 0.0 && texel.is_finite()) {
            return Err(Error::param("texel size", texel, "finite and > 0"));
        }
        Ok(TexelMap {
            nx,
            ny,
            texel,
            values,
        })
    }

    /// The texel (row, column) holding (x, y), clamped to the edge.
    #[inline]
    pub fn texel_of(&self, x: f64, y: f64) -> (usize, usize) {
        let j = ((x + 0.5 * self.nx as f64 * self.texel) / self.texel).floor();
        // Rows run from +y down; the upper edge y = ny·τ/2 − iτ belongs to row i.
        let i = ((0.5 * self.ny as f64 * self.texel - y) / self.texel).ceil() - 1.0;
        let clamp = |v: f64, n: usize| {
            if v.is_nan() || v <= 0.0 {
                0
            } else {
                (v as usize).min(n - 1)
            }
        };
        (clamp(i, self.ny), clamp(j, self.nx))
    }

    /// The value at (x, y).
    #[inline]
    pub fn at(&self, x: f64, y: f64) -> f64 {
        let (i, j) = self.texel_of(x, y);
        self.values[i * self.nx + j]
    }
}

/// An albedo map for the walk: the texel values as integer scatter thresholds.
#[derive(Clone, Debug)]
pub struct AlbedoMap {
    pub map: TexelMap,
    thresholds: Vec<u64>,
}

impl AlbedoMap {
    /// Validates every albedo ∈ [0, 1].
    pub fn new(map: TexelMap) -> Result<Self> {
        if let Some(a) = map.values.iter().find(|a| !(0.0..=1.0).contains(*a)) {
            return Err(Error::param("albedo map value", a, "in [0, 1]"));
        }
        let thresholds = map.values.iter().map(|a| threshold_u32(*a)).collect();
        Ok(AlbedoMap { map, thresholds })
    }
}

impl AlbedoField for AlbedoMap {
    #[inline]
    fn threshold(&self, x: f64, y: f64) -> u64 {
        let (i, j) = self.map.texel_of(x, y);
        self.thresholds[i * self.map.nx + j]
    }
}

/// A density map for the walk: values > 0, majorant = the largest value.
#[derive(Clone, Debug)]
pub struct DensityMap {
    pub map: TexelMap,
    majorant: f64,
}

impl DensityMap {
    /// Validates every density: finite and > 0.
    pub fn new(map: TexelMap) -> Result<Self> {
        if let Some(r) = map.values.iter().find(|r| !(r.is_finite() && **r > 0.0)) {
            return Err(Error::param("density map value", r, "finite and > 0"));
        }
        let majorant = map.values.iter().copied().fold(0.0, f64::max);
        Ok(DensityMap { map, majorant })
    }
}

impl DensityField for DensityMap {
    #[inline]
    fn density(&self, x: f64, y: f64) -> f64 {
        self.map.at(x, y)
    }
    fn majorant(&self) -> f64 {
        self.majorant
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texel_conventions_and_edge_clamp() {
        // 4 × 2 texels of 0.5: x ∈ [−1, 1), y ∈ (−0.5, 0.5].
        let m = TexelMap::new(4, 2, 0.5, (0..8).map(|v| v as f64).collect()).unwrap();
        assert_eq!(m.texel_of(-0.99, 0.49), (0, 0)); // row 0 is +y, column 0 is −x
        assert_eq!(m.texel_of(0.99, -0.49), (1, 3));
        assert_eq!(m.texel_of(-0.5, 0.2), (0, 1)); // x edge belongs to the right texel
        assert_eq!(m.texel_of(0.1, 0.0), (0, 2)); // y edge belongs to the upper row
        assert_eq!(m.texel_of(-100.0, 100.0), (0, 0));
        assert_eq!(m.texel_of(100.0, -100.0), (1, 3));
        assert_eq!(m.texel_of(f64::NAN, 0.3), (0, 0));
        assert_eq!(m.at(0.7, -0.2), 7.0);
        assert!(TexelMap::new(2, 2, 0.5, vec![0.0; 3]).is_err());
        assert!(TexelMap::new(1, 1, 0.0, vec![0.0]).is_err());
        assert!(AlbedoMap::new(TexelMap::new(1, 1, 1.0, vec![1.5]).unwrap()).is_err());
    }
}
