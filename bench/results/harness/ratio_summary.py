# The 12 perf_harness rows of an A/B file: per row the ratio of the base arm's median q/s to the
# main and rings arms' (ratios of medians, not per-round), and their median over the rows.
# Usage: /usr/bin/python3 bench/results/harness/ratio_summary.py FILE
import re,sys,statistics as st
rows=[];cur=None
for l in open(sys.argv[1]):
    m=re.match(r'## (\w+) .*k=(\d+) order=(\w+)',l)
    if m: cur={'row':f"{m[1]} k={m[2]} {m[3]}"}; rows.append(cur); continue
    m=re.match(r'auto/\S+/(\w+)\s+(\d+)\s+([\d.]+)',l)
    if m and cur is not None: cur[m[1]]=float(m[2])
a=[];b=[]
for r in rows:
    x=r['base']/r['main']; y=r['base']/r['rings']; a.append(x); b.append(y)
    print(f"{r['row']:28s} base/main(TBOX=0) {x:.3f}  base/rings {y:.3f}")
print(f"median of 12: base/main {st.median(a):.3f} ({min(a):.2f}-{max(a):.2f}); base/rings {st.median(b):.3f} ({min(b):.2f}-{max(b):.2f})")
