#!/usr/bin/env python3
"""Cross-checks the texture designer's appearance M and its exact gradient
with JAX automatic differentiation (validation only).

    python3 tools/design_grad_check.py            # makes its own targets
    python3 tools/design_grad_check.py FILE.json  # one exported problem

Without arguments it writes a smooth random 20 x 16 target (.npy) into a
temporary folder and exports, with `svkernel design TARGET --export-check`,
the problem of every forward model (point, factorized, learned) under
uniform light and of `learned` under a disk light; then checks each.

The export holds the problem's definition, not its evaluation: the texel
grid, the light, the entry offsets delta_k and weights W_k, the basis
model's Chebyshev coefficients, the blur stack's levels (sigma, node grid)
and, for `learned`, the kernel reads (shift, sigma, share) that the fixed
anchor selects per (texel, offset). This script re-implements, in float64:

* the basis table: ln(A_j/(2 pi alpha^2)) = sum_n c_jn T_n(2x - 1) and
  B_j = exp(ln b_min + ln(b_max/b_min) sigmoid(sum_n d_jn T_n(2x - 1))) at
  `table_nodes` values of x = sqrt(1 - alpha), linearly interpolated in x;
  R_m/alpha^2 = sum_j exp(ln A_j - B_j r); R_1 = p_1(r)/(2 pi r);
* the stack: level 0 the texels at their centres; level l >= 1 the texel
  map (edge texels extended) convolved with a Gaussian of width sigma_l,
  integrated over each texel exactly with the normal CDF along x and along
  y, at the level's nodes (no window: the Rust stencils drop < 2e-9 of the
  mass); a read of width sigma blends the two levels around sigma^2
  linearly in sigma^2 and interpolates each bilinearly with positions
  clamped to the node grid;
* M_e = sum_k W_k S_k over lit x_i = x_e + delta_k with
  point S = R(d; alpha_e), factorized S = sqrt(R(d; alpha_i) R(d; alpha_e)),
  learned S = alpha_i R_1 + l_i l_e R_m(d; alpha_t)/alpha_t^2 with alpha_t
  clamped to [0, 1] and l_i = alpha_i without a first-vertex model; R_1
  scaled by the exported single-scattering factor and R_m/alpha^2 by the
  exported normalisation c(alpha) (linear in sqrt(1 - alpha) between its
  nodes), which make the offsets integrate a homogeneous profile exactly;
* alpha_t in the exported space: linear, the mean of alpha under the
  all-vertex reads; otherwise two-scale, phi^-1(mean of phi(abar)) + mean
  of (alpha - abar), with abar the map (edge texels extended) convolved
  with the exported split kernel, a mixture of Gaussians (sigma, weight;
  sigma = 0 the texel itself), each integrated over each texel exactly at
  each texel centre (no window).

It checks M against the export (1e-8 relative to max |M|) and the
gradient of F = sum_e g_e M_e from jax.grad against the exported adjoint
(1e-6 relative to max |grad|, per texel). Prints PASS/FAIL; exits 1 on
failure.
"""
import json
import math
import os
import subprocess
import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.scipy.special import ndtr  # noqa: E402

M_TOL = 1e-8
GRAD_TOL = 1e-6


def chebyshev(t, degree):
    out = [jnp.ones_like(t), t]
    for _ in range(2, degree + 1):
        out.append(2 * t * out[-1] - out[-2])
    return jnp.stack(out[: degree + 1], axis=-1)


