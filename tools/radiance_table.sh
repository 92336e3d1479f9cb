#!/usr/bin/env bash
# The radiance-observable table of docs/measurements.md: homogeneous media at
# α = 0.3, 0.8, 0.99 under both light kinds (radiance along the normal), and
# the canonical scenes under a diffuse light in both observables. Each scene
# is a built-in one with its light made diffuse (or a constant albedo), so
# nothing but the light kind and the observable changes.
#
#   bash tools/radiance_table.sh [OUT]      # default out/radiance_table
#
# Writes OUT/<scene>/render.json and OUT/table.md (relative RMSE with both
# images' noise subtracted, per method). About 15 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/radiance_table}
paths_h=${PATHS_HOMOGENEOUS:-1e8}
paths_c=${PATHS_CANONICAL:-1e7}
spp=${SPP:-256}
mkdir -p "$out/scenes"
cargo build --release --quiet
bin=./target/release/svkernel
for a in 0.3 0.8 0.99; do
  for k in collimated diffuse; do
    cat > "$out/scenes/h${a}_$k.toml" <<TOML
name = "h${a}_$k"
texel = 0.05
albedo = $a
observable = "radiance"
[light]
kind = "$k"
radius = 1.0
[image]
resolution = 32
half_width = 2.0
TOML
    "$bin" render "$out/scenes/h${a}_$k.toml" --method reference,point --paths "$paths_h" \
      --spp "$spp" --out "$out/h${a}_$k" > /dev/null
  done
done
for s in stripes checker complex color density; do
  for o in exitance radiance; do
    "$bin" scene "$s" | sed -e 's/^kind = "collimated"/kind = "diffuse"/' \
      -e "s/^name = \"$s\"/name = \"${s}_diffuse_$o\"\nobservable = \"$o\"/" \
      > "$out/scenes/${s}_diffuse_$o.toml"
    "$bin" render "$out/scenes/${s}_diffuse_$o.toml" --paths "$paths_c" --spp "$spp" \
      --out "$out/${s}_diffuse_$o" > /dev/null
  done
done
python3 - "$out" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
rows = []
for d in sorted(p for p in out.iterdir() if (p / "render.json").exists()):
    doc = json.loads((d / "render.json").read_text())
    for p in doc["passes"]:
        cells = []
        for m in p["methods"]:
            e = m.get("metrics")
            if not e:
                continue
            v = e["rel_rmse"]
            cells.append(f'{m["method"]} {"< noise" if v is None else f"{100*v:.1f} %"}')
        rows.append(f'| {d.name} | {p["tag"]} | ' + ", ".join(cells) + " |")
(out / "table.md").write_text("| scene | pass | relative RMSE, noise subtracted |\n|---|---|---|\n" + "\n".join(rows) + "\n")
print((out / "table.md").read_text())
PY
