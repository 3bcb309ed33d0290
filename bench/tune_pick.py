#!/usr/bin/env python3
"""Reads perf_harness's CSVs from bench/tune_kernel.sh and prints the device's kernel-form row.

Each CSV is one perf_harness run with its own "base" (the device's current row: defines variant
"base", the build "base" or "auto", the work-group size 0) and candidates that differ from it in
one thing: a defines variant (a kernel field), a build (`cellsN`: the cell population N) or a
work-group size (the `local-size` column). For each candidate the speed against its run's base on
each row (data set, k, order) is ratio_kd(candidate) / ratio_kd(base): both are medians of
per-round ratios against the same kd-tree run, so this is the candidate's speed over base's on the
same queries. The winner is the candidate with the highest median over rows, if it is at least 3 %
ahead and no row loses more than 10 %; else base stays. Prints a table per run, then the row in
lib/src/core/kernel_forms.cpp's format.

    tune_pick.py FILE.csv [FILE.csv ...]"""
import csv
import re
import statistics
import sys

FIELDS = {"BHCL_GRID_FILLSORT": "fill_sort", "BHCL_GRID_ROWCAP": "row_cap", "BHCL_GRID_PREFETCH_LINES": "prefetch_lines",
          "BHCL_GRID_PREFETCH_RING": "prefetch_ring (k <= 8 run: ring0 -> prefetch_ring_from 16, ring1 -> 0)",
          "BHCL_GRID_PREFETCH": "prefetch", "BHCL_GRID_WALKCAP": "walk_cap", "BHCL_GRID_VTOPK": "vtopk"}
ROW = ("name, match, measured, vtopk, prefetch, row_cap, walk_cap, fill_sort, prefetch_lines, "
       "prefetch_ring_from, local_size, cell_target")


def candidate(r):
    """(name, {field: value}) of a CSV row: what it changes from its run's base; ("base", {}) for base."""
    if r["defines_name"] != "base":
        change = {}
        for d in r["defines"].split():
            n, _, v = d[2:].partition("=")
            if n not in FIELDS:
                sys.exit(f"tune_pick: {n} is not a field of the forms table")
            change[FIELDS[n]] = v
        return r["defines_name"], change
    if r["build"] not in ("base", "auto"):
        m = re.fullmatch(r"cells(\d+(?:\.\d+)?)", r["build"])
        if not m:
            sys.exit(f"tune_pick: build '{r['build']}' is not base, auto or cellsN")
        return r["build"], {"cell_target": m.group(1)}
    local = r.get("local-size", "") or "0"
    if local not in ("0", "-1"):
        return "local" + local, {"local_size": local}
    return "base", {}


def read_run(path):
    rows = [r for r in csv.DictReader(open(path)) if r["method"] == "blockhash"]
    if not rows:
        sys.exit(f"tune_pick: no blockhash rows in {path}")
    key = lambda r: (r["data"], r["k"], r["order"])
    base = {key(r): float(r["ratio_kd_median"]) for r in rows if candidate(r)[0] == "base"}
    if not base:
        sys.exit(f"tune_pick: no base (the device's current row) in {path}")
    cands, changes = {}, {}
    for r in rows:
        name, change = candidate(r)
        if float(r["recall"]) < 1.0:
            sys.exit(f"tune_pick: {name} on {key(r)} is not exact (recall {r['recall']}): the forms must give the same rows")
        changes[name] = change
        cands.setdefault(name, {})[key(r)] = float(r["ratio_kd_median"]) / base[key(r)]
    return rows[0]["device"], base, cands, changes


def main(paths):
    best, best_med, best_change, device, n_rows = "base", 1.0, {}, "", 0
    for path in paths:
        device, base, cands, changes = read_run(path)
        n_rows = len(base)
        print(f"# {path}: device {device}")
        print(f"# speed over base per row (data, k, order), median over {len(base)} rows; base's ratio to the kd-tree kernel in brackets")
        keys = sorted(base)
        print("candidate   " + " ".join(f"{k[0][:7]}/{k[1]}/{k[2][:1]}".rjust(12) for k in keys) + "      median")
        print("base        " + " ".join(f"[{base[k]:.2f}]".rjust(12) for k in keys))
        for name, by in sorted(cands.items()):
            if name == "base":
                continue
            med = statistics.median(by.values())
            print(f"{name:<12}" + " ".join(f"{by.get(k, float('nan')):.3f}".rjust(12) for k in keys) + f"  {med:10.3f}")
            if med >= 1.03 and min(by.values()) >= 0.90 and med > best_med:
                best, best_med, best_change = name, med, changes[name]
    print(f"# winner: {best} ({best_change or 'no change'}), median {best_med:.3f} of base")
    print(f"# the row, base's values with the winner's change (kernel_forms.cpp: {ROW}):")
    print(f"#   change {best_change or 'none'} on the device's current row; measured: \"{device}, "
          f"bench/tune_kernel.sh: {best} {best_med:.2f}x base (median of {n_rows} rows)\"")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: tune_pick.py FILE.csv [FILE.csv ...]")
    main(sys.argv[1:])
