//! Scattering-aware texture design: the albedo map whose appearance, after
//! sub-surface scattering, matches a target.
//!
//! Light scatters under the surface of a print and blurs its texture; the
//! remedy is a pre-compensated albedo map. Per channel, [`design`] solves
//!
//! min over α ∈ [lo, hi]ⁿ of F(α) = (1/n) Σ_e (M_e(α) − T_e)² + W·(1/n) Σ_{e~e'} (α_e − α_e')²
//!
//! with M the appearance of [`appearance::Appearance`] (diffuse reflectance
//! at each texel centre under unit irradiance), T the target, e~e' the
//! horizontally and vertically adjacent texel pairs, and the bounds the
//! printable gamut.
//!
//! # Solver
//! The unknowns are the reflectances u = R_d(α) of the homogeneous material
//! (a tabulated monotone map): in u the appearance is close to a blur of u, so the
//! problem is well scaled over the whole gamut, and the bounds stay a box.
//! 1. **Warm start**: up to `warm_start` projected fixed-point steps
//!    u ← Π(u + β(T − M(u))) (Van Cittert 1931, relaxed), one model
//!    evaluation each, each from the best map so far. For a blur with
//!    transfer H ∈ (0, 1] each step shrinks a frequency's error by
//!    1 − βH, where gradient steps on F shrink it by about 1 − H²: the mid
//!    frequencies that scattering damps converge far sooner. The iteration
//!    is not monotone (a frequency whose response lies outside (0, 2/β)
//!    grows, and the gamut clamps); a step that raises F is discarded and
//!    halves β. The warm start ends when β < [`MIN_RELAXATION`] or a step
//!    lowers F by less than [`MIN_GAIN`].
//! 2. **L-BFGS-B** (Byrd, Lu, Nocedal & Zhu 1995; the `rcompat-lbfgsb`
//!    crate) on F and its exact gradient, `iterations` per channel split
//!    over `rounds`. `learned`'s kernel shapes are anchored at the naive map
//!    for the warm start and re-anchored at the current map before each
//!    round (the appearance module's docs); the warm start ignores the
//!    smoothness term, L-BFGS-B minimises all of F.
//!
//! The model's appearance of the designed map (`predicted`) is anchored at
//! that map, as the renderer anchors its kernels.
//!
//! The **naive** map, the baseline, gives every texel the albedo whose
//! homogeneous material has the target's reflectance: R_d(α) = T (clamped
//! to the gamut).

pub mod appearance;
pub mod stack;

use crate::error::{Error, Result};
use crate::metamodel::basis::BasisModel;
use crate::metamodel::meta::MetaModelFile;
use crate::render::svbssrdf::{AlbedoSpace, Method, SPACE_BLUR, Split};
use appearance::{Appearance, Illumination, Quadrature};
use rcompat_lbfgsb::{ArithmeticProfile, Bounds, OptimControl, OptimEvent};
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::time::Instant;

/// What to design and how.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    /// The forward model (`learned`, `factorized` or `point`).
    pub method: Method,
    /// Texel size τ (MFP).
    pub texel: f64,
    /// The printable albedo range [lo, hi].
    pub albedo_range: [f64; 2],
    pub illumination: Illumination,
    /// Projected fixed-point steps before L-BFGS-B (module docs).
    pub warm_start: usize,
    /// L-BFGS-B iterations per channel, over all rounds.
    pub iterations: usize,
    /// L-BFGS-B rounds (learned): the kernel shapes are re-anchored at the
    /// current map before each.
    pub rounds: usize,
    /// Smoothness weight W.
    pub smoothness: f64,
    pub quadrature: Quadrature,
    /// The space of α_t's coarse part (learned; the renderer's default).
    pub albedo_space: AlbedoSpace,
    /// The scale b (MFP) that splits α_t's fine from its coarse part.
    pub space_blur: f64,
    /// The kernel of that split (its darker regime's, [`Split`]).
    pub split: Split,
    /// α_t under the interior vertices' kernel (learned; the renderer's
    /// `interior` variant).
    pub interior_kernel: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            method: Method::Learned,
            texel: 0.05,
            albedo_range: [0.2, 0.99],
            illumination: Illumination::Uniform,
            warm_start: 30,
            iterations: 10,
            rounds: 1,
            smoothness: 0.0,
            quadrature: Quadrature::default(),
            albedo_space: AlbedoSpace::default(),
            space_blur: SPACE_BLUR,
            split: Split::default(),
            interior_kernel: false,
        }
    }
}

