//! The SV-BSSRDF S(x_i, x_e) of every method of docs/design.md §4, evaluated from
//! the basis profile ([`crate::metamodel::basis`]) and the aggregation
//! kernels ([`crate::metamodel`]).
//!
//! # Units and what S is
//! S(x_i, x_e) is the radiant exitance at x_e per unit power entering at
//! x_i (1/MFP²), entry Fresnel loss included (the basis profiles are per
//! incident power); on a basis of the radiance along the normal
//! ([`BasisModel::observable`]) it is that radiance (1/(MFP²·sr)), and every
//! formula below holds with R read as that basis' profile. For a homogeneous medium of albedo α and density ρ,
//! S = R(r; α, ρ) = ρ²·R(ρr; α, 1): every length scales by 1/ρ, so the
//! exitance picks up the area Jacobian ρ². R(r; α, 1) = α·R₁(r; 1) + Rₘ(r; α)
//! with R₁(r; 1) = p₁(r)/(2πr) and Rₘ(r; α) = Σ_k A_k(α)/(2π)·e^{−B_k r}
//! (the basis model's exitance mixture).
//!
//! # The methods
//! | method | S |
//! |---|---|
//! | `point` | R(r; α_e, ρ_e) |
//! | `factorized` | √(R(r; α_i, ρ_i)·R(r; α_e, ρ_e)) |
//! | `line` | R(r; ᾱ, ρ̄) over the segment x_i → x_e |
//! | `ellipse` | R(r; ᾱ, ρ̄) over the ellipse with foci x_i, x_e |
//! | `manual`, `learned` | √(P(ρ_i)·P(ρ_e)), P(ρ) = ρ²·[α₁·R₁(ρr; 1) + α_i·α_e·Rₘ(ρr; α_t)/α_t²] |
//!
//! The kernel methods' profile P is scaled by the densities at both ends
//! ([`DensityLaw::Endpoints`]; P(ρ̄) with the kernel's mean density ρ̄ under
//! [`DensityLaw::Kernel`]); in a homogeneous medium both are P(ρ).
//! Every average over a support (segment, ellipse, kernel) is density-scaled
//! the same way: ᾱ = ∫ρα/∫ρ, ρ̄ = ∫ρ (normalised weights), the design's
//! aggregation with r_eff = r·ρ̄. `line` samples the segment at spacing
//! ≤ τ/2 (cost ∝ d/τ); `ellipse` takes the ellipse with foci x_i, x_e and
//! semi-major axis a = d/2 + 1/ρ₀ (one mean free path beyond each focus,
//! ρ₀ = (ρ_i + ρ_e)/2, the Sone et al. 2017 support), integrated texel row
//! by texel row (exact in x from row prefix sums, midpoint in y; cost ∝ the
//! ellipse's height in texels, ∝ d).
//!
//! `manual` and `learned` use the split form (docs/design.md §4): α₁ = α_i (under
//! collimated normal incidence the single-scattering vertex lies straight
//! below x_i; for the radiance along the normal α₁ = α_e, since the vertex
//! that sends light straight up through x_e lies straight below it under
//! any light), α_t = Σ_k w_k (G_σk ∗ ρα)(μ_k)/Σ_k w_k (G_σk ∗ ρ)(μ_k) and
//! ρ̄ = Σ_k w_k (G_σk ∗ ρ)(μ_k) from Gaussian pyramids ([`super::pyramid`]),
//! with the kernel evaluated at (d, α₀ = (α_i + α_e)/2, ρ₀) and placed in the
//! pair frame (t along x_i → x_e). The ratio α_iα_e/α_t² multiplies
//! Rₘ(α_t)/α_t², which the basis stores as a bounded function
//! (A_k/α² = exp(polynomial)), so nothing divides by α_t: S stays finite as
//! albedos go to 0.
//!
//! # Variants ([`Variant`], compared by `svkernel experiments`)
//! * `plain`: α_t = Σ w_k (G ∗ α)(μ_k) (not density-scaled; ρ̄ as above);
//! * `vertex_kernels` (the default): α_i and α_e of the multiple-scattering
//!   term are aggregated under the first- and last-vertex kernels instead of
//!   read at the points (off: `--point-albedos`). For the radiance along the
//!   normal α_e stays the point value: the vertex that sends light straight
//!   up through x_e lies straight below it;
//! * `two_pass`: the kernel is evaluated again at α₀ = α_t and ρ₀ = ρ̄, and
//!   α_t, ρ̄ recomputed;
//! * `interior` ([`InteriorKernel`]): where `learned`'s α_t leaves out the
//!   first and last vertices, which l_i and l_e already count; by default
//!   blended in where the all-vertex α_t exceeds 0.95 ([`INTERIOR_RAMP`]);
//! * `step_ends` ([`StepEnds`]): where x_i and x_e lie on the two sides of
//!   a coarse albedo step, `learned` counts the ends once in α_t and reads
//!   l_i, l_e towards their two-scale means;
//! * `last_kernel` ([`LastKernel`]): `learned` reads l_e under the
//!   last-vertex kernel queried at l_e itself (the albedo its vertex sees)
//!   rather than at α₀.
//!
//! # r → 0
//! R₁ diverges like 1/r (integrable in area); S is evaluated at
//! max(r, [`R_MIN`]) so that x_i = x_e gives a large finite value.

use crate::error::{Error, Result};
use crate::fastmath::exp4;
use crate::forward::maps::TexelMap;
use crate::forward::medium::Observable;
use crate::metamodel::basis::{BasisModel, ExpMixture, albedo_coordinate};
use crate::metamodel::kernel::{Component, Gmm, INTERIOR_MIN, interior_into};
use crate::metamodel::meta::{MetaModel, MetaModelFile};
use crate::render::pyramid::{self, GaussianPyramid};
use std::f64::consts::PI;
use std::sync::{Arc, OnceLock};

/// Smallest r (MFP) at which S is evaluated.
pub const R_MIN: f64 = 1e-6;

/// The methods of docs/design.md §4's table (the reference is rendered separately).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Method {
    Point,
    Factorized,
    Line,
    Ellipse,
    Manual,
    Learned,
}

impl Method {
    /// In the order of the report's image rows.
    pub const ALL: [Method; 6] = [
        Method::Point,
        Method::Factorized,
        Method::Line,
        Method::Ellipse,
        Method::Manual,
        Method::Learned,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Method::Point => "point",
            Method::Factorized => "factorized",
            Method::Line => "line",
            Method::Ellipse => "ellipse",
            Method::Manual => "manual",
            Method::Learned => "learned",
        }
    }

    /// Parses a method name (`--method`, scene `methods`).
    pub fn parse(s: &str) -> Result<Method> {
        Method::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                Error::param(
                    "method",
                    s,
                    "point, factorized, line, ellipse, manual, learned or reference",
                )
            })
    }

    /// True for the kernel (local/global) methods that need pyramids.
    pub fn uses_kernel(self) -> bool {
        matches!(self, Method::Manual | Method::Learned)
    }
}

/// Written as its name ([`Method::name`]).
impl serde::Serialize for Method {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> serde::Deserialize<'de> for Method {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        Method::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// Options of the kernel methods (module docs). The default aggregates the
/// local terms under the first- and last-vertex kernels (`vertex_kernels`):
/// measured on the canonical scenes it cuts the learned method's relative
/// RMSE 4–12× against point albedos (docs/measurements.md); for `manual`, whose
/// vertex kernels are points, it changes nothing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Variant {
    pub plain: bool,
    pub vertex_kernels: bool,
    pub two_pass: bool,
    /// Where `learned` takes α_t under the interior vertices' kernel
    /// ([`interior_into`]) instead of the all-vertex one.
    pub interior: InteriorKernel,
    /// The space in which α_t is averaged under the all-vertex kernel
    /// (two-scale unless `linear`, see [`AlbedoSpace`]).
    pub space: AlbedoSpace,
    /// The scale b (MFP at the local density) that separates fine from
    /// coarse albedo variation in a two-scale [`AlbedoSpace`].
    pub space_blur: f64,
    /// The kernel of that split ([`Split`]).
    pub split: Split,
    /// The weight c of the coarse variance in the transport space (0, the
    /// default: off; [`COARSE_VARIANCE`] the measured weight).
    pub coarse_variance: f64,
    /// The density that scales the profile where the density varies.
    pub density_law: DensityLaw,
    /// How the kernels are placed where the density varies.
    pub density_kernel: DensityKernel,
    /// How `learned` treats a pair whose ends lie on the two sides of a
    /// coarse albedo step.
    pub step_ends: StepEnds,
    /// The albedo at which `learned` queries the last-vertex kernel that
    /// gives l_e.
    pub last_kernel: LastKernel,
}

/// Where `learned` takes α_t under the kernel of a path's interior
/// vertices ([`interior_into`]), so that the first and last vertices, which
/// l_i and l_e already count, are not counted again in the decay.
///
/// That is exact to first order in the albedo's variation, and measured
/// right where the paths are long and the dark features thin (a milky
/// material with a dark print: `milk` 2.2 → 1.0 %, `marble` 1.0 → 0.6 %).
/// Where the albedo is lower or its features coarse, the paths that reach
/// a bright exit keep to bright texels (a second-order effect the first-order
/// kernels miss), and the end lobes counted twice stand in for part of it:
/// there the interior kernel is worse (`stripes` 1.7 → 8.5 %; a coarse
/// texture of 0.98 | 0.5, 1.7 → 4.9 %). docs/measurements.md has the tables.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum InteriorKernel {
    /// The all-vertex kernel everywhere.
    Never,
    /// Blended in by the albedo that the paths see, the all-vertex α_t:
    /// α_t = α_all + w·(α_int − α_all), w rising smoothly from 0 to 1 over
    /// [`INTERIOR_RAMP`] (the default).
    #[default]
    Auto,
    /// The interior kernel everywhere.
    Always,
}

/// The all-vertex α_t over which [`InteriorKernel::Auto`] blends from the
/// all-vertex kernel (below) to the interior one (above). Chosen where the
/// two cross on a designed texture of albedo 0.8–1 (the model's mean bias
/// per albedo bin, docs/measurements.md) before any of the scenes it was
/// measured on was rendered with it.
pub const INTERIOR_RAMP: [f64; 2] = [0.95, 0.98];

/// The weight of the bright regime at albedo `alpha`: 0 below
/// [`INTERIOR_RAMP`], 1 above, smooth (C¹) between. The interior kernel
/// ([`InteriorKernel::Auto`]) and the split of the two-scale mean
/// ([`Split::Regimes`]) change regime over the same ramp.
#[inline]
pub fn bright_weight(alpha: f64) -> f64 {
    smoothstep(alpha, INTERIOR_RAMP)
}

impl InteriorKernel {
    /// The interior kernel's weight at the all-vertex α_t `alpha`.
    #[inline]
    pub fn weight(self, alpha: f64) -> f64 {
        match self {
            InteriorKernel::Never => 0.0,
            InteriorKernel::Always => 1.0,
            InteriorKernel::Auto => bright_weight(alpha),
        }
    }
}

/// Which density scales the kernel methods' profile, R(r; α_t, ρ) =
/// ρ²·R(ρr; α_t, 1), where the density varies (module docs). In a
/// homogeneous medium both laws are that density law itself.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum DensityLaw {
    /// S = √(R(r; α_t, ρ_i)·R(r; α_t, ρ_e)): the geometric mean of the
    /// profiles at the entry's and the exit's density, reciprocal in x_i and
    /// x_e. Where light enters sets how far it spreads before it turns, and
    /// where it leaves sets how it spreads on the way out; the albedo stays
    /// averaged under the kernel. The default: measured best across density
    /// steps, and equal to `kernel` on the density ramp
    /// (docs/measurements.md).
    #[default]
    Endpoints,
    /// S = R(r; α_t, ρ̄) with ρ̄ = ∫Kρ/∫K, the mean density under the
    /// all-vertex kernel.
    Kernel,
}

impl DensityLaw {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DensityLaw::Endpoints => "endpoints",
            DensityLaw::Kernel => "kernel",
        }
    }
}

/// How `manual`'s and `learned`'s kernels are placed where the density
/// varies (docs/method.md §4, "Across a density step"). At a constant
/// density both are the density law itself (bitwise for a constant
/// `density`, to rounding for a map of one value).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum DensityKernel {
    /// The kernel at the endpoints' mean density ρ₀ = (ρ_i + ρ_e)/2, its
    /// vertices weighted by the density across the whole mixture:
    /// α_t = Σ_k w_k (G ∗ ρα)(μ_k)/Σ_k w_k (G ∗ ρ)(μ_k).
    Scaled,
    /// The optical warp, placed component by component: the kernel at the
    /// mean density along the pair, ρ_s = D/d with D = ∫ρ along x_i → x_e
    /// (the unit-density kernel at the optical distance D, lengths × d/D),
    /// each centre moved to where the optical coordinate τ(t) = ∫₀ᵗρ
    /// reaches its own (ρ_i and ρ_e continue τ beyond the ends), and the
    /// density weighting applied within each component:
    /// α_t = Σ_k w_k (G ∗ ρα)(μ_k)/(G ∗ ρ)(μ_k) / Σ_k w_k.
    /// D and τ come from [`WARP_NODES`] midpoint samples of ρ: O(1) per
    /// evaluation. The default: closer to the reference than `scaled` on
    /// every textured density step measured, equal on density ramps
    /// (docs/measurements.md).
    #[default]
    Warp,
}

impl DensityKernel {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DensityKernel::Scaled => "scaled",
            DensityKernel::Warp => "warp",
        }
    }
}

/// How `learned` treats a pair whose ends lie on the two sides of a coarse
/// albedo step (docs/design.md §4, "Pairs across a step").
///
/// α_t under the all-vertex kernel counts the first and last vertices a
/// second time (l_i and l_e count them already). Where both ends see the
/// same albedo, that double count stands in for a second-order effect:
/// the paths that reach an end keep to the albedo around it
/// ([`InteriorKernel`]). Where the ends lie on the two sides of a coarse
/// step, it counts the dark end's lobe against paths that keep to the
/// bright side, and the end vertices' linear means miss that a path whose
/// end vertex lies on the bright side stayed there.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum StepEnds {
    /// Every pair alike: α_t under the all-vertex kernel (unless the
    /// interior kernel blends in by albedo), l_i and l_e linear means.
    Independent,
    /// The default. By the contrast between the ends' regional albedos
    /// ᾱ_R = G ∗ α over [`REGION_SCALE`] (density-weighted, lengths
    /// divided by the local density): α_t under the interior kernel with
    /// weight w_once = s(min(|α_i − α_e|, |ᾱ_R(x_i) − ᾱ_R(x_e)|)) over
    /// [`STEP_RAMP`] (the ends on two sides, point and region), and l_i,
    /// l_e moved towards their two-scale means ([`AlbedoSpace`], the
    /// darker regime's split) with weight w_corr = s(|ᾱ_R(x_i) −
    /// ᾱ_R(x_e)|) over [`CORRELATED_RAMP`] (a coarse contrast around the
    /// pair), s the smoothstep. A fine texture has no regional contrast,
    /// so nothing changes there. Measured on pencil beams across albedo
    /// steps and on the bench scenes (docs/measurements.md).
    #[default]
    Correlated,
}

impl StepEnds {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            StepEnds::Independent => "independent",
            StepEnds::Correlated => "correlated",
        }
    }
}

/// The albedo at which `learned` queries the last-vertex kernel whose
/// mean of α is l_e (exitance; docs/design.md §4, "The last vertex's
/// albedo").
///
/// The kernel of a homogeneous medium at albedo α says where the last
/// vertex of the paths x_i → x_e lies; how far it reaches depends on α
/// (the medium the path's last flights cross). The pair's mean α₀ =
/// (α_i + α_e)/2 mixes in the entry's albedo, which the last flights do
/// not see. l_e, the kernel-weighted albedo around x_e, is the albedo they
/// do see.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum LastKernel {
    /// At α₀, as the all-vertex kernel.
    Pair,
    /// The default. At l_e: the kernel at α₀ gives a first l_e, the kernel
    /// at that l_e the final one (one fixed-point step; a second moves no
    /// bench scene by more than 0.02 point). Pairs across a coarse step
    /// ([`StepEnds::Correlated`]'s w_once) keep α₀: the query albedo is
    /// l_e + w_once·(α₀ − l_e), since there the exit's lobe is read in the
    /// two-scale space and the paths came from the other side. Measured on
    /// the bench scenes, held-out textures and pencil beams
    /// (docs/measurements.md).
    #[default]
    Exit,
}

impl LastKernel {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LastKernel::Pair => "pair",
            LastKernel::Exit => "exit",
        }
    }
}

/// The scale (MFP at the local density) of the ends' regional albedo
/// ᾱ_R = G ∗ α that tells a coarse step from a fine texture
/// ([`StepEnds::Correlated`]): about one flight, the reach of an end
/// vertex's lobe.
pub const REGION_SCALE: f64 = 1.0;

/// The contrast (albedo units) over which [`StepEnds::Correlated`]'s
/// w_once rises from 0 to 1.
pub const STEP_RAMP: [f64; 2] = [0.1, 0.4];

/// The regional contrast (albedo units) over which
/// [`StepEnds::Correlated`]'s w_corr rises from 0 to 1.
pub const CORRELATED_RAMP: [f64; 2] = [0.02, 0.08];

