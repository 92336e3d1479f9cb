//! The learned meta-model: (d, α, ρ) → Gaussian-mixture aggregation kernel
//! (docs/design.md §3 step 3, §4), evaluated on the fly.
//!
//! # Parameterisation
//! For pair distance d at unit density, with λ = d/2 + 1 MFP (the
//! normalisation of the path-density histograms, [`crate::forward::kernel`]),
//! component k of K is an isotropic Gaussian on the axis with
//!
//! * weight w_k = softmax(ℓ)_k, ℓ_0 = 0 (K − 1 free logits),
//! * centre t_k = d/2 + λ·μ_k (MFP from x_i toward x_e), s_k = 0,
//! * width σ_k = λ·e^{ς_k} (MFP).
//!
//! Each of the 3K − 1 shape parameters θ_j = (ℓ, μ, ς) is a tensor Chebyshev
//! polynomial θ_j(x, y) = Σ_{a ≤ n_x, b ≤ n_y} c_{jab} T_a(x) T_b(y) in
//!
//! * x ∈ [−1, 1]: ln d mapped linearly over the trained range of ln d,
//! * y ∈ [−1, 1]: sqrt(1 − α) mapped linearly over the trained range.
//!
//! Why these choices: in λ units the kernel changes slowly and smoothly from
//! the near field (d ≪ 1: a blob of ~1 MFP around x_i ≈ x_e) to the far field
//! (d ≫ 1: spread along the axis), so low-degree polynomials in ln d suffice;
//! sqrt(1 − α) is the albedo coordinate of diffusion theory (σ_tr/σ_t ∝
//! sqrt(1 − α)), the same as the basis BSSRDF's. Polynomials (rather than
//! splines) keep evaluation to a few dozen multiply-adds and are globally
//! smooth. Outside the trained box, a file that carries an outer model
//! (fitted over a wider box) hands the query to it
//! ([`MetaModelFile::at`]); beyond every box the inputs are clamped to the
//! edge (`clamped` is reported). Inside the box, cells with too few contributing
//! paths to fit ([`crate::fit::meta::MIN_PATHS`]: the low-albedo corners)
//! have no data, and there the polynomials extrapolate from their
//! neighbours (docs/method.md §4, "Where the meta-model has no data").
//!
//! Density: K(·; d, α, ρ) = K(·; ρd, α, 1) with lengths divided by ρ
//! ([`super::kernel::scale_for_density`]).

#[cfg(doc)]
use super::kernel::scale_for_density;
use super::kernel::{Component, Gmm, optical_distance};
use crate::error::{Error, Result};
use crate::fastmath::exp4;
use crate::pair::VertexClass;
use crate::provenance::Provenance;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Format tag of meta-model files.
pub const META_FORMAT: &str = "svkernel.metamodel";
/// Version of the meta-model file format.
pub const META_VERSION: u32 = 1;
/// Largest supported polynomial degree per axis (fixed-size evaluation).
pub const MAX_DEGREE: usize = 7;
/// Width (MFP) standing in for a δ (the exact first-vertex kernel).
pub const DELTA_SIGMA: f64 = 1e-6;
/// Largest number of mixture components.
pub const MAX_K: usize = 5;
const _: () = assert!(3 * MAX_K - 1 <= PACK);

/// Parameters padded to a fixed width for the evaluation's inner loop.
const PACK: usize = 16;

/// One meta-model (one vertex class).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MetaModel {
    /// Mixture components K.
    pub k: usize,
    /// Polynomial degrees in x (ln d) and y (sqrt(1 − α)).
    pub deg_x: usize,
    pub deg_y: usize,
    /// Trained range of ln d (unit density) and of α.
    pub ln_d_range: [f64; 2],
    pub alpha_range: [f64; 2],
    /// `coeffs[j]` for parameter j (ℓ_1..ℓ_{K−1}, μ_0..μ_{K−1}, ς_0..ς_{K−1}),
    /// `(deg_x + 1)·(deg_y + 1)` values, index `a·(deg_y + 1) + b`.
    pub coeffs: Vec<Vec<f64>>,
    /// Derived constants for evaluation (built on first use; not serialised).
    #[serde(skip)]
    prepared: std::sync::OnceLock<Prepared>,
}

