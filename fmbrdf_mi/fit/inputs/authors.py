"""The captured-data layout of the paper's authors (kyotovision-public/fmbrdf), read by :func:`read_object`
(docs/howto/fit-joint.md).  Their vectors are in OpenCV camera axes, (x, y, z) -> (x, -y, -z) here; their scripts'
-AoLP is S2 in the OpenCV image frame, and the raw mosaics are read here directly, so nothing is negated."""
from __future__ import annotations

import glob
import os

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.files import build_observation
from fmbrdf_mi.fit.inputs.manifest import ImageSpec
from fmbrdf_mi.fit.inputs.observations import UNIT_TOL, read_array, read_mask

#: The polariser layout of the authors' mosaics (2x2, row-major).
AUTHORS_LAYOUT = ((90, 45), (135, 0))


def cv_to_ours(v):
    """Directions (..., 3) in OpenCV camera axes (x right, y down, z forward) -> ours (x right, y up, z to camera)."""
    return np.asarray(v, dtype=np.float64) * np.array([1.0, -1.0, -1.0])


def rays_from_intrinsics(K, shape, path=None):
    """Unit view directions (h, w, 3), ours, through the super-pixel centres (2j + 0.5, 2i + 0.5) of a
    (2h, 2w) sensor (OpenCV pixel centres at integer coordinates)."""
    name = "IntrinsicL.npy" if path is None else path
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a 3 x 3 camera matrix of numbers") from None
    if K.shape != (3, 3):
        raise InputError(f"{name}: expected a 3 x 3 camera matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)) or not np.linalg.cond(K) < 1e12:
        raise InputError(f"{name}: the camera matrix must be finite and invertible (focal lengths > 0, "
                         f"last row 0 0 1), got {K.round(6).tolist()}")
    h, w = shape
    u, v = np.meshgrid(2 * np.arange(w) + 0.5, 2 * np.arange(h) + 0.5)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T   # camera -> surface, OpenCV
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return cv_to_ours(-d)


def read_object(root, *, mask=None, holdout=(), conversion_gain=None, read_noise=None, white_level=65535.0,
                dark_level=None, black_level=0.0, demosaic="bilinear", footprint="auto"):
    """(specs, info) for the object in ``root``: an :class:`~fmbrdf_mi.fit.inputs.manifest.ImageSpec` per image
    (``holdout``: indices kept out of the fit) and what was read, with the mask's pixels of non-unit normals."""
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise InputError(f"authors' object directory {root}: " + ("not a directory" if os.path.exists(root)
                                                                    else "no such directory"))

    def need(path, what):
        if not os.path.isfile(path):
            raise InputError(f"{path}: no such file ({what})")
        return path

    cal = os.path.join(root, "calibration")
    lfile = need(os.path.join(cal, "L.txt"), "one comma-separated light direction per image")
    try:
        L = np.loadtxt(lfile, delimiter=",", ndmin=2)
    except ValueError as exc:
        raise InputError(f"{lfile}: expected rows of three comma-separated numbers ({exc})") from None
    if L.ndim != 2 or L.shape[1] != 3:
        raise InputError(f"{lfile}: expected rows x,y,z, got shape {L.shape}")
    bad = np.flatnonzero(~(np.isfinite(L).all(axis=1) & L.any(axis=1)))
    if bad.size:
        raise InputError(f"{lfile}: row {bad[0] + 1} (image {bad[0]}) is {L[bad[0]].tolist()}: each light "
                         "must be three finite numbers, not all zero")
    files = sorted(glob.glob(os.path.join(root, "image", "img_ud", "*.png")))
    if len(files) != len(L):
        raise InputError(f"{root}/image/img_ud: {len(files)} .png images but {len(L)} lights in L.txt")
    nfile = need(os.path.join(root, "normal", "normal_GT.npy"), "ground-truth normals, h x w x 3")
    n = read_array(nfile, "normals")
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"{nfile}: expected shape (h, w, 3), got {n.shape}")
    h, w = n.shape[:2]
    n = cv_to_ours(n)
    if not np.any(np.abs(np.linalg.norm(np.nan_to_num(n, nan=0.0, posinf=0.0, neginf=0.0), axis=-1) - 1.0)
                  <= UNIT_TOL):
        raise InputError(f"{nfile}: no unit normal in the map (every vector is NaN, zero or not of length 1); "
                         "expected (h, w, 3) unit normals in OpenCV camera axes")
    vfile, kfile = os.path.join(cal, "vpL_img.npy"), os.path.join(cal, "IntrinsicL.npy")
    K = read_array(kfile, "intrinsics") if os.path.isfile(kfile) else None
    if os.path.isfile(vfile):
        vp = read_array(vfile, "viewing rays")
        if vp.shape != (h, w, 3):
            raise InputError(f"{vfile}: shape {vp.shape} differs from the normals' ({h}, {w}, 3)")
        v = cv_to_ours(-vp)
        with np.errstate(invalid="ignore", over="ignore"):
            norm = np.linalg.norm(v, axis=-1, keepdims=True)
        ray = np.all(np.isfinite(v), axis=-1) & np.isfinite(norm[..., 0]) & (norm[..., 0] > 0)
        if not ray.any():
            raise InputError(f"{vfile}: no viewing ray in the map (every vector is NaN, infinite or zero); expected "
                             "(h, w, 3) finite non-zero rays camera -> surface in OpenCV camera axes (or remove it: "
                             "the rays then come from IntrinsicL.npy)")
        v = np.where(ray[..., None], v / np.where(ray[..., None], norm, 1.0), np.array([0.0, 0.0, 1.0]))
        view_src = "vpL_img.npy"
    elif K is not None:
        v, view_src = rays_from_intrinsics(K, (h, w), kfile), "IntrinsicL.npy"
        ray = None
    else:
        raise InputError(f"{cal}: neither vpL_img.npy nor IntrinsicL.npy (the viewing rays)")
    if mask is None:
        mask = next((os.path.join(root, c) for c in ("mask_ud.npy", "mask.npy", "mask.png")
                     if os.path.isfile(os.path.join(root, c))), None)
        if mask is None:
            raise InputError(f"{root}: no mask (mask_ud.npy, mask.npy or mask.png; or give one)")
    m = read_mask(mask)
    if m.shape == (2 * h, 2 * w):
        m = m.reshape(h, 2, w, 2).all(axis=(1, 3))   # super-pixels entirely on the object
    elif m.shape != (h, w):
        raise InputError(f"mask {mask}: shape {m.shape} matches neither the normals ({h}, {w}) nor the raw "
                         f"images ({2 * h}, {2 * w})")
    unit = np.abs(np.linalg.norm(n, axis=-1) - 1.0) <= UNIT_TOL
    bad_normals = int((m & ~unit).sum())
    if m.any() and not (m & unit).any():
        raise InputError(f"{nfile}: no unit normal inside the mask {os.fspath(mask)} ({bad_normals} pixels, each "
                         "NaN, zero or not of length 1); expected (h, w, 3) unit normals in OpenCV camera axes")
    m = m & unit
    if ray is not None and (m & ~ray).any():
        raise InputError(f"{vfile}: {int((m & ~ray).sum())} pixels of the mask {os.fspath(mask)} have no viewing ray "
                         "(NaN, infinite or zero); expected finite non-zero rays camera -> surface on the object")
    n = np.where(m[..., None], n, np.array([0.0, 0.0, 1.0]))
    ifile = os.path.join(cal, "intensities.npy")
    power = np.ones(len(L))
    if os.path.isfile(ifile):
        p = read_array(ifile, "light intensities")
        if not np.issubdtype(p.dtype, np.number) or p.size != len(L):
            raise InputError(f"{ifile}: expected {len(L)} positive light intensities (one per image), got "
                             + (f"shape {p.ravel().shape}" if np.issubdtype(p.dtype, np.number) else
                                f"an array of {p.dtype}"))
        p = p.astype(np.float64).ravel()
        bad = np.flatnonzero(~(np.isfinite(p) & (p > 0)))
        if bad.size:
            raise InputError(f"{ifile}: entry {bad[0]} is {p[bad[0]]:g}: expected {len(L)} finite light "
                             "intensities > 0 (one per image)")
        power = p / p.max()
    holdout = {int(k) for k in holdout}
    for k in holdout - set(range(len(L))):
        raise InputError(f"holdout: image index {k} outside 0..{len(L) - 1}")
    specs = []
    for k, f in enumerate(files):
        try:
            o = build_observation(f, geometry=(n, m, v), light=cv_to_ours(L[k]), irradiance=float(power[k]),
                                  layout=AUTHORS_LAYOUT, black_level=black_level, white_level=white_level,
                                  dark_level=dark_level, conversion_gain=conversion_gain, read_noise=read_noise,
                                  demosaic=demosaic, footprint=footprint)
        except InputError as exc:
            raise InputError(f"{f}: {exc}") from None
        o.meta["authors_layout"] = {"index": k, "light_opencv": L[k].tolist(), "file": os.path.abspath(f),
                                    "power": float(power[k])}
        specs.append(ImageSpec(o, o.light_dir, 1.0, k in holdout,
                               os.path.splitext(os.path.basename(f))[0]))
    info = {"root": os.path.abspath(root), "images": len(files), "view_rays": view_src,
            "intensities": power.tolist() if os.path.isfile(ifile) else None,
            "intrinsics": None if K is None else np.asarray(K).tolist(), "mask": os.fspath(mask),
            "mask_pixels": int(m.sum()), "non_unit_normals_left_out": bad_normals,
            "frames": "OpenCV camera axes converted to x right, y up, z towards the camera: (x, y, z) -> (x, -y, -z)"}
    return specs, info
