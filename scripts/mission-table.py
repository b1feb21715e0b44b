#!/usr/bin/env python3
"""The maze robot's missions of campaigns, one markdown row per campaign (or per cell).

Reads each run of a campaign folder (runs.jsonl) and the simulator's summary the run left
(DIR/runs/run-NNNNNN/mission.json: run the campaign with --keep-runs) and prints: missions,
how many succeeded, mission time (simulated seconds) mean and max, late periods (a command
that came after its period's end) mean and max and their share of all periods, collisions, and
wall time per mission. A run that left no mission.json (killed at the time limit, never
started) counts as a mission that did not succeed, and is left out of the times. A
NAME=DIR,DIR,... argument makes one row of several folders (the shards of one cell).
"""

import argparse
import json
import sys
from pathlib import Path


def runs_of(camp):
    path = camp / "runs.jsonl"
    if not path.exists():
        return None
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def row(name, camps):
    n = 0
    missions = []
    for camp in camps:
        runs = runs_of(camp)
        if runs is None:
            print(f"{camp}: no runs.jsonl (not a campaign folder)", file=sys.stderr)
            return None
        for r in runs:
            n += 1
            path = camp / "runs" / f"run-{r['run']:06d}" / "mission.json"
            if path.exists():
                with open(path) as f:
                    missions.append(json.load(f))
        if runs and not (camp / "runs").is_dir():
            print(f"{camp}: no runs/ (run the campaign with --keep-runs; a folder made by "
                  "merge has none)", file=sys.stderr)
            return None
    if n == 0:
        return f"| {name} | 0/0 | – | – | – | – | – |"
    ok = sum(1 for m in missions if m.get("success"))
    if not missions:
        return f"| {name} | 0/{n} | – | – | – | – | – |"
    k = len(missions)
    times = [m["mission_time_s"] for m in missions]
    late = [m["late_periods"] for m in missions]
    periods = sum(m["periods"] for m in missions)
    share = f"{100 * sum(late) / periods:.2f} %" if periods else "–"
    collisions = sum(m["collisions"] for m in missions)
    wall = [m["wall_time_s"] for m in missions]
    return (f"| {name} | {ok}/{n} | {sum(times) / k:.1f} / {max(times):.1f} "
            f"| {sum(late) / k:.1f} / {max(late)} | {share} | {collisions} "
            f"| {sum(wall) / k:.2f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().split("\n")[0],
                                     epilog=__doc__.strip().split("\n", 2)[2])
    parser.add_argument("dirs", nargs="+", metavar="DIR|NAME=DIR,DIR,...")
    args = parser.parse_args()
    print("| Campaign | Successful | Mission time mean / max (s) | Late periods mean / max "
          "| Late share | Collisions | Wall time per mission (s) |")
    print("|---|--:|--:|--:|--:|--:|--:|")
    status = 0
    for arg in args.dirs:
        if "=" in arg:
            name, dirs = arg.split("=", 1)
            line = row(name, [Path(d) for d in dirs.split(",")])
        else:
            line = row(Path(arg).name, [Path(arg)])
        if line:
            print(line)
        else:
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
