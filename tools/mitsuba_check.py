#!/usr/bin/env python3
"""Cross-checks a brute-force reference render (`svkernel render --method
reference`) against Mitsuba 3 with a per-pixel Z-test (validation only).

    svkernel render tools/mitsuba/albedo.toml --method reference --paths 1e8 \\
        --out /tmp/mc/albedo
    python3 tools/mitsuba_check.py /tmp/mc/albedo --spp 1024 --passes 32 \\
        --out /tmp/mc/albedo/mitsuba_check.json

Reads DIR/render.json and DIR/<pass>/{albedo,density,reference_mean,
reference_stderr}.npy and renders the same scene with Mitsuba's `volpath`:

* medium: a `cube` shape (top face z = 0, lateral half-width
  max(W, map extents) + --margin, depth --depth MFP) with a smooth
  `dielectric` BSDF (int_ior = eta, ext_ior = 1; a `null` BSDF for eta = 1)
  and an interior `heterogeneous` medium: sigma_t = density, albedo = albedo,
  both `gridvolume`s with nearest filtering and clamp wrapping, the 2D texel
  maps extruded in depth (2 z-slices), rows flipped (map row 0 = +y, grid row
  0 = -y) and padded with copies of their edge texels out to the box, so the
  grid's voxel (i, j) covers exactly texel (i, j) of the conventions
  (x in [-nx tau/2 + j tau, ...), row 0 at +y); `hg` phase function with g;
* light: a `disk` of radius R at height --epsilon above z = 0 (default
  max(1e-3, 20 (1 + R) RayEpsilon): above Mitsuba's offset of rays leaving
  the surface under it), rotated to face -z, with an `area` emitter of
  radiance E/pi (the surface below receives irradiance E) and a `null` BSDF
  (transparent; seen from above its back side, which does not emit);
* no next-event estimation from the medium (`sample_emitters = false`): it is
  zero in expectation through a smooth dielectric, and Mitsuba's shadow rays
  stop ShadowEpsilon (8.9e-4) x their length short of the light, so with the
  light a hair above the surface long ones miss the interface and add
  unrefracted light (measured +9 % on the image mean with the light 1e-3
  above the surface; none with NEE off or the light 0.01 above);
* sensor: `orthographic`, looking down -z with +y up, covering [-W, W]^2 in
  N x N pixels with a `box` filter (each pixel is the plain average over its
  square; column 0 at -x, row 0 at +y, checked by --self-test);
* the camera ray reflected specularly at z = 0 sees the emitter from below:
  Mitsuba's image holds F(0) E/pi cov(pixel) with F(0) = ((eta-1)/(eta+1))^2
  and cov the fraction of the pixel inside the disk; the reference counts
  sub-surface light only (R_d excludes the specular reflection), so this
  deterministic term is subtracted (its sampling noise stays in the
  pass-to-pass error);
* grey scenes (C = 1) are rendered in an *_rgb variant with the albedo in all
  three channels (identical channels: common random numbers), channel 0 used.

P passes (--passes) of --spp samples per pixel with seeds S..S+P-1 (--seed) give the
Mitsuba mean and its standard error (sample std over passes / sqrt(P)).

Z-test per pixel and channel: z = (ours - mitsuba) / sqrt(se_ours^2 + se_mi^2).
Reported (test pixels and all pixels): mean z, std z, fraction |z| > 3,
chi^2/dof = mean z^2, max |z|; the ratio of the image means ours/mitsuba with
its uncertainty (Mitsuba's from the pass means; ours bracketed: pixels
independent (low) and fully correlated (high)), Mitsuba's wall time and the
command lines.

Pass criterion (documented in tools/mitsuba/README.md). Test pixels: those
where our image is >= --min-signal (2 %) of its maximum, chosen on our precise
image alone so the choice does not depend on Mitsuba's noise (dimmer pixels
get few Mitsuba paths: their pass means are skewed and their z heavy-tailed).
With n test values and P passes, under agreement z is close to Student-t with
P - 1 dof (Mitsuba's error dominates), so FAIL if any of
  (1) chi^2/dof > (P-1)/(P-3) + 5 sqrt(Var_t(z^2)/n)
      or chi^2/dof < 1 - 5 sqrt(2/n)  (errors under- or over-stated);
  (2) |mean z| > --mean-z-limit (0.3; skewed Mitsuba estimates alone give
      mean z ~ +0.1: a low pass mean comes with a low spread);
  (3) fraction |z| > 3 > 2 %;
  (4) |ratio - 1| > 5 sigma for the ratio of the image means (all pixels),
      sigma from Mitsuba's pass means and our error of the image mean with
      independent pixels (measured adequate: the image means of 7 reference
      seeds spread by 0.8x that estimate; the fully-correlated bound, 27x
      larger, is reported too);
  or the --self-test failed.
Exit 0 on PASS, 1 on FAIL, 2 on a usage or input error.
"""
import argparse
import glob
import json
import math
import os
import re
import shlex
import sys
import time

