//! The scalar analog random walk (f64): the plain reference implementation.
//! [`super::simd`] runs the same walk eight paths at a time in f32 lanes and
//! consumes the random streams in exactly the same order.
//!
//! # The step protocol (shared by both walks)
//!
//! *Launch* draws from the path's stream what the source needs (nothing for
//! the pencil beam; disk position, direction and entry Fresnel for disks, see
//! [`launch`]). Then every step draws three 32-bit numbers `a, b, c`:
//!
//! 1. free flight s = −ln(u_a)/σ_t with u_a ∈ (0, 1];
//! 2. if the flight crosses the surface (or a slab's bottom), move to it; with
//!    probability F(|w_z|) (Fresnel from inside, TIR included) reflect the
//!    direction (u_b decides) and take the next step — free flights are
//!    memoryless, so restarting one at the interface is exact — otherwise the
//!    path leaves and is tallied;
//! 3. otherwise move by s and collide: scatter if b < α·2³² (an integer
//!    comparison, exact to 2⁻³² for any α), else be absorbed. A scattered path
//!    turns by the Henyey–Greenstein cos θ from u_c and the azimuth
//!    φ = 2π(b + ½)/t with t = α·2³² rounded ([`threshold_u32`]): b is
//!    uniform below its threshold, so it is reused. (Hence at tiny α only t
//!    azimuths exist, and the effective albedo is t/2³²: e.g. α = 10⁻⁹ gives
//!    t = 4, four azimuths and an albedo 7 % low — irrelevant where scattering
//!    is that rare.)
//!
//! # Termination at α = 1
//!
//! At α = 1 every path returns to the surface, but the return time is heavy
//! tailed (the depth is a recurrent 1-D walk: P(n > N) ~ N^{−1/2}). A path is
//! stopped after `max_events` scatterings and counted as `truncated`. The
//! bias of any tallied fraction is then at most the truncated fraction, which
//! every result reports; for α < 1 it is at most α^max_events.

use super::fresnel::{fresnel_dielectric, r_specular, refract_cos};
use super::maps::{MajorantGrid, TexelMap};
use super::medium::{Medium, Source};
use super::rng::{PathRng, threshold_u32, unit_f64, unit_open0_f64};
use super::sampling::{
    Vec3, hg_pdf, rotate_direction, sample_cosine_cos_theta, sample_disk_concentric, sample_hg_cos,
};
use super::tally::{BinLookup, ProfileTally, RADIANCE_Q, RadianceTally};
use std::f64::consts::PI;

/// A path inside the medium, right after entry.
#[derive(Clone, Copy, Debug)]
pub struct Launched {
    pub position: Vec3,
    pub direction: Vec3,
}

/// Launches path from `source`: `None` if it is reflected specularly at the
/// surface (sampled only for diffuse light; at normal incidence the constant
/// entry transmittance is a weight, [`entry_weight`]).
///
/// Inline for the pencil beam (no draws): the lane-parallel walk launches a
/// path whenever a lane ends, and an out-of-line call there spills every
/// live SIMD register. The disk sources sample out of line.
#[inline]
pub fn launch(source: &Source, eta: f64, rng: &mut PathRng) -> Option<Launched> {
    match *source {
        Source::Pencil => Some(Launched {
            position: [0.0; 3],
            direction: DOWN,
        }),
        Source::Collimated { radius } => Some(Launched {
            position: disk_point(radius, rng),
            direction: DOWN,
        }),
        Source::Diffuse { radius } => launch_diffuse(radius, eta, rng),
    }
}

/// Straight into the medium.
const DOWN: Vec3 = [0.0, 0.0, -1.0];

/// A uniform point of the disk of `radius` on the surface (two draws).
#[inline(never)]
fn disk_point(radius: f64, rng: &mut PathRng) -> Vec3 {
    let d = sample_disk_concentric([rng.uniform(), rng.uniform()]);
    [radius * d[0], radius * d[1], 0.0]
}

/// [`launch`] from a diffuse disk: the point, a cosine-distributed outside
/// direction, the Fresnel decision at entry, the refracted direction.
#[inline(never)]
fn launch_diffuse(radius: f64, eta: f64, rng: &mut PathRng) -> Option<Launched> {
    let position = disk_point(radius, rng);
    let cos_o = sample_cosine_cos_theta(rng.uniform());
    let phi = 2.0 * PI * rng.uniform();
    if rng.uniform() < fresnel_dielectric(cos_o, eta) {
        return None;
    }
    // Snell from outside (η_rel = η): never total internal reflection.
    let cos_t = refract_cos(cos_o, eta).unwrap_or(0.0);
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    Some(Launched {
        position,
        direction: [sin_t * phi.cos(), sin_t * phi.sin(), -cos_t],
    })
}

/// Power carried by each launched path, as a fraction of the incident power:
/// 1 − ((η−1)/(η+1))² at normal incidence, 1 where entry is sampled.
pub fn entry_weight(source: &Source, eta: f64) -> f64 {
    if source.is_normal_incidence() {
        1.0 - r_specular(eta)
    } else {
        1.0
    }
}

/// How a walk ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Fate {
    /// Left through the surface at (x, y) after `events` scatterings.
    Exit {
        x: f64,
        y: f64,
    },
    Transmitted,
    Absorbed,
    Truncated,
}

