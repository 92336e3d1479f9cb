//! Per-path random streams.
//!
//! Path `i` of a simulation with master seed `seed` draws every random number
//! from its own xoshiro128++ generator (Blackman & Vigna 2019,
//! <https://prng.di.unimi.it/>) whose 128-bit state is the SplitMix64 hash of `(seed, i)`
//! (a small generator must hash `(seed, i)` first). The stream
//! is therefore a pure function of (seed, path index, draw number): no state
//! is shared between paths, so the result of a simulation does not depend on
//! the thread count, the chunking or the sharding. The scalar and the
//! lane-parallel walks consume the streams identically (three draws per
//! free-flight step, see [`super::walk`]).
//!
//! The generator is written out here (ten lines) because the lane-parallel
//! walk runs eight of them in SIMD registers; a test pins it bitwise to
//! `rand_xoshiro::Xoshiro128PlusPlus`.

/// SplitMix64 finaliser (Steele, Lea & Flood 2014): a bijective 64-bit mixer.
#[inline]
pub fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// xoshiro128++ state of one path's stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PathRng {
    pub s: [u32; 4],
}

impl PathRng {
    /// The stream of path `path` under master seed `seed`.
    pub fn new(seed: u64, path: u64) -> Self {
        let k = splitmix64(seed ^ splitmix64(path));
        let a = splitmix64(k);
        let b = splitmix64(a);
        let mut s = [a as u32, (a >> 32) as u32, b as u32, (b >> 32) as u32];
        if s == [0; 4] {
            s[0] = 1; // the all-zero state is the generator's only fixed point
        }
        PathRng { s }
    }

    /// The next 32 random bits (xoshiro128++).
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(7).wrapping_add(s[0]);
        let t = s[1] << 9;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(11);
        result
    }

    /// A uniform in [0, 1) with 32 bits of resolution.
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        unit_f64(self.next_u32())
    }
}

/// Maps 32 random bits to [0, 1).
#[inline]
pub fn unit_f64(x: u32) -> f64 {
    x as f64 * (1.0 / 4_294_967_296.0)
}

/// Maps 32 random bits to (0, 1]: safe for `-ln(u)`.
#[inline]
pub fn unit_open0_f64(x: u32) -> f64 {
    (x as f64 + 1.0) * (1.0 / 4_294_967_296.0)
}

/// The integer threshold `t` with P(x < t) = p for x uniform on u32, exact to
/// 2⁻³². Used for the absorption decision so that albedos such as 1 − 1e-9
/// stay distinguishable from 1 (they are not in f32).
#[inline]
pub fn threshold_u32(p: f64) -> u64 {
    (p.clamp(0.0, 1.0) * 4_294_967_296.0).round() as u64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_xoshiro::Xoshiro128PlusPlus;
    use rand_xoshiro::rand_core::{RngCore, SeedableRng};

    #[test]
    fn matches_rand_xoshiro_bitwise() {
        let mut ours = PathRng::new(7, 12345);
        let mut seed = [0u8; 16];
        for (i, w) in ours.s.iter().enumerate() {
            seed[4 * i..4 * i + 4].copy_from_slice(&w.to_le_bytes());
        }
        let mut theirs = Xoshiro128PlusPlus::from_seed(seed);
        for _ in 0..1000 {
            assert_eq!(ours.next_u32(), theirs.next_u32());
        }
    }

    #[test]
    fn streams_differ_by_seed_and_path() {
        let a = PathRng::new(1, 0).next_u32();
        assert_ne!(a, PathRng::new(1, 1).next_u32());
        assert_ne!(a, PathRng::new(2, 0).next_u32());
        assert_eq!(a, PathRng::new(1, 0).next_u32());
    }

    #[test]
    fn uniform_ranges() {
        assert_eq!(unit_f64(0), 0.0);
        assert!(unit_f64(u32::MAX) < 1.0);
        assert!(unit_open0_f64(0) > 0.0);
        assert_eq!(unit_open0_f64(u32::MAX), 1.0);
        assert_eq!(threshold_u32(1.0), 1 << 32);
        assert_eq!(threshold_u32(0.0), 0);
        assert!(threshold_u32(1.0 - 1e-9) < 1 << 32);
    }
}
