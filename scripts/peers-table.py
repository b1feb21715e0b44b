#!/usr/bin/env python3
"""One markdown table from a results folder of scripts/compare-peers.sh (the raw outputs of
../shared/peers/s3res/compare.sh, plus meta.txt, s3res-memory.jsonl and orig-rss.txt).

Columns: C floor | S³RES | s3res | s3res / S³RES | s3res / C floor. A cell is the median over
the repetitions of each repetition's median, with the per-repetition range when there are
several, and the p99 (median over repetitions) where the run has one.
Usage: python3 scripts/peers-table.py RESULTS_DIR
"""
import glob
import json
import os
import re
import statistics as st
import sys

LEVEL = {"NMR": 0, "SMR": 1, "DMR": 2, "TMR": 3}
NAME = {0: "no voter", 1: "SMR", 2: "DMR", 3: "TMR"}


def kv(line):
    return dict(re.findall(r"(\w+)=([^\s]+)", line))


class Results:
    def __init__(self, res):
        self.res = res

    def files(self, prefix, ext):  # exactly PREFIX-<rep>.EXT
        pat = re.compile(re.escape(prefix) + r"-(\d+)\." + ext + "$")
        out = []
        for f in sorted(glob.glob(os.path.join(self.res, "*"))):
            m = pat.match(os.path.basename(f))
            if m:
                out.append((int(m.group(1)), f))
        return out

    def lines(self, prefix, tag):  # key=value lines starting with TAG, of every repetition
        for _, f in self.files(prefix, "txt"):
            for line in open(f):
                if line.startswith(tag):
                    yield kv(line)

    def c_rtt(self, variant):  # {(size, r): [(med, p99) per rep]}
        out = {}
        for d in self.lines(f"c{variant}", "roundtrip"):
            key = (int(d["size"]), int(d["replicas"]))
            out.setdefault(key, []).append((float(d["median_us"]), float(d["p99_us"])))
        return out

    def orig_rtt(self, variant):
        out = {}
        for d in self.lines(f"orig-{variant}", "s3res_orig_rtt"):
            key = (int(d["size"]), LEVEL[d["level"]])
            out.setdefault(key, []).append((float(d["median_us"]), float(d["p99_us"])))
            self.lost = getattr(self, "lost", 0) + int(d["lost"])
        return out

    def s3res_rtt(self, setup):
        out = {}
        for _, f in self.files(f"s3res-{setup}", "jsonl"):
            for line in open(f):
                if line.startswith("{"):
                    d = json.loads(line)
                    key = (d["size"], d["replicas"])
                    out.setdefault(key, []).append((d["median_us"], d["p99_us"]))
                    self.faults = getattr(self, "faults", 0) + (d.get("faults") or 0)
        return out

    def c_fork(self, variant=""):  # {kib: [(med, max)]}; variant "-written", "-populate"
        out = {}
        for d in self.lines(f"c-fork{variant}", "fork+touch"):
            out.setdefault(int(d["rss_kb"]), []).append((float(d["median_us"]), float(d["max_us"])))
        return out

    def orig_kill(self):
        """TMR kills of every repetition: VoterM's own restart times (gap 0, every timeout)
        and kill → answer at the 2 ms timeout, one list per repetition."""
        restart, k2a = {}, {}
        for rep, f in self.files("orig-kill", "txt"):
            since, pending = [], []
            for line in open(f):
                m = re.match(r"voterm_usec restart \(([\d.]+)\)", line)
                if m:
                    since.append(float(m.group(1)))
                elif line.startswith("s3res_orig_kill"):
                    d = kv(line)
                    pending.append((float(d["kill_to_answer_us"]), since[-1] if since else None))
                    since = []
                elif line.startswith("s3res_orig_restart"):
                    d = kv(line)
                    if d["level"] == "TMR" and d["gap_us"] == "0":
                        restart.setdefault(rep, []).extend(r for _, r in pending if r is not None)
                        if d["timeout_us"] == "2000":
                            k2a.setdefault(rep, []).extend(k for k, _ in pending)
                    pending, since = [], []
        return restart, k2a

    def jsonl(self, prefix):
        rows = []
        for rep, f in self.files(prefix, "jsonl"):
            for line in open(f):
                if line.startswith("{"):
                    d = json.loads(line)
                    d["_rep"] = rep
                    rows.append(d)
        return rows

    def text(self, name):
        p = os.path.join(self.res, name)
        return open(p).read() if os.path.exists(p) else ""


def med(xs):
    xs = [x for x in xs if x is not None]
    return st.median(xs) if xs else None


