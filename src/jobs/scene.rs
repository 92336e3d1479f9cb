//! Scenes: TOML files that name the medium, the material maps, the light, the
//! image and the methods to render (docs/design.md §5; the schema for users is docs/scenes.md).
//!
//! # Schema
//!
//! | key | type | default | units | meaning |
//! |---|---|---|---|---|
//! | `name` | string | file stem | — | scene name |
//! | `medium.eta` | float | 1.5 | 1 | n_inside/n_outside, in [1, 3] |
//! | `medium.g` | float | 0.3 | 1 | Henyey–Greenstein g, in (−1, 1) |
//! | `texel` | float | 0.1 | MFP | texel size τ of every map |
//! | `albedo` | map | — | 1 | single-scattering albedo, values in [0, 1] |
//! | `density` | map | constant 1 | 1 | density ρ (σ_t = ρ), values > 0 |
//! | `light.kind` | `"collimated"` \| `"diffuse"` | `"collimated"` | — | disk light at the origin |
//! | `light.radius` | float | 1 | MFP | disk radius R |
//! | `light.irradiance` | float | 1 | 1 | irradiance before the boundary |
//! | `image.resolution` | int | 64 | pixels | N (N × N image) |
//! | `image.half_width` | float | 4 | MFP | W: the image covers [−W, W]² |
//! | `observable` | `"exitance"` \| `"radiance"` | `"exitance"` | — | M(x, y), or radiance along the normal |
//! | `methods` | list of strings | all | — | among point, factorized, line, ellipse, manual, learned |
//! | `samples` | int | 64 | — | light samples per pixel for the model methods |
//! | `reference_paths` | int | 1e6 | — | paths of the brute-force reference |
//! | `density_sweep` | list of floats | none | 1 | render once per constant density (instead of `density`) |
//!
//! A **map** is one of (a TOML table):
//! * `{ constant = 0.8 }`, or `{ rgb = [0.8, 0.5, 0.3] }`; the shorthands
//!   `albedo = 0.8` and `albedo = [0.8, 0.5, 0.3]` mean the same (a number:
//!   a constant; a list of three numbers: `rgb`), for any map;
//! * `{ pattern = "stripes", values = [a, b], width = w, angle = deg }`
//!   (stripes of width w MFP across the direction `angle` (degrees from +x):
//!   stripe k = ⌊u/w⌋ with u = x cos θ + y sin θ holds a for even k, b for odd),
//!   `{ pattern = "checker", values = [a, b], cell = c }`,
//!   `{ pattern = "ramp", values = [a, b], length = L }` (linear in x from a at
//!   x = −L/2 to b at +L/2, clamped), `{ pattern = "dots", values = [bg, dot],
//!   spacing = s, radius = r }`, `{ pattern = "complex", values = [a, b],
//!   seed = n }` (thin lines and dots at three scales); for RGB, `values` is a
//!   list of three-element lists (one per value);
//! * `{ channels = [map, map, map] }` — R, G, B from three grey maps;
//! * `{ file = "path.npy" }` — an `(ny, nx)` or `(ny, nx, 3)` float64 or
//!   float32 array (row 0 is +y, column 0 is −x), relative to the scene file;
//!   `{ file = "path.exr" }` — the first layer's R, G, B (or Y, or its only
//!   channel), linear; `{ file = "path.png", transfer = "srgb" | "linear" }`
//!   — 8- or 16-bit grey or RGB, values v/(2^bits − 1), the transfer stated
//!   explicitly in any letter case (`srgb` decodes IEC 61966-2-1 to linear);
//!   a PNG with an alpha channel is refused (flatten it first).
//!   Image row 0 is +y, column 0 is −x, one pixel per texel.
//!
//! A key that the map's kind does not read (e.g. `width` on a checker) is
//! an error, not ignored; `size` is accepted on constants (it changes
//! nothing).
//!
//! Every map is sampled on a texel grid of `size` = `[nx, ny]` texels
//! (`size` key of the map table; default: enough texels of size τ to cover the
//! image plus 4 MFP on every side) with the texel conventions of
//! [`crate::forward::maps`]: centred on the origin, nearest-neighbour, edge
//! texel extends outside.
//!
//! Errors name the file, the key and, where the parser knows it, the line;
//! nothing is rendered from a malformed scene.

use crate::error::{Error, Result};
use crate::forward::maps::TexelMap;
use crate::forward::medium::Medium;
use crate::forward::rng::PathRng;
use crate::render::scene::{LightKind, Observable, Scene};
use crate::render::svbssrdf::Method;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// The methods a scene can ask for (docs/design.md §4's table), by name.
pub fn method_names() -> Vec<&'static str> {
    Method::ALL.iter().map(|m| m.name()).collect()
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScene {
    name: Option<String>,
    #[serde(default)]
    medium: RawMedium,
    #[serde(default = "default_texel")]
    texel: f64,
    albedo: RawMap,
    density: Option<RawMap>,
    #[serde(default)]
    light: RawLight,
    #[serde(default)]
    image: RawImage,
    #[serde(default = "default_observable")]
    observable: String,
    methods: Option<Vec<String>>,
    #[serde(default = "default_samples")]
    samples: u32,
    #[serde(default = "default_reference_paths")]
    reference_paths: f64,
    density_sweep: Option<Vec<f64>>,
}

fn default_texel() -> f64 {
    0.1
}
fn default_observable() -> String {
    "exitance".into()
}
fn default_samples() -> u32 {
    64
}
fn default_reference_paths() -> f64 {
    1e6
}

/// `[medium]`; absent keys take the defaults of [`Default`].
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawMedium {
    eta: f64,
    g: f64,
}

impl Default for RawMedium {
    fn default() -> Self {
        RawMedium { eta: 1.5, g: 0.3 }
    }
}

/// `[light]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawLight {
    kind: String,
    radius: f64,
    irradiance: f64,
}

impl Default for RawLight {
    fn default() -> Self {
        RawLight {
            kind: "collimated".into(),
            radius: 1.0,
            irradiance: 1.0,
        }
    }
}

/// `[image]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawImage {
    resolution: usize,
    half_width: f64,
}

impl Default for RawImage {
    fn default() -> Self {
        RawImage {
            resolution: 64,
            half_width: 4.0,
        }
    }
}

