"""Figures of a fit: DoLP and intensity profiles (the paper's figures), image comparisons, albedo and normal maps."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi import stokes_io
from fmbrdf_mi.previews import pyplot
from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg
from fmbrdf_mi.fit.objectives.loss import Target
from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor import rice
from fmbrdf_mi.sensor.mosaic import COLOURS


def _channel_stokes(values, cam):
    """Per-channel Stokes (3, 3, H, W) of (16, H, W) samples, demosaicked as mosaic.stokes_from_colour_mosaic."""
    h, w = values.shape[1:]
    raw = np.empty((4 * h, 4 * w))
    k = 0
    for cr, cc, _ in mosaic.colour_cells(cam.cfa):
        for dr in range(2):
            for dc in range(2):
                raw[2 * cr + dr::4, 2 * cc + dc::4] = values[k]
                k += 1
    return mosaic.stokes_from_colour_mosaic(raw, cam.layout, cam.cfa)[:, :3]


def plot_colour_fit(smp, pred, sel, cam, path, title=""):
    """Observed | fitted | residual intensity and DoLP per colour channel, cropped to the fitted periods ``sel``."""
    plt = pyplot()
    sel = np.asarray(sel, bool)
    obs_s = _channel_stokes(np.where(sel, smp.values, np.nan), cam)
    fit_s = _channel_stokes(pred, cam)
    crop = crop_to(sel)
    fig, axes = plt.subplots(6, 3, figsize=(10, 17))
    for c, ch in enumerate(COLOURS):
        shown = shown_pixels(obs_s[c], obs_s[c], sel, np.flatnonzero(sel))
        for q, (name, f) in enumerate((("intensity", lambda s: s[0]), ("DoLP", stokes_io.dolp))):
            o = np.where(sel, f(obs_s[c]), np.nan)[crop]
            p = np.where(sel, f(fit_s[c]), np.nan)[crop]
            s = shown[name][crop]
            compare_row(fig, axes[2 * c + q], o, p, np.where(s, p - o, np.nan), s, sel[crop] & ~s,
                        (f"{ch} observed {name}", f"{ch} fitted {name}",
                         f"{ch} fitted - observed (hatched: not fitted)"),
                        fontsize=9)
    save(fig, path, 90, title, fontsize=8, wrap=True)


def crop_to(mask, pad=0):
    """The slices (rows, columns) of the bounding box of ``mask`` widened by ``pad`` (all of it if empty)."""
    ys, xs = np.nonzero(mask)
    if not ys.size:
        return slice(None), slice(None)
    return tuple(slice(max(v.min() - pad, 0), v.max() + pad + 1) for v in (ys, xs))


def save(fig, path, dpi, title="", tight=False, **kw):
    if title:
        fig.suptitle(title, **kw)
    if not tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi, **({"bbox_inches": "tight"} if tight else {}))
    pyplot().close(fig)


def panel(fig, ax, img, title, fontsize=None, colorbar=True, label="", **kw):
    im = ax.imshow(img, **kw)
    ax.set_title(title, fontsize=fontsize)
    ax.axis("off")
    if colorbar:
        fig.colorbar(im, ax=ax, fraction=0.046, label=label)


def compare_row(fig, axes, o, p, err, shown, hidden, titles, fontsize):
    """Observed | predicted | residual on one row, scaled by the ``shown`` pixels, ``hidden`` ones hatched."""
    vmax, emax = scale_from(o, shown), scale_from(err, shown)
    for c, (img, kw) in enumerate(((o, dict(vmin=0, vmax=vmax, cmap="gray")), (p, dict(vmin=0, vmax=vmax, cmap="gray")),
                                   (err, dict(vmin=-emax, vmax=emax, cmap="RdBu_r")))):
        panel(fig, axes[c], img, titles[c], fontsize, **kw)
        if c == 2 and hidden.any():
            axes[c].contourf(hidden.astype(float), levels=[0.5, 1.5], colors=["0.8"], hatches=["////"],
                             origin="upper", extent=(-0.5, hidden.shape[1] - 0.5, hidden.shape[0] - 0.5, -0.5))


def model_dolp(stokes, lin_variance=None):
    """DoLP of a model's Stokes image; with ``lin_variance`` = var(S1) = var(S2), the mean a noisy camera measures."""
    if lin_variance is None:
        return stokes_io.dolp(stokes)
    s = np.asarray(stokes, dtype=np.float64)
    lin = rice.mean_length(np.hypot(s[1], s[2]) + 1e-30, np.sqrt(np.clip(lin_variance, 0, None)))
    return np.where(s[0] > 1e-12, lin / np.where(s[0] > 1e-12, s[0], 1.0), 0.0)


