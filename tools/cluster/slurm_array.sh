#!/usr/bin/env bash
# Slurm array job: one shard per array task, then a dependent merge job.
#
#   jid=$(sbatch --parsable --array=0-15 tools/cluster/slurm_array.sh \
#           profile --albedo 0.99 --paths 1e10 --seed 7)
#   sbatch --dependency=afterok:$jid --wrap "bash tools/cluster/merge.sh profile"
#
# The array size is the shard count N (SLURM_ARRAY_TASK_COUNT); OUT must be
# on a shared filesystem. Preempted tasks resume from their checkpoints
# (--requeue).
#SBATCH --job-name=svkernel-shard
#SBATCH --cpus-per-task=8
#SBATCH --time=04:00:00
#SBATCH --requeue
#SBATCH --output=out/cluster/slurm-%A_%a.log
set -euo pipefail
export RAYON_NUM_THREADS=${SLURM_CPUS_PER_TASK:-8}
exec bash "$(dirname "$0")/shard.sh" "$SLURM_ARRAY_TASK_ID" "$SLURM_ARRAY_TASK_COUNT" "$@"
