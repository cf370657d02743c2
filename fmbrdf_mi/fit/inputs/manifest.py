"""Several images of one object: the manifest (JSON or TOML) and :class:`ImageSpec`."""
from __future__ import annotations

import dataclasses
import json
import os
import re

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.files import build_observation, check_image_options
from fmbrdf_mi.fit.inputs.observations import check_direction, check_file
from fmbrdf_mi.fit.inputs.options import IMAGE_KEYS, IRRADIANCE_RANGE, Option
from fmbrdf_mi.fit.inputs.parse import check_keys, layout_text, parse_layout, parse_vector

#: An image's keys that name files.
PATH_KEYS = ("input", "normals", "mask", "view")

#: The keys of a manifest's image entry: its own and :data:`~fmbrdf_mi.fit.inputs.options.IMAGE_KEYS`.
ENTRY_KEYS = ("input", "light", "power", "holdout", "name") + IMAGE_KEYS


def _is_path(v):
    return isinstance(v, str) and v != ""


def check_options(opts, where):
    """One image's (or [defaults]') options checked, a layout as text ``"90,45,135,0"``; InputError names ``where``."""
    check_image_options(opts, where)
    out = dict(opts)
    for key, v in opts.items():
        if v is None:
            continue
        name = f"{where}: {key}"
        if key in ("normals", "mask", "view", "channel") and not _is_path(v):
            raise InputError(f"{name}: expected " + ("mean, R, G or B" if key == "channel" else "a file name (text)")
                             + f", got {v!r}")
        elif key == "layout":
            out[key] = layout_text(parse_layout(v, name))
    return out


def image_spec(input, light=None, power=1.0, holdout=False, name=None, options=None, *, where, at=""):
    """An :class:`ImageSpec` checked: ``input`` a file or a list of one or four (angle images 0, 45, 90, 135),
    ``light`` ``"x,y,z"`` or three numbers (None: the input's metadata's), ``power`` > 0, ``options`` a table of
    :data:`~fmbrdf_mi.fit.inputs.options.IMAGE_KEYS`; InputError naming ``where`` (``at``: after it, the options)."""
    if not (_is_path(input) or (isinstance(input, list) and len(input) in (1, 4) and all(map(_is_path, input)))):
        raise InputError(f"{where}: input: expected a file name or a list of four angle-image file names, got "
                         f"{input!r}")
    if light is not None and (isinstance(light, bool) or not isinstance(light, (str, list, tuple))):
        raise InputError(f"{where}: light: expected [x, y, z] (towards the light, camera frame), got {light!r}")
    if light is not None:
        check_direction(parse_vector(light, f"{where}: light"), f"{where}: light")
    Option("power", kind="number", lo=IRRADIANCE_RANGE[0], hi=IRRADIANCE_RANGE[1]).check(power, f"{where}: power")
    if not isinstance(holdout, bool):
        raise InputError(f"{where}: holdout must be true or false")
    if name is not None and (isinstance(name, bool) or not isinstance(name, (str, int))):
        raise InputError(f"{where}: name: expected text, got {name!r}")
    if not isinstance(options, dict):
        raise InputError(f"{where}{at}: expected a table, got {options!r}")
    check_keys(options, IMAGE_KEYS, where + at)
    return ImageSpec(input, light, float(power), holdout, name, check_options(options, where + at))


@dataclasses.dataclass
class ImageSpec:
    """One image of a joint fit: its input and the options that build its Observation."""

    input: object                   # path, list of four paths, or an Observation already built
    light: object = None
    power: float = 1.0
    holdout: bool = False
    name: str = None
    options: dict = dataclasses.field(default_factory=dict)


def file_stem(p):
    p = p[0] if isinstance(p, (list, tuple)) else p
    return os.path.splitext(os.path.basename(os.fspath(p)))[0]


