"""Inputs of a fit (:class:`Observation`): polarimetric image, geometry, light; loading and validation.
Conventions (:mod:`fmbrdf_mi.stokes_io`'s): camera frame x right, y up, z towards the camera; images indexed
``[row, column]``, a pixel's centre at ``(x, y) = (column + 0.5, row + 0.5)``; normals and view directions (surface
to camera) are (H, W, 3) unit vectors; the light direction points from the surface towards the light."""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from fmbrdf_mi import stokes_io
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.options import IMAGE_OPTION
from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor.mosaic import stokes_from_angles, stokes_from_raw

#: Largest accepted deviation of a normal / view vector from unit length.
UNIT_TOL = 1e-3


@dataclasses.dataclass
class Observation:
    """One polarimetric image of an object of known geometry under a directional light: ``stokes`` (3, H, W) S0, S1,
    S2 of one channel, ``mask`` the object pixels, ``irradiance`` in image units (1 if unknown: the albedos absorb
    it), ``meta`` what the source said (e.g. true parameters)."""

    stokes: np.ndarray
    mask: np.ndarray
    normals: np.ndarray
    view_dirs: np.ndarray
    light_dir: np.ndarray
    irradiance: float = 1.0
    meta: dict = dataclasses.field(default_factory=dict)
    #: per-pixel variance of S1 (= that of S2), (H, W), if known: the fit models the DoLP's noise bias
    lin_variance: np.ndarray = None
    #: what a pixel integrates over: (offsets (K, 2) in pixels, dx right / dy down, weights (K,)); None: its centre
    footprint: tuple = None
    #: the camera's samples (:class:`fmbrdf_mi.sensor.samples.Samples`); None: derived from ``stokes``
    samples: object = None
    #: the camera's noise (:class:`fmbrdf_mi.sensor.noise.NoiseModel`), if known
    noise: object = None
    #: exact geometry at any image point (:class:`fmbrdf_mi.geometry.SphereGeometry`), or None: interpolate the maps
    geometry: object = None

    def __post_init__(self):
        validate(self)

    @property
    def shape(self):
        return self.mask.shape

    def sample_geometry(self, idx, footprint="own"):
        """Normals and view directions (n K, 3) over the footprint of the pixels ``idx``, and the weights (K,);
        ``footprint``: (offsets, weights) instead of the own (None: pixel centres, K = 1).  Without ``geometry`` the
        maps are interpolated bilinearly and renormalised (erode the mask border)."""
        idx = np.asarray(idx)
        fp = self.footprint if isinstance(footprint, str) else footprint
        if fp is None:
            return self.normals.reshape(-1, 3)[idx], self.view_dirs.reshape(-1, 3)[idx], np.ones(1)
        off, w = fp
        h, wd = self.shape
        rows, cols = np.divmod(idx, wd)
        y = rows[:, None] + np.asarray(off)[None, :, 1]
        x = cols[:, None] + np.asarray(off)[None, :, 0]
        if self.geometry is not None:
            n, v = self.geometry.at(x + 0.5, y + 0.5)
            return n.reshape(-1, 3), v.reshape(-1, 3), np.asarray(w, dtype=np.float64)

        def interp(a):
            y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
            x0 = np.clip(np.floor(x).astype(int), 0, wd - 2)
            fy, fx = (y - y0)[..., None], (x - x0)[..., None]
            v = ((1 - fy) * ((1 - fx) * a[y0, x0] + fx * a[y0, x0 + 1])
                 + fy * ((1 - fx) * a[y0 + 1, x0] + fx * a[y0 + 1, x0 + 1]))
            v = v.reshape(-1, 3)
            return v / np.linalg.norm(v, axis=1, keepdims=True)

        return interp(self.normals), interp(self.view_dirs), np.asarray(w, dtype=np.float64)


