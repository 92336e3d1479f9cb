//! Joint fit of the smooth-in-albedo basis BSSRDF ([`BasisModel`]) to a set
//! of simulated profiles.
//!
//! Residuals: for every profile i and ring j, (m_ij − y_ij)/σ_ij with m the
//! exact ring average of p_m(r; α_i) (see [`super::exp_mixture`]); plus one
//! constraint residual, (Rₘ(1) + R₁(1) − (1 − R_sp))/σ_c, which pins the
//! energy of the conservative medium (all light that enters comes back).
//! Parameters: the Chebyshev coefficients a_kj of ln(A_k/α²) and b_kj of
//! the bounded rate parameter θ_k (B_k = [`super::exp_mixture`]'s rate of θ_k)
//! in t = 2·sqrt(1 − α) − 1. With c_kij the ring term of component k and
//! T_j = T_j(t_i): ∂m_ij/∂a_kj = c_kij·T_j,
//! ∂m_ij/∂b_kj = (∂c_kij/∂ln B)·(∂ln B/∂θ)·T_j.
//!
//! Initialisation (no label switching, no hand tuning): every profile is
//! fitted alone (K exponentials, rates sorted), rank k is followed across
//! albedos, polynomials in t are fitted to ln(A_k/α²) and θ_k weighted by the
//! component's energy share, and Levenberg–Marquardt refines everything
//! jointly. A profile whose own fit fails stops the fit (an error naming
//! it).

use super::exp_mixture::{BinnedDensity, Order, fit_mixture, safe_exp, theta_from_rate};
use super::lm::{Blocks, FitError, FitOptions, FitReport, solve};
use crate::forward::medium::Source;
use crate::forward::medium::{Incidence, Observable};
use crate::forward::profile::ProfileDoc;
use crate::metamodel::basis::{
    B_MAX, BASIS_FORMAT, BASIS_VERSION, BasisModel, ExpMixture, albedo_coordinate, chebyshev,
    component_bin, rate_from_theta,
};
use levenberg_marquardt::LeastSquaresProblem;
use nalgebra::{DMatrix, DVector, Dyn, Owned};

/// σ of the α = 1 energy constraint (absolute, in units of R_d).
pub const ENERGY_CONSTRAINT_SIGMA: f64 = 1e-3;

/// One training profile, ready for fitting.
pub struct TrainingProfile {
    pub alpha: f64,
    pub multi: BinnedDensity,
    pub single: BinnedDensity,
}

impl TrainingProfile {
    /// The profile of `observable` in `doc`.
    pub fn from_doc(doc: &ProfileDoc, observable: Observable) -> Self {
        TrainingProfile {
            alpha: doc.config.medium.alpha,
            multi: BinnedDensity::from_profile(doc, Order::Multi, observable),
            single: BinnedDensity::from_profile(doc, Order::Single, observable),
        }
    }
}

/// The joint least-squares problem.
pub struct BasisFit<'a> {
    pub data: &'a [TrainingProfile],
    pub k: usize,
    pub degree: usize,
    /// R₁ at α = 1 and R_sp: the target of the energy constraint.
    pub single_energy: f64,
    pub r_sp: f64,
    /// Whether the α = 1 energy constraint holds (exitance: all light that
    /// enters a conservative half-space leaves; the normal radiance has no
    /// such law).
    pub energy_constraint: bool,
    /// (a_kj…, b_kj…), each K × (degree + 1), row-major.
    pub theta: DVector<f64>,
}

