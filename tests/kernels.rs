//! The path-density estimator: determinism, the density scaling
//! law, the sensitivity identity, hard cases.

use svkernel::forward::kernel::{
    KernelConfig, KernelDoc, KernelRun, KernelTally, PairGrid, PlanOptions, VertexClass, merge,
};
use svkernel::forward::maps::{AlbedoMap, TexelMap};
use svkernel::forward::medium::{Medium, Source};
use svkernel::forward::rng::{PathRng, threshold_u32};
use svkernel::forward::runner::{RunOptions, Shard, Tally, shard_range};
use svkernel::forward::walk::{
    AlbedoField, AngularBias, Fate, Flights, launch, max_bias, max_stretch_offset, walk_general,
};
use svkernel::provenance::Provenance;
use svkernel::testing::Z_MC;

fn config(albedos: &[f64], distances: &[f64], density: f64, paths: u64, seed: u64) -> KernelConfig {
    KernelConfig {
        g: 0.3,
        eta: 1.5,
        density,
        albedos: albedos.to_vec(),
        distances: distances.to_vec(),
        rel_width: 0.1,
        min_order: 2,
        paths,
        seed,
        max_events: 100_000,
        grid: PairGrid::default(),
        runs: Vec::new(),
    }
}

fn doc(c: &KernelConfig, shard: Option<Shard>) -> KernelDoc {
    let (tally, wall) = c.run(shard, &RunOptions::default()).unwrap();
    KernelDoc::new(
        c.clone(),
        shard,
        vec![shard_range(c.chunks(), shard)],
        tally,
        wall,
        Provenance::current(),
    )
}

/// Runs `c` on one thread, on all, and as `n` merged shards; asserts that
/// all three tallies are bitwise equal and returns the tally and the shards.
fn same_for_threads_and_shards(
    c: &KernelConfig,
    n: u64,
) -> (KernelTally, Vec<(std::path::PathBuf, KernelDoc)>) {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| c.run(None, &RunOptions::default()).unwrap().0);
    let many = c.run(None, &RunOptions::default()).unwrap().0;
    assert_eq!(one, many);
    let shards: Vec<_> = (0..n)
        .map(|k| {
            let s = Shard { index: k, count: n };
            (std::path::PathBuf::from(format!("s{k}")), doc(c, Some(s)))
        })
        .collect();
    let merged = merge(&shards, Provenance::current()).unwrap();
    assert_eq!(merged.tally, many);
    assert_eq!(merged.shard, None);
    (many, shards)
}

#[test]
fn one_vs_many_threads_and_shards_are_bitwise_identical() {
    let c = config(&[0.7, 0.95], &[0.5, 2.0], 1.0, 3 * 16384 + 123, 9);
    let (many, shards) = same_for_threads_and_shards(&c, 3);
    // The same shard twice is refused.
    assert!(
        merge(
            &[shards[0].clone(), shards[0].clone()],
            Provenance::current()
        )
        .is_err()
    );
    // Chunk tallies merge in any grouping to the same counts.
    let mut t = KernelTally::new(&c);
    for k in (0..4).rev() {
        t.merge(&c.simulate_chunk(k));
    }
    assert_eq!(t, many);
}

/// `c` planned as one run per albedo with flights `flights` over every distance.
fn transformed(c: &KernelConfig, flights: Flights, paths: u64) -> KernelConfig {
    let runs: Vec<KernelRun> = (0..c.albedos.len())
        .map(|ia| KernelRun {
            albedo: ia,
            distances: (0..c.distances.len()).collect(),
            flights,
            unit_log2: 20,
            paths,
        })
        .collect();
    KernelConfig {
        paths: runs.iter().map(|r| r.paths).sum(),
        runs,
        ..c.clone()
    }
}

#[test]
fn planned_runs_are_bitwise_identical_for_threads_and_shards() {
    let flights = Flights {
        stretch: 0.8,
        bias: 0.5,
        forced: 1,
        angular: false,
    };
    let c = transformed(
        &config(&[0.3, 0.8], &[0.5, 3.0], 1.0, 1, 5),
        flights,
        2 * 16384 + 77,
    );
    c.validate().unwrap();
    assert_eq!(c.chunks(), 6);
    let (many, _) = same_for_threads_and_shards(&c, 4);
    // Every run reached its cells, with unequal weights.
    for row in &many.cells {
        for cell in row {
            assert!(cell.paths > 0 && cell.effective_paths() < cell.paths as f64);
        }
    }
}

