#!/bin/bash
# MAVFI Table 2 on the robot, unprotected, planner cells in two shards each (issue 16, item 4)
export PATH=/tmp/clbin:$PATH
cd /work/main/target/classify-reg
for bits in 1 3 5; do for k in 1 2; do
  ( s3res-inject -q classify --system /work/main/examples/robot/campaign/none-classify.json \
      --components planner --fault reg --reg-bits $bits --duration 4 --run-timeout 30 \
      --mission mission.json --runs 1030 --seed 1 --shard $k/2 --out planner-reg$bits/shard-$k \
      > planner-reg$bits-$k.stdout 2> planner-reg$bits-$k.stderr ) &
done; done
wait
