#!/usr/bin/env python3
"""The class split's A/B in load-free terms: per cell (data, order, k, variant), block hashing's
speed over the kd-tree kernel measured in the same process and rounds (perf_harness's
ratio_kd_median), after over before, the median over the alternations' runs.
Reads class_split_rounds/{before,after}_*.csv (class_split_ab.sh), or the folder given as the
first argument; > 1: the branch faster.
call_ab.py keys its cells without the query order, so its table shows one order per cell and
moves with the machine's load (FLANN and the kd-tree, unchanged code, move as much); this one
keeps both orders and cancels the load."""
import csv, glob, os, statistics, sys

here = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(os.path.abspath(__file__)), "class_split_rounds")
runs = {"before": [], "after": []}
for name in runs:
    for path in sorted(glob.glob(os.path.join(here, name + "_*.csv"))):
        with open(path, newline="") as f:
            runs[name].append({(r["data"], r["order"], r["k"], r["variant"]): float(r["ratio_kd_median"])
                               for r in csv.DictReader(f) if r["method"] == "blockhash"})
keys = sorted(set.intersection(*(set(r) for r in runs["before"] + runs["after"])))
print("| data | order | k | variant | blockhash/kd-tree before | after | after/before |")
print("|---|---|---|---|---|---|---|")
ratios = []
for key in keys:
    b = statistics.median(r[key] for r in runs["before"])
    a = statistics.median(r[key] for r in runs["after"])
    ratios.append(a / b)
    print(f"| {' | '.join(key)} | {b:.3f} | {a:.3f} | {a / b:.3f} |")
q = statistics.quantiles(ratios, n=4)
print(f"\n{len(ratios)} cells: after/before median {statistics.median(ratios):.3f}, "
      f"quartiles {q[0]:.3f}-{q[2]:.3f}, min {min(ratios):.3f}, max {max(ratios):.3f}")
