//! A refit from a tally: simulate path densities at a few albedos and
//! distances (in memory, 2e6 paths), fit a small meta-model to them
//! (K = 2 Gaussians, degrees 1 in ln d and √(1 − α)), and compare its
//! kernels with the shipped meta-model's at a trained point.
//!
//! `cargo run --release --example refit`
use svkernel::forward::runner::chunk_range;
use svkernel::prelude::*;
use svkernel::provenance::Provenance;

fn main() -> svkernel::Result<()> {
    let config = KernelConfig {
        albedos: vec![0.8, 0.9, 0.95],
        distances: vec![0.5, 1.0, 2.0],
        paths: 2_000_000,
        seed: 11,
        runs: Vec::new(),
        ..svkernel::jobs::shipped::training_config()
    };
    config.validate()?;
    let (tally, wall_s) = config.run(None, &RunOptions::default())?;
    let chunks = vec![chunk_range(config.paths, None)];
    let doc = KernelDoc::new(config, None, chunks, tally, wall_s, Provenance::current());
    println!("simulated {} paths in {wall_s:.1} s", doc.paths);
    let (model, fit) = fit_metamodel(&doc, 2, (1, 1), false)?;
    for j in &fit.joint {
        println!(
            "{}: {} after {} evaluations, χ²/dof = {:.2}",
            j.what, j.termination, j.evaluations, j.chi2_per_dof
        );
    }
    let worst = fit
        .aggregation
        .iter()
        .map(|r| r.meta)
        .fold(0.0f64, f64::max);
    println!("worst aggregation error of the refit over its cells: {worst:.4} (albedo units)");
    let shipped = Models::builtin()?.meta;
    let (d, alpha) = (1.0, 0.9);
    for (name, m) in [("refit  ", &model), ("shipped", &*shipped)] {
        let g = m.eval(VertexClass::All, d, alpha, 1.0).gmm;
        let mean_t: f64 = g.components.iter().map(|c| c.weight * c.t).sum();
        println!("{name}: kernel mean t at d = {d}, α = {alpha}: {mean_t:+.3} MFP");
    }
    Ok(())
}
