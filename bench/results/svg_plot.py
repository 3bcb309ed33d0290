"""What the results' SVG plots share (progressive/plot_convergence.py, render/issue41/plot_part2.py):
the document's opening and its atomic write. Standard library only: no matplotlib on the machine.
"""
import os


def svg_open(width, height, font_size):
    """The opening lines of a plot: the svg element (its size and font) and a white background."""
    return [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'font-family="DejaVu Sans, sans-serif" font-size="{font_size}">',
            f'<rect width="{width}" height="{height}" fill="white"/>']


def write_svg(out, svg):
    """Closes the document and writes it to a temporary beside OUT, renamed into place, so that a
    reader never sees half a plot."""
    tmp = out + ".tmp"
    with open(tmp, "w") as f:
        f.write("\n".join(svg + ["</svg>"]) + "\n")
    os.replace(tmp, out)
