#!/usr/bin/env bash
# Regenerates the wide-box kernel tally data/kernels/eta1.5_g0.3_pencil_wide.json
# and the meta-model fitted to it, data/profiles/metamodel_wide.json (+ its
# report), then makes the shipped meta-model carry it for the kernel queries
# outside its own box (d ∈ [0.1, 10] MFP, α ∈ [0.2, 0.99]).
#
# The box is α ∈ [0.05, 0.999] × d ∈ [0.05, 20] MFP: 10 albedos × 13 pair
# distances on a window of ±6λ (bins of λ/4, as the shipped tally's) with a
# tail of 10 log-spaced bins out to ±32λ (docs/method.md §3, "Grids"), planned
# per cell for 2000 effective contributing paths with the exponential
# transform, the stretch and the angular bias on offer, and one top-up round;
# then two more rounds that may move a cell whose sampling delivered far less
# than its pilot promised to another sampling (--replan, docs/method.md §3):
# that moves α = 0.2, d = 20 MFP from the exponential transform to the
# angular bias. The angular bias leaves the moments of the cells at
# α = 0.999 noisy (heavy-tailed weights), so an analog tally of that row on
# the same grid (eta1.5_g0.3_pencil_wide_top.json, 6e7 paths) is overlaid
# on the planned one for the fit (--in TALLY --in ANALOG: its cells replace
# that row's). The fit sums the last-vertex histograms onto bins of λ/8
# (exact), four times fewer bins than the tally's λ/16, and lets the
# moment residuals allow for the data's errors (--moment-errors) at weight
# 30 (--moment-weight 30): its moments rest on 2000 effective paths, and at
# the default 70 the fit follows them at the bins' expense (docs/method.md
# §4, "The wide box"). It refits
# at degrees (6, 5) from the wide model already in data/profiles (--from,
# its degrees raised where lower), whose coefficients
# start the joint fits where a climb from the new per-cell fits settles in a
# poorer valley (docs/method.md §4); cells where that model is stuck are
# refitted with a width floor first ("Stuck cells"). Without a wide model it
# fits from the data alone.
#
#   bash tools/make_kernels_wide.sh             # tally, fit and the shipped model
#   SKIP_SIM=1 bash tools/make_kernels_wide.sh  # refit an existing tally only
set -euo pipefail
cd "$(dirname "$0")/.."
tally=data/kernels/eta1.5_g0.3_pencil_wide.json
analog=data/kernels/eta1.5_g0.3_pencil_wide_top.json
distances=0.05,0.1,0.2,0.35,0.6,1,1.6,2.5,4,6.5,10,14,20
grid=(--nu 48 --nv 24 --extent 6 --tail-bins 10 --tail-extent 32)
medium=(--rel-width 0.1 --min-order 2 --eta 1.5 --g 0.3 --density 1)
cargo build --release --quiet
bin=./target/release/svkernel
if [ -z "${SKIP_SIM:-}" ]; then
  $bin simulate kernels \
    --albedos 0.05,0.2,0.4,0.6,0.75,0.85,0.92,0.96,0.99,0.999 \
    --distances "$distances" "${grid[@]}" "${medium[@]}" \
    --min-paths 2000 --angular 0.8,0.9,0.97 --top-ups 1 --paths 4e8 --seed 3000 --resume \
    --out "$tally" | sed -n 1p
  $bin simulate kernels --from "$tally" --min-paths 2000 --angular 0.8,0.9,0.97 \
    --top-ups 2 --replan --paths 4e8 --resume --out "$tally" | sed -n 1p
  $bin simulate kernels --albedos 0.999 --distances "$distances" "${grid[@]}" "${medium[@]}" \
    --paths 6e7 --seed 3003 --resume --out "$analog" | sed -n 1p
fi
wide=data/profiles/metamodel_wide.json
start=(--degree 6,5)
if [ -f "$wide" ]; then start+=(--from "$wide"); fi
$bin fit kernels --in "$tally" --in "$analog" "${start[@]}" --vertex-refine 2 \
  --moment-errors --moment-weight 30 --out "$wide" --report data/profiles/metamodel_wide_report
$bin fit outer --model data/profiles/metamodel.json --outer data/profiles/metamodel_wide.json \
  --out data/profiles/metamodel.json
