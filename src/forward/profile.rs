//! Radial-profile simulations: configuration, execution and the output
//! document (`svkernel simulate profile`, `svkernel merge`).

use super::medium::{Medium, Source};
use super::runner::{self, RunOptions, Shard, chunk_paths, chunk_range};
use super::tally::{BinLookup, Estimate, Normalizer, ProfileTally, RadialBins};
use super::walk::{entry_weight, simulate_scalar};
use crate::error::{Error, Result};
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};

/// Format tag and version of profile documents.
pub const PROFILE_FORMAT: &str = "svkernel.profile";
pub const PROFILE_VERSION: u32 = 1;

/// Default cap on scattering events per path (see [`super::walk`]).
pub const DEFAULT_MAX_EVENTS: u32 = 1_000_000;

/// Which implementation of the walk runs. Both consume the same streams; they
/// differ only by rounding (f64 vs f32), so their tallies agree statistically,
/// not bitwise, and documents of different engines do not merge.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Engine {
    /// Plain f64 walk, one path at a time ([`super::walk`]).
    Scalar,
    /// Eight paths per f32 SIMD lane group ([`super::simd`]).
    #[default]
    Lanes,
}

/// Everything that determines a profile simulation's result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileConfig {
    pub medium: Medium,
    pub source: Source,
    /// Paths of the whole (unsharded) simulation.
    pub paths: u64,
    pub seed: u64,
    pub max_events: u32,
    pub bins: RadialBins,
    pub engine: Engine,
    /// Also tally the radiance leaving along the normal (next-event
    /// estimation; the scalar engine only).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub radiance: bool,
}

impl ProfileConfig {
    /// Validates what the constructor of [`Medium`] does not.
    pub fn validate(&self) -> Result<()> {
        Medium::new(
            self.medium.alpha,
            self.medium.g,
            self.medium.eta,
            self.medium.rho,
            self.medium.thickness,
        )?;
        if self.paths == 0 {
            return Err(Error::param("paths", 0, ">= 1"));
        }
        if self.radiance && self.engine != Engine::Scalar {
            return Err(Error::param(
                "engine",
                "lanes",
                "scalar when the radiance is tallied (the lane walk has no next-event estimation)",
            ));
        }
        if self.max_events == 0 {
            return Err(Error::param("max_events", 0, ">= 1"));
        }
        let b = &self.bins;
        if !(b.r_min > 0.0 && b.r_max > b.r_min && b.r_max.is_finite() && b.per_decade > 0) {
            return Err(Error::param(
                "bins",
                format!(
                    "r_min {}, r_max {}, per_decade {}",
                    b.r_min, b.r_max, b.per_decade
                ),
                "0 < r_min < r_max, per_decade > 0",
            ));
        }
        // The last ring must end at r_max (the overflow bin is "beyond
        // r_max"), so r_max/r_min must be a whole number of ring ratios.
        let rings = (b.r_max / b.r_min).log10() * b.per_decade as f64;
        if (rings - rings.round()).abs() > 1e-6 * rings.max(1.0) {
            return Err(Error::param(
                "bins",
                format!(
                    "r_min {}, r_max {}, per_decade {}",
                    b.r_min, b.r_max, b.per_decade
                ),
                "r_max/r_min = 10^(k/per_decade) for a whole number k of rings",
            ));
        }
        Ok(())
    }

    /// Tally of chunk `c`; `bins` is `self.bins.lookup()` (built once per
    /// run by the caller).
    pub fn simulate_chunk(&self, c: u64, bins: &BinLookup) -> ProfileTally {
        assert_eq!(bins.bins(), &self.bins, "a lookup of other bins");
        let (first, count) = chunk_paths(self.paths, c);
        let (m, src, seed) = (&self.medium, &self.source, self.seed);
        match self.engine {
            Engine::Scalar => simulate_scalar(
                m,
                src,
                bins,
                self.max_events,
                seed,
                first,
                count,
                self.radiance,
            ),
            // `validate` refuses the radiance with the lane engine.
            Engine::Lanes => {
                super::simd::simulate_lanes(m, src, bins, self.max_events, seed, first, count)
            }
        }
    }

    /// An empty tally of this simulation's shape.
    pub fn empty_tally(&self) -> ProfileTally {
        if self.radiance {
            ProfileTally::with_radiance(&self.bins)
        } else {
            ProfileTally::new(&self.bins)
        }
    }