/// Where the walk reads the single-scattering albedo: the integer scatter
/// threshold t = α·2³² ([`threshold_u32`]) at a collision at (x, y).
/// Material maps are 2.5D (docs/design.md §2), so depth does not enter.
pub trait AlbedoField {
    fn threshold(&self, x: f64, y: f64) -> u64;
}

/// A homogeneous albedo: the same threshold everywhere.
#[derive(Clone, Copy, Debug)]
pub struct UniformAlbedo(pub u64);

impl AlbedoField for UniformAlbedo {
    #[inline(always)]
    fn threshold(&self, _x: f64, _y: f64) -> u64 {
        self.0
    }
}

/// What the boundary did in one step.
enum Wall {
    /// The flight ends inside the medium.
    Missed,
    /// Moved to the wall and reflected (Fresnel, TIR included).
    Reflected,
    /// Moved to the wall and left: through the surface at (x, y) or the
    /// slab's bottom.
    Left(Fate),
}

/// The boundary part of a step (protocol step 2): if the flight `s` reaches
/// the surface (w_z > 0) or the slab's bottom (w_z < 0), move there and
/// reflect with probability F(|w_z|) decided by `b`, or leave.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn wall(
    x: &mut f64,
    y: &mut f64,
    z: &mut f64,
    w: &mut Vec3,
    s: f64,
    bottom: Option<f64>,
    b: u32,
    inv_eta: f64,
) -> Wall {
    let to_wall = wall_distance(*z, w, bottom);
    if s < to_wall {
        return Wall::Missed;
    }
    hit_wall(x, y, z, w, to_wall, bottom, b, inv_eta)
}

/// Distance along `w` from depth `z` to the surface (w_z > 0) or the slab's
/// bottom (w_z < 0); ∞ if the flight meets neither.
#[inline(always)]
fn wall_distance(z: f64, w: &Vec3, bottom: Option<f64>) -> f64 {
    if w[2] > 0.0 {
        -z / w[2]
    } else if let (Some(zb), true) = (bottom, w[2] < 0.0) {
        (zb - z) / w[2]
    } else {
        f64::INFINITY
    }
}

/// Moves to the wall `to_wall` away and reflects there with probability
/// F(|w_z|) decided by `b` (`Reflected`), or leaves (`Left`).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn hit_wall(
    x: &mut f64,
    y: &mut f64,
    z: &mut f64,
    w: &mut Vec3,
    to_wall: f64,
    bottom: Option<f64>,
    b: u32,
    inv_eta: f64,
) -> Wall {
    *x += w[0] * to_wall;
    *y += w[1] * to_wall;
    let at_top = w[2] > 0.0;
    *z = if at_top { 0.0 } else { bottom.unwrap_or(0.0) };
    if unit_f64(b) < fresnel_dielectric(w[2].abs(), inv_eta) {
        w[2] = -w[2];
        return Wall::Reflected;
    }
    Wall::Left(if at_top {
        Fate::Exit { x: *x, y: *y }
    } else {
        Fate::Transmitted
    })
}

/// Protocol step 3 at a real collision at `p`: absorbed if b ≥ α·2³²
/// (`Some(Absorbed)`), else a scattering vertex (counted, `visit`ed with the
/// arrival direction; `Some(Truncated)` at `max_events`) that turns `w` by
/// the HG cos θ from `u_hg` and the azimuth φ = 2π(b + ½)/t (b is uniform
/// below the local threshold t). `None`: the walk goes on.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn collide<A: AlbedoField>(
    albedo: &A,
    g: f64,
    p: Vec3,
    w: &mut Vec3,
    b: u32,
    u_hg: f64,
    n: &mut u32,
    max_events: u32,
    visit: &mut impl FnMut(Vec3, Vec3),
) -> Option<Fate> {
    let alpha_threshold = albedo.threshold(p[0], p[1]);
    if (b as u64) >= alpha_threshold {
        return Some(Fate::Absorbed);
    }
    *n += 1;
    visit(p, *w);
    if *n >= max_events {
        return Some(Fate::Truncated);
    }
    let cos_theta = sample_hg_cos(g, u_hg);
    let phi = 2.0 * PI * (b as f64 + 0.5) / alpha_threshold as f64;
    *w = rotate_direction(*w, cos_theta, phi);
    None
}

/// Walks one launched path to its end; returns the fate and the number of
/// scattering events.
pub fn walk(medium: &Medium, max_events: u32, start: Launched, rng: &mut PathRng) -> (Fate, u32) {
    let albedo = UniformAlbedo(threshold_u32(medium.alpha));
    walk_general(medium, &albedo, max_events, start, rng, |_, _| {})
}

/// The walk with the albedo read from `albedo` at every collision (the
/// medium's own `alpha` is ignored) and `visit` called with the position of
/// every scattering vertex and the direction the path arrived in, in order.
/// Density stays homogeneous (σ_t of `medium`). The stream is consumed
/// exactly as by [`walk`]: with a uniform field both give the same path. The
/// azimuth φ = 2π(b + ½)/t uses the local threshold t, below which b is
/// uniform, so it stays exact.
#[inline]
pub fn walk_general<A: AlbedoField>(
    medium: &Medium,
    albedo: &A,
    max_events: u32,
    start: Launched,
    rng: &mut PathRng,
    visit: impl FnMut(Vec3, Vec3),
) -> (Fate, u32) {
    let (fate, n, _) = walk_transformed(
        medium,
        albedo,
        max_events,
        &FlightSampler::ANALOG,
        start,
        rng,
        visit,
    );
    (fate, n)
}

