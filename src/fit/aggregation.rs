//! The aggregation error: how good a kernel is where it matters.
//!
//! For cell (α, d) and a random albedo texture A (texel size τ, values
//! uniform in [0, 1], random offset and orientation relative to the pair
//! frame; seeded), the aggregated albedo under a kernel K is
//! α_t(K) = Σ_b m_b(K)·Ā_b / Σ_b m_b(K) over the histogram's grid, with m_b
//! the kernel's mass in bin b and Ā_b the texture averaged over bin b and
//! its mirror image in s (the histogram is folded in |s|), by 4 × 4
//! sub-samples per bin (more in the wider bins of a window's tail). The
//! reference is the measured histogram; the error of a kernel is the RMS
//! over textures of α_t(K) − α_t(histogram). Off-grid mass is left out of
//! every method alike.

use crate::fit::gmm::{KernelHistogram, histogram_of};
use crate::fit::meta::{Cell, PlaneMoments};
use crate::forward::kernel::VertexClass;
use crate::forward::rng::PathRng;
use crate::metamodel::kernel::{Gmm, manual_kernel};
use serde::{Deserialize, Serialize};

/// Textures per cell in the aggregation-error measure.
pub const TEXTURES: u64 = 64;
/// Texel sizes (MFP) cycled through the textures.
pub const TEXEL_SIZES: [f64; 4] = [0.25, 0.5, 1.0, 2.0];

/// A seeded random texture: values in [0, 1] on a texel grid of size τ,
/// rotated by φ and offset, evaluated at pair-frame points.
struct Texture {
    tau: f64,
    cos: f64,
    sin: f64,
    offset: [f64; 2],
    seed: u64,
}

impl Texture {
    fn new(seed: u64, index: u64) -> Self {
        let mut rng = PathRng::new(seed, index);
        let phi = 2.0 * std::f64::consts::PI * rng.uniform();
        Texture {
            tau: TEXEL_SIZES[(index % TEXEL_SIZES.len() as u64) as usize],
            cos: phi.cos(),
            sin: phi.sin(),
            offset: [rng.uniform() * 100.0, rng.uniform() * 100.0],
            seed: seed ^ (index << 20),
        }
    }

    /// The albedo at pair-frame point (t, s): a hash of the texel index.
    fn at(&self, t: f64, s: f64) -> f64 {
        let x = self.cos * t - self.sin * s + self.offset[0];
        let y = self.sin * t + self.cos * s + self.offset[1];
        let (i, j) = ((x / self.tau).floor() as i64, (y / self.tau).floor() as i64);
        let key = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).rotate_left(32);
        PathRng::new(self.seed, key).uniform()
    }

    /// Mean over bin [t0, t1] × [s0, s1] and its mirror in s, by `kt` × `ks`
    /// samples at the centres of equal sub-cells.
    fn bin_mean(&self, (t0, t1, kt): (f64, f64, usize), (s0, s1, ks): (f64, f64, usize)) -> f64 {
        let mut sum = 0.0;
        for a in 0..kt {
            let t = t0 + (t1 - t0) * (a as f64 + 0.5) / kt as f64;
            for b in 0..ks {
                let s = s0 + (s1 - s0) * (b as f64 + 0.5) / ks as f64;
                sum += self.at(t, s) + self.at(t, -s);
            }
        }
        sum / (2 * kt * ks) as f64
    }
}

/// Sub-samples along one axis for each bin of `edges`: 4 in the narrowest
/// bin, and as many more as a wider bin (a tail bin, `PairGrid::tail`) is
/// wider, at most [`MAX_SUBSAMPLES`]. A uniform grid gets 4 everywhere.
fn subsamples(edges: &[f64]) -> Vec<(f64, f64, usize)> {
    let narrowest = edges
        .windows(2)
        .map(|e| e[1] - e[0])
        .fold(f64::INFINITY, f64::min);
    edges
        .windows(2)
        .map(|e| {
            let k = 4 * ((e[1] - e[0]) / narrowest).round().max(1.0) as usize;
            (e[0], e[1], k.min(MAX_SUBSAMPLES))
        })
        .collect()
}

/// The most sub-samples along one axis of a bin.
const MAX_SUBSAMPLES: usize = 16;

/// Per texture: the texture's bin means over the grid of `hists[0]` (one
/// evaluation shared by every kernel and by the noise estimate) and α_t of
/// each kernel histogram.
pub fn aggregated(hists: &[&KernelHistogram], seed: u64) -> Vec<(Vec<f64>, Vec<f64>)> {
    let grid = hists[0];
    let (ts, ss) = (subsamples(&grid.t_edges), subsamples(&grid.s_edges));
    (0..TEXTURES)
        .map(|k| {
            let tex = Texture::new(seed, k);
            let means: Vec<f64> = ts
                .iter()
                .flat_map(|&t| ss.iter().map(move |&s| (t, s)))
                .map(|(t, s)| tex.bin_mean(t, s))
                .collect();
            let at = hists
                .iter()
                .map(|h| {
                    let m: f64 = h.mass.iter().map(|v| v.max(0.0)).sum();
                    let a: f64 = h.mass.iter().zip(&means).map(|(v, a)| v.max(0.0) * a).sum();
                    if m > 0.0 { a / m } else { f64::NAN }
                })
                .collect();
            (means, at)
        })
        .collect()
}

