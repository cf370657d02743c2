"""Plots of a Mueller BRDF fit: measured against fitted elements in and out of the plane of incidence (a
4 x 4 panel in SCATMECH's s/p bases, as metrology papers show them), and residual maps of f_r11 and of the
DoLP of reflected unpolarised light over the outgoing hemisphere."""
from __future__ import annotations

import numpy as np

from . import mueller as T


def relative_geometry(w_in, w_out):
    """(incidence angle deg, exit angle deg, exit azimuth deg relative to the forward direction of the plane
    of incidence, in (-180, 180]) of direction pairs."""
    th_i = np.degrees(np.arccos(np.clip(w_in[:, 2], -1, 1)))
    th_o = np.degrees(np.arccos(np.clip(w_out[:, 2], -1, 1)))
    phi_src = np.arctan2(w_in[:, 1], w_in[:, 0])
    phi_o = np.arctan2(w_out[:, 1], w_out[:, 0])
    rel = np.degrees(np.angle(np.exp(1j * (phi_o - phi_src - np.pi))))
    return th_i, th_o, rel


def _groups(table, max_incidences=3):
    """{(incidence, plane azimuth): (row indices sorted by signed exit angle, signed exit angles)} of the
    planes: the plane of incidence and the most populated other plane, for the most populated incidences."""
    th_i, th_o, rel = relative_geometry(table.w_in, table.w_out)
    inc = np.round(th_i, 1)
    plane = np.round(np.mod(rel, 180.0), 0) % 180.0
    signed = np.where(np.abs(np.angle(np.exp(1j * np.radians(rel - plane)))) < 1e-3, th_o, -th_o)
    incs = [v for v, _ in sorted(zip(*np.unique(inc, return_counts=True)), key=lambda t: -t[1])][:max_incidences]
    out = {}
    for i in sorted(incs):
        sel = inc == i
        planes = np.unique(plane[sel], return_counts=True)
        chosen = [0.0] if (plane[sel] == 0.0).sum() >= 3 else []
        others = [p for p, c in sorted(zip(*planes), key=lambda t: -t[1]) if p != 0.0 and c >= 3]
        for p in chosen + others[:1]:
            idx = np.flatnonzero(sel & (plane == p))
            order = np.argsort(signed[idx])
            out[(float(i), float(p))] = (idx[order], signed[idx][order])
    return out


def mueller_panel(table, fitted, path, title=""):
    """The 4 x 4 panel: element (i, j) in the s/p bases against the signed exit angle (positive: forward), the
    measurement as points and each model (``fitted``: {name: (n, 4, 4) package frames}) as lines; M11 is
    f_r11 (log scale), the others normalised.  Solid: the plane of incidence; dashed: the other plane."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _groups(table)
    obs = T.package_to_sp(table.mueller, table.w_in, table.w_out)
    fits = {k: T.package_to_sp(v, table.w_in, table.w_out) for k, v in fitted.items()}
    fig, axes = plt.subplots(4, 4, figsize=(14, 12), sharex=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ["-", "--", ":", "-."]
    for g, ((inc, plane), (idx, x)) in enumerate(groups.items()):
        c = colours[g % len(colours)]
        label = f"θi {inc:g}°, plane {plane:g}°"
        for i in range(4):
            for j in range(4):
                ax = axes[i, j]
                o = obs[idx, i, j] if (i, j) == (0, 0) else obs[idx, i, j] / obs[idx, 0, 0]
                ax.plot(x, o, "o", ms=3, color=c, label=label if (i, j) == (0, 0) else None)
                for k, (name, M) in enumerate(fits.items()):
                    v = M[idx, i, j] if (i, j) == (0, 0) else M[idx, i, j] / M[idx, 0, 0]
                    ax.plot(x, v, styles[k % len(styles)], lw=1, color=c,
                            label=name if (i, j) == (0, 1) and g == 0 else None)
    for i in range(4):
        for j in range(4):
            ax = axes[i, j]
            ax.set_title(f"f_r11 (1/sr)" if (i, j) == (0, 0) else f"m{i + 1}{j + 1}", fontsize=9)
            if (i, j) == (0, 0):
                ax.set_yscale("log")
            else:
                ax.set_ylim(-1.05, 1.05)
            if i == 3:
                ax.set_xlabel("signed exit angle (deg)")
    axes[0, 0].legend(fontsize=6)
    axes[0, 1].legend(fontsize=6, title="lines", title_fontsize=6)
    fig.suptitle(title + "\npoints: measured; lines: fitted (s/p bases of the planes of incidence and exit)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def residual_maps(table, fitted, path, title=""):
    """log10(f_fit / f_measured) and DoLP_fit - DoLP_measured (unpolarised light) over the outgoing
    hemisphere (projected: sin(theta_o) times the unit vector of the exit azimuth relative to the forward
    direction), one column per incidence angle (up to three)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    th_i, th_o, rel = relative_geometry(table.w_in, table.w_out)
    inc = np.round(th_i, 1)
    vals, counts = np.unique(inc, return_counts=True)
    cols = [v for v, _ in sorted(zip(vals, counts), key=lambda t: -t[1])[:3]]
    if len(vals) > 3 and counts.max() < 10:    # random geometries: one map of everything
        cols = [None]
    f_obs = table.f_r11
    dolp = lambda M: np.hypot(M[:, 1, 0], M[:, 2, 0]) / M[:, 0, 0]
    names = list(fitted)
    fig, axes = plt.subplots(2 * len(names), len(cols), figsize=(4 * len(cols), 3.6 * 2 * len(names)), squeeze=False)
    x = np.sin(np.radians(th_o)) * np.cos(np.radians(rel))
    y = np.sin(np.radians(th_o)) * np.sin(np.radians(rel))
    for m, name in enumerate(names):
        M = fitted[name]
        rf = np.log10(M[:, 0, 0] / f_obs)
        rd = dolp(M) - dolp(table.mueller)
        for c, i in enumerate(cols):
            sel = np.ones(len(inc), bool) if i is None else inc == i
            for r, (v, what, lim) in enumerate(((rf, "log10 f_r11 fit/measured", max(np.abs(rf).max(), 1e-3)),
                                               (rd, "DoLP fit - measured", max(np.abs(rd).max(), 1e-3)))):
                ax = axes[2 * m + r, c]
                sc = ax.scatter(x[sel], y[sel], c=v[sel], cmap="RdBu_r", vmin=-lim, vmax=lim, s=14)
                ax.add_patch(plt.Circle((0, 0), 1, fill=False, lw=0.5))
                ax.set_aspect("equal")
                ax.set_xlim(-1.05, 1.05)
                ax.set_ylim(-1.05, 1.05)
                ax.set_title(f"{name}: {what}" + ("" if i is None else f", θi {i:g}°"), fontsize=8)
                fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.suptitle(title + "\nx: towards the forward direction; radius sin(θo)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)

