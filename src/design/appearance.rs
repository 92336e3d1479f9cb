//! The appearance of an albedo map under an SV-BSSRDF model, and its exact
//! gradient with respect to every texel.
//!
//! # The estimate
//! The appearance at texel centre x_e is the diffuse reflectance
//! M(x_e) = ∫ E(x_i)·S(x_i, x_e) dx_i under unit irradiance E (uniform over
//! the plane, or 1 inside a disk at the origin). It is estimated with one
//! fixed set of K entry offsets δ_k shared by every texel (x_i = x_e + δ_k):
//! K_r rings stratified in the radial CDF of the balanced mixture of the
//! homogeneous profiles at two albedos (the map's lower and upper ends, so
//! that both short and long transport are covered), K_φ angles per ring,
//! each ring turned by the golden ratio. Weights W_k = 1/(K·p(δ_k)) with p
//! the mixture's area density (1/MFP²). The same offsets everywhere make
//! M a smooth, deterministic function of α: its quadrature error is one
//! stencil's, not per-texel noise that an optimiser would learn to cancel.
//! That error would bias every design, so the profile terms are normalised
//! so that the offsets integrate a homogeneous profile exactly
//! (the type `Normalisation`).
//!
//! # The models (per channel, unit density)
//! * `point`: S = R(d; α_e) = α_e R₁(d) + α_e² Rₘ(d; α_e)/α_e².
//! * `factorized`: S = √(R(d; α_i)·R(d; α_e)).
//! * `learned`: the split form of the renderer, S = α_i R₁(d) +
//!   l_i·l_e·Rₘ(d; α_t)/α_t², with l_e (l_i) the linear mean of α under the
//!   last- (first-) vertex kernel, l_i = α_i without a first-vertex model,
//!   and α_t the renderer's two-scale mean under the all-vertex kernel
//!   ([`AlbedoSpace`]): α_t = φ⁻¹(⟨φ(ᾱ)⟩) + ⟨α − ᾱ⟩ with ᾱ = S ∗ α
//!   ([`pyramid::blur_mixture`]), by default φ(α) = √(1 − α), b =
//!   [`SPACE_BLUR`] and S the darker regime's split kernel of [`Split`]
//!   (0.2·δ + 0.8·G_b) at every albedo; in the linear space α_t = ⟨α⟩.
//!   Point albedos are the
//!   texel under the point. The kernels' *shapes* are the meta-model's at
//!   an **anchor** map A, held fixed while α varies: the first-vertex
//!   kernel at (A_i + A_e)/2, the last-vertex kernel at the anchor's l_e
//!   read under the kernel at that mean (the renderer's `--last-kernel
//!   exit`), the all-vertex kernel at the anchor's first-pass α_t
//!   (the renderer's two passes), on a grid of [`ANCHOR_BINS`] albedos
//!   uniform in √(1 − α). With the shapes fixed, M is a smooth function of
//!   α whose gradient this module computes exactly; the designer
//!   re-anchors at its current map before each L-BFGS-B round. With
//!   [`Appearance::with_interior_kernel`] α_t is read under the interior
//!   vertices' kernel at each bin's α (the renderer's `--interior`), the
//!   anchor's first pass still under the all-vertex one.
//!
//! The Gaussian means read a [`BlurStack`] (one of α and, in a two-scale
//! space, one of φ(ᾱ) and one of α − ᾱ); the gradient runs the reads
//! backwards into the stacks' adjoint buffers, then through their
//! transposed stencils, and the two-scale parts through φ′(ᾱ) and the
//! transposed blur ([`pyramid::blur_mixture_transpose`]). Sums are taken over a fixed number of pixel blocks
//! in a fixed order, so results do not depend on the thread count.

use super::stack::BlurStack;
use crate::error::{Error, Result};
use crate::forward::maps::TexelMap;
use crate::metamodel::basis::BasisModel;
use crate::metamodel::kernel::{Gmm, interior_into};
use crate::metamodel::meta::MetaModelFile;
use crate::render::pyramid;
use crate::render::svbssrdf::{AlbedoSpace, BasisTable, Method, R_MIN, SPACE_BLUR, Split};
use rayon::prelude::*;
use std::f64::consts::PI;
use std::sync::Arc;

/// Albedos at which the kernel shapes are tabulated (uniform in √(1 − α)
/// over the meta-model's range).
pub const ANCHOR_BINS: usize = 64;

/// Pixel blocks of the parallel sums (fixed: results independent of threads).
const BLOCKS: usize = 4;

/// The light over the texture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Illumination {
    /// Unit irradiance over the whole plane.
    Uniform,
    /// Unit irradiance inside a disk of this radius (MFP) at the origin.
    Disk(f64),
}

impl Illumination {
    /// `uniform` or `disk:R` (R in MFP, > 0).
    pub fn parse(s: &str) -> Result<Self> {
        if s == "uniform" {
            return Ok(Illumination::Uniform);
        }
        match s.strip_prefix("disk:").map(str::parse::<f64>) {
            Some(Ok(r)) if r > 0.0 && r.is_finite() => Ok(Illumination::Disk(r)),
            _ => Err(Error::param(
                "illumination",
                s,
                "uniform or disk:R with R > 0 (MFP)",
            )),
        }
    }

    pub fn name(&self) -> String {
        match self {
            Illumination::Uniform => "uniform".into(),
            Illumination::Disk(r) => format!("disk:{r}"),
        }
    }

    #[inline]
    fn lit(&self, x: [f64; 2]) -> bool {
        match self {
            Illumination::Uniform => true,
            Illumination::Disk(r) => x[0] * x[0] + x[1] * x[1] <= r * r,
        }
    }
}

/// How the appearance is estimated.
#[derive(Clone, Debug, PartialEq)]
pub struct Quadrature {
    /// Rings K_r (radii).
    pub rings: usize,
    /// Angles per ring K_φ.
    pub angles: usize,
}

impl Default for Quadrature {
    fn default() -> Self {
        Quadrature {
            rings: 12,
            angles: 2,
        }
    }
}

/// One entry offset of the quadrature.
#[derive(Clone, Copy, Debug)]
struct Offset {
    delta: [f64; 2],
    d: f64,
    weight: f64,
    /// R₁(d) at unit density.
    single: f64,
}

/// One Gaussian read of a kernel component planned for an offset: its
/// centre relative to x_e (MFP), its stack levels and its share w_c/Σw.
#[derive(Clone, Copy, Debug)]
struct Read {
    shift: [f64; 2],
    level: (usize, f64),
    share: f64,
}

