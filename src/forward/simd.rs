//! The lane-parallel walk: eight paths at a time in f32 SIMD lanes (`wide`,
//! one AVX2 register per quantity).
//!
//! Each lane holds one path of the analog walk of [`super::walk`], and every
//! lane consumes its own xoshiro128++ stream in exactly the order of the
//! scalar walk (launch draws, then `a, b, c` per step, see the step protocol
//! in [`super::walk`]). The two engines therefore sample the same
//! distribution from the same streams; they differ only by rounding (f32
//! here, f64 there), so their tallies agree statistically but not bitwise (a
//! path whose f32 and f64 trajectories straddle a decision threshold ends
//! differently, and from then on its stream is used differently). The result
//! of a path range is a pure function of the range: it does not depend on
//! which lane a path runs in (ranges concatenate exactly, tested).
//!
//! # Structure
//!
//! * The hot loop (`Lanes::step`) is branch-free except for two branches:
//!   `if` some lane crosses the surface (or a slab's bottom), the wall
//!   distance and the Fresnel reflectance are evaluated for all lanes; `if`
//!   some lane ended, the ended lanes are tallied and refilled. No lane ever
//!   waits for another: a lane that ends is refilled at once.
//! * Launch, tally and refill are scalar and shared with the scalar walk
//!   ([`launch`], [`record`]): a lane that ends is tallied from its f32 state
//!   (converted to f64) and reloaded with the next path of the range; when the
//!   range is exhausted the lane goes idle (its results are masked out) and
//!   the loop ends once every lane is idle.
//! * ln and sin/cos are short minimax polynomials without range reduction
//!   (`free_flight`, `azimuth`); the HG inversion is rewritten without
//!   the 1/g cancellation (`HgLanes`).
//! * The order of the statements in `Lanes::step` matters (the compiler
//!   keeps it): starting the long dependency chains first made the step
//!   ≈ 15 % faster on the development machine.
//!
//! # Differences from the f64 walk (all far below the Monte Carlo noise)
//!
//! * **Free-flight tail.** u_a = (⌊a/2⁸⌋ + 1)·2⁻²⁴ ∈ (0, 1] has 24 bits, so
//!   the longest flight is 24·ln 2/σ_t ≈ 16.6/σ_t: flights longer than that
//!   (probability e^{−16.6} = 6·10⁻⁸ per flight) are shortened to it, and the
//!   exponential is sampled on a 2⁻²⁴ grid of u. The f64 walk's u_a has 32
//!   bits (longest flight 22.2/σ_t). −ln u_a is evaluated to ≈ 2·10⁻⁷
//!   relative (`free_flight`).
//! * **Uniforms** u_b (Fresnel decision) and u_c (HG) keep the top 23 bits
//!   of b and c (the mantissa of an f32 in [1, 2), `unit23`); the
//!   absorption decision compares all 32 bits of b with the integer
//!   threshold, as in the f64 walk, so every albedo (1 − 10⁻⁹ included) is
//!   exact, and the azimuth uses all 32 bits of b (`Walk::half_azimuth`).
//! * **Directions** are rotated in f32 (`Basis`) and never renormalised:
//!   the rotation contracts a norm error (the cos θ·w term carries it with
//!   weight |cos θ| < 1 on average), so rounding does not accumulate: over
//!   4·10⁵ scatterings of each of 8 paths at α = 1, ||w| − 1| stays below
//!   5·10⁻⁶ for g ∈ {0, 0.75, ±0.99} (tested against 10⁻⁵).
//! * **Positions** are f32: relative precision 6·10⁻⁸, i.e. 6·10⁻⁶ MFP at
//!   100 MFP from the origin, far below the radial bins' resolution.

use super::medium::{Medium, Source};
use super::rng::{PathRng, threshold_u32};
use super::sampling::HG_ISOTROPIC_G;
use super::tally::{BinLookup, ProfileTally};
use super::walk::{Fate, Launched, launch, record};
use std::f64::consts::{LN_2, PI};
use wide::bytemuck::cast;
use wide::{f32x8, i32x8, u32x8};

/// f32 lanes.
type F = f32x8;
/// u32 lanes (and lane masks of integer comparisons).
type U = u32x8;
/// i32 lanes.
type I = i32x8;

/// Paths walked side by side.
const LANES: usize = 8;

/// Converts i32 lanes to f32 (exact below 2²⁴).
#[inline(always)]
fn i2f(x: I) -> F {
    F::from_i32x8(x)
}

/// Reinterprets an integer lane mask as a float lane mask.
#[inline(always)]
fn fmask(m: U) -> F {
    cast(m)
}

/// Reinterprets a float lane mask as an integer lane mask.
#[inline(always)]
fn umask(m: F) -> U {
    cast(m)
}

/// Rotates each lane left by `k` bits (0 < k < 32).
#[inline(always)]
fn rotl(x: U, k: u32) -> U {
    x.unbounded_shl_scalar(k) | x.unbounded_shr_scalar(32 - k)
}

/// Eight xoshiro128++ generators, one per lane: lane `i` of `s[k]` is word
/// `k` of the state of [`PathRng`] `i`. [`LaneRng::next_u32`] is
/// [`PathRng::next_u32`] applied to every lane (Blackman & Vigna 2019), so a
/// lane's outputs are bitwise those of the scalar generator (tested).
#[derive(Clone, Copy, Debug, Default)]
struct LaneRng {
    s: [U; 4],
}

impl LaneRng {
    /// The next 32 random bits of every lane.
    #[inline(always)]
    fn next_u32(&mut self) -> U {
        let [s0, s1, s2, s3] = &mut self.s;
        let result = rotl(*s0 + *s3, 7) + *s0;
        let t = s1.unbounded_shl_scalar(9);
        *s2 ^= *s0;
        *s3 ^= *s1;
        *s1 ^= *s2;
        *s0 ^= *s3;
        *s2 ^= t;
        *s3 = rotl(*s3, 11);
        result
    }