import numpy as np


def pick_libllvm():
    """Dr.Jit's LLVM backend needs LLVM >= 16 for this Mitsuba (older ones
    abort with 'Cannot select ... fminimum'); point DRJIT_LIBLLVM_PATH at the
    newest libLLVM found unless the user set it."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    best = None
    for path in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"):
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
        if m and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), path)
    if best and best[0] >= 16:
        os.environ["DRJIT_LIBLLVM_PATH"] = best[1]
        return best[1]
    return None


def die(msg):
    print(f"mitsuba_check: error: {msg}", file=sys.stderr)
    sys.exit(2)


# --------------------------------------------------------------------------
# Inputs


def load_reference(directory, tag):
    path = os.path.join(directory, "render.json")
    if not os.path.exists(path):
        die(f"{path} is missing (the --out folder of `svkernel render --method reference`)")
    with open(path) as f:
        meta = json.load(f)
    if tag is None:
        passes = meta.get("passes") or [{"tag": "main"}]
        tag = passes[0]["tag"]
    sub = os.path.join(directory, tag)
    arrays = {}
    for name in ("albedo", "density", "reference_mean", "reference_stderr"):
        path = os.path.join(sub, name + ".npy")
        if not os.path.exists(path):
            die(f"{path} is missing (render with --method reference)")
        arrays[name] = np.load(path)
    light = meta["light"]
    if light.get("kind") != "diffuse":
        die(f"light kind {light.get('kind')!r}: only 'diffuse' is supported")
    if meta.get("observable") != "radiance":
        die(f"observable {meta.get('observable')!r}: only 'radiance' is supported")
    mean, se = arrays["reference_mean"], arrays["reference_stderr"]
    n = int(meta["resolution"])
    if mean.shape != se.shape or mean.shape[:2] != (n, n) or mean.ndim != 3:
        die(f"reference arrays have shape {mean.shape} / {se.shape}, expected ({n}, {n}, C)")
    alb = arrays["albedo"]
    if alb.ndim == 2:
        alb = alb[:, :, None]
    if alb.shape[2] not in (1, 3) or alb.shape[2] != mean.shape[2] and alb.shape[2] != 1:
        die(f"albedo shape {alb.shape} does not match {mean.shape[2]} channels")
    dens = arrays["density"]
    if dens.ndim != 2:
        die(f"density shape {dens.shape}: expected (ny, nx)")
    return dict(
        meta=meta,
        tag=tag,
        eta=float(meta["eta"]),
        g=float(meta["g"]),
        texel=float(meta["texel"]),
        # The albedo array's own texel: differs from `texel` (τ/2) when the
        # scene's channels differ in shape and were resampled onto one grid.
        albedo_texel=float(meta.get("albedo_texel", meta["texel"])),
        radius=float(light["radius"]),
        irradiance=float(light.get("irradiance", 1.0)),
        n=n,
        half_width=float(meta["half_width"]),
        albedo=alb.astype(np.float64),
        density=dens.astype(np.float64),
        mean=mean.astype(np.float64),
        stderr=se.astype(np.float64),
        channels=mean.shape[2],
    )


# --------------------------------------------------------------------------
# Geometry helpers (pure numpy)


def grid_layout(ny, nx, tau, half_extent):
    """Padding (texels) and world extent of a padded grid covering
    [-half_extent, half_extent]^2 whose texel lattice matches the map's."""
    kx = max(1, math.ceil((half_extent - nx * tau / 2) / tau) + 1)
    ky = max(1, math.ceil((half_extent - ny * tau / 2) / tau) + 1)
    x0 = -nx * tau / 2 - kx * tau
    y0 = -ny * tau / 2 - ky * tau
    return kx, ky, x0, y0, (nx + 2 * kx) * tau, (ny + 2 * ky) * tau


