#!/usr/bin/env bash
# R_d of the simulator against the oracle values (src/oracles.rs): the exact η = 1, g = 0 row
# (Chandrasekhar's H-function) and the adding-doubling row of the default
# medium (η = 1.5, g = 0.3), 1e7 paths per albedo (lanes engine), as a
# Markdown table with z = (sim − oracle)/stderr. About a minute on 2 cores.
#
#   bash tools/oracle_table.sh > out/oracle_table.md
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
alphas=(0.01 0.1 0.2 0.3 0.5 0.7 0.8 0.9 0.95 0.99 0.999)
exact=(.00154 .01639 .03523 .05721 .11523 .20868 .28525 .41495 .53554 .75272 .91285)
ad=(.00023 .00261 .00602 .01057 .02545 .05809 .09301 .17034 .26572 .51090 .77493)
echo "| medium | α | R_d sim ± stderr | oracle | z | events/s |"
echo "|---|---|---|---|---|---|"
row() {  # label eta g oracle-array-name
  local -n ref=$4
  for i in "${!alphas[@]}"; do
    local f="$tmp/p.json"
    ./target/release/svkernel simulate profile --albedo "${alphas[$i]}" --eta "$2" --g "$3" \
      --paths 1e7 --seed $((500 + i)) --out "$f" > /dev/null
    python3 - "$f" "$1" "${alphas[$i]}" "${ref[$i]}" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
o = float(sys.argv[4])
print(f"| {sys.argv[2]} | {sys.argv[3]} | {d['R_d']:.5f} ± {d['R_d_stderr']:.5f} | {o:.5f} "
      f"| {(d['R_d'] - o) / d['R_d_stderr']:+.1f} | {d['events'] / d['wall_s']:.2e} |")
PY
  done
}
row "η=1, g=0 (exact)" 1 0 exact
row "η=1.5, g=0.3 (A-D ±5e-4)" 1.5 0.3 ad