#[test]
fn stretched_flights_are_unbiased() {
    // The weighted histograms of walks with stretched, shortened and
    // outward-biased flights (the last with biased directions too) against
    // the analog walk's, bin by bin (χ² with both errors), their levels and
    // their whole-plane moments.
    let analog = config(&[0.7], &[0.6, 2.5], 1.0, 600_000, 31);
    let da = doc(&analog, None);
    for (stretch, bias, forced, angular, seed) in [
        (0.7, 0.0, 0, false, 32),
        (1.4, 0.0, 0, false, 33),
        (1.0, 0.6, 2, false, 34),
        (1.0, 0.5, 0, true, 35),
    ] {
        let flights = Flights {
            stretch,
            bias,
            forced,
            angular,
        };
        let c = transformed(&config(&[0.7], &[0.6, 2.5], 1.0, 1, seed), flights, 600_000);
        let db = doc(&c, None);
        for id in 0..2 {
            let n_eff = db.tally.cells[0][id].effective_paths();
            assert!(n_eff > 300.0, "{flights:?} d {id}: {n_eff}");
            // The cell's level: contributing weight per launched path (the
            // transformed run's weights in units of 2⁻²⁰), within Z_MC of
            // both standard errors.
            let level = |cell: &svkernel::forward::kernel::CellTally, unit: f64, n: f64| {
                let m = cell.weight as f64 / unit / n;
                let m2 = cell.weight_sq as f64 / (unit * unit) / n;
                (m, ((m2 - m * m).max(0.0) / n).sqrt())
            };
            let (la, ea) = level(&da.tally.cells[0][id], 1.0, 600_000.0);
            let (lb, eb) = level(&db.tally.cells[0][id], 2f64.powi(20), 600_000.0);
            assert!(
                (la - lb).abs() < Z_MC * ea.hypot(eb),
                "{flights:?} d {id}: level {lb} against {la} (errors {eb}, {ea})"
            );
            for class in VertexClass::ALL {
                let (ha, hb) = (da.histogram(0, id, class), db.histogram(0, id, class));
                let (c2, n) = chi2(&ha, &hb);
                assert!(
                    c2 <= n as f64 + Z_MC * (2.0 * n as f64).sqrt() + 0.1 * n as f64,
                    "{flights:?} d {} {class:?}: χ² {c2} over {n} bins",
                    ha.d
                );
                // Means of u against 5 standard errors of the mean
                // (√(mean v² + 0.5)/√n_eff bounds the spread of u).
                let tol = 5.0 * (ha.mean_v2 + 0.5).sqrt() / n_eff.sqrt();
                assert!(
                    (ha.mean_u - hb.mean_u).abs() < tol,
                    "{flights:?} d {} {class:?}: mean u {} against {} (tol {tol})",
                    ha.d,
                    hb.mean_u,
                    ha.mean_u
                );
            }
        }
    }
}

#[test]
fn a_plan_fills_the_cells_analog_walks_miss() {
    // α = 0.2: analog paths almost never leave 8 MFP away (≈ 1 in 10⁷ in
    // this bin); the plan stretches flights there and fills the cell.
    let c = config(&[0.2], &[1.0, 8.0], 1.0, 1, 41);
    let opts = PlanOptions {
        target: 300.0,
        max_paths: 4_000_000,
        ..Default::default()
    };
    let (planned, cells) = c.plan(&opts, false).unwrap();
    assert_eq!(cells.len(), 2);
    let far = cells.iter().find(|p| p.d == 8.0).unwrap();
    assert_ne!(far.flights, Flights::ANALOG, "{far:?}");
    assert!(planned.paths <= 2 * opts.max_paths);
    // Top-ups correct what the pilots misjudged.
    let (mut config, mut tally) = (
        planned.clone(),
        planned.run(None, &RunOptions::default()).unwrap().0,
    );
    for _ in 0..3 {
        let Some(grown) = config.top_up(&mut tally, &opts).unwrap() else {
            break;
        };
        let range = (config.chunks(), grown.chunks());
        tally.merge(&grown.run_chunks(range, &RunOptions::default()).unwrap().0);
        config = grown;
    }
    // The tally of the grown plan run at once is the same, bitwise.
    assert_eq!(config.run(None, &RunOptions::default()).unwrap().0, tally);
    for id in 0..2 {
        let n_eff = tally.cells[0][id].effective_paths();
        assert!(
            n_eff > 0.5 * opts.target,
            "cell d = {}: {n_eff} effective paths",
            c.distances[id]
        );
    }
    // Planning is deterministic.
    assert_eq!(c.plan(&opts, false).unwrap().0, planned);
}

#[test]
fn a_top_up_moves_a_cell_its_sampling_starves() {
    // Analog walks at α = 0.2 reach d = 4 MFP (after two scatterings) about
    // once in 4·10⁴ paths: a plan that left the cell to them delivers next
    // to nothing there. A plain top-up asks for the most paths one run may
    // have and still falls short; a re-planning one moves the cell to a
    // transformed sampling, drops the analog run's few paths there, and
    // fills it.
    let mut c = config(&[0.2], &[4.0], 1.0, 0, 47);
    let analog = KernelRun {
        albedo: 0,
        distances: vec![0],
        flights: Flights::ANALOG,
        unit_log2: 0,
        paths: 1 << 17,
    };
    c.paths = analog.paths;
    c.runs = vec![analog];
    let opts = PlanOptions {
        target: 300.0,
        max_paths: 1 << 21,
        ..Default::default()
    };
    let run = |c: &KernelConfig, range| c.run_chunks(range, &RunOptions::default()).unwrap().0;
    let first = run(&c, (0, c.chunks()));
    assert!(first.cells[0][0].effective_paths() < 10.0);

    let plain = c.top_up(&mut first.clone(), &opts).unwrap().unwrap();
    assert_eq!(plain.runs[1].flights, Flights::ANALOG);
    assert_eq!(plain.runs[1].paths, opts.max_paths);

    let replan = PlanOptions {
        replan: true,
        ..opts
    };
    let mut tally = first.clone();
    let grown = c.top_up(&mut tally, &replan).unwrap().unwrap();
    // The analog run feeds nothing now (and walks nothing); the new one
    // feeds the cell, from an empty tally.
    assert!(grown.runs[0].distances.is_empty());
    assert_eq!(grown.runs[1].distances, vec![0]);
    assert_ne!(grown.runs[1].flights, Flights::ANALOG);
    assert!(grown.runs[1].paths < opts.max_paths);
    assert_eq!(tally.cells[0][0].effective_paths(), 0.0);
    assert_eq!(tally.paths, first.paths);
    tally.merge(&run(&grown, (c.chunks(), grown.chunks())));
    // The same, bitwise, as the grown configuration run at once.
    assert_eq!(run(&grown, (0, grown.chunks())), tally);
    let n_eff = tally.cells[0][0].effective_paths();
    assert!(n_eff > 0.5 * replan.target, "{n_eff} effective paths");
    // Still short of the target, but within the gain of its pilot's promise:
    // a further round tops the cell up with the same sampling.
    let g = grown.top_up(&mut tally.clone(), &replan).unwrap().unwrap();
    assert_eq!(g.runs.len(), 3);
    assert_eq!(g.runs[2].flights, grown.runs[1].flights);
    assert_eq!(g.runs[2].distances, vec![0]);
}

