#!/usr/bin/env python3
"""Cross-checks Levenberg-Marquardt's optimum of one exponential-mixture fit
with NLopt (validation only).

    cargo run --release -- fit export --albedo 0.9 --out /tmp/problem.json
    python3 tools/nlopt_check.py /tmp/problem.json

Re-implements the weighted residuals of src/fit/exp_mixture.rs (ring means of
p(r) = sum_k A_k r e^{-B_k r}, tail bin = energy beyond r_max, bounded rates
B = B_min (B_max/B_min)^sigmoid(theta)) and minimises chi^2 = sum r_j^2 with
NLopt from LM's optimum and from perturbed starts (BOBYQA, then Subplex).
Passes if no start beats LM's chi^2 by more than 1e-6 relative.

GMM mode (one per-configuration Gaussian-mixture fit, src/fit/gmm.rs):

    ./target/release/svkernel fit export-kernels --vertices all --out /tmp/kexp.json
    python3 tools/nlopt_check.py --gmm /tmp/kexp.json

takes the histogram of cell `gmm_fit.cell` and re-implements chi^2(theta) of
GmmFit: theta = (eta_2..eta_K, t_1..t_K, ln sigma_1..ln sigma_K), softmax
weights with eta_1 = 0, bin masses m = sum_k w_k T_k(i) S_k(j) with
T_k(i) = Phi((t_{i+1}-t_k)/sigma_k) - Phi((t_i-t_k)/sigma_k) and
S_k(j) = 2[Phi(s_{j+1}/sigma_k) - Phi(s_j/sigma_k)], overflow
o = sum_k w_k [(1 - T_tot) + T_tot (1 - S_tot)], residuals (m - y)/scale with
the exported floored standard errors. Checks chi^2 at LM's theta against
`gmm_fit.chi2`, then minimises with NLopt (BOBYQA, then Subplex) from LM's
theta and from perturbed starts; same pass criterion.
"""
import json
import math
import sys

import nlopt
import numpy as np


def gamma_p2(x):
    """P(2, x) = 1 - e^{-x}(1 + x), series for small x."""
    x = np.asarray(x, dtype=float)
    small = x < 1e-2
    out = np.empty_like(x)
    xs = x[small]
    out[small] = xs * xs * (0.5 - xs * (1.0 / 3.0 - xs * (0.125 - xs / 30.0)))
    xl = x[~small]
    out[~small] = 1.0 - np.exp(-xl) * (1.0 + xl)
    return out


def model(theta, prob):
    k = prob["components"]
    a = np.exp(np.clip(theta[:k], -300, 300))
    span = math.log(prob["b_max"] / prob["b_min"])
    s = 1.0 / (1.0 + np.exp(-np.asarray(theta[k:])))
    b = np.exp(math.log(prob["b_min"]) + span * s)
    lo = np.asarray(prob["lo"])
    hi = np.array([np.inf if h is None else h for h in prob["hi"]])
    tail = ~np.isfinite(hi)
    m = np.zeros(len(lo))
    for ak, bk in zip(a, b):
        scale = ak / (bk * bk)
        e = np.empty(len(lo))
        e[tail] = scale * (1.0 - gamma_p2(bk * lo[tail]))
        fin = ~tail
        e[fin] = scale * (gamma_p2(bk * hi[fin]) - gamma_p2(bk * lo[fin])) / (hi[fin] - lo[fin])
        m += e
    return m


def chi2(theta, prob):
    r = (model(theta, prob) - np.asarray(prob["y"])) / np.asarray(prob["sigma"])
    return float(r @ r)


