//! Fuzzing the scene parser and the file loaders with
//! proptest: mutated scene TOML, mutated `.npy` / `.png` / `.exr` textures
//! behind a valid scene, and mutated model and tally files. Every input
//! must load or give an error that names the file: never a panic.
//!
//! The default tier runs a few cases of each; the slow tier runs many
//! (bounded by case count, ≈ 1–2 min in all):
//!
//! ```text
//! cargo test --release --test fuzz -- --ignored
//! ```

use proptest::prelude::*;
use std::path::{Path, PathBuf};
use svkernel::render::scene::Scene;

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("svk-fuzz-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Loads a scene; any error must name the scene file and, when the damage is
/// in a texture, the texture file too.
fn load_names_file(scene: &Path, texture: Option<&Path>) -> Result<(), TestCaseError> {
    if let Err(e) = Scene::load(scene) {
        let msg = e.to_string();
        let names = |p: &Path| msg.contains(&*p.file_name().unwrap().to_string_lossy());
        prop_assert!(
            names(scene) && texture.is_none_or(names),
            "error does not name the damaged file: {msg}"
        );
    }
    Ok(())
}

/// Overwrites bytes at (position mod len) and truncates to `keep` (mod
/// len + 1).
fn mutate(bytes: &[u8], edits: &[(usize, u8)], keep: usize) -> Vec<u8> {
    let mut b = bytes.to_vec();
    if !b.is_empty() {
        for &(at, v) in edits {
            let n = b.len();
            b[at % n] = v;
        }
    }
    b.truncate(keep % (bytes.len() + 1));
    b
}

const TOKENS: &[&str] = &[
    "=", "[", "]", "{", "}", "\"", ",", "\n", "-1", "0", "nan", "inf", "-inf", "1e400", "1e-320",
    "4097", "0.5", "true", "\"x\"", "pattern", "values", "file", "constant", "#",
];

fn scene_text() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/density.toml"))
        .unwrap()
}

fn edits() -> impl Strategy<Value = Vec<(usize, u8)>> {
    prop::collection::vec((any::<usize>(), any::<u8>()), 0..12)
}

/// Mutated scene TOML: tokens spliced in at random places.
fn check_scene_text(splices: &[(usize, usize)], tag: &str) -> Result<(), TestCaseError> {
    let mut text = scene_text();
    for &(at, t) in splices {
        let mut at = at % (text.len() + 1);
        while !text.is_char_boundary(at) {
            at -= 1;
        }
        text.insert_str(at, TOKENS[t % TOKENS.len()]);
    }
    let d = dir(tag);
    let p = d.join("fuzzed.toml");
    std::fs::write(&p, &text).unwrap();
    load_names_file(&p, None)
}

/// A valid texture of `kind` (npy, png or exr) written to `path`.
fn texture(kind: &str, path: &Path) {
    let (n, vals) = (4usize, [0.2, 0.9, 0.5, 0.3]);
    match kind {
        "npy" => {
            let a = ndarray::Array2::from_shape_fn((n, n), |(i, j)| vals[(i + j) % 4]);
            ndarray_npy::write_npy(path, &a).unwrap();
        }
        "png" => {
            let data: Vec<u8> = (0..n * n).map(|k| (k * 13 % 256) as u8).collect();
            svkernel::jobs::output::write_png_bytes(path, n, false, &data).unwrap();
        }
        _ => {
            let mut img = svkernel::render::estimator::Image::zeros(n, 1);
            for (k, v) in img.mean.iter_mut().enumerate() {
                *v = vals[k % 4];
            }
            svkernel::jobs::output::write_exr(path, &img, "albedo").unwrap();
        }
    }
}

/// A scene over a mutated texture file of `kind`.
fn check_texture(
    kind: &str,
    e: &[(usize, u8)],
    keep: usize,
    tag: &str,
) -> Result<(), TestCaseError> {
    let d = dir(tag);
    let tex = d.join(format!("t.{kind}"));
    texture(kind, &tex);
    let bytes = std::fs::read(&tex).unwrap();
    // Keep the whole file most of the time: a mutated header is one case,
    // mutated data another.
    let keep = if keep.is_multiple_of(4) {
        keep
    } else {
        bytes.len()
    };
    std::fs::write(&tex, mutate(&bytes, e, keep)).unwrap();
    let transfer = if kind == "png" {
        ", transfer = \"linear\""
    } else {
        ""
    };
    let scene = d.join("s.toml");
    std::fs::write(
        &scene,
        format!(
            "texel = 0.5\nalbedo = {{ file = \"t.{kind}\"{transfer} }}\n[light]\nradius = 1.0\n\
             [image]\nresolution = 4\nhalf_width = 1.0\n"
        ),
    )
    .unwrap();
    load_names_file(&scene, Some(&tex))
}

/// A mutated shipped model or a mutated reference tally through its loader.
fn check_json_file(
    which: usize,
    e: &[(usize, u8)],
    keep: usize,
    tag: &str,
) -> Result<(), TestCaseError> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (src, name) = [
        ("data/profiles/basis.json", "basis.json"),
        ("data/profiles/metamodel.json", "metamodel.json"),
    ][which % 2];
    let bytes = std::fs::read(root.join(src)).unwrap();
    let keep = if keep.is_multiple_of(4) {
        keep
    } else {
        bytes.len()
    };
    let d = dir(tag);
    let p = d.join(name);
    std::fs::write(&p, mutate(&bytes, e, keep)).unwrap();
    let r = if which.is_multiple_of(2) {
        svkernel::metamodel::basis::BasisModel::load(&p).map(|_| ())
    } else {
        svkernel::metamodel::meta::MetaModelFile::load(&p).map(|_| ())
    };
    if let Err(err) = r {
        prop_assert!(err.to_string().contains(name), "{err}");
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn scene_text_never_panics(s in prop::collection::vec((any::<usize>(), any::<usize>()), 1..6)) {
        check_scene_text(&s, "scene")?;
    }

    #[test]
    fn textures_never_panic(kind in 0usize..3, e in edits(), keep in any::<usize>()) {
        check_texture(["npy", "png", "exr"][kind], &e, keep, "tex")?;
    }

    #[test]
    fn model_files_never_panic(which in 0usize..2, e in edits(), keep in any::<usize>()) {
        check_json_file(which, &e, keep, "json")?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    #[ignore = "slow tier: cargo test --release --test fuzz -- --ignored"]
    fn slow_scene_text_never_panics(s in prop::collection::vec((any::<usize>(), any::<usize>()), 1..10)) {
        check_scene_text(&s, "slow-scene")?;
    }

    #[test]
    #[ignore = "slow tier: cargo test --release --test fuzz -- --ignored"]
    fn slow_textures_never_panic(kind in 0usize..3, e in edits(), keep in any::<usize>()) {
        check_texture(["npy", "png", "exr"][kind], &e, keep, "slow-tex")?;
    }

    #[test]
    #[ignore = "slow tier: cargo test --release --test fuzz -- --ignored"]
    fn slow_model_files_never_panic(which in 0usize..2, e in edits(), keep in any::<usize>()) {
        check_json_file(which, &e, keep, "slow-json")?;
    }
}
