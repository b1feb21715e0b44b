#!/bin/bash
# stall-trace.sh BENCH COMPDIR: one 300,000-round TMR rr-pinned run with idle CPUs polling under
# `perf record` of the scheduler's switches and wake-ups on both CPUs; prints the longest time
# from a wake-up of the voter (`sched_waking`) to the voter on its CPU again, and the trace
# around it (every CPU).
perf record -q -m 4096 -e sched:sched_switch,sched:sched_wakeup,sched:sched_waking -a -o /tmp/st.data -- \
  "$1" --cpu-idle poll echo --setup rr-pinned --replicas 3 --size 8 --count 300000 --warmup 0 \
  --component-dir "$2" --json --quiet 2>&1 | grep -o '"median_us[^,]*,"p99_us[^,]*,"p999_us[^,]*,"max_us[^,]*\|"steal_ms":[0-9]*'
perf script --ns -i /tmp/st.data -F comm,tid,cpu,time,event,trace 2>/dev/null > /tmp/st.txt
python3 - <<'P'
import re
lines = open('/tmp/st.txt').read().splitlines()
woken, best = None, (0, 0, 0)
for i, l in enumerate(lines):
    t = float(re.search(r'(\d+\.\d+):', l).group(1))
    if 'sched_waking' in l and 'comm=s3res-voter' in l and woken is None:
        woken = (t, i)
    elif 'sched_switch' in l and 'next_comm=s3res-voter' in l and woken:
        if t - woken[0] > best[0]:
            best = (t - woken[0], woken[1], i)
        woken = None
gap, a, b = best
print(f"longest from the voter's wake-up to the voter running: {gap * 1e3:.3f} ms (trace lines {a}-{b})")
for l in lines[max(a - 16, 0):b + 4]:
    print(re.sub(r'\s+', ' ', l.strip())[:220])
P
rm -f /tmp/st.data /tmp/st.txt