def read_manifest(path):
    """[ImageSpec] from a JSON or TOML manifest (paths made relative to the manifest's directory)."""
    path = os.fspath(path)
    check_file(path, "manifest")
    ext = os.path.splitext(path)[1].lower()
    if ext in (".yaml", ".yml", ".ini", ".cfg", ".xml", ".csv"):
        raise InputError(f"manifest {path}: a {ext} file; manifests are TOML (.toml) or JSON (.json or any other "
                         "name)")
    try:
        if ext == ".toml":
            import tomllib

            with open(path, "rb") as f:
                d = tomllib.load(f)
        else:
            with open(path, encoding="utf-8") as f:
                d = json.load(f)
    except (ValueError, OSError) as exc:
        kind = "TOML" if ext == ".toml" else "JSON" + (" (its name does not end in .toml)" if ext != ".json" else "")
        raise InputError(f"manifest {path}: not readable as {kind} ({exc})") from None
    return parse_manifest(d, os.path.dirname(os.path.abspath(path)), path)


def parse_manifest(d, base=".", where="manifest"):
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a table with [defaults] and [[image]] entries")
    check_keys(d, ("defaults", "image", "images"), where, shown="expected defaults, image")
    defaults = d.get("defaults", {}) or {}
    if not isinstance(defaults, dict):
        raise InputError(f"{where}: defaults must be a table")
    check_keys(defaults, IMAGE_KEYS, f"{where}: defaults")
    defaults = check_options(defaults, f"{where}: defaults")
    entries = d.get("image", d.get("images"))
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where}: no images (give [[image]] entries with input and light)")
    specs = []
    for k, e in enumerate(entries):
        if not isinstance(e, dict) or "input" not in e:
            raise InputError(f"{where}: image {k}: expected a table with at least 'input'")
        check_keys(e, ENTRY_KEYS, f"{where}: image {k}")
        s = image_spec(e["input"], e.get("light"), e.get("power", 1.0), e.get("holdout", False), e.get("name"),
                       {x: e[x] for x in IMAGE_KEYS if x in e}, where=f"{where}: image {k}")
        s.input, s.options = absolute_paths(s.input, base), {**defaults, **s.options}
        s.options.update({x: absolute_paths(s.options[x], base) for x in PATH_KEYS[1:] if x in s.options})
        specs.append(s)
    return specs


def image_names(specs):
    names, seen = [], {}
    for k, s in enumerate(specs):
        n = s.name or (file_stem(s.input) if not hasattr(s.input, "stokes") else f"image{k}")
        n = re.sub(r"[^A-Za-z0-9_.-]", "_", str(n)) or f"image{k}"
        if n in seen:
            n = f"{n}_{k}"
        seen[n] = 1
        names.append(n)
    return names


def read_image(k, spec, read, **kw):
    """``read(input, light=..., **kw)`` of image ``k``, ``spec``, its errors prefixed with the image."""
    try:
        return read(spec.input, light=None if spec.light is None else parse_vector(spec.light, f"image {k}: light"),
                    **kw)
    except InputError as exc:
        raise InputError(f"image {k} ({file_stem(spec.input)}): {exc}") from None


def build_observations(specs):
    """Observations of the specs (each with irradiance x power)."""
    out = []
    for k, s in enumerate(specs):   # layout, black level None: the capture sidecar's, else IMX250MZR's, 0
        o = s.input if hasattr(s.input, "stokes") else read_image(
            k, s, build_observation, **{"layout": None, "black_level": None, **s.options})
        if s.power != 1.0:
            lo, hi = IRRADIANCE_RANGE
            if not lo <= o.irradiance * s.power <= hi:
                raise InputError(f"image {k} ({image_names(specs)[k]}): power {s.power:g} x irradiance "
                                 f"{o.irradiance:g} = {o.irradiance * s.power:g} is outside [{lo:g}, {hi:g}] (what "
                                 "a fit can work with, image units)")
            o = dataclasses.replace(o, irradiance=o.irradiance * s.power)
        out.append(o)
    return out


def given_power(spec, obs):
    """The relative light power of image ``spec`` (manifest ``power`` or the authors' intensities; 1 if none)."""
    return float((obs.meta.get("authors_layout") or {}).get("power", spec.power))


def absolute_paths(v, base=None):
    """``v`` (a path, a list of paths; anything else as it is) with every path absolute, or joined to ``base``."""
    if isinstance(v, str):
        return os.path.abspath(v) if base is None else os.path.join(base, v)
    return [absolute_paths(x, base) for x in v] if isinstance(v, list) else v
