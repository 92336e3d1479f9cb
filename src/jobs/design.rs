//! `svkernel design`: the albedo map whose appearance after sub-surface
//! scattering matches a target ([`crate::design`]), its files and report,
//! and its validation by brute force.
//!
//! # Outputs (in `--out DIR`, written only when the design is complete)
//! * `albedo.npy` (float64, the target's shape), `albedo.png` (sRGB);
//! * `naive.npy`: the baseline (R_d(α) = target per texel);
//! * `predicted.npy`: the model's appearance of the designed map;
//! * `design.json`: settings, objective per iteration, timings, metrics,
//!   provenance;
//! * `report.html`: target, albedo maps, appearances, error maps and the
//!   convergence plot.
//!
//! Work in progress (each finished channel, and the reference tallies of
//! a validation, checkpointed every 30 s) lives in `.DIR.partial` beside DIR
//! and is resumed from there by a re-run with the same target, settings and
//! models.
//!
//! # Validation
//! With `validate`, the naive and the designed maps (and the maps designed
//! with `point` and `factorized` as the forward model) are rendered by the
//! brute-force reference walk under a collimated disk light that reaches
//! further beyond the texture than the transport does, and compared with
//! the target over the texture's interior: relative RMSE (the reference's
//! own noise subtracted) and the mean CIEDE2000 difference (Sharma, Wu &
//! Dalal 2005; the `palette` crate) of the linear reflectances read as
//! linear sRGB.
//!
//! # Calibration
//! The model's remaining bias is a function of the texture and the
//! albedo, and a design cannot see it. With `calibrate`, one brute-force
//! render of the design (same light and pixel grid as the validation)
//! measures it: per channel, the interior pixels are binned by their
//! designed albedo ([`CALIBRATION_BINS`] bins of equal count) and each bin
//! gets the ratio c = Σ brute force / Σ model. The design is then run
//! again for the target T/c(α₁) at each texel (α₁ its first-design
//! albedo, c linear between the bins' mean albedos): where the model is
//! too bright by c, it is asked for that much more. This is one step of
//! defect correction with the brute-force walk; the designs with `point`
//! and `factorized` that the validation compares are calibrated the same
//! way.

use super::output::{diverging, srgb, to_u8, write_png_bytes_wh};
use super::plot::{Axes, Series, chart};
use super::render::{RenderOptions, Target, render_scene};
use super::report::{Block, to_html};
use super::shipped::Models;
use super::store::{content_hash, write_atomic, write_json_atomic, write_npy_atomic};
use crate::design::appearance::Illumination;
use crate::design::{ChannelDesign, Design, Designer, Settings, Step};
use crate::error::{Error, Result};
use crate::forward::maps::TexelMap;
use crate::forward::medium::Observable;
use crate::provenance::Provenance;
use crate::render::scene::{LightKind, Scene};
use crate::render::svbssrdf::Method;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The format tag of `design.json`.
pub const DESIGN_FORMAT: &str = "svkernel-design";

/// What `svkernel design` does.
#[derive(Clone, Debug)]
pub struct DesignOptions {
    pub target: PathBuf,
    pub out: PathBuf,
    pub settings: Settings,
    /// Reference paths per validated map; `None`: no validation.
    pub validate: Option<u64>,
    /// Reference paths of the calibration render; `None`: no calibration
    /// ([module docs](self)).
    pub calibrate: Option<u64>,
    /// Pixels per side of the validation images (over the texture).
    pub validate_resolution: usize,
    pub seed: u64,
    pub models: Models,
    pub progress: bool,
}

/// The errors of one appearance against the target over the interior.
#[derive(Clone, Debug, Serialize)]
pub struct Errors {
    /// √(max(0, Σ(m − t)² − Σσ²)/Σt²).
    pub rel_rmse: f64,
    /// Mean CIEDE2000 ΔE₀₀ (noise not removed).
    pub delta_e00: f64,
}

/// One validated forward model: the brute-force appearance of its design.
#[derive(Clone, Debug, Serialize)]
pub struct ValidationRow {
    pub method: String,
    pub designed: Errors,
    /// Seconds its design took.
    pub design_s: f64,
}

/// The brute-force validation.
#[derive(Clone, Debug, Serialize)]
pub struct Validation {
    pub paths: u64,
    pub resolution: usize,
    /// The light: a collimated disk of this radius (MFP) at the origin.
    pub light_radius: f64,
    /// Pixels within this distance (MFP) of the texture's edge are left out.
    pub interior_margin: f64,
    /// Relative standard error of the reference per pixel (RMS).
    pub reference_noise: f64,
    pub naive: Errors,
    pub rows: Vec<ValidationRow>,
    /// Naive error ÷ designed error for the designing model (relative
    /// RMSE); `None` when the designed map's error is below the
    /// reference's noise (a ratio the reference cannot resolve).
    pub improvement: Option<f64>,
    pub seconds: f64,
    /// The validation images (not in `design.json`; written as `.npy`).
    #[serde(skip)]
    pub images: ValidationImages,
}

/// Per channel, row-major `resolution²` images of the validation: the
/// target averaged over each pixel, and the brute-force appearance of the
/// naive and of the designed map.
#[derive(Clone, Debug, Default)]
pub struct ValidationImages {
    pub target: Vec<Vec<f64>>,
    pub naive: Vec<Vec<f64>>,
    pub designed: Vec<Vec<f64>>,
}

