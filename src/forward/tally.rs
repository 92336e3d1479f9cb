//! Profile tallies: integer counts, so merging is exact and associative and a
//! simulation's result is bitwise independent of threads and shards.
//!
//! The walk is analog (every path has weight one), so each tally is a count of
//! paths; each path exits at most once, so a bin's count is binomial and its
//! standard error follows from the count alone (oracles.md "Tally hygiene").

use serde::{Deserialize, Serialize};

/// Geometric radial bins: an inner disk [0, r_min), `per_decade` rings per
/// decade up to `r_max`, and an overflow bin [r_max, ∞).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadialBins {
    /// Outer radius of the inner disk (MFP).
    pub r_min: f64,
    /// Outer radius of the last ring (MFP).
    pub r_max: f64,
    /// Rings per decade of radius.
    pub per_decade: u32,
}

impl Default for RadialBins {
    /// 1e-3 … 100 MFP at 20 rings per decade (design: "at least 1e-3 … 100").
    fn default() -> Self {
        RadialBins {
            r_min: 1e-3,
            r_max: 100.0,
            per_decade: 20,
        }
    }
}

impl RadialBins {
    /// Number of rings between r_min and r_max.
    pub fn rings(&self) -> usize {
        ((self.r_max / self.r_min).log10() * self.per_decade as f64).round() as usize
    }

    /// Number of bins including the inner disk and the overflow bin.
    pub fn len(&self) -> usize {
        self.rings() + 2
    }

    /// Always false: there is at least the inner disk and the overflow.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Bin edges, `rings() + 2` of them: 0, r_min, …, r_max (the overflow bin
    /// has no outer edge).
    pub fn edges(&self) -> Vec<f64> {
        let mut e = vec![0.0];
        let n = self.rings();
        e.extend((0..=n).map(|k| self.r_min * 10f64.powf(k as f64 / self.per_decade as f64)));
        e
    }

    /// The bin of radius `r`: 0 for the inner disk, `len() - 1` for overflow.
    #[inline]
    pub fn index(&self, r: f64) -> usize {
        if r < self.r_min {
            return 0;
        }
        let k = ((r / self.r_min).log10() * self.per_decade as f64).floor();
        if k.is_nan() {
            return 0;
        }
        (k as usize).saturating_add(1).min(self.len() - 1) // r = ∞: overflow
    }

    /// A precomputed form of [`Self::index`] for the walks' tally: the same
    /// bin for every `r`, without a logarithm (≈ 40 µs to build: once per
    /// run, not per chunk).
    pub fn lookup(&self) -> BinLookup {
        BinLookup::new(self)
    }
}

/// [`RadialBins::index`] without a logarithm, bitwise the same bin for every
/// radius (tested): the walks tally each exit through it.
///
/// # Method
/// `index` is a non-decreasing step function of r (a composition of
/// correctly rounded or monotone operations), so it is determined by its
/// thresholds t_j, the smallest f64 with `index(t_j) ≥ j`: index(r) =
/// #{j : t_j ≤ r}. They are found exactly at construction, each by stepping
/// ulp by ulp from the analytic edge r_min·10^{(j−1)/per_decade} (a few
/// evaluations of `index`). A lookup reads a table keyed by the top bits of
/// r (exponent and [`Self::MANTISSA_BITS`] mantissa bits: cells finer than
/// the bins) holding the count at the cell's lower end, then steps past the
/// thresholds inside the cell (at most one up to 148 rings per decade).
///
/// Why: the logarithm was a libm call in the lane-parallel walk's refill
/// loop, and around a call every live SIMD register is spilled (all are
/// caller-saved): 10–15 % of the walk's time at α = 0.99.
#[derive(Clone, Debug)]
pub struct BinLookup {
    bins: RadialBins,
    /// t_1, …, t_{len−1}.
    thresholds: Vec<f64>,
    /// Counts #{j : t_j ≤ lower end of cell c}.
    table: Vec<u16>,
    /// Key of cell 0: the top bits of t_1.
    key0: u64,
}

impl BinLookup {
    /// Mantissa bits of the table key: cells span a ratio of at most
    /// 1 + 2⁻⁶ in radius.
    pub const MANTISSA_BITS: u32 = 6;
    const SHIFT: u32 = 52 - Self::MANTISSA_BITS;

    fn new(bins: &RadialBins) -> Self {
        let last = bins.len() - 1;
        assert!(last < u16::MAX as usize, "{last} bins overflow the table");
        let thresholds: Vec<f64> = (1..=last).map(|j| threshold(bins, j)).collect();
        let key = |r: f64| r.to_bits() >> Self::SHIFT;
        let key0 = key(thresholds[0]);
        let table = (key0..=key(thresholds[last - 1]))
            .map(|k| {
                let lower = f64::from_bits(k << Self::SHIFT);
                thresholds.partition_point(|&t| t <= lower) as u16
            })
            .collect();
        BinLookup {
            bins: *bins,
            thresholds,
            table,
            key0,
        }
    }