/// The bound on the exponential transform's bias: at g = 0 it is the root
/// κ of the dispersion relation of isotropic scattering, tabulated as
/// ν₀ = 1/κ (Case & Zweifel, *Linear Transport Theory*, 1967: 1.04438 at
/// α = 0.5, 1.90320 at α = 0.9); it falls as α rises and as g does. A plan
/// walks no sampling beyond it, and one with nothing left is an error.
#[test]
fn a_plan_walks_no_exponential_transform_beyond_its_bound() {
    assert!((1.0 / max_bias(0.5, 0.0) - 1.04438).abs() < 1e-4);
    assert!((1.0 / max_bias(0.9, 0.0) - 1.90320).abs() < 1e-4);
    let b: Vec<f64> = [0.2, 0.4, 0.6, 0.75, 0.85, 0.92, 0.96, 0.99]
        .iter()
        .map(|&a| max_bias(a, 0.3))
        .collect();
    assert!(b.windows(2).all(|w| w[1] < w[0]), "{b:?}");
    assert!(max_bias(0.6, 0.3) < max_bias(0.6, 0.0));
    // At α = 0.75 (bound 0.66 at g = 0.3), bias 0.93 is left out.
    let strong = Flights {
        stretch: 1.0,
        bias: 0.93,
        forced: 2,
        angular: false,
    };
    assert!(!strong.bounded_weights(0.75, 0.3) && strong.bounded_weights(0.2, 0.3));
    let c = config(&[0.75], &[1.0, 6.5], 1.0, 1, 43);
    let opts = PlanOptions {
        target: 100.0,
        max_paths: 1 << 20,
        pilot: 1 << 12,
        flights: vec![Flights::ANALOG, strong],
        bias_fractions: vec![0.6],
        stretch_fractions: Vec::new(),
        angular_fractions: Vec::new(),
        replan: false,
    };
    let (planned, cells) = c.plan(&opts, false).unwrap();
    assert_eq!(cells.len(), 2);
    for r in &planned.runs {
        assert!(r.flights.bounded_weights(0.75, 0.3), "{:?}", r.flights);
        assert_ne!(r.flights, strong);
    }
    // The far cell goes to the transform at 0.6 of the bound.
    let far = cells.iter().find(|p| p.d == 6.5).unwrap();
    assert!(
        (far.flights.bias - 0.6 * max_bias(0.75, 0.3)).abs() < 1e-12,
        "{far:?}"
    );
    let none = PlanOptions {
        flights: vec![strong],
        bias_fractions: Vec::new(),
        ..opts
    };
    let err = c.plan(&none, false).unwrap_err().to_string();
    assert!(err.contains("flights"), "{err}");
}

/// The stretch's bound: a flight drawn at rate c·σ_t weighs e^((c − 1)σ_t s)/c,
/// whose second moment 1/(c(2 − c)) (checked here by sampling) grows by the
/// albedo per collision, so |c − 1| < √(1 − α). Flights twice as dense are
/// unbounded at every albedo; a plan walks the stretches its albedo allows.
#[test]
fn a_plan_walks_no_stretch_beyond_its_bound() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let c = 1.2f64;
    let n = 400_000;
    let m2 = (0..n)
        .map(|_| {
            let s = -(1.0 - rng.random::<f64>()).ln() / c;
            ((c - 1.0) * s).exp().powi(2) / (c * c)
        })
        .sum::<f64>()
        / n as f64;
    let exact = 1.0 / (c * (2.0 - c));
    assert!((m2 / exact - 1.0).abs() < 0.01, "{m2} against {exact}");
    assert!((max_stretch_offset(0.96) - 0.2).abs() < 1e-12);
    let twice = Flights {
        stretch: 2.0,
        bias: 0.0,
        forced: 0,
        angular: false,
    };
    let mild = Flights {
        stretch: 1.2,
        ..twice
    };
    for a in [0.0, 0.2, 0.6, 0.96, 0.99] {
        assert!(!twice.bounded_weights(a, 0.3), "α = {a}");
    }
    assert!(mild.bounded_weights(0.9, 0.3) && !mild.bounded_weights(0.99, 0.3));
    let cfg = config(&[0.96], &[0.1, 1.0], 1.0, 1, 47);
    let opts = PlanOptions {
        target: 100.0,
        max_paths: 1 << 20,
        pilot: 1 << 12,
        flights: vec![Flights::ANALOG, twice],
        bias_fractions: Vec::new(),
        stretch_fractions: vec![0.6],
        angular_fractions: Vec::new(),
        replan: false,
    };
    let (planned, cells) = cfg.plan(&opts, false).unwrap();
    assert_eq!(cells.len(), 2);
    for r in &planned.runs {
        assert!(r.flights.bounded_weights(0.96, 0.3), "{:?}", r.flights);
        assert!(
            r.flights == Flights::ANALOG || (r.flights.stretch - 1.12).abs() < 1e-12,
            "{:?}",
            r.flights
        );
    }
    let bad = PlanOptions {
        stretch_fractions: vec![1.0],
        ..opts
    };
    let err = cfg.plan(&bad, false).unwrap_err().to_string();
    assert!(err.contains("stretch_fractions"), "{err}");
}

