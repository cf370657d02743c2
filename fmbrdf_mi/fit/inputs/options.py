"""The option schema's row type :class:`Option` with its value check, and :data:`IMAGE_OPTIONS`, the options of one
image; the rest of the schema is :mod:`fmbrdf_mi.fit.api.options`."""
from __future__ import annotations

import dataclasses
import math
import numbers

from fmbrdf_mi.fit.errors import InputError

#: The irradiances (image units) a fit can work with: beyond them the albedos leave its arithmetic's range.
IRRADIANCE_RANGE = (1e-20, 1e20)

#: The records of a fit.json that can keep an option (``Option.records``).
RECORDS = ("single", "colour", "joint")


@dataclasses.dataclass(frozen=True)
class Option:
    """One option, declared once.  ``kind``: ``"int"`` / ``"number"`` (in [``lo``, ``hi``], ``lo_open`` /
    ``hi_open`` excluding the end), ``"choice"`` (of ``choices``), ``"bool"``, or None (checked by
    :func:`fmbrdf_mi.fit.api.options.check_fit_options`).  ``fit``: a :class:`~fmbrdf_mi.fit.api.options.FitOptions`
    field.  ``records``: the fit.json records keeping it (:data:`RECORDS`; ``if_given``: only when given).
    ``refused_by``: the modes refusing it (:data:`fmbrdf_mi.fit.cli.command.REFUSED`).  ``flag`` (None: none),
    ``group``, ``cli``: its flag, help section and further ``add_argument`` keywords.  ``parse``: text -> value
    (``"kappa=0"`` -> ``{"kappa": 0.0}``).  ``many``: a value may be a list of up to this many (comma-separated)."""

    name: str
    default: object = None
    help: str = None
    flag: str = None
    group: str = None
    kind: str = None
    lo: float = None
    hi: float = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple = ()
    fit: bool = False
    records: tuple = ()
    if_given: tuple = ()
    refused_by: tuple = ()
    cli: dict = dataclasses.field(default_factory=dict)
    parse: object = None
    many: int = 1

    def range_text(self):
        """The valid range as an interval, e.g. ``(0, 180)``, ``[1, inf)``."""
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        return f"{left}{lo}, {hi}{right}"

    def split(self, text, name=None):
        """A many-valued option's comma-separated ``text`` -> one number or a tuple of up to ``many``; else as is."""
        if not isinstance(text, str) or self.many < 2:
            return text
        try:
            vals = tuple(float(x) for x in text.replace(" ", "").split(","))
        except ValueError:
            vals = ()
        if not 1 <= len(vals) <= self.many:
            raise InputError(f"{name or self.name}: expected {self.cli.get('metavar', self.name)} (one to {self.many} "
                             f"comma-separated numbers), got {text!r}")
        return vals[0] if len(vals) == 1 else vals

    def check(self, value, name=None):
        """``value`` checked against the kind and range (None passes), a number as int / float; else InputError naming
        ``name`` (default: the option's) and what is valid."""
        name = name or self.name
        if value is None or self.kind is None:
            return value
        if self.many > 1 and isinstance(value, (tuple, list)):
            if not 1 <= len(value) <= self.many:
                raise InputError(f"{name}: expected one value or up to {self.many}, got {value!r}")
            return tuple(dataclasses.replace(self, many=1).check(x, name) for x in value)
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise InputError(f"{name}: expected one of {', '.join(self.choices)}, got {value!r}")
            return value
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise InputError(f"{name}: expected True or False, got {value!r}")
            return value
        whole = self.kind == "int"
        what = "an integer" if whole else "a number"
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise InputError(f"{name}: expected {what} in {self.range_text()}, got {value!r}")
        v = float(value)
        bad = not math.isfinite(v) or (whole and v != int(v)) \
            or (self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo)) \
            or (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))
        if bad:
            raise InputError(f"{name}: expected {'a finite number' if not whole else what} in "
                             f"{self.range_text()}, got {value!r}")
        return int(v) if whole else v


_IMAGE = "polarimetric image"
_GEOMETRY = "geometry and light (camera frame: x image right, y image up, z towards the camera)"

