#!/usr/bin/env bash
# The learned model's own error per canonical scene and pass: `learned` at
# 1024 spp against a reference of many paths, relative RMSE with both
# images' noise subtracted (tools/cell_bias.py, as `compare` measures it).
#
#   bash tools/bias_table.sh [MODEL.json] [extra render options]
#
# MODEL: a meta-model file (default: the built-in one). Environment: OUT
# (default out/bias_table), SCENES, SPP (1024). References are rendered once
# into OUT/ref/SCENE and reused: 2e8 paths for the canonical scenes, 1e8
# per pass for `features`, 2e7 for the translucent scenes (about 7 min in
# all on 2 cores); each run then takes about 3 min. Needs numpy on PATH's
# python3.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-}
[ $# -gt 0 ] && shift
out=${OUT:-out/bias_table}
tag=$(basename "${model:-builtin}" .json)
cargo build --release --quiet
bin=./target/release/svkernel
for s in ${SCENES:-stripes checker complex color density features marble skin milk}; do
  case $s in
    marble | skin | milk) src=scenes/$s.toml paths=2e7 ;;
    features) src=$s paths=1e8 ;;
    *) src=$s paths=2e8 ;;
  esac
  ref=$out/ref/$s
  [ -f "$ref/render.json" ] || "$bin" render "$src" --method reference --paths $paths --out "$ref" > /dev/null
  tallies=()
  for p in "$ref"/*/; do tallies+=(--reference-tally "${p}reference.tally.json"); done
  run=$out/$tag/$s
  "$bin" render "$src" --method learned --spp "${SPP:-1024}" "${tallies[@]}" \
    ${model:+--model "$model"} "$@" --out "$run" > /dev/null
  line="$s:"
  for p in "$ref"/*/; do
    pass=$(basename "$p")
    err=$(python3 tools/cell_bias.py "$run" --pass "$pass" --reference "$ref" | tail -1 | awk '{print $(NF-1)}')
    line="$line $pass $err %"
  done
  echo "$line"
done
