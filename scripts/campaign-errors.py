#!/usr/bin/env python3
"""What happened around each error and false positive of a campaign.

For every injection counted as an error (unrecovered or undetected) and every run with a
false positive, prints the injections into the same component and the voter's events about it
within a window on either side, times relative to the injection (or to the event no injection
explains). It needs the runs' events: run the campaign with --keep-runs
(DIR/runs/run-NNNNNN/events.jsonl), and name the campaign or shard folders that hold them (a
folder made by `merge` has none).
"""

import argparse
import gzip
import json
import sys
from pathlib import Path

FAULTS = ("sdc", "crash", "hang", "protocol")


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
    return None


def match_window_ns(camp):
    """The campaign's own matching window (`--match-window-ms`, 2000 by default)."""
    try:
        with open(camp / "campaign.json") as f:
            return json.load(f).get("match_window_ms", 2000) * 1_000_000
    except (OSError, ValueError):
        return 2000 * 1_000_000


def events_of(camp, run):
    path = camp / "runs" / f"run-{run:06d}" / "events.jsonl"
    return list(jsonl(path)) if path.exists() else None


def show(camp, run, component, t0, window_ns, injs, why):
    events = events_of(camp, run)
    print(f"\n{camp.name} run {run}, {component}: {why}")
    if events is None:
        print("  (no events: the runs were not kept here; run the campaign with --keep-runs and "
              "name its shard folders, not a merged one)")
        return
    rows = []
    for i in injs:
        if i["run"] == run and i["component"] == component and i["outcome"] != "missed":
            detected = f" as {i['detected_as']}" if i.get("detected_as") else ""
            rows.append((i["ts_ns"], f"inject {i['kind']} into #{i['replica']} pid {i['pid']}: "
                         f"{i['outcome']}{detected}"))
    for e in events:
        if e.get("component") == component and e.get("kind") not in ("start", None):
            who = f"#{e['replica']} pid {e.get('pid')}" if e.get("replica") is not None else "-"
            extra = f" -> pid {e['new_pid']}" if e.get("new_pid") else ""
            rows.append((e["ts_ns"], f"{e['kind']} {who}{extra} {e.get('cause') or ''} "
                         f"{e.get('detail') or ''}"))
    for ts, text in sorted(rows):
        if abs(ts - t0) <= window_ns:
            print(f"  {(ts - t0) / 1e6:+10.1f} ms  {text}")


def false_positives(camp, run, injs, shown_ns):
    """The fault events of `run` naming a replica that no injection into that process came
    shortly before (the campaign's matching window; the rule without its one-to-one pairing)."""
    events = events_of(camp, run)
    if events is None:
        print(f"\n{camp.name} run {run}: a false positive, but the run's events were not kept")
        return
    window = match_window_ns(camp)
    mine = [i for i in injs if i["run"] == run and i["outcome"] != "missed"]
    for e in events:
        if e.get("kind") not in FAULTS or e.get("replica") is None:
            continue
        explained = any(
            i["component"] == e.get("component") and i["replica"] == e["replica"]
            and i["pid"] == e.get("pid") and 0 <= e["ts_ns"] - i["ts_ns"] <= window
            for i in mine)
        if not explained:
            show(camp, run, e["component"], e["ts_ns"], shown_ns, injs,
                 f"{e['kind']} of #{e['replica']} pid {e.get('pid')} that no injection "
                 "explains (at +0.0 ms)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().split("\n")[0],
                                     epilog=__doc__.strip().split("\n", 2)[2])
    parser.add_argument("--window-ms", type=int, default=3000,
                        help="how much to show on either side (default 3000)")
    parser.add_argument("dirs", nargs="+", metavar="CAMPAIGN_DIR")
    args = parser.parse_args()
    shown_ns = args.window_ms * 1_000_000
    status = 0
    for arg in args.dirs:
        camp = Path(arg)
        injs = injections(camp)
        if injs is None:
            print(f"{camp}: no injections.jsonl (not a campaign folder)", file=sys.stderr)
            status = 1
            continue
        for i in injs:
            if i["outcome"] in ("unrecovered", "undetected"):
                show(camp, i["run"], i["component"], i["ts_ns"], shown_ns, injs,
                     f"injection {i['index']} {i['outcome']}")
        runs = camp / "runs.jsonl"
        for r in (jsonl(runs) if runs.exists() else []):
            if r.get("false_positives"):
                false_positives(camp, r["run"], injs, shown_ns)
    return status


if __name__ == "__main__":
    sys.exit(main())
