#!/bin/bash
bin=$1; out=$2; : > $out
for maze in $(seq 1 16); do for d in 0 2 4 8; do
  $bin $maze 100 $d 0 | grep -v "^run" >> $out
done; done