/// The smoothstep (C¹) of `x` over `[lo, hi]`: 0 below, 1 above.
#[inline]
fn smoothstep(x: f64, [lo, hi]: [f64; 2]) -> f64 {
    let t = ((x - lo) / (hi - lo)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Midpoint samples of the density along the pair for
/// [`DensityKernel::Warp`].
pub const WARP_NODES: usize = 16;

/// The optical coordinate τ(t) = ∫₀ᵗρ along a pair, from [`WARP_NODES`]
/// midpoint samples of ρ on [0, d] (piecewise constant), continued by the
/// endpoints' densities beyond them.
struct OpticalAxis {
    d: f64,
    ends: [f64; 2],
    rho: [f64; WARP_NODES],
    /// τ at the nodes t_k = k·d/N.
    tau: [f64; WARP_NODES + 1],
}

impl OpticalAxis {
    /// D = τ(d), the optical distance of the pair.
    #[inline]
    fn optical_distance(&self) -> f64 {
        self.tau[WARP_NODES]
    }

    /// t with τ(t) = u (τ is increasing: ρ > 0).
    #[inline]
    fn inverse(&self, u: f64) -> f64 {
        let h = self.d / WARP_NODES as f64;
        if u <= 0.0 {
            return u / self.ends[0];
        }
        if u >= self.tau[WARP_NODES] {
            return self.d + (u - self.tau[WARP_NODES]) / self.ends[1];
        }
        let k = self.tau.partition_point(|&x| x <= u).clamp(1, WARP_NODES) - 1;
        k as f64 * h + (u - self.tau[k]) / self.rho[k]
    }

    /// Moves each centre of `g`, the kernel at the mean density
    /// ρ_s = D/d, to τ⁻¹(ρ_s·t).
    #[inline]
    fn place(&self, g: &mut Gmm) {
        let rho_s = self.optical_distance() / self.d;
        for c in &mut g.components {
            c.t = self.inverse(rho_s * c.t);
        }
    }
}

/// The default [`Variant::space_blur`], in MFP: the value a sweep over
/// 0.1–3 MFP on the canonical scenes picked (docs/measurements.md).
pub const SPACE_BLUR: f64 = 0.25;

/// The weight of the point in the darker regime's split kernel
/// ([`Split::Regimes`]): the share of a vertex's next flights too short to
/// leave its texel. Measured on the canonical and held-out scenes (a sweep
/// over 0, 0.1, 0.2 and 0.3, docs/measurements.md).
pub const SPLIT_POINT_WEIGHT: f64 = 0.2;

/// The mean flight length ℓ (MFP at the local density) of the bright
/// regime's split kernel ([`Split::Regimes`], [`FLIGHT_KERNEL`]). Measured
/// like [`SPLIT_POINT_WEIGHT`] (a sweep over 0.3, 0.4, 0.5 and 1 MFP).
pub const BRIGHT_FLIGHT: f64 = 0.5;

/// The surface displacement of one flight, as a Gaussian mixture in units
/// of its mean length ℓ: (σ/ℓ, weight), σ = 0 a point. A flight of length
/// L ∼ Exp(1/ℓ) in a uniformly random 3D direction moves a vertex by a
/// lateral offset whose 2D characteristic function is that of the 3D
/// flight at k_z = 0, arctan(kℓ)/(kℓ) (the Fourier transform of the point
/// kernel e^{−r/ℓ}/(4πℓr²); Case & Zweifel, *Linear Transport Theory*,
/// 1967): a cusp at 0 and a 1/k tail, where a Gaussian falls off as
/// e^{−k²σ²/2}. The
/// weights are the non-negative least-squares fit on kℓ ∈ [0, 60] (within
/// 0.004 of arctan(kℓ)/(kℓ) there, tested), normalised to unit mass.
pub const FLIGHT_KERNEL: [(f64, f64); 8] = [
    (0.0, 0.028_561),
    (0.05, 0.064_902),
    (0.1, 0.065_956),
    (0.2, 0.154_546),
    (0.4, 0.233_682),
    (0.8, 0.299_588),
    (1.6, 0.147_980),
    (3.2, 0.004_783),
];

/// The kernel S that splits the albedo into its local mean ᾱ = S ∗ α and
/// the fine residual α − ᾱ ([`AlbedoSpace`]): what a path's next vertex
/// sees of the albedo around the last one. Both kernels are Gaussian
/// mixtures (a point included) whose lengths scale as 1/ρ.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Split {
    /// One Gaussian of σ = b ([`Variant::space_blur`]) everywhere.
    Gaussian,
    /// Two regimes, by the endpoints' mean albedo α₀ over
    /// [`INTERIOR_RAMP`] ([`bright_weight`]), the α_t of each blended by
    /// that weight. Below: a point of weight [`SPLIT_POINT_WEIGHT`] (the
    /// short flights, which see their own texel) and the Gaussian of
    /// σ = b, so that variation finer than b keeps part of its contrast in
    /// the coarse part. Above, where paths are long: the one-flight kernel
    /// [`FLIGHT_KERNEL`] of mean length [`BRIGHT_FLIGHT`]. The default:
    /// measured better than `gaussian` on 15 of the 19 scenes and passes,
    /// worse on 3 (docs/measurements.md).
    #[default]
    Regimes,
}

impl Split {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Split::Gaussian => "gaussian",
            Split::Regimes => "regimes",
        }
    }

    /// The split kernel of the darker regime (`bright` false) or of the
    /// bright one, as (σ, weight) at unit density, σ = 0 a point; `b` is
    /// [`Variant::space_blur`].
    pub fn components(self, b: f64, bright: bool) -> Vec<(f64, f64)> {
        match (self, bright) {
            (Split::Gaussian, _) => vec![(b, 1.0)],
            (Split::Regimes, false) => {
                vec![(0.0, SPLIT_POINT_WEIGHT), (b, 1.0 - SPLIT_POINT_WEIGHT)]
            }
            (Split::Regimes, true) => {
                let total: f64 = FLIGHT_KERNEL.iter().map(|c| c.1).sum();
                FLIGHT_KERNEL
                    .iter()
                    .map(|&(s, w)| (s * BRIGHT_FLIGHT, w / total))
                    .collect()
            }
        }
    }
}

/// The space in which the kernel methods average the albedo for α_t.
///
/// A path's throughput is the product of its vertices' albedos. Where its
/// vertices fall independently under the kernel K, the expected product is
/// a power of the linear mean ∫Kρα/∫Kρ; where a path stays on one side of
/// a coarse step, the mean is a mixture over sides and the bright side
/// weighs more. So the albedo is split at a scale b (MFP at the local
/// density, [`Variant::space_blur`]) into ᾱ = S ∗ α, its density-weighted
/// local mean under the split kernel S ([`Split`]; in the `gaussian` split
/// G_b, a Gaussian of σ = b), and the fine residual α − ᾱ. The fine part is
/// averaged linearly, the coarse one in the space φ:
///
///   α_t = φ⁻¹(∫Kρ φ(ᾱ) / ∫Kρ) + ∫Kρ (α − ᾱ) / ∫Kρ.
///
/// Under G_b, on a texture much finer than b this is the linear mean; with
/// b = 0 it is the mean in φ. The vertex kernels (first and last) are
/// always averaged linearly: one vertex's expected albedo is its linear
/// mean. Arguments of the logarithms are floored at [`SPACE_FLOOR`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum AlbedoSpace {
    /// φ(α) = α: the kernel-weighted arithmetic mean (b plays no part).
    Linear,
    /// φ(α) = ln α: the geometric mean (the logarithm of a path's
    /// throughput is linear in the ln α it crosses).
    Log,
    /// φ(α) = ln(1 − α): the geometric mean of the absorption probability
    /// per scattering, which weights bright texels more than √(1 − α) does.
    Absorption,
    /// φ(α) = √(1 − α): the diffusion coordinate (the effective transport
    /// coefficient σ_tr = √(3σ_aσ_t') is ∝ √(1 − α) at fixed σ_t').
    /// The default: measured best on the canonical and held-out scenes.
    #[default]
    Transport,
}

/// The scale (MFP at the local density) over which the estimator's
/// importance sampling averages the albedo: a path's first flights reach
/// about one mean free path, so the profile that sets where x_i falls is
/// that of the albedo around x_e, not of the texel under it.
pub const SAMPLING_BLUR: f64 = 1.0;

/// Density maps with at most this many distinct values get exact local
/// means ([`pyramid::blur`] per value); others read the pyramid.
const EXACT_DENSITY_LEVELS: usize = 16;

/// The least argument of a logarithm in [`AlbedoSpace`] (α for `log`, 1 − α
/// for `absorption`).
pub const SPACE_FLOOR: f64 = 1e-6;

/// The scale L (MFP at the local density) of the coarse albedo
/// ᾱ_L = G_L ∗ α whose variance under the kernel corrects the two-scale
/// mean ([`COARSE_VARIANCE`]).
pub const COARSE_SCALE: f64 = 1.0;

/// The measured weight c of the coarse variance
/// ([`Variant::coarse_variance`], `--coarse-variance`; off by default).
///
/// The two-scale mean averages ᾱ in the space φ as if a path's vertices
/// fell independently under the kernel. Where the albedo varies on a scale
/// of a mean free path or more, successive vertices see the same side of
/// a step: the throughput is a mixture over the sides a path keeps to, and
/// the bright side weighs more than its share (the second cumulant of
/// ln ∏α grows with the variance of the albedo along the path). The mean
/// y = ⟨φ(ᾱ)⟩ is therefore replaced by
///
///   y − c·V/y,   V = Σ_k w_k Var_k φ(ᾱ_L) / Σ_k w_k,
///
/// V the variance of φ(G_L ∗ α), L = [`COARSE_SCALE`], within each
/// component k of the kernel (density-weighted where the density varies),
/// less its part along the pair's axis, averaged over the components. To
/// second order, y − c·V/y is the power mean (⟨y^p⟩)^{1/p} with
/// p = 1 − 2c: c = 1/4 averages the coarse part in (1 − α)^{1/4} instead
/// of √(1 − α). Only the variance within a component counts: the spread
/// between components follows the progress from x_i to x_e that every
/// path makes, and counting it too brightens the far side of a step (+8 %
/// at 4 MFP, docs/measurements.md). Within a component, variation along
/// the axis is crossed in series, which the mean in φ already describes;
/// what a path can choose is the side, across the axis. So the axial part,
/// ((ỹ(μ + σu) − ỹ(μ − σu))/2)² with ỹ the component's mean of φ(ᾱ_L)
/// moved by ±σ along the axis u, is taken out: on the albedo edge it takes
/// `learned` from 1.72 to 1.40 % and holds the bright side within 2 % of
/// the reference out to 4 MFP, where the isotropic variance overshot by
/// up to 5 % (docs/measurements.md). Variation finer than L has hardly
/// any variance in ᾱ_L, so fine textures keep the two-scale mean. c = 1/4
/// was measured on an albedo edge and on stripes of width 0.5 and 4 MFP
/// (docs/measurements.md). It is off by default: it costs about 50 %
/// more time per evaluation (two more pyramids per kernel component and
/// two axial reads) and two more pyramids at set-up, and it moves no
/// canonical scene but `features` at ρ ≥ 2, which it makes slightly
/// worse. Read in the transport space only.
pub const COARSE_VARIANCE: f64 = 0.25;

/// The least y by which [`COARSE_VARIANCE`]'s term divides.
const COARSE_Y_FLOOR: f64 = 1e-3;

impl AlbedoSpace {
    /// Index of the space among the material's pyramid slots.
    fn index(self) -> usize {
        self as usize
    }

    /// φ(α).
    pub fn forward(self, alpha: f64) -> f64 {
        match self {
            AlbedoSpace::Linear => alpha,
            AlbedoSpace::Log => alpha.max(SPACE_FLOOR).ln(),
            AlbedoSpace::Absorption => (1.0 - alpha).max(SPACE_FLOOR).ln(),
            AlbedoSpace::Transport => (1.0 - alpha).max(0.0).sqrt(),
        }
    }

    /// φ⁻¹(y).
    #[inline]
    pub fn inverse(self, y: f64) -> f64 {
        match self {
            AlbedoSpace::Linear => y,
            AlbedoSpace::Log => y.exp(),
            AlbedoSpace::Absorption => 1.0 - y.exp(),
            AlbedoSpace::Transport => 1.0 - y * y,
        }
    }

    /// dφ/dα at α (0 where the floor of a logarithm, or 1 − α ≤ 0 in
    /// `transport`, holds φ constant).
    pub fn forward_derivative(self, alpha: f64) -> f64 {
        match self {
            AlbedoSpace::Linear => 1.0,
            AlbedoSpace::Log if alpha > SPACE_FLOOR => 1.0 / alpha,
            AlbedoSpace::Absorption if 1.0 - alpha > SPACE_FLOOR => -1.0 / (1.0 - alpha),
            AlbedoSpace::Transport if alpha < 1.0 => -0.5 / (1.0 - alpha).sqrt(),
            _ => 0.0,
        }
    }

    /// dφ⁻¹/dy at y.
    pub fn inverse_derivative(self, y: f64) -> f64 {
        match self {
            AlbedoSpace::Linear => 1.0,
            AlbedoSpace::Log => y.exp(),
            AlbedoSpace::Absorption => -y.exp(),
            AlbedoSpace::Transport => -2.0 * y,
        }
    }

    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            AlbedoSpace::Linear => "linear",
            AlbedoSpace::Log => "log",
            AlbedoSpace::Absorption => "absorption",
            AlbedoSpace::Transport => "transport",
        }
    }
}

impl Default for Variant {
    fn default() -> Self {
        Variant {
            plain: false,
            vertex_kernels: true,
            two_pass: false,
            interior: InteriorKernel::Auto,
            space: AlbedoSpace::Transport,
            space_blur: SPACE_BLUR,
            split: Split::Regimes,
            coarse_variance: 0.0,
            density_law: DensityLaw::Endpoints,
            density_kernel: DensityKernel::Warp,
            step_ends: StepEnds::Correlated,
            last_kernel: LastKernel::Exit,
        }
    }
}

impl Variant {
    /// A short tag: "" for the default, else e.g. "+plain+2pass".
    pub fn tag(&self) -> String {
        let mut s = String::new();
        if self.plain {
            s += "+plain";
        }
        if !self.vertex_kernels {
            s += "+point-albedos";
        }
        if self.two_pass {
            s += "+2pass";
        }
        match self.interior {
            InteriorKernel::Auto => {}
            InteriorKernel::Always => s += "+interior",
            InteriorKernel::Never => s += "+no-interior",
        }
        let d = Variant::default();
        if self.space != d.space {
            s += "+";
            s += self.space.name();
            s += "-albedo";
        }
        if self.space_blur != d.space_blur && self.space != AlbedoSpace::Linear {
            s += &format!("+blur{}", self.space_blur);
        }
        if self.split != d.split && self.space != AlbedoSpace::Linear {
            s += "+";
            s += self.split.name();
            s += "-split";
        }
        if self.coarse_variance != d.coarse_variance && self.space == AlbedoSpace::Transport {
            s += &format!("+coarse{}", self.coarse_variance);
        }
        if self.density_law != d.density_law {
            s += "+";
            s += self.density_law.name();
            s += "-density";
        }
        if self.density_kernel != d.density_kernel {
            s += "+";
            s += self.density_kernel.name();
            s += "-kernel";
        }
        if self.step_ends != d.step_ends {
            s += "+";
            s += self.step_ends.name();
            s += "-step-ends";
        }
        if self.last_kernel != d.last_kernel {
            s += "+";
            s += self.last_kernel.name();
            s += "-last-kernel";
        }
        s
    }
}

/// Nodes of [`BasisTable`] in the albedo coordinate x = √(1 − α).
pub const TABLE_NODES: usize = 8192;

/// The basis model tabulated for fast evaluation: ln(A_k/(2πα²)) and B_k at
/// `TABLE_NODES` (8192) equally spaced values of x = √(1 − α), linearly
/// interpolated (max relative error of Rₘ against [`BasisModel::multi`]
/// for r ≤ 10 MFP and any α: < 1e-4, tested), plus p₁ at α = 1.
#[derive(Clone, Debug)]
pub struct BasisTable {
    k: usize,
    /// Per node: K values of ln(A_k/(2π α²)) then K values of B_k.
    nodes: Vec<f64>,
    single: ExpMixture,
    /// ln A of the single-scattering components.
    single_ln_a: Vec<f64>,
    /// The model's η.
    pub eta: f64,
    /// The observable the basis is a profile of.
    pub observable: Observable,
}

impl BasisTable {
    pub fn new(model: &BasisModel) -> Self {
        let k = model.components();
        let mut nodes = Vec::with_capacity(TABLE_NODES * 2 * k);
        for n in 0..TABLE_NODES {
            let x = n as f64 / (TABLE_NODES - 1) as f64;
            // ln(A/(2πα²)) straight from the model's polynomials: exact at
            // α = 0 too (x = 1).
            let (ln_a, b) = model.multi_over_alpha2(1.0 - x * x);
            nodes.extend(ln_a.iter().map(|l| l - (2.0 * PI).ln()));
            nodes.extend(b);
        }
        BasisTable {
            k,
            nodes,
            single_ln_a: model.single.a.iter().map(|a| a.ln()).collect(),
            single: model.single.clone(),
            eta: model.eta,
            observable: model.observable,
        }
    }

