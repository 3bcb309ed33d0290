#!/usr/bin/env python3
"""Python's add / remove against the library's own insert / remove (issues 39 and 40).

An index over N uniform points, then a sequence of adds (each --frac of N) and removes (each
--frac of N, random live ids), every call timed twice in the same call: the Python wall time of
add / remove, and the time of the C++ call inside it (the extension's insert / remove, which is
the library's insert / remove behind pybind11's argument conversion: timed by a proxy put in
place of the wrapper's _impl). The table gives per operation the medians and the median and
largest ratio Python / C++ over the calls. No test times this (timings on a shared machine are
noisy); it is a report.

    POCL_MAX_PTHREAD_COUNT=2 PYTHONPATH=<the built package> /usr/bin/python3 bench/update_bench_python.py

--distributed: the same on a blockhash_cl.DistributedIndex, run under mpirun (every rank adds
its share of each add, a point set over the whole box, and removes its share of the ids; a
barrier before each timed call); each rank times its own calls, rank 0 prints every rank's rows.
The Python side there includes the layer's agreement over the ranks (one mpi_agree and one
allreduce per call), the C++ side is the library's collective insert / remove.

    mpirun -np 2 --oversubscribe -x POCL_MAX_PTHREAD_COUNT=1 -x PYTHONPATH /usr/bin/python3 \\
        bench/update_bench_python.py --distributed --method kdtree
"""
import argparse
import statistics
import sys
import time

import numpy as np


class Timed:
    """The extension's index with its insert and remove timed (`last`: the latest call's
    seconds); everything else passed through."""

    TIMED = ("insert", "remove")

    def __init__(self, impl):
        object.__setattr__(self, "impl", impl)
        object.__setattr__(self, "last", 0.0)

    def __getattr__(self, name):
        fn = getattr(self.impl, name)
        if name not in Timed.TIMED:
            return fn

        def timed(*args):
            t0 = time.perf_counter()
            try:
                return fn(*args)
            finally:
                object.__setattr__(self, "last", time.perf_counter() - t0)
        return timed


def timed_calls(ix, timed, calls, m, rng, share, id_dtype, sync):
    """`calls` adds of m points then `calls` removes of m live ids (of the index's id type):
    {op: [(python_s, cpp_s)]}. share(a) is this process's part of an array every process draws
    alike; sync() runs before each timed call (the ranks' barrier: a rank that arrives first
    would otherwise count its wait for the others as the Python layer's time)."""
    rows = {"add": [], "remove": []}
    alive = np.ones(ix.id_bound, bool)
    for _ in range(calls):
        pts = share(rng.random((m, 3), dtype=np.float32))
        sync()
        t0 = time.perf_counter()
        ix.add(pts)
        rows["add"].append((time.perf_counter() - t0, timed.last))
    alive = np.concatenate([alive, np.ones(ix.id_bound - len(alive), bool)])
    for _ in range(calls):
        ids = rng.choice(np.flatnonzero(alive), size=m, replace=False)
        alive[ids] = False
        mine = share(ids).astype(id_dtype)
        sync()
        t0 = time.perf_counter()
        ix.remove(mine)
        rows["remove"].append((time.perf_counter() - t0, timed.last))
    return rows


def table(rows, label=""):
    """The medians and the median / largest ratio Python / C++ per operation, as text lines."""
    out = [f"{'op':8} {'py_med_ms':>10} {'cpp_med_ms':>11} {'ratio_med':>10} {'ratio_max':>10}{label and '  rank'}"]
    for op, r in rows.items():
        ok = [(p, c) for p, c in r if c > 0]
        ratios = [p / c for p, c in ok]
        out.append(f"{op:8} {1e3 * statistics.median(p for p, _ in ok):10.3f} "
                   f"{1e3 * statistics.median(c for _, c in ok):11.3f} {statistics.median(ratios):10.3f} "
                   f"{max(ratios):10.3f}{label and '  ' + label}")
    return out


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=1_000_000, help="points of the build")
    ap.add_argument("--frac", type=float, default=0.01, help="share of N per add / remove")
    ap.add_argument("--calls", type=int, default=15, help="adds, then as many removes")
    ap.add_argument("--method", default="blockhash", help="the index's method")
    ap.add_argument("--distributed", action="store_true", help="a DistributedIndex, under mpirun")
    a = ap.parse_args(argv)
    if a.N < 1000 or not (0 < a.frac <= 0.5) or a.calls < 1:
        ap.error("need --N >= 1000, 0 < --frac <= 0.5, --calls >= 1")
    import blockhash_cl as bh

    rng = np.random.default_rng(39)  # the same draws in every process
    pts = rng.random((a.N, 3), dtype=np.float32)
    m = max(1, int(a.frac * a.N))
    if a.distributed:
        from mpi4py import MPI
        comm = MPI.COMM_WORLD
        rank, ranks = comm.Get_rank(), comm.Get_size()

        def share(x):
            return x[rank * len(x) // ranks:(rank + 1) * len(x) // ranks]

        ix = bh.DistributedIndex(a.method, share(pts), comm)
        sync = comm.Barrier
    else:
        rank, ranks = 0, 1

        def share(x):
            return x

        ix = bh.make_index(a.method, pts)

        def sync():
            pass
    timed = Timed(ix._impl)
    ix._impl = timed
    rows = timed_calls(ix, timed, a.calls, m, rng, share, np.int64 if a.distributed else np.int32, sync)
    kind = f"DistributedIndex over {ranks} ranks" if a.distributed else "Index"
    lines = table(rows, f"{rank}" if a.distributed else "")
    if a.distributed:
        gathered = comm.gather(lines[1:], root=0)
        if rank != 0:
            return 0
        lines = lines[:1] + [line for part in gathered for line in part]
    print(f"# update_bench_python  {kind}  method {a.method}  N {a.N}  {a.calls} adds of {m} points, "
          f"then {a.calls} removes of {m} ids")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