impl BasisFit<'_> {
    fn n_coef(&self) -> usize {
        self.degree + 1
    }

    fn t_of(&self, alpha: f64) -> Vec<f64> {
        let mut t = vec![0.0; self.n_coef()];
        chebyshev(2.0 * albedo_coordinate(alpha) - 1.0, self.degree, &mut t);
        t
    }

    /// (A_k, B_k, d ln B_k/dθ_k) at α and the Chebyshev values used.
    #[allow(clippy::type_complexity)]
    fn components(&self, alpha: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let t = self.t_of(alpha);
        let nc = self.n_coef();
        let off = self.k * nc;
        let dot = |start: usize| (0..nc).map(|j| self.theta[start + j] * t[j]).sum::<f64>();
        let a = (0..self.k)
            .map(|k| alpha * alpha * safe_exp(dot(k * nc)))
            .collect();
        let (b, db) = (0..self.k)
            .map(|k| rate_from_theta(dot(off + k * nc)))
            .unzip();
        (a, b, db, t)
    }

    /// The model this parameter vector describes.
    pub fn model(
        &self,
        (incidence, observable): (Incidence, Observable),
        single: ExpMixture,
        albedo_range: (f64, f64),
        eta: f64,
        g: f64,
        provenance: serde_json::Value,
    ) -> BasisModel {
        let nc = self.n_coef();
        let rows = |start: usize| {
            (0..self.k)
                .map(|k| self.theta.as_slice()[start + k * nc..start + (k + 1) * nc].to_vec())
                .collect()
        };
        BasisModel {
            format: BASIS_FORMAT.into(),
            version: BASIS_VERSION,
            eta,
            g,
            incidence,
            observable,
            degree: self.degree,
            ln_a: rows(0),
            ln_b: rows(self.k * nc),
            single,
            albedo_range,
            r_sp: self.r_sp,
            provenance,
        }
    }

    fn n_residuals(&self) -> usize {
        self.data.iter().map(|d| d.multi.len()).sum::<usize>() + usize::from(self.energy_constraint)
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for BasisFit<'_> {
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
        let mut r = DVector::zeros(self.n_residuals());
        let mut row = 0;
        for p in self.data {
            let (a, b, _, _) = self.components(p.alpha);
            let d = &p.multi;
            for j in 0..d.len() {
                let m: f64 = (0..self.k)
                    .map(|k| component_bin(a[k], b[k], 1, d.lo[j], d.hi[j]).0)
                    .sum();
                r[row] = (m - d.y[j]) / d.sigma[j];
                row += 1;
            }
        }
        if self.energy_constraint {
            let (a, b, _, _) = self.components(1.0);
            let e: f64 = a.iter().zip(&b).map(|(a, b)| a / (b * b)).sum();
            r[row] = (e + self.single_energy - (1.0 - self.r_sp)) / ENERGY_CONSTRAINT_SIGMA;
        }
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let nc = self.n_coef();
        let off = self.k * nc;
        let mut jac = DMatrix::zeros(self.n_residuals(), self.theta.len());
        let mut row = 0;
        for p in self.data {
            let (a, b, db, t) = self.components(p.alpha);
            let d = &p.multi;
            for j in 0..d.len() {
                for k in 0..self.k {
                    let (c, dlnb) = component_bin(a[k], b[k], 1, d.lo[j], d.hi[j]);
                    for (q, tq) in t.iter().enumerate() {
                        jac[(row, k * nc + q)] = c * tq / d.sigma[j];
                        jac[(row, off + k * nc + q)] = dlnb * db[k] * tq / d.sigma[j];
                    }
                }
                row += 1;
            }
        }
        let (a, b, db, t) = self.components(1.0);
        for k in (0..self.k).filter(|_| self.energy_constraint) {
            // E_k = A_k/B_k²: ∂E_k/∂ln A = E_k, ∂E_k/∂ln B = −2E_k.
            let e_k = a[k] / (b[k] * b[k]);
            for (q, tq) in t.iter().enumerate() {
                jac[(row, k * nc + q)] = e_k * tq / ENERGY_CONSTRAINT_SIGMA;
                jac[(row, off + k * nc + q)] = -2.0 * e_k * db[k] * tq / ENERGY_CONSTRAINT_SIGMA;
            }
        }
        jac.iter().all(|v| v.is_finite()).then_some(jac)
    }
}

