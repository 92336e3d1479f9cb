//! Tolerances shared by the tests, each with the rule it encodes, and the
//! shipped models for unit tests.

/// Closed-form identities evaluated in f64.
pub const REL_CLOSED_FORM: f64 = 1e-12;
/// Numerical quadrature against a closed form.
pub const REL_QUADRATURE: f64 = 1e-8;
/// Monte Carlo checks pass within `Z_MC` of the estimate's own standard error
/// (plus the stated accuracy of the reference value). Four sigma: a false
/// alarm rate of 6e-5 per check.
pub const Z_MC: f64 = 4.0;
/// Significance level of the χ² sampler tests.
pub const CHI2_ALPHA: f64 = 1e-4;

/// Upper quantile of the χ² distribution with `dof` degrees of freedom at
/// tail probability `alpha`, by the Wilson–Hilferty approximation (relative
/// error < 1 % for dof ≥ 10, which is all the tests use).
pub fn chi2_critical(dof: usize, alpha: f64) -> f64 {
    let k = dof as f64;
    let z = normal_upper_quantile(alpha);
    let h = 2.0 / (9.0 * k);
    k * (1.0 - h + z * h.sqrt()).powi(3)
}

/// A standard normal deviate from `rng` (Box–Muller).
pub fn standard_normal(rng: &mut crate::forward::rng::PathRng) -> f64 {
    let (u1, u2) = (1.0 - rng.uniform(), rng.uniform());
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// z with P(Z > z) = alpha for a standard normal, by bisection on erfc.
pub fn normal_upper_quantile(alpha: f64) -> f64 {
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if 0.5 * erfc(mid / std::f64::consts::SQRT_2) > alpha {
            lo = mid
        } else {
            hi = mid
        }
    }
    0.5 * (lo + hi)
}

/// Complementary error function (Numerical Recipes `erfcc`, |rel err| < 1.2e-7).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.26551223
            + t * (1.00002368
                + t * (0.37409196
                    + t * (0.09678418
                        + t * (-0.18628806
                            + t * (0.27886807
                                + t * (-1.13520398
                                    + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277)))))))))
            .exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

/// Pearson's χ² statistic of observed counts against expected counts; bins
/// with expectation below 5 are pooled into their neighbour first.
pub fn chi2_statistic(observed: &[u64], expected: &[f64]) -> (f64, usize) {
    let (mut obs, mut exp) = (Vec::new(), Vec::new());
    let (mut o_acc, mut e_acc) = (0.0, 0.0);
    for (&o, &e) in observed.iter().zip(expected) {
        o_acc += o as f64;
        e_acc += e;
        if e_acc >= 5.0 {
            obs.push(o_acc);
            exp.push(e_acc);
            o_acc = 0.0;
            e_acc = 0.0;
        }
    }
    if e_acc > 0.0
        && let (Some(lo), Some(le)) = (obs.last_mut(), exp.last_mut())
    {
        *lo += o_acc;
        *le += e_acc;
    }
    let stat = obs
        .iter()
        .zip(&exp)
        .map(|(o, e)| (o - e) * (o - e) / e)
        .sum();
    (stat, exp.len().saturating_sub(1))
}

/// The shipped basis BSSRDF (pencil incidence), parsed from the copy built
/// into the crate.
pub fn shipped_basis() -> crate::metamodel::basis::BasisModel {
    crate::doc::from_json(
        include_str!("../data/profiles/basis.json"),
        std::path::Path::new("data/profiles/basis.json"),
    )
    .expect("the shipped basis model parses")
}

/// The shipped kernel meta-model, parsed from the copy built into the crate.
pub fn shipped_meta() -> crate::metamodel::meta::MetaModelFile {
    crate::doc::from_json(
        include_str!("../data/profiles/metamodel.json"),
        std::path::Path::new("data/profiles/metamodel.json"),
    )
    .expect("the shipped meta-model parses")
}