/// The reads of one kernel class per (offset, bin):
/// `reads[start[i]..start[i + 1]]` for i = offset·[`ANCHOR_BINS`] + bin.
#[derive(Debug, Default)]
struct Plans {
    reads: Vec<Read>,
    start: Vec<usize>,
}

impl Plans {
    #[inline]
    fn get(&self, offset: usize, bin: u16) -> &[Read] {
        let i = offset * ANCHOR_BINS + bin as usize;
        &self.reads[self.start[i]..self.start[i + 1]]
    }
}

/// The kernel shapes per (offset, anchor bin), as planned reads.
#[derive(Debug)]
struct Kernels {
    /// α_t's kernel: the all-vertex one, or the interior vertices' one
    /// ([`Appearance::with_interior_kernel`]).
    all: Plans,
    /// The all-vertex kernel for the anchor's first pass where `all` is the
    /// interior one.
    first_pass: Option<Plans>,
    last: Plans,
    first: Option<Plans>,
    y_range: [f64; 2],
}

impl Kernels {
    fn bin(&self, alpha: f64) -> u16 {
        let y = (1.0 - alpha.clamp(0.0, 1.0)).sqrt();
        let [y0, y1] = self.y_range;
        let f = ((y - y0) / (y1 - y0)).clamp(0.0, 1.0);
        (f * (ANCHOR_BINS - 1) as f64).round() as u16
    }
}

/// The kernel bins of one channel's anchor: per (texel, offset), the bin of
/// the first-vertex kernel (the pair's mean albedo), of the all-vertex
/// kernel (the first-pass α_t) and of the last-vertex kernel (the anchor's
/// l_e).
#[derive(Clone, Debug, Default)]
pub struct Anchor {
    bins: Vec<[u16; 3]>,
}

/// The appearance model of one texture grid ([module docs](self)).
#[derive(Debug)]
pub struct Appearance {
    method: Method,
    basis: Arc<BasisTable>,
    nx: usize,
    ny: usize,
    texel: f64,
    illumination: Illumination,
    offsets: Vec<Offset>,
    /// The multiple-scattering term's normalisation ([`Normalisation`]).
    norm: Normalisation,
    kernels: Option<Kernels>,
    /// The stack's grid (values unused): cloned per evaluation.
    pub(crate) grid: Option<BlurStack>,
    /// The space of α_t's coarse part and the scale b (MFP) that splits it
    /// from the fine part (learned).
    space: AlbedoSpace,
    space_blur: f64,
    /// The split kernel (σ, weight) at unit density, the darker regime's
    /// of the renderer's [`Split`].
    split: Vec<(f64, f64)>,
    /// The gradient's per-block buffers, kept between calls (fresh ones
    /// would be page-faulted in on every call).
    scratch: std::sync::Mutex<Vec<Part>>,
    /// Stacks and partial-derivative buffers of finished evaluations, for
    /// reuse ([`Self::release`]).
    spare_stacks: std::sync::Mutex<Vec<BlurStack>>,
    spare_partials: std::sync::Mutex<Vec<Vec<[f64; 6]>>>,
}

/// One pixel block's share of a gradient: texel weights, and node weights
/// of the α, φ(ᾱ) and α − ᾱ stacks.
type Part = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);

/// The blur stacks of one map (learned).
#[derive(Debug)]
struct Stacks {
    /// Of α: the vertex kernels' means, and α_t's in the linear space.
    alpha: BlurStack,
    /// α_t's aggregands in a two-scale space.
    two_scale: Option<TwoScale>,
}

/// The two-scale parts of a map: ᾱ = S ∗ α, and stacks of φ(ᾱ) and α − ᾱ.
#[derive(Debug)]
struct TwoScale {
    mean: Vec<f64>,
    phi: BlurStack,
    residual: BlurStack,
}

