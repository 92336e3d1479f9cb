#!/usr/bin/env python3
"""The far-field effective albedo of a fine periodic texture.

Far from the light, a textured medium's exitance decays like that of a
homogeneous medium of some albedo α_eff. This tool gives three candidates
for α_eff of one periodic cell of a texture, and, given reference renders,
the α_eff that the brute-force reference itself shows:

* the linear mean ⟨α⟩ (vertices that fall independently);
* the transport mean φ⁻¹⟨φ(α)⟩, φ(α) = √(1 − α) (the diffusion
  coordinate; right for textures much coarser than a mean free path);
* the Perron root λ of the operator f ↦ α·(P ∗ f), P the surface
  displacement of one free flight of mean length ℓ (MFP): a flight of
  length L ~ Exp(1/ℓ) in a uniformly random direction moves the vertex
  over the surface by a displacement whose 2D characteristic function is
  arctan(kℓ)/(kℓ) (Case & Zweifel, *Linear Transport Theory*, 1967). A
  path's throughput is the product of its vertices' albedos, and its
  vertices form a Markov chain with step P, so the expected throughput of
  a long path grows as λⁿ: λ is the albedo per vertex that a path far
  from its ends sees. For independent vertices (P flat) it is ⟨α⟩.

The cell is sampled on an n × n grid and P is applied by FFT (the texture
is periodic, so the convolution is exact up to the sampling).

    python3 tools/perron_albedo.py dots --values 0.99,0.2 --spacing 1.5 --radius 0.15
    python3 tools/perron_albedo.py stripes --values 0.3,0.95 --width 0.5 --vertices 2,3,4

A chain of n vertices (`--vertices`) gives the albedo per vertex of paths
that short: the n-th root of ⟨α·P∗(α·P∗(… α))⟩, which tends to λ.

With `--reference DIR --homogeneous DIR:α ...` it also reads the
reference renders (`svkernel render SCENE --method reference --out DIR`,
scenes lit by the same light and framed alike) and reports the α_eff at
which a homogeneous medium's decay between the rings r ∈ [1.25, 1.75] and
r ∈ [3.75, 4.25] MFP from the image centre matches the textured one's
(linear interpolation in α between the two bracketing homogeneous
references).
"""

import argparse
import json
import os
import sys

import numpy as np


def cell(args, n):
    """One periodic cell of the texture: (albedo on an n × n grid, side in MFP)."""
    lo, hi = args.values
    if args.pattern == "stripes":
        side = 2.0 * args.width
        x = (np.arange(n) + 0.5) / n * side
        a = np.where(x < args.width, lo, hi)
        return np.tile(a, (n, 1)), side
    if args.pattern == "checker":
        side = 2.0 * args.cell
        x = (np.arange(n) + 0.5) / n * side
        X, Y = np.meshgrid(x, x)
        return np.where((X < args.cell) == (Y < args.cell), lo, hi), side
    if args.pattern == "dots":
        side = args.spacing
        x = (np.arange(n) + 0.5) / n * side
        X, Y = np.meshgrid(x, x)
        inside = np.hypot(X - side / 2, Y - side / 2) < args.radius
        return np.where(inside, hi, lo), side
    raise SystemExit(f"unknown pattern {args.pattern!r}")


def flight_transform(n, side, ell):
    """arctan(kℓ)/(kℓ) on the FFT grid of the cell (1 at k = 0)."""
    f = np.fft.fftfreq(n, d=side / n)
    fx, fy = np.meshgrid(f, f)
    k = 2.0 * np.pi * np.hypot(fx, fy) * ell
    out = np.ones_like(k)
    nz = k > 0
    out[nz] = np.arctan(k[nz]) / k[nz]
    return out


def perron_root(a, p_hat, tol=1e-12, max_iter=100000):
    """The largest eigenvalue of f ↦ a·(P ∗ f) by power iteration (a > 0)."""
    f = np.ones_like(a)
    lam = 0.0
    for _ in range(max_iter):
        g = a * np.real(np.fft.ifft2(np.fft.fft2(f) * p_hat))
        new = g.mean() / f.mean()
        f = g / g.mean()
        if abs(new - lam) < tol:
            return new
        lam = new
    raise SystemExit("the power iteration did not converge")


