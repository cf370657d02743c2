"""The camera's own measurements: polariser samples per super-pixel, and which of them can be trusted.

The likelihood (:mod:`fmbrdf_mi.fit.likelihood`) is written for what the sensor
measured, not for a demosaicked Stokes image.  :class:`Samples` holds, per
super-pixel (the grid the geometry lives on), its four polariser samples in
the units of the image (raw DN minus the black level), the polariser angle of
each and where on the super-pixel each was taken:

* **raw mosaic**: the 2x2 raw pixels themselves, at offsets (+-1/4, +-1/4)
  super-pixels from the centre, each 1/2 x 1/2 super-pixel in size (each
  sample is modelled over its own pixel, the mean of the model over m x m
  points of it, :meth:`Samples.footprint`; so the instantaneous-field-of-view
  error of a mosaic is part of the model rather than of the noise).  The samples of different super-pixels are
  independent; bilinear demosaicking would correlate neighbours, which is
  why the likelihood never uses demosaicked values whatever ``--demosaic``
  says (that option shapes the Stokes image of the paper's loss and plots);
* **four angle images**: the four values at the pixel, at its centre;
* **a Stokes image** (EXR): the intensities behind polarisers at 0, 45, 90
  and 135 degrees computed from it (3 degrees of freedom per pixel, not 4:
  :attr:`Samples.dof`).

A super-pixel is **unusable** when any of its raw samples is at or above the
white level (clipped: its value says only "at least this") or at or below
the dark level (clipped at the bottom of the ADC).  Such samples obey no
Gaussian law; the super-pixel is dropped from the fit and counted.  The
choice depends on the observed values, so it selects: near the white level
it keeps the super-pixels whose noise happened to stay below it, near the
dark level those whose noise stayed above.  The resulting bias is confined
to super-pixels within a few noise standard deviations of a clipping level;
a camera with a black-level offset (``--black-level``) has no clipping at
the bottom, and the default exposure of ``render --raw`` keeps the peak at
80 % of the full well.  (A censored likelihood would use those samples
without the selection; not implemented.)
"""
from __future__ import annotations

import dataclasses

import numpy as np

from fmbrdf_mi import polcam
from fmbrdf_mi.camera import default_white_level
from fmbrdf_mi.fit.errors import InputError


@dataclasses.dataclass
class Samples:
    """The n raw samples of every cell of the fit's grid (a mono super-pixel: n = 4; a colour 4x4 period: 16)."""

    values: np.ndarray          # (n, H, W) image units (black level removed)
    angles: tuple               # polariser angle (degrees) of each of the n samples
    offsets: np.ndarray         # (n, 2) (dx right, dy down) in cells from the cell's centre
    saturated: np.ndarray       # (H, W) bool: a sample at or above the white level
    dark: np.ndarray            # (H, W) bool: a sample at or below the dark level
    source: str                 # "raw mosaic", "angle images", "stokes" or "colour raw mosaic"
    white_level: float = None   # raw units (black level included)
    dark_level: float = None
    step: float = 1.0           # quantisation step in image units (0: not quantised)
    dof: int = 4                # independent samples per cell
    channel: np.ndarray = None  # (n,) colour channel of each sample (colour mosaics: 0 R, 1 G, 2 B), else None
    pixel: float = 1.0          # side of each sample's own pixel, in cells (a mono raw mosaic: 1/2)

    @property
    def usable(self):
        return ~(self.saturated | self.dark)

    @property
    def n(self):
        """Samples per cell."""
        return len(self.angles)

    def analyser(self):
        """(n, 3): row k maps (S0, S1, S2) to the intensity behind polariser k."""
        t = np.radians(np.asarray(self.angles, dtype=np.float64))
        return 0.5 * np.stack([np.ones_like(t), np.cos(2 * t), np.sin(2 * t)], axis=1)

    def footprint(self, points=1):
        """Where each sample is modelled, for :meth:`Observation.sample_geometry`: (offsets, weights).

        ``points`` = m: each sample is the mean over an m x m grid of points
        at the centres of equal sub-squares of its own pixel (side
        :attr:`pixel` cells, centred on its offset), as a sensor pixel
        integrates over its area (and ``render --raw`` box-filters).
        Offsets (n m^2, 2) run sample by sample, m^2 per sample; weights
        (m^2,) = 1 / m^2 are those of one sample's points (an evaluator with
        these weights averages each consecutive m^2 points into one sample).
        ``points=1``: one point per sample, at its offset, weight 1.
        """
        m = int(points)
        if m < 1:
            raise ValueError(f"points: expected an integer >= 1, got {points!r}")
        g = ((np.arange(m) + 0.5) / m - 0.5) * self.pixel
        X, Y = np.meshgrid(g, g)
        sub = np.stack([X.ravel(), Y.ravel()], 1)  # (m^2, 2)
        offsets = (np.asarray(self.offsets, dtype=np.float64)[:, None, :] + sub[None]).reshape(-1, 2)
        return offsets, np.full(m * m, 1.0 / (m * m))

    def at(self, idx):
        """(cells, n) sample values of the cells with flat indices ``idx``."""
        return self.values.reshape(self.n, -1)[:, np.asarray(idx)].T


