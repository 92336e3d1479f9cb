//! The shipped kernel meta-model and the `kernel` query.

use std::path::Path;
use std::process::Command;
use svkernel::fit::aggregation::{AggregationRow, aggregation_row};
use svkernel::fit::gmm::fit_gmm;
use svkernel::fit::lm::FitOptions;
use svkernel::fit::meta::cells;
use svkernel::forward::kernel::{KernelDoc, VertexClass};
use svkernel::metamodel::meta::MetaModelFile;

const META: &str = "data/profiles/metamodel.json";
const KERNELS: &str = "data/kernels/eta1.5_g0.3_pencil.json";
const WIDE: &str = "data/kernels/eta1.5_g0.3_pencil_wide.json";
/// The analog tally of the wide box's α = 0.999 row, overlaid on [`WIDE`]
/// for the fit.
const WIDE_TOP: &str = "data/kernels/eta1.5_g0.3_pencil_wide_top.json";

#[test]
fn shipped_model_gives_valid_kernels_everywhere() {
    let f = MetaModelFile::load(Path::new(META)).unwrap();
    for class in VertexClass::ALL {
        for d in [0.0, 1e-6, 0.05, 0.3, 1.0, 5.0, 10.0, 15.0, 50.0] {
            for a in [0.0, 1e-9, 0.1, 0.2, 0.5, 0.9, 0.99, 0.995, 1.0 - 1e-9, 1.0] {
                for rho in [1e-3, 0.5, 1.0, 4.0, 1e3] {
                    let q = f.eval(class, d, a, rho);
                    assert!(
                        q.gmm.is_valid(),
                        "{class:?} d {d} α {a} ρ {rho}: {:?}",
                        q.gmm
                    );
                    let w: f64 = q.gmm.components.iter().map(|c| c.weight).sum();
                    assert!((w - 1.0).abs() < 1e-12);
                    // Inside the trained boxes nothing is clamped: the
                    // shipped model's and, outside it, its outer model's.
                    let inside = (0.05..=20.0).contains(&(d * rho)) && (0.05..=0.999).contains(&a);
                    assert_eq!(q.clamped, !inside, "{class:?} d {d} α {a} ρ {rho}");
                }
            }
        }
    }
    // Density: K(d, α, ρ) = K(ρd, α, 1) with lengths / ρ.
    let a = f.eval(VertexClass::All, 0.5, 0.8, 4.0).gmm;
    let b = f.eval(VertexClass::All, 2.0, 0.8, 1.0).gmm.scaled(0.25);
    assert_eq!(a, b);
}

#[test]
fn learned_kernels_beat_the_manual_kernel_where_it_matters() {
    // Aggregation error (RMS of α_t over random textures against the
    // measured histogram) on a spread of training cells.
    let f = MetaModelFile::load(Path::new(META)).unwrap();
    let doc = KernelDoc::load(Path::new(KERNELS)).unwrap();
    for class in [VertexClass::All, VertexClass::Last] {
        let cs = cells(&doc, class);
        let (mut wins, mut n, mut sum_meta, mut sum_manual) = (0, 0, 0.0, 0.0);
        let mut ceilings = 0;
        for c in cs.iter().step_by(7) {
            let q = f.eval(class, c.d, c.alpha, 1.0);
            let pc = fit_gmm("test", &c.hist, 3, &FitOptions::default()).ok();
            let row = aggregation_row(class, c, pc.as_ref().map(|x| &x.0), &q.gmm);
            wins += (row.meta < row.manual) as usize;
            n += 1;
            sum_meta += row.meta;
            sum_manual += row.manual;
            // The per-configuration fit is the meta-model's ceiling: close to it.
            if let Some(p) = row.per_config {
                assert!(row.meta < p + 0.02, "{row:?}");
                ceilings += 1;
            }
        }
        assert!(n >= 8);
        // The ceiling check ran (the per-configuration fits converge).
        assert!(ceilings * 2 >= n, "{class:?}: {ceilings} ceilings of {n}");
        assert!(
            sum_meta < 0.5 * sum_manual,
            "{class:?}: {sum_meta} vs {sum_manual}"
        );
        assert!(wins * 10 >= n * 8, "{class:?}: meta wins {wins} of {n}");
    }
}

