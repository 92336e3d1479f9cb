//! The basis BSSRDF (docs/design.md §3 step 2a, §4): radial densities as exponential
//! mixtures, smooth in albedo. Pure evaluation, closed forms and sampling;
//! the fitting lives in [`crate::fit::basis`].

use serde::{Deserialize, Serialize};

/// A radial density p(r) = Σ_k A_k·r^n·e^{−B_k r} (1/MFP) with A_k, B_k > 0
/// and n = `power` ∈ {0, 1}.
///
/// n = 0 suits densities finite at r = 0 (single scattering: p₁(0) > 0).
/// n = 1 is a mixture of exponentials in the *exitance*,
/// R(r) = p(r)/(2πr) = Σ (A_k/2π) e^{−B_k r}: the seed's form of the BSSRDF
/// S ≅ Σ A_i e^{−r B_i}. It gives p(0) = 0, which multiple scattering has
/// (the simulated p_m vanishes at r → 0 and rises), and which no positive
/// mixture with n = 0 (monotone decreasing) can reproduce.
///
/// # Formula
/// energy E = Σ A_k n!/B_k^{n+1}; CDF C(r) = Σ (A_k n!/B_k^{n+1}) P(n+1, B_k r)
/// with P the regularised lower incomplete gamma function (P(1, x) = 1 − e^{−x},
/// P(2, x) = 1 − e^{−x}(1 + x)); sampling picks component k with
/// probability A_k n!/B_k^{n+1}/E, then r ~ Gamma(n+1, B_k):
/// r = −(ln u₁ + … + ln u_{n+1})/B_k (exact, docs/design.md §4).
///
/// # Units / domain
/// r in MFP ≥ 0; B_k in 1/MFP; A_k in 1/MFP^{n+1}.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExpMixture {
    pub a: Vec<f64>,
    pub b: Vec<f64>,
    /// n: p(r) = Σ A r^n e^{−Br}.
    #[serde(default)]
    pub power: u32,
}

/// P(n+1, x) for n ∈ {0, 1}, to ≈ 1e-12 relative also for small x: for
/// n = 1 below x = 1e-2 the series P(2, x) = x²/2 − x³/3 + x⁴/8 − x⁵/30 +
/// x⁶/144 − … (Σ_k (−1)^k (k + 1) x^(k+2)/(k + 2)!), whose first omitted term
/// is x⁷/840 ≤ 1.2e-17 ≈ 2e-13 of P there; above, the direct form loses
/// ≈ ε/P(2, x) ≤ 5e-12 to cancellation.
#[inline]
fn gamma_p(n: u32, x: f64) -> f64 {
    match n {
        0 => -(-x).exp_m1(),
        _ if x < 1e-2 => {
            x * x * (0.5 - x * (1.0 / 3.0 - x * (0.125 - x * (1.0 / 30.0 - x / 144.0))))
        }
        _ => 1.0 - (-x).exp() * (1.0 + x),
    }
}

/// Mean over the ring [lo, hi] of one component A r^n e^{−Br}, and its
/// derivative with respect to ln B. `hi = ∞` gives the energy beyond `lo`
/// instead (a "tail bin" of width 1).
///
/// # Formula
/// E = (A n!/B^{n+1})·[P(n+1, B hi) − P(n+1, B lo)],
/// ∂E/∂ln B = −(n+1)E + A[hi^{n+1}e^{−B hi} − lo^{n+1}e^{−B lo}].
#[inline]
pub fn component_bin(a: f64, b: f64, n: u32, lo: f64, hi: f64) -> (f64, f64) {
    let scale = a / if n == 0 { b } else { b * b };
    let (e, edge_hi, w) = if hi.is_infinite() {
        (scale * (1.0 - gamma_p(n, b * lo)), 0.0, 1.0)
    } else {
        let w = hi - lo;
        let e = if n == 0 {
            // (A/B) e^{−B lo} (1 − e^{−BΔ}): no cancellation for small BΔ.
            scale * (-b * lo).exp() * -(-b * w).exp_m1()
        } else {
            scale * (gamma_p(n, b * hi) - gamma_p(n, b * lo))
        };
        (e, a * hi.powi(n as i32 + 1) * (-b * hi).exp(), w)
    };
    let edge_lo = a * lo.powi(n as i32 + 1) * (-b * lo).exp();
    (e / w, (-(n as f64 + 1.0) * e + edge_hi - edge_lo) / w)
}