def chain_albedo(a, p_hat, n):
    """The albedo per vertex of a chain of n vertices: (⟨α·P∗(α·P∗(… α))⟩)^(1/n),
    the n-th root of the expected throughput, vertices stationary on the cell."""
    f = a.copy()
    for _ in range(n - 1):
        f = a * np.real(np.fft.ifft2(np.fft.fft2(f) * p_hat))
    return f.mean() ** (1.0 / n)


def ring_decay(directory, image="reference"):
    """ln of the mean exitance in the ring r ∈ [3.75, 4.25] over the ring
    r ∈ [1.25, 1.75] (MFP from the image centre) of a render's `image`
    (its IMAGE_mean.npy: `reference`, or a method's name)."""
    render = os.path.join(directory, "main", f"{image}_mean.npy")
    if not os.path.exists(render):
        raise SystemExit(f"{render}: not found (svkernel render SCENE --method {image} --out {directory})")
    m = np.load(render)
    m = m[..., 0] if m.ndim == 3 else m
    with open(os.path.join(directory, "render.json")) as fh:
        meta = json.load(fh)
    half = float(meta["half_width"])
    n = m.shape[0]
    x = (np.arange(n) + 0.5) / n * 2.0 * half - half
    r = np.hypot(*np.meshgrid(x, x))

    def ring(lo, hi):
        return m[(r >= lo) & (r < hi)].mean()

    return float(np.log(ring(3.75, 4.25) / ring(1.25, 1.75)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pattern", choices=["stripes", "checker", "dots"])
    ap.add_argument("--values", type=lambda s: [float(v) for v in s.split(",")], required=True,
                    help="two albedos: stripes/checker (first, second); dots (ground, dot)")
    ap.add_argument("--width", type=float, default=0.5, help="stripes: width of one stripe (MFP)")
    ap.add_argument("--cell", type=float, default=0.75, help="checker: side of one square (MFP)")
    ap.add_argument("--spacing", type=float, default=1.5, help="dots: spacing (MFP)")
    ap.add_argument("--radius", type=float, default=0.15, help="dots: radius (MFP)")
    ap.add_argument("--flight", type=float, default=1.0, help="mean flight length ℓ (MFP); 1/ρ")
    ap.add_argument("--vertices", type=lambda s: [int(v) for v in s.split(",")], default=[],
                    help="also the albedo per vertex of chains of these many vertices (e.g. 2,3,6,20)")
    ap.add_argument("--grid", type=int, default=256, help="samples per side of the cell")
    ap.add_argument("--reference", help="reference render of the textured scene")
    ap.add_argument("--image", default="reference",
                    help="which image of --reference to read (reference, or a method such as learned)")
    ap.add_argument("--homogeneous", nargs="*", default=[],
                    help="reference renders of homogeneous media as DIR:α")
    args = ap.parse_args()
    if len(args.values) != 2 or not all(0.0 < v < 1.0 for v in args.values):
        raise SystemExit("--values: two albedos in (0, 1)")
    a, side = cell(args, args.grid)
    linear = a.mean()
    transport = 1.0 - np.sqrt(1.0 - a).mean() ** 2
    p_hat = flight_transform(args.grid, side, args.flight)
    lam = perron_root(a, p_hat)
    print(f"linear mean      {linear:.5f}")
    print(f"transport mean   {transport:.5f}")
    print(f"Perron root      {lam:.5f}  (flight ℓ = {args.flight} MFP)")
    for n in args.vertices:
        if n < 1:
            raise SystemExit("--vertices: counts of at least 1")
        print(f"chain of {n:<3d}     {chain_albedo(a, p_hat, n):.5f}")
    if args.reference:
        if len(args.homogeneous) < 2:
            raise SystemExit("--reference needs at least two --homogeneous DIR:α")
        target = ring_decay(args.reference, args.image)
        homs = sorted((float(s.rsplit(":", 1)[1]), ring_decay(s.rsplit(":", 1)[0])) for s in args.homogeneous)
        for (a0, d0), (a1, d1) in zip(homs, homs[1:]):
            if min(d0, d1) <= target <= max(d0, d1):
                eff = a0 + (a1 - a0) * (target - d0) / (d1 - d0)
                print(f"{args.image:<16} {eff:.5f}  (decay {target:.4f}; homogeneous {a0}: {d0:.4f}, {a1}: {d1:.4f})")
                break
        else:
            spans = ", ".join(f"{a0}: {d0:.4f}" for a0, d0 in homs)
            print(f"reference decay {target:.4f} outside the homogeneous ones ({spans})", file=sys.stderr)
            sys.exit(1)


if __name__ == "__main__":
    main()
