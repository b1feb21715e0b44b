#!/usr/bin/env python3
"""A/B of two s3res builds' round trip, alternated pair by pair (order drawn from the seed)."""
import json, random, statistics, subprocess, sys
old, new, comp, pairs, seed = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
print(f"seed {seed}, {pairs} pairs", flush=True)
rng = random.Random(seed)
cells = [(r, s) for r in (1, 2, 3) for s in (8, 4096)]
res = {c: [] for c in cells}
def run(bindir, r, s):
    out = subprocess.run([f"{bindir}/s3res-bench", "--json", "echo", "--replicas", str(r), "--size", str(s),
                          "--setup", "rr-one-cpu", "--count", "3000", "--warmup", "300", "-q",
                          "--component-dir", comp], capture_output=True, text=True, timeout=300, check=True).stdout
    rows = [json.loads(l) for l in out.splitlines() if l.startswith("{")]
    row = [x for x in rows if x["replicas"] == r][0]
    return row["median_us"]
for p in range(pairs):
    for c in cells:
        order = [("old", old), ("new", new)]
        rng.shuffle(order)
        got = {name: run(d, *c) for name, d in order}
        res[c].append((got["old"], got["new"]))
    print(f"pair {p} done", flush=True)
print("| level | size | old µs | new µs | new/old median (min–max) |")
print("|---|--:|--:|--:|---|")
for (r, s), v in res.items():
    ratios = sorted(n / o for o, n in v)
    print(f"| {['','SMR','DMR','TMR'][r]} | {s} | {statistics.median(o for o,_ in v):.2f} | {statistics.median(n for _,n in v):.2f} | {statistics.median(ratios):.3f} ({ratios[0]:.3f}–{ratios[-1]:.3f}) |")