def _binned(x, y, bins):
    """(bin centres, means of ``y``) of the ``bins`` of ``x`` holding at least 3 points."""
    idx, nb = np.digitize(x, bins) - 1, len(bins) - 1
    ok = (idx >= 0) & (idx < nb)
    n = np.bincount(idx[ok], minlength=nb)
    full = n >= 3
    return (0.5 * (bins[:-1] + bins[1:]))[full], (np.bincount(idx[ok], y[ok], nb)[full] / n[full])


def plot_profiles(obs, fitted, path, pixels=None, title="", others=None, max_points=4000, seed=0):
    """DoLP against the normal-view angle, intensity against the normal-light angle; ``fitted``: predicted Stokes
    (3, H, W), ``others``: {label: Stokes} of baselines (binned means), ``pixels``: flat indices (default: mask)."""
    plt = pyplot()
    idx = np.flatnonzero(obs.mask.ravel()) if pixels is None else np.asarray(pixels)
    n = obs.normals.reshape(-1, 3)[idx]
    ang_v = np.degrees(np.arccos(np.clip(np.sum(n * obs.view_dirs.reshape(-1, 3)[idx], 1), -1, 1)))
    ang_l = np.degrees(np.arccos(np.clip(n @ obs.light_dir, -1, 1)))
    series, var = {"observed": obs.stokes, "fitted": fitted, **(others or {})}, obs.lin_variance
    vals = {k: ((stokes_io.dolp(s) if k == "observed" else model_dolp(s, var)).ravel()[idx], s[0].ravel()[idx])
            for k, s in series.items()}
    sub = np.random.default_rng(seed).choice(len(idx), min(max_points, len(idx)), replace=False)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, x, j, xl, yl in ((axes[0], ang_v, 0, "angle between normal and view (deg)", "DoLP"),
                             (axes[1], ang_l, 1, "angle between normal and light (deg)", "intensity")):
        bins = np.linspace(0, max(90.0, float(x.max())), 46)
        ax.scatter(x[sub], vals["observed"][j][sub], s=2, c="0.6", label="observed", rasterized=True)
        ax.scatter(x[sub], vals["fitted"][j][sub], s=2, c="C3", alpha=0.5, label="fitted (per pixel)",
                   rasterized=True)
        for k, (label, v) in enumerate(vals.items()):
            c, m = _binned(x, v[j], bins)
            ax.plot(c, m, lw=1.5, c="k" if label == "observed" else f"C{(k + 1) % 10}",
                    ls="-" if label in ("observed", "fitted") else "--", label=f"{label} (binned mean)")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl + (" (models: as measured with the camera's noise)" if j == 0 and var is not None else ""))
        ax.grid(alpha=0.3)
    rmse_d = np.sqrt(np.mean((vals["fitted"][0] - vals["observed"][0]) ** 2))
    rmse_i = np.sqrt(np.mean((vals["fitted"][1] - vals["observed"][1]) ** 2)) / np.mean(vals["observed"][1])
    axes[0].set_title(f"DoLP RMSE {rmse_d:.4f}")
    axes[1].set_title(f"intensity RMSE / mean {rmse_i:.4f}")
    axes[1].legend(fontsize=7, loc="upper right")
    save(fig, path, 120, title)


def scale_from(values, sel, q=99.0, floor=1e-6):
    """Colour-scale maximum: the ``q``-th percentile of |values| on ``sel``, so unfitted pixels do not set the scale."""
    v = np.abs(np.asarray(values, dtype=np.float64)[sel])
    v = v[np.isfinite(v)]
    return max(float(np.percentile(v, q)), floor) if v.size else 1.0


def shown_pixels(observed, predicted, mask, pixels=None, dolp_min_intensity=0.02):
    """The pixels the residual panels show, {"intensity", "DoLP"}: (H, W) bool, the fitted ones (``pixels``; default:
    finite, non-zero predictions in the mask), for the DoLP those the loss's DoLP term keeps
    (:class:`fmbrdf_mi.fit.objectives.loss.Target`)."""
    m = np.asarray(mask, bool)
    o = np.asarray(observed, dtype=np.float64)
    p = np.asarray(predicted, dtype=np.float64)
    if pixels is None:
        fitted = m & np.all(np.isfinite(p), axis=0) & (p[0] != 0)
    else:
        fitted = np.zeros(m.size, bool)
        fitted[np.asarray(pixels, dtype=np.int64)] = True
        fitted = fitted.reshape(m.shape) & m
    fitted &= np.all(np.isfinite(o), axis=0)
    dolp = np.zeros_like(fitted)
    if fitted.any() and np.mean(o[0][fitted]) > 0:
        dolp[fitted] = Target.from_stokes(o[:, fitted], dolp_min_intensity=dolp_min_intensity).dolp_valid
    return {"intensity": fitted, "DoLP": dolp}