impl Appearance {
    /// The model `method` (`point`, `factorized` or `learned`; `learned`
    /// needs `meta`) on a grid of `nx × ny` texels of size `texel` (MFP),
    /// its offsets drawn for albedos in [`alpha_lo`, `alpha_hi`].
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        method: Method,
        basis: &BasisModel,
        meta: Option<&MetaModelFile>,
        nx: usize,
        ny: usize,
        texel: f64,
        illumination: Illumination,
        [alpha_lo, alpha_hi]: [f64; 2],
        quadrature: &Quadrature,
    ) -> Result<Self> {
        if !matches!(method, Method::Point | Method::Factorized | Method::Learned) {
            return Err(Error::param(
                "method",
                method.name(),
                "point, factorized or learned",
            ));
        }
        if nx == 0 || ny == 0 || !(texel > 0.0 && texel.is_finite()) {
            return Err(Error::param(
                "texture",
                format!("{nx}x{ny}, τ = {texel}"),
                "non-empty, τ > 0",
            ));
        }
        if quadrature.rings == 0 || quadrature.angles == 0 {
            return Err(Error::param(
                "quadrature",
                format!("{quadrature:?}"),
                ">= 1 ring and angle",
            ));
        }
        let offsets = offsets(basis, [alpha_lo, alpha_hi], quadrature);
        let table = Arc::new(BasisTable::new(basis));
        let mut offsets: Vec<Offset> = offsets
            .into_iter()
            .map(|(delta, weight)| {
                let d = delta[0].hypot(delta[1]);
                Offset {
                    delta,
                    d,
                    weight,
                    single: table.parts(d.max(R_MIN), 0.5).0,
                }
            })
            .collect();
        // Single scattering: R₁ at unit density and albedo, normalised so
        // that the offsets integrate it exactly (R₁(α) = α·∫R₁ dA).
        let sum: f64 = offsets.iter().map(|o| o.weight * o.single).sum();
        let single_scale = basis.r_1_m(1.0).0 / sum;
        for o in &mut offsets {
            o.single *= single_scale;
        }
        let norm = Normalisation::new(basis, &table, &offsets, single_scale);
        let (kernels, grid) = match (method, meta) {
            (Method::Learned, Some(meta)) => {
                let (kernels, grid) = tabulate(meta, &offsets, nx, ny, texel, None);
                (Some(kernels), Some(grid))
            }
            (Method::Learned, None) => {
                return Err(Error::param("method", "learned", "a meta-model"));
            }
            _ => (None, None),
        };
        Ok(Appearance {
            method,
            basis: table,
            nx,
            ny,
            texel,
            illumination,
            offsets,
            norm,
            kernels,
            grid,
            space: AlbedoSpace::default(),
            space_blur: SPACE_BLUR,
            split: Split::default().components(SPACE_BLUR, false),
            scratch: Default::default(),
            spare_stacks: Default::default(),
            spare_partials: Default::default(),
        })
    }

    /// The same model with α_t averaged in `space`, split at scale `blur`
    /// (MFP, ≥ 0; no part in the linear space). The default is the
    /// renderer's: [`AlbedoSpace::default`] at [`SPACE_BLUR`].
    pub fn with_albedo_space(self, space: AlbedoSpace, blur: f64) -> Result<Self> {
        self.with_split(space, blur, Split::default())
    }

    /// [`Self::with_albedo_space`] with the split kernel of `split`: its
    /// darker regime's ([`Split::components`]) everywhere. The renderer's
    /// default ([`Split::Regimes`]) changes to the one-flight kernel where
    /// the endpoints' albedo passes 0.95; this model keeps one kernel, so
    /// that its gradient stays that of one fixed linear split.
    pub fn with_split(mut self, space: AlbedoSpace, blur: f64, split: Split) -> Result<Self> {
        if !(blur.is_finite() && blur >= 0.0) {
            return Err(Error::param("space-blur", blur, "finite and >= 0 (MFP)"));
        }
        self.space = space;
        self.space_blur = blur;
        self.split = split.components(blur, false);
        Ok(self)
    }

    /// The same model (learned) with α_t under the interior vertices'
    /// kernel, the renderer's `interior` variant
    /// ([`crate::render::svbssrdf::Variant::interior`]): `meta` must be the
    /// meta-model this model was built with. Other methods are unchanged.
    pub fn with_interior_kernel(mut self, meta: &MetaModelFile) -> Self {
        if self.kernels.is_some() {
            let (kernels, grid) = tabulate(
                meta,
                &self.offsets,
                self.nx,
                self.ny,
                self.texel,
                Some(&self.basis),
            );
            self.kernels = Some(kernels);
            self.grid = Some(grid);
        }
        self
    }

    /// Whether α_t is taken under the interior vertices' kernel.
    pub fn interior_kernel(&self) -> bool {
        self.kernels
            .as_ref()
            .is_some_and(|k| k.first_pass.is_some())
    }

    /// The space of α_t's coarse part and its scale b (MFP).
    pub fn albedo_space(&self) -> (AlbedoSpace, f64) {
        (self.space, self.space_blur)
    }

    /// Number of entry offsets K.
    pub fn samples(&self) -> usize {
        self.offsets.len()
    }

    /// Texels (ny · nx).
    pub fn len(&self) -> usize {
        self.nx * self.ny
    }

    /// Whether the grid is empty (never: construction refuses it).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The method.
    pub fn method(&self) -> Method {
        self.method
    }

    /// The centre of texel `e` (row-major) in MFP.
    #[inline]
    fn centre(&self, e: usize) -> [f64; 2] {
        let (i, j) = (e / self.nx, e % self.nx);
        [
            -0.5 * self.nx as f64 * self.texel + (j as f64 + 0.5) * self.texel,
            0.5 * self.ny as f64 * self.texel - (i as f64 + 0.5) * self.texel,
        ]
    }

    /// The texel under x (edges extended), row-major.
    #[inline]
    fn texel_of(&self, x: [f64; 2]) -> usize {
        let j =
            ((x[0] / self.texel + 0.5 * self.nx as f64).floor().max(0.0) as usize).min(self.nx - 1);
        let i =
            ((0.5 * self.ny as f64 - x[1] / self.texel).floor().max(0.0) as usize).min(self.ny - 1);
        i * self.nx + j
    }

    /// The texel grid as a map (values zero), for [`pyramid::blur`].
    fn texel_grid(&self, values: Vec<f64>) -> TexelMap {
        TexelMap {
            nx: self.nx,
            ny: self.ny,
            texel: self.texel,
            values,
        }
    }

    /// The stacks of map `alpha` (learned), built.
    fn stack(&self, alpha: &[f64]) -> Option<Stacks> {
        let build = |values: &[f64]| {
            self.grid.as_ref().map(|g| {
                let spare = self.spare_stacks.lock().expect("spare stacks").pop();
                let mut s = spare.unwrap_or_else(|| g.clone());
                s.build(values);
                s
            })
        };
        let two_scale = match self.space {
            AlbedoSpace::Linear => None,
            space => {
                let mean =
                    pyramid::blur_mixture(&self.texel_grid(alpha.to_vec()), &self.split, 1.0)
                        .values;
                let phi: Vec<f64> = mean.iter().map(|&m| space.forward(m)).collect();
                let residual: Vec<f64> = alpha.iter().zip(&mean).map(|(a, m)| a - m).collect();
                let (phi, residual) = rayon::join(|| build(&phi), || build(&residual));
                Some(TwoScale {
                    phi: phi?,
                    residual: residual?,
                    mean,
                })
            }
        };
        Some(Stacks {
            alpha: build(alpha)?,
            two_scale,
        })
    }

    /// α_t under the planned all-vertex `reads`, and the mean y of φ(ᾱ)
    /// (0 in the linear space).
    #[inline]
    fn total(&self, stacks: &Stacks, xe: [f64; 2], reads: &[Read]) -> (f64, f64) {
        match &stacks.two_scale {
            None => (mean(&stacks.alpha, xe, reads), 0.0),
            Some(t) => {
                let (y, r) = mean_pair(&t.phi, &t.residual, xe, reads);
                (self.space.inverse(y) + r, y)
            }
        }
    }

    /// The kernel bins of anchor map `a` (learned; empty otherwise).
    pub fn anchor(&self, a: &[f64]) -> Anchor {
        assert_eq!(a.len(), self.len(), "anchor shape");
        let (Some(k), Some(stack)) = (&self.kernels, self.stack(a)) else {
            return Anchor::default();
        };
        let bins = (0..self.len())
            .into_par_iter()
            .flat_map_iter(|e| {
                let xe = self.centre(e);
                let stack = &stack;
                self.offsets.iter().enumerate().map(move |(o, off)| {
                    let xi = [xe[0] + off.delta[0], xe[1] + off.delta[1]];
                    let b0 = k.bin(0.5 * (a[self.texel_of(xi)] + a[e]));
                    let plain = k.first_pass.as_ref().unwrap_or(&k.all);
                    let t = self.total(stack, xe, plain.get(o, b0)).0;
                    // The last vertex's kernel at the albedo its vertex
                    // sees: l_e under the kernel at the pair's mean, the
                    // renderer's `--last-kernel exit` (one fixed-point step).
                    let le = mean(&stack.alpha, xe, k.last.get(o, b0));
                    [b0, k.bin(t), k.bin(le)]
                })
            })
            .collect();
        Anchor { bins }
    }

    /// The whole problem of Σ_e g_e·M_e at map `alpha` for an independent
    /// re-implementation (`tools/design_grad_check.py`, in JAX): the grid,
    /// the light, the offsets, the basis model's coefficients, the stack's
    /// levels (their σ and node grids, not their values), and per (texel,
    /// offset) the kernel reads that `anchor` selects; with this module's M
    /// and gradient. `basis` is the model this appearance was built from.
    pub fn export_check(
        &self,
        basis: &BasisModel,
        alpha: &[f64],
        anchor: &Anchor,
        g: &[f64],
    ) -> serde_json::Value {
        use crate::metamodel::basis::{B_MAX, B_MIN};
        use crate::render::svbssrdf::TABLE_NODES;
        let lin = self.linearize(alpha, anchor);
        let gradient = self.gradient(&lin, anchor, g);
        let n_k = self.offsets.len();
        // Reads as rows [e, o, shift x, shift y, σ, share] of one class,
        // at the anchor's bin `which` (0: first vertex, 1: all-vertex,
        // 2: last vertex).
        let reads = |plans: Option<&Plans>, which: usize| {
            let (Some(plans), Some(stack)) = (plans, self.grid.as_ref()) else {
                return Vec::new();
            };
            let mut rows = Vec::new();
            for e in 0..self.len() {
                for o in 0..n_k {
                    for r in plans.get(o, anchor.bins[e * n_k + o][which]) {
                        let (l, t) = r.level;
                        rows.push([
                            e as f64,
                            o as f64,
                            r.shift[0],
                            r.shift[1],
                            stack.level_sigma(l, t),
                            r.share,
                        ]);
                    }
                }
            }
            rows
        };
        let k = self.kernels.as_ref();
        let levels = self.grid.as_ref().map(|s| s.levels_json());
        serde_json::json!({
            "format": "svkernel.design-check",
            "method": self.method.name(),
            "nx": self.nx,
            "ny": self.ny,
            "texel": self.texel,
            "illumination": match self.illumination {
                Illumination::Uniform => serde_json::json!({"kind": "uniform"}),
                Illumination::Disk(r) => serde_json::json!({"kind": "disk", "radius": r}),
            },
            "r_min": R_MIN,
            "space": {"kind": self.space.name(), "blur": self.space_blur, "split": self.split},
            "basis": {
                "degree": basis.degree,
                "ln_a": basis.ln_a,
                "ln_b": basis.ln_b,
                "b_min": B_MIN,
                "b_max": B_MAX,
                "single": basis.single,
                "table_nodes": TABLE_NODES,
            },
            "offsets": self.offsets.iter().map(|o| [o.delta[0], o.delta[1], o.weight]).collect::<Vec<_>>(),
            "normalisation": {
                "single": self.norm.single,
                "y": self.norm.y,
                "c": self.norm.c,
            },
            "levels": levels,
            "reads_all": reads(k.map(|k| &k.all), 1),
            "reads_last": reads(k.map(|k| &k.last), 2),
            "reads_first": reads(k.and_then(|k| k.first.as_ref()), 0),
            "has_first": k.is_some_and(|k| k.first.is_some()),
            "alpha": alpha,
            "g": g,
            "m": lin.m,
            "gradient": gradient,
        })
    }

    /// The appearance M of map `alpha` (row-major, one channel) under
    /// `anchor` (from [`Self::anchor`]; ignored by `point` and
    /// `factorized`).
    pub fn appearance(&self, alpha: &[f64], anchor: &Anchor) -> Vec<f64> {
        assert_eq!(alpha.len(), self.len(), "map shape");
        let stack = self.stack(alpha);
        let mut m = vec![0.0; self.len()];
        m.par_chunks_mut(self.nx)
            .enumerate()
            .for_each(|(row, m)| self.row(alpha, stack.as_ref(), anchor, row, m, None));
        self.keep_stacks(stack);
        m
    }

    /// Hands a finished linearization's buffers back for reuse by the next
    /// evaluation (fresh ones of tens of MB would be page-faulted in).
    pub fn release(&self, lin: Linearization) {
        self.keep_stacks(lin.stack);
        self.spare_partials
            .lock()
            .expect("spare partials")
            .push(lin.partials);
    }

    fn keep_stacks(&self, stacks: Option<Stacks>) {
        let Some(s) = stacks else { return };
        let mut spare = self.spare_stacks.lock().expect("spare stacks");
        spare.push(s.alpha);
        if let Some(t) = s.two_scale {
            spare.extend([t.phi, t.residual]);
        }
    }

    /// M of map `alpha` with what its gradient needs ([`Self::gradient`]).
    pub fn linearize(&self, alpha: &[f64], anchor: &Anchor) -> Linearization {
        assert_eq!(alpha.len(), self.len(), "map shape");
        let stack = self.stack(alpha);
        let n_k = self.offsets.len();
        let spare = self.spare_partials.lock().expect("spare partials").pop();
        let mut partials = spare.unwrap_or_default();
        partials.clear();
        partials.resize(self.len() * n_k, [0.0; 6]);
        let mut m = vec![0.0; self.len()];
        m.par_chunks_mut(self.nx)
            .zip(partials.par_chunks_mut(self.nx * n_k))
            .enumerate()
            .for_each(|(row, (m, p))| self.row(alpha, stack.as_ref(), anchor, row, m, Some(p)));
        Linearization { m, partials, stack }
    }

    /// The gradient Σ_e g_e ∂M_e/∂α (row-major) at the linearized map for
    /// the weights `g` (for a least-squares objective, ∂F/∂M).
    pub fn gradient(&self, lin: &Linearization, anchor: &Anchor, g: &[f64]) -> Vec<f64> {
        let n = self.len();
        assert_eq!(g.len(), n, "weights shape");
        let n_k = self.offsets.len();
        let stack = lin.stack.as_ref();
        let nodes_len = stack.map_or(0, |s| s.alpha.len());
        let two_scale = stack.is_some_and(|s| s.two_scale.is_some());
        let two_len = if two_scale { nodes_len } else { 0 };
        let per = n.div_ceil(BLOCKS);
        let mut pool = std::mem::take(&mut *self.scratch.lock().expect("scratch"));
        pool.resize_with(BLOCKS, Default::default);
        let parts: Vec<Part> = pool
            .into_par_iter()
            .enumerate()
            .map(|(block, part)| {
                let (mut texels, mut nodes, mut nodes_phi, mut nodes_res) = part;
                for (v, len) in [
                    (&mut texels, n),
                    (&mut nodes, nodes_len),
                    (&mut nodes_phi, two_len),
                    (&mut nodes_res, two_len),
                ] {
                    v.clear();
                    v.resize(len, 0.0);
                }
                // Per texel row, offsets outside ([`Self::row`]).
                let (lo, hi) = (block * per, ((block + 1) * per).min(n));
                for row in lo / self.nx..hi.div_ceil(self.nx) {
                    let texels_of_row = (row * self.nx).max(lo)..((row + 1) * self.nx).min(hi);
                    for (o, off) in self.offsets.iter().enumerate() {
                        for e in texels_of_row.clone() {
                            if g[e] == 0.0 {
                                continue;
                            }
                            let xe = self.centre(e);
                            let [c_i, c_e, c_t, c_le, c_li, c_y] = lin.partials[e * n_k + o];
                            let w = g[e];
                            let xi = [xe[0] + off.delta[0], xe[1] + off.delta[1]];
                            texels[self.texel_of(xi)] += w * c_i;
                            texels[e] += w * c_e;
                            if let (Some(k), Some(stack)) = (&self.kernels, stack) {
                                let [b0, b1, b2] = anchor.bins[e * n_k + o];
                                let all = k.all.get(o, b1);
                                if c_t != 0.0 {
                                    match &stack.two_scale {
                                        None => {
                                            scatter(&stack.alpha, xe, all, [w * c_t], [&mut nodes])
                                        }
                                        Some(t) => {
                                            let g = [w * c_y, w * c_t];
                                            let nodes = [&mut nodes_phi[..], &mut nodes_res[..]];
                                            scatter(&t.phi, xe, all, g, nodes);
                                        }
                                    }
                                }
                                let a = &stack.alpha;
                                scatter(a, xe, k.last.get(o, b2), [w * c_le], [&mut nodes]);
                                if let Some(f) = &k.first {
                                    scatter(a, xe, f.get(o, b0), [w * c_li], [&mut nodes]);
                                }
                            }
                        }
                    }
                }
                (texels, nodes, nodes_phi, nodes_res)
            })
            .collect();
        // Summed into the first block's buffers in block order per element
        // (chunks in parallel).
        let mut parts = parts;
        let (head, rest) = parts.split_at_mut(1);
        let add = |out: &mut Vec<f64>, pick: &(dyn Fn(&Part) -> &Vec<f64> + Sync)| {
            out.par_chunks_mut(1 << 14)
                .enumerate()
                .for_each(|(c, chunk)| {
                    let at = c << 14;
                    for p in rest.iter() {
                        for (a, b) in chunk.iter_mut().zip(&pick(p)[at..]) {
                            *a += b;
                        }
                    }
                });
        };
        let (texels, nodes, nodes_phi, nodes_res) = &mut head[0];
        add(texels, &|p| &p.0);
        add(nodes, &|p| &p.1);
        add(nodes_phi, &|p| &p.2);
        add(nodes_res, &|p| &p.3);
        let mut texels = std::mem::take(texels);
        if let Some(s) = stack {
            s.alpha.adjoint(nodes, &mut texels);
            if let Some(t) = &s.two_scale {
                // α_t's parts: ∂/∂α = g_r + Bᵀ(φ′(ᾱ)·g_φ − g_r), with g_φ and g_r
                // the texel gradients through the φ(ᾱ) and α − ᾱ stacks.
                let (mut g_phi, mut g_res) = (vec![0.0; n], vec![0.0; n]);
                t.phi.adjoint(nodes_phi, &mut g_phi);
                t.residual.adjoint(nodes_res, &mut g_res);
                let h: Vec<f64> = (0..n)
                    .map(|k| self.space.forward_derivative(t.mean[k]) * g_phi[k] - g_res[k])
                    .collect();
                let back = pyramid::blur_mixture_transpose(
                    &self.texel_grid(Vec::new()),
                    &self.split,
                    1.0,
                    &h,
                );
                for k in 0..n {
                    texels[k] += g_res[k] + back[k];
                }
            }
        }
        *self.scratch.lock().expect("scratch") = parts;
        texels
    }

    /// M along texel row `row` into `m` (one value per texel); with
    /// `partials` (`n_k` per texel), also each offset's weighted partial
    /// derivatives of its term W_k·S_k: with respect to the point albedo
    /// under x_i and under x_e, to α_t (in a two-scale space: to the mean
    /// of α − ᾱ), to the means l_e and l_i, and (two-scale) to the mean y
    /// of φ(ᾱ). The offsets are the outer loop: one offset's reads for
    /// neighbouring texels fall on neighbouring nodes, which stay in the
    /// cache; each texel still sums its terms in offset order.
    fn row(
        &self,
        alpha: &[f64],
        stack: Option<&Stacks>,
        anchor: &Anchor,
        row: usize,
        m: &mut [f64],
        mut partials: Option<&mut [[f64; 6]]>,
    ) {
        let n_k = self.offsets.len();
        m.fill(0.0);
        for (o, off) in self.offsets.iter().enumerate() {
            for (j, mj) in m.iter_mut().enumerate() {
                let e = row * self.nx + j;
                let xe = self.centre(e);
                let xi = [xe[0] + off.delta[0], xe[1] + off.delta[1]];
                if !self.illumination.lit(xi) {
                    continue;
                }
                let (s, d) = self.term(alpha, stack, anchor, e, o, xe, xi);
                *mj += off.weight * s;
                if let Some(p) = partials.as_deref_mut() {
                    p[j * n_k + o] = d.map(|v| off.weight * v);
                }
            }
        }
    }

    /// The term S_k of offset `o` at texel `e` (centre `xe`, entry `xi`)
    /// and its unweighted partial derivatives ([`Self::row`]).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn term(
        &self,
        alpha: &[f64],
        stack: Option<&Stacks>,
        anchor: &Anchor,
        e: usize,
        o: usize,
        xe: [f64; 2],
        xi: [f64; 2],
    ) -> (f64, [f64; 6]) {
        let off = &self.offsets[o];
        let ae = alpha[e];
        let b = &*self.basis;
        let n_k = self.offsets.len();
        let ai = alpha[self.texel_of(xi)];
        let r = off.d.max(R_MIN);
        let profile = |a: f64| {
            let (mm, dm) = self.norm.multi(b, r, a);
            let v = a * off.single + a * a * mm;
            (v, off.single + 2.0 * a * mm + a * a * dm)
        };
        match self.method {
            Method::Point => {
                let (s, ds) = profile(ae);
                (s, [0.0, ds, 0.0, 0.0, 0.0, 0.0])
            }
            Method::Factorized => {
                let ((ri, dri), (re, dre)) = (profile(ai), profile(ae));
                let s = (ri * re).max(0.0).sqrt();
                let h = if s > 0.0 { 0.5 / s } else { 0.0 };
                (s, [h * dri * re, h * ri * dre, 0.0, 0.0, 0.0, 0.0])
            }
            _ => {
                let (Some(k), Some(stack)) = (&self.kernels, stack) else {
                    unreachable!("learned is built with its kernels")
                };
                let [b0, b1, b2] = anchor.bins[e * n_k + o];
                let (at, y) = self.total(stack, xe, k.all.get(o, b1));
                let le = mean(&stack.alpha, xe, k.last.get(o, b2));
                let first = k.first.as_ref().map(|f| f.get(o, b0));
                let li = first.map_or(ai, |f| mean(&stack.alpha, xe, f));
                let t = at.clamp(0.0, 1.0);
                let (mm, dm) = self.norm.multi(b, r, t);
                let s = ai * off.single + li * le * mm;
                // l_i is the point albedo without a first-vertex model.
                let (c_i, c_li) = match first {
                    None => (off.single + le * mm, 0.0),
                    Some(_) => (off.single, le * mm),
                };
                let c_t = if at == t { li * le * dm } else { 0.0 };
                let c_y = c_t * self.space.inverse_derivative(y);
                (s, [c_i, 0.0, c_t, li * mm, c_li, c_y])
            }
        }
    }
}

