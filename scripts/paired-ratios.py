#!/usr/bin/env python3
"""paired-ratios.py — s3res's round trip and restart as ratios to the C floor and to S³RES,
pair by pair, with a confidence interval.

compare-peers.sh measures each implementation for 20,000 rounds per configuration, one after
the other, and divides the medians. On a host whose CPU changes speed every few hundred
milliseconds (docs/benchmarks.md, "Reading the numbers") such a ratio carries the speed each
implementation happened to get, and two runs of it disagree. This script measures in *pairs*
instead: for each cell it runs the C floor, s3res and S³RES back to back, briefly (a few
thousand rounds, or twenty restarts, each; the order drawn anew for every cell of every pair
from the seed), divides within the pair, and repeats. Per cell it prints each implementation's
median of its per-run medians, the median of the per-pair ratios with a 95 % confidence
interval (distribution-free: the binomial order statistics of a median), and how many pairs
were within issue 15's target; and, with S³RES, the C floor's own ratio to it in the same
pairs: how far below S³RES anything can get on this host.

  --what roundtrip  cells are replication level × frame size (8 B, 4 KiB), placed all on one
                    CPU or with the replicas on the other one (--placement); targets s3res / C
                    ≤ 1.5, s3res / S³RES ≤ 0.77 on one CPU and ≤ 1.0 across CPUs
  --what restart    cells are state sizes (4 KiB to 64 MiB): s3res's detection → ready
                    (`s3res-bench restart`, rr-pinned), the C floor's fork + write of every page
                    of the same size, S³RES's own restart time (VoterM's timer, its own
                    replicas, whatever the size); targets s3res / fork + write ≤ 1.5 and, at
                    256 KiB, s3res / S³RES ≤ 0.5

The three are the ones compare-peers.sh runs: the C floor is ../shared/peers/c-floor/limits.c,
built again here with its count, level and size taken from the environment, the placement of
the setup measured, and (restart) every page really written; S³RES is the VoterM,
GenericEmpty and GEVoteTest that ../shared/peers/s3res/build.sh builds (built on first use, as
compare.sh does); s3res is target/release/s3res-bench.

usage: scripts/paired-ratios.py [--what roundtrip|restart] [--pairs N] [--count N] [--seed S]
                                [--placement one-cpu|pinned] [--sizes LIST] [--levels 1,2,3]
                                [--no-s3res-orig] [--components DIR] [--no-journal]
                                [--cpu-idle all|halt] [--res DIR]
       scripts/paired-ratios.py --table RES_DIR      (the table again, from saved results)

Needs root (SCHED_RR), gcc and the release binaries (cargo build --release); without them, or
with arguments that cannot work, it says why in one line and exits with status 2, having run
nothing (a run that fails on the way exits with 1). Run it on a quiet machine: it measures.
Every process it starts runs in a session of its own and is killed when its run ends, times
out, or the script is interrupted.
"""

import argparse
import json
import math
import os
import random
import re
import signal
import statistics
import subprocess
import sys
import time

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
LEVEL_NAMES = {1: "SMR", 2: "DMR", 3: "TMR"}
# Issue 15's targets for the one-CPU rows: s3res / C floor and s3res / S³RES at most these.
TARGET_C = 1.5
TARGET_ORIG = 0.77
TARGET_ORIG_ACROSS = 1.0
# Item 2: detection → ready at most 1.5 × fork + write of the same state (4 KiB to 64 MiB),
# and at 256 KiB at most 0.5 × S³RES's own restart.
TARGET_RESTART_C = 1.5
TARGET_RESTART_ORIG = 0.5
RESTART_SIZES = [4 << 10, 256 << 10, 1 << 20, 8 << 20, 64 << 20]
# Replica kills per S³RES restart run (each gives VoterM's restart time once or more).
ORIG_KILLS = 10
# (s3res-bench --setup, the C floor's placement edit, S³RES's build variant)
PLACEMENTS = {
    "one-cpu": ("rr-one-cpu", ("CPU_SET(c%2,&s)", "CPU_SET(0,&s)"), "onecpu"),
    "pinned": ("rr-pinned", ("pin(core+1+i)", "pin(1)"), "pinned"),
}
# One run's limit: a few thousand rounds take well under a second; a run that takes this long
# is stuck, and is killed and reported.
RUN_TIMEOUT_S = 60


