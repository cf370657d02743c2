"""Several images of one object: the manifest (JSON or TOML) and :class:`ImageSpec`."""
from __future__ import annotations

import dataclasses
import json
import os
import re

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.files import build_observation
from fmbrdf_mi.fit.inputs.parse import parse_vector

#: Options an image entry (or [defaults]) may give: :func:`fmbrdf_mi.fit.inputs.files.build_observation`'s.
INPUT_KEYS = ("normals", "mask", "view", "sphere", "camera", "fov", "irradiance", "layout", "black_level",
              "white_level", "dark_level", "channel", "demosaic", "footprint", "conversion_gain", "read_noise")


PATH_KEYS = ("input", "normals", "mask", "view")


ENTRY_KEYS = ("input", "light", "power", "holdout", "name") + INPUT_KEYS


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
    if not os.path.isfile(path):
        raise InputError(f"manifest {path}: no such file")
    try:
        if path.lower().endswith(".toml"):
            import tomllib

            with open(path, "rb") as f:
                d = tomllib.load(f)
        else:
            with open(path) as f:
                d = json.load(f)
    except (ValueError, OSError) as exc:
        raise InputError(f"manifest {path}: not readable ({exc})") from None
    return parse_manifest(d, os.path.dirname(os.path.abspath(path)), path)


def parse_manifest(d, base=".", where="manifest"):
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a table with [defaults] and [[image]] entries")
    unknown = [k for k in d if k not in ("defaults", "image", "images")]
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)} (expected defaults, image)")
    defaults = d.get("defaults", {}) or {}
    if not isinstance(defaults, dict):
        raise InputError(f"{where}: defaults must be a table")
    bad = [k for k in defaults if k not in INPUT_KEYS]
    if bad:
        raise InputError(f"{where}: defaults: unknown key(s) {', '.join(bad)} (valid: {', '.join(INPUT_KEYS)})")
    entries = d.get("image", d.get("images"))
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where}: no images (give [[image]] entries with input and light)")

    def rel(v):
        if isinstance(v, str):
            return v if os.path.isabs(v) else os.path.join(base, v)
        if isinstance(v, list):
            return [rel(x) for x in v]
        return v

    specs = []
    for k, e in enumerate(entries):
        if not isinstance(e, dict) or "input" not in e:
            raise InputError(f"{where}: image {k}: expected a table with at least 'input'")
        bad = [x for x in e if x not in ENTRY_KEYS]
        if bad:
            raise InputError(f"{where}: image {k}: unknown key(s) {', '.join(bad)} (valid: {', '.join(ENTRY_KEYS)})")
        opts = {**defaults, **{x: e[x] for x in INPUT_KEYS if x in e}}
        for x in PATH_KEYS[1:]:
            if x in opts and isinstance(opts[x], (str, list)):
                opts[x] = rel(opts[x])
        power = e.get("power", 1.0)
        if isinstance(power, bool) or not isinstance(power, (int, float)) or not (np.isfinite(power) and power > 0):
            raise InputError(f"{where}: image {k}: power must be a positive number, got {power!r}")
        if not isinstance(e.get("holdout", False), bool):
            raise InputError(f"{where}: image {k}: holdout must be true or false")
        specs.append(ImageSpec(rel(e["input"]), e.get("light"), float(power), bool(e.get("holdout", False)),
                               e.get("name"), opts))
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


def build_observations(specs):
    """Observations of the specs (each with irradiance x power)."""

    out = []
    for k, s in enumerate(specs):
        if hasattr(s.input, "stokes"):
            o = s.input
        else:
            opts = dict(s.options)
            opts.setdefault("layout", None)        # None: the capture sidecar's, else IMX250MZR
            opts.setdefault("black_level", None)
            try:
                light = parse_vector(s.light, f"image {k}: light") if s.light is not None else None
                o = build_observation(s.input, light=light, **opts)
            except InputError as exc:
                raise InputError(f"image {k} ({file_stem(s.input)}): {exc}") from None
        if s.power != 1.0:
            o = dataclasses.replace(o, irradiance=o.irradiance * s.power)
        out.append(o)
    return out


def given_power(spec, obs):
    """The relative light power image ``spec`` was given: the manifest's ``power``, the authors'
    ``intensities.npy`` / max (both already in the observation's irradiance), 1 if none."""
    return float((obs.meta.get("authors_layout") or {}).get("power", spec.power))


def absolute_paths(v):
    if isinstance(v, str):
        return os.path.abspath(v)
    if isinstance(v, list):
        return [absolute_paths(x) for x in v]
    return v
