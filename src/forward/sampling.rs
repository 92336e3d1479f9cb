//! Pure samplers: each takes uniforms in [0, 1) and returns a sample; each has
//! its pdf beside it. Physics code never sees a generator.

use std::f64::consts::PI;

/// A direction or position in 3D (f64).
pub type Vec3 = [f64; 3];

/// Free-flight distance of an exponential with rate `sigma_t` (1/MFP).
///
/// # Formula
/// x = −ln(u)/σ_t with u ∈ (0, 1]; pdf σ_t·e^{−σ_t x}.
#[inline]
pub fn sample_exponential(u: f64, sigma_t: f64) -> f64 {
    -u.ln() / sigma_t
}

/// Pdf of [`sample_exponential`].
#[inline]
pub fn exponential_pdf(x: f64, sigma_t: f64) -> f64 {
    sigma_t * (-sigma_t * x).exp()
}

/// The u with `sample_exponential(u, sigma_t) == x`.
#[inline]
pub fn invert_exponential_sample(x: f64, sigma_t: f64) -> f64 {
    (-sigma_t * x).exp()
}

/// Below this |g| the Henyey–Greenstein inversion is replaced by the isotropic
/// one: the closed form divides by g and loses all digits as g → 0.
pub const HG_ISOTROPIC_G: f64 = 1e-3;

/// Cosine of the scattering angle of the Henyey–Greenstein phase function.
///
/// # Formula
/// cos θ = (1 + g² − ((1 − g²)/(1 − g + 2gu))²)/(2g) [PBRT4 §11.3.1], with
/// θ the angle between the incoming and outgoing *propagation* directions, so
/// g > 0 is forward scattering. |g| < [`HG_ISOTROPIC_G`]: cos θ = 1 − 2u.
#[inline]
pub fn sample_hg_cos(g: f64, u: f64) -> f64 {
    if g.abs() < HG_ISOTROPIC_G {
        1.0 - 2.0 * u
    } else {
        let sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * u);
        ((1.0 + g * g - sq * sq) / (2.0 * g)).clamp(-1.0, 1.0)
    }
}

/// Pdf of the Henyey–Greenstein phase function in solid angle (1/sr).
#[inline]
pub fn hg_pdf(g: f64, cos_theta: f64) -> f64 {
    let denom = 1.0 + g * g - 2.0 * g * cos_theta;
    (1.0 - g * g) / (4.0 * PI * denom * denom.sqrt())
}

/// Unit vector obtained by rotating the unit vector `w` by polar angle θ
/// (given as cos θ) and azimuth φ about itself. Branch-free orthonormal basis
/// of Duff et al. 2017 ("Building an orthonormal basis, revisited").
#[inline]
pub fn rotate_direction(w: Vec3, cos_theta: f64, phi: f64) -> Vec3 {
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    let (sin_phi, cos_phi) = phi.sin_cos();
    let sign = 1f64.copysign(w[2]);
    let a = -1.0 / (sign + w[2]);
    let b = w[0] * w[1] * a;
    let t1 = [1.0 + sign * w[0] * w[0] * a, sign * b, -sign * w[0]];
    let t2 = [b, sign + w[1] * w[1] * a, -w[1]];
    let (x, y) = (sin_theta * cos_phi, sin_theta * sin_phi);
    [
        x * t1[0] + y * t2[0] + cos_theta * w[0],
        x * t1[1] + y * t2[1] + cos_theta * w[1],
        x * t1[2] + y * t2[2] + cos_theta * w[2],
    ]
}

/// Uniform point on the unit disk, Shirley–Chiu concentric map [PBRT4 §A.5.1].
/// Pdf 1/π per unit area.
#[inline]
pub fn sample_disk_concentric(u: [f64; 2]) -> [f64; 2] {
    let (ox, oy) = (2.0 * u[0] - 1.0, 2.0 * u[1] - 1.0);
    if ox == 0.0 && oy == 0.0 {
        return [0.0, 0.0];
    }
    let (r, theta) = if ox.abs() > oy.abs() {
        (ox, PI / 4.0 * (oy / ox))
    } else {
        (oy, PI / 2.0 - PI / 4.0 * (ox / oy))
    };
    [r * theta.cos(), r * theta.sin()]
}

/// Cosine of a direction drawn from the cosine-weighted hemisphere
/// (pdf cos θ/π per steradian): cos θ = sqrt(u). The azimuth is uniform.
#[inline]
pub fn sample_cosine_cos_theta(u: f64) -> f64 {
    u.sqrt()
}

