#!/bin/bash
# like run.sh but kills replica 1 (its latest pid) at 1.0 s with signal ${SIG:-KILL}
(./run.sh "$@") & sleep ${AT:-1.0}; d=/tmp/explore-newcomer/runs/$1
P=$(grep '"replica":1' $d/ev.jsonl | grep -E '"start"|"recovery"' | tail -1 | grep -o '"new_pid":[0-9]*\|"pid":[0-9]*' | tail -1 | cut -d: -f2)
echo "kill -${SIG:-KILL} $P ($(cat /proc/$P/status 2>/dev/null | grep Threads))"; kill -${SIG:-KILL} $P; wait
