#!/bin/bash
# MAVFI Table 2 on the robot, unprotected: one register flip per mission (issue 16, item 4)
export PATH=/tmp/clbin:$PATH
cd /work/main/target/classify-reg
for comp in navigator planner; do for bits in 1 3 5; do
  ( s3res-inject -q classify --system /work/main/examples/robot/campaign/none-classify.json \
      --components $comp --fault reg --reg-bits $bits --duration 4 --run-timeout 30 \
      --mission mission.json --runs 1030 --seed 1 --out $comp-reg$bits \
      > $comp-reg$bits.stdout 2> $comp-reg$bits.stderr ) &
done; done
( s3res-inject -q campaign --system /work/main/examples/robot/campaign/none-classify.json --fault none --components navigator \
   --runs 100 --seed 1 --keep-runs --out none-baseline > none.stdout 2> none.stderr ) &
wait