    /// Runs the whole simulation or one shard of it.
    pub fn run(&self, shard: Option<Shard>, opts: &RunOptions) -> Result<(ProfileTally, f64)> {
        self.validate()?;
        let key = serde_json::json!({ "config": self, "shard": shard });
        let range = chunk_range(self.paths, shard);
        let lookup = self.bins.lookup();
        let out = runner::run(
            &key,
            range,
            self.empty_tally(),
            |c| self.simulate_chunk(c, &lookup),
            opts,
        )?;
        Ok((out.tally, out.wall_s))
    }
}

/// Per-bin results: ring averages of the radial density p(r) = 2πr·R(r)
/// (1/MFP) and of the exitance R(r) (1/MFP²), split by scattering order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BinResults {
    /// Bin edges in MFP: 0, r_min, …, r_max; the overflow bin [r_max, ∞) is
    /// the last entry of the count arrays and has no density.
    pub edges: Vec<f64>,
    pub p_1: Vec<f64>,
    pub p_1_stderr: Vec<f64>,
    pub p_m: Vec<f64>,
    pub p_m_stderr: Vec<f64>,
    pub r_1: Vec<f64>,
    pub r_m: Vec<f64>,
    /// Fraction of power exiting beyond r_max (single + multiple).
    pub overflow: f64,
    /// Radiance along the normal, when tallied: ring averages of 2πr·L(r)
    /// (1/(MFP·sr) per unit incident power) by scattering order, with their
    /// standard errors; empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub l_1: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub l_1_stderr: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub l_m: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub l_m_stderr: Vec<f64>,
}

/// The radiance along the normal integrated over the surface, ∫L dA per
/// unit incident power (sr⁻¹), by scattering order, with its contribution
/// beyond r_max.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NormalRadiance {
    pub single: Estimate,
    pub multi: Estimate,
    /// (single, multi) beyond r_max, the tally's overflow bin.
    pub overflow: (Estimate, Estimate),
}

impl NormalRadiance {
    /// From the tally's fixed-point sums: the mean per launched path times
    /// the source's power and entry weight.
    fn new(t: &super::tally::RadianceTally, paths: u64, scale: f64) -> Self {
        let last = t.single.len() - 1;
        let est = |sum: u128, sq: u128| radiance_estimate(sum, sq, paths, scale);
        NormalRadiance {
            single: est(t.single.iter().sum(), t.single_path_sq),
            multi: est(t.multi.iter().sum(), t.multi_path_sq),
            overflow: (
                est(t.single[last], t.single_sq[last]),
                est(t.multi[last], t.multi_sq[last]),
            ),
        }
    }
}

/// The mean per path of a fixed-point sum (Σq, Σq²) over `paths` paths,
/// times `scale`, with its standard error.
fn radiance_estimate(sum: u128, sq: u128, paths: u64, scale: f64) -> Estimate {
    use super::tally::RADIANCE_Q;
    let n = paths.max(1) as f64;
    let mean = sum as f64 / RADIANCE_Q / n;
    let var = (sq as f64 / (RADIANCE_Q * RADIANCE_Q) / n - mean * mean).max(0.0);
    Estimate {
        value: scale * mean,
        stderr: scale * (var / n).sqrt(),
    }
}

/// The profile document: summary numbers at top level (names as in the CLI
/// contract), the configuration, per-bin results, the raw integer tally
/// (which `merge` adds) and provenance.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[allow(non_snake_case)]
pub struct ProfileDoc {
    pub format: String,
    pub version: u32,
    pub R_d: f64,
    pub R_d_stderr: f64,
    pub R_1: f64,
    pub R_1_stderr: f64,
    pub R_m: f64,
    pub R_m_stderr: f64,
    /// Specular reflectance at entry (not part of R_d).
    pub R_sp: f64,
    pub absorbed: f64,
    pub transmitted: f64,
    pub transmitted_stderr: f64,
    /// Fraction of paths stopped at the event cap: bounds the bias of R_d.
    pub truncated: f64,
    /// ∫L dA of the radiance along the normal, when tallied.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radiance: Option<NormalRadiance>,
    /// R_d + R_sp + absorbed + transmitted + truncated (+ unscattered exits):
    /// equals 1 up to rounding, by construction of the analog walk.
    pub energy_balance: f64,
    /// Scattering events simulated.
    pub events: u64,
    pub mean_events: f64,
    pub paths: u64,
    pub wall_s: f64,
    pub config: ProfileConfig,
    /// The shard this document holds; `None` for a complete simulation.
    pub shard: Option<Shard>,
    /// Chunk ranges `[lo, hi)` this document's tally covers.
    pub chunks: Vec<(u64, u64)>,
    pub bins: BinResults,
    pub tally: ProfileTally,
    pub provenance: Provenance,
}

