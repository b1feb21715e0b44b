#!/usr/bin/env python3
"""voter-restart.py — how long a voter restart takes, and that it loses nothing.

Runs s3res-bootstrap on a stateful TMR echo (source -> echo -> sink) and SIGKILLs the echo's
voter KILLS times (with --stream: a stateful TMR `s3res-batch --vary` in stream mode instead,
whose successor voters take the replicas' kept frames again), at seeded random moments, 120-320 ms apart (within the default restart
budget, 10 within 1 s). Prints, from the `voter_restart` events, the time from bootstrap seeing
the voter gone to its successor having adopted the replicas (median, p99, max), how many
restarts found an unfinished round to replay, and the sink's verdict (every frame once, in
order, the echo's count continuous).

With --preload PROGRAM (c, awk or python) the component is an unmodified program instead,
protected with the preload library ("runtime": "preload"): a running sum of the numbers it
reads, one line out per line in. Its voter parks the replicas' pipes, and each successor takes
them over (docs/architecture.md, "An unmodified program's voter"); a collector checks every
sum once, in order, continuous.

usage: scripts/voter-restart.py [--kills N] [--work-us US | --stream | --preload PROGRAM]
                               [--hz HZ] [--seed S] [--bin-dir DIR]

Needs the release binaries (cargo build --release). Run it on a quiet machine: it measures.
"""

