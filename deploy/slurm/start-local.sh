#!/usr/bin/env bash
# A single-node SLURM cluster (slurmctld + slurmd, munge) on this machine, for tests, CI and trying
# `maxfs --cluster slurm` without a real cluster. Idempotent: starts only what is not running.
#
#   sudo deploy/slurm/start-local.sh            # prints SLURM_CONF=...; export it to use sbatch & co
#   sudo deploy/slurm/start-local.sh --stop
#
# Needs Debian's `slurm-wlm` and `munge` (apt-get install -y slurm-wlm munge) and root: SlurmUser=root,
# ProctrackType=proctrack/linuxproc and TaskPlugin=task/none need no cgroups, so it starts in containers.
# Files (configuration, state, logs, the job completion log) live in MAXFS_SLURM_DIR
# (default /var/tmp/maxfs-slurm); /etc/slurm is never touched, so a real cluster's setup is safe.
set -euo pipefail
DIR=${MAXFS_SLURM_DIR:-/var/tmp/maxfs-slurm}
CONF=$DIR/slurm.conf
export SLURM_CONF=$CONF

die() { echo "start-local.sh: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "run as root (the single-node setup uses SlurmUser=root)"
for b in munged munge unmunge slurmctld slurmd scontrol sinfo; do
  command -v "$b" >/dev/null || die "$b is missing: apt-get install -y slurm-wlm munge"
done

if [ "${1:-}" = "--stop" ]; then
  for pid in "$DIR/slurmd.pid" "$DIR/slurmctld.pid"; do
    [ -f "$pid" ] && kill "$(cat "$pid")" 2>/dev/null || true
  done
  exit 0
fi

# munge: one key, the daemon as the munge user
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
  if [ ! -s /etc/munge/munge.key ]; then
    install -d -o munge -g munge -m 0700 /etc/munge
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
    chown munge:munge /etc/munge/munge.key && chmod 0400 /etc/munge/munge.key
  fi
  install -d -o munge -g munge -m 0755 /run/munge
  install -d -o munge -g munge -m 0700 /var/log/munge /var/lib/munge
  runuser -u munge -- munged
  for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.1; done
  munge -n | unmunge >/dev/null || die "munged did not start (see /var/log/munge/munged.log)"
fi

node=$(hostname -s)
# a daemon runs when its pid file names a live process (scontrol ping would wait a minute for a dead one)
running() {
  local pid
  pid=$(cat "$DIR/$1.pid" 2>/dev/null) && [ -n "$pid" ] && [ -r "/proc/$pid/stat" ] &&
    ! awk '{exit $3 != "Z"}' "/proc/$pid/stat"
}
node_up() { sinfo -h -n "$node" -o %T 2>/dev/null | grep -qE '^(idle|mixed|allocated|completing)'; }
if running slurmctld && running slurmd && node_up; then
  echo "SLURM_CONF=$CONF"
  exit 0
fi

mkdir -p "$DIR/state" "$DIR/spool"
if [ ! -f "$CONF" ]; then
  hw=$(slurmd -C | head -1 | sed 's/^NodeName=[^ ]* //')
  cat >"$CONF" <<CONF
# written by deploy/slurm/start-local.sh: one node, no cgroups, no database
ClusterName=maxfs
SlurmctldHost=$node(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
# job completion accounting without slurmdbd: one line per finished job
JobCompType=jobcomp/filetxt
JobCompLoc=$DIR/jobcomp.log
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
ReturnToService=2
KillWait=5
MinJobAge=300
SlurmdTimeout=60
NodeName=$node NodeAddr=127.0.0.1 $hw State=UNKNOWN
PartitionName=maxfs Nodes=$node Default=YES MaxTime=INFINITE State=UP
CONF
fi

running slurmctld || slurmctld -f "$CONF"
running slurmd || slurmd -f "$CONF"
for _ in $(seq 150); do
  node_up && break
  sinfo -h -n "$node" -o %T 2>/dev/null | grep -qE '^(down|drain)' && scontrol update nodename="$node" state=resume 2>/dev/null || true
  sleep 0.2
done
node_up || die "the node $node did not come up: $(sinfo -h -n "$node" -o '%T %E' 2>&1); see $DIR/slurmctld.log and $DIR/slurmd.log"
echo "SLURM_CONF=$CONF"
