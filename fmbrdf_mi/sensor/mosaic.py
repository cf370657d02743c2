"""Division-of-focal-plane polarisation mosaics: polariser-angle images, raw mosaics, demosaicking.

An ideal linear polariser at angle theta (measured like the AoLP, from image
right counter-clockwise, see :mod:`fmbrdf_mi.stokes_io`) passes::

    I(theta) = (S0 + S1 cos 2 theta + S2 sin 2 theta) / 2.

A quad-Bayer sensor such as Sony's IMX250MZR puts four polariser angles in each
2x2 super-pixel.  ``IMX250MZR_LAYOUT`` is the angle of each position, rows top
to bottom: 90 45 / 135 0.  Other cameras (or a camera mounted rotated) use
another layout; every function takes ``layout`` to say so.

Angle images here have shape (4, H, W[, C]) in the order of ``ANGLES``.
"""
from __future__ import annotations

import numpy as np

ANGLES = (0, 45, 90, 135)
IMX250MZR_LAYOUT = ((90, 45), (135, 0))


def analyser_matrix(angles):
    """(n, 3): row k maps (S0, S1, S2) to the intensity behind an ideal polariser at ``angles[k]`` degrees."""
    t = np.deg2rad(np.asarray(angles, dtype=np.float64))
    return 0.5 * np.stack([np.ones_like(t), np.cos(2 * t), np.sin(2 * t)], axis=1)  # (n, 3)


def angle_images_from_stokes(stokes, angles=ANGLES):
    """Intensities behind ideal linear polarisers: (len(angles), H, W[, C])."""
    s = np.asarray(stokes)
    if s.shape[0] < 3:
        raise ValueError(f"stokes: expected S0, S1, S2 along axis 0, got shape {s.shape}")
    a = analyser_matrix(angles)
    return np.tensordot(a, s[:3], axes=(1, 0)).astype(s.dtype, copy=False)


def stokes_from_angle_images(images, angles=ANGLES):
    """Linear Stokes vector (4, H, W[, C]) from polariser-angle images; S3 = 0.

    For (0, 45, 90, 135) this is S0 = (I0 + I45 + I90 + I135) / 2,
    S1 = I0 - I90, S2 = I45 - I135; other angle sets use least squares.
    """
    imgs = np.asarray(images)
    if imgs.shape[0] != len(angles) or len(angles) < 3:
        raise ValueError(f"images: expected {len(angles)} polariser-angle images along axis 0 "
                         f"(angles {tuple(angles)}), got shape {imgs.shape}")
    pinv = np.linalg.pinv(analyser_matrix(angles))  # (3, n)
    lin = np.tensordot(pinv, imgs.astype(np.float64), axes=(1, 0))
    out = np.concatenate([lin, np.zeros_like(lin[:1])])
    return out.astype(np.result_type(imgs.dtype, np.float32), copy=False)


def check_layout(layout):
    try:
        flat = [a for row in layout for a in row]
        len(layout), [len(r) for r in layout]
    except TypeError:
        raise ValueError(f"layout: expected a 2x2 arrangement of the angles {ANGLES}, got {layout!r}") from None
    if len(layout) != 2 or any(len(r) != 2 for r in layout) or sorted(flat) != sorted(ANGLES):
        raise ValueError(f"layout: expected a 2x2 arrangement of the angles {ANGLES}, got {layout}")
    return flat


