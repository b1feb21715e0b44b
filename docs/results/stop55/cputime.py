#!/usr/bin/env python3
"""cputime.py ROUNDS CMD...: runs CMD, samples every process named s3res-voter / s3res-echo /
s3res-bench (/proc/PID/stat utime+stime, /proc/PID/schedstat run ns) every 20 ms, and prints
each one's last sample per round (µs)."""
import subprocess, sys, os, time
rounds = int(sys.argv[1]); cmd = sys.argv[2:]
p = subprocess.Popen(cmd)
last = {}
tck = os.sysconf("SC_CLK_TCK")
while p.poll() is None:
    for pid in os.listdir("/proc"):
        if not pid.isdigit(): continue
        try:
            comm = open(f"/proc/{pid}/comm").read().strip()
            if not (comm.startswith("s3res-") or comm.startswith("limits")): continue
            st = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
            ut, stt = int(st[11]), int(st[12])
            run = int(open(f"/proc/{pid}/schedstat").read().split()[0])
            sw = [l for l in open(f"/proc/{pid}/status") if "ctxt_switches" in l]
            last[pid] = (comm, ut, stt, run, sw)
        except Exception: pass
    time.sleep(0.02)
for pid, (comm, ut, stt, run, sw) in sorted(last.items(), key=lambda x: x[1][0]):
    print(f"{comm:12} {pid:>7} user {ut*1e6/tck/rounds:6.2f} µs/round  sys {stt*1e6/tck/rounds:6.2f}  run {run/1e3/rounds:6.2f}  ({sum(int(l.split()[1]) for l in sw)/rounds:.2f} switches/round)")
