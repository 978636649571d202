#!/usr/bin/env bash
# A single-node Slurm cluster on this machine, to run `nostra sweep launcher=slurm ...` for real:
# this host is the controller and the only compute node (its real CPUs and memory), partition `cpu`.
#
#   scripts/slurm_local.sh start    # install slurm-wlm + munge (Debian, root) if missing, start munged, slurmctld, slurmd
#   eval "$(scripts/slurm_local.sh env)"   # SLURM_CONF for sbatch/srun/squeue/sinfo/scontrol, and PATH
#                                          # with its sacct stand-in (see write_sacct), in this shell
#   scripts/slurm_local.sh status   # daemons, sinfo, squeue
#   scripts/slurm_local.sh stop     # cancel its jobs, stop the daemons, remove the state directory
#
# Everything (munge key and socket, slurm.conf, pid files, logs, spool, job completion log) lives in
# $NOSTRA_SLURM_DIR (default /tmp/nostra-slurm); nothing under /etc is written and no system service is
# used. Ports: $NOSTRA_SLURM_PORT (slurmctld, default 6817) and the next one (slurmd).
# start and stop are idempotent. Daemons inherit the caller's niceness (and so do the jobs):
# `nice -n 19 scripts/slurm_local.sh start` keeps its jobs out of the way of other work.
# No accounting daemon (slurmdbd): the real `sacct` does not work; finished jobs stay visible to
# `scontrol show job <id>` for 30 minutes and are recorded in $NOSTRA_SLURM_DIR/log/jobcomp.log.
set -euo pipefail

DIR=${NOSTRA_SLURM_DIR:-/tmp/nostra-slurm}
PORT=${NOSTRA_SLURM_PORT:-6817}
CONF=$DIR/slurm.conf
SOCKET=$DIR/munge/munge.socket.2
export SLURM_CONF=$CONF

say() { echo "slurm_local: $*"; }
die() { echo "slurm_local: ERROR: $*" >&2; exit 1; }

alive() { # alive <pidfile>: the pid in it is running and is that daemon (not a recycled pid)
  local pid name
  [ -s "$1" ] || return 1
  pid=$(cat "$1")
  name=$(basename "$1" .pid)
  kill -0 "$pid" 2>/dev/null && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$name" ]
}

stop_pid() { # stop_pid <name> <pidfile>
  local name=$1 file=$2 pid
  if ! alive "$file"; then
    rm -f "$file"
    return 0
  fi
  pid=$(cat "$file")
  kill "$pid" 2>/dev/null || true
  for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
  if kill -0 "$pid" 2>/dev/null; then
    kill -9 "$pid" 2>/dev/null || true
    say "killed $name (pid $pid)"
  else
    say "stopped $name (pid $pid)"
  fi
  rm -f "$file"
}

install() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sbatch >/dev/null \
      && command -v munged >/dev/null; then
    return 0
  fi
  [ "$(id -u)" = 0 ] || die "slurm-wlm and munge are not installed and this is not root: apt-get install slurm-wlm munge"
  command -v apt-get >/dev/null || die "slurm-wlm and munge are not installed and there is no apt-get"
  say "installing slurm-wlm and munge (apt-get)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >/dev/null || die "apt-get update failed"
  apt-get install -y -q --no-install-recommends slurm-wlm munge >/dev/null || die "apt-get install slurm-wlm munge failed"
}

