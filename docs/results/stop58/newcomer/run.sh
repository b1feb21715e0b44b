#!/bin/bash
# run.sh NAME MODE N [redundancy] [count] [rate] [timeout_us] [extra json fields]
export PATH=${BINDIR:-/tmp/snap58/bin}:$PATH
name=$1 mode=$2 n=$3 red=${4:-tmr} cnt=${5:-30} rate=${6:-20} to=${7:-250000} extra=${8:-}
d=/tmp/explore-newcomer/runs/$name; rm -rf $d; mkdir -p $d; cd $d
cat > sys.json <<J
{ "name": "newbie-$name",
  "components": { "nb": { "exec": "${EXE:-/tmp/explore-newcomer/target/release/newbie}", "args": ["$mode", "$n"],
     "redundancy": "$red", "timeout_us": $to $extra } },
  "channels": [ { "from": "stdin", "to": "nb.in" }, { "from": "nb.out", "to": "stdout" } ] }
J
start=$(date +%s.%N)
seq 1 $cnt | s3res-frames send --as u32 --rate $rate | timeout -k 5 ${TMO:-60} s3res-bootstrap --events ev.jsonl sys.json 2>err.txt | s3res-frames show --format hex > out.txt
echo "rc=${PIPESTATUS[*]} elapsed=$(echo "$(date +%s.%N) - $start" | bc) out_lines=$(wc -l < out.txt)"
