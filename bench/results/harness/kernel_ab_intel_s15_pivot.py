import csv, sys, statistics, collections
rows = list(csv.DictReader(open(sys.argv[1])))
key = sys.argv[2] if len(sys.argv) > 2 else "defines_name"
tab = collections.defaultdict(dict); names = []
for r in rows:
    if r["method"] != "blockhash": continue
    name = r[key] or "?"
    if key == "local-size": name = r["local-size"]
    if key == "build": name = r["build"]
    if name not in names: names.append(name)
    tab[(r["data"], r["k"], r["order"])][name] = (float(r["ratio_kd_median"]), float(r["ratio_flann_median"]), float(r["recall"]))
print("row".ljust(22) + "".join(n[:10].rjust(11) for n in names))
rel = collections.defaultdict(list)
for rk, v in tab.items():
    base = v[names[0]][0]
    print(("%s k%s %s" % rk).ljust(22) + "".join(("%.2f/%.2f" % (v[n][0], v[n][0] / base)).rjust(11) for n in names))
    for n in names: rel[n].append(v[n][0] / base)
print("median".ljust(22) + "".join(("%.3f" % statistics.median(rel[n])).rjust(11) for n in names))
print("min".ljust(22) + "".join(("%.3f" % min(rel[n])).rjust(11) for n in names))
