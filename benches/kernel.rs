//! Evaluation time of the learned kernel meta-model (< 100 ns for K = 3 is the
//! aim) against the manual kernel's construction, on the shipped model.
//! `cargo bench --bench kernel`.

use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use std::path::Path;
use svkernel::forward::kernel::VertexClass;
use svkernel::metamodel::kernel::manual_kernel;
use svkernel::metamodel::meta::MetaModelFile;

fn kernel(c: &mut Criterion) {
    let file = MetaModelFile::load(Path::new("data/profiles/metamodel.json"))
        .expect("shipped data/profiles/metamodel.json");
    let model = file.all.clone();
    // A spread of queries so that branch prediction and caches see variety.
    let queries: Vec<(f64, f64, f64)> = (0..64)
        .map(|i| {
            let f = i as f64 / 63.0;
            (
                0.1 + 9.0 * f * f,
                0.3 + 0.69 * ((i * 37) % 64) as f64 / 63.0,
                1.0 + (i % 3) as f64,
            )
        })
        .collect();
    let mut g = c.benchmark_group("kernel");
    g.bench_function("meta_model_all_K3", |b| {
        let mut i = 0;
        b.iter(|| {
            let (d, a, r) = queries[i & 63];
            i += 1;
            black_box(model.eval(black_box(d), black_box(a), black_box(r)))
        })
    });
    g.bench_function("meta_model_all_K3_into", |b| {
        let mut i = 0;
        let mut out = model.eval(1.0, 0.5, 1.0).gmm;
        b.iter(|| {
            let (d, a, r) = queries[i & 63];
            i += 1;
            black_box(model.eval_into(black_box(d), black_box(a), black_box(r), &mut out));
            black_box(&out);
        })
    });
    g.bench_function("meta_file_last_K3", |b| {
        let mut i = 0;
        b.iter(|| {
            let (d, a, r) = queries[i & 63];
            i += 1;
            black_box(file.eval(VertexClass::Last, black_box(d), black_box(a), black_box(r)))
        })
    });
    g.bench_function("manual_kernel", |b| {
        let mut i = 0;
        b.iter(|| {
            let (d, _, _) = queries[i & 63];
            i += 1;
            black_box(manual_kernel(black_box(d)))
        })
    });
    g.finish();
}

criterion_group!(benches, kernel);
criterion_main!(benches);
