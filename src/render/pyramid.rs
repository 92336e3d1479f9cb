//! Gaussian pyramid of a texel map: the Gaussian-weighted average
//! ∫ N(x; μ, σ²I) f(x) dx of a piecewise-constant map in a bounded number of
//! reads, whatever μ and σ (docs/design.md §4, "Aggregation in O(1)").
//!
//! # What is computed
//! For a [`TexelMap`] f (nearest-neighbour, the edge texel extending to
//! infinity outside the texture; conventions in [`crate::forward::maps`]) and
//! an isotropic 2D Gaussian of centre μ (MFP) and width σ > 0 (MFP),
//!
//! I(μ, σ) = ∫_{ℝ²} N(x; μ, σ²I) f(x) dx = (G_σ ∗ f)(μ),
//!
//! a weighted average of f (dimensionless if f is, e.g. an albedo). Because G
//! is separable and f is constant on texels, the exact value is a double sum of
//! erf products, Σ_ij f_ij·P_x(j)·P_y(i) with P the 1D normal mass of the
//! texel's interval ([`exact`]); the first and last column (row) extend to ∓∞
//! and ±∞, which is the edge clamp. That costs O(nx·ny); the pyramid answers
//! in O(1).
//!
//! # The pyramid
//! * **Levels.** Level ℓ stores L_ℓ = G_{σ_ℓ} ∗ f on a regular grid, with
//!   σ_ℓ = σ_0·r^ℓ, σ_0 = [`SIGMA0_TEXELS`]·τ and r = 2^{1/[`LEVELS_PER_OCTAVE`]}
//!   (variance ratio r² = 2^{1/3} between neighbours; see the constant for why
//!   not r = √2 or 2). The grid spacing is
//!   h_ℓ = σ_ℓ/[`SAMPLES_PER_SIGMA`] (downsampling continuously with σ), and
//!   the grid covers the texture plus a margin of 6σ_ℓ on every side: beyond
//!   it L_ℓ no longer varies across the edge (to Φc(6) ≈ 1e-9 of the map's
//!   range), so a query outside reads the clamped border node.
//! * **Build, exact and O(N).** Level 0 is the exact erf convolution of the
//!   texels (separable: rows, then columns). Level ℓ+1 is level ℓ convolved
//!   with the residual Gaussian σ_res = √(σ_{ℓ+1}² − σ_ℓ²) by the trapezoid
//!   rule on level ℓ's nodes (separable, ±6σ_res, edge-clamped, normalised).
//!   L_ℓ is band-limited by its own Gaussian, so the rule is spectrally exact:
//!   its aliasing error is ≈ exp(−2π²(σ_eff/h_ℓ)²) with
//!   σ_eff = σ_ℓσ_res/σ_{ℓ+1} ≈ 0.45σ_ℓ ≈ 2.3h_ℓ, below 1e-40 here. Every level has
//!   (2X/h_ℓ + 12·[`SAMPLES_PER_SIGMA`])·(2Y/h_ℓ + …) nodes and the h_ℓ grow
//!   geometrically, so storage and build cost are O(N) plus O(1) per level
//!   (N = nx·ny, X, Y the half-sizes of the texture): about
//!   S²(τ/σ_0)²/(1 − 2^{−1/3})·N ≈ 121·N nodes on a large map
//!   (S = [`SAMPLES_PER_SIGMA`]), plus the margins, which dominate on small
//!   maps, and ≈ 1000 nodes per level near the top.
//! * **Storage.** Each level is computed in f64 from the previous level in
//!   f64 and stored as f32 offsets from the map's midrange (4 bytes a node:
//!   measured 59 MB for 320² texels and 534 MB for 1024², margins included):
//!   the rounding, ≤ 2^−25 ≈ 3e-8 of the range, is 7·10⁴× inside
//!   [`PYRAMID_TOLERANCE`] and does not accumulate over the levels; a
//!   constant map is stored exactly. (In f64 the queries measured no faster.)
//! * **Top.** Levels continue up to σ_top ≥ 2^20·(X + Y) (a logarithmic
//!   number of small levels). Beyond σ_top the map is indistinguishable from
//!   its four corner quadrants (the texture and the edge strips carry a mass
//!   ≤ 2(X + Y)/(σ√(2π)) ≤ 8e-7 of the Gaussian): I = Σ_corners c·P_x·P_y
//!   about the texture centre, 4 reads.
//!
//! # Query ([`GaussianPyramid::integrate`])
//! * σ_0 ≤ σ ≤ σ_top: bilinear interpolation at μ in the two levels that
//!   bracket σ, blended **linearly in σ²**: the blend w·G_{σ_a} + (1−w)·G_{σ_b}
//!   is a unit-mass kernel with exactly the variance σ² of G_σ, so fields that
//!   are polynomials of degree ≤ 2 (and, with the bilinear step, linear ramps
//!   exactly) come out right, and the error is second order in the variance
//!   step. Interpolation in ln σ matches neither moment. 8 reads.
//! * σ < σ_0 (below [`SIGMA0_TEXELS`] texels): the exact erf sum over the
//!   texels meeting μ ± 4σ ([`EXACT_HALF_WIDTH`]), the window's outer texels
//!   extended to infinity: only the Gaussian mass beyond ±4σ along an axis
//!   lands on the wrong texel, so the error is ≤ 4Φc(4) ≈ 1.3e-4 of the
//!   range (plus the interpolated Φ's < 1e-8) — 15× inside
//!   [`PYRAMID_TOLERANCE`] and 10× below the levels' error. A window inside
//!   one texel is that texel's value (1 read). Since σ < σ_0 bounds the
//!   window, this is ≤ [`MAX_READS`] reads.
//!
//! # Accuracy (measured, `cargo test --release --lib render::pyramid`)
//! On white-noise maps with values in [0, 1) (37 × 23 texels, τ = 0.5 MFP, the
//! hardest case for interpolation) the pyramid stays within
//! [`PYRAMID_TOLERANCE`] of [`exact`] for σ from 0.05τ to 20τ and μ inside,
//! near the edges and far outside. Measured max |pyramid − exact|/range over
//! 20 000 queries: 4.3e-5 for σ < τ (±4σ window), 1.2e-3 for σ ∈ [τ, 2τ),
//! 6.7e-4 for [2τ, 5τ), 5.5e-4 for [5τ, 20τ]; 6.0e-4 for σ from 20τ to
//! 100σ_top. The worst cases sit outside the texture, where the edge
//! extension leaves full-height steps at every scale. [`exact`] agrees with a
//! Gauss–Legendre quadrature of the clamped map to 4.7e-15.

use crate::error::{Error, Result};
use crate::fastmath::exp4;
use crate::forward::maps::TexelMap;
use crate::metamodel::kernel::gauss_interval;
use wide::bytemuck::cast;
use wide::{f64x4, u64x4};

/// σ_0/τ: the width of level 0 in texels. Below σ_0 the query falls back to
/// the exact erf sum over a window of at most ⌊8σ_0/τ⌋ + 2 texels a side.
pub const SIGMA0_TEXELS: f64 = 1.0;

/// Levels per octave of σ: r = σ_{ℓ+1}/σ_ℓ = 2^{1/6}, a variance ratio
/// q = r² = 2^{1/3}. The linear-in-σ² blend errs on a blurred step of height
/// Δf by ≤ 0.017·(q − 1)²·Δf ≈ 1.2e-3·Δf (max over z of
/// |z(3 − z²)φ(z)|/32, from ∂²Φ(x/√s)/∂s²); q = √2 gives 2.9e-3·Δf and q = 2
/// 1.7e-2·Δf (measured: r = √2 misses the 2e-3 goal by 5×).
pub const LEVELS_PER_OCTAVE: usize = 6;

/// Grid nodes per σ_ℓ in every level: h_ℓ = σ_ℓ/5. Bilinear interpolation
/// errs on a blurred step of height Δf by ≤ (h/σ)²·φ(1)/8·Δf ≈ 1.2e-3·Δf.
pub const SAMPLES_PER_SIGMA: f64 = 5.0;

/// The fallback window below σ_0 is ±`EXACT_HALF_WIDTH`·σ around μ: error
/// ≤ 4Φc(4) ≈ 1.3e-4 of the range (module docs). (±6σ, 2e-9, cost 1.9×
/// as much at σ = 0.9τ: `cargo bench --bench render -- pyramid`.)
pub const EXACT_HALF_WIDTH: f64 = 4.0;