/// Evaluation constants of a [`MetaModel`].
#[derive(Clone, Debug)]
struct Prepared {
    /// `packed[i][j]` = coeffs[j][i], padded to [`PACK`] parameters.
    packed: Vec<[f64; PACK]>,
    /// x = ln d·x_scale + x_offset, y = sqrt(1 − α)·y_scale + y_offset.
    x_scale: f64,
    x_offset: f64,
    y_scale: f64,
    y_offset: f64,
    /// The trained range of d (e^ln_d_range), for [`MetaModel::holds`].
    d_range: [f64; 2],
}

impl PartialEq for MetaModel {
    fn eq(&self, o: &Self) -> bool {
        (
            self.k,
            self.deg_x,
            self.deg_y,
            self.ln_d_range,
            self.alpha_range,
            &self.coeffs,
        ) == (
            o.k,
            o.deg_x,
            o.deg_y,
            o.ln_d_range,
            o.alpha_range,
            &o.coeffs,
        )
    }
}

/// The result of a query.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelQuery {
    pub gmm: Gmm,
    /// True if (ρd, α) was outside the trained range and clamped to it.
    pub clamped: bool,
}

/// Chebyshev T_0..T_{MAX_DEGREE} at t (all of them: a fixed, branch-free
/// recurrence; callers read the first deg + 1).
#[inline(always)]
fn cheb(t: f64) -> [f64; MAX_DEGREE + 1] {
    let mut out = [0.0; MAX_DEGREE + 1];
    out[0] = 1.0;
    out[1] = t;
    for j in 2..=MAX_DEGREE {
        out[j] = (2.0 * t).mul_add(out[j - 1], -out[j - 2]);
    }
    out
}

impl MetaModel {
    /// A model from its coefficients (`coeffs[j]` per parameter, see the
    /// field docs); validity is checked by [`MetaModelFile::load`].
    pub fn new(
        k: usize,
        (deg_x, deg_y): (usize, usize),
        ln_d_range: [f64; 2],
        alpha_range: [f64; 2],
        coeffs: Vec<Vec<f64>>,
    ) -> Self {
        MetaModel {
            k,
            deg_x,
            deg_y,
            ln_d_range,
            alpha_range,
            coeffs,
            prepared: Default::default(),
        }
    }

    /// Number of shape parameters 3K − 1.
    pub fn n_params(k: usize) -> usize {
        3 * k - 1
    }

    /// Coefficients per parameter.
    pub fn n_coeffs(&self) -> usize {
        (self.deg_x + 1) * (self.deg_y + 1)
    }

    /// The normalised coordinates (x, y) of (d at unit density, α), clamped
    /// to [−1, 1]², and whether clamping happened.
    pub fn coordinates(&self, d: f64, alpha: f64) -> ([f64; 2], bool) {
        let p = self.prepared();
        let x = d.max(1e-300).ln().mul_add(p.x_scale, p.x_offset);
        let y = (1.0 - alpha.clamp(0.0, 1.0))
            .sqrt()
            .mul_add(p.y_scale, p.y_offset);
        let clamp = |v: f64| if v.is_nan() { 0.0 } else { v.clamp(-1.0, 1.0) };
        let (xc, yc) = (clamp(x), clamp(y));
        // Clamped only if moved by more than rounding (the box edges map to ±1).
        ([xc, yc], (xc - x).abs() > 1e-12 || (yc - y).abs() > 1e-12)
    }

    /// Whether optical distance `d1` (MFP at unit density) and `alpha`
    /// lie in the trained box (its edges included).
    #[inline]
    pub fn holds(&self, d1: f64, alpha: f64) -> bool {
        let p = self.prepared();
        (p.d_range[0]..=p.d_range[1]).contains(&d1)
            && (self.alpha_range[0]..=self.alpha_range[1]).contains(&alpha)
    }