/// How [`walk_transformed`] draws free flights: at rate
/// σ' = σ_t·stretch·(1 − bias·μ), with μ the cosine between the flight's
/// direction and the horizontal direction away from the entry axis (on the
/// axis, its own horizontal direction: μ = sin θ). `stretch` < 1 lengthens every flight; `bias` > 0 lengthens the
/// flights that lead away from x_i and shortens those that lead back (the
/// exponential transform), so paths reach far exit points without more
/// scatterings. The first `forced` collisions always scatter (survival
/// biasing, ratio α each), so that at low albedo paths live long enough to
/// be multiple scattering.
///
/// With `angular` set, the scattering directions are biased too: at every
/// collision off the entry axis a new direction ω′ is drawn ∝
/// p_HG(ω·ω′)/(1 − bias·μ′) ([`AngularBias`]), a path survives a
/// collision with probability min(1, α·N(ν)) instead of α, and each flight's
/// optical depth follows the radius exactly, σ_t(s − bias·(r(s) − r₀)), so
/// that its ratio is e^(−σ_t·bias·Δr)/(1 − bias·ν) with ν the radial cosine
/// where it ends. Each sampled (1 − bias·μ′) then meets the next flight's
/// 1/(1 − bias·ν) (equal unless the flight turns about the axis), so a
/// path's ratio is near e^(−bias·σ_t·r) for every path that reaches r below
/// the medium's decay rate (α·N < 1; at g = 0, α·N = 1 at bias = κ,
/// [`max_bias`]). That is the exponential transform with angular biasing
/// (Spanier & Gelbard 1969, §3.5; Dwivedi 1982), which keeps the weights of
/// deep paths near-constant where the transform alone leaves them
/// heavy-tailed.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Flights {
    pub stretch: f64,
    pub bias: f64,
    #[serde(default)]
    pub forced: u32,
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub angular: bool,
}

impl Flights {
    /// The analog walk's flights.
    pub const ANALOG: Flights = Flights {
        stretch: 1.0,
        bias: 0.0,
        forced: 0,
        angular: false,
    };

    /// Whether the path weights of these flights keep a finite variance over
    /// long paths in a medium of albedo `albedo` and HG parameter `g`: the
    /// exponential transform's bias must stay below [`max_bias`] and the
    /// stretch within [`max_stretch_offset`] of 1. A sampling that both
    /// stretches and biases is judged by each bound on its own.
    pub fn bounded_weights(&self, albedo: f64, g: f64) -> bool {
        (self.bias == 0.0 || self.bias < max_bias(albedo, g))
            && (self.stretch == 1.0 || (self.stretch - 1.0).abs() < max_stretch_offset(albedo))
    }
}

/// The largest |c − 1| of flights stretched by c (drawn at rate c·σ_t,
/// [`walk_transformed`]) whose path weights keep a finite second moment at
/// albedo `albedo`: √(1 − α). Dimensionless.
///
/// A flight of length s drawn at rate cσ_t weighs w = e^((c − 1)σ_t s)/c,
/// and E\[w²\] = ∫ cσ_t e^(−cσ_t s) w² ds = 1/(c(2 − c)) for c < 2 (infinite
/// from c = 2 on). A path goes on after a collision with probability α, so
/// the second moment of its weight, Σ_n (α/(c(2 − c)))^n, is finite only
/// if c(2 − c) > α, that is |c − 1| < √(1 − α). The flights' directions do
/// not enter, so the bound holds for any phase function. It is the
/// stretch's counterpart of [`max_bias`] (the same argument as Spanier &
/// Gelbard 1969, §3.5, for the exponential transform).
pub fn max_stretch_offset(albedo: f64) -> f64 {
    (1.0 - albedo).max(0.0).sqrt()
}

/// The largest bias β of the exponential transform (flights at rate
/// σ_t(1 − βμ), [`walk_transformed`]) whose path weights keep a finite
/// second moment at albedo `albedo` and HG parameter `g`, in units of σ_t:
///
///   β_max = (1 − αg)·κ(α′),  α′ = α(1 − g)/(1 − αg).
///
/// A flight along μ drawn at rate σ_t(1 − βμ) weighs w = e^(−σ_tβμs)/(1 − βμ),
/// with E[w² | μ] = 1/(1 − β²μ²); over isotropic directions (μ uniform on
/// [−1, 1]) that is artanh(β)/β. A path goes on after a collision with
/// probability α, so the second moment of its weight, Σ_n (α·artanh(β)/β)^n,
/// is finite only if α·artanh(β)/β < 1: β below κ, the root of the
/// dispersion relation of isotropic scattering (α/κ)·artanh(κ) = 1, which is
/// the flux's asymptotic decay rate in units of σ_t (Case & Zweifel 1967).
/// With anisotropic scattering the directions of successive flights are
/// correlated, so a path compounds more outward flights; the similarity
/// relations (Wyman, Patterson & Wilson 1989) carry that in, as the
/// isotropic medium of albedo α′ and σ_t′ = (1 − αg)σ_t. Dimensionless.
pub fn max_bias(albedo: f64, g: f64) -> f64 {
    let a = (albedo * (1.0 - g) / (1.0 - albedo * g)).clamp(0.0, 1.0);
    // f(κ) = a·artanh(κ)/κ − 1 rises from a − 1 ≤ 0 at κ = 0 to +∞ at κ = 1.
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    for _ in 0..60 {
        let k = 0.5 * (lo + hi);
        if a * k.atanh() / k < 1.0 {
            lo = k;
        } else {
            hi = k;
        }
    }
    (1.0 - albedo * g) * lo
}

