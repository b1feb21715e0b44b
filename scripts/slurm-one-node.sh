#!/bin/bash
# A one-node Slurm cluster from Debian's packages (munge, slurmctld, slurmd; no systemd), and the
# campaign example of docs/campaigns.md run on it end to end, as written there:
#
#   1. installs slurm-wlm and munge if missing, builds the workspace, starts munged, slurmctld
#      and slurmd as plain daemons with a slurm.conf of its own (in WORK; /etc/slurm is not
#      touched), all on 127.0.0.1;
#   2. submits the example (the block of docs/campaigns.md with `#SBATCH --job-name=s3res-tmr-cfe`)
#      as an array of N shards, waits, merges the shards, runs the same campaign unsharded, and
#      checks that the merge has the same runs and the same injection schedule, run for run;
#   3. under each ProctrackType of PROCTRACKS: cancels a running shard with scancel (SIGTERM to
#      the job), and kills its s3res-inject with scancel --batch --signal=KILL (SIGKILL to the
#      batch step's process alone, as an out-of-memory kill would), checks that no process of
#      the job is left, that the
#      completed runs are on disk, and that resubmitting the shard (the example has --resume)
#      finishes it; under the first one also lets a shard hit its time limit;
#   4. stops the daemons it started.
#
# Run as root from anywhere in the checkout:   scripts/slurm-one-node.sh
# Environment: PROFILE (release; or debug), N (4 shards), RUNS (12 runs), CANCEL_RUNS (3),
#   PROCTRACKS ("proctrack/pgid proctrack/linuxproc"), BIN (target/PROFILE: where the binaries
#   are taken from), TIMELIMIT_TEST (1; 0 skips it, which takes about two minutes), WORK (a new
#   folder under /tmp), GONE_LIMIT (5: seconds after which a process of a stopped job left is
#   a failure), KEEP=1 leaves the daemons running.
# Exit status 0 if every check passed; the last line says how many passed and failed.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PROFILE=${PROFILE:-release}
N=${N:-4}
RUNS=${RUNS:-12}
CANCEL_RUNS=${CANCEL_RUNS:-3}
PROCTRACKS=${PROCTRACKS:-proctrack/pgid proctrack/linuxproc}
TIMELIMIT_TEST=${TIMELIMIT_TEST:-1}
GONE_LIMIT=${GONE_LIMIT:-5}
STOP_SYSTEM=$REPO/inject/systems/echo-tmr-long.json
WORK=${WORK:-$(mktemp -d /tmp/s3res-slurm.XXXXXX)}
HOST=$(hostname -s)
export SLURM_CONF=$WORK/slurm.conf
case $PROFILE in
    debug) BIN=${BIN:-$REPO/target/debug} ;;
    *) BIN=${BIN:-$REPO/target/$PROFILE} ;;
esac
PASSED=0
FAILED=0
STARTED_MUNGE=

say() { printf '== %s\n' "$*"; }
ok() { printf 'ok: %s\n' "$*"; PASSED=$((PASSED + 1)); }
fail() { printf 'FAIL: %s\n' "$*"; FAILED=$((FAILED + 1)); }
die() { printf 'error: %s\n' "$*" >&2; exit 1; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
lines() { if [ -f "$1" ]; then grep -c . "$1" || true; else echo 0; fi; }

[ "$(id -u)" = 0 ] || die "run as root: it installs packages and starts munged, slurmctld, slurmd"
mkdir -p "$WORK"

# ---- 1. packages, build, daemons ---------------------------------------------------------------

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null \
    || ! command -v jq >/dev/null; then
    say "installing slurm-wlm, munge and jq from Debian's packages"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        slurm-wlm munge jq >/dev/null
fi
say "$(slurmctld -V) on $HOST: $(nproc) cores, work folder $WORK"

say "building the workspace ($PROFILE)"
case $PROFILE in
    debug) (cd "$REPO" && cargo build -q) ;;
    release) (cd "$REPO" && cargo build -q --release) ;;
    *) (cd "$REPO" && cargo build -q --profile "$PROFILE") ;;
esac
[ -x "$BIN/s3res-inject" ] || die "$BIN/s3res-inject was not built"

munge_works() { munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1; }

start_munge() {
    if munge_works; then
        say "munged already runs"
        return
    fi
    if [ ! -s /etc/munge/munge.key ]; then
        mungekey --create --keyfile=/etc/munge/munge.key
        chown munge:munge /etc/munge/munge.key
        chmod 0400 /etc/munge/munge.key
    fi
    install -d -o munge -g munge -m 0755 /run/munge
    install -d -o munge -g munge -m 0700 /var/lib/munge /var/log/munge
    runuser -u munge -- /usr/sbin/munged
    STARTED_MUNGE=$(cat /run/munge/munged.pid 2>/dev/null || true)
    for _ in $(seq 50); do munge_works && break; sleep 0.1; done
    munge_works || die "munged does not answer"
    say "munged started (pid $STARTED_MUNGE)"
}

