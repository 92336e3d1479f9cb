//! The path-density estimator (docs/design.md §1, §3 step 1): where the paths that
//! connect an entry point x_i to an exit point x_e scatter.
//!
//! # What is measured
//! A normal-incidence pencil beam enters the homogeneous half-space at
//! x_i = 0. A path that leaves through the surface at x_e after `n ≥
//! min_order` scatterings (default 2: the multiple-scattering transport that
//! the aggregated albedo α_t serves, docs/design.md §4) *contributes* to the distance
//! bin holding d_p = |x_e| (bins [d(1 − w), d(1 + w)]). Its scattering
//! vertices are expressed in the path's own pair frame: t = v·ê along the axis
//! from x_i (t = 0) to x_e (t = d_p), s = v·ê⊥ across it (depth integrated
//! out: maps are 2.5D), |s| folded by the mirror symmetry. Three classes are
//! tallied: the **first** vertex, the **last** vertex and **all** vertices.
//!
//! Every contributing path of an analog walk has weight 1, so the "all"
//! density is E[#vertices in a cell | the path contributes]. Cells that analog
//! paths reach too rarely (low albedo and long or very short pairs) are filled
//! by a *planned* simulation ([`KernelConfig::plan`]): runs per albedo whose
//! free flights are transformed ([`walk_transformed`]), each path carrying its
//! likelihood ratio as an integer weight, so that every sum below is the
//! analog one in expectation and still exact to merge. A vertex at x is exactly
//! where the path reads α(x): for the analog walk the probability of a path
//! is a product of α(x_j) over its vertices times factors that do not depend
//! on α, hence ∂ ln M(x_e)/∂ ln α(cell) = E[#vertices in the cell | contributes]
//! — the "all" density *is* the first-order sensitivity of the exitance to the
//! albedo map (tested against a finite difference of the heterogeneous walk).
//!
//! # Normalised coordinates
//! Histograms are binned in u = (t − d_p/2)/λ ∈ [−E, E), v = |s|/λ ∈ [0, E)
//! with λ = d_p/2 + ℓ, ℓ = 1/σ_t the mean free path of the simulated medium
//! (uniform bins; the all-vertex grid may go on beyond E in log-spaced bins,
//! [`Tail`], out to a far edge).
//! λ interpolates between the two length scales of the problem: the mean free
//! path (the kernel of a short pair is a blob of a few ℓ around x_i ≈ x_e)
//! and the pair distance (a long pair's vertices spread along the axis).
//! Because λ scales with 1/ρ, the normalised histogram at (d, α, ρ) equals the
//! one at (ρd, α, 1) exactly — the density scaling law, tested bin by bin.
//!
//! # Determinism
//! Integer sums (per bin: Σ w·n_b and Σ w²·n_b² over contributing paths, for
//! standard errors, with w an integer weight: 1 for analog paths, the
//! stochastically rounded likelihood ratio in units of 2^−`unit_log2` for a
//! stretched run) and fixed-point moment sums: mergeable exactly, so results
//! are bitwise identical for any thread count and for shards merged with
//! [`merge`]. Without a plan every albedo reuses the path's stream (common
//! random numbers across albedos); a planned run has streams of its own.

use super::medium::Medium;
use super::rng::{PathRng, splitmix64, threshold_u32, unit_f64};
use super::runner::{self, RunOptions, Shard, Tally, chunk_paths, shard_range};
use super::walk::{
    Fate, FlightSampler, Flights, Launched, UniformAlbedo, launch, max_bias, max_stretch_offset,
    walk_transformed,
};
use crate::error::{Error, Result};
use crate::forward::medium::Source;
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Format tag of kernel documents.
pub const KERNEL_FORMAT: &str = "svkernel.kernels";
/// Version of the kernel document format.
pub const KERNEL_VERSION: u32 = 3;
/// Fixed-point resolution of the moment sums (2⁻¹⁶ in normalised units).
const MOMENT_Q: f64 = 65536.0;

/// The (u, v) grid of the histograms (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairGrid {
    /// Bins along the axis, over u ∈ [−extent, extent).
    pub nu: usize,
    /// Bins across, over v = |s|/λ ∈ [0, extent).
    pub nv: usize,
    pub extent: f64,
    /// The first- and last-vertex histograms have `vertex_refine` times as
    /// many bins along each axis as the all-vertex one
    /// ([`PairGrid::for_class`]). One vertex lies in a core of σ ≈ 0.02–0.1
    /// MFP around its end of the pair, far narrower than the default bin of
    /// λ/4 (≥ 0.26 MFP): on bins of λ/16 the fit sees that core
    /// (docs/method.md §3, "Grids"). The
    /// all-vertex density is smooth on the coarse grid, and there its fit
    /// keeps the tails that aggregation needs. 1 (no refinement) is not
    /// written, so documents and content hashes from before the refinement
    /// existed read and hash as they did.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub vertex_refine: usize,
    /// Log-spaced bins of the all-vertex histogram beyond the uniform core,
    /// out to a far edge ([`Tail`]). None (not written): the window is the
    /// core, and documents from before the tail existed read and hash as
    /// they did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tail: Option<Tail>,
}

/// The all-vertex window beyond the core: `bins` bins on each side of the
/// core along u, and `bins` beyond it along v, whose edges run
/// geometrically from the core's edge X = `PairGrid::extent` to the far
/// edge Y = `extent`, r_k = X·(Y/X)^{k/bins} (k = 0 … bins).
///
/// Why: at high albedo the vertices of exiting paths spread over the
/// diffusion length 1/σ_tr (σ_tr = √(3σ_a σ_t′); 7 MFP at α = 0.99, 22 MFP
/// at 0.999), far beyond a core of a few λ. Of an analog walk's vertex
/// weight at α = 0.99, a window of ±4λ holds as little as 95 %, ±8λ 99.1 %;
/// at α = 0.999, ±4λ as little as 86 %, ±16λ 98.9 % (docs/method.md §3,
/// "Grids"). Bins of the core's width out there would multiply the bins
/// (and the fit's cost) for a density that is smooth: log-spaced bins keep
/// the window's tail in a few dozen.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tail {
    pub bins: usize,
    /// The far edge Y, in units of λ (> `PairGrid::extent`).
    pub extent: f64,
}

fn one() -> usize {
    1
}

fn is_one(n: &usize) -> bool {
    *n == 1
}

impl Default for PairGrid {
    fn default() -> Self {
        PairGrid {
            nu: 32,
            nv: 16,
            extent: 4.0,
            vertex_refine: 4,
            tail: None,
        }
    }
}

impl PairGrid {
    /// The grid of one vertex class's histogram: this one for all vertices,
    /// `vertex_refine` times finer for the first and the last, without the
    /// tail (one vertex lies within a few MFP of its end of the pair).
    pub fn for_class(&self, class: VertexClass) -> PairGrid {
        match class {
            VertexClass::All => PairGrid {
                vertex_refine: 1,
                ..*self
            },
            VertexClass::First | VertexClass::Last => PairGrid {
                nu: self.nu * self.vertex_refine,
                nv: self.nv * self.vertex_refine,
                extent: self.extent,
                vertex_refine: 1,
                tail: None,
            },
        }
    }

    /// Tail bins per side (0 without a tail).
    fn tail_bins(&self) -> usize {
        self.tail.map_or(0, |t| t.bins)
    }

    /// Bins along u and along v, the tail's included.
    pub fn shape(&self) -> (usize, usize) {
        let n = self.tail_bins();
        (self.nu + 2 * n, self.nv + n)
    }

    /// Bins, without the overflow bin (which has index `bins()`).
    pub fn bins(&self) -> usize {
        let (nu, nv) = self.shape();
        nu * nv
    }

    /// λ = d/2 + ℓ in MFP for pair distance d and mean free path ℓ = 1/σ_t.
    pub fn scale(d: f64, mfp: f64) -> f64 {
        0.5 * d + mfp
    }

    /// Tail edge r_k = X·(Y/X)^{k/bins} (`Tail`); r_0 = X, r_bins = Y exactly.
    fn tail_edge(&self, t: &Tail, k: usize) -> f64 {
        match k {
            0 => self.extent,
            k if k == t.bins => t.extent,
            k => self.extent * (t.extent / self.extent).powf(k as f64 / t.bins as f64),
        }
    }

    /// The tail bin k (0 … bins − 1, outward) holding distance a ≥ X from
    /// the core's centre, with [r_k, r_{k+1}), or (r_k, r_{k+1}] when
    /// `mirrored` (a = −u on the negative side of u, whose bins are
    /// [−r_{k+1}, −r_k)); None beyond the far edge.
    fn tail_index(&self, t: &Tail, a: f64, mirrored: bool) -> Option<usize> {
        let inside = |k: usize| {
            let (lo, hi) = (self.tail_edge(t, k), self.tail_edge(t, k + 1));
            if mirrored {
                a > lo && a <= hi
            } else {
                a >= lo && a < hi
            }
        };
        let guess = (t.bins as f64 * (a / self.extent).ln() / (t.extent / self.extent).ln())
            .floor()
            .clamp(0.0, (t.bins - 1) as f64) as usize;
        // The guess is off by at most one where rounding puts a on an edge.
        [guess, guess.saturating_sub(1), (guess + 1).min(t.bins - 1)]
            .into_iter()
            .find(|&k| inside(k))
    }

    /// Bin of the normalised position (u, v ≥ 0); `bins()` if outside.
    #[inline]
    pub fn index(&self, u: f64, v: f64) -> usize {
        let Some(t) = self.tail else {
            let iu = ((u + self.extent) / (2.0 * self.extent) * self.nu as f64).floor();
            let iv = (v / self.extent * self.nv as f64).floor();
            return if iu >= 0.0 && iu < self.nu as f64 && iv >= 0.0 && iv < self.nv as f64 {
                iu as usize * self.nv + iv as usize
            } else {
                self.bins()
            };
        };
        let x = self.extent;
        let n = t.bins;
        let core = |y: f64, lo: f64, nb: usize| {
            (((y - lo) / (x - lo) * nb as f64).floor() as usize).min(nb - 1)
        };
        let iu = if (-x..x).contains(&u) {
            Some(n + core(u, -x, self.nu))
        } else if u < -x {
            self.tail_index(&t, -u, true).map(|k| n - 1 - k)
        } else {
            self.tail_index(&t, u, false).map(|k| n + self.nu + k)
        };
        let iv = if (0.0..x).contains(&v) {
            Some(core(v, 0.0, self.nv))
        } else if v >= x {
            self.tail_index(&t, v, false).map(|k| self.nv + k)
        } else {
            None
        };
        match (iu, iv) {
            (Some(iu), Some(iv)) => iu * (self.nv + n) + iv,
            _ => self.bins(),
        }
    }

    /// Edges in u (`shape().0` + 1).
    pub fn u_edges(&self) -> Vec<f64> {
        let core =
            (0..=self.nu).map(|k| -self.extent + 2.0 * self.extent * k as f64 / self.nu as f64);
        match self.tail {
            None => core.collect(),
            Some(t) => (1..=t.bins)
                .rev()
                .map(|k| -self.tail_edge(&t, k))
                .chain(core)
                .chain((1..=t.bins).map(|k| self.tail_edge(&t, k)))
                .collect(),
        }
    }

