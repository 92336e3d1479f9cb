"""Python's vectorised SvBssrdf.eval against the library's own loop, in one run.

Builds a 256² albedo map (τ = 0.05 MFP) and 1e6 pairs (x_e uniform over the
texture, x_i within 2 MFP of it), times the Rust example `eval_cost` on them
(best of three, ns per pair) and `svkernel.SvBssrdf.eval` on the same pairs
(best of three, array checks and conversion included), and prints both and
their ratio per method. Needs the package installed (`pip install ./python`).

    python tools/python_eval_cost.py [--pairs 1000000]
"""

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import svkernel as sk

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=1_000_000)
    ap.add_argument("--methods", default="point,factorized,manual,learned")
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    n, tau = 256, 0.05
    y, x = np.mgrid[0:n, 0:n] * tau
    albedo = 0.6 + 0.35 * np.sin(x * 2.1) * np.cos(y * 1.3)
    half = n * tau / 2
    xe = rng.uniform(-half, half, size=(args.pairs, 2))
    r = 2.0 * np.sqrt(rng.random(args.pairs))
    phi = 2 * np.pi * rng.random(args.pairs)
    xi = xe + np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    subprocess.run(["cargo", "build", "--release", "--quiet", "--example", "eval_cost"], cwd=ROOT, check=True)
    exe = ROOT / "target" / "release" / "examples" / "eval_cost"
    print(f"{'method':<11} {'Rust ns/pair':>13} {'Python ns/pair':>15} {'ratio':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        np.save(Path(tmp) / "albedo.npy", albedo)
        np.save(Path(tmp) / "pairs.npy", np.hstack([xi, xe]))
        for method in args.methods.split(","):
            out = subprocess.run(
                [str(exe), str(Path(tmp) / "albedo.npy"), str(Path(tmp) / "pairs.npy"), str(tau), method],
                capture_output=True, text=True, check=True,
            )
            rust = json.loads(out.stdout)
            s = sk.SvBssrdf(albedo, texel=tau, method=method)
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                v = s.eval(xi, xe)
                best = min(best, time.perf_counter() - t0)
            py = best * 1e9 / args.pairs
            same = np.isclose(v.sum(), rust["sum"], rtol=1e-12)
            print(f"{method:<11} {rust['ns_per_pair']:>13.1f} {py:>15.1f} {py / rust['ns_per_pair']:>6.2f}"
                  + ("" if same else "  (values differ!)"))


if __name__ == "__main__":
    main()
