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


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/problem.json")
