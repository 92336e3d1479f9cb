#!/usr/bin/env bash
# One shard of a sharded simulation: the body of every cluster job (Slurm
# array task, Kubernetes indexed-Job pod) and of the local test.
#
#   shard.sh K N KIND ARGS...     KIND = profile | kernels | reference
#
# writes $OUT/part$K.json (profile, kernels) or $OUT/part$K/ (reference),
# resuming from its own checkpoint if the task was preempted. Every path has
# its own random stream keyed by (seed, path index), so merging the N parts
# with merge.sh gives bitwise the unsharded result.
#
# Environment: SVKERNEL (the binary; default: svkernel on PATH), OUT
# (a directory every task can write; default out/cluster).
set -euo pipefail
k=$1 n=$2 kind=$3
shift 3
bin=${SVKERNEL:-svkernel}
out=${OUT:-out/cluster}
mkdir -p "$out"
case "$kind" in
  profile) "$bin" simulate profile "$@" --shard "$k/$n" --resume --out "$out/part$k.json" ;;
  kernels) "$bin" simulate kernels "$@" --shard "$k/$n" --resume --out "$out/part$k.json" ;;
  reference) "$bin" render "$@" --method reference --shard "$k/$n" --resume --out "$out/part$k" ;;
  *) echo "shard.sh: unknown kind '$kind' (profile | kernels | reference)" >&2; exit 2 ;;
esac
