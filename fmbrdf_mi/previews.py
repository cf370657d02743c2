"""PNG previews of Stokes images (matplotlib, Agg backend).

All functions take the Stokes array of :mod:`fmbrdf_mi.stokes_io`, shape
(4, H, W, C).  Colour images (C = 3) are shown in colour where that is
meaningful (intensity, polariser-angle images); DoLP, AoLP and the raw mosaic
use the luminance Stokes vector Y = 0.2126 R + 0.7152 G + 0.0722 B (linear
sRGB weights), a monochrome camera's view.

* intensity: S0, scaled so that the 99.5th percentile of the lit pixels maps to
  white (or by a given exposure), sRGB-encoded;
* DoLP: sequential colormap (viridis) from 0 to a round value above the
  largest DoLP (or a given maximum), with a colour bar;
* AoLP: cyclic colormap over (-90, 90] degrees, measured from image right
  counter-clockwise as displayed, with a colour bar; either plain ('twilight')
  or with brightness proportional to the DoLP ('hsv' hue, black where unpolarised);
* angle images: what ideal linear polarisers at 0, 45, 90, 135 degrees pass,
  with the intensity's exposure;
* mosaic: the raw image of a quad-Bayer polarisation sensor (default layout of
  Sony's IMX250MZR, :mod:`fmbrdf_mi.sensor.mosaic`), 2H x 2W pixels, tone-mapped.

Background pixels (S0 = 0) are black in every preview.
"""
from __future__ import annotations

import os

import numpy as np

from . import stokes_io
from .sensor import mosaic

#: Preview kinds and the suffix each adds to the output stem.
PREVIEW_SUFFIXES = {"intensity": "_intensity.png", "dolp": "_dolp.png", "aolp": "_aolp.png",
                    "angles": "_angles.png", "mosaic": "_mosaic.png"}
DEFAULT_PREVIEWS = ("intensity", "dolp", "aolp")
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def luminance_stokes(stokes):
    """(4, H, W) Stokes vector of the luminance (or of the single channel)."""
    s = stokes_io._check_stokes(stokes).astype(np.float64)
    if s.shape[-1] == 1:
        return s[..., 0]
    return np.tensordot(s, LUMINANCE, axes=([3], [0]))


def auto_exposure(stokes, percentile=99.5):
    """Scale that maps the given percentile of the lit pixels' S0 luminance to 1."""
    s0 = luminance_stokes(stokes)[0]
    lit = s0[s0 > 0]
    if lit.size == 0:
        return 1.0
    ref = np.percentile(lit, percentile)
    return float(1.0 / ref) if ref > 0 else 1.0


def srgb_encode(x):
    """Linear [0, 1] -> sRGB-encoded [0, 1] (values clipped)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _tone_map(img, exposure):
    out = srgb_encode(np.asarray(img, dtype=np.float64) * exposure)
    return out[..., 0] if out.ndim == 3 and out.shape[-1] == 1 else out


def _imsave(path, img):
    plt = pyplot()
    if img.ndim == 2:
        plt.imsave(path, img, cmap="gray", vmin=0.0, vmax=1.0)
    else:
        plt.imsave(path, img)


def save_intensity(path, stokes, exposure=None):
    """Tone-mapped S0 at the image's resolution; returns the exposure used."""
    exposure = auto_exposure(stokes) if exposure is None else float(exposure)
    s = stokes_io._check_stokes(stokes)
    _imsave(path, _tone_map(s[0], exposure))
    return exposure


def _scale(h, w, target=256):
    """Integer enlargement so small images are shown at about ``target`` pixels."""
    return max(1, int(round(target / max(h, w))))


