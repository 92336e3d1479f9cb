//! The joint fit of the kernel meta-model (docs/design.md §3 step 2(c)): the
//! Gaussian-mixture parameters as tensor Chebyshev polynomials in
//! (ln d, sqrt(1 − α)) ([`crate::metamodel::meta`]), fitted by LM with exact
//! Jacobians to every measured histogram at once, initialised from the
//! per-configuration fits ([`super::gmm`]).
//!
//! # Chain rule
//! Cell c (distance d_c, λ_c = d_c/2 + 1) has the per-configuration problem
//! [`GmmFit`] in θ_g = (η_2..η_K, t_1..t_K, ln σ_1..ln σ_K). The meta-model
//! gives θ_m = (ℓ, μ, ς) with θ_m,j = Σ_a C_{ja} B_a(x_c, y_c) and
//! η = ℓ, t = d_c/2 + λ_c μ, ln σ = ln λ_c + ς, so
//! ∂r/∂C_{ja} = ∂r/∂θ_g,j · s_j · B_a with s_j = λ_c for the centres and 1
//! otherwise. A weak ridge (residuals w·C_{ja} for every non-constant basis
//! term, w = [`RIDGE`]) keeps coefficients that the data do not constrain
//! (corners of the (d, α) box with no contributing paths) from drifting.
//!
//! # Width floor
//! A cell may carry a width floor f_c (in units of λ_c): its widths are then
//! σ = λ_c·√(e^{2ς} + f_c²), so ∂ln σ/∂ς = e^{2ς}/(e^{2ς} + f_c²) replaces
//! the factor 1. A component far narrower than a bin moves its whole mass
//! from bin to bin and feels no pull from mass two bins away; floored at a
//! bin, it does. The cells stuck that way ([`stuck_cells`]) are floored in
//! one stage only, followed by a plain one: at the start of a refit
//! ([`refit_meta`]) and after the top rung of the ladder ([`fit_meta_with`]).

use super::gmm::{GmmFit, KernelHistogram, MOMENT_WEIGHT, PlaneTarget, fit_gmm};
use super::lm::{
    Blocks, Compressed, CompressedJacobian, FitError, FitOptions, FitReport, solve_compressed,
};
use crate::fit::aggregation::{AggregationRow, aggregation_row};
use crate::forward::kernel::{KernelDoc, NormalizedHistogram, VertexClass};
use crate::metamodel::kernel::Gmm;
use crate::metamodel::meta::{META_FORMAT, META_VERSION, MetaModel, MetaModelFile};
use crate::provenance::Provenance;
use levenberg_marquardt::LeastSquaresProblem;
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use serde::{Deserialize, Serialize};

/// Weight of the ridge residuals on non-constant coefficients.
pub const RIDGE: f64 = 0.1;
/// Relative tolerance (ftol, xtol) of the joint fit.
pub const META_TOL: f64 = 1e-6;
/// Initial dampings of the joint fit's multi-start ([`fit_meta_with`]).
pub const STAGE_DAMPINGS: [f64; 3] = [1e-3, 1.0, 1e3];

/// A labelling of the per-cell components stops climbing the ladder of
/// degrees once its χ² exceeds the best one's by this factor. The first
/// stage does not rank the labellings reliably (measured on the shipped
/// last-vertex kernels: χ²/dof at (1, 1) 41.3 by centre, 19.1 by width; at
/// (3, 3) 1.82 against 5.21), so only a gross loser stops (η = 1.3,
/// g = 0.6, last vertices: 14.0 by centre, 0.46 by width at (1, 1); 11.1
/// against 0.21 at (3, 3)).
pub const PRUNE_RATIO: f64 = 10.0;

/// A cell is stuck when the joint fit's χ² there exceeds this many times
/// its own per-cell fit's, plus its residual count (the χ² of a fit at
/// χ²/dof = 1), so that cells the per-cell fit matches to noise are not
/// flagged for noise ([`stuck_cells`]). Measured on the wide box (130
/// cells, all vertices, its earlier (6, 5) model): the two cells
/// whose all-vertex lobe under x_i or x_e the joint fit had lost stood at
/// 989× and 516× (χ² 10973 and 10866 against 11 and 21); the next cell at
/// 62×.
pub const STUCK_RATIO: f64 = 100.0;

/// How the per-cell fits' components are ordered (the meta-model's
/// component j interpolates the j-th component of every cell).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Labelling {
    /// By centre t (the per-cell fits' own order): components spread
    /// along the pair axis, as in the all-vertex kernels.
    Centre,
    /// By width σ: components sharing a centre, as in the last-vertex
    /// kernels around x_e at low albedo and short distance.
    Width,
}

impl Labelling {
    /// The cell fit `f` relabelled (a failed fit stays failed).
    fn apply(self, f: &CellFit, what: &str) -> CellFit {
        match f {
            Ok((g, r)) => {
                let mut g = g.clone();
                if self == Labelling::Width {
                    g.components.sort_by(|a, b| a.sigma.total_cmp(&b.sigma));
                }
                Ok((g, r.clone()))
            }
            Err(e) => Err(FitError::BadData {
                what: what.into(),
                msg: e.to_string(),
            }),
        }
    }
}
/// Cells with fewer effective contributing paths
/// ([`crate::forward::kernel::CellTally::effective_paths`]) are left out of
/// the fits.
pub const MIN_PATHS: u64 = 1000;

/// The histogram of cell (ia, id) of `doc` in absolute pair-frame MFP at the
/// cell's nominal distance ([`fit_histogram`]).
pub fn histogram_from_doc(
    doc: &KernelDoc,
    ia: usize,
    id: usize,
    class: VertexClass,
) -> KernelHistogram {
    fit_histogram(doc.histogram(ia, id, class))
}

/// A measured kernel as the fits take it: in absolute pair-frame MFP,
/// t = d/2 + λu, |s| = λv (each path was binned in its own frame,
/// d_p ∈ d(1 ± w), so this is exact in normalised units), weighted by the
/// **count errors** ([`NormalizedHistogram::count_sigma`]), not by the
/// masses' standard errors.
///
/// Why: three isotropic Gaussians cannot follow the all-vertex densities
/// (χ²/dof ≈ 100 at 2e7 paths), so the weights decide which bins the fit
/// gives up on. The statistically exact ratio errors are up to 3.6× larger
/// on the central peak bins at high albedo and short distance (see
/// [`KernelDoc::histogram`]), which then weigh up to 13× less, and the
/// whole polynomial moves. Measured on the shipped data (2026-12-01):
/// refitted with the ratio errors, the all-vertex model's aggregation error
/// (the report's `meta` column) went from 0.0046 to 0.0096 on average and
/// from 0.0099 to 0.105 at worst (α = 0.4, d = 0.1 MFP; 0.092 at α = 0.2,
/// d = 0.2; 0.073 at α = 0.99, d = 0.1); the last-vertex model's, which
/// the model follows (χ²/dof ≈ 2), from 0.0030 to 0.0028. A fit weighting
/// designed for the model's misfit (a discrepancy term) is open.
pub fn fit_histogram(h: NormalizedHistogram) -> KernelHistogram {
    let (d, l) = (h.d, h.lambda);
    KernelHistogram {
        d,
        t_edges: h.u_edges.iter().map(|u| 0.5 * d + l * u).collect(),
        s_edges: h.v_edges.iter().map(|v| l * v).collect(),
        mass: h.mass,
        sigma: h.count_sigma,
        overflow: h.overflow,
        overflow_sigma: h.overflow_count_sigma,
        // The σ floor is one path's mass: of an effective (analog) path.
        paths: h.effective_paths.round() as u64,
        plane: None,
    }
}

/// One training configuration.
#[derive(Clone, Debug)]
pub struct Cell {
    pub alpha: f64,
    pub d: f64,
    pub hist: KernelHistogram,
    /// The class's vertices over the whole plane (no window), if tallied.
    pub plane: Option<PlaneMoments>,
}

