#!/usr/bin/env python3
"""Python benchmark: blockhash_cl against scipy's cKDTree, pykdtree and Open3D, from numpy.

Same points and queries for every package (written by the C++ benchmarks' own loader,
build/bench/make_dataset). Per data set and search (kNN at each k, radius search at radii that
hold about 10 and 50 points per query), every variant runs once per round in a shuffled order;
the table gives per variant the median queries/s over the rounds and the median of the per-round
ratio to cKDTree's time in the same round (> 1: faster than cKDTree), with its min-max, and its
recall against the exact answer (blockhash_cl's kdtree, checked against cKDTree). Build times are
reported apart; the first call of each blockhash_cl variant (kernel compile) is not timed.

The packages compared are not dependencies of blockhash_cl: install them in the benchmark's own
environment, e.g.
    python3 -m venv --system-site-packages /tmp/pybench && /tmp/pybench/bin/pip install pykdtree open3d
    /tmp/pybench/bin/pip install .            # blockhash_cl itself
    /tmp/pybench/bin/python bench/python_bench.py --data bunny,cornell,autzen
(Open3D's wheel needs Debian's libusb-1.0-0.) A package that is missing is reported and skipped.
"""
import argparse
import os
import random
import subprocess
import sys
import tempfile
import time

import numpy as np

import blockhash_cl as bh

try:
    from scipy.spatial import cKDTree
except ImportError:  # pragma: no cover - the baseline is required
    sys.exit("python_bench: scipy is required (the baseline is scipy.spatial.cKDTree)")
try:
    from pykdtree.kdtree import KDTree as PyKDTree
except ImportError:
    PyKDTree = None
try:
    import open3d as o3d
    import open3d.core as o3c
except Exception:  # ImportError, or a missing shared library
    o3d = None


def load(make_dataset, name, n_points, n_queries, data_dir):
    with tempfile.TemporaryDirectory() as d:
        p, q = os.path.join(d, "p.npy"), os.path.join(d, "q.npy")
        cmd = [make_dataset, "--data", name, "--N", str(n_points), "--queries", str(n_queries),
               "--out-points", p, "--out-queries", q]
        if data_dir:
            cmd += ["--data-dir", data_dir]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"# {name}: make_dataset failed: {r.stdout.strip()} {r.stderr.strip()}: skipped")
            return None, None
        return np.load(p), np.load(q)


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def knn_recall(ids, truth_ids, k):
    hit = 0
    for a, b in zip(ids, truth_ids):
        hit += len(np.intersect1d(a[:k], b[:k], assume_unique=True))
    return hit / truth_ids[:, :k].size


def radius_recall(slices, truth):
    total = sum(len(t) for t in truth)
    hit = sum(len(np.intersect1d(a, t)) for a, t in zip(slices, truth))
    return hit / total if total else 1.0


def split(offsets, ids):
    return [ids[offsets[i]:offsets[i + 1]] for i in range(len(offsets) - 1)]