def _figure(h, w, title, colorbar=True):
    """Figure whose image axes cover exactly (h, w) * an integer scale in pixels (no resampling blur).

    Returns (plt, fig, ax, cax): cax is the colour bar's axes (None without one).
    """
    plt = pyplot()
    dpi, k = 100, _scale(h, w)
    iw, ih = w * k, h * k
    top, bottom, left = 26, 6, 6
    right = 110 if colorbar else 6
    fw, fh = iw + left + right, ih + top + bottom
    fig = plt.figure(figsize=(fw / dpi, fh / dpi), dpi=dpi)
    ax = fig.add_axes([left / fw, bottom / fh, iw / fw, ih / fh])
    ax.set_axis_off()
    fig.text((left + iw / 2) / fw, 1 - 6 / fh, title, ha="center", va="top", fontsize=9)
    cax = fig.add_axes([(left + iw + 12) / fw, bottom / fh, 14 / fw, ih / fh]) if colorbar else None
    return plt, fig, ax, cax


def nice_dolp_max(d):
    """Smallest of 0.05, 0.1, 0.2, 0.25, 0.5, 1 at or above the 99.5th percentile of ``d``."""
    d = np.asarray(d)
    top = float(np.percentile(d, 99.5)) if d.size else 1.0
    return next((v for v in (0.05, 0.1, 0.2, 0.25, 0.5) if top <= v), 1.0)


def save_dolp(path, stokes, vmax=None):
    """DoLP with a sequential colormap (viridis) and a colour bar over [0, vmax].

    ``vmax`` defaults to :func:`nice_dolp_max` of the lit pixels, so that weak
    polarisation stays visible; the colour bar says which range is shown.
    """
    s = luminance_stokes(stokes)
    d = stokes_io.dolp(s)
    bg = s[0] <= 0
    vmax = nice_dolp_max(d[~bg]) if vmax is None else float(vmax)
    plt, fig, ax, cax = _figure(*d.shape, "degree of linear polarisation")
    cmap = plt.get_cmap("viridis").with_extremes(bad="black")
    im = ax.imshow(np.ma.masked_where(bg, d), cmap=cmap, vmin=0.0, vmax=vmax,
                   interpolation="nearest")
    fig.colorbar(im, cax=cax, label="DoLP")
    fig.savefig(path)
    plt.close(fig)


def save_aolp(path, stokes, modulate=False, dolp_full=None):
    """AoLP with a cyclic colormap and a colour bar.

    With ``modulate`` the brightness is DoLP / ``dolp_full`` (clipped at 1;
    default: :func:`nice_dolp_max` of the lit pixels, as in the DoLP preview),
    so that the angle of weakly polarised light fades to black.
    """
    s = luminance_stokes(stokes)
    psi = np.degrees(stokes_io.aolp(s))
    psi = np.where(psi <= -90.0, psi + 180.0, psi)
    bg = s[0] <= 0
    if not modulate:
        plt, fig, ax, cax = _figure(*psi.shape, "angle of linear polarisation")
        cmap = plt.get_cmap("twilight").with_extremes(bad="black")
        im = ax.imshow(np.ma.masked_where(bg, psi), cmap=cmap, vmin=-90, vmax=90, interpolation="nearest")
    else:
        d = stokes_io.dolp(s)
        dolp_full = nice_dolp_max(d[~bg]) if dolp_full is None else float(dolp_full)
        plt, fig, ax, cax = _figure(*psi.shape, f"AoLP; brightness: DoLP / {dolp_full:g}")
        cmap = plt.get_cmap("hsv")
        rgb = cmap((psi + 90.0) / 180.0)[..., :3] * np.clip(d / dolp_full, 0, 1)[..., None]
        rgb[bg] = 0.0
        ax.imshow(rgb, interpolation="nearest")
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        im = ScalarMappable(norm=Normalize(-90, 90), cmap=cmap)
    cb = fig.colorbar(im, cax=cax, ticks=[-90, -45, 0, 45, 90])
    cb.set_label("AoLP (deg from image right,\ncounter-clockwise)", fontsize=8)
    fig.savefig(path)
    plt.close(fig)