    fn prepared(&self) -> &Prepared {
        self.prepared.get_or_init(|| {
            let [l0, l1] = self.ln_d_range;
            let ya = (1.0 - self.alpha_range[1]).max(0.0).sqrt();
            let yb = (1.0 - self.alpha_range[0]).max(0.0).sqrt();
            Prepared {
                packed: (0..self.n_coeffs())
                    .map(|i| std::array::from_fn(|j| self.coeffs.get(j).map_or(0.0, |c| c[i])))
                    .collect(),
                x_scale: 2.0 / (l1 - l0),
                x_offset: -2.0 * l0 / (l1 - l0) - 1.0,
                y_scale: 2.0 / (yb - ya),
                y_offset: -2.0 * ya / (yb - ya) - 1.0,
                // Rounding of e^ln(d) does not move the edges out.
                d_range: [l0.exp() * (1.0 - 1e-12), l1.exp() * (1.0 + 1e-12)],
            }
        })
    }

    /// The tensor basis T_a(x)·T_b(y) at (x, y), in coefficient order.
    pub fn basis(&self, [x, y]: [f64; 2]) -> Vec<f64> {
        let (tx, ty) = (cheb(x), cheb(y));
        let mut out = Vec::with_capacity(self.n_coeffs());
        for a in tx.iter().take(self.deg_x + 1) {
            for b in ty.iter().take(self.deg_y + 1) {
                out.push(a * b);
            }
        }
        out
    }

    /// The shape parameters θ at normalised coordinates (first 3K − 1
    /// entries; no allocation), with the parameters padded to `W` (≤ [`PACK`]).
    /// The tensor sum row by row, Σ_a T_a(x)·(Σ_b c_ab T_b(y)): the inner sums of
    /// different rows a are independent, so they overlap in the pipeline
    /// instead of forming one (deg_x + 1)(deg_y + 1)-long chain of
    /// dependent multiply-adds per parameter.
    #[inline(always)]
    fn params_packed<const W: usize>(&self, [x, y]: [f64; 2]) -> [f64; 3 * MAX_K - 1] {
        let (tx, ty) = (cheb(x), cheb(y));
        let ny = self.deg_y + 1;
        let packed = &self.prepared().packed;
        let mut acc = [0.0; W];
        for (rows, &txa) in packed.chunks_exact(ny).zip(&tx[..=self.deg_x]) {
            let mut row = [0.0; W];
            for (c, &tyb) in rows.iter().zip(&ty[..ny]) {
                for (o, c) in row.iter_mut().zip(c) {
                    *o = c.mul_add(tyb, *o);
                }
            }
            for (o, r) in acc.iter_mut().zip(&row) {
                *o = r.mul_add(txa, *o);
            }
        }
        std::array::from_fn(|j| if j < W { acc[j] } else { 0.0 })
    }

    /// The mixture of `K` components from shape parameters θ at
    /// unit-density distance d (module docs), every length multiplied by
    /// `scale`, written into `out` (reusing its allocation). `K` is a
    /// compile-time constant so that every loop below unrolls.
    #[inline(always)]
    fn gmm_scaled_into<const K: usize>(theta: &[f64], d: f64, scale: f64, out: &mut Gmm) {
        let lambda = 0.5 * d + 1.0;
        let logit = |i: usize| if i == 0 { 0.0 } else { theta[i - 1] };
        let m = (1..K).map(logit).fold(0.0, f64::max);
        // The 2K exponentials (softmax, widths) four at a time ([`exp4`],
        // ≤ 2 ulp; every argument is bounded: logits minus their maximum,
        // log widths clamped to ±30).
        let mut args = [0.0; 4 * (2 * MAX_K).div_ceil(4)];
        for i in 0..K {
            args[i] = logit(i) - m;
            args[K + i] = theta[2 * K - 1 + i].clamp(-30.0, 30.0);
        }
        let mut e = [0.0; 4 * (2 * MAX_K).div_ceil(4)];
        for c in 0..(2 * K).div_ceil(4) {
            let a = wide::f64x4::from([
                args[4 * c],
                args[4 * c + 1],
                args[4 * c + 2],
                args[4 * c + 3],
            ]);
            e[4 * c..4 * c + 4].copy_from_slice(&exp4(a).to_array());
        }
        let inv_z = 1.0 / e[..K].iter().sum::<f64>();
        let (ts, ss) = (scale * 0.5 * d, scale * lambda);
        let components: [Component; K] = std::array::from_fn(|i| Component {
            weight: e[i] * inv_z,
            t: ss.mul_add(theta[K - 1 + i], ts),
            s: 0.0,
            sigma: ss * e[K + i],
        });
        out.components.clear();
        out.components.extend_from_slice(&components);
    }