    /// Edges in v (`shape().1` + 1).
    pub fn v_edges(&self) -> Vec<f64> {
        let core = (0..=self.nv).map(|k| self.extent * k as f64 / self.nv as f64);
        match self.tail {
            None => core.collect(),
            Some(t) => core
                .chain((1..=t.bins).map(|k| self.tail_edge(&t, k)))
                .collect(),
        }
    }
}

pub use crate::pair::VertexClass;

/// Counts of one vertex class in one (albedo, distance) cell, each path
/// weighted by its integer weight w (1 for an analog walk).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassTally {
    /// Σ over contributing paths of w × the path's vertex count per bin; the
    /// last entry is the overflow (outside the grid).
    #[serde(with = "sparse")]
    pub count: Vec<u128>,
    /// Σ of w² × the squared per-path counts, per bin (for standard errors).
    #[serde(with = "sparse")]
    pub sq: Vec<u128>,
    /// Σ over contributing paths of w² × the per-path count in the bin × the
    /// path's count of this class's vertices (n for "all", 1 for first and
    /// last), per bin: the covariance term of the ratio estimator's error.
    #[serde(with = "sparse")]
    pub cross: Vec<u128>,
    /// Σ w·u and Σ w·v² over the vertices, fixed point (2⁻¹⁶).
    pub sum_u_q: i128,
    pub sum_v2_q: u128,
    /// For the moments' standard errors ([`ClassTally::moment_errors`]),
    /// with S_u and S_v the path's Σu and Σv² over its vertices of this
    /// class in fixed point (2⁻¹⁶) and n_c their count: Σ w²·S_u² and
    /// Σ w²·S_u·n_c, Σ w²·S_v² and Σ w²·S_v·n_c (saturating). Absent (0)
    /// in documents written without them.
    #[serde(default)]
    pub sq_u_q: u128,
    #[serde(default)]
    pub cross_u_q: i128,
    #[serde(default)]
    pub sq_v2_q: u128,
    #[serde(default)]
    pub cross_v2_q: u128,
}

impl ClassTally {
    /// An empty tally on `grid` (the class's own, [`PairGrid::for_class`]).
    fn new(grid: &PairGrid) -> Self {
        ClassTally {
            count: vec![0; grid.bins() + 1],
            sq: vec![0; grid.bins() + 1],
            cross: vec![0; grid.bins() + 1],
            sum_u_q: 0,
            sum_v2_q: 0,
            sq_u_q: 0,
            cross_u_q: 0,
            sq_v2_q: 0,
            cross_v2_q: 0,
        }
    }

    fn merge(&mut self, o: &Self) {
        for (a, b) in self.count.iter_mut().zip(&o.count) {
            *a += b;
        }
        for (a, b) in self.sq.iter_mut().zip(&o.sq) {
            *a += b;
        }
        for (a, b) in self.cross.iter_mut().zip(&o.cross) {
            *a += b;
        }
        self.sum_u_q += o.sum_u_q;
        self.sum_v2_q += o.sum_v2_q;
        self.sq_u_q = self.sq_u_q.saturating_add(o.sq_u_q);
        self.cross_u_q = self.cross_u_q.saturating_add(o.cross_u_q);
        self.sq_v2_q = self.sq_v2_q.saturating_add(o.sq_v2_q);
        self.cross_v2_q = self.cross_v2_q.saturating_add(o.cross_v2_q);
    }

    /// Adds one path of weight `w` whose vertices of this class fall in
    /// `bins` (sorted; all of the path's vertices of this class, overflow
    /// included).
    fn add_path(&mut self, bins: &[usize], w: u128) {
        let n = bins.len() as u128;
        let w2 = w * w;
        let mut k = 0;
        while k < bins.len() {
            let b = bins[k];
            let run = bins[k..].iter().take_while(|&&x| x == b).count() as u128;
            self.count[b] += w * run;
            self.sq[b] += w2 * run * run;
            self.cross[b] += w2 * run * n;
            k += run as usize;
        }
    }

    fn add_moment(&mut self, u: f64, v: f64, w: u128) {
        self.sum_u_q += w as i128 * (u * MOMENT_Q).round() as i128;
        self.sum_v2_q += w * (v * v * MOMENT_Q).round() as u128;
    }

    /// Adds one path's sums for the moments' errors: `su` = Σu and `sv` =
    /// Σv² over its `n` vertices of this class, weight `w`.
    fn add_path_moments(&mut self, su: f64, sv: f64, n: u128, w: u128) {
        let w2 = w.saturating_mul(w);
        let su = (su * MOMENT_Q).round() as i128;
        let sv = (sv * MOMENT_Q).round() as u128;
        let w2s = i128::try_from(w2).unwrap_or(i128::MAX);
        self.sq_u_q = self
            .sq_u_q
            .saturating_add(w2.saturating_mul(su.unsigned_abs().saturating_pow(2)));
        self.cross_u_q = self
            .cross_u_q
            .saturating_add(w2s.saturating_mul(su).saturating_mul(n as i128));
        self.sq_v2_q = self
            .sq_v2_q
            .saturating_add(w2.saturating_mul(sv.saturating_pow(2)));
        self.cross_v2_q = self
            .cross_v2_q
            .saturating_add(w2.saturating_mul(sv).saturating_mul(n));
    }

    /// Weighted vertices tallied (overflow included): Σ w·n_c.
    pub fn vertices(&self) -> u128 {
        self.count.iter().sum()
    }

    /// Mean u and mean v² over the tallied vertices (0 if none).
    pub fn means(&self) -> (f64, f64) {
        let nv = self.vertices().max(1) as f64;
        (
            self.sum_u_q as f64 / MOMENT_Q / nv,
            self.sum_v2_q as f64 / MOMENT_Q / nv,
        )
    }

    /// Standard errors of [`Self::means`], `None` where the document has no
    /// sums for them. Each mean is a ratio R = Σw·S/Σw·n_c over the paths
    /// (S the path's Σu or Σv²); to first order (the delta method, as for
    /// the bins) Var(R) ≈ Σw²(S − R·n_c)²/(Σw·n_c)², expanded in the
    /// tallied sums. `total_sq` is Σw²·n_c².
    pub fn moment_errors(&self, total_sq: f64) -> Option<[f64; 2]> {
        if self.sq_v2_q == 0 {
            return None;
        }
        let nv = (self.vertices() as f64).max(f64::MIN_POSITIVE);
        let (mu, mv) = self.means();
        let q = MOMENT_Q;
        let se = |sq: f64, cross: f64, r: f64| {
            let ez2 = sq / (q * q) - 2.0 * r * cross / q + r * r * total_sq;
            ez2.max(0.0).sqrt() / nv
        };
        Some([
            se(self.sq_u_q as f64, self.cross_u_q as f64, mu),
            se(self.sq_v2_q as f64, self.cross_v2_q as f64, mv),
        ])
    }
}

/// One (albedo, distance) cell.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CellTally {
    /// Contributing paths.
    pub paths: u64,
    /// Σ w and Σ w² of their weights (both equal `paths` for analog paths).
    pub weight: u128,
    pub weight_sq: u128,
    /// Σ w·n and Σ w²·n² of the paths' scattering counts.
    pub events: u128,
    pub events_sq: u128,
    /// all, first, last.
    pub classes: [ClassTally; 3],
}

impl CellTally {
    fn new(grid: &PairGrid) -> Self {
        CellTally {
            paths: 0,
            weight: 0,
            weight_sq: 0,
            events: 0,
            events_sq: 0,
            classes: VertexClass::ALL.map(|class| ClassTally::new(&grid.for_class(class))),
        }
    }

    /// Sums the first- and last-vertex histograms, tallied on `grid`, onto
    /// a grid `refine` times finer than the all-vertex one (a divisor of
    /// `grid.vertex_refine`). Exact: a path has one vertex of each of these
    /// classes, so no path counts in two merged bins, and the squared and
    /// cross sums add as the counts do.
    pub fn coarsen_vertices(&mut self, grid: &PairGrid, refine: usize) -> Result<()> {
        if refine == 0 || !grid.vertex_refine.is_multiple_of(refine) {
            return Err(Error::param(
                "vertex_refine",
                format!("{refine} (the tally's is {})", grid.vertex_refine),
                "a divisor of the tally's vertex_refine",
            ));
        }
        let f = grid.vertex_refine / refine;
        let fine = grid.for_class(VertexClass::Last);
        let to = PairGrid {
            vertex_refine: refine,
            ..*grid
        }
        .for_class(VertexClass::Last);
        let sum = |v: &[u128]| {
            let mut out = vec![0; to.bins() + 1];
            for (b, x) in v.iter().enumerate() {
                let k = if b == fine.bins() {
                    to.bins()
                } else {
                    (b / fine.nv / f) * to.nv + (b % fine.nv) / f
                };
                out[k] += x;
            }
            out
        };
        for class in [VertexClass::First, VertexClass::Last] {
            let t = &mut self.classes[class.slot()];
            (t.count, t.sq, t.cross) = (sum(&t.count), sum(&t.sq), sum(&t.cross));
        }
        Ok(())
    }

    /// Kish's effective number of paths (Σw)²/Σw²: the analog paths that
    /// would give the same precision (`paths` for an analog walk).
    pub fn effective_paths(&self) -> f64 {
        if self.weight_sq == 0 {
            return 0.0;
        }
        let w = self.weight as f64;
        w * w / self.weight_sq as f64
    }
}

impl CellTally {
    /// Adds one contributing path of weight `w` (1 for an analog walk) from
    /// x_i = 0 to `exit` with scattering vertices `vertices` (at least one),
    /// in its own pair frame with normalisation length `lambda`. `bins` is
    /// scratch space.
    pub fn add_path(
        &mut self,
        grid: &PairGrid,
        exit: [f64; 2],
        lambda: f64,
        vertices: &[[f64; 2]],
        w: u64,
        bins: &mut Vec<usize>,
    ) {
        let w = w as u128;
        let n = vertices.len() as u128;
        self.paths += 1;
        self.weight += w;
        self.weight_sq += w * w;
        self.events += w * n;
        self.events_sq += w * w * n * n;
        let d = exit[0].hypot(exit[1]);
        let (ex, ey) = (exit[0] / d, exit[1] / d);
        let frame = |p: [f64; 2]| {
            let t = p[0] * ex + p[1] * ey;
            let s = -p[0] * ey + p[1] * ex;
            ((t - 0.5 * d) / lambda, s.abs() / lambda)
        };
        bins.clear();
        let all = grid.for_class(VertexClass::All);
        let (mut su, mut sv) = (0.0, 0.0);
        for p in vertices {
            let (u, v) = frame(*p);
            bins.push(all.index(u, v));
            self.classes[VertexClass::All.slot()].add_moment(u, v, w);
            su += u;
            sv += v * v;
        }
        bins.sort_unstable();
        let c = &mut self.classes[VertexClass::All.slot()];
        c.add_path(bins, w);
        c.add_path_moments(su, sv, n, w);
        for (class, p) in [
            (VertexClass::First, vertices[0]),
            (VertexClass::Last, vertices[vertices.len() - 1]),
        ] {
            let (u, v) = frame(p);
            let c = &mut self.classes[class.slot()];
            c.add_path(&[grid.for_class(class).index(u, v)], w);
            c.add_moment(u, v, w);
            c.add_path_moments(u, v * v, 1, w);
        }
    }

    /// Adds another cell's counts.
    pub fn merge(&mut self, b: &CellTally) {
        self.paths += b.paths;
        self.weight += b.weight;
        self.weight_sq += b.weight_sq;
        self.events += b.events;
        self.events_sq += b.events_sq;
        for (ca, cb) in self.classes.iter_mut().zip(&b.classes) {
            ca.merge(cb);
        }
    }

