//! Tier (c): the simulator against the oracle values of `svkernel::oracles`.
//!
//! Every check passes when |estimate − oracle| ≤ Z_MC·stderr + accuracy of
//! the oracle value. The default tier uses modest path counts (the whole file
//! runs in well under a minute on 2 cores); `--ignored` runs the same checks
//! with 20× the paths:
//! `cargo test --release --test oracles -- --ignored`.

use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::profile::{DEFAULT_MAX_EVENTS, Engine, ProfileConfig, ProfileDoc};
use svkernel::forward::runner::{RunOptions, chunk_range};
use svkernel::forward::tally::RadialBins;
use svkernel::oracles::*;
use svkernel::provenance::Provenance;
use svkernel::testing::Z_MC;

fn simulate(
    medium: Medium,
    source: Source,
    paths: u64,
    engine: Engine,
    max_events: u32,
) -> ProfileDoc {
    let config = ProfileConfig {
        medium,
        source,
        paths,
        seed: 20261123,
        max_events,
        bins: RadialBins::default(),
        engine,
        radiance: false,
    };
    let (tally, wall) = config.run(None, &RunOptions::default()).unwrap();
    let chunks = vec![chunk_range(paths, None)];
    ProfileDoc::new(config, None, chunks, tally, wall, Provenance::current())
}

fn check(what: &str, est: f64, stderr: f64, oracle: f64, accuracy: f64) {
    let tol = Z_MC * stderr + accuracy;
    println!("{what}: {est:.5} ± {stderr:.5} vs {oracle:.5} (tol {tol:.5})");
    assert!(
        (est - oracle).abs() <= tol,
        "{what}: {est} ± {stderr} vs oracle {oracle} ± {accuracy}"
    );
}

/// Paths for a target stderr at R_d ≈ rd (binomial), clamped to a range.
fn paths_for(rd: f64, rel: f64, scale: u64) -> u64 {
    let n = (1.0 - rd) / (rd * rel * rel);
    (n as u64).clamp(200_000, 16_000_000) * scale
}

fn rd_table(
    eta: f64,
    g: f64,
    table: &[f64; 11],
    exact: bool,
    albedos: &[f64],
    scale: u64,
    engine: Engine,
) {
    for &alpha in albedos {
        let oracle = lookup(table, alpha).unwrap();
        let m = Medium::new(alpha, g, eta, 1.0, None).unwrap();
        let d = simulate(
            m,
            Source::Pencil,
            paths_for(oracle, 0.003, scale),
            engine,
            DEFAULT_MAX_EVENTS,
        );
        check(
            &format!("R_d η={eta} g={g} α={alpha} {engine:?}"),
            d.R_d,
            d.R_d_stderr,
            oracle,
            accuracy(exact, alpha),
        );
        assert_eq!(d.tally.accounted(), d.tally.paths);
    }
}

#[test]
fn rd_index_matched_isotropic_exact() {
    let albedos = [0.01, 0.5, 0.9, 0.99, 0.999];
    rd_table(1.0, 0.0, &RD_ETA1_G0, true, &albedos, 1, Engine::Lanes);
}

#[test]
fn rd_default_medium_adding_doubling() {
    rd_table(1.5, 0.3, &RD_ETA15_G03, false, &ALBEDOS, 1, Engine::Lanes);
}

#[test]
fn rd_other_adding_doubling_rows() {
    let albedos = [0.3, 0.9, 0.99];
    rd_table(1.0, 0.3, &RD_ETA1_G03, false, &albedos, 1, Engine::Lanes);
    rd_table(1.5, 0.0, &RD_ETA15_G0, false, &albedos, 1, Engine::Lanes);
}

#[test]
fn rd_scalar_engine_matches_oracles_too() {
    rd_table(
        1.5,
        0.3,
        &RD_ETA15_G03,
        false,
        &[0.5, 0.95],
        1,
        Engine::Scalar,
    );
}

#[test]
fn spherical_albedo_under_diffuse_light() {
    // Total reflectance of a half-space does not depend on the disk radius.
    for alpha in [0.5, 0.9] {
        let oracle = lookup(&SPHERICAL_ETA1_G0, alpha).unwrap();
        let m = Medium::new(alpha, 0.0, 1.0, 1.0, None).unwrap();
        let d = simulate(
            m,
            Source::Diffuse { radius: 1.0 },
            400_000,
            Engine::Lanes,
            DEFAULT_MAX_EVENTS,
        );
        check(
            &format!("spherical albedo α={alpha}"),
            d.R_d,
            d.R_d_stderr,
            oracle,
            accuracy(true, alpha),
        );
    }
}

