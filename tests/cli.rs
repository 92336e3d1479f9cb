//! The command line as a user drives it: clear errors with non-zero exit and
//! no output left behind; `1e7` notation; shard + merge; resume after kill -9.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::bin;
use svkernel::forward::kernel::{KernelDoc, VertexClass};

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("svk-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// Writes an 8 × 8-pixel scene (τ = 0.25, light radius 1, half-width 2)
/// with a two-valued albedo `pattern` of size 0.5 under `size_key` plus
/// `extra` TOML lines; returns its path.
fn small_scene(
    path: &Path,
    pattern: &str,
    values: [f64; 2],
    size_key: &str,
    extra: &str,
) -> PathBuf {
    std::fs::write(
        path,
        format!(
            "texel = 0.25\nalbedo = {{ pattern = \"{pattern}\", values = [{}, {}], {size_key} = 0.5 }}\n\
             {extra}\n[light]\nradius = 1.0\n[image]\nresolution = 8\nhalf_width = 2.0\n",
            values[0], values[1]
        ),
    )
    .unwrap();
    path.to_path_buf()
}

/// Runs `svkernel ARGS --checkpoint-every 0 --out OUT`, waits (≤ 120 s)
/// until `ckpt` exists, kills it with SIGKILL and asserts the checkpoint
/// was written.
fn kill_after_checkpoint(args: &[&str], out: &Path, ckpt: &Path) {
    let mut child = bin()
        .args(args)
        .args(["--checkpoint-every", "0", "--out"])
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !ckpt.exists() && t0.elapsed() < Duration::from_secs(120) {
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    assert!(ckpt.exists(), "no checkpoint was written");
}

/// `svkernel merge PARTS --out OUT`, which must succeed.
fn merge_ok(parts: &[PathBuf], out: &Path) {
    let o = bin()
        .arg("merge")
        .args(parts)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

fn profile(args: &[&str], out: &Path) -> std::process::Output {
    bin()
        .args(["simulate", "profile"])
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn out_of_domain_parameters_fail_cleanly() {
    let d = tmpdir("domain");
    let out = d.join("x.json");
    for (args, flag) in [
        (vec!["--albedo", "1.5"], "--albedo"),
        (vec!["--albedo", "0.5", "--g", "1"], "--g"),
        (vec!["--albedo", "0.5", "--eta", "0.5"], "--eta"),
        (vec!["--albedo", "0.5", "--density", "-1"], "--density"),
        (vec!["--albedo", "0.5", "--source", "laser"], "--source"),
        (vec!["--albedo", "0.5", "--shard", "3/3"], "--shard"),
        (vec!["--albedo", "0.5", "--paths", "1.5"], "--paths"),
        (vec!["--albedo", "0.5", "--thickness", "0"], "--thickness"),
    ] {
        let o = profile(&args, &out);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?}");
        assert!(err.contains(flag), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert_eq!(
            std::fs::read_dir(&d).unwrap().count(),
            0,
            "{args:?} left a file"
        );
    }
}

#[test]
fn scientific_path_counts_and_output_contract() {
    let d = tmpdir("contract");
    let out = d.join("p.json");
    let o = profile(&["--albedo", "0.8", "--paths", "2e4", "--npy"], &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v = json(&out);
    assert_eq!(v["paths"], 20000);
    for key in [
        "R_d",
        "R_d_stderr",
        "R_1",
        "R_1_stderr",
        "R_m",
        "R_m_stderr",
        "wall_s",
    ] {
        assert!(v[key].as_f64().is_some_and(f64::is_finite), "{key}");
    }
    assert!(v["events"].as_u64().unwrap() > 20000);
    let prov = &v["provenance"];
    assert!(prov["command_line"].as_array().unwrap().len() > 3);
    assert!(prov["threads"].as_u64().unwrap() >= 1);
    assert_eq!(v["config"]["seed"], 1);
    // The .npy sidecar is a real npy file: magic, then a float64 header.
    let npy = std::fs::read(out.with_extension("npy")).unwrap();
    assert_eq!(&npy[..6], b"\x93NUMPY");
    assert!(String::from_utf8_lossy(&npy[..128]).contains("<f8"));
    // No checkpoint left behind after success.
    assert!(!d.join("p.json.ckpt").exists());
}

#[test]
fn shards_merge_to_the_unsharded_result() {
    let d = tmpdir("shards");
    let common = [
        "--albedo",
        "0.9",
        "--paths",
        "1e5",
        "--source",
        "diffuse:2",
        "--seed",
        "7",
    ];
    let full = d.join("full.json");
    assert!(profile(&common, &full).status.success());
    let mut parts = Vec::new();
    for k in 0..3 {
        let p = d.join(format!("s{k}.json"));
        let mut args = common.to_vec();
        let shard = format!("{k}/3");
        args.extend(["--shard", shard.as_str()]);
        assert!(profile(&args, &p).status.success());
        parts.push(p);
    }
    let merged = d.join("merged.json");
    merge_ok(&parts, &merged);
    let (a, b) = (json(&full), json(&merged));
    assert_eq!(a["tally"], b["tally"]);
    assert_eq!(a["bins"], b["bins"]);
    assert_eq!(a["R_d"], b["R_d"]);
    assert_eq!(b["shard"], serde_json::Value::Null);

    // A truncated input is refused with its name, and nothing is written.
    let bad = d.join("bad.json");
    let text = std::fs::read_to_string(&parts[0]).unwrap();
    std::fs::write(&bad, &text[..text.len() / 2]).unwrap();
    let out2 = d.join("merged2.json");
    let o = bin()
        .arg("merge")
        .arg(&bad)
        .arg(&parts[1])
        .arg("--out")
        .arg(&out2)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("bad.json"), "{err}");
    assert!(!out2.exists());
}

#[test]
fn resume_after_kill_is_bitwise_identical() {
    let d = tmpdir("resume");
    // Scalar engine at α = 0.99: a few seconds, many batches.
    let common = [
        "--albedo", "0.99", "--paths", "2e6", "--engine", "scalar", "--seed", "3",
    ];
    let reference = d.join("ref.json");
    assert!(profile(&common, &reference).status.success());

    let out = d.join("run.json");
    let ckpt = d.join("run.json.ckpt");
    let mut args = vec!["simulate", "profile"];
    args.extend(common);
    kill_after_checkpoint(&args, &out, &ckpt);
    assert!(!out.exists(), "the killed run must not leave an output");
    let o = bin()
        .args(["simulate", "profile"])
        .args(common)
        .args(["--resume", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (a, b) = (json(&reference), json(&out));
    assert_eq!(a["tally"], b["tally"]);
    assert_eq!(a["R_d"], b["R_d"]);
    assert!(!ckpt.exists());

    // A checkpoint of another simulation is refused by name.
    std::fs::write(&ckpt, std::fs::read(d.join("ref.json")).unwrap()).unwrap();
    let o = profile(&["--albedo", "0.5", "--paths", "1e4", "--resume"], &out);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("run.json.ckpt"));
}

#[test]
fn kernel_shards_merge_to_the_unsharded_result() {
    let d = tmpdir("kshards");
    let run = |extra: &[&str], out: &Path| {
        let o = bin()
            .args([
                "simulate",
                "kernels",
                "--albedos",
                "0.8,0.95",
                "--distances",
                "0.5,2",
            ])
            .args(["--paths", "6e4", "--seed", "5"])
            .args(extra)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let full = d.join("full.json");
    run(&[], &full);
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| {
            let p = d.join(format!("k{k}.json"));
            run(&["--shard", &format!("{k}/2")], &p);
            p
        })
        .collect();
    let merged = d.join("merged.json");
    merge_ok(&parts, &merged);
    let (a, b) = (json(&full), json(&merged));
    assert_eq!(a["tally"], b["tally"]);
    assert_eq!(a["summary"], b["summary"]);
    assert_eq!(b["shard"], serde_json::Value::Null);
    // Overlapping distance bins are refused, naming the flag, with no output.
    let bad = d.join("bad.json");
    let o = bin()
        .args(["simulate", "kernels", "--distances", "1,1.1", "--out"])
        .arg(&bad)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--distances"), "{err}");
    assert!(!bad.exists());
    // So is a tail that ends inside the core.
    let o = bin()
        .args(["simulate", "kernels", "--extent", "4", "--tail-bins", "4"])
        .args(["--tail-extent", "3", "--out"])
        .arg(&bad)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--tail-extent"),
        "{err}"
    );
    assert!(!bad.exists());
    // A tail's shards merge like the core's, and it holds vertices the core
    // does not: the all-vertex overflow shrinks, the other classes keep theirs.
    let core = d.join("core.json");
    run(&["--extent", "1"], &core);
    let tail = ["--extent", "1", "--tail-bins", "6", "--tail-extent", "16"];
    let tailed = d.join("tailed.json");
    run(&tail, &tailed);
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| {
            let p = d.join(format!("t{k}.json"));
            run(&[&tail[..], &["--shard", &format!("{k}/2")]].concat(), &p);
            p
        })
        .collect();
    merge_ok(&parts, &merged);
    let (t, m) = (json(&tailed), json(&merged));
    assert_eq!(t["tally"], m["tally"]);
    assert_eq!(t["config"]["grid"]["tail"]["bins"], 6);
    // The overflow's share of cell (α = 0.95, d = 0.5) as the fits read it.
    let (core, tailed) = (
        KernelDoc::load(&core).unwrap(),
        KernelDoc::load(&tailed).unwrap(),
    );
    let overflow = |doc: &KernelDoc, class: VertexClass| doc.histogram(1, 0, class).overflow;
    let (o_core, o_tail) = (
        overflow(&core, VertexClass::All),
        overflow(&tailed, VertexClass::All),
    );
    assert!(o_core > 0.05 && o_tail < 0.1 * o_core, "{o_core} {o_tail}");
    assert_eq!(
        overflow(&tailed, VertexClass::Last),
        overflow(&core, VertexClass::Last)
    );
}

/// `render`: the reference rendered in two shards, merged with `merge` and
/// fed back with `--reference-tally` gives bitwise the unsharded images;
/// bad input fails cleanly without an output directory.
#[test]
fn render_reference_shards_merge_and_bad_input() {
    let d = tmpdir("render");
    let scene = small_scene(&d.join("s.toml"), "checker", [0.3, 0.9], "cell", "");
    let render = |args: &[&str], out: &Path| {
        let o = bin()
            .arg("render")
            .arg(&scene)
            .args(args)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let common = ["--method", "reference", "--paths", "1e5"];
    render(&common, &d.join("full"));
    for k in 0..2 {
        let shard = format!("{k}/2");
        let mut args = common.to_vec();
        args.extend(["--shard", &shard]);
        render(&args, &d.join(format!("s{k}")));
    }
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| d.join(format!("s{k}/main/reference.tally.json")))
        .collect();
    merge_ok(&parts, &d.join("merged.json"));
    let merged = d.join("merged.json");
    let mut args = common.to_vec();
    args.extend(["--reference-tally", merged.to_str().unwrap()]);
    render(&args, &d.join("again"));
    let bytes = |p: PathBuf| std::fs::read(p).unwrap();
    for f in ["reference_mean.npy", "reference_stderr.npy"] {
        assert_eq!(
            bytes(d.join("full/main").join(f)),
            bytes(d.join("again/main").join(f)),
            "{f}"
        );
    }
    let doc = json(&d.join("full/render.json"));
    assert_eq!(doc["passes"][0]["methods"][0]["method"], "reference");
    // The same shard twice is refused, naming the file.
    let o = bin()
        .arg("merge")
        .args([&parts[0], &parts[0]])
        .arg("--out")
        .arg(d.join("bad.json"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !d.join("bad.json").exists());
    assert!(err.contains("reference.tally.json"), "{err}");
    // Refused, naming the file and the key, nothing written:
    let refused = |args: &[&str], needles: &[&str]| {
        let out = d.join("never");
        let o = bin().args(args).arg("--out").arg(&out).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?} succeeded");
        assert!(needles.iter().all(|n| err.contains(n)), "{err}");
        assert!(!out.exists());
    };
    let scene_s = scene.to_str().unwrap();
    let part0 = parts[0].to_str().unwrap();
    // one shard's tally where a whole reference is needed;
    refused(
        &["render", scene_s, "--method", "reference", "--paths", "1e5"]
            .into_iter()
            .chain(["--reference-tally", part0])
            .collect::<Vec<_>>(),
        &["s0", "chunks"],
    );
    // as many tallies as the scene has passes;
    let merged_s = merged.to_str().unwrap();
    refused(
        &["render", scene_s, "--method", "reference", "--paths", "1e5"]
            .into_iter()
            .chain(["--reference-tally", merged_s, "--reference-tally", merged_s])
            .collect::<Vec<_>>(),
        &["--reference-tally", "2 files for 1 passes"],
    );
    // a tally whose path count does not match its chunks (an edited or
    // mixed-up file);
    let mut doc = json(&parts[1]);
    doc["tally"]["paths"] = (doc["tally"]["paths"].as_u64().unwrap() + 1).into();
    let forged = d.join("forged.json");
    std::fs::write(&forged, doc.to_string()).unwrap();
    refused(
        &["merge", part0, forged.to_str().unwrap()],
        &["forged.json", "tally.paths"],
    );
    // a shard without chunks (1e5 paths make 7 chunks of 16384).
    refused(
        &["render", scene_s, "--method", "reference", "--paths", "1e5"]
            .into_iter()
            .chain(["--shard", "0/10"])
            .collect::<Vec<_>>(),
        &["--shard", "0/10"],
    );
    // Unknown method and a malformed scene: non-zero, named, nothing written.
    for (args, needle) in [
        (vec!["--method", "pointy"], "--method"),
        (vec!["--spp", "0"], "--spp"),
        // One sample per pixel has no standard error.
        (vec!["--spp", "1"], "--spp"),
        (vec!["--spp", "3", "--sampling", "mis"], "--spp"),
    ] {
        let out = d.join("never");
        let o = bin()
            .arg("render")
            .arg(&scene)
            .args(&args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(needle), "{err}");
        assert!(!out.exists());
    }
    std::fs::write(
        &scene,
        "texel = 0.25\nalbedo = { constant = 0.5 }\n[light]\nradius = -1.0\n",
    )
    .unwrap();
    let o = bin()
        .arg("render")
        .arg(&scene)
        .arg("--out")
        .arg(d.join("never"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("s.toml") && err.contains("light.radius"),
        "{err}"
    );
    assert!(!d.join("never").exists());
    std::fs::remove_dir_all(&d).unwrap();
}

/// The README's first command end to end (fewer profile paths): the
/// profile, the plots, the three demo scenes compared with every method,
/// and one self-contained HTML report.
#[test]
fn demo_runs_end_to_end() {
    let d = tmpdir("demo");
    let o = bin()
        .args(["demo", "--paths", "2e5", "--out"])
        .arg(&d)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(d.join("profile.png").exists() && d.join("profile.json").exists());
    for scene in ["stripes", "checker", "marble"] {
        assert!(d.join(scene).join("main/row.png").exists(), "{scene}");
        let doc = json(&d.join(scene).join("render.json"));
        let methods = doc["passes"][0]["methods"].as_array().unwrap();
        assert_eq!(methods.len(), 7);
        for m in &methods[1..] {
            let e = m["metrics"]["rel_rmse"].as_f64().unwrap();
            assert!(e.is_finite() && e >= 0.0, "{scene}: {m}");
        }
        assert!(
            stdout.contains(&format!("scene {scene}, pass main")),
            "{stdout}"
        );
        let c = json(&d.join(scene).join("compare.json"));
        assert_eq!(c["curves"]["speedups"].as_array().unwrap().len(), 6);
    }
    let html = std::fs::read_to_string(d.join("index.html")).unwrap();
    // Self-contained: every image inline, none linked.
    let imgs = html.matches("<img ").count();
    assert!(imgs >= 3 * 14 + 2, "{imgs} images");
    assert_eq!(html.matches("src=\"data:image/").count(), imgs);
    assert!(html.contains("What accuracy costs in time") && html.contains("learned"));
    let md = std::fs::read_to_string(d.join("index.md")).unwrap();
    assert!(md.contains("](stripes/main/learned.png)"), "{md}");
    std::fs::remove_dir_all(&d).unwrap();
}

/// `compare`: metrics, report and the error-vs-time curves of a small
/// scene; the reference's error falls with its budget, and every model
/// method has a curve.
#[test]
fn compare_writes_metrics_curves_and_report() {
    let d = tmpdir("compare");
    let scene = small_scene(
        &d.join("s.toml"),
        "stripes",
        [0.3, 0.95],
        "width",
        "methods = [\"point\", \"learned\"]",
    );
    let o = bin()
        .arg("compare")
        .arg(&scene)
        .args([
            "--truth-paths",
            "2e6",
            "--spp-list",
            "4,64",
            "--paths-list",
            "1e4,1e6",
            "--out",
        ])
        .arg(&d)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let doc = json(&d.join("compare.json"));
    let curves = doc["curves"]["curves"].as_array().unwrap();
    let names: Vec<&str> = curves
        .iter()
        .map(|c| c["method"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["reference", "point", "learned"]);
    let e = |c: usize, k: usize| curves[c]["points"][k]["rel_rmse"].as_f64().unwrap();
    assert!(
        e(0, 1) < e(0, 0),
        "reference error must fall with 100× the paths"
    );
    assert!(d.join("error_time.png").exists());
    let svg = std::fs::read_to_string(d.join("error_time.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("learned"));
    // The main render's metrics, per channel, and the report.
    let methods = doc["render"]["passes"][0]["methods"].as_array().unwrap();
    assert_eq!(methods.len(), 3);
    let learned = &methods[2]["metrics"];
    assert_eq!(learned["channels"].as_array().unwrap().len(), 1);
    assert_eq!(learned["channels"][0]["rel_bias"], learned["rel_bias"]);
    let skipped = doc["skipped"].as_array().unwrap();
    assert!(
        skipped.iter().any(|e| e == "density pyramid"),
        "{skipped:?}"
    );
    let html = std::fs::read_to_string(d.join("report.html")).unwrap();
    assert!(html.contains("<table>") && !html.contains("src=\"main/"));
    assert!(d.join("report.md").exists());
    // A scene without model methods: the reference curve has one point per
    // budget (an empty method list re-rendered the reference per spp).
    let d2 = d.join("refonly");
    let scene = small_scene(
        &d.join("r.toml"),
        "stripes",
        [0.3, 0.95],
        "width",
        "methods = []",
    );
    let o = bin()
        .arg("compare")
        .arg(&scene)
        .args([
            "--truth-paths",
            "1e5",
            "--spp-list",
            "4,16",
            "--paths-list",
            "1e4",
            "--out",
        ])
        .arg(&d2)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let doc = json(&d2.join("compare.json"));
    let curves = doc["curves"]["curves"].as_array().unwrap();
    assert_eq!(curves.len(), 1, "{curves:?}");
    assert_eq!(curves[0]["points"].as_array().unwrap().len(), 1);
    std::fs::remove_dir_all(&d).unwrap();
}

/// The cluster scripts (`tools/cluster/shard.sh` + `merge.sh`, the body of
/// the Slurm array and Kubernetes indexed jobs) run locally as 3 shards:
/// the merged profile and the merged reference tally equal the unsharded
/// results bitwise.
#[test]
fn cluster_scripts_shard_and_merge_like_one_run() {
    let d = tmpdir("cluster");
    let script = |name: &str, args: &[&str], out: &Path| {
        let o = Command::new("bash")
            .arg(
                Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("tools/cluster")
                    .join(name),
            )
            .args(args)
            .env("SVKERNEL", env!("CARGO_BIN_EXE_svkernel"))
            .env("OUT", out)
            .stdout(Stdio::null())
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    // Profiles.
    let common = ["--albedo", "0.8", "--paths", "1e5", "--seed", "3"];
    let full = d.join("full.json");
    assert!(profile(&common, &full).status.success());
    let out = d.join("profile");
    for k in 0..3 {
        let (k, n) = (k.to_string(), "3".to_string());
        let mut args = vec![k.as_str(), n.as_str(), "profile"];
        args.extend(common);
        script("shard.sh", &args, &out);
    }
    script("merge.sh", &["profile"], &out);
    let (a, b) = (json(&full), json(&out.join("merged.json")));
    assert_eq!(a["tally"], b["tally"]);
    assert_eq!(a["R_d"], b["R_d"]);
    // A reference render.
    let scene = small_scene(&d.join("s.toml"), "stripes", [0.3, 0.9], "width", "");
    let s = scene.to_str().unwrap();
    let out = d.join("reference");
    for k in 0..3 {
        let k = k.to_string();
        script(
            "shard.sh",
            &[&k, "3", "reference", s, "--paths", "1e5"],
            &out,
        );
    }
    script("merge.sh", &["reference"], &out);
    let o = bin()
        .args([
            "render",
            s,
            "--method",
            "reference",
            "--paths",
            "1e5",
            "--out",
        ])
        .arg(d.join("full_ref"))
        .output()
        .unwrap();
    assert!(o.status.success());
    let (a, b) = (
        json(&d.join("full_ref/main/reference.tally.json")),
        json(&out.join("merged.json")),
    );
    assert_eq!(a["tally"], b["tally"]);
    assert_eq!(a["key"], b["key"]);
    std::fs::remove_dir_all(&d).unwrap();
}

/// A homogeneous material outside the meta-model's albedo range: every
/// method is the profile, so no kernel extension is simulated (it was: 5e7
/// paths and a fit, unused).
#[test]
fn a_homogeneous_scene_simulates_no_kernel_extension() {
    let d = tmpdir("homog");
    let scene = d.join("s.toml");
    std::fs::write(
        &scene,
        "texel = 0.25\nalbedo = { constant = 0.1 }\nmethods = [\"learned\"]\n\
         [light]\nradius = 1.0\n[image]\nresolution = 4\nhalf_width = 2.0\n",
    )
    .unwrap();
    let cache = d.join("cache");
    let o = bin()
        .arg("render")
        .arg(&scene)
        .args(["--method", "learned", "--spp", "4", "--cache"])
        .arg(&cache)
        .arg("--out")
        .arg(d.join("out"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cached = std::fs::read_dir(&cache).map_or(0, |r| r.count());
    assert_eq!(cached, 0, "a kernel extension was simulated");
    std::fs::remove_dir_all(&d).unwrap();
}

/// A reference render killed with SIGKILL after a checkpoint and resumed
/// gives bitwise the uninterrupted tally; the killed run leaves no images.
#[test]
fn render_resume_after_kill_is_bitwise_identical() {
    let d = tmpdir("render-resume");
    let scene = small_scene(&d.join("s.toml"), "stripes", [0.9, 0.99], "width", "");
    let s = scene.to_str().unwrap();
    let common = ["render", s, "--method", "reference", "--paths", "3e6"];
    let o = bin()
        .args(common)
        .arg("--out")
        .arg(d.join("full"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = d.join("run");
    let ckpt = out.join("reference.main.ckpt");
    kill_after_checkpoint(&common, &out, &ckpt);
    assert!(!out.join("render.json").exists() && !out.join("main/reference.exr").exists());
    let o = bin()
        .args(common)
        .args(["--resume", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (a, b) = (
        json(&d.join("full/main/reference.tally.json")),
        json(&out.join("main/reference.tally.json")),
    );
    assert_eq!(a["tally"], b["tally"]);
    assert!(!ckpt.exists());
    std::fs::remove_dir_all(&d).unwrap();
}

/// Albedos below the meta-model's trained range: the first render
/// simulates and fits only the missing range into the cache, the second
/// reuses it without simulating, `--no-extend` clamps instead (a different
/// image), and a damaged cache entry is an error naming the file.
#[test]
fn missing_albedo_range_is_simulated_once_and_cached() {
    let d = tmpdir("extend");
    // Below the outer model's 0.05: the shipped model covers [0.05, 0.999].
    let scene = small_scene(&d.join("dark.toml"), "stripes", [0.02, 0.6], "width", "");
    let covered = small_scene(&d.join("covered.toml"), "stripes", [0.1, 0.6], "width", "");
    let cache = d.join("cache");
    let render_of = |scene: &Path, out: &str, extra: &[&str]| {
        let o = bin()
            .arg("render")
            .arg(scene)
            .args(["--method", "learned", "--spp", "16", "--cache"])
            .arg(&cache)
            .args(extra)
            .arg("--out")
            .arg(d.join(out))
            .output()
            .unwrap();
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let render = |out: &str, extra: &[&str]| render_of(&scene, out, extra);
    let ext = |out: &str| {
        json(&d.join(out).join("render.json"))["passes"][0]["metamodel_extension"].clone()
    };
    assert!(render_of(&covered, "covered", &[]).0);
    assert!(ext("covered").is_null(), "{}", ext("covered"));
    assert!(render("a", &[]).0);
    let first = ext("a");
    assert_eq!(first["cached"], false, "{first}");
    assert_eq!(first["missing"][0], 0.02);
    assert_eq!(first["missing"][1], 0.05);
    assert!(first["albedos"][3].as_f64().unwrap() > 0.05);
    let model = PathBuf::from(first["model"].as_str().unwrap());
    assert!(model.starts_with(&cache) && model.exists());
    assert!(render("b", &[]).0);
    assert_eq!(ext("b")["cached"], true);
    assert_eq!(ext("b")["model"], first["model"]);
    assert!(render("c", &["--no-extend"]).0);
    assert!(ext("c").is_null());
    let img = |out: &str| std::fs::read(d.join(out).join("main/learned_mean.npy")).unwrap();
    assert_eq!(img("a"), img("b"), "cached extension, same image");
    assert_ne!(
        img("a"),
        img("c"),
        "the extension changes the kernel below α = 0.05"
    );
    std::fs::write(&model, "{ not json").unwrap();
    let (ok, err) = render("d", &[]);
    assert!(!ok && err.contains("metamodel_ext_"), "{err}");
    assert!(!d.join("d/render.json").exists());
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn fit_outer_and_check_kernels_refuse_bad_input() {
    let d = tmpdir("outer");
    let run = |args: &[&str]| {
        let o = bin().args(args).output().unwrap();
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let shipped = "data/profiles/metamodel.json";
    let wide = "data/profiles/metamodel_wide.json";
    let fit_outer = |model: &str, outer: &str, out: &Path| {
        let out = out.to_str().unwrap();
        run(&[
            "fit", "outer", "--model", model, "--outer", outer, "--out", out,
        ])
    };
    // The shipped model's own box inside the wide one: accepted, and the
    // written file covers the wide box.
    let out = d.join("m.json");
    let (ok, text, err) = fit_outer(shipped, wide, &out);
    assert!(ok, "{err}");
    assert!(text.contains("α ∈ [0.05, 0.999]"), "{text}");
    // The other way round, the outer box does not hold the model's: an
    // error that names the file and the key, and nothing written.
    let bad = d.join("bad.json");
    let (ok, _, err) = fit_outer(wide, shipped, &bad);
    assert!(
        !ok && err.contains("metamodel.json") && err.contains("outer"),
        "{err}"
    );
    assert!(!bad.exists());
    // A refinement that does not divide the tally's.
    let (ok, _, err) = run(&[
        "fit",
        "check-kernels",
        "--model",
        shipped,
        "--vertex-refine",
        "3",
    ]);
    assert!(!ok && err.contains("vertex_refine"), "{err}");
    std::fs::remove_dir_all(&d).unwrap();
}

/// A closed stdout (`svkernel profile … | head -1`) ends the program
/// quietly: no panic message on stderr.
#[cfg(unix)]
#[test]
fn a_closed_stdout_is_no_panic() {
    let mut child = bin()
        .args(["profile", "--albedo", "0.5", "--radii", "0.1,1,10"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !err.contains("panicked") && !err.contains("Broken pipe"),
        "{err}"
    );
}

/// `fit kernels` with its default output writes under `out/fit/` of the
/// folder it runs in, never over the shipped model.
#[test]
fn fit_kernels_writes_under_out_by_default() {
    let d = tmpdir("fit-default");
    let tally = d.join("k.json");
    let o = bin()
        .args([
            "simulate",
            "kernels",
            "--albedos",
            "0.8,0.9,0.95",
            "--distances",
            "0.5,1,2",
            "--paths",
            "1e6",
            "--out",
        ])
        .arg(&tally)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let shipped = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/profiles/metamodel.json"
    ))
    .unwrap();
    let o = bin()
        .current_dir(&d)
        .args([
            "fit",
            "kernels",
            "--components",
            "1",
            "--degree",
            "1,1",
            "--in",
        ])
        .arg(&tally)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(d.join("out/fit/metamodel.json").exists());
    assert!(d.join("out/fit/metamodel_report/report.json").exists());
    // `fit kernels --from MODEL EXTRA… --out OUT`, in `d`.
    let refit = |model: &str, extra: &[&str], out: &str| {
        bin()
            .current_dir(&d)
            .args(["fit", "kernels", "--from", model])
            .args(extra)
            .args(["--out", out, "--in"])
            .arg(&tally)
            .output()
            .unwrap()
    };
    let report = |p: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(d.join(p)).unwrap()).unwrap()
    };
    let fit = report("out/fit/metamodel_report/report.json");
    let chi2 = |r: &serde_json::Value, class: usize| r["joint"][class]["chi2"].as_f64().unwrap();
    // A refit from that model starts where its fit ended, so it ends no
    // higher, and its report names the start; so do raised degrees, which
    // start from the model's polynomials.
    for (extra, out, degree) in [
        (&[][..], "refit", fit["degree"].clone()),
        (
            &["--degree", "2,1"][..],
            "raised",
            serde_json::json!([2, 1]),
        ),
    ] {
        let o = refit(
            "out/fit/metamodel.json",
            extra,
            &format!("{out}/metamodel.json"),
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r = report(&format!("{out}/metamodel_report/report.json"));
        assert_eq!(r["start"], "out/fit/metamodel.json");
        assert_eq!(r["degree"], degree);
        for class in 0..2 {
            let (a, b) = (chi2(&r, class), chi2(&fit, class));
            assert!(a <= b, "{out}: {a} > {b}");
        }
    }
    // The report records how the moments were weighed; a weight that is
    // not a finite number >= 0 is refused.
    assert_eq!(fit["moments"]["weight"], 70.0);
    assert_eq!(fit["moments"]["errors"], false);
    for w in ["-1", "nan", "inf"] {
        let o = refit(
            "out/fit/metamodel.json",
            &[&format!("--moment-weight={w}")],
            "weight/metamodel.json",
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains("--moment-weight"),
            "{w}: {err}"
        );
        assert!(!d.join("weight/metamodel.json").exists());
    }
    // A tally of one albedo overlaid on the first (`--in A --in B`): the
    // report lists it. One of other distances is refused with an error that
    // names its file and the key, and no model is written.
    let simulate = |distances: &str, out: &str| {
        let o = bin()
            .current_dir(&d)
            .args(["simulate", "kernels", "--albedos", "0.95", "--distances"])
            .args([distances, "--paths", "2e5", "--seed", "5", "--out", out])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    simulate("0.5,1,2", "over.json");
    simulate("0.5,1,3", "other.json");
    let overlaid = |over: &str, out: &str| {
        bin()
            .current_dir(&d)
            .args(["fit", "kernels", "--from", "out/fit/metamodel.json", "--in"])
            .arg(&tally)
            .args(["--in", over, "--out", out])
            .output()
            .unwrap()
    };
    let o = overlaid("over.json", "overlaid/metamodel.json");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report("overlaid/metamodel_report/report.json");
    assert_eq!(r["overlays"], serde_json::json!(["over.json"]));
    let o = overlaid("other.json", "mismatch/metamodel.json");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("other.json") && err.contains("config.distances"),
        "{err}"
    );
    assert!(!d.join("mismatch/metamodel.json").exists());
    // Degrees below the model's are refused.
    let o = refit(
        "raised/metamodel.json",
        &["--degree", "1,1"],
        "lower/metamodel.json",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("degrees"), "{err}");
    assert!(!d.join("lower/metamodel.json").exists());
    // The shipped model's box is not this tally's: a clear error.
    let shipped_model = concat!(env!("CARGO_MANIFEST_DIR"), "/data/profiles/metamodel.json");
    let o = refit(shipped_model, &[], "bad/metamodel.json");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("metamodel.json") && err.contains("box"),
        "{err}"
    );
    assert!(!d.join("bad/metamodel.json").exists());
    let after = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/profiles/metamodel.json"
    ))
    .unwrap();
    assert_eq!(shipped, after, "the shipped meta-model changed");
}

/// From a folder with no `data/` and no `scenes/`: the built-in models and
/// scenes serve `kernel`, `profile`, `scene` and `render`.
#[test]
fn commands_work_from_an_empty_folder() {
    let d = tmpdir("empty-folder");
    let run = |args: &[&str]| {
        let o = bin().current_dir(&d).args(args).output().unwrap();
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let k: serde_json::Value =
        serde_json::from_str(&run(&["kernel", "--d", "1", "--albedo", "0.9"])).unwrap();
    assert_eq!(k["model"], "(built-in metamodel.json)");
    let p: serde_json::Value = serde_json::from_str(&run(&["profile", "--albedo", "0.9"])).unwrap();
    assert!(p["R_d"].as_f64().unwrap() > 0.1);
    let toml = run(&["scene", "checker"]);
    assert!(toml.contains("name = \"checker\""));
    run(&[
        "render",
        "checker",
        "--method",
        "reference,learned",
        "--spp",
        "2",
        "--paths",
        "1e3",
        "--resolution",
        "8",
        "--out",
        "r",
    ]);
    assert!(d.join("r/main/learned.exr").exists());
    assert!(!d.join("data").exists() && !d.join("out").exists());
}

/// A small planned kernel simulation whose target (1e9 effective paths per
/// cell) is out of reach, so a top-up is always due.
const SMALL_PLAN: [&str; 14] = [
    "simulate",
    "kernels",
    "--albedos",
    "0.5",
    "--distances",
    "1,4",
    "--nu",
    "8",
    "--nv",
    "4",
    "--min-paths",
    "1e9",
    "--paths",
    "1e6",
];

/// A planned kernel simulation from the command line: the plan goes to
/// stderr, the document records its runs, `--top-ups 0` runs the plan
/// alone, and no round file is left behind.
#[test]
fn planned_kernel_simulation_with_bounded_top_ups() {
    let d = tmpdir("planned");
    let out = d.join("k.json");
    let o = bin()
        .args(SMALL_PLAN)
        .args(["--top-ups", "0", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("plan:"), "{err}");
    // The target is out of reach, so a top-up would be due: none ran.
    assert!(!err.contains("top-up"), "{err}");
    let doc = json(&out);
    let runs = doc["config"]["runs"].as_array().unwrap();
    assert!(!runs.is_empty());
    assert_eq!(
        doc["config"]["paths"].as_u64().unwrap(),
        runs.iter()
            .map(|r| r["paths"].as_u64().unwrap())
            .sum::<u64>()
    );
    assert!(!d.join("k.json.rounds").exists() && !d.join("k.json.ckpt").exists());
    std::fs::remove_dir_all(&d).unwrap();
}

/// `--from` tops up a finished tally: the result is the tally that the
/// same plan with one top-up round gives in one command, bit for bit, and
/// the tally it started from is kept as its first runs.
#[test]
fn kernel_top_up_from_a_finished_tally() {
    let d = tmpdir("topup_from");
    let run = |extra: &[&str], out: &str| {
        let o = bin()
            .args(SMALL_PLAN)
            .args(extra)
            .arg("--out")
            .arg(d.join(out))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(o.status.success(), "{err}");
        (json(&d.join(out)), err)
    };
    let (plan, _) = run(&["--top-ups", "0"], "plan.json");
    let from = d.join("plan.json");
    let (topped, err) = run(
        &["--top-ups", "1", "--from", from.to_str().unwrap()],
        "topped.json",
    );
    assert!(err.contains("top-up 1"), "{err}");
    assert!(
        !err.contains("plan:"),
        "a top-up does not plan again: {err}"
    );
    let (direct, _) = run(&["--top-ups", "1"], "direct.json");
    assert_eq!(topped["config"], direct["config"]);
    assert_eq!(topped["tally"], direct["tally"]);
    let runs = |doc: &serde_json::Value| doc["config"]["runs"].as_array().unwrap().clone();
    let (before, after) = (runs(&plan), runs(&topped));
    assert!(after.len() > before.len());
    assert_eq!(after[..before.len()], before[..]);
    assert!(topped["paths"].as_u64().unwrap() > plan["paths"].as_u64().unwrap());
    assert!(!d.join("topped.json.rounds").exists() && !d.join("topped.json.ckpt").exists());
    // So does a round that may move cells to another sampling.
    let (topped, _) = run(
        &[
            "--top-ups",
            "1",
            "--replan",
            "--from",
            from.to_str().unwrap(),
        ],
        "topped_replan.json",
    );
    let (direct, _) = run(&["--top-ups", "1", "--replan"], "direct_replan.json");
    assert_eq!(topped["config"], direct["config"]);
    assert_eq!(topped["tally"], direct["tally"]);

    // A missing tally is an error that names the file, and nothing is written.
    let o = bin()
        .args(["simulate", "kernels", "--min-paths", "10", "--from"])
        .arg(d.join("missing.json"))
        .arg("--out")
        .arg(d.join("none.json"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.json"));
    assert!(!d.join("none.json").exists());
    std::fs::remove_dir_all(&d).unwrap();
}