def residuals(observed, predicted, mask, pixels=None, lin_variance=None, dolp_min_intensity=0.02):
    """:func:`plot_images`' "fitted - observed" panels, {"intensity", "DoLP"}: (residual (H, W), unit), NaN where
    :func:`shown_pixels` hides it.  With ``lin_variance`` = var(S1) = var(S2) = sigma^2, in noise standard
    deviations (S0's is sigma / sqrt(2), the DoLP's sigma / S0 to first order); else image and DoLP units."""
    shown = shown_pixels(observed, predicted, mask, pixels, dolp_min_intensity)
    o = np.asarray(observed, dtype=np.float64)
    p = np.asarray(predicted, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        diff = {"intensity": p[0] - o[0], "DoLP": model_dolp(p, lin_variance) - stokes_io.dolp(o)}
        unit = {"intensity": "image units", "DoLP": "DoLP"}
        if lin_variance is not None:
            sigma = np.sqrt(np.clip(np.asarray(lin_variance, dtype=np.float64), 0.0, None))
            sd = {"intensity": sigma / np.sqrt(2.0), "DoLP": sigma / np.where(o[0] > 0, o[0], np.nan)}
            for k in diff:
                diff[k] = np.where(sd[k] > 0, diff[k] / sd[k], np.nan)
            unit = {k: "noise s.d." for k in diff}
    return {k: (np.where(shown[k], diff[k], np.nan), unit[k]) for k in diff}


def plot_images(observed, predicted, mask, path, title="", label="fitted", lin_variance=None, pixels=None):
    """Intensity and DoLP: observed | predicted | residual (:func:`residuals`), the object's unshown pixels hatched."""
    plt = pyplot()
    m = np.asarray(mask, bool)
    res = residuals(observed, predicted, m, pixels, lin_variance)
    rows = (("intensity", observed[0], predicted[0]),
            ("DoLP", stokes_io.dolp(observed), model_dolp(predicted, lin_variance)))
    fig, axes = plt.subplots(2, 3, figsize=(11, 7))
    for r, (name, o, p) in enumerate(rows):
        err, unit = res[name]
        shown = np.isfinite(err)
        compare_row(fig, axes[r], np.where(m, o, np.nan), np.where(m, p, np.nan), err, shown, m & ~shown,
                    (f"observed {name}", f"{label} {name}", f"{label} - observed ({unit})\nhatched: not fitted"),
                    fontsize=10)
    save(fig, path, 110, title)


def plot_loss_history(histories, path):
    """Loss against wall time for each fitted model."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, hist in histories.items():
        if hist:
            ax.semilogy([h["time"] for h in hist], [h["loss"] for h in hist], "o-", ms=3, label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("objective (chi^2 for the likelihood; eq:optimization for the paper's loss)")
    ax.grid(alpha=0.3)
    if any(histories.values()):
        ax.legend()
    save(fig, path, 110)


def plot_albedo_maps(maps, path, title=""):
    """Per-pixel albedo maps, their relative standard errors and where the split is identified (a row per colour
    channel); grey scales from the albedos with relative standard error <= 0.5, so poorly determined ones clip."""
    a = {k: np.asarray(maps[k], dtype=np.float64) for k in ("k_s", "k_b", "k_s_se", "k_b_se", "identified")}
    colour = a["k_s"].ndim == 3
    labels = (maps.get("channels") or ["R", "G", "B"]) if colour else [None]
    crop = crop_to(np.any(np.isfinite(a["k_s"]), axis=0) if colour else np.isfinite(a["k_s"]), pad=1)
    fig, axes = pyplot().subplots(len(labels), 5, figsize=(16.0, 3.6 * len(labels)), squeeze=False)
    for c, label in enumerate(labels):
        m = {k: v[c] if colour else v for k, v in a.items()}
        fitted, tag = np.isfinite(m["k_s"]), "" if label is None else f"{label}: "
        panels = []
        for k in ("k_s", "k_b"):
            with np.errstate(invalid="ignore"):
                sel = fitted & (m[k + "_se"] <= 0.5 * m[k])
            panels.append((k, m[k], dict(vmin=0, vmax=scale_from(m[k], sel if sel.any() else fitted), cmap="gray")))
        for k in ("k_s", "k_b"):
            with np.errstate(invalid="ignore", divide="ignore"):
                r = m[k + "_se"] / m[k]
            panels.append((f"SE({k}) / {k}", r, dict(vmin=0, vmax=min(scale_from(r, fitted, 95.0), 1.0), cmap="magma")))
        panels.append(("split identified (both SE <= 0.5)", np.where(fitted, m["identified"], np.nan),
                       dict(vmin=0, vmax=1, cmap="RdYlGn")))
        for ax, (name, img, kw) in zip(axes[c], panels):
            panel(fig, ax, img[crop], tag + name, **kw)
    save(fig, path, 110, title)


def plot_materials(labels, pixels, block, path, title=""):
    """``materials.png``: fitted pixels opaque, labelled unfitted ones faint, unlabelled grey; the legend from
    fit.json's ``materials`` block ``block``."""
    plt = pyplot()
    from matplotlib import colors
    from matplotlib.patches import Patch

    lab = np.asarray(labels)
    M = int(block["count"])
    cmap = plt.get_cmap("tab10" if M <= 10 else "tab20")
    rgb = np.full(lab.shape + (3,), 0.85)
    used = np.zeros(lab.size, bool)
    used[np.asarray(pixels, dtype=np.int64)] = True
    used = used.reshape(lab.shape)
    for m in range(M):
        c = np.asarray(colors.to_rgb(cmap(m % cmap.N)))
        rgb[(lab == m) & used] = c
        rgb[(lab == m) & ~used] = 0.35 * c + 0.65
    fig, ax = plt.subplots(figsize=(5.5, 4.8))
    ax.imshow(rgb, interpolation="nearest")
    ax.axis("off")
    handles = [Patch(color=cmap(m % cmap.N), label=f"{m}: {block['pixels'][m]} px; "
                     + ", ".join(f"{k}={v:.3g}" for k, v in block["parameters"][m].items())) for m in range(M)]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False)
    ax.set_title(title or f"{M} materials (faint: labelled, not fitted; grey: no material)", fontsize=9)
    save(fig, path, 110)