def padded_grid(tex, kx, ky):
    """(ny, nx, C) map -> (2, ny+2ky, nx+2kx, C) grid, rows flipped so grid row
    0 is the lowest y, edge texels copied outwards, two identical z-slices."""
    g = np.flipud(tex)
    g = np.pad(g, ((ky, ky), (kx, kx), (0, 0)), mode="edge")
    return np.ascontiguousarray(np.stack([g, g]), dtype=np.float32)


def texel_index(x, y, ny, nx, tau):
    """Map convention (clamped): column from x, row from y (row 0 = +y)."""
    j = np.clip(np.floor((x + nx * tau / 2) / tau), 0, nx - 1).astype(int)
    i = np.clip(np.floor((ny * tau / 2 - y) / tau), 0, ny - 1).astype(int)
    return i, j


def disk_coverage(n, half_width, radius, sub=2048, centre=(0.0, 0.0)):
    """Fraction of each pixel's square inside the disk |(x, y) - centre| < R
    (pixel (i, j): x in -W + [j, j+1] 2W/N, y in W - [i+1, i] 2W/N): midpoint
    rule in x (sub points per pixel) with the exact y overlap."""
    h = 2 * half_width / n
    cx, cy = centre
    cov = np.zeros((n, n))
    for j in range(n):
        xs = -half_width + (j + (np.arange(sub) + 0.5) / sub) * h
        yc = np.sqrt(np.clip(radius * radius - (xs - cx) ** 2, 0, None))
        for i in range(n):
            ylo, yhi = half_width - (i + 1) * h, half_width - i * h
            overlap = np.clip(np.minimum(yhi, cy + yc) - np.maximum(ylo, cy - yc), 0, None)
            cov[i, j] = overlap.mean() / h
    return cov


# --------------------------------------------------------------------------
# Mitsuba scene


def build_scene(mi, ref, args):
    T = mi.ScalarTransform4f
    tau, W, n = ref["texel"], ref["half_width"], ref["n"]
    tau_a = ref["albedo_texel"]
    alb, dens = ref["albedo"], ref["density"]
    if alb.shape[2] == 1:
        alb = np.repeat(alb, 3, axis=2)  # grey: same value in r, g, b
    elif alb.shape[2] != 3:
        die("albedo must have 1 or 3 channels")
    half = max(W, alb.shape[1] * tau_a / 2, alb.shape[0] * tau_a / 2,
               dens.shape[1] * tau / 2, dens.shape[0] * tau / 2) + args.margin
    depth = args.depth

    def volume(tex, tau):
        ny, nx = tex.shape[:2]
        kx, ky, x0, y0, wx, wy = grid_layout(ny, nx, tau, half + tau)
        data = padded_grid(tex, kx, ky)
        z0, z1 = -depth - 1.0, 1.0
        to_world = T().translate([x0, y0, z0]) @ T().scale([wx, wy, z1 - z0])
        return {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(data),
            "filter_type": "nearest",
            "wrap_mode": "clamp",
            "to_world": to_world,
        }

    medium = {
        "type": "heterogeneous",
        "albedo": volume(alb, tau_a),
        "sigma_t": volume(dens[:, :, None], tau),
        "scale": 1.0,
        "phase": {"type": "hg", "g": ref["g"]},
        # No next-event estimation from the medium: through a smooth
        # dielectric it is zero in expectation, and Mitsuba's shadow rays stop
        # ShadowEpsilon * length (8.9e-4 relative) short of the light, so with
        # the light epsilon above the surface a long one misses the interface
        # and adds unrefracted, un-Fresnelled light (measured: +9 % image mean).
        "sample_emitters": False,
    }
    if ref["eta"] == 1.0:
        bsdf = {"type": "null"}
    else:
        bsdf = {"type": "dielectric", "int_ior": ref["eta"], "ext_ior": 1.0}
    L = ref["irradiance"] / math.pi
    return {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": args.rr_depth},
        "sensor": {
            "type": "orthographic",
            "to_world": T().look_at(origin=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0])
            @ T().scale([W, W, 1]),
            "film": {
                "type": "hdrfilm",
                "width": n,
                "height": n,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
                "sample_border": False,
            },
            "sampler": {"type": "independent", "sample_count": args.spp},
        },
        "slab": {
            "type": "cube",
            "to_world": T().translate([0, 0, -depth / 2]) @ T().scale([half, half, depth / 2]),
            "bsdf": bsdf,
            "interior": medium,
        },
        "light": {
            "type": "disk",
            "to_world": T().translate([0, 0, args.epsilon])
            @ T().rotate([1, 0, 0], 180)
            @ T().scale([ref["radius"], ref["radius"], 1]),
            "bsdf": {"type": "null"},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [L, L, L]}},
        },
    }


