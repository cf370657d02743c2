"""The MERL BRDF database binary format (Matusik et al., "A Data-Driven Reflectance Model", SIGGRAPH 2003).

A file holds three int32 (the sample counts in theta_h, theta_d, phi_d:
90, 90, 180), then 3 * 90 * 90 * 180 little-endian doubles: the red, then the
green, then the blue table, each in C order (theta_h slowest, phi_d fastest).
A stored value times the channel's scale (1/1500, 1.15/1500, 1.66/1500) is
the BRDF in 1/sr; negative values mark bins without a measurement.

Bins, in Rusinkiewicz's half/difference angles (isotropic, phi_h = 0):
theta_h = (i / 90)^2 * pi/2 (the square-root mapping concentrates bins near
the specular peak), theta_d = j / 90 * pi/2, phi_d = k / 180 * pi (phi_d and
phi_d + pi are the same by reciprocity).  The value of bin (i, j, k) is taken
at those angles, the lower edges of the lookup's bins, as the database's
reference code generates and reads them.
"""
from __future__ import annotations

import math
import os

import numpy as np

DIMS = (90, 90, 180)
SCALES = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
HEADER_BYTES = 12
FILE_BYTES = HEADER_BYTES + 8 * 3 * DIMS[0] * DIMS[1] * DIMS[2]


class MerlError(ValueError):
    """A file is not a MERL BRDF binary (one line naming the file and what is expected)."""


def read_merl(path):
    """The BRDF of a MERL binary file: (90, 90, 180, 3) float64 in 1/sr, NaN where not measured."""
    path = os.fspath(path)
    size = os.path.getsize(path)  # OSError (with the path) if it does not exist
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
        if len(head) < HEADER_BYTES:
            raise MerlError(f"{path}: not a MERL BRDF file: {size} bytes, shorter than the 12-byte header")
        dims = tuple(int(x) for x in np.frombuffer(head, dtype="<i4"))
        if dims != DIMS:
            raise MerlError(f"{path}: not a MERL BRDF file: header gives {dims[0]} x {dims[1]} x {dims[2]} "
                            f"samples, the format has 90 x 90 x 180")
        if size != FILE_BYTES:
            raise MerlError(f"{path}: truncated or padded MERL BRDF file: {size} bytes, expected {FILE_BYTES} "
                            "(12-byte header + 3 x 90 x 90 x 180 doubles)")
        data = np.frombuffer(f.read(), dtype="<f8").reshape(3, *DIMS)
    out = np.empty(DIMS + (3,))
    for c in range(3):
        out[..., c] = data[c] * SCALES[c]
    finite = np.isfinite(out)
    if not finite.all():
        raise MerlError(f"{path}: {int((~finite).sum())} values are NaN or infinite; a MERL file holds finite "
                        "values (negative for bins without a measurement)")
    out[out < 0] = np.nan
    return out


def write_merl(path, brdf, force=False):
    """Write a (90, 90, 180, 3) BRDF (1/sr; NaN = not measured, stored as -1) as a MERL binary file.

    Refuses to overwrite an existing file unless ``force``; writes a temporary
    file next to it and renames it, so that no half-written file is left."""
    path = os.fspath(path)
    brdf = np.asarray(brdf, dtype=np.float64)
    if brdf.shape != DIMS + (3,):
        raise MerlError(f"{path}: a MERL BRDF is {DIMS + (3,)} (theta_h, theta_d, phi_d, RGB), got {brdf.shape}")
    if np.isinf(brdf).any() or (brdf < 0).any():
        raise MerlError(f"{path}: BRDF values must be finite and >= 0 (NaN marks bins without a measurement)")
    if os.path.exists(path) and not force:
        raise FileExistsError(f"{path} exists; pass force=True (--force) to overwrite it")
    data = np.empty((3,) + DIMS, dtype="<f8")
    for c in range(3):
        data[c] = np.where(np.isnan(brdf[..., c]), -1.0, brdf[..., c] / SCALES[c])
    tmp = path + ".part"
    try:
        with open(tmp, "wb") as f:
            f.write(np.asarray(DIMS, dtype="<i4").tobytes())
            f.write(data.tobytes())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def bin_angles():
    """(theta_h, theta_d, phi_d) of the bins, each 1-D (90, 90, 180)."""
    i = np.arange(DIMS[0]) / DIMS[0]
    return i * i * (0.5 * math.pi), np.arange(DIMS[1]) / DIMS[1] * (0.5 * math.pi), \
        np.arange(DIMS[2]) / DIMS[2] * math.pi


def half_diff_to_dirs(theta_h, theta_d, phi_d):
    """(w_in, w_out), each (..., 3), of half/difference angles (phi_h = 0), local frame z = normal.

    The difference vector d (theta_d, phi_d in the frame of the half vector) is
    rotated by theta_h about y: w_in = R_y(theta_h) d, w_out = R_y(theta_h) d'
    with d' the mirror of d about the half vector."""
    th, td, pd = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_h, theta_d, phi_d)))
    dx, dy, dz = np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)
    c, s = np.cos(th), np.sin(th)

    def rot(x, y, z):
        return np.stack([c * x + s * z, y, -s * x + c * z], axis=-1)

    return rot(dx, dy, dz), rot(-dx, -dy, dz)


def dirs_to_half_diff(w_in, w_out):
    """(theta_h, phi_h, theta_d, phi_d) of direction pairs (..., 3) (Rusinkiewicz 1998)."""
    h = np.asarray(w_in) + np.asarray(w_out)
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    theta_h = np.arccos(np.clip(h[..., 2], -1, 1))
    phi_h = np.arctan2(h[..., 1], h[..., 0])
    w = np.asarray(w_in, dtype=np.float64)
    # rotate w_in by -phi_h about z, then by -theta_h about y
    cp, sp = np.cos(phi_h), np.sin(phi_h)
    x, y, z = cp * w[..., 0] + sp * w[..., 1], -sp * w[..., 0] + cp * w[..., 1], w[..., 2]
    ct, st = np.cos(theta_h), np.sin(theta_h)
    x, z = ct * x - st * z, st * x + ct * z
    theta_d = np.arccos(np.clip(z, -1, 1))
    phi_d = np.arctan2(y, x)
    return theta_h, phi_h, theta_d, phi_d
