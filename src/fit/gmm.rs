//! Per-configuration fit of a Gaussian-mixture kernel to a measured kernel
//! histogram (docs/design.md §3 step 2b: one GMM per simulated (α, d), the
//! initialisation of the meta-model).
//!
//! # Data
//! A [`KernelHistogram`]: the fraction of unit mass in each bin of a
//! (t, |s|) grid of the pair frame (absolute MFP, docs/design.md §2), folded in |s|,
//! plus the mass that fell outside the grid (the overflow), with standard
//! errors.
//!
//! # Model
//! K ∈ 1..=[`MAX_COMPONENTS`] isotropic Gaussians centred on the axis
//! ([`crate::metamodel::kernel`]): the exact bin masses
//! m_b = Σ_k w_k·T_k(i)·S_k(j) for bin b = (i, j) with
//! T_k(i) = Φ((t_{i+1} − μ_k)/σ_k) − Φ((t_i − μ_k)/σ_k) and
//! S_k(j) = 2·[Φ(s_{j+1}/σ_k) − Φ(s_j/σ_k)], and the model overflow
//! o = 1 − Σ_b m_b = Σ_k w_k·q_k with q_k = 1 − T_k^tot·S_k^tot (the mass of
//! component k off the grid), computed as (1 − T^tot) + T^tot·(1 − S^tot)
//! from complementary error functions, so a tiny overflow is not lost to
//! cancellation against 1.
//!
//! # Parameters (unconstrained, lm.rs convention)
//! θ = (η_2..η_K, μ_1..μ_K, ln σ_1..ln σ_K), 3K − 1 numbers. Weights are a
//! softmax w_k = e^{η_k}/Σ_j e^{η_j} with η_1 fixed at 0. Fixing one logit
//! removes the softmax's additive gauge exactly, so the Jacobian has full
//! rank without a ridge term — a ridge would add an artificial residual that
//! biases the weights and shifts χ²/dof. Any θ is a valid kernel: weights
//! ≥ 0 summing to 1, σ > 0.
//!
//! # Residuals and weights
//! r_b = (m_b − y_b)/σ̃_b for each bin, and (o − y_o)/σ̃_o for the overflow;
//! cost χ² = Σ r². The standard errors are floored in quadrature,
//! σ̃ = √(σ² + f²), with f = 1/`paths`: the mass of one (average) path of the
//! unit-mass tally, i.e. the standard error of a single count. An empty bin
//! (σ = 0) then pulls the model toward zero with the weight of "at most about
//! one path", never with infinite weight, and a populated bin with n counts
//! (σ ≈ √n/paths) has its variance changed by a relative 1/n only. With
//! `paths` = 0 (unknown) the floor is the smallest positive σ of the data, or
//! 1e-6 if every σ is 0 — then all weights are equal and the minimiser is the
//! unweighted least-squares one whatever the floor.
//!
//! # Moments
//! The bins see only the window, and a low-weight component far wider
//! than the window costs nothing there but the overflow; yet the renderer
//! reads the kernel over the whole plane. If the data carry the vertices'
//! whole-plane mean t̄ and rms s̄ ([`KernelHistogram::plane`], from the
//! tally's running sums), two more residuals tie the model's moments to
//! them: W·(Σ w_k μ_k − t̄)/τ_t and W·ln(√(Σ w_k σ_k²)/s̄)/τ_s, with the
//! tolerances of [`moment_tolerances`] (5 % of d in mean t, 10 % in rms s,
//! the meta-model's targets) and the target's weight W
//! ([`PlaneTarget::weight`]): a miss by the tolerance costs W² in χ². The width's residual is logarithmic, so it is
//! gentle near the target and grows without bound for a runaway component.
//! If the target carries the data's standard errors ([`PlaneTarget::se`]),
//! each tolerance τ becomes √(τ² + se²) (se of rms s relative to s̄ for the
//! logarithmic one): a moment known only to ±se is not pulled closer.
//!
//! # Derivatives
//! With z = (x − μ)/σ at a bin edge x, ∂Φ(z)/∂μ = −φ(z)/σ and
//! ∂Φ(z)/∂ln σ = −zφ(z) ([`gauss_interval_grad`]); so
//! ∂m_b/∂μ_k = w_k·∂T_k/∂μ_k·S_k,
//! ∂m_b/∂ln σ_k = w_k·(∂T_k/∂ln σ_k·S_k + T_k·∂S_k/∂ln σ_k), and for the
//! softmax ∂m_b/∂η_j = w_j·(T_j S_j − m_b) (likewise for o with q_j).
//!
//! # Convergence
//! With more components than the data resolve (K = 5 on a three-lobed
//! kernel), two components can merge: along the direction that separates
//! them χ² changes only at fourth order, and Levenberg–Marquardt creeps down
//! that valley without meeting its relative tolerance (observed: Δχ² ≈ 3e-4
//! per 3000 evaluations at χ² ≈ 800). [`fit_gmm`] therefore restarts once
//! from where the solver lost patience (which also resets its damping); if
//! the second pass still loses patience but lowered χ² by at most
//! [`STALLED_CHI2`] = 1e-3 — a parameter move of ≈ 0.03 standard errors,
//! statistically nothing — the fit counts as converged and its report says
//! so. A real failure still returns [`FitError::NotConverged`].

use super::exp_mixture::safe_exp;
use super::lm::{Blocks, FitError, FitOptions, FitReport, solve};
use crate::metamodel::kernel::{
    Component, Gmm, gauss_interval_grad, manual_kernel, std_normal_mass,
};
use levenberg_marquardt::LeastSquaresProblem;
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_1_SQRT_2;

/// Largest χ² decrease over a whole second solver pass for which a fit that
/// lost patience counts as converged (module docs, "Convergence").
pub const STALLED_CHI2: f64 = 1e-3;

