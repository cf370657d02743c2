"""Stokes images: the EXR layout, reading and writing, and derived quantities.

Array layout used throughout the package: ``stokes`` has shape ``(4, H, W, C)``
with ``stokes[k]`` the Stokes component S_k as an image, rows top to bottom, and
C = 3 colour channels (R, G, B) or C = 1 (monochrome, channel "Y").

Stokes frame (that of Mitsuba's ``stokes`` integrator): x = image right,
y = image up, light travelling towards the camera.  S1 > 0 is horizontal
polarisation, S2 > 0 polarisation along the diagonal from lower left to upper
right; the AoLP is measured from image right counter-clockwise as the image is
displayed, in (-pi/2, pi/2].

EXR layout written by :func:`write_stokes_exr`: one float32 channel per Stokes
component and colour, named ``S0.R, S0.G, S0.B, S1.R, ...`` (or ``S0.Y ... S3.Y``),
plus a string header attribute ``fmbrdf_mi`` holding JSON metadata (material
parameters, light, camera, ... as the writer chose).  Plain OpenEXR readers see
ordinary named channels.
"""
from __future__ import annotations

import contextlib
import json
import os

import numpy as np

META_KEY = "fmbrdf_mi"
COLOUR_CHANNELS = {3: ("R", "G", "B"), 1: ("Y",)}


class StokesFileError(ValueError):
    """A Stokes file is missing, unreadable or not in the documented layout."""


def _check_stokes(stokes):
    s = np.asarray(stokes)
    if s.ndim == 3:
        s = s[..., None]
    if s.ndim != 4 or s.shape[0] != 4 or s.shape[3] not in COLOUR_CHANNELS:
        raise ValueError(f"stokes: expected an array of shape (4, H, W, C) with C = 1 or 3 "
                         f"(or (4, H, W)), got shape {np.shape(stokes)}")
    return s


def stokes_from_film(array, names):
    """Stokes array (4, H, W, C) from a Mitsuba ``stokes`` film bitmap.

    ``array`` is ``np.asarray(film.bitmap())`` (H, W, n) and ``names`` its
    channel names (``[f.name for f in bitmap.struct_()]``).  Monochrome variants
    still write S*.R/G/B with equal values; ``mono=True`` layouts come back with C = 1.
    """
    array = np.asarray(array, dtype=np.float32)
    index = {n: i for i, n in enumerate(names)}
    if "S0.R" not in index:
        raise ValueError(f"film has no Stokes channels (got {list(names)}); "
                         "render with the 'stokes' integrator")
    mono = "Y" in index and "R" not in index
    cols = ("R",) if mono else ("R", "G", "B")
    out = np.stack([np.stack([array[..., index[f"S{k}.{c}"]] for c in cols], axis=-1)
                    for k in range(4)])
    return out


def write_stokes_exr(path, stokes, metadata=None, force=False):
    """Write ``stokes`` (4, H, W, C) as a float32 EXR with channels S0.R ... S3.B.

    ``metadata`` (JSON-serialisable dict) goes into the header attribute
    ``fmbrdf_mi``.  An existing file is only replaced with ``force=True``.
    """
    s = _check_stokes(stokes).astype(np.float32)
    cols = COLOUR_CHANNELS[s.shape[3]]
    _write_exr(path, {f"S{k}.{c}": np.ascontiguousarray(s[k, :, :, i]) for k in range(4) for i, c in enumerate(cols)},
               metadata, force)


def write_map_exr(path, image, metadata=None, force=False):
    """Write a map (an albedo map, its standard errors): ``image`` (H, W) as a float32 EXR with channel Y, or
    (3, H, W) with channels R, G, B (NaN where there is no value).  ``metadata`` and ``force`` as
    :func:`write_stokes_exr`."""
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        channels = {"Y": np.ascontiguousarray(a)}
    elif a.ndim == 3 and a.shape[0] == 3:
        channels = {c: np.ascontiguousarray(a[i]) for i, c in enumerate(("R", "G", "B"))}
    else:
        raise ValueError(f"image: expected shape (H, W) or (3, H, W), got {a.shape}")
    _write_exr(path, channels, metadata, force)


