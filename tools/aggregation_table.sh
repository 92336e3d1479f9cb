#!/usr/bin/env bash
# The aggregation-space tables of docs/measurements.md: `learned` and `manual`
# against the reference, relative RMSE (noise subtracted) and mean relative
# bias, for each albedo space and scale b, on the canonical scenes, the edge
# scene and eight held-out textures (written below, not in scenes/); and the
# exitance across the edge, model over reference, at distances from the step.
#
#   bash tools/aggregation_table.sh [OUT]      # default out/aggregation_table
#
# Writes OUT/<config>/<scene>/render.json, OUT/table.md and OUT/edge.md.
# About 15 minutes on 2 cores. Needs python3 (standard library only).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/aggregation_table}
paths=${PATHS:-1e7}
spp=${SPP:-256}
mkdir -p "$out/scenes"
cargo build --release --quiet
bin=./target/release/svkernel

# Held-out textures: none of them was looked at while b was chosen.
held() { # name albedo [head] [light kind] [light radius]
  cat > "$out/scenes/$1.toml" <<TOML
name = "$1"
texel = 0.05
albedo = $2
${3:-}
[light]
kind = "${4:-collimated}"
radius = ${5:-1.0}
[image]
resolution = 64
half_width = 4.0
TOML
}
held coarse '{ pattern = "stripes", values = [0.3, 0.95], width = 2.0 }'
held bigcheck '{ pattern = "checker", values = [0.2, 0.9], cell = 1.5 }'
held translucent '{ pattern = "complex", values = [0.98, 0.5], seed = 3 }'
held diagonal '{ pattern = "stripes", values = [0.6, 0.99], width = 1.0, angle = 45.0 }'
held stripes_diffuse '{ pattern = "stripes", values = [0.3, 0.95], width = 0.5 }' '' diffuse
held checker_radiance '{ pattern = "checker", values = [0.2, 0.9], cell = 0.5 }' \
  'observable = "radiance"' diffuse
held edge_wide '{ pattern = "stripes", values = [0.2, 0.95], width = 100.0 }' '' collimated 3.0
held density_step '{ pattern = "stripes", values = [0.4, 0.9], width = 1.0 }' \
  'density = { pattern = "stripes", values = [0.5, 3.0], width = 100.0 }'

scenes="scenes/stripes.toml scenes/checker.toml scenes/complex.toml scenes/color.toml
  scenes/density.toml scenes/features.toml scenes/extra/edge.toml scenes/extra/dark.toml
  scenes/extra/grey_rgb.toml $(ls "$out"/scenes/*.toml | tr '\n' ' ')"
configs="linear:0 transport:0 transport:0.1 transport:0.25 transport:0.5 transport:1
  log:0.25 absorption:0.25"
for c in $configs; do
  for s in $scenes; do
    name=$(basename "$s" .toml)
    "$bin" render "$s" --method reference,learned,manual --paths "$paths" --spp "$spp" \
      --albedo-space "${c%%:*}" --space-blur "${c##*:}" --out "$out/$c/$name" > /dev/null
  done
done

# The edge at 1e8 paths and 1024 spp: linear against the default.
for c in linear:0 transport:0.25; do
  "$bin" render scenes/extra/edge.toml --method reference,learned,manual --paths 1e8 \
    --spp 1024 --albedo-space "${c%%:*}" --space-blur "${c##*:}" \
    --out "$out/edge_fine/$c" > /dev/null
done

python3 - "$out" $configs <<'PY'
import ast, pathlib, struct, sys
sys.path.insert(0, "tools")
from render_metrics import cell, metrics, table
out, configs = pathlib.Path(sys.argv[1]), sys.argv[2:]

rows = {}
for c in configs:
    for scene, tag, method, e in metrics(out / c):
        key = scene + ("" if tag in ("", "main") else f" {tag}")
        rows.setdefault(method, {}).setdefault(key, {})[c] = cell(e)
text = ""
for method, scenes in rows.items():
    text += f"\n`{method}`, relative RMSE (mean relative bias):\n\n"
    text += table(scenes, configs, lambda c: c.replace(":", " b="))
(out / "table.md").write_text(text)
print(text)

def npy(path):
    raw = path.read_bytes()
    n = struct.unpack("<H", raw[8:10])[0]
    head = ast.literal_eval(raw[10:10 + n].decode())
    shape = head["shape"]
    vals = struct.unpack(f"<{len(raw[10 + n:]) // 8}d", raw[10 + n:])
    return shape, vals

edge = "| x [MFP] | " + " | ".join(
    f"{m} {c.replace(':', ' b=')}" for c in ("linear:0", "transport:0.25") for m in ("learned", "manual")
) + " |\n" + "|---" * 5 + "|\n"
xs = [-3.9, -3.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 3.0, 3.9]
cols = []
for c in ("linear:0", "transport:0.25"):
    d = out / "edge_fine" / c / "main"
    (ny, nx, _), ref = npy(d / "reference_mean.npy")
    band = range(ny // 2 - 4, ny // 2 + 4)  # |y| < 0.5 MFP
    mean = lambda v, j: sum(v[i * nx + j] for i in band)
    for m in ("learned", "manual"):
        _, v = npy(d / f"{m}_mean.npy")
        cols.append([mean(v, int((x + 4) / 8 * nx)) / mean(ref, int((x + 4) / 8 * nx)) for x in xs])
for k, x in enumerate(xs):
    edge += f"| {x:+.1f} | " + " | ".join(f"{col[k]:.3f}" for col in cols) + " |\n"
(out / "edge.md").write_text(edge)
print(edge)
PY