/// Weight W of the whole-plane moment residuals (module docs, "Moments"):
/// a miss by the tolerance costs W² in χ².
///
/// 70, so that a 10 % miss in rms s (4900) weighs as much as a cell's bins
/// (about 900–4000); at W = 1 the bins alone set the widths that the
/// window or the bin size hides, and at W = 30 the all-vertex kernels of
/// α = 0.99 stay 10–14 % narrow. 70 is the least of the weights tried
/// (30, 40, 60, 70, 80, 100) at which the shipped model meets both moment
/// targets in every cell but one whose data is an outlier. docs/method.md
/// §4 ("Whole-plane moments") has the measurements and why the weight
/// does not scale with each cell's own χ².
pub const MOMENT_WEIGHT: f64 = 70.0;

/// The largest number of components [`fit_gmm`] accepts.
pub const MAX_COMPONENTS: usize = 5;

/// The default number of components (the manual kernel's three).
pub const DEFAULT_COMPONENTS: usize = 3;

/// A measured kernel at one (α, d): the fraction of unit mass in each bin of
/// a (t, |s|) grid in absolute MFP in the pair frame, with standard errors.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct KernelHistogram {
    /// Distance d between entry and exit (MFP).
    pub d: f64,
    /// t bin edges (MFP): increasing, nt + 1 edges.
    pub t_edges: Vec<f64>,
    /// |s| bin edges (MFP): increasing, starts at 0, ns + 1 edges (|s| folded).
    pub s_edges: Vec<f64>,
    /// Bin masses, nt·ns, row-major `[it * ns + is]`; Σ mass + overflow = 1.
    pub mass: Vec<f64>,
    /// Standard error of each mass (may be 0 for empty bins).
    pub sigma: Vec<f64>,
    /// Mass outside the grid.
    pub overflow: f64,
    /// Standard error of the overflow.
    pub overflow_sigma: f64,
    /// Contributing paths behind it (for a variance floor).
    pub paths: u64,
    /// Where the vertices lie over the whole plane, window or not, if known:
    /// two more residuals ([`GmmFit`]).
    pub plane: Option<PlaneTarget>,
}

/// The whole-plane moments a fit should reach (module docs, "Moments").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlaneTarget {
    /// Mean t of the vertices (MFP).
    pub mean_t: f64,
    /// rms s of the vertices (MFP).
    pub rms_s: f64,
    /// The residuals' weight W.
    pub weight: f64,
    /// Standard errors of `mean_t` and `rms_s` (MFP) that the residuals
    /// allow for, in quadrature with the tolerances (module docs,
    /// "Moments"); zeros: the tolerances alone.
    #[serde(default)]
    pub se: [f64; 2],
}

impl KernelHistogram {
    /// Number of t bins.
    pub fn nt(&self) -> usize {
        self.t_edges.len().saturating_sub(1)
    }

    /// Number of |s| bins.
    pub fn ns(&self) -> usize {
        self.s_edges.len().saturating_sub(1)
    }

    /// Mass on the grid, Σ_b mass_b (dimensionless).
    pub fn grid_mass(&self) -> f64 {
        self.mass.iter().sum()
    }

    /// Checks the shape and the numbers: edges finite and strictly
    /// increasing, s edges from ≥ 0, one mass and one σ per bin, all finite,
    /// σ ≥ 0. The message names the first problem.
    pub fn validate(&self) -> Result<(), String> {
        let increasing = |e: &[f64]| {
            e.len() >= 2 && e.iter().all(|x| x.is_finite()) && e.windows(2).all(|w| w[0] < w[1])
        };
        if !increasing(&self.t_edges) {
            return Err("t_edges must be ≥ 2 finite, strictly increasing values".into());
        }
        if !increasing(&self.s_edges) || self.s_edges[0] < 0.0 {
            return Err("s_edges must be ≥ 2 finite, strictly increasing values from ≥ 0".into());
        }
        let n = self.nt() * self.ns();
        if self.mass.len() != n || self.sigma.len() != n {
            return Err(format!(
                "{}×{} grid needs {n} masses and σ, got {} and {}",
                self.nt(),
                self.ns(),
                self.mass.len(),
                self.sigma.len()
            ));
        }
        if !self.d.is_finite() || self.d < 0.0 {
            return Err(format!("distance d = {} must be finite and ≥ 0", self.d));
        }
        let finite = |v: f64| v.is_finite();
        if !self.mass.iter().all(|&v| finite(v)) || !finite(self.overflow) {
            return Err("masses must be finite".into());
        }
        if !self
            .sigma
            .iter()
            .chain([&self.overflow_sigma])
            .all(|&v| finite(v) && v >= 0.0)
        {
            return Err("standard errors must be finite and ≥ 0".into());
        }
        Ok(())
    }

    /// The variance floor f of the module docs (mass units).
    pub fn sigma_floor(&self) -> f64 {
        if self.paths > 0 {
            return 1.0 / self.paths as f64;
        }
        self.sigma
            .iter()
            .chain([&self.overflow_sigma])
            .copied()
            .filter(|&v| v > 0.0)
            .min_by(f64::total_cmp)
            .unwrap_or(1e-6)
    }

    /// Floored standard errors σ̃ = √(σ² + f²) of the bins, then of the
    /// overflow.
    pub fn floored_sigma(&self) -> Vec<f64> {
        let f = self.sigma_floor();
        self.sigma
            .iter()
            .chain([&self.overflow_sigma])
            .map(|s| s.hypot(f))
            .collect()
    }

    /// Mass of each t bin (summed over |s|).
    fn t_marginal(&self) -> Vec<f64> {
        let ns = self.ns();
        (0..self.nt())
            .map(|i| self.mass[i * ns..(i + 1) * ns].iter().sum())
            .collect()
    }

