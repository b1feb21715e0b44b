#!/bin/sh
# Fault-free TMR rounds at a 2 ms timeout under SCHED_RR (issue 15 item 3), one seed after
# another, with the steal of both CPUs (/proc/stat, 10 ms ticks here) over each run.
# Run from the repository root after `cargo build --release -p s3res-bench -p s3res-voter -p s3res-components`.
set -eu
out=${1:-docs/results/stop64}
for seed in 9401 9402 9403; do
  s0=$(awk '/^cpu /{print $9}' /proc/stat)
  t0=$(date +%s)
  target/release/s3res-bench detect --setup rr --timeout-us 2000 --count 0 --rounds 1000000 \
    --seed $seed --json -q > "$out/fp-quiet-$seed.json" 2> "$out/fp-quiet-$seed.log"
  s1=$(awk '/^cpu /{print $9}' /proc/stat)
  t1=$(date +%s)
  echo "seed $seed: $((t1 - t0)) s, steal $((s1 - s0)) ticks" | tee -a "$out/fp-quiet-steal.txt"
done