/// Where a class's vertices lie over the whole plane, window or not: the
/// mean of t (MFP from x_i toward x_e) and the rms of s (MFP across), each
/// vertex weighted as in the histogram.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlaneMoments {
    pub mean_t: f64,
    pub rms_s: f64,
    /// Standard errors of `mean_t` and `rms_s` (MFP) for measured moments
    /// whose tally has them ([`crate::forward::kernel::ClassTally::moment_errors`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub se: Option<[f64; 2]>,
}

impl PlaneMoments {
    /// The moments of a kernel: E t = Σ w t_k, E s² = Σ w (s_k² + σ_k²)
    /// (isotropic components), normalised by Σ w.
    pub fn of(g: &Gmm) -> PlaneMoments {
        let w: f64 = g
            .components
            .iter()
            .map(|c| c.weight)
            .sum::<f64>()
            .max(1e-300);
        let t = g.components.iter().map(|c| c.weight * c.t).sum::<f64>() / w;
        let s2 = g
            .components
            .iter()
            .map(|c| c.weight * (c.s * c.s + c.sigma * c.sigma))
            .sum::<f64>()
            / w;
        PlaneMoments {
            mean_t: t,
            rms_s: s2.sqrt(),
            se: None,
        }
    }
}

impl Cell {
    /// The cell of a measured histogram, with its whole-plane moments
    /// (t = d/2 + λu, |s| = λv) and their standard errors where the tally
    /// has them (rms s = λ√⟨v²⟩, so its error is λ·se(⟨v²⟩)/(2√⟨v²⟩)).
    pub fn measured(alpha: f64, h: NormalizedHistogram) -> Cell {
        let (d, l) = (h.d, h.lambda);
        let v2 = h.mean_v2.max(0.0);
        let plane = PlaneMoments {
            mean_t: 0.5 * d + l * h.mean_u,
            rms_s: l * v2.sqrt(),
            se: h
                .moment_errors
                .map(|[u, v]| [l * u, l * v / (2.0 * v2.sqrt()).max(f64::MIN_POSITIVE)]),
        };
        let mut hist = fit_histogram(h);
        hist.plane = Some(PlaneTarget {
            mean_t: plane.mean_t,
            rms_s: plane.rms_s,
            weight: MOMENT_WEIGHT,
            se: [0.0; 2],
        });
        Cell {
            alpha,
            d,
            hist,
            plane: Some(plane),
        }
    }
}

/// `cells` with their moment residuals allowing for the data's own
/// standard errors ([`PlaneTarget::se`]): where a cell's whole-plane
/// moments are noisier than the tolerances (a window that holds little of
/// the vertex weight, heavy-tailed weights), the fit no longer follows
/// their noise at the expense of the bins.
pub fn with_moment_errors(mut cells: Vec<Cell>) -> Vec<Cell> {
    for c in &mut cells {
        if let (Some(t), Some(se)) = (&mut c.hist.plane, c.plane.and_then(|p| p.se)) {
            t.se = se;
        }
    }
    cells
}

/// How a fit weighs the whole-plane moments of the data against its bins
/// ([`crate::fit::gmm`], "Moments").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MomentFit {
    /// W: a miss by the tolerance costs W² in χ² ([`MOMENT_WEIGHT`] by
    /// default).
    pub weight: f64,
    /// The moment residuals allow for the data's own standard errors
    /// ([`with_moment_errors`]).
    pub errors: bool,
}

/// The heaviest moment weight at which [`fit_metamodel_with`]'s ladder
/// climbs from the per-cell fits; a heavier [`MomentFit::weight`] is
/// reached by a refit from the ladder's top ([`refit_meta`]). On the
/// shipped tally a climb at W = 60 settles in a poorer valley (all
/// vertices: χ²/dof 21.3, aggregation error 0.0045 / 0.0095, rms s within
/// 10 % in 75 of 80 cells) than the climb at W = 30 refitted at W = 60
/// (χ²/dof 9.2, 0.0027 / 0.0045, 78 of 80).
pub const LADDER_MOMENT_WEIGHT: f64 = 30.0;

impl Default for MomentFit {
    fn default() -> Self {
        MomentFit {
            weight: MOMENT_WEIGHT,
            errors: false,
        }
    }
}

impl MomentFit {
    /// `cells` with their moment residuals weighed as `self` says (again
    /// on cells it has weighed: it sets, it does not scale).
    pub fn apply(&self, mut cells: Vec<Cell>) -> Vec<Cell> {
        for c in &mut cells {
            if let Some(t) = &mut c.hist.plane {
                t.weight = self.weight;
            }
        }
        if self.errors {
            with_moment_errors(cells)
        } else {
            cells
        }
    }
}

/// The cells of `doc` (one vertex class) with at least [`MIN_PATHS`]
/// effective paths.
/// The document must be at unit density (the meta-model is trained there).
pub fn cells(doc: &KernelDoc, class: VertexClass) -> Vec<Cell> {
    let mut out = Vec::new();
    for (ia, a) in doc.config.albedos.iter().enumerate() {
        for id in 0..doc.config.distances.len() {
            if doc.tally.cells[ia][id].effective_paths() >= MIN_PATHS as f64 {
                out.push(Cell::measured(*a, doc.histogram(ia, id, class)));
            }
        }
    }
    out
}

/// Meta-model shape parameters (ℓ, μ, ς) of a fitted kernel at distance d.
pub fn meta_params(g: &Gmm, d: f64) -> Vec<f64> {
    let lambda = 0.5 * d + 1.0;
    let c = &g.components;
    let w0 = c[0].weight.max(1e-300);
    c[1..]
        .iter()
        .map(|c| (c.weight.max(1e-300) / w0).ln().clamp(-20.0, 20.0))
        .chain(c.iter().map(|c| (c.t - 0.5 * d) / lambda))
        .chain(c.iter().map(|c| (c.sigma / lambda).ln()))
        .collect()
}

/// The joint least-squares problem.
pub struct MetaFit<'a> {
    pub template: MetaModel,
    problems: Vec<GmmFit<'a>>,
    basis: Vec<Vec<f64>>,
    dists: Vec<f64>,
    rows: Vec<usize>,
    coeffs: DVector<f64>,
    /// Each cell's width floor in units of λ (0: none; module docs, "Width
    /// floor").
    floors: Vec<f64>,
    /// Each cell's chain-rule factors ∂θ_g,j/∂θ_m,j at the current
    /// coefficients (module docs, "Chain rule").
    dtheta: Vec<Vec<f64>>,
    /// Counts the evaluations (one per parameter update), if set.
    progress: Option<&'a crate::progress::Task>,
}

impl<'a> MetaFit<'a> {
    /// The problem over `cells` starting from `model`'s coefficients.
    pub fn new(cells: &'a [Cell], model: MetaModel) -> Self {
        let mut rows = vec![0];
        let mut problems = Vec::new();
        let mut basis = Vec::new();
        for c in cells {
            let (xy, _) = model.coordinates(c.d, c.alpha);
            basis.push(model.basis(xy));
            let p = GmmFit::new(&c.hist, model.k, DVector::zeros(3 * model.k - 1));
            rows.push(rows.last().unwrap() + p.residual_count());
            problems.push(p);
        }
        let coeffs = DVector::from_iterator(
            model.coeffs.len() * model.n_coeffs(),
            model.coeffs.iter().flatten().copied(),
        );
        let mut f = MetaFit {
            template: model,
            problems,
            basis,
            dists: cells.iter().map(|c| c.d).collect(),
            rows,
            coeffs: coeffs.clone(),
            floors: vec![0.0; cells.len()],
            dtheta: vec![Vec::new(); cells.len()],
            progress: None,
        };
        f.set_params(&coeffs);
        f
    }

    /// The problem with cell c's widths floored at `floors[c]` (in units of
    /// λ_c; 0: none; module docs, "Width floor").
    pub fn with_floors(mut self, floors: Vec<f64>) -> Self {
        assert_eq!(floors.len(), self.problems.len(), "one floor per cell");
        self.floors = floors;
        let x = self.coeffs.clone();
        self.set_params(&x);
        self
    }