/// Texels per axis of the fallback window, at most: ⌊2·4·σ_0/τ⌋ + 2.
const MAX_WINDOW: usize = (2.0 * EXACT_HALF_WIDTH * SIGMA0_TEXELS) as usize + 2;

/// [`MAX_WINDOW`] rounded up to whole SIMD registers of four.
const WINDOW_LANES: usize = 4 * MAX_WINDOW.div_ceil(4);

/// The most values any query reads (texels or pyramid nodes), whatever μ
/// and σ: the fallback window below σ_0 (10² = 100); the pyramid reads 8 and
/// the corner asymptote 4.
pub const MAX_READS: usize = MAX_WINDOW * MAX_WINDOW;

/// Documented accuracy of [`GaussianPyramid::integrate`] against [`exact`],
/// as a fraction of the map's range (max − min), for any μ and σ; the tests
/// check it on white noise, the worst case.
pub const PYRAMID_TOLERANCE: f64 = 2e-3;

/// Largest |map value| a pyramid accepts: its nodes are f32 (max 3.4e38),
/// and a Gaussian average of values ≤ 1e30 stays far inside that range.
pub const MAX_VALUE: f64 = 1e30;

/// Margin of every level beyond the texture, in σ_ℓ.
const MARGIN_SIGMAS: f64 = 6.0;

/// Half-width of the build's stencils, in σ: the Gaussian's mass beyond
/// ±6σ is 2e-9, below the f32 rounding of the stored nodes (3e-8 of the
/// range). (±8σ, 41 instead of 31 taps per residual blur, gave queries
/// within 3e-8 of these and a ≈ 15 % slower build.)
const STENCIL_SIGMAS: f64 = 6.0;

/// σ_top ≥ `TOP_FACTOR`·(X + Y), where the corner asymptote takes over.
const TOP_FACTOR: f64 = 1_048_576.0;

/// Internal tuning knobs (the public constants are the defaults); kept
/// separate so the tests can measure alternatives.
#[derive(Clone, Copy, Debug)]
struct Config {
    sigma0_texels: f64,
    levels_per_octave: usize,
    samples_per_sigma: f64,
}

const DEFAULT_CONFIG: Config = Config {
    sigma0_texels: SIGMA0_TEXELS,
    levels_per_octave: LEVELS_PER_OCTAVE,
    samples_per_sigma: SAMPLES_PER_SIGMA,
};

/// One level: L_ℓ = G_{σ_ℓ} ∗ f at nodes (x0 + kx·h, y0 + ky·h), stored
/// row-major from −y (ky = 0) in `GaussianPyramid::values[offset..]`.
#[derive(Clone, Debug)]
struct Level {
    sigma: f64,
    h: f64,
    x0: f64,
    y0: f64,
    sx: usize,
    sy: usize,
    offset: usize,
    /// 1/h and the largest node coordinates sx − 1, sy − 1 (for queries).
    inv_h: f64,
    u_max: f64,
    v_max: f64,
}

impl Level {
    /// The grid of a level of width σ over a texture of half-sizes (X, Y).
    fn grid(sigma: f64, half: [f64; 2], cfg: &Config, offset: usize) -> Level {
        let h = sigma / cfg.samples_per_sigma;
        let ex = half[0] + MARGIN_SIGMAS * sigma;
        let ey = half[1] + MARGIN_SIGMAS * sigma;
        let (sx, sy) = (
            (2.0 * ex / h).ceil() as usize + 1,
            (2.0 * ey / h).ceil() as usize + 1,
        );
        Level {
            sigma,
            h,
            x0: -ex,
            y0: -ey,
            sx,
            sy,
            offset,
            inv_h: 1.0 / h,
            u_max: (sx - 1) as f64,
            v_max: (sy - 1) as f64,
        }
    }

    /// The bilinear cell of μ, clamped to the grid: (index of its lower-left
    /// node, t_x, t_y).
    #[inline]
    fn corner(&self, mu: [f64; 2]) -> (usize, f64, f64) {
        let u = ((mu[0] - self.x0) * self.inv_h).clamp(0.0, self.u_max);
        let v = ((mu[1] - self.y0) * self.inv_h).clamp(0.0, self.v_max);
        // (u, v ≥ 0 and bounded: the signed conversion is exact and cheap.)
        let (i, j) = (
            (u as i64 as usize).min(self.sx - 2),
            (v as i64 as usize).min(self.sy - 2),
        );
        (self.offset + j * self.sx + i, u - i as f64, v - j as f64)
    }
}

/// A separable 1D stencil: output node k reads inputs `start[k]..start[k] +
/// len[k]` with weights `w[off[k]..]`.
#[derive(Default)]
struct Stencil {
    start: Vec<usize>,
    len: Vec<usize>,
    off: Vec<usize>,
    w: Vec<f64>,
}

impl Stencil {
    fn push(&mut self, start: usize, weights: &[f64]) {
        self.start.push(start);
        self.len.push(weights.len());
        self.off.push(self.w.len());
        self.w.extend_from_slice(weights);
    }

    /// Output node k's first input and its weights.
    #[inline]
    fn taps(&self, k: usize) -> (usize, &[f64]) {
        (
            self.start[k],
            &self.w[self.off[k]..self.off[k] + self.len[k]],
        )
    }
}

/// Gaussian-pyramid representation of a [`TexelMap`] for O(1) Gaussian
/// aggregation (module docs): [`integrate`](Self::integrate) returns
/// ∫ N(x; μ, σ²I) f(x) dx in at most [`MAX_READS`] reads.
#[derive(Clone, Debug)]
pub struct GaussianPyramid {
    map: TexelMap,
    levels: Vec<Level>,
    /// Every level's nodes in f32, as offsets from `midrange` (computed in
    /// f64; module docs).
    values: Vec<f32>,
    /// The map's (max + min)/2: a node is `midrange + values[k]`, so a
    /// constant map is stored exactly and the rounding is relative to the
    /// range.
    midrange: f64,
    /// 1/σ_0, levels per octave L and the mantissa thresholds 2^{j/L},
    /// j = 1..L − 1, to find the level of σ in O(1) from the bits of σ/σ_0.
    inv_sigma0: f64,
    per_octave: usize,
    octave_steps: Vec<f64>,
}

impl GaussianPyramid {
    /// Builds the pyramid of `map` (O(N) time and memory, N = nx·ny).
    ///
    /// # Errors
    /// [`Error::Param`] if the map's shape or texel size is invalid (see
    /// [`TexelMap::new`]) or a value is not finite or beyond ±[`MAX_VALUE`]
    /// (the nodes are f32).
    pub fn new(map: &TexelMap) -> Result<Self> {
        Self::with_config(map, DEFAULT_CONFIG)
    }

