#!/bin/bash
# rs.sh OUT REPS SIZES variant... : interleaved restart runs, order flipped every other
exec 4>/dev/cpu_dma_latency; printf "\0\0\0\0" >&4
out=$1; reps=$2; sizes=$3; shift 3
for rep in $(seq 1 $reps); do
  vs="$*"; if (( rep % 2 == 0 )); then vs=$(echo $vs | tr ' ' '\n' | tac | tr '\n' ' '); fi
  for v in $vs; do
    /tmp/s48/$v/s3res-bench restart --setup rr-pinned --cpu-idle poll --size $sizes --count ${COUNT:-30} --json --quiet --component-dir /tmp/s48/$v/comp 2>/dev/null | grep '^{' | sed "s/^/$v $rep /" >> $out
  done
done
