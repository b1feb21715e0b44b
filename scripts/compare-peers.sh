#!/bin/bash
# compare-peers.sh — s3res side by side with the original S³RES and the C floor, in one table.
# See docs/benchmarks.md, "Side by side with S³RES and the C floor".
set -uo pipefail

usage() {
  cat <<'EOF'
usage: scripts/compare-peers.sh [-h|--help]

Runs the peer comparison (PEERS/s3res/compare.sh: the C floor, the original S³RES and
target/release/s3res-bench, interleaved repetition by repetition), then the replicas'
resident sizes, and prints one markdown table: C floor, S³RES, s3res, s3res / S³RES and
s3res / C floor, median with p99 where there is one.

Environment:
  PEERS=DIR   the peer tooling (default: ../shared/peers next to the repository)
  REPS=N      repetitions (default 3; one took under 4 minutes on a 2-core VM, plus
              S³RES's build on first use)
  RES=DIR     raw results (default target/s3res-peer/results/<UTC time>)
  COUNT=N     round trips per configuration (default 20000, compare.sh's)
  CPU_IDLE=M  what idle CPUs do (docs/benchmarks.md, "Idle CPUs"):
              halt  the machine as it is: idle CPUs sleep as the kernel decides (default)
              s3res s3res's voters keep idle CPUs polling while each of them runs (a
                    component's `cpu_idle: poll`); the C floor and S³RES run as before
              all   this script keeps idle CPUs polling for the whole comparison (a PM QoS
                    request on /dev/cpu_dma_latency): every implementation alike
  COMPONENTS=L  how s3res's measured components (s3res-echo, s3res-ballast) are linked:
              dynamic  as `cargo build --release` builds them (default)
              static   built again statically linked, as docs/writing-a-component.md
                       ("Statically linked") says, and measured with --component-dir
              musl     built small, for musl in the `replica` profile, as
                       docs/writing-a-component.md ("Small replicas") says (needs
                       `rustup target add x86_64-unknown-linux-musl`)
  JOURNAL=J   whether s3res's voters keep their journal (what a successor needs when a
              voter dies; neither peer survives the death of its voter):
              on   as s3res-bootstrap runs a reactive component (default)
              off  s3res-bench --no-journal: like for like with the peers
Run as root (SCHED_RR). The table alone, again, from saved results:
  python3 scripts/peers-table.py RES_DIR
EOF
}
case "${1:-}" in
  -h|--help) usage; exit 0;;
  "") ;;
  *) usage >&2; exit 2;;
esac

ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${PEERS:-$ROOT/../shared/peers}
if [ ! -f "$PEERS/s3res/compare.sh" ]; then
  echo "compare-peers: no peer tooling at $PEERS (expected $PEERS/s3res/compare.sh; set PEERS=dir)" >&2
  exit 2
fi
PEERS=$(cd "$PEERS" && pwd)
REPS=${REPS:-3}
CPU_IDLE=${CPU_IDLE:-halt}
case "$CPU_IDLE" in
  halt|s3res|all) ;;
  *) echo "compare-peers: CPU_IDLE=$CPU_IDLE is none of halt, s3res, all" >&2; exit 2;;
esac
COMPONENTS=${COMPONENTS:-dynamic}
case "$COMPONENTS" in
  dynamic|static|musl) ;;
  *) echo "compare-peers: COMPONENTS=$COMPONENTS is none of dynamic, static, musl" >&2; exit 2;;
esac
JOURNAL=${JOURNAL:-on}
case "$JOURNAL" in
  on|off) ;;
  *) echo "compare-peers: JOURNAL=$JOURNAL is neither on nor off" >&2; exit 2;;
esac
RES=${RES:-$ROOT/target/s3res-peer/results/$(date -u +%Y%m%dT%H%M%SZ)}
mkdir -p "$RES"
RES=$(cd "$RES" && pwd)
cd "$ROOT"

# Every child runs in a session of its own (GEVoteTest makes its own process groups inside
# it); on INT/TERM every process of those sessions is killed.
kill_sessions() { # [SID]: every process of that session, or of every session started here
  local sig sid pids
  for sig in TERM KILL; do
    for sid in ${1:-$(cat "$SIDS" 2>/dev/null)}; do
      pids=$(ps -eo pid=,sid= | awk -v s="$sid" '$2 == s {print $1}')
      [ -n "$pids" ] && kill -s $sig $pids 2>/dev/null
    done
    [ $sig = TERM ] && sleep 1
  done
}
exec 3>&2  # the trap may run inside a redirection
trap 'echo "compare-peers: interrupted, stopping its processes" >&3; kill_sessions; exit 130' INT TERM
SIDS=$RES/.sessions
: > "$SIDS"
in_session() { # runs "$@" in a new session, in the background; the session id goes to $SIDS
  setsid -w bash -c 'echo $$ >> "$0"; exec "$@"' "$SIDS" "$@" &
}
run_session() { # runs "$@" in a new session and waits for it
  in_session "$@"
  wait $!
}

