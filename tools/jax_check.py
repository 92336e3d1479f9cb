#!/usr/bin/env python3
"""Cross-checks the meta-model fit's residuals, gradient and Jacobian with JAX
automatic differentiation (validation only).

    ./target/release/svkernel fit export-kernels --vertices all --out /tmp/kexp.json
    python3 tools/jax_check.py /tmp/kexp.json

Re-implements the weighted residuals of src/fit/meta.rs (MetaFit) on top of
src/fit/gmm.rs (GmmFit) independently, in float64, as a function of the flat
coefficient vector C (index j*n_coeffs + a):

* cell c with distance d, lambda = d/2 + 1, exported basis row B_a:
  theta_m,j = sum_a C_{ja} B_a;
  logits eta = (0, theta_m[0..K-1]) -> softmax weights w_k;
  centres t_k = d/2 + lambda*theta_m[K-1+k];
  widths sigma_k = exp(ln lambda + theta_m[2K-1+k]);
* bin (i, j): m = sum_k w_k T_k(i) S_k(j) with
  T_k(i) = Phi((t_{i+1}-t_k)/sigma_k) - Phi((t_i-t_k)/sigma_k),
  S_k(j) = 2[Phi(s_{j+1}/sigma_k) - Phi(s_j/sigma_k)];
  overflow o = sum_k w_k q_k, q_k = (1 - T_tot) + T_tot (1 - S_tot);
  residual (m - y)/scale (floored standard errors, exported);
  if the cell has whole-plane moments (t, s), two more residuals
  W (sum_k w_k mu_k - t)/tol_t and W ln(sqrt(sum_k w_k sigma_k^2)/s)/tol_s;
* then the ridge residuals w*C_{ja} for every j and a >= 1 (j-major).

Checks against the Rust export:
  (a) residuals (max difference relative to max |r|, and per entry),
  (b) J^T r from jax.jacfwd and from jax.vjp against `grad`, to 1e-6 relative
      (norm-wise, and per entry relative to max |grad|),
  (c) each exported Jacobian column against jax.jacfwd, to 1e-6 relative to
      the column's norm.
Also checks that each exported basis row is a tensor Chebyshev row
T_a(x) T_b(y) and that x is affine in ln d and y affine in sqrt(1 - alpha)
over the exported cells. Prints PASS/FAIL; exits 1 on failure.
"""
import json
import math
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.scipy.special import erf, erfc  # noqa: E402

TOL = 1e-6
RESID_TOL = 1e-9
INV_SQRT2 = 1.0 / math.sqrt(2.0)


def std_normal_mass(za, zb):
    """Phi(zb) - Phi(za), taken between complements in either tail (as
    src/metamodel/kernel.rs std_normal_mass), so far-tail masses keep their
    relative precision."""
    upper = 0.5 * (erfc(za * INV_SQRT2) - erfc(zb * INV_SQRT2))
    lower = 0.5 * (erfc(-zb * INV_SQRT2) - erfc(-za * INV_SQRT2))
    middle = 0.5 * (erf(zb * INV_SQRT2) - erf(za * INV_SQRT2))
    return jnp.where(za >= 0.0, upper, jnp.where(zb <= 0.0, lower, middle))


