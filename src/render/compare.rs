//! What accuracy costs in time (issue 7 §2, first part): for one scene, the
//! error of every method and of the brute-force reference as their sample
//! budgets grow, against a high-budget reference ("truth") rendered with an
//! independent seed.
//!
//! # Error
//! e = √(max(0, Σ(m − t)² − Σσ_t²)/Σt²) over all pixels and channels of the
//! first pass: the relative RMSE of image m against the truth t with the
//! truth's own variance σ_t² subtracted (so a noisy truth does not inflate
//! it), but *not* m's: the method's noise is part of what its time buys.
//! A model's curve falls like 1/√time until it meets its bias (the floor);
//! the reference's keeps falling, and where it crosses a model's curve is
//! how long brute force needs to match that model.

use super::estimator::Image;
use super::job::{RenderOptions, Target, render_scene};
use super::scene::Scene;
use super::svbssrdf::Method;
use crate::error::{Error, Result};
use serde::Serialize;
use std::path::Path;

/// One point of a curve: the budget (samples per pixel, or reference
/// paths), the wall time it took and the error.
#[derive(Clone, Debug, Serialize)]
pub struct CurvePoint {
    pub budget: u64,
    pub wall_s: f64,
    pub rel_rmse: f64,
}

/// Error against time of one method (or the reference).
#[derive(Clone, Debug, Serialize)]
pub struct Curve {
    pub method: String,
    pub points: Vec<CurvePoint>,
}

/// The truth-noise-subtracted relative RMSE of `m` against `t` (module docs).
pub fn rel_error(m: &Image, t: &Image) -> f64 {
    super::job::rel_rmse(m, t, false)
}

/// Renders the truth (`truth_paths`, seed `opts.seed + 1_000_003`), the
/// reference at each of `paths` and every model method of the scene at each
/// of `spps` (seed `opts.seed`), and returns the curves (first pass only)
/// and the truth's wall time.
pub fn error_vs_time(
    scene: &Scene,
    opts: &RenderOptions,
    truth_paths: u64,
    spps: &[u32],
    paths: &[u64],
) -> Result<(Vec<Curve>, f64)> {
    if spps.contains(&0) || paths.contains(&0) || truth_paths == 0 {
        return Err(Error::param(
            "--spp-list/--paths-list/--truth-paths",
            "0",
            "budgets >= 1",
        ));
    }
    let first = |o: &RenderOptions| -> Result<Vec<(Target, Image, f64)>> {
        let first_pass = render_scene(scene, o)?.swap_remove(0);
        Ok(first_pass
            .rendered
            .into_iter()
            .map(|r| (r.target, r.image, r.wall_s))
            .collect())
    };
    let mut o = opts.clone();
    o.targets = vec![Target::Reference];
    o.reference_paths = Some(truth_paths);
    o.seed = opts.seed.wrapping_add(1_000_003);
    o.out = opts.out.join("truth");
    let truth = first(&o)?;
    let (_, truth_img, truth_s) = &truth[0];

    let mut curves: Vec<Curve> = Vec::new();
    let mut push = |name: &str, p: CurvePoint| match curves.iter_mut().find(|c| c.method == name) {
        Some(c) => c.points.push(p),
        None => curves.push(Curve {
            method: name.to_string(),
            points: vec![p],
        }),
    };
    for &n in paths {
        let mut o = opts.clone();
        o.targets = vec![Target::Reference];
        o.reference_paths = Some(n);
        o.out = opts.out.join(format!("reference_{n}"));
        for (t, img, s) in first(&o)? {
            push(
                t.name(),
                CurvePoint {
                    budget: n,
                    wall_s: s,
                    rel_rmse: rel_error(&img, truth_img),
                },
            );
        }
    }
    let methods: Vec<Target> = scene
        .methods
        .iter()
        .map(|m| Method::parse(m).map(Target::Model))
        .collect::<Result<_>>()?;
    for &spp in spps {
        let mut o = opts.clone();
        o.targets = methods.clone();
        o.spp = Some(spp);
        for (t, img, s) in first(&o)? {
            push(
                t.name(),
                CurvePoint {
                    budget: spp as u64,
                    wall_s: s,
                    rel_rmse: rel_error(&img, truth_img),
                },
            );
        }
    }
    Ok((curves, *truth_s))
}

/// The log-log error-vs-time plot (reference dashed, models in the palette)
/// as PNG at `path` and as SVG beside it (same stem, `.svg`).
pub fn plot_curves(path: &Path, scene: &str, curves: &[Curve]) -> Result<()> {
    use crate::plot::{Axes, Series, chart, chart_svg};
    let series: Vec<Series> = curves
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let pts = c.points.iter().map(|p| (p.wall_s, p.rel_rmse)).collect();
            if c.method == "reference" {
                Series::dashed(c.method.clone(), pts, k)
            } else {
                Series::line(c.method.clone(), pts, k)
            }
        })
        .collect();
    let axes = Axes {
        title: format!("{scene}: error vs time (reference dashed)"),
        x_label: "wall time [s]".into(),
        y_label: "relative RMSE vs truth".into(),
        log_x: true,
        log_y: true,
    };
    chart(path, &axes, &series)?;
    chart_svg(&path.with_extension("svg"), &axes, &series)
}
