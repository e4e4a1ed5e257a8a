#!/usr/bin/env bash
# Stop the cluster scripts/slurm/start.sh started: cancel its jobs, stop slurmctld and slurmd,
# then the munged it started (pid files only; nothing is killed by name).
set -uo pipefail

DIR="${MARCH_SLURM_DIR:-/tmp/march-slurm}"
export SLURM_CONF="$DIR/slurm.conf"

say() { echo "[slurm] $*"; }
alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

if [ -f "$SLURM_CONF" ] && alive "$DIR/slurmctld.pid"; then
    scancel --user=root >/dev/null 2>&1 || true
    scontrol shutdown >/dev/null 2>&1 || true
fi
for name in slurmctld slurmd; do
    pidfile="$DIR/$name.pid"
    for _ in $(seq 30); do alive "$pidfile" || break; sleep 0.5; done
    if alive "$pidfile"; then
        kill "$(cat "$pidfile")" 2>/dev/null || true
        sleep 1
        alive "$pidfile" && kill -9 "$(cat "$pidfile")" 2>/dev/null
    fi
    rm -f "$pidfile"
done
# munged only if start.sh started it (a machine's own munged is left running).
if [ -f "$DIR/munged-started" ] && [ -s /run/munge/munged.pid ]; then
    kill "$(cat /run/munge/munged.pid)" 2>/dev/null || true
    rm -f "$DIR/munged-started"
fi
say "stopped (state and logs kept in $DIR)"