def validate(obs):
    """Raise :class:`InputError` unless ``obs`` is consistent (called on construction)."""
    s = np.asarray(obs.stokes, dtype=np.float64)
    if s.ndim != 3 or s.shape[0] != 3:
        raise InputError(f"stokes: expected shape (3, H, W) (S0, S1, S2 of one channel), got {s.shape}")
    h, w = s.shape[1:]
    mask = check_mask(obs.mask, (h, w))
    if not mask.any():
        raise InputError("mask: no pixel is selected (empty mask)")
    for name in ("normals", "view_dirs"):
        a = np.asarray(getattr(obs, name), dtype=np.float64)
        if a.shape != (h, w, 3):
            raise InputError(f"{name}: expected shape (H, W, 3) = ({h}, {w}, 3) to match the image, "
                             f"got {a.shape}")
        sel = a[mask]
        if not np.all(np.isfinite(sel)):
            raise InputError(f"{name}: non-finite values inside the mask")
        err = np.abs(np.linalg.norm(sel, axis=1) - 1.0)
        if err.max() > UNIT_TOL:
            i = int(np.argmax(err))
            raise InputError(f"{name}: vectors inside the mask must have unit length (tolerance "
                             f"{UNIT_TOL:g}); found length {np.linalg.norm(sel[i]):.4f} at "
                             f"{sel[i].round(4).tolist()} (normal maps stored as colours in [0, 1] "
                             "must be converted with n = 2 c - 1 and normalised)")
        setattr(obs, name, a)
    if not np.all(np.isfinite(s[:, mask])):
        raise InputError("stokes: non-finite values inside the mask")
    if obs.lin_variance is not None:
        var = np.asarray(obs.lin_variance, dtype=np.float64)
        if var.shape != (h, w) or not np.all(np.isfinite(var[mask])) or np.any(var[mask] < 0):
            raise InputError(f"lin_variance: expected finite values >= 0 of shape ({h}, {w}), got shape {var.shape}")
        obs.lin_variance = var
    obs.stokes, obs.mask = s, mask
    if obs.footprint is not None:
        off, wt = (np.asarray(a, dtype=np.float64) for a in obs.footprint)
        if off.ndim != 2 or off.shape[1] != 2 or wt.shape != (len(off),) or not np.isclose(wt.sum(), 1.0) \
                or np.abs(off).max() > 1.0:
            raise InputError("footprint: expected (offsets (K, 2) within one pixel of the centre, "
                             f"weights (K,) summing to 1), got shapes {off.shape}, {wt.shape}")
        obs.footprint = (off, wt)
    if obs.samples is not None and obs.samples.values.shape != (obs.samples.n, h, w):
        raise InputError(f"samples: expected shape ({obs.samples.n}, {h}, {w}) ({obs.samples.n} samples per cell, "
                         f"{obs.samples.source}) to match the image, got {obs.samples.values.shape}")
    obs.light_dir = check_direction(obs.light_dir, "light_dir")
    obs.irradiance = float(IMAGE_OPTION["irradiance"].check(obs.irradiance))   # light power x irradiance
    n = obs.normals[mask]
    if not np.any(n @ obs.light_dir > 0.0):
        raise InputError(f"light_dir {obs.light_dir.round(4).tolist()}: the light is below the horizon "
                         "(n . l <= 0) at every pixel of the mask; check its sign (it points from "
                         "the surface towards the light, camera frame x right, y up, z towards the camera)")
    if not np.any(np.sum(n * obs.view_dirs[mask], axis=1) > 0.0):
        raise InputError("normals / view_dirs: no pixel of the mask faces the camera (n . v <= 0 "
                         "everywhere); normals must point out of the object, view directions towards the camera")


def check_direction(v, name):
    """A finite, non-zero 3-vector, normalised (directions typed by hand need not be unit)."""
    if v is None:
        raise InputError(f"{name}: give the light direction (--light x,y,z, from the surface towards the light; "
                         "x image right, y image up, z towards the camera)")
    try:
        a = None if isinstance(v, (str, bytes)) else np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != (3,) or not np.all(np.isfinite(a)) or not np.any(a):
        raise InputError(f"{name}: expected a finite non-zero 3-vector, three numbers x, y, z (x right, y up, z "
                         f"towards the camera), got {v.tolist() if isinstance(v, np.ndarray) else v!r}")
    with np.errstate(over="ignore", under="ignore"):
        n = np.linalg.norm(a)
    if not 1e-150 < n < 1e150:     # e.g. (1e308, 0, 0): scale first so the norm does not overflow
        a = a / np.abs(a).max()
        n = np.linalg.norm(a)
    return a / n


def check_mask(mask, shape, name="mask"):
    """``mask`` as a boolean (H, W) array of ``shape``: booleans or numbers (non-zero = object), no NaN."""
    try:
        m = np.asarray(mask)
    except Exception:
        m = None
    if m is None or m.dtype == object or not (m.dtype == bool or np.issubdtype(m.dtype, np.number)):
        raise InputError(f"{name}: expected a 2-D array of booleans or numbers (non-zero = object) of shape "
                         f"{tuple(shape)}, got {type(mask).__name__}")
    if m.shape != tuple(shape):
        raise InputError(f"{name}: shape {m.shape} does not match the image {tuple(shape)}")
    if m.dtype != bool and not np.all(np.isfinite(m)):
        raise InputError(f"{name}: {int(np.sum(~np.isfinite(m)))} value(s) NaN or infinite; a mask "
                         "is 0 outside the object and non-zero on it")
    return m != 0


