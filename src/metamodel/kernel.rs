//! Aggregation kernels as Gaussian mixtures (docs/design.md §2 "Frames for kernels",
//! §4 "Aggregation" and "The manual kernel"). Pure evaluation and
//! (de)serialisation; the per-configuration fit lives in [`crate::fit::gmm`].
//!
//! # Frame
//! For an entry point x_i and an exit point x_e at distance d (MFP), the
//! kernel lives in the pair frame: t runs along the axis from x_i (t = 0) to
//! x_e (t = d), s is the perpendicular surface coordinate. Depth is
//! integrated out, so a kernel is a 2D density K(t, s) (1/MFP²) of unit mass,
//! symmetric in s for a homogeneous medium (mirror symmetry).
//!
//! # Model
//! K(t, s) = Σ_k w_k·N₂((t, s); (t_k, s_k), σ_k²·I) with
//! N₂(x; μ, σ²I) = exp(−|x − μ|²/(2σ²))/(2πσ²): isotropic components, so
//! that aggregation under one component is one lookup in a Gaussian pyramid
//! (docs/design.md §4). Our kernels keep every centre on the axis (s_k = 0), which
//! makes them exactly symmetric in s; the field stays in the JSON contract
//! `{ "weight", "t", "s", "sigma" }`.
//!
//! # Density scaling (docs/design.md §2, §4)
//! A homogeneous medium of density ρ has σ_t = ρ, so a length ℓ in it is the
//! optical length ρℓ in the reference medium: all lengths scale by 1/ρ,
//! K(·; d, α, ρ) = K(·; ρd, α, 1) with every length (t, s, σ) divided by ρ.
//! [`optical_distance`] and [`scale_for_density`] implement this once.

use serde::{Deserialize, Serialize};
use std::f64::consts::{FRAC_1_SQRT_2, PI};

/// One isotropic 2D Gaussian of a kernel: weight w (dimensionless, mass of
/// the component), centre (t, s) in MFP in the pair frame, width σ in MFP
/// (standard deviation along each axis).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Component {
    pub weight: f64,
    pub t: f64,
    pub s: f64,
    pub sigma: f64,
}

/// A kernel K(t, s) = Σ_k w_k N₂((t, s); (t_k, s_k), σ_k² I) in the pair
/// frame (module docs). A valid kernel ([`Gmm::is_valid`]) has unit mass.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Gmm {
    pub components: Vec<Component>,
}

/// 1/√(2π).
const FRAC_1_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// Standard normal pdf φ(z) = e^{−z²/2}/√(2π) (0 at z = ±∞).
#[inline]
pub fn std_normal_pdf(z: f64) -> f64 {
    FRAC_1_SQRT_2PI * (-0.5 * z * z).exp()
}

/// z·φ(z), with the limit 0 at z = ±∞ (not ∞·0 = NaN).
#[inline]
fn z_pdf(z: f64) -> f64 {
    if z.is_finite() {
        z * std_normal_pdf(z)
    } else {
        0.0
    }
}

/// Φ(zb) − Φ(za) for za ≤ zb, Φ the standard normal CDF, to full relative
/// precision in either tail.
///
/// # Formula
/// Φ(z) = ½ erfc(−z/√2). When both arguments lie in the upper tail the
/// difference is taken between complements, ½[erfc(za/√2) − erfc(zb/√2)]
/// (and mirrored in the lower tail), so a far-tail interval of mass 1e-30 is
/// not lost to cancellation against 1. Infinite arguments are allowed.
#[inline]
pub fn std_normal_mass(za: f64, zb: f64) -> f64 {
    if za >= 0.0 {
        0.5 * (libm::erfc(za * FRAC_1_SQRT_2) - libm::erfc(zb * FRAC_1_SQRT_2))
    } else if zb <= 0.0 {
        0.5 * (libm::erfc(-zb * FRAC_1_SQRT_2) - libm::erfc(-za * FRAC_1_SQRT_2))
    } else {
        0.5 * (libm::erf(zb * FRAC_1_SQRT_2) - libm::erf(za * FRAC_1_SQRT_2))
    }
}