    /// The bins it looks up.
    pub fn bins(&self) -> &RadialBins {
        &self.bins
    }

    /// [`RadialBins::index`]`(r)`, bitwise.
    #[inline]
    pub fn index(&self, r: f64) -> usize {
        // Below t_1 = r_min, and NaN: the inner disk, as `index`.
        if r.is_nan() || r < self.thresholds[0] {
            return 0;
        }
        // Beyond the last cell (past t_{len−1}): start from the last cell.
        let cell = (((r.to_bits() >> Self::SHIFT) - self.key0) as usize).min(self.table.len() - 1);
        let mut k = self.table[cell] as usize;
        while k < self.thresholds.len() && self.thresholds[k] <= r {
            k += 1;
        }
        k
    }
}

/// The smallest f64 r ≥ 0 with `bins.index(r) ≥ j` (1 ≤ j < len): stepping
/// ulp by ulp from the analytic edge, which is within a few ulps of it; a
/// bisection over the bit patterns if it is not.
fn threshold(bins: &RadialBins, j: usize) -> f64 {
    let at_least = |r: f64| bins.index(r) >= j;
    let up = |r: f64| f64::from_bits(r.to_bits() + 1);
    let down = |r: f64| f64::from_bits(r.to_bits() - 1);
    let mut r = bins.r_min * 10f64.powf((j - 1) as f64 / bins.per_decade as f64);
    for _ in 0..64 {
        match (at_least(r), at_least(down(r))) {
            (true, false) => return r,
            (true, true) => r = down(r),
            (false, _) => r = up(r),
        }
    }
    // Bisection on the ordered bit patterns of positive f64.
    let (mut lo, mut hi) = (0u64, f64::MAX.to_bits());
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if at_least(f64::from_bits(mid)) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    f64::from_bits(hi)
}

/// Counts of one simulation (or a chunk, or a shard of it).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProfileTally {
    /// Launched paths.
    pub paths: u64,
    /// Paths reflected specularly at entry (sampled only for diffuse light;
    /// at normal incidence the entry transmittance is a constant weight).
    pub specular: u64,
    /// Exits with exactly one scattering vertex, per radial bin.
    pub exit_single: Vec<u64>,
    /// Exits with two or more scattering vertices, per radial bin.
    pub exit_multi: Vec<u64>,
    /// Exits through the top without scattering (possible only in a slab).
    pub exit_unscattered: u64,
    /// Paths absorbed inside.
    pub absorbed: u64,
    /// Paths leaving through the bottom of a slab.
    pub transmitted: u64,
    /// Paths stopped at the event cap (their bias bound, see `walk`).
    pub truncated: u64,
    /// Scattering events simulated in total.
    pub events: u64,
    /// Radiance along the normal by next-event estimation, when the
    /// simulation tallies it ([`RadianceTally`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radiance: Option<RadianceTally>,
}

/// Fixed-point scale of the radiance sums: one unit is 2⁻³² of a
/// contribution (sr⁻¹).
pub const RADIANCE_Q: f64 = 4_294_967_296.0;

/// Radiance leaving along the normal, by next-event estimation from every
/// scattering vertex (order 1: the first vertex; order ≥ 2: every later
/// one), in fixed-point units of [`RADIANCE_Q`], so that sums stay exact to
/// merge. Per radial bin: Σ over paths of the path's sum q in the bin, and
/// Σ q² (for the standard error); `*_path_sq` is Σ over paths of the square
/// of the path's sum over all bins (the error of the total).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RadianceTally {
    pub single: Vec<u128>,
    pub single_sq: Vec<u128>,
    pub multi: Vec<u128>,
    pub multi_sq: Vec<u128>,
    pub single_path_sq: u128,
    pub multi_path_sq: u128,
}

impl RadianceTally {
    pub fn new(bins: &RadialBins) -> Self {
        let n = bins.len();
        RadianceTally {
            single: vec![0; n],
            single_sq: vec![0; n],
            multi: vec![0; n],
            multi_sq: vec![0; n],
            single_path_sq: 0,
            multi_path_sq: 0,
        }
    }

    /// Adds `other` (exact, associative, commutative).
    pub fn merge(&mut self, other: &RadianceTally) {
        for (a, b) in [
            (&mut self.single, &other.single),
            (&mut self.single_sq, &other.single_sq),
            (&mut self.multi, &other.multi),
            (&mut self.multi_sq, &other.multi_sq),
        ] {
            for (a, b) in a.iter_mut().zip(b) {
                *a += b;
            }
        }
        self.single_path_sq += other.single_path_sq;
        self.multi_path_sq += other.multi_path_sq;
    }

