#!/usr/bin/env bash
# Regenerates data/kernels/eta1.5_g0.3_pencil.json: path densities (first,
# last and all scattering vertices, multiple scattering) of the default
# medium (η = 1.5, g = 0.3, ρ = 1) under a pencil beam, at 8 albedos and 10
# pair distances (bins d·(1 ± 0.1)), the all-vertex window going on beyond
# ±4λ in 8 log-spaced bins out to ±16λ. The simulation is planned per cell
# (docs/method.md §3): each cell gets the flight sampling its pilot found
# best and paths for 40000 effective contributing paths, one round
# (1.38e9 paths). Then one top-up round gives every cell still below 2000
# effective paths more paths from its own walk (1.25e8 paths). About 17
# minutes on 2 cores in all.
#
#   bash tools/make_kernels.sh                 # the shipped training set
#   SHARD=k/N bash tools/make_kernels.sh       # one slice of the plan (merge the
#       slices with `svkernel merge`, then run the top-up below on the merged file)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-data/kernels/eta1.5_g0.3_pencil.json}
mkdir -p "$(dirname "$out")"
cargo build --release --quiet
shard_args=()
if [ -n "${SHARD:-}" ]; then shard_args=(--shard "$SHARD"); out="${out%.json}.shard${SHARD/\//of}.json"; fi
./target/release/svkernel simulate kernels \
  --albedos 0.2,0.4,0.6,0.75,0.85,0.92,0.96,0.99 \
  --distances 0.1,0.2,0.35,0.6,1,1.6,2.5,4,6.5,10 \
  --rel-width 0.1 --min-order 2 --eta 1.5 --g 0.3 --density 1 \
  --tail-bins 8 --tail-extent 16 \
  --min-paths 40000 --top-ups 0 --paths 4e9 --seed 3000 "${shard_args[@]}" --resume \
  --out "$out" | sed -n 1p
if [ -z "${SHARD:-}" ]; then
  ./target/release/svkernel simulate kernels --from "$out" \
    --min-paths 2000 --top-ups 1 --paths 4e9 --resume --out "$out" | sed -n 1p
fi
