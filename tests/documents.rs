//! The result documents (`render.json`, `compare.json`, `experiments.json`)
//! are typed: each one written by a small real run reads back equal to what
//! was written, and a document without the fields added later (the
//! material, a curve point's set-up, a row's model shape) still reads.

use std::path::{Path, PathBuf};
use svkernel::jobs::compare::{CompareDoc, CompareSettings, compare_scene};
use svkernel::jobs::experiments::{ExperimentsDoc, Settings, run};
use svkernel::jobs::render::{RenderDoc, RenderOptions, Target, render_scene, write_outputs};
use svkernel::render::scene::Scene;
use svkernel::render::svbssrdf::Method;

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("svk-docs-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A scene file in `d`: `head` over a collimated disk light of radius
/// 1 MFP and 8 × 8 pixels over [−2, 2]² MFP.
fn scene(d: &Path, file: &str, head: &str) -> Scene {
    let p = d.join(file);
    std::fs::write(
        &p,
        format!("{head}\n[light]\nradius = 1.0\n[image]\nresolution = 8\nhalf_width = 2.0\n"),
    )
    .unwrap();
    Scene::load(&p).unwrap()
}

fn options(out: &Path) -> RenderOptions {
    RenderOptions {
        spp: Some(4),
        reference_paths: Some(2_000),
        cache: None,
        ..RenderOptions::new(
            out.to_path_buf(),
            svkernel::jobs::shipped::Models::builtin().unwrap(),
        )
    }
}

/// serialize → deserialize → equal, through a string.
fn round_trip<T>(doc: &T) -> T
where
    T: serde::Serialize + serde::de::DeserializeOwned + PartialEq + std::fmt::Debug,
{
    let text = serde_json::to_string_pretty(doc).unwrap();
    let back: T = serde_json::from_str(&text).unwrap();
    assert_eq!(&back, doc);
    back
}

/// `value` without `key` at the JSON pointer `at`.
fn without(mut value: serde_json::Value, at: &str, key: &str) -> serde_json::Value {
    value
        .pointer_mut(at)
        .and_then(|v| v.as_object_mut())
        .unwrap_or_else(|| panic!("{at}"))
        .remove(key)
        .unwrap_or_else(|| panic!("{at}/{key}"));
    value
}

#[test]
fn render_json_round_trips() {
    let d = dir("render");
    let s = scene(
        &d,
        "s.toml",
        "name = \"s\"\ntexel = 0.25\nalbedo = { pattern = \"stripes\", values = [0.3, 0.9], \
         width = 0.5 }\nmethods = [\"point\", \"learned\"]",
    );
    let opts = options(&d.join("out"));
    let passes = render_scene(&s, &opts).unwrap();
    let doc = write_outputs(&s, &opts, &passes).unwrap();
    assert_eq!(doc.passes[0].methods.len(), 3);
    assert_eq!(doc.passes[0].methods[0].method, Target::Reference);
    assert!(doc.passes[0].methods[2].metrics.is_some());
    round_trip(&doc);
    let path = d.join("out/render.json");
    assert_eq!(RenderDoc::load(&path).unwrap(), doc);
    // The previews of the input maps are written beside the images.
    assert!(d.join("out/main/albedo.png").exists());
    // Without the material (older files) it still reads.
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let old: RenderDoc = serde_json::from_value(without(v, "", "material")).unwrap();
    assert_eq!(old.material, None);
    // A black reference's undefined errors (NaN, written null) read back.
    let mut nan = doc.clone();
    nan.passes[0].methods[1].metrics.as_mut().unwrap().rel_rmse = f64::NAN;
    let back: RenderDoc = serde_json::from_str(&serde_json::to_string(&nan).unwrap()).unwrap();
    let m = back.passes[0].methods[1].metrics.as_ref().unwrap();
    assert!(m.rel_rmse.is_nan());
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn compare_json_round_trips_and_the_report_fits_the_scene() {
    let d = dir("compare");
    // A grey albedo written as RGB over a constant density map: the
    // analysis skips work, so the savings are measured too.
    let s = scene(
        &d,
        "g.toml",
        "name = \"g\"\ntexel = 0.25\nalbedo = { pattern = \"stripes\", values = \
         [[0.3, 0.3, 0.3], [0.9, 0.9, 0.9]], width = 0.5 }\ndensity = { constant = 2.0 }\n\
         methods = [\"point\", \"manual\"]",
    );
    let opts = options(&d.join("out"));
    let settings = CompareSettings {
        curves: Some((20_000, vec![4, 16], vec![2_000, 20_000])),
        measure_savings: true,
    };
    let c = compare_scene(&s, &opts, &settings).unwrap();
    let doc = &c.doc;
    assert!(doc.savings.is_some(), "the skips were measured");
    assert_eq!(doc.curves.curves.len(), 3);
    assert_eq!(doc.curves.speedups.len(), 2);
    round_trip(doc);
    let path = d.join("out/compare.json");
    assert_eq!(&CompareDoc::load(&path).unwrap(), doc);
    let text = doc.to_string();
    assert!(
        text.contains("scene g, pass main:") && text.contains("manual"),
        "{text}"
    );
    // Curve points without a set-up (older files) read as set-up 0.
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let old: CompareDoc =
        serde_json::from_value(without(v, "/curves/curves/1/points/0", "setup_s")).unwrap();
    let p = &old.curves.curves[1].points[0];
    assert_eq!((p.setup_s, p.render_s()), (0.0, p.wall_s));
    // The curves plot render time: the kernel method's set-up is recorded
    // beside each point, not in it.
    let manual = &doc.curves.curves[2];
    assert_eq!(manual.method, Target::Model(Method::Manual));
    assert!(
        manual
            .points
            .iter()
            .all(|p| p.setup_s > 0.0 && p.render_s() < p.wall_s)
    );
    // The report: each difference under its method (the reference's cell
    // empty), the input maps, a verdict, the terms, and phrases that are
    // true of this scene.
    let md = std::fs::read_to_string(d.join("out/report.md")).unwrap();
    assert!(
        md.contains("|  | point − reference | manual − reference |"),
        "{md}"
    );
    assert!(md.contains("](main/albedo.png)") && md.contains("](main/density.png)"));
    assert!(md.contains("Verdict: ") && md.contains("## Terms"), "{md}");
    assert!(
        md.contains("three identical channels") && md.contains("a constant density map (ρ = 2)"),
        "{md}"
    );
    assert!(
        !md.contains("pencil basis") && !md.contains("a grey map"),
        "{md}"
    );
    std::fs::remove_dir_all(&d).unwrap();
}

/// The analysis words the light as it is: its kind and radius.
#[test]
fn the_analysis_words_the_light_as_it_is() {
    let d = dir("light");
    for (kind, radius) in [("collimated", 1.0), ("diffuse", 1.5)] {
        let p = d.join(format!("{kind}.toml"));
        std::fs::write(
            &p,
            format!(
                "albedo = {{ constant = 0.5 }}\n[light]\nkind = \"{kind}\"\nradius = {radius}\n"
            ),
        )
        .unwrap();
        let plan = svkernel::render::analysis::analyse(&Scene::load(&p).unwrap(), true);
        let light: Vec<&str> = plan.effects[3..5]
            .iter()
            .map(|e| e.detail.as_str())
            .collect();
        for detail in &light {
            assert!(
                detail.starts_with(&format!(
                    "the light is a {kind} disk of radius {radius} MFP"
                )),
                "{detail}"
            );
        }
        let loaded = if kind == "diffuse" {
            light[1]
        } else {
            light[0]
        };
        assert!(loaded.contains("only the"), "{loaded}");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn experiments_json_round_trips() {
    let d = dir("experiments");
    // Named `stripes`: the scene takes part in every experiment, the
    // meta-model one included.
    let s = d.join("stripes.toml");
    scene(
        &d,
        "stripes.toml",
        "name = \"stripes\"\ntexel = 0.25\nalbedo = { pattern = \"stripes\", values = \
         [0.3, 0.9], width = 0.5 }",
    );
    let settings = Settings {
        scenes: vec![s],
        models: vec!["data/profiles/metamodel.json".into()],
        bases: Vec::new(),
    };
    let rows = run(&settings, &options(&d.join("out"))).unwrap();
    assert!(rows.iter().any(|r| r.method == Method::Manual));
    let with_model = rows.iter().find(|r| r.model.is_some()).unwrap();
    assert!(with_model.model_shape.as_ref().is_some_and(|m| m.k >= 1));
    let doc = ExperimentsDoc::new(4, 2_000, rows);
    let back = round_trip(&doc);
    let path = d.join("experiments.json");
    svkernel::jobs::store::write_json_atomic(&path, &back).unwrap();
    assert_eq!(ExperimentsDoc::load(&path).unwrap(), doc);
    // The console text is the report's tables.
    let text = doc.to_string();
    assert!(
        text.contains("# Learned vs manual vs the baselines") && text.contains("stripes"),
        "{text}"
    );
    std::fs::remove_dir_all(&d).unwrap();
}
