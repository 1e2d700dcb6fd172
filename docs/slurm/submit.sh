#!/bin/bash
# Submit a pipeline manifest as a Slurm job array of N partitions plus the publish job that waits for all of them:
#
#   docs/slurm/submit.sh MANIFEST N [extra sbatch options for the map array, e.g. --partition=cpu --hold]
#
# Prints "MAP_JOB_ID PUBLISH_JOB_ID". If any map task fails or is cancelled, the publish job is cancelled
# (--kill-on-invalid-dep=yes), not left pending; run this again to resume: finished partitions are up to date
# and return at once, the failed ones redo only their stale stages. G2R_PIPELINE names the g2r-pipeline binary
# (default: the one on PATH); the jobs run in the current directory.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: $0 MANIFEST N [sbatch options for the map array]" >&2
  exit 2
fi
manifest=$(realpath "$1"); partitions=$2; shift 2
here=$(dirname "$(realpath "$0")")
export G2R_MANIFEST="$manifest" G2R_PARTITIONS="$partitions"
map=$(sbatch --parsable --export=ALL --array="0-$((partitions - 1))" "$@" "$here/map.sbatch")
publish=$(sbatch --parsable --export=ALL --dependency="afterok:${map%%;*}" --kill-on-invalid-dep=yes \
  "$here/publish.sbatch")
echo "${map%%;*} ${publish%%;*}"
