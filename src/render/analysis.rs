//! Scene analysis: simulate only the effects a scene calls for.
//!
//! Before rendering, [`analyse`] looks at the loaded maps and the light and
//! decides what work the scene needs:
//!
//! * **channels** — an RGB albedo whose three maps are identical is grey:
//!   the models and the reference render one channel, not three;
//! * **density** — a density map with one value everywhere is a constant:
//!   no density (or ρα) pyramid, no density lookups in the walk;
//! * **aggregation** — a constant albedo *and* a constant density make the
//!   material homogeneous: every method collapses to the homogeneous profile
//!   S = R(r·ρ; α)·ρ² (the split form's α₁R₁(r; 1) + (α_iα_e/α_t²)Rₘ(r; α_t)
//!   is R₁(r; α) + Rₘ(r; α) when α_i = α_e = α_t = α, because single
//!   scattering is linear in α), so they are all evaluated as `point`, with
//!   no pyramid (tested: the collapsed and the full renders agree);
//! * **incidence** — a diffuse light needs the diffuse-incidence basis, a
//!   collimated one the collimated basis (only that one is loaded);
//! * **range** — the (α, ρ·d) the scene can query against the range the
//!   meta-model was trained on: albedos outside it are simulated and fitted
//!   ([`crate::jobs::extend`]); optical pair distances beyond it keep the kernel
//!   shape of the largest trained distance, scaled with λ = ρd/2 + 1 (the
//!   compare report states both).
//!
//! The reference walk only tallies the image region (paths are walked
//! wherever they go: exits outside the image are not stored).
//!
//! [`analyse`] is cheap (one pass over the texels) and pure, so the renderer
//! and the report each call it; `RenderOptions::analysis = false` turns the
//! skips off (the full machinery, for measuring what the skips save).

use super::scene::Scene;
use crate::forward::maps::TexelMap;
use serde::{Deserialize, Serialize};

/// The effects the analysis (and the compare report) considers, written as
/// their short names ("rgb channels", "density pyramid", …).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EffectKind {
    #[serde(rename = "rgb channels")]
    RgbChannels,
    #[serde(rename = "density pyramid")]
    DensityPyramid,
    #[serde(rename = "albedo aggregation")]
    AlbedoAggregation,
    #[serde(rename = "collimated-incidence profile")]
    CollimatedProfile,
    #[serde(rename = "diffuse-incidence profile")]
    DiffuseProfile,
    /// Simulating and fitting the meta-model where the scene's albedos
    /// leave its trained range ([`crate::jobs::extend`]).
    #[serde(rename = "kernel simulation (missing albedo range)")]
    KernelSimulation,
}

impl EffectKind {
    /// The short name.
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::RgbChannels => "rgb channels",
            EffectKind::DensityPyramid => "density pyramid",
            EffectKind::AlbedoAggregation => "albedo aggregation",
            EffectKind::CollimatedProfile => "collimated-incidence profile",
            EffectKind::DiffuseProfile => "diffuse-incidence profile",
            EffectKind::KernelSimulation => "kernel simulation (missing albedo range)",
        }
    }
}

impl std::fmt::Display for EffectKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The incidence a basis profile is fitted to: a collimated light needs
/// pencil-beam profiles, a diffuse one diffuse-incidence profiles.
pub use crate::forward::medium::Incidence;

/// One effect the analysis considered.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Effect {
    pub name: EffectKind,
    /// False: skipped (the scene does not call for it).
    pub needed: bool,
    /// Why, in words.
    pub detail: String,
}

/// What the scene needs (module docs).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Plan {
    /// Render one channel (grey albedo).
    pub grey: bool,
    /// The density map is this constant (skip the density pyramid).
    pub constant_density: Option<f64>,
    /// Albedo and density both constant: every method is the homogeneous
    /// profile.
    pub homogeneous: bool,
    /// Pencil (collimated light) or diffuse.
    pub incidence: Incidence,
    /// Albedo range over all channels and texels.
    pub albedo_range: [f64; 2],
    /// Density range (the sweep's or the map's; 1 without either).
    pub density_range: [f64; 2],
    /// Longest optical pair distance ρ_max·d_max the image can query (MFP):
    /// pixel corner to the far edge of the light disk.
    pub max_optical_distance: f64,
    pub effects: Vec<Effect>,
}

/// Values as "a, b and c".
pub fn list(values: &[f64]) -> String {
    let v: Vec<String> = values.iter().map(|v| v.to_string()).collect();
    list_names(&v)
}

/// Words as "a, b and c".
pub fn list_names<S: AsRef<str>>(words: &[S]) -> String {
    let v: Vec<&str> = words.iter().map(|w| w.as_ref()).collect();
    match v.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{} and {last}", rest.join(", ")),
        _ => v.join(""),
    }
}

/// A map's single value, if every texel holds it.
fn constant_value(m: &TexelMap) -> Option<f64> {
    let v0 = m.values[0];
    m.values.iter().all(|v| *v == v0).then_some(v0)
}

fn range(values: impl Iterator<Item = f64>) -> [f64; 2] {
    values.fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], v| {
        [lo.min(v), hi.max(v)]
    })
}

