#!/usr/bin/env python3
"""Markdown tables of the progressive renders' convergence (the stats JSON of bhcl render --passes
with --reference): per pass the wall time and the 32-px block errors against the path tracer."""
import json
import sys

for path in sys.argv[1:]:
    j = json.load(open(path))
    print(f"\n{j['scene']}, {j['method']}, {j['width']}x{j['height']}, {j['photons_requested']} photons a pass, "
          f"{j.get('spp', 1)} spp, {j['gather']} gather rays, k = {j['k']}, alpha = {j['alpha']:.4g}\n")
    print("| pass | wall s | r_i/r_1 | block RMSE | worst block | bias |")
    print("|-----:|-------:|--------:|-----------:|------------:|-----:|")
    for p in j["pass_reports"]:
        print(f"| {p['pass']} | {p['elapsed_s']:.1f} | {p['radius_scale2'] ** 0.5:.3f} | {100 * p['block_rmse']:.2f} % "
              f"| {100 * p['block_worst']:.2f} % | {100 * p['block_bias']:+.2f} % |")
