#!/usr/bin/env bash
# make test-slurm: a real single-node Slurm cluster end to end (slow, needs root; not in CI).
#   start the cluster (apt-installs slurm-wlm + munge if missing) -> test_slurm.py -> stop it
# A cluster that was already up (scripts/slurm/start.sh) is left running.
set -uo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$HERE/../.." && pwd)"
PY="${PY:-$ROOT/.venv/bin/python}"
DIR="${MARCH_SLURM_DIR:-/tmp/march-slurm}"
export SLURM_CONF="$DIR/slurm.conf"
export WARP_CACHE_PATH="${WARP_CACHE_PATH:-$ROOT/.warp_cache}" WANDB_MODE="${WANDB_MODE:-offline}"

started=0
if ! { [ -s "$DIR/slurmctld.pid" ] && kill -0 "$(cat "$DIR/slurmctld.pid")" 2>/dev/null; }; then
    started=1
fi
"$HERE/start.sh" || { echo "[test-slurm] FAILED: the cluster did not start"; exit 1; }
cd "$ROOT" && "$PY" "$HERE/test_slurm.py" "$@"
rc=$?
if [ "$started" = 1 ] && [ "${MARCH_SLURM_KEEP:-0}" != 1 ]; then
    "$HERE/stop.sh"
fi
exit $rc
