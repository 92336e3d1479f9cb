//! The homogeneous medium and the sources that illuminate it.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// A homogeneous medium below the surface z = 0.
///
/// | field | type | default | units | meaning |
/// |---|---|---|---|---|
/// | `alpha` | f64 | — | 1 | single-scattering albedo σ_s/σ_t, in [0, 1] |
/// | `g` | f64 | 0.3 | 1 | Henyey–Greenstein mean cosine, in (−1, 1) |
/// | `eta` | f64 | 1.5 | 1 | n_inside/n_outside, in [1, 3]; 1 = index-matched |
/// | `rho` | f64 | 1 | 1 | density: σ_t = ρ, in (0, ∞) |
/// | `thickness` | f64? | none | MFP | slab thickness; none = half-space |
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Medium {
    pub alpha: f64,
    pub g: f64,
    pub eta: f64,
    pub rho: f64,
    pub thickness: Option<f64>,
}

impl Medium {
    /// Validates every parameter against its domain.
    pub fn new(alpha: f64, g: f64, eta: f64, rho: f64, thickness: Option<f64>) -> Result<Self> {
        if !(0.0..=1.0).contains(&alpha) {
            return Err(Error::param("albedo", alpha, "in [0, 1]"));
        }
        if g.is_nan() || g.abs() >= 1.0 {
            return Err(Error::param("g", g, "in (-1, 1)"));
        }
        if !(1.0..=3.0).contains(&eta) {
            return Err(Error::param("eta", eta, "in [1, 3]"));
        }
        if !(rho > 0.0 && rho.is_finite()) {
            return Err(Error::param("density", rho, "finite and > 0"));
        }
        if let Some(l) = thickness.filter(|l| !(*l > 0.0 && l.is_finite())) {
            return Err(Error::param("thickness", l, "finite and > 0"));
        }
        Ok(Medium {
            alpha,
            g,
            eta,
            rho,
            thickness,
        })
    }

    /// The project's default medium (η = 1.5, g = 0.3, ρ = 1, half-space).
    pub fn default_with_albedo(alpha: f64) -> Result<Self> {
        Self::new(alpha, 0.3, 1.5, 1.0, None)
    }

    /// Extinction coefficient σ_t = ρ·σ_t0 in 1/MFP.
    #[inline]
    pub fn sigma_t(&self) -> f64 {
        self.rho
    }
}

/// The illumination (docs/design.md §2 "Lights").
///
/// The string form used by the CLI is `pencil`, `collimated:R` or `diffuse:R`
/// with R the disk radius in MFP.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Source {
    /// Unit power at the origin, normal incidence.
    Pencil,
    /// Disk of radius `radius` at the origin, unit irradiance, normal incidence.
    Collimated { radius: f64 },
    /// Disk of radius `radius`, unit irradiance, cosine-distributed directions.
    Diffuse { radius: f64 },
}

impl Source {
    /// Parses `pencil`, `diffuse` (a point source of cosine-distributed
    /// directions: diffuse incidence at one point, radius 0), `collimated:R`
    /// or `diffuse:R`.
    pub fn parse(s: &str) -> Result<Self> {
        const ALLOWED: &str = "pencil, diffuse, collimated:R or diffuse:R with R > 0 (MFP)";
        let radius = |r: &str| -> Result<f64> {
            match r.parse::<f64>() {
                Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
                _ => Err(Error::param("source", s, ALLOWED)),
            }
        };
        match s.split_once(':') {
            None if s == "pencil" => Ok(Source::Pencil),
            None if s == "diffuse" => Ok(Source::Diffuse { radius: 0.0 }),
            Some(("collimated", r)) => Ok(Source::Collimated { radius: radius(r)? }),
            Some(("diffuse", r)) => Ok(Source::Diffuse { radius: radius(r)? }),
            _ => Err(Error::param("source", s, ALLOWED)),
        }
    }

    /// Incident power: 1 for the pencil and the diffuse point source, πR²
    /// (unit irradiance) for a disk.
    pub fn power(&self) -> f64 {
        match *self {
            Source::Pencil => 1.0,
            Source::Diffuse { radius: 0.0 } => 1.0,
            Source::Collimated { radius } | Source::Diffuse { radius } => {
                std::f64::consts::PI * radius * radius
            }
        }
    }

    /// Whether every path arrives at normal incidence; then the entry Fresnel
    /// transmittance is one constant, applied as a weight instead of sampled.
    pub fn is_normal_incidence(&self) -> bool {
        self.incidence() == Incidence::Pencil
    }

    /// The directions the light arrives from.
    pub fn incidence(&self) -> Incidence {
        match self {
            Source::Pencil | Source::Collimated { .. } => Incidence::Pencil,
            Source::Diffuse { .. } => Incidence::Diffuse,
        }
    }
}

/// The directions incident light arrives from: the one property of a
/// source that a basis profile depends on (its spatial extent is convolved
/// in by the renderer). Written `pencil` / `diffuse` in documents.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Incidence {
    /// Normal incidence: a pencil beam, or a collimated disk light.
    Pencil,
    /// Cosine-distributed directions (a diffuse light).
    Diffuse,
}

impl Incidence {
    pub fn name(self) -> &'static str {
        match self {
            Incidence::Pencil => "pencil",
            Incidence::Diffuse => "diffuse",
        }
    }
}

/// What leaves the surface and is measured: the radiant exitance, or the
/// radiance along the normal (what an orthographic camera looking straight
/// down sees). A basis profile is of one observable. Written `exitance` /
/// `radiance` in documents.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    Hash,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum Observable {
    /// Radiant exitance M(x, y) per unit incident irradiance.
    #[default]
    Exitance,
    /// Radiance leaving along the normal.
    Radiance,
}

impl Observable {
    pub fn name(self) -> &'static str {
        match self {
            Observable::Exitance => "exitance",
            Observable::Radiance => "radiance",
        }
    }
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::Pencil => write!(f, "pencil"),
            Source::Collimated { radius } => write!(f, "collimated:{radius}"),
            Source::Diffuse { radius } if *radius == 0.0 => write!(f, "diffuse"),
            Source::Diffuse { radius } => write!(f, "diffuse:{radius}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_parameter() {
        let e = Medium::new(1.2, 0.3, 1.5, 1.0, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("albedo") && e.contains("[0, 1]"), "{e}");
        assert!(Medium::new(0.5, 1.0, 1.5, 1.0, None).is_err());
        assert!(Medium::new(0.5, 0.3, 0.9, 1.0, None).is_err());
        assert!(Medium::new(0.5, 0.3, 1.5, 0.0, None).is_err());
        assert!(Medium::new(0.5, 0.3, 1.5, f64::NAN, None).is_err());
        assert!(Medium::new(f64::NAN, 0.3, 1.5, 1.0, None).is_err());
        assert!(Medium::new(0.5, 0.3, 1.5, 1.0, Some(-1.0)).is_err());
    }

    #[test]
    fn source_parse_round_trip() {
        for s in ["pencil", "collimated:1", "diffuse:4.5"] {
            assert_eq!(Source::parse(s).unwrap().to_string(), s);
        }
        for bad in [
            "",
            "laser",
            "collimated",
            "collimated:-1",
            "diffuse:x",
            "pencil:1",
        ] {
            assert!(Source::parse(bad).is_err(), "{bad}");
        }
    }
}