import argparse
import json
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=200, help="voter kills (default 200)")
    ap.add_argument("--work-us", type=int, default=500,
                    help="computation per frame in each replica, us (default 500)")
    ap.add_argument("--stream", action="store_true",
                    help="a stream component (s3res-batch --every 8 --vary --stateful) instead of the echo")
    ap.add_argument("--preload", choices=["c", "awk", "python"], default=None,
                    help="an unmodified program (a running sum) instead of the echo")
    ap.add_argument("--hz", type=int, default=None,
                    help="source rate (default: 1 kHz, or what the echo's work allows)")
    ap.add_argument("--seed", type=int, default=None, help="seed of the kill times (printed)")
    ap.add_argument("--bin-dir", default=os.path.join(os.path.dirname(__file__), "..", "target", "release"))
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else int(time.time_ns() % (1 << 63))
    print(f"seed = {seed}")
    rng = random.Random(seed)
    bins = os.path.abspath(args.bin_dir)
    bootstrap = os.path.join(bins, "s3res-bootstrap")
    if not os.access(bootstrap, os.X_OK):
        sys.exit(f"voter-restart.py: no {bootstrap}; run cargo build --release first")

    # A rate the three replicas keep up with on two cores (1 kHz at most), and enough frames
    # for every kill (at most ~320 ms apart) with some to spare.
    hz = args.hz or (2000 if args.preload else min(1000, 500_000 // max(args.work_us, 1)))
    if hz < 1:
        sys.exit("voter-restart.py: --hz must be at least 1")
    count = int((args.kills * 0.33 + 3) * hz)
    with tempfile.TemporaryDirectory(prefix="s3res-voter-restart-") as tmp:
        summary = os.path.join(tmp, "summary.json")
        events = os.path.join(tmp, "events.jsonl")
        desc = {
            "name": "voter-restart",
            "components": {
                "source": {"exec": "s3res-source", "args": ["--count", str(count), "--hz", str(hz)]},
                "echo": ({"exec": "s3res-batch", "args": ["--every", "8", "--vary", "--stateful"],
                          "mode": "stream", "redundancy": "tmr", "timeout_us": 200000}
                         if args.stream else
                         {"exec": "s3res-echo", "args": ["--stateful", "--work-us", str(args.work_us)],
                          "redundancy": "tmr", "timeout_us": 200000}),
                "sink": {"exec": "s3res-sink",
                         "args": ["--stateful", "--expect", str(count), "--summary", summary]},
            },
            "channels": [
                {"from": "source.out", "to": "echo.in"},
                {"from": "echo.out", "to": "sink.in"},
            ],
        }
        if args.preload:
            desc = preload_system(tmp, args.preload, count, hz, summary)
        path = os.path.join(tmp, "system.json")
        with open(path, "w") as f:
            json.dump(desc, f)
        # stderr to a file, not a pipe nobody reads while the kills go on: a full pipe would
        # block bootstrap and the voters on their next log line.
        err_path = os.path.join(tmp, "stderr.log")
        with open(err_path, "w") as err_file:
            run = subprocess.Popen([bootstrap, "--events", events, path],
                                   stdout=subprocess.DEVNULL, stderr=err_file,
                                   start_new_session=True)
            try:
                kills = kill_voters(run.pid, args.kills, rng)
                run.wait(timeout=count / hz + 60)
            finally:
                if run.poll() is None:
                    os.killpg(run.pid, signal.SIGKILL)
                    run.wait()
        with open(err_path) as f:
            err = f.read()
        restarts = []
        with open(events) as f:
            for line in f:
                e = json.loads(line)
                if e.get("kind") == "voter_restart":
                    restarts.append(e)
        try:
            with open(summary) as f:
                sink = json.load(f)
        except (OSError, ValueError):
            sink = {"ok": False, "error": "no summary: the sink did not finish"}

    took = sorted(e["recovery_us"] for e in restarts)
    if args.preload:
        staged = sum(1 for e in restarts if "lines: 0 in staging" not in e.get("detail", ""))
        ahead = sum(1 for e in restarts if ", 0 given before" not in e.get("detail", ""))
        to_take = sum(1 for e in restarts if ", 0 answers of committed" not in e.get("detail", ""))
        print(f"preload: {staged} restarts found a line in a staging pipe, {ahead} found lines of "
              f"the unfinished round given already, {to_take} found answers of committed rounds "
              f"still to take")
    replayed = sum(1 for e in restarts if " 0 bytes of input replayed" not in e.get("detail", ""))
    print(f"bootstrap exit status {run.returncode}; {kills} kills, {len(restarts)} voter_restart events, "
          f"{replayed} replayed input taken since the last commit")
    if took:
        p99 = took[min(len(took) - 1, int(round(0.99 * (len(took) - 1))))]
        print(f"voter restart (gone -> adopted), us: median {statistics.median(took):.0f}  "
              f"p99 {p99}  max {took[-1]}  (n={len(took)})")
    print("sink: " + ", ".join(f"{k} {sink.get(k)}" for k in
                                ["frames", "missing", "duplicated", "reordered", "corrupt", "state_breaks", "ok", "error"]
                                if k in sink))
    ok = run.returncode == 0 and len(restarts) == kills and sink.get("ok") is True
    if not ok:
        log = os.path.abspath("voter-restart-failed.log")
        with open(log, "w") as f:
            f.write(err)
        print(err[-3000:], file=sys.stderr)
        print(f"bootstrap's whole stderr: {log}", file=sys.stderr)
    sys.exit(0 if ok else 1)


PROGRAMS = {
    "awk": None,  # found on PATH below
    "python": "import sys\ntotal = 0\nfor line in sys.stdin:\n    total += int(line)\n    print(total)\n",
    "c": "#include <stdio.h>\n#include <stdlib.h>\nint main(void){char l[256];long long s=0;"
         "while(fgets(l,sizeof l,stdin)){s+=atoll(l);printf(\"%lld\\n\",s);}return 0;}\n",
}


def preload_system(tmp, program, count, hz, summary):
    """feed -> sum (the unmodified program, TMR, preload) -> collect."""
    py = sys.executable
    sums = os.path.join(os.path.dirname(os.path.abspath(__file__)), "sums")
    if program == "awk":
        awk = shutil.which("awk") or sys.exit("voter-restart.py: no awk")
        version = subprocess.run([awk, "-W", "version"], capture_output=True, text=True,
                                 stdin=subprocess.DEVNULL).stdout
        args = (["-W", "interactive"] if "mawk" in version else []) + ["{ s += $1; printf \"%.0f\\n\", s }"]
        exe = awk
    elif program == "python":
        path = os.path.join(tmp, "count.py")
        with open(path, "w") as f:
            f.write(PROGRAMS["python"])
        exe, args = py, ["-u", path]
    else:
        src, exe = os.path.join(tmp, "sum.c"), os.path.join(tmp, "sum")
        with open(src, "w") as f:
            f.write(PROGRAMS["c"])
        subprocess.run(["cc", "-O1", "-o", exe, src], check=True)
        args = []
    return {
        "name": "voter-restart-preload",
        "components": {
            "feed": {"exec": py, "args": [os.path.join(sums, "feed.py"), str(count), str(hz)]},
            "sum": {"exec": exe, "args": args, "runtime": "preload", "framing": "lines",
                    "redundancy": "tmr", "timeout_us": 300000},
            "collect": {"exec": py, "args": [os.path.join(sums, "collect.py"),
                                             os.path.join(tmp, "sums.txt"), summary, str(count)]},
        },
        "channels": [
            {"from": "feed.out", "to": "sum.in"},
            {"from": "sum.out", "to": "collect.in"},
        ],
    }


def voter_of(bootstrap):
    """The pid of bootstrap's s3res-voter child, if there is one."""
    try:
        with open(f"/proc/{bootstrap}/task/{bootstrap}/children") as f:
            kids = [int(p) for p in f.read().split()]
    except OSError:
        return None
    for pid in kids:
        try:
            with open(f"/proc/{pid}/comm") as f:
                if f.read().strip() == "s3res-voter":
                    return pid
        except OSError:
            continue
    return None


def kill_voters(bootstrap, kills, rng):
    """SIGKILLs the voter `kills` times, each 120-320 ms after its successor appeared."""
    done = 0
    last = None
    deadline = time.monotonic() + 30
    while done < kills:
        pid = voter_of(bootstrap)
        if pid is None or pid == last:
            if time.monotonic() > deadline:
                print(f"no voter to kill after {done} kills", file=sys.stderr)
                break
            time.sleep(0.002)
            continue
        time.sleep(0.120 + rng.random() * 0.200)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            continue
        last = pid
        done += 1
        deadline = time.monotonic() + 30
    return done


if __name__ == "__main__":
    main()
