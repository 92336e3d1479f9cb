//! Every shipped scene loads and is what docs/design.md §5 says it is.

use std::path::Path;
use svkernel::render::scene::{LightKind, Scene};

#[test]
fn every_shipped_scene_loads() {
    let mut names = Vec::new();
    for entry in std::fs::read_dir("scenes").unwrap() {
        let p = entry.unwrap().path();
        if p.extension().is_some_and(|e| e == "toml") {
            let s = Scene::load(&p).unwrap_or_else(|e| panic!("{e}"));
            assert!(
                s.albedo
                    .iter()
                    .all(|m| m.values.iter().all(|v| (0.0..=1.0).contains(v)))
            );
            assert_eq!(s.light, LightKind::Collimated);
            names.push(s.name);
        }
    }
    names.sort();
    assert_eq!(
        names,
        [
            "checker", "color", "complex", "density", "features", "stripes"
        ]
    );
}

/// The extra (non-canonical) example scenes load and exercise what they
/// are for: the scene analysis's skips, and albedos below the meta-model's
/// trained range.
#[test]
fn extra_scenes_load_and_exercise_skips_and_the_range() {
    use svkernel::render::analysis::analyse;
    let grey = Scene::load(Path::new("scenes/extra/grey_rgb.toml")).unwrap();
    let plan = analyse(&grey, true);
    assert!(plan.grey && plan.constant_density == Some(2.0) && plan.skips_work());
    let dark = Scene::load(Path::new("scenes/extra/dark.toml")).unwrap();
    let [lo, _] = analyse(&dark, true).albedo_range;
    let meta =
        svkernel::metamodel::meta::MetaModelFile::load(Path::new("data/profiles/metamodel.json"))
            .unwrap();
    assert!(lo < meta.all.alpha_range[0]);
}

#[test]
fn canonical_scenes_have_their_structure() {
    let s = Scene::load(Path::new("scenes/stripes.toml")).unwrap();
    let vals: std::collections::BTreeSet<u64> =
        s.albedo[0].values.iter().map(|v| v.to_bits()).collect();
    assert_eq!(vals.len(), 2);
    assert!(s.is_grey() && !s.albedo_is_constant() && s.density.is_none());
    let c = Scene::load(Path::new("scenes/color.toml")).unwrap();
    assert_eq!(c.albedo.len(), 3);
    assert!(!c.is_grey());
    let f = Scene::load(Path::new("scenes/features.toml")).unwrap();
    assert_eq!(f.density_sweep, vec![0.5, 1.0, 2.0, 4.0]);
    assert_eq!(f.light_radius, 4.0);
    let d = Scene::load(Path::new("scenes/density.toml")).unwrap();
    let rho = d.density.as_ref().unwrap();
    assert!((rho.at(-10.0, 0.0) - 0.5).abs() < 1e-12 && (rho.at(10.0, 0.0) - 4.0).abs() < 1e-12);
    assert!((rho.at(0.0, 0.0) - 2.25).abs() < 0.05);
}