/// The angular half of [`Flights::angular`]: scattering directions drawn ∝
/// p_HG(ω·ω′)/(1 − βμ′), with μ′ = ω′·e the cosine to the horizontal
/// direction e away from the entry axis at the collision, and the
/// normalization N(ν) of that density for an incoming direction with ν = ω·e.
///
/// N follows from Heine's expansion 1/(z − x) = Σ_l (2l + 1) P_l(x) Q_l(z)
/// (Q_l the Legendre functions of the second kind) at z = 1/β, and from
/// ∫ p_HG(ω·ω′) P_l(ω′·e) dω′ = g^l P_l(ω·e) (Funk–Hecke):
///
///   N(ν) = (1/β) Σ_l (2l + 1) Q_l(1/β) g^l P_l(ν),  Q_0(1/β) = artanh β,
///
/// with the ratios Q_l/Q_(l−1) from the backward recurrence (the minimal
/// solution; Gautschi 1967, "Computational aspects of three-term recurrence
/// relations"). At g = 0 it is artanh(β)/β. Dimensionless.
#[derive(Clone, Debug)]
pub struct AngularBias {
    beta: f64,
    g: f64,
    /// (2l + 1) Q_l(1/β) g^l / β, up to the order where the terms fall below
    /// 10⁻¹⁷ of the first.
    coef: Vec<f64>,
}

impl AngularBias {
    pub fn new(beta: f64, g: f64) -> Self {
        assert!(beta > 0.0 && beta < 1.0 && g.abs() < 1.0, "β {beta}, g {g}");
        let z = 1.0 / beta;
        // Order of the last term kept: (2l + 1)|g|^l < 10⁻¹⁷.
        let mut order = 0usize;
        while order < 4000 && (2 * order + 1) as f64 * g.abs().powi(order as i32) >= 1e-17 {
            order += 1;
        }
        // Backward recurrence for R_l = Q_l/Q_(l−1): (l + 1)Q_(l+1) =
        // (2l + 1)zQ_l − lQ_(l−1) gives R_l = l/((2l + 1)z − (l + 1)R_(l+1)).
        // Started far enough above `order` that the dominant solution's
        // share, r^(2(M − l)) with r = z − √(z² − 1), is below 10⁻¹⁸.
        let r = z - (z * z - 1.0).sqrt();
        let extra = (41.5 / (-r.ln()) / 2.0).ceil() as usize + 8;
        let top = order + extra;
        let mut ratio = vec![0.0; top + 2];
        for l in (1..=top).rev() {
            let lf = l as f64;
            ratio[l] = lf / ((2.0 * lf + 1.0) * z - (lf + 1.0) * ratio[l + 1]);
        }
        let mut q = beta.atanh();
        let mut gl = 1.0;
        let mut coef = Vec::with_capacity(order + 1);
        for (l, rl) in ratio.iter().enumerate().take(order + 1) {
            if l > 0 {
                q *= rl;
                gl *= g;
            }
            coef.push((2 * l + 1) as f64 * q * gl / beta);
        }
        AngularBias { beta, g, coef }
    }

    /// N(ν) = ∫ p_HG(ω·ω′)/(1 − βω′·e) dω′ for ν = ω·e.
    pub fn norm(&self, nu: f64) -> f64 {
        let (mut p0, mut p1) = (1.0, nu);
        let mut sum = self.coef[0];
        for (l, c) in self.coef.iter().enumerate().skip(1) {
            sum += c * p1;
            let lf = l as f64;
            let p2 = ((2.0 * lf + 1.0) * nu * p1 - lf * p0) / (lf + 1.0);
            (p0, p1) = (p1, p2);
        }
        sum
    }

    /// Draws the direction after a scattering at horizontal position (x, y)
    /// (r > 0), arriving along `w_in` with `norm` = N(ν), by rejection from
    /// the phase function:
    /// `first` is the phase function's own draw, each retry draws cos θ, φ
    /// and then the acceptance number from `rng`; a proposal ω′ is kept with
    /// probability (1 − β)/(1 − βμ′). Returns ω′ and ln of the analog pdf
    /// over this one, ln(N(ν)(1 − βμ′)).
    pub fn sample(
        &self,
        x: f64,
        y: f64,
        norm: f64,
        w_in: Vec3,
        first: Vec3,
        rng: &mut PathRng,
    ) -> (Vec3, f64) {
        let r = x.hypot(y);
        let (ex, ey) = (x / r, y / r);
        let mut w = first;
        loop {
            let mu = w[0] * ex + w[1] * ey;
            let keep = (1.0 - self.beta) / (1.0 - self.beta * mu);
            if unit_f64(rng.next_u32()) < keep {
                return (w, (norm * (1.0 - self.beta * mu)).ln());
            }
            let cos_theta = sample_hg_cos(self.g, unit_f64(rng.next_u32()));
            let phi = 2.0 * PI * unit_f64(rng.next_u32());
            w = rotate_direction(w_in, cos_theta, phi);
        }
    }
}