    /// The q-quantile of the t marginal on the grid (masses clipped at 0;
    /// linear within a bin), MFP.
    fn t_quantile(&self, q: f64) -> f64 {
        let m: Vec<f64> = self.t_marginal().into_iter().map(|v| v.max(0.0)).collect();
        let total: f64 = m.iter().sum();
        let target = q * total;
        let mut acc = 0.0;
        for (i, &mi) in m.iter().enumerate() {
            if mi > 0.0 && acc + mi >= target {
                let f = ((target - acc) / mi).clamp(0.0, 1.0);
                return self.t_edges[i] + f * (self.t_edges[i + 1] - self.t_edges[i]);
            }
            acc += mi;
        }
        *self.t_edges.last().unwrap_or(&0.0)
    }

    /// Second moment ⟨s²⟩ of the on-grid mass (masses clipped at 0), exact
    /// for a uniform density within each |s| bin [a, b]:
    /// ⟨s²⟩_bin = (a² + ab + b²)/3 (MFP²).
    fn s_second_moment(&self) -> f64 {
        let ns = self.ns();
        let (mut m, mut m2) = (0.0, 0.0);
        for (b, &v) in self.mass.iter().enumerate() {
            let v = v.max(0.0);
            let (lo, hi) = (self.s_edges[b % ns], self.s_edges[b % ns + 1]);
            m += v;
            m2 += v * (lo * lo + lo * hi + hi * hi) / 3.0;
        }
        m2 / m
    }
}

/// The least-squares problem of one histogram (module docs).
pub struct GmmFit<'a> {
    pub data: &'a KernelHistogram,
    /// Number of components K.
    pub k: usize,
    /// θ = (η_2..η_K, μ_1..μ_K, ln σ_1..ln σ_K).
    pub theta: DVector<f64>,
    /// σ̃ of each bin, then of the overflow ([`KernelHistogram::floored_sigma`]).
    pub scale: Vec<f64>,
}

/// Per-component factors and their derivatives at the current θ.
struct Parts {
    w: Vec<f64>,
    /// [k][i]: T, ∂T/∂μ, ∂T/∂ln σ.
    t: Vec<Vec<[f64; 3]>>,
    /// [k][j]: S, ∂S/∂ln σ.
    s: Vec<Vec<[f64; 2]>>,
    /// [k]: q, ∂q/∂μ, ∂q/∂ln σ.
    q: Vec<[f64; 3]>,
}

impl<'a> GmmFit<'a> {
    /// The problem for `data` with `k` components at parameters `theta`.
    pub fn new(data: &'a KernelHistogram, k: usize, theta: DVector<f64>) -> Self {
        GmmFit {
            data,
            k,
            theta,
            scale: data.floored_sigma(),
        }
    }

    /// Unconstrained parameters of a kernel with `k` on-axis components
    /// (weights clamped to ≥ 1e-300 before the logarithm).
    pub fn theta_of(g: &Gmm) -> DVector<f64> {
        let c = &g.components;
        let w0 = c[0].weight.max(1e-300);
        DVector::from_iterator(
            3 * c.len() - 1,
            c[1..]
                .iter()
                .map(|c| (c.weight.max(1e-300) / w0).ln())
                .chain(c.iter().map(|c| c.t))
                .chain(c.iter().map(|c| c.sigma.ln())),
        )
    }

    /// Softmax weights with η_1 = 0.
    fn weights(&self) -> Vec<f64> {
        let k = self.k;
        let eta = |i: usize| if i == 0 { 0.0 } else { self.theta[i - 1] };
        let max = (0..k).map(eta).fold(f64::NEG_INFINITY, f64::max);
        let e: Vec<f64> = (0..k).map(|i| (eta(i) - max).exp()).collect();
        let sum: f64 = e.iter().sum();
        e.iter().map(|v| v / sum).collect()
    }

    /// Centre μ_k (MFP).
    fn mu(&self, i: usize) -> f64 {
        self.theta[self.k - 1 + i]
    }

    /// Width σ_k (MFP).
    fn sig(&self, i: usize) -> f64 {
        safe_exp(self.theta[2 * self.k - 1 + i])
    }

    /// The kernel at the current parameters (components in parameter order).
    pub fn gmm(&self) -> Gmm {
        let w = self.weights();
        Gmm {
            components: (0..self.k)
                .map(|i| Component {
                    weight: w[i],
                    t: self.mu(i),
                    s: 0.0,
                    sigma: self.sig(i),
                })
                .collect(),
        }
    }

    fn parts(&self) -> Parts {
        let h = self.data;
        let (te, se) = (&h.t_edges, &h.s_edges);
        let (t_lo, t_hi) = (te[0], te[te.len() - 1]);
        let (s_lo, s_hi) = (se[0], se[se.len() - 1]);
        let mut p = Parts {
            w: self.weights(),
            t: Vec::with_capacity(self.k),
            s: Vec::with_capacity(self.k),
            q: Vec::with_capacity(self.k),
        };
        for i in 0..self.k {
            let (mu, sig) = (self.mu(i), self.sig(i));
            p.t.push(
                te.windows(2)
                    .map(|e| gauss_interval_grad(e[0], e[1], mu, sig))
                    .collect(),
            );
            p.s.push(
                se.windows(2)
                    .map(|e| {
                        let g = gauss_interval_grad(e[0], e[1], 0.0, sig);
                        [2.0 * g[0], 2.0 * g[2]]
                    })
                    .collect(),
            );
            // Off-grid mass q = (1 − T) + T(1 − S) over the whole grid.
            let tt = gauss_interval_grad(t_lo, t_hi, mu, sig);
            let st = gauss_interval_grad(s_lo, s_hi, 0.0, sig);
            let (s_tot, ds_tot) = (2.0 * st[0], 2.0 * st[2]);
            let (za, zb) = ((t_lo - mu) / sig, (t_hi - mu) / sig);
            let t_out = std_normal_mass(f64::NEG_INFINITY, za) + std_normal_mass(zb, f64::INFINITY);
            let s_out =
                libm::erfc(s_hi / sig * FRAC_1_SQRT_2) + libm::erf(s_lo / sig * FRAC_1_SQRT_2);
            p.q.push([
                t_out + tt[0] * s_out,
                -tt[1] * s_tot,
                -(tt[2] * s_tot + tt[0] * ds_tot),
            ]);
        }
        p
    }