def eval_volume(mi, vol, xy, zs, channels):
    """Evaluates a volume at points (x, y, z): (n, channels) array."""
    if mi.variant().startswith("scalar"):
        out = []
        for (x, y), z in zip(xy, zs):
            it = mi.Interaction3f()
            it.p = mi.ScalarPoint3f(float(x), float(y), float(z))
            v = vol.eval(it) if channels == 3 else vol.eval_1(it)
            out.append([v[0], v[1], v[2]] if channels == 3 else [v])
        return np.array(out, dtype=np.float64)
    it = mi.Interaction3f()
    it.p = mi.Point3f(*(np.asarray(a, dtype=np.float32) for a in (xy[:, 0], xy[:, 1], zs)))
    if channels == 3:
        v = vol.eval(it)
        return np.stack([np.array(v[c]) for c in range(3)], axis=1).astype(np.float64)
    return np.array(vol.eval_1(it), dtype=np.float64)[:, None]


def self_test(mi, ref, scene_dict, args):
    """Checks the grid placement against the texel convention at texel centres
    and just inside texel boundaries, and the sensor's pixel placement and
    emitter irradiance with a white Lambertian plane under the light."""
    ok = True
    med = scene_dict["slab"]["interior"]
    rng = np.random.default_rng(7)
    for key, tex, tau in (("albedo", ref["albedo"], ref["albedo_texel"]),
                          ("sigma_t", ref["density"][:, :, None], ref["texel"])):
        vol = mi.load_dict(med[key])
        ny, nx = tex.shape[:2]
        ext = max(nx, ny) * tau / 2 + 3 * tau
        pts = [rng.uniform(-ext, ext, size=(4000, 2)),
               rng.uniform(-ext - args.margin, ext + args.margin, size=(4000, 2))]
        # just inside each texel's four edges
        jj, ii = np.meshgrid(np.arange(nx + 2) - 1, np.arange(ny + 2) - 1)
        for dx, dy in ((0.001, 0.5), (0.999, 0.5), (0.5, 0.001), (0.5, 0.999)):
            xs = -nx * tau / 2 + (jj + dx) * tau
            ys = ny * tau / 2 - (ii + dy) * tau
            pts.append(np.stack([xs.ravel(), ys.ravel()], axis=1))
        p = np.concatenate(pts)
        zs = rng.uniform(-args.depth, 0, size=len(p))
        got = eval_volume(mi, vol, p, zs, 3 if key == "albedo" else 1)
        i, j = texel_index(p[:, 0], p[:, 1], ny, nx, tau)
        want = tex[i, j]
        if key == "albedo" and tex.shape[2] == 1:
            want = np.repeat(want, 3, axis=1)
        err = np.abs(got - want).max()
        print(f"self-test: {key} grid vs texel convention at {len(p)} points: max |diff| = {err:.2e}")
        ok &= bool(err < 1e-6)
    # Sensor + emitter: white diffuse plane at z = 0 under the light.
    d = dict(scene_dict)
    d.pop("slab")
    d["plane"] = {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().scale([50, 50, 1]),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1, 1, 1]}},
    }
    d["sensor"] = dict(d["sensor"])
    d["sensor"]["sampler"] = {"type": "independent", "sample_count": 256}
    img = np.array(mi.render(mi.load_dict(d), seed=0))[..., 0]
    cov = disk_coverage(ref["n"], ref["half_width"], ref["radius"])
    want = ref["irradiance"] / math.pi * cov  # irradiance E under the disk, radiance E/pi
    E = ref["irradiance"] / math.pi
    inner = cov > 0.999
    rel_in = abs(img[inner].mean() / want[inner].mean() - 1) if inner.any() else 0.0
    # Pixels away from the disk edge see E/pi inside (minus ~epsilon/R) and a
    # small tail outside; compare the coverage pattern itself on the edge band.
    edge = (cov > 0.0) & (cov < 1.0)
    err_edge = np.abs(img[edge] - want[edge]).max() / E if edge.any() else 0.0
    print(f"self-test: white plane under the light: inner pixels {img[inner].mean():.5f} "
          f"vs E/pi = {E:.5f} (rel {rel_in:.1e}); edge pixels max |diff|/(E/pi) = {err_edge:.3f}")
    # Edge pixels: binomial coverage noise of 256 samples, sd <= 0.5/16; 5 sd.
    tol = 5 * 0.5 / 16 + 0.01
    ok &= bool(rel_in < 0.01 and err_edge < tol)
    # Orientation: an off-centre disk facing the camera, seen directly.
    W = ref["half_width"]
    centre, r = (W / 2, W / 4), W / 6
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},
        "sensor": d["sensor"],
        "probe": {
            "type": "disk",
            "to_world": mi.ScalarTransform4f().translate([centre[0], centre[1], 0]) @ mi.ScalarTransform4f().scale([r, r, 1]),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1, 1, 1]}},
        },
    }
    img = np.array(mi.render(mi.load_dict(d), seed=0))[..., 0]
    want = disk_coverage(ref["n"], W, r, centre=centre)
    err = np.abs(img - want).max()
    print(f"self-test: disk at (x, y) = ({centre[0]:g}, {centre[1]:g}) seen by the camera: "
          f"max |pixel - coverage| = {err:.3f} (flipped in x: {np.abs(img[:, ::-1] - want).max():.3f}, "
          f"in y: {np.abs(img[::-1] - want).max():.3f})")
    ok &= bool(err < tol)
    return ok