/// A map as written in the scene (see the module docs): a table, or the
/// shorthand of a number (a constant) or of three numbers (`rgb`); see the
/// `Deserialize` impl below.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, remote = "Self")]
struct RawMap {
    constant: Option<f64>,
    rgb: Option<[f64; 3]>,
    pattern: Option<String>,
    values: Option<toml::Value>,
    width: Option<f64>,
    angle: Option<f64>,
    cell: Option<f64>,
    length: Option<f64>,
    spacing: Option<f64>,
    radius: Option<f64>,
    seed: Option<u64>,
    file: Option<PathBuf>,
    transfer: Option<String>,
    channels: Option<Vec<RawMap>>,
    size: Option<[usize; 2]>,
}

impl<'de> Deserialize<'de> for RawMap {
    /// A table as derived (`remote = "Self"`); `0.8` as `{ constant = 0.8 }`,
    /// `[r, g, b]` as `{ rgb = [r, g, b] }`.
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::{self, MapAccess, SeqAccess, Visitor};
        struct Shorthand;
        impl<'de> Visitor<'de> for Shorthand {
            type Value = RawMap;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(
                    "a map: a number (a constant), a list [r, g, b] or a table \
                     such as { pattern = \"stripes\", values = [a, b] }",
                )
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> std::result::Result<RawMap, E> {
                Ok(RawMap {
                    constant: Some(v),
                    ..RawMap::default()
                })
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> std::result::Result<RawMap, E> {
                self.visit_f64(v as f64)
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> std::result::Result<RawMap, E> {
                self.visit_f64(v as f64)
            }
            fn visit_seq<A: SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> std::result::Result<RawMap, A::Error> {
                const RGB: &str = "three numbers [r, g, b]";
                let mut rgb = [0.0; 3];
                for (i, c) in rgb.iter_mut().enumerate() {
                    *c = seq
                        .next_element()?
                        .ok_or_else(|| de::Error::invalid_length(i, &RGB))?;
                }
                let mut n = 3;
                while seq.next_element::<de::IgnoredAny>()?.is_some() {
                    n += 1;
                }
                if n != 3 {
                    return Err(de::Error::invalid_length(n, &RGB));
                }
                Ok(RawMap {
                    rgb: Some(rgb),
                    ..RawMap::default()
                })
            }
            fn visit_map<A: MapAccess<'de>>(self, map: A) -> std::result::Result<RawMap, A::Error> {
                RawMap::deserialize(de::value::MapAccessDeserializer::new(map))
            }
        }
        d.deserialize_any(Shorthand)
    }
}

impl Scene {
    /// Loads and validates a scene file.
    pub fn load(path: &Path) -> Result<Scene> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Scene::from_toml(&text, path)
    }

    /// A scene file, or else the built-in canonical scene of that name
    /// ([`crate::jobs::shipped::SCENES`]): `stripes` or `scenes/stripes.toml`.
    ///
    /// ```
    /// use svkernel::render::scene::Scene;
    /// let s = Scene::find(std::path::Path::new("checker"))?;
    /// assert_eq!((s.name.as_str(), s.albedo.len()), ("checker", 1));
    /// # Ok::<(), svkernel::Error>(())
    /// ```
    pub fn find(name_or_path: &Path) -> Result<Scene> {
        if !name_or_path.exists()
            && let Some(text) = name_or_path
                .to_str()
                .and_then(crate::jobs::shipped::scene_text)
        {
            return Scene::from_toml(
                text,
                &PathBuf::from(format!("{}.toml", name_or_path.display())),
            );
        }
        Scene::load(name_or_path)
    }

    /// Parses and validates a scene from its TOML text; `path` names it in
    /// errors, and texture files are found relative to its folder.
    pub fn from_toml(text: &str, path: &Path) -> Result<Scene> {
        let text = text.to_string();
        let raw: RawScene = toml::from_str(&text).map_err(|e| {
            let line = e
                .span()
                .map(|s| format!("line {}", text[..s.start].matches('\n').count() + 1))
                .unwrap_or_else(|| "(unknown line)".into());
            Error::format(path, line, e.message().to_string())
        })?;
        let bad = |key: &str, msg: String| Error::format(path, key.to_string(), msg);
        let in_range = |key: &str, v: f64, ok: bool, allowed: &str| {
            if ok && v.is_finite() {
                Ok(())
            } else {
                Err(bad(key, format!("{v} must be {allowed}")))
            }
        };
        let m = &raw.medium;
        // The medium's domain is the library's; its errors name the scene key.
        Medium::new(0.5, m.g, m.eta, 1.0, None).map_err(|e| scene_key(path, e))?;
        in_range("texel", raw.texel, raw.texel > 0.0, "> 0")?;
        in_range(
            "light.radius",
            raw.light.radius,
            raw.light.radius > 0.0,
            "> 0",
        )?;
        in_range(
            "light.irradiance",
            raw.light.irradiance,
            raw.light.irradiance > 0.0,
            "> 0",
        )?;
        in_range(
            "image.half_width",
            raw.image.half_width,
            raw.image.half_width > 0.0,
            "> 0",
        )?;
        if !(1..=4096).contains(&raw.image.resolution) {
            return Err(bad(
                "image.resolution",
                format!("{} must be in 1..=4096", raw.image.resolution),
            ));
        }
        let light = match raw.light.kind.as_str() {
            "collimated" => LightKind::Collimated,
            "diffuse" => LightKind::Diffuse,
            k => {
                return Err(bad(
                    "light.kind",
                    format!("'{k}' must be collimated or diffuse"),
                ));
            }
        };
        let observable = match raw.observable.as_str() {
            "exitance" => Observable::Exitance,
            "radiance" => Observable::Radiance,
            o => {
                return Err(bad(
                    "observable",
                    format!("'{o}' must be exitance or radiance"),
                ));
            }
        };
        let methods = match &raw.methods {
            None => Method::ALL.to_vec(),
            Some(names) => names
                .iter()
                .map(|m| {
                    Method::parse(m).map_err(|_| {
                        bad(
                            "methods",
                            format!(
                                "unknown method '{m}' (known: {})",
                                method_names().join(", ")
                            ),
                        )
                    })
                })
                .collect::<Result<_>>()?,
        };
        if raw.samples == 0 {
            return Err(bad("samples", "must be >= 1".into()));
        }
        let rp = raw.reference_paths;
        if !((1.0..=1e15).contains(&rp) && rp.fract() == 0.0) {
            return Err(bad(
                "reference_paths",
                format!("{rp} must be an integer in [1, 1e15]"),
            ));
        }
        // Default map size: the image plus 4 MFP on every side.
        let extent = 2.0 * (raw.image.half_width + 4.0);
        let default_size = ((extent / raw.texel).ceil() as usize).max(1);
        let dir = path.parent().unwrap_or(Path::new("."));
        let albedo = build_map(&raw.albedo, "albedo", raw.texel, default_size, dir, path)?;
        for (c, m) in albedo.iter().enumerate() {
            if let Some(k) = m.values.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return Err(bad(
                    "albedo",
                    format!(
                        "{} of channel {c}{} must be in [0, 1]",
                        texel_value(m, k),
                        from_file(&raw.albedo, c)
                    ),
                ));
            }
        }
        let density = match &raw.density {
            None => None,
            Some(d) => {
                let mut maps = build_map(d, "density", raw.texel, default_size, dir, path)?;
                if maps.len() != 1 {
                    return Err(bad("density", "must have one channel".into()));
                }
                let m = maps.remove(0);
                if let Some(k) = m.values.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
                    return Err(bad(
                        "density",
                        format!(
                            "{}{} must be finite and > 0",
                            texel_value(&m, k),
                            from_file(d, 0)
                        ),
                    ));
                }
                Some(m)
            }
        };
        let density_sweep = raw.density_sweep.clone().unwrap_or_default();
        if let Some(r) = density_sweep.iter().find(|r| !(r.is_finite() && **r > 0.0)) {
            return Err(bad("density_sweep", format!("{r} must be finite and > 0")));
        }
        if !density_sweep.is_empty() && density.is_some() {
            return Err(bad(
                "density_sweep",
                "give either density or density_sweep".into(),
            ));
        }
        Ok(Scene {
            density_sweep,
            name: raw.name.clone().unwrap_or_else(|| {
                path.file_stem()
                    .map_or("scene".into(), |s| s.to_string_lossy().into_owned())
            }),
            path: path.to_path_buf(),
            source: text.clone(),
            eta: m.eta,
            g: m.g,
            texel: raw.texel,
            albedo,
            density,
            light,
            light_radius: raw.light.radius,
            irradiance: raw.light.irradiance,
            resolution: raw.image.resolution,
            half_width: raw.image.half_width,
            observable,
            methods,
            samples: raw.samples,
            reference_paths: rp as u64,
        })
    }

    /// True if every albedo channel is one constant (no aggregation needed).
    pub fn albedo_is_constant(&self) -> bool {
        self.albedo
            .iter()
            .all(|m| m.values.iter().all(|v| *v == m.values[0]))
    }

    /// True if the RGB channels are identical (render one channel).
    pub fn is_grey(&self) -> bool {
        self.albedo.len() == 1
            || self.albedo.iter().all(|m| {
                (m.nx, m.ny, &m.values)
                    == (self.albedo[0].nx, self.albedo[0].ny, &self.albedo[0].values)
            })
    }
}