    /// Each cell's χ² at the current coefficients (∞ where not finite).
    pub fn cell_chi2(&self) -> Vec<f64> {
        self.problems
            .iter()
            .map(|p| p.residuals().map_or(f64::INFINITY, |r| r.norm_squared()))
            .collect()
    }

    /// The model at the current coefficients.
    pub fn model(&self) -> MetaModel {
        let t = &self.template;
        let n = t.n_coeffs();
        MetaModel::new(
            t.k,
            (t.deg_x, t.deg_y),
            t.ln_d_range,
            t.alpha_range,
            self.coeffs
                .as_slice()
                .chunks(n)
                .map(|c| c.to_vec())
                .collect(),
        )
    }

    fn ridge_rows(&self) -> usize {
        (MetaModel::n_params(self.template.k)) * (self.template.n_coeffs() - 1)
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for MetaFit<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        if let Some(t) = self.progress {
            t.inc(1);
        }
        self.coeffs.copy_from(x);
        let k = self.template.k;
        let n = self.template.n_coeffs();
        let np = MetaModel::n_params(k);
        for (c, p) in self.problems.iter_mut().enumerate() {
            let d = self.dists[c];
            let lambda = 0.5 * d + 1.0;
            let f2 = self.floors[c] * self.floors[c];
            let dtheta = &mut self.dtheta[c];
            dtheta.clear();
            let theta = DVector::from_fn(np, |j, _| {
                let m: f64 = (0..n).map(|a| x[j * n + a] * self.basis[c][a]).sum();
                let (theta, ds) = if j < k - 1 {
                    (m, 1.0)
                } else if j < 2 * k - 1 {
                    (0.5 * d + lambda * m, lambda)
                } else if f2 > 0.0 {
                    let e = (2.0 * m).exp();
                    (lambda.ln() + 0.5 * (e + f2).ln(), e / (e + f2))
                } else {
                    (lambda.ln() + m, 1.0)
                };
                dtheta.push(ds);
                theta
            });
            p.set_params(&theta);
        }
    }

    fn params(&self) -> DVector<f64> {
        self.coeffs.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let n = self.template.n_coeffs();
        let total = self.rows.last().unwrap() + self.ridge_rows();
        let mut r = DVector::zeros(total);
        for (c, p) in self.problems.iter().enumerate() {
            let rc = p.residuals()?;
            r.rows_mut(self.rows[c], rc.len()).copy_from(&rc);
        }
        let mut row = *self.rows.last().unwrap();
        for j in 0..MetaModel::n_params(self.template.k) {
            for a in 1..n {
                r[row] = RIDGE * self.coeffs[j * n + a];
                row += 1;
            }
        }
        Some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let n = self.template.n_coeffs();
        let np = MetaModel::n_params(self.template.k);
        let total = self.rows.last().unwrap() + self.ridge_rows();
        let mut jac = DMatrix::zeros(total, np * n);
        for (c, p) in self.problems.iter().enumerate() {
            let jc = p.jacobian()?;
            let r0 = self.rows[c];
            for j in 0..np {
                let s = self.dtheta[c][j];
                for a in 0..n {
                    let f = s * self.basis[c][a];
                    if f == 0.0 {
                        continue;
                    }
                    let src = jc.column(j);
                    let mut dst = jac.column_mut(j * n + a);
                    for (i, v) in src.iter().enumerate() {
                        dst[r0 + i] = f * v;
                    }
                }
            }
        }
        let mut row = *self.rows.last().unwrap();
        for j in 0..np {
            for a in 1..n {
                jac[(row, j * n + a)] = RIDGE;
                row += 1;
            }
        }
        Some(jac)
    }
}

impl CompressedJacobian for MetaFit<'_> {
    /// Cell c's rows of the full Jacobian are J_c·M_c, with J_c its
    /// (3K − 1)-column Jacobian in θ_g and M_c = diag(s_j) ⊗ B_cᵀ (module
    /// docs, "Chain rule"). With the thin QR J_c = Q_c R_c, the cell
    /// contributes the 3K − 1 rows R_c M_c to Ĵ and Q_cᵀ r_c to r̂; the ridge
    /// rows are linear and go in as they are. The cells run in parallel and
    /// are stacked in cell order, so the result does not depend on threads.
    fn compressed(&self) -> Option<Compressed> {
        use rayon::prelude::*;
        let n = self.template.n_coeffs();
        let np = MetaModel::n_params(self.template.k);
        let parts: Vec<Option<Compressed>> = self
            .problems
            .par_iter()
            .map(|p| {
                let r = p.residuals()?;
                let j = p.jacobian()?;
                let qr = j.qr();
                let rc = qr.r();
                let qtr = qr.q().tr_mul(&r);
                Some((r.norm_squared(), rc, qtr))
            })
            .collect();
        let ridge = self.ridge_rows();
        let rows = parts.len() * np + ridge;
        let mut jac = DMatrix::zeros(rows, np * n);
        let mut res = DVector::zeros(rows);
        let mut chi2 = 0.0;
        for (c, part) in parts.into_iter().enumerate() {
            let (x2, rc, qtr) = part?;
            chi2 += x2;
            let (ds, b) = (&self.dtheta[c], &self.basis[c]);
            for i in 0..rc.nrows() {
                let row = c * np + i;
                res[row] = qtr[i];
                for j in 0..np {
                    let f = rc[(i, j)] * ds[j];
                    if f == 0.0 {
                        continue;
                    }
                    for (a_, ba) in b.iter().enumerate() {
                        jac[(row, j * n + a_)] = f * ba;
                    }
                }
            }
        }
        let mut row = self.problems.len() * np;
        for j in 0..np {
            for a_ in 1..n {
                let i = j * n + a_;
                res[row] = RIDGE * self.coeffs[i];
                jac[(row, i)] = RIDGE;
                chi2 += res[row] * res[row];
                row += 1;
            }
        }
        (chi2.is_finite() && jac.iter().all(|v| v.is_finite())).then_some((chi2, jac, res))
    }
}

impl Blocks for MetaFit<'_> {
    fn blocks(&self) -> Vec<(String, std::ops::Range<usize>)> {
        let mut out: Vec<_> = self
            .problems
            .iter()
            .enumerate()
            .map(|(c, p)| (format!("d={:.3}", p.data.d), self.rows[c]..self.rows[c + 1]))
            .collect();
        let last = *self.rows.last().unwrap();
        out.push(("ridge".into(), last..last + self.ridge_rows()));
        out
    }
}

/// A per-configuration fit: the kernel and its report, or why it failed.
pub type CellFit = Result<(Gmm, FitReport), FitError>;

/// Per-configuration fits of every cell.
pub fn per_cell_fits(cells: &[Cell], k: usize) -> Vec<CellFit> {
    use rayon::prelude::*;
    cells
        .par_iter()
        .map(|c| {
            let what = format!("GMM α = {} d = {}", c.alpha, c.d);
            fit_gmm(&what, &c.hist, k, &FitOptions::default())
        })
        .collect()
}

/// The box that `cells` span, (ln d range, α range): a meta-model fitted
/// to them maps it onto [−1, 1]² ([`MetaModel::coordinates`]).
pub fn box_of(cells: &[Cell]) -> ([f64; 2], [f64; 2]) {
    let range = |v: &mut dyn Iterator<Item = f64>| {
        v.fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], x| {
            [lo.min(x), hi.max(x)]
        })
    };
    (
        range(&mut cells.iter().map(|c| c.d.ln())),
        range(&mut cells.iter().map(|c| c.alpha)),
    )
}