    /// [`Self::eval_into`] for `K` components and parameters padded to `W`.
    #[inline(always)]
    fn eval_k<const K: usize, const W: usize>(
        &self,
        d: f64,
        alpha: f64,
        rho: f64,
        out: &mut Gmm,
    ) -> bool {
        let d1 = optical_distance(d, rho);
        let (xy, clamped) = self.coordinates(d1, alpha);
        let theta = self.params_packed::<W>(xy);
        Self::gmm_scaled_into::<K>(&theta, d1.max(0.0), 1.0 / rho, out);
        clamped
    }

    /// The kernel at (d, α, ρ): evaluated at the optical distance ρd and
    /// unit density, then all lengths divided by ρ (the law of
    /// [`scale_for_density`], applied while building the mixture).
    #[inline]
    pub fn eval(&self, d: f64, alpha: f64, rho: f64) -> KernelQuery {
        let mut gmm = Gmm {
            components: Vec::with_capacity(self.k),
        };
        let clamped = self.eval_into(d, alpha, rho, &mut gmm);
        KernelQuery { gmm, clamped }
    }

    /// [`Self::eval`] into an existing mixture (its allocation is reused: no
    /// allocation per query, as in a renderer's inner loop); returns
    /// `clamped`.
    #[inline]
    pub fn eval_into(&self, d: f64, alpha: f64, rho: f64, out: &mut Gmm) -> bool {
        // K ≤ 3 has at most 8 shape parameters: half the multiply-adds.
        match self.k {
            1 => self.eval_k::<1, { PACK / 2 }>(d, alpha, rho, out),
            2 => self.eval_k::<2, { PACK / 2 }>(d, alpha, rho, out),
            3 => self.eval_k::<3, { PACK / 2 }>(d, alpha, rho, out),
            4 => self.eval_k::<4, PACK>(d, alpha, rho, out),
            5 => self.eval_k::<5, PACK>(d, alpha, rho, out),
            k => panic!("meta-model with K = {k} outside 1..={MAX_K} (not validated)"),
        }
    }

    fn check(&self, path: &Path, class: &str) -> Result<()> {
        let bad =
            |key: &str, msg: String| Err(Error::format(path, format!("models.{class}.{key}"), msg));
        if !(1..=MAX_K).contains(&self.k) {
            return bad("k", format!("{} not in 1..={MAX_K}", self.k));
        }
        if self.deg_x > MAX_DEGREE || self.deg_y > MAX_DEGREE {
            return bad("deg_x/deg_y", format!("degrees must be <= {MAX_DEGREE}"));
        }
        if self.coeffs.len() != Self::n_params(self.k)
            || self.coeffs.iter().any(|c| c.len() != self.n_coeffs())
        {
            return bad(
                "coeffs",
                format!(
                    "expected {} × {} coefficients",
                    Self::n_params(self.k),
                    self.n_coeffs()
                ),
            );
        }
        if self.coeffs.iter().flatten().any(|c| !c.is_finite()) {
            return bad("coeffs", "non-finite coefficient".into());
        }
        let [l0, l1] = self.ln_d_range;
        let [a0, a1] = self.alpha_range;
        if !(l0.is_finite() && l1.is_finite() && l0 < l1) {
            return bad("ln_d_range", "must be finite and increasing".into());
        }
        if !((0.0..1.0).contains(&a0) && a0 < a1 && a1 <= 1.0) {
            return bad("alpha_range", "must satisfy 0 <= a0 < a1 <= 1".into());
        }
        Ok(())
    }
}