/// The cosine between `w` and the horizontal direction away from the entry
/// axis at (x, y); on the axis, the direction's own horizontal part |w_h|.
#[inline]
fn radial_cosine(x: f64, y: f64, w: &Vec3) -> f64 {
    let r = x.hypot(y);
    if r > 1e-12 {
        (w[0] * x + w[1] * y) / r
    } else {
        w[0].hypot(w[1])
    }
}

/// The length s of a flight from horizontal position (x, y) along `w` whose
/// radially transformed optical depth s − β(r(s) − r₀) (in MFP, r(s) the
/// distance from the entry axis after s) is `tau`. The depth rises with s
/// at rate 1 − βν(s) ≥ 1 − β (ν the radial cosine) and is concave (r(s) is
/// convex), so Newton's method from s₀ = τ/(1 + β|w_h|), where the depth is
/// at most τ, climbs to the root without overshooting.
fn radial_flight(x: f64, y: f64, w: &Vec3, beta: f64, tau: f64) -> f64 {
    let r0 = x.hypot(y);
    let mut s = tau / (1.0 + beta * w[0].hypot(w[1]));
    for _ in 0..64 {
        let (px, py) = (x + w[0] * s, y + w[1] * s);
        let r = px.hypot(py);
        let nu = if r > 1e-300 {
            (px * w[0] + py * w[1]) / r
        } else {
            0.0
        };
        let f = s - beta * (r - r0) - tau;
        let step = -f / (1.0 - beta * nu);
        s += step;
        if step.abs() <= 1e-14 * s.max(1e-300) {
            break;
        }
    }
    s
}

/// [`Flights`] ready to walk in a medium: with `angular`, the normalization
/// of its direction density at the medium's g, computed once.
#[derive(Clone, Debug)]
pub struct FlightSampler {
    pub flights: Flights,
    angular: Option<AngularBias>,
}

impl FlightSampler {
    /// The analog walk's flights and directions.
    pub const ANALOG: FlightSampler = FlightSampler {
        flights: Flights::ANALOG,
        angular: None,
    };

    pub fn new(flights: Flights, g: f64) -> Self {
        let angular =
            (flights.angular && flights.bias > 0.0).then(|| AngularBias::new(flights.bias, g));
        FlightSampler { flights, angular }
    }
}

/// The walk of [`walk_general`] with its free flights (and, with
/// [`Flights::angular`], its directions) drawn as `sampler` says,
/// absorption and scattering analog except at forced collisions.
/// Returns the fate, the number of scatterings and ln r, with r the path's
/// probability under the analog walk over its probability under this one,
///
/// ln r = Σ_collisions [ln(σ_t/σ') − (σ_t − σ')s] − Σ_walls (σ_t − σ')s + Σ_forced ln α,
///
/// and with [`Flights::angular`]
///
/// ln r = −σ_tβ·r_end − Σ_collisions ln(1 − βν) + Σ_biased collisions [ln(α/q) + ln(N(ν)(1 − βμ′))],
///
/// q = min(1, αN(ν)) (on the axis, directions and survival stay analog).
///
/// Weighting each path by r makes any tally unbiased for the analog one
/// (Spanier & Gelbard, *Monte Carlo Principles and Neutron Transport
/// Problems*, 1969, §3.5, the exponential transformation). With
/// [`Flights::ANALOG`] the draws and positions are those of [`walk_general`]
/// exactly and ln r = 0.
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn walk_transformed<A: AlbedoField>(
    medium: &Medium,
    albedo: &A,
    max_events: u32,
    sampler: &FlightSampler,
    start: Launched,
    rng: &mut PathRng,
    mut visit: impl FnMut(Vec3, Vec3),
) -> (Fate, u32, f64) {
    let flights = sampler.flights;
    debug_assert!(sampler.angular.as_ref().is_none_or(|a| a.g == medium.g));
    // With the angular bias the transform follows the radius exactly:
    // optical depth σ_t(s − β(r(s) − r₀)) ([`radial_flight`]).
    let radial = sampler.angular.is_some();
    let sigma_t = medium.sigma_t();
    let analog = flights == Flights::ANALOG;
    let inv_eta = 1.0 / medium.eta;
    let bottom = medium.thickness.map(|l| -l);
    let [mut x, mut y, mut z] = start.position;
    let mut w = start.direction;
    let mut n = 0u32;
    let mut log_ratio = 0.0;
    loop {
        let (a, b, c) = (rng.next_u32(), rng.next_u32(), rng.next_u32());
        // ---- free flight ----------------------------------------------------
        let r0 = if radial { x.hypot(y) } else { 0.0 };
        let sigma = if analog || radial {
            sigma_t
        } else {
            sigma_t * flights.stretch * (1.0 - flights.bias * radial_cosine(x, y, &w))
        };
        let s = if radial {
            radial_flight(x, y, &w, flights.bias, -unit_open0_f64(a).ln() / sigma_t)
        } else {
            -unit_open0_f64(a).ln() / sigma
        };
        // ---- boundary: surface (w_z > 0) or slab bottom (w_z < 0) ------------
        let to_wall = wall_distance(z, &w, bottom);
        if s >= to_wall {
            if radial {
                let r = (x + w[0] * to_wall).hypot(y + w[1] * to_wall);
                log_ratio -= sigma_t * flights.bias * (r - r0);
            } else if !analog {
                log_ratio -= (sigma_t - sigma) * to_wall;
            }
            match hit_wall(&mut x, &mut y, &mut z, &mut w, to_wall, bottom, b, inv_eta) {
                Wall::Missed | Wall::Reflected => continue,
                Wall::Left(fate) => return (fate, n, log_ratio),
            }
        }
        if !analog && !radial {
            log_ratio += (sigma_t / sigma).ln() - (sigma_t - sigma) * s;
        }
        x += w[0] * s;
        y += w[1] * s;
        z += w[2] * s;
        // The radial cosine where the flight ends: the incoming ν of the
        // collision (needed only with the angular bias).
        let nu = if radial { radial_cosine(x, y, &w) } else { 0.0 };
        if radial {
            log_ratio -=
                sigma_t * flights.bias * (x.hypot(y) - r0) + (1.0 - flights.bias * nu).ln();
        }
        // ---- collision: absorb or scatter -----------------------------------
        let p = [x, y, z];
        // Off the axis, the angular bias weighs the survival too: the path
        // goes on with probability q = min(1, α·N(ν)) (ratio α/q), so that
        // a survivor's ratio stays e^(−σ_t·bias·Δr) per step wherever
        // α·N ≤ 1, and paths that the bias would otherwise keep walking
        // indefinitely (α·N ≥ 1 makes the biased walk critical) end.
        let angular = sampler.angular.as_ref().filter(|_| x.hypot(y) > 1e-12);
        let mut norm = 1.0;
        let b = if n < flights.forced || angular.is_some() {
            // Forced to scatter: b uniform below the local threshold t (so
            // the azimuth stays exact), ratio α = t/2³².
            let t = albedo.threshold(p[0], p[1]);
            if t == 0 {
                return (Fate::Absorbed, n, log_ratio);
            }
            let alpha = t as f64 / 4294967296.0;
            if let Some(bias) = angular {
                norm = bias.norm(nu);
                let q = (alpha * norm).min(1.0);
                if unit_f64(rng.next_u32()) >= q {
                    return (Fate::Absorbed, n, log_ratio);
                }
                log_ratio += (alpha / q).ln();
            } else {
                log_ratio += alpha.ln();
            }
            ((b as u64 * t) >> 32) as u32
        } else {
            b
        };
        let w_in = w;
        if let Some(end) = collide(
            albedo,
            medium.g,
            p,
            &mut w,
            b,
            unit_f64(c),
            &mut n,
            max_events,
            &mut visit,
        ) {
            return (end, n, log_ratio);
        }
        // Off the axis, the angular bias redraws the direction, starting
        // from the phase function's own draw (on it, e is undefined: the
        // direction stays analog, which is exact).
        if let Some(bias) = angular {
            let (dir, ln_ratio) = bias.sample(x, y, norm, w_in, w, rng);
            w = dir;
            log_ratio += ln_ratio;
        }
    }
}

