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
//! Every contributing path has weight 1 (analog walk), so the "all" density
//! is E[#vertices in a cell | the path contributes]. A vertex at x is exactly
//! where the path reads α(x): for the analog walk the probability of a path
//! is a product of α(x_j) over its vertices times factors that do not depend
//! on α, hence ∂ ln M(x_e)/∂ ln α(cell) = E[#vertices in the cell | contributes]
//! — the "all" density *is* the first-order sensitivity of the exitance to the
//! albedo map (tested against a finite difference of the heterogeneous walk).
//!
//! # Normalised coordinates
//! Histograms are binned in u = (t − d_p/2)/λ ∈ [−E, E), v = |s|/λ ∈ [0, E)
//! with λ = d_p/2 + ℓ, ℓ = 1/σ_t the mean free path of the simulated medium.
//! λ interpolates between the two length scales of the problem: the mean free
//! path (the kernel of a short pair is a blob of a few ℓ around x_i ≈ x_e)
//! and the pair distance (a long pair's vertices spread along the axis).
//! Because λ scales with 1/ρ, the normalised histogram at (d, α, ρ) equals the
//! one at (ρd, α, 1) exactly — the density scaling law, tested bin by bin.
//!
//! # Determinism
//! Integer counts (per bin: Σ n_b and Σ n_b² over contributing paths, for
//! standard errors) and fixed-point moment sums: mergeable exactly, so results
//! are bitwise identical for any thread count and for shards merged with
//! [`merge`]. Every albedo of a simulation reuses the path's stream
//! (common random numbers across albedos).

use super::medium::Medium;
use super::rng::{PathRng, threshold_u32};
use super::runner::{self, RunOptions, Shard, Tally, chunk_paths, chunk_range};
use super::walk::{Fate, UniformAlbedo, launch, walk_general};
use crate::error::{Error, Result};
use crate::forward::medium::Source;
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Format tag of kernel documents.
pub const KERNEL_FORMAT: &str = "svkernel.kernels";
/// Version of the kernel document format.
pub const KERNEL_VERSION: u32 = 2;
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
}

impl Default for PairGrid {
    fn default() -> Self {
        PairGrid {
            nu: 32,
            nv: 16,
            extent: 4.0,
        }
    }
}

impl PairGrid {
    /// Bins, without the overflow bin (which has index `bins()`).
    pub fn bins(&self) -> usize {
        self.nu * self.nv
    }

    /// λ = d/2 + ℓ in MFP for pair distance d and mean free path ℓ = 1/σ_t.
    pub fn scale(d: f64, mfp: f64) -> f64 {
        0.5 * d + mfp
    }

    /// Bin of the normalised position (u, v ≥ 0); `bins()` if outside.
    #[inline]
    pub fn index(&self, u: f64, v: f64) -> usize {
        let iu = ((u + self.extent) / (2.0 * self.extent) * self.nu as f64).floor();
        let iv = (v / self.extent * self.nv as f64).floor();
        if iu >= 0.0 && iu < self.nu as f64 && iv >= 0.0 && iv < self.nv as f64 {
            iu as usize * self.nv + iv as usize
        } else {
            self.bins()
        }
    }

    /// Edges in u (nu + 1).
    pub fn u_edges(&self) -> Vec<f64> {
        (0..=self.nu)
            .map(|k| -self.extent + 2.0 * self.extent * k as f64 / self.nu as f64)
            .collect()
    }

    /// Edges in v (nv + 1).
    pub fn v_edges(&self) -> Vec<f64> {
        (0..=self.nv)
            .map(|k| self.extent * k as f64 / self.nv as f64)
            .collect()
    }
}

pub use crate::pair::VertexClass;

/// Counts of one vertex class in one (albedo, distance) cell.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassTally {
    /// Σ over contributing paths of the path's vertex count per bin; the last
    /// entry is the overflow (outside the grid).
    #[serde(with = "sparse")]
    pub count: Vec<u64>,
    /// Σ of the squared per-path counts, per bin (for standard errors).
    #[serde(with = "sparse")]
    pub sq: Vec<u64>,
    /// Σ over contributing paths of the per-path count in the bin times the
    /// path's count of this class's vertices (n for "all", 1 for first and
    /// last), per bin: the covariance term of the ratio estimator's error.
    #[serde(with = "sparse")]
    pub cross: Vec<u64>,
    /// Σ u and Σ v² over the vertices, fixed point (2⁻¹⁶).
    pub sum_u_q: i64,
    pub sum_v2_q: u64,
}

