//! Models for any medium: `svkernel medium build/list`, renders that find
//! them, and the presets (the index-matched one against the exact oracles).

mod common;

use std::collections::BTreeMap;
use std::path::Path;
use std::time::SystemTime;
use svkernel::jobs::shipped::{Models, PRESETS, preset};
use svkernel::oracles;

/// Every file under `dir` with its modification time.
fn snapshot(dir: &Path) -> BTreeMap<String, SystemTime> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.display().to_string(),
                    e.metadata().unwrap().modified().unwrap(),
                );
            }
        }
    }
    out
}

const SCENE: &str = r#"name = "other medium"
texel = 0.05
albedo = { pattern = "stripes", values = [0.6, 0.95], width = 0.5 }
methods = ["learned", "factorized"]
samples = 16
reference_paths = 20000
[medium]
eta = 1.3
g = 0.5
[light]
kind = "collimated"
radius = 1.0
[image]
resolution = 8
half_width = 1.5
"#;

#[test]
fn build_list_and_render_with_a_built_medium() {
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("cache");
    let cache_s = cache.to_str().unwrap();
    let build = |extra: &[&str]| {
        let mut args = vec![
            "medium", "build", "--eta", "1.3", "--g", "0.5", "--quick", "--cache", cache_s,
        ];
        args.extend_from_slice(extra);
        common::bin().args(&args).output().unwrap()
    };
    let o = build(&[]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        out.contains("built in") && out.contains("| pencil |") && out.contains("| diffuse |"),
        "{out}"
    );
    assert!(out.contains("Aggregation error over"), "{out}");
    let before = snapshot(&cache);

    // Built once: a second build, the list and a render only read it.
    let o = build(&[]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("already built"));
    let o = common::bin()
        .args(["medium", "list", "--cache", cache_s])
        .output()
        .unwrap();
    let list = String::from_utf8_lossy(&o.stdout);
    assert!(
        list.contains("cached") && list.contains("1.3") && list.contains("preset skin"),
        "{list}"
    );
    std::fs::write(tmp.path().join("scene.toml"), SCENE).unwrap();
    let render = |extra: &[&str]| {
        let mut args = vec!["render", "scene.toml", "--out", "out"];
        args.extend_from_slice(extra);
        common::bin()
            .current_dir(tmp.path())
            .args(&args)
            .output()
            .unwrap()
    };
    let o = render(&["--cache", cache_s]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(tmp.path().join("out/main/learned_mean.npy").exists());
    assert_eq!(
        snapshot(&cache),
        before,
        "the render simulated or fitted again"
    );

    // Without a cache to build into, a medium without models is refused,
    // naming the scene and the key.
    let other = SCENE.replace("g = 0.5", "g = 0.45");
    std::fs::write(tmp.path().join("scene.toml"), other).unwrap();
    let o = render(&["--no-extend"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("scene.toml") && err.contains("medium") && err.contains("no models"),
        "{err}"
    );
}

#[test]
fn a_medium_outside_the_domain_is_refused_naming_the_key() {
    for (eta, g, key) in [("0.5", "0.3", "eta"), ("1.4", "1.2", "g")] {
        let o = common::bin()
            .args([
                "medium", "build", "--eta", eta, "--g", g, "--quick", "--out", "unused",
            ])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains(&format!("invalid --{key}")),
            "{err}"
        );
        assert!(!Path::new("unused").exists());
    }
}

/// The index-matched preset (η = 1, g = 0) against the exact values: R_d
/// under a pencil beam (1 − H(1)√(1 − α)) and under diffuse light (the
/// spherical albedo), within 0.5 % plus the table's rounding.
#[test]
fn index_matched_preset_matches_the_exact_oracles() {
    let p = preset("index-matched").unwrap();
    assert_eq!((p.eta, p.g), (1.0, 0.0));
    let m = p.models(&Models::builtin().unwrap()).unwrap();
    for (k, &alpha) in oracles::ALBEDOS.iter().enumerate() {
        if !(0.1..=0.99).contains(&alpha) {
            continue; // the fit's end points are extrapolation-free but noisier
        }
        for (basis, table) in [
            (&m.basis, &oracles::RD_ETA1_G0),
            (&m.basis_diffuse, &oracles::SPHERICAL_ETA1_G0),
        ] {
            let (got, want) = (basis.r_d(alpha), table[k]);
            let tol = 0.005 * want + oracles::accuracy(true, alpha);
            assert!(
                (got - want).abs() <= tol,
                "α {alpha}: {got} vs exact {want}"
            );
        }
    }
}

/// Every preset: models of its medium, accuracy within the targets, and
/// found by (η, g) by a render.
#[test]
fn presets_are_accurate_and_found_by_their_medium() {
    let base = Models::builtin().unwrap();
    for p in PRESETS {
        let m = base.for_medium(p.eta, p.g, None, false).unwrap();
        assert_eq!(
            (m.basis.eta, m.basis.g, m.meta.eta, m.meta.g),
            (p.eta, p.g, p.eta, p.g)
        );
        let doc: svkernel::jobs::medium::MediumDoc = serde_json::from_str(p.manifest).unwrap();
        let (rd, l2) = doc.accuracy.worst_profile();
        assert!(
            rd <= 0.005 && l2 <= 0.02,
            "{}: R_d {rd}, radial L2 {l2}",
            p.name
        );
        assert_eq!(doc.accuracy.cells_not_beating_manual(), 0, "{}", p.name);
    }
    // The built-in medium is the built-in models.
    let d = base.for_medium(1.5, 0.3, None, false).unwrap();
    assert!(std::sync::Arc::ptr_eq(&d.meta, &base.meta));
}