    /// The normalised histogram of one class (see [`KernelDoc::histogram`]).
    pub fn normalized(
        &self,
        grid: &PairGrid,
        class: VertexClass,
        albedo: f64,
        d: f64,
        lambda: f64,
    ) -> NormalizedHistogram {
        let grid = &grid.for_class(class);
        let cl = &self.classes[class.slot()];
        // Σw, Σw·n_c, Σw²·n_c² (Σw² for first and last, n_c = 1).
        let n = (self.weight as f64).max(f64::MIN_POSITIVE);
        let total = cl.vertices() as f64;
        let mean_vertices = total / n;
        let total_sq = match class {
            VertexClass::All => self.events_sq,
            VertexClass::First | VertexClass::Last => self.weight_sq,
        } as f64;
        let n_eff = self.effective_paths().max(1.0);
        let norm = mean_vertices.max(f64::MIN_POSITIVE);
        // (mass, its standard error, the fit weight's error) of bin b.
        let stat = |b: usize| {
            let (count, sq, cross) = (cl.count[b] as f64, cl.sq[b] as f64, cl.cross[b] as f64);
            let m = count / total.max(f64::MIN_POSITIVE);
            // The ratio estimator m = Σw·n_b/Σw·n_c to first order (the delta
            // method): Var(m) ≈ Σw²(n_b − m·n_c)²/(Σw·n_c)², from the sums of
            // z = n_b − m·n_c, whose weighted mean is 0 at this m.
            let ez2 = sq - 2.0 * m * cross + m * m * total_sq;
            // The bin's weighted mean count n̄_b = Σw·n_b/Σw, its variance
            // ≈ Σw²(n_b − n̄_b)²/(Σw)², with Σw²·n_b taken as n̄_b·Σw² (exact
            // for analog paths).
            let mean_count = count / n;
            let count_var = (sq / self.weight_sq.max(1) as f64 - mean_count * mean_count).max(0.0);
            (
                m,
                ez2.max(0.0).sqrt() / total.max(f64::MIN_POSITIVE),
                (count_var / n_eff).sqrt() / norm,
            )
        };
        let bins = grid.bins();
        let (mut mass, mut sigma, mut count_sigma) = (vec![], vec![], vec![]);
        for (m, s, c) in (0..bins).map(stat) {
            mass.push(m);
            sigma.push(s);
            count_sigma.push(c);
        }
        let (overflow, overflow_sigma, overflow_count_sigma) = stat(bins);
        let (mean_u, mean_v2) = cl.means();
        let moment_errors = cl.moment_errors(total_sq);
        NormalizedHistogram {
            albedo,
            d,
            lambda,
            class,
            u_edges: grid.u_edges(),
            v_edges: grid.v_edges(),
            mass,
            sigma,
            count_sigma,
            overflow,
            overflow_sigma,
            overflow_count_sigma,
            paths: self.paths,
            effective_paths: self.effective_paths(),
            mean_vertices,
            mean_u,
            mean_v2,
            moment_errors,
        }
    }
}

/// The tally of a kernel simulation: `cells[albedo][distance]`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct KernelTally {
    /// Launched paths (each walked once per albedo).
    pub paths: u64,
    pub cells: Vec<Vec<CellTally>>,
}

impl KernelTally {
    pub fn new(config: &KernelConfig) -> Self {
        KernelTally {
            paths: 0,
            cells: config
                .albedos
                .iter()
                .map(|_| {
                    config
                        .distances
                        .iter()
                        .map(|_| CellTally::new(&config.grid))
                        .collect()
                })
                .collect(),
        }
    }
}

impl Tally for KernelTally {
    fn merge(&mut self, other: &Self) {
        self.paths += other.paths;
        for (ra, rb) in self.cells.iter_mut().zip(&other.cells) {
            for (a, b) in ra.iter_mut().zip(rb) {
                a.merge(b);
            }
        }
    }
}

/// Everything that determines a kernel simulation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KernelConfig {
    pub g: f64,
    pub eta: f64,
    /// ρ: σ_t = ρ (homogeneous).
    pub density: f64,
    pub albedos: Vec<f64>,
    /// Nominal pair distances d (MFP); a path contributes to d if
    /// |x_e| ∈ [d(1 − w), d(1 + w)].
    pub distances: Vec<f64>,
    /// w.
    pub rel_width: f64,
    /// Minimum number of scattering vertices of a contributing path.
    pub min_order: u32,
    pub paths: u64,
    pub seed: u64,
    pub max_events: u32,
    pub grid: PairGrid,
    /// A planned simulation ([`KernelConfig::plan`]): the runs that fill the
    /// cells, each at one albedo with its own flight sampling and path count
    /// (`paths` is then their sum). Empty: every albedo is walked by the same
    /// `paths` analog paths.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub runs: Vec<KernelRun>,
}

/// One run of a planned kernel simulation: `paths` paths walked at albedo
/// `albedo` (an index into [`KernelConfig::albedos`]) with flights drawn as
/// `flights` says ([`walk_transformed`]), feeding the distance cells `distances`
/// (indices into [`KernelConfig::distances`]). The runs that feed one cell
/// share flights and unit: the plan's and its top-ups'. A run whose cells a
/// top-up moved to another sampling ([`PlanOptions::replan`]) feeds none.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KernelRun {
    pub albedo: usize,
    pub distances: Vec<usize>,
    pub flights: Flights,
    /// Weights are integers in units of 2^−unit_log2: a path of likelihood
    /// ratio r gets ⌊r·2^unit_log2 + u⌋ with u uniform (unbiased stochastic
    /// rounding; a path rounded to 0 is dropped — Russian roulette on tiny
    /// ratios), at most [`MAX_WEIGHT`].
    pub unit_log2: u32,
    pub paths: u64,
}

/// Largest integer weight of a path (2⁴⁰): keeps every Σw²n² of a cell far
/// inside u128. A path whose weight would exceed it is counted at it (a
/// ratio 2^(40 − unit_log2); the plan puts the typical weight at 2²⁰).
pub const MAX_WEIGHT: u64 = 1 << 40;
/// Typical integer weight of a contributing path in a transformed run (2²⁰):
/// rounding adds a relative variance of ≈ 2⁻⁴².
const TYPICAL_WEIGHT_LOG2: f64 = 20.0;

impl KernelRun {
    /// The stream seed of run `r` under master seed `seed` (distinct from
    /// the unplanned stream of every path and from every other run).
    fn seed(seed: u64, r: usize) -> u64 {
        splitmix64(seed ^ splitmix64(!(r as u64)))
    }
}

/// Settings of [`KernelConfig::plan`].
#[derive(Clone, Debug, PartialEq)]
pub struct PlanOptions {
    /// Effective contributing paths wanted in every cell.
    pub target: f64,
    /// Most paths of one run.
    pub max_paths: u64,
    /// Pilot paths per (albedo, flight sampling), before growing.
    pub pilot: u64,
    /// The flight samplings to choose from (those whose weights are
    /// unbounded at an albedo, [`Flights::bounded_weights`], are left out
    /// there).
    pub flights: Vec<Flights>,
    /// Also, at each albedo, exponential transforms (first two collisions
    /// forced) with biases at these fractions of [`max_bias`]: the
    /// strongest bias that the albedo allows follows its asymptotic decay
    /// rate, which a fixed list cannot.
    pub bias_fractions: Vec<f64>,
    /// Also, at each albedo, flights stretched by c = 1 + q·√(1 − α) for
    /// each fraction q here (c·σ_t, shorter flights that keep paths near
    /// x_i), with and without two forced collisions: the largest stretch
    /// whose weights stay bounded, [`max_stretch_offset`], shrinks as the
    /// albedo rises.
    pub stretch_fractions: Vec<f64>,
    /// Also, at each albedo, exponential transforms with angular biasing
    /// ([`Flights::angular`]) at these fractions of [`max_bias`]: near 1,
    /// their weights stay near-constant over long paths, which fills the
    /// far cells of mid albedo that the transform alone leaves heavy-tailed.
    pub angular_fractions: Vec<f64>,
    /// In a top-up round ([`KernelConfig::top_up`]), move a cell that fell
    /// short, because its sampling delivered far less than its pilot
    /// promised, to another of these samplings ([`REPLAN_GAIN`]): a pilot
    /// misjudges heavy-tailed weights, and the run's numbers show it.
    pub replan: bool,
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            target: 4000.0,
            max_paths: 2_000_000_000,
            pilot: 1 << 16,
            flights: [
                (1.0, 0.0, 0),
                (1.0, 0.5, 0),
                (1.0, 0.8, 0),
                (1.0, 0.0, 2),
                (1.0, 0.8, 2),
                (1.0, 0.93, 2),
            ]
            .map(|(stretch, bias, forced)| Flights {
                stretch,
                bias,
                forced,
                angular: false,
            })
            .to_vec(),
            bias_fractions: vec![0.6, 0.85],
            stretch_fractions: vec![0.6, 0.85],
            angular_fractions: Vec::new(),
            replan: false,
        }
    }
}

/// What the pilots measured for one cell of a plan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlannedCell {
    pub albedo: f64,
    pub d: f64,
    /// The flight sampling of the run that feeds it.
    pub flights: Flights,
    /// Pilot paths with that sampling, and how many contributed here.
    pub pilot_paths: u64,
    pub pilot_contributing: u64,
    /// Effective contributing paths the run should give it.
    pub expected: f64,
}

/// The paths of a run whose cells give `per_path` effective paths per path
/// launched: enough for the neediest to reach `opts.target`, at most
/// `opts.max_paths`, in whole chunks (at least one).
fn run_paths(per_path: impl Iterator<Item = f64>, opts: &PlanOptions) -> u64 {
    let need = per_path
        .map(|r| {
            if r > 0.0 {
                opts.target / r
            } else {
                f64::INFINITY
            }
        })
        .fold(0.0, f64::max);
    whole_chunks(need, opts.max_paths)
}

/// `need` paths rounded up to whole chunks, at most `max_paths` (rounded
/// up too) and at least one chunk.
fn whole_chunks(need: f64, max_paths: u64) -> u64 {
    let chunk = runner::CHUNK_PATHS;
    (need.ceil().min(max_paths as f64) as u64)
        .div_ceil(chunk)
        .max(1)
        * chunk
}

/// A top-up with [`PlanOptions::replan`] moves a short cell whose runs
/// delivered less than 1/this of what their sampling's pilot promised (in
/// effective paths per unit of work) to another sampling whose pilot
/// promises this many times what the runs delivered.
pub const REPLAN_GAIN: f64 = 2.0;

/// A pilot cell needs this many contributing paths before its rate counts.
const PILOT_MIN_PATHS: u64 = 30;
/// Stream family of the pilots (`"pilot"`).
const PILOT_SEED: u64 = 0x70_69_6c_6f_74;

/// What one pilot walk measured.
struct Pilot {
    /// Scatterings walked plus one per launch.
    work: f64,
    count: Vec<u64>,
    sum: Vec<f64>,
    sum_sq: Vec<f64>,
    weights: Vec<Vec<f64>>,
}

impl Pilot {
    fn new(nd: usize) -> Self {
        Pilot {
            work: 0.0,
            count: vec![0; nd],
            sum: vec![0.0; nd],
            sum_sq: vec![0.0; nd],
            weights: vec![Vec::new(); nd],
        }
    }