write_conf() { # $1: ProctrackType
    local mem
    mem=$(($(awk '/^MemTotal/ { print $2 }' /proc/meminfo) / 1024 * 9 / 10))
    mkdir -p "$WORK/state" "$WORK/spool"
    cat >"$SLURM_CONF" <<EOF
ClusterName=s3res-one
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
ProctrackType=$1
TaskPlugin=task/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
ReturnToService=2
KillWait=30
StateSaveLocation=$WORK/state
SlurmdSpoolDir=$WORK/spool
SlurmctldPidFile=$WORK/slurmctld.pid
SlurmdPidFile=$WORK/slurmd.pid
SlurmctldLogFile=$WORK/slurmctld.log
SlurmdLogFile=$WORK/slurmd.log
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=$(nproc) RealMemory=$mem State=UNKNOWN
PartitionName=one Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
}

# Stops the daemon whose pid file is $WORK/$1.pid (one this script started), bounded.
stop_daemon() {
    local pidfile=$WORK/$1.pid pid
    [ -s "$pidfile" ] || return 0
    pid=$(cat "$pidfile")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
    rm -f "$pidfile"
}

stop_slurm() {
    stop_daemon slurmd
    stop_daemon slurmctld
}

start_slurm() { # $1: ProctrackType
    stop_slurm
    write_conf "$1"
    slurmctld -c
    slurmd -c
    for _ in $(seq 300); do
        case $(sinfo -h -n "$HOST" -o %T 2>/dev/null) in idle* | mixed* | allocated*) break ;; esac
        sleep 0.2
    done
    case $(sinfo -h -n "$HOST" -o %T 2>/dev/null) in
        idle*) say "slurmctld and slurmd run, $1: $(sinfo -h -o '%P %D node(s) %c cpus %T')" ;;
        *)
            tail -5 "$WORK/slurmctld.log" "$WORK/slurmd.log" || true
            die "the node did not come up ($(sinfo -h -o %T 2>&1))"
            ;;
    esac
}

cleanup() {
    if [ "${KEEP:-0}" = 1 ]; then
        say "KEEP=1: daemons left running (SLURM_CONF=$SLURM_CONF)"
        return
    fi
    stop_slurm
    if [ -n "$STARTED_MUNGE" ]; then kill "$STARTED_MUNGE" 2>/dev/null || true; fi
}
trap cleanup EXIT

# The live s3res-* processes of array job $1: every process of a job inherits its
# SLURM_ARRAY_JOB_ID, whatever process group or session it is in.
job_procs() {
    local p comm
    for p in /proc/[0-9]*; do
        comm=$(cat "$p/comm" 2>/dev/null) || continue
        case $comm in s3res-*) ;; *) continue ;; esac
        grep -qzx "SLURM_ARRAY_JOB_ID=$1" "$p/environ" 2>/dev/null && echo "${p#/proc/}:$comm"
    done
    return 0
}

# Waits (at most $2 seconds) until job $1 is no longer pending or running.
wait_job() {
    local end=$(($(date +%s) + $2))
    while [ -n "$(squeue -h -j "$1" 2>/dev/null)" ]; do
        [ "$(date +%s)" -lt "$end" ] || { fail "job $1 still in the queue after $2 s"; return 1; }
        sleep 1
    done
}

# The state and exit code of each task of job $1, as slurmctld still remembers it.
job_states() {
    scontrol -o show job "$1" 2>/dev/null | awk '{
        t = s = e = r = ""
        for (i = 1; i <= NF; i++) {
            split($i, kv, "=")
            if (kv[1] == "ArrayTaskId") t = kv[2]
            else if (kv[1] == "JobState") s = kv[2]
            else if (kv[1] == "Reason") r = kv[2]
            else if (kv[1] == "ExitCode") e = kv[2]
        }
        printf "task %s %s (%s) exit %s; ", t, s, r, e
    }' || true
}

# Submits the example from $WORK: $1 out folder, $2 shards N, $3 runs, then sbatch options;
# $SUBMIT_SYSTEM, if set, is the description. Prints the job id.
submit() {
    local out=$1 n=$2 runs=$3 system=${SUBMIT_SYSTEM:-$REPO/inject/systems/echo-tmr.json}
    shift 3
    (cd "$WORK" && S3RES=$REPO BIN=$BIN SYSTEM=$system N=$n RUNS=$runs OUT=$out \
        sbatch --parsable "$@" "$WORK/example.sbatch") | cut -d';' -f1
}

