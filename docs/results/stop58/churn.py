"""Stop 58: a threaded stateful program (threaded.py, a running sum) under TMR, fed LINES
lines at HZ; replica 1 SIGKILLed 2 s in. Counts what the voter did after: restarts of
`sum`, faults, `diverged` events; whether bootstrap succeeded and every sum was right.
usage: churn.py BIN_DIR LABEL RUNS LINES HZ"""
import json, os, signal, subprocess, sys, time

bin_dir, label, runs, lines, hz = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
here = os.path.dirname(os.path.abspath(__file__))
for k in range(runs):
    d = os.path.join(here, f"run-{label}-{k}")
    os.makedirs(d, exist_ok=True)
    sums = os.path.join(d, "sums.txt")
    if os.path.exists(sums):
        os.remove(sums)
    desc = {
        "name": "churn",
        "components": {
            "feed": {"exec": "/usr/bin/python3", "args": [f"{here}/feed.py", str(lines), str(hz)]},
            "sum": {"exec": "/usr/bin/python3", "args": ["-u", f"{here}/threaded.py"],
                    "runtime": "preload", "framing": "lines", "redundancy": "tmr", "timeout_us": 300000},
            "collect": {"exec": "/usr/bin/python3", "args": [f"{here}/collect.py", sums]},
        },
        "channels": [{"from": "feed.out", "to": "sum.in"}, {"from": "sum.out", "to": "collect.in"}],
    }
    path = os.path.join(d, "system.json")
    with open(path, "w") as f:
        json.dump(desc, f)
    ev = os.path.join(d, "events.jsonl")
    env = dict(os.environ, PATH=bin_dir + ":" + os.environ["PATH"])
    t0 = time.time()
    p = subprocess.Popen([bin_dir + "/s3res-bootstrap", "-q", "--events", ev, path], cwd=d, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    victim = None
    while time.time() - t0 < 20 and victim is None:
        time.sleep(0.1)
        if time.time() - t0 < 2:
            continue
        try:
            starts = [json.loads(l) for l in open(ev) if '"start"' in l]
        except OSError:
            continue
        ones = [e["pid"] for e in starts if e.get("component") == "sum" and e.get("replica") == 1]
        if ones:
            victim = ones[-1]
            os.kill(victim, signal.SIGKILL)
    try:
        _, err = p.communicate(timeout=lines / hz + 60)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        _, err = p.communicate()
    events = [json.loads(l) for l in open(ev)]
    rec = [e for e in events if e["kind"] == "recovery" and e["component"] == "sum"]
    faults = [e for e in events if e["kind"] in ("sdc", "crash", "hang", "protocol")]
    div = [e for e in events if e["kind"] == "diverged"]
    got = open(sums).read().split() if os.path.exists(sums) else []
    right = all(int(v) == (i + 1) * (i + 2) // 2 for i, v in enumerate(got))
    last = [l for l in err.decode(errors="replace").splitlines() if "failed beyond recovery" in l][:1]
    print(json.dumps({"label": label, "run": k, "exit": p.returncode, "restarts": len(rec),
                      "exec": sum(1 for e in rec if e.get("method") == "exec"),
                      "faults": len(faults), "diverged": len(div), "sums": len(got), "of": lines,
                      "all_right": right, "secs": round(time.time() - t0, 1), "failed": last}))
