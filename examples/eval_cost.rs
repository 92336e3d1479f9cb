//! The cost of evaluating S(x_i, x_e) over many pairs from the library: the
//! per-pair time that the Python package's vectorised `SvBssrdf.eval` is
//! measured against (`tools/python_eval_cost.py` runs both).
//!
//! `cargo run --release --example eval_cost -- ALBEDO.npy PAIRS.npy TEXEL METHOD`
//!
//! `ALBEDO.npy` is a float64 `(ny, nx)` map, `PAIRS.npy` float64 `(N, 4)`
//! rows (x_i, y_i, x_e, y_e) in MFP. Prints the best of three timings in
//! ns per pair and the sum of the values (to compare with Python's).
use ndarray::{Array2, Ix2};
use std::sync::Arc;
use std::time::Instant;
use svkernel::prelude::*;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [albedo, pairs, texel, method] = args.as_slice() else {
        anyhow::bail!("usage: eval_cost ALBEDO.npy PAIRS.npy TEXEL METHOD");
    };
    let a: Array2<f64> = ndarray_npy::read_npy::<_, ndarray::Array<f64, Ix2>>(albedo)?;
    let p: Array2<f64> = ndarray_npy::read_npy(pairs)?;
    let (ny, nx) = a.dim();
    let map = TexelMap::new(nx, ny, texel.parse()?, a.iter().copied().collect())?;
    let models = Models::builtin()?;
    let s = SvBssrdf::new(
        Method::parse(method)?,
        Variant::default(),
        Arc::new(BasisTable::new(&models.basis)),
        Some(models.meta.clone()),
        vec![map],
        Density::Constant(1.0),
    )?;
    let mut best = f64::INFINITY;
    let mut sum = 0.0;
    for _ in 0..3 {
        let mut scratch = Scratch::default();
        let start = Instant::now();
        let mut out = Vec::with_capacity(p.nrows());
        for r in p.rows() {
            out.push(s.eval(0, [r[0], r[1]], [r[2], r[3]], &mut scratch));
        }
        best = best.min(start.elapsed().as_secs_f64());
        sum = out.iter().sum();
    }
    println!(
        "{{\"ns_per_pair\": {}, \"pairs\": {}, \"sum\": {sum:e}}}",
        best * 1e9 / p.nrows() as f64,
        p.nrows()
    );
    Ok(())
}
