#!/usr/bin/env bash
# Round trip of an unmodified program (cat, preloaded) beside s3res-echo (linked to replica-rt),
# under the same voter, interleaved repetition by repetition so that the machine's load falls on
# both alike. Prints one table per repetition; each row is median, p99, p99.9, max.
#
#   cargo build --release && bash bench/scripts/preload-vs-linked.sh [REPS] [COUNT] [SETUP]
set -euo pipefail
cd "$(dirname "$0")/../.."
reps=${1:-3}
count=${2:-10000}
setup=${3:-rr}
bench=target/release/s3res-bench
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
for rep in $(seq 1 "$reps"); do
  echo "== repetition $rep"
  for program in linked preload-frames; do
    "$bench" -q echo --program "$program" --replicas 1,3 --size 8,4096 \
      --count "$count" --warmup 1000 --setup "$setup" | tail -n +3
  done
  for program in linked preload-lines; do
    "$bench" -q echo --program "$program" --replicas 1,3 --size 64 \
      --count "$count" --warmup 1000 --setup "$setup" | tail -n +3
  done
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
