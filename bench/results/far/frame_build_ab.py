#!/usr/bin/env python3
"""Summarises frame_build_ab.sh's rounds: per row, block hashing's ratio to the kd-tree in each
process (build: build_bench's build_s over the kd-tree's; frame: frame_bench's /kdtree), the median over the
alternations for before (7f729ba) and after (today), and after / before (< 1: faster today)."""
import glob
import os
import statistics
import sys

d = sys.argv[1] if len(sys.argv) > 1 else "bench/results/far/frame_build_rounds"


def build_rows(path):
    # build_s of block hashing over the kd-tree's in the same run (x_kdtree is printed to 2 decimals)
    s = {}
    for line in open(path):
        f = line.split()
        if len(f) > 6 and f[1].isdigit() and f[2] in ("blockhash", "kdtree"):
            s[(f[0], f[1], f[2])] = float(f[3])
    return {f"build {d} {n}": v / s[(d, n, "kdtree")] for (d, n, m), v in s.items()
            if m == "blockhash" and (d, n, "kdtree") in s}


def frame_rows(path):
    out = {}
    for line in open(path):
        f = line.split()
        if len(f) >= 5 and f[0].startswith("blockhash"):
            out[f"frame cornell 1M k50 ({f[0]})"] = float(f[4])
    return out


table = {}
for side in ("before", "after"):
    for p in sorted(glob.glob(os.path.join(d, f"build_{side}_*.txt"))):
        for k, v in build_rows(p).items():
            table.setdefault(k, {}).setdefault(side, []).append(v)
    for p in sorted(glob.glob(os.path.join(d, f"frame_{side}_*.txt"))):
        for k, v in frame_rows(p).items():
            table.setdefault(k, {}).setdefault(side, []).append(v)
print(f"{'row':34s} {'before/kd':>10s} {'after/kd':>10s} {'after/before':>13s} {'n':>3s}")
for k, v in table.items():
    b, a = v.get("before", []), v.get("after", [])
    if not b or not a:
        continue
    mb, ma = statistics.median(b), statistics.median(a)
    print(f"{k:34s} {mb:10.3f} {ma:10.3f} {ma / mb:13.3f} {min(len(a), len(b)):3d}")