def fail(msg, status=1):
    """A run that could not be made or went wrong: one line on stderr, exit status 1."""
    print(f"paired-ratios.py: {msg}", file=sys.stderr)
    sys.exit(status)


def usage_error(msg):
    """Arguments or surroundings that cannot work: one line, exit status 2, nothing run."""
    fail(msg, status=2)


# --- processes ---------------------------------------------------------------------------------

SESSIONS = set()


def session_members(sid):
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        # Fields after the command (which may hold spaces and parentheses): state ppid pgrp sid
        fields = stat[stat.rfind(")") + 2:].split()
        if len(fields) > 3 and int(fields[3]) == sid:
            pids.append(int(entry))
    return pids


def kill_session(sid):
    """SIGKILL every process of the session `sid` (GEVoteTest makes process groups of its own
    inside it), until none is left."""
    for _ in range(50):
        pids = session_members(sid)
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.02)


def steal_ms():
    """Milliseconds the hypervisor has taken from this machine's CPUs since boot (`steal` of
    /proc/stat's `cpu` line, in USER_HZ ticks); None where it cannot be read."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) * 1000 // os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def run(cmd, cwd=None, env=None):
    """Runs `cmd` in a session of its own; returns its stdout. Everything left of the session
    afterwards is killed."""
    p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         start_new_session=True, text=True)
    SESSIONS.add(p.pid)
    try:
        out, err = p.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        kill_session(p.pid)
        p.communicate()
        fail(f"{' '.join(cmd)} did not finish in {RUN_TIMEOUT_S} s (killed)")
    finally:
        kill_session(p.pid)
        SESSIONS.discard(p.pid)
    if p.returncode != 0:
        fail(f"{' '.join(cmd)} exited with {p.returncode}: {err.strip()[-400:]}")
    return out


def kill_all_sessions(*_):
    for sid in list(SESSIONS):
        kill_session(sid)
    sys.exit("paired-ratios.py: interrupted; every process it started is stopped")


def kv(line):
    """The `key=value` fields of one line of limits.c's or GEVoteTest's output."""
    return dict(re.findall(r"(\w+)=([^\s]+)", line))


# --- the three implementations -------------------------------------------------------------------

def build_c_floor(peers, placement, res):
    """limits.c with its round count, level and size from ITERS, LEVEL and SIZE, and the
    placement's pinning; every edit checked, so a changed limits.c is refused, not mismeasured.

    The client pins itself to CPU 0 before it forks the first voter: in limits.c's own run the
    no-voter configuration comes first and pins it, and every voter after inherits CPU 0. A
    run of one configuration alone would otherwise leave its voter free to run on CPU 1, and
    measure a round that crosses CPUs (28.5 µs for SMR 8 B on one CPU, against 18.7)."""
    with open(os.path.join(peers, "c-floor", "limits.c")) as f:
        src = f.read()
    edits = [
        ("int iters=20000;", 'int iters=getenv("ITERS")?atoi(getenv("ITERS")):20000; pin(0);'),
        ("int n=sizes[si];", 'int n=sizes[si]; if(getenv("SIZE")&&n!=atoi(getenv("SIZE")))continue;'),
        ("for(int r=0;r<=3;r++){",
         'for(int r=0;r<=3;r++){ if(getenv("LEVEL")&&r!=atoi(getenv("LEVEL")))continue;'),
        PLACEMENTS[placement][1],
    ]
    return compile_edited(src, edits, os.path.join(res, f"limits-{placement}.c"))


def build_c_restart_floor(peers, res):
    """limits.c's fork floor made to do what compare-peers.sh's `written` floor does (every page
    written, through a volatile pointer, so that gcc keeps the writes), with 4 KiB among its
    sizes, and the size and number of forks from KB and FORKS."""
    with open(os.path.join(peers, "c-floor", "limits.c")) as f:
        src = f.read()
    edits = [
        ("long kbs[]={256,", "long kbs[]={4,256,"),
        ("for(int k=0;do_fork&&k<4;k++){",
         'for(int k=0;do_fork&&k<5;k++){ if(getenv("KB")&&kbs[k]!=atol(getenv("KB")))continue;'),
        ("int N=200;", 'int N=getenv("FORKS")?atoi(getenv("FORKS")):200;'),
        ("m[o]=m[o];", "((volatile char*)m)[o]=m[o];"),
    ]
    return compile_edited(src, edits, os.path.join(res, "limits-restart.c"))


def compile_edited(src, edits, path):
    for old, new in edits:
        if src.count(old) != 1:
            fail(f"limits.c has changed: `{old}` is not in it once; the C floor could not be made")
        src = src.replace(old, new)
    with open(path, "w") as f:
        f.write(src)
    exe = path[:-2]
    r = subprocess.run(["gcc", "-O2", "-w", path, "-o", exe], capture_output=True, text=True)
    if r.returncode != 0:
        fail(f"gcc could not build the C floor: {r.stderr.strip()[-400:]}")
    return exe


def run_c_restart(exe, size, count):
    env = dict(os.environ, KB=str(size // 1024), FORKS=str(count))
    out = run(["chrt", "-r", "60", exe, "fork"], env=env)
    for line in out.splitlines():
        d = kv(line)
        if line.startswith("fork+touch") and int(d["rss_kb"]) * 1024 == size:
            return float(d["median_us"]), None, float(d["max_us"])
    fail(f"the C floor printed no fork figure for {size // 1024} KiB: {out!r}")


# The machine as s3res-bench describes it in its rows (CPU model, cores, kernel, load): the
# first s3res run's, recorded with the run (a VM's host can change between two runs).
MACHINE = []


def note_machine(row):
    if not MACHINE and row.get("machine"):
        MACHINE.append(row["machine"])


def run_s3res_restart(bench, extra, size, count):
    cmd = [bench, "restart", "--setup", "rr-pinned", "--size", str(size), "--count", str(count),
           "--json", "--quiet"] + extra
    for line in run(cmd).splitlines():
        if line.startswith("{"):
            d = json.loads(line)
            if d.get("size") == size:
                note_machine(d)
                return d["median_us"], d["p99_us"], d["max_us"]
    fail(f"s3res-bench printed no restart row for {size} bytes")


def run_orig_restart(test_dir, kills):
    """S³RES's own restart time (VoterM's timer, its ~230 KB replicas): TMR, SIGKILL of a random
    live replica `kills` times, as compare.sh's recovery runs at a 2 ms timeout."""
    cmd = ["./GEVoteTest", "-v", "VoterM", "-r", "TMR", "-s", "8", "-t", "2000", "-p", "60",
           "-w", "500", "-K", str(kills), "-G", "0"]
    times = [float(m.group(1)) for m in re.finditer(r"voterm_usec restart \(([\d.]+)\)", run(cmd, cwd=test_dir))]
    if not times:
        fail("GEVoteTest's VoterM printed no restart time")
    times.sort()
    return statistics.median(times), None, times[-1]


