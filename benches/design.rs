//! Cost of one evaluation of the design's appearance model (module
//! `design::appearance`) on a 256² map of texels of 0.05 MFP, the default
//! quadrature and the renderer's two-scale albedo space: the appearance
//! alone (a warm-start step), and the appearance with its partials followed
//! by the exact gradient (an L-BFGS-B evaluation), per forward model.
//! `cargo bench --bench design`.

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
    (0..N * N)
        .map(|k| {
            let (i, j) = ((k / N) as f64, (k % N) as f64);
            let r = ((i - 128.0).powi(2) + (j - 128.0).powi(2)).sqrt() * 0.05;
            0.785 + 0.15 * (std::f64::consts::TAU * r).sin() + 0.035 * (j / N as f64 - 0.5)
        })
        .collect()
}

fn design(c: &mut Criterion) {
    let basis = BasisModel::load(Path::new("data/profiles/basis.json")).expect("shipped basis");
    let meta =
        MetaModelFile::load(Path::new("data/profiles/metamodel.json")).expect("shipped meta-model");
    let alpha = map();
    let weights: Vec<f64> = alpha.iter().map(|a| a - 0.8).collect();
    let mut g = c.benchmark_group("design_256");
    g.sample_size(10);
    for method in [Method::Learned, Method::Factorized, Method::Point] {
        let app = Appearance::new(
            method,
            &basis,
            Some(&meta),
            N,
            N,
            0.05,
            Illumination::Uniform,
            [0.6, 0.97],
            &Quadrature::default(),
        )
        .expect("appearance");
        let anchor = app.anchor(&alpha);
        g.bench_function(format!("{}/appearance", method.name()), |b| {
            b.iter(|| black_box(app.appearance(black_box(&alpha), &anchor)))
        });
        g.bench_function(format!("{}/gradient", method.name()), |b| {
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