def pct(xs, q):
    xs = sorted(x for x in xs if x is not None)
    return xs[min(len(xs) - 1, int(len(xs) * q))] if xs else None


def num(x):
    if x is None:
        return "—"
    return f"{x:.1f}" if x < 100 else f"{x:.0f}"


def cell(pairs, tail="p99"):
    """pairs: [(median, tail or None)] one per repetition."""
    if not pairs:
        return "—"
    ms = [p[0] for p in pairs]
    s = num(med(ms))
    if len(ms) > 1:
        s += f" [{num(min(ms))}–{num(max(ms))}]"
    t = med([p[1] for p in pairs])
    if t is not None:
        s += f" ({tail} {num(t)})"
    return s


def ratio(a, b):
    """Median over repetitions of a/b (per-repetition medians, same repetition)."""
    if not a or not b:
        return "—"
    rs = [x[0] / y[0] for x, y in zip(a, b) if x[0] and y[0]]
    return f"{med(rs):.2f}" if rs else "—"


def restart_by_size(R, fork, written, populate):
    """The restart against the three C floors, 4 KiB to 64 MiB: each repetition of the floors
    followed by s3res-bench restart over the same sizes (compare-peers.sh)."""
    rst = {}
    for d in R.jsonl("s3res-restart-sizes"):
        rst.setdefault(d["size"] // 1024, []).append((d["median_us"], d.get("p99_us")))
    if not rst or not written:
        return
    print()
    print("Restart by state size: s3res detection → ready (TMR `s3res-ballast`, rr-pinned, 30 "
          "kills) against the C floor's fork of a process holding that state, locked: as limits.c "
          "ships it (its touch compiled away: a bare fork), with every page written, and with "
          "one madvise(MADV_POPULATE_WRITE) as s3res's fork child takes its copies.")
    print()
    print("| state | s3res | C fork only | C fork + write | C fork + populate "
          "| / fork only | / fork + write | / fork + populate |")
    print("|---|---|---|---|---|---|---|---|")
    for kib in sorted(rst):
        s = rst[kib]
        name = f"{kib} KiB" if kib < 1024 else f"{kib // 1024} MiB"
        print("| " + " | ".join([
            name, cell(s), cell(fork.get(kib), "max"), cell(written.get(kib), "max"),
            cell(populate.get(kib), "max"), ratio(s, fork.get(kib)), ratio(s, written.get(kib)),
            ratio(s, populate.get(kib))]) + " |")
    print()
    print("The fork-only column comes from compare.sh's own runs (no 4 KiB size there); the "
          "other floors and s3res from compare-peers.sh's, repetition by repetition.")


def main():
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        sys.exit(0 if len(sys.argv) == 2 else 2)
    R = Results(sys.argv[1])
    meta = R.text("meta.txt")
    env = [l for l in R.text("env.txt").splitlines() if l.strip()]
    for line in meta.splitlines():
        print(f"- {line}")
    if env:
        print("- load (compare.sh's snapshots: time, 1/5/15-min load average, other real-time tasks):")
        for line in env:
            print(f"  - `{line.lstrip('# ').rstrip(',')}`")
    print()

    c1, o1, s1 = R.c_rtt("-1cpu"), R.orig_rtt("onecpu"), R.s3res_rtt("rr-one-cpu")
    cp, op, sp = R.c_rtt("-cpu1"), R.orig_rtt("pinned"), R.s3res_rtt("rr-pinned")
    rows = []
    for size in (8, 4096):
        for r in range(4):
            k = (size, r)
            label = "B" if size == 8 else "KiB"
            rows.append((f"{NAME[r]} round trip, all on one CPU, {size if size == 8 else 4} {label}",
                         cell(c1.get(k)), cell(o1.get(k)), cell(s1.get(k)),
                         ratio(s1.get(k), o1.get(k)), ratio(s1.get(k), c1.get(k))))
    for size in (8, 4096):
        k = (size, 3)
        label = "8 B" if size == 8 else "4 KiB"
        rows.append((f"TMR round trip, voter CPU 0 / replicas CPU 1, {label}",
                     cell(cp.get(k)), cell(op.get(k)), cell(sp.get(k)),
                     ratio(sp.get(k), op.get(k)), ratio(sp.get(k), cp.get(k))))

    # restart after SIGKILL, detection → ready. limits.c's own fork+touch writes no page (gcc
    # drops its `m[o]=m[o]`); compare-peers.sh measures the floor again with every page written.
    fork, written, populate = R.c_fork(), R.c_fork("-written"), R.c_fork("-populate")
    floor, floor_name = (written, "C: fork + every page written") if written else \
        (fork, "C: limits.c's fork + touch, which writes no page")
    orig_restart, orig_k2a = R.orig_kill()
    o_rs = [(med(v), pct(v, 0.9)) for _, v in sorted(orig_restart.items()) if v]
    rst = {}
    for d in R.jsonl("s3res-restart"):
        rst.setdefault(d["size"], []).append((d["median_us"], d.get("p99_us")))
    for kib in (4, 256):
        s = rst.get(kib * 1024)
        c = floor.get(kib)
        rows.append((f"restart after SIGKILL, detection → ready, {kib} KiB state ({floor_name})",
                     cell(c, "max"), cell(o_rs, "p90"), cell(s),
                     ratio(s, o_rs), ratio(s, c)))

    # kill → next answer, TMR, 2 ms voter timeout
    o_k = [(med(v), max(v)) for _, v in sorted(orig_k2a.items()) if v]  # 10 kills a repetition
    det = [(d["median_us"], d.get("p99_us")) for d in R.jsonl("s3res-detect")
           if d.get("what") == "crash-round" and d.get("timeout_us") == 2000]
    rows.append(("SIGKILL → next answer, TMR, 2 ms timeout", "—", cell(o_k, "max"), cell(det),
                 ratio(det, o_k), "—"))

    # resident sizes
    orig_rss = {}
    for line in R.text("orig-rss.txt").splitlines():
        d = kv(line)
        if d.get("vmrss_kib"):
            orig_rss.setdefault(d["comm"], []).append(int(d["vmrss_kib"]))
    mem = [json.loads(l) for l in R.text("s3res-memory.jsonl").splitlines() if l.startswith("{")]
    s_rss = {m["what"]: m["rss_kib"] for m in mem if m["component"] == "s3res-echo" and m["replicas"] == 3}
    for what, comm in (("replica", "GenericEmpty"), ("voter", "VoterM")):
        o = med(orig_rss.get(comm, []))
        s = s_rss.get(what)
        rows.append((f"{what} resident size (VmRSS, KiB; TMR, idle echo)", "—",
                     "—" if o is None else f"{o:.0f}", "—" if s is None else f"{s}",
                     f"{s / o:.1f}" if o and s else "—", "—"))
    # Runs before `lock_memory` existed have no such file.
    used = [json.loads(l) for l in R.text("s3res-memory-used.jsonl").splitlines() if l.startswith("{")]
    u = next((m["rss_kib"] for m in used
              if m["component"] == "s3res-echo" and m["replicas"] == 3 and m["what"] == "replica"), None)
    o = med(orig_rss.get("GenericEmpty", []))
    if u is not None:
        rows.append(("replica resident size, `lock_memory: used` (locked on fault)", "—",
                     "—" if o is None else f"{o:.0f}", f"{u}", f"{u / o:.1f}" if o else "—", "—"))

    print("| | C floor | S³RES | s3res | s3res / S³RES | s3res / C floor |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print()
    print("Times in µs: median (p99 or p90/max as marked); with several repetitions the median of "
          "the per-repetition medians [their range]; ratios are medians of per-repetition ratios "
          "of medians. One CPU: C `limits` with everything on CPU 0; S³RES `onecpu` build; s3res "
          "`--setup rr-one-cpu`. CPU 0/1: C `limits` with replicas on CPU 1; S³RES `pinned` build; "
          "s3res `--setup rr-pinned`. S³RES restart: VoterM's own restart time, TMR, every voter "
          "timeout (its replica's state is whatever GenericEmpty has: the same figure on both rows).")
    floors = {d["size"] // 1024: d.get("floor_us") for d in R.jsonl("s3res-restart")}
    if floors.get(4) is not None and 4 not in floor:
        print(f"The C floor has no 4 KiB size; s3res-bench's own fork + touch floor at 4 KiB, same run: "
              f"{num(floors[4])} µs (at 256 KiB: {num(floors.get(256))} µs).")
    restart_by_size(R, fork, written, populate)
    for v in ("seq", "unpinned"):  # counted, not shown
        R.orig_rtt(v)
    for v in ("rr", "one-cpu"):
        R.s3res_rtt(v)
    detected = sum(1 for line in R.text("s3res-orig-rtt-stderr.log").splitlines() if "detected" in line)
    print(f"Fault-free round trips (every placement compare.sh runs): S³RES lost rounds "
          f"{getattr(R, 'lost', 0)}, VoterM fault detections {detected}; "
          f"s3res fault events {getattr(R, 'faults', 0)}.")


if __name__ == "__main__":
    main()
