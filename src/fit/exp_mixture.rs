//! Per-profile fit of an exponential mixture to a binned radial density
//! (docs/design.md §3 step 2a).
//!
//! Data: ring averages y_j of p(r) over [lo_j, hi_j] with standard errors,
//! and the energy beyond the last ring (a "tail bin" with hi = ∞ whose y is
//! an energy, not a density): without it a component with B → 0 could hide
//! any amount of energy beyond the observed range.
//! Model: the exact ring average of p(r) = Σ_k A_k e^{−B_k r},
//! m_j = (1/Δ_j) Σ_k (A_k/B_k)·e^{−B_k lo_j}·(1 − e^{−B_k Δ_j}) — no
//! bin-centre approximation. Residuals r_j = (m_j − y_j)/σ_j. Parameters
//! θ = (ln A_1..K, θ_1..K) with bounded rates
//! ln B = ln B_min + (ln B_max − ln B_min)·σ(θ) (σ the logistic function),
//! B ∈ [[`B_MIN`], [`B_MAX`]]: rates cannot run off to 0 or ∞, where the
//! problem degenerates. Derivatives (c_kj the term of component k):
//! ∂m_j/∂ln A_k = c_kj,
//! ∂m_j/∂ln B_k = (A_k e^{−B_k lo_j}/Δ_j)·[Δ_j e^{−B_k Δ_j} − lo_j(1 − e^{−B_k Δ_j})] − c_kj.

use super::lm::{Blocks, FitError, FitOptions, FitReport, nnls, solve};
use crate::forward::medium::Observable;
use crate::forward::profile::ProfileDoc;
use crate::metamodel::basis::{B_MAX, B_MIN, ExpMixture, component_bin, rate_from_theta};
use levenberg_marquardt::LeastSquaresProblem;
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use serde::{Deserialize, Serialize};

/// Ring averages of a radial density with their standard errors.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BinnedDensity {
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
    pub y: Vec<f64>,
    pub sigma: Vec<f64>,
}

/// Which part of a profile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Order {
    Single,
    Multi,
}

impl BinnedDensity {
    /// The rings of `doc` (inner disk included, overflow excluded) of the
    /// exitance (`p_1`, `p_m`) or of the radiance along the normal (`l_1`,
    /// `l_m`), and the tail bin [r_max, ∞) with the energy beyond r_max. A
    /// ring with no count gets the standard error of one count (of one
    /// path's largest next-event contribution, f_HG(1)·T(1)/η², for
    /// radiance), so empty bins pull the model toward zero without infinite
    /// weight. Panics if `doc` does not hold `observable`
    /// ([`ProfileDoc::observed`]; [`crate::fit::basis::fit_basis`] checks).
    pub fn from_profile(doc: &ProfileDoc, order: Order, observable: Observable) -> Self {
        let o = doc
            .observed(observable)
            .expect("a profile holding the observable");
        let (y, s) = match order {
            Order::Single => (o.p_1, o.p_1_stderr),
            Order::Multi => (o.p_m, o.p_m_stderr),
        };
        let (b, m) = (&doc.bins, &doc.config.medium);
        let weight = crate::forward::walk::entry_weight(&doc.config.source, m.eta);
        let power = doc.config.source.power();
        let n = doc.paths.max(1) as f64;
        let unit = match observable {
            Observable::Exitance => 1.0,
            Observable::Radiance => {
                crate::forward::sampling::hg_pdf(m.g, 1.0)
                    * crate::forward::walk::normal_exit_factor(m.eta)
            }
        };
        let mut out = BinnedDensity {
            lo: vec![],
            hi: vec![],
            y: vec![],
            sigma: vec![],
        };
        for k in 0..y.len() {
            let (lo, hi) = (b.edges[k], b.edges[k + 1]);
            let one_count = unit * power * weight / (n * (hi - lo));
            out.lo.push(lo);
            out.hi.push(hi);
            out.y.push(y[k]);
            out.sigma.push(s[k].max(one_count));
        }
        // The tail bin [r_max, ∞): its energy from the overflow bin, as a
        // fraction of the incident power.
        let tail = match (observable, &doc.radiance) {
            (Observable::Radiance, Some(r)) => match order {
                Order::Single => r.overflow.0,
                Order::Multi => r.overflow.1,
            },
            _ => {
                let counts = match order {
                    Order::Single => &doc.tally.exit_single,
                    Order::Multi => &doc.tally.exit_multi,
                };
                let norm = crate::forward::tally::Normalizer {
                    paths: doc.tally.paths,
                    weight,
                };
                let f = norm.fraction(*counts.last().unwrap_or(&0));
                crate::forward::tally::Estimate {
                    value: power * f.value,
                    stderr: power * f.stderr,
                }
            }
        };
        out.lo.push(*b.edges.last().unwrap_or(&0.0));
        out.hi.push(f64::INFINITY);
        out.y.push(tail.value);
        out.sigma.push(tail.stderr.max(unit * power * weight / n));
        out
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.y.len()
    }