/// Least-squares coefficients of each parameter over the cells that fitted,
/// with the same ridge: the start of the joint fit.
pub fn initial_model(
    cells: &[Cell],
    fits: &[CellFit],
    k: usize,
    deg: (usize, usize),
) -> Result<MetaModel, FitError> {
    let (ln_d_range, alpha_range) = box_of(cells);
    let bad = |msg: String| FitError::BadData {
        what: "meta-model".into(),
        msg,
    };
    if !(ln_d_range[0] < ln_d_range[1] && alpha_range[0] < alpha_range[1]) {
        return Err(bad("need at least two distances and two albedos".into()));
    }
    let grid = MetaModel::new(k, deg, ln_d_range, alpha_range, vec![]);
    let n = grid.n_coeffs();
    let rows: Vec<(Vec<f64>, Vec<f64>)> = cells
        .iter()
        .zip(fits)
        .filter_map(|(c, f)| {
            let (g, _) = f.as_ref().ok()?;
            let (xy, _) = grid.coordinates(c.d, c.alpha);
            Some((grid.basis(xy), meta_params(g, c.d)))
        })
        .collect();
    if rows.len() < n {
        return Err(bad(format!(
            "{} fitted cells for {n} coefficients per parameter",
            rows.len()
        )));
    }
    let m = rows.len();
    let mut a = DMatrix::zeros(m + n - 1, n);
    for (i, (b, _)) in rows.iter().enumerate() {
        for j in 0..n {
            a[(i, j)] = b[j];
        }
    }
    for j in 1..n {
        a[(m + j - 1, j)] = RIDGE;
    }
    let svd = a.svd(true, true);
    let coeffs = (0..MetaModel::n_params(k))
        .map(|p| {
            let mut y = DVector::zeros(m + n - 1);
            for (i, (_, t)) in rows.iter().enumerate() {
                y[i] = t[p];
            }
            svd.solve(&y, 1e-12)
                .map(|c| c.iter().copied().collect())
                .unwrap_or_else(|_| vec![0.0; n])
        })
        .collect();
    Ok(MetaModel::new(k, deg, ln_d_range, alpha_range, coeffs))
}

/// The whole fit of one vertex class: per-cell fits, initial model, joint LM.
pub fn fit_meta(
    cells: &[Cell],
    k: usize,
    deg: (usize, usize),
    what: &str,
) -> Result<JointFit, FitError> {
    fit_meta_with(cells, k, deg, &[Labelling::Centre], what, None)
}

/// [`fit_meta`], counting the joint fit's evaluations on `progress`: the
/// ladder of degrees from the per-cell fits in each of `labellings`, the
/// lowest χ² kept, then the stuck cells' unsticking ([`refit_meta`]) if
/// any are left, kept where it lowers χ².
pub fn fit_meta_with(
    cells: &[Cell],
    k: usize,
    deg: (usize, usize),
    labellings: &[Labelling],
    what: &str,
    progress: Option<&crate::progress::Task>,
) -> Result<JointFit, FitError> {
    let fits = per_cell_fits(cells, k);
    // The per-cell kernels are not one smooth family (components trade
    // roles across the box), so a least-squares start at a high degree
    // lands in a poor valley: measured on the wide box (α 0.05–0.999,
    // d 0.05–20 MFP), a direct start at degrees (5, 4) ended at χ²/dof
    // 27 against 8.9 at (3, 3). The fit therefore climbs a ladder of
    // degrees, (1, 1), (2, 2), … up to `deg`, each started from the last
    // one's coefficients ([`raise_degree`]), so χ² can only fall with degree.
    let ladder: Vec<(usize, usize)> = (1..=deg.0.max(deg.1))
        .map(|i| (i.min(deg.0), i.min(deg.1)))
        .collect();
    // Each labelling of the per-cell components climbs the ladder; one
    // whose χ² exceeds the best one's by [`PRUNE_RATIO`] stops.
    let starts: Vec<Vec<CellFit>> = labellings
        .iter()
        .map(|l| fits.iter().map(|f| l.apply(f, what)).collect())
        .collect();
    let mut spent = (0, 0.0);
    let mut climbers: Vec<(MetaModel, FitReport)> = Vec::new();
    for (i, &d) in ladder.iter().enumerate() {
        let starts: Vec<MetaModel> = if i == 0 {
            starts
                .iter()
                .map(|f| initial_model(cells, f, k, d))
                .collect::<Result<_, _>>()?
        } else {
            climbers.iter().map(|(m, _)| raise_degree(m, d)).collect()
        };
        climbers = Vec::new();
        for m in starts {
            let (m, rep) = solve_stage(cells, m, None, what, progress)?;
            spent = (spent.0 + rep.evaluations, spent.1 + rep.wall_s);
            climbers.push((m, rep));
        }
        let floor = climbers
            .iter()
            .map(|c| c.1.chi2)
            .fold(f64::INFINITY, f64::min);
        climbers.retain(|c| c.1.chi2 <= PRUNE_RATIO * floor);
    }
    let (mut model, mut rep) = climbers
        .into_iter()
        .min_by(|a, b| a.1.chi2.total_cmp(&b.1.chi2))
        .expect("a climber");
    // The top rung may leave cells stuck, as a refit's start may: unstick
    // them as a refit does, and keep the result if its χ² is lower.
    let stuck = stuck_cells(cells, &model, &fits);
    if !stuck.is_empty() {
        let (m, r) = unstick(cells, model.clone(), &stuck, what, progress)?;
        spent = (spent.0 + r.evaluations, spent.1 + r.wall_s);
        if r.chi2 < rep.chi2 {
            (model, rep) = (m, r);
        }
    }
    Ok(JointFit {
        model,
        report: FitReport {
            evaluations: spent.0,
            wall_s: spent.1,
            ..rep
        },
        fits,
        stuck,
    })
}

/// The joint fit of one vertex class started from a fitted `model`'s
/// coefficients instead of the ladder of [`fit_meta_with`]: one stage
/// (three initial dampings, the lowest χ² kept) at `model`'s K and
/// degrees, with the per-cell fits for the report. For new data over the same box (a re-planned or
/// topped-up tally): the ladder climbs from the new per-cell fits, whose
/// components trade roles differently, and may settle in another valley.
/// Measured on the wide box (129 cells of a re-planned tally, all
/// vertices, K = 4, degrees (5, 4)): the ladder ended at χ²/dof 7.3, a
/// stage from the model fitted to the earlier tally at 2.5. `model`'s box
/// must be the one `cells` span ([`box_of`]).
///
/// Where `model` is stuck in some cells ([`stuck_cells`]), a first stage
/// floors their widths at one bin of their own histogram (module docs,
/// "Width floor"), and the stage above starts from its result. Measured on
/// the wide box (all vertices, from its earlier (6, 5) model, whose
/// two stuck cells at d = 20 MFP had lost a lobe): χ²/dof 0.98 → 0.76, the
/// aggregation error 0.0057 / 0.039 → 0.0050 / 0.027 (mean / worst), and in
/// the two cells 0.039 → 0.008 and 0.029 → 0.006. Flooring every cell
/// instead ended at χ²/dof 4.1: the floor holds the sharp kernels away from
/// their optimum, and the second stage did not find its way back.
pub fn refit_meta(
    cells: &[Cell],
    model: &MetaModel,
    what: &str,
    progress: Option<&crate::progress::Task>,
) -> Result<JointFit, FitError> {
    let (ln_d, alpha) = box_of(cells);
    let same = |a: [f64; 2], b: [f64; 2]| {
        a.iter()
            .zip(&b)
            .all(|(x, y)| (x - y).abs() <= 1e-9 * (1.0 + y.abs()))
    };
    if !(same(ln_d, model.ln_d_range) && same(alpha, model.alpha_range)) {
        let (m_d, m_a) = (model.ln_d_range, model.alpha_range);
        return Err(FitError::BadData {
            what: what.into(),
            msg: format!(
                "the starting model's box d ∈ [{:.4}, {:.4}] MFP, α ∈ [{}, {}] is not the one \
                 the data's cells span, d ∈ [{:.4}, {:.4}] MFP, α ∈ [{}, {}]",
                m_d[0].exp(),
                m_d[1].exp(),
                m_a[0],
                m_a[1],
                ln_d[0].exp(),
                ln_d[1].exp(),
                alpha[0],
                alpha[1]
            ),
        });
    }
    let fits = per_cell_fits(cells, model.k);
    let stuck = stuck_cells(cells, model, &fits);
    let (model, report) = unstick(cells, model.clone(), &stuck, what, progress)?;
    Ok(JointFit {
        model,
        report,
        fits,
        stuck,
    })
}

