#!/usr/bin/env python3
"""Tables of an `anomaly/scripts/robot-eval.sh` folder (MAVFI Table 4 layout), as Markdown.

    anomaly/scripts/robot-eval-table.py OUT

Fault-free missions: missions that reached the goal, `anomaly` events (every one is a false
alarm: nothing was injected), frames the detectors scored (from each voter's exit log), false
alarms per 1000 scored frames, and the voter's mean cost per scored frame (timer included).

Injection campaigns (variable-level exponent flips): missions that reached the goal, and per
injection the campaign's outcome — detected (a fault event matched it), recovered (the injected
replica was replaced after it). "Beyond range" flips are those of the exponent's top bit (bit 62
of the f64): every monitored value is below 2 in magnitude, so its top exponent bit is 0 and the
flip multiplies it by 2^1024 (or makes it Inf/NaN) — a change far beyond any normal range. The
other exponent flips mostly *shrink* a value towards 0 (its exponent bits below the top one are
mostly 1), a change a command or a way-point can make in normal operation too.
"""
import json
import re
import sys
from pathlib import Path

LEVELS = ["smr", "dmr"]
DETECTORS = ["none", "gauss", "ae"]
TARGETS = ["navigator", "planner"]
COST = re.compile(r"voter\{component=(\w+)\}.*frames observed.*frames=(\d+) mean_ns=(\d+)")
ANSI = re.compile(r"\x1b\[[0-9;]*m")


def golden(out: Path):
    print("| level | detector | missions ok | anomaly events | frames scored | false alarms / 1000 frames | ns / frame (navigator, planner) |")
    print("|---|---|--:|--:|--:|--:|--:|")
    for level in LEVELS:
        for det in DETECTORS:
            runs = sorted((out / "golden" / f"{level}-{det}").glob("run-*"))
            if not runs:
                continue
            ok = alarms = frames = 0
            cost = {}
            for run in runs:
                err = ANSI.sub("", (run / "stderr").read_text(errors="replace"))
                ok += "mission succeeded" in err
                events = run / "events.jsonl"
                if events.exists():
                    alarms += sum(json.loads(l)["kind"] == "anomaly" for l in events.read_text().splitlines() if l)
                for comp, n, ns in COST.findall(err):
                    frames += int(n)
                    c = cost.setdefault(comp, [0, 0])
                    c[0] += int(n)
                    c[1] += int(n) * int(ns)
            rate = f"{1000 * alarms / frames:.2f}" if frames else "–"
            ns = ", ".join(
                f"{cost[c][1] / cost[c][0]:.0f}" if c in cost and cost[c][0] else "–" for c in TARGETS
            )
            print(f"| {level.upper()} | {det} | {ok}/{len(runs)} | {alarms} | {frames} | {rate} | {ns if det != 'none' else '–'} |")


def campaigns(out: Path, flips: str):
    print("| level | detector | injected into | missions ok | injected | detected | recovered | beyond range: detected / recovered | false positives |")
    print("|---|---|---|--:|--:|--:|--:|--:|--:|")
    for level in LEVELS:
        for det in DETECTORS:
            for target in TARGETS:
                cell = out / "campaign" / f"{level}-{det}-{target}-{flips}"
                if not (cell / "runs.jsonl").exists():
                    continue
                runs = [json.loads(l) for l in (cell / "runs.jsonl").read_text().splitlines() if l]
                inj = [json.loads(l) for l in (cell / "injections.jsonl").read_text().splitlines() if l]
                inj = [i for i in inj if i["outcome"] != "missed"]
                detected = [i for i in inj if i["outcome"] in ("recovered", "unrecovered")]
                recovered = [i for i in inj if i["outcome"] == "recovered"]
                large = [i for i in inj if 62 in i.get("bits", [])]
                large_det = [i for i in large if i["outcome"] in ("recovered", "unrecovered")]
                large_rec = [i for i in large if i["outcome"] == "recovered"]
                fp = sum(r["false_positives"] for r in runs)
                ok = sum(r["task_ok"] for r in runs)
                print(
                    f"| {level.upper()} | {det} | {target} | {ok}/{len(runs)} | {len(inj)} | {len(detected)} | {len(recovered)} "
                    f"| {len(large_det)} / {len(large_rec)} of {len(large)} | {fp} |"
                )


def main():
    out = Path(sys.argv[1])
    print("Fault-free missions (maze 1):\n")
    golden(out)
    print("\nInjection campaigns (maze 1, 2 Hz for 3 s per mission), any exponent bit:\n")
    campaigns(out, "exp")
    print("\nInjection campaigns, the top exponent bit only (beyond any normal range):\n")
    campaigns(out, "top")


if __name__ == "__main__":
    main()