    fn with_config(map: &TexelMap, cfg: Config) -> Result<Self> {
        use rayon::prelude::*;
        let map = TexelMap::new(map.nx, map.ny, map.texel, map.values.clone())?;
        if let Some(v) = map
            .values
            .iter()
            .find(|v| !v.is_finite() || v.abs() > MAX_VALUE)
        {
            return Err(Error::param(
                "map value",
                v,
                "finite and |v| <= 1e30 (pyramid nodes are f32)",
            ));
        }
        let tau = map.texel;
        let half = [0.5 * map.nx as f64 * tau, 0.5 * map.ny as f64 * tau];
        let sigma0 = cfg.sigma0_texels * tau;
        let r = 2f64.powf(1.0 / cfg.levels_per_octave as f64);
        let sigma_top = TOP_FACTOR * (half[0] + half[1]);
        let n_levels = ((sigma_top / sigma0).ln() / r.ln()).ceil().max(1.0) as usize + 1;

        // The grids first (a level's offset is the size of those below), so
        // that the node array is allocated once.
        let mut levels: Vec<Level> = Vec::with_capacity(n_levels);
        let mut total = 0;
        for l in 0..n_levels {
            let lv = Level::grid(sigma0 * r.powi(l as i32), half, &cfg, total);
            total += lv.sx * lv.sy;
            levels.push(lv);
        }
        let (lo, hi) = map
            .values
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let midrange = 0.5 * (lo + hi);
        let store = |v: &f64| (v - midrange) as f32;
        let mut values: Vec<f32> = Vec::with_capacity(total);
        // Each level is built in f64 from the previous one in f64, then
        // stored in f32: the rounding does not accumulate over the levels.
        // Level 0: exact erf convolution of the texels.
        let (mut level, mut next, mut tmp) = (Vec::new(), Vec::new(), Vec::new());
        let (sx, sy) = rayon::join(
            || texel_stencil(&map, false, &levels[0]),
            || texel_stencil(&map, true, &levels[0]),
        );
        convolve_into(
            &map.values,
            (map.ny, map.nx),
            (&sx, &sy),
            &mut tmp,
            &mut level,
        );
        values.par_extend(level.par_iter().map(store));
        // Level ℓ+1 = level ℓ blurred by σ_res (trapezoid rule, edge-clamped).
        for pair in levels.windows(2) {
            let (prev, lv) = (&pair[0], &pair[1]);
            let s_res = (lv.sigma * lv.sigma - prev.sigma * prev.sigma).sqrt();
            let (sx, sy) = rayon::join(
                || node_stencil((prev.x0, prev.h, prev.sx), (lv.x0, lv.h, lv.sx), s_res),
                || node_stencil((prev.y0, prev.h, prev.sy), (lv.y0, lv.h, lv.sy), s_res),
            );
            convolve_into(&level, (prev.sy, prev.sx), (&sx, &sy), &mut tmp, &mut next);
            values.par_extend(next.par_iter().map(store));
            std::mem::swap(&mut level, &mut next);
        }
        Ok(GaussianPyramid {
            map,
            levels,
            values,
            midrange,
            inv_sigma0: 1.0 / sigma0,
            per_octave: cfg.levels_per_octave,
            octave_steps: (1..cfg.levels_per_octave)
                .map(|j| 2f64.powf(j as f64 / cfg.levels_per_octave as f64))
                .collect(),
        })
    }

    /// ∫ N(x; μ, σ²I) f(x) dx: the average of the map under an isotropic
    /// Gaussian of centre `mu` = (x, y) and width `sigma` (both MFP), the
    /// edge texels extending outside. Unit-weight kernel: the result is a
    /// convex combination of texel values (units of the map).
    ///
    /// Accuracy [`PYRAMID_TOLERANCE`] of the range (≤ 1.3e-4 below σ_0);
    /// at most [`MAX_READS`] reads. Returns NaN unless μ is finite and
    /// σ is finite and > 0.
    #[inline]
    pub fn integrate(&self, mu: [f64; 2], sigma: f64) -> f64 {
        self.integrate_counted(mu, sigma).0
    }

    /// [`integrate`](Self::integrate) and the number of stored values (texels
    /// or pyramid nodes) it read, ≤ [`MAX_READS`].
    pub fn integrate_counted(&self, mu: [f64; 2], sigma: f64) -> (f64, usize) {
        let ([v], reads) = Self::integrate_n([self], mu, sigma);
        (v, reads)
    }

    /// [`integrate`](Self::integrate) of this pyramid and `other` at the same
    /// (μ, σ), sharing the level search, the interpolation weights and (below
    /// σ_0) the erf masses. `other` must be built from a map of the same
    /// shape and texel size (checked in debug builds).
    #[inline]
    pub fn integrate_pair(&self, other: &GaussianPyramid, mu: [f64; 2], sigma: f64) -> (f64, f64) {
        debug_assert!(
            (self.map.nx, self.map.ny, self.map.texel)
                == (other.map.nx, other.map.ny, other.map.texel)
        );
        let ([a, b], _) = Self::integrate_n([self, other], mu, sigma);
        (a, b)
    }

    /// [`integrate`](Self::integrate) of N pyramids built from maps of one
    /// shape and texel size at one (μ, σ) (the first pyramid's levels
    /// decide), and the number of values read from each.
    #[inline]
    pub fn integrate_n<const N: usize>(
        pyramids: [&GaussianPyramid; N],
        mu: [f64; 2],
        sigma: f64,
    ) -> ([f64; N], usize) {
        let p0 = pyramids[0];
        if !(mu[0].is_finite() && mu[1].is_finite() && sigma > 0.0 && sigma.is_finite()) {
            return ([f64::NAN; N], 0);
        }
        let top = p0.levels.len() - 1;
        if sigma < p0.levels[0].sigma {
            return exact_window(std::array::from_fn(|i| &pyramids[i].map), mu, sigma);
        }
        if sigma > p0.levels[top].sigma {
            return (pyramids.map(|p| p.corner_asymptote(mu, sigma)), 4);
        }
        // Bracketing levels a, a + 1 (rounding is absorbed by the clamp of w).
        let a = p0.level_below(sigma).min(top - 1);
        let (la, lb) = (&p0.levels[a], &p0.levels[a + 1]);
        let (va, vb) = (la.sigma * la.sigma, lb.sigma * lb.sigma);
        let w = ((sigma * sigma - va) / (vb - va)).clamp(0.0, 1.0);
        let (ia, ib) = (la.corner(mu), lb.corner(mu));
        let mut values = [0.0; N];
        for (v, p) in values.iter_mut().zip(pyramids) {
            *v = (1.0 - w) * p.bilerp_at(la, ia) + w * p.bilerp_at(lb, ib);
        }
        (values, 8)
    }

    /// ⌊L·log₂(σ/σ_0)⌋ clamped at 0: the level whose σ_ℓ = σ_0·2^{ℓ/L} is
    /// the largest not above σ (up to rounding), from the binary exponent of
    /// σ/σ_0 and L − 1 comparisons of its mantissa (no logarithm).
    #[inline]
    fn level_below(&self, sigma: f64) -> usize {
        let q = sigma * self.inv_sigma0;
        if q < 1.0 {
            return 0;
        }
        let bits = q.to_bits();
        let octave = ((bits >> 52) & 0x7ff) as usize - 1023;
        let mantissa = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 1f64.to_bits());
        let step = self.octave_steps.iter().filter(|&&t| mantissa >= t).count();
        octave * self.per_octave + step
    }

    /// Bilinear interpolation at a located corner (see [`Level::corner`]).
    #[inline]
    fn bilerp_at(&self, lv: &Level, (base, tx, ty): (usize, f64, f64)) -> f64 {
        let row0 = &self.values[base..base + 2];
        let row1 = &self.values[base + lv.sx..base + lv.sx + 2];
        let (a, b) = (f64::from(row0[0]), f64::from(row0[1]));
        let (c, d) = (f64::from(row1[0]), f64::from(row1[1]));
        let bottom = a + tx * (b - a);
        let upper = c + tx * (d - c);
        self.midrange + (bottom + ty * (upper - bottom))
    }

    /// σ > σ_top: the map seen as its four corner quadrants about the texture
    /// centre, Σ c·P_x·P_y (error ≤ 2(X + Y)/(σ√(2π)) of the range).
    fn corner_asymptote(&self, mu: [f64; 2], sigma: f64) -> f64 {
        let m = &self.map;
        let (nx, ny) = (m.nx, m.ny);
        let left = gauss_interval(f64::NEG_INFINITY, 0.0, mu[0], sigma);
        let right = gauss_interval(0.0, f64::INFINITY, mu[0], sigma);
        let lower = gauss_interval(f64::NEG_INFINITY, 0.0, mu[1], sigma);
        let upper = gauss_interval(0.0, f64::INFINITY, mu[1], sigma);
        let v = |i: usize, j: usize| m.values[i * nx + j];
        upper * (left * v(0, 0) + right * v(0, nx - 1))
            + lower * (left * v(ny - 1, 0) + right * v(ny - 1, nx - 1))
    }

    /// Number of levels (σ_0 … σ_top).
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// Width σ_ℓ of level ℓ (MFP), for ℓ < [`levels`](Self::levels).
    pub fn level_sigma(&self, l: usize) -> f64 {
        self.levels[l].sigma
    }

    /// Number of stored pyramid nodes (all levels; 4 bytes each), O(N).
    pub fn nodes(&self) -> usize {
        self.values.len()
    }

    /// The map the pyramid was built from.
    pub fn map(&self) -> &TexelMap {
        &self.map
    }
}

