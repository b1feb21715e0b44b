#!/usr/bin/env python3
"""alternate-builds.py SETUP LEVEL SIZE N "LABEL:BIN=DIR [ENV:NAME=VALUE] [bench args]" ...

Alternates `s3res-bench echo` runs of builds side by side (DIR holds s3res-bench, s3res-voter,
s3res-bootstrap and comp/ with the components), N times, the order reversed every other
time, COUNT rounds each (default 5000, after 1000 of warm-up), idle CPUs polling
(/dev/cpu_dma_latency held at 0, as paired-ratios.py does). Prints each run's median round
trip and the function-call IPIs (/proc/interrupts CAL, both CPUs) per round, then per build
the median of the medians. Root.
"""
import subprocess, json, sys, os, statistics
setup, level, size, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
variants = []
for v in sys.argv[5:]:
    label, rest = v.split(":", 1); parts = rest.split()
    d = parts[0][4:]; env = dict(p[4:].split("=",1) for p in parts[1:] if p.startswith("ENV:")); variants.append((label, d, [p for p in parts[1:] if not p.startswith("ENV:")], env))
qos = open("/dev/cpu_dma_latency", "wb", buffering=0); qos.write(b"\0\0\0\0")
def cal():
    for l in open("/proc/interrupts"):
        if l.strip().startswith("CAL:"):
            f = l.split(); return int(f[1]) + int(f[2])
res = {l: [] for l, *_ in variants}
count = int(os.environ.get("COUNT", "5000"))
for i in range(n):
    order = variants if i % 2 == 0 else variants[::-1]
    line = []
    for label, d, extra, env in order:
        c0 = cal()
        out = subprocess.run([f"{d}/s3res-bench", "echo", "--setup", setup, "--replicas", level, "--size", size,
                              "--count", str(count), "--warmup", "1000", "--json", "--quiet", "--component-dir", f"{d}/comp"] + extra,
                             capture_output=True, text=True, timeout=120, env={**os.environ, **env}).stdout
        c1 = cal()
        for l in out.splitlines():
            if l.startswith("{"):
                r = json.loads(l)
                if r.get("replicas") == int(level):
                    res[label].append((r["median_us"], (c1 - c0) / (count + 1000)))
        line.append(f"{label} {res[label][-1][0]:.1f} ({res[label][-1][1]:.2f})")
    print(i, "  ".join(line), flush=True)
for l, *_ in variants:
    print(l, "median of medians %.2f, CAL/round median %.2f" % (statistics.median(x[0] for x in res[l]), statistics.median(x[1] for x in res[l])))