/// The shipped file: one meta-model per vertex class.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MetaModelFile {
    pub format: String,
    pub version: u32,
    pub all: MetaModel,
    /// `None`: the exact first-vertex kernel of normal incidence — the first
    /// scattering vertex of a collimated normal beam lies straight below x_i
    /// (measured: the whole first-vertex mass in the bin of t = 0, s = 0), a
    /// δ at x_i, returned as one component of width [`DELTA_SIGMA`].
    pub first: Option<MetaModel>,
    pub last: MetaModel,
    /// The medium it was trained for.
    pub g: f64,
    pub eta: f64,
    pub provenance: Provenance,
    /// A model of a wider box, which answers the queries that fall outside
    /// this one's ([`Self::at`]); its box holds this one's, and it has no
    /// outer model of its own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outer: Option<Box<MetaModelFile>>,
}

impl MetaModelFile {
    /// The model that answers a query at optical distance `d1` (MFP at
    /// unit density) and albedo `alpha`: this one inside its all-vertex
    /// box, else its outer model if it has one (which clamps to its own,
    /// wider box).
    #[inline]
    pub fn at(&self, d1: f64, alpha: f64) -> &MetaModelFile {
        match &self.outer {
            Some(o) if !self.all.holds(d1, alpha) => o,
            _ => self,
        }
    }

    /// The model of the widest box: the outer one if there is one.
    fn widest(&self) -> &MetaModelFile {
        self.outer.as_deref().unwrap_or(self)
    }

    /// The albedos covered: the outer model's range if there is one.
    pub fn alpha_range(&self) -> [f64; 2] {
        self.widest().all.alpha_range
    }

    /// The optical distances covered (MFP at unit density): the outer
    /// model's range if there is one.
    pub fn d_range(&self) -> [f64; 2] {
        self.widest().all.ln_d_range.map(f64::exp)
    }

    /// The kernel of `class` at pair distance `d` (MFP), albedo `alpha`
    /// and density `rho`: a Gaussian mixture in the pair frame (t from x_i
    /// toward x_e, s across, MFP), and whether (d, α) was clamped to the
    /// trained range: this model's, or outside it its outer model's
    /// ([`Self::at`]).
    ///
    /// ```
    /// use svkernel::prelude::*;
    /// let models = Models::builtin()?;
    /// let q = models.meta.eval(VertexClass::All, 1.0, 0.9, 1.0);
    /// let mass: f64 = q.gmm.components.iter().map(|c| c.weight).sum();
    /// assert!(!q.clamped && (mass - 1.0).abs() < 1e-9);
    /// // The density law: at ρ = 4 the same optical distance is 4× shorter.
    /// let dense = models.meta.eval(VertexClass::All, 0.25, 0.9, 4.0);
    /// let t = |g: &Gmm| g.components.iter().map(|c| c.weight * c.t).sum::<f64>();
    /// assert!((t(&dense.gmm) - t(&q.gmm) / 4.0).abs() < 1e-9);
    /// # Ok::<(), svkernel::Error>(())
    /// ```
    pub fn eval(&self, class: VertexClass, d: f64, alpha: f64, rho: f64) -> KernelQuery {
        let d1 = optical_distance(d, rho);
        let m = self.at(d1, alpha);
        match (class, &m.first) {
            (VertexClass::All, _) => m.all.eval(d, alpha, rho),
            (VertexClass::Last, _) => m.last.eval(d, alpha, rho),
            (VertexClass::First, Some(f)) => f.eval(d, alpha, rho),
            (VertexClass::First, None) => {
                let (_, clamped) = m.all.coordinates(d1, alpha);
                KernelQuery {
                    gmm: Gmm {
                        components: vec![Component {
                            weight: 1.0,
                            t: 0.0,
                            s: 0.0,
                            sigma: DELTA_SIGMA,
                        }],
                    },
                    clamped,
                }
            }
        }
    }
}