impl Settings {
    /// Refuses settings no design can run with, naming the setting.
    pub fn validate(&self) -> Result<()> {
        let [lo, hi] = self.albedo_range;
        if !(0.0 < lo && lo < hi && hi < 1.0) {
            return Err(Error::param(
                "albedo-range",
                format!("{lo},{hi}"),
                "0 < LO < HI < 1",
            ));
        }
        if !(self.texel > 0.0 && self.texel.is_finite()) {
            return Err(Error::param("texel", self.texel, "finite and > 0 (MFP)"));
        }
        if !(self.smoothness >= 0.0 && self.smoothness.is_finite()) {
            return Err(Error::param(
                "smoothness",
                self.smoothness,
                "finite and >= 0",
            ));
        }
        if self.iterations == 0 || self.rounds == 0 {
            return Err(Error::param(
                "iterations/rounds",
                format!("{}/{}", self.iterations, self.rounds),
                ">= 1",
            ));
        }
        Ok(())
    }
}

/// What a [`Step`] of the history is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// A fixed-point step of the warm start (before the step).
    FixedPoint,
    /// The start of an L-BFGS-B round, after (re-)anchoring.
    Anchor,
    /// An accepted L-BFGS-B iteration.
    Lbfgsb,
}

/// One step of a channel's history.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Step {
    pub channel: usize,
    pub stage: Stage,
    pub round: usize,
    /// The step's number within its stage (L-BFGS-B: over all rounds).
    pub iteration: usize,
    /// F at the step (with the round's anchor).
    pub objective: f64,
    /// Seconds since the channel's start.
    pub seconds: f64,
}

/// The designed maps of every channel.
#[derive(Clone, Debug)]
pub struct Design {
    /// Per channel, row-major `ny × nx`.
    pub albedo: Vec<Vec<f64>>,
    pub naive: Vec<Vec<f64>>,
    /// The model's appearance of the designed and of the naive map.
    pub predicted: Vec<Vec<f64>>,
    pub predicted_naive: Vec<Vec<f64>>,
    pub history: Vec<Step>,
    /// Objective and gradient evaluations, over all channels.
    pub evaluations: usize,
    /// Seconds spent building the model (offsets, kernel tables).
    pub setup_seconds: f64,
    /// Seconds spent optimising.
    pub solve_seconds: f64,
    /// Why each channel's last round stopped.
    pub stops: Vec<String>,
}

/// R_d⁻¹(t) on [lo, hi] (bisection; R_d increases with α).
pub fn naive_albedo(basis: &BasisModel, t: f64, [lo, hi]: [f64; 2]) -> f64 {
    let (mut a, mut b) = (lo, hi);
    if basis.r_d(a) >= t {
        return lo;
    }
    if basis.r_d(b) <= t {
        return hi;
    }
    for _ in 0..60 {
        let m = 0.5 * (a + b);
        if basis.r_d(m) < t {
            a = m;
        } else {
            b = m;
        }
    }
    0.5 * (a + b)
}

/// The warm start ends once rises have halved its relaxation β below this.
pub const MIN_RELAXATION: f64 = 0.2;

/// The warm start ends once a step lowers F by less than this fraction.
pub const MIN_GAIN: f64 = 0.005;

/// Nodes of [`Reflectance`].
const REFLECTANCE_NODES: usize = 4096;

