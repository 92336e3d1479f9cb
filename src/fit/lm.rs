//! The least-squares layer: every fit in svkernel is a
//! [`levenberg_marquardt::LeastSquaresProblem`] solved by [`solve`], which
//! returns the solved problem with a [`FitReport`] — never a silent result.
//!
//! Conventions shared by every problem:
//! * parameters live in unconstrained space (logarithms of positive
//!   quantities), so any parameter vector is a valid model;
//! * residuals are weighted by the data's standard errors,
//!   r_j = (model_j − y_j)/σ_j, so the cost 2·f = Σ r_j² is a χ²;
//! * Jacobians are exact (analytic) and checked against
//!   [`levenberg_marquardt::differentiate_numerically`] in each module's tests.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::time::Instant;

/// Errors of a fit.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitError {
    /// The optimiser stopped without meeting a convergence criterion.
    #[error(
        "{what}: Levenberg–Marquardt did not converge ({termination}) after {evaluations} evaluations, χ²/dof = {chi2_per_dof:.4}"
    )]
    NotConverged {
        what: String,
        termination: String,
        evaluations: usize,
        chi2_per_dof: f64,
    },
    /// The data cannot be fitted (too few points, no signal).
    #[error("{what}: {msg}")]
    BadData { what: String, msg: String },
}

/// A problem whose residuals come in named blocks (e.g. one per albedo), for
/// the per-block RMS of the report.
pub trait Blocks {
    /// `(name, residual index range)` of each block.
    fn blocks(&self) -> Vec<(String, Range<usize>)>;
}

/// What a fit reports.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FitReport {
    /// What was fitted.
    pub what: String,
    /// Levenberg–Marquardt's termination reason.
    pub termination: String,
    pub success: bool,
    /// Residual evaluations.
    pub evaluations: usize,
    /// χ² = Σ r_j² at the optimum.
    pub chi2: f64,
    /// Residuals minus parameters.
    pub dof: usize,
    pub chi2_per_dof: f64,
    /// RMS of the weighted residuals per block.
    pub block_rms: Vec<(String, f64)>,
    pub wall_s: f64,
}

/// Solver settings.
#[derive(Clone, Copy, Debug)]
pub struct FitOptions {
    /// Maximum evaluations, as a multiple of (parameters + 1).
    pub patience: usize,
    /// Relative tolerance of `ftol`, `xtol` (LM's defaults are 1e-15·…).
    pub tol: f64,
    /// Accept a fit that did not converge (the report says so).
    pub allow_nonconvergence: bool,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            patience: 200,
            tol: 1e-12,
            allow_nonconvergence: false,
        }
    }
}

/// Levenberg–Marquardt's termination reason in words.
fn describe(t: &levenberg_marquardt::TerminationReason) -> String {
    use levenberg_marquardt::TerminationReason as T;
    match t {
        T::Converged {
            ftol: true,
            xtol: true,
        } => "converged (relative χ² change and step below tolerance)".into(),
        T::Converged { ftol: true, .. } => "converged (relative χ² change below tolerance)".into(),
        T::Converged { .. } => "converged (relative step below tolerance)".into(),
        T::ResidualsZero => "converged (residuals zero)".into(),
        T::Orthogonal => "converged (residuals orthogonal to the Jacobian)".into(),
        T::LostPatience => "stopped: evaluation budget spent".into(),
        T::NoImprovementPossible(what) => {
            format!("stopped: no further improvement possible ({what})")
        }
        T::Numerical(what) => format!("stopped: numerical problem ({what})"),
        T::User(what) => format!("stopped: {what}"),
        T::NoParameters => "nothing to fit: no parameters".into(),
        T::NoResiduals => "nothing to fit: no residuals".into(),
        T::WrongDimensions(what) => format!("wrong dimensions ({what})"),
    }
}

/// Solves `problem` from its current parameters.
pub fn solve<P>(what: &str, problem: P, opts: &FitOptions) -> Result<(P, FitReport), FitError>
where
    P: LeastSquaresProblem<f64, Dyn, Dyn, ResidualStorage = Owned<f64, Dyn>> + Blocks,
{
    let start = Instant::now();
    let lm = LevenbergMarquardt::new()
        .with_ftol(opts.tol)
        .with_xtol(opts.tol)
        .with_gtol(1e-14)
        .with_patience(opts.patience);
    let (problem, lm_report) = lm.minimize(problem);
    let success = lm_report.termination.was_successful()
        // "No improvement possible" at our tight tolerance means the optimum
        // is resolved to machine precision: a success for our purposes.
        || matches!(lm_report.termination, levenberg_marquardt::TerminationReason::NoImprovementPossible(_));
    let rep = report(
        what,
        &problem,
        describe(&lm_report.termination),
        success,
        lm_report.number_of_evaluations,
        start,
    );
    accept(what, problem, rep, opts)
}

