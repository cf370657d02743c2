"""The camera model: how a polarisation sensor turns a Stokes image into raw numbers (``render --raw`` simulates
it, the fits' likelihood assumes it).

Raw pixel (r, c) sees I = (S0 + S1 cos 2 phi + S2 sin 2 phi) / 2 of the Stokes
image at that pixel behind the polariser phi of its mosaic position (a colour
sensor, ``cfa`` set: the Stokes image of its own colour); ``electrons =
exposure * I`` with Poisson shot noise and Gaussian read noise, clipped to the
full well; ``DN = round(electrons / conversion_gain) + black_level``.  A
sample of mean mu DN above the black level then has the variance
mu / g + (read_noise / g)^2 + 1 / 12 (:meth:`CameraModel.variance`) unless it
is clipped.  A capture's settings travel with it as a JSON sidecar, which
``fmbrdf-mi fit`` reads.
"""
from __future__ import annotations

import dataclasses
import json
import numbers
import os

import numpy as np

from fmbrdf_mi.sensor import mosaic

#: Key that marks a JSON file as a capture sidecar of this package.
SIDECAR_KEY = "fmbrdf_mi_capture"


@dataclasses.dataclass
class CameraModel:
    """Sensor and ADC settings.  Defaults: a 5 MP IMX250MZR-like sensor with a 12-bit ADC over its full well."""

    full_well: float = 10000.0       # electrons
    read_noise: float = 2.5          # electrons rms
    bits: int = 12                   # ADC resolution
    conversion_gain: float = None    # electrons per DN (None: the ADC spans the full well)
    black_level: float = 0.0         # DN added to every sample (an offset keeps the read noise of dark pixels)
    layout: tuple = mosaic.IMX250MZR_LAYOUT
    cfa: tuple = None                # colour filter per 2x2 polariser block (None: monochrome sensor)

    def __post_init__(self):
        for name in ("full_well", "read_noise", "bits", "conversion_gain", "black_level"):
            v = getattr(self, name)
            optional = v is None and name == "conversion_gain"
            if not optional and (isinstance(v, bool) or not isinstance(v, numbers.Real)):
                raise ValueError(f"camera: {name} must be a number, got {v!r}")
        if not (np.isfinite(self.full_well) and self.full_well > 0 and np.isfinite(self.read_noise)
                and self.read_noise >= 0 and 1 <= int(self.bits) <= 16):
            raise ValueError(f"camera: need full_well > 0, read_noise >= 0, bits in [1, 16]; got {self}")
        self.bits = int(self.bits)
        if self.conversion_gain is None:
            self.conversion_gain = self.full_well / self.levels
        if not (np.isfinite(self.conversion_gain) and self.conversion_gain > 0):
            raise ValueError(f"camera: conversion_gain must be > 0 electrons per DN, got {self.conversion_gain}")
        if not (np.isfinite(self.black_level) and 0 <= self.black_level < self.levels):
            raise ValueError(f"camera: black_level must be in [0, {self.levels}), got {self.black_level}")
        try:
            self.layout = tuple(tuple(int(a) for a in row) for row in self.layout)
        except (TypeError, ValueError):
            raise ValueError(f"camera: layout: expected a 2x2 arrangement of the angles {mosaic.ANGLES}, "
                             f"got {self.layout!r}") from None
        mosaic.check_layout(self.layout)
        if self.cfa is not None:
            self.cfa = mosaic.check_cfa(self.cfa)

    @property
    def period(self):
        """Raw pixels per mosaic period: 2 (monochrome) or 4 (colour)."""
        return 2 if self.cfa is None else 4

    @property
    def levels(self):
        """The ADC maximum, 2^bits - 1."""
        return 2 ** int(self.bits) - 1

    @property
    def white_level(self):
        """Raw value (DN) at and above which a sample is clipped: the ADC maximum or the full well."""
        return float(min(self.levels, np.floor(self.full_well / self.conversion_gain + self.black_level)))

    @property
    def read_noise_dn(self):
        return self.read_noise / self.conversion_gain

    def variance(self, mean_dn):
        """Variance (DN^2) of a raw sample whose mean above the black level is ``mean_dn``."""
        mu = np.clip(np.asarray(mean_dn, dtype=np.float64), 0.0, None)
        return mu / self.conversion_gain + self.read_noise_dn ** 2 + 1.0 / 12.0

    def to_dict(self):
        d = dataclasses.asdict(self)
        d["layout"] = [list(r) for r in self.layout]
        if self.cfa is None:
            del d["cfa"]
        else:
            d["cfa"] = [list(r) for r in self.cfa]
        d["white_level"] = self.white_level
        return d

    @classmethod
    def from_dict(cls, d):
        """A CameraModel from :meth:`to_dict`'s form; ValueError naming the key for a malformed one."""
        keys = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict):
            raise ValueError(f"expected a table of camera settings ({', '.join(sorted(keys))}), got {d!r}")
        for k in ("layout", "cfa"):
            v = d.get(k)
            if v is not None and not (isinstance(v, (list, tuple)) and len(v) == 2 and all(
                    isinstance(r, (list, tuple)) and len(r) == 2 for r in v)):
                example = [[90, 45], [135, 0]] if k == "layout" else [["R", "G"], ["G", "B"]]
                raise ValueError(f"{k}: expected a 2x2 list such as {example}, got {v!r}")
        wl = d.get("white_level")
        if wl is not None and (isinstance(wl, bool) or not isinstance(wl, numbers.Real) or not np.isfinite(wl)
                               or wl <= 0):
            raise ValueError(f"white_level: expected a positive number (DN), got {wl!r}")
        return cls(**{k: (tuple(tuple(r) for r in v) if k in ("layout", "cfa") and v is not None else v) for k, v in d.items() if k in keys})