/// A stage from `model` with the widths of the `stuck` cells floored
/// (none if `stuck` is empty), then a plain stage from its result
/// ([`refit_meta`]). Returns the model and the last stage's report with
/// both stages' evaluations and time.
fn unstick(
    cells: &[Cell],
    model: MetaModel,
    stuck: &[StuckCell],
    what: &str,
    progress: Option<&crate::progress::Task>,
) -> Result<(MetaModel, FitReport), FitError> {
    let mut start = model;
    let mut spent = (0, 0.0);
    if !stuck.is_empty() {
        let mut floors = vec![0.0; cells.len()];
        for s in stuck {
            floors[s.cell] = s.floor;
        }
        let (m, rep) = solve_stage(cells, start, Some(&floors), what, progress)?;
        spent = (rep.evaluations, rep.wall_s);
        start = m;
    }
    let (model, rep) = solve_stage(cells, start, None, what, progress)?;
    let rep = FitReport {
        evaluations: spent.0 + rep.evaluations,
        wall_s: spent.1 + rep.wall_s,
        ..rep
    };
    Ok((model, rep))
}

/// A joint fit of one vertex class.
#[derive(Debug)]
pub struct JointFit {
    pub model: MetaModel,
    pub report: FitReport,
    /// The per-cell fits, in cell order.
    pub fits: Vec<CellFit>,
    /// The cells found stuck, at the start of a refit ([`refit_meta`]) or
    /// at the top of the ladder ([`fit_meta_with`]), and refitted with a
    /// width floor first (the ladder keeps that refit only where it lowers
    /// χ²).
    pub stuck: Vec<StuckCell>,
}

/// A cell where the joint fit's χ² far exceeds the cell's own fit's
/// ([`stuck_cells`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StuckCell {
    /// The cell's index in the class's cells.
    pub cell: usize,
    pub alpha: f64,
    /// Pair distance in MFP.
    pub d: f64,
    /// The cell's χ² under the starting model.
    pub chi2: f64,
    /// The χ² of the cell's own per-cell fit.
    pub own_chi2: f64,
    /// The width floor of the first stage: the widest t bin of the cell's
    /// histogram, in units of λ.
    pub floor: f64,
}

/// The cells where `model`'s χ² exceeds [`STUCK_RATIO`] times the per-cell
/// fit's (`fits`, in cell order) plus the cell's residual count: there the
/// per-cell fit found a far better kernel than the joint fit reaches, the
/// sign of a component stranded away from its lobe. A cell whose per-cell
/// fit failed is never stuck.
pub fn stuck_cells(cells: &[Cell], model: &MetaModel, fits: &[CellFit]) -> Vec<StuckCell> {
    let p = MetaFit::new(cells, model.clone());
    p.cell_chi2()
        .into_iter()
        .zip(fits)
        .enumerate()
        .filter_map(|(i, (chi2, f))| {
            let own = f.as_ref().ok()?.1.chi2;
            let n = p.problems[i].residual_count() as f64;
            (chi2 > STUCK_RATIO * own + n).then(|| {
                let (c, lambda) = (&cells[i], 0.5 * cells[i].d + 1.0);
                let floor = c
                    .hist
                    .t_edges
                    .windows(2)
                    .map(|w| w[1] - w[0])
                    .fold(0.0, f64::max)
                    / lambda;
                StuckCell {
                    cell: i,
                    alpha: c.alpha,
                    d: c.d,
                    chi2,
                    own_chi2: own,
                    floor,
                }
            })
        })
        .collect()
}

/// One stage of the ladder: the joint fit from `model`, solved from a
/// bold, a middling and a cautious initial damping, the lowest χ² kept (a
/// deterministic multi-start: the valley floor is rough where components
/// are far narrower than a bin, since a centre crossing a bin edge moves
/// the whole component's mass, so which minimum LM reaches depends on its
/// first steps). The report counts all three solves. `floors`: each cell's
/// width floor ([`MetaFit::with_floors`]), if any.
fn solve_stage(
    cells: &[Cell],
    model: MetaModel,
    floors: Option<&[f64]>,
    what: &str,
    progress: Option<&crate::progress::Task>,
) -> Result<(MetaModel, FitReport), FitError> {
    // The data resolve the kernels far better than three isotropic Gaussians
    // can follow (χ²/dof ≫ 1 for the all-vertex kernels at 2e7 paths), so
    // each stage stops at a relative χ² change of [`META_TOL`] per step.
    let opts = FitOptions {
        patience: 30,
        tol: META_TOL,
        allow_nonconvergence: true,
    };
    let mut best: Option<(MetaModel, FitReport)> = None;
    let mut spent = (0, 0.0);
    for mu0 in STAGE_DAMPINGS {
        let mut problem = MetaFit::new(cells, model.clone());
        if let Some(f) = floors {
            problem = problem.with_floors(f.to_vec());
        }
        problem.progress = progress;
        let (p, rep) = solve_compressed(what, problem, &opts, mu0)?;
        spent = (spent.0 + rep.evaluations, spent.1 + rep.wall_s);
        if best.as_ref().is_none_or(|b| rep.chi2 < b.1.chi2) {
            best = Some((p.model(), rep));
        }
    }
    let (m, rep) = best.expect("at least one damping");
    Ok((
        m,
        FitReport {
            evaluations: spent.0,
            wall_s: spent.1,
            ..rep
        },
    ))
}

/// `m` at degrees `deg` (each ≥ m's): the same polynomials, the new
/// Chebyshev coefficients zero.
pub fn raise_degree(m: &MetaModel, deg: (usize, usize)) -> MetaModel {
    assert!(deg.0 >= m.deg_x && deg.1 >= m.deg_y, "degrees only rise");
    let coeffs = m
        .coeffs
        .iter()
        .map(|c| {
            let mut out = vec![0.0; (deg.0 + 1) * (deg.1 + 1)];
            for a in 0..=m.deg_x {
                for b in 0..=m.deg_y {
                    out[a * (deg.1 + 1) + b] = c[a * (m.deg_y + 1) + b];
                }
            }
            out
        })
        .collect();
    MetaModel::new(m.k, deg, m.ln_d_range, m.alpha_range, coeffs)
}

/// Everything `tools/jax_check.py` and `tools/nlopt_check.py --gmm` need to
/// re-implement the weighted residuals independently: for a few cells the
/// histogram (edges, masses, floored standard errors), the cell's basis row
/// and distance; the meta-model's coefficients; the Rust residual vector,
/// the gradient Jᵀr and a few Jacobian columns at those coefficients; and one
/// per-configuration GMM fit (θ in the GmmFit convention, χ²).
pub fn export_problem(
    cells: &[Cell],
    model: &MetaModel,
    k_cols: usize,
) -> Result<serde_json::Value, FitError> {
    let p = MetaFit::new(cells, model.clone());
    let r = p.residuals().ok_or_else(|| FitError::BadData {
        what: "export".into(),
        msg: "non-finite residuals".into(),
    })?;
    let j = p.jacobian().ok_or_else(|| FitError::BadData {
        what: "export".into(),
        msg: "non-finite Jacobian".into(),
    })?;
    let grad = j.transpose() * &r;
    let n = j.ncols();
    // Columns spread over parameters and basis terms (a stride coprime to
    // the number of basis terms), so higher-order terms are checked too.
    let cols: Vec<usize> = (0..k_cols.min(n)).map(|i| (5 + i * 37) % n).collect();
    let cell_json: Vec<serde_json::Value> = cells
        .iter()
        .zip(&p.basis)
        .map(|(c, b)| {
            serde_json::json!({
                "alpha": c.alpha, "d": c.d, "basis": b,
                "t_edges": c.hist.t_edges, "s_edges": c.hist.s_edges,
                "mass": c.hist.mass, "overflow": c.hist.overflow,
                "scale": c.hist.floored_sigma(),
                "moments": c.hist.plane.map(|p| serde_json::json!({
                    "plane": [p.mean_t, p.rms_s],
                    "tol": crate::fit::gmm::moment_tolerances(c.d),
                    "weight": p.weight,
                })),
            })
        })
        .collect();
    // One per-configuration fit, for the NLopt cross-check.
    let c0 = &cells[cells.len() / 2];
    let (g, rep) = fit_gmm("export", &c0.hist, model.k, &FitOptions::default())?;
    Ok(serde_json::json!({
        "k": model.k, "deg": [model.deg_x, model.deg_y], "ridge": RIDGE,
        "coeffs": model.coeffs,
        "cells": cell_json,
        "residuals": r.as_slice(),
        "chi2": r.norm_squared(),
        "grad": grad.as_slice(),
        "jac_cols": cols,
        "jac": cols.iter().map(|&c| j.column(c).iter().copied().collect::<Vec<f64>>()).collect::<Vec<_>>(),
        "gmm_fit": {
            "cell": cells.len() / 2,
            "theta": GmmFit::theta_of(&g).as_slice(),
            "chi2": rep.chi2,
        },
    }))
}

