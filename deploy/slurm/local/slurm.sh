#!/usr/bin/env bash
# A real single-node SLURM on this machine, from Debian's packages, for the system tests
# (tests/e2e/test_slurm.py), CI (.ci/run) and trying `schlieren submit` (deploy/GUIDE.md
# section 3): no systemd, no site configuration touched.
#
#   deploy/slurm/local/slurm.sh start    # install if missing (root + apt-get), start, wait until the node is idle
#   deploy/slurm/local/slurm.sh env      # print the `export SLURM_CONF=...` line for clients
#   deploy/slurm/local/slurm.sh status   # exit 0 if the controller answers and the node is up
#   deploy/slurm/local/slurm.sh stop     # stop slurmd, slurmctld (munged is left running)
#
# Everything lives in $SCHLIEREN_SLURM_DIR (default /tmp/schlieren-slurm): slurm.conf,
# state, spool, logs and pid files; the slurm user must be able to reach and write it (not
# under a private folder such as pytest's 0700 tmp folders: start refuses such a folder).
# Clients find it through SLURM_CONF, so an existing /etc/slurm is never read or written.
# Every wait is bounded: a daemon that dies is reported at once with the last line of its
# log, one that does not answer within SCHLIEREN_SLURM_WAIT seconds ends the start.
# Exit codes: 0 ok, 3 SLURM cannot be installed or started here (one line on stderr says
# why: the tests skip or fail with it).
set -euo pipefail
umask 022

DIR=${SCHLIEREN_SLURM_DIR:-/tmp/schlieren-slurm}
CONF=$DIR/slurm.conf
PACKAGES="slurmctld slurmd slurm-client munge"
# seconds to wait for the node to come up after the daemons start
WAIT=${SCHLIEREN_SLURM_WAIT:-30}
# seconds one client call (sinfo, munge) may take: a controller that does not answer
# makes sinfo block for its MessageTimeout and retries
CALL=${SCHLIEREN_SLURM_CALL_TIMEOUT:-5}
# seconds apt-get may take to install the packages
INSTALL_WAIT=${SCHLIEREN_SLURM_INSTALL_WAIT:-240}
CTLD_PORT=${SCHLIEREN_SLURMCTLD_PORT:-6817}
D_PORT=${SCHLIEREN_SLURMD_PORT:-6818}

die() { echo "slurm.sh: $*" >&2; exit 3; }

install_packages() {
    command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null \
        && command -v sbatch >/dev/null && return 0
    command -v apt-get >/dev/null || die "SLURM is not installed and this machine has no apt-get"
    echo "slurm.sh: installing $PACKAGES (Debian packages)" >&2
    local log=${TMPDIR:-/tmp}/schlieren-slurm-apt.log
    timeout "$INSTALL_WAIT" bash -c "apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq --no-install-recommends $PACKAGES" >"$log" 2>&1 \
        || die "apt-get install $PACKAGES failed or took over $INSTALL_WAIT s (log: $log): $(tail -n 1 "$log")"
}

munge_answers() { timeout "$CALL" bash -c 'munge -n 2>/dev/null | unmunge >/dev/null 2>&1'; }

start_munge() {
    if munge_answers; then return 0; fi
    [[ -r /etc/munge/munge.key ]] || die "/etc/munge/munge.key is missing (the munge package creates it)"
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    chmod 0755 /run/munge
    setsid runuser -u munge -- /usr/sbin/munged </dev/null >/dev/null 2>&1 || die "munged did not start"
    local deadline=$((SECONDS + 10))
    while ((SECONDS < deadline)); do
        munge_answers && return 0
        sleep 0.2
    done
    die "munged started but does not answer within 10 s (log: /var/log/munge/munged.log)"
}