def save_angle_images(path, stokes, exposure=None, angles=mosaic.ANGLES):
    """The four polariser-angle images in a 2 x 2 grid (labelled), with the intensity's exposure."""
    s = stokes_io._check_stokes(stokes)
    exposure = auto_exposure(stokes) if exposure is None else float(exposure)
    imgs = [_tone_map(img, exposure) for img in mosaic.angle_images_from_stokes(s.astype(np.float64), angles)]
    h, w = s.shape[1:3]
    k, gap = _scale(h, w, 192), 4
    imgs = [np.kron(img, np.ones((k, k) + (1,) * (img.ndim - 2))) for img in imgs]
    hh, ww = h * k, w * k
    grid = np.ones((2 * hh + gap, 2 * ww + gap) + imgs[0].shape[2:])
    for i, img in enumerate(imgs):
        r, c = divmod(i, 2)
        grid[r * (hh + gap):r * (hh + gap) + hh, c * (ww + gap):c * (ww + gap) + ww] = img
    plt = pyplot()
    gh, gw = grid.shape[:2]
    fig = plt.figure(figsize=(gw / 100, gh / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_axis_off()
    ax.imshow(grid, cmap="gray" if grid.ndim == 2 else None, vmin=0, vmax=1, interpolation="nearest")
    for i, a in enumerate(angles):
        r, c = divmod(i, 2)
        ax.text(c * (ww + gap) + 5, r * (hh + gap) + 5, f"polariser {a}\N{DEGREE SIGN}", color="yellow",
                ha="left", va="top", fontsize=9)
    fig.savefig(path)
    plt.close(fig)


def save_mosaic(path, stokes, exposure=None, layout=mosaic.IMX250MZR_LAYOUT):
    """Raw quad-Bayer mosaic (2H x 2W) of the luminance, tone-mapped, at native resolution."""
    exposure = auto_exposure(stokes) if exposure is None else float(exposure)
    s = luminance_stokes(stokes)
    raw = mosaic.mosaic_from_angle_images(mosaic.angle_images_from_stokes(s), layout)
    _imsave(path, _tone_map(raw, exposure))


def preview_paths(stem, kinds=DEFAULT_PREVIEWS):
    """{kind: path} of the previews of ``stem`` (an output path without '.exr')."""
    unknown = [k for k in kinds if k not in PREVIEW_SUFFIXES]
    if unknown:
        raise ValueError(f"unknown preview kind {unknown[0]!r}; expected some of {', '.join(PREVIEW_SUFFIXES)}")
    return {k: os.fspath(stem) + PREVIEW_SUFFIXES[k] for k in kinds}


def write_previews(stem, stokes, kinds=DEFAULT_PREVIEWS, *, exposure=None, dolp_max=None,
                   modulate_aolp=False, force=False):
    """Write the previews of ``kinds`` next to ``stem``; returns {kind: path}.

    Refuses (FileExistsError) to replace an existing file unless ``force``.
    One exposure (``exposure`` or :func:`auto_exposure`) serves intensity,
    angle images and mosaic, so they are comparable; ``dolp_max`` (default
    :func:`nice_dolp_max`) is the top of the DoLP colour scale.
    """
    paths = preview_paths(stem, kinds)
    if not force:
        for p in paths.values():
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass force=True (--force) to overwrite it")
    if paths:
        os.makedirs(os.path.dirname(os.path.abspath(next(iter(paths.values())))), exist_ok=True)
    exposure = auto_exposure(stokes) if exposure is None else float(exposure)
    for kind, p in paths.items():
        if kind == "intensity":
            save_intensity(p, stokes, exposure)
        elif kind == "dolp":
            save_dolp(p, stokes, vmax=dolp_max)
        elif kind == "aolp":
            save_aolp(p, stokes, modulate=modulate_aolp, dolp_full=dolp_max)
        elif kind == "angles":
            save_angle_images(p, stokes, exposure)
        elif kind == "mosaic":
            save_mosaic(p, stokes, exposure)
    return paths