def _write_exr(path, channels, metadata, force):
    """Write float32 ``channels`` {name: (H, W)} atomically (a temporary file, then renamed; the temporary
    file removed when writing fails or is interrupted)."""
    import OpenEXR

    path = os.fspath(path)
    if os.path.exists(path) and not force:
        raise FileExistsError(f"{path} exists; pass force=True (--force) to overwrite it")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if metadata is not None:
        header[META_KEY] = json.dumps(metadata, sort_keys=True)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f".{os.path.basename(path)}.tmp{os.getpid()}.exr")
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
        os.replace(tmp, path)
    except BaseException:      # Ctrl-C or a full disk: no temporary file left behind
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def read_exr(path):
    """``(header dict, {channel name: (H, W) array})`` of an EXR file, read with the OpenEXR package (not
    Mitsuba's reader, which hangs in a process allowed one CPU).  ValueError naming the file when it cannot
    be read: empty, truncated, not an EXR."""
    import OpenEXR

    with _native_output() as said:   # the library's own lines about a damaged file go into the message
        try:
            with OpenEXR.File(os.fspath(path), separate_channels=True) as f:
                return dict(f.header()), {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
        except Exception as exc:  # OpenEXR raises bare RuntimeErrors
            error = exc
    path = os.fspath(path)
    why = next((ln for ln in said() if "EXR_ERR" in ln), None) or str(error)
    raise ValueError(f"{path}: not a readable EXR file ({' '.join(why.removeprefix(f'{path}: ').split())})")


@contextlib.contextmanager
def _native_output():
    """Capture what native code writes to the standard output and error (file descriptors 1 and 2) inside the
    block; yields a function that returns the captured lines once the block has ended."""
    import sys
    import tempfile

    lines = []
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            yield lambda: lines
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            tmp.seek(0)
            lines.extend(tmp.read().decode(errors="replace").splitlines())


def read_stokes_exr(path):
    """Read a Stokes EXR; returns ``(stokes (4, H, W, C) float32, metadata dict)``.

    Accepts the layout of :func:`write_stokes_exr` and Mitsuba's own film output
    (S0.R ... S3.B beside R, G, B).  Raises :class:`StokesFileError` naming the
    file for a missing or malformed file.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise StokesFileError(f"{path}: is a directory, expected a Stokes .exr file")
    if not os.path.isfile(path):
        raise StokesFileError(f"{path}: not a regular file (a device or a pipe), expected a Stokes .exr file"
                              if os.path.exists(path) else f"{path}: no such file")
    try:
        header, channels = read_exr(path)
    except ValueError as exc:
        raise StokesFileError(str(exc)) from None
    cols = next((c for c in (("R", "G", "B"), ("Y",))
                 if all(f"S{k}.{x}" in channels for k in range(4) for x in c)), None)
    if cols is None:
        raise StokesFileError(f"{path}: no Stokes channels S0..S3 (.R/.G/.B or .Y); "
                              f"found {sorted(channels)}")
    stokes = np.stack([np.stack([channels[f"S{k}.{c}"] for c in cols], axis=-1)
                       for k in range(4)]).astype(np.float32)
    meta = header.get(META_KEY)
    if isinstance(meta, bytes):
        meta = meta.decode()
    return stokes, (json.loads(meta) if meta else {})


def intensity(stokes):
    """S0."""
    return np.asarray(stokes)[0]


def dolp(stokes, eps=1e-12):
    """Degree of linear polarisation sqrt(S1^2 + S2^2) / S0 (0 where S0 <= eps)."""
    s = np.asarray(stokes)
    s0 = s[0]
    out = np.hypot(s[1], s[2]) / np.where(s0 > eps, s0, 1.0)
    return np.where(s0 > eps, out, 0.0)


def aolp(stokes):
    """Angle of linear polarisation 0.5 atan2(S2, S1) in radians, in (-pi/2, pi/2]."""
    s = np.asarray(stokes)
    return 0.5 * np.arctan2(s[2], s[1])
