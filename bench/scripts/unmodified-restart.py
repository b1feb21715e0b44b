#!/usr/bin/env python3
"""Restart time of unmodified programs against linked ones, from the voter's own events.

For each program — awk, python3 -u and a C filter (unmodified, `runtime: preload`), and the
Rust `s3res-running-mean` and the C `running_mean` example (linked) — runs a TMR system fed
at 200 Hz, SIGKILLs a replica KILLS times (each after the previous recovery), and prints the
median, p99 and max of `recovery_us` (the voter's detection -> the new replica's Ready) of the
recoveries by fork.

    cargo build --release && python3 bench/scripts/unmodified-restart.py [KILLS]

Needs python3, awk and cc. Everything runs in a temp dir; every process is stopped at the end.
"""
import json, os, random, shutil, signal, subprocess, sys, tempfile, time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BIN = os.path.join(ROOT, "target", "release")
KILLS = int(sys.argv[1]) if len(sys.argv) > 1 else 30
random.seed(1)

FEED = r'''
import os, struct, sys, time
kind, n, hz = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
t0 = time.monotonic()
for k in range(1, n + 1):
    b = str(k).encode() if kind == 'text' else struct.pack('<d', float(k))
    os.write(3, struct.pack('<I', len(b)) + b)
    d = t0 + k / hz - time.monotonic()
    if d > 0:
        time.sleep(d)
'''
SUM_C = r'''
#include <stdio.h>
#include <stdlib.h>
int main(void) {
    char line[256]; long long sum = 0;
    while (fgets(line, sizeof line, stdin)) { sum += atoll(line); printf("%lld\n", sum); }
    return 0;
}
'''


def programs(d):
    awk = shutil.which("awk")
    mawk = "mawk" in subprocess.run([awk, "-W", "version"], capture_output=True, text=True).stdout
    awk_args = (["-W", "interactive"] if mawk else []) + ["{ s += $1; print s; fflush() }"]
    with open(os.path.join(d, "count.py"), "w") as f:
        f.write("import sys\nt = 0\nfor l in sys.stdin:\n    t += int(l)\n    print(t)\n")
    with open(os.path.join(d, "sum.c"), "w") as f:
        f.write(SUM_C)
    subprocess.run(["cc", "-O2", "-o", os.path.join(d, "sum"), os.path.join(d, "sum.c")], check=True)
    c_mean = os.path.join(d, "c_mean")
    subprocess.run(["cc", "-O2", "-I", os.path.join(ROOT, "replica-c", "include"), "-o", c_mean,
                    os.path.join(ROOT, "examples", "c-running-mean", "running_mean.c"),
                    os.path.join(BIN, "libs3res_replica_c.a"), "-lpthread", "-ldl", "-lm"], check=True)
    pre = {"runtime": "preload", "framing": "lines"}
    return [
        ("awk (preload)", "text", dict(exec=awk, args=awk_args, **pre), "in", "out"),
        ("python3 -u (preload)", "text", dict(exec="/usr/bin/python3", args=["-u", os.path.join(d, "count.py")], **pre), "in", "out"),
        ("C filter (preload)", "text", dict(exec=os.path.join(d, "sum"), args=[], **pre), "in", "out"),
        ("Rust running mean (replica-rt)", "f64", dict(exec=os.path.join(BIN, "s3res-running-mean"), args=[]), "samples", "mean"),
        ("C running mean (libs3res_replica_c)", "f64", dict(exec=c_mean, args=[]), "samples", "mean"),
    ]


def pids_of(events, comp):
    pids = {}
    for e in events:
        if e.get("component") != comp:
            continue
        if e["kind"] == "start":
            pids[e["replica"]] = e["pid"]
        elif e["kind"] == "recovery":
            pids[e["replica"]] = e["new_pid"]
    return pids


def read_events(path):
    try:
        with open(path) as f:
            return [json.loads(l) for l in f if l.strip().endswith("}")]
    except FileNotFoundError:
        return []


def measure(d, name, kind, comp, inp, out):
    desc = {
        "name": "restart",
        "components": {
            "feed": {"exec": sys.executable, "args": [os.path.join(d, "feed.py"), kind, "100000", "200"]},
            "c": dict(comp, redundancy="tmr", timeout_us=300000),
        },
        "channels": [{"from": "feed.out", "to": "c." + inp}, {"from": "c." + out, "to": "stdout"}],
    }
    sysfile = os.path.join(d, "system.json")
    with open(sysfile, "w") as f:
        json.dump(desc, f)
    ev = os.path.join(d, "events.jsonl")
    if os.path.exists(ev):
        os.remove(ev)
    p = subprocess.Popen([os.path.join(BIN, "s3res-bootstrap"), "--events", ev, sysfile],
                         cwd=d, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
    try:
        time.sleep(1.5)
        took = []
        for _ in range(KILLS):
            events = read_events(ev)
            slot = random.randrange(3)
            pid = pids_of(events, "c")[slot]
            os.kill(pid, signal.SIGKILL)
            deadline = time.monotonic() + 10
            rec = None
            while rec is None and time.monotonic() < deadline:
                time.sleep(0.01)
                rec = next((e for e in read_events(ev) if e["kind"] == "recovery" and e.get("pid") == pid), None)
            if rec is None:
                raise SystemExit(f"{name}: no recovery of pid {pid}")
            if rec.get("method") == "fork":
                took.append(rec["recovery_us"])
            time.sleep(random.uniform(0.05, 0.15))
        took.sort()
        q = lambda f: took[min(len(took) - 1, int(f * len(took)))]
        print(f"| {name} | {len(took)} of {KILLS} | {q(0.5)} | {q(0.99)} | {took[-1]} |", flush=True)
    finally:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def main():
    with tempfile.TemporaryDirectory(prefix="s3res-restart-") as d:
        with open(os.path.join(d, "feed.py"), "w") as f:
            f.write(FEED)
        print("| program | by fork | median µs | p99 µs | max µs |")
        print("|---|---|---|---|---|")
        for name, kind, comp, inp, out in programs(d):
            measure(d, name, kind, comp, inp, out)


main()