/// Mass of the 1D normal N(μ, σ²) in [a, b] (a ≤ b, MFP; infinite ends allowed).
///
/// # Formula
/// P = Φ((b − μ)/σ) − Φ((a − μ)/σ), via [`std_normal_mass`].
#[inline]
pub fn gauss_interval(a: f64, b: f64, mu: f64, sigma: f64) -> f64 {
    std_normal_mass((a - mu) / sigma, (b - mu) / sigma)
}

/// [`gauss_interval`] and its derivatives with respect to the centre μ and
/// the log width ln σ: `[P, ∂P/∂μ, ∂P/∂ln σ]`.
///
/// # Formula
/// With z = (x − μ)/σ at each end: ∂Φ(z)/∂μ = −φ(z)/σ and
/// ∂Φ(z)/∂ln σ = −z φ(z), so
/// ∂P/∂μ = −[φ(z_b) − φ(z_a)]/σ (1/MFP) and ∂P/∂ln σ = −[z_b φ(z_b) − z_a φ(z_a)]
/// (dimensionless); an infinite end contributes 0.
#[inline]
pub fn gauss_interval_grad(a: f64, b: f64, mu: f64, sigma: f64) -> [f64; 3] {
    let (za, zb) = ((a - mu) / sigma, (b - mu) / sigma);
    [
        std_normal_mass(za, zb),
        -(std_normal_pdf(zb) - std_normal_pdf(za)) / sigma,
        -(z_pdf(zb) - z_pdf(za)),
    ]
}

impl Component {
    /// A vertex that lies exactly under its end of the pair, at t on the
    /// axis, of weight w: a Gaussian of width [`POINT_SIGMA`].
    pub fn point(weight: f64, t: f64) -> Self {
        Component {
            weight,
            t,
            s: 0.0,
            sigma: POINT_SIGMA,
        }
    }

    /// N₂((t, s); (t_k, s_k), σ_k² I)·w_k (1/MFP²).
    #[inline]
    pub fn density(&self, t: f64, s: f64) -> f64 {
        let (dt, ds) = (t - self.t, s - self.s);
        let v = self.sigma * self.sigma;
        self.weight * (-(dt * dt + ds * ds) / (2.0 * v)).exp() / (2.0 * PI * v)
    }

    /// Mass of the component with |s| ∈ [a, b] (0 ≤ a ≤ b), unweighted:
    /// P_s([a, b]) + P_s([−b, −a]) (= 2·[Φ(b/σ) − Φ(a/σ)] for s_k = 0).
    #[inline]
    fn fold_s(&self, a: f64, b: f64) -> f64 {
        let a = a.max(0.0);
        if b <= a {
            return 0.0;
        }
        gauss_interval(a, b, self.s, self.sigma) + gauss_interval(-b, -a, self.s, self.sigma)
    }
}

/// `w 0.335 t +0.052 σ 0.079 | w …`: each component's weight, position
/// along the pair axis and width (MFP), on one line.
impl std::fmt::Display for Gmm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (k, c) in self.components.iter().enumerate() {
            if k > 0 {
                f.write_str(" | ")?;
            }
            write!(f, "w {:.3} t {:+.3} σ {:.3}", c.weight, c.t, c.sigma)?;
        }
        Ok(())
    }
}

impl Gmm {
    /// K(t, s) (1/MFP², t and s in MFP).
    pub fn density(&self, t: f64, s: f64) -> f64 {
        self.components.iter().map(|c| c.density(t, s)).sum()
    }

    /// Density folded in |s|: K(t, u) + K(t, −u) for u > 0 (1/MFP²), the
    /// density of the (t, |s|) histograms of [`crate::fit::gmm`].
    pub fn density_folded(&self, t: f64, u: f64) -> f64 {
        self.density(t, u) + self.density(t, -u)
    }

    /// Σ_k w_k (the mass; 1 for a valid kernel).
    pub fn total_weight(&self) -> f64 {
        self.components.iter().map(|c| c.weight).sum()
    }

