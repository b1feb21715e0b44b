#!/usr/bin/env python3
"""DMR campaign for s3res anomaly attribution (a measurement, not a test).

Usage: dmr-campaign.py BIN_DIR DIR MODEL INJECTIONS SEED
  BIN_DIR  built binaries (target/release)
  DIR      holds layout.json (the fields of s3res-signal's frames) and train.bin (a fault-free
           capture of `s3res-signal` at offset 0, see docs/anomaly-detection.md); MODEL is
           relative to DIR (trained on train.bin)
Runs source -> signal (DMR, detector on signal.out) -> stdout for up to 200 s at 200 Hz and,
every 0.1-0.3 s, flips one random bit (sigqueue SIGUSR2) of one random f64 field (x, y,
speed, odometer) in one random replica's next frame. Each flip is classified by whether it
moves the field by more than (a) the span of its normal frame-to-frame change and (b) its
value range in train.bin (the library's definition), and the voter's verdict is read from the
event log: attributed (sdc naming the injected replica, repaired by fork) or not."""
import ctypes, json, math, os, random, signal, struct, subprocess, sys, time

BIN = sys.argv[1]; DIR = sys.argv[2]; MODEL = sys.argv[3]; N = int(sys.argv[4]); SEED = int(sys.argv[5])
OFFSET, COUNT, HZ = 70000, 40000, 200
FIELDS = [("x", 8), ("y", 16), ("speed", 24), ("odometer", 32)]
LAYOUT = json.load(open(os.path.join(DIR, "layout.json")))
libc = ctypes.CDLL(None, use_errno=True)
SIGUSR2 = signal.SIGUSR2
rng = random.Random(SEED); print("seed", SEED)

def pos(t): return (50 + 20 * math.sin(t * 0.02), 30 + 10 * math.cos(t * 0.013))
def values(seq):
    odo = 0.0
    for s in range(seq + 1):
        t = float(s + OFFSET); x, y = pos(t); px, py = pos(t - 1.0)
        step = math.sqrt((x - px) ** 2 + (y - py) ** 2); odo += step
    return {"x": x, "y": y, "speed": step, "odometer": odo}

# Normal span of each field's change, from the training capture.
def frames(path):
    b = open(path, "rb").read(); i = 0
    while i < len(b):
        n = struct.unpack_from("<I", b, i)[0]; yield b[i + 4:i + 4 + n]; i += 4 + n
prev = None; lo = {}; hi = {}; vlo = {}; vhi = {}
for f in frames(os.path.join(DIR, "train.bin")):
    v = {name: struct.unpack_from("<d", f, off)[0] for name, off in FIELDS}
    for k in v: vlo[k] = min(vlo.get(k, v[k]), v[k]); vhi[k] = max(vhi.get(k, v[k]), v[k])
    if prev:
        for k in v:
            d = v[k] - prev[k]; lo[k] = min(lo.get(k, d), d); hi[k] = max(hi.get(k, d), d)
    prev = v
span = {k: hi[k] - lo[k] for k in lo}
vrange = {k: vhi[k] - vlo[k] for k in vlo}
print("normal span of change:", span); print("value range:", vrange)

desc = {"name": "campaign", "components": {
    "source": {"exec": f"{BIN}/s3res-source", "args": ["--count", str(COUNT), "--hz", str(HZ)]},
    "signal": {"exec": f"{BIN}/s3res-signal", "args": ["--offset", str(OFFSET)], "redundancy": "dmr", "timeout_us": 500000}},
    "channels": [{"from": "source.out", "to": "signal.in"},
                 {"from": "signal.out", "to": "stdout", "max_frame": 64, "fields": LAYOUT,
                  "detector": {"model": MODEL}}]}
json.dump(desc, open(os.path.join(DIR, "campaign.json"), "w"))
ev_path = os.path.join(DIR, "campaign-events.jsonl")
if os.path.exists(ev_path): os.remove(ev_path)
boot = subprocess.Popen([f"{BIN}/s3res-bootstrap", "--events", ev_path, os.path.join(DIR, "campaign.json")],
                        stdout=open(os.path.join(DIR, "campaign-out.bin"), "wb"), stderr=open(os.path.join(DIR, "campaign-err.txt"), "w"))
def events():
    try: return [json.loads(l) for l in open(ev_path) if l.strip()]
    except FileNotFoundError: return []
def pids():
    p = {}
    for e in events():
        if e["kind"] == "start": p[e["replica"]] = e["pid"]
        if e["kind"] == "recovery": p[e["replica"]] = e["new_pid"]
    return p
time.sleep(1.5)
results = []
for i in range(N):
    time.sleep(rng.uniform(0.1, 0.3))
    slot = rng.randrange(2); name, off = rng.choice(FIELDS); b = rng.randrange(64)
    before = len([e for e in events() if e["kind"] == "sdc"])
    pid = pids()[slot]
    if libc.sigqueue(pid, SIGUSR2, ctypes.c_long(off * 8 + b)) != 0: print("sigqueue failed"); break
    deadline = time.time() + 10; sdc = None
    while time.time() < deadline:
        s = [e for e in events() if e["kind"] == "sdc"]
        if len(s) > before: sdc = s[before]; break
        time.sleep(0.01)
    if sdc is None: results.append((name, b, None, False, False, False)); continue
    seq = sdc["round"] - 1
    true = values(seq)[name]
    bits = struct.unpack("<Q", struct.pack("<d", true))[0] ^ (1 << b)
    bad = struct.unpack("<d", struct.pack("<Q", bits))[0]
    change = abs(bad - true) if math.isfinite(bad) else math.inf
    beyond = change > span[name]
    attributed = sdc.get("replica") == slot
    if attributed:  # wait for the repair before the next injection
        while time.time() < deadline and not any(e["kind"] == "recovery" and e.get("pid") == pid for e in events()): time.sleep(0.01)
    results.append((name, b, change, beyond, attributed, change > vrange[name]))
boot.send_signal(signal.SIGTERM); boot.wait(timeout=30)
ev = events()
beyond = [r for r in results if r[3]]; within = [r for r in results if not r[3]]
print(f"injections {len(results)}; beyond normal range {len(beyond)}, attributed {sum(r[4] for r in beyond)}; "
      f"within range {len(within)}, attributed {sum(r[4] for r in within)}")
print("missed beyond-change-span:", [r[:3] for r in beyond if not r[4]])
vb = [r for r in results if r[5]]
print(f"beyond the field's value range (library's definition): {len(vb)}, attributed {sum(r[4] for r in vb)}")
print("missed beyond-value-range:", [r[:3] for r in vb if not r[4]])
print("no sdc event seen:", sum(1 for r in results if r[2] is None))
print("wrongly attributed (attributed replica != injected):",
      sum(1 for e in ev if e["kind"] == "sdc" and e.get("replica") is not None) - sum(r[4] for r in results))
print("recoveries by fork:", sum(1 for e in ev if e["kind"] == "recovery" and e.get("method") == "fork"))
