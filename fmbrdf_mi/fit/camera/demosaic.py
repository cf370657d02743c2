"""Raw quad-Bayer mosaics to Stokes vectors: polariser layouts and demosaicking."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi import polcam
from fmbrdf_mi.fit.errors import InputError


def check_layout(layout):
    try:
        polcam.check_layout(layout)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return tuple(tuple(int(a) for a in row) for row in layout)


def angle_images_at_superpixel_centres(raw, layout=polcam.IMX250MZR_LAYOUT):
    """Angle images (4, H/2, W/2) of a raw mosaic, each interpolated to the super-pixel centres.

    The four polarisers of a super-pixel sit at four different points; taking
    them as they are (:func:`fmbrdf_mi.polcam.angle_images_from_mosaic`)
    mixes spatial change into the Stokes vector (false polarisation at edges
    and highlights).  Here each angle's samples, a lattice of spacing 2, are
    interpolated bilinearly to the centre of every super-pixel (weights 9/16,
    3/16, 3/16, 1/16 from the nearest four samples of that angle; edges
    clamped), so all four angles describe the same point.
    """
    raw = np.asarray(raw, dtype=np.float64)
    flat = [a for row in layout for a in row]
    out = [None] * 4
    for pos, angle in enumerate(flat):
        r, c = divmod(pos, 2)
        # sample (i, j) is raw pixel (2i + r, 2j + c); super-pixel (i, j) is centred at (2i + 0.5, 2j + 0.5)
        lat = raw[r::2, c::2]
        dr_, dc = (1 if r == 0 else -1), (1 if c == 0 else -1)  # direction of the second-nearest sample
        p = np.pad(lat, 1, mode="edge")
        h, w = lat.shape
        near = p[1:h + 1, 1:w + 1]
        row2 = p[1 + dr_:h + 1 + dr_, 1:w + 1]
        col2 = p[1:h + 1, 1 + dc:w + 1 + dc]
        diag = p[1 + dr_:h + 1 + dr_, 1 + dc:w + 1 + dc]
        out[polcam.ANGLES.index(angle)] = (9 * near + 3 * row2 + 3 * col2 + diag) / 16.0
    return np.stack(out)


DEMOSAIC = ("bilinear", "superpixel")


def stokes_from_raw(raw, layout=polcam.IMX250MZR_LAYOUT, black_level=0.0, demosaic="bilinear"):
    """Linear Stokes (3, H/2, W/2) from a raw quad-Bayer mosaic, one vector per super-pixel.

    ``demosaic``: ``bilinear`` (default) interpolates each angle to the
    super-pixel centre (:func:`angle_images_at_superpixel_centres`);
    ``superpixel`` takes the four pixels as they are.
    """
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise InputError(f"raw mosaic: expected a 2-D single-channel image, got shape {raw.shape}")
    if raw.shape[0] % 2 or raw.shape[1] % 2 or min(raw.shape) < 2:
        raise InputError(f"raw mosaic: height and width must be even (2x2 super-pixels), got {raw.shape}")
    layout = check_layout(layout)
    if demosaic not in DEMOSAIC:
        raise InputError(f"demosaic: expected one of {DEMOSAIC}, got {demosaic!r}")
    r = raw.astype(np.float64) - float(black_level)
    if demosaic == "bilinear":
        imgs = angle_images_at_superpixel_centres(r, layout)
    else:
        imgs = polcam.angle_images_from_mosaic(r, layout)
    return polcam.stokes_from_angle_images(imgs)[:3].astype(np.float64)


def stokes_from_angles(images, black_level=0.0):
    """Linear Stokes (3, H, W) from four polariser-angle images in the order 0, 45, 90, 135 degrees."""
    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim != 3 or imgs.shape[0] != 4:
        raise InputError(f"angle images: expected shape (4, H, W) in the order "
                         f"{polcam.ANGLES} degrees, got {imgs.shape}")
    return polcam.stokes_from_angle_images(imgs - float(black_level))[:3].astype(np.float64)