#[test]
fn the_outer_model_holds_the_wide_box() {
    // On the wide tally's cells outside the shipped model's own box (all 50
    // of them fitted; its α = 0.999 row from the analog tally, as in the
    // fit), the shipped model (its outer model answers there) against the
    // same model without it (the queries clamp to the box's edge): the
    // aggregation error and the whole-plane rms s across the axis. The
    // last-vertex kernel changes fast across the box's edge and clamping it
    // fails (measured: aggregation error 0.0277 against 0.0023, rms s
    // within 10 % in 22 against 48 cells). The all-vertex kernel changes
    // slowly, so clamping it costs less there (0.0076 against 0.0047) but
    // misses the moments (rms s within 10 % in 3 against 43; the seven
    // misses are at α = 0.999, where four Gaussians give up the far tail,
    // docs/method.md §4, "The wide box"). The outer model beats the manual
    // kernel in every cell, the far corner (α = 0.05 and 0.2 at d = 20 MFP,
    // where a refit found its end lobes only with a width floor) and
    // α = 0.999, d = 0.1 MFP (where the planned tally's outlier once drew a
    // component several times too wide) included.
    let f = MetaModelFile::load(Path::new(META)).unwrap();
    let outer = f.outer.as_deref().expect("the shipped model carries one");
    assert_eq!(f.alpha_range(), outer.all.alpha_range);
    let mut clamped = f.clone();
    clamped.outer = None;
    let rows = |m: &MetaModelFile| {
        svkernel::jobs::fit_kernels::check_kernels(&[WIDE.into(), WIDE_TOP.into()], m, Some(2))
            .unwrap()
    };
    let (with, without) = (rows(&f), rows(&clamped));
    let outside = |r: &&AggregationRow| !f.all.holds(r.d, r.alpha);
    for class in [VertexClass::All, VertexClass::Last] {
        let pick = |rows: &[AggregationRow]| -> Vec<AggregationRow> {
            rows.iter()
                .filter(outside)
                .filter(|r| r.class == class)
                .cloned()
                .collect()
        };
        let (a, b) = (pick(&with), pick(&without));
        assert!(
            a.len() >= 50 && a.len() == b.len(),
            "{class:?}: {}",
            a.len()
        );
        let mean = |v: &[AggregationRow]| v.iter().map(|r| r.meta).sum::<f64>() / v.len() as f64;
        // rms s within 10 % of the vertices'.
        let within = |v: &[AggregationRow]| {
            v.iter()
                .filter(|r| {
                    let [data, meta] = r.plane.unwrap();
                    (meta.rms_s / data.rms_s - 1.0).abs() <= 0.1
                })
                .count()
        };
        // (mean error against clamping's, share of cells with rms s within
        // 10 %)
        let (ratio, share) = match class {
            VertexClass::Last => (0.2, 0.95),
            _ => (0.75, 0.85),
        };
        assert!(
            mean(&a) <= mean(&b) * ratio,
            "{class:?}: {} against {}",
            mean(&a),
            mean(&b)
        );
        assert!(
            within(&a) as f64 >= share * a.len() as f64,
            "{class:?}: {} of {}",
            within(&a),
            a.len()
        );
        assert!(
            within(&a) > within(&b) + 10,
            "{class:?}: {} against {}",
            within(&a),
            within(&b)
        );
        let losses: Vec<(f64, f64)> = a
            .iter()
            .filter(|r| r.meta >= r.manual)
            .map(|r| (r.alpha, r.d))
            .collect();
        assert!(
            losses.is_empty(),
            "{class:?}: worse than manual at {losses:?}"
        );
    }
    // Inside the box the shipped model answers, as before.
    for (x, y) in with.iter().zip(&without).filter(|(x, _)| !outside(x)) {
        assert_eq!(x.meta, y.meta);
    }
}