#: The options of one image: build_observation's keywords, a manifest image's (or its [defaults]') keys.
IMAGE_OPTIONS = (
    Option("layout", None, flag="--layout", group=_IMAGE, records=("single",),
           help="mosaic polariser angles, 2x2 row-major from the top left (default: the capture sidecar's, else "
                "IMX250MZR 90,45,135,0)"),
    Option("black_level", None, kind="number", lo=0.0, flag="--black-level", group=_IMAGE,
           records=("single", "colour"), cli={"type": float},
           help="subtracted from raw / angle images (default: the sidecar's, else 0)"),
    Option("white_level", None, kind="number", lo=0.0, lo_open=True, flag="--white-level", group=_IMAGE,
           records=("single", "colour"), cli={"type": float, "metavar": "DN"},
           help="raw samples at or above this are clipped: their super-pixel is left out (default: the sidecar's, "
                "else the smallest 2^b - 1, b in 8,10,12,14,16, holding the data)"),
    Option("dark_level", None, kind="number", lo=0.0, flag="--dark-level", group=_IMAGE,
           records=("single",), cli={"type": float, "metavar": "DN"},
           help="raw samples at or below this (raw value, black level included) are clipped: their super-pixel "
                "is left out (default: 0 when the black level is 0, else none)"),
    Option("demosaic", "bilinear", kind="choice", choices=("bilinear", "superpixel"), flag="--demosaic",
           group=_IMAGE, records=("single",),
           help="raw mosaics: interpolate each angle to the super-pixel centre (default) or take the 2x2 pixels "
                "as they are"),
    Option("channel", "mean", flag="--channel", group=_IMAGE, records=("single",),
           help="colour channel of an RGB Stokes EXR: mean, R, G or B"),
    Option("conversion_gain", None, kind="number", lo=0.0, lo_open=True, flag="--conversion-gain", group=_IMAGE,
           records=("single", "colour"), cli={"type": float, "metavar": "E_PER_UNIT"},
           help="camera gain in electrons per image unit (e-/DN for raw images); with --read-noise, the DoLP term "
                "accounts for the noise bias of the observed DoLP"),
    Option("read_noise", None, kind="number", lo=0.0, flag="--read-noise", group=_IMAGE,
           records=("single", "colour"), cli={"type": float, "metavar": "E"}, help="read noise in electrons rms"),
    Option("footprint", "auto", kind="choice", choices=("auto", "point", "box", "demosaic"), flag="--footprint",
           group=_IMAGE, records=("single",),
           help="what a pixel integrates over, modelled by averaging the BSDF over it: the pixel centre, a 3x3 "
                "box, or the demosaicking's raw pixels (auto: demosaic for raw mosaics, point otherwise)"),
    Option("normals", None, flag="--normals", group=_GEOMETRY, records=("single", "colour"),
           cli={"metavar": "N.npy"}, help="normal map, H x W x 3 unit vectors"),
    Option("mask", None, flag="--mask", group=_GEOMETRY, records=("single", "colour"),
           cli={"metavar": "M"}, help="object mask (.npy or .png, non-zero = object)"),
    Option("sphere", None, flag="--sphere", group=_GEOMETRY, records=("single", "colour"),
           cli={"metavar": "CX,CY,R|auto"},
           help="a sphere: centre and radius in pixels (pixel centres at +0.5), or auto (from --mask)"),
    Option("view", None, flag="--view", group=_GEOMETRY, records=("single", "colour"),
           cli={"metavar": "V.npy"}, help="view directions, H x W x 3 (default: from --camera)"),
    Option("camera", "orthographic", kind="choice", choices=("orthographic", "perspective"), flag="--camera",
           group=_GEOMETRY, records=("single", "colour"), help="the camera's projection"),
    Option("fov", None, kind="number", lo=0.0, lo_open=True, hi=180.0, hi_open=True, flag="--fov", group=_GEOMETRY,
           records=("single", "colour"), cli={"type": float},
           help="horizontal field of view (degrees) of a perspective camera"),
    Option("irradiance", None, kind="number", lo=IRRADIANCE_RANGE[0], hi=IRRADIANCE_RANGE[1], flag="--irradiance",
           group=_GEOMETRY, records=("single", "colour"), cli={"type": float},
           help="light irradiance in image units (default 1: absorbed by k_s)"),
)

#: :data:`IMAGE_OPTIONS` by name.
IMAGE_OPTION = {o.name: o for o in IMAGE_OPTIONS}

#: The image options a manifest image (or [defaults]) may give.
IMAGE_KEYS = tuple(o.name for o in IMAGE_OPTIONS)