    /// Effective paths of cell `id`.
    fn ess(&self, id: usize) -> f64 {
        if self.sum_sq[id] > 0.0 {
            self.sum[id] * self.sum[id] / self.sum_sq[id]
        } else {
            0.0
        }
    }

    /// Effective paths of cell `id` per unit of work (0 where the pilot saw
    /// fewer than [`PILOT_MIN_PATHS`] there).
    fn rate(&self, id: usize) -> f64 {
        if self.count[id] < PILOT_MIN_PATHS {
            0.0
        } else {
            self.ess(id) / self.work
        }
    }

    /// The weight unit of a run with flights `f` over the cells `ids`: the
    /// median contributing weight at 2^[`TYPICAL_WEIGHT_LOG2`].
    fn unit_log2(&self, f: Flights, ids: &[usize]) -> u32 {
        if f == Flights::ANALOG {
            0
        } else {
            let m = self.median_weight(ids);
            (TYPICAL_WEIGHT_LOG2 - m.log2()).round().clamp(0.0, 60.0) as u32
        }
    }

    /// The median contributing weight over the cells `ids` (1 if none).
    fn median_weight(&self, ids: &[usize]) -> f64 {
        let mut w: Vec<f64> = ids
            .iter()
            .flat_map(|&id| self.weights[id].iter().copied())
            .collect();
        if w.is_empty() {
            return 1.0;
        }
        w.sort_by(f64::total_cmp);
        w[w.len() / 2]
    }
}

impl KernelConfig {
    /// Chunks of the whole simulation ([`runner::CHUNK_PATHS`] paths each;
    /// with a plan, each run starts a chunk of its own).
    pub fn chunks(&self) -> u64 {
        if self.runs.is_empty() {
            self.paths.div_ceil(runner::CHUNK_PATHS)
        } else {
            self.runs
                .iter()
                .map(|r| r.paths.div_ceil(runner::CHUNK_PATHS))
                .sum()
        }
    }

    /// The first run of the plan that feeds cell (`ia`, `id`), if any;
    /// without a plan the analog walk of every cell (`None`).
    pub fn run_of(&self, ia: usize, id: usize) -> Option<&KernelRun> {
        self.runs
            .iter()
            .find(|r| r.albedo == ia && r.distances.contains(&id))
    }

    /// Paths launched for cell (`ia`, `id`): all of them without a plan, its
    /// runs' with one (0 for a cell no run feeds).
    pub fn launched_for(&self, ia: usize, id: usize) -> u64 {
        if self.runs.is_empty() {
            self.paths
        } else {
            self.runs
                .iter()
                .filter(|r| r.albedo == ia && r.distances.contains(&id))
                .map(|r| r.paths)
                .sum()
        }
    }

    /// The plan grown where `tally` (of this configuration) fell short of
    /// `opts.target` effective paths (by more than 10 %). Each short cell is
    /// topped up by a new run (own streams, same flights and unit as the
    /// cell's first run, one per run) with the paths that bring the neediest
    /// of its cells to the target at the rate seen so far, at most
    /// `opts.max_paths` (and at least one chunk). Pilots misjudge
    /// heavy-tailed weights; this corrects with the real run's numbers.
    ///
    /// With `opts.replan`, the albedos of the short cells are piloted again
    /// ([`KernelConfig::plan`]'s candidates and streams). A short cell whose
    /// runs delivered less than 1/[`REPLAN_GAIN`] of the effective paths per
    /// unit of work that their own sampling's pilot promised (their work per
    /// path taken from that pilot), or whose pilot saw too few paths there
    /// to promise anything, moves to the best other candidate, if its
    /// pilot promises [`REPLAN_GAIN`] times what the runs delivered: its old
    /// runs stop feeding it (a run left with no cell walks no path), its
    /// tally is emptied, and a new run sized by that pilot fills it. So
    /// `tally` becomes the grown configuration's tally over the chunks
    /// already run, and merging the new runs' chunks gives, bitwise, the
    /// grown configuration run at once.
    ///
    /// `None` if every cell has its paths or none can get more.
    pub fn top_up(
        &self,
        tally: &mut KernelTally,
        opts: &PlanOptions,
    ) -> Result<Option<KernelConfig>> {
        let short = |ia: usize, id: usize| {
            self.run_of(ia, id).is_some()
                && tally.cells[ia][id].effective_paths() < 0.9 * opts.target
        };
        if opts.max_paths < runner::CHUNK_PATHS {
            return Ok(None);
        }
        let mut runs = self.runs.clone();
        let mut extra = Vec::new();
        let mut moved = Vec::new();
        if opts.replan {
            for ia in 0..self.albedos.len() {
                let ids: Vec<usize> = (0..self.distances.len())
                    .filter(|&id| short(ia, id))
                    .collect();
                if ids.is_empty() {
                    continue;
                }
                let cands = self.candidates(ia, opts)?;
                let (pilot, stats) = self.pilots(ia, &cands, opts);
                // Each cell to the candidate that beats its runs by the gain.
                let mut to: Vec<(usize, usize)> = Vec::new();
                for &id in &ids {
                    let own = self.run_of(ia, id).expect("short cells have a run").flights;
                    let Some(k) = cands.iter().position(|c| c.1 == own) else {
                        continue;
                    };
                    let work = self.launched_for(ia, id) as f64 * stats[k].work / pilot as f64;
                    let delivered = tally.cells[ia][id].effective_paths() / work;
                    // Only a sampling that fell short of its own pilot's promise
                    // by the gain moves (or one whose pilot saw too few paths
                    // here to promise anything): one that delivers about what
                    // its pilot said is merely slow, and the others' pilots may
                    // overrate them just as much.
                    let promised = stats[k].rate(id);
                    if promised > 0.0 && promised <= REPLAN_GAIN * delivered {
                        continue;
                    }
                    let best = (0..stats.len())
                        .filter(|&j| j != k)
                        .max_by(|&a, &b| stats[a].rate(id).total_cmp(&stats[b].rate(id)));
                    if let Some(j) = best.filter(|&j| stats[j].rate(id) > REPLAN_GAIN * delivered) {
                        to.push((id, j));
                    }
                }
                for (j, stat) in stats.iter().enumerate() {
                    let ids: Vec<usize> = to.iter().filter(|t| t.1 == j).map(|t| t.0).collect();
                    if ids.is_empty() {
                        continue;
                    }
                    let f = cands[j].1;
                    extra.push(KernelRun {
                        albedo: ia,
                        distances: ids.clone(),
                        flights: f,
                        unit_log2: stat.unit_log2(f, &ids),
                        paths: run_paths(ids.iter().map(|&id| stat.ess(id) / pilot as f64), opts),
                    });
                    moved.extend(ids.into_iter().map(|id| (ia, id)));
                }
            }
        }
        for r in &self.runs {
            let ids: Vec<usize> = r
                .distances
                .iter()
                .copied()
                .filter(|&id| {
                    // Each cell topped up by its first run only.
                    self.run_of(r.albedo, id) == Some(r)
                        && short(r.albedo, id)
                        && !moved.contains(&(r.albedo, id))
                })
                .collect();
            if ids.is_empty() {
                continue;
            }
            // The paths that bring the neediest to the target at its rate.
            let need = ids
                .iter()
                .map(|&id| {
                    let ess = tally.cells[r.albedo][id].effective_paths();
                    let launched = self.launched_for(r.albedo, id) as f64;
                    if ess > 0.0 {
                        (opts.target / ess - 1.0) * launched
                    } else {
                        f64::INFINITY
                    }
                })
                .fold(0.0, f64::max);
            extra.push(KernelRun {
                distances: ids,
                paths: whole_chunks(need, opts.max_paths),
                ..r.clone()
            });
        }
        if extra.is_empty() {
            return Ok(None);
        }
        for &(ia, id) in &moved {
            for r in runs.iter_mut().filter(|r| r.albedo == ia) {
                r.distances.retain(|&x| x != id);
            }
            tally.cells[ia][id] = CellTally::new(&self.grid);
        }
        runs.extend(extra);
        let grown = KernelConfig {
            paths: runs.iter().map(|r| r.paths).sum(),
            runs,
            ..self.clone()
        };
        grown.validate()?;
        Ok(Some(grown))
    }

    /// The medium at albedo `alpha` (validated).
    pub fn medium(&self, alpha: f64) -> Result<Medium> {
        Medium::new(alpha, self.g, self.eta, self.density, None)
    }

    pub fn validate(&self) -> Result<()> {
        if self.albedos.is_empty() {
            return Err(Error::param("albedos", "(none)", "at least one albedo"));
        }
        for a in &self.albedos {
            // An albedo out of range is one of `albedos`.
            self.medium(*a).map_err(|e| match e {
                Error::Param {
                    name: "albedo",
                    value,
                    allowed,
                } => Error::Param {
                    name: "albedos",
                    value,
                    allowed,
                },
                e => e,
            })?;
        }
        if self.distances.is_empty() {
            return Err(Error::param("distances", "(none)", "at least one distance"));
        }
        if !(self.rel_width > 0.0 && self.rel_width < 1.0) {
            return Err(Error::param("rel_width", self.rel_width, "in (0, 1)"));
        }
        let mut d = self.distances.clone();
        if d.iter().any(|x| !(*x > 0.0 && x.is_finite())) {
            return Err(Error::param(
                "distances",
                list(&self.distances),
                "finite and > 0",
            ));
        }
        d.sort_by(f64::total_cmp);
        if d.windows(2)
            .any(|p| p[0] * (1.0 + self.rel_width) > p[1] * (1.0 - self.rel_width))
        {
            return Err(Error::param(
                "distances",
                list(&self.distances),
                "bins d(1 ± rel_width) that do not overlap",
            ));
        }
        if self.paths == 0 {
            return Err(Error::param("paths", 0, ">= 1"));
        }
        if self.max_events == 0 {
            return Err(Error::param("max_events", 0, ">= 1"));
        }
        if !self.runs.is_empty() {
            self.validate_runs()?;
        }
        let g = &self.grid;
        if g.nu == 0
            || g.nv == 0
            || g.extent.is_nan()
            || g.extent <= 0.0
            || !(1..=8).contains(&g.vertex_refine)
        {
            return Err(Error::param(
                "grid",
                format!(
                    "nu {}, nv {}, extent {}, vertex_refine {}",
                    g.nu, g.nv, g.extent, g.vertex_refine
                ),
                "nu, nv >= 1, extent > 0, vertex_refine in 1..=8",
            ));
        }
        if let Some(t) = g.tail
            && (t.bins == 0 || t.bins > 64 || !t.extent.is_finite() || t.extent <= g.extent)
        {
            return Err(Error::param(
                "grid.tail",
                format!("bins {}, extent {}", t.bins, t.extent),
                "bins in 1..=64 and a finite far edge beyond the core's extent",
            ));
        }
        Ok(())
    }

