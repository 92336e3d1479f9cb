//! Cost of one SV-BSSRDF evaluation S(x_i, x_e) per method and pair distance
//! (aim: `learned` < 200 ns and flat in d; `line` and `ellipse`
//! grow with d), on the `stripes` texture (τ = 0.05 MFP) with a density
//! ramp, so that every aggregate is density-scaled. Pairs at distance d in
//! 64 directions from spread-out entry points. The `pyramid` group times the
//! building block: one paired Gaussian query (G ∗ ρ, G ∗ ρα) per regime of σ.
//! `cargo bench --bench render`; `SVKERNEL_BENCH_MODELS=a.json,b.json cargo
//! bench --bench render -- svbssrdf_models` also times `learned` under those
//! meta-models (e.g. the K = 1…5 refits of `tools/kernel_complexity.sh`).

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;
use svkernel::forward::maps::TexelMap;
use svkernel::metamodel::basis::BasisModel;
use svkernel::metamodel::meta::MetaModelFile;
use svkernel::render::svbssrdf::{BasisTable, Density, Method, Scratch, SvBssrdf, Variant};

/// Texel size of every bench texture (MFP).
const TAU: f64 = 0.05;

/// n × n texels of [`TAU`]: stripes of albedo 0.3 / 0.95 across x, 10
/// texels (0.5 MFP) wide, the first one 0.3.
fn stripes(n: usize) -> TexelMap {
    let values = (0..n * n)
        .map(|k| {
            if ((k % n) / 10).is_multiple_of(2) {
                0.3
            } else {
                0.95
            }
        })
        .collect();
    TexelMap::new(n, n, TAU, values).expect("map")
}

/// n × n texels of [`TAU`]: density ramp 0.5 … 4 across x.
fn density_ramp(n: usize) -> TexelMap {
    let values = (0..n * n)
        .map(|k| 0.5 + 3.5 * (k % n) as f64 / (n - 1) as f64)
        .collect();
    TexelMap::new(n, n, TAU, values).expect("map")
}

/// Pairs (x_i, x_e) at distance `d` in 64 directions (golden angle) from
/// spread-out entry points.
fn pairs_at(d: f64) -> Vec<([f64; 2], [f64; 2])> {
    (0..64)
        .map(|k| {
            let phi = k as f64 * 2.399_963; // golden angle
            let xi = [2.0 * (k as f64 * 0.37).sin(), 2.0 * (k as f64 * 0.61).cos()];
            (xi, [xi[0] + d * phi.cos(), xi[1] + d * phi.sin()])
        })
        .collect()
}

/// Times `sv.eval` on channel 0 at the bench distances, as `name/d`.
fn bench_distances(
    g: &mut criterion::BenchmarkGroup<criterion::measurement::WallTime>,
    name: &str,
    sv: &SvBssrdf,
) {
    for d in [0.1, 1.0, 10.0, 50.0] {
        g.bench_with_input(BenchmarkId::new(name, d), &pairs_at(d), |b, pairs| {
            let mut scratch = Scratch::default();
            let mut i = 0;
            b.iter(|| {
                let (xi, xe) = pairs[i & 63];
                i += 1;
                black_box(sv.eval(0, black_box(xi), black_box(xe), &mut scratch))
            })
        });
    }
}

/// Meta-models besides the shipped one for the `svbssrdf_models` group:
/// comma-separated paths in `SVKERNEL_BENCH_MODELS` (e.g. the refits of
/// `tools/kernel_complexity.sh` at K = 1…5), none when unset.
fn extra_models() -> Vec<String> {
    std::env::var("SVKERNEL_BENCH_MODELS")
        .map(|v| {
            v.split(',')
                .filter(|s| !s.is_empty())
                .map(String::from)
                .collect()
        })
        .unwrap_or_default()
}

