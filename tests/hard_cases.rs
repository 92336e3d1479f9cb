//! Hard cases: extreme parameters produce finite, consistent
//! results and no panic, in both engines.

use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::profile::{Engine, ProfileConfig, ProfileDoc};
use svkernel::forward::runner::{RunOptions, chunk_range};
use svkernel::forward::tally::RadialBins;
use svkernel::provenance::Provenance;

fn run(alpha: f64, g: f64, eta: f64, rho: f64, source: Source, engine: Engine) -> ProfileDoc {
    let config = ProfileConfig {
        medium: Medium::new(alpha, g, eta, rho, None).unwrap(),
        source,
        paths: 3000,
        seed: 1,
        max_events: 20_000,
        bins: RadialBins::default(),
        engine,
        radiance: false,
    };
    let (tally, wall) = config.run(None, &RunOptions::default()).unwrap();
    ProfileDoc::new(
        config,
        None,
        vec![chunk_range(3000, None)],
        tally,
        wall,
        Provenance::current(),
    )
}

fn assert_sane(d: &ProfileDoc, what: &str) {
    assert_eq!(d.tally.accounted(), d.tally.paths, "{what}");
    let v = serde_json::to_value(d).unwrap();
    let mut stack = vec![&v];
    while let Some(x) = stack.pop() {
        match x {
            serde_json::Value::Number(n) => {
                assert!(n.as_f64().is_some_and(f64::is_finite), "{what}")
            }
            serde_json::Value::Null => {}
            serde_json::Value::Array(a) => stack.extend(a),
            serde_json::Value::Object(o) => stack.extend(o.values()),
            _ => {}
        }
    }
    assert!(
        (d.energy_balance - 1.0).abs() < 1e-9,
        "{what}: {}",
        d.energy_balance
    );
    assert!(d.R_d >= 0.0 && d.R_d <= 1.0, "{what}");
}

#[test]
fn extreme_parameters_are_finite() {
    for engine in [Engine::Scalar, Engine::Lanes] {
        for alpha in [0.0, 1e-9, 1.0 - 1e-9, 1.0] {
            for g in [-0.99, 0.0, 0.99] {
                let d = run(alpha, g, 1.5, 1.0, Source::Pencil, engine);
                assert_sane(&d, &format!("{engine:?} α={alpha} g={g}"));
                if alpha == 0.0 {
                    assert_eq!(d.events, 0);
                    assert_eq!(d.R_d, 0.0);
                }
            }
        }
        for eta in [1.0, 1.0001, 3.0] {
            for source in [Source::Pencil, Source::Diffuse { radius: 0.5 }] {
                let d = run(0.9, 0.3, eta, 1.0, source, engine);
                assert_sane(&d, &format!("{engine:?} η={eta} {source:?}"));
            }
        }
        for rho in [1e-3, 1e3] {
            let d = run(
                0.9,
                0.3,
                1.5,
                rho,
                Source::Collimated { radius: 1.0 },
                engine,
            );
            assert_sane(&d, &format!("{engine:?} ρ={rho}"));
        }
    }
}

#[test]
fn albedo_just_below_one_still_absorbs() {
    // 1 − 1e-9 is 1.0 in f32; the integer absorption threshold keeps it apart.
    let t = svkernel::forward::rng::threshold_u32(1.0 - 1e-9);
    assert!(t < 1 << 32);
    let d = run(1.0 - 1e-9, 0.0, 1.0, 1.0, Source::Pencil, Engine::Lanes);
    assert_sane(&d, "α = 1 − 1e-9");
}

/// Radial bins must end at r_max: a ratio r_max/r_min that is not a whole
/// number of rings is refused, naming the bins; whole ones end exactly there.
#[test]
fn radial_bins_end_at_r_max() {
    let with = |r_max: f64| ProfileConfig {
        medium: Medium::new(0.5, 0.0, 1.0, 1.0, None).unwrap(),
        source: Source::Pencil,
        paths: 10,
        seed: 1,
        max_events: 100,
        bins: RadialBins {
            r_min: 1e-3,
            r_max,
            per_decade: 20,
        },
        engine: Engine::Scalar,
        radiance: false,
    };
    for r_max in [52.0, 60.0] {
        let err = with(r_max).validate().unwrap_err().to_string();
        assert!(
            err.contains("bins") && err.contains("whole number"),
            "{err}"
        );
    }
    for r_max in [100.0, 10f64.powf(1.35)] {
        let c = with(r_max);
        assert!(c.validate().is_ok(), "{r_max}");
        let last = *c.bins.edges().last().unwrap();
        assert!((last / r_max - 1.0).abs() < 1e-12, "{last} vs {r_max}");
    }
}
