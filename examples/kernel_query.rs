//! A kernel query: where the light paths from x_i to x_e at distance d
//! scatter, as a Gaussian mixture in the pair frame (t along x_i → x_e,
//! s across; MFP), from the learned meta-model and the fixed manual kernel.
//!
//! `cargo run --release --example kernel_query`
use svkernel::prelude::*;

fn main() -> svkernel::Result<()> {
    let models = Models::builtin()?;
    for (d, alpha, rho) in [
        (0.5, 0.9, 1.0),
        (1.0, 0.9, 1.0),
        (4.0, 0.99, 1.0),
        (1.0, 0.9, 4.0),
    ] {
        let q = models.meta.eval(VertexClass::All, d, alpha, rho);
        println!(
            "d = {d} MFP, α = {alpha}, ρ = {rho}{}",
            if q.clamped {
                " (outside the trained range: clamped)"
            } else {
                ""
            }
        );
        println!("  learned: {}", q.gmm);
        println!("  manual : {}", manual_kernel(d));
        let mean_t: f64 = q.gmm.components.iter().map(|c| c.weight * c.t).sum();
        println!("  learned mean t = {mean_t:+.3} MFP (x_e is at t = {d})");
    }
    Ok(())
}