    /// Puts the state of `rng` into lane `lane`.
    #[inline]
    fn set_lane(&mut self, lane: usize, rng: &PathRng) {
        for (v, &w) in self.s.iter_mut().zip(&rng.s) {
            v.as_mut_array()[lane] = w;
        }
    }
}

/// Bits of 1.0f32.
const ONE_BITS: u32 = 0x3F80_0000;

/// The top 23 bits of `x` as a uniform in [0, 1): the f32 with the exponent
/// of 1 and mantissa ⌊x/2⁹⌋ lies in [1, 2); subtracting 1 is exact. Costs
/// two integer operations and one addition (no int → float conversion).
#[inline(always)]
fn unit23(x: U) -> F {
    cast::<U, F>(x.unbounded_shr_scalar(9) | U::splat(ONE_BITS)) - F::ONE
}

/// Coefficients of 2·atanh(s)/s = 2(1 + s²/3 + s⁴/5 + …) as a cubic in s²,
/// minimax on s² ∈ [0, ((√2 − 1)/(√2 + 1))²] (Remez, relative error
/// 1.4·10⁻⁹).
const ATANH2: [f64; 4] = [
    1.999_999_998_614_441_2,
    0.666_668_163_719_932_9,
    0.399_747_567_787_823_3,
    0.299_265_145_395_889_1,
];

/// Free-flight length −ln(u)/σ_t of u = (⌊a/2⁸⌋ + 1)·2⁻²⁴ ∈ (0, 1].
///
/// # Formula
/// x = ⌊a/2⁸⌋ + 1 ∈ [1, 2²⁴] is exact in f32; split x = 2^e·m with
/// m ∈ [√½, √2) by integer operations on its bits (Cephes `logf`). Then
/// −ln u = (24 − e)·ln 2 − ln m and ln m = 2·atanh(s) with
/// s = (m − 1)/(m + 1) ∈ [−0.172, 0.172], by the polynomial [`ATANH2`]. The
/// constants carry the factor 1/σ_t ([`Walk::flight`]). Relative error
/// ≈ 2·10⁻⁷ (f32 rounding; the polynomial's is 1.4·10⁻⁹).
#[inline(always)]
fn free_flight(a: U, c: &FlightConsts) -> F {
    let x = i2f(a.unbounded_shr_scalar(8).cast_signed() + I::splat(1));
    let bits: I = cast(x);
    let e = (bits - I::splat(0x3F35_04F3)).unbounded_shr_scalar(23); // arithmetic
    let m: F = cast(bits - e.unbounded_shl_scalar(23));
    let s = (m - F::ONE) / (m + F::ONE);
    let s2 = s * s;
    let p = c.p[3]
        .mul_add(s2, c.p[2])
        .mul_add(s2, c.p[1])
        .mul_add(s2, c.p[0]);
    s.mul_add(p, i2f(I::splat(24) - e) * c.ln2)
}

/// Constants of [`free_flight`] for one σ_t.
#[derive(Clone, Copy, Debug)]
struct FlightConsts {
    /// −[`ATANH2`]/σ_t.
    p: [F; 4],
    /// ln 2/σ_t.
    ln2: F,
}

impl FlightConsts {
    fn new(sigma_t: f64) -> Self {
        FlightConsts {
            p: ATANH2.map(|c| F::splat((-c / sigma_t) as f32)),
            ln2: F::splat((LN_2 / sigma_t) as f32),
        }
    }
}

/// Henyey–Greenstein cos θ from 32 random bits, eight lanes, without
/// division by g.
///
/// # Formula
/// The inversion of [`super::sampling::sample_hg_cos`],
/// cos θ = (1 + g² − ((1 − g²)/(1 − g + 2gu))²)/(2g) [PBRT4 §11.3.1], with
/// D = 1 − g + 2gu multiplied out is
///
/// cos θ = (−(1 − g)² + 2(1 + g²)(1 − g)·u + 2g(1 + g²)·u²) / D²,
///
/// which for g ≥ 0 has no cancellation (the closed form loses all digits of
/// f32 as g → 0; this one tends to 2u − 1). For g < 0 the mirror identity
/// cos θ(g, u) = −cos θ(|g|, 1 − u) keeps g ≥ 0 in the polynomial. For
/// |g| < [`HG_ISOTROPIC_G`] the scalar walk uses cos θ = 1 − 2u, which is
/// −(the polynomial at g = 0). All cases run the same branch-free code: u is
/// [`unit23`] of c or, for g < 0, 1 − u (exact, from the integer 2²³ − ⌊c/2⁹⌋),
/// and the sign goes into the coefficients.
#[derive(Clone, Copy, Debug)]
struct HgLanes {
    /// Bits of 1 + u: (⌊c/2⁹⌋ ^ k_xor) + k_add.
    k_xor: U,
    k_add: U,
    /// Numerator ±(p0 + p1·u + p2·u²).
    p0: F,
    p1: F,
    p2: F,
    /// D = d0 + d1·u.
    d0: F,
    d1: F,
}

impl HgLanes {
    fn new(g: f64) -> Self {
        // (|g| used in the polynomial, flip u, sign of cos θ)
        let (g, flip, sign) = if g.abs() < HG_ISOTROPIC_G {
            (0.0, false, -1.0)
        } else if g < 0.0 {
            (-g, true, -1.0)
        } else {
            (g, false, 1.0)
        };
        let s = |v: f64| F::splat(v as f32);
        HgLanes {
            // flip: (k ^ !0) + 2²³ + 1 = 2²³ − k (wrapping), so 1 + u = 2 − k·2⁻²³.
            k_xor: U::splat(if flip { u32::MAX } else { 0 }),
            k_add: U::splat(if flip {
                ONE_BITS + (1 << 23) + 1
            } else {
                ONE_BITS
            }),
            p0: s(-sign * (1.0 - g) * (1.0 - g)),
            p1: s(sign * 2.0 * (1.0 + g * g) * (1.0 - g)),
            p2: s(sign * 2.0 * g * (1.0 + g * g)),
            d0: s(1.0 - g),
            d1: s(2.0 * g),
        }
    }