    pub fn is_empty(&self) -> bool {
        self.y.is_empty()
    }

    /// Width of bin j; 1 for the tail bin, whose y is an energy.
    pub fn width(&self, j: usize) -> f64 {
        if self.hi[j].is_finite() {
            self.hi[j] - self.lo[j]
        } else {
            1.0
        }
    }

    /// Energy ∫p of the data (Σ y_j Δ_j).
    pub fn energy(&self) -> f64 {
        (0..self.len()).map(|j| self.y[j] * self.width(j)).sum()
    }

    /// Energy-weighted mean radius of the data (the tail bin counts at its
    /// lower edge).
    pub fn mean_radius(&self) -> f64 {
        let e = self.energy().max(1e-300);
        let mid = |j: usize| {
            if self.hi[j].is_finite() {
                0.5 * (self.lo[j] + self.hi[j])
            } else {
                self.lo[j]
            }
        };
        (0..self.len())
            .map(|j| self.y[j] * self.width(j) * mid(j))
            .sum::<f64>()
            / e
    }
}

/// Inverse of [`rate_from_theta`] (B clamped inside the bounds).
pub fn theta_from_rate(b: f64) -> f64 {
    let span = (B_MAX / B_MIN).ln();
    let s = ((b.clamp(B_MIN * 1.0001, B_MAX * 0.9999)).ln() - B_MIN.ln()) / span;
    (s / (1.0 - s)).ln()
}

/// e^x with x clamped to ±300, so that a wild trial step of the optimiser
/// gives large but finite values (and finite residuals) instead of ∞·0.
#[inline]
pub fn safe_exp(x: f64) -> f64 {
    x.clamp(-300.0, 300.0).exp()
}

/// The least-squares problem of one profile.
pub struct ExpMixtureFit<'a> {
    pub data: &'a BinnedDensity,
    /// n of p(r) = Σ A r^n e^{−Br}.
    pub power: u32,
    /// (ln A_1..K, ln B_1..K).
    pub theta: DVector<f64>,
}

impl ExpMixtureFit<'_> {
    pub fn k(&self) -> usize {
        self.theta.len() / 2
    }

    pub fn mixture(&self) -> ExpMixture {
        let k = self.k();
        ExpMixture {
            a: (0..k).map(|i| safe_exp(self.theta[i])).collect(),
            b: (0..k)
                .map(|i| rate_from_theta(self.theta[k + i]).0)
                .collect(),
            power: self.power,
        }
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for ExpMixtureFit<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.theta.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.theta.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let m = self.mixture();
        let d = self.data;
        let r = DVector::from_iterator(
            d.len(),
            (0..d.len()).map(|j| (m.bin_mean(d.lo[j], d.hi[j]) - d.y[j]) / d.sigma[j]),
        );
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let (k, d) = (self.k(), self.data);
        let mut j = DMatrix::zeros(d.len(), 2 * k);
        for i in 0..k {
            let a = safe_exp(self.theta[i]);
            let (b, dlnb_dtheta) = rate_from_theta(self.theta[k + i]);
            for row in 0..d.len() {
                let (c, dlnb) = component_bin(a, b, self.power, d.lo[row], d.hi[row]);
                j[(row, i)] = c / d.sigma[row];
                j[(row, k + i)] = dlnb * dlnb_dtheta / d.sigma[row];
            }
        }
        j.iter().all(|v| v.is_finite()).then_some(j)
    }
}

impl Blocks for ExpMixtureFit<'_> {
    fn blocks(&self) -> Vec<(String, std::ops::Range<usize>)> {
        vec![("bins".into(), 0..self.data.len())]
    }
}

