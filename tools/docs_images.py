"""Regenerate the figures of docs/images/ that the README and the documentation show.

    python tools/docs_images.py [--only previews,fit,layout] [--images docs/images]

* ``previews``: the render previews (default scene, variant llvm_ad_spectral_polarized, and
  scenes/spheres.xml) through the ``fmbrdf-mi render`` command.
* ``fit``: the fitting example of docs/howto/fit.md (two mono renders, ``fmbrdf-mi fit --relight
  --baselines``; about a minute): ``fit_profiles.png``, ``fit_images.png``.
* ``layout``: the polariser-layout convention (``polariser_layout.png``).  Left: one 2x2 super-pixel of
  a raw mosaic as ``--layout`` reads it (row-major from the top-left pixel, default IMX250MZR
  90,45,135,0), each pixel's polariser transmission axis drawn at its angle phi, measured from image
  right (x) towards image up (y), the frame of the Stokes images (S1 = I0 - I90, S2 = I45 - I135).
  Right: the same sensor seen through a mirror: 45 and 135 trade places, S2 changes sign, and
  ``--layout 90,135,45,0`` reads it.  The angles come from
  :data:`fmbrdf_mi.sensor.mosaic.IMX250MZR_LAYOUT` and the fit's own ``mirrored`` (the layout check),
  so the figure shows what the code uses.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def cli(*args):
    """One ``fmbrdf-mi`` command in a child process (quiet)."""
    subprocess.run([sys.executable, "-m", "fmbrdf_mi", *args, "-q"], check=True, cwd=ROOT)


def previews(tmp, images):
    cli("render", f"{tmp}/sphere.exr", "--angles", "--mosaic")
    cli("render", f"{tmp}/mod/sphere.exr", "--aolp-dolp")
    cli("render", "-s", "scenes/spheres.xml", f"{tmp}/spheres.exr")
    names = [f"sphere_{k}.png" for k in ("intensity", "dolp", "aolp", "angles", "mosaic")]
    names += [f"spheres_{k}.png" for k in ("intensity", "dolp", "aolp")]
    for n in names:
        shutil.copy(os.path.join(tmp, n), images)
    shutil.copy(os.path.join(tmp, "mod", "sphere_aolp.png"), os.path.join(images, "sphere_aolp_dolp.png"))


def fit(tmp, images):
    mono = ("--variant", "llvm_ad_mono_polarized", "-D", "alpha=0.15")
    cli("render", *mono, "-D", "light_dir=-0.5,0.5,1", f"{tmp}/a.exr")
    cli("render", *mono, "-D", "light_dir=0.7,-0.2,0.6", f"{tmp}/b.exr")
    cli("fit", f"{tmp}/a.exr", "--relight", f"{tmp}/b.exr", "--baselines", "-o", f"{tmp}/fit_a")
    shutil.copy(os.path.join(tmp, "fit_a", "profiles.png"), os.path.join(images, "fit_profiles.png"))
    shutil.copy(os.path.join(tmp, "fit_a", "images.png"), os.path.join(images, "fit_images.png"))


def layout(tmp, images):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fmbrdf_mi.fit.cli.layout_check import layout_text, mirrored
    from fmbrdf_mi.sensor.mosaic import IMX250MZR_LAYOUT

    layouts = [(IMX250MZR_LAYOUT, f"--layout {layout_text(IMX250MZR_LAYOUT)} (IMX250MZR, the default)"),
               (mirrored(IMX250MZR_LAYOUT), f"mirrored: --layout {layout_text(mirrored(IMX250MZR_LAYOUT))}")]
    fig, axes = plt.subplots(1, 2, figsize=(8.4, 4.4))
    for ax, (lay, title) in zip(axes, layouts):
        for r in range(2):
            for c in range(2):
                phi = lay[r][c]
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
    fig.savefig(os.path.join(images, "polariser_layout.png"), dpi=110)


PARTS = {"previews": previews, "fit": fit, "layout": layout}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", default=",".join(PARTS), help=f"which figures: a comma list of {', '.join(PARTS)}")
    p.add_argument("--images", default=os.path.join(ROOT, "docs", "images"), help="where the figures go")
    a = p.parse_args(argv)
    parts = [s for s in a.only.split(",") if s]
    bad = [s for s in parts if s not in PARTS]
    if bad:
        p.error(f"--only: unknown {', '.join(bad)}; valid: {', '.join(PARTS)}")
    os.makedirs(a.images, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for part in parts:
            PARTS[part](tmp, os.path.abspath(a.images))
            print(f"{part}: written to {a.images}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