    /// The uniform u ∈ [0, 1) of `c` (for g < 0: 1 − u ∈ (0, 1]).
    #[inline(always)]
    fn uniform(&self, c: U) -> F {
        let k = (c.unbounded_shr_scalar(9) ^ self.k_xor) + self.k_add;
        cast::<U, F>(k) - F::ONE
    }

    /// cos θ in [−1, 1] from the random bits `c`.
    #[inline(always)]
    fn cos_theta(&self, c: U) -> F {
        let u = self.uniform(c);
        let p = self.p2.mul_add(u, self.p1).mul_add(u, self.p0);
        let d = self.d1.mul_add(u, self.d0);
        (p / (d * d)).fast_clamp(F::splat(-1.0), F::ONE)
    }
}

/// Minimax coefficients (Remez on h² ∈ [0, (π/2)²]) of sin h = h·S(h²)
/// (relative error 4·10⁻⁹) and cos h = C(h²) (absolute error 5·10⁻⁸).
const SIN_H: [f64; 5] = [
    0.999_999_995_732_802_8,
    -0.166_666_579_919_142_4,
    0.008_333_051_063_454_765,
    -0.000_198_090_752_919_418_67,
    2.605_224_917_255_694_4e-6,
];
const COS_H: [f64; 5] = [
    0.999_999_953_466_670_9,
    -0.499_999_053_470_766_84,
    0.041_663_584_693_106_7,
    -0.001_385_370_430_823_467_5,
    2.315_393_165_927_304_8e-5,
];

/// (cos φ, sin φ) from the half angle h = (φ − π)/2 ∈ [−π/2, π/2].
///
/// # Formula
/// sin h and cos h by the polynomials [`SIN_H`], [`COS_H`], then
/// sin φ = −sin 2h = −2 sin h cos h and cos φ = −cos 2h = 2 sin²h − 1.
/// Branch-free and free of range reduction, unlike a general sin/cos.
#[inline(always)]
fn azimuth(h: F) -> (F, F) {
    let s = |v: f64| F::splat(v as f32);
    let h2 = h * h;
    let sin_h = s(SIN_H[4])
        .mul_add(h2, s(SIN_H[3]))
        .mul_add(h2, s(SIN_H[2]))
        .mul_add(h2, s(SIN_H[1]))
        .mul_add(h2, s(SIN_H[0]))
        * h;
    let cos_h = s(COS_H[4])
        .mul_add(h2, s(COS_H[3]))
        .mul_add(h2, s(COS_H[2]))
        .mul_add(h2, s(COS_H[1]))
        .mul_add(h2, s(COS_H[0]));
    let two_sin_h = sin_h + sin_h;
    let cos_phi = two_sin_h.mul_add(sin_h, F::splat(-1.0));
    let sin_phi = -(two_sin_h * cos_h);
    (cos_phi, sin_phi)
}

/// Sign bit of f32 lanes.
const SIGN_BIT: u32 = 0x8000_0000;

/// The orthonormal basis (t₁, t₂, w) of Duff et al. 2017 ("Building an
/// orthonormal basis, revisited"), branch-free, as in
/// [`super::sampling::rotate_direction`], eight lanes.
///
/// # Formula
/// With s = sign(w_z), r = 1/(s + w_z) (Duff's a = −r) and m = w_x·w_y:
/// t₁ = (1 − s·r·w_x², −s·r·m, −s·w_x), t₂ = (−r·m, s − r·w_y², −w_y).
/// Only the non-trivial components are kept; sign flips are bit operations.
/// It depends on the direction only, so [`Lanes::step`] builds it first and
/// the division overlaps with the sampling of the new angles.
#[derive(Clone, Copy, Debug)]
struct Basis {
    /// t₁ₓ = 1 − s·r·w_x².
    t1x: F,
    /// s·r·m = −t₁ᵧ.
    srm: F,
    /// s·w_x = −t₁_z.
    swx: F,
    /// r·m = −t₂ₓ.
    rm: F,
    /// t₂ᵧ = s − r·w_y².
    t2y: F,
}

impl Basis {
    #[inline(always)]
    fn new([wx, wy, wz]: [F; 3]) -> Self {
        let sign_bit = umask(wz) & U::splat(SIGN_BIT);
        let flip = |v: F| -> F { cast(umask(v) ^ sign_bit) }; // s·v
        let sign = flip(F::ONE);
        let r = F::ONE / (sign + wz);
        let sr = flip(r);
        let m = wx * wy;
        Basis {
            t1x: (sr * wx).mul_neg_add(wx, F::ONE),
            srm: sr * m,
            swx: flip(wx),
            rm: r * m,
            t2y: (r * wy).mul_neg_add(wy, sign),
        }
    }

    /// The unit vector at polar angle θ and azimuth φ (given as cosines and
    /// sines) from `w`: w' = sin θ cos φ·t₁ + sin θ sin φ·t₂ + cos θ·w.
    #[inline(always)]
    fn rotate(
        &self,
        [wx, wy, wz]: [F; 3],
        cos_theta: F,
        sin_theta: F,
        cos_phi: F,
        sin_phi: F,
    ) -> [F; 3] {
        let (px, py) = (sin_theta * cos_phi, sin_theta * sin_phi);
        let nx = px.mul_add(self.t1x, py.mul_neg_add(self.rm, cos_theta * wx));
        let ny = px.mul_neg_add(self.srm, py.mul_add(self.t2y, cos_theta * wy));
        let nz = px.mul_neg_add(self.swx, py.mul_neg_add(wy, cos_theta * wz));
        [nx, ny, nz]
    }
}