/// The exact ∫ N(x; μ, σ²I) f(x) dx over the edge-clamped map, by brute force
/// over all texels: Σ_ij f_ij·P_x(j)·P_y(i), with P the normal mass of the
/// texel's interval, the first/last column and row extended to infinity.
///
/// O(nx + ny) erfc and O(nx·ny) products; accurate to a few ulps of the
/// range. μ, σ in MFP; NaN unless μ is finite and σ is finite and > 0.
pub fn exact(map: &TexelMap, mu: [f64; 2], sigma: f64) -> f64 {
    if !(mu[0].is_finite() && mu[1].is_finite() && sigma > 0.0 && sigma.is_finite()) {
        return f64::NAN;
    }
    let (px, py) = axes(map, mu, sigma, (0, map.nx - 1), (0, map.ny - 1));
    weighted_sum(map, &px, &py, 0, 0)
}

/// The map blurred by N(0, σ²): at every texel centre, [`exact`]'s mean of
/// the map (nearest-neighbour, edge clamp) under a Gaussian of σ (MFP).
/// Separable, so O(nx·ny·σ/τ); equal to [`exact`] at each centre but for the
/// mass beyond 6σ, which goes to the window's outer texels (≤ 2e-9 of it).
pub fn blur(map: &TexelMap, sigma: f64) -> TexelMap {
    let values = blur_pass(
        map,
        sigma,
        &blur_pass(map, sigma, &map.values, false, false),
        true,
        false,
    );
    TexelMap {
        nx: map.nx,
        ny: map.ny,
        texel: map.texel,
        values,
    }
}

/// Σ w·G_{σ·scale} ∗ `map` over a Gaussian mixture `mixture` of (σ, w)
/// pairs, σ = 0 a point (the map itself), by separable blurs ([`blur`]).
pub fn blur_mixture(map: &TexelMap, mixture: &[(f64, f64)], scale: f64) -> TexelMap {
    let mut out = map.clone();
    out.values = mixture_sum(
        mixture,
        map.values.len(),
        |sigma| blur(map, sigma * scale).values,
        &map.values,
    );
    out
}

/// The transpose of [`blur_mixture`] as a linear map of the texel values,
/// for texel weights `g` ([`blur_transpose`] per component).
pub fn blur_mixture_transpose(
    map: &TexelMap,
    mixture: &[(f64, f64)],
    scale: f64,
    g: &[f64],
) -> Vec<f64> {
    mixture_sum(
        mixture,
        g.len(),
        |sigma| blur_transpose(map, sigma * scale, g),
        g,
    )
}

/// Σ w·f(σ) over `mixture`, with `point` for σ = 0: the terms computed in
/// parallel, summed in the mixture's order (the same result for any
/// number of threads).
fn mixture_sum(
    mixture: &[(f64, f64)],
    n: usize,
    f: impl Fn(f64) -> Vec<f64> + Sync,
    point: &[f64],
) -> Vec<f64> {
    use rayon::prelude::*;
    let terms: Vec<Option<Vec<f64>>> = mixture
        .par_iter()
        .map(|&(sigma, _)| (sigma > 0.0).then(|| f(sigma)))
        .collect();
    let mut out = vec![0.0; n];
    for (&(_, weight), term) in mixture.iter().zip(&terms) {
        let values = term.as_deref().unwrap_or(point);
        for (o, v) in out.iter_mut().zip(values) {
            *o += weight * v;
        }
    }
    out
}

/// The transpose of [`blur`] as a linear map of the texel values: for
/// texel weights g (row-major, the grid of `map`, whose values are not
/// read), the gradient Σ_k g_k·∂(blur(α))_k/∂α. With edge clamp the blur is
/// not symmetric near the edges, so this is not [`blur`] itself.
pub fn blur_transpose(map: &TexelMap, sigma: f64, g: &[f64]) -> Vec<f64> {
    assert_eq!(g.len(), map.nx * map.ny, "texel buffer length");
    blur_pass(
        map,
        sigma,
        &blur_pass(map, sigma, g, true, true),
        false,
        true,
    )
}

/// One separable pass of [`blur`] along x (`y_axis` false) or y, or its
/// transpose: output k along the axis from the window of texels around
/// its centre, for every line l across it.
fn blur_pass(map: &TexelMap, sigma: f64, src: &[f64], y_axis: bool, transpose: bool) -> Vec<f64> {
    let tau = map.texel;
    let (nx, ny) = (map.nx, map.ny);
    let (n, lines) = if y_axis { (ny, nx) } else { (nx, ny) };
    let at = |k: usize, l: usize| if y_axis { k * nx + l } else { l * nx + k };
    let mut out = vec![0.0; src.len()];
    for k in 0..n {
        let c = if y_axis {
            0.5 * ny as f64 * tau - (k as f64 + 0.5) * tau
        } else {
            (k as f64 + 0.5) * tau - 0.5 * nx as f64 * tau
        };
        let (lo, hi) = window(map, y_axis, c, 6.0 * sigma);
        let w = axis_masses(map, y_axis, c, sigma, lo, hi);
        for l in 0..lines {
            if transpose {
                let v = src[at(k, l)];
                for (q, wq) in w.iter().enumerate() {
                    out[at(lo + q, l)] += wq * v;
                }
            } else {
                out[at(k, l)] = w
                    .iter()
                    .enumerate()
                    .map(|(q, wq)| wq * src[at(lo + q, l)])
                    .sum();
            }
        }
    }
    out
}

/// Mass of N(μ_x, σ²) on columns `lo..=hi` (x axis) or rows (y axis, with
/// v = −y so that row i covers v ∈ [−Y + iτ, −Y + (i+1)τ)), the outer two
/// extended to ∓∞.
fn axis_masses(map: &TexelMap, y_axis: bool, m: f64, sigma: f64, lo: usize, hi: usize) -> Vec<f64> {
    let tau = map.texel;
    let (n, mu) = if y_axis { (map.ny, -m) } else { (map.nx, m) };
    let x0 = -0.5 * n as f64 * tau;
    if lo == hi {
        return vec![1.0];
    }
    (lo..=hi)
        .map(|j| {
            let a = if j == lo {
                f64::NEG_INFINITY
            } else {
                x0 + j as f64 * tau
            };
            let b = if j == hi {
                f64::INFINITY
            } else {
                x0 + (j + 1) as f64 * tau
            };
            gauss_interval(a, b, mu, sigma)
        })
        .collect()
}

/// Columns and rows masses over the given index ranges.
fn axes(
    map: &TexelMap,
    mu: [f64; 2],
    sigma: f64,
    cols: (usize, usize),
    rows: (usize, usize),
) -> (Vec<f64>, Vec<f64>) {
    (
        axis_masses(map, false, mu[0], sigma, cols.0, cols.1),
        axis_masses(map, true, mu[1], sigma, rows.0, rows.1),
    )
}

/// Σ_ij f(i0 + i, j0 + j)·px[j]·py[i].
fn weighted_sum(map: &TexelMap, px: &[f64], py: &[f64], i0: usize, j0: usize) -> f64 {
    py.iter()
        .enumerate()
        .map(|(i, wy)| {
            let row = &map.values[(i0 + i) * map.nx + j0..][..px.len()];
            wy * row.iter().zip(px).map(|(f, wx)| f * wx).sum::<f64>()
        })
        .sum()
}

/// Index range of the texels (columns, or rows for `y_axis`) meeting
/// [μ − Kσ, μ + Kσ], clamped to the map.
fn window(map: &TexelMap, y_axis: bool, m: f64, half_width: f64) -> (usize, usize) {
    let (n, mu) = if y_axis { (map.ny, -m) } else { (map.nx, m) };
    let x0 = -0.5 * n as f64 * map.texel;
    let idx = |x: f64| (((x - x0) / map.texel).floor().max(0.0) as usize).min(n - 1);
    (idx(mu - half_width), idx(mu + half_width))
}

/// Nodes per unit z of [`fast_phi`]'s table, and its half-range.
const PHI_NODES_PER_UNIT: f64 = 32.0;
const PHI_RANGE: f64 = 6.5;

/// Φ(z_k) and φ(z_k) at z_k = −6.5 + k/32.
static PHI_TABLE: std::sync::LazyLock<Vec<(f64, f64)>> = std::sync::LazyLock::new(|| {
    let n = (2.0 * PHI_RANGE * PHI_NODES_PER_UNIT) as usize + 1;
    (0..n)
        .map(|k| {
            let z = -PHI_RANGE + k as f64 / PHI_NODES_PER_UNIT;
            (
                0.5 * libm::erfc(-z * std::f64::consts::FRAC_1_SQRT_2),
                crate::metamodel::kernel::std_normal_pdf(z),
            )
        })
        .collect()
});