/// A library error about a parameter (`eta`) as the scene file's key that
/// set it (`medium.eta`); other errors as they are.
fn scene_key(path: &Path, e: Error) -> Error {
    match e {
        Error::Param {
            name,
            value,
            allowed,
        } => {
            let key = match name {
                "eta" => "medium.eta",
                "g" => "medium.g",
                other => other,
            };
            Error::format(path, key, format!("{value} must be {allowed}"))
        }
        e => e,
    }
}

/// "value V at texel (row i, column j)" of the `k`-th value of `m`.
fn texel_value(m: &TexelMap, k: usize) -> String {
    format!(
        "value {} at texel (row {}, column {})",
        m.values[k],
        k / m.nx,
        k % m.nx
    )
}

/// " in FILE" when channel `c` of the map comes from a file, else "".
fn from_file(raw: &RawMap, c: usize) -> String {
    let file = raw
        .file
        .as_ref()
        .or_else(|| raw.channels.as_ref()?.get(c)?.file.as_ref());
    file.map_or(String::new(), |f| format!(" in {}", f.display()))
}

/// The values of a map: one per channel.
fn values_of(raw: &RawMap, key: &str, path: &Path) -> Result<Vec<Vec<f64>>> {
    let bad = |msg: String| Error::format(path, format!("{key}.values"), msg);
    let v = raw
        .values
        .as_ref()
        .ok_or_else(|| bad("a pattern needs `values = [a, b]`".into()))?;
    let arr = v.as_array().ok_or_else(|| bad("must be a list".into()))?;
    if arr.len() != 2 {
        return Err(bad(format!(
            "needs exactly two values, found {}",
            arr.len()
        )));
    }
    let num = |x: &toml::Value| x.as_float().or_else(|| x.as_integer().map(|i| i as f64));
    // Grey: [a, b]; RGB: [[r, g, b], [r, g, b]].
    if arr.iter().all(|x| num(x).is_some()) {
        return Ok(vec![arr.iter().map(|x| num(x).unwrap_or(0.0)).collect()]);
    }
    let rgb: Option<Vec<Vec<f64>>> = arr
        .iter()
        .map(|x| {
            let a = x.as_array()?;
            (a.len() == 3).then(|| a.iter().map(num).collect::<Option<Vec<f64>>>())?
        })
        .collect();
    let rgb = rgb.ok_or_else(|| bad("must be two numbers or two [r, g, b] lists".into()))?;
    Ok((0..3).map(|c| vec![rgb[0][c], rgb[1][c]]).collect())
}

/// A map's kind with what it reads, validated: the typed form of
/// [`RawMap`].
#[derive(Clone, Debug, PartialEq)]
enum MapSpec {
    Constant(f64),
    Rgb([f64; 3]),
    /// R, G, B from three grey maps.
    Channels(Vec<MapSpec>),
    /// A texture file, relative to the scene file.
    File {
        file: PathBuf,
        format: FileFormat,
    },
    /// A procedural pattern on `size` texels, blending `values` (per
    /// channel: [a, b]).
    Pattern {
        pattern: Pattern,
        size: [usize; 2],
        values: Vec<Vec<f64>>,
    },
}

/// How a texture file is read.
#[derive(Clone, Copy, Debug, PartialEq)]
enum FileFormat {
    Npy,
    Exr,
    /// 8- or 16-bit PNG; `srgb`: decode the sRGB transfer to linear.
    Png {
        srgb: bool,
    },
}

