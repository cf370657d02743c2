"""The raw samples of a colour polarisation mosaic (IMX250MYR type), 16 per 4x4 period."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi import polcam
from fmbrdf_mi.camera import default_white_level
from fmbrdf_mi.fit.camera.samples import Samples
from fmbrdf_mi.fit.errors import InputError

CHANNELS = polcam.COLOURS


def colour_samples(raw, layout=polcam.IMX250MZR_LAYOUT, cfa=polcam.BAYER_RGGB, black_level=0.0,
                   white_level=None):
    """The :class:`~fmbrdf_mi.fit.camera.samples.Samples` (16 per 4x4 period, with their colour channels) of a raw
    colour mosaic (4H, 4W) in DN; a period with a clipped sample is unusable."""

    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 4 or raw.shape[1] % 4:
        raise InputError(f"raw colour mosaic: expected a 2-D image with height and width multiples of 4, "
                         f"got {raw.shape}")
    white = default_white_level(raw) if white_level is None else float(white_level)
    r = raw.astype(np.float64)
    vals, chans, angles, offs = [], [], [], []
    for cr, cc, ch in polcam.colour_cells(cfa):
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