    /// The interpolated (ln(A_j/(2πα²)), B_j) of multiple-scattering
    /// component j < K at α (linear in x = √(1 − α) between table nodes).
    #[inline]
    fn interpolated(&self, alpha: f64) -> impl Fn(usize) -> (f64, f64) + '_ {
        let u = albedo_coordinate(alpha) * (TABLE_NODES - 1) as f64;
        let i = (u as usize).min(TABLE_NODES - 2);
        let (f, k) = (u - i as f64, self.k);
        let n0 = &self.nodes[i * 2 * k..(i + 1) * 2 * k];
        let n1 = &self.nodes[(i + 1) * 2 * k..(i + 2) * 2 * k];
        move |j| {
            (
                n0[j] + f * (n1[j] - n0[j]),
                n0[k + j] + f * (n1[k + j] - n0[k + j]),
            )
        }
    }

    /// Rₘ(r; α)/α² at unit density (1/MFP²): bounded for every α ∈ [0, 1].
    #[inline]
    pub fn multi_over_alpha2(&self, r: f64, alpha: f64) -> f64 {
        let at = self.interpolated(alpha);
        (0..self.k)
            .map(|j| {
                let (ln_a, b) = at(j);
                (ln_a - b * r).exp()
            })
            .sum()
    }

    /// (Rₘ(r; α)/α², its derivative in α) at unit density (1/MFP²): the
    /// table's interpolant is linear in x = √(1 − α) between nodes, so the
    /// derivative is exact for it (dx/dα = −1/(2x); x floored at 1e-6).
    pub fn multi_over_alpha2_grad(&self, r: f64, alpha: f64) -> (f64, f64) {
        let x = albedo_coordinate(alpha);
        let u = x * (TABLE_NODES - 1) as f64;
        let i = (u as usize).min(TABLE_NODES - 2);
        let (f, k) = (u - i as f64, self.k);
        let n0 = &self.nodes[i * 2 * k..(i + 1) * 2 * k];
        let n1 = &self.nodes[(i + 1) * 2 * k..(i + 2) * 2 * k];
        let du_dalpha = -0.5 * (TABLE_NODES - 1) as f64 / x.max(1e-6);
        // Exponents ln A − B r and their u-derivatives, four per SIMD
        // exponential ([`exp4`]); padding lanes at −∞ (e^−∞ = 0).
        let (mut v, mut dv) = (0.0, 0.0);
        for lane in (0..k).step_by(4) {
            let mut ex = [f64::NEG_INFINITY; 4];
            let mut de = [0.0; 4];
            for (o, j) in (lane..(lane + 4).min(k)).enumerate() {
                let (dl, db) = (n1[j] - n0[j], n1[k + j] - n0[k + j]);
                ex[o] = (n0[j] + f * dl) - (n0[k + j] + f * db) * r;
                de[o] = dl - r * db;
            }
            let e = exp4(wide::f64x4::from(ex));
            v += e.reduce_add();
            dv += (e * wide::f64x4::from(de)).reduce_add();
        }
        (v, dv * du_dalpha)
    }

    /// n̄ − 2 at unit density: the mean number of a multiply scattered
    /// path's interior vertices (all but its first and last) at distance r
    /// (MFP) and albedo α, from Rₘ(r; α) = Σₙ pₙ(r)·αⁿ:
    /// n̄ = ∂ln Rₘ/∂ln α, so n̄ − 2 = α·∂(Rₘ/α²)/∂α / (Rₘ/α²). 0 where the
    /// table's Rₘ underflows.
    pub fn interior_vertices(&self, r: f64, alpha: f64) -> f64 {
        let (v, dv) = self.multi_over_alpha2_grad(r, alpha);
        if v > 0.0 && (alpha * dv / v).is_finite() {
            (alpha * dv / v).max(0.0)
        } else {
            0.0
        }
    }

    /// (R₁(r; 1), Rₘ(r; α)/α²) at unit density (1/MFP²), r ≥ [`R_MIN`]:
    /// both mixtures' exponentials in f64x4 lanes ([`exp4`]) when the model
    /// has ≤ 4 single and ≤ 8 multiple components (the shipped one has 4
    /// and 6), else [`Self::single_exitance`] and [`Self::multi_over_alpha2`].
    #[inline]
    pub fn parts(&self, r: f64, alpha: f64) -> (f64, f64) {
        let r = r.max(R_MIN);
        let (k, ks) = (self.k, self.single.a.len());
        if ks > 4 || k > 8 {
            return (self.single_exitance(r), self.multi_over_alpha2(r, alpha));
        }
        let at = self.interpolated(alpha);
        // Exponents ln A − B r; padding lanes at −∞ (e^−∞ = 0).
        let mut e = [f64::NEG_INFINITY; 12];
        for (e, (ln_a, b)) in e
            .iter_mut()
            .zip(self.single_ln_a.iter().zip(&self.single.b))
        {
            *e = ln_a - b * r;
        }
        for j in 0..k {
            let (ln_a, b) = at(j);
            e[4 + j] = ln_a - b * r;
        }
        let v = |o: usize| exp4(wide::f64x4::from([e[o], e[o + 1], e[o + 2], e[o + 3]]));
        let single = v(0).reduce_add() / (2.0 * PI * r);
        let multi = (v(4) + v(8)).reduce_add();
        (single, multi)
    }

    /// R₁(r; 1) = p₁(r)/(2πr) at unit density (1/MFP²), r ≥ [`R_MIN`].
    #[inline]
    pub fn single_exitance(&self, r: f64) -> f64 {
        let r = r.max(R_MIN);
        self.single.density(r) / (2.0 * PI * r)
    }

    /// The homogeneous exitance R(r; α, ρ) = ρ²[α R₁(ρr) + α² Rₘ(ρr; α)/α²].
    #[inline]
    pub fn exitance(&self, r: f64, alpha: f64, rho: f64) -> f64 {
        let (single, multi) = self.parts(r.max(R_MIN) * rho, alpha);
        rho * rho * alpha * (single + alpha * multi)
    }

    /// The radial density of the homogeneous profile at (α, ρ) as mixtures
    /// (single: n = 0, multiple: n = 1) at unit density, for importance
    /// sampling ([`super::estimator`]); lengths are divided by ρ by the caller.
    pub fn mixtures(&self, alpha: f64) -> [ExpMixture; 2] {
        let at = self.interpolated(alpha);
        let (ln_a, b): (Vec<f64>, Vec<f64>) = (0..self.k).map(at).unzip();
        [
            self.single.scaled(alpha),
            ExpMixture {
                a: ln_a
                    .iter()
                    .map(|l| l.exp() * 2.0 * PI * alpha * alpha)
                    .collect(),
                b,
                power: 1,
            },
        ]
    }
}

/// The density of a scene: constant or a map (with its pyramid when a
/// kernel method needs it).
#[derive(Clone, Debug)]
pub enum Density {
    Constant(f64),
    Map(TexelMap),
}

impl Density {
    #[inline]
    pub fn at(&self, x: f64, y: f64) -> f64 {
        match self {
            Density::Constant(r) => *r,
            Density::Map(m) => m.at(x, y),
        }
    }
}

/// Where the kernel methods read their aggregates.
#[derive(Debug)]
struct Pyramids {
    /// Pyramids of α: the vertex kernels' aggregates, and α_t's in the
    /// linear space.
    linear: Aggregand,
    /// α_t's aggregands in a two-scale [`AlbedoSpace`] (the darker
    /// regime's under [`Split::Regimes`]).
    mapped: Option<Mapped>,
    /// The bright regime's (two-scale spaces under [`Split::Regimes`]).
    bright: Option<Mapped>,
    /// y = φ(ᾱ_L) and y² ([`COARSE_VARIANCE`]; the transport space with a
    /// coarse variance weight above 0).
    coarse: Option<[Aggregand; 2]>,
    /// G ∗ ρ (density maps only).
    rho: Option<GaussianPyramid>,
    /// The b, the split and the coarse variance weight of `mapped`,
    /// `bright` and `coarse`.
    blur: f64,
    split: Split,
    coarse_variance: f64,
}

/// The aggregands of a two-scale [`AlbedoSpace`].
#[derive(Debug)]
struct Mapped {
    /// φ(ᾱ).
    phi: Aggregand,
    /// α − ᾱ.
    residual: Aggregand,
}

/// The pyramids of one aggregated quantity q (α or φ(ᾱ)).
#[derive(Debug)]
struct Aggregand {
    /// G ∗ q per channel (constant density, or the `plain` variant).
    alpha: Vec<GaussianPyramid>,
    /// G ∗ ρq per channel (density maps only).
    rho_alpha: Vec<GaussianPyramid>,
}

/// `model`'s kernel at (d, α, ρ) into `out`, placed by `warp` where the
/// density varies ([`DensityKernel::Warp`]).
#[inline]
fn placed_into(
    model: &MetaModel,
    d: f64,
    alpha: f64,
    rho: f64,
    warp: Option<&OpticalAxis>,
    out: &mut Gmm,
) {
    model.eval_into(d, alpha, rho, out);
    if let Some(w) = warp {
        w.place(out);
    }
}

/// Per-thread scratch space of [`SvBssrdf::eval`] (no allocation per call).
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    kernel: Gmm,
    first: Gmm,
    last: Gmm,
    interior: Gmm,
}

/// The material of one render pass: albedo channels and density on one
/// common texel grid, with the aggregation structures the methods read
/// (Gaussian pyramids, row sums). Each structure is built the first time a
/// method needs it and then shared by every method and every render on
/// this material.
#[derive(Debug)]
pub struct Material {
    albedo: Vec<TexelMap>,
    density: Density,
    /// Pyramids of the density-scaled (`[2s]`) and the plain (`[2s + 1]`)
    /// variant, of φ(α) in albedo space s ([`AlbedoSpace`]).
    pyramids: [OnceLock<Arc<Pyramids>>; 8],
    rows: OnceLock<Arc<Rows>>,
    /// The channel-mean albedo under a Gaussian of σ = [`SAMPLING_BLUR`]/ρ
    /// ([`Material::sampling_albedo`]).
    sampling: OnceLock<TexelMap>,
}

impl Material {
    /// The material of `albedo` (one map per channel) and `density`; every
    /// map is resampled onto one common grid (exact for nearest-neighbour
    /// maps, see `common_grid`), as products ρα need.
    pub fn new(albedo: Vec<TexelMap>, density: Density) -> Result<Self> {
        let mut all: Vec<&TexelMap> = albedo.iter().collect();
        if let Density::Map(rho) = &density {
            all.push(rho);
        }
        let mut maps = common_grid(&all)?;
        let density = match density {
            Density::Map(_) => Density::Map(maps.pop().expect("pushed")),
            c => c,
        };
        Ok(Material {
            albedo: maps,
            density,
            pyramids: Default::default(),
            rows: OnceLock::new(),
            sampling: OnceLock::new(),
        })
    }

    /// The albedo maps (one per channel, on the common grid).
    pub fn albedo(&self) -> &[TexelMap] {
        &self.albedo
    }

    /// The density.
    pub fn density(&self) -> &Density {
        &self.density
    }

    /// The pyramids of the kernel methods under `variant` (built once).
    fn pyramids(&self, variant: &Variant) -> Result<Arc<Pyramids>> {
        let varying = matches!(self.density, Density::Map(_));
        // The plain variant's pyramids differ only with a density map.
        let slot =
            &self.pyramids[usize::from(varying && variant.plain) + 2 * variant.space.index()];
        if let Some(p) = slot.get().filter(|p| {
            p.blur == variant.space_blur
                && p.split == variant.split
                && p.coarse_variance == variant.coarse_variance
        }) {
            return Ok(p.clone());
        }
        // One set of pyramids of `maps` (of α, or of φ(ᾱ)).
        let aggregand = |maps: &[TexelMap]| -> Result<Aggregand> {
            let alpha = if !varying || variant.plain {
                maps.iter()
                    .map(GaussianPyramid::new)
                    .collect::<Result<_>>()?
            } else {
                Vec::new()
            };
            let rho_alpha = match &self.density {
                Density::Map(_) => density_weighted(maps, &self.density)
                    .iter()
                    .map(GaussianPyramid::new)
                    .collect::<Result<_>>()?,
                Density::Constant(_) => Vec::new(),
            };
            Ok(Aggregand { alpha, rho_alpha })
        };
        let linear = aggregand(&self.albedo)?;
        let (b, two_scale) = (variant.space_blur, variant.space != AlbedoSpace::Linear);
        if two_scale && !(b.is_finite() && b >= 0.0) {
            return Err(Error::param("space_blur", b, "finite and >= 0 (MFP)"));
        }
        let c = variant.coarse_variance;
        if two_scale && !(c.is_finite() && (0.0..=0.5).contains(&c)) {
            return Err(Error::param("coarse_variance", c, "in [0, 0.5]"));
        }
        // The two-scale aggregands under one split kernel.
        let mapped = |bright: bool| -> Result<Mapped> {
            let means = self.local_means(&variant.split.components(b, bright))?;
            let map = |f: &dyn Fn(f64, f64) -> f64| {
                means
                    .iter()
                    .zip(&self.albedo)
                    .map(|(m, a)| {
                        let mut out = m.clone();
                        for (v, &x) in out.values.iter_mut().zip(&a.values) {
                            *v = f(*v, x);
                        }
                        out
                    })
                    .collect::<Vec<_>>()
            };
            let phi = map(&|mean, _| variant.space.forward(mean));
            let residual = map(&|mean, a| a - mean);
            Ok(Mapped {
                phi: aggregand(&phi)?,
                residual: aggregand(&residual)?,
            })
        };
        // The bright regime is read only where α₀ = (α_i + α_e)/2 passes
        // the ramp's start, so never on a map whose albedo does not.
        let [ramp, _] = INTERIOR_RAMP;
        let reaches = self
            .albedo
            .iter()
            .any(|a| a.values.iter().any(|&v| v > ramp));
        // The power-mean reading of y − c·V/y ([`COARSE_VARIANCE`]) needs
        // y > 0 falling with α: the transport space's √(1 − α).
        let coarse = || -> Result<Option<[Aggregand; 2]>> {
            if variant.space != AlbedoSpace::Transport || c == 0.0 {
                return Ok(None);
            }
            // y = φ(ᾱ_L) and y².
            let mut y = self.local_means(&[(COARSE_SCALE, 1.0)])?;
            y.iter_mut().for_each(|m| {
                m.values
                    .iter_mut()
                    .for_each(|v| *v = variant.space.forward(*v))
            });
            let y2: Vec<TexelMap> = y
                .iter()
                .map(|m| {
                    let mut m = m.clone();
                    m.values.iter_mut().for_each(|v| *v *= *v);
                    m
                })
                .collect();
            Ok(Some([aggregand(&y)?, aggregand(&y2)?]))
        };
        let ((bright, mapped), coarse) = rayon::join(
            || {
                rayon::join(
                    || {
                        (two_scale && variant.split == Split::Regimes && reaches)
                            .then(|| mapped(true))
                            .transpose()
                    },
                    || two_scale.then(|| mapped(false)).transpose(),
                )
            },
            coarse,
        );
        let (bright, mapped, coarse) = (bright?, mapped?, coarse?);
        let rho = match &self.density {
            Density::Map(rho) => Some(GaussianPyramid::new(rho)?),
            Density::Constant(_) => None,
        };
        let built = Arc::new(Pyramids {
            linear,
            mapped,
            bright,
            coarse,
            rho,
            blur: variant.space_blur,
            split: variant.split,
            coarse_variance: c,
        });
        // Cached unless the slot holds another blur's (built for a variant
        // of its own).
        Ok(match slot.get() {
            Some(_) => built,
            None => slot.get_or_init(|| built).clone(),
        })
    }

    /// Per channel, each texel's ᾱ = S ∗ α: the (density-weighted) mean of
    /// α under the split kernel S (`split`, [`Split::components`]: (σ,
    /// weight) at unit density, σ = 0 a point) centred on the texel, its
    /// lengths divided by the texel's own density for a density map.
    fn local_means(&self, split: &[(f64, f64)]) -> Result<Vec<TexelMap>> {
        self.local_means_of(&self.albedo, split)
    }

    /// [`Self::local_means`] of `maps` (one per channel, on the common
    /// grid) instead of α.
    fn local_means_of(&self, maps: &[TexelMap], split: &[(f64, f64)]) -> Result<Vec<TexelMap>> {
        let Density::Map(rho) = &self.density else {
            let Density::Constant(r) = self.density else {
                unreachable!()
            };
            return Ok(maps
                .iter()
                .map(|a| pyramid::blur_mixture(a, split, 1.0 / r))
                .collect());
        };
        let weighted = density_weighted(maps, &self.density);
        // Few distinct densities (steps, stripes, a constant map): exact,
        // two separable blurs per density and component. Otherwise one
        // pyramid query per texel and component (to the pyramid's
        // accuracy).
        let mut levels: Vec<f64> = rho.values.clone();
        levels.sort_by(f64::total_cmp);
        levels.dedup();
        if levels.len() <= EXACT_DENSITY_LEVELS {
            let rho_blurred: Vec<TexelMap> = levels
                .iter()
                .map(|&r| pyramid::blur_mixture(rho, split, 1.0 / r))
                .collect();
            let level = |r: f64| levels.partition_point(|&l| l < r);
            return Ok(weighted
                .iter()
                .zip(maps)
                .map(|(w, a)| {
                    let w_blurred: Vec<TexelMap> = levels
                        .iter()
                        .map(|&r| pyramid::blur_mixture(w, split, 1.0 / r))
                        .collect();
                    let mut m = a.clone();
                    for (k, v) in m.values.iter_mut().enumerate() {
                        let l = level(rho.values[k]);
                        *v = w_blurred[l].values[k] / rho_blurred[l].values[k];
                    }
                    m
                })
                .collect());
        }
        let rho_pyramid = GaussianPyramid::new(rho)?;
        let (nx, ny, tau) = (rho.nx, rho.ny, rho.texel);
        weighted
            .iter()
            .zip(maps)
            .map(|(w, a)| {
                let wp = GaussianPyramid::new(w)?;
                let mut m = a.clone();
                for i in 0..ny {
                    for j in 0..nx {
                        let mu = [
                            (j as f64 + 0.5) * tau - 0.5 * nx as f64 * tau,
                            0.5 * ny as f64 * tau - (i as f64 + 0.5) * tau,
                        ];
                        let k = i * nx + j;
                        let (mut r, mut ra) = (0.0, 0.0);
                        for &(sigma, weight) in split {
                            let [r1, ra1] = if sigma > 0.0 {
                                GaussianPyramid::integrate_n(
                                    [&rho_pyramid, &wp],
                                    mu,
                                    sigma / rho.values[k],
                                )
                                .0
                            } else {
                                [rho.values[k], w.values[k]]
                            };
                            r += weight * r1;
                            ra += weight * ra1;
                        }
                        m.values[k] = ra / r;
                    }
                }
                Ok(m)
            })
            .collect()
    }