/// One row of the aggregation-error table.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AggregationRow {
    pub class: VertexClass,
    pub alpha: f64,
    pub d: f64,
    pub paths: u64,
    /// RMS over textures of α_t − α_t(histogram) for the per-configuration
    /// GMM (None if its fit failed), the meta-model, the manual kernel.
    pub per_config: Option<f64>,
    pub meta: f64,
    pub manual: f64,
    /// The histogram's own statistical noise on α_t (RMS over textures of
    /// the standard error, from the bins' standard errors).
    pub noise: f64,
    /// The fraction of the class's vertex weight inside the tally's window
    /// (1 − overflow): what the histogram, and so the fit, sees.
    #[serde(default = "one")]
    pub window: f64,
    /// Whole-plane moments of the measured vertices and of the meta-model
    /// kernel ([`PlaneMoments`]), where the tally has them.
    #[serde(default)]
    pub plane: Option<[PlaneMoments; 2]>,
}

fn one() -> f64 {
    1.0
}

pub fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    (s / n.max(1) as f64).sqrt()
}

/// The aggregation errors of one cell.
pub fn aggregation_row(
    class: VertexClass,
    cell: &Cell,
    per_config: Option<&Gmm>,
    meta: &Gmm,
) -> AggregationRow {
    let mut row = aggregation_row_of(class, cell, per_config, &histogram_of(meta, &cell.hist));
    row.plane = cell.plane.map(|data| [data, PlaneMoments::of(meta)]);
    row
}

/// [`aggregation_row`] for a kernel given by its masses on the cell's grid
/// (`meta_h`, a histogram on the cell histogram's bins): a kernel that is
/// not a mixture, such as one warped across a density step. No whole-plane
/// moments.
pub fn aggregation_row_of(
    class: VertexClass,
    cell: &Cell,
    per_config: Option<&Gmm>,
    meta_h: &KernelHistogram,
) -> AggregationRow {
    let h = &cell.hist;
    let manual = histogram_of(&manual_kernel(cell.d), h);
    let pc = per_config.map(|g| histogram_of(g, h));
    let mut list = vec![h, meta_h, &manual];
    if let Some(p) = &pc {
        list.push(p);
    }
    let seed = 0xA66 ^ (cell.alpha.to_bits() >> 3) ^ cell.d.to_bits();
    let at = aggregated(&list, seed);
    let err = |k: usize| rms(at.iter().map(|(_, r)| r[k] - r[0]));
    // Noise: α_t = Σ m A / Σ m; first order σ² = Σ σ_b² (A_b − α_t)² / (Σm)².
    let m: f64 = h.mass.iter().map(|v| v.max(0.0)).sum();
    let noise = rms(at.iter().take(8).map(|(means, r)| {
        let s2: f64 = h
            .sigma
            .iter()
            .zip(means)
            .map(|(s, a)| (s * (a - r[0])).powi(2))
            .sum();
        s2.sqrt() / m.max(1e-300)
    }));
    AggregationRow {
        class,
        alpha: cell.alpha,
        d: cell.d,
        paths: h.paths,
        per_config: pc.map(|_| err(3)),
        meta: err(1),
        manual: err(2),
        noise,
        window: 1.0 - h.overflow,
        plane: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::kernel::{PairGrid, Tail};

    #[test]
    fn wide_bins_are_sampled_in_proportion_up_to_the_cap() {
        // A uniform grid keeps 4 sub-samples per bin, so its aggregation
        // errors are those of a grid without a tail.
        let core = PairGrid::default();
        assert!(subsamples(&core.u_edges()).iter().all(|b| b.2 == 4));
        // A tail's bins get 4 per narrowest-bin width, at most the cap.
        let g = PairGrid {
            tail: Some(Tail {
                bins: 16,
                extent: 16.0,
            }),
            ..core
        };
        let v = subsamples(&g.v_edges());
        assert!(v[..16].iter().all(|b| b.2 == 4));
        // Tail edges 4·4^(k/16): its bins are 1.45, 1.58, … and 5.3 bins
        // of λ/4 wide.
        assert_eq!((v[16].2, v[17].2), (4, 8));
        assert_eq!(v[31].2, MAX_SUBSAMPLES);
        assert!(v.windows(2).all(|w| w[0].2 <= w[1].2));
    }
}