impl ExpMixture {
    /// p(r).
    #[inline]
    pub fn density(&self, r: f64) -> f64 {
        let rn = if self.power == 0 { 1.0 } else { r };
        self.a
            .iter()
            .zip(&self.b)
            .map(|(a, b)| a * rn * (-b * r).exp())
            .sum()
    }

    /// Energy of component k.
    #[inline]
    pub fn component_energy(&self, k: usize) -> f64 {
        self.a[k] / self.b[k].powi(self.power as i32 + 1)
    }

    /// Total energy ∫₀^∞ p(r) dr.
    pub fn energy(&self) -> f64 {
        (0..self.a.len()).map(|k| self.component_energy(k)).sum()
    }

    /// ∫₀^r p.
    pub fn cdf(&self, r: f64) -> f64 {
        (0..self.a.len())
            .map(|k| self.component_energy(k) * gamma_p(self.power, self.b[k] * r))
            .sum()
    }

    /// Mean of p over the bin [lo, hi] (exact integral / width).
    #[inline]
    pub fn bin_mean(&self, lo: f64, hi: f64) -> f64 {
        self.a
            .iter()
            .zip(&self.b)
            .map(|(a, b)| component_bin(*a, *b, self.power, lo, hi).0)
            .sum()
    }

    /// Normalised pdf p(r)/E of [`ExpMixture::sample`].
    pub fn pdf(&self, r: f64) -> f64 {
        self.density(r) / self.energy()
    }

    /// Draws r from p/E with three uniforms in [0, 1) (the third is used
    /// only for n = 1).
    pub fn sample(&self, u: [f64; 3]) -> f64 {
        let target = u[0] * self.energy();
        let last = self.a.len() - 1;
        let mut acc = 0.0;
        let mut k = last;
        for i in 0..=last {
            acc += self.component_energy(i);
            if target < acc {
                k = i;
                break;
            }
        }
        let mut x = -(1.0 - u[1]).ln();
        if self.power == 1 {
            x -= (1.0 - u[2]).ln();
        }
        x / self.b[k]
    }

    /// Scales every amplitude by `s`.
    pub fn scaled(&self, s: f64) -> Self {
        ExpMixture {
            a: self.a.iter().map(|a| a * s).collect(),
            ..self.clone()
        }
    }
}

/// A radial density made of several mixtures (e.g. single + multiple
/// scattering, which use different powers).
#[derive(Clone, Debug, PartialEq)]
pub struct RadialProfile {
    pub parts: Vec<ExpMixture>,
}

impl RadialProfile {
    pub fn density(&self, r: f64) -> f64 {
        self.parts.iter().map(|m| m.density(r)).sum()
    }
    pub fn energy(&self) -> f64 {
        self.parts.iter().map(|m| m.energy()).sum()
    }
    pub fn cdf(&self, r: f64) -> f64 {
        self.parts.iter().map(|m| m.cdf(r)).sum()
    }
    pub fn bin_mean(&self, lo: f64, hi: f64) -> f64 {
        self.parts.iter().map(|m| m.bin_mean(lo, hi)).sum()
    }
}

/// Lower bound of the fitted rates B (1/MFP): a decay length of 1000 MFP.
pub const B_MIN: f64 = 1e-3;
/// Upper bound of the fitted rates B (1/MFP): below the inner disk's 1e-3 MFP.
pub const B_MAX: f64 = 1e4;

/// Rate from its unbounded parameter: B = B_min (B_max/B_min)^σ(θ); also
/// returns d ln B/dθ.
#[inline]
pub fn rate_from_theta(theta: f64) -> (f64, f64) {
    let span = (B_MAX / B_MIN).ln();
    let s = 1.0 / (1.0 + (-theta).exp());
    ((B_MIN.ln() + span * s).exp(), span * s * (1.0 - s))
}

/// Chebyshev polynomials T_0..T_degree at t ∈ [−1, 1].
pub fn chebyshev(t: f64, degree: usize, out: &mut [f64]) {
    out[0] = 1.0;
    if degree >= 1 {
        out[1] = t;
    }
    for j in 2..=degree {
        out[j] = 2.0 * t * out[j - 1] - out[j - 2];
    }
}