start_munge
FIRST_PT=${PROCTRACKS%% *}
start_slurm "$FIRST_PT"

# ---- 2. the example, sharded, merged, against the unsharded campaign ----------------------------

awk '/^```sh$/ { inb = 1; blk = ""; next }
     inb && /^```$/ { if (blk ~ /#SBATCH --job-name=s3res-tmr-cfe/) { printf "%s", blk; exit } inb = 0; next }
     inb { blk = blk $0 "\n" }' "$REPO/docs/campaigns.md" >"$WORK/example.sbatch"
[ -s "$WORK/example.sbatch" ] || die "no Slurm example (#SBATCH --job-name=s3res-tmr-cfe) in docs/campaigns.md"
say "the example of docs/campaigns.md, as submitted (N=$N RUNS=$RUNS from the environment):"
sed 's/^/    /' "$WORK/example.sbatch"

RES=$WORK/results/tmr-cfe
t0=$(now)
JOB=$(submit "$RES" "$N" "$RUNS" --array=1-"$N")
say "sbatch --array=1-$N: job $JOB"
wait_job "$JOB" $((RUNS * 60 + 120)) || true
say "array done in $(since "$t0") s: $(job_states "$JOB")"
all_shards=1
for k in $(seq "$N"); do
    want=$(( (RUNS - k + N) / N ))
    have=$(lines "$RES/shard-$k/runs.jsonl")
    if [ -f "$RES/shard-$k/summary.json" ] && [ "$have" = "$want" ]; then :; else
        all_shards=0
        fail "shard $k: $have of $want runs, summary.json $([ -f "$RES/shard-$k/summary.json" ] && echo present || echo missing)"
        tail -5 "$WORK"/s3res-tmr-cfe_"${JOB}"_"$k".out 2>/dev/null || true
    fi
done
[ "$all_shards" = 1 ] && ok "all $N shards wrote their $RUNS runs, each task's log in the submission folder ($(ls "$WORK"/s3res-tmr-cfe_"${JOB}"_*.out | wc -l) files)"

"$BIN/s3res-inject" -q merge --out "$RES/all" "$RES"/shard-* >"$WORK/merge.md" 2>"$WORK/merge.err" \
    || fail "merge: $(cat "$WORK/merge.err")"
say "merged table:"
sed 's/^/    /' "$RES/all/table.md"

t0=$(now)
"$BIN/s3res-inject" -q campaign --system "$REPO/inject/systems/echo-tmr.json" --fault cfe --rate 2 \
    --runs "$RUNS" --seed 42 --task-summary task.json --out "$RES/unsharded" \
    >/dev/null 2>"$WORK/unsharded.err" || fail "unsharded campaign: $(tail -3 "$WORK/unsharded.err")"
say "unsharded campaign (same parameters, outside Slurm) in $(since "$t0") s:"
sed 's/^/    /' "$RES/unsharded/table.md"

same() { # $1: what, then two commands' outputs to compare
    if [ "$2" = "$3" ]; then ok "merged == unsharded: $1"; else
        fail "merged != unsharded: $1"
        diff <(echo "$2") <(echo "$3") | head -10
    fi
}
ident() { jq -S 'del(.shard, .machine)' "$1/campaign.json"; }
runs_key() { jq -c '[.run, .run_seed, .planned]' "$1/runs.jsonl"; }
inj_key() { jq -c '[.run, .index, .at_ns, .kind, .component]' "$1/injections.jsonl"; }
sum_key() { jq -c '.[0] | [.runs, .runs_done, .planned, .seed, .config, .fault]' "$1/summary.json"; }
same "the campaign's parameters" "$(ident "$RES/all")" "$(ident "$RES/unsharded")"
same "$(lines "$RES/all/runs.jsonl") runs: run, run seed, planned injections" \
    "$(runs_key "$RES/all")" "$(runs_key "$RES/unsharded")"
same "$(lines "$RES/all/injections.jsonl") injections: run, index, instant, kind, component" \
    "$(inj_key "$RES/all")" "$(inj_key "$RES/unsharded")"
same "summary: runs, runs done, planned, seed, config, fault" \
    "$(sum_key "$RES/all")" "$(sum_key "$RES/unsharded")"

# ---- 3. cancelled and timed-out shards --------------------------------------------------------

# Submits one shard of the echo demo's long system (10 s a run: a run left behind would still
# be running), waits until it has $2 run(s) done and a system running, then does $1 (scancel
# options, or "timelimit": the shard was submitted with --time=1 and is left to it). Checks
# that nothing of the job is left GONE_LIMIT seconds later, that the finished runs are on disk,
# and (unless $3 is "no-resume") that resubmitting the same shard finishes it.
stop_test() {
    local how=$1 after=$2 resume=${3:-resume} label=${1:-scancel} name out job t0 left gone=
    name=$(echo "$PT-$label" | tr -c 'a-zA-Z0-9-\n' '-')
    out=$WORK/results/$name
    local runs=$CANCEL_RUNS opts=(--array=1)
    if [ "$how" = timelimit ]; then
        runs=20
        opts+=(--time=1)
    fi
    job=$(SUBMIT_SYSTEM=$STOP_SYSTEM submit "$out" 1 "$runs" "${opts[@]}")
    local end=$(($(date +%s) + 300))
    while :; do
        [ "$(date +%s)" -lt "$end" ] || { fail "$PT $how: job $job never got going"; scancel "$job"; return; }
        # (No `| grep -q`: with pipefail, job_procs killed by SIGPIPE would make it false.)
        if [ "$(lines "$out/shard-1/runs.jsonl")" -ge "$after" ] \
            && [[ $(job_procs "$job") == *:s3res-voter* ]]; then break; fi
        sleep 0.2
    done
    local before
    before=$(job_procs "$job")
    if [ "$how" = timelimit ]; then
        say "$PT: job $job runs (runs done: $(lines "$out/shard-1/runs.jsonl")); waiting for its 1-minute limit"
        while [[ $(job_procs "$job") == *:s3res-inject* ]] && [ "$(date +%s)" -lt $((end + 300)) ]; do
            sleep 0.1
        done
        t0=$(now)
    else
        t0=$(now)
        scancel $how "$job"
    fi
    local limit_at=$(($(date +%s) + GONE_LIMIT))
    while :; do
        left=$(job_procs "$job")
        if [ -z "$left" ]; then gone=$(since "$t0"); break; fi
        [ "$(date +%s)" -lt "$limit_at" ] || break
        sleep 0.1
    done
    if [ -z "$gone" ]; then
        for _ in $(seq 600); do [ -n "$(job_procs "$job")" ] || break; sleep 0.1; done
        say "    (left over after ${GONE_LIMIT} s: $(echo "$left" | tr '\n' ' '); all gone $(since "$t0") s after)"
    fi
    wait_job "$job" 120 || true
    local done_runs
    done_runs=$(lines "$out/shard-1/runs.jsonl")
    say "$PT, $label: $(echo "$before" | wc -l) s3res processes before: $(echo "$before" | cut -d: -f2 | sort | uniq -c | awk '{ printf "%s %s, ", $1, $2 }')"
    say "    $(job_states "$job")runs on disk: $done_runs; summary.json: $([ -f "$out/shard-1/summary.json" ] && echo written || echo not written)"
    tail -3 "$WORK/s3res-tmr-cfe_${job}_1.out" 2>/dev/null | sed 's/^/    log: /'
    if [ -n "$gone" ]; then
        ok "$PT, $label: nothing of the job left $gone s after $([ "$how" = timelimit ] && echo "s3res-inject ended at the limit" || echo "scancel")"
    else
        fail "$PT, $label: still running ${GONE_LIMIT} s later: $(echo "$left" | tr '\n' ' ')"
    fi
    if [ "$done_runs" -ge "$after" ]; then ok "$PT, $label: the $done_runs finished run(s) are on disk"; else
        fail "$PT, $label: $done_runs run(s) on disk, $after were done before"
    fi
    [ "$resume" = resume ] || return 0
    t0=$(now)
    job=$(SUBMIT_SYSTEM=$STOP_SYSTEM submit "$out" 1 "$runs" --array=1)
    wait_job "$job" $((runs * 60 + 120)) || true
    local final
    final=$(lines "$out/shard-1/runs.jsonl")
    if [ "$final" = "$runs" ] && grep -q "resuming: $done_runs run(s) already done" "$WORK/s3res-tmr-cfe_${job}_1.out" \
        && [ "$(jq -r '.[0].runs_done' "$out/shard-1/summary.json")" = "$runs" ]; then
        ok "$PT, $label: resubmitted, the shard resumed from $done_runs and finished its $runs runs in $(since "$t0") s"
    else
        fail "$PT, $label: resubmitted shard has $final of $runs runs"
        tail -5 "$WORK/s3res-tmr-cfe_${job}_1.out" 2>/dev/null || true
    fi
}

for PT in $PROCTRACKS; do
    [ "$PT" = "$FIRST_PT" ] || start_slurm "$PT"
    stop_test "" 1
    stop_test "--batch --signal=KILL" 1
    if [ "$PT" = "$FIRST_PT" ] && [ "$TIMELIMIT_TEST" = 1 ]; then stop_test timelimit 1 no-resume; fi
done

echo "slurm-one-node: $PASSED passed, $FAILED failed (work folder $WORK)"
[ "$FAILED" = 0 ]
