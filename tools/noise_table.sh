#!/usr/bin/env bash
# The model's own noise per canonical scene, apart from its bias: `learned`
# rendered SEEDS times at SPP samples per pixel (seeds 1..SEEDS) against one
# render of the same model at 4096 spp (seed 77), as the relative RMSE
# √(Σ(m − h)²/Σh²) over every pass and channel (the measure of `compare`),
# with the median render time (set-up excluded) and their product
# error² × time (lower is better: the time to a given error).
#
#   bash tools/noise_table.sh [OUT]            # default out/noise_table
#   SAMPLING=profile bash tools/noise_table.sh # another sampler
#   SPP=16 SEEDS=8 SCENES="stripes milk" bash tools/noise_table.sh
#
# The 4096-spp renders are kept in OUT/hi and reused. About 5 minutes on
# 2 cores (the first run 10 more for the 4096-spp renders). Needs python3
# with numpy (tools/requirements.txt).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/noise_table}
spp=${SPP:-64}
seeds=${SEEDS:-4}
sampling=${SAMPLING:-importance}
scenes=${SCENES:-"stripes checker complex color density features marble skin milk"}
cargo build --release --quiet
bin=./target/release/svkernel
for s in $scenes; do
  if [ ! -f "$out/hi/$s/render.json" ]; then
    $bin render "$s" --method learned --spp 4096 --seed 77 --sampling "$sampling" \
      --out "$out/hi/$s" > /dev/null
  fi
  for k in $(seq 1 "$seeds"); do
    $bin render "$s" --method learned --spp "$spp" --seed "$k" --sampling "$sampling" \
      --out "$out/$sampling-$spp/$s/$k" > /dev/null
  done
done
python3 - "$out" "$sampling-$spp" "$seeds" $scenes <<'PY'
import json, pathlib, sys
import numpy as np
out, tag, seeds, scenes = pathlib.Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4:]
rows = []
for s in scenes:
    hi = out / "hi" / s
    passes = sorted(p.parent.name for p in hi.glob("*/learned_mean.npy"))
    err, times = [], []
    for k in range(1, seeds + 1):
        d = out / tag / s / str(k)
        num = den = 0.0
        for p in passes:
            h = np.load(hi / p / "learned_mean.npy")
            m = np.load(d / p / "learned_mean.npy")
            num += float(np.sum((m - h) ** 2))
            den += float(np.sum(h**2))
        err.append(num / den)
        doc = json.loads((d / "render.json").read_text())
        times.append(sum(x["wall_s"] - x["setup_s"] for q in doc["passes"] for x in q["methods"]))
    e, t = float(np.sqrt(np.mean(err))), float(np.median(times))
    rows.append(f"| {s} | {100 * e:.2f} % | {t:.3f} s | {1e6 * e * e * t:.0f} |")
head = (
    f"| scene | noise at {tag.split('-')[1]} spp ({tag.split('-')[0]}) | time | "
    "error² × time [10⁻⁶ s] |\n|---|---|---|---|\n"
)
(out / f"{tag}.md").write_text(head + "\n".join(rows) + "\n")
print((out / f"{tag}.md").read_text())
PY