/// `design.json`.
#[derive(Clone, Debug, Serialize)]
pub struct DesignDoc {
    pub format: String,
    pub target: PathBuf,
    /// (ny, nx, channels).
    pub shape: [usize; 3],
    pub method: String,
    pub texel: f64,
    pub albedo_range: [f64; 2],
    pub illumination: String,
    pub warm_start: usize,
    pub iterations: usize,
    pub rounds: usize,
    pub smoothness: f64,
    pub quadrature: [usize; 2],
    /// α_t's space, scale b (MFP) and split kernel in `learned`.
    pub albedo_space: String,
    pub space_blur: f64,
    pub split: String,
    /// α_t under the interior vertices' kernel in `learned`.
    pub interior_kernel: bool,
    pub history: Vec<Step>,
    pub evaluations: usize,
    pub setup_s: f64,
    pub solve_s: f64,
    pub total_s: f64,
    pub stops: Vec<String>,
    /// The model's own error (relative RMSE of its appearance against the
    /// target, whole texture): naive and designed.
    pub model_naive_rel_rmse: f64,
    pub model_designed_rel_rmse: f64,
    /// The brute-force calibration of the model's bias, if asked for.
    pub calibration: Option<Calibration>,
    pub validation: Option<Validation>,
    pub provenance: Provenance,
}

/// Runs `svkernel design` and returns what `design.json` holds.
pub fn run(opts: &DesignOptions) -> Result<DesignDoc> {
    let start = Instant::now();
    let s = &opts.settings;
    let (target, nx, ny) = load_target(opts)?;
    let staging = staging_dir(&opts.out)?;
    let (designed, calibration) = design_calibrated(opts, &staging, s, &target, nx, ny)?;
    let mut validation = None;
    if let Some(paths) = opts.validate {
        validation = Some(validate(opts, &staging, &target, nx, ny, &designed, paths)?);
    }
    let flat = |v: &[Vec<f64>]| v.iter().flatten().copied().collect::<Vec<f64>>();
    let t = flat(&target);
    let doc = DesignDoc {
        format: DESIGN_FORMAT.into(),
        target: opts.target.clone(),
        shape: [ny, nx, target.len()],
        method: s.method.name().into(),
        texel: s.texel,
        albedo_range: s.albedo_range,
        illumination: s.illumination.name(),
        warm_start: s.warm_start,
        iterations: s.iterations,
        rounds: s.rounds,
        smoothness: s.smoothness,
        quadrature: [s.quadrature.rings, s.quadrature.angles],
        albedo_space: s.albedo_space.name().into(),
        space_blur: s.space_blur,
        split: s.split.name().into(),
        interior_kernel: s.interior_kernel,
        history: designed.history.clone(),
        evaluations: designed.evaluations,
        setup_s: designed.setup_seconds,
        solve_s: designed.solve_seconds,
        total_s: start.elapsed().as_secs_f64(),
        stops: designed.stops.clone(),
        model_naive_rel_rmse: rel_rmse(&flat(&designed.predicted_naive), &t, None),
        model_designed_rel_rmse: rel_rmse(&flat(&designed.predicted), &t, None),
        calibration,
        validation,
        provenance: Provenance::current(),
    };
    write_outputs(opts, &staging, &doc, &designed, &target, nx, ny)?;
    Ok(doc)
}

/// The target's channels (row-major reflectances), nx and ny, with the
/// settings checked.
fn load_target(opts: &DesignOptions) -> Result<(Vec<Vec<f64>>, usize, usize)> {
    opts.settings.validate()?;
    let maps = super::scene::load_image(&opts.target, opts.settings.texel)?;
    let (nx, ny) = (maps[0].nx, maps[0].ny);
    let target: Vec<Vec<f64>> = maps.iter().map(|m| m.values.clone()).collect();
    if let Some(v) = target.iter().flatten().find(|v| !(0.0..=1.0).contains(*v)) {
        return Err(Error::format(
            &opts.target,
            "(values)",
            format!("{v}: a target holds reflectances in [0, 1]"),
        ));
    }
    Ok((target, nx, ny))
}

/// Writes to `file` the appearance problem of the target's first channel
/// at its naive map under the settings' model, with the model's M and
/// exact gradient, for `tools/design_grad_check.py` (an independent JAX
/// implementation that differentiates it automatically).
pub fn export_check(opts: &DesignOptions, file: &Path) -> Result<()> {
    let (target, nx, ny) = load_target(opts)?;
    let models = &opts.models;
    let designer = Designer::new(
        &target,
        nx,
        ny,
        &models.basis,
        Some(&models.meta),
        &opts.settings,
    )?;
    super::store::write_json_compact_atomic(file, &designer.export_check(&models.basis, 0))
}

/// The staging folder `.NAME.partial` beside `out` (created if missing).
fn staging_dir(out: &Path) -> Result<PathBuf> {
    let name = out
        .file_name()
        .ok_or_else(|| Error::param("out", out.display(), "a folder name"))?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty());
    let dir = parent
        .unwrap_or(Path::new("."))
        .join(format!(".{}.partial", name.to_string_lossy()));
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    Ok(dir)
}