    /// ∫_{t0}^{t1}∫_{s0}^{s1} K dt ds over an axis-aligned box (t0 ≤ t1,
    /// s0 ≤ s1, MFP; infinite edges allowed). Exact:
    /// Σ_k w_k·[Φ((t1 − t_k)/σ_k) − Φ((t0 − t_k)/σ_k)]·[Φ((s1 − s_k)/σ_k) − Φ((s0 − s_k)/σ_k)].
    pub fn mass_in_box(&self, t0: f64, t1: f64, s0: f64, s1: f64) -> f64 {
        self.components
            .iter()
            .map(|c| {
                c.weight
                    * gauss_interval(t0, t1, c.t, c.sigma)
                    * gauss_interval(s0, s1, c.s, c.sigma)
            })
            .sum()
    }

    /// Mass with t ∈ [t0, t1] and |s| ∈ [a, b] (0 ≤ a ≤ b; a < 0 is read as
    /// 0): the bin mass of a histogram folded in |s|. Exact: the two mirror
    /// boxes s ∈ [a, b] and s ∈ [−b, −a]; for a centre on the axis the s
    /// factor is 2·[Φ(b/σ_k) − Φ(a/σ_k)].
    pub fn mass_in_fold(&self, t0: f64, t1: f64, a: f64, b: f64) -> f64 {
        self.components
            .iter()
            .map(|c| c.weight * gauss_interval(t0, t1, c.t, c.sigma) * c.fold_s(a, b))
            .sum()
    }

    /// The same kernel with weights divided by their sum, so that it has unit
    /// mass. A kernel whose total weight is not positive and finite is
    /// returned unchanged (it cannot be normalised; [`Gmm::is_valid`] says no).
    pub fn normalized(&self) -> Gmm {
        let total = self.total_weight();
        if !(total.is_finite() && total > 0.0) {
            return self.clone();
        }
        Gmm {
            components: self
                .components
                .iter()
                .map(|c| Component {
                    weight: c.weight / total,
                    ..c.clone()
                })
                .collect(),
        }
    }

    /// A usable kernel: at least one component, every number finite,
    /// weights ≥ 0 summing to 1 within 1e-12, widths σ > 0.
    pub fn is_valid(&self) -> bool {
        !self.components.is_empty()
            && self.components.iter().all(|c| {
                c.weight.is_finite()
                    && c.weight >= 0.0
                    && c.t.is_finite()
                    && c.s.is_finite()
                    && c.sigma.is_finite()
                    && c.sigma > 0.0
            })
            && (self.total_weight() - 1.0).abs() <= 1e-12
    }

    /// Mean position along the axis, Σ w_k t_k / Σ w_k (MFP).
    pub fn mean_t(&self) -> f64 {
        self.components.iter().map(|c| c.weight * c.t).sum::<f64>() / self.total_weight()
    }

    /// Every length (t, s, σ) multiplied by `factor` (> 0); weights, hence
    /// the mass, unchanged. The density transforms as
    /// K'(t, s) = K(t/f, s/f)/f².
    pub fn scaled(&self, factor: f64) -> Gmm {
        Gmm {
            components: self
                .components
                .iter()
                .map(|c| Component {
                    weight: c.weight,
                    t: c.t * factor,
                    s: c.s * factor,
                    sigma: c.sigma * factor,
                })
                .collect(),
        }
    }
}

/// The least interior vertex count m of [`interior_into`]: it bounds the
/// signed weights to [−1/m, (m + 2)/m] = [−1, 3].
pub const INTERIOR_MIN: f64 = 1.0;

/// Width (MFP) of the component that stands for an end vertex that lies
/// exactly under its end point (narrower than any texel, so a read of it is
/// the texel's value).
pub const POINT_SIGMA: f64 = 1e-3;

