"""The polariser-layout convention as a figure (docs/images/polariser_layout.png).

    python tools/layout_figure.py [--out docs/images/polariser_layout.png]

Left: one 2x2 super-pixel of a raw mosaic as ``--layout`` reads it (row-major from the top-left pixel,
default IMX250MZR 90,45,135,0), each pixel's polariser transmission axis drawn at its angle phi,
measured from image right (x) towards image up (y), the frame of the Stokes images (S1 = I0 - I90,
S2 = I45 - I135).  Right: the same sensor seen through a mirror (or decoded with another sensor's
convention): 45 and 135 trade places, S2 changes sign, and ``--layout 90,135,45,0`` reads it.  The
angles come from :data:`fmbrdf_mi.sensor.mosaic.IMX250MZR_LAYOUT` and the fit's own ``mirrored`` (the
layout check), so the figure shows what the code uses.
"""
from __future__ import annotations

import argparse
import math
import os
import sys


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=os.path.join("docs", "images", "polariser_layout.png"))
    a = p.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fmbrdf_mi.fit.cli.layout_check import layout_text, mirrored
    from fmbrdf_mi.sensor.mosaic import IMX250MZR_LAYOUT

    layouts = [(IMX250MZR_LAYOUT, f"--layout {layout_text(IMX250MZR_LAYOUT)} (IMX250MZR, the default)"),
               (mirrored(IMX250MZR_LAYOUT), f"mirrored: --layout {layout_text(mirrored(IMX250MZR_LAYOUT))}")]
    fig, axes = plt.subplots(1, 2, figsize=(8.4, 4.4))
    for ax, (layout, title) in zip(axes, layouts):
        for r in range(2):
            for c in range(2):
                phi = layout[r][c]
                x0, y0 = c + 0.5, 1.56 - r           # pixel centre (a little up: the label below), y up
                ax.add_patch(plt.Rectangle((c, 1 - r), 1, 1, fill=False, lw=1.5))
                dx, dy = 0.3 * math.cos(math.radians(phi)), 0.3 * math.sin(math.radians(phi))
                ax.plot([x0 - dx, x0 + dx], [y0 - dy, y0 + dy], lw=4, color="tab:blue")
                ax.text(c + 0.06, 1.94 - r, f"row {r}, col {c}", fontsize=7, va="top", color="0.4")
                ax.text(x0, 1.02 - r, f"{phi}°", fontsize=10, ha="center", va="bottom")
        ax.annotate("", xy=(2.35, -0.15), xytext=(1.85, -0.15), arrowprops=dict(arrowstyle="->"))
        ax.text(2.38, -0.15, "x (image right)", va="center", fontsize=8)
        ax.annotate("", xy=(-0.15, 0.5), xytext=(-0.15, 0.0), arrowprops=dict(arrowstyle="->"))
        ax.text(-0.15, 0.55, "y (up)", ha="center", fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.set_xlim(-0.4, 3.1)
        ax.set_ylim(-0.4, 2.2)
        ax.set_aspect("equal")
        ax.axis("off")
    fig.suptitle("One 2x2 super-pixel: each pixel's polariser axis at phi from image right towards image up\n"
                 "S1 = I(0) - I(90), S2 = I(45) - I(135); a mirror swaps 45 and 135 and flips the sign of S2",
                 fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
