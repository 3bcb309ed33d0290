#!/usr/bin/env python3
"""Mean luminance of fixed image regions of two renders of the shipped specular scene (256x256):
the before/after table of docs/RENDER.md. Usage: render_regions.py BEFORE.exr AFTER.exr
(needs numpy and the OpenEXR wheel from PyPI; the regions are pixel boxes read off the image)."""
import sys, OpenEXR, numpy as np
def load(p):
    with OpenEXR.File(p) as f:
        ch = f.channels()
        if "RGB" in ch:
            a = ch["RGB"].pixels
        else:
            a = np.stack([ch[c].pixels for c in ("R", "G", "B")], -1)
    return np.asarray(a, dtype=np.float64)
regions = {  # (x0, x1, y0, y1) in the 256x256 image, y down
    "floor seen through the glass block": (132, 185, 185, 228),
    "mirror front": (82, 122, 108, 150),
    "ceiling": (60, 200, 4, 24),
    "back wall (direct view)": (140, 200, 60, 140),
    "floor in air": (20, 70, 225, 250),
    "left (red) wall": (10, 40, 60, 200),
}
b, a = load(sys.argv[1]), load(sys.argv[2])
lum = lambda im: 0.2126 * im[..., 0] + 0.7152 * im[..., 1] + 0.0722 * im[..., 2]
lb, la = lum(b), lum(a)
print("| region (pixels x0-x1, y0-y1 of 256x256) | before | after | after / before |")
print("|---|---|---|---|")
for name, (x0, x1, y0, y1) in regions.items():
    mb, ma = lb[y0:y1, x0:x1].mean(), la[y0:y1, x0:x1].mean()
    print(f"| {name} ({x0}-{x1}, {y0}-{y1}) | {mb:.4f} | {ma:.4f} | {ma / mb:.3f} |")
print(f"| whole image | {lb.mean():.4f} | {la.mean():.4f} | {la.mean() / lb.mean():.3f} |")
