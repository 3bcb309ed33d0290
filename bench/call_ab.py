#!/usr/bin/env python3
"""Two builds of a benchmark run in alternation (A, B, A, B, ...): the median of per-round ratios.

    call_ab.py --before OLD --after NEW --alternations 5 --out DIR -- ARGS...

Each round runs OLD then NEW (the order flips every round, so that neither always runs second)
with the same ARGS plus --csv; per cell, the round's ratio is before/after of the cell's time
(call_bench: wall_s, the median of the binary's rounds; perf_harness: 1/qps_median). A ratio
> 1 means the new build is faster. Prints one table row per cell: the median ratio and the
min-max over rounds, and keeps every round's CSV under DIR.
"""
import argparse
import csv
import os
import statistics
import subprocess
import sys


def cell_times(path):
    """Cell -> seconds, from a call_bench or perf_harness CSV."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    times = {}
    if rows and "wall_s" in rows[0]:  # call_bench: the median over the binary's own rounds
        per = {}
        for r in rows:
            per.setdefault((r["data"], r["method"], r["kind"], r["n"], r["k"]), []).append(float(r["wall_s"]))
        times = {key: statistics.median(v) for key, v in per.items()}
    else:  # perf_harness: queries/s of the kernels
        for r in rows:
            times[(r["data"], r["variant"], "knn", r["n"], r["k"])] = 1.0 / float(r["qps_median"])
    return times


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True)
    ap.add_argument("--after", required=True)
    ap.add_argument("--alternations", type=int, default=5)
    ap.add_argument("--out", required=True, help="folder for every round's CSV")
    ap.add_argument("args", nargs=argparse.REMAINDER)
    o = ap.parse_args()
    args = [a for a in o.args if a != "--"]
    os.makedirs(o.out, exist_ok=True)
    ratios = {}
    for i in range(o.alternations):
        runs = [("before", o.before), ("after", o.after)]
        if i % 2:
            runs.reverse()
        got = {}
        for name, exe in runs:
            path = os.path.join(o.out, f"{name}_{i}.csv")
            subprocess.run([exe, *args, "--csv", path], check=True, stdout=subprocess.DEVNULL)
            got[name] = cell_times(path)
        for key, t in got["before"].items():
            if key in got["after"]:
                ratios.setdefault(key, []).append(t / got["after"][key])
    print("| data | method | kind | n | k | before/after (median) | min-max |")
    print("|---|---|---|---|---|---|---|")
    for key in sorted(ratios):
        v = ratios[key]
        print(f"| {' | '.join(key)} | {statistics.median(v):.3f} | {min(v):.3f}-{max(v):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