/// The solver's coordinate: the reflectance u = R_d(α) of the homogeneous
/// material, in which the appearance is close to a blur of u (near-identity
/// scaling, so that L-BFGS-B's steps mean the same everywhere in the
/// gamut). α(u) is the piecewise-linear interpolant of (R_d(α_k), α_k) at
/// [`REFLECTANCE_NODES`] albedos uniform on [lo, hi]; its derivative is
/// exact for that interpolant.
struct Reflectance {
    u: Vec<f64>,
    alpha: Vec<f64>,
}

impl Reflectance {
    fn new(basis: &BasisModel, [lo, hi]: [f64; 2]) -> Self {
        let alpha: Vec<f64> = (0..REFLECTANCE_NODES)
            .map(|k| lo + (hi - lo) * k as f64 / (REFLECTANCE_NODES - 1) as f64)
            .collect();
        let u = alpha.iter().map(|&a| basis.r_d(a)).collect();
        Reflectance { u, alpha }
    }

    /// u(α) on the same interpolant (the inverse of [`Self::alpha`]).
    fn u_of(&self, a: f64) -> f64 {
        let k = self
            .alpha
            .partition_point(|&x| x <= a)
            .clamp(1, REFLECTANCE_NODES - 1)
            - 1;
        let f = (a - self.alpha[k]) / (self.alpha[k + 1] - self.alpha[k]);
        (self.u[k] + f * (self.u[k + 1] - self.u[k]))
            .clamp(self.u[0], self.u[REFLECTANCE_NODES - 1])
    }

    fn range(&self) -> [f64; 2] {
        [self.u[0], self.u[REFLECTANCE_NODES - 1]]
    }

    /// (α(u), dα/du).
    fn alpha(&self, u: f64) -> (f64, f64) {
        let k = self
            .u
            .partition_point(|&x| x <= u)
            .clamp(1, REFLECTANCE_NODES - 1)
            - 1;
        let slope = (self.alpha[k + 1] - self.alpha[k]) / (self.u[k + 1] - self.u[k]);
        let a = (self.alpha[k] + slope * (u - self.u[k]))
            .clamp(self.alpha[0], self.alpha[REFLECTANCE_NODES - 1]);
        (a, slope)
    }
}

/// The smoothness term W·(1/n)Σ_{e~e'}(α_e − α_e')² and its gradient.
fn smoothness(alpha: &[f64], nx: usize, w: f64) -> (f64, Vec<f64>) {
    let n = alpha.len() as f64;
    let mut grad = vec![0.0; alpha.len()];
    if w == 0.0 {
        return (0.0, grad);
    }
    let ny = alpha.len() / nx;
    let mut s = 0.0;
    for i in 0..ny {
        for j in 0..nx {
            let e = i * nx + j;
            for nb in [(j + 1 < nx).then(|| e + 1), (i + 1 < ny).then(|| e + nx)]
                .into_iter()
                .flatten()
            {
                let d = alpha[e] - alpha[nb];
                s += d * d;
                grad[e] += 2.0 * w * d / n;
                grad[nb] -= 2.0 * w * d / n;
            }
        }
    }
    (w * s / n, grad)
}

/// The data term (1/n)Σ(M − T)².
fn misfit(m: &[f64], target: &[f64]) -> f64 {
    m.iter()
        .zip(target)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        / m.len() as f64
}

/// One channel's solve: the map, its history, the solver's stop message
/// and the number of model evaluations.
struct Solved {
    alpha: Vec<f64>,
    /// The appearance of the naive map under its own anchor (the warm
    /// start's first evaluation), if the warm start ran.
    naive_m: Option<Vec<f64>>,
    steps: Vec<Step>,
    stop: String,
    evaluations: usize,
}