def mosaic_from_angle_images(images, layout=IMX250MZR_LAYOUT):
    """Raw mosaic (2H, 2W) from angle images (4, H, W), one super-pixel per pixel."""
    imgs = np.asarray(images)
    if imgs.ndim != 3 or imgs.shape[0] != 4:
        raise ValueError(f"images: expected shape (4, H, W), got {imgs.shape}")
    flat = check_layout(layout)
    _, h, w = imgs.shape
    raw = np.empty((2 * h, 2 * w), dtype=imgs.dtype)
    for pos, angle in enumerate(flat):
        raw[pos // 2::2, pos % 2::2] = imgs[ANGLES.index(angle)]
    return raw


def angle_images_from_mosaic(raw, layout=IMX250MZR_LAYOUT):
    """Angle images (4, H/2, W/2) from a raw mosaic, one per super-pixel (no interpolation)."""
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise ValueError(f"raw: expected a 2-D mosaic with even height and width, got shape {raw.shape}")
    flat = check_layout(layout)
    out = [None] * 4
    for pos, angle in enumerate(flat):
        out[ANGLES.index(angle)] = raw[pos // 2::2, pos % 2::2]
    return np.stack(out)


# ---------------------------------------------------------------- colour polarisation sensors
#: Colour channels of a colour-polarisation sensor's Bayer cells (IMX250MYR type), in output order.
COLOURS = ("R", "G", "B")
#: The Bayer arrangement of 2x2 polariser blocks, rows top to bottom: an RGGB 4x4 period.
BAYER_RGGB = (("R", "G"), ("G", "B"))


def check_cfa(cfa):
    """The 2x2 colour filter arrangement as a tuple of tuples; ValueError unless it has one R, two G, one B."""
    try:
        cfa = tuple(tuple(str(c).upper() for c in row) for row in cfa)
    except TypeError:
        raise ValueError(f"cfa: expected a 2x2 arrangement of R, G, G, B, got {cfa!r}") from None
    flat = [c for row in cfa for c in row]
    if len(cfa) != 2 or any(len(r) != 2 for r in cfa) or sorted(flat) != ["B", "G", "G", "R"]:
        raise ValueError(f"cfa: expected a 2x2 arrangement of R, G, G, B (e.g. RGGB), got {cfa!r}")
    return cfa


def parse_cfa(text):
    """'RGGB' (or 'R,G,G,B') -> (('R', 'G'), ('G', 'B'))."""
    s = str(text).replace(",", "").replace(" ", "").upper()
    if len(s) != 4:
        raise ValueError(f"cfa: expected four letters such as RGGB, got {text!r}")
    return check_cfa(((s[0], s[1]), (s[2], s[3])))


def colour_cells(cfa=BAYER_RGGB):
    """[(row, col, channel index into COLOURS)] of the four Bayer cells in row-major order."""
    cfa = check_cfa(cfa)
    return [(r, c, COLOURS.index(cfa[r][c])) for r in range(2) for c in range(2)]


def colour_mosaic_from_angle_images(images, layout=IMX250MZR_LAYOUT, cfa=BAYER_RGGB):
    """Raw colour mosaic (4H, 4W) from per-channel angle images (3, 4, H, W) (channels R, G, B).

    Each 4x4 period holds the Bayer cells ``cfa``; each cell is a 2x2
    polariser block arranged as ``layout``.  Both G cells take the G images.
    """
    imgs = np.asarray(images)
    if imgs.ndim != 4 or imgs.shape[:2] != (3, 4):
        raise ValueError(f"images: expected shape (3 channels, 4 angles, H, W), got {imgs.shape}")
    _, _, h, w = imgs.shape
    raw = np.empty((4 * h, 4 * w), dtype=imgs.dtype)
    for r, c, ch in colour_cells(cfa):
        cell = mosaic_from_angle_images(imgs[ch], layout)  # (2H, 2W): block (i, j) at rows 2i, 2i+1
        for dr in range(2):
            for dc in range(2):
                raw[2 * r + dr::4, 2 * c + dc::4] = cell[dr::2, dc::2]
    return raw


def colour_cell_angle_images(raw, layout=IMX250MZR_LAYOUT, cfa=BAYER_RGGB):
    """Angle images per Bayer cell, (4 cells, 4 angles, H/4, W/4), and each cell's channel index (4,).

    Super-pixel demosaicking: one value per cell and angle per 4x4 period (no interpolation).
    """
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 4 or raw.shape[1] % 4:
        raise ValueError(f"raw: expected a 2-D colour mosaic with height and width multiples of 4, "
                         f"got shape {raw.shape}")
    out, chans = [], []
    for r, c, ch in colour_cells(cfa):
        block = np.empty((raw.shape[0] // 2, raw.shape[1] // 2), dtype=raw.dtype)
        for dr in range(2):
            for dc in range(2):
                block[dr::2, dc::2] = raw[2 * r + dr::4, 2 * c + dc::4]
        out.append(angle_images_from_mosaic(block, layout))
        chans.append(ch)
    return np.stack(out), np.array(chans)


def stokes_from_colour_mosaic(raw, layout=IMX250MZR_LAYOUT, cfa=BAYER_RGGB):
    """Per-channel linear Stokes (3 channels R, G, B; 4; H/4, W/4) of a colour mosaic, one per 4x4 period.

    R and B from their cell; G from the mean of the two G cells' angle images.
    """
    cells, chans = colour_cell_angle_images(raw, layout, cfa)
    per = [cells[chans == ch].astype(np.float64).mean(axis=0) for ch in range(3)]
    return np.stack([stokes_from_angle_images(a) for a in per])


# ---------------------------------------------------------------- demosaicking
def angle_images_at_superpixel_centres(raw, layout=IMX250MZR_LAYOUT):
    """Angle images (4, H/2, W/2) of a raw mosaic, each interpolated to the super-pixel centres.

    The four polarisers of a super-pixel sit at four different points; taking
    them as they are (:func:`angle_images_from_mosaic`)
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
        out[ANGLES.index(angle)] = (9 * near + 3 * row2 + 3 * col2 + diag) / 16.0
    return np.stack(out)


DEMOSAIC = ("bilinear", "superpixel")


def stokes_from_raw(raw, layout=IMX250MZR_LAYOUT, black_level=0.0, demosaic="bilinear"):
    """Linear Stokes (3, H/2, W/2) from a raw quad-Bayer mosaic, one vector per super-pixel.

    ``demosaic``: ``bilinear`` (default) interpolates each angle to the
    super-pixel centre (:func:`angle_images_at_superpixel_centres`);
    ``superpixel`` takes the four pixels as they are.
    """
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"raw mosaic: expected a 2-D single-channel image, got shape {raw.shape}")
    if raw.shape[0] % 2 or raw.shape[1] % 2 or min(raw.shape) < 2:
        raise ValueError(f"raw mosaic: height and width must be even (2x2 super-pixels), got {raw.shape}")
    check_layout(layout)
    if demosaic not in DEMOSAIC:
        raise ValueError(f"demosaic: expected one of {DEMOSAIC}, got {demosaic!r}")
    r = raw.astype(np.float64) - float(black_level)
    if demosaic == "bilinear":
        imgs = angle_images_at_superpixel_centres(r, layout)
    else:
        imgs = angle_images_from_mosaic(r, layout)
    return stokes_from_angle_images(imgs)[:3].astype(np.float64)


def stokes_from_angles(images, black_level=0.0):
    """Linear Stokes (3, H, W) from four polariser-angle images in the order 0, 45, 90, 135 degrees."""
    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim != 3 or imgs.shape[0] != 4:
        raise ValueError(f"angle images: expected shape (4, H, W) in the order "
                         f"{ANGLES} degrees, got {imgs.shape}")
    return stokes_from_angle_images(imgs - float(black_level))[:3].astype(np.float64)
