#!/bin/bash
# Interleaved A/B of hang/crash detection and fault-free false positives (issue 15 item 3).
# usage: detect-ab.sh OLD_DIR NEW_DIR COMP_DIR OUT SEEDS...
old=$1; new=$2; comp=$3; out=$4; shift 4; mkdir -p $out
i=0
for seed in "$@"; do
  if [ $((i % 2)) = 0 ]; then order="old new"; else order="new old"; fi
  for b in $order; do
    d=$old; [ $b = new ] && d=$new
    s0=$(awk '/^cpu /{print $9}' /proc/stat); t0=$(date +%s)
    $d/s3res-bench detect --setup rr --timeout-us 2000 --count 300 --rounds 300000 --seed $seed \
      --component-dir $comp --json -q > $out/$b-$seed.json 2> $out/$b-$seed.log
    s1=$(awk '/^cpu /{print $9}' /proc/stat); t1=$(date +%s)
    echo "$b seed $seed: $((t1-t0)) s, steal $((s1-s0)) ticks" | tee -a $out/steal.txt
  done
  i=$((i+1))
done