#[test]
fn corrupted_model_files_are_named() {
    let text = std::fs::read_to_string(META).unwrap();
    let dir = std::env::temp_dir().join(format!("svk-meta-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("meta.json");
    std::fs::write(&p, &text[..text.len() / 2]).unwrap();
    let e = MetaModelFile::load(&p).unwrap_err().to_string();
    assert!(e.contains("meta.json") && e.contains("truncated"), "{e}");
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["all"]["coeffs"][0].as_array_mut().unwrap().pop();
    std::fs::write(&p, v.to_string()).unwrap();
    let e = MetaModelFile::load(&p).unwrap_err().to_string();
    assert!(e.contains("models.all.coeffs"), "{e}");
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["last"]["k"] = 9.into();
    std::fs::write(&p, v.to_string()).unwrap();
    assert!(
        MetaModelFile::load(&p)
            .unwrap_err()
            .to_string()
            .contains("models.last.k")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

fn query(args: &[&str]) -> (bool, serde_json::Value, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_svkernel"))
        .arg("kernel")
        .args(args)
        .output()
        .unwrap();
    let v = serde_json::from_slice(&o.stdout).unwrap_or(serde_json::Value::Null);
    (
        o.status.success(),
        v,
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

#[test]
fn kernel_query_command() {
    let (ok, v, _) = query(&["--d", "1", "--albedo", "0.9", "--json"]);
    assert!(ok);
    let comps = v["components"].as_array().unwrap();
    assert_eq!(comps.len(), 4, "the shipped all-vertex kernel has four");
    let w: f64 = comps.iter().map(|c| c["weight"].as_f64().unwrap()).sum();
    assert!((w - 1.0).abs() < 1e-12);
    for c in comps {
        assert!(c["sigma"].as_f64().unwrap() > 0.0 && c["s"].as_f64() == Some(0.0));
    }
    assert_eq!(v["clamped"], false);
    let (_, v, _) = query(&["--d", "100", "--albedo", "0.9", "--json"]);
    assert_eq!(v["clamped"], true);
    let (_, v, _) = query(&["--d", "2", "--albedo", "0.5", "--manual", "--json"]);
    let w: Vec<f64> = v["components"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["weight"].as_f64().unwrap())
        .collect();
    assert_eq!(w, vec![0.25, 0.5, 0.25]);
    assert_eq!(v["components"][1]["sigma"].as_f64(), Some(0.5 + 0.3 * 2.0));
    // The density law, as the renderer applies it: at ρ = 0.5 the kernel of
    // optical distance 1, lengths ×2.
    let (_, v, _) = query(&[
        "--d",
        "2",
        "--albedo",
        "0.5",
        "--density",
        "0.5",
        "--manual",
        "--json",
    ]);
    assert_eq!(v["components"][1]["t"].as_f64(), Some(1.0));
    assert_eq!(
        v["components"][1]["sigma"].as_f64(),
        Some(2.0 * (0.5 + 0.3))
    );
    let (_, v, _) = query(&[
        "--d",
        "2",
        "--albedo",
        "0.5",
        "--vertices",
        "first",
        "--json",
    ]);
    assert_eq!(v["components"][0]["t"].as_f64(), Some(0.0));
    for (args, flag) in [
        (
            vec!["--d", "1", "--albedo", "0.5", "--vertices", "middle"],
            "--vertices",
        ),
        (vec!["--d", "-1", "--albedo", "0.5"], "--d"),
        (vec!["--d", "1", "--albedo", "2"], "--albedo"),
        (
            vec!["--d", "1", "--albedo", "0.5", "--density", "0"],
            "--density",
        ),
        (
            vec![
                "--d",
                "1",
                "--albedo",
                "0.5",
                "--model",
                "/nonexistent/m.json",
            ],
            "m.json",
        ),
    ] {
        let (ok, _, err) = query(&args);
        assert!(!ok && err.contains(flag), "{args:?}: {err}");
    }
}

/// The shipped model's whole-plane moments meet the targets (|Δ mean t|
/// within 0.05·d + 0.01λ, rms s within 10 %) in every cell of the shipped
/// box with twice the data's standard error allowed, and without it in all
/// cells but one: α = 0.92, d = 0.6 MFP, whose tallied rms s (0.839 ±
/// 0.151 MFP) rests on a few far vertices of heavy weight. A model fitted
/// with the moments at W = 30 misses rms s in four more cells (α = 0.99,
/// d = 0.6–2.5 MFP, 10–14 % narrow), at d = 1.6 beyond twice the data's
/// error.
#[test]
fn the_shipped_model_meets_the_moment_targets() {
    use svkernel::jobs::fit_kernels::moment_within;
    let doc = KernelDoc::load(Path::new(KERNELS)).unwrap();
    let f = MetaModelFile::load(Path::new(META)).unwrap();
    for class in [VertexClass::All, VertexClass::Last] {
        let mut misses = Vec::new();
        for c in cells(&doc, class) {
            let data = c.plane.expect("measured cells carry their moments");
            let meta = svkernel::fit::meta::PlaneMoments::of(&f.eval(class, c.d, c.alpha, 1.0).gmm);
            let se = data.se.expect("the shipped tally has the moments' errors");
            let [t, s] = moment_within(c.d, &data, &meta, se);
            assert!(
                t && s,
                "{class:?} α {} d {}: {meta:?} against {data:?}",
                c.alpha,
                c.d
            );
            let [t, s] = moment_within(c.d, &data, &meta, [0.0; 2]);
            if !(t && s) {
                misses.push((c.alpha, c.d));
            }
        }
        assert!(
            misses.is_empty() || (class == VertexClass::All && misses == [(0.92, 0.6)]),
            "{class:?}: outside the targets at {misses:?}"
        );
    }
}

/// The whole-plane moments the tally keeps agree with the histogram where
/// the window holds nearly every vertex (binned means to within a bin), and
/// every report row carries the window's share and both moments.
#[test]
fn whole_plane_moments_and_the_window_are_reported() {
    let doc = KernelDoc::load(Path::new(KERNELS)).unwrap();
    let f = MetaModelFile::load(Path::new(META)).unwrap();
    let mut checked = 0;
    for class in [VertexClass::All, VertexClass::Last] {
        for c in cells(&doc, class) {
            let plane = c.plane.expect("measured cells carry their moments");
            let h = &c.hist;
            let ns = h.ns();
            let (mut m, mut mt, mut ms2) = (0.0, 0.0, 0.0);
            for (b, w) in h.mass.iter().enumerate() {
                let (it, is) = (b / ns, b % ns);
                let t = 0.5 * (h.t_edges[it] + h.t_edges[it + 1]);
                let s = 0.5 * (h.s_edges[is] + h.s_edges[is + 1]);
                m += w;
                mt += w * t;
                ms2 += w * s * s;
            }
            let row = aggregation_row(class, &c, None, &f.eval(class, c.d, c.alpha, 1.0).gmm);
            assert!(row.window > 0.5 && row.window <= 1.0 + 1e-12, "{row:?}");
            assert!(
                (row.window - m).abs() < 1e-9,
                "window {} vs Σ mass {m}",
                row.window
            );
            let [data, meta] = row.plane.expect("moments in the row");
            assert_eq!(data, plane);
            assert!(meta.rms_s > 0.0 && meta.mean_t.is_finite());
            if row.window > 0.999 {
                let dt = h.t_edges[1] - h.t_edges[0];
                let ds = h.s_edges[1] - h.s_edges[0];
                assert!(
                    (mt / m - plane.mean_t).abs() < dt,
                    "{class:?} α {} d {}",
                    c.alpha,
                    c.d
                );
                assert!(
                    ((ms2 / m).sqrt() - plane.rms_s).abs() < ds,
                    "{class:?} α {} d {}",
                    c.alpha,
                    c.d
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 20, "only {checked} cells with the whole window");
}