/// What [`fit_metamodel`] reports besides the model.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MetaModelFit {
    /// The joint fit of each class (all, last).
    pub joint: Vec<FitReport>,
    /// Per-cell fit reports (or the error) per class.
    pub per_cell: Vec<(String, Vec<std::result::Result<FitReport, String>>)>,
    /// The aggregation error of every cell ([`crate::fit::aggregation`]).
    pub aggregation: Vec<AggregationRow>,
    /// The cells found stuck and unstuck with a width floor, per class
    /// ([`JointFit::stuck`]).
    pub stuck: Vec<(String, Vec<StuckCell>)>,
}

/// Gaussian components of the meta-model, per vertex class. The shipped
/// model has 4 for all vertices (a point under x_i, a lobe near x_e and
/// the interior at two widths) and 5 for the last one, whose sharp core
/// around x_e, shoulder and tail toward x_i fewer isotropic Gaussians do
/// not all hold (docs/method.md §4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Components {
    pub all: usize,
    pub last: usize,
}

impl Components {
    fn of(self, class: VertexClass) -> usize {
        match class {
            VertexClass::All => self.all,
            VertexClass::First | VertexClass::Last => self.last,
        }
    }
}

/// The same K for both classes.
impl From<usize> for Components {
    fn from(k: usize) -> Self {
        Components { all: k, last: k }
    }
}

/// Fits the meta-model of the all-vertex and the last-vertex kernels with
/// `k` components (one K for both, or [`Components`]) and polynomial
/// degrees `degree` (in ln d, in √(1 − α)) to a kernel tally at unit
/// density, and measures every cell's aggregation error. Pure: the caller
/// writes the model and the report.
///
/// The quick fit of a medium built on demand: the ladder alone, with the
/// moments at [`LADDER_MOMENT_WEIGHT`] (no refit at a heavier weight,
/// which costs a second pass of per-cell and joint fits);
/// [`fit_metamodel_with`] fits as `svkernel fit kernels` does.
pub fn fit_metamodel(
    doc: &KernelDoc,
    k: impl Into<Components>,
    degree: (usize, usize),
    progress: bool,
) -> crate::Result<(MetaModelFile, MetaModelFit)> {
    let start = FitStart::Ladder {
        components: k.into(),
        degree,
    };
    let moments = MomentFit {
        weight: LADDER_MOMENT_WEIGHT,
        errors: false,
    };
    fit_metamodel_with(doc, &start, moments, progress)
}

/// Where the joint fits of [`fit_metamodel_with`] start.
#[derive(Clone, Copy, Debug)]
pub enum FitStart<'a> {
    /// From the per-cell fits, up a ladder of degrees to `degree`
    /// ([`fit_meta_with`]): a fit from the data alone.
    Ladder {
        components: Components,
        degree: (usize, usize),
    },
    /// From a fitted meta-model's coefficients, at its K and at its degrees
    /// or raised to `degree` (the new coefficients zero, [`raise_degree`]),
    /// ([`refit_meta`]): a refit of new data over the same box. Its medium
    /// (g, η) must be the tally's; its outer model is not carried over.
    From {
        model: &'a MetaModelFile,
        degree: Option<(usize, usize)>,
    },
}