/// Pdf of [`sample_cosine_cos_theta`] in solid angle.
#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f64) -> f64 {
    cos_theta.max(0.0) / PI
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::rng::PathRng;
    use crate::testing::*;

    /// χ² of `n` samples of cos θ in `bins` equal bins against the expected
    /// mass from the closed-form CDF.
    fn chi2_cos(sample: impl Fn(f64) -> f64, cdf: impl Fn(f64) -> f64, bins: usize, n: usize) {
        let mut rng = PathRng::new(99, 0);
        let mut counts = vec![0u64; bins];
        for _ in 0..n {
            let c = sample(rng.uniform());
            let b = (((c + 1.0) / 2.0) * bins as f64)
                .floor()
                .clamp(0.0, bins as f64 - 1.0);
            counts[b as usize] += 1;
        }
        let expected: Vec<f64> = (0..bins)
            .map(|b| {
                let lo = -1.0 + 2.0 * b as f64 / bins as f64;
                let hi = -1.0 + 2.0 * (b + 1) as f64 / bins as f64;
                n as f64 * (cdf(hi) - cdf(lo))
            })
            .collect();
        let (stat, dof) = chi2_statistic(&counts, &expected);
        assert!(
            stat < chi2_critical(dof, CHI2_ALPHA),
            "chi2 {stat} dof {dof}"
        );
    }

    /// CDF of the HG cos θ in closed form: the inverse of `sample_hg_cos`.
    fn hg_cdf(g: f64, c: f64) -> f64 {
        if g.abs() < HG_ISOTROPIC_G {
            return (c + 1.0) / 2.0;
        }
        let d = (1.0 + g * g - 2.0 * g * c).sqrt();
        (1.0 - g * g) / (2.0 * g) * (1.0 / d - 1.0 / (1.0 + g))
    }

    #[test]
    fn hg_chi2() {
        for g in [-0.9, -0.3, 0.0, 0.3, 0.75, 0.95] {
            chi2_cos(|u| sample_hg_cos(g, u), |c| hg_cdf(g, c), 64, 200_000);
        }
    }

    #[test]
    fn hg_cdf_matches_pdf_integral() {
        // The χ² test trusts hg_cdf; pin it to the pdf by quadrature.
        for g in [-0.7, 0.3, 0.9] {
            let n = 200_000;
            let h = 2.0 / n as f64;
            let integral: f64 = (0..n)
                .map(|i| 2.0 * PI * hg_pdf(g, -1.0 + (i as f64 + 0.5) * h) * h)
                .sum();
            assert!((integral - 1.0).abs() < 1e-6, "g={g}: {integral}");
            assert!((hg_cdf(g, 1.0) - 1.0).abs() < 1e-12);
            assert!(hg_cdf(g, -1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn positive_g_scatters_forward() {
        // Mean cosine of HG is g: positive g keeps the propagation direction.
        let mut rng = PathRng::new(3, 0);
        let n = 100_000;
        let mean: f64 = (0..n)
            .map(|_| sample_hg_cos(0.6, rng.uniform()))
            .sum::<f64>()
            / n as f64;
        assert!((mean - 0.6).abs() < 0.01, "{mean}");
        // And the rotated direction is at that cosine from the old one.
        let w = [0.0, 0.0, -1.0];
        let w2 = rotate_direction(w, 0.9, 1.0);
        assert!((w2[2] - (-0.9)).abs() < REL_CLOSED_FORM * 10.0);
    }

    #[test]
    fn rotation_preserves_norm_and_angle() {
        let mut rng = PathRng::new(5, 0);
        for _ in 0..10_000 {
            let ct = 1.0 - 2.0 * rng.uniform();
            let phi = 2.0 * PI * rng.uniform();
            let c0 = 1.0 - 2.0 * rng.uniform();
            let s0 = (1.0 - c0 * c0).sqrt();
            let p0 = 2.0 * PI * rng.uniform();
            let w = [s0 * p0.cos(), s0 * p0.sin(), c0];
            let w2 = rotate_direction(w, ct, phi);
            let norm = (w2[0] * w2[0] + w2[1] * w2[1] + w2[2] * w2[2]).sqrt();
            assert!((norm - 1.0).abs() < 1e-12);
            let dot = w[0] * w2[0] + w[1] * w2[1] + w[2] * w2[2];
            assert!((dot - ct).abs() < 1e-12);
        }
    }

    #[test]
    fn hg_extremes_finite() {
        for g in [-0.99, -1e-9, 0.0, 1e-9, 0.99] {
            for u in [0.0, 1e-12, 0.5, 1.0 - 1e-12, 1.0] {
                let c = sample_hg_cos(g, u);
                assert!(
                    c.is_finite() && (-1.0..=1.0).contains(&c),
                    "g={g} u={u} c={c}"
                );
            }
        }
    }

    #[test]
    fn exponential_round_trip() {
        for u in [1e-9, 0.1, 0.5, 1.0] {
            let x = sample_exponential(u, 2.0);
            assert!((invert_exponential_sample(x, 2.0) - u).abs() < 1e-12 * u.max(1e-3));
            assert!((exponential_pdf(x, 2.0) - 2.0 * u).abs() < 1e-12);
        }
    }

    #[test]
    fn disk_chi2() {
        // Uniform on the disk: the mass of a ring is its area fraction, of a
        // sector its angle fraction. 16 rings × 16 sectors.
        let (nr, na, n) = (16, 16, 256_000);
        let mut rng = PathRng::new(11, 0);
        let mut counts = vec![0u64; nr * na];
        for _ in 0..n {
            let p = sample_disk_concentric([rng.uniform(), rng.uniform()]);
            let r2 = p[0] * p[0] + p[1] * p[1];
            assert!(r2 <= 1.0 + 1e-12);
            let ir = ((r2 * nr as f64) as usize).min(nr - 1); // equal-area rings
            let a = p[1].atan2(p[0]) + PI;
            let ia = ((a / (2.0 * PI) * na as f64) as usize).min(na - 1);
            counts[ir * na + ia] += 1;
        }
        let expected = vec![n as f64 / (nr * na) as f64; nr * na];
        let (stat, dof) = chi2_statistic(&counts, &expected);
        assert!(
            stat < chi2_critical(dof, CHI2_ALPHA),
            "chi2 {stat} dof {dof}"
        );
    }

    #[test]
    fn cosine_chi2() {
        // cos θ = sqrt(u) has CDF c² on [0, 1]; map to the [-1, 1] binning.
        chi2_cos(
            |u| 2.0 * sample_cosine_cos_theta(u) - 1.0,
            |c| {
                let x = ((c + 1.0) / 2.0).clamp(0.0, 1.0);
                x * x
            },
            50,
            200_000,
        );
        assert!((cosine_hemisphere_pdf(1.0) - 1.0 / PI).abs() < REL_CLOSED_FORM);
    }
}
