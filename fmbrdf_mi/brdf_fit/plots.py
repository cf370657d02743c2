"""Plots of a BRDF fit: slices of the measured and the fitted BRDF in half/difference angles."""
from __future__ import annotations

import numpy as np

from . import merl

CHANNEL_NAMES = ("red", "green", "blue")
#: The phi_d index of the slices (90 deg): the only bins :func:`slice_plot` reads.
PHI_D_INDEX = merl.DIMS[2] // 2


def slice_plot(measured, fitted, path, title=""):
    """Two rows x three channels: f against theta_h for a few theta_d, and against theta_d for a few
    theta_h, both at phi_d = 90 deg (the incidence plane perpendicular to the half-vector's plane),
    log scale; measured as dots, fitted as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    th, td, pd = merl.bin_angles()
    k = PHI_D_INDEX  # phi_d = 90 deg
    # fixed margins: constrained layout took about 1 s of a few-second fit-brdf run
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.07, top=0.9 if title else 0.95, wspace=0.2, hspace=0.3)
    cmap = plt.get_cmap("viridis")
    j_sel = [1, 30, 60, 80]
    i_sel = [0, 20, 45, 70]
    for c in range(3):
        ax = axes[0, c]
        for n, j in enumerate(j_sel):
            col = cmap(n / (len(j_sel) - 1))
            ax.plot(np.degrees(th), measured[:, j, k, c], ".", ms=3, color=col)
            ax.plot(np.degrees(th), fitted[:, j, k, c], "-", lw=1.2, color=col,
                    label=f"θd = {np.degrees(td[j]):.0f}°")
        ax.set_xlabel("θh (deg)")
        ax.set_yscale("log")
        ax.set_title(f"{CHANNEL_NAMES[c]}: against θh, φd = 90°")
        ax = axes[1, c]
        for n, i in enumerate(i_sel):
            col = cmap(n / (len(i_sel) - 1))
            ax.plot(np.degrees(td), measured[i, :, k, c], ".", ms=3, color=col)
            ax.plot(np.degrees(td), fitted[i, :, k, c], "-", lw=1.2, color=col,
                    label=f"θh = {np.degrees(th[i]):.1f}°")
        ax.set_xlabel("θd (deg)")
        ax.set_yscale("log")
        ax.set_title(f"{CHANNEL_NAMES[c]}: against θd, φd = 90°")
    for ax in axes[:, 0]:
        ax.set_ylabel("BRDF (1/sr)")
    for ax in axes[:, 2]:
        ax.legend(fontsize=8, title="dots: measured, lines: FMBRDF fit", title_fontsize=8)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