/// Where the walk reads the density ρ(x, y) (2.5D, piecewise constant) and
/// its majorant ρ_max ≥ ρ everywhere (for delta tracking).
pub trait DensityField {
    fn density(&self, x: f64, y: f64) -> f64;
    fn majorant(&self) -> f64;
}

/// The walk through a heterogeneous medium: albedo from `albedo`, density
/// from `density` (σ_t = ρ(x, y)), phase, η and slab thickness from `medium`.
///
/// # Delta tracking (Woodcock), unbiased
/// Flights are sampled with the majorant σ̄ = ρ_max: s = −ln u_a/σ̄. A
/// tentative collision at x is real with probability p = ρ(x)/σ̄, decided by
/// u_c < p; otherwise it is a null collision and the path flies on unchanged
/// (memorylessness makes this exact for any piecewise-constant ρ ≤ σ̄). At a
/// real collision u_c/p is again uniform on [0, 1) and drives the HG
/// sampling; b decides absorption and the azimuth exactly as in [`walk`].
/// Every step (real, null or wall) consumes one triple (a, b, c). With a
/// constant density the walk is bitwise [`walk_general`] at that density.
pub fn walk_delta<A: AlbedoField, D: DensityField>(
    medium: &Medium,
    albedo: &A,
    density: &D,
    max_events: u32,
    start: Launched,
    rng: &mut PathRng,
    mut visit: impl FnMut(Vec3, Vec3),
) -> (Fate, u32) {
    let sigma_bar = density.majorant();
    let inv_eta = 1.0 / medium.eta;
    let bottom = medium.thickness.map(|l| -l);
    let [mut x, mut y, mut z] = start.position;
    let mut w = start.direction;
    let mut n = 0u32;
    let mut steps = 0u64;
    let max_steps = max_tracking_steps(max_events);
    loop {
        steps += 1;
        if steps > max_steps {
            return (Fate::Truncated, n);
        }
        let (a, b, c) = (rng.next_u32(), rng.next_u32(), rng.next_u32());
        let s = -unit_open0_f64(a).ln() / sigma_bar;
        match wall(&mut x, &mut y, &mut z, &mut w, s, bottom, b, inv_eta) {
            Wall::Missed => {}
            Wall::Reflected => continue,
            Wall::Left(fate) => return (fate, n),
        }
        x += w[0] * s;
        y += w[1] * s;
        z += w[2] * s;
        let p = density.density(x, y) / sigma_bar;
        let uc = unit_f64(c);
        if uc >= p {
            continue; // null collision
        }
        // u_c/p is again uniform on [0, 1) at a real collision.
        if let Some(end) = collide(
            albedo,
            medium.g,
            [x, y, z],
            &mut w,
            b,
            uc / p,
            &mut n,
            max_events,
            &mut visit,
        ) {
            return (end, n);
        }
    }
}

