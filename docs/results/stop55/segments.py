#!/usr/bin/env python3
"""segments.py FILE ROUNDS TSC_GHZ: reads the dump of the segment profiler
(segment-profiler.diff: `from to count cycles` per pair of consecutive marks in the voter) and
prints the time per round of each segment, the system calls' (`x>` → `x<`) apart, and the
user-space total with the marks' own cost (two rdtsc each, 27.4 cycles apiece measured here)
taken out. ROUNDS: the rounds the dump covers (it is written every 20,000 loop turns, two turns
a round)."""
import sys
path, rounds, ghz = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rows = [(a, b, int(c), int(cy)) for a, b, c, cy in (l.split() for l in open(path))]
user = marks = 0
for a, b, c, cy in sorted(rows, key=lambda r: -r[3]):
    marks += c
    is_call = a.endswith(">") and b == a[:-1] + "<"
    if not is_call:
        user += cy
    if cy / ghz / 1e3 / rounds >= 0.01:
        print(f"{a:>14} → {b:<14} {c / rounds:5.2f}/round {cy / c / ghz:9.1f} ns each "
              f"{cy / ghz / rounds:8.0f} ns/round{'  (system call)' if is_call else ''}")
mark_ns = 2 * 27.4 / ghz
print(f"user space: {user / ghz / 1e3 / rounds:.2f} µs a round, of which the marks' own "
      f"{marks * mark_ns / 1e3 / rounds:.2f} ({marks / rounds:.0f} marks a round): "
      f"{(user / ghz - marks * mark_ns) / 1e3 / rounds:.2f} µs of the voter's code")
