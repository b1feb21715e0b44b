#!/usr/bin/env bash
# The anomaly detectors on the maze robot (issue 7, step 6; MAVFI Table 4 layout).
#
#   anomaly/scripts/robot-eval.sh BIN OUT [RUNS] [GOLDEN] [BEYOND]
#
# BIN: the folder of the release binaries (target/release); OUT: a new folder. RUNS injection
# missions per cell (default 20), GOLDEN fault-free missions per configuration (default 8),
# BEYOND missions per cell of the beyond-range campaigns (default 10).
#
# 1. Capture: the campaign robot (examples/robot/campaign/smr.json) flies fault-free missions in
#    mazes 2..25 with `capture` on navigator.cmd and planner.waypoints (training data); maze 1,
#    the one the campaigns fly, is captured too and kept out of training (held-out check).
# 2. Train a Gaussian and an autoencoder model per channel with s3res-train (seed 1).
# 3. Fault-free missions (maze 1) per level (smr, dmr) and detector (none, gauss, ae), with
#    RUST_LOG=info: anomaly events (false alarms), frames scored and the voter's mean cost.
# 4. Campaigns (maze 1, seed 7, 2 Hz for 3 s): variable-level flips of the exponent of the
#    navigator's `v` (cmd, byte 5) and of the planner's first way-point `x0` (waypoints, byte
#    11), per level and detector: any exponent bit (`exp`), and (`top`, DMR only) the top
#    exponent bit alone, which takes a value below 2 far beyond any normal range (the issue's
#    attribution target).
#
# Everything random is seeded; the commands are printed as they run.
set -euo pipefail

BIN=$(realpath "$1")
OUT=$2
RUNS=${3:-20}
GOLDEN=${4:-8}
BEYOND=${5:-10}
ROOT=${S3RES_ROOT:-$(cd "$(dirname "$0")/../.." && pwd)}
[ -e "$OUT" ] && { echo "robot-eval: $OUT exists; give a new folder" >&2; exit 2; }
mkdir -p "$OUT"
OUT=$(realpath "$OUT")
export PATH="$BIN:$PATH"

NAV_FIELDS='[{"name":"v","type":"f64","offset":5},{"name":"w","type":"f64","offset":13}]'
PLAN_FIELDS='[{"name":"n","type":"u16","offset":9},{"name":"x0","type":"f64","offset":11},{"name":"y0","type":"f64","offset":19}]'
echo "$NAV_FIELDS" > "$OUT/nav-cmd.layout.json"
echo "$PLAN_FIELDS" > "$OUT/plan-wp.layout.json"

# config LEVEL MAZE_SEED DETECTOR(none|gauss|ae|capture) > description
config() {
  python3 - "$ROOT/examples/robot/campaign/$1.json" "$2" "$3" "$NAV_FIELDS" "$PLAN_FIELDS" "$OUT" <<'EOF'
import json, sys
path, seed, det, nav, plan, out = sys.argv[1:]
d = json.load(open(path))
args = d["components"]["sim"]["args"]
args[args.index("--seed") + 1] = seed
for ch in d["channels"]:
    for src, fields, name in (("navigator.cmd", nav, "nav-cmd"), ("planner.waypoints", plan, "plan-wp")):
        if ch["from"] != src:
            continue
        ch["fields"] = json.loads(fields)
        if det == "capture":
            ch["capture"] = f"{name}.bin"
        elif det != "none":
            ch["detector"] = {"model": f"{out}/{name}.{det}.json"}
print(json.dumps(d, indent=1))
EOF
}

echo "== capture $(date +%T)"
for seed in $(seq 1 25); do
  dir="$OUT/capture/maze-$seed"
  mkdir -p "$dir"
  config smr "$seed" capture > "$dir/system.json"
  (cd "$dir" && s3res-bootstrap -q system.json > stdout 2> stderr) || echo "capture maze $seed: exit $?"
  echo "maze $seed: $(grep -h 'mission' "$dir/stderr" | tail -1)"
done

echo "== train $(date +%T)"
for ch in nav-cmd plan-wp; do
  frames=()
  for seed in $(seq 2 25); do frames+=(--frames "$OUT/capture/maze-$seed/$ch.bin"); done
  RUST_LOG=warn s3res-train gaussian --layout "$OUT/$ch.layout.json" "${frames[@]}" --out "$OUT/$ch.gauss.json"
  RUST_LOG=warn s3res-train autoencoder --layout "$OUT/$ch.layout.json" "${frames[@]}" --out "$OUT/$ch.ae.json" --seed 1
  for det in gauss ae; do
    echo "held-out maze 1, $ch, $det:"
    RUST_LOG=warn s3res-train check --model "$OUT/$ch.$det.json" --frames "$OUT/capture/maze-1/$ch.bin" | tail -3
  done
done

echo "== fault-free missions $(date +%T)"
for level in smr dmr; do
  for det in none gauss ae; do
    for k in $(seq 1 "$GOLDEN"); do
      dir="$OUT/golden/$level-$det/run-$k"
      mkdir -p "$dir"
      config "$level" 1 "$det" > "$dir/system.json"
      (cd "$dir" && RUST_LOG=info s3res-bootstrap --events events.jsonl system.json > stdout 2> stderr) \
        || echo "golden $level-$det $k: exit $?"
    done
    echo "$level-$det: $(grep -h 'mission' "$OUT"/golden/$level-$det/run-*/stderr | grep -c succeeded)/$GOLDEN succeeded"
  done
done

echo "== campaigns $(date +%T)"
mkdir -p "$OUT/systems"
# campaign LEVEL DETECTOR TARGET FLIPS(exp|top) RUNS
campaign() {
  local level=$1 det=$2 target=$3 flips=$4 runs=$5
  local offset=5 cell="$1-$2-$3-$4"
  [ "$target" = planner ] && offset=11
  local bits=(--var-field exponent)
  [ "$flips" = top ] && bits=(--var-bits 62)
  echo "-- $cell $(date +%T)"
  s3res-inject campaign --system "$OUT/systems/$level-$det.json" --fault var --var-offset "$offset" \
    "${bits[@]}" --rate 2 --runs "$runs" --seed 7 --duration 3 --run-timeout 60 \
    --components "$target" --label "${level^^} $det" --keep-runs --out "$OUT/campaign/$cell" \
    2> "$OUT/campaign-$cell.log" || echo "campaign $cell: exit $?"
  tail -4 "$OUT/campaign/$cell/table.md" 2>/dev/null | head -1
}
for level in smr dmr; do
  for det in none gauss ae; do
    config "$level" 1 "$det" > "$OUT/systems/$level-$det.json"
  done
done
for det in none gauss ae; do
  for target in navigator planner; do
    campaign dmr "$det" "$target" top "$BEYOND"
  done
done
for level in smr dmr; do
  for det in none gauss ae; do
    for target in navigator planner; do
      campaign "$level" "$det" "$target" exp "$RUNS"
    done
  done
done
echo "== done $(date +%T)"
