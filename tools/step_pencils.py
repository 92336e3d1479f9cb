"""Pencil beams across an albedo step: `learned` against brute force.

A collimated light of radius 0.05 MFP at the origin, a vertical albedo
step at x = a (bright for x < a), for a in {0.25, 0.5, 1, 2} MFP and two
steps (0.95 | 0.2 and 0.9 | 0.25). Each exit pixel on the row through the
light is one pair x_i → x_e with x_i at distance a inside the bright side.
Prints, per configuration, learned / reference along x - a, and the RMS
and largest |ratio - 1| on each side of the step (pixels whose reference
is resolved to 3 %, |x - a| <= 4, the light's own pixel left out).

    python3 tools/step_pencils.py --bin target/release/svkernel --out out/pencils \
        [--paths 1e8] [--spp 256] [-- RENDER-FLAGS...]

The references are rendered once into OUT/ref and reused; RENDER-FLAGS
(for example `--step-ends independent`) go to the `learned` renders, in
OUT/TAG (`--tag`, default "learned").
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

TEXEL, HALF, RES, WIDTH = 0.05, 9.0, 64, 5.0
STEPS = [(0.95, 0.2), (0.9, 0.25)]
OFFSETS = [0.25, 0.5, 1.0, 2.0]


def write_scene(folder, a, hi, lo):
    name = f"a{a}_{hi}_{lo}"
    n = int(round(2 * HALF / TEXEL))
    x = -HALF + (np.arange(n) + 0.5) * TEXEL
    np.save(os.path.join(folder, name + ".npy"), np.tile(np.where(x < a, hi, lo), (n, 1)))
    path = os.path.join(folder, name + ".toml")
    with open(path, "w") as f:
        f.write(
            f'name = "{name}"\ntexel = {TEXEL}\nalbedo = {{ file = "{name}.npy" }}\n'
            f'[light]\nkind = "collimated"\nradius = 0.05\n'
            f"[image]\nresolution = {RES}\nhalf_width = {WIDTH}\n"
        )
    return name, path


def render(binary, scene, out, methods, extra):
    cmd = [binary, "render", scene, "--method", methods, "--out", out, *extra]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--tag", default="learned")
    ap.add_argument("--paths", default="1e8")
    ap.add_argument("--spp", default="256")
    ap.add_argument("flags", nargs="*")
    args = ap.parse_args()
    scenes = os.path.join(args.out, "scenes")
    os.makedirs(scenes, exist_ok=True)
    sides = {"bright": [], "dark": []}
    for hi, lo in STEPS:
        for a in OFFSETS:
            name, path = write_scene(scenes, a, hi, lo)
            ref = os.path.join(args.out, "ref", name)
            if not os.path.exists(os.path.join(ref, "render.json")):
                render(args.bin, path, ref, "reference", ["--paths", args.paths])
            run = os.path.join(args.out, args.tag, name)
            tally = os.path.join(ref, "main", "reference.tally.json")
            render(
                args.bin,
                path,
                run,
                "reference,learned",
                ["--spp", args.spp, "--paths", args.paths, "--reference-tally", tally, *args.flags],
            )
            r = np.load(os.path.join(ref, "main", "reference_mean.npy")).squeeze()
            se = np.load(os.path.join(ref, "main", "reference_stderr.npy")).squeeze()
            m = np.load(os.path.join(run, "main", "learned_mean.npy")).squeeze()
            rows = slice(RES // 2 - 2, RES // 2 + 2)
            ref_row, model_row = r[rows].sum(0), m[rows].sum(0)
            err = np.sqrt((se[rows] ** 2).sum(0)) / ref_row
            x = -WIDTH + (np.arange(RES) + 0.5) * 2 * WIDTH / RES
            ratio = model_row / ref_row
            shown = [i for i in range(0, RES, 2) if abs(x[i] - a) <= 4.2]
            print(f"{name}: x - a (MFP) and learned / reference")
            print("  " + " ".join(f"{x[i] - a:5.1f}" for i in shown))
            print("  " + " ".join(f"{ratio[i]:5.2f}" for i in shown))
            ok = (np.abs(x - a) <= 4) & (err < 0.03) & (np.abs(x) > 0.2)
            sides["bright"] += list(ratio[ok & (x < a)] - 1)
            sides["dark"] += list(ratio[ok & (x > a)] - 1)
    summary = {
        side: {"rms": float(np.sqrt(np.mean(np.square(v)))), "max": float(np.max(np.abs(v)))}
        for side, v in sides.items()
    }
    print(json.dumps({"tag": args.tag, "flags": args.flags, "summary": summary}))


if __name__ == "__main__":
    sys.exit(main())
