#!/usr/bin/env python3
"""End-to-end benchmark (issue 37, part 2): the whole call against the kernel, and against the
kd-tree's whole call, for `bhcl knn` and for the Python `Index.query`.

Rows: each query count (--sizes, the first n of --queries) and each k (--k), exact mode (the grid
layout's default), dispatched in Hilbert order (the default). Per row and round, the methods run
in a shuffled order:
  - bhcl knn: one process per run (each run pays its program build: from the library's program
    binary cache once a first run stored it, beside reading its inputs), its --stats file's
    "stages" read back; the search wall is the stats' wall_s (the query call with its output
    files' appends, and any wait for that program), kernel_s the kernel's event time;
  - Python: one process for all rounds, both indexes built once; the search wall is the stats
    dict's wall_s (the library call), kernel query_s. The first call of each (method, k) in the
    process is a warm-up (its compile) and not counted.
The table gives the median over the rounds of the per-round ratios: wall / kernel for block
hashing (the target: <= 1.15) and the kd-tree's wall / block hashing's wall (>= 1.5), with their
min-max, and the median stages of block hashing's runs.

    POCL_MAX_PTHREAD_COUNT=2 /usr/bin/python3 bench/e2e_bench.py --bhcl build/host/bhcl \\
        --points POINTS.npy --queries QUERIES.npy --python-path DIR --out bench/results/e2e/cornell1m.md
(POINTS/QUERIES from build/bench/make_dataset --data cornell --N 1000000 --queries 1000000.)
"""
import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile

import numpy as np

# What the table's "search wall" is, written under its command.
SEARCH_WALL = ("Search wall: for `bhcl knn`, the stats file's `stages.wall_s`: the query call with its output "
               "files' appends (binary .npy; where the file system takes O_DIRECT, ids and dist2 stored by the "
               "search into two page-aligned buffers per slice whose writes run beside the next slice's search: "
               "the write stage is those buffers made present and the last slice's write; else the files mapped "
               "and stored into) and any wait for the kNN program built beside reading the inputs (in "
               "`compile`), not their commit "
               "(flush to the disk and rename, `stages.commit_s`); for Python, the stats dict's `wall_s`: the "
               "library call (the arrays go to numpy without a copy). kernel: the kernel's event time. "
               "other: the wall less every named stage (the call's set-up, locks, the first touch of fresh "
               "result pages outside the kernel).")

STAGES = ["compile_s", "sort_s", "upload_s", "kernel_s", "download_s", "unsort_s", "write_s", "other_s"]


def med(xs):
    return statistics.median(xs) if xs else float("nan")


def span(xs):
    return f"{med(xs):.2f} ({min(xs):.2f}-{max(xs):.2f})" if xs else "-"


