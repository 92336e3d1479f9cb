#!/usr/bin/env bash
# Regenerates data/profiles/eta1.5_g0.3_pencil/: the default medium (η = 1.5,
# g = 0.3, ρ = 1, half-space), pencil beam, 32 albedos uniform in sqrt(1 − α)
# from 0.01 to 0.999. Path counts give ≤ 0.25 % relative standard error on
# R_d (at least 2e7 paths, for smooth radial bins); seed 1000 + index.
#
#   bash tools/make_profiles.sh            # writes data/profiles/eta1.5_g0.3_pencil/a*.json
#   SOURCE=diffuse bash tools/make_profiles.sh   # diffuse incidence at a point:
#                                          # data/profiles/eta1.5_g0.3_diffuse/a*.json
#   SHARD=k/N bash tools/make_profiles.sh  # one slice of every simulation (merge later)
#   RADIANCE=1 bash tools/make_profiles.sh # also the radiance along the normal (scalar
#                                          # engine, a quarter of the paths: next-event
#                                          # estimation is the quieter estimator):
#                                          # data/profiles/eta1.5_g0.3_pencil_radiance/a*.json
#
# Takes about 45 s on 2 cores (lanes engine; 1.42e9 paths, 9.8e9 scattering events).
set -euo pipefail
cd "$(dirname "$0")/.."
source=${SOURCE:-pencil}
radiance=${RADIANCE:-}
suffix=${radiance:+_radiance}
out=${OUT:-data/profiles/eta1.5_g0.3_$source$suffix}
mkdir -p "$out"
cargo build --release --quiet
shard_args=()
[ -n "${SHARD:-}" ] && shard_args=(--shard "$SHARD")
radiance_args=()
[ -n "$radiance" ] && radiance_args=(--radiance)
run() {  # albedo paths seed
  local f="$out/a$1.json" paths=$2
  [ -n "${SHARD:-}" ] && f="$out/a$1.shard${SHARD/\//of}.json"
  [ -n "$radiance" ] && paths=$(awk -v p="$2" 'BEGIN { printf "%.4g", p / 4 }')
  ./target/release/svkernel simulate profile --albedo "$1" --eta 1.5 --g 0.3 \
    --source "$source" --paths "$paths" --seed "$3" "${radiance_args[@]}" "${shard_args[@]}" \
    --resume --out "$f" | sed -n 1p
}
run 0.010000 696e6 1000
run 0.070875 88e6 1001
run 0.129819 45e6 1002
run 0.186831 29e6 1003
run 0.241912 21e6 1004
run 0.295062 20e6 1005
run 0.346280 20e6 1006
run 0.395566 20e6 1007
run 0.442921 20e6 1008
run 0.488345 20e6 1009
run 0.531837 20e6 1010
run 0.573397 20e6 1011
run 0.613026 20e6 1012
run 0.650724 20e6 1013
run 0.686490 20e6 1014
run 0.720325 20e6 1015
run 0.752228 20e6 1016
run 0.782200 20e6 1017
run 0.810240 20e6 1018
run 0.836349 20e6 1019
run 0.860526 20e6 1020
run 0.882772 20e6 1021
run 0.903087 20e6 1022
run 0.921469 20e6 1023
run 0.937921 20e6 1024
run 0.952441 20e6 1025
run 0.965029 20e6 1026
run 0.975686 20e6 1027
run 0.984412 20e6 1028
run 0.991206 20e6 1029
run 0.996069 20e6 1030
run 0.999000 20e6 1031