impl ClassTally {
    fn new(grid: &PairGrid) -> Self {
        ClassTally {
            count: vec![0; grid.bins() + 1],
            sq: vec![0; grid.bins() + 1],
            cross: vec![0; grid.bins() + 1],
            sum_u_q: 0,
            sum_v2_q: 0,
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
    }

    /// Adds one path whose vertices of this class fall in `bins` (sorted;
    /// all of the path's vertices of this class, overflow included).
    fn add_path(&mut self, bins: &[usize]) {
        let n = bins.len() as u64;
        let mut k = 0;
        while k < bins.len() {
            let b = bins[k];
            let run = bins[k..].iter().take_while(|&&x| x == b).count() as u64;
            self.count[b] += run;
            self.sq[b] += run * run;
            self.cross[b] += run * n;
            k += run as usize;
        }
    }

    fn add_moment(&mut self, u: f64, v: f64) {
        self.sum_u_q += (u * MOMENT_Q).round() as i64;
        self.sum_v2_q += (v * v * MOMENT_Q).round() as u64;
    }

    /// Vertices tallied (overflow included).
    pub fn vertices(&self) -> u64 {
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
}

/// One (albedo, distance) cell.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CellTally {
    /// Contributing paths.
    pub paths: u64,
    /// Σ n and Σ n² of the paths' scattering counts.
    pub events: u64,
    pub events_sq: u64,
    /// all, first, last.
    pub classes: [ClassTally; 3],
}

impl CellTally {
    fn new(grid: &PairGrid) -> Self {
        CellTally {
            paths: 0,
            events: 0,
            events_sq: 0,
            classes: std::array::from_fn(|_| ClassTally::new(grid)),
        }
    }
}

impl CellTally {
    /// Adds one contributing path from x_i = 0 to `exit` with scattering
    /// vertices `vertices` (at least one), in its own pair frame with
    /// normalisation length `lambda`. `bins` is scratch space.
    pub fn add_path(
        &mut self,
        grid: &PairGrid,
        exit: [f64; 2],
        lambda: f64,
        vertices: &[[f64; 2]],
        bins: &mut Vec<usize>,
    ) {
        let n = vertices.len() as u64;
        self.paths += 1;
        self.events += n;
        self.events_sq += n * n;
        let d = exit[0].hypot(exit[1]);
        let (ex, ey) = (exit[0] / d, exit[1] / d);
        let frame = |p: [f64; 2]| {
            let t = p[0] * ex + p[1] * ey;
            let s = -p[0] * ey + p[1] * ex;
            ((t - 0.5 * d) / lambda, s.abs() / lambda)
        };
        bins.clear();
        for p in vertices {
            let (u, v) = frame(*p);
            bins.push(grid.index(u, v));
            self.classes[VertexClass::All.slot()].add_moment(u, v);
        }
        bins.sort_unstable();
        self.classes[VertexClass::All.slot()].add_path(bins);
        for (class, p) in [
            (VertexClass::First, vertices[0]),
            (VertexClass::Last, vertices[vertices.len() - 1]),
        ] {
            let (u, v) = frame(p);
            let c = &mut self.classes[class.slot()];
            c.add_path(&[grid.index(u, v)]);
            c.add_moment(u, v);
        }
    }

