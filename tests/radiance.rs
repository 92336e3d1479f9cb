//! The radiance along the normal: its profile simulation (next-event
//! estimation) against exact values, and its shipped bases against the
//! simulations they were fitted to.

use std::f64::consts::PI;
use svkernel::fit::basis::pencil_single_radiance;
use svkernel::forward::medium::{Incidence, Medium, Observable, Source};
use svkernel::forward::profile::{DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use svkernel::forward::runner::{RunOptions, chunk_range};
use svkernel::forward::tally::RadialBins;
use svkernel::jobs::shipped::Models;
use svkernel::provenance::Provenance;

fn simulate(
    alpha: f64,
    g: f64,
    eta: f64,
    source: Source,
    radiance: bool,
    paths: u64,
) -> ProfileDoc {
    let config = ProfileConfig {
        medium: Medium::new(alpha, g, eta, 1.0, None).unwrap(),
        source,
        paths,
        seed: 11,
        max_events: DEFAULT_MAX_EVENTS,
        bins: RadialBins::default(),
        engine: Engine::Scalar,
        radiance,
    };
    let (tally, wall) = config.run(None, &RunOptions::default()).unwrap();
    let chunks = vec![chunk_range(paths, None)];
    ProfileDoc::new(config, None, chunks, tally, wall, Provenance::current())
}

/// Index-matched isotropic half-space, pencil beam: the normal radiance
/// integrated over the surface is α·H(1)²/(8π) (Chandrasekhar 1960, §28;
/// H(1) = 1.25126 at α = 0.5, oracles.md), its single-scattering part is
/// α·f(−1)/2 = α/(8π), and all of that lies at x_i (the inner disk).
#[test]
fn normal_radiance_reproduces_chandrasekhar() {
    let alpha = 0.5;
    let doc = simulate(alpha, 0.0, 1.0, Source::Pencil, true, 2_000_000);
    let r = doc.radiance.as_ref().expect("tallied");
    let total = r.single.value + r.multi.value;
    let err = r.single.stderr.hypot(r.multi.stderr);
    let want = alpha * 1.25126f64.powi(2) / (8.0 * PI);
    assert!(
        (total - want).abs() < 4.0 * err + 2e-5,
        "{total} ± {err} vs {want}"
    );
    assert!(err < 2e-3 * want, "stderr {err} too large to test");
    let single = alpha * pencil_single_radiance(0.0, 1.0);
    assert!((single - alpha / (8.0 * PI)).abs() < 1e-15);
    assert!(
        (r.single.value - single).abs() < 4.0 * r.single.stderr,
        "{} ± {} vs {single}",
        r.single.value,
        r.single.stderr
    );
    let t = doc.tally.radiance.as_ref().unwrap();
    assert!(t.single[0] > 0 && t.single[1..].iter().all(|&q| q == 0));
    // The ring densities integrate to the totals.
    let b = &doc.bins;
    let rings: f64 = (0..b.l_m.len())
        .map(|k| b.l_m[k] * (b.edges[k + 1] - b.edges[k]))
        .sum();
    assert!((rings + r.overflow.1.value - r.multi.value).abs() < 1e-12 * r.multi.value);
}

/// Tallying the radiance changes no path: the exit counts are those of the
/// plain scalar walk, bitwise, and the walk refuses the lane engine.
#[test]
fn radiance_tally_leaves_the_walk_unchanged() {
    for source in [Source::Pencil, Source::Diffuse { radius: 0.0 }] {
        let with = simulate(0.9, 0.3, 1.5, source, true, 100_000);
        let without = simulate(0.9, 0.3, 1.5, source, false, 100_000);
        let mut t = with.tally.clone();
        t.radiance = None;
        assert_eq!(t, without.tally, "{source:?}");
    }
    let c = ProfileConfig {
        engine: Engine::Lanes,
        ..simulate(0.9, 0.3, 1.5, Source::Pencil, true, 10).config
    };
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("engine") && e.contains("scalar"), "{e}");
}

/// The shipped radiance bases reproduce the simulated radiance profiles they
/// were fitted to: ∫L dA within 0.5 % at every training albedo, and the
/// pencil basis' single scattering is the closed form, a point at x_i.
#[test]
fn shipped_radiance_bases_match_their_profiles() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/profiles");
    let models = Models::builtin().unwrap();
    for (incidence, dir) in [
        (Incidence::Pencil, "eta1.5_g0.3_pencil_radiance"),
        (Incidence::Diffuse, "eta1.5_g0.3_diffuse_radiance"),
    ] {
        let (basis, _) = models.basis_for(incidence, Observable::Radiance);
        assert_eq!(basis.observable, Observable::Radiance);
        for name in ["a0.295062.json", "a0.810240.json", "a0.991206.json"] {
            let doc = ProfileDoc::load(&root.join(dir).join(name)).unwrap();
            let alpha = doc.config.medium.alpha;
            let o = doc.observed(Observable::Radiance).unwrap();
            let model = basis.r_d(alpha);
            let rel = model / o.total.value - 1.0;
            assert!(
                rel.abs() < 5e-3,
                "{dir}/{name}: {model} vs {} ({rel:+.4})",
                o.total.value
            );
        }
        if incidence == Incidence::Pencil {
            let single = basis.single.energy();
            assert!((single / pencil_single_radiance(0.3, 1.5) - 1.0).abs() < 1e-12);
            assert!(basis.single.cdf(1e-3) > 0.99 * single);
        }
    }
}
