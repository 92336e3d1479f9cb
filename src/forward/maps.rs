//! Piecewise-constant 2.5D material maps (docs/design.md §2): a texture of `nx × ny`
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
        if self.values.len() == 1 {
            return (0, 0); // a constant map (the common case of the walks)
        }
        let j = ((x + 0.5 * self.nx as f64 * self.texel) / self.texel).floor();
        // Rows run from +y down; the upper edge y = ny·τ/2 − iτ belongs to row
        // i: ⌊(ny·τ/2 − y)/τ⌋ (the module's convention).
        let i = ((0.5 * self.ny as f64 * self.texel - y) / self.texel).floor();
        (clamp_index(i, self.ny), clamp_index(j, self.nx))
    }

    /// The index into `values` of the texel at texel coordinates (u, v):
    /// u texels right of the left edge, v texels down from the top edge,
    /// clamped to the edge ([`Self::texel_of`] with x, y scaled by 1/τ and
    /// shifted to the corner).
    #[inline]
    pub fn index_at_texel(&self, u: f64, v: f64) -> usize {
        clamp_index(v.floor(), self.ny) * self.nx + clamp_index(u.floor(), self.nx)
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
    lookup: Lookup,
}

impl AlbedoMap {
    /// Validates every albedo ∈ [0, 1].
    pub fn new(map: TexelMap) -> Result<Self> {
        if let Some(a) = map.values.iter().find(|a| !(0.0..=1.0).contains(*a)) {
            return Err(Error::param("albedo map value", a, "in [0, 1]"));
        }
        let thresholds = map.values.iter().map(|a| threshold_u32(*a)).collect();
        Ok(AlbedoMap {
            lookup: Lookup::new(&map),
            map,
            thresholds,
        })
    }
}

