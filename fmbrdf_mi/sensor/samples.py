"""The camera's own measurements: the raw samples of each cell of the fit's grid, and which can be trusted.

The likelihood is written for what the sensor measured, not for a
demosaicked image: a cell (a mono 2x2 super-pixel, or a colour 4x4 period)
holds its raw samples in image units (DN minus the black level), each with
its polariser angle, its colour channel and its offset from the cell centre
(the mosaic's instantaneous-field-of-view error is then part of the model,
not of the noise).  A cell with a sample at the white level or at the dark
level (clipped) obeys no Gaussian law and is unusable.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor.camera import default_white_level


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
        return mosaic.analyser_matrix(self.angles)

    def footprint(self, points=1):
        """Where each sample is modelled, for :meth:`fmbrdf_mi.fit.Observation.sample_geometry`: (offsets, weights).

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


def from_raw(raw, layout=mosaic.IMX250MZR_LAYOUT, black_level=0.0, white_level=None, dark_level=None):
    """:class:`Samples` of a raw mosaic (2H, 2W) in DN.

    ``white_level``: None takes :func:`~fmbrdf_mi.sensor.camera.default_white_level`;
    ``dark_level``: None takes the black level when it is 0 (samples at 0 may
    be clipped), else no dark test (an offset keeps the noise of dark pixels
    measurable; use ``dark_level`` to exclude dim super-pixels anyway).
    """

    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise ValueError(f"raw mosaic: expected a 2-D image with even height and width, got {raw.shape}")
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
    return Samples(imgs - float(black_level), tuple(mosaic.ANGLES), np.zeros((4, 2)), sat, drk,
                   "angle images", white, dark, 1.0 if integer else 0.0, 4)


def from_stokes(stokes):
    """:class:`Samples` computed from a (3, H, W) Stokes image (float data: no clipping, no quantisation)."""
    s = np.asarray(stokes, dtype=np.float64)
    imgs = mosaic.angle_images_from_stokes(s[:3])
    z = np.zeros(s.shape[1:], bool)
    return Samples(imgs, tuple(mosaic.ANGLES), np.zeros((4, 2)), z, z.copy(), "stokes", None, None, 0.0, 3)


def colour_samples(raw, layout=mosaic.IMX250MZR_LAYOUT, cfa=mosaic.BAYER_RGGB, black_level=0.0,
                   white_level=None):
    """The :class:`Samples` (16 per 4x4 period, with their colour channels) of a raw
    colour mosaic (4H, 4W) in DN; a period with a clipped sample is unusable."""

    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 4 or raw.shape[1] % 4:
        raise ValueError(f"raw colour mosaic: expected a 2-D image with height and width multiples of 4, "
                         f"got {raw.shape}")
    white = default_white_level(raw) if white_level is None else float(white_level)
    r = raw.astype(np.float64)
    vals, chans, angles, offs = [], [], [], []
    for cr, cc, ch in mosaic.colour_cells(cfa):
        for dr in range(2):
            for dc in range(2):
                R, C = 2 * cr + dr, 2 * cc + dc
                vals.append(r[R::4, C::4])
                chans.append(ch)
                angles.append(layout[dr][dc])
                offs.append(((C + 0.5) / 4 - 0.5, (R + 0.5) / 4 - 0.5))   # (dx right, dy down) in periods
    v = np.stack(vals)
    saturated = np.any(v >= white, axis=0)
    dark = np.any(v <= 0, axis=0) if float(black_level) == 0 else np.zeros(v.shape[1:], bool)
    return Samples(v - float(black_level), tuple(angles), np.asarray(offs, float), saturated, dark,
                   "colour raw mosaic", white, 0.0 if float(black_level) == 0 else None, 1.0, 16, np.asarray(chans),
                   pixel=0.25)