/// The albedo coordinate of the smooth model: x = sqrt(1 − α) ∈ [0, 1]
/// (diffusion theory's σ_tr/σ_t scales like x, so the profile is smooth in x).
#[inline]
pub fn albedo_coordinate(alpha: f64) -> f64 {
    (1.0 - alpha.clamp(0.0, 1.0)).sqrt()
}

/// The smooth basis BSSRDF of one medium (η, g) under one illumination.
///
/// # Formula
/// p(r; α) = α·p₁(r) + p_m(r; α), with p₁ the single-scattering density at
/// α = 1 (single scattering is exactly linear in α; an [`ExpMixture`] with
/// n = 0) and p_m(r; α) = r·Σ_k A_k(α) e^{−B_k(α) r} (n = 1: the exitance
/// Rₘ(r) = Σ (A_k/2π) e^{−B_k r} is the mixture),
/// A_k(α) = α²·exp(Σ_j a_kj T_j(2x − 1)),
/// B_k(α) = [`rate_from_theta`](Σ_j b_kj T_j(2x − 1)) ∈ [B_MIN, B_MAX],
/// x = sqrt(1 − α). Any α ∈ [0, 1] gives positive, finite A_k, B_k; Rₘ = 0 at
/// α = 0 and Rₘ/α² stays bounded as α → 0 (two or more vertices carry α²).
///
/// # Units / domain
/// r in MFP, α ∈ [0, 1]; outside the training range (see `albedo_range`) the
/// polynomials extrapolate gently to α = 0 and α = 1, where the fit
/// constrains the energy R_d(1) = 1 − R_sp.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BasisModel {
    pub format: String,
    pub version: u32,
    pub eta: f64,
    pub g: f64,
    /// "pencil" (normal incidence) or "diffuse".
    pub incidence: crate::forward::medium::Incidence,
    /// "exitance" (the profile R(r)) or "radiance" (the radiance leaving
    /// along the normal, L(r) in 1/(MFP²·sr); p(r) = 2πr·L(r)).
    #[serde(default)]
    pub observable: crate::forward::medium::Observable,
    /// Polynomial degree in the albedo coordinate.
    pub degree: usize,
    /// a_kj: K rows of degree + 1 Chebyshev coefficients of ln(A_k/α²).
    pub ln_a: Vec<Vec<f64>>,
    /// b_kj: K rows of degree + 1 Chebyshev coefficients of the bounded-rate
    /// parameter θ_k(α) with B_k = rate_from_theta(θ_k).
    pub ln_b: Vec<Vec<f64>>,
    /// p₁(r) at α = 1.
    pub single: ExpMixture,
    /// Albedo range of the training profiles.
    pub albedo_range: (f64, f64),
    /// Specular reflectance at entry (not in R_d).
    pub r_sp: f64,
    /// Free-form provenance (command, data, git commit, fit report summary).
    pub provenance: serde_json::Value,
}

/// Format tag of [`BasisModel`] files.
pub const BASIS_FORMAT: &str = "svkernel.basis";
pub const BASIS_VERSION: u32 = 1;

impl BasisModel {
    /// Components K of the multiple-scattering mixture.
    pub fn components(&self) -> usize {
        self.ln_a.len()
    }

    /// The multiple-scattering density p_m(r; α).
    pub fn multi(&self, alpha: f64) -> ExpMixture {
        let alpha = alpha.clamp(0.0, 1.0);
        let (ln_a, b) = self.multi_over_alpha2(alpha);
        ExpMixture {
            a: ln_a.iter().map(|l| alpha * alpha * l.exp()).collect(),
            b,
            power: 1,
        }
    }