    /// Residuals: one per bin, the overflow, and two whole-plane moments
    /// if the data have them.
    pub fn residual_count(&self) -> usize {
        self.data.nt() * self.data.ns() + 1 + if self.data.plane.is_some() { 2 } else { 0 }
    }

    /// The moment residuals (module docs, "Moments") and their gradients in
    /// θ, if the data have whole-plane moments.
    fn moments(&self, w: &[f64]) -> Option<[(f64, Vec<f64>); 2]> {
        let PlaneTarget {
            mean_t: t_data,
            rms_s: s_data,
            weight,
            se,
        } = self.data.plane?;
        let k = self.k;
        let d = self.data.d;
        let s_data = s_data.max(1e-6);
        let (tol_t, tol_s) = moment_tolerances(d);
        let (tol_t, tol_s) = (tol_t.hypot(se[0]), tol_s.hypot(se[1] / s_data));
        let mu: Vec<f64> = (0..k).map(|i| self.mu(i)).collect();
        let s2: Vec<f64> = (0..k).map(|i| self.sig(i).powi(2)).collect();
        let et: f64 = (0..k).map(|i| w[i] * mu[i]).sum();
        let es2: f64 = (0..k).map(|i| w[i] * s2[i]).sum::<f64>().max(1e-300);
        let rs = es2.sqrt();
        let (ft, fs) = (weight / tol_t, weight / tol_s);
        let mut gt = vec![0.0; 3 * k - 1];
        let mut gs = vec![0.0; 3 * k - 1];
        for c in 0..k {
            if c > 0 {
                gt[c - 1] = ft * w[c] * (mu[c] - et);
                gs[c - 1] = fs * w[c] * (s2[c] - es2) / (2.0 * es2);
            }
            gt[k - 1 + c] = ft * w[c];
            gs[2 * k - 1 + c] = fs * w[c] * s2[c] / es2;
        }
        Some([(ft * (et - t_data), gt), (fs * (rs / s_data).ln(), gs)])
    }

    /// Model bin masses (row-major like the data), then the overflow.
    fn model(&self, p: &Parts) -> Vec<f64> {
        let (nt, ns) = (self.data.nt(), self.data.ns());
        let mut m = vec![0.0; nt * ns + 1];
        for k in 0..self.k {
            for i in 0..nt {
                let wt = p.w[k] * p.t[k][i][0];
                for j in 0..ns {
                    m[i * ns + j] += wt * p.s[k][j][0];
                }
            }
            m[nt * ns] += p.w[k] * p.q[k][0];
        }
        m
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for GmmFit<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.theta.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.theta.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let h = self.data;
        let p = self.parts();
        let m = self.model(&p);
        let n = m.len();
        let moments = self.moments(&p.w);
        let r = DVector::from_iterator(
            self.residual_count(),
            (0..n)
                .map(|b| {
                    let y = if b + 1 < n { h.mass[b] } else { h.overflow };
                    (m[b] - y) / self.scale[b]
                })
                .chain(moments.into_iter().flatten().map(|(r, _)| r)),
        );
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let (nt, ns, k) = (self.data.nt(), self.data.ns(), self.k);
        let p = self.parts();
        let m = self.model(&p);
        let mut jac = DMatrix::zeros(self.residual_count(), 3 * k - 1);
        let (col_mu, col_ls) = (k - 1, 2 * k - 1);
        for i in 0..nt {
            for j in 0..ns {
                let b = i * ns + j;
                let inv = 1.0 / self.scale[b];
                for c in 0..k {
                    let [t, dt_mu, dt_ls] = p.t[c][i];
                    let [s, ds_ls] = p.s[c][j];
                    let w = p.w[c];
                    if c > 0 {
                        jac[(b, c - 1)] = w * (t * s - m[b]) * inv;
                    }
                    jac[(b, col_mu + c)] = w * dt_mu * s * inv;
                    jac[(b, col_ls + c)] = w * (dt_ls * s + t * ds_ls) * inv;
                }
            }
        }
        let b = nt * ns;
        let inv = 1.0 / self.scale[b];
        for c in 0..k {
            let [q, dq_mu, dq_ls] = p.q[c];
            let w = p.w[c];
            if c > 0 {
                jac[(b, c - 1)] = w * (q - m[b]) * inv;
            }
            jac[(b, col_mu + c)] = w * dq_mu * inv;
            jac[(b, col_ls + c)] = w * dq_ls * inv;
        }
        for (row, (_, g)) in self.moments(&p.w).into_iter().flatten().enumerate() {
            for (col, v) in g.into_iter().enumerate() {
                jac[(b + 1 + row, col)] = v;
            }
        }
        jac.iter().all(|v| v.is_finite()).then_some(jac)
    }
}

impl Blocks for GmmFit<'_> {
    fn blocks(&self) -> Vec<(String, std::ops::Range<usize>)> {
        let n = self.data.nt() * self.data.ns();
        let mut out = vec![("bins".into(), 0..n), ("overflow".into(), n..n + 1)];
        if self.data.plane.is_some() {
            out.push(("moments".into(), n + 1..n + 3));
        }
        out
    }
}