/// The design with settings `s`, with a progress line; each finished
/// channel is checkpointed in `staging` (keyed by the target channel, the
/// settings and the models) and taken from there by a re-run.
fn design_with(
    opts: &DesignOptions,
    staging: &Path,
    s: &Settings,
    target: &[Vec<f64>],
    nx: usize,
    ny: usize,
) -> Result<Design> {
    let models = &opts.models;
    let designer = Designer::new(target, nx, ny, &models.basis, Some(&models.meta), s)?;
    let total = designer.evaluations_per_channel() * designer.channels();
    let task = crate::progress::Task::new(
        opts.progress,
        format!("design ({})", s.method.name()),
        total as u64,
        "evaluations",
    );
    let mut done = 0;
    let mut channels = Vec::new();
    for (c, t) in target.iter().enumerate() {
        let bytes: Vec<u8> = t.iter().flat_map(|v| v.to_le_bytes()).collect();
        let settings = format!(
            "{s:?} {nx}x{ny} {} {}",
            models.basis_origin.display(),
            models.meta_origin.display()
        );
        let key = content_hash([bytes.as_slice(), settings.as_bytes()]);
        let file = staging.join(format!("{}-channel{c}.json", s.method.name()));
        let stored = std::fs::read(&file)
            .ok()
            .and_then(|b| serde_json::from_slice::<ChannelCheckpoint>(&b).ok())
            .filter(|ck| ck.key == key);
        let ch = match stored {
            Some(ck) => ck.design,
            None => {
                let ch = designer.channel(c, |k| task.set((done + k) as u64))?;
                write_json_atomic(
                    &file,
                    &ChannelCheckpoint {
                        key,
                        design: ch.clone(),
                    },
                )?;
                ch
            }
        };
        done += ch.evaluations;
        task.set(done as u64);
        channels.push(ch);
    }
    task.finish();
    Ok(Design::assemble(
        designer.naive(),
        designer.setup_seconds(),
        channels,
    ))
}

/// The brute-force calibration of a forward model's bias ([module
/// docs](self)).
#[derive(Clone, Debug, Serialize)]
pub struct Calibration {
    pub paths: u64,
    /// Per channel, the brute-force over model ratio per albedo bin.
    pub channels: Vec<CalibrationTable>,
    pub seconds: f64,
}

/// One channel's calibration: per bin of the first design's pixel albedos
/// (equal pixel counts, [`CALIBRATION_BINS`]), their mean albedo, the
/// ratio Σ brute force / Σ model over their pixels, and their number.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CalibrationTable {
    pub albedo: Vec<f64>,
    pub ratio: Vec<f64>,
    pub pixels: Vec<usize>,
}

/// Bins of a [`CalibrationTable`].
pub const CALIBRATION_BINS: usize = 8;

impl CalibrationTable {
    /// The bins of `(albedo, brute force, model)` per pixel: sorted by
    /// albedo, cut into [`CALIBRATION_BINS`] runs of equal count (bins
    /// whose mean albedos lie within 1e-6 of each other pooled).
    pub fn fit(mut pixels: Vec<(f64, f64, f64)>) -> CalibrationTable {
        pixels.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (n, bins) = (pixels.len(), CALIBRATION_BINS.min(pixels.len()));
        // Per bin: Σ albedo, Σ brute force, Σ model, count.
        let mut sums: Vec<[f64; 4]> = Vec::new();
        for b in 0..bins {
            let s = pixels[b * n / bins..(b + 1) * n / bins]
                .iter()
                .fold([0.0; 4], |s, p| {
                    [s[0] + p.0, s[1] + p.1, s[2] + p.2, s[3] + 1.0]
                });
            match sums.last_mut() {
                Some(last) if (s[0] / s[3] - last[0] / last[3]).abs() <= 1e-6 => {
                    for (a, v) in last.iter_mut().zip(s) {
                        *a += v;
                    }
                }
                _ => sums.push(s),
            }
        }
        CalibrationTable {
            albedo: sums.iter().map(|s| s[0] / s[3]).collect(),
            ratio: sums
                .iter()
                .map(|s| if s[2] > 0.0 { s[1] / s[2] } else { 1.0 })
                .collect(),
            pixels: sums.iter().map(|s| s[3] as usize).collect(),
        }
    }

    /// The ratio at albedo `a`: linear between the bins' mean albedos,
    /// flat beyond them (1 without bins).
    pub fn at(&self, a: f64) -> f64 {
        let (x, y) = (&self.albedo, &self.ratio);
        match x.len() {
            0 => 1.0,
            _ if a <= x[0] => y[0],
            n if a >= x[n - 1] => y[n - 1],
            _ => {
                let k = x.partition_point(|&v| v <= a) - 1;
                y[k] + (a - x[k]) / (x[k + 1] - x[k]) * (y[k + 1] - y[k])
            }
        }
    }
}