write_conf() {
  local node host mem
  host=$(hostname -s)
  # the node's real CPUs, sockets, cores, threads and memory, as slurmd sees them
  node=$(slurmd -C | head -1)
  [[ $node == NodeName=* ]] || die "slurmd -C did not describe this node: $node"
  mem=$(sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' <<<"$node")
  cat >"$CONF" <<EOF
# written by scripts/slurm_local.sh: single-node cluster, $host is controller and compute node
ClusterName=nostra
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$SOCKET
StateSaveLocation=$DIR/spool/ctld
SlurmdSpoolDir=$DIR/spool/d
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
SlurmdTimeout=60
KillWait=5
MinJobAge=1800
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/filetxt
JobCompLoc=$DIR/log/jobcomp.log
DefMemPerCPU=$((mem / 4 > 1024 ? 1024 : mem / 4))
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=cpu Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
}

write_sacct() {
  # No slurmdbd here, so the real sacct answers "accounting storage is disabled". submitit polls
  # `sacct -o JobID,State,NodeList --parsable2 -j <id>...` to notice jobs that ended without a result
  # (cancelled, killed, failed to start); this stand-in answers that one query from the controller's
  # `scontrol show job` (jobs stay there MinJobAge seconds) and hands any other call to the real sacct.
  mkdir -p "$DIR/bin"
  cat >"$DIR/bin/sacct" <<'EOF'
#!/usr/bin/env bash
# written by scripts/slurm_local.sh: submitit's job-state query answered by scontrol (no slurmdbd)
export SLURM_CONF=${SLURM_CONF:-$(dirname "$0")/../slurm.conf}
args=("$@"); ids=(); fmt=""; parsable=0
while [ $# -gt 0 ]; do
  case $1 in
    -o|--format) fmt=$2; shift 2 ;;
    --parsable2) parsable=1; shift ;;
    -j|--jobs) ids+=(${2//,/ }); shift 2 ;;
    *) exec /usr/bin/sacct "${args[@]}" ;;
  esac
done
if [ "$fmt" != JobID,State,NodeList ] || [ $parsable != 1 ] || [ ${#ids[@]} = 0 ]; then
  exec /usr/bin/sacct "${args[@]}"
fi
echo "JobID|State|NodeList"
for id in "${ids[@]}"; do
  scontrol -o show job "$id" 2>/dev/null | awk '{
    delete f
    for (i = 1; i <= NF; i++) { k = index($i, "="); if (k) f[substr($i, 1, k - 1)] = substr($i, k + 1) }
    id = f["JobId"]
    if (f["ArrayTaskId"] != "")
      id = f["ArrayJobId"] "_" (f["ArrayTaskId"] ~ /^[0-9]+$/ ? f["ArrayTaskId"] : "[" f["ArrayTaskId"] "]")
    print id "|" f["JobState"] "|" f["NodeList"] }'
done
EOF
  chmod +x "$DIR/bin/sacct"
}

node_state() { sinfo -h -N -o %t 2>/dev/null | head -1; }

start() {
  install
  mkdir -p "$DIR"/munge "$DIR"/spool/ctld "$DIR"/spool/d "$DIR"/log
  chmod 700 "$DIR"/munge
  if alive "$DIR/slurmctld.pid" && alive "$DIR/slurmd.pid" && alive "$DIR/munge/munged.pid"; then
    say "already running in $DIR (slurmctld $(cat "$DIR/slurmctld.pid"), slurmd $(cat "$DIR/slurmd.pid"))"
    return 0
  fi
  # munge: a key of our own, its own socket (slurm.conf AuthInfo points there)
  if [ ! -s "$DIR/munge/munge.key" ]; then
    dd if=/dev/urandom of="$DIR/munge/munge.key" bs=1024 count=1 status=none
    chmod 400 "$DIR/munge/munge.key"
    say "wrote munge key $DIR/munge/munge.key"
  fi
  if ! alive "$DIR/munge/munged.pid"; then
    munged --force --socket="$SOCKET" --key-file="$DIR/munge/munge.key" --pid-file="$DIR/munge/munged.pid" \
      --log-file="$DIR/log/munged.log" --seed-file="$DIR/munge/munged.seed" \
      || die "munged did not start (see $DIR/log/munged.log)"
    for _ in $(seq 50); do [ -S "$SOCKET" ] && break; sleep 0.1; done
    [ -S "$SOCKET" ] || die "munged did not create $SOCKET (see $DIR/log/munged.log)"
    say "started munged (pid $(cat "$DIR/munge/munged.pid"))"
  fi
  munge -n -S "$SOCKET" | unmunge -S "$SOCKET" >/dev/null || die "munge credential round trip failed"

  if ! alive "$DIR/slurmctld.pid"; then
    write_conf
    write_sacct
    say "wrote $CONF ($(grep '^NodeName' "$CONF"))"
  fi
  if ! alive "$DIR/slurmctld.pid"; then
    slurmctld -f "$CONF" || die "slurmctld did not start (see $DIR/log/slurmctld.log)"
    for _ in $(seq 100); do alive "$DIR/slurmctld.pid" && scontrol ping >/dev/null 2>&1 && break; sleep 0.1; done
    scontrol ping >/dev/null 2>&1 || die "slurmctld does not answer (see $DIR/log/slurmctld.log)"
    say "started slurmctld (pid $(cat "$DIR/slurmctld.pid"))"
  fi
  if ! alive "$DIR/slurmd.pid"; then
    slurmd -f "$CONF" || die "slurmd did not start (see $DIR/log/slurmd.log)"
    for _ in $(seq 100); do alive "$DIR/slurmd.pid" && break; sleep 0.1; done
    alive "$DIR/slurmd.pid" || die "slurmd exited (see $DIR/log/slurmd.log)"
    say "started slurmd (pid $(cat "$DIR/slurmd.pid"))"
  fi
  local state=""
  for _ in $(seq 300); do
    state=$(node_state)
    [[ $state == idle* || $state == mix* || $state == alloc* ]] && break
    sleep 0.1
  done
  [[ $state == idle* || $state == mix* || $state == alloc* ]] \
    || die "node $(hostname -s) is '$state', not idle (see $DIR/log/slurmd.log and slurmctld.log)"
  say "cluster up: partition cpu, node $(hostname -s) $state"
  say "in your shell: eval \"\$($0 env)\"   (SLURM_CONF=$CONF, PATH with $DIR/bin/sacct)"
}

stop() {
  if [ ! -d "$DIR" ]; then
    say "not running (no $DIR)"
    return 0
  fi
  if alive "$DIR/slurmctld.pid"; then
    local jobs
    jobs=$(squeue -h -o %A 2>/dev/null | sort -u | tr '\n' ' ' || true)
    if [ -n "${jobs// }" ]; then
      scancel $jobs 2>/dev/null || true
      say "cancelled jobs $jobs"
      for _ in $(seq 100); do [ -z "$(squeue -h -o %A 2>/dev/null)" ] && break; sleep 0.1; done
    fi
  fi
  stop_pid slurmd "$DIR/slurmd.pid"
  stop_pid slurmctld "$DIR/slurmctld.pid"
  stop_pid munged "$DIR/munge/munged.pid"
  rm -rf "$DIR"
  say "removed $DIR"
}

status() {
  local name file
  for name in munged slurmctld slurmd; do
    file=$DIR/$name.pid
    [ $name = munged ] && file=$DIR/munge/munged.pid
    if alive "$file"; then say "$name running (pid $(cat "$file"))"; else say "$name not running"; fi
  done
  if alive "$DIR/slurmctld.pid"; then
    echo "SLURM_CONF=$CONF"
    sinfo
    squeue
  fi
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) status ;;
  env) echo "export SLURM_CONF=$CONF PATH=$DIR/bin:\$PATH" ;;
  *) echo "usage: $0 start|stop|status|env" >&2; exit 2 ;;
esac