fn svbssrdf(c: &mut Criterion) {
    let basis = Arc::new(BasisTable::new(
        &BasisModel::load(Path::new("data/profiles/basis.json")).expect("shipped basis"),
    ));
    let shipped = "data/profiles/metamodel.json";
    let meta = Arc::new(MetaModelFile::load(Path::new(shipped)).expect("shipped meta-model"));
    // 320 × 320 texels of 0.05 MFP: stripes 0.3 / 0.95 of width 0.5 MFP,
    // density ramp 0.5 … 4 across x.
    let (albedo, density) = (stripes(320), density_ramp(320));
    let mut g = c.benchmark_group("svbssrdf");
    // Every method with the default variant, and `learned` with point
    // albedos for the local terms (one kernel instead of two).
    let point_albedos = Variant {
        vertex_kernels: false,
        ..Variant::default()
    };
    let configs = Method::ALL
        .into_iter()
        .map(|m| (m, Variant::default(), m.name().to_string()))
        .chain([(
            Method::Learned,
            point_albedos,
            "learned_point_albedos".to_string(),
        )]);
    for (method, variant, name) in configs {
        let sv = SvBssrdf::new(
            method,
            variant,
            basis.clone(),
            Some(meta.clone()),
            vec![albedo.clone()],
            Density::Map(density.clone()),
        )
        .expect("prepared");
        bench_distances(&mut g, &name, &sv);
    }
    g.finish();
    // `learned` under other meta-models (what the kernel's size costs per
    // evaluation), with the shipped one again in the same group.
    let extra = extra_models();
    if extra.is_empty() {
        return;
    }
    let mut g = c.benchmark_group("svbssrdf_models");
    for path in std::iter::once(shipped.to_string()).chain(extra) {
        let model = MetaModelFile::load(Path::new(&path)).expect("meta-model");
        let k = model.all.k;
        let sv = SvBssrdf::new(
            Method::Learned,
            Variant::default(),
            basis.clone(),
            Some(Arc::new(model)),
            vec![albedo.clone()],
            Density::Map(density.clone()),
        )
        .expect("prepared");
        let stem = Path::new(&path)
            .file_stem()
            .map_or(path.clone(), |s| s.to_string_lossy().into());
        bench_distances(&mut g, &format!("learned_K{k}_{stem}"), &sv);
    }
    g.finish();
}