/// Unpolarised Fresnel reflectance seen from inside the medium, eight
/// lanes: [`super::fresnel::fresnel_dielectric`]`(cos_i, 1/η)` in f32.
/// `one_minus_eta2` is 1 − η² (rounded once from f64).
///
/// # Formula
/// With η_rel = 1/η: cos²θ_t = 1 − η²(1 − cos²θ_i) = (1 − η²) + η²cos²θ_i,
/// total internal reflection (F = 1) if cos²θ_t ≤ 0; else, multiplying
/// numerators and denominators of the PBRT4 §9.3.5 amplitudes by η,
/// r_∥ = A/B = (cos θ_i − η cos θ_t)/(cos θ_i + η cos θ_t),
/// r_⊥ = C/D = (η cos θ_i − cos θ_t)/(η cos θ_i + cos θ_t), and
/// F = (r_∥² + r_⊥²)/2 = ((AD)² + (CB)²)/(2(BD)²) with one reciprocal.
/// Writing cos²θ_t this way keeps η = 1 exact in f32 (cos θ_t = cos θ_i, no
/// spurious total reflection at grazing angles).
#[inline(always)]
fn fresnel_inside(cos_i: F, eta: F, one_minus_eta2: F) -> F {
    let ci = cos_i.fast_clamp(F::ZERO, F::ONE);
    let cos2_t = (eta * eta * ci).mul_add(ci, one_minus_eta2);
    let tir = cos2_t.simd_le(F::ZERO);
    let ct = cos2_t.fast_max(F::ZERO).sqrt();
    let (e_ct, e_ci) = (eta * ct, eta * ci);
    let (a, b, c, d) = (ci - e_ct, ci + e_ct, e_ci - ct, e_ci + ct);
    let (ad, cb, bd) = (a * d, c * b, b * d);
    let num = ad.mul_add(ad, cb * cb);
    let f = num / ((bd * bd) * F::splat(2.0));
    tir.select(F::ONE, f.fast_min(F::ONE))
}

/// Per-medium constants of the walk, splatted to the lanes.
#[derive(Clone, Copy, Debug)]
struct Walk {
    flight: FlightConsts,
    /// z of the slab's bottom, −∞ for a half-space.
    z_bottom: F,
    /// η = n_inside/n_outside, and 1 − η².
    eta: F,
    one_minus_eta2: F,
    /// Scatter iff b < `scatter_below` (unsigned) or `always_scatter` is set:
    /// together, b < t with t = α·2³² ∈ [0, 2³²] ([`threshold_u32`]).
    scatter_below: U,
    always_scatter: U,
    /// Truncated when n reaches max(max_events, 1) (the scalar walk
    /// truncates at the first scattering when max_events = 0).
    trunc_at: U,
    /// Half azimuth angle h = (φ − π)/2 = (b − ⌊t/2⌋)·h_scale + h_offset,
    /// from φ = 2π(b + ½)/t. b − ⌊t/2⌋ ∈ [−2³¹, 2³¹) is an exact i32 and is
    /// converted to f32 with one rounding, so all 32 bits of b count.
    half_t: U,
    h_scale: F,
    h_offset: F,
    hg: HgLanes,
}

impl Walk {
    fn new(medium: &Medium, max_events: u32) -> Self {
        let t = threshold_u32(medium.alpha);
        let half = t / 2;
        let (h_scale, h_offset) = if t == 0 {
            (0.0, 0.0) // never scatters; keep the unused lanes finite
        } else {
            // h = π(b + ½)/t − π/2 = (b − half)·π/t + (half + ½ − t/2)·π/t
            let k = PI / t as f64;
            (k, (half as f64 + 0.5 - 0.5 * t as f64) * k)
        };
        Walk {
            flight: FlightConsts::new(medium.sigma_t()),
            z_bottom: F::splat(medium.thickness.map_or(f32::NEG_INFINITY, |l| -l as f32)),
            eta: F::splat(medium.eta as f32),
            one_minus_eta2: F::splat((1.0 - medium.eta * medium.eta) as f32),
            scatter_below: U::splat(t.min(u32::MAX as u64) as u32),
            always_scatter: U::splat(if t > u32::MAX as u64 { u32::MAX } else { 0 }),
            trunc_at: U::splat(max_events.max(1)),
            half_t: U::splat(half as u32),
            h_scale: F::splat(h_scale as f32),
            h_offset: F::splat(h_offset as f32),
            hg: HgLanes::new(medium.g),
        }
    }

    /// The half azimuth angle of [`azimuth`] from the bits b.
    #[inline(always)]
    fn half_azimuth(&self, b: U) -> F {
        i2f((b - self.half_t).cast_signed()).mul_add(self.h_scale, self.h_offset)
    }
}

/// Lane masks of the paths that ended in one step (all-ones lanes); an ended
/// lane in none of the three fate masks was truncated.
#[derive(Clone, Copy, Debug)]
struct Ended {
    any: U,
    exit_top: U,
    transmitted: U,
    absorbed: U,
}

/// The state of eight paths.
#[derive(Clone, Copy, Debug, Default)]
struct Lanes {
    x: F,
    y: F,
    z: F,
    wx: F,
    wy: F,
    wz: F,
    /// Scattering events so far.
    n: U,
    rng: LaneRng,
}

impl Lanes {
    /// Puts a freshly launched path into lane `lane`.
    fn load(&mut self, lane: usize, start: &Launched, rng: &PathRng) {
        let [x, y, z] = start.position;
        let [wx, wy, wz] = start.direction;
        for (v, s) in [
            (&mut self.x, x),
            (&mut self.y, y),
            (&mut self.z, z),
            (&mut self.wx, wx),
            (&mut self.wy, wy),
            (&mut self.wz, wz),
        ] {
            v.as_mut_array()[lane] = s as f32;
        }
        self.n.as_mut_array()[lane] = 0;
        self.rng.set_lane(lane, rng);
    }