    /// Adds one path's contributions, `(bin, q, order ≥ 2)` per scattering
    /// vertex in any order (sorted in place).
    pub fn add_path(&mut self, contrib: &mut [(usize, u128, bool)]) {
        contrib.sort_unstable_by_key(|c| (c.2, c.0));
        let mut totals = [0u128; 2];
        let mut k = 0;
        while k < contrib.len() {
            let (bin, multi) = (contrib[k].0, contrib[k].2);
            let mut q = 0u128;
            while k < contrib.len() && contrib[k].0 == bin && contrib[k].2 == multi {
                q += contrib[k].1;
                k += 1;
            }
            let (sum, sq) = if multi {
                (&mut self.multi, &mut self.multi_sq)
            } else {
                (&mut self.single, &mut self.single_sq)
            };
            sum[bin] += q;
            sq[bin] += q * q;
            totals[usize::from(multi)] += q;
        }
        self.single_path_sq += totals[0] * totals[0];
        self.multi_path_sq += totals[1] * totals[1];
    }
}

impl ProfileTally {
    pub fn new(bins: &RadialBins) -> Self {
        ProfileTally {
            paths: 0,
            specular: 0,
            exit_single: vec![0; bins.len()],
            exit_multi: vec![0; bins.len()],
            exit_unscattered: 0,
            absorbed: 0,
            transmitted: 0,
            truncated: 0,
            events: 0,
            radiance: None,
        }
    }

    /// An empty tally that also tallies the radiance along the normal.
    pub fn with_radiance(bins: &RadialBins) -> Self {
        ProfileTally {
            radiance: Some(RadianceTally::new(bins)),
            ..ProfileTally::new(bins)
        }
    }

    /// Adds `other` (exact, associative, commutative).
    pub fn merge(&mut self, other: &ProfileTally) {
        self.paths += other.paths;
        self.specular += other.specular;
        for (a, b) in self.exit_single.iter_mut().zip(&other.exit_single) {
            *a += b;
        }
        for (a, b) in self.exit_multi.iter_mut().zip(&other.exit_multi) {
            *a += b;
        }
        self.exit_unscattered += other.exit_unscattered;
        self.absorbed += other.absorbed;
        self.transmitted += other.transmitted;
        self.truncated += other.truncated;
        self.events += other.events;
        match (&mut self.radiance, &other.radiance) {
            (Some(a), Some(b)) => a.merge(b),
            (None, None) => {}
            _ => panic!("merging a radiance tally with one without"),
        }
    }

    /// Paths that ended in some way: equals `paths` for a finished tally.
    pub fn accounted(&self) -> u64 {
        self.specular
            + self.exit_single.iter().sum::<u64>()
            + self.exit_multi.iter().sum::<u64>()
            + self.exit_unscattered
            + self.absorbed
            + self.transmitted
            + self.truncated
    }
}

/// A fraction of the incident power with its standard error.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value: f64,
    pub stderr: f64,
}

/// Converts counts to fractions of incident power.
///
/// `weight` is the power each launched path carries as a fraction of the
/// incident power *before* any sampled event: the constant entry
/// transmittance 1 − F(1) at normal incidence, 1 when entry is sampled.
#[derive(Clone, Copy, Debug)]
pub struct Normalizer {
    pub paths: u64,
    pub weight: f64,
}

impl Normalizer {
    /// Fraction of power for `count` binomial successes out of `paths`, with
    /// its standard error sqrt(c(1 − c/N))/N.
    pub fn fraction(&self, count: u64) -> Estimate {
        let n = self.paths.max(1) as f64;
        let c = count as f64;
        Estimate {
            value: self.weight * c / n,
            stderr: self.weight * (c * (1.0 - c / n)).max(0.0).sqrt() / n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::rng::PathRng;

    /// The lookup is `index` bitwise: on log-uniform radii over every bin
    /// and beyond, within ±64 ulps of every threshold, and at the special
    /// values, for the default bins and two others.
    #[test]
    fn lookup_is_index_bitwise() {
        let cases = [
            RadialBins::default(),
            RadialBins {
                r_min: 0.01,
                r_max: 10.0,
                per_decade: 7,
            },
            RadialBins {
                r_min: 1e-4,
                r_max: 1e3,
                per_decade: 64,
            },
        ];
        for bins in cases {
            let lookup = bins.lookup();
            let check =
                |r: f64| assert_eq!(lookup.index(r), bins.index(r), "{bins:?} at r = {r:e}");
            let mut rng = PathRng::new(3, 0);
            for _ in 0..200_000 {
                check(10f64.powf(-6.0 + 11.0 * rng.uniform()));
            }
            for &t in &lookup.thresholds {
                assert!(bins.index(t) > bins.index(f64::from_bits(t.to_bits() - 1)));
                for k in 0..=128u64 {
                    check(f64::from_bits(t.to_bits() + k - 64));
                }
            }
            for r in [
                0.0,
                -1.0,
                f64::NAN,
                f64::INFINITY,
                f64::MAX,
                f64::MIN_POSITIVE,
            ] {
                check(r);
            }
            assert_eq!(lookup.thresholds.len(), bins.len() - 1);
        }
    }
}
