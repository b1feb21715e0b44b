#!/bin/bash
# irq.sh ROUNDS CMD...: runs CMD (a round-trip benchmark of ROUNDS rounds, warm-up included)
# and prints, per round, the interrupts /proc/interrupts counted on both CPUs (LOC timer,
# RES rescheduling, CAL function-call IPIs) and, system-wide, context switches and system
# calls (perf stat). CMD's own output is kept in $OUT (default irq.out). Needs root and perf.
R=$1; shift
OUT=${OUT:-irq.out}
PERF=$(mktemp)
snap() { awk '/RES:|CAL:|LOC:/ {print $1, $2+$3}' /proc/interrupts | tr '\n' ' '; }
a=$(snap)
perf stat -a -x, -e context-switches,raw_syscalls:sys_enter -o "$PERF" -- "$@" > "$OUT" 2>&1
b=$(snap)
python3 - "$R" "$a" "$b" "$PERF" <<'P'
import sys
R = float(sys.argv[1]); a = sys.argv[2].split(); b = sys.argv[3].split()
d = {a[i]: (float(b[i + 1]) - float(a[i + 1])) / R for i in range(0, len(a), 2)}
p = {}
for l in open(sys.argv[4]):
    f = l.strip().split(',')
    if len(f) > 2 and f[0].replace('.', '').isdigit():
        p[f[2]] = float(f[0]) / R
print(' '.join(f"{k} {v:.2f}" for k, v in d.items()), ' '.join(f"{k} {v:.2f}" for k, v in p.items()))
P
rm -f "$PERF"