def main(path):
    prob = json.load(open(path))
    theta0 = np.asarray(prob["theta"])
    lm = prob["chi2"]
    mine = chi2(theta0, prob)
    print(f"alpha = {prob['alpha']}: LM chi2 = {lm:.10g}; python re-evaluation = {mine:.10g}")
    assert abs(mine - lm) <= 1e-9 * max(1.0, lm), "the Python residuals disagree with Rust's"
    rng = np.random.default_rng(1)
    best = math.inf
    for start in range(8):
        x0 = theta0 if start == 0 else theta0 + rng.normal(0.0, 0.3, theta0.size)
        for alg in (nlopt.LN_BOBYQA, nlopt.LN_SBPLX):
            opt = nlopt.opt(alg, theta0.size)
            opt.set_min_objective(lambda x, grad: chi2(x, prob))
            opt.set_ftol_rel(1e-14)
            opt.set_xtol_rel(1e-12)
            opt.set_maxeval(40000)
            try:
                x = opt.optimize(x0)
                x0 = x
            except nlopt.RoundoffLimited:
                x = x0
            best = min(best, chi2(x, prob))
    rel = (lm - best) / lm
    print(f"best NLopt chi2 = {best:.10g}; LM - NLopt = {lm - best:.3g} ({rel:.3g} relative)")
    if rel > 1e-6:
        print("FAIL: NLopt found a lower chi2 than LM by more than 1e-6 relative")
        sys.exit(1)
    print("OK: LM's optimum is not beaten by more than 1e-6 relative")


# ---------------------------------------------------------------- GMM mode

_ERFC = np.frompyfunc(math.erfc, 1, 1)
_ERF = np.frompyfunc(math.erf, 1, 1)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)


def erfc(x):
    return _ERFC(np.asarray(x, dtype=float)).astype(float)


def erf(x):
    return _ERF(np.asarray(x, dtype=float)).astype(float)


def std_normal_mass(za, zb):
    """Phi(zb) - Phi(za) elementwise, taken between complements in either tail
    (as src/metamodel/kernel.rs std_normal_mass)."""
    za, zb = np.broadcast_arrays(np.asarray(za, dtype=float), np.asarray(zb, dtype=float))
    out = np.empty(za.shape)
    up = za >= 0.0
    lo = ~up & (zb <= 0.0)
    mid = ~up & ~lo
    out[up] = 0.5 * (erfc(za[up] * _INV_SQRT2) - erfc(zb[up] * _INV_SQRT2))
    out[lo] = 0.5 * (erfc(-zb[lo] * _INV_SQRT2) - erfc(-za[lo] * _INV_SQRT2))
    out[mid] = 0.5 * (erf(zb[mid] * _INV_SQRT2) - erf(za[mid] * _INV_SQRT2))
    return out


def gmm_residuals(theta, h):
    k = h["k"]
    theta = np.asarray(theta, dtype=float)
    eta = np.concatenate([[0.0], theta[: k - 1]])
    e = np.exp(eta - eta.max())
    w = e / e.sum()
    mu = theta[k - 1 : 2 * k - 1]
    sig = np.exp(np.clip(theta[2 * k - 1 :], -300.0, 300.0))
    te, se = h["te"], h["se"]
    zt = (te[None, :] - mu[:, None]) / sig[:, None]
    zs = se[None, :] / sig[:, None]
    T = std_normal_mass(zt[:, :-1], zt[:, 1:])
    S = 2.0 * std_normal_mass(zs[:, :-1], zs[:, 1:])
    m = np.einsum("k,ki,kj->ij", w, T, S).reshape(-1)
    za, zb = zt[:, 0], zt[:, -1]
    t_tot = std_normal_mass(za, zb)
    t_out = std_normal_mass(-np.inf, za) + std_normal_mass(zb, np.inf)
    s_out = erfc(se[-1] / sig * _INV_SQRT2) + erf(se[0] / sig * _INV_SQRT2)
    o = float(w @ (t_out + t_tot * s_out))
    model = np.concatenate([m, [o]])
    r = (model - h["y"]) / h["scale"]
    mom = h.get("moments")
    if mom is None:
        return r
    # Whole-plane moments, as in src/fit/gmm.rs ("Moments").
    (t_data, s_data), (tol_t, tol_s), wgt = mom["plane"], mom["tol"], mom["weight"]
    et = float(w @ mu)
    rs = math.sqrt(max(float(w @ (sig * sig)), 1e-300))
    extra = [wgt * (et - t_data) / tol_t, wgt * math.log(rs / max(s_data, 1e-6)) / tol_s]
    return np.concatenate([r, extra])