/// The standard normal CDF Φ(z) by cubic Hermite interpolation of a table
/// of Φ and φ = Φ′ (spacing h = 1/32): absolute error ≤ h⁴/384·max|Φ⁗|
/// < 3e-9 (measured in the tests: 1.4e-9); 0 or 1 beyond |z| = 6.5
/// (Φc(6.5) = 4e-11). A few nanoseconds against ~20 for `erfc`.
#[inline]
pub fn fast_phi(z: f64) -> f64 {
    let t = PHI_TABLE.as_slice();
    if z.is_nan() || z <= -PHI_RANGE {
        return 0.0;
    }
    if z >= PHI_RANGE {
        return 1.0;
    }
    let u = (z + PHI_RANGE) * PHI_NODES_PER_UNIT;
    let k = (u as usize).min(t.len() - 2);
    let (x, h) = (u - k as f64, 1.0 / PHI_NODES_PER_UNIT);
    let ((p0, d0), (p1, d1)) = (t[k], t[k + 1]);
    let (x2, x3) = (x * x, x * x * x);
    (2.0 * x3 - 3.0 * x2 + 1.0) * p0
        + (x3 - 2.0 * x2 + x) * h * d0
        + (-2.0 * x3 + 3.0 * x2) * p1
        + (x3 - x2) * h * d1
}

/// [`fast_phi`] in four lanes on a table fetched once by the caller (the
/// same formula, bitwise; the table reads stay scalar).
#[inline(always)]
fn phi_hermite4(t: &[(f64, f64)], z: f64x4) -> f64x4 {
    let zc = z
        .fast_max(f64x4::splat(-PHI_RANGE))
        .fast_min(f64x4::splat(PHI_RANGE));
    let u = (zc + f64x4::splat(PHI_RANGE)) * f64x4::splat(PHI_NODES_PER_UNIT);
    let kf = u.floor();
    // The node index from the low mantissa bits of kf + 2^52 (0 ≤ kf < 2^31).
    let bits: u64x4 = cast(kf + f64x4::splat(4_503_599_627_370_496.0));
    let k = bits
        .to_array()
        .map(|b| ((b & 0xffff_ffff) as usize).min(t.len() - 2));
    // (Where the index is clamped, z ≥ 6.5 and the lane is replaced below.)
    let x = u - kf;
    let gather = |f: &dyn Fn(usize) -> f64| f64x4::from(k.map(f));
    let (p0, d0) = (gather(&|k| t[k].0), gather(&|k| t[k].1));
    let (p1, d1) = (gather(&|k| t[k + 1].0), gather(&|k| t[k + 1].1));
    let h = f64x4::splat(1.0 / PHI_NODES_PER_UNIT);
    let (x2, x3) = (x * x, x * x * x);
    let two = f64x4::splat(2.0);
    let three = f64x4::splat(3.0);
    let v = (two * x3 - three * x2 + f64x4::ONE) * p0
        + (x3 - two * x2 + x) * h * d0
        + (three * x2 - two * x3) * p1
        + (x3 - x2) * h * d1;
    // 0 at and below −6.5 (and for NaN), 1 at and above +6.5, as the scalar.
    let below = !z.simd_gt(f64x4::splat(-PHI_RANGE));
    let above = z.simd_ge(f64x4::splat(PHI_RANGE));
    above.bitselect(f64x4::ONE, v & !below)
}

/// The normal masses of the texels `lo..=hi` along one axis for N(m, σ²),
/// the outer two extended to ∓∞, into `out` (returns the count): differences
/// of [`fast_phi`] at the edges (absolute error < 1e-8 each).
#[inline]
fn edge_masses(
    map: &TexelMap,
    y_axis: bool,
    m: f64,
    sigma: f64,
    (lo, hi): (usize, usize),
    out: &mut [f64; MAX_WINDOW],
) -> usize {
    let count = hi - lo + 1;
    if count == 1 {
        out[0] = 1.0;
        return 1;
    }
    let tau = map.texel;
    let (n, mu) = if y_axis { (map.ny, -m) } else { (map.nx, m) };
    let x0 = -0.5 * n as f64 * tau;
    // Φ at the edges (0 and 1 at the outer, infinite ones).
    // Four edges per step ([`phi_hermite4`]); lanes past the last inner edge
    // are computed and overwritten.
    let mut phi = [0.0; 4 * (MAX_WINDOW + 1).div_ceil(4) + 4];
    let (table, inv_sigma) = (PHI_TABLE.as_slice(), 1.0 / sigma);
    let z1 = (x0 + (lo + 1) as f64 * tau - mu) * inv_sigma;
    let dz = tau * inv_sigma;
    let lanes = f64x4::from([0.0, 1.0, 2.0, 3.0]);
    for c in 0..(count - 1).div_ceil(4) {
        let z = (lanes + f64x4::splat((4 * c) as f64)).mul_add(f64x4::splat(dz), f64x4::splat(z1));
        phi[1 + 4 * c..5 + 4 * c].copy_from_slice(&phi_hermite4(table, z).to_array());
    }
    phi[0] = 0.0;
    phi[count] = 1.0;
    for k in 0..count {
        out[k] = phi[k + 1] - phi[k];
    }
    count
}

/// The exact sums over the texels within ±4σ of μ of every map (same
/// shape), outer ones extended to infinity; for σ < σ_0 at most
/// [`MAX_READS`] texels each. Returns (values, reads per map).
fn exact_window<const N: usize>(
    maps: [&TexelMap; N],
    mu: [f64; 2],
    sigma: f64,
) -> ([f64; N], usize) {
    let map = maps[0];
    let k = EXACT_HALF_WIDTH * sigma;
    let cols = window(map, false, mu[0], k);
    let rows = window(map, true, mu[1], k);
    if cols.0 == cols.1 && rows.0 == rows.1 {
        // One texel (a component far narrower than a texel, away from its
        // edges): its value, which is also what the sums below return.
        return (maps.map(|m| m.values[rows.0 * m.nx + cols.0]), 1);
    }
    let (mut px, mut py) = ([0.0; MAX_WINDOW], [0.0; MAX_WINDOW]);
    let nx = edge_masses(map, false, mu[0], sigma, cols, &mut px);
    let ny = edge_masses(map, true, mu[1], sigma, rows, &mut py);
    // Column sums first (Σ_i py_i f_ij for all j of the window at once, in
    // registers of four lanes), then one dot product with px. Each row is
    // read as a fixed run of WINDOW_LANES texels from its first column (the
    // texels past the window get px = 0; near the end of the map the row is
    // copied into a zero-padded buffer), so no load or store is masked.
    let mut pxv = [0.0; WINDOW_LANES];
    pxv[..nx].copy_from_slice(&px[..nx]);
    let mut values = [0.0; N];
    for (v, m) in values.iter_mut().zip(maps) {
        let mut acc = [f64x4::ZERO; WINDOW_LANES / 4];
        for (i, &wy) in py[..ny].iter().enumerate() {
            let start = (rows.0 + i) * m.nx + cols.0;
            let mut padded = [0.0; WINDOW_LANES];
            let row: &[f64] = match m.values.get(start..start + WINDOW_LANES) {
                Some(r) => r,
                None => {
                    padded[..nx].copy_from_slice(&m.values[start..start + nx]);
                    &padded
                }
            };
            let w = f64x4::splat(wy);
            for (a, f) in acc.iter_mut().zip(row.chunks_exact(4)) {
                *a = w.mul_add(f64x4::from([f[0], f[1], f[2], f[3]]), *a);
            }
        }
        let dot = acc
            .iter()
            .zip(pxv.chunks_exact(4))
            .fold(f64x4::ZERO, |d, (a, p)| {
                a.mul_add(f64x4::from([p[0], p[1], p[2], p[3]]), d)
            });
        *v = dot.reduce_add();
    }
    (values, nx * ny)
}

/// Stencil from texel columns (or rows) to the level-0 nodes of `lv`: the
/// exact masses of N(node, σ_0²) over the texels within ±6σ_0.
fn texel_stencil(map: &TexelMap, y_axis: bool, lv: &Level) -> Stencil {
    let mut st = Stencil::default();
    let (n, p0) = if y_axis {
        (lv.sy, lv.y0)
    } else {
        (lv.sx, lv.x0)
    };
    for k in 0..n {
        let p = p0 + k as f64 * lv.h;
        let (lo, hi) = window(map, y_axis, p, STENCIL_SIGMAS * lv.sigma);
        st.push(lo, &axis_masses(map, y_axis, p, lv.sigma, lo, hi));
    }
    st
}