def intensity_at_each_pixel(stokes3, layout):
    """Intensity behind the polariser of each pixel's mosaic position, (H, W), from (3, H, W) Stokes."""
    s = np.asarray(stokes3, dtype=np.float64)
    _, h, w = s.shape
    out = np.empty((h, w))
    for pos, angle in enumerate(a for row in layout for a in row):
        r, c = divmod(pos, 2)
        t = np.radians(angle)
        sp = s[:, r::2, c::2]
        out[r::2, c::2] = 0.5 * (sp[0] + np.cos(2 * t) * sp[1] + np.sin(2 * t) * sp[2])
    return out


def intensity_at_each_pixel_colour(stokes, layout, cfa):
    """(4H, 4W) intensity of a colour sensor: each raw pixel behind its polariser sees its colour's Stokes.

    ``stokes``: (3 channels R, G, B; >=3; 4H, 4W).
    """
    s = np.asarray(stokes, dtype=np.float64)
    out = np.empty(s.shape[2:])
    for r, c, ch in mosaic.colour_cells(cfa):
        for dr in range(2):
            for dc in range(2):
                sl = (slice(2 * r + dr, None, 4), slice(2 * c + dc, None, 4))
                angle = np.radians(layout[dr][dc])
                sp = s[ch][(slice(0, 3),) + sl]
                out[sl] = 0.5 * (sp[0] + np.cos(2 * angle) * sp[1] + np.sin(2 * angle) * sp[2])
    return out


