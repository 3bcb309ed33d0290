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
Two other modes (issue 40): --front compares blockhash_cl.KDTree, the scipy-compatible front,
with scipy's KDTree (workers=-1), pykdtree and napf (pip install pykdtree napf), with recall@k
against scipy beside every time, builds and first calls apart; --utm N measures the float64
refinement on the UTM-like case (docs/PYTHON.md has both tables and their commands).
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


class Table:
    """A Markdown table printed as it grows (a row at a time), its lines kept for the output file."""

    def __init__(self, title, columns):
        self.lines = [title, "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        print("\n".join(self.lines), flush=True)

    def row(self, *cells):
        line = "| " + " | ".join(str(c) for c in cells) + " |"
        self.lines.append(line)
        print(line, flush=True)


def write_atomic(path, text):
    """The table to `path` through a temporary beside it and a rename (never half a file)."""
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


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


def recall_at_k(ids, truth_ids):
    """The share of the reference's indices that a row returned, over all rows ((n, k) arrays of
    indices distinct within a row, as an exact kNN answer's are): rows sorted side by side, a match
    is a value met twice."""
    both = np.sort(np.concatenate([ids, truth_ids], axis=1), axis=1)
    return float(np.count_nonzero(both[:, 1:] == both[:, :-1])) / truth_ids.size


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


def utm(a):
    """Issue 40's float64 case: points in a 100 m patch at 4.3e6 m (UTM-like), queries over the
    patch; per exact method and k, the share of rows equal to scipy's float64 answer at rel 1e-9
    (distances, and indices where scipy's distances do not tie), refined (the default for such
    points) and not (refine=False), the refinement's share of the call (stats refine_share) and
    the refined call's time against the unrefined one's; then the KDTree front against scipy's
    KDTree (workers=-1)."""
    from scipy.spatial import KDTree as SciKDTree
    rng = np.random.default_rng(40)
    base = np.array([512345.678, 4312345.678, 112.5])
    pts = base + rng.random((a.utm, 3)) * 100.0
    qs = base + rng.random((a.queries, 3)) * 100.0
    tree = cKDTree(pts)
    methods = [m for m in ("bruteforce", "kdtree", "flann", "blockhash") if m in bh.method_names()]
    lines = [f"# UTM case: {a.utm} points, {a.queries} queries in a 100 m patch at 4.3e6 m; blockhash_cl "
             f"{bh.__version__} on {bh.get_runtime().device['summary']}; median of {a.rounds} rounds",
             "| method | search | rows right, refined | rows right, float32 | refine_share | refined s | unrefined s |",
             "|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)

    def right(d, ids, rd, ri):
        close = np.abs(d - rd) <= 1e-9 * np.maximum(rd, 1e-300)
        tie = (rd == np.roll(rd, 1, axis=1)) | (rd == np.roll(rd, -1, axis=1))
        return float(np.mean(np.all(close & ((ids == ri) | tie), axis=1)))

    for method in methods:
        q = qs if method != "bruteforce" else qs[: max(1, a.queries // 20)]
        ref64 = bh.make_index(method, pts)
        ref32 = bh.make_index(method, pts, refine=False)
        for k in [int(x) for x in a.k.split(",")]:
            rd, ri = tree.query(q, k=k, workers=-1)
            rd, ri = rd.reshape(len(q), k), ri.reshape(len(q), k)
            ref64.query(q[:16], k=k)
            ref32.query(q[:16], k=k)
            t64, t32, share = [], [], []
            for _ in range(a.rounds):
                s, (d2, ids, st) = timed(lambda: ref64.query(q, k=k, return_stats=True))
                t64.append(s)
                share.append(st["refine_share"])
                s, (d2b, idb) = timed(lambda: ref32.query(q, k=k))
                t32.append(s)
            line = (f"| {method} | kNN k={k} | {right(np.sqrt(d2), ids, rd, ri):.6f} | "
                    f"{right(np.sqrt(d2b.astype(np.float64)), idb, rd, ri):.6f} | {np.median(share):.3f} | "
                    f"{np.median(t64):.3f} | {np.median(t32):.3f} |")
            lines.append(line)
            print(line, flush=True)
        r = 2.0
        truth = tree.query_ball_point(q, r, workers=-1)
        s64, res = timed(lambda: ref64.radius_search(q, r))
        st = ref64.last_stats
        s32, _ = timed(lambda: ref32.radius_search(q, r))
        ok = 0
        for j in range(len(q)):
            d2, ids = res.slice(j)
            want = np.array(sorted(truth[j]), dtype=np.int64)
            exact = np.sum((pts[ids] - q[j]) ** 2, axis=1)
            ok += np.array_equal(np.sort(ids), want) and np.allclose(d2, exact, rtol=1e-9, atol=0)
        line = f"| {method} | radius r={r} | {ok / len(q):.6f} | - | {st['refine_share']:.3f} | {s64:.3f} | {s32:.3f} |"
        lines.append(line)
        print(line, flush=True)
    # The front against scipy's KDTree, k = 10.
    front = bh.KDTree(pts)
    sci = SciKDTree(pts)
    front.query(qs[:16], k=10)
    tf = [timed(lambda: front.query(qs, k=10))[0] for _ in range(a.rounds)]
    ts = [timed(lambda: sci.query(qs, k=10, workers=-1))[0] for _ in range(a.rounds)]
    d, i = front.query(qs, k=10)
    rd, ri = sci.query(qs, k=10, workers=-1)
    line = (f"| KDTree front (blockhash) vs scipy KDTree workers=-1 | kNN k=10 | {right(d, i, rd, ri):.6f} | - | - | "
            f"{np.median(tf):.3f} | scipy {np.median(ts):.3f} |")
    lines.append(line)
    print(line, flush=True)
    if a.markdown:
        write_atomic(a.markdown, "\n".join(lines) + "\n")


def front(a):
    """Issue 40's drop-in comparison: blockhash_cl.KDTree (scipy's interface, float64 answers; the
    default method "blockhash" and method="kdtree") against scipy.spatial.KDTree (workers=-1),
    pykdtree (OMP_NUM_THREADS) and napf (nthread) where installed, all on the same float64 points
    and queries. Per data set, query kind ("data": the points themselves, shuffled; "box": uniform
    over the points' bounding box) and k: every variant once per round in a shuffled order, the
    median query time, the median of the per-round ratios scipy time / variant time (> 1: faster
    than scipy) with its min-max, recall@k against scipy's answers (the share of scipy's k indices
    returned) and the share of rows equal to scipy's (indices, and distances at rel 1e-9, either
    order where scipy's distances tie). Apart from the query time: each build (median of
    --build-rounds interleaved builds) and each variant's first call on the query set at a k (the
    query itself included), which for blockhash_cl compiles the kernels for that k: with
    --cold-cache (the default) the kernel caches start empty, so a kernel's first compile shows in
    the first data set's rows (later ones load it from the process's or the disk cache)."""
    from scipy.spatial import KDTree as SciKDTree
    import scipy
    try:
        import napf
    except ImportError:
        napf = None
    threads = os.cpu_count() or 1  # what scipy's workers=-1 uses
    os.environ["OMP_NUM_THREADS"] = os.environ.get("OMP_NUM_THREADS") or str(threads)
    ver = lambda m: getattr(m, "__version__", "?")
    try:
        from importlib import metadata
        pyk_ver = metadata.version("pykdtree") if PyKDTree else "missing"
        napf_ver = metadata.version("napf") if napf else "missing"
    except Exception:  # pragma: no cover - metadata of an odd install
        pyk_ver = napf_ver = "?"
    table = Table(f"# blockhash_cl {bh.__version__} KDTree on {bh.get_runtime().device['summary']}, "
                  f"POCL_MAX_PTHREAD_COUNT={os.environ.get('POCL_MAX_PTHREAD_COUNT', 'unset')}; "
                  f"scipy {ver(scipy)} KDTree workers=-1 ({threads} threads); pykdtree {pyk_ver} "
                  f"(OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}); napf {napf_ver} (nthread={threads}); "
                  f"kernel caches {'cold (empty at start)' if a.cold_cache else 'as found'}; "
                  f"{a.rounds} query rounds, {a.build_rounds} build rounds, interleaved, median; "
                  f"load average at start {os.getloadavg()[0]:.1f}",
                  ["data", "N", "queries", "k", "variant", "build s", "first call s", "query s",
                   "vs scipy (median, min-max)", "recall@k", "rows = scipy's"])
    lines, row = table.lines, table.row
    rng = np.random.default_rng(40)
    ks = [int(x) for x in a.k.split(",")]

    builders = {
        "scipy KDTree": lambda p: SciKDTree(p),
        "blockhash_cl KDTree": lambda p: bh.KDTree(p),
        "blockhash_cl KDTree (kdtree)": lambda p: bh.KDTree(p, method="kdtree"),
    }
    if PyKDTree:
        builders["pykdtree"] = lambda p: PyKDTree(p, leafsize=16)
    if napf:
        builders["napf"] = lambda p: napf.KDT(p, metric=2)

    def querier(v, tree, qs, k):
        """The variant's call, returning (distances, indices): Euclidean distances everywhere
        (napf returns squared ones)."""
        if v == "scipy KDTree":
            return lambda: tree.query(qs, k=k, workers=-1)
        if v == "pykdtree":
            return lambda: tree.query(qs, k=k)
        if v == "napf":
            def napf_q():
                d2, i = tree.knn_search(qs, k, threads)
                return np.sqrt(d2), i
            return napf_q
        return lambda: tree.query(qs, k=k)

    for name in a.data.split(","):
        pts, _ = load(a.make_dataset, name, a.N, 1, a.data_dir)
        if pts is None:
            continue
        pts = np.ascontiguousarray(pts, np.float64)
        n = min(a.queries, len(pts))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        query_sets = {"data": pts[rng.permutation(len(pts))[:n]], "box": lo + rng.random((n, 3)) * (hi - lo)}
        # Builds: interleaved rounds, the last round's trees kept.
        build_st = run_rounds({v: (lambda f=f: timed(lambda: f(pts))) for v, f in builders.items()},
                              a.build_rounds, "scipy KDTree")
        trees = {v: res for v, (_, _, res) in build_st.items()}
        build_s = {v: float(np.median(t)) for v, (t, _, _) in build_st.items()}
        for qname, qs in query_sets.items():
            for k in ks:
                # The first call of each variant on the whole set, untimed in the rounds: for
                # blockhash_cl it compiles the kernels this k needs (the kNN kernel, and the radius
                # kernel where the float64 refinement searches a near-tie row again), which a call
                # of a few queries does not reach.
                first = {v: timed(querier(v, trees[v], qs, k))[0] for v in builders}
                variants = {v: querier(v, trees[v], qs, k) for v in builders}
                st = run_rounds({v: (lambda f=f: timed(f)) for v, f in variants.items()}, a.rounds, "scipy KDTree")
                rd, ri = (np.asarray(x).reshape(n, k) for x in st["scipy KDTree"][2])
                tie = (rd == np.roll(rd, 1, axis=1)) | (rd == np.roll(rd, -1, axis=1))
                for v, (times, ratios, res) in st.items():
                    d, i = (np.asarray(x).reshape(n, k) for x in res)
                    close = np.abs(d - rd) <= 1e-9 * np.maximum(rd, 1e-300)
                    same = float(np.mean(np.all(close & ((i == ri) | tie), axis=1)))
                    recall = recall_at_k(i.astype(np.int64), ri.astype(np.int64))
                    row(name, len(pts), qname, k, v, f"{build_s[v]:.3f}", f"{first[v]:.3f}", f"{np.median(times):.3f}",
                        f"{np.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})", f"{recall:.4f}", f"{same:.4f}")
        del trees, build_st
    lines.append(f"(load average at the end {os.getloadavg()[0]:.1f})")
    print(lines[-1], flush=True)
    if a.markdown:
        write_atomic(a.markdown, "\n".join(lines) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--front", action="store_true",
                    help="compare the scipy-compatible blockhash_cl.KDTree with scipy's KDTree, pykdtree and napf "
                         "(uses --data, --N, --queries, --k, --rounds, --threads, --markdown)")
    ap.add_argument("--utm", type=int, default=0,
                    help="run issue 40's float64 case instead (this many points, e.g. 200000): rows right at "
                         "rel 1e-9 refined and not, refine_share; uses --queries, --k, --rounds, --markdown")
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
    ap.add_argument("--build-rounds", type=int, default=3, help="--front: interleaved builds per data set")
    ap.add_argument("--cold-cache", type=int, default=1,
                    help="--front: 1 (default) starts with empty kernel caches (BHCL_CACHE_DIR and POCL_CACHE_DIR in a "
                         "temporary directory, removed at exit), so the first calls include the kernels' compile; 0 "
                         "uses the caches as found")
    a = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    if a.utm:
        return utm(a)
    if a.front:
        if not a.cold_cache:
            return front(a)
        with tempfile.TemporaryDirectory(prefix="bhcl-bench-cache-") as d:
            os.environ["BHCL_CACHE_DIR"] = os.path.join(d, "blockhash_cl")
            os.environ["POCL_CACHE_DIR"] = os.path.join(d, "pocl")
            return front(a)
    random.seed(12345)
    ks = [int(x) for x in a.k.split(",")]
    As = [float(x) for x in a.A.split(",")]
    per_query = [int(x) for x in a.per_query.split(",")]
    dev = bh.get_runtime().device
    table = Table(f"# blockhash_cl {bh.__version__} on {dev['summary']}; numpy {np.__version__}; "
                  f"cKDTree workers={a.threads}; pykdtree {'yes' if PyKDTree else 'missing'}; "
                  f"Open3D {o3d.__version__ if o3d else 'missing'}; {a.rounds} rounds, shuffled",
                  ["data", "N", "search", "variant", "build s", "q/s (median)", "vs cKDTree (median, min-max)", "recall"])
    lines, row = table.lines, table.row

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
        write_atomic(a.markdown, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