/// Nodes of [`Normalisation`], uniform in y = √(1 − α).
const NORM_NODES: usize = 128;

/// The albedo range of [`Normalisation`]'s table.
const NORM_RANGE: [f64; 2] = [0.01, 0.999];

/// The quadrature's normalisation of the multiple-scattering term: the
/// fixed offsets integrate Rₘ(d; α)/α² to Σ_k W_k Rₘ(d_k; α)/α², which
/// differs from the basis's Rₘ(α)/α² (−1 % to +5 % on the shipped basis;
/// most where the profile reaches beyond the offsets, at α → 1). The term
/// is scaled by c(α) = Rₘ(α)/Σ_k W_k Rₘ(d_k; α), so that a homogeneous map
/// looks exactly like R_d(α) (a ratio estimator); c is tabulated at
/// [`NORM_NODES`] albedos uniform in y = √(1 − α) and interpolated
/// linearly in y.
#[derive(Clone, Debug)]
struct Normalisation {
    /// y at the first and last node.
    y: [f64; 2],
    c: Vec<f64>,
    /// The same for single scattering, one factor (R₁ ∝ α): ∫R₁ dA over
    /// Σ_k W_k R₁(d_k), already applied to the offsets' R₁.
    single: f64,
}

impl Normalisation {
    fn new(basis: &BasisModel, table: &BasisTable, offsets: &[Offset], single: f64) -> Self {
        let y = NORM_RANGE.map(|a| (1.0 - a).sqrt());
        let c = (0..NORM_NODES)
            .map(|j| {
                let yj = y[0] + (y[1] - y[0]) * j as f64 / (NORM_NODES - 1) as f64;
                let a = 1.0 - yj * yj;
                let sum: f64 = offsets
                    .iter()
                    .map(|o| o.weight * table.multi_over_alpha2_grad(o.d.max(R_MIN), a).0)
                    .sum();
                basis.r_1_m(a).1 / (a * a * sum)
            })
            .collect();
        Normalisation { y, c, single }
    }