def check_observations(observations, where, least=1):
    """A list of at least ``least`` :class:`Observation` s (one alone is a list of one), else InputError."""
    items = observations if isinstance(observations, (list, tuple)) else [observations]
    for k, o in enumerate(items):
        if not isinstance(o, Observation):
            hint = (" (a file name: read it with fmbrdf_mi.fit.fit_files, or build the Observation with "
                    "fmbrdf_mi.fit.inputs.files.build_observation)") if isinstance(o, (str, os.PathLike)) else ""
            at = f" item {k}:" if len(items) > 1 else ""
            raise InputError(f"{where}:{at} expected an Observation, got {type(o).__name__} {o!r:.60}{hint}")
    if len(items) < least:
        raise InputError(f"{where}: expected at least {least} Observations, got {len(items)}")
    return list(items)


def check_file(path, what):
    """InputError unless ``path`` is a regular file: a directory or a device is said to be one."""
    path = os.fspath(path)
    if os.path.isfile(path):
        return path
    if os.path.isdir(path):
        raise InputError(f"{what} {path}: is a directory, expected a file")
    if os.path.exists(path):
        raise InputError(f"{what} {path}: not a regular file (a device or a pipe), expected a file")
    raise InputError(f"{what} {path}: no such file")


def read_array(path, what):
    """A 2-D or 3-D numeric array from .npy, .png or .tif(f)."""
    path = os.fspath(path)
    check_file(path, what)
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext == ".npy":
            return np.load(path, allow_pickle=False)
        if ext in (".png", ".tif", ".tiff"):
            from PIL import Image

            with Image.open(path) as im:
                if im.mode in ("I;16", "I;16B", "I;16L", "I", "F", "L"):
                    return np.asarray(im)
                return np.asarray(im.convert("RGB"))
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{what} {path}: not a readable {ext} file ({exc})") from None
    raise InputError(f"{what} {path}: unsupported file type '{ext}' (use .npy, .png or .tif; "
                     "Stokes images as .exr)")


def check_samples(a, name):
    """``a`` if its samples are integers or real numbers, else InputError naming ``name``."""
    if a.dtype.kind not in "uif":
        raise InputError(f"{name}: samples of dtype {a.dtype}; a polarisation image holds integers or real numbers "
                         "(uint8, uint16, int32, float32, float64, ...)")
    if a.size and not np.isfinite(a).any():
        raise InputError(f"{name}: no finite sample (every value is NaN or infinite)")
    return a


def load_polarisation(paths, *, layout=mosaic.IMX250MZR_LAYOUT, channel="mean", black_level=0.0,
                      demosaic="bilinear"):
    """(stokes (3, H, W) float64, meta) of ``paths``: a Stokes ``.exr`` (its metadata as ``meta``), a raw mosaic
    (2-D ``.npy``, 16-bit ``.png`` / ``.tif``) split with ``layout`` at half resolution, or polariser-angle images 0,
    45, 90, 135 (a (4, H, W) ``.npy`` or four files); ``channel`` picks a channel of an RGB Stokes EXR."""
    def one_channel(what):
        if channel not in (None, "mean"):
            raise InputError(f"--channel {channel}: picks a colour channel of an RGB Stokes EXR; {what} has one "
                             "channel (a colour polarisation mosaic takes its channels from its sidecar)")
    if isinstance(paths, (list, tuple)):
        if len(paths) == 1:
            paths = paths[0]
        elif len(paths) == 4:
            imgs = [check_samples(read_array(p, f"angle image {a} deg"), f"angle image {p}")
                    for p, a in zip(paths, mosaic.ANGLES)]
            for p, im in zip(paths, imgs):
                if im.ndim != 2:
                    raise InputError(f"angle image {p}: expected a 2-D single-channel image, got {im.shape}")
            if len({im.shape for im in imgs}) != 1:
                raise InputError(f"angle images: shapes differ: {[im.shape for im in imgs]}")
            one_channel("four angle images")
            a = np.stack(imgs)
            return stokes_from_angles(a, black_level), {"source": "angle images", "_array": a}
        else:
            raise InputError(f"polarisation input: give one file (Stokes .exr, raw mosaic, or a (4, H, W) "
                             f".npy of angle images) or four angle images, got {len(paths)} paths")
    path = os.fspath(paths)
    if path.lower().endswith(".exr"):
        try:
            stokes, meta = stokes_io.read_stokes_exr(path)
        except stokes_io.StokesFileError as exc:
            raise InputError(str(exc)) from None
        s = np.asarray(stokes, dtype=np.float64)
        if s.ndim == 3:
            one_channel(f"the Stokes EXR {path}")
            return s[:3], meta
        names = stokes_io.COLOUR_CHANNELS.get(s.shape[-1], ())   # a colour channel or their mean (exact for the
        if channel in (None, "mean"):                           # fit: the model is linear in the albedos)
            return s[:3].mean(axis=-1), meta
        if channel in names:
            return s[:3, ..., names.index(channel)], meta
        raise InputError(f"channel: expected 'mean' or one of {names}, got {channel!r}")
    a = check_samples(read_array(path, "polarisation image"), f"polarisation image {path}")
    if a.ndim in (2, 3):
        one_channel(f"{path} ({'a raw mosaic' if a.ndim == 2 else 'angle images'})")
    if a.ndim == 2:
        try:
            return (stokes_from_raw(a, layout, black_level, demosaic),
                    {"source": "raw mosaic", "layout": layout, "demosaic": demosaic, "_array": a})
        except ValueError as exc:  # the sensor's checks: odd size, layout, demosaic
            raise InputError(str(exc)) from None
    if a.ndim == 3 and a.shape[0] == 4:
        return stokes_from_angles(a, black_level), {"source": "angle images", "_array": a}
    raise InputError(f"polarisation image {path}: expected a 2-D raw mosaic or (4, H, W) angle images, "
                     f"got shape {a.shape}")


