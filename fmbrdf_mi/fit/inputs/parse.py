"""Values given as text (command line, manifests): vectors, spheres, bounds, start and fixed values, layouts."""
from __future__ import annotations

import math

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.options import Option
from fmbrdf_mi.sensor.mosaic import check_layout


def check_keys(given, valid, where, what="key(s)", shown=None):
    """InputError naming ``where`` and the keys of ``given`` not in ``valid`` (listed, or ``shown`` instead)."""
    bad = [str(k) for k in given if k not in valid]
    if bad:
        raise InputError(f"{where}: unknown {what} {', '.join(bad)} ({shown or 'valid: ' + ', '.join(valid)})")


def parse_vector(text, name, n=3):
    """``"x,y,z"`` or ``n`` numbers -> a list of ``n`` floats (None passes), else InputError naming ``name``."""
    if text is None:
        return None
    try:
        vals = [float(x) for x in ([x for x in text.replace(" ", "").split(",") if x] if isinstance(text, str)
                                   else text)]
    except (TypeError, ValueError):   # words, nested lists, a number alone: not n numbers
        vals = None
    if vals is None or len(vals) != n:
        raise InputError(f"{name}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def parse_sphere(value, name="sphere"):
    """``auto`` or a sphere's centre and radius in pixels (``"cx,cy,r"`` or three numbers) -> ``"auto"`` or
    (cx, cy, r), a finite centre and a radius > 0."""
    if value is None or (isinstance(value, str) and value == "auto"):
        return value
    if isinstance(value, bool) or not isinstance(value, (str, list, tuple)):
        raise InputError(f"{name}: expected auto, \"cx,cy,r\" or [cx, cy, r] (pixels), got {value!r}")
    cx, cy, r = parse_vector(value, f"{name} (cx,cy,r in pixels)")
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r) and r > 0):
        raise InputError(f"{name}: expected a finite centre and a radius > 0 (pixels), got {value!r}")
    return cx, cy, r


def check_number(name, value, *, lo=None, lo_incl=True, hi=None, hi_incl=True):
    """``value`` if a finite real number in the range (not text, a list or a bool; None passes), else InputError."""
    return Option(name, kind="number", lo=lo, lo_open=not lo_incl, hi=hi, hi_open=not hi_incl).check(value)


def parse_pairs(items, name, form, example, value=float):
    """``NAME=...`` items (a list, or text of comma-separated items) -> {NAME: value(...)}, else InputError naming
    ``name`` (the option) with the ``form`` and an ``example``; a table (or None) is returned as it is."""
    if isinstance(items, dict) or items is None:
        return items
    if not isinstance(items, (str, list, tuple)):
        raise InputError(f"{name}: expected {form} items, e.g. {example}, got {items!r}")
    out = {}
    for item in ",".join([items] if isinstance(items, str) else map(str, items)).split(","):
        key, sep, text = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[key.strip()] = value(text)
        except ValueError:
            raise InputError(f"{name} {item!r}: expected {form}, e.g. {example}") from None
    return out


def _interval(text):
    lo, hi = text.split(":")
    return float(lo), float(hi)


def parse_bounds(items, name="--bounds"):
    """``["alpha=0.05:0.5", ...]`` -> {"alpha": (0.05, 0.5)} (bounds narrowed)."""
    return parse_pairs(items, name, "NAME=LO:HI", "alpha=0.05:0.5", _interval)


def parse_init(text, name="--init"):
    """``"eta=1.5,alpha=0.3,..."`` -> {"eta": 1.5, ...} (start values of all reported parameters)."""
    return parse_pairs(text, name, "NAME=VALUE,...", "eta=1.5,alpha=0.3,beta=2,kappa=10,k_s=1,r_k=1")


def parse_fixed(items, name="--fix"):
    """``["kappa=0", "eta=1.5"]`` or ``"kappa=0,eta=1.5"`` -> {"kappa": 0.0, "eta": 1.5} (parameters held fixed)."""
    return parse_pairs(items, name, "NAME=VALUE", "kappa=0")


def parse_layout(value, name="layout"):
    """``"90,45,135,0"`` or four whole angles in degrees, flat or 2x2 (row-major) -> ((90, 45), (135, 0))."""
    flat = value
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(isinstance(r, (list, tuple)) for r in value):
        flat = [a for r in value for a in r]
    if isinstance(flat, (list, tuple)) and not any(isinstance(a, bool) or not isinstance(a, int) for a in flat):
        flat = ",".join(map(str, flat))
    try:
        a = [int(x) for x in flat.replace(" ", "").split(",")]
    except (AttributeError, ValueError):
        raise InputError(f"{name}: expected four angles in degrees (row-major 2x2) such as \"90,45,135,0\" or "
                         f"[90, 45, 135, 0], got {value!r}") from None
    if len(a) != 4:
        raise InputError(f"{name}: expected four angles (row-major 2x2), got {value!r}")
    try:
        check_layout(((a[0], a[1]), (a[2], a[3])))
    except ValueError as exc:
        raise InputError(f"{name}{str(exc).removeprefix('layout')}") from None
    return ((a[0], a[1]), (a[2], a[3]))


def layout_text(layout):
    """``"90,45,135,0"``: a 2x2 layout as the command line and manifests write it."""
    return ",".join(str(int(a)) for row in layout for a in row)


def check_render_parameters(p, where):
    """The built-in scene's parameters in a render's metadata (an EXR's or a capture sidecar's): ``width``,
    ``height``, ``camera``, ``fov`` and ``distance`` checked, else InputError naming ``where`` and the key."""
    at = f"{where}: " if where else ""
    if not isinstance(p, dict):
        raise InputError(f"{at}parameters: expected a table, got {p!r:.60}")
    for key in ("width", "height", "camera", "fov", "distance"):
        if key not in p:
            raise InputError(f"{at}parameters: missing '{key}'")
    for key in ("width", "height"):
        v = p[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise InputError(f"{at}parameters.{key}: expected a whole number of pixels >= 1, got {v!r}")
    if p["camera"] not in ("orthographic", "perspective"):
        raise InputError(f"{at}parameters.camera: expected orthographic or perspective, got {p['camera']!r}")
    check_number(f"{at}parameters.fov", p["fov"], lo=0.0, lo_incl=False, hi=180.0, hi_incl=False)
    check_number(f"{at}parameters.distance", p["distance"], lo=0.0, lo_incl=False)
    return p