/// The design with settings `s`, calibrated by brute force when
/// `opts.calibrate` asks for it ([module docs](self)): the design, one
/// brute-force render of it, the ratio of that render to the model's
/// appearance per albedo bin, and the design again for the target divided
/// by that ratio at each texel's first-design albedo. The naive map and
/// its appearance stay the original target's; `predicted` is the
/// calibrated model's, ratio × model.
fn design_calibrated(
    opts: &DesignOptions,
    staging: &Path,
    s: &Settings,
    target: &[Vec<f64>],
    nx: usize,
    ny: usize,
) -> Result<(Design, Option<Calibration>)> {
    let first = design_with(opts, staging, s, target, nx, ny)?;
    let Some(paths) = opts.calibrate else {
        return Ok((first, None));
    };
    let start = Instant::now();
    let grid = Grid::new(opts, nx, ny)?;
    let maps: Vec<&Vec<f64>> = first.albedo.iter().collect();
    let light_radius = grid.light_radius(opts, &maps);
    let geometry = (grid.res, grid.half_width, light_radius, paths);
    let tag = format!("calibrate-{}", s.method.name());
    let (brute, _) = reference_image(opts, staging, &tag, &first.albedo, (nx, ny), geometry)?;
    let tables: Vec<CalibrationTable> = (0..target.len())
        .map(|c| {
            let (a, m) = (
                grid.pixels(&first.albedo[c]),
                grid.pixels(&first.predicted[c]),
            );
            CalibrationTable::fit(
                grid.keep
                    .iter()
                    .map(|&k| (a[k], brute[c][k], m[k]))
                    .collect(),
            )
        })
        .collect();
    let calibrated: Vec<Vec<f64>> = target
        .iter()
        .zip(&first.albedo)
        .zip(&tables)
        .map(|((t, a), table)| {
            t.iter()
                .zip(a)
                .map(|(t, a)| (t / table.at(*a)).clamp(0.0, 1.0))
                .collect()
        })
        .collect();
    let seconds = start.elapsed().as_secs_f64();
    let mut d = design_with(opts, staging, s, &calibrated, nx, ny)?;
    for ((p, a), table) in d.predicted.iter_mut().zip(&d.albedo).zip(&tables) {
        for (p, a) in p.iter_mut().zip(a) {
            *p *= table.at(*a);
        }
    }
    d.naive = first.naive;
    d.predicted_naive = first.predicted_naive;
    d.evaluations += first.evaluations;
    d.solve_seconds += first.solve_seconds;
    d.setup_seconds += first.setup_seconds;
    Ok((
        d,
        Some(Calibration {
            paths,
            channels: tables,
            seconds,
        }),
    ))
}

/// A finished channel in the staging folder.
#[derive(Serialize, serde::Deserialize)]
struct ChannelCheckpoint {
    key: String,
    design: ChannelDesign,
}

/// √(max(0, Σ(m − t)² − Σσ²)/Σt²) over the texels where `keep` (all if None).
fn rel_rmse(m: &[f64], t: &[f64], noise: Option<&[f64]>) -> f64 {
    let se: f64 = m.iter().zip(t).map(|(a, b)| (a - b).powi(2)).sum();
    let var: f64 = noise.map_or(0.0, |n| n.iter().map(|s| s * s).sum());
    let norm: f64 = t.iter().map(|b| b * b).sum();
    ((se - var).max(0.0) / norm).sqrt()
}

/// Mean CIEDE2000 between per-pixel linear reflectances (1 or 3 channels).
fn mean_delta_e(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    use palette::color_difference::Ciede2000;
    use palette::{FromColor, Lab, LinSrgb};
    let lab = |m: &[Vec<f64>], k: usize| -> Lab {
        let c = |i: usize| m[i.min(m.len() - 1)][k].clamp(0.0, 1.0) as f32;
        Lab::from_color(LinSrgb::new(c(0), c(1), c(2)))
    };
    let n = a[0].len();
    (0..n)
        .map(|k| lab(a, k).difference(lab(b, k)) as f64)
        .sum::<f64>()
        / n.max(1) as f64
}

/// Per channel, the mean and the standard error of an image (row-major).
type Planes = (Vec<Vec<f64>>, Vec<Vec<f64>>);

/// Renders `maps` by brute force on the validation grid: per channel, the
/// mean and standard error per pixel (row-major `res × res`).
fn reference_image(
    opts: &DesignOptions,
    staging: &Path,
    tag: &str,
    maps: &[Vec<f64>],
    (nx, ny): (usize, usize),
    (res, half_width, light_radius, paths): (usize, f64, f64, u64),
) -> Result<Planes> {
    let s = &opts.settings;
    let albedo = maps
        .iter()
        .map(|m| TexelMap::new(nx, ny, s.texel, m.clone()))
        .collect::<Result<Vec<_>>>()?;
    let scene = Scene {
        name: format!("design-{tag}"),
        path: opts.target.clone(),
        source: format!("design validation: {tag}"),
        eta: opts.models.basis.eta,
        g: opts.models.meta.g,
        texel: s.texel,
        albedo,
        density: None,
        light: LightKind::Collimated,
        light_radius,
        irradiance: 1.0,
        resolution: res,
        half_width,
        observable: Observable::Exitance,
        methods: Vec::new(),
        samples: 1,
        reference_paths: paths,
        density_sweep: Vec::new(),
    };
    let mut ro = RenderOptions::new(staging.join(tag), opts.models.clone());
    ro.targets = vec![Target::Reference];
    ro.seed = opts.seed;
    ro.analysis = false;
    ro.checkpoint = Some(staging.join(format!("{tag}.reference")));
    ro.run.resume = true;
    ro.run.progress = opts.progress;
    ro.run.checkpoint_every = std::time::Duration::from_secs(30);
    let passes = render_scene(&scene, &ro)?;
    let img = &passes[0].rendered[0].image;
    let n = res * res;
    let split = |v: &[f64]| {
        (0..img.channels)
            .map(|c| v[c * n..(c + 1) * n].to_vec())
            .collect()
    };
    Ok((split(&img.mean), split(&img.stderr)))
}