    /// The albedo the estimator's importance sampling reads at `(x, y)`:
    /// the channel mean of the density-weighted local mean
    /// (G ∗ ρα)/(G ∗ ρ) under a Gaussian of σ = [`SAMPLING_BLUR`]/ρ̄, ρ̄ the
    /// map's mean density (one σ for the whole map: this only steers where
    /// x_i is drawn, so it need not follow the density texel by texel).
    /// Built once, by separable blurs ([`pyramid::blur`]).
    pub fn sampling_albedo(&self, x: f64, y: f64) -> f64 {
        self.sampling
            .get_or_init(|| {
                let (sigma, rho) = match &self.density {
                    Density::Constant(r) => (SAMPLING_BLUR / r, None),
                    Density::Map(m) => {
                        let mean = m.values.iter().sum::<f64>() / m.values.len() as f64;
                        let sigma = SAMPLING_BLUR / mean;
                        (sigma, Some(pyramid::blur(m, sigma)))
                    }
                };
                let weighted = density_weighted(&self.albedo, &self.density);
                let mut out = pyramid::blur(&weighted[0], sigma);
                for w in &weighted[1..] {
                    let b = pyramid::blur(w, sigma);
                    out.values
                        .iter_mut()
                        .zip(&b.values)
                        .for_each(|(v, o)| *v += o);
                }
                let n = weighted.len() as f64;
                for (k, v) in out.values.iter_mut().enumerate() {
                    *v /= n * rho.as_ref().map_or(1.0, |r| r.values[k]);
                }
                out
            })
            .at(x, y)
    }

    /// The row sums of the ellipse method (built once).
    fn rows(&self) -> Arc<Rows> {
        self.rows
            .get_or_init(|| {
                Arc::new(Rows {
                    rho_alpha: density_weighted(&self.albedo, &self.density)
                        .into_iter()
                        .map(RowPrefix::new)
                        .collect(),
                    rho: match &self.density {
                        Density::Map(rho) => Some(RowPrefix::new(rho.clone())),
                        Density::Constant(_) => None,
                    },
                })
            })
            .clone()
    }
}

/// What a method reads besides point values.
#[derive(Debug)]
enum Aggregates {
    /// Point values only (point, factorized, line).
    None,
    /// Gaussian pyramids (manual, learned).
    Kernel(Arc<Pyramids>),
    /// Row sums (ellipse).
    Rows(Arc<Rows>),
}

/// A material and one method, ready to evaluate S(x_i, x_e) per channel.
#[derive(Debug)]
pub struct SvBssrdf {
    pub method: Method,
    pub variant: Variant,
    basis: Arc<BasisTable>,
    meta: Option<Arc<MetaModelFile>>,
    /// A meta-model for albedos outside `meta`'s range ([`crate::jobs::extend`]).
    extension: Option<Arc<MetaModelFile>>,
    material: Arc<Material>,
    aggregates: Aggregates,
}

impl SvBssrdf {
    /// Prepares `method` on the maps `albedo` and `density` (a material of
    /// its own: [`SvBssrdf::on`] shares one between methods). `meta` is
    /// required by `learned`.
    pub fn new(
        method: Method,
        variant: Variant,
        basis: Arc<BasisTable>,
        meta: Option<Arc<MetaModelFile>>,
        albedo: Vec<TexelMap>,
        density: Density,
    ) -> Result<Self> {
        let material = Arc::new(Material::new(albedo, density)?);
        SvBssrdf::on(method, variant, basis, meta, material)
    }

    /// Prepares `method` on a shared `material`, building (once per
    /// material) only the aggregates the method and variant read. `meta` is
    /// required by `learned`.
    pub fn on(
        method: Method,
        variant: Variant,
        basis: Arc<BasisTable>,
        meta: Option<Arc<MetaModelFile>>,
        material: Arc<Material>,
    ) -> Result<Self> {
        if method == Method::Learned && meta.is_none() {
            return Err(Error::param(
                "meta_model",
                "(none)",
                "a meta-model file for method learned",
            ));
        }
        let aggregates = match method {
            m if m.uses_kernel() => Aggregates::Kernel(material.pyramids(&variant)?),
            Method::Ellipse => Aggregates::Rows(material.rows()),
            _ => Aggregates::None,
        };
        Ok(SvBssrdf {
            method,
            variant,
            basis,
            meta,
            extension: None,
            material,
            aggregates,
        })
    }

    /// Uses `ext` for kernel queries whose albedo α₀ lies outside the main
    /// meta-model's trained range (simulated and fitted for the scene's
    /// missing range by [`crate::jobs::extend::ensure`]).
    pub fn with_extension(mut self, ext: Arc<MetaModelFile>) -> Self {
        self.extension = Some(ext);
        self
    }

    /// The meta-model for kernel queries at albedo `alpha0` and optical
    /// distance `d1` (MFP at unit density): the extension outside the main
    /// model's albedo range (its outer model's, if it has one), if there is
    /// an extension; else the main model or its outer one
    /// ([`MetaModelFile::at`]).
    #[inline]
    fn meta_for(&self, alpha0: f64, d1: f64) -> Option<&MetaModelFile> {
        let main = self.meta.as_deref()?;
        let [lo, hi] = main.alpha_range();
        match &self.extension {
            Some(ext) if !(lo..=hi).contains(&alpha0) => Some(ext),
            _ => Some(main.at(d1, alpha0)),
        }
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.material.albedo.len()
    }

    /// The albedo importance sampling reads at a point
    /// ([`Material::sampling_albedo`]).
    pub fn sampling_albedo(&self, x: f64, y: f64) -> f64 {
        self.material.sampling_albedo(x, y)
    }

    /// The albedo of channel `c` at a point.
    #[inline]
    pub fn albedo_at(&self, c: usize, x: f64, y: f64) -> f64 {
        self.material.albedo[c].at(x, y)
    }

    /// The albedo map of channel `c`.
    pub fn albedo_map(&self, c: usize) -> &TexelMap {
        &self.material.albedo[c]
    }

    /// The density at a point.
    #[inline]
    pub fn density_at(&self, x: f64, y: f64) -> f64 {
        self.material.density.at(x, y)
    }

    /// The basis table.
    pub fn basis(&self) -> &BasisTable {
        &self.basis
    }

    /// S(x_i, x_e) of channel `c` (1/MFP², module docs).
    #[inline]
    pub fn eval(&self, c: usize, xi: [f64; 2], xe: [f64; 2], scratch: &mut Scratch) -> f64 {
        let (dx, dy) = (xe[0] - xi[0], xe[1] - xi[1]);
        let d = (dx * dx + dy * dy).sqrt();
        let (ai, ae) = (
            self.albedo_at(c, xi[0], xi[1]),
            self.albedo_at(c, xe[0], xe[1]),
        );
        let (ri, re) = (self.density_at(xi[0], xi[1]), self.density_at(xe[0], xe[1]));
        let b = &*self.basis;
        match self.method {
            Method::Point => b.exitance(d, ae, re),
            Method::Factorized => (b.exitance(d, ai, ri) * b.exitance(d, ae, re)).sqrt(),
            Method::Line => {
                let (a, r) = self.line_average(c, xi, xe, d);
                b.exitance(d, a, r)
            }
            Method::Ellipse => {
                let (a, r) = self.ellipse_average(c, xi, xe, d, 0.5 * (ri + re));
                b.exitance(d, a, r)
            }
            Method::Manual | Method::Learned => {
                self.eval_split(c, xi, [dx, dy], d, [ai, ae], [ri, re], scratch)
            }
        }
    }