/// Amplitudes A ≥ 0 for fixed rates B by weighted NNLS.
pub fn amplitudes_for_rates(data: &BinnedDensity, b: &[f64], power: u32) -> (Vec<f64>, f64) {
    let n = data.len();
    let design = DMatrix::from_fn(n, b.len(), |j, k| {
        component_bin(1.0, b[k], power, data.lo[j], data.hi[j]).0 / data.sigma[j]
    });
    let rhs = DVector::from_iterator(n, (0..n).map(|j| data.y[j] / data.sigma[j]));
    let a = nnls(&design, &rhs);
    let chi2 = (&design * &a - rhs).norm_squared();
    (a.iter().cloned().collect(), chi2)
}

/// Log-spaced rates relative to the data's scale: B_k = (β_k / r̄) with β
/// from `lo` to `hi` (r̄ the mean radius).
pub fn rate_grid(data: &BinnedDensity, k: usize, lo: f64, hi: f64) -> Vec<f64> {
    let s = 1.0 / data.mean_radius().max(1e-6);
    (0..k)
        .map(|i| s * lo * (hi / lo).powf(i as f64 / (k.max(2) - 1) as f64))
        .collect()
}

/// Rates of the dense grid used by [`initial_guess`].
const DENSE_RATES: usize = 80;

/// Robust start for `k` components (no hand tuning): non-negative least
/// squares over a dense log grid of rates in [B_MIN, B_MAX] gives a sparse,
/// globally optimal amplitude vector; its runs of adjacent active rates
/// become components (amplitudes summed, rates averaged in log weighted by
/// energy). The `k` most energetic clusters are kept; if there are fewer,
/// the most energetic one is split in two (rates ×/÷ 1.5) until there are
/// `k`. Every component starts with a real share of the energy, so none is
/// dead (a component with A ≈ 0 has no gradient and never revives).
pub fn initial_guess(data: &BinnedDensity, k: usize, power: u32) -> ExpMixture {
    let grid: Vec<f64> = (0..DENSE_RATES)
        .map(|i| 2.0 * B_MIN * (0.25 * B_MAX / B_MIN).powf(i as f64 / (DENSE_RATES - 1) as f64))
        .collect();
    let (a, _) = amplitudes_for_rates(data, &grid, power);
    let energy_of = |a: f64, b: f64| a / b.powi(power as i32 + 1);
    // Clusters of adjacent active rates: (A, energy, Σ energy·ln B).
    let mut clusters: Vec<(f64, f64, f64)> = Vec::new();
    let mut open = false;
    for (ai, bi) in a.iter().zip(&grid) {
        if *ai > 0.0 {
            let e = energy_of(*ai, *bi);
            match (open, clusters.last_mut()) {
                (true, Some(c)) => {
                    c.0 += ai;
                    c.1 += e;
                    c.2 += e * bi.ln();
                }
                _ => clusters.push((*ai, e, e * bi.ln())),
            }
            open = true;
        } else {
            open = false;
        }
    }
    if clusters.is_empty() {
        // No signal at all: a flat start on the data's scale.
        let b = rate_grid(data, k, 0.1, 100.0);
        let e = data.energy().abs().max(1e-30) / k as f64;
        return ExpMixture {
            a: b.iter().map(|b| e * b.powi(power as i32 + 1)).collect(),
            b,
            power,
        };
    }
    clusters.sort_by(|x, y| y.1.total_cmp(&x.1));
    clusters.truncate(k);
    let mut comps: Vec<(f64, f64)> = clusters.iter().map(|c| (c.1, (c.2 / c.1).exp())).collect(); // (energy, B)
    while comps.len() < k {
        comps.sort_by(|x, y| y.0.total_cmp(&x.0));
        let (e, b) = comps[0];
        comps[0] = (0.5 * e, (b * 1.5).min(0.5 * B_MAX));
        comps.push((0.5 * e, (b / 1.5).max(2.0 * B_MIN)));
    }
    let mut m = ExpMixture {
        a: comps
            .iter()
            .map(|(e, b)| e * b.powi(power as i32 + 1))
            .collect(),
        b: comps.iter().map(|c| c.1).collect(),
        power,
    };
    sort_by_rate(&mut m);
    m
}