    /// Adds another cell's counts.
    pub fn merge(&mut self, b: &CellTally) {
        self.paths += b.paths;
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
        let cl = &self.classes[class.slot()];
        let n = self.paths.max(1) as f64;
        let total = cl.vertices();
        let mean_vertices = total as f64 / n;
        let norm = mean_vertices.max(f64::MIN_POSITIVE);
        // Σ n_c² over the paths of this class's per-path vertex count n_c.
        let total_sq = match class {
            VertexClass::All => self.events_sq,
            VertexClass::First | VertexClass::Last => self.paths,
        } as f64;
        // (mass, its standard error, the fit weight's error) of bin b.
        let stat = |b: usize| {
            let mean_count = cl.count[b] as f64 / n;
            let m = mean_count / norm;
            // The ratio estimator m = Σn_b/Σn_c to first order (the delta
            // method): Var(m) ≈ Var(n_b − m·n_c)/(N·n̄_c²), the sample variance
            // of z = n_b − m·n_c, whose mean is 0 at this m.
            let ez2 = (cl.sq[b] as f64 - 2.0 * m * cl.cross[b] as f64 + m * m * total_sq) / n;
            let count_var = (cl.sq[b] as f64 / n - mean_count * mean_count).max(0.0);
            (
                m,
                (ez2.max(0.0) / n).sqrt() / norm,
                (count_var / n).sqrt() / norm,
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
            mean_vertices,
            mean_u,
            mean_v2,
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
}

impl KernelConfig {
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
        if self.grid.nu == 0
            || self.grid.nv == 0
            || self.grid.extent.is_nan()
            || self.grid.extent <= 0.0
        {
            return Err(Error::param(
                "grid",
                format!(
                    "nu {}, nv {}, extent {}",
                    self.grid.nu, self.grid.nv, self.grid.extent
                ),
                "nu, nv >= 1, extent > 0",
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
                vertices.clear();
                let (fate, n) =
                    walk_general(medium, albedo, self.max_events, start, &mut rng, |v, _| {
                        vertices.push([v[0], v[1]])
                    });
                let Fate::Exit { x, y } = fate else { continue };
                if n < self.min_order {
                    continue;
                }
                let d = x.hypot(y);
                let Some(id) = self.distance_bin(d) else {
                    continue;
                };
                tally.cells[ia][id].add_path(
                    &self.grid,
                    [x, y],
                    PairGrid::scale(d, mfp),
                    &vertices,
                    &mut bins,
                );
            }
        }
        tally
    }

    /// Runs the whole simulation or one shard of it.
    pub fn run(&self, shard: Option<Shard>, opts: &RunOptions) -> Result<(KernelTally, f64)> {
        self.validate()?;
        let key = serde_json::json!({ "kernels": self, "shard": shard });
        let out = runner::run(
            &key,
            chunk_range(self.paths, shard),
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
    /// Mean vertices of this class per contributing path (1 for first/last).
    pub mean_vertices: f64,
    /// Mean of u and of v² over the vertices.
    pub mean_u: f64,
    pub mean_v2: f64,
}

/// One row of the summary of a kernel document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellSummary {
    pub albedo: f64,
    pub d: f64,
    /// Contributing paths, and their fraction of the launched paths.
    pub paths: u64,
    pub fraction: f64,
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
                let n = c.paths.max(1) as f64;
                let means = c.classes.each_ref().map(ClassTally::means);
                summary.push(CellSummary {
                    albedo: *a,
                    d: *d,
                    paths: c.paths,
                    fraction: c.paths as f64 / tally.paths.max(1) as f64,
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
        let bins = c.grid.bins() + 1;
        let shape_ok = doc.tally.cells.len() == c.albedos.len()
            && doc.tally.cells.iter().all(|row| {
                row.len() == c.distances.len()
                    && row.iter().all(|cell| {
                        cell.classes
                            .iter()
                            .all(|k| [&k.count, &k.sq, &k.cross].iter().all(|v| v.len() == bins))
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
    let complete = joined == [chunk_range(first.config.paths, None)];
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
        nz: Vec<(usize, u64)>,
    }

    pub fn serialize<S: Serializer>(v: &[u64], s: S) -> Result<S::Ok, S::Error> {
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

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u64>, D::Error> {
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
            cell.add_path(&self.grid, [x, y], self.lambda, &vertices, &mut bins);
        }
        cell
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One cell at d = 1 (λ = 1) and paths given by their vertex lists.
    fn cell(paths: &[Vec<[f64; 2]>]) -> (PairGrid, CellTally) {
        let grid = PairGrid::default();
        let mut c = CellTally::new(&grid);
        let mut scratch = Vec::new();
        for v in paths {
            c.add_path(&grid, [1.0, 0.0], 1.0, v, &mut scratch);
        }
        (grid, c)
    }

    #[test]
    fn a_bin_holding_every_vertex_has_no_error() {
        // Two paths of 1 and 3 vertices, all at one point: the "all" mass
        // there is exactly 1 whatever the path lengths. (Treating Σn as
        // exact gave σ = √½/2 = 0.35.)
        let (grid, c) = cell(&[vec![[0.5, 0.0]], vec![[0.5, 0.0]; 3]]);
        let b = grid.index(0.0, 0.0);
        for class in [VertexClass::All, VertexClass::First, VertexClass::Last] {
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
        let k = masses.len() as f64;
        let mean = masses.iter().sum::<f64>() / k;
        let spread = (masses.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (k - 1.0)).sqrt();
        let reported = sigmas.iter().sum::<f64>() / k;
        // The spread's own relative error over 400 batches is ≈ 3.5 %.
        assert!(
            (reported / spread - 1.0).abs() < 0.15,
            "reported σ {reported:.5} against the spread {spread:.5}"
        );
    }
}