/// Designs channel `c` from its naive map ([module docs](self)).
#[allow(clippy::too_many_arguments)]
fn solve_channel(
    app: &Appearance,
    coord: &Reflectance,
    settings: &Settings,
    c: usize,
    target: &[f64],
    naive: &[f64],
    nx: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<Solved> {
    let start = Instant::now();
    let [u_lo, u_hi] = coord.range();
    let w = settings.smoothness;
    let full = |alpha: &[f64], m: &[f64]| misfit(m, target) + smoothness(alpha, nx, w).0;
    let step = |stage: Stage, round: usize, iteration: usize, objective: f64| Step {
        channel: c,
        stage,
        round,
        iteration,
        objective,
        seconds: start.elapsed().as_secs_f64(),
    };
    let mut steps = Vec::new();
    let mut evaluations = 0;
    let mut x = naive.to_vec();
    let mut anchor = app.anchor(&x);
    // The warm start: projected fixed-point steps u ← Π(u + β(T − M(u)))
    // from the best map so far; a step that raises F halves β.
    let mut u: Vec<f64> = x.iter().map(|&a| coord.u_of(a)).collect();
    let (mut best, mut best_u, mut best_m) = (f64::INFINITY, u.clone(), Vec::new());
    let mut beta = 1.0;
    let mut naive_m = None;
    for k in 0..settings.warm_start {
        let m = app.appearance(&x, &anchor);
        evaluations += 1;
        progress(evaluations);
        let f = full(&x, &m);
        steps.push(step(Stage::FixedPoint, 0, k, f));
        if k == 0 {
            naive_m = Some(m.clone());
        }
        if f < best {
            let gain = (best - f) / f;
            (best, best_u, best_m) = (f, u, m);
            if gain < MIN_GAIN {
                break;
            }
        } else {
            beta *= 0.5;
            if beta < MIN_RELAXATION {
                break;
            }
        }
        u = best_u
            .iter()
            .zip(&best_m)
            .zip(target)
            .map(|((v, mm), tt)| (v + beta * (tt - mm)).clamp(u_lo, u_hi))
            .collect();
        x = u.iter().map(|&v| coord.alpha(v).0).collect();
    }
    let moved = best.is_finite();
    if moved {
        x = best_u.iter().map(|&v| coord.alpha(v).0).collect();
    }
    let rounds = if settings.method == Method::Learned {
        settings.rounds
    } else {
        1
    };
    let mut done = 0;
    let mut stop = String::from("no iterations");
    for round in 0..rounds {
        if round > 0 || moved {
            anchor = app.anchor(&x);
        }
        let iters = (settings.iterations - done) / (rounds - round);
        if iters == 0 {
            continue;
        }
        let m = app.appearance(&x, &anchor);
        steps.push(step(Stage::Anchor, round, done, full(&x, &m)));
        // F and ∂F/∂u at u; the gradient is computed with the value and
        // handed to the solver's gradient call at the same point.
        let evals = RefCell::new(0usize);
        let eval = |p: &[f64]| -> (f64, Vec<f64>) {
            let (alpha, slope): (Vec<f64>, Vec<f64>) = p.iter().map(|&v| coord.alpha(v)).unzip();
            let lin = app.linearize(&alpha, &anchor);
            let n = alpha.len() as f64;
            let g: Vec<f64> = lin
                .m
                .iter()
                .zip(target)
                .map(|(a, b)| 2.0 * (a - b) / n)
                .collect();
            let (s, sg) = smoothness(&alpha, nx, w);
            let grad = app.gradient(&lin, &anchor, &g);
            *evals.borrow_mut() += 1;
            let du = grad
                .iter()
                .zip(&sg)
                .zip(&slope)
                .map(|((a, b), d)| (a + b) * d);
            let f = misfit(&lin.m, target) + s;
            let du = du.collect();
            app.release(lin);
            (f, du)
        };
        let cache: RefCell<Option<(Vec<f64>, Vec<f64>)>> = RefCell::new(None);
        let accepted = RefCell::new(Vec::new());
        let bounds = Bounds::new(vec![u_lo; x.len()], vec![u_hi; x.len()])
            .map_err(|e| Error::param("albedo-range", e, "valid bounds"))?;
        let mut control = OptimControl::default_for_dimension(x.len());
        control.maxit = iters;
        control.factr = 1e5;
        let u0: Vec<f64> = x.iter().map(|&a| coord.u_of(a)).collect();
        let result = rcompat_lbfgsb::optim_lbfgsb_with_gradient_observed(
            u0,
            bounds,
            |p: &[f64]| {
                let (f, g) = eval(p);
                *cache.borrow_mut() = Some((p.to_vec(), g));
                progress(evaluations + *evals.borrow());
                f
            },
            |p: &[f64]| {
                if let Some((q, g)) = cache.borrow().as_ref()
                    && q.as_slice() == p
                {
                    return g.clone();
                }
                eval(p).1
            },
            control,
            ArithmeticProfile::legacy(),
            |ev: OptimEvent| {
                if let OptimEvent::Accepted { value, .. } = ev {
                    accepted.borrow_mut().push(value);
                }
            },
        )
        .map_err(|e| Error::param("design solver", e, "a successful L-BFGS-B run"))?;
        for value in accepted.into_inner() {
            done += 1;
            steps.push(step(Stage::Lbfgsb, round, done, value));
        }
        done = done.max(settings.iterations * (round + 1) / rounds);
        evaluations += evals.into_inner();
        x = result.par.iter().map(|&v| coord.alpha(v).0).collect();
        stop = result.message.clone();
    }
    Ok(Solved {
        alpha: x,
        naive_m,
        steps,
        stop,
        evaluations,
    })
}

/// One designed channel.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ChannelDesign {
    /// The designed map, row-major `ny × nx`.
    pub albedo: Vec<f64>,
    /// The model's appearance of the designed and of the naive map.
    pub predicted: Vec<f64>,
    pub predicted_naive: Vec<f64>,
    pub history: Vec<Step>,
    /// Why L-BFGS-B stopped.
    pub stop: String,
    /// Model evaluations (fixed-point steps and L-BFGS-B's).
    pub evaluations: usize,
    /// Seconds this channel took.
    pub seconds: f64,
}