def gmm_chi2(theta, h):
    r = gmm_residuals(theta, h)
    v = float(r @ r)
    return v if math.isfinite(v) else math.inf


def gmm_main(path):
    prob = json.load(open(path))
    fit = prob["gmm_fit"]
    c = prob["cells"][fit["cell"]]
    k = prob["k"]
    h = {
        "k": k,
        "te": np.asarray(c["t_edges"], dtype=float),
        "se": np.asarray(c["s_edges"], dtype=float),
        "y": np.asarray(list(c["mass"]) + [c["overflow"]], dtype=float),
        "scale": np.asarray(c["scale"], dtype=float),
        "moments": c.get("moments"),
    }
    assert h["y"].size == h["scale"].size == (h["te"].size - 1) * (h["se"].size - 1) + 1
    theta0 = np.asarray(fit["theta"], dtype=float)
    assert theta0.size == 3 * k - 1
    lm = fit["chi2"]
    mine = gmm_chi2(theta0, h)
    dof = h["y"].size - theta0.size
    print(
        f"cell {fit['cell']} (alpha = {c['alpha']}, d = {c['d']}), K = {k}, "
        f"{h['y'].size} residuals: LM chi2 = {lm:.12g} (chi2/dof = {lm / dof:.5g}); "
        f"python re-evaluation = {mine:.12g} (rel diff {abs(mine - lm) / lm:.3g})"
    )
    if not abs(mine - lm) <= 1e-9 * max(1.0, lm):
        print("FAIL: the Python residuals disagree with Rust's")
        sys.exit(1)
    rng = np.random.default_rng(1)
    best, best_x = math.inf, theta0
    starts = [("LM optimum", theta0)]
    starts += [(f"LM + N(0, 0.3^2) #{i}", theta0 + rng.normal(0.0, 0.3, theta0.size)) for i in range(1, 6)]
    starts += [(f"LM + N(0, 1^2) #{i}", theta0 + rng.normal(0.0, 1.0, theta0.size)) for i in range(1, 3)]
    for name, x0 in starts:
        seen = {"f": math.inf, "x": x0, "n": 0}

        def f(x, grad):
            v = gmm_chi2(x, h)
            seen["n"] += 1
            if v < seen["f"]:
                seen["f"], seen["x"] = v, np.array(x)
            return v

        f0 = gmm_chi2(x0, h)
        x = x0
        for alg in (nlopt.LN_BOBYQA, nlopt.LN_SBPLX):
            opt = nlopt.opt(alg, theta0.size)
            opt.set_min_objective(f)
            opt.set_ftol_rel(1e-14)
            opt.set_xtol_rel(1e-12)
            opt.set_maxeval(20000)
            try:
                x = opt.optimize(x)
            except (nlopt.RoundoffLimited, RuntimeError, ValueError):
                x = seen["x"]
        v = seen["f"]
        print(
            f"  start {name:24s}: chi2 {f0:.10g} -> {v:.10g} ({seen['n']} evaluations; "
            f"(LM - this)/LM = {(lm - v) / lm:.3g})"
        )
        if v < best:
            best, best_x = v, seen["x"]
    rel = (lm - best) / lm
    print(f"best NLopt chi2 = {best:.12g}; LM - NLopt = {lm - best:.3g} ({rel:.3g} relative)")
    print(f"  LM theta     = {np.array2string(theta0, precision=6)}")
    print(f"  NLopt theta  = {np.array2string(np.asarray(best_x), precision=6)}")
    if rel > 1e-6:
        print("FAIL: NLopt found a lower chi2 than LM by more than 1e-6 relative")
        sys.exit(1)
    print("OK: LM's optimum is not beaten by more than 1e-6 relative")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--gmm":
        gmm_main(sys.argv[2] if len(sys.argv) > 2 else "/tmp/kexp.json")
    else:
        main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/problem.json")
