#!/usr/bin/env python3
# Usage: seq_ab.py BHCL POINTS.npy QUERIES.npy K ROUNDS [VAR=VALUE ...] (B's env); results: mapped_outputs_sequences_s14.txt
# e2e_bench's sequence (a kd-tree run before each block-hashing run, the same output paths),
# block hashing alternating between env A and env B; prints medians of write, wall/kernel.
import json, os, subprocess, statistics, sys, random
bhcl, P, Q, k, rounds = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5])
envs = {"A": {}, "B": dict(e.split("=", 1) for e in sys.argv[6:])}
tmp = os.environ.get("SEQ_TMP", "/tmp/seq_ab"); os.makedirs(tmp, exist_ok=True)
def run(m, extra):
    env = dict(os.environ); env.update(extra)
    st = os.path.join(tmp, "s.json")
    subprocess.run([bhcl, "knn", "--points", P, "--queries", Q, "--method", m, "--k", k, "--out-ids", tmp + "/ids.npy",
                    "--out-dist2", tmp + "/d2.npy", "--stats", st, "--quiet"], check=True, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.load(open(st))["stages"]
res = {"A": [], "B": []}
for r in range(rounds + 1):
    order = ["A", "B"] if r % 2 == 0 else ["B", "A"]
    for a in order:
        run("kdtree", {})
        s = run("blockhash", envs[a])
        if r: res[a].append(s)
for a in "AB":
    w = [s["write_s"] * 1e3 for s in res[a]]; wk = [s["wall_s"] / s["kernel_s"] for s in res[a]]
    print(a, envs[a], "write ms med %.1f (%.1f-%.1f)" % (statistics.median(w), min(w), max(w)),
          "wall/kernel med %.3f (%.3f-%.3f)" % (statistics.median(wk), min(wk), max(wk)))