def read_mask(path_or_array, shape=None):
    """A boolean mask from an array or a .npy / .png file (non-zero = object)."""
    file = isinstance(path_or_array, (str, os.PathLike))
    name = f"mask {os.fspath(path_or_array)}" if file else "mask"
    m = read_array(path_or_array, "mask") if file else np.asarray(path_or_array)
    if m.ndim == 3:
        m = m[..., 0]
    if m.ndim != 2:
        raise InputError(f"{name}: expected a 2-D array, got shape {m.shape}")
    return check_mask(m, m.shape if shape is None else shape, name)


def read_vectors(path_or_array, name, shape=None):
    """(H, W, 3) float64 vectors from an array or a .npy file."""
    a = np.asarray(read_array(path_or_array, name) if isinstance(path_or_array, (str, os.PathLike))
                   else path_or_array, dtype=np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError(f"{name}: expected shape (H, W, 3), got {a.shape}")
    if shape is not None and a.shape[:2] != tuple(shape):
        raise InputError(f"{name}: shape {a.shape[:2]} does not match the image {tuple(shape)}")
    return a


def check_camera(camera, fov):
    """``camera`` and ``fov`` checked (:data:`~fmbrdf_mi.fit.inputs.options.IMAGE_OPTIONS`)."""
    IMAGE_OPTION["camera"].check(camera)
    if camera == "perspective" and fov is None:
        raise InputError("fov: a perspective camera needs its horizontal field of view in (0, 180) degrees")
    return camera, IMAGE_OPTION["fov"].check(fov)


def find_sphere(mask):
    """Centre (x, y) and radius in pixels of the disc in ``mask``: a Kasa circle through the midpoints between mask
    pixels and their outside 4-neighbours (unbiased samples of the outline, as a pixel is in the disc when its
    centre is); the image border is no outline (a sphere cut by the frame)."""
    m = read_mask(mask)
    if m.sum() < 12:
        raise InputError(f"mask: {int(m.sum())} pixels are too few to find a sphere in (need >= 12)")
    xs, ys = [], []
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        a = m[max(-dy, 0):m.shape[0] - max(dy, 0), max(-dx, 0):m.shape[1] - max(dx, 0)]
        b = m[max(dy, 0):, max(dx, 0):][:a.shape[0], :a.shape[1]]
        yy, xx = np.nonzero(a & ~b)
        yy, xx = yy + max(-dy, 0), xx + max(-dx, 0)
        xs.append(xx + 0.5 + 0.5 * dx)
        ys.append(yy + 0.5 + 0.5 * dy)
    x, y = np.concatenate(xs), np.concatenate(ys)
    if len(x) < 6:
        raise InputError("mask: its outline is too short to fit a circle (is it a sphere inside the frame?)")
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    a, b, c = sol
    r = np.sqrt(max(c + a * a + b * b, 0.0))
    return (float(a), float(b)), float(r)


def erode(mask, pixels=1):
    """Mask minus ``pixels`` layers of its boundary (4-neighbourhood)."""
    m = np.asarray(mask, dtype=bool)
    for _ in range(int(pixels)):
        pad = np.pad(m, 1, constant_values=False)
        m = m & pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
    return m


def downsample_geometry(normals, mask, view_dirs, cell=2):
    """Geometry pooled over ``cell`` x ``cell`` pixels (a power of 2): mean vectors renormalised, mask all."""
    def pool(a):
        a = np.asarray(a, float)[: a.shape[0] - a.shape[0] % 2, : a.shape[1] - a.shape[1] % 2]
        return 0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])

    n, m, v = normals, mask, view_dirs
    for _ in range(int(cell).bit_length() - 1):
        n, m, v = (pool(a) for a in (n, m, v))
        n, m, v = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12), m > 0.999, \
            v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    return n, m, v