    /// One step of the protocol of [`super::walk`] in every lane: free flight,
    /// then either the wall (reflect or leave) or a collision (absorb,
    /// truncate or scatter). Lanes that ended keep their final position and
    /// event count for tallying.
    #[inline(always)]
    fn step(&mut self, k: &Walk) -> Ended {
        // The statements are in the order that runs fastest: the compiler
        // keeps it, and starting the long dependency chains first (the basis
        // division, then the angles) lets them overlap with the rest.
        let w = [self.wx, self.wy, self.wz];
        let basis = Basis::new(w);
        let a = self.rng.next_u32();
        let b = self.rng.next_u32();
        let c = self.rng.next_u32();
        // ---- scattering angles (used only where a scattering happens) --------
        let cos_theta = k.hg.cos_theta(c);
        let (cos_phi, sin_phi) = azimuth(k.half_azimuth(b));
        // ---- free flight: s = −ln(u_a)/σ_t -----------------------------------
        let s = free_flight(a, &k.flight);
        let sin_theta = cos_theta
            .mul_neg_add(cos_theta, F::ONE)
            .fast_max(F::ZERO)
            .sqrt();
        let zn = self.wz.mul_add(s, self.z);
        // ---- boundary: z + s·w_z beyond the surface (w_z > 0) or bottom --------
        let cross_top = self.wz.simd_gt(F::ZERO) & zn.simd_ge(F::ZERO);
        let cross_bottom = self.wz.simd_lt(F::ZERO) & zn.simd_le(k.z_bottom);
        let cross = cross_top | cross_bottom;
        // ---- collision: scatter iff b < α·2³² (unsigned) ---------------------
        let scatter_ok = b.simd_lt(k.scatter_below) | k.always_scatter;
        // ---- the direction after a scattering --------------------------------
        let w = basis.rotate(w, cos_theta, sin_theta, cos_phi, sin_phi);
        if !cross.any() {
            // Every lane collides; absorbed and truncated lanes end (and are
            // reloaded), so the new direction needs no select.
            self.x = self.wx.mul_add(s, self.x);
            self.y = self.wy.mul_add(s, self.y);
            self.z = zn;
            self.n -= scatter_ok; // mask lanes are −1
            [self.wx, self.wy, self.wz] = w;
            let absorbed = !scatter_ok;
            return Ended {
                any: absorbed | self.n.simd_eq(k.trunc_at),
                exit_top: U::ZERO,
                transmitted: U::ZERO,
                absorbed,
            };
        }
        // ---- some lane reaches a wall: move it there, reflect or leave --------
        let wall = cross_top.select(F::ZERO, k.z_bottom);
        let d = cross.select((wall - self.z) / self.wz, s);
        self.x = self.wx.mul_add(d, self.x);
        self.y = self.wy.mul_add(d, self.y);
        self.z = cross.select(wall, zn);
        let f = fresnel_inside(self.wz.abs(), k.eta, k.one_minus_eta2);
        let reflect = cross & unit23(b).simd_lt(f);
        let leave = umask(cross & !reflect);
        let up = umask(self.wz.simd_gt(F::ZERO));
        let wz = reflect.select(-self.wz, self.wz);
        let collide = !umask(cross);
        let scatter = collide & scatter_ok;
        let absorbed = collide & !scatter_ok;
        self.n -= scatter;
        let scatter = fmask(scatter);
        self.wx = scatter.select(w[0], self.wx);
        self.wy = scatter.select(w[1], self.wy);
        self.wz = scatter.select(w[2], wz);
        Ended {
            any: leave | absorbed | self.n.simd_eq(k.trunc_at),
            exit_top: leave & up,
            transmitted: leave & !up,
            absorbed,
        }
    }
}

/// Hands out the paths of the range in order: launches them (scalar, shared
/// with the f64 walk) and counts launches and specular reflections.
struct Feeder<'a> {
    source: &'a Source,
    eta: f64,
    seed: u64,
    next: u64,
    end: u64,
}

impl Feeder<'_> {
    /// The next path that enters the medium, with its stream after launch.
    fn next(&mut self, tally: &mut ProfileTally) -> Option<(Launched, PathRng)> {
        while self.next < self.end {
            let path = self.next;
            self.next += 1;
            tally.paths += 1;
            let mut rng = PathRng::new(self.seed, path);
            match launch(self.source, self.eta, &mut rng) {
                None => tally.specular += 1,
                Some(start) => return Some((start, rng)),
            }
        }
        None
    }
}

/// Simulates paths `first..first + count` of the stream family `seed` with the
/// lane-parallel walk and tallies them; statistically equivalent to
/// [`super::walk::simulate_scalar`] (same streams, f32 rounding).
pub fn simulate_lanes(
    medium: &Medium,
    source: &Source,
    bins: &BinLookup,
    max_events: u32,
    seed: u64,
    first: u64,
    count: u64,
) -> ProfileTally {
    let mut tally = ProfileTally::new(bins.bins());
    let walk = Walk::new(medium, max_events);
    let mut feeder = Feeder {
        source,
        eta: medium.eta,
        seed,
        next: first,
        end: first + count,
    };
    let mut lanes = Lanes::default();
    let mut active = 0u32; // bit i: lane i holds a live path
    for lane in 0..LANES {
        if let Some((start, rng)) = feeder.next(&mut tally) {
            lanes.load(lane, &start, &rng);
            active |= 1 << lane;
        } else {
            park(&mut lanes, lane);
        }
    }
    while active != 0 {
        let ended = lanes.step(&walk);
        if !ended.any.any() {
            continue;
        }
        let mut bits = ended.any.to_bitmask() & active;
        if bits == 0 {
            continue;
        }
        let (top, bottom, absorbed) = (
            ended.exit_top.to_bitmask(),
            ended.transmitted.to_bitmask(),
            ended.absorbed.to_bitmask(),
        );
        let (xs, ys, ns) = (lanes.x.to_array(), lanes.y.to_array(), lanes.n.to_array());
        while bits != 0 {
            let lane = bits.trailing_zeros() as usize;
            let bit = 1 << lane;
            bits &= !bit;
            let fate = if top & bit != 0 {
                Fate::Exit {
                    x: xs[lane] as f64,
                    y: ys[lane] as f64,
                }
            } else if bottom & bit != 0 {
                Fate::Transmitted
            } else if absorbed & bit != 0 {
                Fate::Absorbed
            } else {
                Fate::Truncated
            };
            record(&mut tally, bins, fate, ns[lane]);
            if let Some((start, rng)) = feeder.next(&mut tally) {
                lanes.load(lane, &start, &rng);
            } else {
                active &= !bit;
                park(&mut lanes, lane);
            }
        }
    }
    tally
}

