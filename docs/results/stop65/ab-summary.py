import json, glob, re, statistics, sys, os
d = sys.argv[1]
rows = {}
for f in sorted(glob.glob(d + "/*.json")):
    b, seed = os.path.basename(f)[:-5].split("-")
    for l in open(f):
        r = json.loads(l)
        rows.setdefault(b, {}).setdefault(seed, {})[r["what"]] = r
steal = {}
for l in open(d + "/steal.txt"):
    m = re.match(r"(\w+) seed (\d+): (\d+) s, steal (\d+) ticks", l)
    steal[(m[1], m[2])] = (int(m[3]), int(m[4]))
for b in ["old", "new"]:
    print(f"== {b}")
    for seed, w in sorted(rows.get(b, {}).items()):
        h, c, fp = w.get("hang"), w.get("crash"), w.get("false-positives")
        print(f"seed {seed}: hang med {h['median_us']:.1f} p99 {h['p99_us']:.0f} max {h['max_us']:.0f} | crash med {c['median_us']:.1f} | fp {fp['faults']} in {fp['count']} (round med {fp['median_us']:.1f}) | {steal.get((b, seed))}")
    hs = [w["hang"]["median_us"] for w in rows[b].values()]
    hp = [w["hang"]["p99_us"] for w in rows[b].values()]
    cs = [w["crash"]["median_us"] for w in rows[b].values()]
    fps = sum(w["false-positives"]["faults"] for w in rows[b].values())
    n = sum(w["false-positives"]["count"] for w in rows[b].values())
    st = sum(steal[(b, s)][1] for s in rows[b])
    print(f"{b}: runs {len(hs)}, hang median of medians {statistics.median(hs):.1f}, median of p99s {statistics.median(hp):.0f}, crash median of medians {statistics.median(cs):.1f}, false positives {fps} in {n}, steal {st/100:.1f} s")
