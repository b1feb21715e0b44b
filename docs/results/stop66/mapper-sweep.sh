#!/bin/bash
# The mapper sweep of stop 66: mazes 1–16, plans up to 0, 2, 4 and 8 periods late, RUNS missions
# each (in-process, release build of the delay_sweep example; time limit 240 s).
#   cargo build --release -p s3res-robot --example delay_sweep
#   B=target/release/examples/delay_sweep docs/results/stop66/mapper-sweep.sh 50 > sweep.txt
B=${B:-target/release/examples/delay_sweep}
runs=${1:-50}
for d in 0 2 4 8; do for m in $(seq 1 16); do "$B" "$m" "$runs" "$d" | tail -1; done; done