/// A compressed least-squares system: (χ², Ĵ, r̂) ([`CompressedJacobian`]).
pub type Compressed = (f64, DMatrix<f64>, DVector<f64>);

/// Relative step below which [`solve_compressed`] stops (converged).
pub const STEP_TOL: f64 = 1e-10;

/// A problem that hands [`solve_compressed`] its Jacobian compressed: a
/// short matrix Ĵ and vector r̂ with ĴᵀĴ = JᵀJ and Ĵᵀr̂ = Jᵀr, so that
/// ‖J h + r‖² = ‖Ĵ h + r̂‖² + (‖r‖² − ‖r̂‖²) for every step h. Worth it where
/// the Jacobian is tall and structured: in the joint meta-model fit each
/// cell's ~10³ residuals depend on 3K − 1 numbers of its own, so a QR of
/// each cell's small Jacobian compresses it to 3K − 1 rows, while the full
/// Jacobian has ~10⁵ rows. Unlike the normal equations, the compressed
/// system keeps the Jacobian's condition number rather than squaring it.
pub trait CompressedJacobian:
    LeastSquaresProblem<
        f64,
        Dyn,
        Dyn,
        ResidualStorage = Owned<f64, Dyn>,
        ParameterStorage = Owned<f64, Dyn>,
    >
{
    /// (χ² = ‖r‖², Ĵ, r̂) at the current parameters; `None` if not finite.
    fn compressed(&self) -> Option<Compressed>;
}

/// Solves `problem` from its current parameters by Levenberg–Marquardt on
/// its compressed Jacobian ([`CompressedJacobian`]), starting with damping
/// μ = `initial_damping` (1e-3 is the usual choice). The step h minimises
/// ‖Ĵh + r̂‖² + μ‖Dh‖², by QR of the stacked [Ĵ; √μ·D], with Marquardt's
/// scaling D = diag of Ĵ's column norms; the damping μ follows the gain
/// ratio ϱ = (χ² − χ²(x + h)) / (‖r̂‖² − ‖Ĵh + r̂‖²) as in Madsen, Nielsen &
/// Tingleff, *Methods for non-linear least squares problems* (2004),
/// Algorithm 3.16 (μ ← μ·max(⅓, 1 − (2ϱ − 1)³) on success, μ ← μν, ν ← 2ν on
/// failure). It stops when an accepted step lowers χ² by a relative
/// `opts.tol` or less and predicted no more (converged, MINPACK's `ftol`
/// test), when a step is below [`STEP_TOL`] relative to the parameters
/// (`xtol`), or after `opts.patience`·(n + 1) evaluations. Same report and
/// errors as [`solve`].
pub fn solve_compressed<P>(
    what: &str,
    mut problem: P,
    opts: &FitOptions,
    initial_damping: f64,
) -> Result<(P, FitReport), FitError>
where
    P: CompressedJacobian + Blocks,
{
    let start = Instant::now();
    let mut x = problem.params();
    let n = x.len();
    let budget = opts.patience * (n + 1);
    let mut evaluations = 1;
    let not_finite = |evaluations| FitError::NotConverged {
        what: what.to_string(),
        termination: "stopped: numerical problem (non-finite χ²)".into(),
        evaluations,
        chi2_per_dof: f64::INFINITY,
    };
    let Some((mut chi2, mut jac, mut res)) = problem.compressed() else {
        return Err(not_finite(evaluations));
    };
    let (mut mu, mut nu): (f64, f64) = (initial_damping, 2.0);
    let termination = loop {
        if evaluations >= budget {
            break (false, "stopped: evaluation budget spent".to_string());
        }
        if mu > 1e30 {
            break (true, "converged (no step lowers χ²)".to_string());
        }
        let m = jac.nrows();
        let norms: Vec<f64> = (0..n).map(|j| jac.column(j).norm()).collect();
        let nmax = norms.iter().copied().fold(0.0, f64::max).max(1e-300);
        let mut stacked = DMatrix::zeros(m + n, n);
        stacked.rows_mut(0, m).copy_from(&jac);
        for (j, v) in norms.iter().enumerate() {
            stacked[(m + j, j)] = mu.sqrt() * v.max(1e-12 * nmax);
        }
        let mut rhs = DVector::zeros(m + n);
        rhs.rows_mut(0, m).copy_from(&(-&res));
        let qr = stacked.qr();
        let Some(h) = qr.r().solve_upper_triangular(&(qr.q().tr_mul(&rhs))) else {
            mu *= nu;
            nu *= 2.0;
            continue;
        };
        if !h.iter().all(|v| v.is_finite()) {
            mu *= nu;
            nu *= 2.0;
            continue;
        }
        if h.norm() <= STEP_TOL * (x.norm() + STEP_TOL) {
            break (
                true,
                "converged (relative step below tolerance)".to_string(),
            );
        }
        let predicted = res.norm_squared() - (&jac * &h + &res).norm_squared();
        let trial = &x + &h;
        problem.set_params(&trial);
        evaluations += 1;
        let new = problem.residuals().map(|r| r.norm_squared());
        match new {
            Some(c) if c.is_finite() && c < chi2 && predicted > 0.0 => {
                let rho = (chi2 - c) / predicted;
                let gain = (chi2 - c) / chi2;
                let predicted_gain = predicted / chi2;
                x = trial;
                let Some(next) = problem.compressed() else {
                    return Err(not_finite(evaluations));
                };
                (chi2, jac, res) = next;
                mu *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
                nu = 2.0;
                if gain <= opts.tol && predicted_gain <= opts.tol {
                    break (
                        true,
                        "converged (relative χ² change below tolerance)".to_string(),
                    );
                }
            }
            _ => {
                problem.set_params(&x);
                mu *= nu;
                nu *= 2.0;
            }
        }
    };
    problem.set_params(&x);
    let (success, termination) = termination;
    let rep = report(what, &problem, termination, success, evaluations, start);
    accept(what, problem, rep, opts)
}