/// The validation's pixel grid over the texture (`nx × ny` texels):
/// `res²` pixels of `f × f` texels, the image's half-width, and the
/// interior pixels (row-major indices; those further than `margin` MFP
/// inside the texture's edge).
struct Grid {
    nx: usize,
    ny: usize,
    res: usize,
    f: usize,
    half_width: f64,
    texel: f64,
    margin: f64,
    keep: Vec<usize>,
}

impl Grid {
    fn new(opts: &DesignOptions, nx: usize, ny: usize) -> Result<Grid> {
        let texel = opts.settings.texel;
        let side = nx.max(ny);
        let f = side.div_ceil(opts.validate_resolution.max(1)).max(1);
        let res = side.div_ceil(f);
        let half_width = 0.5 * (res * f) as f64 * texel;
        let h = 2.0 * half_width / res as f64;
        let margin = 0.5;
        let (tx, ty) = (0.5 * nx as f64 * texel, 0.5 * ny as f64 * texel);
        let keep: Vec<usize> = (0..res * res)
            .filter(|k| {
                let (i, j) = (k / res, k % res);
                let (x0, y1) = (-half_width + j as f64 * h, half_width - i as f64 * h);
                let (x1, y0) = (x0 + h, y1 - h);
                x0 >= -tx + margin && x1 <= tx - margin && y0 >= -ty + margin && y1 <= ty - margin
            })
            .collect();
        if keep.is_empty() {
            return Err(Error::param(
                "validate-resolution",
                opts.validate_resolution,
                "pixels inside the texture's interior (a texture wider than 1 MFP)",
            ));
        }
        Ok(Grid {
            nx,
            ny,
            res,
            f,
            half_width,
            texel,
            margin,
            keep,
        })
    }

    /// Per pixel, the mean of the texel values `map` (row-major `ny × nx`,
    /// edge texels extended) over its `f × f` texels.
    fn pixels(&self, map: &[f64]) -> Vec<f64> {
        let (res, f, tau, nx, ny) = (self.res, self.f, self.texel, self.nx, self.ny);
        let h = 2.0 * self.half_width / res as f64;
        (0..res * res)
            .map(|k| {
                let (x0, y1) = (
                    -self.half_width + (k % res) as f64 * h,
                    self.half_width - (k / res) as f64 * h,
                );
                let mut sum = 0.0;
                for a in 0..f {
                    for b in 0..f {
                        let x = x0 + (b as f64 + 0.5) * h / f as f64;
                        let y = y1 - (a as f64 + 0.5) * h / f as f64;
                        let jj =
                            ((x / tau + 0.5 * nx as f64).floor().max(0.0) as usize).min(nx - 1);
                        let ii =
                            ((0.5 * ny as f64 - y / tau).floor().max(0.0) as usize).min(ny - 1);
                        sum += map[ii * nx + jj];
                    }
                }
                sum / (f * f) as f64
            })
            .collect()
    }

    /// The light's radius (MFP) for rendering `maps` on this grid: the
    /// settings' disk, or under uniform light a disk reaching 4 diffusion
    /// lengths 1/σ_tr beyond the image for the largest albedo on the maps'
    /// edges (σ_tr = √(3σ_a σ_t′), unit σ_t; beyond the texture the medium
    /// is its edge texels extended): light from further out contributes
    /// < 1 % of the reflectance there.
    fn light_radius(&self, opts: &DesignOptions, maps: &[&Vec<f64>]) -> f64 {
        let (nx, ny) = (self.nx, self.ny);
        let alpha_max = maps
            .iter()
            .flat_map(|m| {
                (0..nx * ny)
                    .filter(|k| {
                        let (i, j) = (k / nx, k % nx);
                        i == 0 || j == 0 || i + 1 == ny || j + 1 == nx
                    })
                    .map(|k| m[k])
            })
            .fold(0.0f64, f64::max);
        let g = opts.models.meta.g;
        let sigma_tr = (3.0 * (1.0 - alpha_max) * (1.0 - alpha_max * g))
            .sqrt()
            .max(1e-3);
        let reach = (4.0 / sigma_tr).min(40.0);
        match opts.settings.illumination {
            Illumination::Uniform => self.half_width * std::f64::consts::SQRT_2 + reach,
            Illumination::Disk(r) => r,
        }
    }
}