impl Blocks for BasisFit<'_> {
    fn blocks(&self) -> Vec<(String, std::ops::Range<usize>)> {
        let mut out = Vec::new();
        let mut row = 0;
        for p in self.data {
            out.push((format!("alpha={:.6}", p.alpha), row..row + p.multi.len()));
            row += p.multi.len();
        }
        if self.energy_constraint {
            out.push(("energy(alpha=1)".into(), row..row + 1));
        }
        out
    }
}

/// Weighted least-squares polynomial (Chebyshev in t) fit: coefficients c
/// minimising Σ w_i (Σ_j c_j T_j(t_i) − y_i)².
fn poly_fit(t: &[f64], y: &[f64], w: &[f64], degree: usize) -> Vec<f64> {
    let n = t.len();
    let mut basis = vec![0.0; degree + 1];
    let mut design = DMatrix::zeros(n, degree + 1);
    for i in 0..n {
        chebyshev(t[i], degree, &mut basis);
        for j in 0..=degree {
            design[(i, j)] = basis[j] * w[i].sqrt();
        }
    }
    let rhs = DVector::from_iterator(n, (0..n).map(|i| y[i] * w[i].sqrt()));
    let c = design
        .svd(true, true)
        .solve(&rhs, 1e-12)
        .unwrap_or_else(|_| DVector::zeros(degree + 1));
    c.iter().cloned().collect()
}

/// Pools the single-scattering densities of all profiles into p₁(r; α = 1):
/// each profile gives y/α with error σ/α; inverse-variance weighted mean.
pub fn pooled_single(data: &[TrainingProfile]) -> BinnedDensity {
    let first = &data[0].single;
    let mut out = first.clone();
    for j in 0..first.len() {
        let (mut sw, mut swy) = (0.0, 0.0);
        for p in data.iter().filter(|p| p.alpha > 0.0) {
            let (y, s) = (p.single.y[j] / p.alpha, p.single.sigma[j] / p.alpha);
            sw += 1.0 / (s * s);
            swy += y / (s * s);
        }
        out.y[j] = swy / sw;
        out.sigma[j] = (1.0 / sw).sqrt();
    }
    out
}

/// ∫L₁ dA (sr⁻¹ per unit incident power) of the radiance along the normal
/// from single scattering under normal incidence at α = 1: the first vertex
/// lies straight below x_i at depth z ~ σ_t e^{−σ_t z} and sends
/// f_HG(−1)·e^{−σ_t z}·T(1)/η² back up the same line, so
/// L₁ = (1 − R_sp)·f_HG(−1)·T(1)/(2η²), all of it at x_i, independent of σ_t.
pub fn pencil_single_radiance(g: f64, eta: f64) -> f64 {
    (1.0 - crate::forward::fresnel::r_specular(eta))
        * crate::forward::sampling::hg_pdf(g, -1.0)
        * crate::forward::walk::normal_exit_factor(eta)
        / 2.0
}

/// The report of a closed-form mixture against binned data (nothing
/// fitted: every degree of freedom is a bin).
fn closed_form_report(what: &str, data: &BinnedDensity, model: &ExpMixture) -> FitReport {
    let chi2: f64 = (0..data.len())
        .map(|j| {
            let m = if data.hi[j].is_infinite() {
                model.energy() - model.cdf(data.lo[j])
            } else {
                model.bin_mean(data.lo[j], data.hi[j])
            };
            ((m - data.y[j]) / data.sigma[j]).powi(2)
        })
        .sum();
    let dof = data.len();
    FitReport {
        what: what.into(),
        termination: "closed form".into(),
        success: true,
        evaluations: 1,
        chi2,
        dof,
        chi2_per_dof: chi2 / dof.max(1) as f64,
        block_rms: vec![("all".into(), (chi2 / dof.max(1) as f64).sqrt())],
        wall_s: 0.0,
    }
}