# --------------------------------------------------------------------------
# Statistics


def t_moments(nu):
    """E[t^2], Var[t^2] of Student's t with nu dof (nu > 4)."""
    e2 = nu / (nu - 2)
    e4 = 3 * nu * nu / ((nu - 2) * (nu - 4))
    return e2, e4 - e2 * e2


def zstats(z):
    n = z.size
    return {
        "n": int(n),
        "mean_z": float(np.mean(z)),
        "std_z": float(np.std(z, ddof=1)),
        "frac_abs_z_gt_3": float(np.mean(np.abs(z) > 3)),
        "chi2_dof": float(np.mean(z**2)),
        "max_abs_z": float(np.max(np.abs(z))),
    }


def ztest(ref, mi_mean, mi_se, mi_pass_means, passes, min_signal, mean_z_limit):
    ours, se_o = ref["mean"], ref["stderr"]
    denom = np.sqrt(se_o**2 + mi_se**2)
    valid = denom > 0
    z = np.where(valid, (ours - mi_mean) / np.where(valid, denom, 1), 0.0)
    # Test pixels: chosen on our (precise) image only, so the choice does not
    # depend on Mitsuba's noise: at least min_signal of the channel's maximum.
    peak = ours.reshape(-1, ours.shape[2]).max(axis=0)
    test = valid & (ours >= min_signal * peak[None, None, :])
    if not test.any():
        die("no test pixels (all below --min-signal)")
    st_all = zstats(z[valid])
    st = zstats(z[test])
    n = st["n"]

    m_o = float(ours.mean())
    m_m = float(mi_mean.mean())
    s_m = float(np.std(mi_pass_means, ddof=1) / math.sqrt(passes))
    s_o_ind = float(math.sqrt(np.sum(se_o**2)) / se_o.size)
    s_o_cor = float(se_o.mean())
    ratio = m_o / m_m
    sig_lo = ratio * math.hypot(s_o_ind / m_o, s_m / m_m)
    sig_hi = ratio * math.hypot(s_o_cor / m_o, s_m / m_m)

    nu = passes - 1
    e2, v2 = t_moments(nu) if nu > 4 else (float("inf"), float("inf"))
    chi2_hi = e2 + 5 * math.sqrt(v2 / n)
    chi2_lo = 1 - 5 * math.sqrt(2 / n)
    chi2, mean_z, frac3 = st["chi2_dof"], st["mean_z"], st["frac_abs_z_gt_3"]
    checks = {
        "chi2_dof_upper": {"value": chi2, "limit": chi2_hi, "pass": chi2 <= chi2_hi},
        "chi2_dof_lower": {"value": chi2, "limit": chi2_lo, "pass": chi2 >= chi2_lo},
        "mean_z": {"value": mean_z, "limit": mean_z_limit, "pass": abs(mean_z) <= mean_z_limit},
        "frac_abs_z_gt_3": {"value": frac3, "limit": 0.02, "pass": frac3 <= 0.02},
        "ratio": {"value": ratio, "limit": 5 * sig_lo, "pass": abs(ratio - 1) <= 5 * sig_lo},
    }
    stats = dict(st)
    stats.update({
        "test_pixels": "ours >= %g x channel max" % min_signal,
        "all_pixels": st_all,
        "image_mean_ours": m_o,
        "image_mean_mitsuba": m_m,
        "image_mean_mitsuba_stderr": s_m,
        "image_mean_ours_stderr_independent": s_o_ind,
        "image_mean_ours_stderr_correlated": s_o_cor,
        "ratio_ours_over_mitsuba": ratio,
        "ratio_sigma_independent": sig_lo,
        "ratio_sigma_correlated": sig_hi,
        "median_rel_stderr_ours": float(np.median(se_o[test] / ours[test])),
        "median_rel_stderr_mitsuba": float(np.median(mi_se[test] / np.abs(mi_mean[test]).clip(1e-300))),
        # Test pixels where Mitsuba's estimate is too noisy for a normal z
        # (relative stderr > 0.3, or no spread at all): raise --spp.
        "mitsuba_unreliable_test_pixels": int(np.sum(test & ((mi_se == 0) | (mi_se > 0.3 * np.abs(mi_mean))))),
    })
    return z, test, stats, checks


