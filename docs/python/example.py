"""svkernel from Python: a learned kernel, and a render against brute force.

Draws (1) the learned all-vertex kernel for d = 1 MFP at three albedos and the
manual kernel, as densities along the pair axis t (s = 0), and (2) the
canonical `stripes` scene rendered by `learned`, `point` and the brute-force
reference, with the row through the light's centre. Writes kernel.png and
render.png into --out (default: the current folder).

    pip install ./python matplotlib
    python docs/python/example.py --out docs/python
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import svkernel as sk  # noqa: E402


def along_axis(k: sk.Kernel, t: np.ndarray) -> np.ndarray:
    """The kernel's density K(t, s = 0) (1/MFP²) at the points t."""
    w, c, s = k.weights[..., None], k.centres[..., 0, None], k.widths[..., None]
    g = w * np.exp(-0.5 * ((t - c) ** 2 + k.centres[..., 1, None] ** 2) / s**2) / (2 * np.pi * s**2)
    return g.sum(axis=-2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("."))
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    t = np.linspace(-1.5, 2.5, 400)
    albedos = np.array([0.5, 0.9, 0.99])
    learned = sk.kernel(1.0, albedos)  # vectorised over the albedos
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for a, dens in zip(albedos, along_axis(learned, t)):
        ax.plot(t, dens, label=f"learned, albedo {a}")
    ax.plot(t, along_axis(sk.kernel(1.0, 0.9, manual=True), t), "k--", label="manual")
    ax.axvline(0, color="grey", lw=0.5)
    ax.axvline(1, color="grey", lw=0.5)
    ax.set(xlabel="t (MFP): x_i at 0, x_e at 1", ylabel="K(t, 0) (1/MFP²)",
           title="Where paths from x_i to x_e scatter (d = 1 MFP)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "kernel.png", dpi=120)

    r = sk.render("stripes", methods=["reference", "point", "learned"], spp=args.spp)
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.4))
    vmax = r["reference"]["mean"].max()
    for ax, m in zip(axes, ["reference", "point", "learned"]):
        ax.imshow(r[m]["mean"][..., 0], vmin=0, vmax=vmax, cmap="magma")
        err = "" if m == "reference" else f"\nrel. RMSE {100 * r[m]['rel_rmse']:.1f} %"
        ax.set_title(f"{m} ({r[m]['seconds']:.2f} s){err}", fontsize=9)
        ax.axis("off")
    row = r["reference"]["mean"].shape[0] // 2
    for m, style in [("reference", "k-"), ("point", "C0--"), ("learned", "C1-")]:
        axes[3].plot(r[m]["mean"][row, :, 0], style, label=m, lw=1)
    axes[3].set(title="row through the light", xlabel="pixel")
    axes[3].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "render.png", dpi=100)
    for m in ["point", "learned"]:
        print(f"{m:<8} rel. RMSE {100 * r[m]['rel_rmse']:5.2f} %  bias {100 * r[m]['rel_bias']:+5.2f} %  "
              f"{r[m]['seconds']:.2f} s")
    print(f"wrote {args.out / 'kernel.png'} and {args.out / 'render.png'}")


if __name__ == "__main__":
    main()