    /// The split (local/global) form of `manual` and `learned`.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn eval_split(
        &self,
        c: usize,
        xi: [f64; 2],
        delta: [f64; 2],
        d: f64,
        [ai, ae]: [f64; 2],
        [ri, re]: [f64; 2],
        scratch: &mut Scratch,
    ) -> f64 {
        let axis = if d > 0.0 {
            [delta[0] / d, delta[1] / d]
        } else {
            [1.0, 0.0]
        };
        let frame = Frame { xi, axis };
        let warp = self.optical_axis(&frame, d, [ri, re]);
        let rho0 = match &warp {
            Some(w) => w.optical_distance() / d,
            None => 0.5 * (ri + re),
        };
        let a0 = 0.5 * (ai + ae);
        let b = &*self.basis;
        // The vertex kernels (learned only) are queried at the same (d, α₀,
        // ρ₀) as the first all-vertex kernel: all of them are evaluated
        // before any aggregation, so that their independent chains overlap.
        let vertex = match (self.variant.vertex_kernels, self.method) {
            (true, Method::Learned) => self.meta_for(a0, d * rho0),
            _ => None,
        };
        self.kernels(vertex, d, a0, rho0, warp.as_ref(), scratch);
        // A pair across a coarse albedo step ([`StepEnds`]): the ends'
        // weights of being counted once and of their two-scale means.
        let [once, correlated] = match vertex {
            Some(_) => {
                let xe = [xi[0] + delta[0], xi[1] + delta[1]];
                self.step_weights(c, [xi, xe], [ai, ae], [ri, re])
            }
            None => [0.0; 2],
        };
        let dark = self.pyramids().mapped.as_ref();
        let end_albedo = |kernel: &Gmm, linear: f64| match dark {
            Some(q) if correlated > 0.0 => {
                linear + correlated * (self.aggregate(c, &frame, kernel, Some(q)).0 - linear)
            }
            _ => linear,
        };
        // A point vertex kernel (manual's both; learned's first under normal
        // incidence, `first: None`; the last for the radiance along the
        // normal, whose last vertex lies straight below x_e) aggregates to
        // the point albedo in hand.
        let (mut li, mut le) = (ai, ae);
        if vertex.is_some_and(|meta| meta.first.is_some()) {
            li = end_albedo(
                &scratch.first,
                self.aggregate(c, &frame, &scratch.first, None).0,
            );
        }
        let interior = vertex.filter(|_| self.variant.interior != InteriorKernel::Never);
        // The bright regime's weight (its split, [`Split::Regimes`]).
        let bright = bright_weight(a0);
        let (mut alpha_t, mut rho_bar, le_read) =
            self.regime_albedo(interior, c, &frame, d, rho0, [bright, once], scratch);
        if vertex.is_some() && b.observable == Observable::Exitance {
            let linear =
                le_read.unwrap_or_else(|| self.aggregate(c, &frame, &scratch.last, None).0);
            le = end_albedo(&scratch.last, linear);
            if let (LastKernel::Exit, Some(meta), true) =
                (self.variant.last_kernel, vertex, once < 1.0)
            {
                // The last-vertex kernel again, at the albedo its vertex
                // sees ([`LastKernel::Exit`]; a pair across a step keeps
                // the kernel at α₀).
                let alpha = le + once * (a0 - le);
                placed_into(&meta.last, d, alpha, rho0, warp.as_ref(), &mut scratch.last);
                let linear = self.aggregate(c, &frame, &scratch.last, None).0;
                le = end_albedo(&scratch.last, linear);
            }
        }
        if self.variant.two_pass {
            // The warp keeps its mean density along the pair.
            let rho = if warp.is_some() { rho0 } else { rho_bar };
            self.kernels(interior, d, alpha_t, rho, warp.as_ref(), scratch);
            (alpha_t, rho_bar, _) =
                self.regime_albedo(interior, c, &frame, d, rho, [bright, once], scratch);
        }
        // The single-scattering vertex: below x_i under normal incidence;
        // for the radiance along the normal below x_e under any light.
        let a1 = match b.observable {
            Observable::Exitance => ai,
            Observable::Radiance => ae,
        };
        let profile = |rho: f64| {
            let (single, multi) = b.parts(d.max(R_MIN) * rho, alpha_t);
            rho * rho * (a1 * single + li * le * multi)
        };
        match self.variant.density_law {
            DensityLaw::Endpoints if ri == re => profile(ri),
            DensityLaw::Endpoints => (profile(ri) * profile(re)).sqrt(),
            DensityLaw::Kernel => profile(rho_bar),
        }
    }

    /// [`StepEnds::Correlated`]'s weights [w_once, w_corr] for the pair
    /// x_i → x_e of channel `c` with point albedos `[ai, ae]` and point
    /// densities `[ri, re]` (0 under [`StepEnds::Independent`]).
    #[inline]
    fn step_weights(
        &self,
        c: usize,
        [xi, xe]: [[f64; 2]; 2],
        [ai, ae]: [f64; 2],
        [ri, re]: [f64; 2],
    ) -> [f64; 2] {
        if self.variant.step_ends != StepEnds::Correlated {
            return [0.0; 2];
        }
        let contrast = (self.regional_albedo(c, xi, ri) - self.regional_albedo(c, xe, re)).abs();
        [
            smoothstep(contrast.min((ai - ae).abs()), STEP_RAMP),
            smoothstep(contrast, CORRELATED_RAMP),
        ]
    }

    /// The regional albedo ᾱ_R of channel `c` at `x`, where the density
    /// is `rho` ([`StepEnds`]): the (density-weighted) mean of α under a
    /// Gaussian of σ = [`REGION_SCALE`]/ρ, one query of the linear
    /// pyramids.
    #[inline]
    fn regional_albedo(&self, c: usize, x: [f64; 2], rho: f64) -> f64 {
        let p = self.pyramids();
        let sigma = REGION_SCALE / rho;
        match (&self.material.density, &p.rho) {
            (Density::Map(_), Some(rho)) => {
                let ([r, ra], _) =
                    GaussianPyramid::integrate_n([rho, &p.linear.rho_alpha[c]], x, sigma);
                ra / r
            }
            _ => GaussianPyramid::integrate_n([&p.linear.alpha[c]], x, sigma).0[0],
        }
    }

    /// The all-vertex kernel and, with `vertex`, its first- (when the
    /// model has one) and last-vertex (in exitance) kernels at (d, α, ρ)
    /// into `scratch`, each placed by `warp` where the density varies
    /// ([`DensityKernel::Warp`]).
    #[inline]
    fn kernels(
        &self,
        vertex: Option<&MetaModelFile>,
        d: f64,
        alpha: f64,
        rho: f64,
        warp: Option<&OpticalAxis>,
        scratch: &mut Scratch,
    ) {
        self.all_kernel(d, alpha, rho, &mut scratch.kernel);
        if let Some(w) = warp {
            w.place(&mut scratch.kernel);
        }
        let Some(meta) = vertex else { return };
        if let Some(first) = &meta.first {
            placed_into(first, d, alpha, rho, warp, &mut scratch.first);
        }
        if self.basis.observable == Observable::Exitance {
            placed_into(&meta.last, d, alpha, rho, warp, &mut scratch.last);
        }
    }

    /// The optical coordinate along the pair in `frame` for
    /// [`DensityKernel::Warp`]: `None` for the other placement, at a
    /// constant density or at d = 0.
    #[inline]
    fn optical_axis(&self, frame: &Frame, d: f64, ends: [f64; 2]) -> Option<OpticalAxis> {
        if self.variant.density_kernel != DensityKernel::Warp
            || d <= 0.0
            || matches!(self.material.density, Density::Constant(_))
        {
            return None;
        }
        let h = d / WARP_NODES as f64;
        let mut w = OpticalAxis {
            d,
            ends,
            rho: [0.0; WARP_NODES],
            tau: [0.0; WARP_NODES + 1],
        };
        for k in 0..WARP_NODES {
            let t = (k as f64 + 0.5) * h;
            let [x, y] = [
                frame.xi[0] + t * frame.axis[0],
                frame.xi[1] + t * frame.axis[1],
            ];
            w.rho[k] = self.density_at(x, y);
            w.tau[k + 1] = w.tau[k] + w.rho[k] * h;
        }
        Some(w)
    }

    /// [`Self::total_albedo`] in the darker regime's two-scale aggregands
    /// and the bright regime's ([`Split::Regimes`]), blended by `bright`,
    /// the bright regime's weight; each regime is read only where its
    /// weight is not 0. (ρ̄ and l_e do not depend on the regime.) `once` is
    /// the interior kernel's least weight ([`StepEnds`]).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn regime_albedo(
        &self,
        interior: Option<&MetaModelFile>,
        c: usize,
        frame: &Frame,
        d: f64,
        rho: f64,
        [bright, once]: [f64; 2],
        scratch: &mut Scratch,
    ) -> (f64, f64, Option<f64>) {
        let p = self.pyramids();
        let dark = p.mapped.as_ref();
        let mut under = |q| self.total_albedo(interior, c, frame, d, rho, q, once, scratch);
        match p.bright.as_ref() {
            Some(q) if bright >= 1.0 => under(Some(q)),
            Some(q) if bright > 0.0 => {
                let (lo, rho_bar, le) = under(dark);
                let (hi, _, _) = under(Some(q));
                (lo + bright * (hi - lo), rho_bar, le)
            }
            _ => under(dark),
        }
    }

    /// (α_t, ρ̄) under the all-vertex kernel in `scratch.kernel`, averaged
    /// with the two-scale aggregands `q` (the linear mean if `None`), with
    /// `interior` (the model whose end kernels are in `scratch`) blended
    /// towards α_t under the interior vertices' kernel by the variant's
    /// [`InteriorKernel::weight`] at the all-vertex α_t, or `once` where
    /// that is larger ([`StepEnds`]); and l_e where that blend read it on
    /// the way (in exitance at a constant density).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn total_albedo(
        &self,
        interior: Option<&MetaModelFile>,
        c: usize,
        frame: &Frame,
        d: f64,
        rho: f64,
        q: Option<&Mapped>,
        once: f64,
        scratch: &mut Scratch,
    ) -> (f64, f64, Option<f64>) {
        let (parts, rho_bar) = self.aggregate_parts(c, frame, &scratch.kernel, q);
        let all = self.alpha_of_parts(parts, q);
        let w = self.variant.interior.weight(all).max(once);
        let Some(meta) = interior.filter(|_| w > 0.0) else {
            return (all, rho_bar, None);
        };
        let (inner, le) = match self.interior_in_parts(meta, c, frame, d, rho, parts, q, scratch) {
            Some((inner, le)) => (inner, Some(le)),
            None => {
                // n̄ at the all-vertex α_t: the albedo that the paths see.
                self.interior_kernel(meta, d, all, rho, scratch);
                (self.aggregate_interior(c, frame, scratch, all, q), None)
            }
        };
        let alpha_t = if w >= 1.0 {
            inner
        } else {
            all + w * (inner - all)
        };
        (alpha_t, rho_bar, le)
    }

    /// The interior vertices' kernel ([`interior_into`]) into
    /// `scratch.interior`, from the all-vertex and end kernels in `scratch`
    /// (queried at (d, α, ρ)) and n̄ − 2 of the homogeneous profile there.
    #[inline]
    fn interior_kernel(
        &self,
        meta: &MetaModelFile,
        d: f64,
        alpha: f64,
        rho: f64,
        scratch: &mut Scratch,
    ) {
        let b = &*self.basis;
        let m = b.interior_vertices(d.max(R_MIN) * rho, alpha);
        let first = meta.first.as_ref().map(|_| &scratch.first);
        let last = (b.observable == Observable::Exitance).then_some(&scratch.last);
        interior_into(&scratch.kernel, first, last, d, m, &mut scratch.interior);
    }

    /// α_t under `scratch.interior`, given `all`, α_t under the all-vertex
    /// kernel. A signed mixture's density weight ∫K_int ρ can fail to be
    /// positive where the density jumps by orders of magnitude between the
    /// ends and the interior; there the all-vertex α_t stands.
    #[inline]
    fn aggregate_interior(
        &self,
        c: usize,
        frame: &Frame,
        scratch: &Scratch,
        all: f64,
        q: Option<&Mapped>,
    ) -> f64 {
        match self.aggregate(c, frame, &scratch.interior, q) {
            (alpha, weight) if alpha.is_finite() && weight > 0.0 => alpha,
            _ => all,
        }
    }

    /// (α_t under the interior kernel, l_e) in the common case, a constant
    /// density with the first vertex under x_i in exitance, from the parts
    /// of K_int's signed mixture read once each: K_all's (`parts`, from
    /// [`Self::aggregate_parts`]), K_last's (which also give l_e) and the
    /// point's, combined as ((m + 2)·ȳ_all − ȳ_last − ȳ_point)/m per
    /// aggregand (the same sums as [`Self::interior_kernel`]'s mixture, in
    /// another order). `None` otherwise (density-weighted means do not
    /// combine linearly).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn interior_in_parts(
        &self,
        meta: &MetaModelFile,
        c: usize,
        frame: &Frame,
        d: f64,
        rho0: f64,
        parts: [f64; 2],
        q: Option<&Mapped>,
        scratch: &mut Scratch,
    ) -> Option<(f64, f64)> {
        let b = &*self.basis;
        let (Aggregates::Kernel(p), Density::Constant(_)) =
            (&self.aggregates, &self.material.density)
        else {
            return None;
        };
        if meta.first.is_some() || b.observable != Observable::Exitance {
            return None;
        }
        let point = &mut scratch.interior.components;
        point.clear();
        point.push(Component::point(1.0, 0.0));
        // n̄ at the all-vertex α_t: the albedo that the paths see.
        let m = b
            .interior_vertices(d.max(R_MIN) * rho0, self.alpha_of_parts(parts, q))
            .max(INTERIOR_MIN);
        let [y_a, r_a] = parts;
        let combine = |all: f64, last: f64, point: f64| ((m + 2.0) * all - last - point) / m;
        Some(match q {
            Some(q) => {
                let ([y_l, r_l, le], _) =
                    self.means(p, [&q.phi, &q.residual, &p.linear], c, frame, &scratch.last);
                let ([y_p, r_p], _) =
                    self.means(p, [&q.phi, &q.residual], c, frame, &scratch.interior);
                let space = self.variant.space;
                let alpha_t = space.inverse(combine(y_a, y_l, y_p)) + combine(r_a, r_l, r_p);
                (alpha_t.clamp(0.0, 1.0), le.clamp(0.0, 1.0))
            }
            None => {
                let ([le], _) = self.means(p, [&p.linear], c, frame, &scratch.last);
                let ([a_p], _) = self.means(p, [&p.linear], c, frame, &scratch.interior);
                (combine(y_a, le, a_p).clamp(0.0, 1.0), le.clamp(0.0, 1.0))
            }
        })
    }

    /// The all-vertex kernel at (d, α₀, ρ₀) in physical MFP, into `out`:
    /// the meta-model's for `learned`, else the manual kernel (docs/design.md §4) at
    /// the optical distance ρ₀d with lengths divided by ρ₀ (the density law).
    #[inline]
    fn all_kernel(&self, d: f64, alpha0: f64, rho0: f64, out: &mut Gmm) {
        match (self.method, self.meta_for(alpha0, d * rho0)) {
            (Method::Learned, Some(meta)) => {
                meta.all.eval_into(d, alpha0, rho0, out);
            }
            _ => manual_into(d * rho0, 1.0 / rho0, out),
        }
    }

    /// (α_t, ρ̄) of channel `c` under `kernel` placed in `frame`: the linear
    /// mean of α, or with the two-scale aggregands `q` the two-scale mean
    /// of the variant's [`AlbedoSpace`].
    #[inline]
    fn aggregate(&self, c: usize, frame: &Frame, kernel: &Gmm, q: Option<&Mapped>) -> (f64, f64) {
        if q.is_some() {
            let (parts, rho_bar) = self.aggregate_parts(c, frame, kernel, q);
            return (self.alpha_of_parts(parts, q), rho_bar);
        }
        let p = self.pyramids();
        let ([a], rho_bar) = self.means(p, [&p.linear], c, frame, kernel);
        (a.clamp(0.0, 1.0), rho_bar)
    }

    /// The two means that make α_t under `kernel` ([`AlbedoSpace`]):
    /// ([mean of φ(ᾱ), mean of α − ᾱ], ρ̄) with the two-scale aggregands
    /// `q`, ([mean of α, 0], ρ̄) without.
    #[inline]
    fn aggregate_parts(
        &self,
        c: usize,
        frame: &Frame,
        kernel: &Gmm,
        q: Option<&Mapped>,
    ) -> ([f64; 2], f64) {
        let p = self.pyramids();
        match (q, &p.coarse) {
            (Some(m), Some(coarse)) => {
                let ([y, r], rho_bar, var) = self.coarse_means(p, m, coarse, c, frame, kernel);
                let shift = p.coarse_variance * var / y.max(COARSE_Y_FLOOR);
                ([(y - shift).max(0.0), r], rho_bar)
            }
            (Some(m), None) => self.means(p, [&m.phi, &m.residual], c, frame, kernel),
            (None, _) => {
                let ([a], rho_bar) = self.means(p, [&p.linear], c, frame, kernel);
                ([a, 0.0], rho_bar)
            }
        }
    }

    /// [`Self::means`] of the two-scale aggregands `m` under `kernel`, and
    /// V, the variance of y = φ(ᾱ_L) within each component averaged over
    /// the components ([`COARSE_VARIANCE`]; `coarse` holds y and y²). At a
    /// constant density each component is one query of four pyramids; with
    /// a density map the variance is read per component (density-weighted
    /// unless `plain`) beside [`Self::means`].
    #[inline]
    fn coarse_means(
        &self,
        p: &Pyramids,
        m: &Mapped,
        [y1, y2]: &[Aggregand; 2],
        c: usize,
        frame: &Frame,
        kernel: &Gmm,
    ) -> ([f64; 2], f64, f64) {
        // Σ w·max(Var, 0) / Σ w over the components with finite parts.
        let (mut wsum, mut var) = (0.0, 0.0);
        let mut add = |w: f64, v: f64| {
            if w.is_finite() && v.is_finite() {
                wsum += w;
                var += w * v.max(0.0);
            }
        };
        // The axial part of a component's variance of φ(ᾱ_L), unweighted.
        let plain_along = |mu: [f64; 2], sigma: f64| {
            frame.along_axis_variance(mu, sigma, |x| {
                GaussianPyramid::integrate_n([&y1.alpha[c]], x, sigma).0[0]
            })
        };
        let (parts, rho_bar) = match &self.material.density {
            Density::Map(_) => {
                let rho = p.rho.as_ref().expect("a density map has its ρ pyramid");
                for comp in &kernel.components {
                    let mu = frame.place(comp);
                    if self.variant.plain {
                        let ([a, b], _) = GaussianPyramid::integrate_n(
                            [&y1.alpha[c], &y2.alpha[c]],
                            mu,
                            comp.sigma,
                        );
                        add(comp.weight, b - a * a - plain_along(mu, comp.sigma));
                    } else {
                        let ([r, a, b], _) = GaussianPyramid::integrate_n(
                            [rho, &y1.rho_alpha[c], &y2.rho_alpha[c]],
                            mu,
                            comp.sigma,
                        );
                        let mean = a / r;
                        let along = frame.along_axis_variance(mu, comp.sigma, |x| {
                            let ([r, a], _) = GaussianPyramid::integrate_n(
                                [rho, &y1.rho_alpha[c]],
                                x,
                                comp.sigma,
                            );
                            a / r
                        });
                        add(comp.weight * r, b / r - mean * mean - along);
                    }
                }
                self.means(p, [&m.phi, &m.residual], c, frame, kernel)
            }
            Density::Constant(rho) => {
                let (mut wtot, mut sums) = (0.0, [0.0; 2]);
                for comp in &kernel.components {
                    let mu = frame.place(comp);
                    let ([y, res, a, b], _) = GaussianPyramid::integrate_n(
                        [
                            &m.phi.alpha[c],
                            &m.residual.alpha[c],
                            &y1.alpha[c],
                            &y2.alpha[c],
                        ],
                        mu,
                        comp.sigma,
                    );
                    wtot += comp.weight;
                    sums[0] += comp.weight * y;
                    sums[1] += comp.weight * res;
                    add(comp.weight, b - a * a - plain_along(mu, comp.sigma));
                }
                (sums.map(|s| s / wtot), *rho)
            }
        };
        let var = if wsum > 0.0 { var / wsum } else { 0.0 };
        (parts, rho_bar, var)
    }

    /// α_t from [`Self::aggregate_parts`]'s two means.
    #[inline]
    fn alpha_of_parts(&self, [y, r]: [f64; 2], q: Option<&Mapped>) -> f64 {
        match q {
            Some(_) => (self.variant.space.inverse(y) + r).clamp(0.0, 1.0),
            None => y.clamp(0.0, 1.0),
        }
    }

    /// The kernel methods' pyramids.
    #[inline]
    fn pyramids(&self) -> &Pyramids {
        let Aggregates::Kernel(p) = &self.aggregates else {
            unreachable!("kernel methods are built with their pyramids")
        };
        p
    }

    /// The (density-weighted unless `plain`) means of the aggregands `qs`
    /// of channel `c` under `kernel` placed in `frame`, and ρ̄ (one pyramid
    /// query per component). One or two aggregands; three at a constant
    /// density.
    #[inline]
    fn means<const N: usize>(
        &self,
        p: &Pyramids,
        qs: [&Aggregand; N],
        c: usize,
        frame: &Frame,
        kernel: &Gmm,
    ) -> ([f64; N], f64) {
        debug_assert!((1..=3).contains(&N), "one to three aggregands");
        // The density weighting within each component (the warp) or across
        // the mixture.
        let within = self.variant.density_kernel == DensityKernel::Warp;
        let mut wsum = 0.0;
        let mut den = 0.0;
        let mut num = [0.0; N];
        for comp in &kernel.components {
            let mu = frame.place(comp);
            wsum += comp.weight;
            match (&self.material.density, &p.rho) {
                (Density::Map(_), Some(rho)) => {
                    // ρ, then the N aggregands (of ρq, or of q when plain).
                    let pick = |i: usize| -> &GaussianPyramid {
                        match i {
                            0 => rho,
                            i if self.variant.plain => &qs[i - 1].alpha[c],
                            i => &qs[i - 1].rho_alpha[c],
                        }
                    };
                    debug_assert!(N <= 2, "three aggregands only at a constant density");
                    let mut v = [0.0; 3];
                    if N == 1 {
                        let ([r, o], _) =
                            GaussianPyramid::integrate_n([pick(0), pick(1)], mu, comp.sigma);
                        v[..2].copy_from_slice(&[r, o]);
                    } else {
                        (v, _) = GaussianPyramid::integrate_n(
                            [pick(0), pick(1), pick(2)],
                            mu,
                            comp.sigma,
                        );
                    }
                    den += comp.weight * v[0];
                    let w = if within && !self.variant.plain {
                        comp.weight / v[0]
                    } else {
                        comp.weight
                    };
                    for (n, o) in num.iter_mut().zip(&v[1..=N]) {
                        *n += w * o;
                    }
                }
                _ => {
                    let (v, _) =
                        GaussianPyramid::integrate_n(qs.map(|q| &q.alpha[c]), mu, comp.sigma);
                    for (n, o) in num.iter_mut().zip(v) {
                        *n += comp.weight * o;
                    }
                }
            }
        }
        match &self.material.density {
            Density::Constant(r) => (num.map(|n| n / wsum), *r),
            Density::Map(_) if self.variant.plain || within => (num.map(|n| n / wsum), den / wsum),
            Density::Map(_) => (num.map(|n| n / den), den / wsum),
        }
    }

    /// Density-weighted mean albedo and mean density along the segment.
    fn line_average(&self, c: usize, xi: [f64; 2], xe: [f64; 2], d: f64) -> (f64, f64) {
        let tau = self.material.albedo[c].texel;
        let n = ((2.0 * d / tau).ceil() as usize).max(1);
        let (mut ra, mut r) = (0.0, 0.0);
        for k in 0..n {
            let t = (k as f64 + 0.5) / n as f64;
            let (x, y) = (xi[0] + t * (xe[0] - xi[0]), xi[1] + t * (xe[1] - xi[1]));
            let rho = self.density_at(x, y);
            ra += rho * self.albedo_at(c, x, y);
            r += rho;
        }
        (ra / r, r / n as f64)
    }

    /// Density-weighted mean albedo and mean density over the ellipse with
    /// foci x_i, x_e and semi-major axis a = d/2 + 1/ρ₀: texel rows crossed
    /// by the ellipse, each chord integrated exactly in x from row prefix
    /// sums ([`RowPrefix`]) at the row's (clipped) mid-line (midpoint rule
    /// in y). Cost ∝ the ellipse's height in texels.
    fn ellipse_average(
        &self,
        c: usize,
        xi: [f64; 2],
        xe: [f64; 2],
        d: f64,
        rho0: f64,
    ) -> (f64, f64) {
        let Aggregates::Rows(rows) = &self.aggregates else {
            unreachable!("the ellipse method is built with its row sums")
        };
        let a = 0.5 * d + 1.0 / rho0;
        let b = (a * a - 0.25 * d * d).sqrt();
        let centre = [0.5 * (xi[0] + xe[0]), 0.5 * (xi[1] + xe[1])];
        let [ux, uy] = if d > 0.0 {
            [(xe[0] - xi[0]) / d, (xe[1] - xi[1]) / d]
        } else {
            [1.0, 0.0]
        };
        // The ellipse as A X² + B X + C(Y) ≤ 0 with X = x − c_x, Y = y − c_y.
        let (ia2, ib2) = (1.0 / (a * a), 1.0 / (b * b));
        let qa = ux * ux * ia2 + uy * uy * ib2;
        let qb = 2.0 * ux * uy * (ia2 - ib2);
        let qc = uy * uy * ia2 + ux * ux * ib2;
        let half_h = (a * a * uy * uy + b * b * ux * ux).sqrt();
        let (ra, r) = (&rows.rho_alpha[c], &rows.rho);
        let (mut num, mut den, mut area) = (0.0, 0.0, 0.0);
        for (y, h, i) in ra.bands(centre[1] - half_h, centre[1] + half_h) {
            let yy = y - centre[1];
            let (bq, cq) = (qb * yy, qc * yy * yy - 1.0);
            let disc = bq * bq - 4.0 * qa * cq;
            if disc <= 0.0 {
                continue;
            }
            let s = disc.sqrt();
            let (x0, x1) = (
                centre[0] + (-bq - s) / (2.0 * qa),
                centre[0] + (-bq + s) / (2.0 * qa),
            );
            num += h * ra.integral(i, x0, x1);
            den += h * r.as_ref().map_or(x1 - x0, |r| r.integral(i, x0, x1));
            area += h * (x1 - x0);
        }
        if !(den > 0.0 && area > 0.0) {
            let rho = self.density_at(centre[0], centre[1]);
            return (self.albedo_at(c, centre[0], centre[1]), rho);
        }
        match (&self.material.density, r) {
            (Density::Constant(rho), _) => (num / den, *rho),
            _ => (num / den, den / area),
        }
    }
}