def render_passes(ref, args):
    llvm = pick_libllvm()
    import drjit as dr
    import mitsuba as mi

    variant = args.variant
    if variant is None:
        variant = "scalar_rgb"
        if llvm and "llvm_ad_rgb" in mi.variants():
            variant = "llvm_ad_rgb"
    mi.set_variant(variant)
    if not variant.endswith("_rgb"):
        die("use an *_rgb variant (albedo/sigma_t grids are RGB values, no spectral upsampling)")
    print(f"mitsuba {mi.__version__}, drjit {dr.__version__}, variant {variant}"
          + (f", libLLVM {llvm}" if variant.startswith("llvm") else ""))
    print(f"scene: eta {ref['eta']}, g {ref['g']}, texel {ref['texel']}, albedo map {ref['albedo'].shape}, "
          f"density map {ref['density'].shape}, light R {ref['radius']} E {ref['irradiance']}, "
          f"N {ref['n']}, W {ref['half_width']}, C {ref['channels']}, light height {args.epsilon:.3g}")

    scene_dict = build_scene(mi, ref, args)
    self_ok = None
    if args.self_test:
        self_ok = self_test(mi, ref, scene_dict, args)
        print(f"self-test: {'PASS' if self_ok else 'FAIL'}")

    scene = mi.load_dict(scene_dict)
    t0 = time.time()
    imgs = []
    for p in range(args.passes):
        tp = time.time()
        img = np.array(mi.render(scene, seed=args.seed + p, spp=args.spp), dtype=np.float64)
        imgs.append(img)
        print(f"  pass {p + 1}/{args.passes}: {time.time() - tp:.1f} s, image mean {img[..., 0].mean():.6g}",
              flush=True)
    return {
        "imgs": np.stack(imgs),  # (P, N, N, 3)
        "self_ok": self_ok,
        "wall_s": time.time() - t0,
        "version": mi.__version__,
        "drjit": dr.__version__,
        "variant": variant,
        "libllvm": llvm if variant.startswith("llvm") else None,
        "spp": args.spp,
        "passes": args.passes,
        "seeds": [args.seed, args.seed + args.passes - 1],
        "epsilon": args.epsilon,
        "margin": args.margin,
        "depth": args.depth,
        "rr_depth": args.rr_depth,
    }