/// Fits `k` exponentials, p(r) = Σ A r^power e^{−Br}, to `data`.
pub fn fit_mixture(
    what: &str,
    data: &BinnedDensity,
    k: usize,
    power: u32,
    opts: &FitOptions,
) -> Result<(ExpMixture, FitReport), FitError> {
    if data.len() < 2 * k + 1 || data.energy() <= 0.0 {
        return Err(FitError::BadData {
            what: what.into(),
            msg: format!(
                "{} bins with energy {:.3e}: too little data for {k} components",
                data.len(),
                data.energy()
            ),
        });
    }
    let init = initial_guess(data, k, power);
    let theta = DVector::from_iterator(
        2 * k,
        init.a
            .iter()
            .map(|v| v.ln())
            .chain(init.b.iter().map(|&b| theta_from_rate(b))),
    );
    let (p, rep) = solve(what, ExpMixtureFit { data, power, theta }, opts)?;
    let mut m = p.mixture();
    sort_by_rate(&mut m);
    Ok((m, rep))
}

/// Orders components by decreasing rate (short range first).
pub fn sort_by_rate(m: &mut ExpMixture) {
    let mut idx: Vec<usize> = (0..m.a.len()).collect();
    idx.sort_by(|&i, &j| m.b[j].total_cmp(&m.b[i]));
    *m = ExpMixture {
        a: idx.iter().map(|&i| m.a[i]).collect(),
        b: idx.iter().map(|&i| m.b[i]).collect(),
        power: m.power,
    };
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::lm::jacobian_mismatch;
    use crate::forward::rng::PathRng;

    fn synthetic(m: &ExpMixture, noise: f64, seed: u64) -> BinnedDensity {
        let mut rng = PathRng::new(seed, 0);
        let edges: Vec<f64> = std::iter::once(0.0)
            .chain((0..=100).map(|k| 1e-3 * 10f64.powf(k as f64 / 20.0)))
            .collect();
        let mut d = BinnedDensity {
            lo: vec![],
            hi: vec![],
            y: vec![],
            sigma: vec![],
        };
        for w in edges.windows(2) {
            let t = m.bin_mean(w[0], w[1]);
            let s = noise * t + 1e-9;
            // Sum of 12 uniforms − 6: an approximately normal deviate.
            let z: f64 = (0..12).map(|_| rng.uniform()).sum::<f64>() - 6.0;
            d.lo.push(w[0]);
            d.hi.push(w[1]);
            d.y.push(t + s * z);
            d.sigma.push(s);
        }
        d
    }

    #[test]
    fn jacobian_matches_numerical() {
        let truth = ExpMixture {
            a: vec![0.2, 0.05, 0.004],
            b: vec![20.0, 2.0, 0.3],
            power: 1,
        };
        let d = synthetic(&truth, 0.01, 1);
        let mut rng = PathRng::new(2, 0);
        for _ in 0..5 {
            let theta = DVector::from_iterator(
                6,
                (0..6).map(|i| {
                    if i < 3 {
                        -4.0 + 3.0 * rng.uniform()
                    } else {
                        -1.5 + 4.0 * rng.uniform()
                    }
                }),
            );
            let mut p = ExpMixtureFit {
                data: &d,
                power: 1,
                theta,
            };
            let err = jacobian_mismatch(&mut p);
            assert!(err < 1e-5, "relative Jacobian error {err}");
            // The crate's own numerical differentiation agrees too.
            let analytic = p.jacobian().unwrap();
            let numeric = levenberg_marquardt::differentiate_numerically(&mut p).unwrap();
            let rel = (analytic - &numeric).norm() / numeric.norm();
            assert!(rel < 1e-6, "differentiate_numerically: {rel}");
        }
    }

    #[test]
    fn recovers_a_known_mixture() {
        for power in [0, 1] {
            recovers(power);
        }
    }

    fn recovers(power: u32) {
        let truth = ExpMixture {
            a: vec![0.2, 0.05, 0.004],
            b: vec![20.0, 2.0, 0.3],
            power,
        };
        let d = synthetic(&truth, 1e-3, 3);
        let (m, rep) = fit_mixture("synthetic", &d, 3, power, &FitOptions::default()).unwrap();
        assert!(rep.chi2_per_dof < 1.5, "{rep:?}");
        assert!((m.energy() / truth.energy() - 1.0).abs() < 1e-3);
        for (k, (a, b)) in truth.a.iter().zip(&truth.b).enumerate() {
            assert!(
                (m.a[k] / a - 1.0).abs() < 0.05 && (m.b[k] / b - 1.0).abs() < 0.05,
                "{m:?}"
            );
        }
    }
}