/// A procedural pattern and its sizes (MFP).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Pattern {
    /// Stripes of `width` across the direction `angle` (radians from +x).
    Stripes {
        width: f64,
        angle: f64,
    },
    Checker {
        cell: f64,
    },
    /// Linear in x over `length`, centred on the origin, clamped.
    Ramp {
        length: f64,
    },
    Dots {
        spacing: f64,
        radius: f64,
    },
    /// Thin lines and dots at three scales ([`complex_pattern`]).
    Complex {
        seed: u64,
    },
    /// Veins of half-width `width` every `spacing` across `angle`,
    /// displaced by turbulence ([`marble_pattern`]).
    Marble {
        spacing: f64,
        width: f64,
        angle: f64,
        seed: u64,
    },
    /// Smooth mottling of feature size `cell` ([`fbm`]).
    Mottled {
        cell: f64,
        seed: u64,
    },
}

impl Pattern {
    /// Selector in [0, 1] at (x, y): 0 → values[0], 1 → values[1].
    fn select(&self, x: f64, y: f64) -> f64 {
        match *self {
            Pattern::Stripes { width, angle } => {
                let u = x * angle.cos() + y * angle.sin();
                ((u / width).floor().rem_euclid(2.0) != 0.0) as u8 as f64
            }
            Pattern::Checker { cell } => {
                (((x / cell).floor() + (y / cell).floor()).rem_euclid(2.0) != 0.0) as u8 as f64
            }
            Pattern::Ramp { length } => (x / length + 0.5).clamp(0.0, 1.0),
            Pattern::Dots { spacing, radius } => {
                let (dx, dy) = (
                    x - spacing * (x / spacing).round(),
                    y - spacing * (y / spacing).round(),
                );
                (dx.hypot(dy) < radius) as u8 as f64
            }
            Pattern::Complex { seed } => complex_pattern(seed, x, y),
            Pattern::Marble {
                spacing,
                width,
                angle,
                seed,
            } => marble_pattern(spacing, width, angle, seed, x, y),
            Pattern::Mottled { cell, seed } => fbm(seed, x / cell, y / cell),
        }
    }
}

