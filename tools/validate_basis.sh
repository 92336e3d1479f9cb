#!/usr/bin/env bash
# Fresh, independent simulations at albedos that are NOT in the training grid
# (midpoints in sqrt(1 − α) of tools/make_profiles.sh's grid, α ≥ 0.2, plus
# 0.9995 beyond the last training albedo), then the accuracy of the shipped
# basis model against them (the accuracy aims: R_d within 0.5 %, radial L2
# over r ∈ [0.01, 20] MFP ≤ 2 % of R_d; Christensen–Burley in the same table).
#
#   bash tools/validate_basis.sh     # writes out/validate_basis/{a*.json,check.json}
#
# Seeds 2000 + index: independent of the training seeds (1000 + index).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-out/validate_basis}
mkdir -p "$out"
cargo build --release --quiet
i=0
for a in 0.214613 0.320912 0.419485 0.510332 0.593453 0.668848 0.736518 0.796461 \
         0.848679 0.893171 0.929937 0.958977 0.980291 0.993879 0.997776 0.999500; do
  paths=2e7
  if awk "BEGIN{exit !($a < 0.5)}"; then paths=6e7; fi
  ./target/release/svkernel simulate profile --albedo "$a" --eta 1.5 --g 0.3 --source pencil \
    --paths "$paths" --seed $((2000 + i)) --out "$out/a$a.json" | sed -n 1p
  i=$((i + 1))
done
./target/release/svkernel fit check --model "${MODEL:-data/profiles/basis.json}" --in "$out" --out "$out/check.json"