    /// (c(α), dc/dα).
    #[inline]
    fn scale(&self, alpha: f64) -> (f64, f64) {
        let yv = (1.0 - alpha).max(0.0).sqrt();
        let h = (self.y[1] - self.y[0]) / (NORM_NODES - 1) as f64;
        let f = ((yv - self.y[0]) / h).clamp(0.0, (NORM_NODES - 1) as f64);
        let i = (f as usize).min(NORM_NODES - 2);
        let slope = (self.c[i + 1] - self.c[i]) / h;
        let c = self.c[i] + slope * (f - i as f64) * h;
        // Flat beyond the table (y clamped; y[0] > y[1]).
        let inside = yv < self.y[0] && yv > self.y[1];
        (c, if inside { -slope * 0.5 / yv } else { 0.0 })
    }

    /// Rₘ(r; α)/α² normalised, and its α-derivative.
    #[inline]
    fn multi(&self, table: &BasisTable, r: f64, alpha: f64) -> (f64, f64) {
        let (mm, dm) = table.multi_over_alpha2_grad(r, alpha);
        let (c, dc) = self.scale(alpha);
        (c * mm, c * dm + dc * mm)
    }
}

/// The appearance of one map with its partial derivatives per (texel,
/// offset), from [`Appearance::linearize`].
#[derive(Debug)]
pub struct Linearization {
    /// M per texel.
    pub m: Vec<f64>,
    partials: Vec<[f64; 6]>,
    stack: Option<Stacks>,
}