/// The brute-force validation ([module docs](self)).
fn validate(
    opts: &DesignOptions,
    staging: &Path,
    target: &[Vec<f64>],
    nx: usize,
    ny: usize,
    designed: &Design,
    paths: u64,
) -> Result<Validation> {
    let start = Instant::now();
    let s = &opts.settings;
    let grid = Grid::new(opts, nx, ny)?;
    let maps: Vec<&Vec<f64>> = designed.albedo.iter().chain(&designed.naive).collect();
    let light_radius = grid.light_radius(opts, &maps);
    let (res, half_width, keep, margin) = (grid.res, grid.half_width, &grid.keep, grid.margin);
    let target_full: Vec<Vec<f64>> = target.iter().map(|t| grid.pixels(t)).collect();
    let target_px: Vec<Vec<f64>> = target_full
        .iter()
        .map(|c| keep.iter().map(|&k| c[k]).collect())
        .collect();
    let geometry = (res, half_width, light_radius, paths);
    let errors = |mean: &[Vec<f64>], err: &[Vec<f64>]| -> Errors {
        let pick = |v: &[Vec<f64>]| -> Vec<Vec<f64>> {
            v.iter()
                .map(|c| keep.iter().map(|&k| c[k]).collect())
                .collect()
        };
        let (m, e) = (pick(mean), pick(err));
        let flat = |v: &[Vec<f64>]| v.iter().flatten().copied().collect::<Vec<f64>>();
        Errors {
            rel_rmse: rel_rmse(&flat(&m), &flat(&target_px), Some(&flat(&e))),
            delta_e00: mean_delta_e(&m, &target_px),
        }
    };
    let (naive_m, naive_e) =
        reference_image(opts, staging, "naive", &designed.naive, (nx, ny), geometry)?;
    let naive = errors(&naive_m, &naive_e);
    let noise = {
        let flat_m: Vec<f64> = keep.iter().map(|&k| naive_m[0][k]).collect();
        let flat_e: Vec<f64> = keep.iter().map(|&k| naive_e[0][k]).collect();
        let mean = flat_m.iter().sum::<f64>() / flat_m.len() as f64;
        (flat_e.iter().map(|e| e * e).sum::<f64>() / flat_e.len() as f64).sqrt() / mean
    };
    let mut rows = Vec::new();
    let mut designed_image = Vec::new();
    for method in [Method::Learned, Method::Factorized, Method::Point] {
        let (maps, design_s) = if method == s.method {
            (designed.albedo.clone(), designed.solve_seconds)
        } else {
            let mut other = s.clone();
            other.method = method;
            let (d, _) = design_calibrated(opts, staging, &other, target, nx, ny)?;
            (d.albedo, d.solve_seconds)
        };
        let (m, e) = reference_image(opts, staging, method.name(), &maps, (nx, ny), geometry)?;
        if method == s.method {
            designed_image = m.clone();
        }
        rows.push(ValidationRow {
            method: method.name().into(),
            designed: errors(&m, &e),
            design_s,
        });
    }
    let designed_error = rows[0].designed.rel_rmse;
    let improvement = (designed_error > 0.0).then(|| naive.rel_rmse / designed_error);
    Ok(Validation {
        paths,
        resolution: res,
        light_radius,
        interior_margin: margin,
        reference_noise: noise,
        naive,
        rows,
        improvement,
        seconds: start.elapsed().as_secs_f64(),
        images: ValidationImages {
            target: target_full,
            naive: naive_m,
            designed: designed_image,
        },
    })
}

/// A `ny × nx` PNG of 1 or 3 channels (linear values, sRGB-encoded).
fn write_map_png(path: &Path, maps: &[Vec<f64>], nx: usize, ny: usize) -> Result<()> {
    let c = maps.len();
    let data: Vec<u8> = (0..nx * ny)
        .flat_map(|k| maps.iter().map(move |m| to_u8(srgb(m[k]))))
        .collect();
    write_png_bytes_wh(path, nx, ny, c == 3, &data)
}

/// A diverging PNG (`w × h`) of the channel-mean difference a − t over
/// ±`range`.
fn write_error_png(
    path: &Path,
    a: &[Vec<f64>],
    t: &[Vec<f64>],
    (w, h): (usize, usize),
    range: f64,
) -> Result<()> {
    let data: Vec<u8> = (0..w * h)
        .flat_map(|k| {
            let e = a.iter().zip(t).map(|(x, y)| x[k] - y[k]).sum::<f64>() / a.len() as f64;
            diverging((e / range).clamp(-1.0, 1.0))
        })
        .collect();
    write_png_bytes_wh(path, w, h, true, &data)
}

/// (ny, nx, c) or (ny, nx) array of per-channel maps.
fn array(maps: &[Vec<f64>], nx: usize, ny: usize) -> ndarray::ArrayD<f64> {
    let c = maps.len();
    if c == 1 {
        ndarray::ArrayD::from_shape_vec(vec![ny, nx], maps[0].clone()).expect("shape")
    } else {
        ndarray::ArrayD::from_shape_fn(vec![ny, nx, c], |ix| maps[ix[2]][ix[0] * nx + ix[1]])
    }
}

