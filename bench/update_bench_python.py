#!/usr/bin/env python3
"""Python's Index.add / Index.remove against the library's own insert / remove (issue 39).

A block-hash index over N uniform points, then a sequence of adds (each --frac of N) and removes
(each --frac of N, random live ids), every call timed twice in the same call: the Python wall
time of Index.add / Index.remove, and the time of the C++ call inside it (the extension's
Index.insert / Index.remove, which is bhcl::Index::insert / remove behind pybind11's argument
conversion: timed by a proxy put in place of the wrapper's _impl). The table gives per operation
the medians and the median and largest ratio Python / C++ over the calls. No test times this
(timings on a shared machine are noisy); it is a report.

    POCL_MAX_PTHREAD_COUNT=2 PYTHONPATH=build-py/python /usr/bin/python3 bench/update_bench_python.py
"""
import argparse
import statistics
import sys
import time

import numpy as np


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=1_000_000, help="points of the build")
    ap.add_argument("--frac", type=float, default=0.01, help="share of N per add / remove")
    ap.add_argument("--calls", type=int, default=15, help="adds, then as many removes")
    ap.add_argument("--method", default="blockhash", help="the index's method")
    a = ap.parse_args(argv)
    if a.N < 1000 or not (0 < a.frac <= 0.5) or a.calls < 1:
        ap.error("need --N >= 1000, 0 < --frac <= 0.5, --calls >= 1")
    import blockhash_cl as bh

    rng = np.random.default_rng(39)
    ix = bh.make_index(a.method, rng.random((a.N, 3), dtype=np.float32))
    m = max(1, int(a.frac * a.N))

    class Timed:
        """The extension's index, its insert and remove timed; everything else passed through."""

        def __init__(self, impl):
            object.__setattr__(self, "impl", impl)
            object.__setattr__(self, "last", 0.0)

        def __getattr__(self, name):
            return getattr(self.impl, name)

        def insert(self, *args):
            t0 = time.perf_counter()
            try:
                return self.impl.insert(*args)
            finally:
                object.__setattr__(self, "last", time.perf_counter() - t0)

        def remove(self, *args):
            t0 = time.perf_counter()
            try:
                return self.impl.remove(*args)
            finally:
                object.__setattr__(self, "last", time.perf_counter() - t0)

    timed = Timed(ix._impl)
    ix._impl = timed

    rows = {"add": [], "remove": []}
    for _ in range(a.calls):
        pts = rng.random((m, 3), dtype=np.float32)
        t0 = time.perf_counter()
        ix.add(pts)
        py = time.perf_counter() - t0
        rows["add"].append((py, timed.last))
    alive = np.ones(ix.id_bound, bool)
    for _ in range(a.calls):
        ids = rng.choice(np.flatnonzero(alive), size=m, replace=False).astype(np.int32)
        alive[ids] = False
        t0 = time.perf_counter()
        ix.remove(ids)
        py = time.perf_counter() - t0
        rows["remove"].append((py, timed.last))
    print(f"# update_bench_python  method {a.method}  N {a.N}  {a.calls} adds of {m} points, then {a.calls} removes of {m} ids")
    print(f"{'op':8} {'py_med_ms':>10} {'cpp_med_ms':>11} {'ratio_med':>10} {'ratio_max':>10}")
    for op, r in rows.items():
        ok = [(p, c) for p, c in r if c > 0]
        ratios = [p / c for p, c in ok]
        print(f"{op:8} {1e3 * statistics.median(p for p, _ in ok):10.3f} {1e3 * statistics.median(c for _, c in ok):11.3f} "
              f"{statistics.median(ratios):10.3f} {max(ratios):10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