/// The planned mean Σ_c share_c·(G_σc ∗ α)(x_e + shift_c).
#[inline]
fn mean(stack: &BlurStack, xe: [f64; 2], reads: &[Read]) -> f64 {
    reads
        .iter()
        .map(|r| r.share * stack.read_at([xe[0] + r.shift[0], xe[1] + r.shift[1]], r.level))
        .sum()
}

/// The planned means of two stacks on one grid, their taps shared.
#[inline]
fn mean_pair(a: &BlurStack, b: &BlurStack, xe: [f64; 2], reads: &[Read]) -> (f64, f64) {
    reads.iter().fold((0.0, 0.0), |(sa, sb), r| {
        let [va, vb] = a.read_pair_at(b, [xe[0] + r.shift[0], xe[1] + r.shift[1]], r.level);
        (sa + r.share * va, sb + r.share * vb)
    })
}

/// Adds g_k·∂(planned mean)/∂node into `buffers[k]`, for stacks on the
/// grid of `stack`.
#[inline]
fn scatter<const N: usize>(
    stack: &BlurStack,
    xe: [f64; 2],
    reads: &[Read],
    g: [f64; N],
    mut buffers: [&mut [f64]; N],
) {
    for r in reads {
        let mu = [xe[0] + r.shift[0], xe[1] + r.shift[1]];
        let bufs = buffers.each_mut().map(|b| &mut **b);
        stack.scatter_at(mu, r.level, g.map(|v| v * r.share), bufs);
    }
}