    fn validate_runs(&self) -> Result<()> {
        let mut fed = vec![vec![None; self.distances.len()]; self.albedos.len()];
        for r in &self.runs {
            // A run may feed no cell: a top-up moved its cells away.
            let cells_ok = r.albedo < self.albedos.len()
                && r.distances.iter().all(|&id| {
                    id < self.distances.len()
                        && *fed[r.albedo][id].get_or_insert((r.flights, r.unit_log2))
                            == (r.flights, r.unit_log2)
                });
            if !cells_ok {
                return Err(Error::param(
                    "runs",
                    format!("albedo {} distances {:?}", r.albedo, r.distances),
                    "indices into albedos and distances; the runs of a cell share flights and unit",
                ));
            }
            check_flights(&r.flights, "runs.flights")?;
            if r.unit_log2 > 60 {
                return Err(Error::param("runs.unit_log2", r.unit_log2, "<= 60"));
            }
            if r.paths == 0 {
                return Err(Error::param("runs.paths", 0, ">= 1"));
            }
        }
        let total: u64 = self.runs.iter().map(|r| r.paths).sum();
        if total != self.paths {
            return Err(Error::param(
                "paths",
                format!("{} (the runs sum to {total})", self.paths),
                "the sum of the runs' paths",
            ));
        }
        Ok(())
    }

    /// The distance bin of an exit at radius r, if any.
    fn distance_bin(&self, r: f64) -> Option<usize> {
        let w = self.rel_width;
        self.distances
            .iter()
            .position(|d| r >= d * (1.0 - w) && r <= d * (1.0 + w))
    }

    /// Simulates chunk `c`.
    pub fn simulate_chunk(&self, c: u64) -> KernelTally {
        if !self.runs.is_empty() {
            return self.simulate_run_chunk(c);
        }
        let (first, count) = chunk_paths(self.paths, c);
        let mut tally = KernelTally::new(self);
        let mfp = 1.0 / self.density;
        let media: Vec<(Medium, UniformAlbedo)> = self
            .albedos
            .iter()
            .map(|a| {
                let m = self.medium(*a).expect("validated");
                (m, UniformAlbedo(threshold_u32(*a)))
            })
            .collect();
        let mut vertices: Vec<[f64; 2]> = Vec::new();
        let mut bins: Vec<usize> = Vec::new();
        for path in first..first + count {
            tally.paths += 1;
            let mut base = PathRng::new(self.seed, path);
            let Some(start) = launch(&Source::Pencil, self.eta, &mut base) else {
                continue;
            };
            for (ia, (medium, albedo)) in media.iter().enumerate() {
                let mut rng = base;
                let walk = (medium, albedo, &FlightSampler::ANALOG, start);
                let Some((exit, id, _)) =
                    self.counted_walk(walk, &mut rng, &mut vertices, |_| true)
                else {
                    continue;
                };
                let scale = PairGrid::scale(exit[0].hypot(exit[1]), mfp);
                tally.cells[ia][id].add_path(&self.grid, exit, scale, &vertices, 1, &mut bins);
            }
        }
        tally
    }

    /// Chunk `c` of a planned simulation: the run it falls in, from the
    /// run's own streams.
    fn simulate_run_chunk(&self, c: u64) -> KernelTally {
        let mut tally = KernelTally::new(self);
        let mut offset = 0;
        let Some((r, run)) = self.runs.iter().enumerate().find(|(_, run)| {
            let n = run.paths.div_ceil(runner::CHUNK_PATHS);
            offset += n;
            c < offset
        }) else {
            return tally;
        };
        let local = c - (offset - run.paths.div_ceil(runner::CHUNK_PATHS));
        let (first, count) = chunk_paths(run.paths, local);
        if run.distances.is_empty() {
            // Its cells moved to another sampling: its paths would feed none.
            tally.paths += count;
            return tally;
        }
        let medium = self.medium(self.albedos[run.albedo]).expect("validated");
        let albedo = UniformAlbedo(threshold_u32(self.albedos[run.albedo]));
        let mut feeds = vec![false; self.distances.len()];
        for &id in &run.distances {
            feeds[id] = true;
        }
        let scale = (run.unit_log2 as f64).exp2();
        let sampler = FlightSampler::new(run.flights, self.g);
        let seed = KernelRun::seed(self.seed, r);
        let mfp = 1.0 / self.density;
        let mut vertices: Vec<[f64; 2]> = Vec::new();
        let mut bins: Vec<usize> = Vec::new();
        for path in first..first + count {
            tally.paths += 1;
            let mut rng = PathRng::new(seed, path);
            let Some(start) = launch(&Source::Pencil, self.eta, &mut rng) else {
                continue;
            };
            let walk = (&medium, &albedo, &sampler, start);
            let Some((exit, id, log_ratio)) =
                self.counted_walk(walk, &mut rng, &mut vertices, |id| feeds[id])
            else {
                continue;
            };
            let w = if run.flights == Flights::ANALOG {
                scale as u64
            } else {
                let ratio = log_ratio.exp();
                let u = unit_f64(rng.next_u32());
                (ratio * scale + u).floor().min(MAX_WEIGHT as f64) as u64
            };
            if w == 0 {
                continue;
            }
            let scale = PairGrid::scale(exit[0].hypot(exit[1]), mfp);
            tally.cells[run.albedo][id].add_path(&self.grid, exit, scale, &vertices, w, &mut bins);
        }
        tally
    }

    /// Walks one path (`walk`: medium, albedo, flights, entry state) with its
    /// scattering vertices into `vertices`. It counts if it exits into a
    /// distance bin that `feeds` admits after at least `min_order`
    /// scatterings: then its exit point, distance bin and ln of its
    /// likelihood ratio ([`walk_transformed`]).
    fn counted_walk(
        &self,
        (medium, albedo, sampler, start): (&Medium, &UniformAlbedo, &FlightSampler, Launched),
        rng: &mut PathRng,
        vertices: &mut Vec<[f64; 2]>,
        feeds: impl Fn(usize) -> bool,
    ) -> Option<([f64; 2], usize, f64)> {
        vertices.clear();
        let (fate, n, log_ratio) = walk_transformed(
            medium,
            albedo,
            self.max_events,
            sampler,
            start,
            rng,
            |v, _| vertices.push([v[0], v[1]]),
        );
        let Fate::Exit { x, y } = fate else {
            return None;
        };
        let id = self.distance_bin(x.hypot(y)).filter(|&id| feeds(id))?;
        (n >= self.min_order).then_some(([x, y], id, log_ratio))
    }

    /// Plans the simulation so that every cell gets at least `opts.target`
    /// effective contributing paths where `opts.max_paths` allows: for each
    /// albedo, short pilot walks with every flight sampling of `opts.flights`
    /// measure each cell's effective paths per unit of work (scatterings
    /// walked plus one per launch); each cell goes to the sampling that fills
    /// it cheapest, and each (albedo, sampling) becomes a run with the paths its neediest
    /// cell asks for (rounded up to whole chunks, at most `max_paths`). A
    /// pilot that sees too few paths in a cell is repeated with 8× and then
    /// 64× the paths. Deterministic: the pilots have streams of their own.
    /// Returns the planned configuration and what the pilots measured.
    pub fn plan(
        &self,
        opts: &PlanOptions,
        progress: bool,
    ) -> Result<(KernelConfig, Vec<PlannedCell>)> {
        let base = KernelConfig {
            runs: Vec::new(),
            ..self.clone()
        };
        base.validate()?;
        if opts.flights.is_empty() {
            return Err(Error::param(
                "flights",
                "(none)",
                "at least one flight sampling",
            ));
        }
        for f in &opts.flights {
            check_flights(f, "flights")?;
        }
        for (key, fractions) in [
            ("bias_fractions", &opts.bias_fractions),
            ("stretch_fractions", &opts.stretch_fractions),
            ("angular_fractions", &opts.angular_fractions),
        ] {
            if let Some(q) = fractions.iter().find(|q| !(**q > 0.0 && **q < 1.0)) {
                return Err(Error::param(key, q, "in (0, 1)"));
            }
        }
        let nd = self.distances.len();
        let bar =
            crate::progress::Task::new(progress, "planning", self.albedos.len() as u64, "albedos");
        let (mut runs, mut cells) = (Vec::new(), Vec::new());
        for ia in 0..self.albedos.len() {
            let cands = base.candidates(ia, opts)?;
            let (pilot, stats) = base.pilots(ia, &cands, opts);
            // Each cell to its cheapest sampling (the first of equals).
            let mut choice: Vec<(usize, f64)> = Vec::with_capacity(nd);
            for id in 0..nd {
                let best = (0..stats.len()).fold(0, |b, ic| {
                    if stats[ic].rate(id) > stats[b].rate(id) {
                        ic
                    } else {
                        b
                    }
                });
                let r = stats[best].rate(id);
                // Unreached everywhere: the sampling that saw the most paths.
                let ic = if r > 0.0 {
                    best
                } else {
                    (0..stats.len()).fold(0, |b, ic| {
                        if stats[ic].count[id] > stats[b].count[id] {
                            ic
                        } else {
                            b
                        }
                    })
                };
                let per_path = stats[ic].ess(id) / pilot as f64;
                choice.push((ic, per_path));
            }
            for (ic, pilot_ic) in stats.iter().enumerate() {
                let ids: Vec<usize> = (0..nd).filter(|&id| choice[id].0 == ic).collect();
                if ids.is_empty() {
                    continue;
                }
                let paths = run_paths(ids.iter().map(|&id| choice[id].1), opts);
                let f = cands[ic].1;
                let unit_log2 = pilot_ic.unit_log2(f, &ids);
                for &id in &ids {
                    cells.push(PlannedCell {
                        albedo: self.albedos[ia],
                        d: self.distances[id],
                        flights: f,
                        pilot_paths: pilot,
                        pilot_contributing: pilot_ic.count[id],
                        expected: choice[id].1 * paths as f64,
                    });
                }
                runs.push(KernelRun {
                    albedo: ia,
                    distances: ids,
                    flights: f,
                    unit_log2,
                    paths,
                });
            }
            bar.set(ia as u64 + 1);
        }
        bar.finish();
        let planned = KernelConfig {
            paths: runs.iter().map(|r| r.paths).sum(),
            runs,
            ..base
        };
        planned.validate()?;
        Ok((planned, cells))
    }

    /// The flight samplings a plan chooses from at albedo `ia`, each with its
    /// index among all candidates (its pilot stream family): the given
    /// samplings whose weights keep a bounded variance over long paths (a
    /// pilot cannot see an unbounded one, and would size its run on a
    /// variance estimate that does not converge), then the exponential
    /// transforms, the stretches and the angular biases at the given
    /// fractions of this albedo's bounds.
    fn candidates(&self, ia: usize, opts: &PlanOptions) -> Result<Vec<(usize, Flights)>> {
        let alpha = self.albedos[ia];
        let beta_max = max_bias(alpha, self.g);
        let c_max = max_stretch_offset(alpha);
        let stretched = opts.stretch_fractions.iter().flat_map(|&q| {
            [0, 2].map(|forced| Flights {
                stretch: 1.0 + q * c_max,
                bias: 0.0,
                forced,
                angular: false,
            })
        });
        let cands: Vec<(usize, Flights)> = opts
            .flights
            .iter()
            .copied()
            .chain(opts.bias_fractions.iter().map(|&q| Flights {
                stretch: 1.0,
                bias: q * beta_max,
                forced: 2,
                angular: false,
            }))
            .chain(stretched)
            .chain(opts.angular_fractions.iter().map(|&q| Flights {
                stretch: 1.0,
                bias: q * beta_max,
                forced: 0,
                angular: true,
            }))
            .enumerate()
            .filter(|(_, f)| f.bounded_weights(alpha, self.g))
            .collect();
        if cands.is_empty() {
            return Err(Error::param(
                "flights",
                format!("(none bounded at albedo {alpha})"),
                "a flight sampling within max_bias(albedo, g) and max_stretch_offset(albedo)",
            ));
        }
        Ok(cands)
    }

