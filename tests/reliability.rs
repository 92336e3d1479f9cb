//! Reliability sweep through the CLI: bad and extreme inputs
//! give a clear error naming the file and the key, a non-zero exit, no
//! panic, and no output left behind.

use std::path::{Path, PathBuf};

mod common;
use common::bin;

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("svk-reliability-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `args`, expects failure without a panic, every needle in stderr,
/// and `out` not created. The exit code is 1, or 2 for a value the
/// command line itself refuses (clap's usage errors, which list the
/// accepted values).
fn fails(args: &[&str], needles: &[&str], out: &Path) {
    let o = bin().args(args).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{args:?} succeeded");
    let usage = err.starts_with("error: invalid value");
    let want = if usage { 2 } else { 1 };
    assert_eq!(o.status.code(), Some(want), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
    // Worded for the user: no Rust debug text, no serde type names.
    for debug in ["Some(", "None", "RawMap", "RawScene", "expected struct"] {
        assert!(!err.contains(debug), "{args:?}: '{debug}' in: {err}");
    }
    for n in needles {
        assert!(err.contains(n), "{args:?}: '{n}' not in: {err}");
    }
    assert!(!out.exists(), "{args:?} left {}", out.display());
}

#[test]
fn bad_scenes_fail_cleanly_through_the_cli() {
    let d = tmpdir("scenes");
    let out = d.join("out");
    let o = out.to_str().unwrap();
    let npy = |name: &str, v: f64, shape: (usize, usize)| {
        let arr = ndarray::Array2::from_elem(shape, v);
        svkernel::jobs::store::write_npy_atomic(&d.join(name), &arr).unwrap();
    };
    npy("nan.npy", f64::NAN, (3, 3));
    npy("neg.npy", -0.5, (3, 3));
    npy("over.npy", 1.5, (3, 3));
    npy("e0.npy", 0.5, (0, 3));
    std::fs::write(d.join("junk.npy"), b"\x93NUMPY garbage").unwrap();
    std::fs::write(d.join("junk.exr"), b"not an exr").unwrap();
    std::fs::write(d.join("junk.png"), b"not a png").unwrap();
    let cases: &[(&str, &str, &[&str])] = &[
        (
            "malformed",
            "albedo = { constant = 0.5\n",
            &["malformed.toml", "line"],
        ),
        (
            "unknown-key",
            "albedo = { constant = 0.5 }\ncolour = 1\n",
            &["unknown-key.toml", "colour"],
        ),
        (
            "unknown-map-key",
            "albedo = { constant = 0.5, sheen = 1 }\n",
            &["unknown-map-key.toml", "sheen"],
        ),
        // (File stems that do not contain the key the error must name.)
        ("no-a", "texel = 0.1\n", &["no-a.toml", "albedo"]),
        (
            "missing-file",
            "albedo = { file = \"nope.npy\" }\n",
            &["nope.npy"],
        ),
        (
            "nan",
            "albedo = { file = \"nan.npy\" }\n",
            &["nan.toml", "albedo"],
        ),
        (
            "negative",
            "albedo = { file = \"neg.npy\" }\n",
            &["negative.toml", "albedo"],
        ),
        (
            "over",
            "albedo = { file = \"over.npy\" }\n",
            &["over.toml", "albedo"],
        ),
        (
            "e-map",
            "albedo = { file = \"e0.npy\" }\n",
            &["e-map.toml", "albedo.file", "e0.npy", "shape"],
        ),
        (
            "junk-npy",
            "albedo = { file = \"junk.npy\" }\n",
            &["junk.npy"],
        ),
        (
            "junk-exr",
            "albedo = { file = \"junk.exr\" }\n",
            &["junk.exr"],
        ),
        (
            "junk-png",
            "albedo = { file = \"junk.png\", transfer = \"srgb\" }\n",
            &["junk.png"],
        ),
        (
            "png-no-transfer",
            "albedo = { file = \"junk.png\" }\n",
            &["png-no-transfer.toml", "albedo.transfer", "srgb"],
        ),
        (
            "png-transfer",
            "albedo = { file = \"junk.png\", transfer = \"gamma\" }\n",
            &["png-transfer.toml", "albedo.transfer", "'gamma'"],
        ),
        (
            "string-map",
            "albedo = \"white\"\n",
            &["string-map.toml", "line 1", "a number"],
        ),
        (
            "zero-image",
            "albedo = { constant = 0.5 }\n[image]\nresolution = 0\n",
            &["zero-image.toml", "image.resolution"],
        ),
        (
            "t0",
            "texel = 0.0\nalbedo = { constant = 0.5 }\n",
            &["t0.toml", "texel"],
        ),
        (
            "rho0",
            "albedo = { constant = 0.5 }\ndensity = { constant = 0.0 }\n",
            &["rho0.toml", "density"],
        ),
        (
            "eta",
            "albedo = { constant = 0.5 }\nmedium = { eta = 0.5 }\n",
            &["eta.toml", "medium.eta"],
        ),
        (
            "light-kind",
            "albedo = { constant = 0.5 }\n[light]\nkind = \"laser\"\n",
            &["light-kind.toml", "light.kind"],
        ),
        (
            "method",
            "albedo = { constant = 0.5 }\nmethods = [\"magic\"]\n",
            &["method.toml", "methods"],
        ),
    ];
    for (name, text, needles) in cases {
        let p = d.join(format!("{name}.toml"));
        std::fs::write(&p, text).unwrap();
        fails(&["render", p.to_str().unwrap(), "--out", o], needles, &out);
    }
    fails(
        &[
            "render",
            d.join("absent.toml").to_str().unwrap(),
            "--out",
            o,
        ],
        &["absent.toml"],
        &out,
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn corrupted_models_and_tallies_fail_cleanly() {
    let d = tmpdir("models");
    let out = d.join("out");
    let o = out.to_str().unwrap();
    let scene = d.join("s.toml");
    std::fs::write(
        &scene,
        "albedo = { constant = 0.5 }\n[image]\nresolution = 4\n",
    )
    .unwrap();
    let s = scene.to_str().unwrap();
    // Truncated and wrong-format model files, named.
    let basis = std::fs::read_to_string("data/profiles/basis.json").unwrap();
    std::fs::write(d.join("basis_cut.json"), &basis[..basis.len() / 2]).unwrap();
    let meta = std::fs::read_to_string("data/profiles/metamodel.json").unwrap();
    std::fs::write(d.join("meta_cut.json"), &meta[..meta.len() / 3]).unwrap();
    let bc = d.join("basis_cut.json");
    let mc = d.join("meta_cut.json");
    fails(
        &[
            "render",
            s,
            "--method",
            "point",
            "--basis",
            bc.to_str().unwrap(),
            "--out",
            o,
        ],
        &["basis_cut.json"],
        &out,
    );
    fails(
        &[
            "render",
            s,
            "--method",
            "learned",
            "--model",
            mc.to_str().unwrap(),
            "--out",
            o,
        ],
        &["meta_cut.json"],
        &out,
    );
    fails(
        &[
            "render",
            s,
            "--method",
            "point",
            "--basis",
            "data/profiles/metamodel.json",
            "--out",
            o,
        ],
        &["metamodel.json"],
        &out,
    );
    // A diffuse light with the collimated basis: refused, naming the key.
    let diffuse = d.join("d.toml");
    std::fs::write(
        &diffuse,
        "albedo = { constant = 0.5 }\n[light]\nkind = \"diffuse\"\n",
    )
    .unwrap();
    fails(
        &[
            "render",
            diffuse.to_str().unwrap(),
            "--method",
            "point",
            "--basis-diffuse",
            "data/profiles/basis.json",
            "--out",
            o,
        ],
        &["basis.json", "incidence"],
        &out,
    );
    // A corrupted reference tally.
    std::fs::write(
        d.join("tally.json"),
        "{\"format\": \"svkernel.reference\", \"version\": 1, \"key\":",
    )
    .unwrap();
    let t = d.join("tally.json");
    fails(
        &[
            "render",
            s,
            "--method",
            "reference",
            "--reference-tally",
            t.to_str().unwrap(),
            "--out",
            o,
        ],
        &["tally.json"],
        &out,
    );
    fails(
        &[
            "merge",
            t.to_str().unwrap(),
            "--out",
            d.join("m.json").to_str().unwrap(),
        ],
        &["tally.json"],
        &d.join("m.json"),
    );
    // Bad flags.
    fails(
        &["render", s, "--sampling", "random", "--out", o],
        &["--sampling"],
        &out,
    );
    fails(
        &["render", s, "--resolution", "0", "--out", o],
        &["--resolution"],
        &out,
    );
    fails(
        &["render", s, "--shard", "3/3", "--out", o],
        &["--shard"],
        &out,
    );
    fails(
        &["compare", s, "--spp-list", "0", "--out", o],
        &["budgets"],
        &out,
    );
    std::fs::remove_dir_all(&d).unwrap();
}

/// A document of the wrong kind is named by its `format` tag (both the
/// kind found and the kind expected), not by the first field it lacks; a
/// JSON file that is no svkernel document says so.
#[test]
fn documents_of_the_wrong_kind_are_named_by_their_format() {
    let d = tmpdir("kinds");
    let out = d.join("out");
    let o = out.to_str().unwrap();
    let scene = d.join("s.toml");
    std::fs::write(&scene, "albedo = 0.5\n[image]\nresolution = 4\n").unwrap();
    let s = scene.to_str().unwrap();
    let kernels = "data/kernels/eta1.5_g0.3_pencil.json";
    let (basis, meta) = ("data/profiles/basis.json", "data/profiles/metamodel.json");
    std::fs::write(d.join("other.json"), "{\"type\": \"FeatureCollection\"}").unwrap();
    let other = d.join("other.json");
    let other = other.to_str().unwrap();
    let none = d.join("none");
    let cases: &[(&[&str], &[&str])] = &[
        (
            &["kernel", "--d", "1", "--albedo", "0.5", "--model", kernels],
            &[
                "eta1.5_g0.3_pencil.json",
                "`svkernel.kernels`",
                "kernel tally",
                "`svkernel.metamodel`",
                "kernel meta-model",
            ],
        ),
        (
            &["profile", "--albedo", "0.5", "--model", meta],
            &["metamodel.json", "`svkernel.metamodel`", "`svkernel.basis`"],
        ),
        (
            &[
                "render", s, "--method", "learned", "--model", basis, "--out", o,
            ],
            &["basis.json", "`svkernel.basis`", "`svkernel.metamodel`"],
        ),
        (
            &[
                "render", s, "--method", "point", "--basis", kernels, "--out", o,
            ],
            &["`svkernel.kernels`", "`svkernel.basis`"],
        ),
        (
            &[
                "render",
                s,
                "--method",
                "reference",
                "--reference-tally",
                meta,
                "--out",
                o,
            ],
            &[
                "metamodel.json",
                "`svkernel.metamodel`",
                "`svkernel.reference`",
            ],
        ),
        (
            &["kernel", "--d", "1", "--albedo", "0.5", "--model", other],
            &[
                "other.json",
                "not an svkernel document",
                "`svkernel.metamodel`",
            ],
        ),
        (
            &["merge", other, "--out", none.to_str().unwrap()],
            &["other.json", "not an svkernel document"],
        ),
        (
            &["merge", basis, "--out", none.to_str().unwrap()],
            &["basis.json", "`svkernel.basis`", "`svkernel.profile`"],
        ),
    ];
    for (args, needles) in cases {
        let target = if args.contains(&"merge") { &none } else { &out };
        fails(args, needles, target);
        let err = String::from_utf8_lossy(&bin().args(*args).output().unwrap().stderr).into_owned();
        assert!(!err.contains("missing field"), "{args:?}: {err}");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// The library names a parameter (`albedo`); the CLI names the flag that
/// set it (`--albedo`), and a scene's value is named by the scene file and
/// key (`medium.eta`), never by a flag the user did not type.
#[test]
fn parameter_errors_name_the_flag_or_the_scene_key() {
    let d = tmpdir("params");
    let out = d.join("out.json");
    let o = out.to_str().unwrap();
    let sim = |extra: &[&str]| -> Vec<String> {
        let mut v: Vec<String> = ["simulate", "profile", "--albedo", "0.5", "--paths", "100"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        v.extend(extra.iter().map(|s| s.to_string()));
        v.extend(["--out".into(), o.into()]);
        v
    };
    let scene = d.join("s.toml");
    std::fs::write(&scene, "albedo = 0.5\n[image]\nresolution = 4\n").unwrap();
    let s = scene.to_str().unwrap().to_string();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            ["profile", "--albedo", "2"].map(String::from).to_vec(),
            "--albedo",
        ),
        (
            ["simulate", "profile", "--albedo", "2", "--out", o]
                .map(String::from)
                .to_vec(),
            "--albedo",
        ),
        (sim(&["--eta", "0.5"]), "--eta"),
        (sim(&["--g", "1"]), "--g"),
        (sim(&["--density", "0"]), "--density"),
        (sim(&["--thickness", "-1"]), "--thickness"),
        (sim(&["--source", "laser"]), "--source"),
        (sim(&["--max-events", "0"]), "--max-events"),
        (sim(&["--shard", "2/2"]), "--shard"),
        (
            ["simulate", "kernels", "--albedos", "0.5,1.2", "--out", o]
                .map(String::from)
                .to_vec(),
            "--albedos",
        ),
        (
            ["simulate", "kernels", "--rel-width", "2", "--out", o]
                .map(String::from)
                .to_vec(),
            "--rel-width",
        ),
        (
            [
                "kernel",
                "--d",
                "1",
                "--albedo",
                "0.5",
                "--vertices",
                "middle",
            ]
            .map(String::from)
            .to_vec(),
            "--vertices",
        ),
        (
            ["fit", "density-step", "--albedos", "1.5"]
                .map(String::from)
                .to_vec(),
            "--albedos",
        ),
        (
            vec![
                "render".into(),
                s.clone(),
                "--method".into(),
                "magic".into(),
                "--out".into(),
                d.join("r").to_str().unwrap().into(),
            ],
            "--method",
        ),
    ];
    for (args, flag) in &cases {
        let args: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        // A closed set or a range is checked by the command line itself,
        // which names the flag and the values it takes.
        let needle = if ["--vertices", "--method"].contains(flag) {
            format!("for '{flag} <")
        } else {
            format!("invalid {flag} = ")
        };
        fails(&args, &[&needle], &out);
        let err = String::from_utf8_lossy(&bin().args(&args).output().unwrap().stderr).into_owned();
        assert!(!err.contains("Some(") && !err.contains("None"), "{err}");
    }
    // From a scene: the scene file and its key, not the flag.
    for (text, key) in [
        ("albedo = 0.5\n[medium]\neta = 0.5\n", "medium.eta"),
        ("albedo = 0.5\nmedium = { g = 1.0 }\n", "medium.g"),
    ] {
        let p = d.join("medium.toml");
        std::fs::write(&p, text).unwrap();
        let r = d.join("r");
        let o = bin()
            .args(["render", p.to_str().unwrap(), "--out", r.to_str().unwrap()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && !r.exists(), "{err}");
        assert!(
            err.contains("medium.toml") && err.contains(key),
            "{key}: {err}"
        );
        assert!(
            !err.contains("--eta") && !err.contains("--g "),
            "{key}: {err}"
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}