    /// (ln(A_j/α²), B_j) of p_m(r; α) = α²·Σ_j (A_j/α²)·e^{−B_j r}: the
    /// polynomials themselves, so that p_m/α² stays exact as α → 0 (no α²
    /// to multiply in and divide out, which would underflow there).
    pub fn multi_over_alpha2(&self, alpha: f64) -> (Vec<f64>, Vec<f64>) {
        let alpha = alpha.clamp(0.0, 1.0);
        let mut t = vec![0.0; self.degree + 1];
        chebyshev(2.0 * albedo_coordinate(alpha) - 1.0, self.degree, &mut t);
        let dot = |c: &Vec<f64>| c.iter().zip(&t).map(|(c, t)| c * t).sum::<f64>();
        (
            self.ln_a.iter().map(dot).collect(),
            self.ln_b
                .iter()
                .map(|c| rate_from_theta(dot(c)).0)
                .collect(),
        )
    }

    /// The single-scattering density α·p₁(r).
    pub fn single(&self, alpha: f64) -> ExpMixture {
        self.single.scaled(alpha.clamp(0.0, 1.0))
    }

    /// (R₁, Rₘ) totals at α.
    pub fn r_1_m(&self, alpha: f64) -> (f64, f64) {
        (self.single(alpha).energy(), self.multi(alpha).energy())
    }

    /// R_d(α) = R₁ + Rₘ (specular excluded).
    pub fn r_d(&self, alpha: f64) -> f64 {
        let (a, b) = self.r_1_m(alpha);
        a + b
    }

    /// p(r; α) = α p₁(r) + p_m(r; α).
    pub fn density(&self, r: f64, alpha: f64) -> f64 {
        self.single(alpha).density(r) + self.multi(alpha).density(r)
    }

    /// ∫₀^r p(r'; α) dr'.
    pub fn cdf(&self, r: f64, alpha: f64) -> f64 {
        self.single(alpha).cdf(r) + self.multi(alpha).cdf(r)
    }

    /// Exitance R(r; α) = p(r; α)/(2πr) in 1/MFP² (diverges like 1/r at 0).
    pub fn exitance(&self, r: f64, alpha: f64) -> f64 {
        self.density(r, alpha) / (2.0 * std::f64::consts::PI * r)
    }

    /// The whole density p(r; α) = α p₁(r) + p_m(r; α).
    pub fn profile(&self, alpha: f64) -> RadialProfile {
        RadialProfile {
            parts: vec![self.single(alpha), self.multi(alpha)],
        }
    }
}

impl crate::doc::Document for BasisModel {
    const FORMAT: &'static str = BASIS_FORMAT;
    const VERSION: u32 = BASIS_VERSION;