/// χ² between two independent normalised histograms over bins with data.
fn chi2(
    a: &svkernel::forward::kernel::NormalizedHistogram,
    b: &svkernel::forward::kernel::NormalizedHistogram,
) -> (f64, usize) {
    let (mut c2, mut n) = (0.0, 0);
    for k in 0..a.mass.len() {
        let var = a.sigma[k].powi(2) + b.sigma[k].powi(2);
        if a.mass[k] + b.mass[k] > 0.0 && var > 0.0 && a.sigma[k] > 0.0 && b.sigma[k] > 0.0 {
            c2 += (a.mass[k] - b.mass[k]).powi(2) / var;
            n += 1;
        }
    }
    (c2, n)
}

#[test]
fn density_only_rescales_lengths() {
    // K(·; d, α, ρ) = K(·; ρd, α, 1) with lengths / ρ. In normalised
    // coordinates (λ = d/2 + 1/ρ) the histograms are equal.
    let a = config(&[0.9], &[1.0, 3.0], 2.0, 400_000, 21);
    let b = config(&[0.9], &[2.0, 6.0], 1.0, 400_000, 22);
    let (da, db) = (doc(&a, None), doc(&b, None));
    // Same stream, ρ = 2: positions are exactly halved (a power of two), so
    // the counts are bitwise those of ρ = 1 at 2d.
    let same_seed = config(&[0.9], &[2.0, 6.0], 1.0, 400_000, 21);
    assert_eq!(da.tally.cells, doc(&same_seed, None).tally.cells);
    // Independent streams: χ² per bin, for every class.
    for id in 0..2 {
        for class in VertexClass::ALL {
            let (ha, hb) = (da.histogram(0, id, class), db.histogram(0, id, class));
            assert!(ha.paths > 2000, "{}", ha.paths);
            let (c2, n) = chi2(&ha, &hb);
            assert!(
                c2 < n as f64 + Z_MC * (2.0 * n as f64).sqrt() + 0.1 * n as f64,
                "d {} {class:?}: χ² {c2} over {n} bins",
                ha.d
            );
            assert!(
                (ha.mean_u - hb.mean_u).abs() < 0.02,
                "{} {}",
                ha.mean_u,
                hb.mean_u
            );
        }
    }
}

#[test]
fn first_vertex_lies_below_the_entry_point() {
    // Pencil beam: the first vertex is on the z axis below x_i, so t = s = 0,
    // u = −(d_p/2)/λ(d_p) exactly (d_p ∈ [0.9, 1.1], the path's own
    // distance), v = 0.
    let c = config(&[0.8], &[1.0], 1.0, 200_000, 3);
    let d = doc(&c, None);
    let h = d.histogram(0, 0, VertexClass::First);
    let u_of = |dp: f64| -0.5 * dp / PairGrid::scale(dp, 1.0);
    let u0 = u_of(1.0);
    assert!(h.mean_u < u_of(0.9) && h.mean_u > u_of(1.1), "{}", h.mean_u);
    assert!(
        (h.mean_u - u0).abs() < 2e-3 && h.mean_v2 < 1e-8,
        "{} {}",
        h.mean_u,
        h.mean_v2
    );
    assert!((h.mass.iter().sum::<f64>() + h.overflow - 1.0).abs() < 1e-12);
    // Every first vertex in the bins of v = 0 that u(d_p) crosses.
    let g = c.grid.for_class(VertexClass::First);
    let below: f64 = (g.index(u_of(1.1), 0.0)..=g.index(u_of(0.9), 0.0))
        .step_by(g.nv)
        .map(|b| h.mass[b])
        .sum();
    assert!((below - 1.0).abs() < 1e-12, "{below}");
    // The last vertex is spread around x_e, the all-vertex kernel in between.
    let last = d.histogram(0, 0, VertexClass::Last);
    let all = d.histogram(0, 0, VertexClass::All);
    assert!(last.mean_u > 0.0 && all.mean_u > u0 && all.mean_u < last.mean_u);
    assert!(all.mean_vertices > 2.0);
}

/// Vertices of a heterogeneous walk per texel, for paths that exit with at
/// least two scatterings inside the disk of `radius` around `centre`.
struct Scene {
    medium: Medium,
    centre: [f64; 2],
    radius: f64,
}

impl Scene {
    /// Does the path contribute, and where are its vertices.
    fn walk(&self, albedo: &impl AlbedoField, path: u64, vertices: &mut Vec<[f64; 3]>) -> bool {
        let mut rng = PathRng::new(77, path);
        let start = launch(&Source::Pencil, self.medium.eta, &mut rng).unwrap();
        vertices.clear();
        let (fate, n) = walk_general(&self.medium, albedo, 100_000, start, &mut rng, |v, _| {
            vertices.push(v)
        });
        match fate {
            Fate::Exit { x, y } => {
                n >= 2 && (x - self.centre[0]).hypot(y - self.centre[1]) < self.radius
            }
            _ => false,
        }
    }
}

