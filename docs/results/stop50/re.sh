#!/bin/bash
# re.sh OUT REPS variant... : interleaved echo round trips (TMR and DMR, 8 B and 4 KiB, one CPU), order flipped every other rep
out=$1; reps=$2; shift 2
for rep in $(seq 1 $reps); do
  vs="$*"; if (( rep % 2 == 0 )); then vs=$(echo $vs | tr ' ' '\n' | tac | tr '\n' ' '); fi
  for v in $vs; do
    /tmp/s50/$v/s3res-bench echo --setup rr-one-cpu --cpu-idle poll --replicas ${REPL:-1,2,3} --size 8,4096 --count ${COUNT:-3000} --json --component-dir /tmp/s50/$v/comp 2>/dev/null | grep '^{' | sed "s/^/$v $rep /" >> $out
  done
done
