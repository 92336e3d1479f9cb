//! Lean four-wide exponential for the renderer's and the meta-model's inner
//! loops, where every argument is known to be finite and bounded.
//!
//! `wide`'s `f64x4::exp` is accurate but guards every lane against overflow,
//! underflow, NaN and infinity with compares, blends and an early-out branch;
//! in the kernel query (six exponentials) and the importance sampler's
//! profile tail those guards cost as much as the polynomial. [`exp4`] keeps
//! the same algorithm and accuracy (Cody–Waite range reduction, degree-12
//! polynomial: ≤ 2 ulp against `f64::exp`, tested) and replaces the guards by
//! one clamp of the argument to [−708, 708]: results below e^−708 ≈ 3e−308
//! are flushed to zero, which is what every caller needs (a profile tail or a
//! softmax weight that small is zero in the sums it enters).

use wide::bytemuck::cast;
use wide::{f64x4, u64x4};

/// Arguments are clamped to ±this (e^±708 stays a normal double).
const LIMIT: f64 = 708.0;

/// Taylor coefficients 1/n! of e^r, n = 0..=12 (n! exact in f64, then one
/// rounding).
const INV_FACTORIAL: [f64; 13] = {
    let mut t = [1.0; 13];
    let mut n = 1;
    while n < 13 {
        let mut f = 1.0;
        let mut k = 2;
        while k <= n {
            f *= k as f64;
            k += 1;
        }
        t[n] = 1.0 / f;
        n += 1;
    }
    t
};

/// e^x per lane, ≤ 2 ulp for |x| ≤ 708; e^x = 0 for x < −708, e^708 for
/// x > 708. NaN lanes give an unspecified finite value: callers pass finite
/// arguments.
///
/// Algorithm: x = k·ln 2 + r with k = round(x/ln 2), |r| ≤ ln 2 / 2, ln 2 split
/// into a 32-bit head and a tail (Cody & Waite 1980) so r is exact to a few
/// ulp; e^r as its Taylor polynomial of degree 12 (truncation error
/// (ln2/2)^13/13! ≈ 1.7e−16 relative) evaluated with Estrin's scheme (a
/// dependency chain of five multiply-adds and the final + 1, instead of
/// twelve multiply-adds for Horner's); 2^k built in the exponent field.
#[inline(always)]
pub fn exp4(x: f64x4) -> f64x4 {
    const LN2_HI: f64 = 0.693_145_751_953_125;
    const LN2_LO: f64 = 1.428_606_820_309_417_3e-6;
    let xc = x
        .fast_max(f64x4::splat(-LIMIT))
        .fast_min(f64x4::splat(LIMIT));
    let k = (xc * f64x4::splat(std::f64::consts::LOG2_E)).round();
    let r = k.mul_neg_add(f64x4::splat(LN2_HI), xc);
    let r = k.mul_neg_add(f64x4::splat(LN2_LO), r);
    let c = |n: usize| f64x4::splat(INV_FACTORIAL[n]);
    // e^r = 1 + (r + r²·q(r)), q = Σ_{n=2}^{12} r^{n−2}/n!: the small terms
    // are summed first and the 1 added last (≈ 0.5 ulp from that add).
    let r2 = r * r;
    let r4 = r2 * r2;
    let r8 = r4 * r4;
    // Estrin: pairs (c_n + c_{n+1} r), then quadruples in r², octets in r⁴.
    let p23 = r.mul_add(c(3), c(2));
    let p45 = r.mul_add(c(5), c(4));
    let p67 = r.mul_add(c(7), c(6));
    let p89 = r.mul_add(c(9), c(8));
    let p1011 = r.mul_add(c(11), c(10));
    let p25 = r2.mul_add(p45, p23);
    let p69 = r2.mul_add(p89, p67);
    let p1012 = r2.mul_add(c(12), p1011);
    let q = r8.mul_add(p1012, r4.mul_add(p69, p25));
    let p = r2.mul_add(q, r) + f64x4::ONE;
    // 2^k: k + 2^52 + 1023 holds the biased exponent in its low mantissa bits.
    let biased = k + f64x4::splat(4_503_599_627_370_496.0 + 1023.0);
    let two_k: f64x4 = cast(cast::<f64x4, u64x4>(biased) << 52);
    let e = p * two_k;
    // x < −708 (before clamping): flush to zero.
    e & !x.simd_lt(f64x4::splat(-LIMIT))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f64, b: f64) -> u64 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs()
    }

    #[test]
    fn matches_std_exp_within_two_ulp() {
        let mut worst = 0;
        let n = 200_000;
        for i in 0..n {
            let x = -708.0 + 1416.0 * (i as f64 + 0.37) / n as f64;
            let got = exp4(f64x4::from([x, x * 1e-3, -x * 1e-6, x * 0.05]));
            for (g, v) in got
                .to_array()
                .iter()
                .zip([x, x * 1e-3, -x * 1e-6, x * 0.05])
            {
                worst = worst.max(ulps(*g, v.exp()));
            }
        }
        assert!(worst <= 2, "worst error {worst} ulp");
    }

    #[test]
    fn edges() {
        let got = exp4(f64x4::from([0.0, -709.0, -1e300, 1e300])).to_array();
        assert_eq!(got[0], 1.0);
        assert_eq!(got[1], 0.0);
        assert_eq!(got[2], 0.0);
        assert!(got[3].is_finite() && got[3] > 1e307);
        let small = exp4(f64x4::splat(-707.9)).to_array()[0];
        assert!(small > 0.0 && ulps(small, (-707.9f64).exp()) <= 2);
    }
}