/// Row prefix sums of a texel map: P_i(j) = τ·Σ_{j' < j} v_ij', so that
/// ∫ over [x0, x1] of row i (edge texels extended) is O(1).
#[derive(Debug)]
struct RowPrefix {
    map: TexelMap,
    prefix: Vec<f64>,
}

impl RowPrefix {
    fn new(map: TexelMap) -> Self {
        let (nx, tau) = (map.nx, map.texel);
        let mut prefix = Vec::with_capacity(map.ny * (nx + 1));
        for row in map.values.chunks(nx) {
            let mut acc = 0.0;
            prefix.push(0.0);
            for v in row {
                acc += tau * v;
                prefix.push(acc);
            }
        }
        RowPrefix { map, prefix }
    }

    /// ∫_{x_left}^{x} of row i (negative left of the texture).
    #[inline]
    fn cumulative(&self, i: usize, x: f64) -> f64 {
        let m = &self.map;
        let (nx, tau) = (m.nx, m.texel);
        let left = -0.5 * nx as f64 * tau;
        let row = &m.values[i * nx..(i + 1) * nx];
        let p = &self.prefix[i * (nx + 1)..(i + 1) * (nx + 1)];
        let u = (x - left) / tau;
        if u <= 0.0 {
            (x - left) * row[0]
        } else if u >= nx as f64 {
            p[nx] + (u - nx as f64) * tau * row[nx - 1]
        } else {
            let j = u as usize;
            p[j] + (u - j as f64) * tau * row[j]
        }
    }

    #[inline]
    fn integral(&self, i: usize, x0: f64, x1: f64) -> f64 {
        self.cumulative(i, x1) - self.cumulative(i, x0)
    }

    /// The texel-row bands crossing [y0, y1]: (mid-line y, height, row index),
    /// rows beyond the texture mapped to the edge row.
    fn bands(&self, y0: f64, y1: f64) -> impl Iterator<Item = (f64, f64, usize)> + '_ {
        let (ny, tau) = (self.map.ny, self.map.texel);
        let top = 0.5 * ny as f64 * tau;
        // Row k (unclamped) covers y ∈ (top − (k+1)τ, top − kτ].
        let k0 = ((top - y1) / tau).floor() as i64;
        let k1 = ((top - y0) / tau).floor() as i64;
        (k0..=k1).filter_map(move |k| {
            let hi = (top - k as f64 * tau).min(y1);
            let lo = (top - (k + 1) as f64 * tau).max(y0);
            (hi > lo).then(|| (0.5 * (lo + hi), hi - lo, k.clamp(0, ny as i64 - 1) as usize))
        })
    }
}

/// Row sums for `ellipse`: of ρα per channel (α for a constant density) and
/// of ρ (density maps only).
#[derive(Debug)]
struct Rows {
    rho_alpha: Vec<RowPrefix>,
    rho: Option<RowPrefix>,
}

/// The albedo channels times the density map, texel by texel (ρα); the
/// albedo itself for a constant density (which cancels in every average).
/// The maps share one grid ([`common_grid`]).
fn density_weighted(albedo: &[TexelMap], density: &Density) -> Vec<TexelMap> {
    albedo
        .iter()
        .map(|a| {
            let mut m = a.clone();
            if let Density::Map(rho) = density {
                for (v, r) in m.values.iter_mut().zip(&rho.values) {
                    *v *= r;
                }
            }
            m
        })
        .collect()
}

/// The maps resampled onto one texel grid that refines all of them, so that
/// every fine texel lies inside one texel of each map (then the resampling
/// is exact): centred, half-width the largest of the maps', spacing τ, or
/// τ/2 where the texel counts differ in parity (their edges are then offset
/// by τ/2). Maps must share τ. Maps already of one shape come back as is.
pub(crate) fn common_grid(maps: &[&TexelMap]) -> Result<Vec<TexelMap>> {
    let tau = maps[0].texel;
    if maps.iter().any(|m| m.texel != tau) {
        return Err(Error::param(
            "texel size",
            "differing",
            "the same for every map",
        ));
    }
    let (nx, ny) = (maps[0].nx, maps[0].ny);
    if maps.iter().all(|m| (m.nx, m.ny) == (nx, ny)) {
        return Ok(maps.iter().map(|m| (*m).clone()).collect());
    }
    let parity = |f: fn(&TexelMap) -> usize| maps.iter().any(|m| (f(m) + f(maps[0])) % 2 == 1);
    let fine = parity(|m| m.nx) || parity(|m| m.ny);
    let h = if fine { 0.5 * tau } else { tau };
    let big_x = maps.iter().map(|m| m.nx).max().unwrap_or(1) as f64 * tau;
    let big_y = maps.iter().map(|m| m.ny).max().unwrap_or(1) as f64 * tau;
    let (gx, gy) = ((big_x / h).round() as usize, (big_y / h).round() as usize);
    maps.iter()
        .map(|m| {
            let mut v = Vec::with_capacity(gx * gy);
            for i in 0..gy {
                let y = 0.5 * big_y - (i as f64 + 0.5) * h;
                for j in 0..gx {
                    v.push(m.at(-0.5 * big_x + (j as f64 + 0.5) * h, y));
                }
            }
            TexelMap::new(gx, gy, h, v)
        })
        .collect()
}

/// The pair frame on the surface: origin x_i, unit axis toward x_e.
struct Frame {
    xi: [f64; 2],
    axis: [f64; 2],
}

impl Frame {
    /// The surface position of a component's centre (t along the axis, s to
    /// its left).
    #[inline]
    fn place(&self, c: &Component) -> [f64; 2] {
        let [ux, uy] = self.axis;
        [
            self.xi[0] + c.t * ux - c.s * uy,
            self.xi[1] + c.t * uy + c.s * ux,
        ]
    }

    /// The part along the pair axis of a component's variance of a field
    /// f: ((f̃(μ + σu) − f̃(μ − σu))/2)², with f̃ = `mean` the field's mean
    /// under the component's Gaussian centred at a point, u the axis and σ
    /// the component's width. For a field linear over the component,
    /// f = f₀ + g·x, the component's variance of f is σ²|g|² and this is
    /// σ²(g·u)², its axial share.
    #[inline]
    fn along_axis_variance(
        &self,
        mu: [f64; 2],
        sigma: f64,
        mut mean: impl FnMut([f64; 2]) -> f64,
    ) -> f64 {
        let [ux, uy] = self.axis;
        let ahead = mean([mu[0] + sigma * ux, mu[1] + sigma * uy]);
        let behind = mean([mu[0] - sigma * ux, mu[1] - sigma * uy]);
        0.25 * (ahead - behind) * (ahead - behind)
    }
}