impl crate::doc::Document for MetaModelFile {
    const FORMAT: &'static str = META_FORMAT;
    const VERSION: u32 = META_VERSION;

    fn validate(&self, path: &std::path::Path) -> crate::Result<()> {
        let f = self;
        f.all.check(path, "all")?;
        if let Some(m) = &f.first {
            m.check(path, "first")?;
        }
        f.last.check(path, "last")?;
        if let Some(o) = &f.outer {
            let bad = |msg: String| Err(Error::format(path, "outer", msg));
            if o.outer.is_some() {
                return bad("an outer model has no outer model of its own".into());
            }
            if (o.g - f.g).abs() > 1e-12 || (o.eta - f.eta).abs() > 1e-12 {
                return bad(format!(
                    "trained for g = {}, η = {}, but the model for g = {}, η = {}",
                    o.g, o.eta, f.g, f.eta
                ));
            }
            for (name, inner, outer) in [("all", &f.all, &o.all), ("last", &f.last, &o.last)] {
                let holds = |a: [f64; 2], b: [f64; 2]| b[0] <= a[0] + 1e-12 && a[1] <= b[1] + 1e-12;
                if !holds(inner.ln_d_range, outer.ln_d_range)
                    || !holds(inner.alpha_range, outer.alpha_range)
                {
                    return bad(format!(
                        "its {name}-vertex box (d ∈ {:?} MFP, α ∈ {:?}) does not hold the model's \
                         (d ∈ {:?}, α ∈ {:?})",
                        outer.ln_d_range.map(f64::exp),
                        outer.alpha_range,
                        inner.ln_d_range.map(f64::exp),
                        inner.alpha_range
                    ));
                }
            }
            o.validate(path).map_err(|e| match e {
                Error::Format { key, msg, .. } => Error::format(path, format!("outer.{key}"), msg),
                e => e,
            })?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(k: usize) -> MetaModel {
        let (dx, dy) = (2, 2);
        let n = (dx + 1) * (dy + 1);
        let coeffs = (0..MetaModel::n_params(k))
            .map(|j| {
                (0..n)
                    .map(|i| 0.1 * ((j * 7 + i * 3) % 5) as f64 - 0.2)
                    .collect()
            })
            .collect();
        MetaModel {
            k,
            deg_x: dx,
            deg_y: dy,
            ln_d_range: [0.1f64.ln(), 10f64.ln()],
            alpha_range: [0.2, 0.99],
            coeffs,
            prepared: Default::default(),
        }
    }

    #[test]
    fn kernels_are_valid_everywhere_and_clamping_is_reported() {
        for k in 1..=MAX_K {
            let m = model(k);
            for d in [1e-6, 0.1, 1.0, 10.0, 50.0] {
                for a in [0.0, 1e-9, 0.5, 1.0 - 1e-9, 1.0] {
                    for rho in [1e-3, 1.0, 1e3] {
                        let q = m.eval(d, a, rho);
                        assert!(q.gmm.is_valid(), "{k} {d} {a} {rho}: {:?}", q.gmm);
                        let inside = (0.1..=10.0).contains(&(d * rho)) && (0.2..=0.99).contains(&a);
                        assert_eq!(q.clamped, !inside, "{d} {a} {rho}");
                    }
                }
            }
        }
    }

    fn file(all: MetaModel, last: MetaModel) -> MetaModelFile {
        MetaModelFile {
            format: META_FORMAT.into(),
            version: META_VERSION,
            all,
            first: None,
            last,
            g: 0.3,
            eta: 1.5,
            provenance: Provenance::current(),
            outer: None,
        }
    }

    #[test]
    fn the_outer_model_answers_outside_the_box_only() {
        use crate::doc::Document;
        let wide = |mut m: MetaModel| {
            m.ln_d_range = [0.05f64.ln(), 20f64.ln()];
            m.alpha_range = [0.05, 0.999];
            for c in m.coeffs.iter_mut().flatten() {
                *c = -*c;
            }
            m
        };
        let mut f = file(model(3), model(4));
        f.outer = Some(Box::new(file(wide(model(3)), wide(model(4)))));
        let path = Path::new("m.json");
        f.validate(path).unwrap();
        assert_eq!(f.alpha_range(), [0.05, 0.999]);
        assert!((f.d_range()[1] - 20.0).abs() < 1e-9);
        let outer = f.outer.as_deref().unwrap();
        for (d, a, rho, inside) in [
            (1.0, 0.5, 1.0, true),
            (10.0, 0.99, 1.0, true),
            (0.1, 0.2, 1.0, true),
            // The optical distance decides: 6 MFP at ρ = 2 is 12.
            (6.0, 0.5, 2.0, false),
            (15.0, 0.5, 1.0, false),
            (0.07, 0.5, 1.0, false),
            (1.0, 0.1, 1.0, false),
            (1.0, 0.995, 1.0, false),
            // Beyond both boxes, the outer one clamps.
            (50.0, 0.9999, 1.0, false),
        ] {
            let want = if inside { &f } else { outer };
            assert!(std::ptr::eq(f.at(d * rho, a), want), "{d} {a} {rho}");
            for class in [VertexClass::All, VertexClass::Last] {
                let m = |x: &MetaModelFile| match class {
                    VertexClass::All => x.all.eval(d, a, rho),
                    _ => x.last.eval(d, a, rho),
                };
                assert_eq!(f.eval(class, d, a, rho), m(want), "{d} {a} {rho}");
                assert_ne!(m(&f).gmm, m(outer).gmm, "the two models differ");
            }
        }
        // An outer model that does not hold the box, or has its own outer
        // model, or another medium, is refused with the key named.
        let key = |f: &MetaModelFile| match f.validate(path) {
            Err(Error::Format { key, .. }) => key,
            other => panic!("{other:?}"),
        };
        let mut narrow = f.clone();
        narrow.outer.as_mut().unwrap().last.alpha_range = [0.3, 0.999];
        assert_eq!(key(&narrow), "outer");
        let mut nested = f.clone();
        nested.outer.as_mut().unwrap().outer = Some(Box::new(file(model(3), model(4))));
        assert_eq!(key(&nested), "outer");
        let mut medium = f.clone();
        medium.outer.as_mut().unwrap().g = 0.0;
        assert_eq!(key(&medium), "outer");
        let mut broken = f.clone();
        broken.outer.as_mut().unwrap().all.coeffs[0][0] = f64::NAN;
        assert_eq!(key(&broken), "outer.models.all.coeffs");
        // It round-trips through JSON; a file without one reads as before.
        let text = serde_json::to_string(&f).unwrap();
        assert_eq!(serde_json::from_str::<MetaModelFile>(&text).unwrap(), f);
        let plain = serde_json::to_string(&file(model(3), model(4))).unwrap();
        assert!(!plain.contains("\"outer\""), "{plain}");
    }

    #[test]
    fn density_scaling_law() {
        let m = model(3);
        let a = m.eval(0.5, 0.8, 2.0).gmm;
        let b = crate::metamodel::kernel::scale_for_density(&m.eval(1.0, 0.8, 1.0).gmm, 2.0);
        for (x, y) in a.components.iter().zip(&b.components) {
            assert!((x.weight - y.weight).abs() < 1e-15);
            assert!((x.t - y.t).abs() < 1e-12 && (x.sigma - y.sigma).abs() < 1e-12);
        }
    }
}