#[test]
fn vertex_density_is_the_albedo_sensitivity() {
    // ∂ ln M / ∂ ln α(texel) = E[#vertices in the texel | contributes], with
    // M the multiple-scattering exitance into a disk. The right side from
    // the vertex counts, the left from a central finite difference of the
    // heterogeneous walk (ε = 10 %, common random numbers).
    let values: Vec<f64> = (0..36)
        .map(|k| 0.6 + 0.35 * (((k * 7919) % 36) as f64 / 35.0))
        .collect();
    let map = TexelMap::new(6, 6, 0.5, values).unwrap();
    let scene = Scene {
        medium: Medium::new(0.8, 0.3, 1.5, 1.0, None).unwrap(),
        centre: [0.75, 0.0],
        radius: 0.5,
    };
    let texels = [
        map.texel_of(0.1, 0.1),
        map.texel_of(0.6, -0.1),
        map.texel_of(0.3, 0.6),
    ];
    let n_paths = 3_000_000u64;
    let eps = 0.1;
    let base = AlbedoMap::new(map.clone()).unwrap();
    let perturbed = |(i, j): (usize, usize), f: f64| {
        let mut m = map.clone();
        m.values[i * m.nx + j] *= f;
        AlbedoMap::new(m).unwrap()
    };
    let mut v = Vec::new();
    // Estimator: vertex counts per texel over contributing paths.
    let (mut contrib, mut sum, mut sq) = (0u64, [0f64; 3], [0f64; 3]);
    for p in 0..n_paths {
        if scene.walk(&base, p, &mut v) {
            contrib += 1;
            for (k, t) in texels.iter().enumerate() {
                let c = v.iter().filter(|x| map.texel_of(x[0], x[1]) == *t).count() as f64;
                sum[k] += c;
                sq[k] += c * c;
            }
        }
    }
    let n = contrib as f64;
    assert!(contrib > 10_000, "{contrib}");
    for (k, t) in texels.iter().enumerate() {
        let kern = sum[k] / n;
        let kern_se = ((sq[k] / n - kern * kern) / n).sqrt();
        let (plus, minus) = (perturbed(*t, 1.0 + eps), perturbed(*t, 1.0 - eps));
        let (mut dsum, mut dsq) = (0f64, 0f64);
        for p in 0..n_paths {
            let d = scene.walk(&plus, p, &mut v) as i32 - scene.walk(&minus, p, &mut v) as i32;
            dsum += d as f64;
            dsq += (d * d) as f64;
        }
        let np = n_paths as f64;
        let m0 = n / np;
        let fd = dsum / np / (2.0 * eps * m0);
        let fd_se = ((dsq / np - (dsum / np).powi(2)) / np).sqrt() / (2.0 * eps * m0);
        eprintln!(
            "texel {t:?}: vertices/path {kern:.4} ± {kern_se:.4}, ∂ln M/∂ln α {fd:.4} ± {fd_se:.4}"
        );
        // Central difference in α (not ln α): O(ε²) relative, < 1 % here.
        assert!(
            (fd - kern).abs() < Z_MC * kern_se.hypot(fd_se) + 0.01 * kern,
            "texel {t:?}: vertices {kern:.4} ± {kern_se:.4}, finite difference {fd:.4} ± {fd_se:.4}"
        );
        assert!(kern > 0.05, "texel {t:?} barely visited: {kern}");
    }
}

#[test]
fn hard_cases_stay_finite() {
    for (albedos, distances, rho) in [
        (vec![0.0, 1e-9, 1.0 - 1e-9, 1.0], vec![1e-6, 1.0, 50.0], 1.0),
        (vec![0.5, 0.99], vec![1e-6, 0.5, 50.0], 1e-3),
        (vec![0.5, 0.99], vec![1e-6, 0.5, 50.0], 1e3),
    ] {
        let mut c = config(&albedos, &distances, rho, 20_000, 5);
        c.max_events = 10_000;
        let d = doc(&c, None);
        for (ia, alpha) in albedos.iter().enumerate() {
            for (id, dist) in distances.iter().enumerate() {
                for class in VertexClass::ALL {
                    let h = d.histogram(ia, id, class);
                    assert!(
                        h.mass
                            .iter()
                            .chain(&h.sigma)
                            .all(|x| x.is_finite() && *x >= 0.0),
                        "α {alpha} d {dist} ρ {rho}"
                    );
                    let total = h.mass.iter().sum::<f64>() + h.overflow;
                    assert!(h.paths == 0 || (total - 1.0).abs() < 1e-9);
                    assert!(h.mean_u.is_finite() && h.mean_v2.is_finite());
                }
            }
        }
    }
    // α = 0: nothing scatters twice.
    let c = config(&[0.0], &[1.0], 1.0, 20_000, 5);
    assert_eq!(doc(&c, None).tally.cells[0][0].paths, 0);
}

#[test]
fn bad_configurations_are_refused() {
    let good = config(&[0.5], &[1.0, 2.0], 1.0, 100, 1);
    assert!(good.validate().is_ok());
    // The library names the parameter (the CLI names its flag).
    let name = |c: &KernelConfig| match c.validate() {
        Err(svkernel::Error::Param { name, .. }) => name,
        other => panic!("expected a parameter error, got {other:?}"),
    };
    let mut c = good.clone();
    c.distances = vec![1.0, 1.1]; // overlapping bins
    assert_eq!(name(&c), "distances");
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("1,1.1") && !e.contains('['), "{e}");
    let mut c = good.clone();
    c.albedos = vec![1.2];
    assert_eq!(name(&c), "albedos");
    let mut c = good.clone();
    c.rel_width = 1.5;
    assert_eq!(name(&c), "rel_width");
    let mut c = good.clone();
    c.max_events = 0;
    assert_eq!(name(&c), "max_events");
    let mut c = good;
    c.density = 0.0;
    assert_eq!(name(&c), "density");
}

