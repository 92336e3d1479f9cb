//! Reference values (exact H-function results and adding-doubling tables), as data: the tests and the demo
//! compare simulations with them. Lengths in MFP; R_d excludes the specular
//! reflection.

/// Albedos of the R_d tables.
pub const ALBEDOS: [f64; 11] = [0.01, 0.1, 0.2, 0.3, 0.5, 0.7, 0.8, 0.9, 0.95, 0.99, 0.999];

/// η = 1, g = 0: R_d = 1 − H(1)·sqrt(1 − α), exact (5 decimals).
pub const RD_ETA1_G0: [f64; 11] = [
    0.00154, 0.01639, 0.03523, 0.05721, 0.11523, 0.20868, 0.28525, 0.41495, 0.53554, 0.75272,
    0.91285,
];
/// η = 1, g = 0: spherical albedo (reflectance under diffuse illumination), exact.
pub const SPHERICAL_ETA1_G0: [f64; 11] = [
    0.00206, 0.02170, 0.04626, 0.07445, 0.14654, 0.25656, 0.34187, 0.47802, 0.59667, 0.79456,
    0.92971,
];
/// Adding-doubling, η = 1, g = 0.3.
pub const RD_ETA1_G03: [f64; 11] = [
    0.00081, 0.00886, 0.01975, 0.03335, 0.07328, 0.14767, 0.21574, 0.34174, 0.46780, 0.70958,
    0.89624,
];
/// Adding-doubling, η = 1.5, g = 0.
pub const RD_ETA15_G0: [f64; 11] = [
    0.00052, 0.00561, 0.01234, 0.02057, 0.04429, 0.08898, 0.13209, 0.22008, 0.32132, 0.56219,
    0.80158,
];
/// Adding-doubling, η = 1.5, g = 0.3: the project's default medium.
pub const RD_ETA15_G03: [f64; 11] = [
    0.00023, 0.00261, 0.00602, 0.01057, 0.02545, 0.05809, 0.09301, 0.17034, 0.26572, 0.51090,
    0.77493,
];

/// Stated accuracy of a table entry: half a unit of the last printed digit
/// for exact values; ±0.0005 for adding-doubling (±0.002 for α ≥ 0.99).
pub fn accuracy(exact: bool, alpha: f64) -> f64 {
    if exact {
        5e-6
    } else if alpha >= 0.99 {
        0.002
    } else {
        0.0005
    }
}

/// Single scattering only, R_ss/α (Fresnel in and out): (η, g, value).
pub const RSS_OVER_ALPHA: [(f64, f64, f64); 4] = [
    (1.0, 0.0, 0.153426),
    (1.0, 0.3, 0.08014),
    (1.5, 0.0, 0.05147),
    (1.5, 0.3, 0.02277),
];

/// van de Hulst slab: optical thickness 2, α = 0.9, g = 0.75, η = 1, normal
/// incidence: (R_d, total transmission including the unscattered e⁻²).
pub const VAN_DE_HULST: (f64, f64) = (0.09739, 0.66096);

/// The oracle R_d of a table at `alpha`, if `alpha` is one of [`ALBEDOS`].
pub fn lookup(table: &[f64; 11], alpha: f64) -> Option<f64> {
    ALBEDOS
        .iter()
        .position(|&a| (a - alpha).abs() < 1e-12)
        .map(|i| table[i])
}

/// The default-medium table (η = 1.5, g = 0.3) interpolated linearly in
/// sqrt(1 − α): a rough guide (used to plan path counts), not an oracle.
pub fn default_medium_rd_guide(alpha: f64) -> f64 {
    let x = |a: f64| (1.0 - a).max(0.0).sqrt();
    let xs: Vec<f64> = ALBEDOS.iter().map(|&a| x(a)).collect();
    let t = x(alpha);
    // xs decreases with α; extend with (α = 1, R_d = 0.96) at x = 0.
    let (mut px, mut py) = (0.0, 0.96);
    for i in (0..11).rev() {
        if t <= xs[i] {
            let f = (t - px) / (xs[i] - px);
            return py + f * (RD_ETA15_G03[i] - py);
        }
        px = xs[i];
        py = RD_ETA15_G03[i];
    }
    RD_ETA15_G03[0] * alpha / 0.01
}