def gmm_residuals(eta_free, mu, log_sig, cell):
    """Weighted residuals (bins row-major, then the overflow) of one histogram
    for a K-component on-axis mixture: logits (0, eta_free), centres mu,
    log widths log_sig (all jnp arrays)."""
    te, se = cell["te"], cell["se"]
    eta = jnp.concatenate([jnp.zeros(1), eta_free])
    e = jnp.exp(eta - jnp.max(eta))
    w = e / jnp.sum(e)
    sig = jnp.exp(jnp.clip(log_sig, -300.0, 300.0))
    # [k, i]: T_k(i); [k, j]: S_k(j).
    zt = (te[None, :] - mu[:, None]) / sig[:, None]
    zs = se[None, :] / sig[:, None]
    T = std_normal_mass(zt[:, :-1], zt[:, 1:])
    S = 2.0 * std_normal_mass(zs[:, :-1], zs[:, 1:])
    m = jnp.einsum("k,ki,kj->ij", w, T, S).reshape(-1)
    # Off-grid mass per component: (1 - T_tot) + T_tot (1 - S_tot).
    za, zb = zt[:, 0], zt[:, -1]
    t_tot = std_normal_mass(za, zb)
    t_out = std_normal_mass(-jnp.inf, za) + std_normal_mass(zb, jnp.inf)
    s_out = erfc(se[-1] / sig * INV_SQRT2) + erf(se[0] / sig * INV_SQRT2)
    q = t_out + t_tot * s_out
    o = jnp.sum(w * q)
    model = jnp.concatenate([m, o[None]])
    r = (model - cell["y"]) / cell["scale"]
    mom = cell.get("moments")
    if mom is None:
        return r
    # Whole-plane moments: W (sum w mu - t)/tol_t, W ln(sqrt(sum w sig^2)/s)/tol_s.
    (t_data, s_data), (tol_t, tol_s), wgt = mom["plane"], mom["tol"], mom["weight"]
    et = jnp.sum(w * mu)
    rs = jnp.sqrt(jnp.maximum(jnp.sum(w * sig * sig), 1e-300))
    extra = jnp.stack(
        [wgt * (et - t_data) / tol_t, wgt * jnp.log(rs / max(s_data, 1e-6)) / tol_s]
    )
    return jnp.concatenate([r, extra])


def load(path):
    p = json.load(open(path))
    k, (dx, dy) = p["k"], p["deg"]
    n = (dx + 1) * (dy + 1)
    np_ = 3 * k - 1
    assert len(p["coeffs"]) == np_ and all(len(c) == n for c in p["coeffs"])
    cells = []
    for c in p["cells"]:
        cells.append(
            {
                "d": float(c["d"]),
                "alpha": float(c["alpha"]),
                "basis": jnp.asarray(c["basis"], dtype=jnp.float64),
                "te": jnp.asarray(c["t_edges"], dtype=jnp.float64),
                "se": jnp.asarray(c["s_edges"], dtype=jnp.float64),
                "y": jnp.asarray(list(c["mass"]) + [c["overflow"]], dtype=jnp.float64),
                "scale": jnp.asarray(c["scale"], dtype=jnp.float64),
                "moments": c.get("moments"),
            }
        )
        nt, ns = len(c["t_edges"]) - 1, len(c["s_edges"]) - 1
        assert len(c["mass"]) == nt * ns and len(c["scale"]) == nt * ns + 1
    return p, k, (dx, dy), n, np_, cells


def make_residuals(k, n, np_, cells, ridge):
    def residuals(x):
        C = x.reshape(np_, n)
        out = []
        for c in cells:
            d = c["d"]
            lam = 0.5 * d + 1.0
            th = C @ c["basis"]  # theta_m, 3K - 1 values
            eta_free = th[: k - 1]
            mu = 0.5 * d + lam * th[k - 1 : 2 * k - 1]
            log_sig = math.log(lam) + th[2 * k - 1 :]
            out.append(gmm_residuals(eta_free, mu, log_sig, c))
        out.append(ridge * C[:, 1:].reshape(-1))
        return jnp.concatenate(out)

    return residuals


def cheb(t, deg):
    out = [1.0, t]
    while len(out) < deg + 1:
        out.append(2.0 * t * out[-1] - out[-2])
    return np.asarray(out[: deg + 1])


def check_basis(p, dx, dy):
    """The exported rows are T_a(x) T_b(y), x affine in ln d, y affine in
    sqrt(1 - alpha). Returns (max row mismatch, max affine-fit residual)."""
    worst_row, xs, ys, lnd, sq = 0.0, [], [], [], []
    for c in p["cells"]:
        b = np.asarray(c["basis"])
        x = b[1 * (dy + 1)] if dx >= 1 else 0.0
        y = b[1] if dy >= 1 else 0.0
        row = np.outer(cheb(x, dx), cheb(y, dy)).reshape(-1)
        worst_row = max(worst_row, float(np.max(np.abs(row - b))))
        xs.append(x)
        ys.append(y)
        lnd.append(math.log(c["d"]))
        sq.append(math.sqrt(1.0 - c["alpha"]))
    worst_fit = 0.0
    for u, v in ((lnd, xs), (sq, ys)):
        u, v = np.asarray(u), np.asarray(v)
        if np.ptp(u) > 0 and len(u) > 2:
            a = np.vstack([u, np.ones_like(u)]).T
            coef, *_ = np.linalg.lstsq(a, v, rcond=None)
            worst_fit = max(worst_fit, float(np.max(np.abs(a @ coef - v))))
    return worst_row, worst_fit