#[test]
fn corrupted_kernel_documents_are_named() {
    let c = config(&[0.5], &[1.0], 1.0, 1000, 1);
    let d = doc(&c, None);
    let dir = std::env::temp_dir().join(format!("svk-kern-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("k.json");
    svkernel::jobs::store::write_json_atomic(&p, &d).unwrap();
    assert_eq!(KernelDoc::load(&p).unwrap(), d);
    let text = std::fs::read_to_string(&p).unwrap();
    std::fs::write(&p, &text[..text.len() / 2]).unwrap();
    let e = KernelDoc::load(&p).unwrap_err().to_string();
    assert!(e.contains("k.json") && e.contains("truncated"), "{e}");
    let mut bad = d.clone();
    bad.tally.cells[0][0].classes[0].count.pop();
    svkernel::jobs::store::write_json_atomic(&p, &bad).unwrap();
    let e = KernelDoc::load(&p).unwrap_err().to_string();
    assert!(e.contains("tally.cells"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A tally of one albedo overlaid on a tally of two replaces exactly that
/// albedo's cells; one of other distances or of an albedo the first lacks
/// is refused with an error naming its file and the key.
#[test]
fn an_overlay_replaces_the_cells_at_its_albedos() {
    let base = doc(&config(&[0.7, 0.95], &[0.5, 2.0], 1.0, 16384, 9), None);
    let over = doc(&config(&[0.95], &[0.5, 2.0], 1.0, 32768, 10), None);
    assert_ne!(base.tally.cells[1], over.tally.cells[0]);
    let mut d = base.clone();
    let path = std::path::Path::new("over.json");
    assert_eq!(d.overlay(&over, path).unwrap(), vec![0.95]);
    assert_eq!(d.tally.cells[0], base.tally.cells[0]);
    assert_eq!(d.tally.cells[1], over.tally.cells[0]);
    assert_eq!(
        d.histogram(1, 1, VertexClass::All),
        over.histogram(0, 1, VertexClass::All)
    );
    let s = d.summary.iter().find(|s| s.albedo == 0.95 && s.d == 2.0);
    assert_eq!(s.unwrap().paths, over.tally.cells[0][1].paths);
    for (c, key) in [
        (
            config(&[0.95], &[0.5, 1.0], 1.0, 16384, 10),
            "config.distances",
        ),
        (
            config(&[0.8], &[0.5, 2.0], 1.0, 16384, 10),
            "config.albedos",
        ),
    ] {
        let mut d = base.clone();
        let e = d.overlay(&doc(&c, None), path).unwrap_err().to_string();
        assert!(e.contains("over.json") && e.contains(key), "{e}");
        assert_eq!(d, base);
    }
}

/// A constant density map walked with delta tracking is bitwise the plain
/// walk at that density (no null collisions: p = 1).
/// Walks paths 0..20 000 of seed 4 (pencil beam) with `a` and with `b` and
/// asserts both give bitwise the same fate, event count and vertices.
fn assert_same_walks(a: Walker<'_>, b: Walker<'_>) {
    for path in 0..20_000 {
        let (mut r1, mut r2) = (PathRng::new(4, path), PathRng::new(4, path));
        let s1 = launch(&Source::Pencil, 1.5, &mut r1).unwrap();
        let s2 = launch(&Source::Pencil, 1.5, &mut r2).unwrap();
        let (mut v1, mut v2) = (Vec::new(), Vec::new());
        assert_eq!(a(s1, &mut r1, &mut v1), b(s2, &mut r2, &mut v2));
        assert_eq!(v1, v2);
    }
}

/// A walk under test: start, stream, vertex sink → (fate, events).
type Walker<'a> =
    &'a dyn Fn(svkernel::forward::walk::Launched, &mut PathRng, &mut Vec<[f64; 3]>) -> (Fate, u32);

#[test]
fn delta_tracking_with_constant_density_is_the_plain_walk() {
    use svkernel::forward::maps::DensityMap;
    use svkernel::forward::walk::{UniformAlbedo, walk_delta};
    let medium = Medium::new(0.9, 0.3, 1.5, 2.0, None).unwrap();
    let albedo = UniformAlbedo(threshold_u32(0.9));
    let density = DensityMap::new(TexelMap::new(3, 3, 1.0, vec![2.0; 9]).unwrap()).unwrap();
    assert_same_walks(
        &|s, r, v| walk_general(&medium, &albedo, 10_000, s, r, |p, _| v.push(p)),
        &|s, r, v| walk_delta(&medium, &albedo, &density, 10_000, s, r, |p, _| v.push(p)),
    );
}

/// Exit probability and mean exit radius of `n` paths from `source`, each
/// walked by `walk`, with their standard errors: (p, σ_p, r̄, σ_r̄).
fn exit_stats(
    n: u64,
    seed: u64,
    source: &Source,
    walk: impl Fn(svkernel::forward::walk::Launched, &mut PathRng) -> Fate,
) -> (f64, f64, f64, f64) {
    let (mut exits, mut r_sum, mut r2_sum) = (0u64, 0.0, 0.0);
    for path in 0..n {
        let mut rng = PathRng::new(seed, path);
        let Some(s) = launch(source, 1.5, &mut rng) else {
            continue;
        };
        if let Fate::Exit { x, y } = walk(s, &mut rng) {
            exits += 1;
            let r = x.hypot(y);
            r_sum += r;
            r2_sum += r * r;
        }
    }
    let p = exits as f64 / n as f64;
    let mean_r = r_sum / exits as f64;
    let var_r = r2_sum / exits as f64 - mean_r * mean_r;
    (
        p,
        (p * (1.0 - p) / n as f64).sqrt(),
        mean_r,
        (var_r / exits as f64).sqrt(),
    )
}

/// Null collisions are unbiased: a majorant four times the density (one far
/// texel at 4ρ) leaves the exitance statistics unchanged.
#[test]
fn null_collisions_do_not_bias_the_walk() {
    use svkernel::forward::maps::DensityMap;
    use svkernel::forward::walk::{UniformAlbedo, walk_delta};
    let medium = Medium::new(0.9, 0.3, 1.5, 1.0, None).unwrap();
    let albedo = UniformAlbedo(threshold_u32(0.9));
    let mut values = vec![1.0; 9];
    values[0] = 4.0; // texel (0, 0) at x < −500, y > 500: never reached
    let density = DensityMap::new(TexelMap::new(3, 3, 1000.0, values).unwrap()).unwrap();
    let n = 400_000u64;
    let run = |delta: bool, seed: u64| {
        exit_stats(n, seed, &Source::Pencil, |s, rng| {
            if delta {
                walk_delta(&medium, &albedo, &density, 100_000, s, rng, |_, _| {}).0
            } else {
                walk_general(&medium, &albedo, 100_000, s, rng, |_, _| {}).0
            }
        })
    };
    let (p1, s1, r1, e1) = run(false, 1);
    let (p2, s2, r2, e2) = run(true, 2);
    assert!(
        (p1 - p2).abs() < Z_MC * s1.hypot(s2),
        "{p1} ± {s1} vs {p2} ± {s2}"
    );
    assert!(
        (r1 - r2).abs() < Z_MC * e1.hypot(e2),
        "{r1} ± {e1} vs {r2} ± {e2}"
    );
}

/// The grid walk with a constant density in one cell (a 1 × 1 map of ρ = 1;
/// a 5 × 3 map of ρ = 2) is the plain walk at that density, vertex by
/// vertex. (Smaller cells split flights at their faces, which changes the
/// last bits of the flight length.)
#[test]
fn grid_walk_with_constant_density_is_the_plain_walk() {
    use svkernel::forward::maps::{DensityMap, MajorantGrid};
    use svkernel::forward::walk::{UniformAlbedo, walk_grid};
    let albedo = UniformAlbedo(threshold_u32(0.9));
    for (rho, map, cells) in [
        (1.0, TexelMap::new(1, 1, 1.0, vec![1.0]), 1),
        (2.0, TexelMap::new(5, 3, 0.5, vec![2.0; 15]), 5),
    ] {
        let medium = Medium::new(0.9, 0.3, 1.5, rho, None).unwrap();
        let grid = MajorantGrid::new(&DensityMap::new(map.unwrap()).unwrap(), cells);
        assert!(grid.is_exact());
        assert_same_walks(
            &|s, r, v| walk_general(&medium, &albedo, 10_000, s, r, |p, _| v.push(p)),
            &|s, r, v| walk_grid(&medium, &albedo, &grid, 10_000, s, r, |p, _| v.push(p)),
        );
    }
}

/// Every free-flight sampler is exact for the same heterogeneous walk: over
/// a density checker (ρ = 0.25 | 4, texels of 0.5 MFP) under a smooth ramp
/// (×1 … ×2 across x), delta tracking ([`walk_delta`], the kernel
/// estimator's) and majorant grids of 2 (majorant 4·ramp in every cell), 3
/// (cells straddling texels) and 16 texels (one cell) give the exit
/// probability and mean exit radius of regular tracking (cells of one
/// texel) within 4σ.
#[test]
fn every_tracking_agrees_with_regular_tracking() {
    use svkernel::forward::maps::{DensityMap, MajorantGrid};
    use svkernel::forward::walk::{UniformAlbedo, walk_delta, walk_grid};
    let medium = Medium::new(0.9, 0.3, 1.5, 1.0, None).unwrap();
    let albedo = UniformAlbedo(threshold_u32(0.9));
    let n_side = 16;
    let values = (0..n_side * n_side)
        .map(|k| {
            let ramp = 1.0 + (k % n_side) as f64 / n_side as f64;
            ramp * if (k / n_side + k % n_side) % 2 == 0 {
                0.25
            } else {
                4.0
            }
        })
        .collect();
    let density = DensityMap::new(TexelMap::new(n_side, n_side, 0.5, values).unwrap()).unwrap();
    let n = 150_000u64;
    let source = Source::Collimated { radius: 1.0 };
    let grid = |cell: usize| {
        let g = MajorantGrid::new(&density, cell);
        move |s, rng: &mut PathRng| walk_grid(&medium, &albedo, &g, 100_000, s, rng, |_, _| {}).0
    };
    let (p0, e0, m0, f0) = exit_stats(n, 1, &source, grid(1));
    let delta =
        |s, rng: &mut PathRng| walk_delta(&medium, &albedo, &density, 100_000, s, rng, |_, _| {}).0;
    let others = [
        ("delta", exit_stats(n, 2, &source, delta)),
        ("cells 2", exit_stats(n, 3, &source, grid(2))),
        ("cells 3", exit_stats(n, 4, &source, grid(3))),
        ("cells 16", exit_stats(n, 5, &source, grid(16))),
    ];
    for (name, (p, e, m, f)) in others {
        assert!(
            (p0 - p).abs() < 4.0 * e0.hypot(e),
            "{name}: R_d {p0} ± {e0} vs {p} ± {e}"
        );
        assert!(
            (m0 - m).abs() < 4.0 * f0.hypot(f),
            "{name}: mean r {m0} ± {f0} vs {m} ± {f}"
        );
    }
}

/// The normalization of the angularly biased direction density,
/// N(ν) = ∫ p_HG(ω·ω′)/(1 − βω′·e) dω′, against a direct quadrature over
/// the sphere (cos θ′ about ω by Gauss-free midpoints, φ′ uniform), and its
/// closed form artanh(β)/β at g = 0.
#[test]
fn the_angular_bias_normalization_matches_quadrature() {
    use std::f64::consts::PI;
    let hg = |g: f64, c: f64| (1.0 - g * g) / (4.0 * PI * (1.0 + g * g - 2.0 * g * c).powf(1.5));
    for beta in [0.2, 0.6, 0.9, 0.985] {
        let iso = AngularBias::new(beta, 0.0);
        for nu in [-1.0, -0.3, 0.0, 0.5, 1.0] {
            let n = iso.norm(nu);
            let exact = beta.atanh() / beta;
            assert!(
                (n / exact - 1.0).abs() < 1e-12,
                "β {beta} ν {nu}: {n} against {exact}"
            );
        }
        for g in [0.3, -0.5, 0.8] {
            let bias = AngularBias::new(beta, g);
            for nu in [-1.0f64, -0.6, 0.0, 0.4, 0.95, 1.0] {
                // ω in the (e, z) plane at cos ν to e; ω′ by (cos θ′, φ′) about it.
                let (nt, mphi) = (4000, 720);
                let s_nu = (1.0 - nu * nu).max(0.0).sqrt();
                let mut sum = 0.0;
                for i in 0..nt {
                    let c = -1.0 + (i as f64 + 0.5) * 2.0 / nt as f64;
                    let s = (1.0 - c * c).sqrt();
                    let mut ring = 0.0;
                    for j in 0..mphi {
                        let phi = (j as f64 + 0.5) * 2.0 * PI / mphi as f64;
                        // ω = (ν, 0, s_ν); a perpendicular pair (−s_ν, 0, ν), (0, 1, 0).
                        let mu = c * nu - s * phi.cos() * s_nu;
                        ring += 1.0 / (1.0 - beta * mu);
                    }
                    sum += hg(g, c) * ring * (2.0 * PI / mphi as f64) * (2.0 / nt as f64);
                }
                let n = bias.norm(nu);
                assert!(
                    (n / sum - 1.0).abs() < 2e-4,
                    "β {beta} g {g} ν {nu}: {n} against {sum}"
                );
            }
        }
    }
}

/// One biased direction draw is unbiased on its own: over draws from
/// p_HG(ω·ω′)/((1 − βμ′)N(ν)) with ratio N(ν)(1 − βμ′), the mean ratio is 1
/// and the mean of ratio·ω′ is the phase function's mean direction g·ω.
#[test]
fn a_biased_direction_draw_keeps_the_phase_functions_moments() {
    let (beta, g) = (0.9, 0.3);
    let bias = AngularBias::new(beta, g);
    let (x, y) = (1.2, -0.7);
    let r = f64::hypot(x, y);
    let w_in = {
        let v: [f64; 3] = [0.3, 0.8, -0.5];
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|c| c / n)
    };
    let norm = bias.norm((w_in[0] * x + w_in[1] * y) / r);
    let n = 400_000u64;
    let (mut s1, mut s1sq) = (0.0, 0.0);
    let mut sw = [0.0f64; 3];
    let mut sw_sq = [0.0f64; 3];
    for i in 0..n {
        let mut rng = PathRng::new(11, i);
        // The phase function's own first proposal, as the walk makes it.
        let c = svkernel::forward::sampling::sample_hg_cos(g, rng.uniform());
        let phi = 2.0 * std::f64::consts::PI * rng.uniform();
        let first = svkernel::forward::sampling::rotate_direction(w_in, c, phi);
        let (w, ln_ratio) = bias.sample(x, y, norm, w_in, first, &mut rng);
        let q = ln_ratio.exp();
        s1 += q;
        s1sq += q * q;
        for k in 0..3 {
            sw[k] += q * w[k];
            sw_sq[k] += (q * w[k]).powi(2);
        }
    }
    let nf = n as f64;
    let check = |sum: f64, sum_sq: f64, exact: f64, what: &str| {
        let m = sum / nf;
        let se = ((sum_sq / nf - m * m) / nf).sqrt();
        assert!(
            (m - exact).abs() < Z_MC * se,
            "{what}: {m} against {exact} (se {se})"
        );
    };
    check(s1, s1sq, 1.0, "mean ratio");
    for k in 0..3 {
        check(sw[k], sw_sq[k], g * w_in[k], "mean ratio·ω′");
    }
}

/// At α = 0.6 the exponential transform alone leaves a cell 14 MFP away
/// with heavy-tailed weights; offered the angular bias, the plan takes it
/// there, and the run fills the cell.
#[test]
fn a_plan_takes_the_angular_bias_for_a_far_cell_at_mid_albedo() {
    let c = config(&[0.6], &[1.0, 14.0], 1.0, 1, 53);
    let opts = PlanOptions {
        target: 300.0,
        max_paths: 1 << 22,
        angular_fractions: vec![0.9],
        ..Default::default()
    };
    let (planned, cells) = c.plan(&opts, false).unwrap();
    let far = cells.iter().find(|p| p.d == 14.0).unwrap();
    assert!(far.flights.angular, "{far:?}");
    let (tally, _) = planned.run(None, &RunOptions::default()).unwrap();
    let n_eff = tally.cells[0][1].effective_paths();
    assert!(n_eff > 0.5 * opts.target, "{n_eff} effective paths");
    // Without it, the same budget leaves the cell short.
    let (plain, _) = c
        .plan(
            &PlanOptions {
                angular_fractions: Vec::new(),
                ..opts.clone()
            },
            false,
        )
        .unwrap();
    let (tally, _) = plain.run(None, &RunOptions::default()).unwrap();
    let plain_eff = tally.cells[0][1].effective_paths();
    assert!(plain_eff < 0.5 * n_eff, "{plain_eff} against {n_eff}");
}