impl AlbedoField for AlbedoMap {
    #[inline]
    fn threshold(&self, x: f64, y: f64) -> u64 {
        // (The texel by a multiplication with 1/τ, see `MajorantGrid::density_at`.)
        let (i, j) = self.lookup.texel_of(x, y);
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

/// Local density majorants on a coarse grid, for tracking that mixes the
/// two classic free-flight samplers (pbrt-v4's majorant grid, PBRT4 §14.2.3;
/// Novák et al. 2018, "Monte Carlo methods for physically based volume
/// rendering", §4): a flight is tracked **regularly through the cells**
/// (optical depth against the cell's majorant, cell faces crossed one by one)
/// and **delta-tracked within a cell** (a tentative collision is real with
/// probability ρ(x)/ρ_maj(cell)). One cell per texel is regular tracking (the
/// majorant is the density: every collision is real); one cell for the whole
/// map is delta tracking against ρ_max. In between, the cost per real
/// collision trades cell crossings (fewer for larger cells) against null
/// collisions (fewer for tighter majorants).
///
/// # Geometry
/// Cells are squares of M texels a side (M = `cell_texels`), the grid
/// centred on the origin like every map ([`TexelMap`] conventions) with
/// ⌈nx/M⌉ × ⌈ny/M⌉ cells, the edge cells extending to infinity like the edge
/// texels. A cell's majorant is the largest density of the texels it meets
/// (edge texels clamped), so ρ ≤ ρ_maj everywhere, outside the texture too.
#[derive(Clone, Debug)]
pub struct MajorantGrid {
    pub density: DensityMap,
    /// ρ_maj per cell, a map of texel size Mτ.
    pub majorant: TexelMap,
    /// Texel lookups of the density map and of the cells for the walk.
    fine: Lookup,
    coarse: Lookup,
    /// Cell edge M in texels (≥ 1; 1: the majorant is the density itself).
    pub cell_texels: usize,
    /// ρ = ρ_maj everywhere (one texel per cell, or a constant density): no
    /// null collisions, so the walk skips the acceptance test.
    exact: bool,
}

impl MajorantGrid {
    /// The grid of cells of `cell_texels` texels (clamped to [1, max(nx, ny)];
    /// the upper end is a single cell, i.e. delta tracking against ρ_max).
    pub fn new(density: &DensityMap, cell_texels: usize) -> Self {
        let m = &density.map;
        let cell = cell_texels.clamp(1, m.nx.max(m.ny));
        let majorant = Self::majorants(density, cell);
        let constant = m.values.iter().all(|&v| v == m.values[0]);
        MajorantGrid {
            density: density.clone(),
            fine: Lookup::new(m),
            coarse: Lookup::new(&majorant),
            majorant,
            cell_texels: cell,
            exact: cell == 1 || constant,
        }
    }

    /// The majorant map alone (what [`MajorantGrid::new`] builds, without
    /// copying the density): cells of `cell_texels` texels, clamped as there.
    pub fn majorants(density: &DensityMap, cell_texels: usize) -> TexelMap {
        let m = &density.map;
        let cell = cell_texels.clamp(1, m.nx.max(m.ny));
        if cell == 1 {
            return m.clone();
        }
        if cell == m.nx.max(m.ny) {
            return TexelMap {
                nx: 1,
                ny: 1,
                texel: cell as f64 * m.texel,
                values: vec![density.majorant()],
            };
        }
        let (cols, rows) = (cell_ranges(m.nx, cell), cell_ranges(m.ny, cell));
        let mut values = Vec::with_capacity(cols.len() * rows.len());
        for &(i0, i1) in &rows {
            for &(j0, j1) in &cols {
                let mut v = 0.0f64;
                for i in i0..=i1 {
                    for &r in &m.values[i * m.nx + j0..=i * m.nx + j1] {
                        v = v.max(r);
                    }
                }
                values.push(v);
            }
        }
        TexelMap {
            nx: cols.len(),
            ny: rows.len(),
            texel: cell as f64 * m.texel,
            values,
        }
    }

    /// The density at (x, y) ([`TexelMap::at`] by a multiplication with
    /// 1/τ instead of a division: the texel may differ within an ulp of a
    /// face, which a tentative collision never distinguishes).
    #[inline]
    pub fn density_at(&self, x: f64, y: f64) -> f64 {
        let (i, j) = self.fine.texel_of(x, y);
        self.density.map.values[i * self.fine.nx + j]
    }

    /// The cell (row, column) of (x, y) in [`MajorantGrid::majorant`]
    /// (multiplication by 1/(Mτ), as [`MajorantGrid::density_at`]).
    #[inline]
    pub fn cell_of(&self, x: f64, y: f64) -> (usize, usize) {
        self.coarse.texel_of(x, y)
    }

    /// Whether the majorant is the density itself (no null collisions).
    #[inline]
    pub fn is_exact(&self) -> bool {
        self.exact
    }

    /// Tentative collisions per real one ([`steps_per_collision`]).
    pub fn steps_per_collision(&self) -> f64 {
        steps_per_collision(&self.density.map, &self.majorant)
    }
}

/// Tentative collisions per real one on the majorant map `majorant` of
/// `density`, Σ ρ_maj/Σ ρ over the texels (the cell of each texel's
/// centre): the null-collision overhead for paths spread evenly over the
/// texture.
pub fn steps_per_collision(density: &TexelMap, majorant: &TexelMap) -> f64 {
    let m = density;
    let (x0, y0) = (-0.5 * m.nx as f64 * m.texel, 0.5 * m.ny as f64 * m.texel);
    let (mut maj, mut rho) = (0.0, 0.0);
    for i in 0..m.ny {
        for j in 0..m.nx {
            let (x, y) = (
                x0 + (j as f64 + 0.5) * m.texel,
                y0 - (i as f64 + 0.5) * m.texel,
            );
            maj += majorant.at(x, y);
            rho += m.values[i * m.nx + j];
        }
    }
    maj / rho
}

/// [`TexelMap::texel_of`] with the reciprocal of τ precomputed (for the
/// walk's hot loop): the same texel except within an ulp of a face, where
/// either neighbour is as good (a collision lands there with probability 0).
#[derive(Clone, Copy, Debug)]
struct Lookup {
    left: f64,
    top: f64,
    inv_tau: f64,
    nx: usize,
    ny: usize,
}

impl Lookup {
    fn new(m: &TexelMap) -> Self {
        Lookup {
            left: -0.5 * m.nx as f64 * m.texel,
            top: 0.5 * m.ny as f64 * m.texel,
            inv_tau: 1.0 / m.texel,
            nx: m.nx,
            ny: m.ny,
        }
    }

    #[inline]
    fn texel_of(&self, x: f64, y: f64) -> (usize, usize) {
        if self.nx == 1 && self.ny == 1 {
            return (0, 0);
        }
        let j = ((x - self.left) * self.inv_tau).floor();
        let i = ((self.top - y) * self.inv_tau).floor();
        (clamp_index(i, self.ny), clamp_index(j, self.nx))
    }
}

/// ⌊v⌋ as an index in 0..n (NaN and negatives to 0). Through i64, whose
/// saturating conversion (NaN to 0, ±∞ to the extremes) is a few
/// instructions cheaper than usize's, and an integer clamp.
#[inline]
fn clamp_index(v: f64, n: usize) -> usize {
    (v as i64).clamp(0, n as i64 - 1) as usize
}

/// The fine index ranges (inclusive, clamped) that each of the ⌈n/M⌉ cells
/// of M fine cells meets, both grids centred: cell k covers fine-index
/// coordinates [kM − o, (k + 1)M − o) with o = (⌈n/M⌉M − n)/2; the first and
/// last cells extend to the ends (edge clamp).
fn cell_ranges(n: usize, cell: usize) -> Vec<(usize, usize)> {
    let nc = n.div_ceil(cell);
    let o = 0.5 * (nc * cell - n) as f64;
    (0..nc)
        .map(|k| {
            let lo = (k as f64 * cell as f64 - o).floor().max(0.0) as usize;
            let hi = (((k + 1) as f64 * cell as f64 - o).ceil() as usize).min(n) - 1;
            (
                if k == 0 { 0 } else { lo },
                if k + 1 == nc { n - 1 } else { hi },
            )
        })
        .collect()
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
        // The y edge is the upper edge of the lower row, and belongs to it:
        // y ∈ (ny·τ/2 − (i+1)τ, ny·τ/2 − iτ].
        assert_eq!(m.texel_of(0.1, 0.0), (1, 2));
        assert_eq!(m.texel_of(0.1, 0.5), (0, 2));
        assert_eq!(m.texel_of(-100.0, 100.0), (0, 0));
        assert_eq!(m.texel_of(100.0, -100.0), (1, 3));
        assert_eq!(m.texel_of(f64::NAN, 0.3), (0, 0));
        assert_eq!(m.at(0.7, -0.2), 7.0);
        assert!(TexelMap::new(2, 2, 0.5, vec![0.0; 3]).is_err());
        assert!(TexelMap::new(1, 1, 0.0, vec![0.0]).is_err());
        assert!(AlbedoMap::new(TexelMap::new(1, 1, 1.0, vec![1.5]).unwrap()).is_err());
    }

    /// Every texel's density lies below its cell's majorant, at texel
    /// centres, corners and far outside, for cell sizes that do and do not
    /// divide the map, and the extreme sizes are regular and delta tracking.
    #[test]
    fn majorant_grid_bounds_the_density() {
        let (nx, ny, tau) = (13, 7, 0.3);
        let v: Vec<f64> = (0..nx * ny).map(|k| 0.1 + ((k * 37) % 17) as f64).collect();
        let d = DensityMap::new(TexelMap::new(nx, ny, tau, v).unwrap()).unwrap();
        for cell in [1, 2, 3, 4, 5, 8, 13, 100] {
            let g = MajorantGrid::new(&d, cell);
            assert_eq!(g.majorant.texel, g.cell_texels as f64 * tau);
            for k in -40..=40 {
                for l in -40..=40 {
                    let (x, y) = (k as f64 * 0.07 + 0.013, l as f64 * 0.05 - 0.011);
                    let gap = g.majorant.at(x, y) - d.map.at(x, y);
                    assert!(gap >= 0.0, "cell {cell} at ({x}, {y}): {gap}");
                }
            }
            assert!(g.steps_per_collision() >= 1.0);
            if cell == 1 {
                assert!(g.is_exact() && g.majorant == d.map);
                assert_eq!(g.steps_per_collision(), 1.0);
            } else {
                assert!(!g.is_exact() && g.steps_per_collision() > 1.0);
            }
            if cell >= 13 {
                assert_eq!(g.majorant.values, vec![d.majorant()]);
            }
        }
        // The walk's lookups are the maps' own (the sample points avoid faces).
        let g = MajorantGrid::new(&d, 3);
        for k in -40..=40 {
            let (x, y) = (k as f64 * 0.071 + 0.013, k as f64 * -0.053 - 0.011);
            assert_eq!(g.density_at(x, y), d.map.at(x, y));
            assert_eq!(g.cell_of(x, y), g.majorant.texel_of(x, y));
        }
        // A cell of two texels on a 2-periodic map holds both values: its
        // majorant is the larger one everywhere.
        let stripes = (0..16).map(|k| [1.0, 3.0][k % 2]).collect();
        let d = DensityMap::new(TexelMap::new(4, 4, 1.0, stripes).unwrap()).unwrap();
        let g = MajorantGrid::new(&d, 2);
        assert_eq!(g.majorant.values, vec![3.0; 4]);
        assert_eq!(g.steps_per_collision(), 1.5);
    }
}