/// Gives an idle lane a harmless state (deep inside, heading down) so that
/// the masked-out work it still does stays finite and normal.
fn park(lanes: &mut Lanes, lane: usize) {
    let start = Launched {
        position: [0.0, 0.0, -1.0],
        direction: [0.0, 0.0, -1.0],
    };
    lanes.load(lane, &start, &PathRng::new(0, lane as u64));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::fresnel::fresnel_dielectric;
    use crate::forward::sampling::sample_hg_cos;
    use crate::forward::tally::RadialBins;
    use crate::forward::walk::simulate_scalar;
    use crate::testing::*;

    fn lane_rng(seed: u64, first: u64) -> (LaneRng, Vec<PathRng>) {
        let mut lanes = LaneRng::default();
        let scalars: Vec<PathRng> = (0..LANES as u64)
            .map(|i| PathRng::new(seed, first + i))
            .collect();
        for (i, r) in scalars.iter().enumerate() {
            lanes.set_lane(i, r);
        }
        (lanes, scalars)
    }

    #[test]
    fn xoshiro_lanes_match_path_rng_bitwise() {
        for (seed, first) in [(0, 0), (7, 12_345), (u64::MAX, 1 << 40)] {
            let (mut lanes, mut scalars) = lane_rng(seed, first);
            for _ in 0..10_000 {
                let v = lanes.next_u32().to_array();
                for (i, r) in scalars.iter_mut().enumerate() {
                    assert_eq!(v[i], r.next_u32());
                }
            }
        }
    }

    #[test]
    fn uniforms_and_flights() {
        let vals = [
            0,
            1,
            255,
            256,
            511,
            512,
            0x8000_0000,
            0xFFFF_FE00,
            0xFFFF_FFFF,
            12_345_678,
        ];
        for shift in 0..4 {
            let x = U::new(std::array::from_fn(|i| vals[(i + shift) % vals.len()]));
            let u = unit23(x).to_array();
            let k = Walk::new(&Medium::new(0.5, 0.3, 1.5, 2.0, None).unwrap(), 10);
            let fl = free_flight(x, &k.flight).to_array();
            for (i, &v) in x.to_array().iter().enumerate() {
                assert_eq!(u[i] as f64, (v >> 9) as f64 / 8_388_608.0);
                let ua = ((v >> 8) + 1) as f64 / 16_777_216.0;
                let want = -ua.ln() / 2.0;
                assert!(
                    (fl[i] as f64 - want).abs() <= 3e-7 * want + 1e-7,
                    "{v}: {} vs {want}",
                    fl[i]
                );
            }
        }
        // −ln u over the whole range of u: relative error ≈ 2e-7.
        let k = Walk::new(&Medium::new(0.5, 0.3, 1.5, 1.0, None).unwrap(), 10);
        for i in 0..(1u64 << 24) / 997 {
            let a: [u32; LANES] =
                std::array::from_fn(|j| (((i * 997 + j as u64 * 61) % (1 << 24)) << 8) as u32);
            let fl = free_flight(U::new(a), &k.flight).to_array();
            for j in 0..LANES {
                let ua = ((a[j] >> 8) + 1) as f64 / 16_777_216.0;
                let want = -ua.ln();
                assert!(
                    (fl[j] as f64 - want).abs() <= 4e-7 * want + 2e-8,
                    "{}: {} vs {want}",
                    a[j],
                    fl[j]
                );
            }
        }
        assert_eq!(
            unit23(U::splat(u32::MAX)).to_array()[0] as f64,
            1.0 - 1.0 / 8_388_608.0
        );
    }

    #[test]
    fn hg_matches_scalar_sampler() {
        for g in [
            -0.99, -0.3, -1.1e-3, -5e-4, 0.0, 5e-4, 1.1e-3, 0.3, 0.75, 0.99,
        ] {
            let hg = HgLanes::new(g);
            for i in 0..(16_384 / LANES as u32) {
                let c: [u32; LANES] =
                    std::array::from_fn(|j| ((i * LANES as u32 + j as u32) * 512) << 9);
                let got = hg.cos_theta(U::new(c)).to_array();
                for j in 0..LANES {
                    let u = (c[j] >> 9) as f64 / 8_388_608.0;
                    let want = sample_hg_cos(g, u);
                    // The f64 closed form itself loses digits as g → 0.
                    let tol = 2e-6 + 1e-9 / g.abs().max(1e-3);
                    assert!(
                        (got[j] as f64 - want).abs() < tol,
                        "g={g} u={u}: {} vs {want}",
                        got[j]
                    );
                }
            }
            // The extremes of u map to the extremes of cos θ.
            let ends = hg.cos_theta(U::new(std::array::from_fn(|j| {
                if j % 2 == 0 { 0 } else { u32::MAX }
            })));
            for (j, &c) in ends.to_array().iter().enumerate() {
                let want = sample_hg_cos(
                    g,
                    if j % 2 == 0 {
                        0.0
                    } else {
                        1.0 - 1.0 / 8_388_608.0
                    },
                );
                assert!((c as f64 - want).abs() < 1e-5, "g={g}: {c} vs {want}");
            }
        }
    }

    #[test]
    fn azimuth_matches_sin_cos() {
        for t in [1u64, 3, 1 << 20, 4_294_967_295, 1 << 32] {
            let k = Walk::new(
                &Medium::new(t as f64 / 4_294_967_296.0, 0.3, 1.5, 1.0, None).unwrap(),
                10,
            );
            assert_eq!(threshold_u32(t as f64 / 4_294_967_296.0), t);
            let top = t.min(u32::MAX as u64 + 1);
            for i in 0..1000u64 {
                let b: [u32; LANES] = std::array::from_fn(|j| {
                    (((i * LANES as u64 + j as u64) * top) / (1000 * LANES as u64)).min(t - 1)
                        as u32
                });
                let h = k.half_azimuth(U::new(b));
                let (c, s) = azimuth(h);
                for ((&bj, c), s) in b.iter().zip(c.to_array()).zip(s.to_array()) {
                    let phi = 2.0 * PI * (bj as f64 + 0.5) / t as f64;
                    assert!((c as f64 - phi.cos()).abs() < 1e-6, "t={t} b={bj}");
                    assert!((s as f64 - phi.sin()).abs() < 1e-6, "t={t} b={bj}");
                }
            }
        }
    }

    #[test]
    fn fresnel_matches_scalar() {
        for eta in [1.0f64, 1.0001, 1.33, 1.5, 3.0] {
            let cos_crit = (1.0 - 1.0 / (eta * eta)).sqrt();
            for i in 0..=10_000 {
                let c = (i as f64 / 10_000.0) as f32;
                let got = fresnel_inside(
                    F::splat(c),
                    F::splat(eta as f32),
                    F::splat((1.0 - eta * eta) as f32),
                )
                .to_array()[0] as f64;
                let want = fresnel_dielectric(c as f64, 1.0 / eta);
                // F has an infinite slope at the critical angle: allow for
                // the f32 rounding of sin²θ_t there.
                let tol = if (c as f64 - cos_crit).abs() < 1e-3 {
                    3e-3
                } else {
                    2e-5
                };
                assert!(
                    (got - want).abs() < tol,
                    "eta={eta} cos={c}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn rotation_keeps_unit_norm_and_hg_mean_cosine() {
        // α = 1, deep inside, no walls: every step scatters. 4·10⁵ scatterings
        // per path (lane) without renormalisation.
        for g in [0.0, 0.75, 0.99, -0.99] {
            let medium = Medium::new(1.0, g, 1.5, 1.0, None).unwrap();
            let k = Walk::new(&medium, u32::MAX);
            let mut lanes = Lanes::default();
            for lane in 0..LANES {
                let start = Launched {
                    position: [0.0, 0.0, -1e30],
                    direction: [0.6, 0.0, -0.8],
                };
                lanes.load(lane, &start, &PathRng::new(3, lane as u64));
            }
            let (mut sum, mut sum2, mut n) = (0.0f64, 0.0f64, 0u64);
            let mut worst = 0.0f64;
            let steps = 400_000;
            for _ in 0..steps {
                let w0 = [lanes.wx, lanes.wy, lanes.wz];
                let ended = lanes.step(&k);
                assert!(!ended.any.any());
                let dot = lanes
                    .wx
                    .mul_add(w0[0], lanes.wy.mul_add(w0[1], lanes.wz * w0[2]));
                let norm = lanes
                    .wx
                    .mul_add(lanes.wx, lanes.wy.mul_add(lanes.wy, lanes.wz * lanes.wz));
                for (d, q) in dot.to_array().into_iter().zip(norm.to_array()) {
                    sum += d as f64;
                    sum2 += (d * d) as f64;
                    n += 1;
                    worst = worst.max((q as f64 - 1.0).abs());
                }
            }
            assert!(worst < 1e-5, "g={g}: norm drift {worst}");
            assert_eq!(lanes.n.to_array(), [steps; LANES]);
            let mean = sum / n as f64;
            let se = ((sum2 / n as f64 - mean * mean) / n as f64).sqrt();
            assert!(
                (mean - g).abs() < Z_MC * se + 1e-6,
                "g={g}: mean cos {mean} (se {se})"
            );
        }
    }

    /// Both engines on the same streams; totals within `Z_MC` combined
    /// binomial standard errors, radial bins by a two-sample χ².
    fn compare_engines(medium: Medium, source: Source, paths: u64, seed: u64) {
        let bins = RadialBins::default().lookup();
        let max_events = 100_000;
        let s = simulate_scalar(&medium, &source, &bins, max_events, seed, 0, paths, false);
        let l = simulate_lanes(&medium, &source, &bins, max_events, seed, 0, paths);
        let ctx = format!("{medium:?} {source}");
        assert_eq!(l.paths, paths, "{ctx}");
        assert_eq!(l.accounted(), paths, "{ctx}");
        assert_eq!(s.accounted(), paths, "{ctx}");
        assert_eq!(l.specular, s.specular, "{ctx}: launch is shared");
        let sum = |v: &[u64]| v.iter().sum::<u64>();
        let totals = [
            ("single", sum(&s.exit_single), sum(&l.exit_single)),
            ("multi", sum(&s.exit_multi), sum(&l.exit_multi)),
            ("unscattered", s.exit_unscattered, l.exit_unscattered),
            ("absorbed", s.absorbed, l.absorbed),
            ("transmitted", s.transmitted, l.transmitted),
            ("truncated", s.truncated, l.truncated),
        ];
        let n = paths as f64;
        for (name, cs, cl) in totals {
            let p = (cs + cl) as f64 / (2.0 * n);
            let se = (2.0 * n * p * (1.0 - p)).sqrt();
            let diff = (cs as f64 - cl as f64).abs();
            assert!(
                diff <= Z_MC * se + 0.5,
                "{ctx}: {name} scalar {cs} lanes {cl} (se {se:.1})"
            );
        }
        // Mean scatterings per path: a sensitive check of the free flights.
        let (ms, ml) = (s.events as f64 / n, l.events as f64 / n);
        assert!(
            (ms - ml).abs() < 0.02 * ms + 0.01,
            "{ctx}: mean events {ms} vs {ml}"
        );
        // Two-sample χ² on the multiple-scattering radial bins (equal N):
        // Σ (a − b)²/(a + b), bins pooled to ≥ 10 counts.
        let (mut stat, mut dof) = (0.0, 0usize);
        let (mut acc_s, mut acc_l) = (0u64, 0u64);
        for (&a, &b) in s
            .exit_multi
            .iter()
            .zip(&l.exit_multi)
            .chain(s.exit_single.iter().zip(&l.exit_single))
        {
            acc_s += a;
            acc_l += b;
            if acc_s + acc_l >= 20 {
                let d = acc_s as f64 - acc_l as f64;
                stat += d * d / (acc_s + acc_l) as f64;
                dof += 1;
                (acc_s, acc_l) = (0, 0);
            }
        }
        assert!(dof >= 10, "{ctx}: too few bins ({dof})");
        let crit = chi2_critical(dof, CHI2_ALPHA);
        assert!(
            stat < crit,
            "{ctx}: radial chi2 {stat:.1} > {crit:.1} (dof {dof})"
        );
    }

    #[test]
    fn agrees_with_scalar_walk() {
        let m = |a, g, eta, l| Medium::new(a, g, eta, 1.0, l).unwrap();
        let paths = 200_000;
        compare_engines(m(0.9, 0.3, 1.5, None), Source::Pencil, paths, 1);
        compare_engines(m(0.99, 0.3, 1.5, None), Source::Pencil, paths, 2);
        compare_engines(m(0.5, 0.0, 1.0, None), Source::Pencil, paths, 3);
        compare_engines(m(0.9, 0.75, 1.0, Some(2.0)), Source::Pencil, paths, 4);
        compare_engines(
            m(0.9, 0.3, 1.5, Some(2.0)),
            Source::Collimated { radius: 1.0 },
            paths,
            5,
        );
        compare_engines(
            m(0.9, -0.5, 1.33, None),
            Source::Diffuse { radius: 1.0 },
            paths,
            6,
        );
    }

    #[test]
    fn hard_cases_stay_sane() {
        let bins = RadialBins::default().lookup();
        let max_events = 10_000;
        let paths = 64;
        for alpha in [0.0, 1e-9, 1.0 - 1e-9, 1.0] {
            for g in [-0.99, 0.0, 0.99] {
                for eta in [1.0, 1.0001, 3.0] {
                    for rho in [1e-3, 1e3] {
                        for thickness in [None, Some(1e-2)] {
                            let medium = Medium::new(alpha, g, eta, rho, thickness).unwrap();
                            for source in [Source::Pencil, Source::Diffuse { radius: 2.0 }] {
                                let t = simulate_lanes(
                                    &medium, &source, &bins, max_events, 9, 0, paths,
                                );
                                let ctx = format!("{medium:?} {source}");
                                assert_eq!(t.paths, paths, "{ctx}");
                                assert_eq!(t.accounted(), paths, "{ctx}");
                                assert!(t.events <= paths * max_events as u64, "{ctx}");
                                let entered = paths - t.specular;
                                if alpha == 0.0 {
                                    assert_eq!(t.events, 0, "{ctx}");
                                    assert_eq!(
                                        t.exit_single.iter().chain(&t.exit_multi).sum::<u64>(),
                                        0,
                                        "{ctx}"
                                    );
                                }
                                if alpha == 1.0 {
                                    assert_eq!(t.absorbed, 0, "{ctx}");
                                }
                                if alpha == 0.0 && thickness.is_none() && source == Source::Pencil {
                                    assert_eq!(t.absorbed, entered, "{ctx}");
                                }
                                if thickness.is_none() {
                                    assert_eq!(t.transmitted + t.exit_unscattered, 0, "{ctx}");
                                }
                                if alpha < 1.0 - 1e-6 && alpha > 0.0 {
                                    // α ≈ 1e-9: ~1e-9 chance that any path scatters.
                                    assert!(t.events <= 1, "{ctx}");
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn short_and_odd_ranges() {
        let bins = RadialBins::default().lookup();
        let medium = Medium::new(0.9, 0.3, 1.5, 1.0, None).unwrap();
        for source in [Source::Pencil, Source::Diffuse { radius: 1.0 }] {
            for (first, count) in [
                (0, 0),
                (5, 0),
                (0, 1),
                (3, 7),
                (0, 8),
                (11, 13),
                (100, 1001),
            ] {
                let t = simulate_lanes(&medium, &source, &bins, 1000, 4, first, count);
                assert_eq!(t.paths, count);
                assert_eq!(t.accounted(), count);
                let s = simulate_scalar(&medium, &source, &bins, 1000, 4, first, count, false);
                assert_eq!(t.specular, s.specular);
            }
        }
        assert_eq!(
            simulate_lanes(&medium, &Source::Pencil, &bins, 1000, 4, 0, 0),
            ProfileTally::new(bins.bins())
        );
        // max_events = 0 truncates at the first scattering, as the scalar walk.
        let t = simulate_lanes(&medium, &Source::Pencil, &bins, 0, 4, 0, 1000);
        let s = simulate_scalar(&medium, &Source::Pencil, &bins, 0, 4, 0, 1000, false);
        assert_eq!((t.truncated, t.events), (s.truncated, s.events));
        // Ranges concatenate: [0, 37) + [37, 100) == [0, 100) exactly.
        let mut a = simulate_lanes(&medium, &Source::Pencil, &bins, 1000, 4, 0, 37);
        a.merge(&simulate_lanes(
            &medium,
            &Source::Pencil,
            &bins,
            1000,
            4,
            37,
            63,
        ));
        assert_eq!(
            a,
            simulate_lanes(&medium, &Source::Pencil, &bins, 1000, 4, 0, 100)
        );
    }
}