/// The kernel of a path's interior vertices (all but the first and the
/// last), into `out`, from the all-vertex kernel `all` and the end
/// vertices' kernels at distance `d` (MFP): `first` (`None`: a point at
/// x_i, t = 0, as under normal incidence) and `last` (`None`: a point at
/// x_e, t = d).
///
/// The all-vertex kernel is the vertices' density normalised by their mean
/// count n̄, so n̄·K_all = K_first + K_last + (n̄ − 2)·K_int and
///
///   K_int = ((m + 2)·K_all − K_first − K_last)/m,  m = max(n̄ − 2, [`INTERIOR_MIN`]),
///
/// a signed mixture of unit mass (each input kernel is normalised first).
/// For the homogeneous profile, n̄ − 2 = ∂ln(Rₘ/α²)/∂ln α
/// ([`crate::render::svbssrdf::BasisTable::interior_vertices`]). Below the
/// floor the end lobes are only partly removed (docs/design.md §4).
pub fn interior_into(
    all: &Gmm,
    first: Option<&Gmm>,
    last: Option<&Gmm>,
    d: f64,
    m: f64,
    out: &mut Gmm,
) {
    let m = m.max(INTERIOR_MIN);
    out.components.clear();
    let mut push = |g: Option<&Gmm>, t: f64, scale: f64| match g {
        Some(g) => {
            let w = scale / g.total_weight();
            out.components
                .extend(g.components.iter().map(|c| Component {
                    weight: c.weight * w,
                    ..c.clone()
                }));
        }
        None => out.components.push(Component::point(scale, t)),
    };
    push(Some(all), 0.0, (m + 2.0) / m);
    push(first, 0.0, -1.0 / m);
    push(last, d, -1.0 / m);
}

/// The manual kernel at distance d (MFP, d ≥ 0), docs/design.md §4, fixed and never
/// tuned against render errors: three isotropic Gaussians on the axis at
/// t = 0, d/2, d with weights 0.25, 0.5, 0.25 and widths
/// σ = 0.5, 0.5 + 0.3·d, 0.5 MFP. It stands in for the seed's hand fit, whose
/// numbers were not published. It is a unit-density kernel: for density ρ,
/// use `scale_for_density(&manual_kernel(optical_distance(d, ρ)), ρ)`.
pub fn manual_kernel(d: f64) -> Gmm {
    let c = |weight: f64, t: f64, sigma: f64| Component {
        weight,
        t,
        s: 0.0,
        sigma,
    };
    Gmm {
        components: vec![
            c(0.25, 0.0, 0.5),
            c(0.5, 0.5 * d, 0.5 + 0.3 * d),
            c(0.25, d, 0.5),
        ],
    }
}

/// Optical distance ρ·d (MFP of the reference medium) of a physical distance
/// d (MFP) in a homogeneous medium of density ρ > 0 (σ_t = ρ). This is the
/// distance at which the unit-density kernel (meta-model or
/// [`manual_kernel`]) is evaluated; see [`scale_for_density`].
#[inline]
pub fn optical_distance(d: f64, rho: f64) -> f64 {
    d * rho
}

