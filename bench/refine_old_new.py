#!/usr/bin/env python3
"""Two builds' float64 refinement compared on issue 40's UTM case, round by round.

Runs bench/refine_bench.py one round at a time, alternately with PYTHONPATH set to an old build's
package and to a new one's (a process each: two builds of the _core module cannot share one
process; each process runs two rounds and the second is kept: a fresh process's first call of a
variant faults in its output pages, the buffer pool being empty, which hid the difference), and
gives per method and k the medians over the rounds of each build's refine_share and
refine_s (the default refined query) and of the per-round ratios new / old of refine_s, of
refine_cpu_s (the process's CPU time over the refinement: less swayed by the load) and of
the refined wall time over the same process's float32 wall time (the whole cost of float64
answers). On a shared machine the per-round ratios are the figures to quote.

    PYTHONPATH=NEW_PYTHONPATH python3 bench/refine_old_new.py --old OLD_PYTHONPATH --new NEW_PYTHONPATH --rounds 5 \\
        --markdown out.md -- --n 200000 --queries 200000 --k 1,10,50

The arguments after -- go to refine_bench.py. Set POCL_MAX_PTHREAD_COUNT and quote it. (The
script itself imports the package, for the benches' atomic writer: run it with one of the two.)
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from python_bench import write_atomic  # noqa: E402  (the benches' one atomic writer)


def one_round(pythonpath, bench_args):
    """refine_bench.py's records of two rounds run with this PYTHONPATH (the second is used)."""
    fd, out = tempfile.mkstemp(prefix="refine_old_new.", suffix=".json")
    os.close(fd)
    try:
        env = dict(os.environ, PYTHONPATH=pythonpath)
        subprocess.run([sys.executable, os.path.join(HERE, "refine_bench.py"), "--rounds", "2", "--json", out]
                       + bench_args, env=env, check=True, stdout=subprocess.DEVNULL)
        with open(out) as f:
            return json.load(f)
    finally:
        os.unlink(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="PYTHONPATH of the old build's package")
    ap.add_argument("--new", required=True, help="PYTHONPATH of the new build's package")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--markdown", default="")
    ap.add_argument("bench_args", nargs=argparse.REMAINDER)
    a = ap.parse_args()
    bench_args = [x for x in a.bench_args if x != "--"]
    runs = {"old": [], "new": []}
    header = ""
    for r in range(a.rounds):
        order = ["old", "new"] if r % 2 == 0 else ["new", "old"]
        for build in order:
            got = one_round(a.old if build == "old" else a.new, bench_args)
            header = header or got["header"]
            runs[build].append({(x["method"], x["k"]): x["rec"] for x in got["records"]})
        print(f"round {r + 1}/{a.rounds} done", file=sys.stderr, flush=True)
    lines = [header.replace("median of 2 rounds", f"old and new build alternated, {a.rounds} rounds each (a process "
                                                 "each, its second round kept)"),
             "| method | k | old refine_share | new refine_share | old refine_s | new refine_s | "
             "new / old refine_s (min-max) | new / old refine_cpu_s (min-max) | old wall / float32 | "
             "new wall / float32 | new / old of wall / float32 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key in runs["new"][0]:
        def per_round(build, field):
            return np.array([rnd[key]["refined"][field][-1] for rnd in runs[build]])
        rs_ratio = per_round("new", "rs") / per_round("old", "rs")
        wall_ratio = per_round("new", "ratio") / per_round("old", "ratio")
        cpu_ratio = per_round("new", "rcpu") / per_round("old", "rcpu")
        lines.append(f"| {key[0]} | {key[1]} | {np.median(per_round('old', 'share')):.3f} | "
                     f"{np.median(per_round('new', 'share')):.3f} | {np.median(per_round('old', 'rs')):.4f} | "
                     f"{np.median(per_round('new', 'rs')):.4f} | {np.median(rs_ratio):.2f} "
                     f"({rs_ratio.min():.2f}-{rs_ratio.max():.2f}) | {np.median(cpu_ratio):.2f} "
                     f"({cpu_ratio.min():.2f}-{cpu_ratio.max():.2f}) | {np.median(per_round('old', 'ratio')):.2f} | "
                     f"{np.median(per_round('new', 'ratio')):.2f} | {np.median(wall_ratio):.2f} |")
    print("\n".join(lines))
    if a.markdown:
        write_atomic(a.markdown, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