/// Tolerances of the whole-plane moments at distance d (module docs,
/// "Moments"): 0.05·d + 0.01·λ MFP for mean t (λ = d/2 + 1 MFP), and
/// ln 1.1 for ln rms s (10 %).
pub fn moment_tolerances(d: f64) -> (f64, f64) {
    let lambda = 0.5 * d + 1.0;
    (0.05 * d + 0.01 * lambda, 1.1f64.ln())
}

/// Robust start for `k` components, without hand tuning.
///
/// * Width scale from the data's second moment: for on-axis isotropic
///   components ⟨s²⟩ = Σ_k w_k σ_k², so σ̄ = √⟨s²⟩ (MFP; bins read as
///   uniform, [`KernelHistogram`] masses clipped at 0).
/// * K = 3: the manual kernel's layout ([`manual_kernel`]`(d)`): centres
///   t = 0, d/2, d, weights ¼, ½, ¼, widths in the manual ratios
///   0.5 : 0.5 + 0.3d : 0.5 rescaled so that Σ w σ² = σ̄².
/// * Other K: equal weights and widths σ̄, centres spread evenly between the
///   10 % and 90 % quantiles of the t marginal (K = 1: its median).
///
/// The data must have positive mass on the grid (else σ̄ is not finite; the
/// result is then the manual kernel's layout, or widths of 1 MFP).
pub fn initial_guess(h: &KernelHistogram, k: usize) -> Gmm {
    let s2 = h.s_second_moment();
    let sbar = if s2.is_finite() && s2 > 0.0 {
        s2.sqrt()
    } else {
        1.0
    };
    if k == 3 {
        let manual = manual_kernel(h.d);
        let norm: f64 = manual
            .components
            .iter()
            .map(|c| c.weight * c.sigma * c.sigma)
            .sum();
        let f = sbar / norm.sqrt();
        return Gmm {
            components: manual
                .components
                .iter()
                .map(|c| Component {
                    sigma: c.sigma * f,
                    ..c.clone()
                })
                .collect(),
        };
    }
    let centre = |i: usize| {
        if k == 1 {
            h.t_quantile(0.5)
        } else {
            h.t_quantile(0.1 + 0.8 * i as f64 / (k - 1) as f64)
        }
    };
    Gmm {
        components: (0..k)
            .map(|i| Component {
                weight: 1.0 / k as f64,
                t: centre(i),
                s: 0.0,
                sigma: sbar,
            })
            .collect(),
    }
}

/// Fits a `k`-component on-axis GMM (1 ≤ k ≤ [`MAX_COMPONENTS`]) to `h` by
/// Levenberg–Marquardt with exact Jacobians (module docs), from
/// [`initial_guess`]. The returned kernel has unit mass and its components
/// are sorted by t (stable labelling for the meta-model).
///
/// # Errors
/// [`FitError::BadData`] for a malformed histogram, no positive mass on the
/// grid, k out of range or fewer residuals than parameters;
/// [`FitError::NotConverged`] when the solver lost patience twice and χ²
/// still moved by more than [`STALLED_CHI2`] (unless
/// `opts.allow_nonconvergence`; the report then says `success: false`), or
/// when χ² is not finite.
pub fn fit_gmm(
    what: &str,
    h: &KernelHistogram,
    k: usize,
    opts: &FitOptions,
) -> Result<(Gmm, FitReport), FitError> {
    let bad = |msg: String| FitError::BadData {
        what: what.into(),
        msg,
    };
    h.validate().map_err(bad)?;
    if !(1..=MAX_COMPONENTS).contains(&k) {
        return Err(bad(format!("{k} components: must be 1..={MAX_COMPONENTS}")));
    }
    let residuals = h.nt() * h.ns() + 1;
    if residuals < 3 * k {
        return Err(bad(format!(
            "{residuals} residuals for {} parameters: too little data for {k} components",
            3 * k - 1
        )));
    }
    let on_grid: f64 = h.mass.iter().map(|v| v.max(0.0)).sum();
    if on_grid <= 0.0 {
        return Err(bad("no positive mass on the grid".into()));
    }
    let init = initial_guess(h, k);
    // Solve, then settle a lost patience (module docs, "Convergence").
    let inner = FitOptions {
        allow_nonconvergence: true,
        ..*opts
    };
    let (mut p, mut rep) = solve(what, GmmFit::new(h, k, GmmFit::theta_of(&init)), &inner)?;
    if !rep.success {
        let (before, evaluations, wall_s) = (rep.chi2, rep.evaluations, rep.wall_s);
        (p, rep) = solve(what, p, &inner)?;
        rep.evaluations += evaluations;
        rep.wall_s += wall_s;
        let gain = before - rep.chi2;
        if !rep.success && gain.abs() <= STALLED_CHI2 {
            rep.success = true;
            rep.termination = format!(
                "{} twice; χ² stalled (Δχ² = {gain:.1e} over the second pass)",
                rep.termination
            );
        }
    }
    if !rep.success && !opts.allow_nonconvergence {
        return Err(FitError::NotConverged {
            what: what.into(),
            termination: rep.termination,
            evaluations: rep.evaluations,
            chi2_per_dof: rep.chi2_per_dof,
        });
    }
    let mut g = p.gmm().normalized();
    g.components.sort_by(|a, b| a.t.total_cmp(&b.t));
    if !g.is_valid() {
        let parts: Vec<String> = g
            .components
            .iter()
            .map(|c| format!("w {} t {} s {} σ {}", c.weight, c.t, c.s, c.sigma))
            .collect();
        return Err(bad(format!(
            "the fit gave an invalid kernel ({})",
            parts.join("; ")
        )));
    }
    Ok((g, rep))
}