/// Analyses `scene` (module docs). With `skip = false` the plan keeps every
/// effect (the effects list still says what could have been skipped).
pub fn analyse(scene: &Scene, skip: bool) -> Plan {
    let grey = scene.is_grey();
    let constant_density = match (&scene.density, scene.density_sweep.len()) {
        (Some(m), _) => constant_value(m),
        (None, 0) => Some(1.0),
        // A sweep renders constant densities, one per pass.
        (None, _) => None,
    };
    let albedo_constant = scene.albedo.iter().all(|m| constant_value(m).is_some());
    // Without a map every pass has a constant density (1 or the sweep's).
    let homogeneous = albedo_constant && (constant_density.is_some() || scene.density.is_none());
    let albedo_range = range(scene.albedo.iter().flat_map(|m| m.values.iter().copied()));
    let density_range = match (&scene.density, scene.density_sweep.is_empty()) {
        (Some(m), _) => range(m.values.iter().copied()),
        (None, false) => range(scene.density_sweep.iter().copied()),
        (None, true) => [1.0, 1.0],
    };
    let corner = scene.half_width * std::f64::consts::SQRT_2;
    let max_optical_distance = density_range[1] * (corner + scene.light_radius);
    let incidence = scene.light.incidence();
    let light = format!(
        "the light is a {} disk of radius {} MFP",
        scene.light.name(),
        scene.light_radius
    );
    let observable = match scene.observable {
        crate::forward::medium::Observable::Exitance => "",
        crate::forward::medium::Observable::Radiance => ", of the radiance along the normal,",
    };
    let basis = |kind: Incidence, name: &str| {
        if incidence == kind {
            format!("{light}: only the {name} basis{observable} is loaded")
        } else {
            format!("{light}: the {name} basis is not loaded")
        }
    };
    let mut effects = vec![
        Effect {
            name: EffectKind::RgbChannels,
            needed: !grey,
            detail: if scene.albedo.len() == 1 {
                "the albedo is grey: one channel".into()
            } else if grey {
                "the three albedo channels are identical: one channel rendered, not three".into()
            } else {
                "the albedo channels differ: three channels".into()
            },
        },
        Effect {
            name: EffectKind::DensityPyramid,
            needed: scene.density.is_some() && constant_density.is_none(),
            detail: match (&scene.density, constant_density) {
                (Some(_), Some(v)) => {
                    format!("the density map is the constant {v}: no density pyramid")
                }
                (Some(_), None) => format!(
                    "the density map varies (ρ ∈ [{}, {}]): ρ and ρα pyramids",
                    density_range[0], density_range[1]
                ),
                (None, _) if !scene.density_sweep.is_empty() => format!(
                    "a sweep of constant densities (ρ = {}), one pass each: no density pyramid",
                    list(&scene.density_sweep)
                ),
                (None, _) => "no density map (ρ = 1): no density pyramid".into(),
            },
        },
        Effect {
            name: EffectKind::AlbedoAggregation,
            needed: !homogeneous,
            detail: if homogeneous {
                "albedo and density are constant: every method is the homogeneous profile, no pyramid"
                    .into()
            } else if albedo_constant {
                "the albedo is constant but the density varies: density aggregation kept".into()
            } else {
                "the albedo varies: kernel aggregation".into()
            },
        },
        Effect {
            name: EffectKind::CollimatedProfile,
            needed: incidence == Incidence::Pencil,
            detail: basis(Incidence::Pencil, "collimated-incidence (pencil-beam)"),
        },
        Effect {
            name: EffectKind::DiffuseProfile,
            needed: incidence == Incidence::Diffuse,
            detail: basis(Incidence::Diffuse, "diffuse-incidence"),
        },
    ];
    if !skip {
        for e in &mut effects[..3] {
            if !e.needed {
                e.needed = true;
                e.detail = format!("analysis off (would skip: {})", e.detail);
            }
        }
    }
    Plan {
        grey: skip && grey && scene.albedo.len() > 1,
        constant_density: if skip && scene.density.is_some() {
            constant_density
        } else {
            None
        },
        homogeneous: skip && homogeneous,
        incidence,
        albedo_range,
        density_range,
        max_optical_distance,
        effects,
    }
}

impl Plan {
    /// The effects that were skipped.
    pub fn skipped(&self) -> impl Iterator<Item = &Effect> {
        self.effects.iter().filter(|e| !e.needed)
    }

    /// True if the plan avoids work the full renderer would do.
    pub fn skips_work(&self) -> bool {
        self.grey || self.constant_density.is_some() || self.homogeneous
    }

    /// The albedo channels to render: the first one only for a grey plan.
    pub fn albedo(&self, scene: &Scene) -> Vec<TexelMap> {
        if self.grey {
            vec![scene.albedo[0].clone()]
        } else {
            scene.albedo.clone()
        }
    }

    /// The density map to render with (`None` where the plan makes it a
    /// constant, see [`Plan::constant_density`]).
    pub fn density_map<'a>(&self, scene: &'a Scene) -> Option<&'a TexelMap> {
        match self.constant_density {
            Some(_) => None,
            None => scene.density.as_ref(),
        }
    }
}
