#!/usr/bin/env python3
"""The convergence plot of issue 24 as an SVG (standard library only: no matplotlib here).

Reads the stats JSON of `bhcl render --passes N --reference REF --reference-block 32` (one per
scene and method, `pass_reports`) and draws, per scene, the error of the running image against the
path-traced reference after each pass: the worst 32-px tile (solid) and the RMSE over the tiles
(dashed), against passes (left) and against wall time (right), one colour per method, on a log
scale, with the 5 % line of the must-show.

Usage: plot_convergence.py OUT.svg ppm_SCENE_METHOD.json ...
"""
import json
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from svg_plot import svg_open, write_svg  # noqa: E402  (bench/results/svg_plot.py)

COLOURS = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#666666"]


def label(j):
    return f"{j['method']}, {j['spp']} spp x {j['gather']} gather"
W, H = 620, 300          # one panel (the legend right of its plot)
ML, MR, MT, MB = 64, 216, 34, 46
Y_LO, Y_HI = 0.1, 30.0   # per cent, log scale


def esc(t):
    return t.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def main():
    out, paths = sys.argv[1], sys.argv[2:]
    runs = {}
    for p in paths:
        j = json.load(open(p))
        runs.setdefault(j["scene"], []).append(j)
    scenes = sorted(runs)
    total_w, total_h = 2 * W, len(scenes) * H + 40
    svg = svg_open(total_w, total_h, 12)
    for si, scene in enumerate(scenes):
        for pi, xkey in enumerate(("pass", "elapsed_s")):
            ox, oy = pi * W, si * H
            pw, ph = W - ML - MR, H - MT - MB
            xs = [r[xkey] for j in runs[scene] for r in j["pass_reports"]]
            x_lo = 0 if xkey == "elapsed_s" else 1
            x_hi = max(xs) * (1.05 if xkey == "elapsed_s" else 1.0)

            def X(v):
                return ox + ML + (v - x_lo) / (x_hi - x_lo) * pw

            def Y(v):
                v = min(max(v, Y_LO), Y_HI)
                return oy + MT + (math.log10(Y_HI) - math.log10(v)) / (math.log10(Y_HI) - math.log10(Y_LO)) * ph

            j0 = runs[scene][0]
            title = (f"{scene}, {j0['width']}x{j0['height']}, {j0['photons_requested'] // 1000}k photons/pass"
                     + (" : by pass" if xkey == "pass" else " : by wall time"))
            svg.append(f'<text x="{ox + ML}" y="{oy + 20}" font-size="13" font-weight="bold">{esc(title)}</text>')
            svg.append(f'<rect x="{ox + ML}" y="{oy + MT}" width="{pw}" height="{ph}" fill="none" stroke="#444"/>')
            for v in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20):
                y = Y(v)
                svg.append(f'<line x1="{ox + ML}" x2="{ox + ML + pw}" y1="{y:.1f}" y2="{y:.1f}" '
                           f'stroke="{"#c00" if v == 5 else "#ddd"}" stroke-width="{1.5 if v == 5 else 1}"/>')
                svg.append(f'<text x="{ox + ML - 6}" y="{y + 4:.1f}" text-anchor="end">{v:g} %</text>')
            ticks = list(range(1, int(x_hi) + 1)) if xkey == "pass" else None
            if xkey == "pass":
                ticks = [t for t in ticks if t == 1 or t % 2 == 0]
            else:
                step = 10 ** math.floor(math.log10(x_hi / 4))
                step *= 5 if x_hi / step > 20 else (2 if x_hi / step > 8 else 1)
                ticks = [step * i for i in range(0, int(x_hi / step) + 1)]
            for t in ticks:
                x = X(t)
                svg.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{oy + MT + ph}" y2="{oy + MT + ph + 4}" stroke="#444"/>')
                svg.append(f'<text x="{x:.1f}" y="{oy + MT + ph + 17}" text-anchor="middle">{t:g}</text>')
            xlabel = "passes" if xkey == "pass" else "wall time (s)"
            svg.append(f'<text x="{ox + ML + pw / 2}" y="{oy + H - 10}" text-anchor="middle">{xlabel}</text>')
            svg.append(f'<text transform="translate({ox + 16},{oy + MT + ph / 2}) rotate(-90)" text-anchor="middle">'
                       f'error against the path tracer</text>')
            ly = oy + MT + 10
            for ci, j in enumerate(sorted(runs[scene], key=lambda j: (j["spp"], j["method"]))):
                c = COLOURS[ci % len(COLOURS)]
                for key, dash, name in (("block_worst", "", "worst tile"), ("block_rmse", "6,4", "tile RMSE")):
                    pts = " ".join(f"{X(r[xkey]):.1f},{Y(100 * r[key]):.1f}" for r in j["pass_reports"])
                    svg.append(f'<polyline points="{pts}" fill="none" stroke="{c}" stroke-width="2"'
                               + (f' stroke-dasharray="{dash}"' if dash else "") + "/>")
                    for r in j["pass_reports"]:
                        svg.append(f'<circle cx="{X(r[xkey]):.1f}" cy="{Y(100 * r[key]):.1f}" r="2.2" fill="{c}"/>')
                    lx = ox + ML + pw + 12
                    svg.append(f'<line x1="{lx}" x2="{lx + 24}" y1="{ly - 4}" y2="{ly - 4}" stroke="{c}" stroke-width="2"'
                               + (f' stroke-dasharray="{dash}"' if dash else "") + "/>")
                    svg.append(f'<text x="{lx + 30}" y="{ly}" font-size="11">{esc(label(j))}:</text>')
                    svg.append(f'<text x="{lx + 30}" y="{ly + 13}" font-size="11">{name}</text>')
                    ly += 31
            svg.append(f'<text x="{ox + ML + 4}" y="{Y(5) - 4:.1f}" fill="#c00">5 %</text>')
    svg.append(f'<text x="8" y="{total_h - 12}" fill="#444">32-px tiles of luminance, the tiles where the reference '
               f'sees the emitter left out; progressive photon mapping (Knaus-Zwicker, alpha 2/3), k = 50, 32 gather rays, '
               f'camera samples (spp) and gather rays as labelled.</text>')
    write_svg(out, svg)


if __name__ == "__main__":
    main()