def _flags(raw4, white, dark):
    sat = np.zeros(raw4.shape[1:], bool) if white is None else np.any(raw4 >= white, axis=0)
    drk = np.zeros(raw4.shape[1:], bool) if dark is None else np.any(raw4 <= dark, axis=0)
    return sat, drk


def from_raw(raw, layout=polcam.IMX250MZR_LAYOUT, black_level=0.0, white_level=None, dark_level=None):
    """:class:`Samples` of a raw mosaic (2H, 2W) in DN.

    ``white_level``: None takes :func:`fmbrdf_mi.camera.default_white_level`;
    ``dark_level``: None takes the black level when it is 0 (samples at 0 may
    be clipped), else no dark test (an offset keeps the noise of dark pixels
    measurable; use ``dark_level`` to exclude dim super-pixels anyway).
    """

    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise InputError(f"raw mosaic: expected a 2-D image with even height and width, got {raw.shape}")
    white = default_white_level(raw) if white_level is None else float(white_level)
    dark = (0.0 if float(black_level) == 0 else None) if dark_level is None else float(dark_level)
    r = raw.astype(np.float64)
    vals, offs, angles = [], [], []
    for pos, angle in enumerate(a for row in layout for a in row):
        rr, cc = divmod(pos, 2)
        vals.append(r[rr::2, cc::2])
        offs.append(((cc - 0.5) / 2.0, (rr - 0.5) / 2.0))
        angles.append(angle)
    raw4 = np.stack(vals)
    sat, drk = _flags(raw4, white, dark)
    return Samples(raw4 - float(black_level), tuple(angles), np.array(offs), sat, drk, "raw mosaic",
                   white, dark, 1.0, 4, pixel=0.5)


def from_angle_images(images, black_level=0.0, white_level=None, dark_level=None, integer=True):
    """:class:`Samples` of four angle images (4, H, W) in the order 0, 45, 90, 135 degrees."""

    imgs = np.asarray(images, dtype=np.float64)
    white = (default_white_level(imgs) if integer else None) if white_level is None else float(white_level)
    dark = (0.0 if (integer and float(black_level) == 0) else None) if dark_level is None else float(dark_level)
    sat, drk = _flags(imgs, white, dark)
    return Samples(imgs - float(black_level), tuple(polcam.ANGLES), np.zeros((4, 2)), sat, drk,
                   "angle images", white, dark, 1.0 if integer else 0.0, 4)


def from_stokes(stokes):
    """:class:`Samples` computed from a (3, H, W) Stokes image (float data: no clipping, no quantisation)."""
    s = np.asarray(stokes, dtype=np.float64)
    imgs = polcam.angle_images_from_stokes(s[:3])
    z = np.zeros(s.shape[1:], bool)
    return Samples(imgs, tuple(polcam.ANGLES), np.zeros((4, 2)), z, z.copy(), "stokes", None, None, 0.0, 3)