def main(path):
    p, k, (dx, dy), n, np_, cells = load(path)
    ridge = float(p["ridge"])
    x0 = jnp.asarray(np.asarray(p["coeffs"], dtype=float).reshape(-1))
    r_rust = np.asarray(p["residuals"], dtype=float)
    g_rust = np.asarray(p["grad"], dtype=float)
    print(
        f"{path}: K = {k}, degrees ({dx}, {dy}), {len(cells)} cells, "
        f"{x0.size} coefficients, {r_rust.size} residuals, ridge w = {ridge}"
    )
    ok = True

    brow, bfit = check_basis(p, dx, dy)
    good = brow <= 1e-12 and bfit <= 1e-9
    ok &= good
    print(
        f"[{'PASS' if good else 'FAIL'}] basis rows: max |row - T_a(x)T_b(y)| = {brow:.3g}; "
        f"max residual of the affine fits x(ln d), y(sqrt(1-alpha)) = {bfit:.3g}"
    )

    residuals = jax.jit(make_residuals(k, n, np_, cells, ridge))
    r = np.asarray(residuals(x0))
    assert r.shape == r_rust.shape, (r.shape, r_rust.shape)
    diff = np.abs(r - r_rust)
    rmax = float(np.max(np.abs(r_rust)))
    rel_max = float(np.max(diff)) / rmax
    per_entry = float(np.max(diff / np.maximum(np.abs(r_rust), 1.0)))
    chi2 = float(r @ r)
    chi2_rel = abs(chi2 - p["chi2"]) / p["chi2"]
    good = rel_max <= RESID_TOL and chi2_rel <= RESID_TOL
    ok &= good
    print(
        f"[{'PASS' if good else 'FAIL'}] (a) residuals: max |r_jax - r_rust| = {np.max(diff):.3g} "
        f"= {rel_max:.3g} of max |r| ({rmax:.4g}); max per entry |diff|/max(|r|,1) = {per_entry:.3g}; "
        f"chi2 jax = {chi2:.12g}, rust = {p['chi2']:.12g} (rel {chi2_rel:.3g})"
    )

    J = np.asarray(jax.jit(jax.jacfwd(residuals))(x0))
    g_fwd = J.T @ r
    _, vjp = jax.vjp(residuals, x0)
    (g_vjp,) = vjp(jnp.asarray(r))
    g_vjp = np.asarray(g_vjp)
    gscale = float(np.max(np.abs(g_rust)))
    gnorm = float(np.linalg.norm(g_rust))
    for name, g in (("jacfwd J^T r", g_fwd), ("vjp", g_vjp)):
        norm_rel = float(np.linalg.norm(g - g_rust)) / gnorm
        entry_rel = float(np.max(np.abs(g - g_rust))) / gscale
        worst = int(np.argmax(np.abs(g - g_rust)))
        good = norm_rel <= TOL and entry_rel <= TOL
        ok &= good
        print(
            f"[{'PASS' if good else 'FAIL'}] (b) gradient ({name}): ||g - g_rust||/||g_rust|| = {norm_rel:.3g}; "
            f"max_i |g_i - g_rust,i| / max|g_rust| = {entry_rel:.3g} (worst i = {worst}); "
            f"||g_rust|| = {gnorm:.4g}"
        )

    worst_col = 0.0
    lines = []
    for c, col in zip(p["jac_cols"], p["jac"]):
        col = np.asarray(col, dtype=float)
        cn = float(np.linalg.norm(col))
        e_norm = float(np.linalg.norm(J[:, c] - col)) / cn
        e_max = float(np.max(np.abs(J[:, c] - col))) / cn
        worst_col = max(worst_col, e_norm, e_max)
        lines.append(f"      column {c:4d} (j={c // n}, a={c % n}): ||col|| = {cn:.4g}, "
                     f"||diff||/||col|| = {e_norm:.3g}, max|diff|/||col|| = {e_max:.3g}")
    good = worst_col <= TOL
    ok &= good
    print(f"[{'PASS' if good else 'FAIL'}] (c) {len(p['jac_cols'])} Jacobian columns: "
          f"worst relative difference = {worst_col:.3g}")
    print("\n".join(lines))

    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} EXPORT.json")
    sys.exit(main(sys.argv[1]))