# --------------------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir", help="output folder of `svkernel render --method reference`")
    ap.add_argument("--pass", dest="tag", default=None,
                    help="pass subfolder (default: the first in render.json, e.g. main)")
    ap.add_argument("--spp", type=int, default=1024, help="samples per pixel per pass [1024]")
    ap.add_argument("--passes", type=int, default=32, help="independent passes (seeds S..S+P-1) [32]")
    ap.add_argument("--seed", type=int, default=0, help="first pass seed S [0]")
    ap.add_argument("--variant", default=None,
                    help="Mitsuba variant (default: llvm_ad_rgb if it runs, else scalar_rgb)")
    ap.add_argument("--margin", type=float, default=30.0,
                    help="box half-width beyond the image/maps, MFP [30]")
    ap.add_argument("--depth", type=float, default=60.0, help="box depth, MFP [60]")
    ap.add_argument("--epsilon", type=float, default=None,
                    help="light height above z = 0, MFP [max(1e-3, 20 (1 + R) RayEpsilon)]")
    ap.add_argument("--rr-depth", type=int, default=5, help="volpath Russian roulette depth [5]")
    ap.add_argument("--min-signal", type=float, default=0.02,
                    help="test pixels: ours >= this fraction of the channel maximum [0.02]")
    ap.add_argument("--mean-z-limit", type=float, default=0.3,
                    help="pass limit on |mean z| over the test pixels [0.3]")
    ap.add_argument("--self-test", action="store_true",
                    help="first check grid placement, pixel placement and the light's irradiance")
    ap.add_argument("--save", default=None,
                    help="also write the Mitsuba passes, mean, stderr, z and test mask (.npy) here")
    ap.add_argument("--from-saved", default=None,
                    help="re-analyse the passes an earlier --save wrote to this folder (no rendering)")
    ap.add_argument("--out", default=None, help="JSON report path")
    args = ap.parse_args()
    if args.passes < 2:
        die("--passes must be at least 2")

    ref = load_reference(args.dir, args.tag)
    if args.epsilon is None:
        # Above the offset Mitsuba gives rays leaving the surface under the
        # light, (1 + max|p|) * RayEpsilon (RayEpsilon = 1500 * 2^-24).
        args.epsilon = max(1e-3, 20 * (1 + ref["radius"]) * 1500 * 2.0**-24)
    f0 = ((ref["eta"] - 1) / (ref["eta"] + 1)) ** 2
    C = ref["channels"]
    self_ok = None
    if args.from_saved:
        # Re-analysis of passes saved by an earlier --save run (no rendering).
        imgs = np.load(os.path.join(args.from_saved, "mitsuba_passes.npy"))
        with open(os.path.join(args.from_saved, "mitsuba_meta.json")) as f:
            run = json.load(f)
        if imgs.shape[1:] != ref["mean"].shape:
            die(f"saved passes {imgs.shape} do not match the reference {ref['mean'].shape}")
        args.passes, args.spp = imgs.shape[0], run["spp"]
        print(f"loaded {args.passes} saved passes from {args.from_saved} ({run['variant']}, {run['spp']} spp)")
    else:
        run = render_passes(ref, args)
        imgs = run.pop("imgs")
        # Remove the camera ray's specular reflection of the light (not in the reference).
        cov = disk_coverage(ref["n"], ref["half_width"], ref["radius"])
        imgs = imgs - (f0 * ref["irradiance"] / math.pi * cov)[None, :, :, None]
        if C == 1:
            spread = float(np.abs(imgs - imgs[..., :1]).max())
            if spread > 1e-6 * max(1e-30, float(np.abs(imgs).max())):
                print(f"warning: grey scene but channels differ by {spread:.3g}")
            imgs = imgs[..., :1]
        self_ok = run.pop("self_ok")
    wall = run["wall_s"]
    mi_mean = imgs.mean(axis=0)
    mi_se = imgs.std(axis=0, ddof=1) / math.sqrt(args.passes)
    pass_means = imgs.mean(axis=(1, 2, 3))

    z, test, stats, checks = ztest(ref, mi_mean, mi_se, pass_means, args.passes,
                                   args.min_signal, args.mean_z_limit)
    passed = all(c["pass"] for c in checks.values()) and self_ok is not False

    print(f"Mitsuba: {args.passes} passes x {args.spp} spp "
          + (f"(saved; wall time of the run that saved them: {wall:.1f} s)" if args.from_saved
             else f"in {wall:.1f} s ({wall / args.passes:.1f} s/pass)"))
    print(f"median relative stderr: ours {stats['median_rel_stderr_ours']:.4f}, "
          f"mitsuba {stats['median_rel_stderr_mitsuba']:.4f}")
    for label, st in (("test pixels (%s)" % stats["test_pixels"], stats), ("all pixels", stats["all_pixels"])):
        print(f"Z-test, {label}: n {st['n']}, mean z {st['mean_z']:+.3f}, std z {st['std_z']:.3f}, "
              f"|z| > 3: {100 * st['frac_abs_z_gt_3']:.2f} %, chi2/dof {st['chi2_dof']:.3f}, "
              f"max |z| {st['max_abs_z']:.2f}")
    print(f"image mean: ours {stats['image_mean_ours']:.6g}, mitsuba {stats['image_mean_mitsuba']:.6g} "
          f"± {stats['image_mean_mitsuba_stderr']:.2g}; ratio ours/mitsuba {stats['ratio_ours_over_mitsuba']:.4f} "
          f"± {stats['ratio_sigma_independent']:.4f} (our pixels independent) "
          f"/ ± {stats['ratio_sigma_correlated']:.4f} (fully correlated)")
    if stats["mitsuba_unreliable_test_pixels"]:
        print(f"warning: {stats['mitsuba_unreliable_test_pixels']} test pixels have a Mitsuba relative stderr "
              "> 0.3 or none: z is not normal there; raise --spp or --passes")
    for name, c in checks.items():
        print(f"  {'ok  ' if c['pass'] else 'FAIL'} {name}: {c['value']:.4g} (limit {c['limit']:.4g})")
    print("PASS" if passed else "FAIL")

    if args.save:
        os.makedirs(args.save, exist_ok=True)
        np.save(os.path.join(args.save, "mitsuba_mean.npy"), mi_mean)
        np.save(os.path.join(args.save, "mitsuba_stderr.npy"), mi_se)
        np.save(os.path.join(args.save, "z.npy"), z)
        np.save(os.path.join(args.save, "test_mask.npy"), test)
        np.save(os.path.join(args.save, "mitsuba_passes.npy"), imgs)
        with open(os.path.join(args.save, "mitsuba_meta.json"), "w") as f:
            json.dump(run, f, indent=2)
    if args.out:
        report = {
            "format": "svkernel.mitsuba_check",
            "dir": os.path.abspath(args.dir),
            "pass": ref["tag"],
            "passed": passed,
            "self_test": self_ok,
            "stats": stats,
            "checks": checks,
            "mitsuba": dict(run, specular_term_subtracted={"F0": f0, "max": f0 * ref["irradiance"] / math.pi}),
            "commands": {
                "reference": shlex.join(ref["meta"].get("provenance", {}).get("command_line", [])),
                "mitsuba_check": shlex.join([sys.executable] + sys.argv),
            },
        }
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
        print(f"wrote {args.out}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
