//! Throughput of the forward walk in scattering events per second: the f64
//! scalar walk against the eight-lane f32 walk, on one thread and on all
//! threads (rayon over chunks, merged in chunk order as the runner does).
//!
//! Medium: α ∈ {0.9, 0.99}, g = 0.3, η = 1.5, ρ = 1, half-space; pencil
//! source; default bins and event cap. `cargo bench --bench forward`.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use rayon::prelude::*;
use std::hint::black_box;
use std::time::Duration;
use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::profile::{DEFAULT_MAX_EVENTS, Engine, ProfileConfig};
use svkernel::forward::runner::CHUNK_PATHS;
use svkernel::forward::tally::{BinLookup, ProfileTally, RadialBins};

const SEED: u64 = 0x5EED;
/// Chunks of the all-threads benchmarks.
const CHUNKS: u64 = 32;

fn config(alpha: f64, engine: Engine) -> ProfileConfig {
    ProfileConfig {
        medium: Medium::new(alpha, 0.3, 1.5, 1.0, None).unwrap(),
        source: Source::Pencil,
        paths: CHUNKS * CHUNK_PATHS,
        seed: SEED,
        max_events: DEFAULT_MAX_EVENTS,
        bins: RadialBins::default(),
        engine,
        radiance: false,
    }
}

/// All chunks of `cfg` in parallel, merged in chunk order.
fn all_threads(cfg: &ProfileConfig, bins: &BinLookup) -> ProfileTally {
    let parts: Vec<ProfileTally> = (0..CHUNKS)
        .into_par_iter()
        .map(|c| cfg.simulate_chunk(c, bins))
        .collect();
    let mut total = ProfileTally::new(&cfg.bins);
    for p in &parts {
        total.merge(p);
    }
    total
}

/// The first chunk ([`CHUNK_PATHS`] paths) on the calling thread.
fn one_thread(cfg: &ProfileConfig, bins: &BinLookup) -> ProfileTally {
    cfg.simulate_chunk(0, bins)
}

fn forward(c: &mut Criterion) {
    let mut group = c.benchmark_group("forward");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(5))
        .warm_up_time(Duration::from_secs(1));
    for alpha in [0.9, 0.99] {
        for (name, engine, threads) in [
            ("scalar_1thread", Engine::Scalar, false),
            ("lanes_1thread", Engine::Lanes, false),
            ("scalar_all_threads", Engine::Scalar, true),
            ("lanes_all_threads", Engine::Lanes, true),
        ] {
            let cfg = config(alpha, engine);
            // The bins' lookup is built once per run, as `ProfileConfig::run` does.
            let bins = cfg.bins.lookup();
            let run = |cfg: &ProfileConfig| {
                if threads {
                    all_threads(cfg, &bins)
                } else {
                    one_thread(cfg, &bins)
                }
            };
            // Throughput in scattering events of this exact input.
            let events = run(&cfg).events;
            group.throughput(Throughput::Elements(events));
            group.bench_with_input(BenchmarkId::new(name, alpha), &cfg, |b, cfg| {
                b.iter(|| black_box(run(black_box(cfg))))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, forward);
criterion_main!(benches);