impl MapSpec {
    /// Validates a written map (`key` and `path` name it in errors): one
    /// kind, only the keys that kind reads, values in their domains.
    fn parse(raw: &RawMap, key: &str, default_size: usize, path: &Path) -> Result<MapSpec> {
        let bad = |sub: &str, msg: String| Error::format(path, format!("{key}{sub}"), msg);
        let kinds = [
            raw.constant.is_some(),
            raw.rgb.is_some(),
            raw.pattern.is_some(),
            raw.file.is_some(),
            raw.channels.is_some(),
        ];
        if kinds.iter().filter(|k| **k).count() != 1 {
            return Err(bad(
                "",
                "give exactly one of constant, rgb, pattern, file, channels".into(),
            ));
        }
        // A key the map's kind does not read is an error, not silently
        // ignored (e.g. `width` on a checker, whose cell would stay at its
        // default).
        let (what, takes): (String, &[&str]) = match (&raw.pattern, &raw.file) {
            (Some(p), _) => (
                format!("pattern \"{p}\""),
                match p.as_str() {
                    "stripes" => &["values", "size", "width", "angle"],
                    "checker" => &["values", "size", "cell"],
                    "ramp" => &["values", "size", "length"],
                    "dots" => &["values", "size", "spacing", "radius"],
                    "complex" => &["values", "size", "seed"],
                    "marble" => &["values", "size", "spacing", "width", "angle", "seed"],
                    "mottled" => &["values", "size", "cell", "seed"],
                    _ => &[
                        "values", "size", "width", "angle", "cell", "length", "spacing", "radius",
                        "seed",
                    ],
                },
            ),
            (None, Some(_)) => ("a file map".into(), &["transfer"]),
            // A constant reads the same at every size: `size` is harmless.
            _ if raw.constant.is_some() || raw.rgb.is_some() => {
                ("a constant map".into(), &["size"])
            }
            _ => ("this map".into(), &[]),
        };
        let given = [
            ("values", raw.values.is_some()),
            ("width", raw.width.is_some()),
            ("angle", raw.angle.is_some()),
            ("cell", raw.cell.is_some()),
            ("length", raw.length.is_some()),
            ("spacing", raw.spacing.is_some()),
            ("radius", raw.radius.is_some()),
            ("seed", raw.seed.is_some()),
            ("transfer", raw.transfer.is_some()),
            ("size", raw.size.is_some()),
        ];
        if let Some((k, _)) = given.iter().find(|(k, on)| *on && !takes.contains(k)) {
            let takes = if takes.is_empty() {
                "no other key".to_string()
            } else {
                takes.join(", ")
            };
            return Err(bad(
                &format!(".{k}"),
                format!("not a key of {what} (it takes: {takes})"),
            ));
        }
        if let Some(ch) = &raw.channels {
            if ch.len() != 3 {
                return Err(bad(
                    ".channels",
                    format!("needs three maps (R, G, B), found {}", ch.len()),
                ));
            }
            return ch
                .iter()
                .enumerate()
                .map(|(c, m)| {
                    MapSpec::parse(m, &format!("{key}.channels[{c}]"), default_size, path)
                })
                .collect::<Result<_>>()
                .map(MapSpec::Channels);
        }
        if let Some(c) = raw.constant {
            return Ok(MapSpec::Constant(c));
        }
        if let Some(rgb) = raw.rgb {
            return Ok(MapSpec::Rgb(rgb));
        }
        if let Some(file) = &raw.file {
            let ext = file
                .extension()
                .map(|e| e.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            // Any letter case: "sRGB", "Linear".
            let lower = raw.transfer.as_ref().map(|t| t.to_ascii_lowercase());
            let transfer = lower.as_deref();
            match (ext.as_str(), transfer) {
                ("png", Some("srgb" | "linear")) | ("npy" | "exr", None | Some("linear")) => {}
                ("png", None) => {
                    return Err(bad(
                        ".transfer",
                        "missing: a PNG map needs transfer = \"srgb\" or \"linear\"".into(),
                    ));
                }
                ("png", Some(_)) => {
                    return Err(bad(
                        ".transfer",
                        format!(
                            "'{}': a PNG map needs transfer = \"srgb\" or \"linear\"",
                            raw.transfer.as_deref().unwrap_or_default()
                        ),
                    ));
                }
                (_, Some(_)) => {
                    return Err(bad(
                        ".transfer",
                        format!(
                            "'{}': .npy and .exr maps hold linear values",
                            raw.transfer.as_deref().unwrap_or_default()
                        ),
                    ));
                }
                _ => {}
            }
            let format = match ext.as_str() {
                "npy" => FileFormat::Npy,
                "exr" => FileFormat::Exr,
                "png" => FileFormat::Png {
                    srgb: transfer == Some("srgb"),
                },
                _ => {
                    return Err(bad(
                        ".file",
                        format!("{}: expected a .npy, .exr or .png file", file.display()),
                    ));
                }
            };
            return Ok(MapSpec::File {
                file: file.clone(),
                format,
            });
        }
        let [nx, ny] = raw.size.unwrap_or([default_size, default_size]);
        if nx == 0 || ny == 0 || nx.checked_mul(ny).is_none_or(|n| n > 1 << 26) {
            return Err(bad(
                ".size",
                format!("[{nx}, {ny}] must be positive and at most 2^26 texels"),
            ));
        }
        let values = values_of(raw, key, path)?;
        let positive = |name: &str, v: Option<f64>, default: f64| -> Result<f64> {
            let v = v.unwrap_or(default);
            if v > 0.0 && v.is_finite() {
                Ok(v)
            } else {
                Err(bad(
                    &format!(".{name}"),
                    format!("{v} must be finite and > 0"),
                ))
            }
        };
        let finite = |name: &str, v: f64| -> Result<f64> {
            if v.is_finite() {
                Ok(v)
            } else {
                Err(bad(&format!(".{name}"), format!("{v} must be finite")))
            }
        };
        let pattern = match raw.pattern.as_deref().unwrap_or_default() {
            "stripes" => Pattern::Stripes {
                width: positive("width", raw.width, 0.5)?,
                angle: finite("angle", raw.angle.unwrap_or(0.0))?.to_radians(),
            },
            "checker" => Pattern::Checker {
                cell: positive("cell", raw.cell, 0.5)?,
            },
            "ramp" => Pattern::Ramp {
                length: positive("length", raw.length, 8.0)?,
            },
            "dots" => Pattern::Dots {
                spacing: positive("spacing", raw.spacing, 1.0)?,
                radius: positive("radius", raw.radius, 0.2)?,
            },
            "complex" => Pattern::Complex {
                seed: raw.seed.unwrap_or(1),
            },
            "marble" => Pattern::Marble {
                spacing: positive("spacing", raw.spacing, 3.0)?,
                width: positive("width", raw.width, 0.1)?,
                angle: finite("angle", raw.angle.unwrap_or(30.0))?.to_radians(),
                seed: raw.seed.unwrap_or(1),
            },
            "mottled" => Pattern::Mottled {
                cell: positive("cell", raw.cell, 1.0)?,
                seed: raw.seed.unwrap_or(1),
            },
            p => {
                return Err(bad(
                    ".pattern",
                    format!(
                        "unknown pattern '{p}' (stripes, checker, ramp, dots, complex, marble, mottled)"
                    ),
                ));
            }
        };
        Ok(MapSpec::Pattern {
            pattern,
            size: [nx, ny],
            values,
        })
    }

    /// The map's channels on texels of size `texel`; files are read from
    /// `dir` (errors name the scene file `path`, the key and the file).
    fn build(&self, key: &str, texel: f64, dir: &Path, path: &Path) -> Result<Vec<TexelMap>> {
        let bad = |sub: &str, msg: String| Error::format(path, format!("{key}{sub}"), msg);
        match self {
            MapSpec::Constant(c) => Ok(vec![TexelMap::new(1, 1, texel, vec![*c])?]),
            MapSpec::Rgb(rgb) => rgb
                .iter()
                .map(|c| TexelMap::new(1, 1, texel, vec![*c]))
                .collect(),
            MapSpec::Channels(ch) => {
                let mut out = Vec::new();
                for (c, m) in ch.iter().enumerate() {
                    let mut v = m.build(&format!("{key}.channels[{c}]"), texel, dir, path)?;
                    if v.len() != 1 {
                        return Err(bad(
                            &format!(".channels[{c}]"),
                            "each channel must be a grey map".into(),
                        ));
                    }
                    out.push(v.remove(0));
                }
                Ok(out)
            }
            MapSpec::File { file, format } => {
                let path_of = dir.join(file);
                let loaded = match format {
                    FileFormat::Npy => load_npy(&path_of, texel),
                    FileFormat::Exr => load_exr(&path_of, texel),
                    FileFormat::Png { srgb } => load_png(&path_of, texel, *srgb),
                };
                // Named by the scene file and key, and the map file.
                loaded.map_err(|e| {
                    let (msg, name) = (e.to_string(), path_of.display().to_string());
                    bad(
                        ".file",
                        if msg.contains(&name) {
                            msg
                        } else {
                            format!("{name}: {msg}")
                        },
                    )
                })
            }
            MapSpec::Pattern {
                pattern,
                size: [nx, ny],
                values,
            } => {
                let (nx, ny) = (*nx, *ny);
                let centre = |i: usize, j: usize| {
                    (
                        -0.5 * nx as f64 * texel + (j as f64 + 0.5) * texel,
                        0.5 * ny as f64 * texel - (i as f64 + 0.5) * texel,
                    )
                };
                values
                    .iter()
                    .map(|vals| {
                        let mut v = Vec::with_capacity(nx * ny);
                        for i in 0..ny {
                            for j in 0..nx {
                                let (x, y) = centre(i, j);
                                let s = pattern.select(x, y);
                                v.push(vals[0] + s * (vals[1] - vals[0]));
                            }
                        }
                        TexelMap::new(nx, ny, texel, v)
                    })
                    .collect()
            }
        }
    }
}

/// Builds a map's channels on its texel grid: validated
/// ([`MapSpec::parse`]), then built ([`MapSpec::build`]).
fn build_map(
    raw: &RawMap,
    key: &str,
    texel: f64,
    default_size: usize,
    dir: &Path,
    path: &Path,
) -> Result<Vec<TexelMap>> {
    MapSpec::parse(raw, key, default_size, path)?.build(key, texel, dir, path)
}

/// Thin lines and dots at three scales (seeded): 1 on a feature, 0 off.
fn complex_pattern(seed: u64, x: f64, y: f64) -> f64 {
    let mut rng = PathRng::new(seed, 0);
    let mut on = false;
    for scale in [0.4, 1.0, 2.5] {
        let (ox, oy, a) = (
            rng.uniform() * scale,
            rng.uniform() * scale,
            rng.uniform() * 3.0,
        );
        // Thin lines (width scale/8) at angle a, period 2·scale.
        let u = (x - ox) * a.cos() + (y - oy) * a.sin();
        on |= (u / (2.0 * scale)).rem_euclid(1.0) < 1.0 / 16.0;
        // Dots of radius scale/6 on a lattice of period 1.5·scale.
        let p = 1.5 * scale;
        let (dx, dy) = (
            x - ox - p * ((x - ox) / p).round(),
            y - oy - p * ((y - oy) / p).round(),
        );
        on |= dx.hypot(dy) < scale / 6.0;
    }
    on as u8 as f64
}

/// Value noise in [0, 1] on the unit lattice: a uniform number per lattice
/// point (stream (seed, point)), blended by smoothstep.
fn value_noise(seed: u64, x: f64, y: f64) -> f64 {
    let (i, j) = (x.floor(), y.floor());
    let smooth = |t: f64| t * t * (3.0 - 2.0 * t);
    let (fx, fy) = (smooth(x - i), smooth(y - j));
    let at = |a: f64, b: f64| {
        let key = ((a as i64 as u64) << 32) ^ (b as i64 as u64 & 0xffff_ffff);
        PathRng::new(seed, key).uniform()
    };
    let (v00, v10) = (at(i, j), at(i + 1.0, j));
    let (v01, v11) = (at(i, j + 1.0), at(i + 1.0, j + 1.0));
    let bottom = v00 + fx * (v10 - v00);
    let top = v01 + fx * (v11 - v01);
    bottom + fy * (top - bottom)
}

/// Fractal value noise in [0, 1]: four octaves of [`value_noise`], each at
/// twice the frequency and half the amplitude of the last, normalised.
fn fbm(seed: u64, x: f64, y: f64) -> f64 {
    let (mut sum, mut amp, mut freq, mut norm) = (0.0, 1.0, 1.0, 0.0);
    for octave in 0..4u64 {
        sum += amp * value_noise(seed.wrapping_add(octave), x * freq, y * freq);
        norm += amp;
        amp *= 0.5;
        freq *= 2.0;
    }
    sum / norm
}

/// Marble veins: 1 on a vein, falling linearly to 0 at `width` from its
/// centre line. Vein centre lines run across `angle` every `spacing`,
/// displaced along it by turbulence ([`fbm`] at the spacing's scale, ±0.75
/// spacing).
fn marble_pattern(spacing: f64, width: f64, angle: f64, seed: u64, x: f64, y: f64) -> f64 {
    let u = x * angle.cos() + y * angle.sin();
    let t = u + 1.5 * spacing * (fbm(seed, x / spacing, y / spacing) - 0.5);
    // Distance to the nearest centre line (t a multiple of `spacing`).
    let dist = (t - spacing * (t / spacing).round()).abs();
    (1.0 - dist / width).max(0.0)
}

/// Loads an image file as 1 or 3 texel maps of size `texel`: `.npy`
/// (`(ny, nx)` or `(ny, nx, 3)`, float64 or float32, linear), `.exr`
/// (linear) or `.png` (8 or 16 bit, decoded from sRGB); row 0 is +y.
pub fn load_image(file: &Path, texel: f64) -> Result<Vec<TexelMap>> {
    let ext = file
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or_default()
        .to_ascii_lowercase();
    match ext.as_str() {
        "npy" => load_npy(file, texel),
        "exr" => load_exr(file, texel),
        "png" => load_png(file, texel, true),
        _ => Err(Error::format(
            file,
            "(extension)",
            "expected a .png (sRGB), .exr or .npy image",
        )),
    }
}

/// Loads the first layer of an OpenEXR file: channels R, G, B (3 maps), or
/// Y, or the only channel (1 map); row 0 of the image is +y.
fn load_exr(file: &Path, texel: f64) -> Result<Vec<TexelMap>> {
    let img = exr::prelude::read_all_flat_layers_from_file(file)
        .map_err(|e| Error::format(file, "(exr)", e))?;
    let layer = img
        .layer_data
        .first()
        .ok_or_else(|| Error::format(file, "(exr)", "no layer"))?;
    let (nx, ny) = (layer.size.0, layer.size.1);
    let list = &layer.channel_data.list;
    let find = |n: &str| list.iter().find(|c| c.name.to_string() == n);
    let chosen: Vec<_> = match (find("R"), find("G"), find("B"), find("Y")) {
        (Some(r), Some(g), Some(b), _) => vec![r, g, b],
        (_, _, _, Some(y)) => vec![y],
        _ if list.len() == 1 => vec![&list[0]],
        _ => {
            return Err(Error::format(
                file,
                "(channels)",
                "expected R, G, B or Y or a single channel",
            ));
        }
    };
    chosen
        .iter()
        .map(|c| {
            let v = (0..nx * ny)
                .map(|k| c.sample_data.value_by_flat_index(k).to_f32() as f64)
                .collect();
            TexelMap::new(nx, ny, texel, v)
        })
        .collect()
}

/// Loads an 8- or 16-bit PNG (grey or RGB) as 1 or 3 maps with values
/// v/(2^bits − 1), decoded from sRGB to linear if `srgb` (IEC 61966-2-1);
/// row 0 of the image is +y. An alpha channel (or a tRNS transparency,
/// which the decoder expands to one) is refused: what would it mean for an
/// albedo or a density?
fn load_png(file: &Path, texel: f64, srgb: bool) -> Result<Vec<TexelMap>> {
    let bad = |e: &dyn std::fmt::Display| Error::format(file, "(png)", e.to_string());
    let f = std::fs::File::open(file).map_err(|e| Error::io(file, e))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(f));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec.read_info().map_err(|e| bad(&e))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| bad(&e))?;
    let (nx, ny) = (info.width as usize, info.height as usize);
    let colours = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::Rgb => 3,
        png::ColorType::GrayscaleAlpha | png::ColorType::Rgba => {
            return Err(Error::format(
                file,
                "(png)",
                "has an alpha channel; svkernel reads grey or RGB maps: flatten the image first",
            ));
        }
        png::ColorType::Indexed => return Err(bad(&"indexed colour left unexpanded")),
    };
    let wide = info.bit_depth == png::BitDepth::Sixteen;
    let max = if wide { 65535.0 } else { 255.0 };
    let stride = colours;
    let sample = |k: usize| -> f64 {
        let v = if wide {
            u16::from_be_bytes([buf[2 * k], buf[2 * k + 1]]) as f64
        } else {
            buf[k] as f64
        } / max;
        if srgb {
            if v <= 0.040_45 {
                v / 12.92
            } else {
                ((v + 0.055) / 1.055).powf(2.4)
            }
        } else {
            v
        }
    };
    (0..colours)
        .map(|c| {
            let v = (0..nx * ny).map(|p| sample(p * stride + c)).collect();
            TexelMap::new(nx, ny, texel, v)
        })
        .collect()
}

