#!/usr/bin/env bash
# The speed-up tables of docs/measurements.md: `svkernel compare` on every
# canonical scene (the translucent ones included), and per model its best
# speed-up over brute force at equal error and its error ratio in equal time.
#
#   bash tools/speedup_table.sh [OUT]                 # default out/speedup_table
#   SEQUENCE=independent bash tools/speedup_table.sh  # without the Sobol' points
#   SAMPLING=profile bash tools/speedup_table.sh      # without the albedo guide
#
# Writes OUT/<scene>/compare.json (and its report) and OUT/table.md. About
# 20 minutes on 2 cores. Needs python3 (standard library only).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/speedup_table}
sequence=${SEQUENCE:-sobol}
sampling=${SAMPLING:-importance}
scenes=${SCENES:-"stripes checker complex color density features marble skin milk"}
mkdir -p "$out"
cargo build --release --quiet
for s in $scenes; do
  ./target/release/svkernel compare "$s" --sequence "$sequence" --sampling "$sampling" --out "$out/$s" > /dev/null
done
python3 - "$out" $scenes <<'PY'
import json, pathlib, sys
out, scenes = pathlib.Path(sys.argv[1]), sys.argv[2:]
rows = []
for s in scenes:
    doc = json.loads((out / s / "compare.json").read_text())
    for p in doc["curves"]["speedups"]:
        e, re = p["rel_rmse"], p.get("reference_error")
        eq = "—" if re is None else f"{100 * re:.1f} % ({re / e:.1f}×)"
        rows.append(
            f"| {s} | {p['method']} | {p['budget']} | {p['wall_s'] - p['setup_s']:.3f} s | "
            f"{100 * e:.1f} % | {p['reference_s']:.3f} s | {p['ratio']:.2f}× | {eq} |"
        )
head = (
    "| scene | method | best spp | time | error | reference time to that error | "
    "speed-up | reference error in equal time (ratio) |\n|---|---|---|---|---|---|---|---|\n"
)
(out / "table.md").write_text(head + "\n".join(rows) + "\n")
print((out / "table.md").read_text())
PY