    fn validate(&self, path: &std::path::Path) -> crate::Result<()> {
        let m = self;
        use crate::Error;
        let rows_ok = |rows: &Vec<Vec<f64>>| {
            rows.iter()
                .all(|r| r.len() == m.degree + 1 && r.iter().all(|v| v.is_finite()))
        };
        if m.ln_a.is_empty()
            || m.ln_a.len() != m.ln_b.len()
            || !rows_ok(&m.ln_a)
            || !rows_ok(&m.ln_b)
        {
            return Err(Error::format(
                path,
                "ln_a/ln_b",
                "need K ≥ 1 rows of degree + 1 finite coefficients each",
            ));
        }
        let s = &m.single;
        if s.a.is_empty()
            || s.a.len() != s.b.len()
            || s.a.iter().chain(&s.b).any(|v| !(v.is_finite() && *v > 0.0))
        {
            return Err(Error::format(
                path,
                "single",
                "need matching positive finite a and b",
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gamma_p_is_accurate_at_small_x() {
        // P(2, x) = Σ_k (−1)^k (k + 1) x^(k+2)/(k + 2)!, summed to convergence
        // (alternating, terms falling ≥ 100× a step for x ≤ 0.02).
        let series = |x: f64| {
            let (mut sum, mut fact) = (0.0, 2.0);
            for k in 0..12 {
                sum += (-1f64).powi(k) * (k + 1) as f64 * x.powi(k + 2) / fact;
                fact *= (k + 3) as f64;
            }
            sum
        };
        for x in [1e-6, 1e-4, 0.005, 0.0099, 0.0101, 0.02] {
            let rel = (gamma_p(1, x) / series(x) - 1.0).abs();
            assert!(rel < 1e-11, "x = {x}: relative error {rel:e}");
        }
    }
    use crate::forward::rng::PathRng;
    use crate::testing::*;

    fn mix() -> ExpMixture {
        ExpMixture {
            a: vec![0.3, 0.05, 0.002],
            b: vec![8.0, 1.2, 0.15],
            power: 0,
        }
    }

    #[test]
    fn closed_forms_agree_with_quadrature() {
        for power in [0, 1] {
            closed_forms(&ExpMixture { power, ..mix() });
        }
    }

    fn closed_forms(m: &ExpMixture) {
        let n = 2_000_000;
        let (r_max, mut acc) = (300.0, 0.0);
        let h = r_max / n as f64;
        for i in 0..n {
            acc += m.density((i as f64 + 0.5) * h) * h;
        }
        assert!((acc - m.energy()).abs() < 1e-7 * m.energy());
        assert!((m.cdf(1e6) - m.energy()).abs() < REL_CLOSED_FORM * m.energy());
        for (lo, hi) in [(0.3, 0.7), (1e-4, 1.2e-4), (0.0, 1e-3)] {
            let mean = (m.cdf(hi) - m.cdf(lo)) / (hi - lo);
            assert!((m.bin_mean(lo, hi) - mean).abs() < 1e-9 * mean, "{lo} {hi}");
        }
        // The tail bin is the energy beyond lo.
        let tail =
            m.a.iter()
                .zip(&m.b)
                .map(|(a, b)| component_bin(*a, *b, m.power, 5.0, f64::INFINITY).0)
                .sum::<f64>();
        assert!((tail - (m.energy() - m.cdf(5.0))).abs() < 1e-12 * m.energy());
    }

    #[test]
    fn bin_derivative_matches_finite_difference() {
        for n in [0, 1] {
            for (lo, hi) in [(0.0, 1e-3), (0.3, 0.7), (2.0, f64::INFINITY)] {
                let (a, b) = (0.7, 1.3);
                let d = component_bin(a, b, n, lo, hi).1;
                // h balances truncation (h²) against rounding (ε·f/(h·f′)):
                // in [0, 1e-3] the bin mean barely depends on B (f′/f ≈ 6e-4).
                let h = 1e-4;
                let f = |lnb: f64| component_bin(a, lnb.exp(), n, lo, hi).0;
                let num = (f(b.ln() + h) - f(b.ln() - h)) / (2.0 * h);
                assert!(
                    (d - num).abs() < 1e-7 * num.abs().max(1e-12),
                    "n={n} [{lo},{hi}]: {d} vs {num}"
                );
            }
        }
    }

    #[test]
    fn sampling_chi2() {
        for power in [0, 1] {
            sampling(&ExpMixture { power, ..mix() });
        }
    }

    fn sampling(m: &ExpMixture) {
        let e = m.energy();
        let mut rng = PathRng::new(17, 0);
        let n = 200_000;
        let edges: Vec<f64> = (0..=60)
            .map(|k| 1e-3 * 10f64.powf(k as f64 / 10.0))
            .collect();
        let mut counts = vec![0u64; edges.len() + 1];
        for _ in 0..n {
            let r = m.sample([rng.uniform(), rng.uniform(), rng.uniform()]);
            let k = edges.partition_point(|&x| x <= r);
            counts[k] += 1;
        }
        let mut expected = Vec::new();
        let mut prev = 0.0;
        for &x in &edges {
            expected.push(n as f64 * (m.cdf(x) - prev) / e);
            prev = m.cdf(x);
        }
        expected.push(n as f64 * (e - prev) / e);
        let (stat, dof) = chi2_statistic(&counts, &expected);
        assert!(stat < chi2_critical(dof, CHI2_ALPHA), "χ² {stat} dof {dof}");
        // pdf integrates to 1.
        assert!((m.cdf(1e9) / e - 1.0).abs() < REL_CLOSED_FORM);
    }

    #[test]
    fn chebyshev_values() {
        let mut t = [0.0; 5];
        chebyshev(0.5, 4, &mut t);
        // T2 = 2t²−1, T3 = 4t³−3t, T4 = 8t⁴−8t²+1.
        assert_eq!(t[0], 1.0);
        assert!(
            (t[2] - (-0.5)).abs() < 1e-15
                && (t[3] - (-1.0)).abs() < 1e-15
                && (t[4] - (-0.5)).abs() < 1e-15
        );
    }
}
