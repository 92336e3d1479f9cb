#!/usr/bin/env bash
# The density tables of docs/measurements.md: `learned` and `manual`
# against the reference, relative RMSE (noise subtracted) and mean relative
# bias, on every scene whose density varies: the canonical `density`, the
# two step scenes of scenes/extra, four steps the law was chosen on, three
# held-out scenes and two held-out textured steps (written below, not in
# scenes/). Each scene is rendered once per value of one option:
#
#   bash tools/density_law_table.sh [OUT]      # --density-law kernel|endpoints
#   OPTION=density-kernel VALUES="scaled warp" bash tools/density_law_table.sh [OUT]
#
# Writes OUT/<value>/<scene>/render.json and OUT/table.md. About 15 minutes
# per value on 2 cores (the reference is rendered once per scene and value).
# Needs python3 (standard library only).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/density_law_table}
paths=${PATHS:-1e8}
spp=${SPP:-256}
mkdir -p "$out/scenes"
cargo build --release --quiet
bin=./target/release/svkernel

scene() { # name albedo density light-radius [light kind]
  cat > "$out/scenes/$1.toml" <<TOML
name = "$1"
texel = 0.05
albedo = $2
density = $3
[light]
kind = "${5:-collimated}"
radius = $4
[image]
resolution = 64
half_width = 4.0
TOML
}
step() { echo "{ pattern = \"stripes\", values = [$1], width = 100.0 }"; }
# The steps the law was chosen on.
scene chosen_a 0.6 "$(step 1.0,4.0)" 1.0
scene chosen_b 0.95 "$(step 4.0,1.0)" 0.5
scene chosen_c 0.8 "$(step 0.5,2.0)" 1.5
scene chosen_d '{ pattern = "stripes", values = [0.3, 0.95], width = 0.5, angle = 0.0 }' \
  "$(step 1.0,3.0)" 1.0
# Held out: not rendered before the law was fixed.
scene held_ramp_checker '{ pattern = "checker", values = [0.2, 0.9], cell = 1.0 }' \
  '{ pattern = "ramp", values = [0.5, 4.0], length = 8.0 }' 1.0
scene held_density_checker 0.8 '{ pattern = "checker", values = [1.0, 3.0], cell = 2.0 }' 1.0
scene held_step_diffuse '{ pattern = "stripes", values = [0.4, 0.9], width = 1.0 }' \
  "$(step 0.5,3.0)" 1.0 diffuse
scene held_bright_step '{ pattern = "stripes", values = [0.9, 0.99], width = 0.5, angle = 0.0 }' \
  "$(step 1.0,4.0)" 1.0
scene held_dark_step '{ pattern = "checker", values = [0.3, 0.7], cell = 0.5 }' "$(step 4.0,1.0)" 1.0

scenes="scenes/density.toml scenes/extra/density_step.toml scenes/extra/uniform_step.toml
  $(ls "$out"/scenes/*.toml | tr '\n' ' ')"
option=${OPTION:-density-law}
laws=${VALUES:-kernel endpoints}
for law in $laws; do
  for s in $scenes; do
    name=$(basename "$s" .toml)
    "$bin" render "$s" --method reference,learned,manual --paths "$paths" --spp "$spp" \
      "--$option" "$law" --out "$out/$law/$name" > /dev/null
  done
done

python3 - "$out" $laws <<'PY'
import pathlib, sys
sys.path.insert(0, "tools")
from render_metrics import cell, metrics, table
out, laws = pathlib.Path(sys.argv[1]), sys.argv[2:]

rows = {}
for law in laws:
    for scene, _, method, e in metrics(out / law):
        rows.setdefault(scene, {})[(method, law)] = cell(e)
cols = [(m, law) for m in ("learned", "manual") for law in laws]
text = table(rows, cols, lambda c: f"{c[0]}, {c[1]}")
(out / "table.md").write_text(text)
print(text)
PY
