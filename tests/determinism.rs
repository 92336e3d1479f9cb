//! Bitwise determinism: 1 vs N threads, shards merged vs unsharded (both
//! engines, and the scalar walk with the radiance tally), and shipped profiles re-simulated from their recorded
//! configuration. (The lane walk against the scalar walk, statistically —
//! they round differently — is `forward::simd`'s `agrees_with_scalar_walk`.)

use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::profile::{self, DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use svkernel::forward::runner::{CHUNK_PATHS, RunOptions, Shard, chunk_range};
use svkernel::forward::tally::{ProfileTally, RadialBins};
use svkernel::provenance::Provenance;

/// The engines, and the scalar one with the radiance along the normal.
const WALKS: [(Engine, bool); 3] = [
    (Engine::Scalar, false),
    (Engine::Lanes, false),
    (Engine::Scalar, true),
];

fn config((engine, radiance): (Engine, bool), source: Source) -> ProfileConfig {
    ProfileConfig {
        medium: Medium::new(0.95, 0.3, 1.5, 1.0, None).unwrap(),
        source,
        paths: 5 * CHUNK_PATHS + 1234,
        seed: 42,
        max_events: DEFAULT_MAX_EVENTS,
        bins: RadialBins::default(),
        engine,
        radiance,
    }
}

fn run_with_threads(c: &ProfileConfig, threads: usize, shard: Option<Shard>) -> ProfileTally {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| c.run(shard, &RunOptions::default()).unwrap().0)
}

#[test]
fn one_vs_many_threads_bitwise() {
    for walk in WALKS {
        for source in [Source::Pencil, Source::Diffuse { radius: 1.0 }] {
            let c = config(walk, source);
            let t1 = run_with_threads(&c, 1, None);
            let t4 = run_with_threads(&c, 4, None);
            assert_eq!(t1, t4, "{walk:?} {source:?}");
            assert_eq!(t1.radiance.is_some(), walk.1);
            assert_eq!(t1.paths, c.paths);
        }
    }
}

#[test]
fn shards_merged_equal_unsharded_bitwise() {
    for walk in WALKS {
        let c = config(walk, Source::Collimated { radius: 1.0 });
        let full_tally = run_with_threads(&c, 2, None);
        let full = ProfileDoc::new(
            c.clone(),
            None,
            vec![chunk_range(c.paths, None)],
            full_tally,
            0.0,
            Provenance::current(),
        );
        let n = 4;
        // Merge in a scrambled order: the merge is order independent.
        let mut docs = Vec::new();
        for k in [2, 0, 3, 1] {
            let shard = Some(Shard { index: k, count: n });
            let t = run_with_threads(&c, 2, shard);
            let d = ProfileDoc::new(
                c.clone(),
                shard,
                vec![chunk_range(c.paths, shard)],
                t,
                0.0,
                Provenance::current(),
            );
            docs.push((std::path::PathBuf::from(format!("shard{k}")), d));
        }
        let merged = profile::merge(&docs, Provenance::current()).unwrap();
        assert_eq!(merged.tally, full.tally);
        assert_eq!(merged.shard, None);
        assert_eq!(merged.chunks, full.chunks);
        // Every derived number too (the documents differ only in provenance).
        // Through the written text: a radiance tally's u128 sums do not fit
        // serde_json's in-memory numbers (the tallies are compared above).
        let strip = |d: &ProfileDoc| {
            let text = serde_json::to_string(d).unwrap();
            let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
            v.as_object_mut().unwrap().remove("provenance");
            v
        };
        assert_eq!(strip(&merged), strip(&full));
        // A shard twice is refused.
        let dup = vec![docs[0].clone(), docs[0].clone()];
        assert!(profile::merge(&dup, Provenance::current()).is_err());
        // A different configuration is refused.
        let mut other = docs[1].clone();
        other.1.config.seed += 1;
        assert!(profile::merge(&[docs[0].clone(), other], Provenance::current()).is_err());
    }
}

/// The shipped profiles are what `data/profiles/REGENERATE` says produced
/// them: re-simulating three of them from the configuration each document
/// records (20 million paths each, pencil and diffuse incidence, about 2 s
/// on 2 cores) gives their tallies bitwise. A change to the random streams,
/// the walk's arithmetic or the tallying that alters any result fails here
/// (and then the shipped data, fits and figures must be regenerated).
#[test]
fn shipped_profiles_reproduce_bitwise() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/profiles");
    for file in [
        "eta1.5_g0.3_pencil/a0.295062.json",
        "eta1.5_g0.3_pencil/a0.903087.json",
        "eta1.5_g0.3_diffuse/a0.295062.json",
        "eta1.5_g0.3_pencil_radiance/a0.295062.json",
    ] {
        let doc = ProfileDoc::load(&root.join(file)).unwrap();
        assert_eq!(doc.shard, None, "{file}");
        let (tally, _) = doc.config.run(None, &RunOptions::default()).unwrap();
        assert_eq!(
            tally, doc.tally,
            "{file}: the shipped tally is not reproduced"
        );
    }
}