/// The step cap of the walks with null collisions ([`walk_delta`],
/// [`walk_grid`]): a path in vanishing density would otherwise take ≈ ρ_maj/ρ
/// steps per real collision, so steps (real, null or wall) are bounded by 64×
/// the event cap (plus 10⁶); a path that reaches it is truncated.
#[inline]
fn max_tracking_steps(max_events: u32) -> u64 {
    64 * max_events as u64 + 1_000_000
}

/// Free flight through a piecewise-constant 2.5D density map by regular
/// (exact) tracking: from (x, y) along the horizontal part (w_x, w_y) of a
/// unit direction, the distance s at which the optical depth ∫ρ ds reaches
/// `depth`, crossing texel columns one by one (ρ is constant along z within
/// a column, so only the vertical texel faces matter); (i, j) is the texel
/// (row, column) of (x, y) ([`TexelMap::texel_of`]). Returns
/// `Some((s, ρ))` with the density of the texel where the depth runs out, or
/// `None` if the flight reaches `s_max` (the wall) first. Cost ∝ texel faces
/// crossed (face distances from one reciprocal of w_x and w_y per flight);
/// the edge texels extend to infinity.
#[inline]
pub fn track_flight(
    map: &TexelMap,
    (i, j): (usize, usize),
    (x, y): (f64, f64),
    (wx, wy): (f64, f64),
    depth: f64,
    s_max: f64,
) -> Option<(f64, f64)> {
    let (nx, ny, tau) = (map.nx, map.ny, map.texel);
    if nx == 1 && ny == 1 {
        // No faces: the loop below in one step, without its set-up.
        let rho = map.values[0];
        return (rho * s_max >= depth).then(|| (depth / rho, rho));
    }
    let left = -0.5 * nx as f64 * tau;
    let top = 0.5 * ny as f64 * tau;
    let (inv_wx, inv_wy) = (1.0 / wx, 1.0 / wy);
    let (mut i, mut j) = (i, j);
    let (mut s, mut remaining) = (0.0f64, depth);
    // The next face ahead: column j + 1 (w_x > 0) or j; row i (w_y > 0,
    // toward +y) or i + 1. Selected without branches on the direction.
    let (ahead_j, ahead_i) = (usize::from(wx > 0.0), usize::from(wy <= 0.0));
    loop {
        let rho = map.values[i * nx + j];
        // Distance (from the start) to the next face in x and in y, if any
        // (none where the direction is parallel or the map ends).
        let sx = (left + (j + ahead_j) as f64 * tau - x) * inv_wx;
        let has_x = (wx > 0.0 && j + 1 < nx) || (wx < 0.0 && j >= 1);
        let sx = if has_x { sx } else { f64::INFINITY };
        let sy = (top - (i + ahead_i) as f64 * tau - y) * inv_wy;
        let has_y = (wy > 0.0 && i >= 1) || (wy < 0.0 && i + 1 < ny);
        let sy = if has_y { sy } else { f64::INFINITY };
        let next = sx.min(sy).min(s_max).max(s);
        let seg = next - s;
        if rho * seg >= remaining {
            return Some((s + remaining / rho, rho));
        }
        if next >= s_max {
            return None;
        }
        remaining -= rho * seg;
        s = next;
        if sx <= sy {
            j = if wx > 0.0 { j + 1 } else { j - 1 };
        } else {
            i = if wy > 0.0 { i - 1 } else { i + 1 };
        }
    }
}

/// The walk through a heterogeneous medium tracked on a [`MajorantGrid`]:
/// regular tracking through the grid's cells against their majorants
/// ([`track_flight`] on the majorant map), delta tracking within a cell.
///
/// # Step protocol and unbiasedness
/// Every step draws (a, b, c) as in [`walk`]: optical depth −ln u_a against
/// the cell majorants; the tentative collision at x is real with probability
/// p = ρ(x)/ρ_maj(x), decided by u_c < p, and then u_c/p (again uniform on
/// [0, 1)) drives the HG sampling while b decides absorption and the azimuth;
/// a null collision continues the flight with the next triple (memoryless
/// exponential, exact for any ρ ≤ ρ_maj: Woodcock tracking with a piecewise
/// constant majorant). A wall reached first reflects or leaves by b.
/// With one cell per texel p = 1: plain regular (exact) tracking, whatever
/// the density contrast; with one cell for the whole map, delta tracking
/// against ρ_max. With a constant density in one cell it is
/// [`walk_general`] at that density (the wall test rounds differently:
/// ρ·d_wall ≥ depth instead of depth/ρ < d_wall; tested equal vertex by
/// vertex on 20 000 paths). Steps are capped
/// like [`walk_delta`]'s (64 × the event cap).
pub fn walk_grid<A: AlbedoField>(
    medium: &Medium,
    albedo: &A,
    grid: &MajorantGrid,
    max_events: u32,
    start: Launched,
    rng: &mut PathRng,
    mut visit: impl FnMut(Vec3, Vec3),
) -> (Fate, u32) {
    let inv_eta = 1.0 / medium.eta;
    let bottom = medium.thickness.map(|l| -l);
    let [mut x, mut y, mut z] = start.position;
    let mut w = start.direction;
    let mut n = 0u32;
    let exact = grid.is_exact();
    let mut steps = 0u64;
    let max_steps = max_tracking_steps(max_events);
    loop {
        steps += 1;
        if steps > max_steps {
            return (Fate::Truncated, n);
        }
        let (a, b, c) = (rng.next_u32(), rng.next_u32(), rng.next_u32());
        let depth = -unit_open0_f64(a).ln();
        let to_wall = wall_distance(z, &w, bottom);
        let cell = grid.cell_of(x, y);
        let flight = track_flight(&grid.majorant, cell, (x, y), (w[0], w[1]), depth, to_wall);
        let Some((s, rho_maj)) = flight else {
            let hit = hit_wall(&mut x, &mut y, &mut z, &mut w, to_wall, bottom, b, inv_eta);
            match hit {
                Wall::Left(fate) => return (fate, n),
                _ => continue,
            }
        };
        x += w[0] * s;
        y += w[1] * s;
        z += w[2] * s;
        let uc = unit_f64(c);
        let u_hg = if exact {
            uc
        } else {
            // Real iff u_c < p = ρ/ρ_maj, tested without the division.
            let rho = grid.density_at(x, y);
            if uc * rho_maj >= rho {
                continue; // null collision
            }
            uc * rho_maj / rho
        };
        if let Some(end) = collide(
            albedo,
            medium.g,
            [x, y, z],
            &mut w,
            b,
            u_hg,
            &mut n,
            max_events,
            &mut visit,
        ) {
            return (end, n);
        }
    }
}