/// A prepared design problem: the model, the coordinate and the naive
/// maps, channel by channel ([`Designer::channel`]) so that a caller can
/// checkpoint between channels.
pub struct Designer<'a> {
    app: Appearance,
    coord: Reflectance,
    settings: Settings,
    target: &'a [Vec<f64>],
    naive: Vec<Vec<f64>>,
    nx: usize,
    setup_seconds: f64,
}

impl<'a> Designer<'a> {
    /// Validates the target (per channel row-major `ny × nx` reflectances
    /// in [0, 1]) and the settings, and builds the model.
    pub fn new(
        target: &'a [Vec<f64>],
        nx: usize,
        ny: usize,
        basis: &BasisModel,
        meta: Option<&MetaModelFile>,
        settings: &Settings,
    ) -> Result<Self> {
        settings.validate()?;
        if target.is_empty() || target.iter().any(|t| t.len() != nx * ny) {
            return Err(Error::param(
                "target",
                "shape",
                "one or three channels of ny × nx values",
            ));
        }
        if let Some(bad) = target.iter().flatten().find(|v| !(0.0..=1.0).contains(*v)) {
            return Err(Error::param(
                "target",
                bad,
                "reflectances in [0, 1] (no NaN)",
            ));
        }
        let start = Instant::now();
        let range = settings.albedo_range;
        let naive: Vec<Vec<f64>> = target
            .iter()
            .map(|t| t.iter().map(|&v| naive_albedo(basis, v, range)).collect())
            .collect();
        // The offsets cover the naive maps' albedos (2nd and 98th percentiles).
        let mut all: Vec<f64> = naive.iter().flatten().copied().collect();
        all.sort_by(f64::total_cmp);
        let pick = |q: f64| all[((all.len() - 1) as f64 * q).round() as usize];
        let span = [
            pick(0.02).min(0.9),
            pick(0.98).max(pick(0.02) + 0.05).min(0.99),
        ];
        let app = Appearance::new(
            settings.method,
            basis,
            meta,
            nx,
            ny,
            settings.texel,
            settings.illumination,
            span,
            &settings.quadrature,
        )?
        .with_split(settings.albedo_space, settings.space_blur, settings.split)?;
        let app = match (settings.interior_kernel, meta) {
            (true, Some(meta)) => app.with_interior_kernel(meta),
            _ => app,
        };
        Ok(Designer {
            app,
            coord: Reflectance::new(basis, range),
            settings: settings.clone(),
            target,
            naive,
            nx,
            setup_seconds: start.elapsed().as_secs_f64(),
        })
    }

