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
        (1 + k as usize).min(self.len() - 1)
    }
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
