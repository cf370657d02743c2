"""Images of normal maps and of their changes (normal refinement's outputs), cropped to the object."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.outputs.plots import pyplot


def _crop(mask, pad=2):
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return slice(max(ys.min() - pad, 0), min(ys.max() + pad + 1, h)), slice(max(xs.min() - pad, 0),
                                                                           min(xs.max() + pad + 1, w))


def rgb(n, mask):
    """(H, W, 3) colours (n + 1) / 2 on the mask, white elsewhere (x right = red, y up = green, z = blue)."""
    out = np.ones(n.shape)
    out[mask] = np.clip((n[mask] + 1.0) / 2.0, 0.0, 1.0)
    return out


def angle_deg(a, b):
    c = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def plot_normal_map(n, mask, path, title=""):
    plt = pyplot()
    ys, xs = _crop(mask)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.imshow(rgb(n, mask)[ys, xs], interpolation="nearest")
    ax.set_title(title + "\n(x right: red, y up: green, z to the camera: blue)", fontsize=9)
    ax.axis("off")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def plot_change(n0, n1, mask, path, gt=None):
    """Start | refined | angle between them; with ``gt``, a second row: angle to gt before | after."""
    plt = pyplot()
    ys, xs = _crop(mask)
    rows = 2 if gt is not None else 1
    fig, axes = plt.subplots(rows, 3, figsize=(13, 4.2 * rows), squeeze=False)

    def angle_panel(ax, img, title, vmax):
        im = ax.imshow(np.where(mask, img, np.nan)[ys, xs], cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046, label="degrees")

    for ax, n, t in ((axes[0, 0], n0, "start"), (axes[0, 1], n1, "refined")):
        ax.imshow(rgb(n, mask)[ys, xs], interpolation="nearest")
        ax.set_title(t, fontsize=9)
        ax.axis("off")
    ch = angle_deg(n0, n1)
    angle_panel(axes[0, 2], ch, f"angle start -> refined\nmean {ch[mask].mean():.2f} deg",
                max(float(np.percentile(ch[mask], 99)), 1e-3))
    if gt is not None:
        e0, e1 = angle_deg(n0, gt), angle_deg(n1, gt)
        vmax = max(float(np.percentile(e0[mask], 99)), 1e-3)
        angle_panel(axes[1, 0], e0, f"start vs ground truth\nmean {e0[mask].mean():.2f}, median "
                                    f"{np.median(e0[mask]):.2f} deg", vmax)
        angle_panel(axes[1, 1], e1, f"refined vs ground truth (same scale)\nmean {e1[mask].mean():.2f}, "
                                    f"median {np.median(e1[mask]):.2f} deg", vmax)
        v1 = max(float(np.percentile(e1[mask], 99)), 1e-3)
        angle_panel(axes[1, 2], e1, "refined vs ground truth (own scale)", v1)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