    pub fn channels(&self) -> usize {
        self.target.len()
    }

    /// The appearance problem of channel `c` at its naive map with the
    /// least-squares weights g = M − target, for an independent check of
    /// the gradient ([`Appearance::export_check`]; `basis` is the model
    /// the designer was built with).
    pub fn export_check(&self, basis: &BasisModel, c: usize) -> serde_json::Value {
        let alpha = &self.naive[c];
        let anchor = self.app.anchor(alpha);
        let m = self.app.appearance(alpha, &anchor);
        let g: Vec<f64> = m.iter().zip(&self.target[c]).map(|(m, t)| m - t).collect();
        self.app.export_check(basis, alpha, &anchor, &g)
    }

    /// The naive maps.
    pub fn naive(&self) -> &[Vec<f64>] {
        &self.naive
    }

    /// Seconds spent building the model.
    pub fn setup_seconds(&self) -> f64 {
        self.setup_seconds
    }

    /// About how many model evaluations a channel takes (fixed-point steps
    /// plus about 1.2 per L-BFGS-B iteration), for progress.
    pub fn evaluations_per_channel(&self) -> usize {
        self.settings.warm_start + self.settings.iterations * 6 / 5
    }

    /// Designs channel `c`; `progress(k)` after each of its evaluations.
    pub fn channel(&self, c: usize, mut progress: impl FnMut(usize)) -> Result<ChannelDesign> {
        let start = Instant::now();
        let (app, naive) = (&self.app, &self.naive[c]);
        let s = solve_channel(
            app,
            &self.coord,
            &self.settings,
            c,
            &self.target[c],
            naive,
            self.nx,
            &mut progress,
        )?;
        Ok(ChannelDesign {
            predicted: app.appearance(&s.alpha, &app.anchor(&s.alpha)),
            predicted_naive: s
                .naive_m
                .unwrap_or_else(|| app.appearance(naive, &app.anchor(naive))),
            albedo: s.alpha,
            history: s.steps,
            stop: s.stop,
            evaluations: s.evaluations,
            seconds: start.elapsed().as_secs_f64(),
        })
    }
}

impl Design {
    /// The design of `channels` (in channel order) from their naive maps.
    pub fn assemble(
        naive: &[Vec<f64>],
        setup_seconds: f64,
        channels: Vec<ChannelDesign>,
    ) -> Design {
        let mut d = Design {
            albedo: Vec::new(),
            naive: naive.to_vec(),
            predicted: Vec::new(),
            predicted_naive: Vec::new(),
            history: Vec::new(),
            evaluations: 0,
            setup_seconds,
            solve_seconds: 0.0,
            stops: Vec::new(),
        };
        for ch in channels {
            d.albedo.push(ch.albedo);
            d.predicted.push(ch.predicted);
            d.predicted_naive.push(ch.predicted_naive);
            d.history.extend(ch.history);
            d.stops.push(ch.stop);
            d.evaluations += ch.evaluations;
            d.solve_seconds += ch.seconds;
        }
        d
    }
}

