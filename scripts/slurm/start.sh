#!/usr/bin/env bash
# Start a single-node Slurm cluster on this machine (munged + slurmctld + slurmd, as root).
#
#   scripts/slurm/start.sh          # installs slurm-wlm and munge with apt if missing
#   export SLURM_CONF=/tmp/march-slurm/slurm.conf   # what start.sh prints; then sbatch/srun work
#   scripts/slurm/stop.sh
#
# State, logs and the generated slurm.conf live in $MARCH_SLURM_DIR (default /tmp/march-slurm);
# /etc/slurm is left alone, so clients find the cluster through SLURM_CONF. The node gets
# $MARCH_SLURM_CPUS CPUs (default 2, at most nproc) and 90% of the machine's memory.
set -euo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
DIR="${MARCH_SLURM_DIR:-/tmp/march-slurm}"
PARTITION="${MARCH_SLURM_PARTITION:-debug}"
CONF="$DIR/slurm.conf"

say() { echo "[slurm] $*"; }
die() { echo "[slurm] error: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "run as root (slurmctld, slurmd and munged are started here)"

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    say "installing slurm-wlm and munge with apt"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
fi

# munge: one key shared by every daemon and client on the machine.
if [ ! -s /etc/munge/munge.key ]; then
    say "creating /etc/munge/munge.key"
    mungekey --create --force
    chown munge:munge /etc/munge/munge.key
    chmod 600 /etc/munge/munge.key
fi
mkdir -p /run/munge /var/log/munge /var/lib/munge
chown munge:munge /run/munge /var/log/munge /var/lib/munge
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    say "starting munged"
    runuser -u munge -- /usr/sbin/munged
    mkdir -p "$DIR" && touch "$DIR/munged-started"  # stop.sh stops only a munged started here
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
    munge -n | unmunge >/dev/null || die "munged does not answer (see /var/log/munge/munged.log)"
fi

HOST="$(hostname -s)"
NPROC="$(nproc)"
CPUS="${MARCH_SLURM_CPUS:-2}"
[ "$CPUS" -le "$NPROC" ] || CPUS="$NPROC"
MEM_MB="$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)"
mkdir -p "$DIR/state" "$DIR/spool" "$DIR/log"
sed -e "s|@HOST@|$HOST|g" -e "s|@DIR@|$DIR|g" -e "s|@CPUS@|$CPUS|g" -e "s|@MEM_MB@|$MEM_MB|g" \
    -e "s|@PARTITION@|$PARTITION|g" -e "s|@CTLD_PORT@|${MARCH_SLURM_CTLD_PORT:-6817}|g" \
    -e "s|@SLURMD_PORT@|${MARCH_SLURM_SLURMD_PORT:-6818}|g" "$HERE/slurm.conf.in" >"$CONF"
export SLURM_CONF="$CONF"

alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
if alive "$DIR/slurmctld.pid"; then
    say "slurmctld already running (pid $(cat "$DIR/slurmctld.pid"))"
else
    # -c: a clean start (no jobs left over from an earlier cluster in $DIR).
    slurmctld -c -f "$CONF"
fi
if alive "$DIR/slurmd.pid"; then
    say "slurmd already running (pid $(cat "$DIR/slurmd.pid"))"
else
    # MARCH_SLURM_NICE=10: jobs (children of slurmd) run at a lower CPU priority.
    ${MARCH_SLURM_NICE:+nice -n "$MARCH_SLURM_NICE"} slurmd -f "$CONF" -N "$HOST"
fi

# Wait until the node takes jobs.
for _ in $(seq 60); do
    state="$(sinfo -h -n "$HOST" -o %T 2>/dev/null || true)"
    case "$state" in
        idle*|mixed*|allocated*) break ;;
        down*|drain*) scontrol update nodename="$HOST" state=resume >/dev/null 2>&1 || true ;;
    esac
    sleep 1
done
case "$state" in
    idle*|mixed*|allocated*) ;;
    *) die "node $HOST is '$state' (see $DIR/log/slurmctld.log and slurmd.log)" ;;
esac
answer="$(timeout 60 srun -N1 -n1 hostname)" || die "srun hostname failed"
say "cluster up: node $HOST ($CPUS CPUs, ${MEM_MB} MB), partition $PARTITION; srun hostname -> $answer"
say "clients need: export SLURM_CONF=$CONF"
