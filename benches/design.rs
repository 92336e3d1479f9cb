//! Cost of one evaluation of the design's appearance model (module
//! `design::appearance`) on a 256² map of texels of 0.05 MFP, the default
//! quadrature and the renderer's two-scale albedo space: the appearance
//! alone (a warm-start step), and the appearance with its partials followed
//! by the exact gradient (an L-BFGS-B evaluation), per forward model; and
//! `learned` on a bright map (albedo 0.9 … 0.995), where the split's bright
//! regime is read too. `cargo bench --bench design`.

use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use std::path::Path;
use svkernel::design::appearance::{Appearance, Illumination, Quadrature};
use svkernel::metamodel::basis::BasisModel;
use svkernel::metamodel::meta::MetaModelFile;
use svkernel::render::svbssrdf::Method;

/// Texels per side.
const N: usize = 256;

/// Concentric rings of albedo 0.6 … 0.97 (period 1 MFP) over a smooth
/// gradient: the contrast a design works on.
fn map() -> Vec<f64> {
    rings(0.785, 0.15, 0.035)
}

/// The same rings at albedo 0.9 … 0.995: the endpoints' albedo crosses the
/// regimes' ramp (0.95 → 0.98).
fn bright_map() -> Vec<f64> {
    rings(0.9475, 0.04, 0.015)
}

/// Rings of amplitude `amp` about `mean` (period 1 MFP) over a gradient of
/// `tilt` across the map.
fn rings(mean: f64, amp: f64, tilt: f64) -> Vec<f64> {
    (0..N * N)
        .map(|k| {
            let (i, j) = ((k / N) as f64, (k % N) as f64);
            let r = ((i - 128.0).powi(2) + (j - 128.0).powi(2)).sqrt() * 0.05;
            mean + amp * (std::f64::consts::TAU * r).sin() + tilt * (j / N as f64 - 0.5)
        })
        .collect()
}

fn design(c: &mut Criterion) {
    let basis = BasisModel::load(Path::new("data/profiles/basis.json")).expect("shipped basis");
    let meta =
        MetaModelFile::load(Path::new("data/profiles/metamodel.json")).expect("shipped meta-model");
    let mut g = c.benchmark_group("design_256");
    g.sample_size(10);
    for (name, method, alpha, range) in [
        ("learned", Method::Learned, map(), [0.6, 0.97]),
        ("factorized", Method::Factorized, map(), [0.6, 0.97]),
        ("point", Method::Point, map(), [0.6, 0.97]),
        (
            "learned-bright",
            Method::Learned,
            bright_map(),
            [0.9, 0.995],
        ),
    ] {
        let weights: Vec<f64> = alpha.iter().map(|a| a - 0.8).collect();
        let app = Appearance::new(
            method,
            &basis,
            Some(&meta),
            N,
            N,
            0.05,
            Illumination::Uniform,
            range,
            &Quadrature::default(),
        )
        .expect("appearance");
        let anchor = app.anchor(&alpha);
        g.bench_function(format!("{name}/appearance"), |b| {
            b.iter(|| black_box(app.appearance(black_box(&alpha), &anchor)))
        });
        g.bench_function(format!("{name}/gradient"), |b| {
            b.iter(|| {
                let lin = app.linearize(black_box(&alpha), &anchor);
                let grad = app.gradient(&lin, &anchor, &weights);
                app.release(lin);
                black_box(grad)
            })
        });
    }
    g.finish();
}

criterion_group!(benches, design);
criterion_main!(benches);
