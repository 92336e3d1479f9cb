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
            "checker", "color", "complex", "density", "features", "marble", "milk", "skin",
            "stripes"
        ]
    );
}

/// The translucent scenes are translucent: albedo ≥ 0.95 on most of the
/// surface (every channel), as docs/design.md §5 says.
#[test]
fn translucent_scenes_are_bright_over_most_of_the_surface() {
    for name in ["marble", "skin", "milk"] {
        let s = Scene::load(Path::new(&format!("scenes/{name}.toml"))).unwrap();
        for m in &s.albedo {
            let bright = m.values.iter().filter(|&&v| v >= 0.95).count();
            assert!(
                bright as f64 > 0.8 * m.values.len() as f64,
                "{name}: {bright} of {} texels ≥ 0.95",
                m.values.len()
            );
        }
    }
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

/// A fresh temporary directory for one test's scene and texture files.
fn tmpdir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("svk-scenes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Writes `text` as `dir/name` and loads it as a scene.
fn load(dir: &Path, name: &str, text: &str) -> svkernel::Result<Scene> {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    Scene::load(&p)
}

/// Every texel of every channel, bit for bit.
fn bits(s: &Scene) -> Vec<Vec<u64>> {
    let mut v: Vec<Vec<u64>> = s
        .albedo
        .iter()
        .map(|m| m.values.iter().map(|x| x.to_bits()).collect())
        .collect();
    v.extend(
        s.density
            .iter()
            .map(|m| m.values.iter().map(|x| x.to_bits()).collect()),
    );
    v
}

/// A float32 `.npy` texture (as numpy writes by default for `float32`
/// images) loads to the same texels as the float64 one, grey and RGB, for
/// albedo and density; other dtypes are refused naming the file and the
/// accepted dtypes.
#[test]
fn float32_npy_textures_load_like_float64() {
    use ndarray_npy::write_npy;
    let d = tmpdir("npy32");
    // Values exact in f32 (k/64), so widening is exact.
    let grey = ndarray::Array2::from_shape_fn((3, 5), |(i, j)| (1 + i * 5 + j) as f64 / 64.0);
    let rgb = ndarray::Array3::from_shape_fn((2, 4, 3), |(i, j, c)| {
        (1 + (i * 4 + j) * 3 + c) as f64 / 64.0
    });
    write_npy(d.join("g64.npy"), &grey).unwrap();
    write_npy(d.join("g32.npy"), &grey.mapv(|v| v as f32)).unwrap();
    write_npy(d.join("c64.npy"), &rgb).unwrap();
    write_npy(d.join("c32.npy"), &rgb.mapv(|v| v as f32)).unwrap();
    for (a, b) in [("g64", "g32"), ("c64", "c32")] {
        let scene = |f: &str| {
            load(
                &d,
                &format!("{f}.toml"),
                &format!(
                    "texel = 0.5\nalbedo = {{ file = \"{f}.npy\" }}\n\
                     density = {{ file = \"g{}.npy\" }}\n",
                    &f[1..]
                ),
            )
            .unwrap_or_else(|e| panic!("{e}"))
        };
        let (s64, s32) = (scene(a), scene(b));
        assert_eq!(s64.albedo.len(), if a == "g64" { 1 } else { 3 });
        assert_eq!(bits(&s64), bits(&s32), "{a} vs {b}");
    }
    // An integer array: refused, naming the texture and the dtypes read.
    write_npy(d.join("int.npy"), &ndarray::Array2::<i64>::zeros((2, 2))).unwrap();
    let e = load(&d, "int.toml", "albedo = { file = \"int.npy\" }\n")
        .unwrap_err()
        .to_string();
    for n in ["int.toml", "albedo.file", "int.npy", "float64", "float32"] {
        assert!(e.contains(n), "'{n}' not in: {e}");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// Writes a 2 × 2 PNG of `color` with 8-bit samples `data`.
fn png(path: &Path, color: png::ColorType, data: &[u8]) {
    let f = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), 2, 2);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().unwrap().write_image_data(data).unwrap();
}

/// `transfer` is read in any letter case (`sRGB` as image tools write it),
/// and a PNG with an alpha channel is refused naming the file, not loaded
/// with its alpha silently dropped.
#[test]
fn png_transfer_in_any_case_and_alpha_refused() {
    let d = tmpdir("png");
    png(
        &d.join("g.png"),
        png::ColorType::Grayscale,
        &[0, 64, 128, 255],
    );
    let with = |t: &str| {
        load(
            &d,
            "t.toml",
            &format!("texel = 1.0\nalbedo = {{ file = \"g.png\", transfer = \"{t}\" }}\n"),
        )
        .unwrap_or_else(|e| panic!("{t}: {e}"))
    };
    let srgb = bits(&with("srgb"));
    let linear = bits(&with("linear"));
    assert_ne!(srgb, linear);
    for t in ["sRGB", "SRGB", "Srgb"] {
        assert_eq!(bits(&with(t)), srgb, "{t}");
    }
    for t in ["Linear", "LINEAR"] {
        assert_eq!(bits(&with(t)), linear, "{t}");
    }
    // Not a transfer: named as given, without debug text.
    let e = load(
        &d,
        "gamma.toml",
        "albedo = { file = \"g.png\", transfer = \"gamma2.2\" }\n",
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("gamma.toml") && e.contains("albedo.transfer") && e.contains("'gamma2.2'"),
        "{e}"
    );
    assert!(!e.contains("Some(") && !e.contains("None"), "{e}");
    let e = load(&d, "none.toml", "albedo = { file = \"g.png\" }\n")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("albedo.transfer") && e.contains("missing"),
        "{e}"
    );
    assert!(!e.contains("Some(") && !e.contains("None"), "{e}");
    // Alpha: RGBA and grey + alpha, as albedo and as density.
    png(&d.join("rgba.png"), png::ColorType::Rgba, &[200; 16]);
    png(&d.join("ga.png"), png::ColorType::GrayscaleAlpha, &[200; 8]);
    for (file, key) in [("rgba.png", "albedo"), ("ga.png", "density")] {
        let text = if key == "albedo" {
            format!("albedo = {{ file = \"{file}\", transfer = \"sRGB\" }}\n")
        } else {
            format!("albedo = 0.5\ndensity = {{ file = \"{file}\", transfer = \"linear\" }}\n")
        };
        let e = load(&d, "alpha.toml", &text).unwrap_err().to_string();
        for n in ["alpha.toml", &format!("{key}.file"), file, "alpha channel"] {
            assert!(e.contains(n), "'{n}' not in: {e}");
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// `albedo = 0.8` is `{ constant = 0.8 }`, `albedo = [r, g, b]` is
/// `{ rgb = [r, g, b] }`, likewise for `density` and inside `channels`;
/// a wrong shorthand is an error naming the line, not a serde type name.
#[test]
fn scalar_and_list_shorthands_for_maps() {
    let d = tmpdir("shorthand");
    let same = |short: &str, long: &str| {
        let a = load(&d, "short.toml", short).unwrap_or_else(|e| panic!("{short}: {e}"));
        let b = load(&d, "long.toml", long).unwrap_or_else(|e| panic!("{long}: {e}"));
        assert_eq!(bits(&a), bits(&b), "{short} vs {long}");
        a
    };
    let s = same("albedo = 0.8\n", "albedo = { constant = 0.8 }\n");
    assert!(s.albedo_is_constant() && s.albedo[0].values == [0.8]);
    same("albedo = 1\n", "albedo = { constant = 1.0 }\n");
    let s = same(
        "albedo = 0.8\ndensity = 2.0\n",
        "albedo = { constant = 0.8 }\ndensity = { constant = 2.0 }\n",
    );
    assert_eq!(s.density.as_ref().unwrap().values, [2.0]);
    let s = same(
        "albedo = [0.8, 0.5, 0.3]\n",
        "albedo = { rgb = [0.8, 0.5, 0.3] }\n",
    );
    assert_eq!(s.albedo.len(), 3);
    same(
        "albedo = { channels = [0.8, { constant = 0.5 }, 0.3] }\n",
        "albedo = { rgb = [0.8, 0.5, 0.3] }\n",
    );
    // Domain checks still apply to the shorthand.
    let e = load(&d, "over.toml", "albedo = 1.5\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("over.toml") && e.contains("albedo"), "{e}");
    for (text, want) in [
        ("albedo = [0.8, 0.5]\n", "three numbers"),
        ("albedo = [0.8, 0.5, 0.3, 0.1]\n", "three numbers"),
        ("albedo = \"red\"\n", "a number"),
    ] {
        let e = load(&d, "bad.toml", text).unwrap_err().to_string();
        assert!(
            e.contains("bad.toml") && e.contains("line 1") && e.contains(want),
            "{text}: {e}"
        );
        assert!(
            !e.contains("RawMap") && !e.contains("struct"),
            "{text}: {e}"
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}
