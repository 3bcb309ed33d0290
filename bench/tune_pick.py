#!/usr/bin/env python3
"""Reads perf_harness's CSV from bench/tune_kernel.sh and prints the device's kernel-form row.

For each candidate (a defines variant, one change from the device's current row, "base"), the
speed against base on each row (data set, k, order) is ratio_kd(candidate) / ratio_kd(base):
both are medians of per-round ratios against the same kd-tree run, so this is the candidate's
speed over base's on the same queries. The winner is the candidate with the highest median over
rows, if it is at least 3 % ahead and no row loses more than 10 %; else base stays. Prints a
table, then the row in lib/src/core/kernel_forms.cpp's format."""
import csv
import statistics
import sys

FIELDS = {"BHCL_GRID_FILLSORT": "fill_sort", "BHCL_GRID_ROWCAP": "row_cap", "BHCL_GRID_PREFETCH_LINES": "prefetch_lines",
          "BHCL_GRID_PREFETCH": "prefetch", "BHCL_GRID_WALKCAP": "walk_cap", "BHCL_GRID_VTOPK": "vtopk"}


def main(path):
    rows = [r for r in csv.DictReader(open(path)) if r["method"] == "blockhash"]
    if not rows:
        sys.exit(f"tune_pick: no blockhash rows in {path}")
    key = lambda r: (r["data"], r["k"], r["order"])
    base = {key(r): float(r["ratio_kd_median"]) for r in rows if r["defines_name"] == "base"}
    if not base:
        sys.exit("tune_pick: no 'base' variant (the device's current row) in the CSV")
    device = rows[0]["device"]
    cands, defines = {}, {}
    for r in rows:
        name = r["defines_name"]
        defines[name] = r["defines"]
        if float(r["recall"]) < 1.0:
            sys.exit(f"tune_pick: {name} on {key(r)} is not exact (recall {r['recall']}): the forms must give the same rows")
        cands.setdefault(name, {})[key(r)] = float(r["ratio_kd_median"]) / base[key(r)]
    print(f"# device: {device}")
    print(f"# speed over base per row (data, k, order), median over {len(base)} rows; base's ratio to the kd-tree kernel in brackets")
    keys = sorted(base)
    print("candidate   " + " ".join(f"{k[0][:7]}/{k[1]}/{k[2][:1]}" .rjust(12) for k in keys) + "      median")
    print("base        " + " ".join(f"[{base[k]:.2f}]".rjust(12) for k in keys))
    best, best_med = "base", 1.0
    for name, by in sorted(cands.items()):
        if name == "base":
            continue
        med = statistics.median(by.values())
        print(f"{name:<12}" + " ".join(f"{by.get(k, float('nan')):.3f}".rjust(12) for k in keys) + f"  {med:10.3f}")
        if med >= 1.03 and min(by.values()) >= 0.90 and med > best_med:
            best, best_med = name, med
    print(f"# winner: {best} ({defines.get(best, '')}), median {best_med:.3f} of base")
    change = {}
    for d in defines.get(best, "").split():
        n, _, v = d[2:].partition("=")
        if n not in FIELDS:
            sys.exit(f"tune_pick: {n} is not a field of the forms table")
        change[FIELDS[n]] = v
    print("# the row, base's values with the winner's change (kernel_forms.cpp: name, match, measured, vtopk, "
          "prefetch, row_cap, walk_cap, fill_sort, prefetch_lines):")
    print(f"#   change {change or 'none'} on the device's current row; measured: \"{device}, "
          f"bench/tune_kernel.sh: {best} {best_med:.2f}x base (median of {len(base)} rows)\"")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else sys.exit("usage: tune_pick.py FILE.csv"))
