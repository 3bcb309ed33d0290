#!/usr/bin/env python3
"""Issue 41: the talk's sheet and the error table from run.sh's outputs.

    /usr/bin/python3 bench/results/render/issue41/make_sheet.py IN_DIR OUT_DIR

For each preset (paper, paper-cells) one PNG, OUT_DIR/sheet_<preset>.png: a row per scene and
photon count, each row the top row of bhcl render --compare's sheet (kd-tree, then block hashing
at A = 4, 8, 16, each labelled with its RMSE, relative RMSE, false negatives and max / mean
dilation), reduced to 256 colours to keep the repository small. Prints the markdown table of
docs/ACCURACY.md (relative RMSE, the talk's three measures, B, P, median cell) and writes it to
OUT_DIR/table.md. Every file is written to a temporary beside it and renamed into place.
"""
import json
import os
import sys

from PIL import Image, ImageDraw, ImageFont

SCENES = [("cornell", "diffuse"), ("specular", "specular")]
PHOTONS = [200000, 1000000]
PRESETS = ["paper", "paper-cells"]
BACKGROUND = (40, 40, 40)  # the sheets' background (compare.cpp)
FONT = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"


def atomic_save(write, path):
    tmp = path + ".tmp"
    write(tmp)
    os.replace(tmp, path)


def top_row(path, tile_height):
    """The first row of a compare sheet: from the top to the first all-background line below the
    first tiles (the gap between its rows)."""
    img = Image.open(path).convert("RGB")
    w, h = img.size
    px = img.load()
    for y in range(tile_height + 8, h):
        if all(px[x, y] == BACKGROUND for x in range(w)):
            return img.crop((0, 0, w, y + 1))
    raise SystemExit(f"{path}: no gap below the first row")


def sheet(in_dir, preset, out_path):
    font = ImageFont.truetype(FONT, 13) if os.path.exists(FONT) else ImageFont.load_default()
    rows = []
    for scene, title in SCENES:
        for n in PHOTONS:
            base = os.path.join(in_dir, f"{scene}_{n}_{preset}")
            with open(base + ".json") as f:
                height = json.load(f)["height"]
            row = top_row(base + "_compare.png", height)
            caption = f"{title} Cornell box, {n // 1000}k photons, preset {preset}"
            band = Image.new("RGB", (row.width, 20), BACKGROUND)
            ImageDraw.Draw(band).text((8, 3), caption, fill=(255, 220, 120), font=font)
            rows.append(band)
            rows.append(row)
    out = Image.new("RGB", (max(r.width for r in rows), sum(r.height for r in rows)), BACKGROUND)
    y = 0
    for r in rows:
        out.paste(r, (0, y))
        y += r.height
    small = out.quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    atomic_save(lambda p: small.save(p, format="PNG", optimize=True), out_path)


def table(in_dir):
    lines = ["| scene | photons | preset | A | rel. RMSE | false neg. | dil. max | dil. mean | B | P | median cell |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for scene, title in SCENES:
        for n in PHOTONS:
            for preset in PRESETS:
                with open(os.path.join(in_dir, f"{scene}_{n}_{preset}.json")) as f:
                    j = json.load(f)
                for r in j["runs"][1:]:
                    a, b = r["lists_accuracy"], r["build"]
                    lines.append(
                        f"| {title} | {j['photons']} | {preset} | {r['A']:g} | {100 * r['relative_rmse']:.2f} % | "
                        f"{a['false_negative_rate']:.3f} | {a['max_dilation']:.2f} | {a['mean_dilation']:.3f} | "
                        f"{b['B']} | {b['P']} | {b['median_cell_points']:.0f} |")
    return "\n".join(lines) + "\n"


def main():
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    in_dir, out_dir = sys.argv[1], sys.argv[2]
    for preset in PRESETS:
        sheet(in_dir, preset, os.path.join(out_dir, f"sheet_{preset}.png"))
    t = table(in_dir)

    def write(p):
        with open(p, "w") as f:
            f.write(t)
    atomic_save(write, os.path.join(out_dir, "table.md"))
    print(t, end="")


if __name__ == "__main__":
    main()
