#!/usr/bin/env python3
"""Plots `bhcl render --compare` stats with several density estimators (--estimator/--filter lists):
left, each estimator's block-hashing image error against the exact render with the same estimator,
by A, with the photon-seed noise floor; right (when --reference was given), each estimator's exact
render against the independent reference: block error and mean bias, beside another render seed's.

    python3 plot_estimators.py STATS.json OUT.png

Needs matplotlib (the benchmark venv: pip install matplotlib)."""
import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(stats_path, out_path):
    with open(stats_path) as f:
        j = json.load(f)
    ests = j["estimators"]
    colours = {"kth": "tab:blue", "mean": "tab:orange", "var": "tab:green"}
    styles = {"box": ":", "cone": "-", "epanechnikov": "--"}
    has_ref = all("vs_reference" in e for e in ests)
    fig, axes = plt.subplots(1, 2 if has_ref else 1, figsize=(13 if has_ref else 7, 5.2), squeeze=False)
    ax = axes[0][0]
    floors = []
    for e in ests:
        runs = [r for r in e["runs"] if r["method"] != j["exact"]]
        A = [r["A"] for r in runs]
        err = [100 * r["relative_rmse"] for r in runs]
        ax.plot(A, err, styles[e["filter"]], color=colours[e["radius"]], marker="o", label=e["estimator"])
        floors += [100 * n["relative_rmse"] for n in e["noise_floor"] if "photon seed" in n["what"]]
    if floors:
        lo, hi = min(floors), max(floors)
        ax.axhspan(lo, hi, color="grey", alpha=0.3, label=f"photon-seed noise of the exact render ({lo:.1f}-{hi:.1f}%)")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("block hashing A (candidates examined, in units of k)")
    ax.set_ylabel("relative RMSE vs the exact render, same estimator (%)")
    ax.set_title(f"Block hashing's image error by density estimator\n{j['scene']} {j['width']}x{j['height']}, "
                 f"{j['spp']} spp, {j['photons']} photons, k={j['k']}, {j['gather']} gather rays")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if has_ref:
        ax = axes[0][1]
        names = [e["estimator"] for e in ests]
        x = range(len(names))
        block = [100 * e["vs_reference"]["block_relative_rmse"] for e in ests]
        bias = [100 * e["vs_reference"]["mean_bias"] for e in ests]
        seed = [100 * e["vs_reference"].get("render_seed_block_relative_rmse", float("nan")) for e in ests]
        w = 0.27
        ax.bar([i - w for i in x], block, w, label="block rel. RMSE vs reference", color="tab:blue")
        ax.bar(list(x), seed, w, label="the same, another render seed (noise)", color="tab:grey")
        ax.bar([i + w for i in x], bias, w, label="mean bias vs reference", color="tab:red")
        ax.axhline(0, color="black", lw=0.8)
        ax.set_xticks(list(x))
        ax.set_xticklabels(names, rotation=35, ha="right", fontsize=8)
        ax.set_ylabel("%")
        b = ests[0]["vs_reference"]["block"]
        ax.set_title(f"Exact render vs the path-traced reference\n(blocks of {b}x{b} pixels, emitter blocks left out)")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_path, dpi=110)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