/// Loads an `(ny, nx)` or `(ny, nx, 3)` float64 or float32 `.npy` as 1 or 3
/// channels (float32 values widened exactly).
fn load_npy(file: &Path, texel: f64) -> Result<Vec<TexelMap>> {
    use ndarray::ArrayD;
    use ndarray_npy::{ReadNpyError, ReadNpyExt};
    let open = || std::fs::File::open(file).map_err(|e| Error::io(file, e));
    let bad = |e: ReadNpyError| Error::format(file, "(npy)", e);
    // The dtype is checked on the header, before any data is read: a float32
    // file costs one extra header parse.
    let a = match ArrayD::<f64>::read_npy(open()?) {
        Ok(a) => a,
        Err(ReadNpyError::WrongDescriptor(_)) => match ArrayD::<f32>::read_npy(open()?) {
            Ok(a) => a.mapv(f64::from),
            Err(ReadNpyError::WrongDescriptor(d)) => {
                return Err(Error::format(
                    file,
                    "(npy)",
                    format!("dtype {d}: svkernel reads float64 ('<f8') or float32 ('<f4') arrays"),
                ));
            }
            Err(e) => return Err(bad(e)),
        },
        Err(e) => return Err(bad(e)),
    };
    let shape = a.shape().to_vec();
    let (ny, nx, nc) = match shape[..] {
        [ny, nx] => (ny, nx, 1),
        [ny, nx, 3] => (ny, nx, 3),
        _ => {
            let dims: Vec<String> = shape.iter().map(|n| n.to_string()).collect();
            return Err(Error::format(
                file,
                "(shape)",
                format!("({}): expected (ny, nx) or (ny, nx, 3)", dims.join(", ")),
            ));
        }
    };
    let flat: Vec<f64> = a.iter().copied().collect();
    (0..nc)
        .map(|c| {
            let v = (0..ny * nx).map(|k| flat[k * nc + c]).collect();
            TexelMap::new(nx, ny, texel, v)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("svk-scene-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    /// The translucent scenes' patterns: selectors in [0, 1], continuous
    /// mottling that spans most of its range with mean ≈ 1/2, and marble
    /// veins covering about their width's share of the plane (a vein of
    /// half-width w falling linearly covers 2w/spacing at half weight).
    #[test]
    fn marble_and_mottled_patterns() {
        let (n, step) = (400, 0.05);
        let grid = || (0..n * n).map(|k| ((k % n) as f64 * step, (k / n) as f64 * step));
        let mottled: Vec<f64> = grid().map(|(x, y)| fbm(3, x, y)).collect();
        let mean = mottled.iter().sum::<f64>() / mottled.len() as f64;
        let (lo, hi) = mottled
            .iter()
            .fold((1.0f64, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
        assert!((0.0..=1.0).contains(&lo) && (0.0..=1.0).contains(&hi));
        assert!(
            (mean - 0.5).abs() < 0.1 && hi - lo > 0.5,
            "{mean} {lo} {hi}"
        );
        // Continuous: neighbours one texel apart differ by little.
        let jump = (1..mottled.len())
            .filter(|k| k % n != 0)
            .map(|k| (mottled[k] - mottled[k - 1]).abs());
        assert!(jump.fold(0.0f64, f64::max) < 0.2);
        let (spacing, width) = (2.5, 0.15);
        let marble: Vec<f64> = grid()
            .map(|(x, y)| marble_pattern(spacing, width, 0.5, 5, x, y))
            .collect();
        assert!(marble.iter().all(|v| (0.0..=1.0).contains(v)));
        let share = marble.iter().sum::<f64>() / marble.len() as f64;
        let want = width / spacing; // ∫(1 − |d|/w) over ±w = w, per spacing
        assert!((share - want).abs() < 0.5 * want, "{share} vs {want}");
        assert_eq!(fbm(3, 1.3, -2.7), fbm(3, 1.3, -2.7));
        assert_ne!(fbm(3, 1.3, -2.7), fbm(4, 1.3, -2.7));
    }

    #[test]
    fn exr_and_png_maps() {
        use crate::render::estimator::Image;
        let dir = std::env::temp_dir().join(format!("svk-scene-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // EXR: 3 × 3 RGB, channel c of pixel k holds (c + 1)·k/100.
        let mut img = Image::zeros(3, 3);
        for c in 0..3 {
            for k in 0..9 {
                img.mean[c * 9 + k] = (c + 1) as f64 * k as f64 / 100.0;
            }
        }
        crate::jobs::output::write_exr(&dir.join("m.exr"), &img, "t").unwrap();
        let p = write("exr.toml", "texel = 1.0\nalbedo = { file = \"m.exr\" }\n");
        let s = Scene::load(&p).unwrap();
        assert_eq!(s.albedo.len(), 3);
        assert!((s.albedo[1].values[5] - 0.10).abs() < 1e-6);
        // PNG: 2 × 2 grey, values 0, 128, 255, 64 (row 0 first).
        crate::jobs::output::write_png_bytes(&dir.join("m.png"), 2, false, &[0, 128, 255, 64])
            .unwrap();
        let p = write(
            "png.toml",
            "texel = 1.0\nalbedo = { file = \"m.png\", transfer = \"linear\" }\n",
        );
        let s = Scene::load(&p).unwrap();
        assert_eq!(
            s.albedo[0].values,
            vec![0.0, 128.0 / 255.0, 1.0, 64.0 / 255.0]
        );
        let p = write(
            "png2.toml",
            "texel = 1.0\nalbedo = { file = \"m.png\", transfer = \"srgb\" }\n",
        );
        let v = Scene::load(&p).unwrap().albedo[0].values[1];
        assert!((v - 0.2158605).abs() < 1e-6, "{v}");
        // A PNG without its transfer, or a transfer on an EXR: refused, naming the key.
        let p = write("png3.toml", "texel = 1.0\nalbedo = { file = \"m.png\" }\n");
        let e = Scene::load(&p).unwrap_err().to_string();
        assert!(
            e.contains("png3.toml") && e.contains("albedo.transfer"),
            "{e}"
        );
        let p = write(
            "exr2.toml",
            "texel = 1.0\nalbedo = { file = \"m.exr\", transfer = \"srgb\" }\n",
        );
        assert!(
            Scene::load(&p)
                .unwrap_err()
                .to_string()
                .contains("albedo.transfer")
        );
        let p = write("bmp.toml", "texel = 1.0\nalbedo = { file = \"m.bmp\" }\n");
        assert!(
            Scene::load(&p)
                .unwrap_err()
                .to_string()
                .contains("albedo.file")
        );
        // A key the map does not read.
        for (name, text, key) in [
            (
                "width.toml",
                "texel = 1.0\nalbedo = { pattern = \"checker\", values = [0.3, 0.9], width = 0.5 }\n",
                "albedo.width",
            ),
            (
                "transfer.toml",
                "texel = 1.0\nalbedo = { constant = 0.5, transfer = \"srgb\" }\n",
                "albedo.transfer",
            ),
        ] {
            let err = Scene::load(&write(name, text)).unwrap_err().to_string();
            assert!(err.contains(key) && err.contains("not a key"), "{err}");
        }
        // A missing map file: the scene, the key and the map are named.
        let p = write(
            "gone.toml",
            "texel = 1.0\nalbedo = { constant = 0.5 }\ndensity = { file = \"gone.npy\" }\n",
        );
        let err = Scene::load(&p).unwrap_err().to_string();
        assert!(
            ["gone.toml", "density.file", "gone.npy"]
                .iter()
                .all(|n| err.contains(n)),
            "{err}"
        );
    }

    #[test]
    fn patterns_follow_the_texel_conventions() {
        let p = write(
            "stripes.toml",
            "texel = 0.25\nalbedo = { pattern = \"stripes\", values = [0.3, 0.95], width = 0.5, size = [8, 2] }\n",
        );
        let s = Scene::load(&p).unwrap();
        let m = &s.albedo[0];
        assert_eq!((m.nx, m.ny), (8, 2));
        // x ∈ [−1, 1): stripe k = ⌊x/w⌋, even k → values[0]: [−1, −0.5)
        // is k = −2 → 0.3, [−0.5, 0) is k = −1 → 0.95, [0, 0.5) → 0.3.
        assert_eq!(m.at(-0.9, 0.0), 0.3);
        assert_eq!(m.at(-0.3, 0.0), 0.95);
        assert_eq!(m.at(0.2, 0.0), 0.3);
        assert!(!s.albedo_is_constant() && s.is_grey());
        assert_eq!(s.methods.len(), method_names().len());
        // Channels with the same values in different shapes are not grey.
        let p = write(
            "shapes.toml",
            "texel = 0.25\nalbedo = { channels = [\
             { pattern = \"ramp\", values = [0.2, 0.9], length = 0.5, size = [2, 1] }, \
             { constant = 0.2 }, \
             { pattern = \"ramp\", values = [0.2, 0.9], length = 0.5, size = [2, 1] }] }\n",
        );
        let mut s = Scene::load(&p).unwrap();
        let (a, b) = (s.albedo[0].clone(), &mut s.albedo[1]);
        *b = TexelMap::new(1, 2, a.texel, a.values.clone()).unwrap();
        assert_eq!(s.albedo[1].values, s.albedo[0].values);
        assert!(!s.is_grey());
    }

    #[test]
    fn errors_name_the_file_key_and_line() {
        for (text, want) in [
            ("albedo = { constant = 1.5 }\n", "albedo"),
            (
                "albedo = { constant = 0.5 }\n[medium]\neta = 0.5\n",
                "medium.eta",
            ),
            (
                "albedo = { constant = 0.5 }\n[light]\nkind = \"laser\"\n",
                "light.kind",
            ),
            (
                "albedo = { constant = 0.5 }\nmethods = [\"magic\"]\n",
                "methods",
            ),
            (
                "albedo = { pattern = \"zebra\", values = [0.1, 0.2] }\n",
                "albedo.pattern",
            ),
            ("albedo = { constant = 0.5 }\ncolour = 3\n", "line 2"),
            (
                "albedo = { constant = 0.5 }\n[image]\nresolution = \"big\"\n",
                "line 3",
            ),
            (
                "albedo = { constant = 0.5, rgb = [0.1, 0.2, 0.3] }\n",
                "exactly one",
            ),
            (
                "albedo = { constant = 0.5 }\ndensity = { constant = 0 }\n",
                "density",
            ),
        ] {
            let p = write("bad.toml", text);
            let e = Scene::load(&p).unwrap_err().to_string();
            assert!(e.contains("bad.toml") && e.contains(want), "{text:?}: {e}");
        }
    }

    #[test]
    fn rgb_and_npy_maps() {
        let p = write(
            "rgb.toml",
            "albedo = { pattern = \"checker\", values = [[0.2, 0.3, 0.4], [0.9, 0.8, 0.7]], cell = 0.5, size = [4, 4] }\n",
        );
        let s = Scene::load(&p).unwrap();
        assert_eq!(s.albedo.len(), 3);
        assert!(!s.is_grey());
        let dir = p.parent().unwrap();
        let arr = ndarray::Array3::from_shape_fn((2, 3, 3), |(i, j, c)| {
            0.1 * (i * 3 + j) as f64 + 0.01 * c as f64
        });
        ndarray_npy::write_npy(dir.join("m.npy"), &arr).unwrap();
        let p = write("npy.toml", "texel = 1.0\nalbedo = { file = \"m.npy\" }\n");
        let s = Scene::load(&p).unwrap();
        assert_eq!((s.albedo[0].nx, s.albedo[0].ny), (3, 2));
        // Row 0 is +y, column 0 is −x; channel 2 offset 0.02.
        assert!((s.albedo[2].at(-1.4, 0.9) - 0.02).abs() < 1e-12);
        assert!((s.albedo[0].at(1.4, -0.9) - 0.5).abs() < 1e-12);
    }
}