if [ "$CPU_IDLE" != halt ] && ! [ -w /dev/cpu_dma_latency ]; then
  echo "compare-peers: CPU_IDLE=$CPU_IDLE needs root (writing /dev/cpu_dma_latency)" >&2
  exit 2
fi

echo "compare-peers: cargo build --release" >&2
cargo build --release -q || { echo "compare-peers: cargo build --release failed" >&2; exit 1; }
# What every s3res-bench run gets besides its own arguments.
BENCH_ARGS=()
host=$(rustc -vV | sed -n 's/^host: //p')
if [ "$COMPONENTS" = static ]; then
  triple=$host
  echo "compare-peers: the components again, statically linked, for $triple" >&2
  RUSTFLAGS="-C target-feature=+crt-static" cargo build --release --locked -q --target "$triple" \
    -p s3res-components || { echo "compare-peers: the static build of s3res-components failed" >&2; exit 1; }
  BENCH_ARGS+=(--component-dir "$ROOT/target/$triple/release")
elif [ "$COMPONENTS" = musl ]; then
  triple=$(echo "$host" | sed -n 's/-linux-gnu$/-linux-musl/p')
  if [ -z "$triple" ]; then
    echo "compare-peers: COMPONENTS=musl needs a *-linux-gnu host, whose musl twin it builds for" >&2
    exit 2
  fi
  echo "compare-peers: the components again, small, for $triple (profile replica)" >&2
  cargo build --profile replica --locked -q --target "$triple" -p s3res-components || {
    echo "compare-peers: the musl build of s3res-components failed (rustup target add $triple?)" >&2
    exit 1
  }
  BENCH_ARGS+=(--component-dir "$ROOT/target/$triple/replica")
fi

{
  echo "commit $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- . ':!docs' ':!scripts' 2>/dev/null || echo ' (with uncommitted changes outside docs/ and scripts/)')"
  echo "branch $(git rev-parse --abbrev-ref HEAD)"
  echo "started $(date -u '+%Y-%m-%d %H:%M:%S UTC')"
  echo "reps $REPS"
  echo "cpu_idle $CPU_IDLE"
  echo "components $COMPONENTS"
  echo "journal $JOURNAL"
  echo "load_start $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "machine $(nproc) CPUs, $(uname -r), $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //')"
} > "$RES/meta.txt"

if [ "$CPU_IDLE" = all ]; then
  # Held on fd 4 until this script exits (the kernel drops the request when the last copy of
  # the fd closes): opened only now, so that nothing started before (cargo, git) inherits it.
  exec 4>/dev/cpu_dma_latency && printf '\0\0\0\0' >&4 ||
    { echo "compare-peers: CPU_IDLE=all: could not write /dev/cpu_dma_latency" >&2; exit 2; }