/// The solved problem and its report, or the error if the fit did not
/// converge (and `opts` does not allow that) or χ² is not finite.
fn accept<P>(
    what: &str,
    problem: P,
    rep: FitReport,
    opts: &FitOptions,
) -> Result<(P, FitReport), FitError> {
    if !rep.success && !opts.allow_nonconvergence || !rep.chi2.is_finite() {
        return Err(FitError::NotConverged {
            what: what.to_string(),
            termination: rep.termination,
            evaluations: rep.evaluations,
            chi2_per_dof: rep.chi2_per_dof,
        });
    }
    Ok((problem, rep))
}

/// The report of a solved problem at its current parameters.
fn report<P>(
    what: &str,
    problem: &P,
    termination: String,
    success: bool,
    evaluations: usize,
    start: Instant,
) -> FitReport
where
    P: LeastSquaresProblem<f64, Dyn, Dyn, ResidualStorage = Owned<f64, Dyn>> + Blocks,
{
    let r = problem.residuals();
    let chi2 = r.as_ref().map_or(f64::INFINITY, |r| r.norm_squared());
    let n_params = problem.params().len();
    let blocks = problem.blocks();
    let n_res = blocks.iter().map(|b| b.1.end).max().unwrap_or(0);
    let dof = n_res.saturating_sub(n_params).max(1);
    let block_rms = blocks
        .into_iter()
        .map(|(name, range)| {
            let n = range.len().max(1) as f64;
            let s = r
                .as_ref()
                .map_or(f64::NAN, |r| r.rows_range(range).norm_squared());
            (name, (s / n).sqrt())
        })
        .collect();
    FitReport {
        what: what.to_string(),
        termination,
        success,
        evaluations,
        chi2,
        dof,
        chi2_per_dof: chi2 / dof as f64,
        block_rms,
        wall_s: start.elapsed().as_secs_f64(),
    }
}

