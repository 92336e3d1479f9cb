//! The appearance of an albedo map under the learned SV-BSSRDF: the diffuse
//! reflectance at every texel centre under unit irradiance over the plane,
//! as `svkernel design` models it, for any map (a design's `albedo.npy`,
//! a texture of your own). The kernel shapes are anchored at the map
//! itself, as the renderer anchors them.
//!
//! ```sh
//! cargo run --release --example appearance -- MAP.npy OUT.npy \
//!     [--meta FILE] [--space transport|linear|log|absorption] [--blur 0.25] \
//!     [--quadrature 12,2] [--span LO,HI] [--texel 0.05]
//! ```
//!
//! MAP is a float64 `(ny, nx)` `.npy` of albedos; OUT gets M, same shape.
//! `--span` sets the albedos whose profiles place the quadrature offsets
//! (`design` takes the 2nd and 98th percentiles of its naive map).
use ndarray::Array2;
use ndarray_npy::{read_npy, write_npy};
use std::path::Path;
use svkernel::design::appearance::{Appearance, Illumination, Quadrature};
use svkernel::prelude::*;
use svkernel::render::svbssrdf::AlbedoSpace;

fn pair(s: &str) -> [f64; 2] {
    let v: Vec<f64> = s.split(',').map(|x| x.parse().expect("a number")).collect();
    [v[0], v[1]]
}

fn main() -> svkernel::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (map, out) = match args.as_slice() {
        [m, o, ..] => (m.clone(), o.clone()),
        _ => {
            eprintln!(
                "usage: appearance MAP.npy OUT.npy [--meta FILE] [--space S] [--blur B] [--quadrature R,A] [--span LO,HI] [--texel T]"
            );
            std::process::exit(2);
        }
    };
    let opt = |key: &str| {
        args.iter()
            .position(|a| a == key)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let models = Models::builtin()?;
    let meta = match opt("--meta") {
        Some(f) => MetaModelFile::load(Path::new(&f))?,
        None => (*models.meta).clone(),
    };
    let space = match opt("--space") {
        Some(s) => <AlbedoSpace as clap::ValueEnum>::from_str(&s, true).unwrap_or_else(|_| {
            eprintln!("--space {s}: expected transport, linear, log or absorption");
            std::process::exit(2);
        }),
        None => AlbedoSpace::Transport,
    };
    let blur: f64 = opt("--blur").map_or(0.25, |b| b.parse().expect("a number"));
    let [rings, angles] = pair(&opt("--quadrature").unwrap_or("12,2".into()));
    let span = pair(&opt("--span").unwrap_or("0.2,0.99".into()));
    let texel: f64 = opt("--texel").map_or(0.05, |t| t.parse().expect("a number"));
    let a: Array2<f64> = read_npy(&map).expect("a float64 (ny, nx) .npy");
    let (ny, nx) = a.dim();
    let alpha: Vec<f64> = a.iter().copied().collect();
    let quadrature = Quadrature {
        rings: rings as usize,
        angles: angles as usize,
    };
    let app = Appearance::new(
        Method::Learned,
        &models.basis,
        Some(&meta),
        nx,
        ny,
        texel,
        Illumination::Uniform,
        span,
        &quadrature,
    )?
    .with_albedo_space(space, blur)?;
    let m = app.appearance(&alpha, &app.anchor(&alpha));
    let mean = m.iter().sum::<f64>() / m.len() as f64;
    write_npy(&out, &Array2::from_shape_vec((ny, nx), m).expect("shape")).expect("writable");
    println!("wrote {out}: {nx}×{ny}, mean appearance {mean:.5}");
    Ok(())
}