fi
echo "compare-peers: $PEERS/s3res/compare.sh, REPS=$REPS, raw results in $RES" >&2
export REPS RES
# (${A[@]+"${A[@]}"}: an empty array under `set -u`, on every bash)
RUN_ARGS=(${BENCH_ARGS[@]+"${BENCH_ARGS[@]}"})
[ "$CPU_IDLE" = s3res ] && RUN_ARGS+=(--cpu-idle poll)
[ "$JOURNAL" = off ] && RUN_ARGS+=(--no-journal)
if [ ${#RUN_ARGS[@]} -gt 0 ]; then
  # compare.sh runs $BENCH; this one adds the options to every s3res-bench it runs.
  printf '#!/bin/bash\nexec %q%s "$@"\n' "$ROOT/target/release/s3res-bench" "$(printf ' %q' "${RUN_ARGS[@]}")" \
    > "$RES/s3res-bench-with-options"
  chmod +x "$RES/s3res-bench-with-options"
  export BENCH=$RES/s3res-bench-with-options
fi
# compare.sh works in target/s3res-peer (its OUT) and does not create it: on a fresh checkout
# its `cd` failed and the C floor was compiled nowhere, leaving that column empty.
mkdir -p "${OUT:-$PWD/target/s3res-peer}"
run_session bash "$PEERS/s3res/compare.sh" > "$RES/compare.log" 2>&1
rc=$?
grep -E '^(===|TIMEOUT)' "$RES/compare.log" >&2
[ $rc = 0 ] || { echo "compare-peers: compare.sh failed ($rc), see $RES/compare.log" >&2; exit 1; }
for f in "$RES"/c-*.txt; do
  [ -s "$f" ] || { echo "compare-peers: the C floor produced nothing ($f is empty), see $RES/compare.log" >&2; exit 1; }
done

# The restart floor, made to do what it says. limits.c's child "touches" each page with
# `m[o]=m[o]`, which gcc -O2 compiles away: its fork+touch figure is a bare fork, no page
# copied (docs/benchmarks.md, "The C floor's restart"). Built again here from the same
# source, changed only in that loop: `written` writes every page (volatile), `populate` takes
# its copies with one madvise(MADV_POPULATE_WRITE), as s3res's fork child does. Both also at
# 4 KiB, and run as compare.sh runs limits (SCHED_RR 60, unpinned), each repetition followed by
# s3res's restart over the same sizes, so that the ratios of every size are of one run.
if [ "${SKIP_RECOVERY:-0}" != 1 ]; then
  with_4k=(-e 's/long kbs\[\]={256,/long kbs[]={4,256,/' -e 's/k<4;k++/k<5;k++/')
  sed "${with_4k[@]}" -e 's/m\[o\]=m\[o\];/((volatile char*)m)[o]=m[o];/' \
      "$PEERS/c-floor/limits.c" > "$RES/limits-written.c"
  sed "${with_4k[@]}" \
      -e 's/for(long o=0;o<sz;o+=pg)m\[o\]=m\[o\];/if(madvise((char*)((long)m\&-pg),sz+((long)m\&(pg-1)),23))kill(getppid(),9);/' \
      "$PEERS/c-floor/limits.c" > "$RES/limits-populate.c"
  for v in written populate; do
    grep -q 'kbs\[\]={4,' "$RES/limits-$v.c" && ! grep -q 'm\[o\]=m\[o\];' "$RES/limits-$v.c" ||
      { echo "compare-peers: limits.c has changed; the $v floor could not be made from it" >&2; exit 1; }
    gcc -O2 -w "$RES/limits-$v.c" -o "$RES/limits-$v" ||
      { echo "compare-peers: could not build the $v floor" >&2; exit 1; }
  done
  for rep in $(seq 1 "$REPS"); do
    echo "=== restart floors and s3res restart by size, repetition $rep $(date +%T)" >&2
    for v in written populate; do
      run_session chrt -r 60 "$RES/limits-$v" fork > "$RES/c-fork-$v-$rep.txt" ||
        { echo "compare-peers: the $v floor failed, see $RES/c-fork-$v-$rep.txt" >&2; exit 1; }
    done
    # ($BENCH, when set, is the wrapper above: it carries BENCH_ARGS already.)
    run_session "${BENCH:-$ROOT/target/release/s3res-bench}" restart \
      --size 4k,256k,1m,8m,64m --count 30 --setup rr-pinned --json --quiet \
      > "$RES/s3res-restart-sizes-$rep.jsonl" 2>>"$RES/restart-sizes-stderr.log" ||
      { echo "compare-peers: s3res-bench restart failed, see $RES/restart-sizes-stderr.log" >&2; exit 1; }
  done
fi

# Replica resident size. s3res: s3res-bench memory (TMR s3res-echo, idle after 1000 rounds).
echo "compare-peers: resident sizes" >&2
run_session target/release/s3res-bench ${BENCH_ARGS[@]+"${BENCH_ARGS[@]}"} memory --size 0 --json --quiet \
  > "$RES/s3res-memory.jsonl" 2>>"$RES/rss-stderr.log"
# The same with the replicas locking only what they touch (a component's `lock_memory: used`).
run_session target/release/s3res-bench ${BENCH_ARGS[@]+"${BENCH_ARGS[@]}"} memory --size 0 --json --quiet --lock-memory used \
  > "$RES/s3res-memory-used.jsonl" 2>>"$RES/rss-stderr.log"
# S³RES: a TMR GenericEmpty under VoterM (pinned build), one round a millisecond; VmRSS of
# each process once the rounds run.
GE=${OUT:-$ROOT/target/s3res-peer}/pinned/test
(cd "$GE" && in_session ./GEVoteTest -v VoterM -r TMR -s 8 -n 6000 -w 0 -i 1000 -t 20000 -p 60 \
  > "$RES/orig-rss-run.log" 2>&1; wait $!) &
ge=$!
sleep 4
sid=$(tail -n1 "$SIDS")
for p in $(ps -eo pid=,sid=,comm= | awk -v s="$sid" '$2 == s && ($3 == "VoterM" || $3 == "GenericEmpty") {print $1}'); do
  echo "rss comm=$(cat /proc/$p/comm) pid=$p vmrss_kib=$(awk '/^VmRSS/ {print $2}' /proc/$p/status)" \
    "pss_kib=$(awk '/^Pss:/ {print $2}' /proc/$p/smaps_rollup 2>/dev/null)"
done > "$RES/orig-rss.txt"
kill_sessions "$sid"
wait $ge 2>/dev/null

echo "load_end $(cut -d' ' -f1-3 /proc/loadavg)" >> "$RES/meta.txt"
echo "finished $(date -u '+%Y-%m-%d %H:%M:%S UTC')" >> "$RES/meta.txt"
python3 "$ROOT/scripts/peers-table.py" "$RES"
