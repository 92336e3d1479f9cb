#!/usr/bin/env bash
# Error vs kernel complexity and meta-model size: refits the
# kernel meta-model from the shipped kernel tallies with K = 1…5 Gaussians
# (polynomial degrees 3, 3) and with degrees 1…4 at K = 3, and the basis
# BSSRDF from the shipped profiles with 3, 4, 6 and 8 exponential terms,
# then renders stripes and checker with `learned` under each, inside the
# open experiments. About 5 min (fits) + 4 min (experiments) on 2 cores.
#
#   bash tools/kernel_complexity.sh            # writes out/models/, out/experiments/
#   SVKERNEL=path/to/svkernel OUT=dir bash tools/kernel_complexity.sh
set -euo pipefail
cd "$(dirname "$0")/.."
SVKERNEL=${SVKERNEL:-target/release/svkernel}
OUT=${OUT:-out}
[ -x "$SVKERNEL" ] || cargo build --release
mkdir -p "$OUT/models"
models=()
fit() { # K DX DY
  local m="$OUT/models/k$1_deg$2$3.json"
  if [ ! -f "$m" ]; then
    "$SVKERNEL" fit kernels --components "$1" --degree "$2,$3" --out "$m" \
      --report "$OUT/models/k$1_deg$2$3_report" > "$OUT/models/k$1_deg$2$3.log"
  fi
  models+=("$m")
}
for k in 1 2 3 4 5; do fit "$k" 3 3; done
for d in 1 2 4; do fit 3 "$d" "$d"; done
bases=()
for n in 3 4 6 8; do
  b="$OUT/models/basis_$n.json"
  if [ ! -f "$b" ]; then
    "$SVKERNEL" fit profiles --components "$n" --out "$b" \
      --report "$OUT/models/basis_${n}_report" > "$OUT/models/basis_$n.log"
  fi
  bases+=("$b")
done
list=$(IFS=,; echo "${models[*]}")
blist=$(IFS=,; echo "${bases[*]}")
"$SVKERNEL" experiments --models "$list" --bases "$blist" --out "$OUT/experiments" "$@"
