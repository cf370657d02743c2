"""Figures of a fit: DoLP and intensity profiles (as in the paper's figures) and image comparisons."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi import stokes_io
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


def colour_shown(obs_s, sel, dolp_min_intensity=0.02):
    """Which cells :func:`plot_colour_fit`'s residual panels show, per channel: (3, 2, H, W) bool
    (channel; intensity, DoLP).  Intensity: the fitted cells ``sel``; DoLP: of those, the ones whose
    observed intensity in that channel exceeds ``dolp_min_intensity`` times its 99th percentile over
    ``sel`` (the rule of the DoLP term, :class:`fmbrdf_mi.fit.objectives.loss.Target`: the DoLP of an
    unlit cell is noise)."""
    sel = np.asarray(sel, bool)
    out = np.zeros((len(obs_s), 2) + sel.shape, bool)
    for c, s in enumerate(obs_s):
        i = np.asarray(s[0], dtype=np.float64)
        ok = sel & np.all(np.isfinite(s), axis=0)
        out[c, 0] = ok
        if ok.any():
            out[c, 1] = ok & (i > dolp_min_intensity * np.percentile(i[ok], 99))
    return out


def plot_colour_fit(smp, pred, sel, cam, path, title=""):
    """Observed vs fitted intensity and DoLP per channel, cropped to the fitted periods; residuals beside,
    shown on the cells :func:`colour_shown` selects (the object's other cells grey and hatched)."""
    plt = pyplot()
    obs_s = _channel_stokes(np.where(sel, smp.values, np.nan), cam)
    fit_s = _channel_stokes(pred, cam)
    shown = colour_shown(obs_s, sel)
    rows, cols = np.nonzero(sel)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    fig, axes = plt.subplots(6, 3, figsize=(10, 17))
    for c, ch in enumerate(COLOURS):
        for q, (name, f) in enumerate((("intensity", lambda s: s[0]), ("DoLP", stokes_io.dolp))):
            o = np.where(sel, f(obs_s[c]), np.nan)[r0:r1, c0:c1]
            p = np.where(sel, f(fit_s[c]), np.nan)[r0:r1, c0:c1]
            s = shown[c, q, r0:r1, c0:c1]
            err = np.where(s, p - o, np.nan)
            vmax = scale_from(o, s)
            emax = scale_from(err, s)
            row = 2 * c + q
            for k, (img, t, kw) in enumerate(((o, f"{ch} observed {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                              (p, f"{ch} fitted {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                              (err, f"{ch} fitted - observed (hatched: not fitted)",
                                               dict(vmin=-emax, vmax=emax, cmap="RdBu_r")))):
                im = axes[row, k].imshow(img, **kw)
                if k == 2:
                    _not_shown(axes[row, k], np.asarray(sel, bool)[r0:r1, c0:c1] & ~s)
                axes[row, k].set_title(t, fontsize=9)
                axes[row, k].axis("off")
                fig.colorbar(im, ax=axes[row, k], fraction=0.046)
    if title:
        fig.suptitle(title, fontsize=8, wrap=True)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def model_dolp(stokes, lin_variance=None):
    """DoLP of a model's Stokes image; with the camera's var(S1) = var(S2), the DoLP it measures on average.

    That is what the fit compares with a noisy observation (loss.py); the
    noise-free DoLP of a dim, weakly polarised pixel lies below the observed one.
    """
    if lin_variance is None:
        return stokes_io.dolp(stokes)
    s = np.asarray(stokes, dtype=np.float64)
    lin = rice.mean_length(np.hypot(s[1], s[2]) + 1e-30, np.sqrt(np.clip(lin_variance, 0, None)))
    return np.where(s[0] > 1e-12, lin / np.where(s[0] > 1e-12, s[0], 1.0), 0.0)


def _binned(x, y, bins):
    idx = np.digitize(x, bins) - 1
    centres, means = [], []
    for b in range(len(bins) - 1):
        sel = idx == b
        if sel.sum() >= 3:
            centres.append(0.5 * (bins[b] + bins[b + 1]))
            means.append(np.mean(y[sel]))
    return np.array(centres), np.array(means)


def plot_profiles(obs, fitted, path, pixels=None, title="", others=None, max_points=4000, seed=0):
    """DoLP against the angle between normal and view, intensity against the angle between normal and light.

    ``fitted``: predicted Stokes (3, H, W); ``others``: {label: Stokes} of
    further models (baselines) drawn as binned means; ``pixels``: flat indices
    (default: the mask).
    """
    plt = pyplot()
    idx = np.flatnonzero(obs.mask.ravel()) if pixels is None else np.asarray(pixels)
    n = obs.normals.reshape(-1, 3)[idx]
    ang_v = np.degrees(np.arccos(np.clip(np.sum(n * obs.view_dirs.reshape(-1, 3)[idx], 1), -1, 1)))
    ang_l = np.degrees(np.arccos(np.clip(n @ obs.light_dir, -1, 1)))
    series = {"observed": obs.stokes, "fitted": fitted}
    series.update(others or {})
    var = obs.lin_variance
    vals = {k: ((stokes_io.dolp(s) if k == "observed" else model_dolp(s, var)).ravel()[idx], s[0].ravel()[idx])
            for k, s in series.items()}
    rng = np.random.default_rng(seed)
    sub = rng.choice(len(idx), min(max_points, len(idx)), replace=False)
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
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def scale_from(values, sel, q=99.0, floor=1e-6):
    """Colour-scale maximum: the ``q``-th percentile of |values| over the selected (fitted) pixels.

    Unlit pixels (whose DoLP is noise) and the one-pixel rim (whose DoLP and
    error are extreme) are not fitted, so they do not set the scale.
    """
    v = np.abs(np.asarray(values, dtype=np.float64)[sel])
    v = v[np.isfinite(v)]
    return max(float(np.percentile(v, q)), floor) if v.size else 1.0


def shown_pixels(observed, predicted, mask, pixels=None, dolp_min_intensity=0.02):
    """Which pixels the residual panels of :func:`plot_images` show: {"intensity": (H, W), "DoLP": (H, W)} bool.

    Intensity: the fitted pixels (``pixels``, flat indices; default the mask
    pixels the prediction covers, i.e. finite and not zero: predict_image
    leaves the others at 0).  DoLP: of those, the ones bright enough for
    their DoLP not to be noise, by the rule of the paper's loss's DoLP term
    (:class:`fmbrdf_mi.fit.objectives.loss.Target`: observed intensity above
    ``dolp_min_intensity`` times its 99th percentile over the fitted pixels).  Unlit pixels, the eroded
    rim (pixels partly off the object) and the pixels near the pole are not
    fitted, so their difference is not a misfit and is not shown.
    """
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
    """The "fitted - observed" panels of :func:`plot_images`: {name: (residual (H, W), unit)}, name
    "intensity" or "DoLP", the residual NaN where :func:`shown_pixels` does not show it.

    The model's DoLP is the one the fit compares (:func:`model_dolp`).  With
    ``lin_variance`` = var(S1) = var(S2) known, residuals are in units of the
    noise standard deviation: S0 = (I0 + I45 + I90 + I135) / 2 has half the
    variance of S1 = I0 - I90, and the DoLP's standard deviation is sigma / S0
    to first order (the noise along (S1, S2)); without it, in image and DoLP units.
    """
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


def _not_shown(ax, hidden):
    """Grey, hatched, where a residual panel does not show the pixel (object pixels outside its set)."""
    if hidden.any():
        ax.contourf(hidden.astype(float), levels=[0.5, 1.5], colors=["0.8"], hatches=["////"],
                    origin="upper", extent=(-0.5, hidden.shape[1] - 0.5, hidden.shape[0] - 0.5, -0.5))


def plot_images(observed, predicted, mask, path, title="", label="fitted", lin_variance=None, pixels=None):
    """Intensity and DoLP: observed | predicted | residual (``lin_variance``: see :func:`model_dolp`).

    The residual panels (:func:`residuals`) show the pixels the fit used
    (``pixels``, flat indices; default the mask pixels with a prediction; the
    DoLP only where its term uses it), in units of the noise standard
    deviation when ``lin_variance`` is known; the object's other pixels are
    grey and hatched.  Colour scales come from the 99th percentile over the
    shown pixels.
    """
    plt = pyplot()
    m = np.asarray(mask, bool)
    res = residuals(observed, predicted, m, pixels, lin_variance)
    rows = (("intensity", observed[0], predicted[0]),
            ("DoLP", stokes_io.dolp(observed), model_dolp(predicted, lin_variance)))
    fig, axes = plt.subplots(2, 3, figsize=(11, 7))
    for r, (name, o, p) in enumerate(rows):
        err, unit = res[name]
        shown = np.isfinite(err)
        o = np.where(m, o, np.nan)
        p = np.where(m, p, np.nan)
        vmax = scale_from(o, shown, 99.0)
        emax = scale_from(err, shown, 99.0)
        for c, (img, t, kw) in enumerate(((o, f"observed {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                          (p, f"{label} {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                          (err, f"{label} - observed ({unit})\nhatched: not fitted",
                                           dict(vmin=-emax, vmax=emax, cmap="RdBu_r")))):
            im = axes[r, c].imshow(img, **kw)
            if c == 2:
                _not_shown(axes[r, c], m & ~shown)
            axes[r, c].set_title(t, fontsize=10)
            axes[r, c].axis("off")
            fig.colorbar(im, ax=axes[r, c], fraction=0.046)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_albedo_maps(maps, path, title=""):
    """Per-pixel albedos (a fit with ``albedo="per-pixel"``): k_s, k_b, their relative standard errors and
    where the surface / body split is identified, cropped to the fitted pixels; a colour fit's maps
    ((3, H, W): R, G, B) one row per channel, each map's grey scale its own channel's (the channels' albedos
    differ by the colour filters' transmission).  The grey scales are set by the albedos whose relative
    standard error is at most 0.5 (poorly determined ones, e.g. k_s where the surface lobe is dark, show
    clipped)."""
    plt = pyplot()
    ks_all = np.asarray(maps["k_s"], dtype=np.float64)
    colour = ks_all.ndim == 3
    labels = (maps.get("channels") or ["R", "G", "B"]) if colour else [None]

    def layer(key, c, dtype=np.float64):
        a = np.asarray(maps[key], dtype=dtype)
        return a[c] if colour else a

    fitted_any = np.any(np.isfinite(ks_all), axis=0) if colour else np.isfinite(ks_all)
    ys, xs = np.nonzero(fitted_any)
    if ys.size:
        crop = (slice(max(ys.min() - 1, 0), ys.max() + 2), slice(max(xs.min() - 1, 0), xs.max() + 2))
    else:
        crop = (slice(None), slice(None))
    rows = []
    for c, label in enumerate(labels):
        ks, kb = layer("k_s", c), layer("k_b", c)
        with np.errstate(invalid="ignore", divide="ignore"):
            rs, rb = layer("k_s_se", c) / ks, layer("k_b_se", c) / kb
        fitted = np.isfinite(ks)
        ident = np.where(fitted, layer("identified", c, float), np.nan)
        tag = "" if label is None else f"{label}: "
        with np.errstate(invalid="ignore"):
            sel_s, sel_b = (fitted & (layer(k + "_se", c) <= 0.5 * v) for k, v in (("k_s", ks), ("k_b", kb)))
        sel_s, sel_b = (sel if sel.any() else fitted for sel in (sel_s, sel_b))
        rows.append(((tag + "k_s", ks, dict(vmin=0, vmax=scale_from(ks, sel_s), cmap="gray")),
                     (tag + "k_b", kb, dict(vmin=0, vmax=scale_from(kb, sel_b), cmap="gray")),
                     (tag + "SE(k_s) / k_s", rs, dict(vmin=0, vmax=min(scale_from(rs, fitted, 95.0), 1.0),
                                                      cmap="magma")),
                     (tag + "SE(k_b) / k_b", rb, dict(vmin=0, vmax=min(scale_from(rb, fitted, 95.0), 1.0),
                                                      cmap="magma")),
                     (tag + "split identified (both SE <= 0.5)", ident, dict(vmin=0, vmax=1, cmap="RdYlGn"))))
    ncol = len(rows[0])
    fig, axes = plt.subplots(len(rows), ncol, figsize=(3.2 * ncol, 3.6 * len(rows)), squeeze=False)
    for r, panels in enumerate(rows):
        for ax, (name, img, kw) in zip(axes[r], panels):
            im = ax.imshow(img[crop], **kw)
            ax.set_title(name)
            ax.axis("off")
            fig.colorbar(im, ax=ax, fraction=0.046)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_materials(labels, pixels, block, path, title=""):
    """The label map a fit of several materials used (``materials.png``): each material in its colour
    (grey: not fitted), its fitted pixels opaque and its labelled but unused pixels (eroded border, pole,
    saturated, subset) faint; the legend gives each material's pixels and parameters (``block``: fit.json's
    ``materials`` block)."""
    plt = pyplot()
    from matplotlib import colors

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
    from matplotlib.patches import Patch

    handles = []
    for m in range(M):
        p = block["parameters"][m]
        text = ", ".join(f"{k}={v:.3g}" for k, v in p.items())
        handles.append(Patch(color=cmap(m % cmap.N), label=f"{m}: {block['pixels'][m]} px; {text}"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False)
    ax.set_title(title or f"{M} materials (faint: labelled, not fitted; grey: no material)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