/// [`fit_metamodel`] from `start`, with the moment residuals weighed as
/// `moments` says.
pub fn fit_metamodel_with(
    doc: &KernelDoc,
    start: &FitStart,
    moments: MomentFit,
    progress: bool,
) -> crate::Result<(MetaModelFile, MetaModelFit)> {
    if let FitStart::From {
        model: f,
        degree: Some(deg),
    } = start
        && (deg.0 < f.all.deg_x.max(f.last.deg_x) || deg.1 < f.all.deg_y.max(f.last.deg_y))
    {
        return Err(FitError::BadData {
            what: "meta-model".into(),
            msg: format!(
                "degrees ({}, {}) below the starting model's ({}, {}): a refit only raises them",
                deg.0, deg.1, f.all.deg_x, f.all.deg_y
            ),
        }
        .into());
    }
    if let FitStart::From { model: f, .. } = start
        && (f.g != doc.config.g || f.eta != doc.config.eta)
    {
        return Err(FitError::BadData {
            what: "meta-model".into(),
            msg: format!(
                "the starting model is for g = {}, η = {}, the tally for g = {}, η = {}",
                f.g, f.eta, doc.config.g, doc.config.eta
            ),
        }
        .into());
    }
    let task = crate::progress::Task::open(
        progress,
        "fitting the meta-model (all and last vertices)",
        "Levenberg–Marquardt evaluations",
    );
    // The two classes are independent fits: run them side by side (the QR
    // inside LM is single-threaded).
    let fit_class = |class: VertexClass| {
        let cs = moments.apply(cells(doc, class));
        let what = format!("meta-model ({} vertices)", class.name());
        // The last-vertex kernels' components may share a centre: they
        // are fitted from both labellings.
        let labellings: &[Labelling] = match class {
            VertexClass::Last => &[Labelling::Centre, Labelling::Width],
            _ => &[Labelling::Centre],
        };
        match start {
            FitStart::Ladder { components, degree } => {
                // The climb weighs the moments at most at LADDER_MOMENT_WEIGHT;
                // a heavier weight is reached from its top (a continuation).
                let climb = MomentFit {
                    weight: moments.weight.min(LADDER_MOMENT_WEIGHT),
                    ..moments
                };
                let top = fit_meta_with(
                    &climb.apply(cs.clone()),
                    components.of(class),
                    *degree,
                    labellings,
                    &what,
                    Some(&task),
                );
                match top {
                    Ok(top) if climb.weight < moments.weight => {
                        refit_meta(&cs, &top.model, &what, Some(&task))
                    }
                    top => top,
                }
            }
            FitStart::From { model: f, degree } => {
                let m = match class {
                    VertexClass::Last => &f.last,
                    _ => &f.all,
                };
                let m = degree.map_or_else(|| m.clone(), |deg| raise_degree(m, deg));
                refit_meta(&cs, &m, &what, Some(&task))
            }
        }
        .map(|r| (class, cs, r))
    };
    let (a, l) = rayon::join(
        || fit_class(VertexClass::All),
        || fit_class(VertexClass::Last),
    );
    let mut models: Vec<MetaModel> = Vec::new();
    let mut joint = Vec::new();
    let mut per_cell = Vec::new();
    let mut aggregation = Vec::new();
    let mut stuck = Vec::new();
    for r in [a, l] {
        let (class, cs, fit) = r?;
        let JointFit {
            model: m,
            report: rep,
            fits,
            stuck: s,
        } = fit;
        if !s.is_empty() {
            stuck.push((format!("{class:?}"), s));
        }
        use rayon::prelude::*;
        aggregation.extend(
            cs.par_iter()
                .zip(&fits)
                .map(|(c, f)| {
                    let q = m.eval(c.d, c.alpha, 1.0);
                    aggregation_row(class, c, f.as_ref().ok().map(|x| &x.0), &q.gmm)
                })
                .collect::<Vec<_>>(),
        );
        per_cell.push((
            format!("{class:?}"),
            fits.into_iter()
                .map(|f| f.map(|x| x.1).map_err(|e| e.to_string()))
                .collect(),
        ));
        joint.push(rep);
        models.push(m);
    }
    let last = models.pop().expect("two models");
    let all = models.pop().expect("two models");
    let file = MetaModelFile {
        format: META_FORMAT.into(),
        version: META_VERSION,
        all,
        first: None,
        last,
        g: doc.config.g,
        eta: doc.config.eta,
        provenance: Provenance::current(),
        outer: None,
    };
    task.finish();
    Ok((
        file,
        MetaModelFit {
            joint,
            per_cell,
            aggregation,
            stuck,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_moments_of_a_mixture() {
        use crate::metamodel::kernel::Component;
        let g = Gmm {
            components: vec![
                Component {
                    weight: 0.25,
                    t: 0.0,
                    s: 0.0,
                    sigma: 1.0,
                },
                Component {
                    weight: 0.75,
                    t: 2.0,
                    s: 0.0,
                    sigma: 3.0,
                },
            ],
        };
        let m = PlaneMoments::of(&g);
        assert!((m.mean_t - 1.5).abs() < 1e-15);
        assert!((m.rms_s - (0.25f64 + 0.75 * 9.0).sqrt()).abs() < 1e-15);
    }
    use crate::fit::gmm::histogram_of;
    use crate::fit::lm::jacobian_mismatch;
    use crate::forward::rng::PathRng;

    /// Synthetic cells from a known meta-model, 1 % errors.
    fn synthetic(truth: &MetaModel) -> Vec<Cell> {
        let mut out = Vec::new();
        for a in [0.3, 0.6, 0.8, 0.95] {
            for d in [0.2, 0.5, 1.0, 3.0, 8.0] {
                let g = truth.eval(d, a, 1.0).gmm;
                let l = 0.5 * d + 1.0;
                let template = KernelHistogram {
                    d,
                    t_edges: (0..=24)
                        .map(|i| 0.5 * d + l * (-4.0 + i as f64 / 3.0))
                        .collect(),
                    s_edges: (0..=12).map(|i| l * i as f64 / 3.0).collect(),
                    mass: vec![],
                    sigma: vec![],
                    overflow: 0.0,
                    overflow_sigma: 0.0,
                    paths: 1_000_000,
                    plane: None,
                };
                let mut h = histogram_of(&g, &template);
                h.sigma = h.mass.iter().map(|m| 0.01 * m + 1e-7).collect();
                h.overflow_sigma = 0.01 * h.overflow + 1e-7;
                out.push(Cell {
                    alpha: a,
                    d,
                    hist: h,
                    plane: None,
                });
            }
        }
        out
    }

    fn truth() -> MetaModel {
        MetaModel::new(
            3,
            (1, 1),
            [0.2f64.ln(), 8f64.ln()],
            [0.3, 0.95],
            vec![
                vec![0.7, 0.1, -0.1, 0.0],
                vec![0.0, 0.2, 0.1, 0.0],
                vec![-0.45, -0.1, 0.0, 0.0],
                vec![0.0, 0.0, 0.05, 0.0],
                vec![0.45, 0.1, 0.0, 0.0],
                vec![-0.8, 0.1, 0.0, 0.0],
                vec![-0.3, -0.1, 0.05, 0.0],
                vec![-0.8, 0.1, 0.0, 0.0],
            ],
        )
    }

    /// `m` with every coefficient moved by up to ±`size`, in a fixed
    /// pattern set by `mix`.
    fn perturbed(m: &MetaModel, size: f64, mix: (usize, usize)) -> MetaModel {
        let mut coeffs = m.coeffs.clone();
        for (j, c) in coeffs.iter_mut().enumerate() {
            for (a, v) in c.iter_mut().enumerate() {
                *v += size * (((j * mix.0 + a * mix.1) % 7) as f64 - 3.0) / 3.0;
            }
        }
        MetaModel::new(m.k, (m.deg_x, m.deg_y), m.ln_d_range, m.alpha_range, coeffs)
    }

    #[test]
    fn jacobian_matches_numerical() {
        let t = truth();
        let cells = synthetic(&t);
        let mut p = MetaFit::new(&cells, perturbed(&t, 0.05, (5, 3)));
        let err = jacobian_mismatch(&mut p);
        assert!(err < 1e-6, "{err}");
    }

    /// The chain rule through the width floor (module docs), in the full
    /// Jacobian and in the compressed one.
    #[test]
    fn jacobians_hold_with_width_floors() {
        let t = truth();
        let cells = synthetic(&t);
        let floors: Vec<f64> = (0..cells.len())
            .map(|c| if c % 3 == 0 { 0.3 } else { 0.0 })
            .collect();
        let mut p = MetaFit::new(&cells, perturbed(&t, 0.05, (5, 3))).with_floors(floors);
        let err = jacobian_mismatch(&mut p);
        assert!(err < 1e-6, "{err}");
        let (r, j) = (p.residuals().unwrap(), p.jacobian().unwrap());
        let (chi2, jc, rc) = p.compressed().unwrap();
        assert!((chi2 - r.norm_squared()).abs() <= 1e-12 * chi2);
        let (a, a0) = (jc.tr_mul(&jc), j.tr_mul(&j));
        assert!((&a - &a0).norm() <= 1e-10 * a0.norm());
        let (g, g0) = (jc.tr_mul(&rc), j.tr_mul(&r));
        assert!((&g - &g0).norm() <= 1e-10 * g0.norm());
        // A floor widens every component of its cell, and only there.
        let plain = MetaFit::new(&cells, perturbed(&t, 0.05, (5, 3)));
        let (x0, x1) = (plain.cell_chi2(), p.cell_chi2());
        for c in 0..cells.len() {
            assert_eq!(x0[c] == x1[c], c % 3 != 0, "cell {c}");
        }
    }

    #[test]
    fn the_compressed_jacobian_keeps_the_normal_equations() {
        let t = truth();
        let cells = synthetic(&t);
        let p = MetaFit::new(&cells, perturbed(&t, 0.03, (3, 5)));
        let (r, j) = (p.residuals().unwrap(), p.jacobian().unwrap());
        let (chi2, jc, rc) = p.compressed().unwrap();
        assert!((chi2 - r.norm_squared()).abs() <= 1e-12 * chi2);
        assert!(jc.nrows() < j.nrows() / 10);
        let (a, g) = (jc.tr_mul(&jc), jc.tr_mul(&rc));
        let (a0, g0) = (j.tr_mul(&j), j.tr_mul(&r));
        assert!(
            (&a - &a0).norm() <= 1e-10 * a0.norm(),
            "{}",
            (&a - &a0).norm()
        );
        assert!(
            (&g - &g0).norm() <= 1e-10 * g0.norm(),
            "{}",
            (&g - &g0).norm()
        );
    }

    #[test]
    fn raising_the_degree_keeps_the_model() {
        let t = truth();
        let r = raise_degree(&t, (3, 2));
        for a in [0.3, 0.5, 0.77, 0.95] {
            for d in [0.2, 0.9, 4.0, 8.0] {
                assert_eq!(t.eval(d, a, 1.0).gmm, r.eval(d, a, 1.0).gmm);
            }
        }
    }

    #[test]
    fn compressed_lm_finds_the_crates_optimum() {
        // From the same perturbed start, the compressed solver and the
        // levenberg-marquardt crate reach the same χ² and kernels.
        let t = truth();
        let mut cells = synthetic(&t);
        for (i, c) in cells.iter_mut().enumerate() {
            // Noise, so that the optimum is not at χ² = 0.
            for (b, m) in c.hist.mass.iter_mut().enumerate() {
                let u = PathRng::new(9, (i * 1000 + b) as u64).uniform();
                *m += 0.01 * *m * (2.0 * u - 1.0);
            }
        }
        let start = perturbed(&t, 0.05, (5, 3));
        let opts = FitOptions {
            tol: 1e-10,
            ..FitOptions::default()
        };
        let (a, ra) = solve_compressed(
            "compressed",
            MetaFit::new(&cells, start.clone()),
            &opts,
            1e-3,
        )
        .unwrap();
        let (b, rb) = crate::fit::lm::solve("crate", MetaFit::new(&cells, start), &opts).unwrap();
        assert!(
            (ra.chi2 - rb.chi2).abs() <= 1e-6 * rb.chi2,
            "{} {}",
            ra.chi2,
            rb.chi2
        );
        let (ma, mb) = (a.model(), b.model());
        for c in &cells {
            let (ga, gb) = (
                ma.eval(c.d, c.alpha, 1.0).gmm,
                mb.eval(c.d, c.alpha, 1.0).gmm,
            );
            let (ha, hb) = (histogram_of(&ga, &c.hist), histogram_of(&gb, &c.hist));
            assert!(crate::fit::gmm::l2_error(&ha, &hb) < 1e-5);
        }
    }

    #[test]
    fn recovers_a_known_meta_model() {
        let t = truth();
        let cells = synthetic(&t);
        let JointFit {
            model: m,
            report: rep,
            fits,
            stuck,
        } = fit_meta(&cells, 3, (1, 1), "synthetic").unwrap();
        // The ladder ends at the known model: no cell is stuck there.
        assert!(stuck.is_empty(), "{stuck:?}");
        assert!(fits.iter().all(|f| f.is_ok()));
        assert!(rep.chi2_per_dof < 0.05, "{rep:?}");
        for c in &cells {
            let (a, b) = (t.eval(c.d, c.alpha, 1.0).gmm, m.eval(c.d, c.alpha, 1.0).gmm);
            let (ha, hb) = (histogram_of(&a, &c.hist), histogram_of(&b, &c.hist));
            assert!(crate::fit::gmm::l2_error(&ha, &hb) < 1e-3);
        }
    }

    /// A refit from a perturbed model climbs back to the known one in one
    /// stage, and a model over another box is refused.
    #[test]
    fn a_refit_starts_from_the_given_model_and_checks_its_box() {
        let t = truth();
        let cells = synthetic(&t);
        let start = perturbed(&t, 0.05, (5, 3));
        let chi2_0 = MetaFit::new(&cells, start.clone())
            .residuals()
            .unwrap()
            .norm_squared();
        let JointFit {
            model: m,
            report: rep,
            fits,
            ..
        } = refit_meta(&cells, &start, "refit", None).unwrap();
        assert_eq!(fits.len(), cells.len());
        assert!(rep.chi2 < 1e-3 * chi2_0, "{} from {chi2_0}", rep.chi2);
        assert!(rep.chi2_per_dof < 0.05, "{rep:?}");
        for c in &cells {
            let (a, b) = (t.eval(c.d, c.alpha, 1.0).gmm, m.eval(c.d, c.alpha, 1.0).gmm);
            let (ha, hb) = (histogram_of(&a, &c.hist), histogram_of(&b, &c.hist));
            assert!(crate::fit::gmm::l2_error(&ha, &hb) < 1e-3);
        }
        let wider = MetaModel::new(
            t.k,
            (t.deg_x, t.deg_y),
            [0.1f64.ln(), t.ln_d_range[1]],
            t.alpha_range,
            t.coeffs.clone(),
        );
        let err = refit_meta(&cells, &wider, "refit", None).unwrap_err();
        assert!(err.to_string().contains("box"), "{err}");
    }

    /// A start whose third component is stranded three bins beyond its lobe
    /// and far narrower than a bin: every cell is stuck. One plain stage
    /// stays in that valley; the refit floors the widths first and finds
    /// the known model.
    #[test]
    fn a_refit_floors_the_stuck_cells_and_finds_their_lobes() {
        let t = truth();
        let cells = synthetic(&t);
        let mut coeffs = t.coeffs.clone();
        coeffs[4] = vec![1.5, 0.0, 0.0, 0.0];
        coeffs[7] = vec![0.01f64.ln(), 0.0, 0.0, 0.0];
        let start = MetaModel::new(t.k, (t.deg_x, t.deg_y), t.ln_d_range, t.alpha_range, coeffs);
        let fits = per_cell_fits(&cells, t.k);
        let stuck = stuck_cells(&cells, &start, &fits);
        let (plain, _) = solve_stage(&cells, start.clone(), None, "plain", None).unwrap();
        let plain_chi2 = MetaFit::new(&cells, plain)
            .residuals()
            .unwrap()
            .norm_squared();
        let fit = refit_meta(&cells, &start, "refit", None).unwrap();
        assert_eq!(stuck.len(), cells.len());
        assert_eq!(fit.stuck, stuck);
        // One bin of the synthetic histograms: λ/3.
        assert!(stuck.iter().all(|s| (s.floor - 1.0 / 3.0).abs() < 1e-12));
        assert!(
            plain_chi2 > 1e6 * fit.report.chi2,
            "{plain_chi2} {:?}",
            fit.report
        );
        assert!(fit.report.chi2_per_dof < 0.05, "{:?}", fit.report);
        for c in &cells {
            let (a, b) = (
                t.eval(c.d, c.alpha, 1.0).gmm,
                fit.model.eval(c.d, c.alpha, 1.0).gmm,
            );
            let (ha, hb) = (histogram_of(&a, &c.hist), histogram_of(&b, &c.hist));
            assert!(crate::fit::gmm::l2_error(&ha, &hb) < 1e-3);
        }
        // The known model itself is stuck nowhere.
        assert!(stuck_cells(&cells, &t, &fits).is_empty());
    }

    /// Relabelling by width orders a fit's components by σ and keeps a
    /// failed fit failed; climbing from two labellings never ends above the
    /// centre labelling alone (it is one of the climbers) and recovers the
    /// known model.
    #[test]
    fn labellings_relabel_and_the_best_climber_is_kept() {
        let t = truth();
        let cells = synthetic(&t);
        let fits = per_cell_fits(&cells, 3);
        let (g, _) = Labelling::Width.apply(&fits[0], "x").unwrap();
        assert!(g.components.windows(2).all(|w| w[0].sigma <= w[1].sigma));
        let (g, _) = Labelling::Centre.apply(&fits[0], "x").unwrap();
        assert!(g.components.windows(2).all(|w| w[0].t <= w[1].t));
        let failed: CellFit = Err(FitError::BadData {
            what: "cell".into(),
            msg: "no data".into(),
        });
        assert!(Labelling::Width.apply(&failed, "x").is_err());
        let centre = fit_meta_with(&cells, 3, (1, 1), &[Labelling::Centre], "c", None)
            .unwrap()
            .report;
        let both = [Labelling::Centre, Labelling::Width];
        let JointFit {
            model: m,
            report: rep,
            ..
        } = fit_meta_with(&cells, 3, (1, 1), &both, "b", None).unwrap();
        assert!(rep.chi2 <= centre.chi2, "{} > {}", rep.chi2, centre.chi2);
        assert!(rep.evaluations >= centre.evaluations);
        assert!(rep.chi2_per_dof < 0.05, "{rep:?}");
        let c = &cells[cells.len() / 2];
        let (a, b) = (t.eval(c.d, c.alpha, 1.0).gmm, m.eval(c.d, c.alpha, 1.0).gmm);
        let (ha, hb) = (histogram_of(&a, &c.hist), histogram_of(&b, &c.hist));
        assert!(crate::fit::gmm::l2_error(&ha, &hb) < 1e-3);
    }
}
