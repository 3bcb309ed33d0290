#!/usr/bin/env python3
"""Plots and a markdown summary from knn_bench CSV files.

usage: plot.py RESULTS.csv [MORE.csv ...] --out DIR

Writes DIR/<csv name>_qps_vs_recall_<data>_N<N>_k<k>.png (one curve per method, the A sweep as
points),
DIR/build_vs_N.png and DIR/memory_vs_N.png when several N were run, and DIR/summary.md: per data
set, N and k, every method's queries/s and recall, and block hashing's speed-up over each exact
baseline at the smallest A whose recall@k >= 0.95.
"""
import argparse
import csv
import os
import sys
from collections import defaultdict


def load(paths):
    rows = []
    for p in paths:
        with open(p, newline="") as f:
            source = os.path.splitext(os.path.basename(p))[0]
            for r in csv.DictReader(f):
                r["source"] = source
                for key in ("N", "n", "k", "threads", "incomplete"):
                    r[key] = int(float(r[key]))
                for key in ("A", "build_s", "compile_s", "query_s", "queries_per_s", "recall",
                            "fn_rate", "max_dilation", "mean_dilation", "mean_rel_err", "bytes_per_point"):
                    r[key] = float(r[key]) if r[key] not in ("", "inf", "nan") else float("nan")
                rows.append(r)
    return rows


# One colour per method in every plot; the preset is the line style, Hilbert-sorted queries the
# marker, so that a method reads the same across figures.
METHOD_COLOURS = {"bruteforce": "#7f7f7f", "kdtree": "#1f77b4", "flann": "#2ca02c",
                  "blockhash": "#d62728"}
PRESET_STYLES = {"": "-", "auto": "-", "paper": "--"}


def colour(method):
    return METHOD_COLOURS.get(method, "#9467bd")


def style(r, several):
    line = PRESET_STYLES.get(r["preset"], ":") if several else ""
    return ("^" if r["sort"] == "on" else "o") + line


def outside_legend(ax, fig):
    """The legend right of the axes, so that it never covers data."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()


def label(r):
    m = r["method"]
    if r["preset"]:
        m += f"-{r['preset']}"
    if r["sort"] == "on":
        m += " (hilbert-sorted)"
    return m


def plots(rows, out):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("plot.py: matplotlib not installed (python3-matplotlib): no plots", file=sys.stderr)
        return []
    made = []
    groups = defaultdict(list)
    for r in rows:
        groups[(r["source"], r["data"], r["N"], r["k"])].append(r)
    for (source, data, N, k), rs in sorted(groups.items()):
        fig, ax = plt.subplots(figsize=(8.4, 4.4))
        curves = defaultdict(list)
        for r in rs:
            curves[label(r)].append(r)
        for name, cr in sorted(curves.items()):
            cr.sort(key=lambda r: r["A"])
            xs = [r["recall"] for r in cr]
            ys = [r["queries_per_s"] for r in cr]
            ax.plot(xs, ys, style(cr[0], len(cr) > 1), label=name, markersize=5,
                    color=colour(cr[0]["method"]))
            if len(cr) > 1:
                for r in cr:
                    ax.annotate(f"A={r['A']:g}", (r["recall"], r["queries_per_s"]), fontsize=6,
                                xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel(f"recall@{k}")
        ax.set_ylabel("queries / s (median)")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        dev = rs[0]["device"]
        ax.set_title(f"{data}, N={N:,}, k={k}, {rs[0]['n']:,} queries\n{dev}", fontsize=9)
        outside_legend(ax, fig)
        path = os.path.join(out, f"{source}_qps_vs_recall_{data}_N{N}_k{k}.png")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        made.append(path)
    # Build time and memory against N, per method and data set, where several N exist.
    for metric, ylabel, fname in (("build_s", "build time (s)", "build_vs_N.png"),
                                  ("bytes_per_point", "memory (bytes / point)", "memory_vs_N.png")):
        series = defaultdict(dict)
        for r in rows:
            series[(r["data"], r["method"], r["preset"])][r["N"]] = r[metric]
        series = {k: v for k, v in series.items() if len(v) > 1}
        if not series:
            continue
        fig, ax = plt.subplots(figsize=(8.4, 4.4))
        markers = {d: m for d, m in zip(sorted({k[0] for k in series}), "osD^vP*X")}
        for (data, m, preset), pts in sorted(series.items()):
            ns = sorted(pts)
            name = m + (f"-{preset}" if preset else "")
            ax.plot(ns, [pts[n] for n in ns], markers[data] + PRESET_STYLES.get(preset, ":"),
                    label=f"{name} ({data})", markersize=4, color=colour(m))
        ax.set_xscale("log")
        if metric == "build_s":
            ax.set_yscale("log")
        ax.set_xlabel("N points")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title(f"{ylabel} against N (colour: method, marker: data set)", fontsize=9)
        outside_legend(ax, fig)
        path = os.path.join(out, fname)
        fig.savefig(path, dpi=110)
        plt.close(fig)
        made.append(path)
    return made


def summary(rows, out):
    lines = ["# knn_bench summary", ""]
    groups = defaultdict(list)
    for r in rows:
        groups[(r["source"], r["data"], r["N"], r["k"], r["sort"])].append(r)
    for (source, data, N, k, sort), rs in sorted(groups.items()):
        lines.append(f"## {source}: {data}, N = {N:,}, k = {k}, queries {rs[0]['n']:,}"
                     f"{', Hilbert-sorted queries' if sort == 'on' else ''}")
        lines.append(f"device: {rs[0]['device']}; host threads {rs[0]['threads']}")
        lines.append("")
        lines.append("| method | A | queries/s | recall@k | FN | max dil | mean dil | build s | B/point |")
        lines.append("|---|---|---|---|---|---|---|---|---|")
        for r in sorted(rs, key=lambda r: (r["method"], r["preset"], r["A"])):
            lines.append(f"| {label(r)} | {r['A']:g} | {r['queries_per_s']:,.0f} | {r['recall']:.4f} | "
                         f"{r['fn_rate']:.4f} | {r['max_dilation']:.3f} | {r['mean_dilation']:.4f} | "
                         f"{r['build_s']:.3f} | {r['bytes_per_point']:.1f} |")
        exact = {r["method"]: r for r in rs if r["A"] == 0}
        for preset in sorted({r["preset"] for r in rs if r["method"] == "blockhash"}):
            bh = sorted((r for r in rs if r["method"] == "blockhash" and r["preset"] == preset),
                        key=lambda r: r["A"])
            ok = [r for r in bh if r["recall"] >= 0.95]
            lines.append("")
            if not ok:
                best = max(bh, key=lambda r: r["recall"]) if bh else None
                lines.append(f"blockhash-{preset}: recall@{k} never reaches 0.95"
                             + (f" (best {best['recall']:.4f} at A = {best['A']:g})" if best else ""))
                continue
            r = ok[0]
            ratios = ", ".join(f"{r['queries_per_s'] / e['queries_per_s']:.2f}x {m}"
                               for m, e in sorted(exact.items()) if e["queries_per_s"] > 0)
            lines.append(f"blockhash-{preset} at the smallest A with recall@{k} >= 0.95 (A = {r['A']:g}, "
                         f"recall {r['recall']:.4f}): {r['queries_per_s']:,.0f} queries/s = {ratios}")
        lines.append("")
    path = os.path.join(out, "summary.md")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv", nargs="+")
    ap.add_argument("--out", default=".")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    rows = load(a.csv)
    if not rows:
        print("plot.py: no rows", file=sys.stderr)
        return 1
    for p in plots(rows, a.out) + [summary(rows, a.out)]:
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
