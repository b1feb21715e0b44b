#!/usr/bin/env python3
"""campaign-errors.py — what happened around each error and false positive of a campaign.

usage: scripts/campaign-errors.py [--window-ms MS] CAMPAIGN_DIR...

For every injection counted as an error (unrecovered or undetected) and every run with a
false positive, prints the injections into the same component and the voter's events about it
within MS milliseconds (default 3000) on either side, times relative to the injection. It
needs the runs' events: run the campaign with --keep-runs (OUT/runs/run-NNNNNN/events.jsonl).
A campaign folder whose runs were not kept is named, and skipped.
"""

import gzip
import json
import sys
from pathlib import Path


def jsonl(path):
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        for line in f:
            line = line.strip()
            if line:
                yield json.loads(line)


def injections(camp):
    for name in ("injections.jsonl", "injections.jsonl.gz"):
        if (camp / name).exists():
            return list(jsonl(camp / name))
    return []


def events_of(camp, run):
    path = camp / "runs" / f"run-{run:06d}" / "events.jsonl"
    return list(jsonl(path)) if path.exists() else None


def show(camp, run, component, t0, window_ns, injs, why):
    events = events_of(camp, run)
    print(f"\n{camp.name} run {run}, {component}: {why}")
    if events is None:
        print("  (no events: the campaign's runs were not kept; run it with --keep-runs)")
        return
    rows = []
    for i in injs:
        if i["run"] == run and i["component"] == component and i["outcome"] != "missed":
            rows.append((i["ts_ns"], f"inject {i['kind']} into #{i['replica']} pid {i['pid']}: "
                         f"{i['outcome']}" + (f" as {i['detected_as']}" if i.get("detected_as") else "")))
    for e in events:
        if e.get("component") == component and e.get("kind") not in ("start", None):
            who = f"#{e['replica']} pid {e.get('pid')}" if e.get("replica") is not None else "-"
            extra = f" -> pid {e['new_pid']}" if e.get("new_pid") else ""
            detail = (e.get("detail") or "")[:110]
            rows.append((e["ts_ns"], f"{e['kind']} {who}{extra} {e.get('cause') or ''} {detail}"))
    for ts, text in sorted(rows):
        if abs(ts - t0) <= window_ns:
            print(f"  {(ts - t0) / 1e6:+10.1f} ms  {text}")


def main(argv):
    window_ms = 3000
    if argv[:1] == ["--window-ms"]:
        window_ms = int(argv[1])
        argv = argv[2:]
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if argv else 2
    for arg in argv:
        camp = Path(arg)
        injs = injections(camp)
        if not injs:
            print(f"{camp}: no injections.jsonl", file=sys.stderr)
            continue
        for i in injs:
            if i["outcome"] in ("unrecovered", "undetected"):
                show(camp, i["run"], i["component"], i["ts_ns"], window_ms * 1_000_000, injs,
                     f"injection {i['index']} {i['outcome']}")
        runs = camp / "runs.jsonl"
        for r in (jsonl(runs) if runs.exists() else []):
            if r.get("false_positives"):
                events = events_of(camp, r["run"])
                print(f"\n{camp.name} run {r['run']}: {r['false_positives']} false positive(s)")
                if events is None:
                    print("  (no events: the campaign's runs were not kept)")
                    continue
                # The fault events naming a replica that no injection into that process came
                # shortly before (the matching rule, without its one-to-one pairing).
                mine = [i for i in injs if i["run"] == r["run"] and i["outcome"] != "missed"]
                for e in events:
                    if e.get("kind") not in ("sdc", "crash", "hang", "protocol"):
                        continue
                    if e.get("replica") is None:
                        continue
                    explained = any(
                        i["component"] == e.get("component") and i["replica"] == e["replica"]
                        and i["pid"] == e.get("pid")
                        and 0 <= e["ts_ns"] - i["ts_ns"] <= window_ms * 1_000_000
                        for i in mine)
                    if not explained:
                        show(camp, r["run"], e["component"], e["ts_ns"], window_ms * 1_000_000,
                             injs, f"{e['kind']} of #{e['replica']} pid {e.get('pid')} that "
                             "no injection explains (at +0.0 ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