/// Designs every channel of `target` ([`Designer`]). `progress(done,
/// total)` is called after every model evaluation, with the evaluations
/// done and an estimate of the total.
pub fn design(
    target: &[Vec<f64>],
    nx: usize,
    ny: usize,
    basis: &BasisModel,
    meta: Option<&MetaModelFile>,
    settings: &Settings,
    mut progress: impl FnMut(usize, usize),
) -> Result<Design> {
    let designer = Designer::new(target, nx, ny, basis, meta, settings)?;
    let total = designer.evaluations_per_channel() * designer.channels();
    let mut done = 0;
    let mut channels = Vec::new();
    for c in 0..designer.channels() {
        let ch = designer.channel(c, |k| progress(done + k, total.max(done + k)))?;
        done += ch.evaluations;
        channels.push(ch);
    }
    Ok(Design::assemble(
        designer.naive(),
        designer.setup_seconds(),
        channels,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40 × 40 target (τ = 0.1 MFP): reflectance 0.17 ± 0.07 in a
    /// product of sines of period 2 MFP, detail at the transport's scale.
    fn squares() -> Vec<f64> {
        let n = 40;
        let w = 2.0 * std::f64::consts::PI / 20.0;
        (0..n * n)
            .map(|k| {
                let (i, j) = ((k / n) as f64, (k % n) as f64);
                0.17 + 0.07 * (w * i).sin() * (w * j).sin()
            })
            .collect()
    }

    fn settings(method: Method) -> Settings {
        Settings {
            method,
            texel: 0.1,
            iterations: 30,
            quadrature: Quadrature {
                rings: 8,
                angles: 2,
            },
            ..Settings::default()
        }
    }

    #[test]
    fn the_design_brings_the_appearance_closer_than_the_naive_map() {
        let basis = crate::testing::shipped_basis();
        let meta = crate::testing::shipped_meta();
        let t = squares();
        let d = design(
            std::slice::from_ref(&t),
            40,
            40,
            &basis,
            Some(&meta),
            &settings(Method::Learned),
            |_, _| {},
        )
        .unwrap();
        let err = |m: &[f64]| {
            (m.iter().zip(&t).map(|(a, b)| (a - b).powi(2)).sum::<f64>()
                / t.iter().map(|b| b * b).sum::<f64>())
            .sqrt()
        };
        let (naive, designed) = (err(&d.predicted_naive[0]), err(&d.predicted[0]));
        assert!(
            designed < 0.4 * naive,
            "model error: naive {naive}, designed {designed}"
        );
        // Inside the gamut, and L-BFGS-B never let the objective rise within a round.
        assert!(d.albedo[0].iter().all(|a| (0.2..=0.99).contains(a)));
        for w in d.history.windows(2) {
            if w[1].stage == Stage::Lbfgsb && w[1].round == w[0].round {
                assert!(w[1].objective <= w[0].objective * (1.0 + 1e-12));
            }
        }
        // The naive map has the target's reflectance texel by texel.
        for (a, v) in d.naive[0].iter().zip(&t) {
            assert!((basis.r_d(*a) - v).abs() < 1e-9);
        }
    }

    #[test]
    fn designs_are_independent_of_the_thread_count() {
        let basis = crate::testing::shipped_basis();
        let meta = crate::testing::shipped_meta();
        let t = squares();
        let mut s = settings(Method::Learned);
        s.iterations = 4;
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    design(
                        std::slice::from_ref(&t),
                        40,
                        40,
                        &basis,
                        Some(&meta),
                        &s,
                        |_, _| {},
                    )
                    .unwrap()
                })
        };
        let (one, two) = (run(1), run(2));
        assert_eq!(one.albedo, two.albedo);
        assert_eq!(one.predicted, two.predicted);
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        let s = Settings {
            albedo_range: [0.9, 0.5],
            ..Settings::default()
        };
        assert!(
            s.validate()
                .unwrap_err()
                .to_string()
                .contains("albedo-range")
        );
        let basis = crate::testing::shipped_basis();
        let e = design(
            &[vec![0.5, f64::NAN]],
            2,
            1,
            &basis,
            None,
            &Settings::default(),
            |_, _| {},
        );
        assert!(e.unwrap_err().to_string().contains("target"));
    }
}
