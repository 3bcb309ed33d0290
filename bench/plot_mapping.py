#!/usr/bin/env python3
"""Plots mapping_bench's per-scan CSV: update time and query time per point, per scan, for block
hashing, nanoflann's dynamic adaptor and, where the CSV has its columns (mapping_bench built
with ikd-Tree), ikd-Tree (issue 39).

    /usr/bin/python3 bench/plot_mapping.py bench/results/mapping/autzen_80.csv docs/mapping_autzen.png

Needs matplotlib (Debian: python3-matplotlib). The image is written to a temporary beside the
target and renamed over it, so a failed run never leaves a partial file.
"""
import csv
import os
import sys
import tempfile


def read_rows(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise SystemExit(f"plot_mapping: {path}: no rows")
    need = {"scan", "scan_points", "bh_update_s", "bh_query_s", "nf_update_s", "nf_query_s"}
    missing = need - set(rows[0])
    if missing:
        raise SystemExit(f"plot_mapping: {path}: missing columns {sorted(missing)}")
    return rows


def main(argv):
    if len(argv) != 3:
        raise SystemExit("usage: plot_mapping.py PER_SCAN.csv OUT.png")
    src, out = argv[1], argv[2]
    rows = read_rows(src)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scan = [int(r["scan"]) for r in rows]
    pts = [float(r["scan_points"]) for r in rows]
    series = {
        "block hashing (grid, exact)": ("bh_update_s", "bh_query_s", "tab:blue"),
        "nanoflann dynamic adaptor": ("nf_update_s", "nf_query_s", "tab:orange"),
    }
    if "ik_update_s" in rows[0]:
        series["ikd-Tree"] = ("ik_update_s", "ik_query_s", "tab:green")
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for name, (u, q, colour) in series.items():
        a.plot(scan, [1e3 * float(r[u]) for r in rows], label=name, color=colour, lw=1.2)
        b.plot(scan, [1e6 * float(r[q]) / p for r, p in zip(rows, pts)], label=name, color=colour, lw=1.2)
    a.set_ylabel("update per scan (ms)\ninsert + crop remove")
    a.set_yscale("log")
    a.legend()
    a.grid(alpha=0.3)
    b.set_ylabel("k = 5 query per point (µs)")
    b.set_xlabel("scan")
    b.grid(alpha=0.3)
    fig.suptitle("Autzen mapping sequence (mapping_bench), AVX-512, 2 threads")
    fig.tight_layout()
    d = os.path.dirname(os.path.abspath(out))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(out) + ".", suffix=".tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            fig.savefig(f, format="png", dpi=110)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600
        os.replace(tmp, out)
    except BaseException:
        os.unlink(tmp)
        raise


if __name__ == "__main__":
    main(sys.argv)
