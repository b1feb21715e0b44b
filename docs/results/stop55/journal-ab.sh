#!/bin/sh
# DMR 8 B, rr-one-cpu, journal on and off alternated: 6 repetitions of 10,000 rounds each.
B=/work/main/target/release/s3res-bench
C=/work/main/target/x86_64-unknown-linux-musl/replica
for rep in 1 2 3 4 5 6; do
  if [ $((rep % 2)) = 1 ]; then order="on off"; else order="off on"; fi
  for j in $order; do
    flag=""; [ $j = off ] && flag="--no-journal"
    printf 'rep %s journal %-3s ' $rep $j
    timeout 120 $B echo -q --setup rr-one-cpu --replicas 2 --size 8 --count 10000 --component-dir $C $flag --json | python3 /tmp/s56/rows.py
  done
done