/// Writes every output into the staging folder, then moves them into `out`.
fn write_outputs(
    opts: &DesignOptions,
    staging: &Path,
    doc: &DesignDoc,
    d: &Design,
    target: &[Vec<f64>],
    nx: usize,
    ny: usize,
) -> Result<()> {
    let files = staging.join("files");
    std::fs::create_dir_all(&files).map_err(|e| Error::io(&files, e))?;
    write_npy_atomic(&files.join("albedo.npy"), &array(&d.albedo, nx, ny))?;
    write_npy_atomic(&files.join("naive.npy"), &array(&d.naive, nx, ny))?;
    write_npy_atomic(&files.join("predicted.npy"), &array(&d.predicted, nx, ny))?;
    write_map_png(&files.join("albedo.png"), &d.albedo, nx, ny)?;
    write_json_atomic(&files.join("design.json"), doc)?;
    // The report's images.
    let img = staging.join("img");
    std::fs::create_dir_all(&img).map_err(|e| Error::io(&img, e))?;
    let p = |n: &str| img.join(n);
    write_map_png(&p("target.png"), target, nx, ny)?;
    write_map_png(&p("naive.png"), &d.naive, nx, ny)?;
    write_map_png(&p("albedo.png"), &d.albedo, nx, ny)?;
    write_map_png(&p("predicted_naive.png"), &d.predicted_naive, nx, ny)?;
    write_map_png(&p("predicted.png"), &d.predicted, nx, ny)?;
    let range = 0.1;
    write_error_png(
        &p("error_naive.png"),
        &d.predicted_naive,
        target,
        (nx, ny),
        range,
    )?;
    write_error_png(
        &p("error_designed.png"),
        &d.predicted,
        target,
        (nx, ny),
        range,
    )?;
    let series: Vec<Series> = (0..target.len())
        .map(|c| {
            let pts = d
                .history
                .iter()
                .filter(|h| h.channel == c)
                .enumerate()
                .map(|(k, h)| (k as f64, h.objective))
                .collect();
            Series::line(format!("channel {c}"), pts, c)
        })
        .collect();
    chart(
        &p("convergence.png"),
        &Axes {
            title: "objective: fixed-point steps, then L-BFGS-B iterations".into(),
            x_label: "step".into(),
            y_label: "F(α)".into(),
            log_x: false,
            log_y: true,
        },
        &series,
    )?;
    let cell = |caption: &str, name: &str| Some((caption.to_string(), p(name)));
    let mut blocks = vec![
        Block::Para(
            format!(
                "Target `{}` ({ny} × {nx}, {} channel(s)), texel {} MFP, albedo range [{}, {}], \
             {} illumination, forward model `{}`. {} of at most {} relaxed fixed-point steps \
             over all channels (a step that raises F is undone and halves the relaxation; \
             each channel stops when it falls below {} or a step gains less than {} %), then \
             {} L-BFGS-B iterations per channel{}, in {:.1} s ({} model evaluations), \
             set-up {:.1} s.",
                opts.target.display(),
                target.len(),
                doc.texel,
                doc.albedo_range[0],
                doc.albedo_range[1],
                doc.illumination,
                doc.method,
                doc.history
                    .iter()
                    .filter(|h| h.stage == crate::design::Stage::FixedPoint)
                    .count(),
                doc.warm_start * target.len(),
                crate::design::MIN_RELAXATION,
                100.0 * crate::design::MIN_GAIN,
                doc.iterations,
                if doc.method == Method::Learned.name() {
                    " from the kernel shapes re-anchored at the warm start's map (F jumps there)"
                } else {
                    ""
                },
                doc.solve_s,
                doc.evaluations,
                doc.setup_s,
            ) + if doc.calibration.is_some() {
                " Calibrated (below): the design ran twice, for the target and for the \
             corrected one; the steps and the convergence plot are the second run's, the time \
             and the evaluations both runs'."
            } else {
                ""
            },
        ),
        Block::Heading(2, "Maps".into()),
        Block::Grid {
            rows: vec![vec![
                cell("target (appearance)", "target.png"),
                cell("naive albedo", "naive.png"),
                cell("designed albedo", "albedo.png"),
            ]],
            width: 256,
        },
        Block::Heading(2, "Appearance under the model".into()),
        Block::Grid {
            rows: vec![vec![
                cell("naive", "predicted_naive.png"),
                cell("designed", "predicted.png"),
                cell(&format!("naive − target (±{range})"), "error_naive.png"),
                cell(
                    &format!("designed − target (±{range})"),
                    "error_designed.png",
                ),
            ]],
            width: 256,
        },
        Block::table(
            &["map", "model's relative RMSE against the target"],
            vec![
                vec![
                    "naive".into(),
                    format!("{:.2} %", 100.0 * doc.model_naive_rel_rmse),
                ],
                vec![
                    "designed".into(),
                    format!("{:.2} %", 100.0 * doc.model_designed_rel_rmse),
                ],
            ],
        ),
        Block::Figure {
            caption: "convergence".into(),
            path: p("convergence.png"),
        },
    ];
    let mut published = vec![
        "albedo.npy",
        "albedo.png",
        "naive.npy",
        "predicted.npy",
        "design.json",
        "report.html",
    ];
    if let Some(c) = &doc.calibration {
        blocks.push(Block::Heading(2, "Calibration by brute force".into()));
        blocks.push(Block::Para(format!(
            "One reference render of the first design ({} paths, the validation's light and \
             pixels) against the model's appearance of it, per bin of the designed albedo \
             (equal pixel counts, interior pixels); the design was run again for the target \
             divided by the ratio at each texel's first-design albedo. The model's appearance \
             above is the calibrated one (ratio × model). {:.0} s.",
            c.paths, c.seconds
        )));
        let rows = c
            .channels
            .iter()
            .enumerate()
            .flat_map(|(k, t)| {
                (0..t.albedo.len()).map(move |b| {
                    vec![
                        k.to_string(),
                        format!("{:.3}", t.albedo[b]),
                        t.pixels[b].to_string(),
                        format!("{:.3}", t.ratio[b]),
                    ]
                })
            })
            .collect();
        blocks.push(Block::table(
            &[
                "channel",
                "mean designed albedo",
                "pixels",
                "brute force ÷ model",
            ],
            rows,
        ));
    }
    if let Some(v) = &doc.validation {
        let r = v.resolution;
        let im = &v.images;
        write_npy_atomic(&files.join("reference_naive.npy"), &array(&im.naive, r, r))?;
        write_npy_atomic(
            &files.join("reference_designed.npy"),
            &array(&im.designed, r, r),
        )?;
        published.extend(["reference_naive.npy", "reference_designed.npy"]);
        write_map_png(&p("v_target.png"), &im.target, r, r)?;
        write_map_png(&p("v_naive.png"), &im.naive, r, r)?;
        write_map_png(&p("v_designed.png"), &im.designed, r, r)?;
        write_error_png(
            &p("v_error_naive.png"),
            &im.naive,
            &im.target,
            (r, r),
            range,
        )?;
        write_error_png(
            &p("v_error_designed.png"),
            &im.designed,
            &im.target,
            (r, r),
            range,
        )?;
        blocks.push(Block::Heading(2, "Brute-force validation".into()));
        blocks.push(Block::Grid {
            rows: vec![vec![
                cell("target (pixel means)", "v_target.png"),
                cell("naive, brute force", "v_naive.png"),
                cell("designed, brute force", "v_designed.png"),
                cell(&format!("naive − target (±{range})"), "v_error_naive.png"),
                cell(
                    &format!("designed − target (±{range})"),
                    "v_error_designed.png",
                ),
            ]],
            // Five tiles on one row within the page's width.
            width: 224,
        });
        blocks.push(Block::Para(format!(
            "Reference walk, {} paths per map, {}² pixels, collimated disk light of radius \
             {:.1} MFP; interior: pixels at least {} MFP inside the texture; reference noise \
             {:.1} % per pixel (RMS, subtracted from the relative RMSE, not from ΔE₀₀). \
             {:.0} s.",
            v.paths,
            v.resolution,
            v.light_radius,
            v.interior_margin,
            100.0 * v.reference_noise,
            v.seconds
        )));
        let mut rows = vec![vec![
            "naive".into(),
            format!("{:.2} %", 100.0 * v.naive.rel_rmse),
            format!("{:.2}", v.naive.delta_e00),
            "—".into(),
        ]];
        for r in &v.rows {
            rows.push(vec![
                format!("designed with `{}`", r.method),
                format!("{:.2} %", 100.0 * r.designed.rel_rmse),
                format!("{:.2}", r.designed.delta_e00),
                format!("{:.1}", r.design_s),
            ]);
        }
        blocks.push(Block::table(
            &["map", "relative RMSE", "mean ΔE₀₀", "design time [s]"],
            rows,
        ));
    }
    let html = to_html("svkernel design", &blocks)?;
    write_atomic(&files.join("report.html"), html.as_bytes())?;
    // Publish: every file into `out`, then drop the staging folder.
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::io(&opts.out, e))?;
    for name in published {
        let to = opts.out.join(name);
        std::fs::rename(files.join(name), &to).map_err(|e| Error::io(&to, e))?;
    }
    std::fs::remove_dir_all(staging).map_err(|e| Error::io(staging, e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_calibration_table_bins_by_albedo_and_interpolates() {
        // Pixels at albedo 0.5 (brute force 0.9 × model) and 0.9 (1.1 ×),
        // half each; the bins pool where their albedos coincide.
        let pixels: Vec<(f64, f64, f64)> = (0..80)
            .map(|k| {
                let (a, r) = if k % 2 == 0 { (0.5, 0.9) } else { (0.9, 1.1) };
                let m = 0.1 + 0.001 * k as f64;
                (a, r * m, m)
            })
            .collect();
        let t = CalibrationTable::fit(pixels);
        assert_eq!(t.albedo.len(), 2, "{t:?}");
        assert_eq!(t.pixels, vec![40, 40]);
        assert!((t.ratio[0] - 0.9).abs() < 1e-12 && (t.ratio[1] - 1.1).abs() < 1e-12);
        assert!((t.at(0.7) - 1.0).abs() < 1e-12, "halfway: {}", t.at(0.7));
        assert_eq!(t.at(0.1), t.ratio[0]);
        assert_eq!(t.at(0.99), t.ratio[1]);
        // Distinct albedos: CALIBRATION_BINS bins of equal count, in order.
        let spread: Vec<(f64, f64, f64)> = (0..100)
            .map(|k| (0.2 + 0.007 * k as f64, 1.0, 1.0))
            .collect();
        let t = CalibrationTable::fit(spread);
        assert_eq!(t.albedo.len(), CALIBRATION_BINS);
        assert!(t.albedo.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(t.pixels.iter().sum::<usize>(), 100);
        assert_eq!(CalibrationTable::fit(Vec::new()).at(0.5), 1.0);
    }
}
