"""Where a method's error lies on a texture: its bias against the reference
by the albedo under each pixel, and by that pixel's distance to the
nearest texel of another albedo.

    svkernel render SCENE --method reference,learned --out RUN
    python3 tools/bias_by_albedo.py RUN [--method learned] [--radius R]

For every pass of RUN (a `svkernel render` output folder), the pixels whose
centre lies within R of the origin (world units; default 7/8 of the light's
radius, where the light is) are grouped by the albedo of the texel under
their centre (nearest neighbour, as the renderer reads maps; the first
channel) and, for maps of at most four albedos, by the distance in MFP
(world distance × the pass's density) from the pixel's centre to the
nearest texel of another albedo. Each group's bias is Σ(method −
reference)/Σ reference over its pixels, in %; the noise of both images
averages out over a group. Maps follow render.json's conventions: centred
on the origin, row 0 = +y, column 0 = −x.

numpy only.
"""
import argparse
import json
import pathlib

import numpy as np

DISTANCE_BINS = [0.0, 0.5, 1.0, 2.0, 4.0, np.inf]


def pixel_centres(doc):
    """World (x, y) of every pixel centre, rows from +y down."""
    n, w = doc["resolution"], doc["half_width"]
    c = (np.arange(n) + 0.5) * 2 * w / n
    return np.meshgrid(-w + c, w - c)


def texel_index(x, y, shape, texel):
    """(row, column) of the texel under world point (x, y), edges extended."""
    ny, nx = shape
    col = np.clip(np.floor(x / texel + nx / 2).astype(int), 0, nx - 1)
    row = np.clip(np.floor(ny / 2 - y / texel).astype(int), 0, ny - 1)
    return row, col


def distance_to_other(amap, rows, cols, texel):
    """World distance from each texel (rows, cols) to the nearest texel
    centre of another albedo (∞ if the map has one albedo)."""
    other = np.zeros(amap.shape, bool)
    other[:-1] |= amap[:-1] != amap[1:]
    other[1:] |= amap[1:] != amap[:-1]
    other[:, :-1] |= amap[:, :-1] != amap[:, 1:]
    other[:, 1:] |= amap[:, 1:] != amap[:, :-1]
    br, bc = np.nonzero(other)
    out = np.full(rows.shape, np.inf)
    for i, (r, c) in enumerate(zip(rows.ravel(), cols.ravel())):
        # The boundary texels of another albedo than this one's.
        m = amap[br, bc] != amap[r, c]
        if m.any():
            out.flat[i] = texel * np.sqrt(((br[m] - r) ** 2 + (bc[m] - c) ** 2).min())
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=pathlib.Path)
    ap.add_argument("--method", default="learned")
    ap.add_argument("--radius", type=float, default=None)
    a = ap.parse_args()
    doc = json.loads((a.run / "render.json").read_text())
    radius = a.radius if a.radius is not None else 0.875 * doc["light"]["radius"]
    x, y = pixel_centres(doc)
    inside = np.hypot(x, y) < radius
    for p in doc["passes"]:
        d = a.run / (p["tag"] or "main")
        first = lambda name: np.load(d / f"{name}.npy").reshape(x.shape + (-1,))[..., 0]
        m, ref = first(f"{a.method}_mean"), first("reference_mean")
        amap = np.load(d / "albedo.npy")
        amap = amap.reshape(amap.shape[:2] + (-1,))[..., 0]
        rows, cols = texel_index(x, y, amap.shape, doc["albedo_texel"])
        under = amap[rows, cols]
        values = np.unique(under[inside])
        rho = p.get("density") or 1.0
        dist = None
        if len(np.unique(amap)) <= 4:
            dist = rho * distance_to_other(amap, rows, cols, doc["albedo_texel"])
        total = 100 * (m[inside] - ref[inside]).sum() / ref[inside].sum()
        print(f"{p['tag'] or 'main'}: {a.method} against the reference within r < {radius:g}: bias {total:+.2f} %")
        if len(values) <= 8:
            groups = [(f"albedo {v:.3g}", inside & (under == v)) for v in values]
        else:
            # Quintiles by rank, so that ties cannot empty a group.
            idx = np.flatnonzero(inside)
            idx = idx[np.argsort(under.flat[idx], kind="stable")]
            groups = []
            for i, part in enumerate(np.array_split(idx, 5)):
                sel = np.zeros(under.shape, bool)
                sel.flat[part] = True
                groups.append((f"albedo quintile {i + 1} (mean {under[sel].mean():.3g})", sel))
        for label, sel in groups:
            if not sel.any():
                continue
            line = f"  {label}: {sel.sum()} px, bias {100 * (m[sel] - ref[sel]).sum() / ref[sel].sum():+.2f} %"
            if dist is not None:
                cells = []
                for lo, hi in zip(DISTANCE_BINS[:-1], DISTANCE_BINS[1:]):
                    s = sel & (dist >= lo) & (dist < hi)
                    if s.sum() >= 10:
                        b = 100 * (m[s] - ref[s]).sum() / ref[s].sum()
                        cells.append(f"[{lo:g}, {hi:g}) MFP: {b:+.2f} % ({s.sum()} px)")
                line += "; from another albedo " + ", ".join(cells)
            print(line)


if __name__ == "__main__":
    main()
