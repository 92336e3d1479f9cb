"""Writes the two example targets of `svkernel design` (256 x 256, sRGB PNG):

* docs/design/lines.png: a line drawing with lettering (dark ink, R = 0.12,
  on a light ground, R = 0.32): strokes of 6-16 texels (0.3-0.8 MFP at the
  default texel of 0.05 MFP), the scale at which sub-surface transport blurs
  a print and pre-compensation can still restore it;
* docs/design/photo.png: a photograph-like RGB image: a shaded sphere on a
  textured ground, soft shadows, fine detail and smooth gradients, every
  channel within R = 0.03-0.45.

Both are band-limited by a Gaussian of σ = 10 texels (0.5 MFP at the
default texel): detail much finer than the transport cannot be put into the
appearance by any albedo map (the exit side averages the albedo over about
1 MFP), so a printable target is low-passed first, as a print workflow
gamut-maps its colours.

Usage: python tools/design_targets.py [OUT_DIR]   (numpy only)
"""

import struct
import sys
import zlib
from pathlib import Path

import numpy as np

N = 256

# A 5 x 7 bitmap font for the lettering.
GLYPHS = {
    "S": ["01111", "10000", "10000", "01110", "00001", "00001", "11110"],
    "V": ["10001", "10001", "10001", "10001", "10001", "01010", "00100"],
    "K": ["10001", "10010", "10100", "11000", "10100", "10010", "10001"],
    "E": ["11111", "10000", "10000", "11110", "10000", "10000", "11111"],
    "R": ["11110", "10001", "10001", "11110", "10100", "10010", "10001"],
    "N": ["10001", "11001", "10101", "10011", "10001", "10001", "10001"],
    "L": ["10000", "10000", "10000", "10000", "10000", "10000", "11111"],
}


def srgb_encode(v):
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def write_png(path, linear):
    """Linear reflectances (ny, nx) or (ny, nx, 3) -> 8-bit sRGB PNG."""
    img = np.round(srgb_encode(linear) * 255).astype(np.uint8)
    h, w = img.shape[:2]
    colour = 2 if img.ndim == 3 else 0
    rows = b"".join(b"\x00" + img[i].tobytes() for i in range(h))

    def chunk(tag, data):
        c = struct.pack(">I", len(data)) + tag + data
        return c + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(rows, 9))
    png += chunk(b"IEND", b"")
    Path(path).write_bytes(png)


BAND_LIMIT = 10.0  # texels


def blur(a, sigma=BAND_LIMIT):
    """Separable Gaussian blur of (ny, nx[, 3]) with edge extension."""
    r = int(4 * sigma) + 1
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        pad = [(0, 0)] * a.ndim
        pad[axis] = (r, r)
        p = np.pad(a, pad, mode="edge")
        a = sum(k[i] * np.take(p, range(i, i + a.shape[axis]), axis=axis) for i in range(2 * r + 1))
    return a


def lines():
    ink, ground = 0.12, 0.32
    y, x = np.mgrid[0:N, 0:N] + 0.5
    mask = np.zeros((N, N), bool)
    # Circles of stroke widths 6-16 texels.
    for cx, cy, r, w in [(60, 60, 44, 6), (60, 60, 22, 10), (190, 60, 44, 12), (190, 60, 20, 16)]:
        mask |= np.abs(np.hypot(x - cx, y - cy) - r) < 0.5 * w
    # A fan of straight strokes, 6-12 texels wide.
    for k in range(5):
        a = np.pi * k / 4
        d = np.abs((x - 128) * np.sin(a) - (y - 250) * np.cos(a))
        along = (x - 128) * np.cos(a) + (y - 250) * np.sin(a)
        mask |= (d < 3 + 1.5 * k) & (along < -60) & (along > -110)
    # Lettering: 8-texel pixels of the 5 x 7 font.
    text, s, x0, y0 = "SVK", 8, 52, 118
    for i, ch in enumerate(text):
        for r, row in enumerate(GLYPHS[ch]):
            for c, bit in enumerate(row):
                if bit == "1":
                    xs = x0 + i * 6 * s + c * s
                    ys = y0 + r * s
                    mask[ys : ys + s, xs : xs + s] = True
    return blur(np.where(mask, ink, ground))


def photo():
    y, x = (np.mgrid[0:N, 0:N] + 0.5) / N
    rng = np.random.default_rng(7)
    # Ground: a warm gradient with a fine woven texture and soft noise.
    noise = np.zeros((N, N))
    for octave in range(5):
        f = 4 * 2**octave
        phase = rng.uniform(0, 2 * np.pi, 4)
        noise += (
            np.sin(2 * np.pi * f * x + phase[0]) * np.sin(2 * np.pi * f * y + phase[1])
            + np.sin(2 * np.pi * f * (x + y) + phase[2])
        ) / 2 ** (octave + 1)
    weave = 0.5 + 0.5 * np.sin(2 * np.pi * 32 * x) * np.sin(2 * np.pi * 32 * y)
    base = 0.22 + 0.10 * y + 0.03 * noise + 0.04 * weave
    rgb = np.stack([base * 1.15, base * 0.95, base * 0.75], axis=-1)
    # A soft shadow, then a shaded sphere with a specular-like highlight.
    cx, cy, r = 0.45, 0.45, 0.25
    shadow = np.exp(-(((x - cx - 0.1) / 0.28) ** 2 + ((y - cy - 0.22) / 0.1) ** 2))
    rgb *= (1 - 0.6 * shadow)[..., None]
    d2 = ((x - cx) ** 2 + (y - cy) ** 2) / r**2
    inside = d2 < 1
    nz = np.sqrt(np.clip(1 - d2, 0, 1))
    nx_, ny_ = (x - cx) / r, (y - cy) / r
    light = np.clip(-0.5 * nx_ - 0.6 * ny_ + 0.62 * nz, 0, 1)
    sphere = 0.04 + 0.34 * light + 0.08 * np.clip(light, 0.9, 1.0) ** 40
    stripes = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * 10 * (x + 0.3 * y)))
    colour = np.stack([0.35 + 0.6 * stripes, 0.55 - 0.2 * stripes, 0.9 - 0.5 * stripes], -1)
    rgb = np.where(inside[..., None], sphere[..., None] * colour, rgb)
    return blur(np.clip(rgb, 0.03, 0.45))


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/design")
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "lines.png", lines())
    write_png(out / "photo.png", photo())
    print(f"wrote {out}/lines.png, {out}/photo.png")


if __name__ == "__main__":
    main()