impl ProfileDoc {
    /// Derives every reported number from the integer tally.
    pub fn new(
        config: ProfileConfig,
        shard: Option<Shard>,
        chunks: Vec<(u64, u64)>,
        tally: ProfileTally,
        wall_s: f64,
        provenance: Provenance,
    ) -> Self {
        let norm = Normalizer {
            paths: tally.paths,
            weight: entry_weight(&config.source, config.medium.eta),
        };
        let n1: u64 = tally.exit_single.iter().sum();
        let nm: u64 = tally.exit_multi.iter().sum();
        let (r_d, r_1, r_m) = (norm.fraction(n1 + nm), norm.fraction(n1), norm.fraction(nm));
        let r_sp = if config.source.is_normal_incidence() {
            crate::forward::fresnel::r_specular(config.medium.eta)
        } else {
            norm.fraction(tally.specular).value
        };
        let absorbed = norm.fraction(tally.absorbed).value;
        let transmitted = norm.fraction(tally.transmitted);
        let truncated = norm.fraction(tally.truncated).value;
        let unscattered = norm.fraction(tally.exit_unscattered).value;
        let bins = bin_results(&config, &tally, &norm);
        let radiance = tally
            .radiance
            .as_ref()
            .map(|t| NormalRadiance::new(t, tally.paths, config.source.power() * norm.weight));
        ProfileDoc {
            format: PROFILE_FORMAT.into(),
            version: PROFILE_VERSION,
            R_d: r_d.value,
            R_d_stderr: r_d.stderr,
            R_1: r_1.value,
            R_1_stderr: r_1.stderr,
            R_m: r_m.value,
            R_m_stderr: r_m.stderr,
            R_sp: r_sp,
            absorbed,
            transmitted: transmitted.value,
            transmitted_stderr: transmitted.stderr,
            truncated,
            radiance,
            energy_balance: r_d.value
                + r_sp
                + absorbed
                + transmitted.value
                + truncated
                + unscattered,
            events: tally.events,
            mean_events: tally.events as f64 / tally.paths.max(1) as f64,
            paths: tally.paths,
            wall_s,
            config,
            shard,
            chunks,
            bins,
            tally,
            provenance,
        }
    }

    /// The summary R_d (and R₁, Rₘ) with standard errors, as estimates.
    pub fn r_d(&self) -> Estimate {
        Estimate {
            value: self.R_d,
            stderr: self.R_d_stderr,
        }
    }
}

/// One observable of a profile document: its total over the surface (R_d,
/// or ∫L dA) and its ring densities by scattering order.
pub struct Observed<'a> {
    pub total: Estimate,
    pub p_1: &'a [f64],
    pub p_1_stderr: &'a [f64],
    pub p_m: &'a [f64],
    pub p_m_stderr: &'a [f64],
}

impl ProfileDoc {
    /// The exitance or the radiance along the normal; `None` for radiance
    /// when the simulation did not tally it.
    pub fn observed(&self, observable: super::medium::Observable) -> Option<Observed<'_>> {
        let b = &self.bins;
        match observable {
            super::medium::Observable::Exitance => Some(Observed {
                total: self.r_d(),
                p_1: &b.p_1,
                p_1_stderr: &b.p_1_stderr,
                p_m: &b.p_m,
                p_m_stderr: &b.p_m_stderr,
            }),
            super::medium::Observable::Radiance => {
                let r = self.radiance.as_ref()?;
                Some(Observed {
                    total: Estimate {
                        value: r.single.value + r.multi.value,
                        stderr: r.single.stderr.hypot(r.multi.stderr),
                    },
                    p_1: &b.l_1,
                    p_1_stderr: &b.l_1_stderr,
                    p_m: &b.l_m,
                    p_m_stderr: &b.l_m_stderr,
                })
            }
        }
    }
}

impl crate::doc::Document for ProfileDoc {
    const FORMAT: &'static str = PROFILE_FORMAT;
    const VERSION: u32 = PROFILE_VERSION;