def run_c(exe, level, size, count):
    env = dict(os.environ, ITERS=str(count), LEVEL=str(level), SIZE=str(size))
    out = run(["chrt", "-r", "60", exe, "roundtrip"], env=env)
    for line in out.splitlines():
        d = kv(line)
        if line.startswith("roundtrip") and int(d["replicas"]) == level and int(d["size"]) == size:
            return float(d["median_us"]), float(d["p99_us"]), float(d["max_us"])
    fail(f"the C floor printed no round trip for level {level}, size {size}: {out!r}")


def run_s3res(bench, setup, extra, level, size, count, warmup):
    cmd = [bench, "echo", "--setup", setup, "--replicas", str(level), "--size", str(size),
           "--count", str(count), "--warmup", str(warmup), "--json", "--quiet"] + extra
    for line in run(cmd).splitlines():
        if line.startswith("{"):
            d = json.loads(line)
            if d.get("replicas") == level and d.get("size") == size:
                if d.get("faults"):
                    fail(f"s3res reported {d['faults']} fault events in a fault-free run: {line}")
                note_machine(d)
                return d["median_us"], d["p99_us"], d["max_us"]
    fail(f"s3res-bench printed no row for level {level}, size {size}")


def run_orig(test_dir, level, size, count, warmup):
    cmd = ["./GEVoteTest", "-v", "VoterM", "-r", LEVEL_NAMES[level], "-s", str(size),
           "-n", str(count), "-w", str(warmup), "-t", "20000", "-p", "60"]
    out = run(cmd, cwd=test_dir)
    for line in out.splitlines():
        if line.startswith("s3res_orig_rtt"):
            d = kv(line)
            lost = int(d.get("lost", 0))
            if lost:
                # Its watchdog fired in a fault-free run: the run is kept, marked, and its
                # pair left out of the table (which says how many were).
                print(f"S³RES lost {lost} rounds in a fault-free run (pair left out): {line}",
                      file=sys.stderr)
            return float(d["median_us"]), float(d["p99_us"]), float(d.get("max_us", "nan")), lost
    fail(f"GEVoteTest printed no round trip for {LEVEL_NAMES[level]}, size {size}")