def rgb(n, mask):
    """(H, W, 3) colours (n + 1) / 2 on the mask, white elsewhere (x right = red, y up = green, z = blue)."""
    out = np.ones(n.shape)
    out[mask] = np.clip((n[mask] + 1.0) / 2.0, 0.0, 1.0)
    return out


def plot_normal_map(n, mask, path, title=""):
    fig, ax = pyplot().subplots(figsize=(5, 5))
    panel(fig, ax, rgb(n, mask)[crop_to(mask, 2)], title + "\n(x right: red, y up: green, z to the camera: blue)", 9,
          colorbar=False, interpolation="nearest")
    save(fig, path, 100, tight=True)


def plot_change(n0, n1, mask, path, gt=None):
    """Start | refined | angle between them; with ``gt``, a second row: angle to gt before | after."""
    crop = crop_to(mask, 2)
    fig, axes = pyplot().subplots(1 + (gt is not None), 3, figsize=(13, 4.2 * (1 + (gt is not None))), squeeze=False)

    def angles(ax, img, title, vmax=None):
        vmax = vmax or max(float(np.percentile(img[mask], 99)), 1e-3)
        panel(fig, ax, np.where(mask, img, np.nan)[crop], title, 9, label="degrees", cmap="magma", vmin=0, vmax=vmax,
              interpolation="nearest")
        return vmax

    for ax, n, t in ((axes[0, 0], n0, "start"), (axes[0, 1], n1, "refined")):
        panel(fig, ax, rgb(n, mask)[crop], t, 9, colorbar=False, interpolation="nearest")
    ch = angular_error_deg(n0, n1)
    angles(axes[0, 2], ch, f"angle start -> refined\nmean {ch[mask].mean():.2f} deg")
    if gt is not None:
        e0, e1 = angular_error_deg(n0, gt), angular_error_deg(n1, gt)
        vmax = angles(axes[1, 0], e0, f"start vs ground truth\nmean {e0[mask].mean():.2f}, median "
                                      f"{np.median(e0[mask]):.2f} deg")
        angles(axes[1, 1], e1, f"refined vs ground truth (same scale)\nmean {e1[mask].mean():.2f}, "
                               f"median {np.median(e1[mask]):.2f} deg", vmax)
        angles(axes[1, 2], e1, "refined vs ground truth (own scale)")
    save(fig, path, 90, tight=True)
