//! Unpolarised dielectric Fresnel reflectance and refraction at the flat
//! surface z = 0 (and the bottom of a slab).

/// Fresnel reflectance of unpolarised light at a dielectric interface.
///
/// `cos_i` ≥ 0 is the cosine of the incidence angle on the incident side and
/// `eta` = n_transmitted / n_incident. Returns 1 under total internal
/// reflection (sin θ_t ≥ 1).
///
/// # Formula
/// r_∥ = (η cos θ_i − cos θ_t)/(η cos θ_i + cos θ_t),
/// r_⊥ = (cos θ_i − η cos θ_t)/(cos θ_i + η cos θ_t), F = (r_∥² + r_⊥²)/2,
/// with η sin θ_t = sin θ_i [PBRT4 §9.3.5, `FrDielectric`].
#[inline]
pub fn fresnel_dielectric(cos_i: f64, eta: f64) -> f64 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

/// Cosine of the refracted angle for incidence cosine `cos_i` and relative
/// index `eta` = n_t/n_i; `None` under total internal reflection.
#[inline]
pub fn refract_cos(cos_i: f64, eta: f64) -> Option<f64> {
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    (sin2_t < 1.0).then(|| (1.0 - sin2_t).sqrt())
}

/// Specular reflectance at normal incidence, ((η−1)/(η+1))².
#[inline]
pub fn r_specular(eta: f64) -> f64 {
    ((eta - 1.0) / (eta + 1.0)).powi(2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;

    #[test]
    fn normal_incidence() {
        for eta in [1.0, 1.33, 1.5, 3.0] {
            let f = r_specular(eta);
            assert!((fresnel_dielectric(1.0, eta) - f).abs() < REL_CLOSED_FORM);
            // Same from the other side.
            assert!((fresnel_dielectric(1.0, 1.0 / eta) - f).abs() < REL_CLOSED_FORM);
        }
        assert!((r_specular(1.5) - 0.04).abs() < REL_CLOSED_FORM);
    }

    #[test]
    fn critical_angle_and_grazing() {
        // oracles.md: η = 1.5, cos θ_crit = 0.74536 from inside.
        let cos_crit = (1.0 - 1.0 / (1.5 * 1.5f64)).sqrt();
        assert!((cos_crit - 0.74536).abs() < 5e-6);
        assert_eq!(fresnel_dielectric(cos_crit - 1e-9, 1.0 / 1.5), 1.0);
        assert!(fresnel_dielectric(cos_crit + 1e-6, 1.0 / 1.5) < 1.0);
        assert!(fresnel_dielectric(cos_crit + 1e-6, 1.0 / 1.5) > 0.9);
        assert!(refract_cos(cos_crit - 1e-9, 1.0 / 1.5).is_none());
        // Grazing from outside reflects everything.
        assert!((fresnel_dielectric(0.0, 1.5) - 1.0).abs() < REL_CLOSED_FORM);
        // Index-matched: nothing reflects at any angle.
        // (cos θ_t = sqrt(1 − sin²θ_i) may differ from cos θ_i in the last
        // bit, hence a rounding-level bound rather than exact zero.)
        assert_eq!(fresnel_dielectric(0.0, 1.0), 1.0);
        for c in [0.3, 0.7, 1.0] {
            assert!(fresnel_dielectric(c, 1.0) < 1e-28, "{c}");
        }
    }

    #[test]
    fn hemispherical_averages() {
        // oracles.md: 2∫F cos θ sin θ dθ = 0.0918 (outside), 0.5964 (inside).
        let avg = |eta: f64| {
            let n = 1_000_000;
            (0..n)
                .map(|i| {
                    let mu = (i as f64 + 0.5) / n as f64;
                    2.0 * fresnel_dielectric(mu, eta) * mu / n as f64
                })
                .sum::<f64>()
        };
        // The oracle values are printed to 4 decimals: the bound is half a
        // unit of the last digit plus the quadrature's error (< 1e-6).
        // (Exactly: inside = 1 − (1 − outside)/η² = 0.596346.)
        assert!((avg(1.5) - 0.0918).abs() < 5.1e-5, "{}", avg(1.5));
        assert!(
            (avg(1.0 / 1.5) - 0.5964).abs() < 5.5e-5,
            "{}",
            avg(1.0 / 1.5)
        );
        assert!((avg(1.0 / 1.5) - (1.0 - (1.0 - avg(1.5)) / 2.25)).abs() < 1e-6);
    }

    #[test]
    fn snell() {
        let cos_i: f64 = 0.6;
        let ct = refract_cos(cos_i, 1.5).unwrap();
        let (si, st) = ((1.0 - cos_i * cos_i).sqrt(), (1.0 - ct * ct).sqrt());
        assert!((si - 1.5 * st).abs() < REL_CLOSED_FORM);
    }
}