/// The offsets and weights of the quadrature ([module docs](self)).
fn offsets(basis: &BasisModel, [lo, hi]: [f64; 2], q: &Quadrature) -> Vec<([f64; 2], f64)> {
    let albedos = [lo.clamp(0.05, 0.999), hi.clamp(0.05, 0.999)];
    let rd = albedos.map(|a| basis.r_d(a));
    // The mixture's radial density (per unit r) and CDF, each part normalised.
    let pdf = |r: f64| {
        0.5 * (0..2)
            .map(|i| basis.density(r, albedos[i]) / rd[i])
            .sum::<f64>()
    };
    let cdf = |r: f64| {
        0.5 * (0..2)
            .map(|i| basis.cdf(r, albedos[i]) / rd[i])
            .sum::<f64>()
    };
    let k = (q.rings * q.angles) as f64;
    let golden = 0.5 * (5f64.sqrt() - 1.0);
    let mut out = Vec::with_capacity(q.rings * q.angles);
    for ring in 0..q.rings {
        let u = (ring as f64 + 0.5) / q.rings as f64;
        // Bisection on the CDF over [0, 1000] MFP (to 1e-12 MFP).
        let (mut a, mut b) = (0.0, 1000.0);
        while b - a > 1e-12 * (1.0 + b) {
            let m = 0.5 * (a + b);
            if cdf(m) < u {
                a = m;
            } else {
                b = m;
            }
        }
        let r = 0.5 * (a + b);
        let area_pdf = pdf(r) / (2.0 * PI * r);
        let turn = (ring as f64 * golden).fract();
        for j in 0..q.angles {
            let phi = 2.0 * PI * (j as f64 + turn) / q.angles as f64;
            out.push(([r * phi.cos(), r * phi.sin()], 1.0 / (k * area_pdf)));
        }
    }
    out
}