/// A point mass of `energy` at r = 0 as an exponential of the largest rate
/// the basis allows (a decay length of 1/[`B_MAX`] = 1e-4 MFP, far below a
/// texel): evaluated, integrated and sampled like every other component.
pub fn point_single(energy: f64) -> ExpMixture {
    ExpMixture {
        a: vec![energy * B_MAX],
        b: vec![B_MAX],
        power: 0,
    }
}

/// Everything a basis fit produces.
pub struct BasisFitOutcome {
    pub model: BasisModel,
    pub joint: FitReport,
    pub single: FitReport,
    /// Per-profile (unsmoothed) fits, for the report.
    pub per_profile: Vec<(f64, ExpMixture, FitReport)>,
}

/// Fits the smooth model with `k` components and polynomial `degree` to
/// `docs` (all of one medium and illumination).
pub fn fit_basis(
    docs: &[ProfileDoc],
    observable: Observable,
    k: usize,
    degree: usize,
    opts: &FitOptions,
    provenance: serde_json::Value,
) -> Result<BasisFitOutcome, FitError> {
    let bad = |msg: String| FitError::BadData {
        what: "basis".into(),
        msg,
    };
    if docs.len() < degree + 2 {
        return Err(bad(format!(
            "{} profiles: need at least degree + 2 = {}",
            docs.len(),
            degree + 2
        )));
    }
    let c0 = &docs[0].config;
    if let Some(d) = docs.iter().find(|d| {
        d.config.medium.eta != c0.medium.eta
            || d.config.medium.g != c0.medium.g
            || d.config.source != c0.source
            || d.config.bins != c0.bins
    }) {
        return Err(bad(format!(
            "profile at α = {} has another medium, source or binning than the first",
            d.config.medium.alpha
        )));
    }
    // The basis is a point-source profile: a disk source's bins carry its
    // power πR² and its exitance is the profile convolved with the disk.
    if let Source::Collimated { radius } | Source::Diffuse { radius } = c0.source
        && radius > 0.0
    {
        return Err(bad(format!(
            "profiles of a disk source (radius {radius} MFP): the basis is fitted to point \
             sources (pencil, or diffuse at a point)"
        )));
    }
    if let Some(d) = docs.iter().find(|d| d.observed(observable).is_none()) {
        return Err(bad(format!(
            "profile at α = {} holds no radiance tally (simulate it with --radiance)",
            d.config.medium.alpha
        )));
    }
    let mut data: Vec<TrainingProfile> = docs
        .iter()
        .map(|d| TrainingProfile::from_doc(d, observable))
        .collect();
    data.sort_by(|a, b| a.alpha.total_cmp(&b.alpha));

    // Single scattering at α = 1, pooled over all profiles; in closed form
    // for the normal radiance under normal incidence, a point at x_i.
    let pooled = pooled_single(&data);
    let (single, single_rep) = match (observable, c0.source.incidence()) {
        (Observable::Radiance, Incidence::Pencil) => {
            let m = &c0.medium;
            let energy = pencil_single_radiance(m.g, m.eta);
            let model = point_single(energy);
            let report =
                closed_form_report("single scattering L1(r; 1), closed form", &pooled, &model);
            (model, report)
        }
        _ => fit_mixture("single scattering p1(r; 1)", &pooled, k.min(4), 0, opts)?,
    };

    // Per-profile fits: the joint fit's starting point, and diagnostics for
    // the report (non-convergence is recorded there; bad data is an error).
    let lenient = FitOptions {
        allow_nonconvergence: true,
        ..*opts
    };
    let mut per_profile = Vec::new();
    for p in &data {
        let (m, rep) = fit_mixture(
            &format!("p_m(r; α = {:.6})", p.alpha),
            &p.multi,
            k,
            1,
            &lenient,
        )?;
        per_profile.push((p.alpha, m, rep));
    }

    // ---- initialisation from the per-profile fits ---------------------------
    // Components sorted by rate at every albedo; rank k is followed across
    // albedos, and polynomials in t are fitted to ln(A_k/α²) and to the
    // bounded-rate parameter θ_k, weighted by the component's energy share.
    let ts: Vec<f64> = data
        .iter()
        .map(|p| 2.0 * albedo_coordinate(p.alpha) - 1.0)
        .collect();
    let nc = degree + 1;
    let mut theta = DVector::zeros(2 * k * nc);
    for kk in 0..k {
        let (mut ya, mut yb, mut w) = (Vec::new(), Vec::new(), Vec::new());
        for (alpha, m, _) in &per_profile {
            let share = m.component_energy(kk) / m.energy().max(1e-300);
            ya.push((m.a[kk].max(1e-300) / (alpha * alpha).max(1e-300)).ln());
            yb.push(theta_from_rate(m.b[kk]));
            w.push(share + 1e-3);
        }
        let (ca, cb) = (
            poly_fit(&ts, &ya, &w, degree),
            poly_fit(&ts, &yb, &w, degree),
        );
        for q in 0..nc {
            theta[kk * nc + q] = ca[q];
            theta[k * nc + kk * nc + q] = cb[q];
        }
    }

    let r_sp = docs[0].R_sp;
    let problem = BasisFit {
        data: &data,
        k,
        degree,
        single_energy: single.energy(),
        r_sp,
        energy_constraint: observable == Observable::Exitance,
        theta,
    };
    let (solved, joint) = solve("basis (joint, all albedos)", problem, opts)?;
    let range = (data[0].alpha, data[data.len() - 1].alpha);
    let model = solved.model(
        (c0.source.incidence(), observable),
        single,
        range,
        c0.medium.eta,
        c0.medium.g,
        provenance,
    );
    Ok(BasisFitOutcome {
        model,
        joint,
        single: single_rep,
        per_profile,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::lm::jacobian_mismatch;
    use crate::forward::rng::PathRng;

    /// Synthetic profiles from a known smooth model.
    fn synthetic_data() -> Vec<TrainingProfile> {
        let mut rng = PathRng::new(9, 0);
        let edges: Vec<f64> = std::iter::once(0.0)
            .chain((0..=100).map(|k| 1e-3 * 10f64.powf(k as f64 / 20.0)))
            .collect();
        (0..8)
            .map(|i| {
                let alpha = 1.0 - (0.9 - 0.1 * i as f64).powi(2);
                let x = (1.0 - alpha).sqrt();
                let m = ExpMixture {
                    a: vec![0.3 * alpha * alpha, 0.05 * alpha * alpha],
                    b: vec![5.0 + x, 0.3 + 2.0 * x],
                    power: 1,
                };
                let mut d = BinnedDensity {
                    lo: vec![],
                    hi: vec![],
                    y: vec![],
                    sigma: vec![],
                };
                for w in edges.windows(2) {
                    let t = m.bin_mean(w[0], w[1]);
                    d.lo.push(w[0]);
                    d.hi.push(w[1]);
                    d.y.push(t * (1.0 + 0.01 * (rng.uniform() - 0.5)));
                    d.sigma.push(0.01 * t + 1e-8);
                }
                TrainingProfile {
                    alpha,
                    multi: d.clone(),
                    single: d,
                }
            })
            .collect()
    }

    #[test]
    fn jacobian_matches_numerical() {
        let data = synthetic_data();
        let mut rng = PathRng::new(4, 0);
        for _ in 0..3 {
            let (k, degree) = (2, 3);
            let theta = DVector::from_iterator(
                2 * k * (degree + 1),
                (0..2 * k * (degree + 1)).map(|_| rng.uniform() - 0.5),
            );
            let mut p = BasisFit {
                data: &data,
                k,
                degree,
                single_energy: 0.05,
                r_sp: 0.04,
                energy_constraint: true,
                theta,
            };
            let err = jacobian_mismatch(&mut p);
            assert!(err < 1e-5, "relative Jacobian error {err}");
        }
    }
}