# --- statistics ----------------------------------------------------------------------------------

def median_ci(xs, level=0.95):
    """The median of `xs` and a distribution-free confidence interval for it: the order
    statistics x(k), x(n+1-k) with the largest k for which P(Binomial(n, 1/2) < k) <= (1-level)/2.
    None for the interval when n is too small to have one (n < 6 at 95 %)."""
    xs = sorted(xs)
    n = len(xs)
    med = statistics.median(xs)
    tail = (1 - level) / 2
    k, below = 0, 0.0
    while True:
        below_next = below + math.comb(n, k) / 2**n  # P(B <= k) = P(B < k + 1)
        if below_next > tail:
            break
        below, k = below_next, k + 1
    if k == 0:
        return med, None
    return med, (xs[k - 1], xs[n - k])


def table(res):
    with open(os.path.join(res, "meta.json")) as f:
        meta = json.load(f)
    with open(os.path.join(res, "runs.jsonl")) as f:
        runs = [json.loads(line) for line in f]
    restart = meta.get("what", "roundtrip") == "restart"
    impls = ["c", "s3res"] + (["orig"] if meta["with_orig"] else [])
    # Each ratio: s3res over another implementation, and issue 15's target for it.
    if restart:
        targets = [("c", "C fork + write", TARGET_RESTART_C)]
        if meta["with_orig"]:
            targets.append(("orig", "S³RES", TARGET_RESTART_ORIG))
    else:
        targets = [("c", "C", TARGET_C)]
        if meta["with_orig"]:
            across = meta["placement"] != "one-cpu"
            targets.append(("orig", "S³RES", TARGET_ORIG_ACROSS if across else TARGET_ORIG))
    by = {}
    # A run that lost rounds (S³RES's watchdog fired with no fault) was not fault-free: its
    # pair is left out of its cell, and counted below the table.
    lossy = {}
    for r in runs:
        if r.get("lost"):
            lossy.setdefault((r["level"], r["size"]), set()).add(r["pair"])
    for r in runs:
        if r["pair"] not in lossy.get((r["level"], r["size"]), ()):
            by.setdefault((r["level"], r["size"]), {}).setdefault(r["pair"], {})[r["impl"]] = r["median_us"]
    what = ("restart, detection → ready (s3res, rr-pinned TMR ballast); C: fork + write every page "
            "of the same size; S³RES: VoterM's own restart time, its own replicas" if restart
            else f"round trip, placement {meta['placement']}")
    out = [
        f"Paired runs of the {what}: commit {meta['commit']}, {meta['pairs']} pairs of "
        f"{meta['count']} {'restarts' if restart else 'rounds'} per run, seed {meta['seed']}, "
        f"idle CPUs {meta['cpu_idle']}, journal {meta.get('journal', 'on')}, {meta['started']} to {meta.get('ended', '(interrupted)')}"
        + (f"; {meta['machine']}." if "machine" in meta else "."),
        "",
        "Per cell: each implementation's median of its per-run medians (µs); the median over "
        "pairs of s3res's ratio to the other, with a 95 % confidence interval, and how many "
        "pairs were within issue 15's target.",
        "",
    ]
    names = {"c": "C", "s3res": "s3res", "orig": "S³RES"}
    # With S³RES: the C floor's own ratio to it, in the same pairs — how far below S³RES
    # anything can get on this host, and so whether a target against S³RES is reachable.
    floor = [("C / S³RES", "c", "orig")] if meta["with_orig"] else []
    out.append("| " + ("size" if restart else "level | size") + " | "
               + " | ".join(names[i] for i in impls) + " | "
               + " | ".join(f"s3res / {name} (≤ {t})" for _, name, t in targets)
               + "".join(f" | {title}" for title, _, _ in floor) + " |")
    out.append("|" + ("---|" if restart else "---|--:|") + "--:|" * len(impls)
               + "---|" * (len(targets) + len(floor)))
    for (level, size) in sorted(by):
        pairs = [p for p in by[(level, size)].values() if all(i in p for i in impls)]
        if not pairs:
            continue
        size_s = size_label(size)
        row = "| " + (size_s if restart else f"{LEVEL_NAMES[level]} | {size_s}") + " |"
        for i in impls:
            row += f" {statistics.median(p[i] for p in pairs):.1f} |"
        for other, _, target in targets:
            ratios = [p["s3res"] / p[other] for p in pairs]
            med, ci = median_ci(ratios)
            within = sum(r <= target for r in ratios)
            ci_s = f"{ci[0]:.2f}–{ci[1]:.2f}" if ci else "no interval below 6 pairs"
            row += f" **{med:.2f}** ({ci_s}); {within}/{len(ratios)} |"
        for _, num, den in floor:
            med, ci = median_ci([p[num] / p[den] for p in pairs])
            row += f" {med:.2f} ({ci[0]:.2f}–{ci[1]:.2f}) |" if ci else f" {med:.2f} |"
        out.append(row)
    for (level, size), pairs in sorted(lossy.items()):
        out.append("")
        out.append(f"Left out of {LEVEL_NAMES[level]} {size_label(size)}: {len(pairs)} pair(s) in which S³RES "
                   f"lost rounds without a fault (pairs {', '.join(map(str, sorted(pairs)))}).")
    return "\n".join(out)


