#!/usr/bin/env python3
"""Issue 41, part 2: error against wall time, one SVG (standard library only).

    /usr/bin/python3 plot_part2.py OUT.svg POINTS.txt PPM_JSON...

POINTS.txt: part2.sh's lines "scene method samples seconds tile_rmse worst region". PPM_JSON: the
stats of the 16-pass runs (their pass_reports: each pass's worst 16-px tile and tile RMSE against
the reference, by elapsed time). One panel per scene, log-log: per method the worst tile (solid),
the tile RMSE (dashed) and, on the specular scene, the caustic region's error (dotted, the
ladder's points), with the 5 % and 2 % lines of the issue's goal. The file is written to a
temporary beside it and renamed into place.
"""
import json
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
from svg_plot import svg_open, write_svg  # noqa: E402  (bench/results/svg_plot.py)

COLOURS = {"pathtrace": "#d95f02", "ppm-blockhash": "#1b9e77", "ppm-kdtree": "#7570b3"}
W, H = 560, 360
ML, MR, MT, MB = 60, 170, 34, 46
X_LO, X_HI = 0.02, 100.0
Y_LO, Y_HI = 0.2, 100.0


def xs(t):
    t = min(max(t, X_LO), X_HI)
    return ML + (math.log10(t) - math.log10(X_LO)) / (math.log10(X_HI) - math.log10(X_LO)) * (W - ML - MR)


def ys(e):
    e = min(max(e, Y_LO), Y_HI)
    return MT + (math.log10(Y_HI) - math.log10(e)) / (math.log10(Y_HI) - math.log10(Y_LO)) * (H - MT - MB)


def polyline(pts, colour, dash, ox):
    p = " ".join(f"{ox + xs(t):.1f},{ys(e):.1f}" for t, e in pts if t > 0)
    d = f' stroke-dasharray="{dash}"' if dash else ""
    marks = "".join(f'<circle cx="{ox + xs(t):.1f}" cy="{ys(e):.1f}" r="2.5" fill="{colour}"/>' for t, e in pts if t > 0)
    return f'<polyline points="{p}" fill="none" stroke="{colour}" stroke-width="1.8"{d}/>' + marks


def main():
    out, points_path, jsons = sys.argv[1], sys.argv[2], sys.argv[3:]
    series = {}  # (scene, method, measure) -> [(t, err %)]
    for line in open(points_path):
        f = line.split()
        if len(f) != 7:
            continue
        scene, method, _, t, rmse, worst, region = f[0], f[1], f[2], float(f[3]), float(f[4]), float(f[5]), float(f[6])
        if method == "pathtrace":
            series.setdefault((scene, method, "worst"), []).append((t, 100 * worst))
            series.setdefault((scene, method, "rmse"), []).append((t, 100 * rmse))
        if scene == "cornell-specular":
            series.setdefault((scene, method, "region"), []).append((t, 100 * region))
    for p in jsons:
        j = json.load(open(p))
        m = "ppm-" + j["method"]
        for r in j["pass_reports"]:
            series.setdefault((j["scene"], m, "worst"), []).append((r["elapsed_s"], 100 * r["block_worst"]))
            series.setdefault((j["scene"], m, "rmse"), []).append((r["elapsed_s"], 100 * r["block_rmse"]))
    scenes = ["cornell-specular", "cornell"]
    svg = svg_open(2 * W, H, 11)
    for i, scene in enumerate(scenes):
        ox = i * W
        svg.append(f'<text x="{ox + ML}" y="18" font-size="13">{scene}, 128x128: error against the path-traced '
                   f'reference by wall time</text>')
        svg.append(f'<rect x="{ox + ML}" y="{MT}" width="{W - ML - MR}" height="{H - MT - MB}" fill="none" stroke="#999"/>')
        for t in [0.1, 1, 10, 100]:
            svg.append(f'<line x1="{ox + xs(t):.1f}" y1="{MT}" x2="{ox + xs(t):.1f}" y2="{H - MB}" stroke="#eee"/>')
            svg.append(f'<text x="{ox + xs(t):.1f}" y="{H - MB + 14}" text-anchor="middle">{t:g} s</text>')
        for e in [0.5, 1, 2, 5, 10, 20, 50, 100]:
            colour = "#c00" if e in (2, 5) else "#eee"
            svg.append(f'<line x1="{ox + ML}" y1="{ys(e):.1f}" x2="{ox + W - MR}" y2="{ys(e):.1f}" stroke="{colour}"/>')
            svg.append(f'<text x="{ox + ML - 4}" y="{ys(e) + 4:.1f}" text-anchor="end">{e:g} %</text>')
        svg.append(f'<text x="{ox + (W - MR + ML) / 2}" y="{H - 12}" text-anchor="middle">wall time (s), AVX-512, 2 threads</text>')
        ly = MT + 4
        for method, colour in COLOURS.items():
            for measure, dash in (("worst", ""), ("rmse", "6,3"), ("region", "2,3")):
                pts = sorted(series.get((scene, method, measure), []))
                if not pts:
                    continue
                svg.append(polyline(pts, colour, dash, ox))
                name = {"worst": "worst 16-px tile", "rmse": "tile RMSE", "region": "caustic floor"}[measure]
                d = f' stroke-dasharray="{dash}"' if dash else ""
                svg.append(f'<line x1="{ox + W - MR + 8}" y1="{ly}" x2="{ox + W - MR + 30}" y2="{ly}" stroke="{colour}" '
                           f'stroke-width="1.8"{d}/>')
                svg.append(f'<text x="{ox + W - MR + 34}" y="{ly + 4}">{method}: {name}</text>')
                ly += 15
    write_svg(out, svg)


if __name__ == "__main__":
    main()
