#!/usr/bin/env python3
"""mission-table.py — the maze robot's missions of campaigns, one row per campaign.

usage: scripts/mission-table.py CAMPAIGN_DIR... | NAME=DIR,DIR,...

A NAME=DIR,DIR,... argument makes one row of several folders (the shards of one cell).

Reads the simulator's summary of every kept run (OUT/runs/run-NNNNNN/mission.json: run the
campaign with --keep-runs) and prints a markdown row per campaign folder: missions, how many
succeeded, mission time (simulated seconds) mean and max, late periods (a command that came
after its period's end) mean and max and their share of all periods, collisions, and wall time
per mission. Folders whose runs were not kept are named on stderr and skipped.
"""

import json
import sys
from pathlib import Path


def row(name, camps):
    missions = []
    for camp in camps:
        found = sorted((camp / "runs").glob("run-*/mission.json"))
        if not found:
            print(f"{camp}: no runs/run-*/mission.json (run the campaign with --keep-runs)",
                  file=sys.stderr)
        for path in found:
            with open(path) as f:
                missions.append(json.load(f))
    if not missions:
        return None
    n = len(missions)
    ok = sum(1 for m in missions if m.get("success"))
    times = [m["mission_time_s"] for m in missions]
    late = [m["late_periods"] for m in missions]
    periods = sum(m["periods"] for m in missions)
    collisions = sum(m["collisions"] for m in missions)
    wall = [m["wall_time_s"] for m in missions]
    return (f"| {name} | {ok}/{n} | {sum(times) / n:.1f} / {max(times):.1f} "
            f"| {sum(late) / n:.1f} / {max(late)} | {100 * sum(late) / periods:.2f} % "
            f"| {collisions} | {sum(wall) / n:.2f} |")


def main(argv):
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if argv else 2
    print("| Campaign | Successful | Mission time mean / max (s) | Late periods mean / max "
          "| Late share | Collisions | Wall time per mission (s) |")
    print("|---|--:|--:|--:|--:|--:|--:|")
    for arg in argv:
        if "=" in arg:
            name, dirs = arg.split("=", 1)
            line = row(name, [Path(d) for d in dirs.split(",")])
        else:
            line = row(Path(arg).name, [Path(arg)])
        if line:
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