/// Adds one finished path to the tally (`bins`: the lookup of the tally's
/// [`RadialBins`](crate::forward::tally::RadialBins)).
#[inline]
pub fn record(tally: &mut ProfileTally, bins: &BinLookup, fate: Fate, events: u32) {
    tally.events += events as u64;
    match fate {
        Fate::Exit { x, y } => {
            let k = bins.index((x * x + y * y).sqrt());
            match events {
                0 => tally.exit_unscattered += 1,
                1 => tally.exit_single[k] += 1,
                _ => tally.exit_multi[k] += 1,
            }
        }
        Fate::Transmitted => tally.transmitted += 1,
        Fate::Absorbed => tally.absorbed += 1,
        Fate::Truncated => tally.truncated += 1,
    }
}

/// T(1)/η² (unitless): the radiance leaving along the normal per unit
/// radiance arriving at the surface along the normal from inside, with
/// T(1) = 1 − F(1) the normal Fresnel transmittance and 1/η² the change of
/// radiance across the interface (L/n² is invariant; Pharr et al., pbrt-v4
/// §11.2, "non-symmetric scattering and refraction").
pub fn normal_exit_factor(eta: f64) -> f64 {
    (1.0 - fresnel_dielectric(1.0, 1.0 / eta)) / (eta * eta)
}

/// Simulates paths `first..first + count` of the stream family `seed` with the
/// scalar walk and tallies them.
///
/// With `radiance` it also tallies the radiance along the normal by
/// next-event estimation: every scattering vertex at depth |z| with arrival
/// direction ω adds q = f_HG(ω·ẑ)·e^{−σ_t|z|}·T(1)/η² (sr⁻¹,
/// [`normal_exit_factor`]) to the radial bin of its horizontal distance
/// from the source point. The vertical ray to the surface stays inside the
/// medium, so e^{−σ_t|z|} is its exact transmittance (in a slab too). The
/// paths, their draws and so the exit counts are the same either way, and
/// without it no vertex is visited. The estimator is that of the
/// brute-force reference's radiance images ([`crate::render::reference`]).
#[allow(clippy::too_many_arguments)]
pub fn simulate_scalar(
    medium: &Medium,
    source: &Source,
    bins: &BinLookup,
    max_events: u32,
    seed: u64,
    first: u64,
    count: u64,
    radiance: bool,
) -> ProfileTally {
    let mut tally = ProfileTally::new(bins.bins());
    let mut nee = radiance.then(|| RadianceTally::new(bins.bins()));
    let albedo = UniformAlbedo(threshold_u32(medium.alpha));
    let exit = normal_exit_factor(medium.eta);
    let (g, sigma_t) = (medium.g, medium.sigma_t());
    let mut contrib: Vec<(usize, u128, bool)> = Vec::new();
    for path in first..first + count {
        tally.paths += 1;
        let mut rng = PathRng::new(seed, path);
        let Some(start) = launch(source, medium.eta, &mut rng) else {
            tally.specular += 1;
            continue;
        };
        let (fate, n) = match &mut nee {
            None => walk(medium, max_events, start, &mut rng),
            Some(nee) => {
                contrib.clear();
                let mut order = 0u32;
                let visit = |v: Vec3, w: Vec3| {
                    order += 1;
                    let q = hg_pdf(g, w[2]) * (-sigma_t * v[2].abs()).exp() * exit;
                    let bin = bins.index((v[0] * v[0] + v[1] * v[1]).sqrt());
                    contrib.push((bin, (q * RADIANCE_Q).round() as u128, order >= 2));
                };
                let end = walk_general(medium, &albedo, max_events, start, &mut rng, visit);
                nee.add_path(&mut contrib);
                end
            }
        };
        record(&mut tally, bins, fate, n);
    }
    tally.radiance = nee;
    tally
}
