#!/usr/bin/env python3
"""A/B of bhcl knn (blockhash, exact, Cornell 1M) between two builds, alternating processes (the order
swapped each round), one process per run; per-round ratios. Used for early_outputs_ab.txt (issue 37):
    POCL_MAX_PTHREAD_COUNT is set to 2 here; python3 early_outputs_ab.py ROUNDS OUT.json
Paths: main = /work/main/build/host/bhcl (0d1578e), new = /work/h37e/build/host/bhcl; inputs in /tmp/h37e
(P.npy, Q.npy from make_dataset --data cornell --N 1000000 --queries 1000000; q100k.npy = Q[:100000])."""
import json, os, statistics, subprocess, sys, time
builds = {"main": "/work/main/build/host/bhcl", "new": "/work/h37e/build/host/bhcl"}
rows = [("/tmp/h37e/q100k.npy", "100k", 10), ("/tmp/h37e/q100k.npy", "100k", 50),
        ("/tmp/h37e/Q.npy", "1M", 10), ("/tmp/h37e/Q.npy", "1M", 50)]
rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 5
tmp = "/tmp/h37e/ab"
env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="2")
def run(b, q, k):
    st = os.path.join(tmp, "st.json")
    cmd = [builds[b], "knn", "--points", "/tmp/h37e/P.npy", "--queries", q, "--method", "blockhash", "--k", str(k),
           "--out-ids", os.path.join(tmp, "ids.npy"), "--out-dist2", os.path.join(tmp, "d2.npy"), "--stats", st, "--quiet"]
    t0 = time.time(); subprocess.run(cmd, check=True, env=env, stderr=subprocess.DEVNULL); p = time.time() - t0
    j = json.load(open(st)); s = j["stages"]; s["proc_s"] = p; s["build_s"] = j.get("build_s", 0)
    return s
res = {}
for r in range(rounds + 1):
    for q, name, k in rows:
        order = ["main", "new"] if r % 2 else ["new", "main"]
        got = {b: run(b, q, k) for b in order}
        if r == 0: continue
        res.setdefault((name, k), []).append(got)
print("load", open("/proc/loadavg").read().strip())
def med(x): return statistics.median(x)
print("row | wall/kernel new (min-max) | main | new/main wall-minus-kernel (per-round median) | proc new/main | write new/main ms | populate_ahead ms, MB")
for (name, k), rs in res.items():
    wk = lambda b: [x[b]["wall_s"] / x[b]["kernel_s"] for x in rs]
    nk = [(x["new"]["wall_s"] - x["new"]["kernel_s"]) / (x["main"]["wall_s"] - x["main"]["kernel_s"]) for x in rs]
    pr = [x["new"]["proc_s"] / x["main"]["proc_s"] for x in rs]
    print(f"{name}x{k} | {med(wk('new')):.3f} ({min(wk('new')):.3f}-{max(wk('new')):.3f}) | {med(wk('main')):.3f} ({min(wk('main')):.3f}-{max(wk('main')):.3f}) | "
          f"{med(nk):.2f} | {med(pr):.3f} ({min(pr):.2f}-{max(pr):.2f}) | {med([x['new']['write_s'] for x in rs])*1e3:.1f} / {med([x['main']['write_s'] for x in rs])*1e3:.1f} | "
          f"{med([x['new'].get('populate_ahead_s',0) for x in rs])*1e3:.0f}, {med([x['new'].get('populate_ahead_bytes',0) for x in rs])/1e6:.0f}")
    print("   proc s new:", " ".join(f"{x['new']['proc_s']:.2f}" for x in rs), " main:", " ".join(f"{x['main']['proc_s']:.2f}" for x in rs))
    print("   kernel s new:", " ".join(f"{x['new']['kernel_s']:.3f}" for x in rs), " main:", " ".join(f"{x['main']['kernel_s']:.3f}" for x in rs))
json.dump({f"{a}x{b}": v for (a, b), v in res.items()}, open(sys.argv[2] if len(sys.argv) > 2 else "/tmp/h37e/ab.json", "w"))