#[test]
fn single_scattering_closed_forms() {
    // R₁/α is independent of α; α = 1 maximises the count.
    for (eta, g, oracle) in RSS_OVER_ALPHA {
        let m = Medium::new(0.5, g, eta, 1.0, None).unwrap();
        let d = simulate(
            m,
            Source::Pencil,
            1_000_000,
            Engine::Lanes,
            DEFAULT_MAX_EVENTS,
        );
        check(
            &format!("R_ss/α η={eta} g={g}"),
            d.R_1 / 0.5,
            d.R_1_stderr / 0.5,
            oracle,
            5e-6,
        );
    }
}

#[test]
fn conservative_medium_energy_balance() {
    // α = 1: everything that enters comes back out, up to the truncated
    // fraction, which bounds the bias (walk.rs "Termination at α = 1").
    let m = Medium::new(1.0, 0.3, 1.5, 1.0, None).unwrap();
    let d = simulate(
        m,
        Source::Pencil,
        100_000,
        Engine::Lanes,
        DEFAULT_MAX_EVENTS,
    );
    assert_eq!(d.absorbed, 0.0);
    // P(n > N) decays like N^{-1/2}: about 0.4 % of paths reach 1e6 events.
    assert!(d.truncated < 0.01, "truncated {}", d.truncated);
    let (lo, hi) = (
        d.R_d - Z_MC * d.R_d_stderr,
        d.R_d + d.truncated + Z_MC * d.R_d_stderr,
    );
    println!(
        "α=1: R_d {:.5} ± {:.5}, truncated {:.5}: 1 − R_sp must lie in [{lo:.5}, {hi:.5}]",
        d.R_d, d.R_d_stderr, d.truncated
    );
    assert!(lo <= 0.96 && 0.96 <= hi);
    assert!((d.energy_balance - 1.0).abs() < 1e-12);
}

#[test]
fn van_de_hulst_slab() {
    let m = Medium::new(0.9, 0.75, 1.0, 1.0, Some(2.0)).unwrap();
    let d = simulate(
        m,
        Source::Pencil,
        1_000_000,
        Engine::Lanes,
        DEFAULT_MAX_EVENTS,
    );
    let (rd, t) = VAN_DE_HULST;
    check("van de Hulst R_d", d.R_d, d.R_d_stderr, rd, 5e-6);
    check(
        "van de Hulst T",
        d.transmitted,
        d.transmitted_stderr,
        t,
        5e-6,
    );
}

#[test]
fn density_rescales_lengths_exactly() {
    // σ_t = ρ: at ρ = 2 every free flight of a path is exactly half of its
    // flight at ρ = 1 (division by a power of two is exact), its decisions
    // are the same, so it exits at exactly half the position.
    use svkernel::forward::rng::PathRng;
    use svkernel::forward::walk::{Fate, launch, walk};
    let m1 = Medium::new(0.95, 0.3, 1.5, 1.0, None).unwrap();
    let m2 = Medium::new(0.95, 0.3, 1.5, 2.0, None).unwrap();
    let mut exits = 0;
    for path in 0..20_000 {
        let run = |m: &Medium| {
            let mut rng = PathRng::new(5, path);
            let start = launch(&Source::Collimated { radius: 1.0 }, m.eta, &mut rng).unwrap();
            let start = svkernel::forward::walk::Launched {
                position: start.position.map(|v| v / m.rho),
                ..start
            };
            walk(m, DEFAULT_MAX_EVENTS, start, &mut rng)
        };
        let (f1, n1) = run(&m1);
        let (f2, n2) = run(&m2);
        assert_eq!(n1, n2);
        match (f1, f2) {
            (Fate::Exit { x: x1, y: y1 }, Fate::Exit { x: x2, y: y2 }) => {
                assert_eq!((x1 / 2.0, y1 / 2.0), (x2, y2));
                exits += 1;
            }
            (a, b) => assert_eq!(a, b),
        }
    }
    assert!(exits > 1000);
}

// ---- slow tier: same checks, 20× the paths --------------------------------

#[test]
#[ignore = "slow statistical tier: cargo test --release --test oracles -- --ignored"]
fn slow_rd_all_rows() {
    rd_table(1.0, 0.0, &RD_ETA1_G0, true, &ALBEDOS, 20, Engine::Lanes);
    rd_table(1.5, 0.3, &RD_ETA15_G03, false, &ALBEDOS, 20, Engine::Lanes);
    rd_table(1.0, 0.3, &RD_ETA1_G03, false, &ALBEDOS, 20, Engine::Lanes);
    rd_table(1.5, 0.0, &RD_ETA15_G0, false, &ALBEDOS, 20, Engine::Lanes);
}