def bhcl_run(bhcl, points, queries, method, k, tmp):
    stats = os.path.join(tmp, "stats.json")
    cmd = [bhcl, "knn", "--points", points, "--queries", queries, "--method", method, "--k", str(k),
           "--out-ids", os.path.join(tmp, "ids.npy"), "--out-dist2", os.path.join(tmp, "d2.npy"),
           "--stats", stats, "--quiet"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    with open(stats) as f:
        return json.load(f)


def bench_cli(args, sizes, ks, tmp, all_q):
    rows = []
    for n in sizes:
        qpath = os.path.join(tmp, f"q{n}.npy")
        np.save(qpath, all_q[:n])
        for k in ks:
            wk, speed, stages = [], [], {s: [] for s in STAGES}
            for r in range(args.rounds + 1):  # round 0: stores the program binaries, not counted
                order = ["blockhash", "kdtree"]
                random.shuffle(order)
                got = {m: bhcl_run(args.bhcl, args.points, qpath, m, k, tmp) for m in order}
                if r == 0:
                    continue
                bh, kd = got["blockhash"], got["kdtree"]
                wk.append(bh["stages"]["wall_s"] / bh["stages"]["kernel_s"])
                speed.append(kd["stages"]["wall_s"] / bh["stages"]["wall_s"])
                for s in STAGES:
                    stages[s].append(bh["stages"][s])
            rows.append(("bhcl knn", n, k, wk, speed, stages))
            print(f"bhcl knn n={n} k={k}: wall/kernel {span(wk)}  kd-tree wall / blockhash wall {span(speed)}",
                  flush=True)
    return rows


def bench_python(args, sizes, ks, all_q):
    sys.path.insert(0, args.python_path)
    import blockhash_cl as bh
    pts = np.load(args.points)
    idx = {m: bh.make_index(m, pts) for m in ("blockhash", "kdtree")}
    rows = []
    for n in sizes:
        q = np.ascontiguousarray(all_q[:n])
        for k in ks:
            for m in idx:  # warm-up: the compile
                idx[m].query(q, k)
            wk, speed, stages = [], [], {s: [] for s in STAGES}
            for _ in range(args.rounds):
                order = list(idx)
                random.shuffle(order)
                st = {}
                for m in order:
                    st[m] = idx[m].query(q, k, return_stats=True)[-1]
                b, d = st["blockhash"], st["kdtree"]
                wk.append(b["wall_s"] / b["query_s"])
                speed.append(d["wall_s"] / b["wall_s"])
                named = {"compile_s": b["compile_s"], "sort_s": b["sort_s"], "upload_s": b["upload_s"],
                         "kernel_s": b["query_s"], "download_s": b["download_s"], "unsort_s": b["unsort_s"],
                         "write_s": 0.0}
                named["other_s"] = max(0.0, b["wall_s"] - sum(named.values()))
                for s in STAGES:
                    stages[s].append(named[s])
            rows.append(("Python query", n, k, wk, speed, stages))
            print(f"python n={n} k={k}: wall/kernel {span(wk)}  kd-tree wall / blockhash wall {span(speed)}",
                  flush=True)
    return rows


def table(rows):
    head = ("| front | queries | k | wall / kernel (<= 1.15) | kd-tree wall / blockhash wall (>= 1.5) | "
            + " | ".join(s[:-2] + " ms" for s in STAGES) + " |")
    out = [head, "|" + "---|" * (5 + len(STAGES))]
    for front, n, k, wk, speed, stages in rows:
        out.append(f"| {front} | {n} | {k} | {span(wk)} | {span(speed)} | "
                   + " | ".join(f"{1e3 * med(stages[s]):.1f}" for s in STAGES) + " |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bhcl", required=True)
    ap.add_argument("--points", required=True)
    ap.add_argument("--queries", required=True)
    ap.add_argument("--sizes", default="100000,1000000")
    ap.add_argument("--k", default="10,50")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--python-path", default="", help="folder holding the blockhash_cl package (empty: skip Python)")
    ap.add_argument("--out", default="")
    ap.add_argument("--title", default="Cornell 1M", help="the table's title (the data set)")
    ap.add_argument("--cpu", default="AVX-512", help="the machine, for the title")
    ap.add_argument("--note", default="", help="a line under the command: the inputs, the code measured")
    args = ap.parse_args()
    random.seed(1)
    sizes = [int(x) for x in args.sizes.split(",")]
    ks = [int(x) for x in args.k.split(",")]
    all_q = np.load(args.queries)
    with tempfile.TemporaryDirectory(prefix="bhcl-e2e-") as tmp:
        rows = bench_cli(args, sizes, ks, tmp, all_q)
    if args.python_path:
        rows += bench_python(args, sizes, ks, all_q)
    text = table(rows)
    print(text)
    if args.out:
        threads = os.environ.get('POCL_MAX_PTHREAD_COUNT', '?')
        header = (f"# End to end, {args.title} ({args.cpu}, {threads} threads)\n\n"
                  f"Command: `POCL_MAX_PTHREAD_COUNT={os.environ.get('POCL_MAX_PTHREAD_COUNT', '')} "
                  + " ".join(["python3"] + sys.argv) + f"`\n\n{args.note}\n\n" + SEARCH_WALL
                  + f"\n\nMedian of {args.rounds} rounds (min-max); stages: block hashing's median, ms.\n\n")
        tmp_out = args.out + ".tmp"
        with open(tmp_out, "w") as f:
            f.write(header + text + "\n")
        os.replace(tmp_out, args.out)


if __name__ == "__main__":
    main()