def size_label(size):
    return (f"{size >> 20} MiB" if size >= 1 << 20 and size % (1 << 20) == 0
            else f"{size >> 10} KiB" if size >= 1024 else f"{size} B")


def write_meta(res, meta):
    with open(os.path.join(res, "meta.json"), "w") as f:
        json.dump(meta, f, indent=1)


def parse_size(text):
    text = text.strip().lower()
    scale = {"k": 1024, "m": 1024 * 1024}.get(text[-1:], 1)
    try:
        return int(text[:-1] if scale > 1 else text) * scale
    except ValueError:
        usage_error(f"--sizes: `{text}` is not a size (a number of bytes, or with k or m)")


# --- main ----------------------------------------------------------------------------------------

def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--what", choices=["roundtrip", "restart"], default="roundtrip",
                    help="roundtrip (default): round trips per level and size; restart: detection → ready per state size, "
                         "against the C fork + write floor of that size and S³RES's own restart")
    ap.add_argument("--pairs", type=int, default=30, help="pairs per cell (default 30)")
    ap.add_argument("--count", type=int, default=None,
                    help="per run: measured rounds (default 3000), or restarts and floor forks (default 20; S³RES: 10 kills)")
    ap.add_argument("--warmup", type=int, default=500, help="round trip: rounds before measuring, s3res and S³RES (default 500; the C floor's is its own 1000)")
    ap.add_argument("--placement", choices=sorted(PLACEMENTS), default="one-cpu",
                    help="round trip: one-cpu (default), everything on CPU 0 (s3res rr-one-cpu); pinned: client and voter on CPU 0, "
                         "replicas on CPU 1 (rr-pinned). Restarts are always rr-pinned, as compare.sh's")
    ap.add_argument("--sizes", default=None,
                    help="round trip: frame sizes of those limits.c knows, 8 and 4096 (default both); "
                         "restart: state sizes of 4k, 256k, 1m, 8m, 64m (default 4k,256k)")
    ap.add_argument("--levels", default="1,2,3", help="round trip: replication levels (default 1,2,3)")
    ap.add_argument("--seed", type=int, default=None, help="seed of the run order (printed)")
    ap.add_argument("--no-s3res-orig", action="store_true", help="leave S³RES out (the C floor and s3res only)")
    ap.add_argument("--components", default=None, help="s3res-bench --component-dir (e.g. the musl `replica` build)")
    ap.add_argument("--no-journal", action="store_true",
                    help="s3res's voters without their journal (s3res-bench --no-journal): like for like with the peers, which keep none")
    ap.add_argument("--cpu-idle", choices=["all", "halt"], default=None,
                    help="all: keep idle CPUs polling for the whole run (/dev/cpu_dma_latency, root), as compare-peers.sh "
                         "CPU_IDLE=all; halt: as the machine is (default: all where writable)")
    ap.add_argument("--peers", default=os.path.join(ROOT, "..", "shared", "peers"), help="the peer tooling (default ../shared/peers)")
    ap.add_argument("--bin-dir", default=os.path.join(ROOT, "target", "release"), help="s3res-bench's folder (default target/release)")
    ap.add_argument("--res", default=None, help="results folder (default target/s3res-peer/paired/<UTC time>)")
    ap.add_argument("--table", metavar="RES_DIR", default=None, help="print the table from saved results and exit")
    args = ap.parse_args()
    if args.table:
        if not os.path.isfile(os.path.join(args.table, "meta.json")):
            usage_error(f"--table: no meta.json in {args.table}")
        print(table(args.table))
        return

    restart = args.what == "restart"
    sizes = [parse_size(x) for x in (args.sizes or ("4k,256k" if restart else "8,4096")).split(",")]
    levels = [3] if restart else [int(x) for x in args.levels.split(",")]
    count = args.count or (20 if restart else 3000)
    if restart and any(x not in RESTART_SIZES for x in sizes):
        usage_error("--sizes: the C fork floor measures 4k, 256k, 1m, 8m and 64m only")
    if not restart and any(x not in (8, 4096) for x in sizes):
        usage_error("--sizes: the C floor measures round trips of 8 and 4096 bytes only")
    if any(x not in LEVEL_NAMES for x in levels):
        usage_error("--levels: 1, 2 or 3")
    if args.pairs < 1 or count < (5 if restart else 100):
        usage_error(f"--pairs at least 1, --count at least {5 if restart else 100}")
    if os.geteuid() != 0:
        usage_error("needs root: every implementation runs under SCHED_RR")
    peers = os.path.abspath(args.peers)
    if not os.path.isfile(os.path.join(peers, "c-floor", "limits.c")):
        usage_error(f"no peer tooling at {peers} (expected c-floor/limits.c; --peers DIR)")
    bench = os.path.join(os.path.abspath(args.bin_dir), "s3res-bench")
    if not os.access(bench, os.X_OK):
        usage_error(f"no {bench}; run cargo build --release first")
    placement = "pinned" if restart else args.placement
    setup, _, orig_variant = PLACEMENTS[placement]
    with_orig = not args.no_s3res_orig
    peer_out = os.path.join(ROOT, "target", "s3res-peer")
    test_dir = os.path.join(peer_out, orig_variant, "test")
    if with_orig and not os.access(os.path.join(test_dir, "GEVoteTest"), os.X_OK):
        print("paired-ratios.py: building S³RES (../shared/peers/s3res/build.sh)", file=sys.stderr)
        os.makedirs(peer_out, exist_ok=True)
        r = subprocess.run(["bash", os.path.join(peers, "s3res", "build.sh")], cwd=peer_out,
                           env=dict(os.environ, OUT=peer_out), capture_output=True, text=True)
        if r.returncode != 0 or not os.access(os.path.join(test_dir, "GEVoteTest"), os.X_OK):
            fail(f"S³RES could not be built (or use --no-s3res-orig): {r.stderr.strip()[-400:]}")

    seed = args.seed if args.seed is not None else int(time.time_ns() % (1 << 63))
    print(f"seed = {seed}", file=sys.stderr)
    rng = random.Random(seed)
    res = os.path.abspath(args.res or os.path.join(
        peer_out, "paired", time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())))
    os.makedirs(res, exist_ok=True)
    signal.signal(signal.SIGINT, kill_all_sessions)
    signal.signal(signal.SIGTERM, kill_all_sessions)

    cpu_idle = args.cpu_idle or ("all" if os.access("/dev/cpu_dma_latency", os.W_OK) else "halt")
    qos = None
    if cpu_idle == "all":
        try:
            # Held until the script exits: the kernel drops the request when the fd closes.
            qos = open("/dev/cpu_dma_latency", "wb", buffering=0)
            qos.write(b"\0\0\0\0")
        except OSError as e:
            fail(f"--cpu-idle all: could not write /dev/cpu_dma_latency: {e}")

    c_exe = build_c_restart_floor(peers, res) if restart else build_c_floor(peers, placement, res)
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    meta = {
        "what": args.what, "commit": commit, "placement": placement, "pairs": args.pairs,
        "count": count, "warmup": args.warmup, "seed": seed, "cpu_idle": cpu_idle,
        "with_orig": with_orig, "components": args.components,
        "journal": "off" if args.no_journal else "on", "sizes": sizes, "levels": levels,
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "load_start": open("/proc/loadavg").read().split()[:3],
    }
    # Written now and again at the end, so that an interrupted run's pairs can still be read
    # with --table.
    write_meta(res, meta)

    s3res_extra = (["--component-dir", args.components] if args.components else []) + (
        ["--no-journal"] if args.no_journal else [])

    def measure(impl, level, size):
        if restart:
            if impl == "c":
                return run_c_restart(c_exe, size, count)
            if impl == "s3res":
                return run_s3res_restart(bench, s3res_extra, size, count)
            return run_orig_restart(test_dir, ORIG_KILLS)
        if impl == "c":
            return run_c(c_exe, level, size, count)
        if impl == "s3res":
            return run_s3res(bench, setup, s3res_extra, level, size, count, args.warmup)
        return run_orig(test_dir, level, size, count, args.warmup)

    cells = [(lv, x) for lv in levels for x in sizes]
    impls = ["c", "s3res"] + (["orig"] if with_orig else [])
    with open(os.path.join(res, "runs.jsonl"), "w") as runs:
        for pair in range(1, args.pairs + 1):
            print(f"pair {pair}/{args.pairs} {time.strftime('%H:%M:%S')}", file=sys.stderr)
            order = cells[:]
            rng.shuffle(order)
            for level, size in order:
                turn = impls[:]
                rng.shuffle(turn)
                for impl in turn:
                    stolen = steal_ms()
                    m = measure(impl, level, size)
                    row = {"pair": pair, "level": level, "size": size, "impl": impl,
                           "median_us": m[0], "p99_us": m[1], "max_us": m[2]}
                    after = steal_ms()
                    if stolen is not None and after is not None:
                        # What the host took from this VM's CPUs during the run (0 on bare
                        # metal): a max_us of ~100 ms beside it is the host's.
                        row["steal_ms"] = after - stolen
                    if len(m) > 3 and m[3]:
                        row["lost"] = m[3]
                    runs.write(json.dumps(row) + "\n")
                    runs.flush()
                    if MACHINE and "machine" not in meta:
                        meta["machine"] = MACHINE[0]
                        write_meta(res, meta)
    meta["ended"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    meta["load_end"] = open("/proc/loadavg").read().split()[:3]
    write_meta(res, meta)
    if qos:
        qos.close()
    print(f"raw results in {res}", file=sys.stderr)
    print(table(res))


if __name__ == "__main__":
    main()