/// [`crate::metamodel::kernel::manual_kernel`] at optical distance `d1`,
/// lengths multiplied by `scale` (= 1/ρ), into `out` without allocating.
#[inline]
fn manual_into(d1: f64, scale: f64, out: &mut Gmm) {
    out.components.clear();
    for (weight, t, sigma) in [
        (0.25, 0.0, 0.5),
        (0.5, 0.5 * d1, 0.5 + 0.3 * d1),
        (0.25, d1, 0.5),
    ] {
        out.components.push(Component {
            weight,
            t: t * scale,
            s: 0.0,
            sigma: sigma * scale,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::rng::PathRng;
    use crate::metamodel::kernel::{manual_kernel, optical_distance, scale_for_density};

    fn basis() -> (BasisModel, Arc<BasisTable>) {
        let m = crate::testing::shipped_basis();
        let t = Arc::new(BasisTable::new(&m));
        (m, t)
    }

    /// `learned` with `variant` on one albedo channel over a density map.
    fn learned_over(
        variant: Variant,
        t: &Arc<BasisTable>,
        meta: &Arc<MetaModelFile>,
        albedo: &TexelMap,
        density: &TexelMap,
    ) -> SvBssrdf {
        SvBssrdf::new(
            Method::Learned,
            variant,
            t.clone(),
            Some(meta.clone()),
            vec![albedo.clone()],
            Density::Map(density.clone()),
        )
        .unwrap()
    }

    /// The distance x_i → x_e and the pair's frame.
    fn pair_frame(xi: [f64; 2], xe: [f64; 2]) -> (f64, Frame) {
        let delta = [xe[0] - xi[0], xe[1] - xi[1]];
        let d = delta[0].hypot(delta[1]);
        let axis = [delta[0] / d, delta[1] / d];
        (d, Frame { xi, axis })
    }

    fn noise_map(n: usize, tau: f64, lo: f64, hi: f64, seed: u64) -> TexelMap {
        let mut rng = PathRng::new(seed, 0);
        let v = (0..n * n).map(|_| lo + (hi - lo) * rng.uniform()).collect();
        TexelMap::new(n, n, tau, v).unwrap()
    }

    #[test]
    fn basis_table_matches_the_model() {
        let (m, t) = basis();
        let mut worst: f64 = 0.0;
        for k in 0..2000 {
            let alpha = 1.0 - ((k as f64 + 0.37) / 2000.0).powi(2);
            for r in [0.0f64, 0.05, 0.5, 2.0, 10.0] {
                let want = m.multi(alpha).density(r.max(1e-300)) / (2.0 * PI * r.max(1e-300));
                let got = alpha * alpha * t.multi_over_alpha2(r, alpha);
                if want > 1e-12 {
                    worst = worst.max((got / want - 1.0).abs());
                }
            }
        }
        assert!(worst < 1e-4, "worst relative error {worst}");
        // The lane-parallel evaluation is the scalar one.
        for (r, alpha) in [(0.0, 0.5), (0.3, 0.99), (4.0, 0.2), (40.0, 1.0), (1.0, 0.0)] {
            let (s, m) = t.parts(r, alpha);
            let (s0, m0) = (
                t.single_exitance(r),
                t.multi_over_alpha2(r.max(R_MIN), alpha),
            );
            assert!(
                (s - s0).abs() <= 1e-14 * s0 && (m - m0).abs() <= 1e-14 * m0.max(1e-300),
                "{r} {alpha}"
            );
        }
        // Single scattering is exact.
        let r = 0.7;
        let want = m.single(1.0).density(r) / (2.0 * PI * r);
        assert!((t.single_exitance(r) - want).abs() < 1e-15 * want.max(1.0));
    }

    #[test]
    fn interior_vertices_are_the_albedo_derivative_of_the_profile() {
        // n̄ − 2 = ∂ln(Rₘ/α²)/∂ln α of the basis model itself (a central
        // difference in α; the table is within 1e-4 of the model), growing
        // with the albedo as paths get longer.
        let (m, t) = basis();
        let ln_m = |r: f64, a: f64| (m.multi(a).density(r) / (a * a)).ln();
        for r in [0.3, 1.0, 3.0] {
            let mut last = 0.0;
            for a in [0.3, 0.6, 0.8, 0.9, 0.95, 0.99] {
                let h = 1e-4;
                let want = a * (ln_m(r, a + h) - ln_m(r, a - h)) / (2.0 * h);
                let got = t.interior_vertices(r, a);
                assert!(
                    (got - want).abs() < 0.02 * want + 0.01,
                    "r {r}, α {a}: {got} vs {want}"
                );
                assert!(got > last, "r {r}, α {a}: {got} after {last}");
                last = got;
            }
        }
        assert_eq!(t.interior_vertices(1e6, 0.5), 0.0, "R_m underflows");
    }

    #[test]
    fn the_interior_kernel_blends_in_over_its_ramp() {
        let [lo, hi] = INTERIOR_RAMP;
        let auto = |a| InteriorKernel::Auto.weight(a);
        assert_eq!(auto(0.3), 0.0);
        assert_eq!(
            auto(lo),
            0.0,
            "the canonical scenes' albedos stay below the ramp"
        );
        assert_eq!(auto(hi), 1.0);
        assert_eq!(auto(1.0), 1.0);
        assert!((auto(0.5 * (lo + hi)) - 0.5).abs() < 1e-12);
        let mut last = 0.0;
        for k in 1..=100 {
            let w = auto(lo + (hi - lo) * k as f64 / 100.0);
            assert!(w > last, "rising: {w} after {last}");
            last = w;
        }
        for a in [0.0, 0.96, 1.0] {
            assert_eq!(InteriorKernel::Never.weight(a), 0.0);
            assert_eq!(InteriorKernel::Always.weight(a), 1.0);
        }
    }

    #[test]
    fn the_interior_kernel_in_parts_is_the_whole_mixture() {
        // At a constant density `learned --interior` combines K_all's,
        // K_last's and the point's means; a density map of ones takes the
        // whole signed mixture through the density-weighted means. Both
        // spaces, channels of different textures.
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        let albedo = vec![
            noise_map(24, 0.25, 0.2, 0.95, 7),
            noise_map(24, 0.25, 0.85, 0.995, 9),
        ];
        let ones = TexelMap::new(24, 24, 0.25, vec![1.0; 24 * 24]).unwrap();
        let cases = [AlbedoSpace::Transport, AlbedoSpace::Linear]
            .into_iter()
            .flat_map(|s| [(s, InteriorKernel::Always), (s, InteriorKernel::Auto)]);
        for (space, interior) in cases {
            let variant = Variant {
                interior,
                space,
                ..Variant::default()
            };
            let sv = |density| {
                SvBssrdf::new(
                    Method::Learned,
                    variant,
                    t.clone(),
                    Some(meta.clone()),
                    albedo.clone(),
                    density,
                )
                .unwrap()
            };
            let (parts, whole) = (sv(Density::Constant(1.0)), sv(Density::Map(ones.clone())));
            let plain = SvBssrdf::new(
                Method::Learned,
                Variant {
                    space,
                    interior: InteriorKernel::Never,
                    ..Variant::default()
                },
                t.clone(),
                Some(meta.clone()),
                albedo.clone(),
                Density::Constant(1.0),
            )
            .unwrap();
            let mut scratch = Scratch::default();
            for c in 0..2 {
                for (xi, xe) in [
                    ([0.1, -0.2], [0.9, 0.4]),
                    ([-1.0, 1.0], [1.5, -2.0]),
                    ([0.3, 0.3], [0.35, 0.3]),
                ] {
                    let a = parts.eval(c, xi, xe, &mut scratch);
                    let b = whole.eval(c, xi, xe, &mut scratch);
                    assert!(
                        (a - b).abs() <= 1e-9 * b,
                        "{space:?} channel {c}: {a} vs {b}"
                    );
                    // Always: the ends matter; blended: the dark channel
                    // (α ≤ 0.95) stays on the all-vertex kernel.
                    let p = plain.eval(c, xi, xe, &mut scratch);
                    match interior {
                        InteriorKernel::Always => assert!(
                            (a - p).abs() > 1e-4 * p,
                            "{space:?} channel {c}: the ends must matter"
                        ),
                        _ if c == 0 => assert_eq!(a, p, "{space:?}: below the ramp"),
                        _ => {}
                    }
                }
            }
        }
    }

    #[test]
    fn the_table_stays_exact_at_zero_albedo_for_tiny_amplitudes() {
        // Amplitudes e^{-60}: α²·A/α² underflowed at the old table's
        // α = 1e-150 stand-in, leaving Rₘ/α² = 0 at α = 0.
        let (mut m, _) = basis();
        for c in &mut m.ln_a {
            c[0] -= 60.0;
        }
        let t = BasisTable::new(&m);
        for alpha in [0.0, 1e-6, 0.3] {
            let (ln_a, b) = m.multi_over_alpha2(alpha);
            let want: f64 = ln_a
                .iter()
                .zip(&b)
                .map(|(l, b)| (l - b * 0.5).exp() / (2.0 * PI))
                .sum();
            let got = t.multi_over_alpha2(0.5, alpha);
            assert!(
                want > 0.0 && (got / want - 1.0).abs() < 1e-3,
                "{alpha}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn common_grid_resamples_exactly() {
        let a = noise_map(5, 0.5, 0.0, 1.0, 3);
        let b = noise_map(8, 0.5, 0.5, 2.0, 4);
        let c = TexelMap::new(1, 1, 0.5, vec![0.25]).unwrap();
        let out = common_grid(&[&a, &b, &c]).unwrap();
        assert_eq!((out[0].nx, out[0].texel), (16, 0.25));
        let mut rng = PathRng::new(1, 1);
        for _ in 0..10_000 {
            let (x, y) = (6.0 * rng.uniform() - 3.0, 6.0 * rng.uniform() - 3.0);
            for (m, o) in [&a, &b, &c].iter().zip(&out) {
                assert_eq!(m.at(x, y), o.at(x, y), "({x}, {y})");
            }
        }
        assert!(common_grid(&[&a, &TexelMap::new(1, 1, 0.3, vec![1.0]).unwrap()]).is_err());
    }

    #[test]
    fn ellipse_rows_match_a_fine_grid() {
        let (_, t) = basis();
        let albedo = noise_map(48, 0.25, 0.0, 1.0, 1);
        let rho = noise_map(48, 0.25, 0.5, 4.0, 2);
        for density in [Density::Constant(1.5), Density::Map(rho.clone())] {
            let sv = SvBssrdf::new(
                Method::Ellipse,
                Variant::default(),
                t.clone(),
                None,
                vec![albedo.clone()],
                density.clone(),
            )
            .unwrap();
            for (xi, xe) in [
                ([0.1f64, 0.2], [2.3f64, -1.1]),
                ([-5.0, 5.5], [-5.6, 7.0]),
                ([1.0, 1.0], [1.0, 1.0]),
            ] {
                let d = (xe[0] - xi[0]).hypot(xe[1] - xi[1]);
                let rho0 = 0.5 * (density.at(xi[0], xi[1]) + density.at(xe[0], xe[1]));
                let (a_rows, r_rows) = sv.ellipse_average(0, xi, xe, d, rho0);
                // Brute force: a grid of spacing τ/16 over the bounding box.
                let a = 0.5 * d + 1.0 / rho0;
                let b = (a * a - 0.25 * d * d).sqrt();
                let c = [0.5 * (xi[0] + xe[0]), 0.5 * (xi[1] + xe[1])];
                let u = if d > 0.0 {
                    [(xe[0] - xi[0]) / d, (xe[1] - xi[1]) / d]
                } else {
                    [1.0, 0.0]
                };
                let h = 0.25 / 16.0;
                let (mut ra, mut r, mut n) = (0.0, 0.0, 0.0);
                let m = (a / h).ceil() as i64;
                for i in -m..m {
                    for j in -m..m {
                        let (p, q) = ((i as f64 + 0.5) * h, (j as f64 + 0.5) * h);
                        if (p / a).powi(2) + (q / b).powi(2) > 1.0 {
                            continue;
                        }
                        let (x, y) = (c[0] + p * u[0] - q * u[1], c[1] + p * u[1] + q * u[0]);
                        let rr = density.at(x, y);
                        ra += rr * albedo.at(x, y);
                        r += rr;
                        n += 1.0;
                    }
                }
                assert!((a_rows - ra / r).abs() < 0.01, "{a_rows} vs {}", ra / r);
                assert!(
                    (r_rows / (r / n) - 1.0).abs() < 0.01,
                    "{r_rows} vs {}",
                    r / n
                );
            }
        }
    }

    /// The coarse variance ([`COARSE_VARIANCE`]) brightens α_t beside a
    /// step coarser than a mean free path, on both sides, and leaves S as it
    /// was where the albedo is uniform over more than a few L or varies far
    /// finer than L (there the fused four-pyramid query must give the
    /// two-scale means of [`SvBssrdf::means`]).
    #[test]
    fn coarse_variance_acts_on_coarse_steps_only() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        let (nx, ny, tau) = (400, 80, 0.05);
        let x_of = |k: usize| ((k % nx) as f64 + 0.5) * tau - 0.5 * nx as f64 * tau;
        // A step 0.2 | 0.9 at x = 0 (20 × 4 MFP) and stripes of 0.1 MFP.
        let step: Vec<f64> = (0..nx * ny)
            .map(|k| if x_of(k) < 0.0 { 0.2 } else { 0.9 })
            .collect();
        let fine: Vec<f64> = (0..nx * ny)
            .map(|k| {
                if (k % nx / 2).is_multiple_of(2) {
                    0.2
                } else {
                    0.9
                }
            })
            .collect();
        let build = |values: &[f64], c: f64, density: Density| {
            let variant = Variant {
                coarse_variance: c,
                ..Variant::default()
            };
            let map = TexelMap::new(nx, ny, tau, values.to_vec()).unwrap();
            let (t, meta) = (t.clone(), Some(meta.clone()));
            SvBssrdf::new(Method::Learned, variant, t, meta, vec![map], density)
        };
        let eval = |values: &[f64], c: f64, density: Density, xi: [f64; 2], xe: [f64; 2]| {
            let sv = build(values, c, density).unwrap();
            sv.eval(0, xi, xe, &mut Scratch::default())
        };
        for density in [Density::Constant(1.0), Density::Constant(2.0)] {
            let both = |values: &[f64], xi, xe| {
                let off = eval(values, 0.0, density.clone(), xi, xe);
                let on = eval(values, COARSE_VARIANCE, density.clone(), xi, xe);
                on / off
            };
            // Beside the step and along it, on the dark side and on the
            // bright one: S grows, by less on the dark side, where single
            // scattering carries most of it (measured: 4e-4 and 1.4 % at
            // ρ = 1).
            for (xi, xe, least) in [
                ([-0.5, -0.5], [-0.5, 0.5], 1e-4),
                ([0.5, -0.5], [0.5, 0.5], 5e-3),
            ] {
                let r = both(&step, xi, xe);
                assert!(r > 1.0 + least, "{density:?} {xi:?} → {xe:?}: {r}");
            }
            // Far from it, and on the fine stripes.
            let r = both(&step, [-8.0, 0.0], [-7.6, 0.0]);
            assert!((r - 1.0).abs() < 1e-9, "{density:?} far: {r}");
            let r = both(&fine, [-0.3, 0.0], [0.2, 0.0]);
            assert!((r - 1.0).abs() < 1e-6, "{density:?} fine: {r}");
        }
        // A density map follows the same rule (its own, density-weighted
        // path): a constant map gives a constant density's S.
        let rho = || Density::Map(TexelMap::new(nx, ny, tau, vec![1.0; nx * ny]).unwrap());
        for (xi, xe) in [([-0.5, -0.5], [-0.5, 0.5]), ([-8.0, 0.0], [-7.6, 0.0])] {
            let (map, constant) = (
                eval(&step, COARSE_VARIANCE, rho(), xi, xe),
                eval(&step, COARSE_VARIANCE, Density::Constant(1.0), xi, xe),
            );
            assert!(
                (map / constant - 1.0).abs() < 1e-3,
                "{xi:?}: {map} vs {constant}"
            );
        }
        // Only the variance across the pair's axis counts: on a gentle ramp
        // in x, a pair along x (the ramp in series) is left as it is, a
        // pair along y (the ramp beside it) brightens. The isotropic
        // variance would brighten both alike.
        let ramp: Vec<f64> = (0..nx * ny).map(|k| 0.6 + 0.03 * x_of(k)).collect();
        let ratio = |density: Density, xi: [f64; 2], xe: [f64; 2]| {
            eval(&ramp, COARSE_VARIANCE, density.clone(), xi, xe)
                / eval(&ramp, 0.0, density, xi, xe)
        };
        for density in [Density::Constant(1.0), rho()] {
            let beside = ratio(density.clone(), [0.0, -0.75], [0.0, 0.75]) - 1.0;
            let series = ratio(density.clone(), [-0.75, 0.0], [0.75, 0.0]) - 1.0;
            assert!(beside > 5e-5, "{density:?}: beside {beside}");
            assert!(
                series.abs() < 0.05 * beside,
                "{density:?}: series {series}, beside {beside}"
            );
        }
        // Outside [0, 0.5]: a clear error.
        let sv = build(&step, 0.7, Density::Constant(1.0));
        assert!(sv.is_err_and(|e| e.to_string().contains("coarse_variance")));
    }

    #[test]
    fn split_form_stays_bounded_as_albedos_vanish() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        for eps in [0.0, 1e-300, 1e-12, 1e-6, 1e-3] {
            // A map of ε with one bright texel far away, and a map of ε only.
            let mut v = vec![eps; 16 * 16];
            v[0] = 0.9;
            for map in [
                TexelMap::new(16, 16, 0.5, v).unwrap(),
                TexelMap::new(1, 1, 0.5, vec![eps]).unwrap(),
            ] {
                for method in [Method::Manual, Method::Learned] {
                    for variant in [
                        Variant::default(),
                        Variant {
                            plain: true,
                            vertex_kernels: true,
                            two_pass: true,
                            interior: InteriorKernel::Always,
                            space: AlbedoSpace::Log,
                            space_blur: 0.5,
                            split: Split::Gaussian,
                            coarse_variance: 0.0,
                            density_law: DensityLaw::Kernel,
                            density_kernel: DensityKernel::Warp,
                            step_ends: StepEnds::Correlated,
                            last_kernel: LastKernel::Pair,
                        },
                        Variant {
                            coarse_variance: COARSE_VARIANCE,
                            ..Variant::default()
                        },
                    ] {
                        // A 1 × 1 density map under a 16 × 16 albedo: resampled.
                        let rho = Density::Map(TexelMap::new(1, 1, 0.5, vec![1.0]).unwrap());
                        let sv = SvBssrdf::new(
                            method,
                            variant,
                            t.clone(),
                            Some(meta.clone()),
                            vec![map.clone()],
                            rho,
                        )
                        .unwrap();
                        for d in [0.0, 0.3, 3.0] {
                            let s = sv.eval(0, [0.5, 0.5], [0.5 + d, 0.5], &mut Scratch::default());
                            assert!(s.is_finite() && s >= 0.0, "{eps} {d}: {s}");
                            // S = O(ε): single scattering carries α_i, the rest α_iα_e/α_t²·Rₘ(α_t).
                            assert!(s <= 1e3 * eps.max(1e-300) / d.max(1e-6), "{eps} {d}: {s}");
                            if map.nx == 1 {
                                // A uniform ε: the split form is the homogeneous
                                // profile at ε, constant included.
                                let want = t.exitance(d, eps, 1.0);
                                assert!(
                                    (s - want).abs() <= 1e-9 * want,
                                    "{eps} {d}: {s} vs homogeneous {want}"
                                );
                            }
                        }
                    }
                }
            }
            // Near the bright texel the ratio α_iα_e/α_t² is ε²/α_t²: finite.
            let mut v = vec![eps; 16 * 16];
            v[0] = 0.9;
            let map = TexelMap::new(16, 16, 0.5, v).unwrap();
            for method in [Method::Manual, Method::Learned] {
                let sv = SvBssrdf::new(
                    method,
                    Variant::default(),
                    t.clone(),
                    Some(meta.clone()),
                    vec![map.clone()],
                    Density::Constant(1.0),
                )
                .unwrap();
                let s = sv.eval(0, [-3.0, 3.0], [-2.0, 3.5], &mut Scratch::default());
                assert!(s.is_finite() && s >= 0.0, "{eps}: {s}");
            }
        }
    }

    /// An n × n checker of single 0.05 MFP texels, 0.2 and 0.8, and a
    /// density map of 3 on the 0.8 texels and 1 on the 0.2 ones.
    fn fine_checker(n: usize) -> (TexelMap, TexelMap) {
        let checker: Vec<f64> = (0..n * n)
            .map(|k| {
                if (k / n + k % n).is_multiple_of(2) {
                    0.2
                } else {
                    0.8
                }
            })
            .collect();
        let rho = checker
            .iter()
            .map(|&a| if a > 0.5 { 3.0 } else { 1.0 })
            .collect();
        (
            TexelMap::new(n, n, 0.05, checker).unwrap(),
            TexelMap::new(n, n, 0.05, rho).unwrap(),
        )
    }

    /// One Gaussian of σ = 1.5 MFP at t = 0.5 on the x axis from the
    /// origin: far wider than [`fine_checker`]'s texels.
    fn wide_kernel() -> (Gmm, Frame) {
        let kernel = Gmm {
            components: vec![Component {
                weight: 1.0,
                t: 0.5,
                s: 0.0,
                sigma: 1.5,
            }],
        };
        let frame = Frame {
            xi: [0.0, 0.0],
            axis: [1.0, 0.0],
        };
        (kernel, frame)
    }

    /// Each albedo space aggregates its own mean: on a fine checker of 0.2
    /// and 0.8 under a wide kernel with b = 0, α_t is 0.5 (linear),
    /// √(0.2·0.8) = 0.4 (log), 1 − √(0.8·0.2) = 0.6 (absorption) and
    /// 1 − ((√0.8 + √0.2)/2)² (transport); with a density map, ρ weights
    /// φ(α). With b = 1 MFP, far coarser than the checker's texels, every
    /// space gives the linear mean.
    #[test]
    fn each_albedo_space_aggregates_its_mean() {
        let (_, t) = basis();
        let (albedo, rho) = fine_checker(400);
        let (kernel, frame) = wide_kernel();
        let mean =
            |w: f64, f: fn(f64) -> f64, inv: fn(f64) -> f64| inv((f(0.2) + w * f(0.8)) / (1.0 + w));
        let log = |a: f64| a.ln();
        let absorption = |a: f64| (1.0 - a).ln();
        let transport = |a: f64| (1.0 - a).sqrt();
        for (density, w) in [(Density::Constant(1.0), 1.0), (Density::Map(rho), 3.0)] {
            let linear = mean(w, |a| a, |y| y);
            for (space, blur, want) in [
                (AlbedoSpace::Linear, 0.0, linear),
                (AlbedoSpace::Log, 0.0, mean(w, log, f64::exp)),
                (
                    AlbedoSpace::Absorption,
                    0.0,
                    mean(w, absorption, |y| 1.0 - y.exp()),
                ),
                (
                    AlbedoSpace::Transport,
                    0.0,
                    mean(w, transport, |y| 1.0 - y * y),
                ),
                (AlbedoSpace::Log, 1.0, linear),
                (AlbedoSpace::Absorption, 1.0, linear),
                (AlbedoSpace::Transport, 1.0, linear),
            ] {
                let sv = SvBssrdf::new(
                    Method::Manual,
                    Variant {
                        space,
                        space_blur: blur,
                        split: Split::Gaussian,
                        ..Variant::default()
                    },
                    t.clone(),
                    None,
                    vec![albedo.clone()],
                    density.clone(),
                )
                .unwrap();
                let (alpha_t, _) = sv.aggregate(0, &frame, &kernel, sv.pyramids().mapped.as_ref());
                assert!(
                    (alpha_t - want).abs() < 2e-3,
                    "{space:?}, b = {blur}: α_t {alpha_t} against {want}"
                );
            }
        }
    }

    /// The darker regime of [`Split::Regimes`] keeps the point's share of
    /// a fine texture's contrast in the coarse part: on the fine checker
    /// of 0.2 and 0.8 with b = 1 MFP, ᾱ = 0.2·α + 0.8·0.5 and α_t =
    /// φ⁻¹(⟨φ(ᾱ)⟩) in the transport space (the residual's mean is 0); the
    /// bright regime reads the one-flight kernel's aggregands.
    #[test]
    fn regimes_split_keeps_the_points_share() {
        let (_, t) = basis();
        let (albedo, _) = fine_checker(400);
        let (kernel, frame) = wide_kernel();
        let space = AlbedoSpace::Transport;
        let bar = |a: f64| SPLIT_POINT_WEIGHT * a + (1.0 - SPLIT_POINT_WEIGHT) * 0.5;
        let want = space.inverse(0.5 * (space.forward(bar(0.2)) + space.forward(bar(0.8))));
        let sv = SvBssrdf::new(
            Method::Manual,
            Variant {
                space_blur: 1.0,
                ..Variant::default()
            },
            t.clone(),
            None,
            vec![albedo],
            Density::Constant(1.0),
        )
        .unwrap();
        let p = sv.pyramids();
        let (dark, _) = sv.aggregate(0, &frame, &kernel, p.mapped.as_ref());
        assert!((dark - want).abs() < 3e-4, "α_t {dark} against {want}");
        assert!(want > 0.5 + 1.5e-3, "the point's share must show: {want}");
        // The one-flight kernel keeps a little of this checker's contrast
        // (its point's weight and its cusp: arctan(kℓ)/(kℓ) ≈ 0.03 at the
        // checker's kℓ), less than the darker regime's point of 0.2.
        let (bright, _) = sv.aggregate(0, &frame, &kernel, p.bright.as_ref());
        assert!(
            bright > 0.5 && bright < dark - 1e-3,
            "{bright} against {dark}"
        );
    }

    /// The one-flight kernel's Gaussian mixture has unit mass and the
    /// characteristic function arctan(kℓ)/(kℓ) of a flight's surface
    /// displacement to 0.004 for kℓ ≤ 60.
    #[test]
    fn flight_kernel_is_one_flights_displacement() {
        let mass: f64 = FLIGHT_KERNEL.iter().map(|c| c.1).sum();
        assert!((mass - 1.0).abs() < 1e-5, "{mass}");
        for i in 0..=600 {
            let k = 0.1 * i as f64;
            let want = if k > 0.0 { k.atan() / k } else { 1.0 };
            let got: f64 = FLIGHT_KERNEL
                .iter()
                .map(|&(s, w)| w * (-0.5 * k * k * s * s).exp())
                .sum();
            assert!((got - want).abs() < 4e-3, "k = {k}: {got} against {want}");
        }
        let flight = Split::Regimes.components(1.0, true);
        let mass: f64 = flight.iter().map(|c| c.1).sum();
        assert!((mass - 1.0).abs() < 1e-12);
        assert!(flight.iter().any(|c| c.0 == 0.0), "the cusp's point");
    }

    /// The importance sampler's albedo is the local mean over about a mean
    /// free path: the constant on a constant map, the mean of a checker far
    /// finer than that, and density-weighted on a density map.
    #[test]
    fn sampling_albedo_is_the_local_mean() {
        let (_, t) = basis();
        let (albedo, heavy) = fine_checker(200);
        let constant = TexelMap::new(1, 1, 0.05, vec![0.7]).unwrap();
        for (map, density, want) in [
            (constant, Density::Constant(2.0), 0.7),
            (albedo.clone(), Density::Constant(1.0), 0.5),
            (albedo, Density::Map(heavy), (0.2 + 3.0 * 0.8) / 4.0),
        ] {
            let sv = SvBssrdf::new(
                Method::Point,
                Variant::default(),
                t.clone(),
                None,
                vec![map],
                density,
            )
            .unwrap();
            for (x, y) in [(0.0, 0.0), (0.52, -1.13)] {
                let got = sv.sampling_albedo(x, y);
                assert!((got - want).abs() < 1e-3, "{got} vs {want}");
            }
        }
    }

    /// `learned` with vertex kernels puts each kernel in its role: α_t and
    /// ρ̄ from the all-vertex kernel (again at (α_t, ρ̄) with `two_pass`),
    /// α_i from the first-vertex kernel when the model has one, α_e from the
    /// last-vertex kernel (all evaluated at (d, α₀, ρ₀) before aggregating;
    /// [`LastKernel::Pair`]).
    #[test]
    fn learned_puts_each_kernel_in_its_role() {
        let (_, t) = basis();
        let mut file = crate::testing::shipped_meta();
        // A first-vertex model unlike the last-vertex one (the shipped file
        // has none: under normal incidence the first vertex is a δ).
        file.first = Some(file.all.clone());
        let meta = Arc::new(file);
        let albedo = noise_map(24, 0.25, 0.2, 0.95, 7);
        let density = noise_map(24, 0.25, 0.5, 3.0, 8);
        for (two_pass, density_law, interior) in [
            (false, DensityLaw::Endpoints, InteriorKernel::Never),
            (true, DensityLaw::Endpoints, InteriorKernel::Never),
            (false, DensityLaw::Kernel, InteriorKernel::Never),
            (false, DensityLaw::Endpoints, InteriorKernel::Always),
        ] {
            let variant = Variant {
                two_pass,
                density_law,
                interior,
                density_kernel: DensityKernel::Scaled,
                step_ends: StepEnds::Independent,
                last_kernel: LastKernel::Pair,
                ..Variant::default()
            };
            let sv = learned_over(variant, &t, &meta, &albedo, &density);
            for (xi, xe) in [([0.1, -0.2], [0.9, 0.4]), ([-1.0, 1.0], [1.5, -2.0])] {
                let got = sv.eval(0, xi, xe, &mut Scratch::default());
                let (d, frame) = pair_frame(xi, xe);
                let (ai, ae) = (albedo.at(xi[0], xi[1]), albedo.at(xe[0], xe[1]));
                let rho0 = 0.5 * (density.at(xi[0], xi[1]) + density.at(xe[0], xe[1]));
                let a0 = 0.5 * (ai + ae);
                // α_t in the variant's space, the vertex albedos linear.
                // (α₀ ≤ 0.95 here: the darker regime's split.)
                assert_eq!(bright_weight(a0), 0.0);
                let dark = sv.pyramids().mapped.as_ref();
                let agg = |k: &Gmm, mapped| sv.aggregate(0, &frame, k, mapped);
                let (mut alpha_t, mut rho_bar) = agg(&meta.all.eval(d, a0, rho0).gmm, dark);
                if two_pass {
                    (alpha_t, rho_bar) = agg(&meta.all.eval(d, alpha_t, rho_bar).gmm, dark);
                }
                let first = meta.first.as_ref().unwrap();
                if interior == InteriorKernel::Always {
                    // Without the end lobes, n̄ at the all-vertex α_t.
                    let mut k = Gmm::default();
                    interior_into(
                        &meta.all.eval(d, a0, rho0).gmm,
                        Some(&first.eval(d, a0, rho0).gmm),
                        Some(&meta.last.eval(d, a0, rho0).gmm),
                        d,
                        t.interior_vertices(d * rho0, alpha_t),
                        &mut k,
                    );
                    let plain = alpha_t;
                    alpha_t = agg(&k, dark).0;
                    assert!((alpha_t - plain).abs() > 1e-3, "the ends must matter here");
                }
                let li = agg(&first.eval(d, a0, rho0).gmm, None).0;
                let le = agg(&meta.last.eval(d, a0, rho0).gmm, None).0;
                assert!(
                    (li - le).abs() > 1e-3,
                    "the two vertex kernels must differ here"
                );
                let profile = |rho: f64| {
                    let (single, multi) = t.parts(d * rho, alpha_t);
                    rho * rho * (ai * single + li * le * multi)
                };
                let (ri, re) = (density.at(xi[0], xi[1]), density.at(xe[0], xe[1]));
                assert_ne!(ri, re, "the endpoints' densities must differ here");
                let want = match density_law {
                    DensityLaw::Endpoints => (profile(ri) * profile(re)).sqrt(),
                    DensityLaw::Kernel => profile(rho_bar),
                };
                assert_eq!(
                    got, want,
                    "{density_law:?}, two_pass {two_pass}, {xi:?} → {xe:?}"
                );
            }
        }
    }

    /// Across a coarse step (0.9 | 0.25 at x = 0, ends 2 MFP from it), the
    /// correlated step ends take α_t under the interior kernel and l_e as
    /// its two-scale mean (written out here); on a checker of 0.05 MFP,
    /// whose regional albedo is flat, they change nothing, bit for bit.
    #[test]
    fn step_ends_count_the_ends_once_across_a_coarse_step_only() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        assert!(meta.first.is_none(), "l_i is the point albedo here");
        let variant = |step_ends| Variant {
            density_kernel: DensityKernel::Scaled,
            step_ends,
            ..Variant::default()
        };
        let n = 48;
        let step: Vec<f64> = (0..n * n)
            .map(|k| if k % n < n / 2 { 0.9 } else { 0.25 })
            .collect();
        let albedo = TexelMap::new(n, n, 0.25, step).unwrap();
        let density = TexelMap::new(n, n, 0.25, vec![1.0; n * n]).unwrap();
        let sv = learned_over(variant(StepEnds::Correlated), &t, &meta, &albedo, &density);
        let independent =
            learned_over(variant(StepEnds::Independent), &t, &meta, &albedo, &density);
        let (xi, xe) = ([-2.0, 0.1], [2.0, -0.1]);
        assert_eq!(
            sv.step_weights(0, [xi, xe], [0.9, 0.25], [1.0, 1.0]),
            [1.0, 1.0]
        );
        let got = sv.eval(0, xi, xe, &mut Scratch::default());
        let (d, frame) = pair_frame(xi, xe);
        let a0 = 0.5 * (0.9 + 0.25);
        let dark = sv.pyramids().mapped.as_ref();
        let agg = |k: &Gmm| sv.aggregate(0, &frame, k, dark).0;
        let (all, last) = (
            meta.all.eval(d, a0, 1.0).gmm,
            meta.last.eval(d, a0, 1.0).gmm,
        );
        let mut inner = Gmm::default();
        let m = t.interior_vertices(d, agg(&all));
        interior_into(&all, None, Some(&last), d, m, &mut inner);
        let (single, multi) = t.parts(d, agg(&inner));
        let want = 0.9 * single + 0.9 * agg(&last) * multi;
        assert!((got - want).abs() <= 1e-12 * want, "{got} vs {want}");
        let before = independent.eval(0, xi, xe, &mut Scratch::default());
        assert!((got / before - 1.0).abs() > 0.01, "{got} vs {before}");

        let (checker, rho) = fine_checker(96);
        let sv = learned_over(variant(StepEnds::Correlated), &t, &meta, &checker, &rho);
        let independent = learned_over(variant(StepEnds::Independent), &t, &meta, &checker, &rho);
        for (xi, xe) in [([0.01, 0.02], [0.93, -0.4]), ([-1.1, 0.7], [1.3, 0.9])] {
            let densities = [rho.at(xi[0], xi[1]), rho.at(xe[0], xe[1])];
            assert_eq!(
                sv.step_weights(0, [xi, xe], [0.2, 0.8], densities),
                [0.0, 0.0]
            );
            let mut scratch = Scratch::default();
            assert_eq!(
                sv.eval(0, xi, xe, &mut scratch),
                independent.eval(0, xi, xe, &mut scratch)
            );
        }
    }

    /// [`LastKernel::Exit`] on a fine checker (no regional contrast, so
    /// neither step weight): l_e under the last-vertex kernel queried at
    /// the l_e that the kernel at α₀ gives, and nothing else changed.
    #[test]
    fn the_last_vertex_kernel_is_queried_at_the_albedo_its_vertex_sees() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        assert!(meta.first.is_none(), "l_i is the point albedo here");
        let n = 48;
        let checker = (0..n * n)
            .map(|k: usize| {
                if (k / n + k % n).is_multiple_of(2) {
                    0.3
                } else {
                    0.9
                }
            })
            .collect();
        let albedo = TexelMap::new(n, n, 0.25, checker).unwrap();
        let over = |last_kernel| {
            let variant = Variant {
                last_kernel,
                ..Variant::default()
            };
            let maps = vec![albedo.clone()];
            let density = Density::Constant(1.0);
            SvBssrdf::new(
                Method::Learned,
                variant,
                t.clone(),
                Some(meta.clone()),
                maps,
                density,
            )
            .unwrap()
        };
        let (exit, pair) = (over(LastKernel::Exit), over(LastKernel::Pair));
        for (xi, xe) in [([0.1, 0.1], [1.35, 0.6]), ([-0.4, 0.1], [-0.1, 0.35])] {
            let [ai, ae] = [xi, xe].map(|x| exit.albedo_at(0, x[0], x[1]));
            assert_eq!(exit.step_weights(0, [xi, xe], [ai, ae], [1.0; 2]), [0.0; 2]);
            let (d, frame) = pair_frame(xi, xe);
            let le = |alpha: f64| {
                exit.aggregate(0, &frame, &meta.last.eval(d, alpha, 1.0).gmm, None)
                    .0
            };
            let first = le(0.5 * (ai + ae));
            let want = le(first) / first;
            let single = ai * t.single_exitance(d);
            let mut scratch = Scratch::default();
            let got = (exit.eval(0, xi, xe, &mut scratch) - single)
                / (pair.eval(0, xi, xe, &mut scratch) - single);
            assert!((got - want).abs() <= 1e-12, "{got} vs {want}");
            assert!((want - 1.0).abs() > 1e-3, "the query moves l_e: {want}");
        }
    }

    #[test]
    fn learned_hands_queries_outside_the_box_to_the_outer_model() {
        let (_, t) = basis();
        // The shipped model alone, and another model over a wider box:
        // the shipped coefficients spread over d ∈ [0.05, 20] MFP and
        // α ∈ [0.05, 0.999] give other kernels.
        let mut inner = crate::testing::shipped_meta();
        inner.outer = None;
        let mut wide = inner.clone();
        for m in [&mut wide.all, &mut wide.last] {
            *m = crate::metamodel::meta::MetaModel::new(
                m.k,
                (m.deg_x, m.deg_y),
                [0.05f64.ln(), 20f64.ln()],
                [0.05, 0.999],
                m.coeffs.clone(),
            );
        }
        let mut both = inner.clone();
        both.outer = Some(Box::new(wide.clone()));
        let n = 64;
        let checker = (0..n * n)
            .map(|k: usize| {
                if (k / n / 3 + k % n / 3).is_multiple_of(2) {
                    0.5
                } else {
                    0.996
                }
            })
            .collect();
        let albedo = TexelMap::new(n, n, 0.25, checker).unwrap();
        let over = |meta: &MetaModelFile, rho: f64| {
            SvBssrdf::new(
                Method::Learned,
                Variant::default(),
                t.clone(),
                Some(Arc::new(meta.clone())),
                vec![albedo.clone()],
                Density::Constant(rho),
            )
            .unwrap()
        };
        let mut scratch = Scratch::default();
        let mut seen = [0; 2];
        for rho in [1.0, 2.0] {
            let [inner, both, wide] = [&inner, &both, &wide].map(|m| over(m, rho));
            let a = |x: [f64; 2]| inner.albedo_at(0, x[0], x[1]);
            for (xi, xe) in [
                ([-1.0f64, 0.3], [1.2f64, -0.4]),
                ([-6.0, 0.2], [1.5, 0.7]),
                ([0.2, 0.1], [0.23, 0.12]),
                ([-7.2, -7.3], [-6.2, -7.0]),
            ] {
                let d = (xe[0] - xi[0]).hypot(xe[1] - xi[1]);
                let a0 = 0.5 * (a(xi) + a(xe));
                let inside = inner.meta.as_deref().unwrap().all.holds(rho * d, a0);
                let [s_inner, s_both, s_wide] =
                    [&inner, &both, &wide].map(|m| m.eval(0, xi, xe, &mut scratch));
                let want = if inside { s_inner } else { s_wide };
                assert_eq!(s_both, want, "ρ = {rho}, d = {d}, α₀ = {a0}");
                assert_ne!(s_inner, s_wide, "ρ = {rho}, d = {d}: the models differ");
                seen[inside as usize] += 1;
            }
        }
        assert!(
            seen[0] >= 3 && seen[1] >= 2,
            "pairs outside / inside: {seen:?}"
        );
    }

    /// The warp ([`DensityKernel::Warp`]) across a density step 1 | 4 at
    /// x = 0: the kernel at ρ_s = D/d, each centre moved through the
    /// step's optical coordinate (written out here), α_t the weighted mean
    /// of each component's own density-weighted mean.
    #[test]
    fn the_warp_places_each_component_by_the_optical_coordinate() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        let albedo = noise_map(24, 0.25, 0.2, 0.9, 11);
        let n = 24;
        let step: Vec<f64> = (0..n * n)
            .map(|i| if i % n < n / 2 { 1.0 } else { 4.0 })
            .collect();
        let density = TexelMap::new(n, n, 0.25, step).unwrap();
        let variant = Variant {
            vertex_kernels: false,
            interior: InteriorKernel::Never,
            space: AlbedoSpace::Linear,
            density_kernel: DensityKernel::Warp,
            ..Variant::default()
        };
        let sv = learned_over(variant, &t, &meta, &albedo, &density);
        // d = 1.6 with the step 0.5 from x_i, on a node boundary of the
        // density's samples: D = 0.5·1 + 1.1·4 = 4.9.
        let (xi, xe) = ([-0.5, 0.3], [1.1, 0.3]);
        let (d, big_d) = (1.6, 4.9);
        let tau_inverse = |u: f64| if u <= 0.5 { u } else { 0.5 + (u - 0.5) / 4.0 };
        let got = sv.eval(0, xi, xe, &mut Scratch::default());
        let frame = Frame {
            xi,
            axis: [1.0, 0.0],
        };
        let (ai, ae) = (albedo.at(xi[0], xi[1]), albedo.at(xe[0], xe[1]));
        let g = meta.all.eval(d, 0.5 * (ai + ae), big_d / d).gmm;
        let (mut num, mut den) = (0.0, 0.0);
        for c in &g.components {
            let placed = Component {
                t: tau_inverse(big_d / d * c.t),
                ..c.clone()
            };
            assert!(
                c.t <= 0.0 || c.t >= d || (placed.t - c.t).abs() > 1e-3,
                "a centre between the ends must move"
            );
            let one = Gmm {
                components: vec![placed],
            };
            num += c.weight * sv.aggregate(0, &frame, &one, None).0;
            den += c.weight;
        }
        let alpha_t = num / den;
        let profile = |rho: f64| {
            let (single, multi) = t.parts(d * rho, alpha_t);
            rho * rho * (ai * single + ai * ae * multi)
        };
        let want = (profile(1.0) * profile(4.0)).sqrt();
        assert!((got / want - 1.0).abs() < 1e-12, "{got} against {want}");
        // Scaled at the endpoints' mean density: another α_t.
        let scaled = learned_over(
            Variant {
                density_kernel: DensityKernel::Scaled,
                ..variant
            },
            &t,
            &meta,
            &albedo,
            &density,
        );
        let other = scaled.eval(0, xi, xe, &mut Scratch::default());
        assert!((other / got - 1.0).abs() > 1e-4, "{other} against {got}");
    }

    /// Where the density map is constant the warp is the density law.
    #[test]
    fn the_warp_at_a_constant_density_is_the_density_law() {
        let (_, t) = basis();
        let meta = Arc::new(crate::testing::shipped_meta());
        let albedo = noise_map(24, 0.25, 0.2, 0.95, 12);
        let density = TexelMap::new(24, 24, 0.25, vec![2.5; 24 * 24]).unwrap();
        let make = |density_kernel| {
            learned_over(
                Variant {
                    density_kernel,
                    ..Variant::default()
                },
                &t,
                &meta,
                &albedo,
                &density,
            )
        };
        let (scaled, warp) = (make(DensityKernel::Scaled), make(DensityKernel::Warp));
        for (xi, xe) in [([0.1, -0.2], [0.9, 0.4]), ([-1.0, 1.0], [1.5, -2.0])] {
            let a = scaled.eval(0, xi, xe, &mut Scratch::default());
            let b = warp.eval(0, xi, xe, &mut Scratch::default());
            assert!((a / b - 1.0).abs() < 1e-12, "{a} against {b}");
        }
    }

    #[test]
    fn manual_into_is_the_manual_kernel_under_the_density_law() {
        for (d, rho) in [(0.0, 1.0), (1.3, 1.0), (2.0, 4.0), (7.0, 0.5)] {
            let want = scale_for_density(&manual_kernel(optical_distance(d, rho)), rho);
            let mut got = Gmm::default();
            manual_into(d * rho, 1.0 / rho, &mut got);
            for (a, b) in got.components.iter().zip(&want.components) {
                assert!((a.weight - b.weight).abs() < 1e-15);
                assert!((a.t - b.t).abs() < 1e-12 && (a.sigma - b.sigma).abs() < 1e-12);
            }
        }
    }
}
