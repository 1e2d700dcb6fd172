#!/bin/bash
# Submit a pipeline manifest as a Slurm job array of N partitions plus the publish job that waits for all of them:
#
#   docs/slurm/submit.sh MANIFEST N [sbatch options for both jobs] [-- sbatch options for the map array only]
#
# Site options (--partition=cpu --time=04:00:00 --account=proj) go before any `--` and reach both jobs, so the
# publish job runs where the map tasks did; options after `--` (e.g. --hold) reach the map array only.
#
# Prints "MAP_JOB_ID PUBLISH_JOB_ID". If any map task fails or is cancelled, the publish job is cancelled
# (--kill-on-invalid-dep=yes), not left pending; run this again to resume: finished partitions are up to date
# and return at once, the failed ones redo only their stale stages. G2R_PIPELINE names the g2r-pipeline binary
# (default: the one on PATH); the jobs run in the current directory.
set -euo pipefail
usage="usage: $0 MANIFEST N [sbatch options for both jobs] [-- sbatch options for the map array only]"
if [ $# -lt 2 ]; then
  echo "$usage" >&2
  exit 2
fi
manifest=$(realpath "$1"); partitions=$2; shift 2
if ! [[ "$partitions" =~ ^[1-9][0-9]*$ ]]; then
  echo "$0: N='$partitions' is not a partition count (1 or more): $usage" >&2
  exit 2
fi
both=(); map_only=()
while [ $# -gt 0 ]; do
  if [ "$1" = "--" ]; then shift; map_only=("$@"); break; fi
  both+=("$1"); shift
done
here=$(dirname "$(realpath "$0")")
export G2R_MANIFEST="$manifest" G2R_PARTITIONS="$partitions"
map=$(sbatch --parsable --export=ALL --array="0-$((partitions - 1))" "${both[@]}" "${map_only[@]}" \
  "$here/map.sbatch")
publish=$(sbatch --parsable --export=ALL --dependency="afterok:${map%%;*}" --kill-on-invalid-dep=yes "${both[@]}" \
  "$here/publish.sbatch")
echo "${map%%;*} ${publish%%;*}"
