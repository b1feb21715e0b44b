#!/bin/bash
# paper-exposure.sh — the maze-robot campaign at the S³RES paper's exposure, cell by cell.
# See docs/results.md, "At the paper's exposure".
set -uo pipefail

usage() {
  cat <<'EOF'
usage: scripts/paper-exposure.sh [-h|--help] CELL...

Runs each CELL of the maze-robot campaign at the paper's exposure: faults at 2 Hz through
the whole of every mission of the 8 x 8 campaign robot (examples/robot/campaign-8x8/, about
65 simulated seconds and 15 s of wall time a mission), into the filter, navigator, mapper
and planner, in SHARDS shards run one after another (each resumable), then merged.

CELL is LEVEL-FAULT: tmr-exec, tmr-sdc, tmr-cfe, dmr-exec, dmr-cfe (210 missions each,
about 6,000 injections), none-none and smr-none (105 missions, nothing injected), tmr-none
and dmr-none (70 missions, nothing injected: false positives of a quiet system), or
tmr-mixed (10 Hz, exec/sdc/cfe drawn per injection, 20 missions: the harsher cell).
MAVFI's register table under TMR: tmr-regN-COMPONENT, N bits flipped in a register of
COMPONENT (navigator or planner) at each injection, N = 1, 3 or 5 (48 missions, about
1,000 injections; issue 16, item 4). The same without protection: none-regN-COMPONENT,
`classify` by mission of the unprotected 4 x 4 campaign robot
(examples/robot/campaign/none-classify.json), one flip per mission, 1,030 missions of about
4.5 s (the planner's take longer: a robot without a planner waits for the 60 s limit).

Environment:
  OUT=DIR     where the cells go (default target/paper-exposure); a cell's shards are
              OUT/CELL-shard-K-of-N, merged into OUT/CELL
  SHARDS=N    shards per cell (default 3); run several of this script with SHARD=K to
              split a cell across machines, then merge by hand
  SHARD=K     run only shard K of each cell (no merge)
  BIN=DIR     the s3res binaries (default target/release next to this script's repository)
  KEEP=1      keep every run's folder (events, stderr) under the shard: needed to look into
              an error or a false positive afterwards (about 40 MB a cell)
Run as root (SCHED_RR), on an otherwise quiet machine: the figures record the load.
Example, the whole of issue 16's item 2, one cell after another (about 5 hours):
  scripts/paper-exposure.sh tmr-exec tmr-sdc tmr-cfe dmr-exec dmr-cfe none-none smr-none \
    tmr-none dmr-none
EOF
}
case "${1:-}" in
  -h|--help) usage; exit 0;;
  "") usage >&2; exit 2;;
esac

ROOT=$(cd "$(dirname "$0")/.." && pwd)
# Absolute: the campaigns run from the repository root.
BIN=$(realpath -m "${BIN:-$ROOT/target/release}")
OUT=$(realpath -m "${OUT:-$ROOT/target/paper-exposure}")
SHARDS=${SHARDS:-3}
SHARD=${SHARD:-}
INJECT=$BIN/s3res-inject
if [ ! -x "$INJECT" ]; then
  echo "paper-exposure: no $INJECT (build with cargo build --release, or set BIN=dir)" >&2
  exit 2
fi
case "$SHARDS" in ''|*[!0-9]*|0) echo "paper-exposure: SHARDS=$SHARDS is not a count" >&2; exit 2;; esac
if [ -n "$SHARD" ] && { [[ "$SHARD" == *[!0-9]* ]] || [ "$SHARD" -lt 1 ] || [ "$SHARD" -gt "$SHARDS" ]; }; then
  echo "paper-exposure: SHARD=$SHARD is not one of 1..$SHARDS" >&2
  exit 2
fi

# rate and missions of a cell; every cell is checked before the first one starts (a cell
# runs for most of an hour: a misspelled last one must not wait that long to fail).
cell_params() {
  case "$1" in
    tmr-exec|tmr-sdc|tmr-cfe|dmr-exec|dmr-cfe) echo "2 210" ;;
    none-none|smr-none) echo "2 105" ;;
    tmr-none|dmr-none) echo "2 70" ;;
    tmr-mixed) echo "10 20" ;;
    tmr-reg[135]-navigator|tmr-reg[135]-planner) echo "2 48" ;;
    none-reg[135]-navigator|none-reg[135]-planner) echo "- 1030" ;;
    *) return 1 ;;
  esac
}
for cell in "$@"; do
  cell_params "$cell" > /dev/null || { echo "paper-exposure: unknown cell '$cell' (see --help)" >&2; exit 2; }
done
mkdir -p "$OUT"
keep=()
[ "${KEEP:-0}" = 1 ] && keep=(--keep-runs)

status=0
for cell in "$@"; do
  level=${cell%%-*}
  fault=${cell#*-}
  components=filter,navigator,mapper,planner
  extra=()
  case "$fault" in
    reg[135]-*)
      # regN-COMPONENT: N bits into COMPONENT only.
      bits=${fault%%-*}
      bits=${bits#reg}
      components=${fault#*-}
      fault=reg
      extra=(--reg-bits "$bits")
      ;;
  esac
  read -r rate runs < <(cell_params "$cell")
  label=$(echo "$level" | tr a-z A-Z)
  if [ -n "$SHARD" ]; then shards=$SHARD; else shards=$(seq 1 "$SHARDS"); fi
  parts=()
  whole=1
  for k in $shards; do
    dir=$OUT/$cell-shard-$k-of-$SHARDS
    parts+=("$dir")
    echo "$(date -u +%FT%TZ) $cell shard $k/$SHARDS -> $dir (load $(cut -d' ' -f1-3 /proc/loadavg))"
    # From the repository root: the system descriptions name the robot's files relative to it.
    if [ "$level" = none ] && [ "$fault" = reg ]; then
      # One flip per mission, unprotected: classified by the mission (issue 16, item 4).
      (cd "$ROOT" && "$INJECT" -q classify --system examples/robot/campaign/none-classify.json \
        --components "$components" --fault reg "${extra[@]}" --duration 4 --run-timeout 30 \
        --mission mission.json --runs "$runs" --seed 1 --shard "$k/$SHARDS" --resume \
        --out "$dir")
    else
    (cd "$ROOT" && "$INJECT" -q campaign --system "examples/robot/campaign-8x8/$level.json" \
      --fault "$fault" --rate "$rate" --runs "$runs" --seed 1 --duration 60 --run-timeout 120 \
      --components "$components" --label "$label" --shard "$k/$SHARDS" \
      --resume "${keep[@]}" "${extra[@]}" --out "$dir")
    fi
    code=$?
    if [ "$code" -ge 128 ]; then
      # Stopped by a signal (Ctrl-C, a batch system's kill): stop here; --resume goes on.
      echo "paper-exposure: stopped during $cell shard $k (give the same command to resume)" >&2
      exit "$code"
    elif [ "$code" -ne 0 ]; then
      echo "paper-exposure: $cell shard $k failed (exit $code); not merged" >&2
      status=1 whole=0
    fi
  done
  if [ -z "$SHARD" ] && [ "$whole" = 1 ]; then
    rm -rf "$OUT/$cell"
    "$INJECT" merge --out "$OUT/$cell" "${parts[@]}" || status=1
  fi
done
exit $status
