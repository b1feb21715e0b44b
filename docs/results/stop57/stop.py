import subprocess, time, os, signal, json, sys
def one(binary_dir, mode, k):
    ev = f"ev-{mode}-{k}.jsonl"
    env = dict(os.environ, PATH=binary_dir + ":" + os.environ["PATH"])
    p = subprocess.Popen([binary_dir + "/s3res-bootstrap", "--events", ev, "long.json"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, start_new_session=True)
    time.sleep(1.5)
    t = time.monotonic()
    if mode == "group":
        os.killpg(p.pid, signal.SIGTERM)
    else:
        os.kill(p.pid, signal.SIGTERM)
    _, err = p.communicate(timeout=30)
    dt = time.monotonic() - t
    err = err.decode(errors="replace")
    faults = 0
    for line in open(ev):
        e = json.loads(line)
        if e["kind"] in ("sdc", "crash", "hang", "protocol"):
            faults += 1
    try: os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError: pass
    return dt, p.returncode, "killing them" in err, faults, "not from bootstrap" in err, " failed: " in err
which, binary_dir = sys.argv[1], sys.argv[2]
for mode in ("bootstrap", "group"):
    rows = [one(binary_dir, mode, k) for k in range(int(sys.argv[3]))]
    dts = sorted(r[0] for r in rows)
    print(f"{which} SIGTERM to {mode}: stop s median {dts[len(dts)//2]:.3f} max {dts[-1]:.3f}; exit {sorted(set(r[1] for r in rows))}; "
          f"SIGKILLed after timeout {sum(r[2] for r in rows)}/{len(rows)}; runs with faults {sum(r[3]>0 for r in rows)}/{len(rows)} (faults {sum(r[3] for r in rows)}); "
          f"stray line {sum(r[4] for r in rows)}; 'failed' lines {sum(r[5] for r in rows)}")