def capture(stokes, camera=None, *, exposure=None, peak_fraction=0.9, seed=0, noiseless=False):
    """Raw quad-Bayer capture of a Stokes image through ``camera`` (:class:`CameraModel`).

    ``stokes``: (>=3, 2H, 2W) linear Stokes image (one channel) at the
    resolution of the raw sensor.  ``exposure``: electrons per unit of
    ``stokes``; None chooses it so that the brightest raw pixel collects
    ``peak_fraction`` of the full well.  Returns a dict with

    * ``raw``: (2H, 2W) uint16 digital numbers, black level included;
    * ``exposure``: electrons per input unit; ``dn_to_input``: multiply
      (raw - black level) by this to get back the input's units
      (= conversion_gain / exposure);
    * ``saturated``: fraction of samples at the white level.

    A colour camera (``camera.cfa`` set) takes ``stokes`` of shape
    (3 channels R, G, B; 3 or 4; 4H, 4W) and returns a (4H, 4W) colour mosaic.

    ``noiseless=True`` skips shot and read noise (rounding and clipping stay).
    """
    cam = camera or CameraModel()
    if cam.cfa is None:
        s = np.asarray(stokes, dtype=np.float64)[:3]
        if s.ndim != 3 or s.shape[1] % 2 or s.shape[2] % 2:
            raise ValueError(f"stokes: expected shape (3 or 4, 2H, 2W) with even sizes, got {np.shape(stokes)}")
        ideal = np.clip(intensity_at_each_pixel(s, cam.layout), 0.0, None)
    else:
        s = np.asarray(stokes, dtype=np.float64)
        if s.ndim != 4 or s.shape[0] != 3 or s.shape[1] < 3 or s.shape[2] % 4 or s.shape[3] % 4:
            raise ValueError(f"stokes: a colour sensor needs shape (3 channels R, G, B; 3 or 4; 4H, 4W) with "
                             f"sizes multiples of 4, got {np.shape(stokes)}")
        ideal = np.clip(intensity_at_each_pixel_colour(s, cam.layout, cam.cfa), 0.0, None)
    if exposure is None:
        peak = ideal.max()
        if peak <= 0:
            raise ValueError("stokes: the image is black; cannot choose an exposure")
        exposure = peak_fraction * cam.full_well / peak
    if not (np.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure: must be > 0 electrons per unit, got {exposure}")
    electrons = ideal * exposure
    rng = np.random.default_rng(seed)
    if not noiseless:
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons += rng.normal(0.0, cam.read_noise, electrons.shape)
    electrons = np.clip(electrons, 0.0, cam.full_well)
    dn = np.clip(np.round(electrons / cam.conversion_gain + cam.black_level), 0, cam.levels)
    return {"raw": dn.astype(np.uint16), "exposure": float(exposure),
            "dn_to_input": cam.conversion_gain / exposure,
            "saturated": float(np.mean(dn >= cam.white_level))}


# ---------------------------------------------------------------- sidecar
def sidecar_path(raw_path):
    """``capture.png`` -> ``capture.json``."""
    return os.path.splitext(os.fspath(raw_path))[0] + ".json"


def write_sidecar(raw_path, camera, extra=None, force=False):
    """Write the JSON sidecar of a raw capture (camera settings plus ``extra``, e.g. scene metadata)."""
    path = sidecar_path(raw_path)
    if os.path.exists(path) and not force:
        raise FileExistsError(f"{path} exists; pass --force to overwrite it")
    d = dict(extra or {})
    d.update({SIDECAR_KEY: 1, "sensor": camera.to_dict()})
    with open(path, "w") as f:
        json.dump(d, f, indent=2)
    return path


def read_sidecar(raw_path):
    """The sidecar dict of a raw capture, or None when there is none (or the JSON beside it is not one).

    ``d["sensor"]`` is the :class:`CameraModel`; the rest is what the writer added.
    """
    path = sidecar_path(raw_path)
    if not os.path.isfile(path):
        return None
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable JSON sidecar ({exc})") from None
    if not isinstance(d, dict) or SIDECAR_KEY not in d:
        return None
    if "sensor" not in d:
        raise ValueError(f"{path}: sensor: missing (the camera settings of the capture)")
    try:
        d["sensor"] = CameraModel.from_dict(d["sensor"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: sensor: {str(exc).removeprefix('camera: ')}") from None
    d["path"] = path
    return d


def default_white_level(raw):
    """The ADC maximum assumed when none is given: the smallest 2^b - 1 (b in 8, 10, 12, 14, 16) >= max(raw).

    A 12-bit camera stored in 16-bit files clips at 4095: its clipped
    samples are then recognised without the user saying so.
    """
    m = float(np.max(raw)) if np.size(raw) else 0.0
    for b in (8, 10, 12, 14, 16):
        if m <= 2 ** b - 1:
            return float(2 ** b - 1)
    return m
