#!/usr/bin/env python3
"""The float64 refinement's cost on issue 40's UTM case, variants compared in one process.

Points and queries uniform in a 100 m cube at (512345.678, 4312345.678, 112.5) m (as
`python_bench.py --utm`). Per exact method and k, every round runs, in an order that alternates
round by round:
  refined        the default refined query (make_index's refine for such points);
  refined-plain  the same without the output buffer pool and the prefetch (BHCL_REFINE_POOL=0,
                 BHCL_REFINE_PREFETCH=0) and with _refine.query_delta in numpy: the refinement as
                 it was before issue 40's step 2, less its two (n, k) np.full passes and its np.sum
                 of the found ids;
  float32        the unrefined index (refine=False) over the same points: the search alone.
The table gives per variant the median over the rounds of refine_share (the refinement's part of
the call's wall time, its stats), refine_cpu_share (its part of the process's CPU time over the
call) and refine_s, and the medians of the per-round ratios of its wall and CPU time to float32's
in the same round (the whole cost of float64 answers, the k + 1-th candidate included).

    python3 bench/refine_bench.py --n 200000 --queries 200000 --k 1,10,50 --rounds 5 --markdown out.md

Set POCL_MAX_PTHREAD_COUNT to the cores to use and quote it with the figures.
"""
import argparse
import json
import os
import platform
import sys
import time

import numpy as np

import blockhash_cl as bh
from blockhash_cl import _refine

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from python_bench import write_atomic  # noqa: E402  (the benches' one atomic writer)


def run_variant(name, index, q, k):
    """(wall s, process CPU s, stats) of one query call of variant `name`."""
    fast_delta = _refine.query_delta
    if name == "refined-plain":
        os.environ["BHCL_REFINE_POOL"] = "0"
        os.environ["BHCL_REFINE_PREFETCH"] = "0"
        _refine.query_delta = _refine._query_delta_numpy
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        index.query(q, k=k)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        os.environ.pop("BHCL_REFINE_POOL", None)
        os.environ.pop("BHCL_REFINE_PREFETCH", None)
        _refine.query_delta = fast_delta
    return wall, cpu, dict(index.last_stats)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=200000)
    ap.add_argument("--queries", type=int, default=200000)
    ap.add_argument("--k", default="1,10,50")
    ap.add_argument("--methods", default="kdtree,flann,blockhash")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--markdown", default="")
    ap.add_argument("--json", default="", help="also write the per-round records here (refine_old_new.py)")
    a = ap.parse_args()
    rng = np.random.default_rng(40)
    base = np.array([512345.678, 4312345.678, 112.5])
    pts = base + rng.random((a.n, 3)) * 100.0
    qs = base + rng.random((a.queries, 3)) * 100.0
    lines = [f"# Refinement cost, UTM case: {a.n} points, {a.queries} queries; blockhash_cl {bh.__version__} on "
             f"{bh.get_runtime().device['summary']}; POCL_MAX_PTHREAD_COUNT="
             f"{os.environ.get('POCL_MAX_PTHREAD_COUNT', 'unset')}, {os.cpu_count()} CPUs ({platform.processor() or 'cpu'}); "
             f"median of {a.rounds} rounds",
             "| method | k | variant | refine_share | refine_cpu_share | refine_s | wall / float32 wall (min-max) "
             "| CPU / float32 CPU | wall s |",
             "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    variants = ["refined", "refined-plain", "float32"]
    records = []
    for method in [m for m in a.methods.split(",") if m in bh.method_names()]:
        refined = bh.make_index(method, pts)
        plain = bh.make_index(method, pts, refine=False)
        assert refined.refined and not plain.refined
        for k in [int(x) for x in a.k.split(",")]:
            # Warm-up: the kernels of k + 1 and of a re-search's 2 (k + 1) candidates compiled.
            for idx, kk in ((refined, k), (plain, k), (plain, min(bh.MAX_K, 2 * (k + 1)))):
                idx.query(qs[:64], k=kk)
            rec = {v: {"wall": [], "share": [], "cshare": [], "rs": [], "rcpu": [], "ratio": [], "cratio": []} for v in variants}
            for r in range(a.rounds):
                order = variants if r % 2 == 0 else variants[::-1]
                walls, cpus = {}, {}
                for v in order:
                    wall, cpu, st = run_variant(v, plain if v == "float32" else refined, qs, k)
                    walls[v], cpus[v] = wall, cpu
                    rec[v]["wall"].append(wall)
                    rec[v]["share"].append(st.get("refine_share", 0.0))
                    rec[v]["cshare"].append(st.get("refine_cpu_share", 0.0))
                    rec[v]["rs"].append(st.get("refine_s", 0.0))
                    rec[v]["rcpu"].append(st.get("refine_cpu_s", 0.0))
                for v in variants:
                    rec[v]["ratio"].append(walls[v] / walls["float32"])
                    rec[v]["cratio"].append(cpus[v] / cpus["float32"])
            records.append({"method": method, "k": k, "rec": rec})
            for v in variants:
                x = rec[v]
                line = (f"| {method} | {k} | {v} | {np.median(x['share']):.3f} | {np.median(x['cshare']):.3f} | "
                        f"{np.median(x['rs']):.4f} | "
                        f"{np.median(x['ratio']):.2f} ({min(x['ratio']):.2f}-{max(x['ratio']):.2f}) | "
                        f"{np.median(x['cratio']):.2f} | {np.median(x['wall']):.3f} |")
                lines.append(line)
                print(line, flush=True)
    if a.markdown:
        write_atomic(a.markdown, "\n".join(lines) + "\n")
    if a.json:
        write_atomic(a.json, json.dumps({"header": lines[0], "records": records}))


if __name__ == "__main__":
    main()