def run_rounds(variants, rounds, baseline):
    """variants: name -> callable returning (seconds, result). Returns name -> (times, ratios, last)."""
    stats = {v: ([], [], None) for v in variants}
    names = list(variants)
    for _ in range(rounds):
        random.shuffle(names)
        secs = {}
        for v in names:
            s, res = variants[v]()
            secs[v] = s
            stats[v] = (stats[v][0] + [s], stats[v][1], res)
        for v in variants:
            stats[v][1].append(secs[baseline] / secs[v])
    return stats


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="bunny,cornell,autzen")
    ap.add_argument("--N", type=int, default=1000000, help="points per set (file sets: the first N)")
    ap.add_argument("--queries", type=int, default=100000)
    ap.add_argument("--k", default="10,50")
    ap.add_argument("--A", default="2,8", help="blockhash_cl budgets A (examine A*k points per query)")
    ap.add_argument("--per-query", default="10,50", help="radius search: points per query the radii hold")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--make-dataset", default=os.path.join("build", "bench", "make_dataset"))
    ap.add_argument("--data-dir", default=os.environ.get("BHCL_DATA_DIR", ""))
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                    help="threads for cKDTree (workers) and pykdtree/Open3D (OMP_NUM_THREADS)")
    ap.add_argument("--markdown", default="", help="also write the table here")
    a = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    random.seed(12345)
    ks = [int(x) for x in a.k.split(",")]
    As = [float(x) for x in a.A.split(",")]
    per_query = [int(x) for x in a.per_query.split(",")]
    dev = bh.get_runtime().device
    lines = [f"# blockhash_cl {bh.__version__} on {dev['summary']}; numpy {np.__version__}; "
             f"cKDTree workers={a.threads}; pykdtree {'yes' if PyKDTree else 'missing'}; "
             f"Open3D {o3d.__version__ if o3d else 'missing'}; {a.rounds} rounds, shuffled",
             "| data | N | search | variant | build s | q/s (median) | vs cKDTree (median, min-max) | recall |",
             "|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)

    def row(*cells):
        line = "| " + " | ".join(str(c) for c in cells) + " |"
        lines.append(line)
        print(line, flush=True)

    for name in a.data.split(","):
        pts, qs = load(a.make_dataset, name, a.N, a.queries, a.data_dir)
        if pts is None:
            continue
        N, n = len(pts), len(qs)
        builds = {}
        builds["cKDTree"], tree = timed(lambda: cKDTree(pts))
        builds["blockhash_cl blockhash"], bhi = timed(lambda: bh.make_index("blockhash", pts))
        builds["blockhash_cl kdtree"], kdi = timed(lambda: bh.make_index("kdtree", pts))
        if PyKDTree:
            builds["pykdtree"], pyk = timed(lambda: PyKDTree(pts, leafsize=16))
        if o3d:
            def o3d_build():
                nns = o3c.nns.NearestNeighborSearch(o3c.Tensor(pts))
                nns.knn_index()
                return nns
            builds["Open3D"], nns = timed(o3d_build)
        for k in ks:
            # The exact answer: blockhash_cl's kdtree (identical to cKDTree up to ties).
            truth_d, truth_i = kdi.query(qs, k=k)
            variants = {
                "cKDTree": lambda: timed(lambda: tree.query(qs, k=k, workers=a.threads)[1]),
                "blockhash_cl kdtree": lambda: timed(lambda: kdi.query(qs, k=k)[1]),
            }
            for A in As:
                bhi.query(qs[:16], k=k, A=A)  # compiles the kernel variant: not timed
                variants[f"blockhash_cl blockhash A={A:g}"] = (lambda A=A: timed(lambda: bhi.query(qs, k=k, A=A)[1]))
            kdi.query(qs[:16], k=k)
            if PyKDTree:
                variants["pykdtree"] = lambda: timed(lambda: pyk.query(qs, k=k)[1])
            if o3d:
                qt = o3c.Tensor(qs)
                variants["Open3D"] = lambda: timed(lambda: nns.knn_search(qt, k)[0].numpy())
            st = run_rounds(variants, a.rounds, "cKDTree")
            for v, (times, ratios, res) in st.items():
                res = np.asarray(res).reshape(n, k)
                rec = knn_recall(res, truth_i, k)
                bkey = v if v in builds else ("blockhash_cl blockhash" if "blockhash A=" in v else v)
                row(name, N, f"kNN k={k}", v, f"{builds.get(bkey, 0):.2f}", f"{n / np.median(times):.0f}",
                    f"{np.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})", f"{rec:.4f}")
        # Radius search at radii holding about `t` points per query (median distance to the t-th).
        for t in per_query:
            d, _ = kdi.query(qs[:2000], k=min(t, bh.MAX_K))
            r = float(np.sqrt(np.median(d[:, -1])))
            o_t, _, i_t = kdi.radius_search(qs, r)
            truth = split(o_t, i_t)
            variants = {
                "cKDTree": lambda: timed(lambda: tree.query_ball_point(qs, r, workers=a.threads, return_sorted=False)),
                "blockhash_cl kdtree": lambda: timed(lambda: kdi.radius_search(qs, r)),
                "blockhash_cl blockhash": lambda: timed(lambda: bhi.radius_search(qs, r)),
            }
            bhi.radius_search(qs[:16], r)
            if o3d:
                qt = o3c.Tensor(qs)
                nns.fixed_radius_index(r)
                variants["Open3D"] = lambda: timed(lambda: nns.fixed_radius_search(qt, r))
            st = run_rounds(variants, a.rounds, "cKDTree")
            mean = o_t[-1] / n
            for v, (times, ratios, res) in st.items():
                if v == "cKDTree":
                    slices = [np.asarray(s) for s in res]
                elif v == "Open3D":
                    idx, _, splits = res
                    slices = split(splits.numpy(), idx.numpy())
                else:
                    slices = split(res[0], res[2])
                rec = radius_recall(slices, truth)
                row(name, N, f"radius r={r:.4g} ({mean:.1f}/query)", v, "", f"{n / np.median(times):.0f}",
                    f"{np.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})", f"{rec:.4f}")
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
