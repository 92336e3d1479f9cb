//! Christensen & Burley 2015 ("Approximate reflectance profiles for efficient
//! subsurface scattering", Pixar tech memo 15-04): the two-exponential
//! baseline profile, for comparison with the learned basis.
//!
//! # Formula
//! R(r) = A·s·(e^{−s r/ℓ} + e^{−s r/(3ℓ)})/(8π ℓ r), so the radial density
//! p(r) = 2πr·R(r) = (A s/4ℓ)(e^{−s r/ℓ} + e^{−s r/(3ℓ)}) has energy A.
//! For perpendicular incidence with ℓ the mean free path (here 1 MFP):
//! s(A) = 1.85 − A + 7|A − 0.8|³ [ChristensenBurley2015, eq. 5 "dmfp"].
//!
//! # Units / domain
//! r in MFP; A ∈ (0, 1) the total diffuse reflectance (surface albedo).
//! svkernel sets A to the simulated R_d of the same medium, so the
//! comparison measures the *shape* of the profile at equal energy.

use super::basis::ExpMixture;

/// The scaling factor s(A) for perpendicular incidence, ℓ = 1 MFP.
pub fn scale_perpendicular(a: f64) -> f64 {
    1.85 - a + 7.0 * (a - 0.8).abs().powi(3)
}

/// Christensen–Burley's radial density for surface albedo `a`, as a
/// two-term exponential mixture (ℓ = 1 MFP).
pub fn profile(a: f64) -> ExpMixture {
    let s = scale_perpendicular(a);
    ExpMixture {
        a: vec![a * s / 4.0, a * s / 4.0],
        b: vec![s, s / 3.0],
        power: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn energy_is_the_albedo() {
        for a in [0.01, 0.3, 0.8, 0.99] {
            assert!((profile(a).energy() - a).abs() < 1e-14);
        }
        assert!((scale_perpendicular(0.8) - 1.05).abs() < 1e-14);
    }
}
