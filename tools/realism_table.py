"""Runs `v2ce eval realism --json` for several simulations of one recording and prints the
statistics side by side as a Markdown table (value, and distance to the real stream in brackets),
with the count of statistics on which each simulation is the closest.

    python tools/realism_table.py REAL [--frames F | --fps N] NAME=SIM.csv [NAME=SIM.csv ...]

The simulations come from `v2ce convert`, `tools/eventcv_peer.py` and `tools/naive_peer.py`
(docs/results.md, "Realism").
"""

import json
import os
import subprocess
import sys

V2CE = os.environ.get("V2CE", "target/release/v2ce")


def realism(real, extra, sim):
    out = subprocess.run(
        [V2CE, "eval", "realism", "--json", "--real", real, "--sim", sim, *extra],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout)


def show(v):
    if v is None:
        return "undefined"
    return f"{v:.4g}"


def main(argv):
    real, rest = argv[1], argv[2:]
    extra = []
    while rest and rest[0] in ("--frames", "--fps"):
        extra += rest[:2]
        rest = rest[2:]
    runs = [(name, realism(real, extra, path)) for name, path in (a.split("=", 1) for a in rest)]
    names = [s["name"] for s in runs[0][1]["statistics"]]
    print("| statistic | real | " + " | ".join(n for n, _ in runs) + " |")
    print("|---|---:|" + "---:|" * len(runs))
    wins = {n: 0 for n, _ in runs}
    for i, stat in enumerate(names):
        real_value = runs[0][1]["statistics"][i]["real"]
        cells, best = [], None
        for n, r in runs:
            s = r["statistics"][i]
            cells.append(f"{show(s['sim'])} ({show(s['distance'])})")
            if s["distance"] is not None and (best is None or s["distance"] < best[1]):
                best = (n, s["distance"])
        if best is not None:
            wins[best[0]] += 1
        print(f"| {stat} | {show(real_value)} | " + " | ".join(cells) + " |")
    print("| events | " + str(runs[0][1]["real_events"]) + " | "
          + " | ".join(str(r["sim_events"]) for _, r in runs) + " |")
    print("| closest on | | " + " | ".join(str(wins[n]) for n, _ in runs) + " |")


if __name__ == "__main__":
    main(sys.argv)