/// Stencil of the trapezoid-rule convolution with N(0, s²) from the grid
/// `src` = (x0, h, n) to the nodes of `dst`, over ±6s, edge-clamped (weights
/// of nodes beyond the grid fall on its border node) and normalised.
fn node_stencil(src: (f64, f64, usize), dst: (f64, f64, usize), s: f64) -> Stencil {
    let (x0, h, n) = src;
    let mut st = Stencil::default();
    let (mut w, mut g) = (Vec::new(), Vec::new());
    for k in 0..dst.2 {
        let p = dst.0 + k as f64 * dst.1;
        let lo = ((p - STENCIL_SIGMAS * s - x0) / h).ceil() as i64;
        let hi = ((p + STENCIL_SIGMAS * s - x0) / h).floor() as i64;
        let (clo, chi) = (lo.clamp(0, n as i64 - 1), hi.clamp(0, n as i64 - 1));
        // The Gaussian at the taps lo..=hi, four at a time ([`exp4`]).
        let taps = (hi - lo + 1) as usize;
        g.clear();
        g.resize(taps.div_ceil(4) * 4, 0.0);
        for (c, out) in g.chunks_exact_mut(4).enumerate() {
            let z = f64x4::from(std::array::from_fn(|i| {
                (p - (x0 + (lo + (4 * c + i) as i64) as f64 * h)) / s
            }));
            out.copy_from_slice(&exp4(f64x4::splat(-0.5) * z * z).to_array());
        }
        w.clear();
        w.resize((chi - clo + 1) as usize, 0.0);
        for (m, gm) in (lo..=hi).zip(&g) {
            w[(m.clamp(clo, chi) - clo) as usize] += gm;
        }
        let total: f64 = w.iter().sum();
        w.iter_mut().for_each(|x| *x /= total);
        st.push(clo as usize, &w);
    }
    st
}