write_conf() {
    local host cpus mem
    host=$(hostname -s)
    cpus=$(nproc)
    # the node's memory in MB, less 1 GB for the system (slurmd refuses a node that claims more than it has)
    mem=$(( $(awk '/^MemTotal:/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
    mkdir -p "$DIR"/{state,spool,log,run}
    chmod 0755 "$DIR"
    chown -R slurm:slurm "$DIR"/state "$DIR"/log "$DIR"/run
    reachable_by_slurm
    cat >"$CONF" <<CONF
# written by deploy/slurm/local/slurm.sh: one node, for tests
ClusterName=schlieren-local
SlurmctldHost=$host
AuthType=auth/munge
SlurmUser=slurm
SlurmdUser=root
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
SlurmctldPidFile=$DIR/run/slurmctld.pid
SlurmdPidFile=$DIR/run/slurmd.pid
SlurmctldPort=$CTLD_PORT
SlurmdPort=$D_PORT
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
KillWait=5
MinJobAge=30
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
}

# slurmctld runs as the slurm user: it dies at once ("Unable to stat state save loc:
# Permission denied") when a parent of $DIR is private to root, e.g. /tmp/pytest-of-root
reachable_by_slurm() {
    command -v runuser >/dev/null || return 0
    runuser -u slurm -- test -w "$DIR/state" -a -x "$DIR/state" -a -w "$DIR/log" -a -w "$DIR/run" 2>/dev/null \
        || die "the slurm user cannot write $DIR/state (is a parent folder private, mode 0700?); set SCHLIEREN_SLURM_DIR to a folder others can traverse, e.g. under /tmp"
}

node_state() { SLURM_CONF=$CONF timeout "$CALL" sinfo -h -N -o '%t' 2>/dev/null | head -1 || true; }

# the last line a daemon logged (its log file, else what it printed before logging began)
last_log_line() {
    local f
    for f in "$DIR/log/$1.log" "$DIR/log/$1.out"; do
        [[ -s $f ]] && { tail -n 1 "$f"; return; }
    done
    echo "(no log)"
}

# our controller runs (its pid file names a live process): another SLURM on the same port
# must not pass for ours
own_controller() { [[ -f $DIR/run/slurmctld.pid ]] && kill -0 "$(cat "$DIR/run/slurmctld.pid")" 2>/dev/null; }

port_taken() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }

status() {
    [[ -f $CONF ]] && own_controller || return 1
    local s
    s=$(node_state)
    [[ -n $s && $s != down* && $s != drain* && $s != unk* ]]
}

start() {
    if command -v sinfo >/dev/null && status; then echo "slurm.sh: already running ($CONF)" >&2; return 0; fi
    [[ $(id -u) == 0 ]] || die "starting SLURM needs root (its node daemon runs as root; run: sudo $0 start)"
    install_packages
    start_munge
    stop_daemons
    for port in "$CTLD_PORT" "$D_PORT"; do
        ! port_taken "$port" || die "port $port is taken (another SLURM?); choose free ports with SCHLIEREN_SLURMCTLD_PORT and SCHLIEREN_SLURMD_PORT"
    done
    write_conf
    local t0=$SECONDS deadline=$((SECONDS + WAIT)) ctld d
    SLURM_CONF=$CONF setsid slurmctld -D -i -f "$CONF" </dev/null >>"$DIR/log/slurmctld.out" 2>&1 &
    ctld=$!
    disown "$ctld"
    SLURM_CONF=$CONF setsid slurmd -D -f "$CONF" </dev/null >>"$DIR/log/slurmd.out" 2>&1 &
    d=$!
    disown "$d"
    while ((SECONDS < deadline)); do
        kill -0 "$ctld" 2>/dev/null || failed "slurmctld exited after $((SECONDS - t0)) s: $(last_log_line slurmctld)"
        kill -0 "$d" 2>/dev/null || failed "slurmd exited after $((SECONDS - t0)) s: $(last_log_line slurmd)"
        if status; then
            echo "slurm.sh: node $(hostname -s) is $(node_state) after $((SECONDS - t0)) s; export SLURM_CONF=$CONF" >&2
            return 0
        fi
        sleep 0.2
    done
    local state
    state=$(node_state)
    failed "the node did not come up within $WAIT s (node state: ${state:-no answer from the controller}; slurmctld: $(last_log_line slurmctld); logs: $DIR/log)"
}

# a start that failed leaves no daemon behind
failed() { stop_daemons; die "$@"; }

# our cluster's jobs, cancelled and gone (at most 10 s): a slurmd stopped under a running
# job leaves its slurmstepd behind
cancel_jobs() {
    [[ -f $CONF ]] && own_controller || return 0
    local jobs deadline=$((SECONDS + 10))
    jobs=$(SLURM_CONF=$CONF timeout "$CALL" squeue -h -o %i 2>/dev/null || true)
    [[ -n $jobs ]] || return 0
    SLURM_CONF=$CONF timeout "$CALL" scancel $jobs 2>/dev/null || true
    while ((SECONDS < deadline)); do
        [[ -z $(SLURM_CONF=$CONF timeout "$CALL" squeue -h -o %i 2>/dev/null || echo timeout) ]] && return 0
        sleep 0.5
    done
}

stop_daemons() {
    cancel_jobs
    for d in slurmd slurmctld; do
        # a stale pid file may name another process by now: only one started with our config
        local pid
        pid=$(cat "$DIR/run/$d.pid" 2>/dev/null || true)
        if [[ -n $pid ]] && { tr '\0' ' ' <"/proc/$pid/cmdline"; } 2>/dev/null | grep -qF -- "$CONF"; then
            kill "$pid" 2>/dev/null || true
        fi
        pkill -f "^$d -D .*-f $CONF" 2>/dev/null || true
    done
    for _ in $(seq 50); do
        pgrep -f "^slurm(ctld|d) -D .*-f $CONF" >/dev/null || return 0
        sleep 0.1
    done
    pkill -9 -f "^slurm(ctld|d) -D .*-f $CONF" 2>/dev/null || true
}

case ${1:-} in
    start) start ;;
    stop) stop_daemons ;;
    status) status ;;
    env) echo "export SLURM_CONF=$CONF" ;;
    *) echo "usage: $0 start|stop|status|env" >&2; exit 2 ;;
esac