/// The histogram of `gmm` on the grid of `template`: exact bin masses
/// ([`Gmm::mass_in_fold`]), overflow = Σ w − Σ bins (clipped at 0), zero
/// standard errors; `d` and `paths` copied from the template.
pub fn histogram_of(gmm: &Gmm, template: &KernelHistogram) -> KernelHistogram {
    let (te, se) = (&template.t_edges, &template.s_edges);
    let mut mass = Vec::with_capacity(template.nt() * template.ns());
    for t in te.windows(2) {
        for s in se.windows(2) {
            mass.push(gmm.mass_in_fold(t[0], t[1], s[0], s[1]));
        }
    }
    let overflow = (gmm.total_weight() - mass.iter().sum::<f64>()).max(0.0);
    KernelHistogram {
        d: template.d,
        t_edges: te.clone(),
        s_edges: se.clone(),
        sigma: vec![0.0; mass.len()],
        mass,
        overflow,
        overflow_sigma: 0.0,
        paths: template.paths,
        plane: None,
    }
}

/// Euclidean distance between two histograms on the same grid, bins and
/// overflow together: √(Σ_b (a_b − b_b)² + (a_o − b_o)²), in units of the
/// unit mass (dimensionless). NaN if the grids differ.
pub fn l2_error(a: &KernelHistogram, b: &KernelHistogram) -> f64 {
    if a.t_edges != b.t_edges || a.s_edges != b.s_edges || a.mass.len() != b.mass.len() {
        return f64::NAN;
    }
    let bins: f64 = a
        .mass
        .iter()
        .zip(&b.mass)
        .map(|(x, y)| (x - y) * (x - y))
        .sum();
    (bins + (a.overflow - b.overflow).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::lm::jacobian_mismatch;
    use crate::forward::rng::PathRng;

    fn edges(lo: f64, hi: f64, n: usize) -> Vec<f64> {
        (0..=n)
            .map(|i| lo + (hi - lo) * i as f64 / n as f64)
            .collect()
    }

    /// An empty histogram on a uniform grid.
    fn template(d: f64, t: (f64, f64, usize), s: (f64, usize), paths: u64) -> KernelHistogram {
        KernelHistogram {
            d,
            t_edges: edges(t.0, t.1, t.2),
            s_edges: edges(0.0, s.0, s.1),
            mass: vec![0.0; t.2 * s.1],
            sigma: vec![0.0; t.2 * s.1],
            overflow: 0.0,
            overflow_sigma: 0.0,
            paths,
            plane: None,
        }
    }

    fn truth3() -> Gmm {
        let c = |weight, t, sigma| Component {
            weight,
            t,
            s: 0.0,
            sigma,
        };
        Gmm {
            components: vec![c(0.3, 0.0, 0.45), c(0.5, 1.6, 1.0), c(0.2, 3.0, 0.55)],
        }
    }

    /// A Poisson deviate of mean `lambda`: inversion below 50, rounded
    /// normal above.
    fn poisson(rng: &mut PathRng, lambda: f64) -> f64 {
        if lambda < 50.0 {
            let u = rng.uniform();
            let (mut n, mut p) = (0u64, (-lambda).exp());
            let mut cdf = p;
            while u > cdf && n < 1000 {
                n += 1;
                p *= lambda / n as f64;
                cdf += p;
            }
            n as f64
        } else {
            (lambda + lambda.sqrt() * crate::testing::standard_normal(rng))
                .round()
                .max(0.0)
        }
    }

    /// Counts of `paths` unit-weight paths drawn bin by bin (independent
    /// Poisson counts), as fractions with σ = √n/paths.
    fn noisy(exact: &KernelHistogram, paths: u64, seed: u64) -> KernelHistogram {
        let mut rng = PathRng::new(seed, 0);
        let n = paths as f64;
        let mut h = exact.clone();
        for (m, s) in h.mass.iter_mut().zip(&mut h.sigma) {
            let c = poisson(&mut rng, *m * n);
            *m = c / n;
            *s = c.sqrt() / n;
        }
        let c = poisson(&mut rng, h.overflow * n);
        h.overflow = c / n;
        h.overflow_sigma = c.sqrt() / n;
        h.paths = paths;
        h
    }

    fn check_kernel(g: &Gmm, k: usize, label: &str) {
        assert_eq!(g.components.len(), k, "{label}");
        assert!(g.is_valid(), "{label}: {g:?}");
        assert!((g.total_weight() - 1.0).abs() < 1e-12, "{label}");
        assert!(
            g.components.windows(2).all(|w| w[0].t <= w[1].t),
            "{label}: not sorted"
        );
    }

    #[test]
    fn model_is_the_kernels_histogram() {
        // The problem's bin masses and overflow equal Gmm::mass_in_fold and
        // sum to 1 exactly (to rounding).
        let truth = truth3();
        let h = histogram_of(&truth, &template(3.0, (-2.0, 5.0, 17), (2.5, 9), 1000));
        let p = GmmFit::new(&h, 3, GmmFit::theta_of(&truth));
        let m = p.model(&p.parts());
        for (a, b) in m.iter().zip(h.mass.iter().chain([&h.overflow])) {
            assert!((a - b).abs() < 1e-15, "{a} vs {b}");
        }
        assert!((m.iter().sum::<f64>() - 1.0).abs() < 1e-14);
        assert!(p.residuals().unwrap().norm() < 1e-9);
        // A far-off component: the overflow keeps its relative precision.
        let far = Gmm {
            components: vec![Component {
                weight: 1.0,
                t: 0.0,
                s: 0.0,
                sigma: 0.05,
            }],
        };
        let h = template(0.0, (-1.0, 1.0, 4), (1.0, 4), 10);
        let p = GmmFit::new(&h, 1, GmmFit::theta_of(&far));
        let o = p.model(&p.parts())[16];
        // Φc(20)·2 (t) + erfc(20/√2) (s) ≈ 3·Φc(20)·… : just positive and tiny.
        assert!(o > 0.0 && o < 1e-80, "{o}");
    }

    /// [`truth3`] on a 14 × 7 grid with the noise of 10⁵ paths.
    fn noisy_truth3() -> KernelHistogram {
        noisy(
            &histogram_of(&truth3(), &template(3.0, (-2.0, 5.0, 14), (2.5, 7), 0)),
            100_000,
            11,
        )
    }

    /// The moment residuals allow for the data's standard errors in
    /// quadrature with the tolerances, and their Jacobian still matches.
    #[test]
    fn moment_residuals_allow_for_the_datas_errors() {
        let h = noisy_truth3();
        let (tol_t, tol_s) = moment_tolerances(h.d);
        let target = |se: [f64; 2]| PlaneTarget {
            mean_t: 1.3,
            rms_s: 0.9,
            weight: 2.0,
            se,
        };
        let theta = GmmFit::theta_of(&truth3());
        let moments = |se: [f64; 2]| {
            let mut hp = h.clone();
            hp.plane = Some(target(se));
            let mut p = GmmFit::new(&hp, 3, theta.clone());
            assert!(jacobian_mismatch(&mut p) < 1e-6);
            let r = p.residuals().unwrap();
            [r[r.len() - 2], r[r.len() - 1]]
        };
        let bare = moments([0.0; 2]);
        let noisy = moments([3.0 * tol_t, 3.0 * tol_s * 0.9]);
        for (a, b) in bare.iter().zip(&noisy) {
            assert!(a.abs() > 1e-3, "{a}");
            assert!((b / a - 1.0 / 10f64.sqrt()).abs() < 1e-12, "{b} / {a}");
        }
    }

    #[test]
    fn jacobian_matches_numerical() {
        let h = noisy_truth3();
        let mut with_moments = h.clone();
        with_moments.plane = Some(PlaneTarget {
            mean_t: 1.3,
            rms_s: 0.9,
            weight: 2.0,
            se: [0.0; 2],
        });
        let mut rng = PathRng::new(12, 0);
        for (k, h) in [
            (1, &h),
            (3, &h),
            (5, &h),
            (3, &with_moments),
            (5, &with_moments),
        ] {
            for _ in 0..4 {
                let theta = DVector::from_iterator(
                    3 * k - 1,
                    (0..3 * k - 1).map(|i| {
                        let u = rng.uniform();
                        if i < k - 1 {
                            -2.0 + 4.0 * u // logits
                        } else if i < 2 * k - 1 {
                            -1.0 + 4.0 * u // centres, MFP
                        } else {
                            -1.5 + 2.0 * u // ln σ
                        }
                    }),
                );
                let mut p = GmmFit::new(h, k, theta);
                let err = jacobian_mismatch(&mut p);
                assert!(err < 1e-6, "K = {k}: relative Jacobian error {err}");
                let analytic = p.jacobian().unwrap();
                let numeric = levenberg_marquardt::differentiate_numerically(&mut p).unwrap();
                let rel = (analytic - &numeric).norm() / numeric.norm();
                assert!(rel < 1e-6, "K = {k}: differentiate_numerically {rel}");
            }
        }
    }

    #[test]
    fn recovers_a_known_mixture() {
        let truth = truth3();
        let mut h = histogram_of(
            &truth,
            &template(3.0, (-2.0, 5.0, 40), (3.0, 20), 1_000_000_000_000),
        );
        for (s, m) in h.sigma.iter_mut().zip(&h.mass) {
            *s = 0.01 * m + 1e-12;
        }
        h.overflow_sigma = 0.01 * h.overflow + 1e-12;
        let (g, rep) = fit_gmm("exact 3", &h, 3, &FitOptions::default()).unwrap();
        check_kernel(&g, 3, "exact");
        assert!(rep.success && rep.chi2_per_dof < 1e-10, "{rep:?}");
        for (a, b) in g.components.iter().zip(&truth.components) {
            assert!(
                (a.weight - b.weight).abs() < 1e-6
                    && (a.t - b.t).abs() < 1e-6
                    && (a.sigma - b.sigma).abs() < 1e-6,
                "{g:?}"
            );
        }
        assert!(l2_error(&histogram_of(&g, &h), &histogram_of(&truth, &h)) < 1e-8);
    }

    #[test]
    fn whole_plane_moments_reach_past_the_window() {
        // A wide, light component mostly off a narrow grid: the bins barely
        // see it, the moments do.
        let c = |weight, t, sigma| Component {
            weight,
            t,
            s: 0.0,
            sigma,
        };
        let truth = Gmm {
            components: vec![c(0.5, 0.2, 0.4), c(0.4, 1.0, 0.6), c(0.1, 0.8, 6.0)],
        };
        let moments = crate::fit::meta::PlaneMoments::of(&truth);
        let mut h = noisy(
            &histogram_of(&truth, &template(1.0, (-1.0, 2.5, 14), (1.5, 6), 0)),
            1_000_000,
            5,
        );
        let fit = |h: &KernelHistogram| fit_gmm("moments", h, 3, &FitOptions::default()).unwrap().0;
        let blind = crate::fit::meta::PlaneMoments::of(&fit(&h));
        h.plane = Some(PlaneTarget {
            mean_t: moments.mean_t,
            rms_s: moments.rms_s,
            weight: MOMENT_WEIGHT,
            se: [0.0; 2],
        });
        let seen = crate::fit::meta::PlaneMoments::of(&fit(&h));
        let (tol_t, tol_s) = moment_tolerances(h.d);
        assert!(
            (seen.mean_t - moments.mean_t).abs() < tol_t
                && (seen.rms_s / moments.rms_s).ln().abs() < tol_s,
            "with moments: {seen:?} against {moments:?}"
        );
        // Without them the width is a guess from the overflow alone.
        assert!(
            (blind.rms_s / moments.rms_s).ln().abs() > (seen.rms_s / moments.rms_s).ln().abs(),
            "without moments {blind:?}, with {seen:?}, truth {moments:?}"
        );
    }

    #[test]
    fn poisson_noise_gives_unit_chi2() {
        let exact = histogram_of(&truth3(), &template(3.0, (-2.0, 5.0, 40), (2.5, 20), 0));
        for seed in [21, 22, 23] {
            let h = noisy(&exact, 10_000_000, seed);
            let (g, rep) = fit_gmm("poisson", &h, 3, &FitOptions::default()).unwrap();
            check_kernel(&g, 3, "poisson");
            assert!(
                (0.7..1.4).contains(&rep.chi2_per_dof),
                "seed {seed}: χ²/dof = {} ({rep:?})",
                rep.chi2_per_dof
            );
            for (a, b) in g.components.iter().zip(&truth3().components) {
                assert!(
                    (a.weight - b.weight).abs() < 0.02 && (a.t - b.t).abs() < 0.05,
                    "{g:?}"
                );
            }
        }
    }

    #[test]
    fn hard_cases_stay_finite() {
        let opts = FitOptions::default();
        let noisy3 = noisy(
            &histogram_of(&truth3(), &template(3.0, (-2.0, 5.0, 40), (2.5, 20), 0)),
            1_000_000,
            31,
        );
        let tiny_d = noisy(
            &histogram_of(
                &manual_kernel(1e-6),
                &template(1e-6, (-2.5, 2.5, 40), (2.5, 20), 0),
            ),
            1_000_000,
            32,
        );
        let far_d = noisy(
            &histogram_of(
                &manual_kernel(50.0),
                &template(50.0, (-5.0, 55.0, 40), (30.0, 20), 0),
            ),
            1_000_000,
            33,
        );
        // 200 paths on 800 bins: mostly empty bins, σ = 0 where empty.
        let sparse = noisy(
            &histogram_of(&truth3(), &template(3.0, (-2.0, 5.0, 40), (2.5, 20), 0)),
            200,
            34,
        );
        // Exact masses with every σ zero, with and without a path count.
        let zero_sigma = histogram_of(
            &truth3(),
            &template(3.0, (-2.0, 5.0, 40), (2.5, 20), 100_000),
        );
        assert!(zero_sigma.sigma.iter().all(|&s| s == 0.0) && zero_sigma.overflow_sigma == 0.0);
        let mut zero_no_paths = zero_sigma.clone();
        zero_no_paths.paths = 0;
        let cases: Vec<(&str, &KernelHistogram, usize)> = vec![
            ("K=1", &noisy3, 1),
            ("K=5", &noisy3, 5),
            ("d=1e-6 K=3", &tiny_d, 3),
            ("d=1e-6 K=5", &tiny_d, 5),
            ("d=50", &far_d, 3),
            ("sparse K=3", &sparse, 3),
            ("sparse K=5", &sparse, 5),
            ("zero sigma", &zero_sigma, 3),
            ("zero sigma, no paths", &zero_no_paths, 3),
        ];
        for (label, h, k) in cases {
            let (g, rep) = fit_gmm(label, h, k, &opts).unwrap_or_else(|e| panic!("{label}: {e}"));
            check_kernel(&g, k, label);
            assert!(rep.chi2.is_finite(), "{label}: {rep:?}");
            // The fit explains the data at least as well as its start.
            let start = l2_error(&histogram_of(&initial_guess(h, k), h), h);
            let end = l2_error(&histogram_of(&g, h), h);
            assert!(
                end <= start * 1.000_001 + 1e-12,
                "{label}: {end} vs start {start}"
            );
        }
        // The manual kernel at d = 50 is recovered from its noisy histogram.
        let (g, _) = fit_gmm("d=50", &far_d, 3, &opts).unwrap();
        for (a, b) in g.components.iter().zip(&manual_kernel(50.0).components) {
            assert!(
                (a.weight - b.weight).abs() < 0.01
                    && (a.t - b.t).abs() < 0.1
                    && (a.sigma / b.sigma - 1.0).abs() < 0.02,
                "{g:?}"
            );
        }
    }

    #[test]
    fn degenerate_data_is_an_error_not_a_panic() {
        let opts = FitOptions::default();
        let empty = template(1.0, (-1.0, 2.0, 10), (1.0, 5), 100);
        assert!(matches!(
            fit_gmm("empty", &empty, 3, &opts),
            Err(FitError::BadData { .. })
        ));
        let mut nan = histogram_of(&manual_kernel(1.0), &empty);
        nan.mass[3] = f64::NAN;
        assert!(matches!(
            fit_gmm("nan", &nan, 3, &opts),
            Err(FitError::BadData { .. })
        ));
        let mut short = histogram_of(&manual_kernel(1.0), &empty);
        short.mass.pop();
        assert!(matches!(
            fit_gmm("short", &short, 3, &opts),
            Err(FitError::BadData { .. })
        ));
        let ok = histogram_of(&manual_kernel(1.0), &empty);
        for k in [0, 6] {
            assert!(matches!(
                fit_gmm("k", &ok, k, &opts),
                Err(FitError::BadData { .. })
            ));
        }
        let tiny = histogram_of(
            &manual_kernel(1.0),
            &template(1.0, (-1.0, 2.0, 2), (1.0, 2), 100),
        );
        assert!(matches!(
            fit_gmm("tiny", &tiny, 3, &opts),
            Err(FitError::BadData { .. })
        ));
        assert!(l2_error(&ok, &tiny).is_nan());
    }
}