/// One paired pyramid query (`integrate_pair`, as the kernel methods make
/// per component) on the density ramp and ρ·stripes of the `svbssrdf` bench
/// (320² texels, τ = 0.05 MFP), at 64 spread-out centres, per regime of σ:
/// the exact window below a texel (σ = 0.02τ, 0.5τ, 0.9τ), pyramid levels
/// (σ = 3τ, 30τ). Also on a 32² map of the same texel size, where every
/// pyramid node stays in the caches: what is left is arithmetic.
fn pyramid(c: &mut Criterion) {
    use svkernel::render::pyramid::GaussianPyramid;
    let maps = |n: usize| {
        let rho = density_ramp(n);
        let rho_alpha = TexelMap {
            values: rho
                .values
                .iter()
                .zip(&stripes(n).values)
                .map(|(r, a)| r * a)
                .collect(),
            ..rho.clone()
        };
        let build = |m: &TexelMap| GaussianPyramid::new(m).expect("pyramid");
        (build(&rho), build(&rho_alpha))
    };
    let mut g = c.benchmark_group("pyramid");
    for n in [320usize, 32] {
        let (rho, rho_alpha) = maps(n);
        let half = 0.45 * n as f64 * TAU;
        let centres: Vec<[f64; 2]> = (0..64)
            .map(|k| {
                let k = k as f64;
                [half * (k * 0.37).sin(), half * (k * 0.61).cos()]
            })
            .collect();
        for sigma_texels in [0.02, 0.5, 0.9, 3.0, 30.0] {
            let sigma = sigma_texels * TAU;
            let id = BenchmarkId::new(format!("pair_{n}x{n}"), format!("{sigma_texels}tau"));
            g.bench_with_input(id, &centres, |b, centres| {
                let mut i = 0;
                b.iter(|| {
                    let mu = centres[i & 63];
                    i += 1;
                    black_box(rho.integrate_pair(&rho_alpha, black_box(mu), black_box(sigma)))
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, svbssrdf, pyramid, walks);
criterion_main!(benches);

/// Scattering events per second of the reference walk (texel maps, image
/// tally) against the homogeneous scalar walk (`simulate_scalar`, at the
/// reference's albedos) under the same collimated disk light, all on one
/// thread: a constant albedo 0.9, where only the machinery differs; the
/// `stripes` albedo; a density ramp (τ = 0.05 MFP) on the majorant grid the
/// reference picks, on its extremes (regular and delta tracking) and on
/// cells of 2 … 256 texels; and albedo stripes and ramp together.
fn walks(c: &mut Criterion) {
    use criterion::Throughput;
    use svkernel::forward::medium::{Medium, Source};
    use svkernel::forward::tally::RadialBins;
    use svkernel::forward::walk::simulate_scalar;
    use svkernel::render::estimator::View;
    use svkernel::render::reference::{Reference, Tracking};
    use svkernel::render::scene::{LightKind, Observable};
    let paths = 16_384u64;
    let view = View {
        light_radius: 1.0,
        irradiance: 1.0,
        resolution: 64,
        half_width: 4.0,
    };
    let source = Source::Collimated { radius: 1.0 };
    let bins = RadialBins::default().lookup();
    let mut g = c.benchmark_group("walk");
    g.sample_size(10);
    // The homogeneous walk at the reference's albedos: events per second
    // depend on the path length (per-path launch and tally), so the
    // heterogeneous reference is compared with the albedos it contains.
    let homogeneous = |alpha: f64| {
        let medium = Medium::new(alpha, 0.3, 1.5, 1.0, None).expect("medium");
        simulate_scalar(&medium, &source, &bins, 1_000_000, 1, 0, paths, false)
    };
    for alpha in [0.9, 0.3, 0.95] {
        g.throughput(Throughput::Elements(homogeneous(alpha).events));
        g.bench_function(format!("homogeneous_scalar_a{alpha}"), |b| {
            b.iter(|| black_box(homogeneous(black_box(alpha))))
        });
    }
    let (stripes, ramp) = (stripes(320), density_ramp(320));
    let constant = TexelMap::new(1, 1, TAU, vec![0.9]).expect("map");
    // Albedo stripes and the density ramp separately, then together; with a
    // density map both trackings (the reference picks one per scene).
    let mut configs = Vec::new();
    for (albedo, alone, with_ramp, sweep) in [
        (&constant, "constant_a0.9", "a0.9", true),
        (&stripes, "stripes", "stripes", false),
    ] {
        configs.push((format!("reference_{alone}"), albedo, None, None));
        // The majorant grid the reference picks for the ramp (`None`), then
        // regular and delta tracking (cells of one texel, one cell).
        let trackings = [
            (None, "grid".to_string()),
            (Some(Tracking::REGULAR), "regular".to_string()),
            (Some(Tracking::DELTA), "delta".to_string()),
        ];
        // With the constant albedo, every cell size between (the data that
        // calibrates `reference::STEP_IN_CROSSINGS`).
        let cells = (1..9).map(|k| {
            (
                Some(Tracking {
                    cell_texels: 1 << k,
                }),
                format!("cells{}", 1 << k),
            )
        });
        for (t, how) in trackings.into_iter().chain(cells.filter(|_| sweep)) {
            let name = format!("reference_{with_ramp}_density_ramp_{how}");
            configs.push((name, albedo, Some(&ramp), t));
        }
    }
    for (name, albedo, density, tracking) in configs {
        let mut r = Reference::new(
            1.5,
            0.3,
            std::slice::from_ref(albedo),
            density,
            1.0,
            &LightKind::Collimated,
            view,
            Observable::Exitance,
            1,
            paths,
        )
        .expect("reference");
        if let Some(t) = tracking {
            r.set_tracking(t);
        }
        let events = r.chunk(0).events;
        g.throughput(Throughput::Elements(events));
        g.bench_function(&name, |b| b.iter(|| black_box(r.chunk(0))));
        if name == "reference_stripes" {
            // Per-path work (launch, entry Fresnel, tally) makes events per
            // second depend on the path length, and the stripes' paths are
            // short (most end in an α = 0.3 stripe): their homogeneous
            // counterpart is the albedo whose paths are as long (bisection on
            // events per path, fixed streams).
            let per_path = |a: f64| homogeneous(a).events as f64 / paths as f64;
            let target = events as f64 / paths as f64;
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..20 {
                let mid = 0.5 * (lo + hi);
                if per_path(mid) < target {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let alpha = 0.5 * (lo + hi);
            println!("stripes: {target:.3} events per path; homogeneous equivalent α = {alpha:.4}");
            g.throughput(Throughput::Elements(homogeneous(alpha).events));
            g.bench_function("homogeneous_scalar_stripes_equivalent", |b| {
                b.iter(|| black_box(homogeneous(black_box(alpha))))
            });
        }
    }
    g.finish();
}
