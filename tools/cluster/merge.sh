#!/usr/bin/env bash
# Merges the N parts written by shard.sh into $OUT/merged.json (exact: integer
# tallies, chunk order). For a reference render, feed the result back with
#   svkernel render SCENE.toml --method reference --paths P --reference-tally $OUT/merged.json
#
#   merge.sh KIND                 KIND = profile | kernels | reference
set -euo pipefail
kind=$1
bin=${SVKERNEL:-svkernel}
out=${OUT:-out/cluster}
case "$kind" in
  profile | kernels) parts=("$out"/part*.json) ;;
  reference) parts=("$out"/part*/main/reference.tally.json) ;;
  *) echo "merge.sh: unknown kind '$kind'" >&2; exit 2 ;;
esac
"$bin" merge "${parts[@]}" --out "$out/merged.json"