class Basis:
    def __init__(self, b):
        self.k = len(b["ln_a"])
        n = b["table_nodes"]
        self.n = n
        x = np.arange(n) / (n - 1)
        t = np.asarray(chebyshev(jnp.asarray(2 * x - 1), b["degree"]))
        ln_a = t @ np.asarray(b["ln_a"]).T - math.log(2 * math.pi)
        theta = t @ np.asarray(b["ln_b"]).T
        span = math.log(b["b_max"] / b["b_min"])
        rate = np.exp(math.log(b["b_min"]) + span / (1 + np.exp(-theta)))
        self.ln_a, self.rate = jnp.asarray(ln_a), jnp.asarray(rate)
        s = b["single"]
        self.single = (np.asarray(s["a"]), np.asarray(s["b"]), s.get("power", 0))

    def single_exitance(self, r):
        a, b, p = self.single
        return float(np.sum(a * r**p * np.exp(-b * r)) / (2 * math.pi * r))

    def multi_over_alpha2(self, r, alpha):
        """R_m(r; alpha)/alpha^2, the table linearly interpolated in x."""
        x = jnp.sqrt(1 - jnp.clip(alpha, 0.0, 1.0))
        u = x * (self.n - 1)
        i = jnp.minimum(jnp.floor(u), self.n - 2).astype(jnp.int32)
        f = u - i
        ln_a = self.ln_a[i] + f[..., None] * (self.ln_a[i + 1] - self.ln_a[i])
        b = self.rate[i] + f[..., None] * (self.rate[i + 1] - self.rate[i])
        return jnp.sum(jnp.exp(ln_a - b * r[..., None]), axis=-1)


def gaussian_weights(n, tau, sigma, nodes):
    """(nodes, n): the mass of each texel (edge texels extended) under the
    unit Gaussian of width sigma centred at each node."""
    e = -0.5 * n * tau + tau * np.arange(n + 1)
    cdf = ndtr((e[None, :] - nodes[:, None]) / sigma)
    cdf = cdf.at[:, 0].set(0.0).at[:, -1].set(1.0)
    return cdf[:, 1:] - cdf[:, :-1]


def stack_levels(p):
    """Per level (values from the map, read function)."""
    nx, ny, tau = p["nx"], p["ny"], p["texel"]
    out = []
    for lv in p["levels"]:
        gx = lv["x0"] + lv["h"] * np.arange(lv["nx"])
        gu = lv["u0"] + lv["h"] * np.arange(lv["ny"])
        if lv["sigma"] == 0.0:
            wx = wu = None
        else:
            wx = gaussian_weights(nx, tau, lv["sigma"], jnp.asarray(gx))
            # Rows of the map run along u = -y (row 0 at the top).
            wu = gaussian_weights(ny, tau, lv["sigma"], jnp.asarray(gu))
        out.append((lv, wx, wu))
    return out


def level_values(levels, amap):
    vals = []
    for lv, wx, wu in levels:
        vals.append(amap if wx is None else wu @ amap @ wx.T)
    return vals


def bilinear(lv, vals, x, y):
    def axis(v, v0, n):
        f = jnp.clip((v - v0) / lv["h"], 0.0, n - 1)
        k = jnp.minimum(jnp.floor(f), max(n - 2, 0)).astype(jnp.int32)
        return k, jnp.minimum(k + 1, n - 1), f - k

    i0, i1, fx = axis(x, lv["x0"], lv["nx"])
    j0, j1, fu = axis(-y, lv["u0"], lv["ny"])
    return (
        vals[j0, i0] * (1 - fx) * (1 - fu)
        + vals[j0, i1] * fx * (1 - fu)
        + vals[j1, i0] * (1 - fx) * fu
        + vals[j1, i1] * fx * fu
    )


def read(levels, vals, x, y, sigma):
    """(G_sigma * alpha)(x, y) blended between the levels around sigma^2."""
    sig = np.array([lv["sigma"] for lv, _, _ in levels])
    out = jnp.zeros_like(x)
    for l in range(len(levels) - 1):
        s0, s1 = sig[l], sig[l + 1]
        last = l == len(levels) - 2
        sel = (sigma >= s0) & ((sigma < s1) | last)
        if l == 0:
            sel = sel | (sigma < s0)
        if not np.any(sel):
            continue
        t = np.clip((sigma**2 - s0**2) / (s1**2 - s0**2), 0.0, 1.0)
        lo = bilinear(levels[l][0], vals[l], x, y)
        hi = bilinear(levels[l + 1][0], vals[l + 1], x, y)
        out = out + jnp.where(sel, (1 - t) * lo + t * hi, 0.0)
    return out