/// The kernel shapes per (offset, bin) from the meta-model, planned on
/// the stack that covers their widths.
fn tabulate(
    meta: &MetaModelFile,
    offsets: &[Offset],
    nx: usize,
    ny: usize,
    texel: f64,
    interior: Option<&BasisTable>,
) -> (Kernels, BlurStack) {
    let [a0, a1] = meta.all.alpha_range;
    let y_range = [(1.0 - a1).sqrt(), (1.0 - a0).sqrt()];
    let alpha_of = |b: usize| {
        let y = y_range[0] + (y_range[1] - y_range[0]) * b as f64 / (ANCHOR_BINS - 1) as f64;
        1.0 - y * y
    };
    let shapes = |m: &crate::metamodel::meta::MetaModel| -> Vec<Gmm> {
        offsets
            .iter()
            .flat_map(|o| (0..ANCHOR_BINS).map(move |b| m.eval(o.d, alpha_of(b), 1.0).gmm))
            .collect()
    };
    let (all, last) = (shapes(&meta.all), shapes(&meta.last));
    let first = meta.first.as_ref().map(shapes);
    let sigma_max = all
        .iter()
        .chain(&last)
        .chain(first.iter().flatten())
        .flat_map(|g| g.components.iter().map(|c| c.sigma))
        .fold(0.0, f64::max);
    let stack = BlurStack::new(nx, ny, texel, sigma_max);
    let plan = |gmms: &[Gmm]| -> Plans {
        let mut p = Plans::default();
        p.start.push(0);
        for (i, g) in gmms.iter().enumerate() {
            let off = &offsets[i / ANCHOR_BINS];
            // The pair frame: origin x_i = x_e + δ, axis toward x_e.
            let [ux, uy] = if off.d > 0.0 {
                [-off.delta[0] / off.d, -off.delta[1] / off.d]
            } else {
                [1.0, 0.0]
            };
            let total: f64 = g.components.iter().map(|c| c.weight).sum();
            for c in &g.components {
                p.reads.push(Read {
                    shift: [
                        off.delta[0] + c.t * ux - c.s * uy,
                        off.delta[1] + c.t * uy + c.s * ux,
                    ],
                    level: stack.level_of(c.sigma),
                    share: c.weight / total,
                });
            }
            p.start.push(p.reads.len());
        }
        p
    };
    // The interior kernel at each bin's α, from the kernels there and n̄ − 2
    // of the homogeneous profile at (d, α) (the renderer's, with its
    // all-vertex α_t as this bin's α).
    let interior = interior.map(|table| {
        (0..all.len())
            .map(|i| {
                let (d, alpha) = (offsets[i / ANCHOR_BINS].d, alpha_of(i % ANCHOR_BINS));
                let m = table.interior_vertices(d.max(R_MIN), alpha);
                let f = first.as_ref().map(|f| &f[i]);
                let mut out = Gmm::default();
                interior_into(&all[i], f, Some(&last[i]), d, m, &mut out);
                out
            })
            .collect::<Vec<_>>()
    });
    let kernels = Kernels {
        all: plan(interior.as_deref().unwrap_or(&all)),
        first_pass: interior.is_some().then(|| plan(&all)),
        last: plan(&last),
        first: first.as_deref().map(plan),
        y_range,
    };
    (kernels, stack)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::rng::PathRng;

    fn model(
        method: Method,
        nx: usize,
        ny: usize,
        light: Illumination,
        q: &Quadrature,
    ) -> Appearance {
        let basis = crate::testing::shipped_basis();
        let meta = crate::testing::shipped_meta();
        Appearance::new(
            method,
            &basis,
            Some(&meta),
            nx,
            ny,
            0.1,
            light,
            [0.3, 0.95],
            q,
        )
        .unwrap()
    }

    fn noise(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = PathRng::new(seed, 0);
        (0..n).map(|_| 0.3 + 0.6 * rng.uniform()).collect()
    }

    #[test]
    fn gradients_match_central_differences() {
        let default = (AlbedoSpace::default(), SPACE_BLUR);
        for (method, light, (space, blur), interior) in [
            (Method::Point, Illumination::Uniform, default, false),
            (Method::Factorized, Illumination::Uniform, default, false),
            (Method::Learned, Illumination::Uniform, default, false),
            (Method::Learned, Illumination::Disk(0.6), default, false),
            (Method::Learned, Illumination::Uniform, default, true),
            (
                Method::Learned,
                Illumination::Uniform,
                (AlbedoSpace::Linear, 0.0),
                false,
            ),
            (
                Method::Learned,
                Illumination::Uniform,
                (AlbedoSpace::Log, 0.0),
                false,
            ),
            (
                Method::Learned,
                Illumination::Uniform,
                (AlbedoSpace::Absorption, 0.5),
                true,
            ),
        ] {
            let (nx, ny) = (9, 7);
            let q = Quadrature {
                rings: 6,
                angles: 3,
            };
            let mut m = model(method, nx, ny, light, &q)
                .with_albedo_space(space, blur)
                .unwrap();
            if interior {
                m = m.with_interior_kernel(&crate::testing::shipped_meta());
                assert!(m.interior_kernel());
            }
            let alpha = noise(nx * ny, 3);
            let anchor = m.anchor(&alpha);
            let g = noise(nx * ny, 4)
                .iter()
                .map(|v| v - 0.6)
                .collect::<Vec<_>>();
            let f = |a: &[f64]| -> f64 {
                m.appearance(a, &anchor)
                    .iter()
                    .zip(&g)
                    .map(|(x, y)| x * y)
                    .sum()
            };
            let lin = m.linearize(&alpha, &anchor);
            let grad = m.gradient(&lin, &anchor, &g);
            // Evaluations that reuse the released buffers give the same bits.
            m.release(lin);
            let again = m.linearize(&alpha, &anchor);
            assert_eq!(m.gradient(&again, &anchor, &g), grad, "{method:?}: reuse");
            assert_eq!(m.appearance(&alpha, &anchor), again.m, "{method:?}: reuse");
            let scale = grad.iter().fold(0.0f64, |s, v| s.max(v.abs()));
            assert!(scale > 0.0, "{method:?}: zero gradient");
            for t in [0, 5, 31, 40, nx * ny - 1] {
                // The basis table is linear between its nodes in √(1 − α):
                // M has kinks there, which a wider step may straddle. A
                // step that straddles one is retried ten times smaller.
                let central = |h: f64| {
                    let (mut up, mut down) = (alpha.clone(), alpha.clone());
                    up[t] += h;
                    down[t] -= h;
                    (f(&up) - f(&down)) / (2.0 * h)
                };
                let mut fd = central(1e-7);
                if (fd - grad[t]).abs() > 1e-6 * scale {
                    fd = central(1e-8);
                }
                assert!(
                    (fd - grad[t]).abs() <= 1e-6 * scale,
                    "{method:?} {light:?} {space:?} b {blur} texel {t}: adjoint {} vs central difference {fd}",
                    grad[t]
                );
            }
        }
    }

    #[test]
    fn the_last_vertex_kernel_is_anchored_at_the_albedo_its_vertex_sees() {
        // A step of 0.95 | 0.3 at x = 0 on a map 6 MFP wide. For an exit
        // 2 MFP into the dark side and entries on the bright side, the
        // first-vertex bin is the pair's mean albedo, and the last vertex's
        // is the l_e under it: the dark side's albedo, not the pair's mean.
        let (nx, ny) = (60, 6);
        let m = model(
            Method::Learned,
            nx,
            ny,
            Illumination::Uniform,
            &Quadrature::default(),
        );
        let k = m.kernels.as_ref().expect("learned has kernels");
        let step: Vec<f64> = (0..nx * ny)
            .map(|e| if e % nx < nx / 2 { 0.95 } else { 0.3 })
            .collect();
        let anchor = m.anchor(&step);
        let n_k = m.samples();
        let e = 2 * nx + nx / 2 + 20;
        let xe = m.centre(e);
        assert!((xe[0] - 2.05).abs() < 1e-9, "exit at {xe:?}");
        let mut mixed = 0;
        for (o, off) in m.offsets.iter().enumerate() {
            if xe[0] + off.delta[0] >= 0.0 {
                continue;
            }
            mixed += 1;
            let [b0, _, b2] = anchor.bins[e * n_k + o];
            assert_eq!(b0, k.bin(0.5 * (0.95 + 0.3)), "offset {o}");
            assert!(
                b2.abs_diff(k.bin(0.3)) <= 2 && b0.abs_diff(b2) >= 8,
                "offset {o}: last-vertex bin {b2}, dark side's {}, pair's {b0}",
                k.bin(0.3)
            );
        }
        assert!(mixed > 0, "no entry on the bright side");
        // On a constant map the two bins agree.
        let anchor = m.anchor(&vec![0.6; nx * ny]);
        assert!(anchor.bins.iter().all(|[b0, _, b2]| b0 == b2));
    }

    #[test]
    fn a_homogeneous_map_looks_like_its_reflectance() {
        // The normalised quadrature integrates the homogeneous profile:
        // M = R_d(α) at every albedo, inside the offsets' range (drawn for
        // [0.3, 0.95]) or not (without the normalisation: 4 % low at 0.99).
        // The interior kernel has unit mass, so it aggregates a constant
        // map to that constant too.
        let basis = crate::testing::shipped_basis();
        let interior = model(
            Method::Learned,
            5,
            5,
            Illumination::Uniform,
            &Quadrature::default(),
        )
        .with_interior_kernel(&crate::testing::shipped_meta());
        for m in [Method::Point, Method::Factorized, Method::Learned]
            .map(|method| model(method, 5, 5, Illumination::Uniform, &Quadrature::default()))
            .into_iter()
            .chain([interior])
        {
            let method = (m.method(), m.interior_kernel());
            for a in [0.1, 0.3, 0.6, 0.9, 0.95, 0.99] {
                let map = vec![a; 25];
                let anchor = m.anchor(&map);
                let got = m.appearance(&map, &anchor)[12];
                let want = basis.r_d(a);
                assert!(
                    (got / want - 1.0).abs() < 1e-3,
                    "{method:?} α = {a}: {got} vs R_d {want}"
                );
            }
        }
    }
}