/// Separable convolution of a row-major `rows × cols` array: columns through
/// `sx`, then rows through `sy`; the result is `sy.len() × sx.len()`. Rows
/// are split over rayon's threads; every output value is the same sum in
/// the same order whatever the thread count (bitwise deterministic).
fn convolve_into(
    src: &[f64],
    (rows, cols): (usize, usize),
    (sx, sy): (&Stencil, &Stencil),
    tmp: &mut Vec<f64>,
    out: &mut Vec<f64>,
) {
    use rayon::prelude::*;
    let (ox, oy) = (sx.start.len(), sy.start.len());
    // (The buffers are reused from level to level: no allocation, and no
    // unmapping of freed pages, per level. `tmp` is overwritten entirely, so
    // it is only resized; `out` accumulates, so it starts from zeros.)
    tmp.resize(rows * ox, 0.0);
    // Four rows at a time, interleaved (column c of row 4g + i at 4c + i):
    // the stencil of an output column is then one four-lane multiply-add
    // per tap for all four rows, with no horizontal sums.
    // (One interleaving buffer per rayon job, not per group; lanes past the
    // last row of a short final group hold stale values and are not stored.)
    tmp.par_chunks_mut(4 * ox).enumerate().for_each_init(
        || vec![0.0; 4 * cols],
        |lanes, (g, out)| {
            let n = out.len() / ox;
            for i in 0..n {
                let row = &src[(4 * g + i) * cols..(4 * g + i + 1) * cols];
                for (c, &v) in row.iter().enumerate() {
                    lanes[4 * c + i] = v;
                }
            }
            for k in 0..ox {
                let (start, w) = sx.taps(k);
                let x = &lanes[4 * start..4 * (start + w.len())];
                let acc = x.chunks_exact(4).zip(w).fold(f64x4::ZERO, |acc, (v, &wt)| {
                    f64x4::from([v[0], v[1], v[2], v[3]]).mul_add(f64x4::splat(wt), acc)
                });
                for (i, a) in acc.to_array().iter().enumerate().take(n) {
                    out[i * ox + k] = *a;
                }
            }
        },
    );
    out.clear();
    out.resize(oy * ox, 0.0);
    out.par_chunks_mut(ox).enumerate().for_each(|(k, dst)| {
        let (start, w) = sy.taps(k);
        let row = |t: usize| &tmp[(start + t) * ox..(start + t + 1) * ox];
        // Four input rows per sweep of the output row: one load and store of
        // each output value per four taps, not per tap.
        let quads = w.chunks_exact(4);
        let rest = quads.remainder();
        for (q, ws) in quads.enumerate() {
            let [w0, w1, w2, w3] = [ws[0], ws[1], ws[2], ws[3]];
            let (r0, r1, r2, r3) = (row(4 * q), row(4 * q + 1), row(4 * q + 2), row(4 * q + 3));
            for (i, d) in dst.iter_mut().enumerate() {
                *d += w0.mul_add(r0[i], w1 * r1[i]) + w2.mul_add(r2[i], w3 * r3[i]);
            }
        }
        for (t, wt) in rest.iter().enumerate() {
            for (d, s) in dst.iter_mut().zip(row(w.len() - rest.len() + t)) {
                *d = wt.mul_add(*s, *d);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::rng::PathRng;

    /// A white-noise map with values in [0, 1): texel k from stream (seed, k).
    fn noise_map(nx: usize, ny: usize, tau: f64, seed: u64) -> TexelMap {
        let values = (0..nx * ny)
            .map(|k| PathRng::new(seed, k as u64).uniform())
            .collect();
        TexelMap::new(nx, ny, tau, values).unwrap()
    }

    /// `blur_transpose` is the transpose of `blur`: ⟨B x, g⟩ = ⟨x, Bᵀ g⟩ on
    /// a non-square map, with the window reaching past the edges.
    #[test]
    fn blur_transpose_is_the_adjoint() {
        let x = noise_map(23, 17, 0.1, 3);
        let g = noise_map(23, 17, 0.1, 4);
        for sigma in [0.05, 0.25, 0.9] {
            let bx = blur(&x, sigma);
            let btg = blur_transpose(&x, sigma, &g.values);
            let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
            let (lhs, rhs) = (dot(&bx.values, &g.values), dot(&x.values, &btg));
            assert!(
                (lhs - rhs).abs() < 1e-12 * lhs.abs(),
                "σ {sigma}: {lhs} vs {rhs}"
            );
            // Near an edge the blur is not symmetric: the transpose differs.
            let bg = blur(&g, sigma);
            assert!(
                bg.values
                    .iter()
                    .zip(&btg)
                    .any(|(a, b)| (a - b).abs() > 1e-6)
            );
        }
    }

    /// `blur` is [`exact`] at every texel centre, edges and corners
    /// included, on a non-square map, for σ below, at and above a texel.
    #[test]
    fn blur_is_exact_at_texel_centres() {
        let map = noise_map(23, 17, 0.1, 11);
        for sigma in [0.03, 0.1, 0.37] {
            let b = blur(&map, sigma);
            for i in 0..map.ny {
                for j in 0..map.nx {
                    let mu = [
                        (j as f64 + 0.5) * 0.1 - 0.5 * 23.0 * 0.1,
                        0.5 * 17.0 * 0.1 - (i as f64 + 0.5) * 0.1,
                    ];
                    let (got, want) = (b.values[i * map.nx + j], exact(&map, mu, sigma));
                    assert!(
                        (got - want).abs() < 1e-9,
                        "σ {sigma} ({i}, {j}): {got} vs {want}"
                    );
                }
            }
        }
    }

    /// A query point: 40% inside, 40% within ±2τ of an edge or a corner, 20%
    /// anywhere up to 6× the half-sizes away.
    fn sample_mu(map: &TexelMap, rng: &mut PathRng) -> [f64; 2] {
        let (hx, hy) = (
            0.5 * map.nx as f64 * map.texel,
            0.5 * map.ny as f64 * map.texel,
        );
        let kind = rng.uniform();
        let u = [2.0 * rng.uniform() - 1.0, 2.0 * rng.uniform() - 1.0];
        let r = [rng.uniform(), rng.uniform()];
        if kind < 0.4 {
            [u[0] * hx, u[1] * hy]
        } else if kind < 0.8 {
            let e = 2.0 * map.texel;
            let snap = |u: f64, h: f64, r: f64| {
                if r < 0.3 {
                    u * h
                } else {
                    h.copysign(u) + e * (2.0 * r - 1.0)
                }
            };
            [snap(u[0], hx, r[0]), snap(u[1], hy, r[1])]
        } else {
            [u[0] * 6.0 * hx, u[1] * 6.0 * hy]
        }
    }

    /// Gauss–Legendre nodes and weights on [−1, 1] (Newton on P_n).
    fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
        (1..=n)
            .map(|i| {
                let mut x = (std::f64::consts::PI * (i as f64 - 0.25) / (n as f64 + 0.5)).cos();
                loop {
                    let (mut p0, mut p1) = (1.0, x);
                    for k in 2..=n {
                        let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                        p0 = p1;
                        p1 = p2;
                    }
                    let dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                    let dx = p1 / dp;
                    x -= dx;
                    if dx.abs() < 1e-15 {
                        return (x, 2.0 / ((1.0 - x * x) * dp * dp));
                    }
                }
            })
            .collect()
    }

    /// ∫ N(x; μ, σ²) map.at(x, y) dx dy by tensor Gauss–Legendre (16 points)
    /// on cells cut at every texel edge and every σ/2 over μ ± 14σ: the
    /// integrand is smooth on each cell, and `map.at` supplies the edge clamp.
    fn quadrature(map: &TexelMap, mu: [f64; 2], sigma: f64) -> f64 {
        let gl = gauss_legendre(16);
        let nodes = |m: f64, n: usize| {
            let (lo, hi) = (m - 14.0 * sigma, m + 14.0 * sigma);
            let x0 = -0.5 * n as f64 * map.texel;
            let mut cuts: Vec<f64> = (0..=56).map(|k| lo + k as f64 * 0.5 * sigma).collect();
            cuts.extend(
                (0..=n)
                    .map(|j| x0 + j as f64 * map.texel)
                    .filter(|x| (lo..=hi).contains(x)),
            );
            cuts.sort_by(f64::total_cmp);
            let mut out = Vec::new();
            for c in cuts.windows(2).filter(|c| c[1] > c[0]) {
                let (mid, half) = (0.5 * (c[0] + c[1]), 0.5 * (c[1] - c[0]));
                for (t, w) in &gl {
                    let x = mid + half * t;
                    let z = (x - m) / sigma;
                    let pdf = (-0.5 * z * z).exp() / (sigma * (2.0 * std::f64::consts::PI).sqrt());
                    out.push((x, w * half * pdf));
                }
            }
            out
        };
        let (qx, qy) = (nodes(mu[0], map.nx), nodes(mu[1], map.ny));
        qy.iter()
            .map(|(y, wy)| wy * qx.iter().map(|(x, wx)| wx * map.at(*x, *y)).sum::<f64>())
            .sum()
    }

    #[test]
    fn exact_matches_quadrature_of_the_clamped_map() {
        // 5 × 3 texels of 0.5 MFP: x ∈ [−1.25, 1.25), y ∈ (−0.75, 0.75].
        let map = noise_map(5, 3, 0.5, 1);
        let mut worst: f64 = 0.0;
        for mu in [
            [0.1, 0.2],
            [-1.2, 0.7],
            [1.3, -0.8],
            [0.4, 3.0],
            [-5.0, -0.3],
            [9.0, 7.0],
        ] {
            for sigma in [0.03, 0.2, 0.5, 1.3, 4.0] {
                let (e, q) = (exact(&map, mu, sigma), quadrature(&map, mu, sigma));
                worst = worst.max((e - q).abs());
                assert!((e - q).abs() <= 1e-12, "μ {mu:?} σ {sigma}: {e} vs {q}");
            }
        }
        println!("exact vs quadrature: max |Δ| = {worst:.1e}");
        // Orientation: row 0 is +y and column 0 is −x; a narrow Gaussian well
        // inside texel (0, 4) returns that texel's value.
        let v = exact(&map, [1.0, 0.5], 1e-3);
        assert!(
            (v - map.values[4]).abs() < 1e-15,
            "{v} vs {}",
            map.values[4]
        );
    }

    #[test]
    fn pyramid_matches_exact_on_white_noise() {
        let map = noise_map(37, 23, 0.5, 2);
        let p = GaussianPyramid::new(&map).unwrap();
        let (lo, hi) = map
            .values
            .iter()
            .fold((1.0f64, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
        let range = hi - lo;
        let sigma0 = p.level_sigma(0);
        // Bands of σ/τ: [0.05, 1), [1, 2), [2, 5), [5, 20].
        let edges = [0.05, 1.0, 2.0, 5.0, 20.0];
        let mut worst = [0.0f64; 4];
        let mut rng = PathRng::new(3, 0);
        for _ in 0..20_000 {
            let mu = sample_mu(&map, &mut rng);
            let sigma = map.texel * 0.05 * 400f64.powf(rng.uniform());
            let err = (p.integrate(mu, sigma) - exact(&map, mu, sigma)).abs() / range;
            let band = edges[1..]
                .iter()
                .position(|e| sigma / map.texel < *e)
                .unwrap_or(3);
            worst[band] = worst[band].max(err);
            // Below σ_0: the mass beyond ±4σ, 4Φc(4) = 1.27e-4 (module docs).
            let tol = if sigma < sigma0 {
                1.3e-4
            } else {
                PYRAMID_TOLERANCE
            };
            assert!(
                err <= tol,
                "μ {mu:?} σ {sigma}: error {err:.2e} of the range"
            );
        }
        println!(
            "max |pyramid − exact|/range by σ/τ band {edges:?}: {:?}",
            worst.map(|w| format!("{w:.2e}"))
        );
    }

    #[test]
    fn wide_kernels_and_the_corner_asymptote_match_exact() {
        let map = noise_map(37, 23, 0.5, 4);
        let p = GaussianPyramid::new(&map).unwrap();
        let top = p.level_sigma(p.levels() - 1);
        let mut rng = PathRng::new(5, 0);
        let mut worst: f64 = 0.0;
        for k in 0..4000 {
            // σ from 20τ to 100 σ_top, μ out to ±3σ.
            let sigma = 10.0
                * (10.0 * top / 10.0).powf(rng.uniform())
                * if k % 4 == 0 { 100.0 } else { 1.0 };
            let mu = [
                3.0 * sigma * (2.0 * rng.uniform() - 1.0),
                3.0 * sigma * (2.0 * rng.uniform() - 1.0),
            ];
            let err = (p.integrate(mu, sigma) - exact(&map, mu, sigma)).abs();
            worst = worst.max(err);
            assert!(err <= PYRAMID_TOLERANCE, "μ {mu:?} σ {sigma}: {err:.2e}");
        }
        // Right above σ_top the asymptote is within 2(X + Y)/(σ√2π) < 1e-6.
        for mu in [[0.0, 0.0], [top, -0.5 * top], [-2.0 * top, 3.0 * top]] {
            let s = top * 1.000_001;
            let err = (p.integrate(mu, s) - exact(&map, mu, s)).abs();
            assert!(err < 1e-6, "μ {mu:?}: {err:.2e}");
        }
        println!("σ ∈ [20τ, 100σ_top], σ_top = {top:.3e}: max |Δ| = {worst:.2e}");
    }

    #[test]
    fn fast_phi_matches_erfc() {
        let mut worst: f64 = 0.0;
        for k in 0..200_001 {
            let z = -8.0 + 16.0 * k as f64 / 200_000.0;
            let want = 0.5 * libm::erfc(-z * std::f64::consts::FRAC_1_SQRT_2);
            worst = worst.max((fast_phi(z) - want).abs());
        }
        assert!(worst < 3e-9, "{worst:e}");
        assert_eq!(
            (fast_phi(f64::NEG_INFINITY), fast_phi(f64::INFINITY)),
            (0.0, 1.0)
        );
    }

    #[test]
    fn four_lane_phi_is_the_scalar_bitwise() {
        let t = PHI_TABLE.as_slice();
        let mut z: Vec<f64> = (0..40_000)
            .map(|k| -7.0 + 14.0 * k as f64 / 39_999.0)
            .collect();
        // Nodes, the range ends and beyond, and NaN.
        z.extend([
            -6.5,
            6.5,
            -6.5 + 1e-12,
            6.5 - 1e-12,
            0.0,
            -1e300,
            1e300,
            f64::NAN,
        ]);
        for c in z.chunks(4) {
            let lanes: [f64; 4] = std::array::from_fn(|i| c.get(i).copied().unwrap_or(0.3));
            let got = phi_hermite4(t, f64x4::from(lanes)).to_array();
            for (g, z) in got.iter().zip(lanes) {
                assert_eq!(g.to_bits(), fast_phi(z).to_bits(), "z = {z}");
            }
        }
    }

    #[test]
    fn pair_queries_are_two_single_queries() {
        let (a, b) = (noise_map(37, 23, 0.5, 11), noise_map(37, 23, 0.5, 12));
        let (pa, pb) = (
            GaussianPyramid::new(&a).unwrap(),
            GaussianPyramid::new(&b).unwrap(),
        );
        let mut rng = PathRng::new(13, 0);
        for _ in 0..5000 {
            let mu = sample_mu(&a, &mut rng);
            let sigma = 0.5 * 1e-2 * 1e9f64.powf(rng.uniform());
            let (x, y) = pa.integrate_pair(&pb, mu, sigma);
            assert_eq!(
                (x, y),
                (pa.integrate(mu, sigma), pb.integrate(mu, sigma)),
                "μ {mu:?} σ {sigma}"
            );
        }
    }

    #[test]
    fn constant_map_integrates_to_the_constant() {
        let c = 0.371;
        let map = TexelMap::new(37, 23, 0.5, vec![c; 37 * 23]).unwrap();
        let p = GaussianPyramid::new(&map).unwrap();
        let mut rng = PathRng::new(6, 0);
        for _ in 0..5000 {
            let mu = sample_mu(&map, &mut rng);
            let sigma = 0.5 * 1e-3 * 1e14f64.powf(rng.uniform());
            let v = p.integrate(mu, sigma);
            // Exact up to the rounding of ~300 normalised passes (the f32
            // nodes hold offsets from the map's midrange: here ~1e-17).
            assert!((v - c).abs() <= 1e-13 * c, "μ {mu:?} σ {sigma}: {v}");
        }
    }

    #[test]
    fn linear_ramp_integrates_to_its_value() {
        // f = 0.2 + 0.6·(x + X)/(2X) at column centres, 400 × 4 texels of 0.5.
        let (nx, ny, tau) = (400, 4, 0.5);
        let hx = 0.5 * nx as f64 * tau;
        let ramp = |x: f64| 0.2 + 0.6 * (x + hx) / (2.0 * hx);
        let values = (0..ny)
            .flat_map(|_| (0..nx).map(|j| ramp(-hx + (j as f64 + 0.5) * tau)))
            .collect();
        let map = TexelMap::new(nx, ny, tau, values).unwrap();
        let p = GaussianPyramid::new(&map).unwrap();
        let mut rng = PathRng::new(7, 0);
        let half_step = 0.5 * 0.6 / nx as f64; // the staircase's deviation
        let mut worst: f64 = 0.0;
        for _ in 0..5000 {
            let sigma = tau * 0.05 * 400f64.powf(rng.uniform());
            let room = hx - 8.0 * sigma;
            let mu = [
                room * (2.0 * rng.uniform() - 1.0),
                20.0 * (rng.uniform() - 0.5),
            ];
            let err = (p.integrate(mu, sigma) - ramp(mu[0])).abs();
            if sigma >= p.level_sigma(0) {
                // Pyramid: bilinear and σ²-blend are exact on a linear field,
                // the staircase ripple is ~e^{−2π²σ²/τ²} < 3e-9 and the f32
                // nodes (offsets from the midrange) round by ≤ 2^−25·0.6 ≈ 1.8e-8.
                worst = worst.max(err);
                assert!(err < 3e-8, "μ {mu:?} σ {sigma}: {err:.2e}");
            } else {
                assert!(err <= half_step + 1e-12, "μ {mu:?} σ {sigma}: {err:.2e}");
            }
        }
        println!("ramp, σ ≥ σ_0: max |Δ| = {worst:.1e}");
    }

    #[test]
    fn reads_are_bounded_whatever_sigma_and_mu() {
        let map = noise_map(37, 23, 0.5, 8);
        let p = GaussianPyramid::new(&map).unwrap();
        let (s0, top) = (p.level_sigma(0), p.level_sigma(p.levels() - 1));
        let mut rng = PathRng::new(9, 0);
        let mut most = 0;
        for k in -24..=48 {
            let sigma = map.texel * 10f64.powf(k as f64 / 4.0);
            for _ in 0..200 {
                let mu = sample_mu(&map, &mut rng);
                let (v, reads) = p.integrate_counted(mu, sigma);
                assert!(v.is_finite());
                most = most.max(reads);
                let expected = if sigma > top {
                    reads == 4
                } else if sigma >= s0 {
                    reads == 8
                } else {
                    let w = (2.0 * EXACT_HALF_WIDTH * sigma / map.texel).floor() as usize + 2;
                    reads >= 1 && reads <= w * w
                };
                assert!(expected && reads <= MAX_READS, "σ {sigma}: {reads} reads");
            }
        }
        assert_eq!(MAX_READS, 100);
        println!("most reads: {most} (bound {MAX_READS})");
    }

    #[test]
    fn the_build_does_not_depend_on_the_thread_count() {
        let map = noise_map(61, 47, 0.25, 13);
        let build = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| GaussianPyramid::new(&map).unwrap())
        };
        let (one, four) = (build(1), build(4));
        assert_eq!(one.values.len(), four.values.len());
        assert!(
            one.values
                .iter()
                .zip(&four.values)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }

    #[test]
    fn a_window_inside_one_texel_is_its_value() {
        let map = noise_map(7, 5, 0.5, 12);
        let p = GaussianPyramid::new(&map).unwrap();
        for (i, j) in [(0, 0), (2, 3), (4, 6)] {
            // The texel's centre (row 0 is +y), σ = 0.1τ: ±4σ stays inside.
            let mu = [
                -1.75 + (j as f64 + 0.5) * 0.5,
                1.25 - (i as f64 + 0.5) * 0.5,
            ];
            let (v, reads) = p.integrate_counted(mu, 0.05);
            assert_eq!((v, reads), (map.values[i * 7 + j], 1));
            // The neighbours lie 5σ away: mass 4Φc(5) ≈ 1.1e-6.
            assert!((v - exact(&map, mu, 0.05)).abs() < 1.2e-6);
        }
    }

    #[test]
    fn storage_is_linear_in_the_texel_count() {
        let small = GaussianPyramid::new(&noise_map(37, 23, 0.5, 10)).unwrap();
        let t = std::time::Instant::now();
        let big = GaussianPyramid::new(&noise_map(296, 184, 0.5, 10)).unwrap();
        let build = t.elapsed().as_secs_f64();
        let small_per_texel = small.nodes() as f64 / (37.0 * 23.0);
        let per_texel = big.nodes() as f64 / (296.0 * 184.0);
        println!(
            "nodes/texel: 37×23 {small_per_texel:.0} ({} levels), 296×184 {per_texel:.0} \
             ({} levels, built in {build:.2} s)",
            small.levels(),
            big.levels()
        );
        // 121·N from the geometric sum of the levels, plus the margins (6σ_ℓ a
        // side) and ≈ 3700 nodes per top level, which small maps cannot amortise.
        assert!(per_texel < 170.0, "{per_texel}");
        assert!(per_texel < small_per_texel / 5.0);
        assert!(big.levels() < small.levels() + 20);
    }

    #[test]
    fn invalid_input_is_rejected() {
        let mut map = noise_map(3, 2, 0.5, 11);
        let p = GaussianPyramid::new(&map).unwrap();
        for (mu, sigma) in [
            ([0.0, 0.0], 0.0),
            ([0.0, 0.0], -1.0),
            ([0.0, 0.0], f64::NAN),
            ([0.0, 0.0], f64::INFINITY),
            ([f64::NAN, 0.0], 1.0),
            ([0.0, f64::INFINITY], 1.0),
        ] {
            assert!(p.integrate(mu, sigma).is_nan(), "{mu:?} {sigma}");
            assert!(exact(&map, mu, sigma).is_nan(), "{mu:?} {sigma}");
        }
        // Beyond the f32 nodes' safe range, and NaN.
        for bad in [1e31, -1e31, f64::NAN] {
            map.values[3] = bad;
            assert!(matches!(
                GaussianPyramid::new(&map),
                Err(Error::Param { .. })
            ));
        }
        map.values.pop();
        assert!(matches!(
            GaussianPyramid::new(&map),
            Err(Error::Param { .. })
        ));
    }
}
