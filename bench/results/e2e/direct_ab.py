#!/usr/bin/env python3
"""A/B of two bhcl binaries on `bhcl knn` (block hashing, exact): each round runs A and B one
after the other (order alternating), one process each, and records the stats' search wall /
kernel and the whole process's wall (its start to its exit: reading, search, commit). Prints
per-config medians of the per-round ratios B / A. Usage:
  direct_ab.py --a MAIN_BHCL --b NEW_BHCL --points P.npy --queries Q.npy --rounds 5 [--sizes 100000,1000000] [--k 10,50]
Extra env for B only: --b-env VAR=VALUE (repeatable)."""
import argparse, json, os, statistics, subprocess, time
import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("--a", required=True); ap.add_argument("--b", required=True)
ap.add_argument("--points", required=True); ap.add_argument("--queries", required=True)
ap.add_argument("--rounds", type=int, default=5)
ap.add_argument("--sizes", default="100000,1000000"); ap.add_argument("--k", default="10,50")
ap.add_argument("--tmp", default="/tmp/h37f/ab")
ap.add_argument("--b-env", action="append", default=[]); ap.add_argument("--a-env", action="append", default=[])
args = ap.parse_args()
os.makedirs(args.tmp, exist_ok=True)
q = np.load(args.queries)

def run(binary, qpath, k, extra):
    st = os.path.join(args.tmp, "stats.json")
    env = dict(os.environ); env.update(dict(e.split("=", 1) for e in extra))
    cmd = [binary, "knn", "--points", args.points, "--queries", qpath, "--method", "blockhash", "--k", str(k),
           "--out-ids", os.path.join(args.tmp, "ids.npy"), "--out-dist2", os.path.join(args.tmp, "d2.npy"),
           "--stats", st, "--quiet"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    proc = time.perf_counter() - t0
    s = json.load(open(st))["stages"]
    return dict(proc=proc, wall=s["wall_s"], kernel=s["kernel_s"], write=s.get("write_s", 0), commit=s.get("commit_s", 0))

def med(x): return statistics.median(x)
def span(x): return f"{med(x):.3f} ({min(x):.3f}-{max(x):.3f})"
for n in [int(s) for s in args.sizes.split(",")]:
    qpath = os.path.join(args.tmp, f"q{n}.npy"); np.save(qpath, q[:n])
    for k in [int(s) for s in args.k.split(",")]:
        rec = {"a": [], "b": []}
        for r in range(args.rounds + 1):
            order = ["a", "b"] if r % 2 == 0 else ["b", "a"]
            got = {}
            for w in order:
                got[w] = run(getattr(args, w), qpath, k, getattr(args, w + "_env"))
            if r == 0: continue  # warm-up round (program cache), not counted
            for w in "ab": rec[w].append(got[w])
        A, B = rec["a"], rec["b"]
        wk = {w: [x["wall"] / x["kernel"] for x in rec[w]] for w in "ab"}
        print(f"n={n} k={k}: wall/kernel A {span(wk['a'])}  B {span(wk['b'])}")
        for f in ["proc", "wall", "kernel", "write", "commit"]:
            print(f"   {f:7s} A med {med([x[f] for x in A]):.3f} s  B med {med([x[f] for x in B]):.3f} s  "
                  f"B/A per round {span([b[f] / a[f] if a[f] else float('nan') for a, b in zip(A, B)])}")
        print(f"   load {os.getloadavg()[0]:.2f}", flush=True)