    fn validate(&self, path: &std::path::Path) -> crate::Result<()> {
        let doc = self;
        let n = doc.config.bins.len();
        if doc.tally.exit_single.len() != n || doc.tally.exit_multi.len() != n {
            return Err(Error::format(
                path,
                "tally",
                "bin count does not match config.bins",
            ));
        }
        if let Some(r) = &doc.tally.radiance
            && [&r.single, &r.single_sq, &r.multi, &r.multi_sq]
                .iter()
                .any(|v| v.len() != n)
        {
            return Err(Error::format(
                path,
                "tally.radiance",
                "bin count does not match config.bins",
            ));
        }
        if doc.tally.radiance.is_some() != doc.config.radiance {
            return Err(Error::format(
                path,
                "tally.radiance",
                "present if and only if config.radiance is true",
            ));
        }
        if doc.tally.accounted() != doc.tally.paths {
            return Err(Error::format(
                path,
                "tally.paths",
                "counts do not add up to the launched paths",
            ));
        }
        Ok(())
    }
}

fn bin_results(config: &ProfileConfig, tally: &ProfileTally, norm: &Normalizer) -> BinResults {
    let edges = config.bins.edges();
    let power = config.source.power();
    let rings = edges.len() - 1;
    let (mut p_1, mut p_1_stderr, mut p_m, mut p_m_stderr, mut r_1, mut r_m) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for k in 0..rings {
        let (lo, hi) = (edges[k], edges[k + 1]);
        let width = hi - lo;
        let area = std::f64::consts::PI * (hi * hi - lo * lo);
        let e1 = norm.fraction(tally.exit_single[k]);
        let em = norm.fraction(tally.exit_multi[k]);
        p_1.push(power * e1.value / width);
        p_1_stderr.push(power * e1.stderr / width);
        p_m.push(power * em.value / width);
        p_m_stderr.push(power * em.stderr / width);
        r_1.push(power * e1.value / area);
        r_m.push(power * em.value / area);
    }
    let last = config.bins.len() - 1;
    let (mut l_1, mut l_1_stderr, mut l_m, mut l_m_stderr) = (vec![], vec![], vec![], vec![]);
    if let Some(t) = &tally.radiance {
        let scale = power * norm.weight;
        for k in 0..rings {
            let width = edges[k + 1] - edges[k];
            let e1 = radiance_estimate(t.single[k], t.single_sq[k], tally.paths, scale / width);
            let em = radiance_estimate(t.multi[k], t.multi_sq[k], tally.paths, scale / width);
            l_1.push(e1.value);
            l_1_stderr.push(e1.stderr);
            l_m.push(em.value);
            l_m_stderr.push(em.stderr);
        }
    }
    BinResults {
        l_1,
        l_1_stderr,
        l_m,
        l_m_stderr,
        edges,
        p_1,
        p_1_stderr,
        p_m,
        p_m_stderr,
        r_1,
        r_m,
        overflow: norm
            .fraction(tally.exit_single[last] + tally.exit_multi[last])
            .value,
    }
}

/// Merges shard documents (any order) into one. The configurations must be
/// identical and the chunk ranges disjoint; if they tile the whole
/// simulation, the result is the complete document, bitwise equal (up to
/// provenance and wall time) to the unsharded run.
pub fn merge(
    docs: &[(std::path::PathBuf, ProfileDoc)],
    provenance: Provenance,
) -> Result<ProfileDoc> {
    let Some((_, first)) = docs.first() else {
        return Err(Error::param("merge inputs", "none", "at least one file"));
    };
    let mut tally = first.config.empty_tally();
    let mut wall_s = 0.0;
    for (path, d) in docs {
        if d.config != first.config {
            return Err(Error::Merge {
                path: path.clone(),
                msg: "configuration differs from the first input (medium, source, paths, seed, bins, engine must match)".into(),
            });
        }
        tally.merge(&d.tally);
        wall_s += d.wall_s;
    }
    let joined =
        super::runner::join_chunks(docs.iter().map(|(p, d)| (p.as_path(), &d.chunks[..])))?;
    let complete = joined == [chunk_range(first.config.paths, None)];
    let shard = if complete { None } else { first.shard };
    Ok(ProfileDoc::new(
        first.config.clone(),
        shard,
        joined,
        tally,
        wall_s,
        provenance,
    ))
}