SPACES = {
    "linear": (lambda a: a, lambda y: y),
    "transport": (lambda a: jnp.sqrt(jnp.maximum(1 - a, 0.0)), lambda y: 1 - y * y),
    "log": (lambda a: jnp.log(jnp.maximum(a, 1e-6)), jnp.exp),
    "absorption": (lambda a: jnp.log(jnp.maximum(1 - a, 1e-6)), lambda y: 1 - jnp.exp(y)),
}


def check(p):
    nx, ny, tau = p["nx"], p["ny"], p["texel"]
    n = nx * ny
    basis = Basis(p["basis"])
    offs = np.asarray(p["offsets"])
    e = np.arange(n)
    xe = -0.5 * nx * tau + (e % nx + 0.5) * tau
    ye = 0.5 * ny * tau - (e // nx + 0.5) * tau
    # Per (texel, offset): entry point, its texel, lit, distance.
    xi = xe[:, None] + offs[None, :, 0]
    yi = ye[:, None] + offs[None, :, 1]
    col = np.clip(np.floor(xi / tau + 0.5 * nx), 0, nx - 1).astype(int)
    row = np.clip(np.floor(0.5 * ny - yi / tau), 0, ny - 1).astype(int)
    ti = row * nx + col
    light = p["illumination"]
    lit = np.ones_like(xi, bool)
    if light["kind"] == "disk":
        lit = xi**2 + yi**2 <= light["radius"] ** 2
    d = np.hypot(offs[:, 0], offs[:, 1])
    r = np.maximum(d, p["r_min"])
    w = offs[:, 2]
    # The quadrature's normalisation: single scattering by one factor, the
    # multiple term by c(alpha), linear in y = sqrt(1 - alpha) between the
    # exported nodes (flat beyond them).
    norm = p["normalisation"]
    single = norm["single"] * np.array([basis.single_exitance(v) for v in r])
    ys = np.linspace(norm["y"][0], norm["y"][1], len(norm["c"]))
    order = np.argsort(ys)
    ys, cs = jnp.asarray(ys[order]), jnp.asarray(np.asarray(norm["c"])[order])

    def multi(a):
        c = jnp.interp(jnp.sqrt(1 - jnp.clip(a, 0.0, 1.0)), ys, cs)
        return c * basis.multi_over_alpha2(jnp.asarray(r), a)
    method = p["method"]
    levels = stack_levels(p) if method == "learned" else None
    space = p.get("space", {"kind": "linear", "blur": 0.0})
    phi, phi_inv = SPACES[space["kind"]]
    cx = -0.5 * nx * tau + tau * (np.arange(nx) + 0.5)
    cu = -0.5 * ny * tau + tau * (np.arange(ny) + 0.5)
    # The split kernel: (sigma, weight) pairs, sigma = 0 the texel itself.
    split = [
        (w, None if sigma == 0 else (
            gaussian_weights(ny, tau, sigma, jnp.asarray(cu)),
            gaussian_weights(nx, tau, sigma, jnp.asarray(cx))))
        for sigma, w in space.get("split", [[space["blur"], 1.0]])
    ]

    def local_mean(a):
        return sum(w * (a if b is None else b[0] @ a @ b[1].T) for w, b in split)

    def means(vals, rows):
        """Per (texel, offset) sum of share * read over the exported reads."""
        rows = np.asarray(rows).reshape(-1, 6)
        ee, oo = rows[:, 0].astype(int), rows[:, 1].astype(int)
        x = xe[ee] + rows[:, 2]
        y = ye[ee] + rows[:, 3]
        v = rows[:, 5] * read(levels, vals, x, y, rows[:, 4])
        return jnp.zeros((n, len(offs))).at[ee, oo].add(v)

    def profile(a):
        return a * single + a * a * multi(a)

    def appearance(alpha):
        ai, ae = alpha[ti], alpha[:, None] * jnp.ones_like(xi)
        if method == "point":
            s = profile(ae)
        elif method == "factorized":
            s = jnp.sqrt(jnp.maximum(profile(ai) * profile(ae), 0.0))
        else:
            amap = alpha.reshape(ny, nx)
            vals = level_values(levels, amap)
            if space["kind"] == "linear":
                at = means(vals, p["reads_all"])
            else:
                abar = local_mean(amap)
                y = means(level_values(levels, phi(abar)), p["reads_all"])
                at = phi_inv(y) + means(level_values(levels, amap - abar), p["reads_all"])
            le = means(vals, p["reads_last"])
            li = means(vals, p["reads_first"]) if p["has_first"] else ai
            t = jnp.clip(at, 0.0, 1.0)
            s = ai * single + li * le * multi(t)
        return jnp.sum(jnp.where(lit, w * s, 0.0), axis=1)

    alpha = jnp.asarray(p["alpha"])
    g = jnp.asarray(p["g"])
    m = appearance(alpha)
    grad = jax.grad(lambda a: jnp.dot(g, appearance(a)))(alpha)
    m_rust, grad_rust = np.asarray(p["m"]), np.asarray(p["gradient"])
    m_err = float(np.max(np.abs(np.asarray(m) - m_rust)) / np.max(np.abs(m_rust)))
    scale = float(np.max(np.abs(grad_rust)))
    g_err = float(np.max(np.abs(np.asarray(grad) - grad_rust)) / scale)
    ok = m_err <= M_TOL and g_err <= GRAD_TOL and scale > 0
    print(
        f"{'PASS' if ok else 'FAIL'} {method:10s} {light['kind']:7s} {space['kind']:9s} {nx}x{ny}, "
        f"{len(offs)} offsets: M rel. diff {m_err:.1e} (tol {M_TOL:g}), "
        f"gradient rel. diff {g_err:.1e} (tol {GRAD_TOL:g}, max |grad| {scale:.3e})"
    )
    return ok


def exported_problems(folder):
    svkernel = os.environ.get("SVKERNEL_BIN", "./target/release/svkernel")
    rng = np.random.default_rng(7)
    # A smooth random target in [0.05, 0.6] (blurred noise), 20 x 16 texels.
    z = rng.standard_normal((16, 20))
    for _ in range(3):
        z = (z + np.roll(z, 1, 0) + np.roll(z, 1, 1) + np.roll(z, -1, 0) + np.roll(z, -1, 1)) / 5
    z = (z - z.min()) / (z.max() - z.min())
    target = os.path.join(folder, "target.npy")
    np.save(target, 0.05 + 0.55 * z)
    cases = [
        ("point", "uniform", "transport"),
        ("factorized", "uniform", "transport"),
        ("learned", "uniform", "transport"),
        ("learned", "disk:0.4", "transport"),
        ("learned", "uniform", "linear"),
    ]
    for method, light, space in cases:
        out = os.path.join(folder, f"{method}-{light.replace(':', '')}-{space}.json")
        subprocess.run(
            [svkernel, "design", target, "--export-check", out, "--texel", "0.05",
             "--method", method, "--illumination", light, "--quadrature", "6,3",
             "--albedo-space", space],
            check=True, stdout=subprocess.DEVNULL,
        )
        yield out


def main():
    if len(sys.argv) > 1:
        files = sys.argv[1:]
        ok = all([check(json.load(open(f))) for f in files])
    else:
        with tempfile.TemporaryDirectory() as folder:
            ok = all([check(json.load(open(f))) for f in exported_problems(folder)])
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
