#!/usr/bin/env python3
"""Where a method's bias lies: its relative bias against the reference,
binned by the albedo under each pixel and by the distance from the light's
centre.

    svkernel render checker --method learned --method reference \
        --spp 1024 --paths 3e8 --out out/cb
    python3 tools/cell_bias.py out/cb [--method learned] [--pass main] \
        [--rings 0,1,1.6,2.5,inf] [--split 0.5] [--reference DIR]

Reads OUT/render.json for the geometry and OUT/PASS/{albedo,METHOD_mean,
METHOD_stderr}.npy, and the reference's {reference_mean,reference_stderr}.npy
from OUT/PASS or, with --reference, from DIR/PASS (a render of the
reference alone, whose tally the method's render read with
--reference-tally). Pixels and texels follow the
render's conventions (render.json "conventions": row 0 is +y, column 0 is
−x, both maps centred on the origin); the albedo of a pixel is the texel
under its centre (mean over channels). Pixels are split into "dark"
(albedo < SPLIT, default the midpoint of the map's range) and "bright". For
each class and ring it prints the relative bias Σm/Σref − 1 with its standard
error (from both images' per-pixel standard errors), the share of Σref² (what
the ring weighs in the relative RMSE), and the reference's mean; the last
line gives the relative RMSE with the noise of both images subtracted, as
`compare` measures it.
"""
import argparse
import json
import math
from pathlib import Path

import numpy as np


def grey(a):
    return a.mean(axis=-1) if a.ndim == 3 else a


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="a render's --out directory")
    ap.add_argument("--method", default="learned")
    ap.add_argument("--pass", dest="pass_", default="main")
    ap.add_argument("--rings", default="0,1,1.6,2.5,inf",
                    help="ring edges, MFP from the light's centre")
    ap.add_argument("--split", type=float, default=None,
                    help="albedo that separates dark from bright pixels")
    ap.add_argument("--reference", type=Path, default=None,
                    help="the reference's render directory (default: OUT)")
    args = ap.parse_args()

    meta = json.loads((args.out / "render.json").read_text())
    d = args.out / args.pass_
    r = (args.reference or args.out) / args.pass_
    ref = grey(np.load(r / "reference_mean.npy"))
    ref_se = grey(np.load(r / "reference_stderr.npy"))
    m = grey(np.load(d / f"{args.method}_mean.npy"))
    se_path = d / f"{args.method}_stderr.npy"
    m_se = grey(np.load(se_path)) if se_path.exists() else np.zeros_like(m)
    albedo = grey(np.load(d / "albedo.npy"))

    n, w = meta["resolution"], meta["half_width"]
    h = 2.0 * w / n
    x = -w + (np.arange(n) + 0.5) * h  # column j
    y = w - (np.arange(n) + 0.5) * h   # row i
    X, Y = np.meshgrid(x, y)
    tex = meta["albedo_texel"]
    ny, nx = albedo.shape
    col = np.clip(np.floor((X + 0.5 * nx * tex) / tex).astype(int), 0, nx - 1)
    row = np.clip(np.floor((0.5 * ny * tex - Y) / tex).astype(int), 0, ny - 1)
    A = albedo[row, col]
    split = args.split if args.split is not None else 0.5 * (albedo.min() + albedo.max())
    R = np.hypot(X, Y)
    edges = [float(e) for e in args.rings.split(",")]

    ok = ref > 0
    total2 = (ref[ok] ** 2).sum()
    var = ref_se ** 2 + m_se ** 2
    print(f"{args.out}/{args.pass_}: {args.method} against the reference; "
          f"dark: albedo < {split:.3g}")
    print(f"{'ring [MFP]':>14} {'class':>6} {'pixels':>6} {'bias':>8} "
          f"{'± se':>6} {'Σref² share':>11} {'ref mean':>10}")
    for lo, hi in zip(edges[:-1], edges[1:]):
        for name, cls in (("dark", A < split), ("bright", A >= split)):
            k = ok & cls & (R >= lo) & (R < hi)
            if not k.any():
                continue
            s = ref[k].sum()
            bias = m[k].sum() / s - 1.0
            err = math.sqrt(var[k].sum()) / s
            share = (ref[k] ** 2).sum() / total2
            print(f"{f'[{lo:g}, {hi:g})':>14} {name:>6} {k.sum():>6} "
                  f"{100 * bias:>+7.2f}% {100 * err:>5.2f}% {100 * share:>10.1f}% "
                  f"{ref[k].mean():>10.4g}")
    d2 = ((m - ref)[ok] ** 2).sum() - var[ok].sum()
    rmse = math.sqrt(max(d2, 0.0) / total2)
    print(f"relative RMSE, noise subtracted: {100 * rmse:.2f} %")


if __name__ == "__main__":
    main()