/// The density scaling law, implemented once (docs/design.md §2, §4).
///
/// In a homogeneous medium of density ρ > 0 (σ_t = ρ) every length scales by
/// 1/ρ: K(·; d, α, ρ) = K(·; ρd, α, 1) with all lengths divided by ρ. The
/// caller evaluates the unit-density kernel at the optical distance
/// [`optical_distance`]`(d, ρ)` = ρd, then calls `scale_for_density(k, ρ)`,
/// which is `k.scaled(1/ρ)`: the result is the kernel in physical MFP of the
/// reference medium, with its axis running from t = 0 to t = d.
pub fn scale_for_density(kernel_at_unit_density_for_rho_d: &Gmm, rho: f64) -> Gmm {
    kernel_at_unit_density_for_rho_d.scaled(1.0 / rho)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_interior_kernel_is_what_the_ends_leave() {
        // All vertices of paths with m interior vertices drawn from `wide`,
        // the first at x_i and the last from `end`: n̄·K_all = δ_i + K_end
        // + m·K_wide with n̄ = m + 2. Removing the ends gives back `wide`.
        let c = |weight: f64, t: f64, sigma: f64| Component {
            weight,
            t,
            s: 0.0,
            sigma,
        };
        let (d, m) = (1.5, 3.0);
        let wide = Gmm {
            components: vec![c(0.7, 0.75, 0.6), c(0.3, 0.2, 1.1)],
        };
        let end = Gmm {
            components: vec![c(1.0, 1.4, 0.15)],
        };
        let n = m + 2.0;
        let mut all = Gmm {
            components: vec![c(1.0 / n, 0.0, POINT_SIGMA)],
        };
        all.components
            .extend(end.components.iter().map(|k| c(k.weight / n, k.t, k.sigma)));
        all.components.extend(
            wide.components
                .iter()
                .map(|k| c(k.weight * m / n, k.t, k.sigma)),
        );
        // Input kernels of any mass: each is normalised first.
        let heavier = |g: &Gmm, f: f64| Gmm {
            components: g
                .components
                .iter()
                .map(|k| c(k.weight * f, k.t, k.sigma))
                .collect(),
        };
        let all = heavier(&all, 2.0);
        let mut out = Gmm::default();
        interior_into(&all, None, Some(&heavier(&end, 0.5)), d, m, &mut out);
        assert!((out.total_weight() - 1.0).abs() < 1e-12);
        for (t, s) in [
            (0.0, 0.0),
            (0.3, 0.1),
            (0.75, 0.0),
            (1.4, 0.0),
            (1.4, 0.3),
            (2.5, -0.5),
        ] {
            let (got, want) = (out.density(t, s), wide.density(t, s));
            assert!(
                (got - want).abs() < 1e-9 * (1.0 + want),
                "({t}, {s}): {got} vs {want}"
            );
        }
        // A point last vertex lies at t = d; below the floor m the ends are
        // only partly removed, and the weights stay within [−1, 3].
        interior_into(&all, None, None, d, 0.2, &mut out);
        assert_eq!(out.components.last().unwrap().t, d);
        assert!((out.total_weight() - 1.0).abs() < 1e-12);
        assert!(
            out.components
                .iter()
                .all(|k| (-1.0..=3.0).contains(&k.weight))
        );
    }

    /// A non-trivial kernel with off-axis centres and unequal widths.
    fn skewed() -> Gmm {
        Gmm {
            components: vec![
                Component {
                    weight: 0.2,
                    t: -0.3,
                    s: 0.4,
                    sigma: 0.35,
                },
                Component {
                    weight: 0.5,
                    t: 1.1,
                    s: 0.0,
                    sigma: 0.8,
                },
                Component {
                    weight: 0.3,
                    t: 2.0,
                    s: -0.2,
                    sigma: 0.5,
                },
            ],
        }
    }

    /// Midpoint rule on an n×n grid of ∫∫ f over [t0, t1]×[s0, s1].
    fn midpoint(f: impl Fn(f64, f64) -> f64, t0: f64, t1: f64, s0: f64, s1: f64, n: usize) -> f64 {
        let (ht, hs) = ((t1 - t0) / n as f64, (s1 - s0) / n as f64);
        let mut sum = 0.0;
        for i in 0..n {
            let t = t0 + (i as f64 + 0.5) * ht;
            for j in 0..n {
                sum += f(t, s0 + (j as f64 + 0.5) * hs);
            }
        }
        sum * ht * hs
    }

    #[test]
    fn std_normal_mass_is_accurate_in_the_tails() {
        // Φ(∞) − Φ(−∞) = 1, Φ(0) − Φ(−∞) = ½, and a far upper tail keeps its
        // relative precision: Φc(10) = 7.619853024160527e-24.
        assert_eq!(std_normal_mass(f64::NEG_INFINITY, f64::INFINITY), 1.0);
        assert!((std_normal_mass(f64::NEG_INFINITY, 0.0) - 0.5).abs() < 1e-16);
        let tail = std_normal_mass(10.0, f64::INFINITY);
        assert!(
            (tail / 7.619_853_024_160_527e-24 - 1.0).abs() < 1e-12,
            "{tail}"
        );
        let mirror = std_normal_mass(f64::NEG_INFINITY, -10.0);
        assert_eq!(tail, mirror);
        // Φ(1) − Φ(−1) = erf(1/√2) = 0.682689492137086.
        assert!((std_normal_mass(-1.0, 1.0) - 0.682_689_492_137_086).abs() < 1e-14);
    }

    #[test]
    fn manual_kernel_has_unit_mass() {
        for d in [0.0, 1e-6, 0.5, 1.0, 3.0, 50.0] {
            let k = manual_kernel(d);
            assert!(k.is_valid(), "{d}: {k:?}");
            assert!((k.total_weight() - 1.0).abs() < 1e-15);
            let big = 60.0 + 2.0 * d;
            let m = k.mass_in_box(-big, d + big, -big, big);
            assert!((m - 1.0).abs() < 1e-12, "d = {d}: box mass {m}");
            let f = k.mass_in_fold(-big, d + big, 0.0, big);
            assert!((f - 1.0).abs() < 1e-12, "d = {d}: folded mass {f}");
            let inf = f64::INFINITY;
            assert!((k.mass_in_box(-inf, inf, -inf, inf) - 1.0).abs() < 1e-15);
            // Symmetric layout: the mean sits half-way along the axis.
            assert!((k.mean_t() - 0.5 * d).abs() < 1e-12 * (1.0 + d));
            assert!(k.density(0.5 * d, 0.0).is_finite() && k.density(0.5 * d, 0.0) > 0.0);
        }
        // The exact layout of docs/design.md §4 at d = 2.
        let k = manual_kernel(2.0);
        let want = [(0.25, 0.0, 0.5), (0.5, 1.0, 1.1), (0.25, 2.0, 0.5)];
        for (c, w) in k.components.iter().zip(want) {
            assert_eq!((c.weight, c.t, c.s), (w.0, w.1, 0.0));
            assert!((c.sigma - w.2).abs() < 1e-15);
        }
    }

    #[test]
    fn box_and_fold_masses_match_quadrature() {
        let k = skewed();
        let n = 2000;
        for (t0, t1, s0, s1) in [
            (-1.0, 0.5, -0.5, 0.7),
            (0.3, 2.7, 0.1, 1.9),
            (1.5, 3.0, -2.0, -0.4),
        ] {
            let exact = k.mass_in_box(t0, t1, s0, s1);
            let quad = midpoint(|t, s| k.density(t, s), t0, t1, s0, s1, n);
            assert!(
                (exact - quad).abs() < 1e-6,
                "box {t0} {t1} {s0} {s1}: {exact} vs {quad}"
            );
        }
        for (t0, t1, a, b) in [
            (-1.0, 0.5, 0.0, 0.7),
            (0.3, 2.7, 0.2, 1.9),
            (-2.0, 4.0, 1.0, 3.0),
        ] {
            let exact = k.mass_in_fold(t0, t1, a, b);
            let quad = midpoint(|t, u| k.density_folded(t, u), t0, t1, a, b, n);
            assert!(
                (exact - quad).abs() < 1e-6,
                "fold {t0} {t1} {a} {b}: {exact} vs {quad}"
            );
            // The fold is the sum of the two mirror boxes.
            let boxes = k.mass_in_box(t0, t1, a, b) + k.mass_in_box(t0, t1, -b, -a);
            assert!((exact - boxes).abs() < 1e-15);
        }
        // Centred components: the fold factor is 2·(Φ(b/σ) − Φ(a/σ)).
        let m = manual_kernel(1.0);
        let (a, b) = (0.3, 1.2);
        let direct: f64 = m
            .components
            .iter()
            .map(|c| {
                c.weight
                    * gauss_interval(0.0, 1.0, c.t, c.sigma)
                    * 2.0
                    * std_normal_mass(a / c.sigma, b / c.sigma)
            })
            .sum();
        assert!((m.mass_in_fold(0.0, 1.0, a, b) - direct).abs() < 1e-15);
    }

    #[test]
    fn interval_gradient_matches_differences() {
        for (a, b, mu, sigma) in [
            (-0.5, 0.7, 0.1, 0.4),
            (1.0, 3.0, -0.2, 0.9),
            (0.0, f64::INFINITY, 0.3, 0.6),
        ] {
            let g = gauss_interval_grad(a, b, mu, sigma);
            let h = 1e-6;
            let dmu = (gauss_interval(a, b, mu + h, sigma) - gauss_interval(a, b, mu - h, sigma))
                / (2.0 * h);
            let dls = (gauss_interval(a, b, mu, sigma * h.exp())
                - gauss_interval(a, b, mu, sigma * (-h).exp()))
                / (2.0 * h);
            assert!((g[0] - gauss_interval(a, b, mu, sigma)).abs() < 1e-16);
            assert!((g[1] - dmu).abs() < 1e-8, "{g:?} {dmu}");
            assert!((g[2] - dls).abs() < 1e-8, "{g:?} {dls}");
        }
    }

    #[test]
    fn density_scaling_round_trips() {
        let (d, rho) = (1.7, 2.5);
        let unit = manual_kernel(optical_distance(d, rho));
        let k = scale_for_density(&unit, rho);
        assert!(k.is_valid());
        // The axis runs from 0 to the physical distance d.
        assert!((k.components[2].t - d).abs() < 1e-14);
        assert!((k.mean_t() - 0.5 * d).abs() < 1e-14);
        // Back to unit density.
        let back = k.scaled(rho);
        for (a, b) in back.components.iter().zip(&unit.components) {
            assert_eq!(a.weight, b.weight);
            assert!((a.t - b.t).abs() < 1e-14 && (a.sigma - b.sigma).abs() < 1e-14);
        }
        // Masses: a physical box B holds what the unit kernel holds in ρB,
        // and the density transforms as K(t, s) = ρ²·K₁(ρt, ρs).
        let (t0, t1, s0, s1) = (0.2, 1.1, -0.3, 0.5);
        let m = k.mass_in_box(t0, t1, s0, s1);
        let m1 = unit.mass_in_box(rho * t0, rho * t1, rho * s0, rho * s1);
        assert!((m - m1).abs() < 1e-14, "{m} vs {m1}");
        let (t, s) = (0.9, 0.2);
        assert!((k.density(t, s) - rho * rho * unit.density(rho * t, rho * s)).abs() < 1e-12);
        // ρ = 1 is the identity.
        assert_eq!(scale_for_density(&unit, 1.0), unit);
    }

    #[test]
    fn extreme_distances_are_finite() {
        for d in [1e-6, 50.0] {
            let k = manual_kernel(d);
            assert!(k.is_valid());
            for (t, s) in [(0.0, 0.0), (0.5 * d, 0.3), (d, -1.0), (-3.0, 2.0)] {
                let v = k.density(t, s);
                assert!(v.is_finite() && v >= 0.0, "d = {d}: K({t}, {s}) = {v}");
            }
            let m = k.mass_in_fold(-1.0, d + 1.0, 0.0, 1.0);
            assert!(m.is_finite() && m > 0.0 && m < 1.0);
        }
    }

    #[test]
    fn normalisation_and_json_contract() {
        let mut k = skewed();
        for c in &mut k.components {
            c.weight *= 3.0;
        }
        assert!(!k.is_valid());
        let n = k.normalized();
        assert!(n.is_valid() && (n.total_weight() - 1.0).abs() < 1e-15);
        let zero = Gmm {
            components: vec![Component {
                weight: 0.0,
                t: 0.0,
                s: 0.0,
                sigma: 1.0,
            }],
        };
        assert_eq!(zero.normalized(), zero);
        assert!(!zero.is_valid());
        let json = serde_json::to_string(&manual_kernel(1.0)).unwrap();
        assert!(
            json.starts_with(r#"{"components":[{"weight":0.25,"t":0.0,"s":0.0,"sigma":0.5}"#),
            "{json}"
        );
        let back: Gmm = serde_json::from_str(&json).unwrap();
        assert_eq!(back, manual_kernel(1.0));
    }
}