/// Largest relative difference between a problem's analytic Jacobian and a
/// numerical one at its current parameters, relative to the column norm
/// (test helper). The numerical Jacobian is a Richardson-extrapolated central
/// difference of whole residual vectors (O(n) evaluations;
/// `levenberg_marquardt::differentiate_numerically` re-evaluates all
/// residuals per entry, O(m·n), too slow for the joint fits).
pub fn jacobian_mismatch<P>(problem: &mut P) -> f64
where
    P: LeastSquaresProblem<
            f64,
            Dyn,
            Dyn,
            JacobianStorage = Owned<f64, Dyn, Dyn>,
            ParameterStorage = Owned<f64, Dyn>,
            ResidualStorage = Owned<f64, Dyn>,
        >,
{
    let analytic = problem.jacobian().expect("jacobian");
    let x0 = problem.params();
    let mut numeric = analytic.clone();
    for c in 0..x0.len() {
        let h = 1e-4 * x0[c].abs().max(1.0);
        let mut at = |dx: f64| {
            let mut x = x0.clone();
            x[c] += dx;
            problem.set_params(&x);
            problem.residuals().expect("residuals")
        };
        let d1 = (at(h) - at(-h)) / (2.0 * h);
        let d2 = (at(h / 2.0) - at(-h / 2.0)) / h;
        numeric.set_column(c, &((4.0 * d2 - d1) / 3.0));
    }
    problem.set_params(&x0);
    let mut worst: f64 = 0.0;
    for c in 0..analytic.ncols() {
        let scale = numeric.column(c).norm().max(1e-300);
        let diff = (analytic.column(c) - numeric.column(c)).norm();
        // NaN (an analytic or numeric entry that is not a number) must
        // show, not be dropped by f64::max.
        let rel = diff / scale;
        if rel.is_nan() || rel > worst {
            worst = rel;
        }
    }
    worst
}

/// Non-negative least squares: minimises ‖A x − b‖ subject to x ≥ 0 by the
/// active-set method of Lawson & Hanson (1974, ch. 23). Used to initialise
/// the linear amplitudes of exponential mixtures.
pub fn nnls(a: &nalgebra::DMatrix<f64>, b: &DVector<f64>) -> DVector<f64> {
    let n = a.ncols();
    let mut x = DVector::zeros(n);
    let mut passive = vec![false; n];
    let tol = 1e-12 * a.norm() * b.norm().max(1e-300);
    for _outer in 0..3 * n + 10 {
        let w = a.transpose() * (b - a * &x);
        let candidate = (0..n)
            .filter(|&j| !passive[j] && w[j] > tol)
            .max_by(|&i, &j| w[i].total_cmp(&w[j]));
        let Some(j) = candidate else { break };
        passive[j] = true;
        for _inner in 0..3 * n + 10 {
            let idx: Vec<usize> = (0..n).filter(|&k| passive[k]).collect();
            let sub = a.select_columns(&idx);
            let Some(z_p) = sub.clone().svd(true, true).solve(b, 1e-14).ok() else {
                break;
            };
            if z_p.iter().all(|&v| v > 0.0) {
                for (t, &k) in idx.iter().enumerate() {
                    x[k] = z_p[t];
                }
                break;
            }
            // Step back to the boundary and drop the variables that hit zero.
            let mut step = 1.0f64;
            for (t, &k) in idx.iter().enumerate() {
                if z_p[t] <= 0.0 {
                    step = step.min(x[k] / (x[k] - z_p[t]));
                }
            }
            for (t, &k) in idx.iter().enumerate() {
                x[k] += step * (z_p[t] - x[k]);
                if x[k] <= 1e-300 {
                    x[k] = 0.0;
                    passive[k] = false;
                }
            }
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    #[test]
    fn nnls_matches_known_solution() {
        // Unconstrained optimum has a negative component; NNLS clamps it and
        // re-solves the rest.
        let a = DMatrix::from_row_slice(4, 2, &[1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, -1.0]);
        let b = DVector::from_vec(vec![2.0, -1.0, 1.0, 3.0]);
        let x = nnls(&a, &b);
        assert!(x.iter().all(|&v| v >= 0.0));
        // With x1 = 0: minimise (x0−2)² + 1 + (x0−1)² + (x0−3)² → x0 = 2.
        assert!((x[0] - 2.0).abs() < 1e-10 && x[1] == 0.0, "{x}");
        // A positive problem is solved exactly.
        let b2 = &a * DVector::from_vec(vec![0.5, 1.5]);
        let x2 = nnls(&a, &b2);
        assert!((x2[0] - 0.5).abs() < 1e-10 && (x2[1] - 1.5).abs() < 1e-10);
    }
}
