//! The SV-BSSRDF inside a minimal shading loop: the exitance M(x_e) along a
//! line across an albedo edge (0.3 | 0.95) lit by a disk light of radius
//! 1 MFP, by Monte Carlo over entry points x_i that the BSSRDF itself
//! importance-samples for each x_e:
//!
//! M(x_e) = ∫_disk E·S(x_i, x_e) dA(x_i) ≈ (1/n) Σ E·S(x_i, x_e)·1[x_i ∈ disk] / p(x_i).
//!
//! `cargo run --release --example shading_loop`
use std::sync::Arc;
use svkernel::forward::rng::PathRng;
use svkernel::prelude::*;

fn main() -> svkernel::Result<()> {
    let models = Models::builtin()?;
    let basis = Arc::new(BasisTable::new(&models.basis));
    // 160 × 160 texels of 0.05 MFP: albedo 0.3 for x < 0, 0.95 for x ≥ 0.
    let (n, tau) = (160usize, 0.05);
    let values = (0..n * n)
        .map(|k| if k % n < n / 2 { 0.3 } else { 0.95 })
        .collect();
    let albedo = TexelMap::new(n, n, tau, values)?;
    let (radius, irradiance, samples) = (1.0f64, 1.0, 4096u64);
    println!("exitance M(x_e) along y = 0 under a disk light of radius {radius} MFP");
    println!(
        "{:>6} {:>10} {:>10} {:>10}",
        "x_e", "point", "manual", "learned"
    );
    let methods = [Method::Point, Method::Manual, Method::Learned];
    let bssrdfs = methods
        .iter()
        .map(|&m| {
            SvBssrdf::new(
                m,
                Variant::default(),
                basis.clone(),
                Some(models.meta.clone()),
                vec![albedo.clone()],
                Density::Constant(1.0),
            )
        })
        .collect::<svkernel::Result<Vec<_>>>()?;
    let mut scratch = Scratch::default();
    for step in -4..=4 {
        let xe = [0.25 * step as f64, 0.0];
        let row: Vec<f64> = bssrdfs
            .iter()
            .map(|s| {
                let mut sum = 0.0;
                let sampler = s.entry_sampler(xe);
                for j in 0..samples {
                    // The same entry points for every method (one stream per sample).
                    let mut rng = PathRng::new(1, j);
                    let e = sampler.sample([rng.uniform(), rng.uniform()]);
                    if e.pdf > 0.0 && e.xi[0].hypot(e.xi[1]) <= radius {
                        sum += irradiance * s.eval(0, e.xi, xe, &mut scratch) / e.pdf;
                    }
                }
                sum / samples as f64
            })
            .collect();
        println!(
            "{:>6.2} {:>10.5} {:>10.5} {:>10.5}",
            xe[0], row[0], row[1], row[2]
        );
    }
    Ok(())
}
