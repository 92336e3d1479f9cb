//! `svkernel design` end to end: the files it writes (and only when the
//! design is complete), its validation by brute force, and bad input
//! refused by name.

mod common;

use std::path::{Path, PathBuf};
use svkernel::design::Settings;
use svkernel::design::appearance::Quadrature;
use svkernel::jobs::design::{DesignOptions, run};
use svkernel::jobs::shipped::Models;

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("svk-design-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A 24 × 20 target (τ = 0.2 MFP): a soft bright disk on a darker ground.
fn target(path: &Path) {
    let (nx, ny) = (24, 20);
    let t = ndarray::Array2::from_shape_fn((ny, nx), |(i, j)| {
        let (x, y) = (j as f64 - 11.5, i as f64 - 9.5);
        0.08 + 0.15 * (-(x * x + y * y) / 30.0).exp()
    });
    ndarray_npy::write_npy(path, &t).unwrap();
}

fn options(target: PathBuf, out: PathBuf, validate: Option<u64>) -> DesignOptions {
    DesignOptions {
        target,
        out,
        settings: Settings {
            texel: 0.2,
            warm_start: 5,
            iterations: 6,
            quadrature: Quadrature {
                rings: 6,
                angles: 2,
            },
            ..Settings::default()
        },
        validate,
        validate_resolution: 12,
        calibrate: None,
        seed: 3,
        models: Models::builtin().unwrap(),
        progress: false,
    }
}

#[test]
fn design_writes_its_files_and_validates_by_brute_force() {
    let d = dir("run");
    let t = d.join("target.npy");
    target(&t);
    let out = d.join("out");
    let doc = run(&options(t, out.clone(), Some(200_000))).unwrap();
    for f in [
        "albedo.npy",
        "albedo.png",
        "naive.npy",
        "predicted.npy",
        "design.json",
        "report.html",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // Nothing of the work in progress is left behind.
    assert!(!d.join(".out.partial").exists());
    let albedo: ndarray::Array2<f64> = ndarray_npy::read_npy(out.join("albedo.npy")).unwrap();
    assert_eq!(albedo.shape(), &[20, 24]);
    assert!(albedo.iter().all(|a| (0.2..=0.99).contains(a)));
    assert!(doc.model_designed_rel_rmse < doc.model_naive_rel_rmse);
    let v = doc.validation.expect("validated");
    assert_eq!(v.rows.len(), 3);
    assert!(v.naive.rel_rmse.is_finite() && v.naive.delta_e00 >= 0.0);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("design.json")).unwrap()).unwrap();
    assert_eq!(json["format"], "svkernel-design");
    assert!(json["history"].as_array().unwrap().len() >= 5);
}

#[test]
fn a_calibrated_design_asks_the_model_for_its_measured_bias() {
    let d = dir("calibrate");
    let t = d.join("target.npy");
    target(&t);
    let out = d.join("out");
    let mut opts = options(t.clone(), out.clone(), None);
    opts.calibrate = Some(4_000_000);
    let doc = run(&opts).unwrap();
    let c = doc.calibration.expect("calibrated");
    let table = &c.channels[0];
    assert!(!table.ratio.is_empty());
    assert!(table.albedo.windows(2).all(|w| w[0] < w[1]));
    // The model's bias on a soft target is a few per cent up to α ≈ 0.92
    // and grows towards α = 1: on this 4 × 4.8 MFP target the reference is
    // 0.80× the model at α ≈ 0.987 (4e7 paths), so a ratio outside
    // [0.7, 1.3] means the table is wrong, not the model.
    assert!(
        table.ratio.iter().all(|r| (0.7..1.3).contains(r)),
        "{table:?}"
    );
    assert!(
        table.ratio[..4].iter().all(|r| (0.93..1.07).contains(r)),
        "{table:?}"
    );
    // The design ran twice: once for the target, once for the corrected one.
    let uncalibrated = run(&options(t, d.join("plain"), None)).unwrap();
    assert_eq!(doc.shape, uncalibrated.shape);
    assert!(doc.evaluations > uncalibrated.evaluations);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("design.json")).unwrap()).unwrap();
    assert_eq!(json["calibration"]["paths"], 4_000_000);
    assert!(!d.join(".out.partial").exists());
}

#[test]
fn bad_targets_are_refused_naming_the_file() {
    let d = dir("bad");
    // Out of [0, 1].
    let t = d.join("hot.npy");
    ndarray_npy::write_npy(&t, &ndarray::Array2::from_elem((4, 4), 1.5)).unwrap();
    let e = run(&options(t, d.join("out"), None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("hot.npy") && e.contains("[0, 1]"), "{e}");
    // Missing, and of an unknown kind.
    let e = run(&options(d.join("gone.npy"), d.join("out"), None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("gone.npy"), "{e}");
    let txt = d.join("target.txt");
    std::fs::write(&txt, "0.5").unwrap();
    let e = run(&options(txt, d.join("out"), None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("target.txt") && e.contains(".png"), "{e}");
    assert!(!d.join("out").exists(), "no output for a refused target");
}

/// `design --export-check` from the command line, with the paired options
/// written as the help shows them (`LO,HI`, `RINGS,ANGLES`): the problem's
/// definition and the model's M and gradient, one per texel, and no design.
#[test]
fn export_check_writes_the_problem_from_the_command_line() {
    let d = dir("export");
    let t = d.join("target.npy");
    target(&t);
    let file = d.join("problem.json");
    let o = common::bin()
        .args([
            "design",
            t.to_str().unwrap(),
            "--export-check",
            file.to_str().unwrap(),
        ])
        .args([
            "--texel",
            "0.2",
            "--albedo-range",
            "0.3,0.95",
            "--quadrature",
            "5,3",
        ])
        .args(["--illumination", "disk:1.5"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let p: serde_json::Value = serde_json::from_slice(&std::fs::read(&file).unwrap()).unwrap();
    assert_eq!(p["format"], "svkernel.design-check");
    assert_eq!((p["nx"].as_u64(), p["ny"].as_u64()), (Some(24), Some(20)));
    assert_eq!(p["offsets"].as_array().unwrap().len(), 15);
    assert_eq!(p["illumination"]["radius"], 1.5);
    let alpha: Vec<f64> = serde_json::from_value(p["alpha"].clone()).unwrap();
    assert!(
        alpha.iter().all(|a| (0.3..=0.95).contains(a)),
        "naive map within the range"
    );
    for key in ["m", "gradient", "g"] {
        assert_eq!(p[key].as_array().unwrap().len(), 24 * 20, "{key}");
    }
    assert!(!p["reads_all"].as_array().unwrap().is_empty());
    // A malformed pair is refused naming the option.
    let o = common::bin()
        .args([
            "design",
            t.to_str().unwrap(),
            "--export-check",
            file.to_str().unwrap(),
        ])
        .args(["--albedo-range", "0.3"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--albedo-range"),
        "{err}"
    );
}