    /// The pilots of `cands` at albedo `ia`: `opts.pilot` paths each, 8× and
    /// then 64× that while some cell sees too few paths under every
    /// candidate. Returns the pilot paths per candidate and what each saw.
    fn pilots(
        &self,
        ia: usize,
        cands: &[(usize, Flights)],
        opts: &PlanOptions,
    ) -> (u64, Vec<Pilot>) {
        let nd = self.distances.len();
        let mut pilot = opts.pilot.max(1);
        loop {
            let stats: Vec<Pilot> = cands
                .iter()
                .map(|&(ic, f)| self.pilot(ia, ic, f, pilot))
                .collect();
            let thin = (0..nd).any(|id| stats.iter().all(|p| p.count[id] < PILOT_MIN_PATHS));
            if !thin || pilot >= opts.pilot.max(1) * 64 {
                return (pilot, stats);
            }
            pilot *= 8;
        }
    }

    /// `paths` pilot paths at albedo `ia` with flights `f` (stream family `ic`).
    fn pilot(&self, ia: usize, ic: usize, f: Flights, paths: u64) -> Pilot {
        use rayon::prelude::*;
        let nd = self.distances.len();
        let medium = self.medium(self.albedos[ia]).expect("validated");
        let albedo = UniformAlbedo(threshold_u32(self.albedos[ia]));
        let seed = KernelRun::seed(self.seed ^ PILOT_SEED, ia * 64 + ic);
        let chunks = paths.div_ceil(runner::CHUNK_PATHS);
        let sampler = FlightSampler::new(f, self.g);
        let parts: Vec<Pilot> = (0..chunks)
            .into_par_iter()
            .map(|k| {
                let (first, count) = chunk_paths(paths, k);
                let mut p = Pilot::new(nd);
                for path in first..first + count {
                    let mut rng = PathRng::new(seed, path);
                    p.work += 1.0;
                    let Some(start) = launch(&Source::Pencil, self.eta, &mut rng) else {
                        continue;
                    };
                    let (fate, n, log_ratio) = walk_transformed(
                        &medium,
                        &albedo,
                        self.max_events,
                        &sampler,
                        start,
                        &mut rng,
                        |_, _| {},
                    );
                    p.work += n as f64;
                    let Fate::Exit { x, y } = fate else { continue };
                    let Some(id) = self.distance_bin(x.hypot(y)) else {
                        continue;
                    };
                    if n < self.min_order {
                        continue;
                    }
                    let w = log_ratio.exp();
                    p.count[id] += 1;
                    p.sum[id] += w;
                    p.sum_sq[id] += w * w;
                    p.weights[id].push(w);
                }
                p
            })
            .collect();
        let mut total = Pilot::new(nd);
        for p in parts {
            total.work += p.work;
            for id in 0..nd {
                total.count[id] += p.count[id];
                total.sum[id] += p.sum[id];
                total.sum_sq[id] += p.sum_sq[id];
                total.weights[id].extend_from_slice(&p.weights[id]);
            }
        }
        total
    }

    /// Runs the whole simulation or one shard of it.
    pub fn run(&self, shard: Option<Shard>, opts: &RunOptions) -> Result<(KernelTally, f64)> {
        self.run_chunks(shard_range(self.chunks(), shard), opts)
    }

    /// Runs chunks `range.0..range.1` (e.g. the runs a [`Self::top_up`]
    /// added; their tally merges with the rest's exactly).
    pub fn run_chunks(&self, range: (u64, u64), opts: &RunOptions) -> Result<(KernelTally, f64)> {
        self.validate()?;
        let key = serde_json::json!({ "kernels": self, "chunks": range });
        let out = runner::run(
            &key,
            range,
            KernelTally::new(self),
            |c| self.simulate_chunk(c),
            opts,
        )?;
        Ok((out.tally, out.wall_s))
    }
}

/// A measured kernel on the normalised grid: the fraction of the class's
/// vertices in each bin (Σ mass + overflow = 1), with standard errors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NormalizedHistogram {
    pub albedo: f64,
    pub d: f64,
    /// λ = d/2 + ℓ at the nominal d: t = d/2 + λu, |s| = λv in MFP.
    pub lambda: f64,
    pub class: VertexClass,
    pub u_edges: Vec<f64>,
    pub v_edges: Vec<f64>,
    /// `nu × nv`, row-major `[iu * nv + iv]`.
    pub mass: Vec<f64>,
    /// Standard errors of the masses (the ratio estimator's, see
    /// [`KernelDoc::histogram`]).
    pub sigma: Vec<f64>,
    /// The error of the bin's mean per-path count divided by n̄_c, i.e. the
    /// mass's error with the denominator Σn_c treated as exact: the joint
    /// fit's weights ([`crate::fit::meta::fit_histogram`] says why).
    pub count_sigma: Vec<f64>,
    pub overflow: f64,
    pub overflow_sigma: f64,
    pub overflow_count_sigma: f64,
    pub paths: u64,
    /// Kish's effective number of contributing paths ([`CellTally::effective_paths`]).
    pub effective_paths: f64,
    /// Mean vertices of this class per contributing path (1 for first/last).
    pub mean_vertices: f64,
    /// Mean of u and of v² over the vertices.
    pub mean_u: f64,
    pub mean_v2: f64,
    /// Standard errors of `mean_u` and `mean_v2`
    /// ([`ClassTally::moment_errors`]), if the document has their sums.
    pub moment_errors: Option<[f64; 2]>,
}

/// One row of the summary of a kernel document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellSummary {
    pub albedo: f64,
    pub d: f64,
    /// Contributing paths, and their fraction of the paths launched for the
    /// cell (all, or its run's).
    pub paths: u64,
    pub fraction: f64,
    /// Effective contributing paths ([`CellTally::effective_paths`]) and the
    /// flight sampling of the walk that fed the cell.
    pub effective_paths: f64,
    pub flights: Flights,
    /// Mean scattering vertices per contributing path.
    pub mean_vertices: f64,
    /// Mean u and v² of all / first / last vertices.
    pub mean_u: [f64; 3],
    pub mean_v2: [f64; 3],
}

/// The output of `svkernel simulate kernels`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KernelDoc {
    pub format: String,
    pub version: u32,
    pub paths: u64,
    pub wall_s: f64,
    pub config: KernelConfig,
    pub shard: Option<Shard>,
    pub chunks: Vec<(u64, u64)>,
    pub summary: Vec<CellSummary>,
    pub tally: KernelTally,
    pub provenance: Provenance,
}

impl KernelDoc {
    pub fn new(
        config: KernelConfig,
        shard: Option<Shard>,
        chunks: Vec<(u64, u64)>,
        tally: KernelTally,
        wall_s: f64,
        provenance: Provenance,
    ) -> Self {
        let mut summary = Vec::new();
        for (ia, a) in config.albedos.iter().enumerate() {
            for (id, d) in config.distances.iter().enumerate() {
                let c = &tally.cells[ia][id];
                let n = (c.weight as f64).max(1.0);
                let means = c.classes.each_ref().map(ClassTally::means);
                summary.push(CellSummary {
                    albedo: *a,
                    d: *d,
                    paths: c.paths,
                    fraction: c.paths as f64 / config.launched_for(ia, id).max(1) as f64,
                    effective_paths: c.effective_paths(),
                    flights: config.run_of(ia, id).map_or(Flights::ANALOG, |r| r.flights),
                    mean_vertices: c.events as f64 / n,
                    mean_u: means.map(|m| m.0),
                    mean_v2: means.map(|m| m.1),
                });
            }
        }
        KernelDoc {
            format: KERNEL_FORMAT.into(),
            version: KERNEL_VERSION,
            paths: tally.paths,
            wall_s,
            config,
            shard,
            chunks,
            summary,
            tally,
            provenance,
        }
    }

    /// The first- and last-vertex histograms summed onto a grid `refine`
    /// times finer than the all-vertex one ([`CellTally::coarsen_vertices`]),
    /// for a fit with fewer bins.
    pub fn coarsen_vertices(&mut self, refine: usize) -> Result<()> {
        let grid = self.config.grid;
        for cell in self.tally.cells.iter_mut().flatten() {
            cell.coarsen_vertices(&grid, refine)?;
        }
        self.config.grid.vertex_refine = refine;
        Ok(())
    }

    /// Replaces this tally's cells at the albedos of `other` by `other`'s
    /// cells: a tally simulated for a few albedos overlaid on a wider one,
    /// for a fit or a check (say an analog tally where a plan's transformed
    /// samplings leave the whole-plane moments unsettled). The medium, the
    /// distances, the window and the grid must be the same, and every
    /// albedo of `other` must be one of this tally's; an error names `path`
    /// (`other`'s file) and the key that differs. Returns the albedos
    /// replaced.
    ///
    /// The result is a set of cells, not one simulation: its configuration,
    /// runs and provenance stay this tally's, so it is not written back.
    pub fn overlay(&mut self, other: &KernelDoc, path: &std::path::Path) -> Result<Vec<f64>> {
        let (a, b) = (&self.config, &other.config);
        let same: [(&str, bool); 7] = [
            ("config.g", a.g == b.g),
            ("config.eta", a.eta == b.eta),
            ("config.density", a.density == b.density),
            ("config.rel_width", a.rel_width == b.rel_width),
            ("config.min_order", a.min_order == b.min_order),
            ("config.grid", a.grid == b.grid),
            ("config.distances", a.distances == b.distances),
        ];
        if let Some((key, _)) = same.iter().find(|(_, ok)| !ok) {
            return Err(Error::format(
                path,
                *key,
                "differs from the tally it overlays (the medium, distances, window and grid must match)",
            ));
        }
        let rows: Vec<usize> = b
            .albedos
            .iter()
            .map(|x| {
                a.albedos.iter().position(|y| y == x).ok_or_else(|| {
                    Error::format(
                        path,
                        "config.albedos",
                        format!(
                            "{x} is not one of the overlaid tally's albedos ({})",
                            list(&a.albedos)
                        ),
                    )
                })
            })
            .collect::<Result<_>>()?;
        for (ib, &ia) in rows.iter().enumerate() {
            self.tally.cells[ia] = other.tally.cells[ib].clone();
        }
        // Same albedos and distances, so every row of `other`'s summary
        // has its place in this one.
        for o in &other.summary {
            if let Some(s) = self
                .summary
                .iter_mut()
                .find(|s| s.albedo == o.albedo && s.d == o.d)
            {
                *s = o.clone();
            }
        }
        Ok(b.albedos.clone())
    }

    /// The normalised histogram of cell (albedo `ia`, distance `id`).
    ///
    /// mass_b = Σ n_b / Σ n_c (fraction of the class's vertices; n_b the
    /// path's vertices in bin b, n_c its vertices of the class: n for "all",
    /// 1 for first and last). Its standard error is the ratio estimator's
    /// first-order (delta-method) error, sqrt(Var(n_b − m·n_c)/N)/n̄_c with
    /// Var(z) = (Σn_b² − 2m·Σn_b·n_c + m²·Σn_c²)/N: numerator and denominator
    /// are correlated for "all", and treating the denominator as exact (the
    /// error of the count alone, [`NormalizedHistogram::count_sigma`]) is
    /// wrong both ways. On the shipped training data it understates the
    /// central peak bin (40–50 % of the vertices at α ≥ 0.96, d ≤ 1 MFP) by
    /// up to 3.6×, since long paths put a smaller share of their vertices
    /// there, and overstates elsewhere by ≤ 5 %; for vertices placed
    /// independently in a bin it overstates by √(1 + m·Var(n)/(n̄(1 − m))).
    /// For first and last (n_c = 1) both are the binomial error.
    pub fn histogram(&self, ia: usize, id: usize, class: VertexClass) -> NormalizedHistogram {
        let c = &self.config;
        self.tally.cells[ia][id].normalized(
            &c.grid,
            class,
            c.albedos[ia],
            c.distances[id],
            PairGrid::scale(c.distances[id], 1.0 / c.density),
        )
    }
}

impl crate::doc::Document for KernelDoc {
    const FORMAT: &'static str = KERNEL_FORMAT;
    const VERSION: u32 = KERNEL_VERSION;

    fn validate(&self, path: &std::path::Path) -> crate::Result<()> {
        let doc = self;
        let c = &doc.config;
        let bins = VertexClass::ALL.map(|class| c.grid.for_class(class).bins() + 1);
        let shape_ok = doc.tally.cells.len() == c.albedos.len()
            && doc.tally.cells.iter().all(|row| {
                row.len() == c.distances.len()
                    && row.iter().all(|cell| {
                        cell.classes
                            .iter()
                            .zip(bins)
                            .all(|(k, n)| [&k.count, &k.sq, &k.cross].iter().all(|v| v.len() == n))
                    })
            });
        if !shape_ok {
            return Err(Error::format(
                path,
                "tally.cells",
                "shape does not match config (albedos × distances × grid bins)",
            ));
        }
        Ok(())
    }
}

/// A flight sampling must keep σ' > 0 in every direction.
fn check_flights(f: &Flights, name: &'static str) -> Result<()> {
    if !(f.stretch > 0.0
        && f.stretch <= 8.0
        && (0.0..1.0).contains(&f.bias)
        && f.forced <= 64
        && (!f.angular || (f.bias > 0.0 && f.stretch == 1.0)))
    {
        return Err(Error::param(
            name,
            format!(
                "stretch {}, bias {}, forced {}, angular {}",
                f.stretch, f.bias, f.forced, f.angular
            ),
            "stretch in (0, 8], bias in [0, 1) (above 0 and stretch 1 with angular), forced <= 64",
        ));
    }
    Ok(())
}

/// `0.1,0.25,0.5`: a list as the command line takes it.
fn list(v: &[f64]) -> String {
    v.iter()
        .map(|x| x.to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// Merges shard documents into one (see [`super::profile::merge`]).
pub fn merge(docs: &[(PathBuf, KernelDoc)], provenance: Provenance) -> Result<KernelDoc> {
    let Some((_, first)) = docs.first() else {
        return Err(Error::param("merge inputs", "none", "at least one file"));
    };
    let mut tally = KernelTally::new(&first.config);
    let mut wall_s = 0.0;
    for (path, d) in docs {
        if d.config != first.config {
            return Err(Error::Merge {
                path: path.clone(),
                msg: "configuration differs from the first input".into(),
            });
        }
        tally.merge(&d.tally);
        wall_s += d.wall_s;
    }
    let joined = runner::join_chunks(docs.iter().map(|(p, d)| (p.as_path(), &d.chunks[..])))?;
    let complete = joined == [(0, first.config.chunks())];
    let shard = if complete { None } else { first.shard };
    Ok(KernelDoc::new(
        first.config.clone(),
        shard,
        joined,
        tally,
        wall_s,
        provenance,
    ))
}

/// Serde adapter for mostly-zero count arrays: `{"len": n, "nz": [[i, v], …]}`
/// (index, value) pairs of the non-zero entries. Kernel tallies are ≈ 80 %
/// zeros; this keeps shipped documents small and stays readable from Python
/// (`a = np.zeros(len); a[nz[:, 0]] = nz[:, 1]`).
mod sparse {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error as _};

    #[derive(Serialize, Deserialize)]
    struct Sparse {
        len: usize,
        nz: Vec<(usize, u128)>,
    }

    pub fn serialize<S: Serializer>(v: &[u128], s: S) -> Result<S::Ok, S::Error> {
        Sparse {
            len: v.len(),
            nz: v
                .iter()
                .enumerate()
                .filter(|(_, x)| **x != 0)
                .map(|(i, x)| (i, *x))
                .collect(),
        }
        .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u128>, D::Error> {
        let sp = Sparse::deserialize(d)?;
        if sp.len > 1 << 28 {
            return Err(D::Error::custom(format!("len {} too large", sp.len)));
        }
        let mut v = vec![0; sp.len];
        for (i, x) in sp.nz {
            *v.get_mut(i)
                .ok_or_else(|| D::Error::custom(format!("index {i} outside len {}", sp.len)))? = x;
        }
        Ok(v)
    }
}

/// A kernel measurement in a heterogeneous medium for one pair direction:
/// pencil beam at x_i = 0, paths with ≥ `min_order` scatterings that exit at
/// |x_e| ∈ d(1 ± w) with azimuth within `wedge` radians of +x, walked with
/// delta tracking ([`super::walk::walk_delta`]) through `albedo` and
/// `density`. Histograms in the pair frame with normalisation length
/// `lambda` (fixed, since ρ varies).
pub struct DirectedKernel<'a, A, D> {
    pub medium: Medium,
    pub albedo: &'a A,
    pub density: &'a D,
    pub d: f64,
    pub rel_width: f64,
    pub wedge: f64,
    pub min_order: u32,
    pub lambda: f64,
    pub grid: PairGrid,
    pub paths: u64,
    pub seed: u64,
    pub max_events: u32,
}

impl<A: super::walk::AlbedoField + Sync, D: super::walk::DensityField + Sync>
    DirectedKernel<'_, A, D>
{
    /// Simulates every chunk (rayon) and merges them in chunk order.
    pub fn run(&self) -> CellTally {
        use rayon::prelude::*;
        let chunks = self.paths.div_ceil(runner::CHUNK_PATHS);
        let parts: Vec<CellTally> = (0..chunks).into_par_iter().map(|c| self.chunk(c)).collect();
        let mut total = CellTally::new(&self.grid);
        for p in &parts {
            total.merge(p);
        }
        total
    }

    fn chunk(&self, c: u64) -> CellTally {
        let (first, count) = chunk_paths(self.paths, c);
        let mut cell = CellTally::new(&self.grid);
        let mut vertices: Vec<[f64; 2]> = Vec::new();
        let mut bins = Vec::new();
        for path in first..first + count {
            let mut rng = PathRng::new(self.seed, path);
            let Some(start) = launch(&Source::Pencil, self.medium.eta, &mut rng) else {
                continue;
            };
            vertices.clear();
            let (fate, n) = super::walk::walk_delta(
                &self.medium,
                self.albedo,
                self.density,
                self.max_events,
                start,
                &mut rng,
                |v, _| vertices.push([v[0], v[1]]),
            );
            let Fate::Exit { x, y } = fate else { continue };
            let r = x.hypot(y);
            if n < self.min_order
                || (r - self.d).abs() > self.rel_width * self.d
                || y.atan2(x).abs() > self.wedge
            {
                continue;
            }
            cell.add_path(&self.grid, [x, y], self.lambda, &vertices, 1, &mut bins);
        }
        cell
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default grid with a tail of 6 bins out to ±16λ.
    fn tailed() -> PairGrid {
        PairGrid {
            tail: Some(Tail {
                bins: 6,
                extent: 16.0,
            }),
            ..PairGrid::default()
        }
    }

    #[test]
    fn a_tail_bins_every_point_of_its_window_where_its_edges_say() {
        let g = tailed();
        let (ue, ve) = (g.u_edges(), g.v_edges());
        assert_eq!((ue.len() - 1, ve.len() - 1), g.shape());
        assert_eq!((g.shape(), g.bins()), ((32 + 12, 16 + 6), 44 * 22));
        assert_eq!((ue[0], ue[44], ve[22]), (-16.0, 16.0, 16.0));
        assert!(ue.windows(2).chain(ve.windows(2)).all(|e| e[0] < e[1]));
        // The core's edges are the grid's without a tail, exactly.
        assert_eq!(ue[6..=38], PairGrid::default().u_edges()[..]);
        assert_eq!(ve[..=16], PairGrid::default().v_edges()[..]);
        // Log-spaced: each tail bin 16/4 ^ (1/6) times as far out as the last.
        let q = 4f64.powf(1.0 / 6.0);
        assert!(ve[17..].windows(2).all(|e| (e[1] / e[0] - q).abs() < 1e-12));
        // Random points and every edge itself land in the bin [lo, hi) ×
        // [lo, hi) whose edges hold them, or in the overflow outside
        // [−16, 16) × [0, 16).
        let mut rng = PathRng::new(7, 0);
        let mut points: Vec<(f64, f64)> = (0..20_000)
            .map(|_| (40.0 * rng.uniform() - 20.0, 20.0 * rng.uniform()))
            .collect();
        points.extend(ue.iter().map(|&u| (u, 1.0)));
        points.extend(ve.iter().map(|&v| (0.3, v)));
        for (u, v) in points {
            let b = g.index(u, v);
            if !((-16.0..16.0).contains(&u) && (0.0..16.0).contains(&v)) {
                assert_eq!(b, g.bins(), "{u} {v}");
                continue;
            }
            let (iu, iv) = (b / g.shape().1, b % g.shape().1);
            assert!(
                ue[iu] <= u && u < ue[iu + 1] && ve[iv] <= v && v < ve[iv + 1],
                "{u} {v} in {iu} {iv}"
            );
        }
    }

    #[test]
    fn a_tail_holds_the_far_vertices_and_leaves_the_other_classes_alone() {
        let g = tailed();
        let mut c = CellTally::new(&g);
        let mut scratch = Vec::new();
        // λ = 1: one path with vertices in the core, in the tail along u and
        // across, and beyond the far edge; its last vertex in the core.
        let vertices = [[0.5, 30.0], [-9.0, 0.2], [0.5, 10.0], [0.4, 0.1]];
        c.add_path(&g, [1.0, 0.0], 1.0, &vertices, 1, &mut scratch);
        let all = c.normalized(&g, VertexClass::All, 0.5, 1.0, 1.0);
        assert_eq!(all.mass.len(), g.bins());
        assert_eq!(all.overflow, 0.25);
        assert_eq!(all.mass[g.index(-9.5, 0.2)], 0.25);
        assert_eq!(all.mass[g.index(0.0, 10.0)], 0.25);
        assert_eq!(all.mass[g.index(-0.1, 0.1)], 0.25);
        let last = c.normalized(&g, VertexClass::Last, 0.5, 1.0, 1.0);
        assert_eq!(last.mass.len(), 128 * 64);
        assert_eq!(
            last.u_edges,
            PairGrid::default().for_class(VertexClass::Last).u_edges()
        );
        // The tail is written only where there is one, and reads back.
        let json = serde_json::to_string(&g).unwrap();
        assert!(json.contains("tail"));
        assert_eq!(serde_json::from_str::<PairGrid>(&json).unwrap(), g);
        assert!(
            !serde_json::to_string(&PairGrid::default())
                .unwrap()
                .contains("tail")
        );
    }

    /// One cell at d = 1 (λ = 1) and paths given by their vertex lists.
    fn cell(paths: &[Vec<[f64; 2]>]) -> (PairGrid, CellTally) {
        let grid = PairGrid::default();
        let mut c = CellTally::new(&grid);
        let mut scratch = Vec::new();
        for v in paths {
            c.add_path(&grid, [1.0, 0.0], 1.0, v, 1, &mut scratch);
        }
        (grid, c)
    }

    #[test]
    fn a_common_weight_changes_nothing() {
        // The same paths with weight 2³⁰ each: identical masses, errors and
        // moments (every sum scales by w or w², and the estimators are ratios).
        let paths: Vec<Vec<[f64; 2]>> = (0..50)
            .map(|k| {
                (0..1 + k % 7)
                    .map(|j| [0.1 * j as f64, 0.05 * k as f64])
                    .collect()
            })
            .collect();
        let (grid, a) = cell(&paths);
        let mut b = CellTally::new(&grid);
        let mut scratch = Vec::new();
        for v in &paths {
            b.add_path(&grid, [1.0, 0.0], 1.0, v, 1 << 30, &mut scratch);
        }
        assert_eq!(b.effective_paths(), 50.0);
        for class in [VertexClass::All, VertexClass::First, VertexClass::Last] {
            let (ha, hb) = (
                a.normalized(&grid, class, 0.5, 1.0, 1.0),
                b.normalized(&grid, class, 0.5, 1.0, 1.0),
            );
            for k in 0..ha.mass.len() {
                assert!((ha.mass[k] - hb.mass[k]).abs() < 1e-12);
                assert!((ha.sigma[k] - hb.sigma[k]).abs() < 1e-12);
                assert!((ha.count_sigma[k] - hb.count_sigma[k]).abs() < 1e-12);
            }
            assert!(
                (ha.mean_u - hb.mean_u).abs() < 1e-12 && (ha.mean_v2 - hb.mean_v2).abs() < 1e-12
            );
            let (ea, eb) = (ha.moment_errors.unwrap(), hb.moment_errors.unwrap());
            for (x, y) in ea.iter().zip(&eb) {
                assert!(
                    (x - y).abs() <= 1e-9 * x.abs(),
                    "{class:?}: {ea:?} against {eb:?}"
                );
            }
        }
    }

    #[test]
    fn unequal_weights_count_as_fewer_paths() {
        // Two paths of weights 1 and 3: Kish's n = 16/10, and the first
        // vertex's mass is the weighted share 3/4 in the heavier path's bin.
        let grid = PairGrid::default();
        let mut c = CellTally::new(&grid);
        let mut scratch = Vec::new();
        c.add_path(&grid, [1.0, 0.0], 1.0, &[[0.5, 0.0]], 1, &mut scratch);
        c.add_path(&grid, [1.0, 0.0], 1.0, &[[0.5, 1.5]], 3, &mut scratch);
        assert!((c.effective_paths() - 1.6).abs() < 1e-12);
        let h = c.normalized(&grid, VertexClass::First, 0.5, 1.0, 1.0);
        let first = grid.for_class(VertexClass::First);
        assert!((h.mass[first.index(0.0, 1.5)] - 0.75).abs() < 1e-12);
        assert!((h.mass[first.index(0.0, 0.0)] - 0.25).abs() < 1e-12);
    }

    #[test]
    fn vertex_classes_are_binned_on_their_own_grid() {
        // Two vertices 0.15 λ apart across the axis share a bin of λ/4 in
        // the all-vertex histogram and fall in two bins of λ/16 in the
        // last-vertex one.
        let grid = PairGrid::default();
        assert_eq!(grid.vertex_refine, 4);
        let mut c = CellTally::new(&grid);
        let mut scratch = Vec::new();
        for s in [0.05, 0.2] {
            c.add_path(&grid, [1.0, 0.0], 1.0, &[[0.5, s]], 1, &mut scratch);
        }
        let all = c.normalized(&grid, VertexClass::All, 0.5, 1.0, 1.0);
        let last = c.normalized(&grid, VertexClass::Last, 0.5, 1.0, 1.0);
        assert_eq!((all.mass.len(), last.mass.len()), (32 * 16, 128 * 64));
        assert_eq!(all.v_edges[1], 0.25);
        assert_eq!(last.v_edges[1], 0.0625);
        assert_eq!(all.mass[grid.index(0.0, 0.05)], 1.0);
        let fine = grid.for_class(VertexClass::Last);
        assert_eq!(last.mass[fine.index(0.0, 0.05)], 0.5);
        assert_eq!(last.mass[fine.index(0.0, 0.2)], 0.5);
        // A grid written before the refinement existed reads as unrefined.
        let old: PairGrid = serde_json::from_str(r#"{"nu": 32, "nv": 16, "extent": 4.0}"#).unwrap();
        assert_eq!(old.vertex_refine, 1);
        assert_eq!(
            old.for_class(VertexClass::Last),
            old.for_class(VertexClass::All)
        );
    }

    #[test]
    fn coarsened_vertex_histograms_are_the_coarser_grids_own() {
        // Paths of 1–6 vertices anywhere in the window (and beyond it),
        // weights 1–4: tallied on bins of λ/16 and summed onto λ/8 or λ/4,
        // they are exactly the tallies made on those grids.
        let mut rng = PathRng::new(5, 0);
        let paths: Vec<(Vec<[f64; 2]>, u64)> = (0..400)
            .map(|k| {
                let n = 1 + k % 6;
                let v = (0..n)
                    .map(|_| [9.0 * rng.uniform() - 3.5, 9.0 * rng.uniform() - 4.5])
                    .collect();
                (v, 1 + (k % 4) as u64)
            })
            .collect();
        let tally = |refine: usize| {
            let grid = PairGrid {
                vertex_refine: refine,
                ..PairGrid::default()
            };
            let mut c = CellTally::new(&grid);
            let mut scratch = Vec::new();
            for (v, w) in &paths {
                c.add_path(&grid, [1.0, 0.0], 1.0, v, *w, &mut scratch);
            }
            (grid, c)
        };
        let (grid, fine) = tally(4);
        assert!(
            fine.classes[VertexClass::Last.slot()].count[grid.for_class(VertexClass::Last).bins()]
                > 0
        );
        for refine in [2, 1] {
            let mut c = fine.clone();
            c.coarsen_vertices(&grid, refine).unwrap();
            assert_eq!(c, tally(refine).1, "refine {refine}");
        }
        let mut c = fine.clone();
        assert!(c.coarsen_vertices(&grid, 3).is_err());
    }

    #[test]
    fn a_bin_holding_every_vertex_has_no_error() {
        // Two paths of 1 and 3 vertices, all at one point: the "all" mass
        // there is exactly 1 whatever the path lengths. (Treating Σn as
        // exact gave σ = √½/2 = 0.35.)
        let (grid, c) = cell(&[vec![[0.5, 0.0]], vec![[0.5, 0.0]; 3]]);
        for class in [VertexClass::All, VertexClass::First, VertexClass::Last] {
            let b = grid.for_class(class).index(0.0, 0.0);
            let h = c.normalized(&grid, class, 0.5, 1.0, 1.0);
            assert_eq!(h.mass[b], 1.0, "{class:?}");
            assert!(h.sigma[b] < 1e-12, "{class:?}: {}", h.sigma[b]);
        }
    }

    #[test]
    fn ratio_errors_match_the_spread_over_batches() {
        // Paths of geometric length (mean 20), each vertex in bin A with
        // probability 0.1, else in bin B: the reported σ of A's "all" mass
        // against its spread over 400 independent batches of 500 paths.
        let mut rng = PathRng::new(11, 0);
        let (a, b) = ([0.5, 0.0], [0.5, 1.5]);
        let mut masses = Vec::new();
        let mut sigmas = Vec::new();
        let grid = PairGrid::default();
        let bin_a = grid.index(0.0, 0.0);
        for _ in 0..400 {
            let paths: Vec<Vec<[f64; 2]>> = (0..500)
                .map(|_| {
                    let mut v = Vec::new();
                    loop {
                        v.push(if rng.uniform() < 0.1 { a } else { b });
                        if rng.uniform() < 0.05 {
                            break v;
                        }
                    }
                })
                .collect();
            let (_, c) = cell(&paths);
            let h = c.normalized(&grid, VertexClass::All, 0.5, 1.0, 1.0);
            masses.push(h.mass[bin_a]);
            sigmas.push(h.sigma[bin_a]);
        }
        errors_match_the_spread(&masses, &sigmas, "the mass of bin A");
    }

    /// The mean of the reported `errors` against the spread of `values`
    /// over batches, within 15 % (over 400 batches the spread's own
    /// relative error is ≈ 3.5 %).
    fn errors_match_the_spread(values: &[f64], errors: &[f64], what: &str) {
        let k = values.len() as f64;
        let mean = values.iter().sum::<f64>() / k;
        let spread = (values.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (k - 1.0)).sqrt();
        let reported = errors.iter().sum::<f64>() / k;
        assert!(
            (reported / spread - 1.0).abs() < 0.15,
            "{what}: reported σ {reported:.5} against the spread {spread:.5}"
        );
    }

    #[test]
    fn moment_errors_match_the_spread_over_batches() {
        // Paths of geometric length (mean 10) whose vertices share a random
        // offset across the axis, so that a path's vertices are correlated:
        // the reported errors of mean u and mean v² (all vertices, and the
        // first vertex) against their spread over 400 batches of 300 paths.
        let mut rng = PathRng::new(12, 0);
        let grid = PairGrid::default();
        let classes = [VertexClass::All, VertexClass::First];
        // [class][u or v²] → (means, reported errors).
        let mut seen = [
            [(Vec::new(), Vec::new()), (Vec::new(), Vec::new())],
            Default::default(),
        ];
        for _ in 0..400 {
            let paths: Vec<Vec<[f64; 2]>> = (0..300)
                .map(|_| {
                    let offset = 2.0 * rng.uniform();
                    let mut v = Vec::new();
                    loop {
                        v.push([0.5 + rng.uniform() - 0.5, offset + 0.5 * rng.uniform()]);
                        if rng.uniform() < 0.1 {
                            break v;
                        }
                    }
                })
                .collect();
            let (_, c) = cell(&paths);
            for (k, class) in classes.into_iter().enumerate() {
                let h = c.normalized(&grid, class, 0.5, 1.0, 1.0);
                let se = h.moment_errors.expect("tallied with their sums");
                for (i, mean) in [h.mean_u, h.mean_v2].into_iter().enumerate() {
                    seen[k][i].0.push(mean);
                    seen[k][i].1.push(se[i]);
                }
            }
        }
        for (k, class) in classes.into_iter().enumerate() {
            for (i, (means, errors)) in seen[k].iter().enumerate() {
                errors_match_the_spread(means, errors, &format!("{class:?}, moment {i}"));
            }
        }
    }

    #[test]
    fn documents_without_moment_sums_have_no_moment_errors() {
        let (grid, c) = cell(&[vec![[0.5, 0.3]], vec![[0.5, 0.7]; 2]]);
        let mut old = serde_json::to_value(&c).unwrap();
        for class in old["classes"].as_array_mut().unwrap() {
            for key in ["sq_u_q", "cross_u_q", "sq_v2_q", "cross_v2_q"] {
                class.as_object_mut().unwrap().remove(key);
            }
        }
        let old: CellTally = serde_json::from_value(old).unwrap();
        let h = old.normalized(&grid, VertexClass::All, 0.5, 1.0, 1.0);
        let new = c.normalized(&grid, VertexClass::All, 0.5, 1.0, 1.0);
        assert_eq!(h.moment_errors, None);
        assert_eq!(h.mean_v2, new.mean_v2);
        assert!(new.moment_errors.is_some());
    }
}
