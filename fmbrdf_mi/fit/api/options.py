"""Validation of the fit's options, shared by :func:`fmbrdf_mi.fit.fit` and ``fmbrdf-mi fit``.

Every numeric option is range-checked before any file is read or any BSDF is
built; mistakes raise :class:`~fmbrdf_mi.fit.errors.InputError` (a
ValueError) with one line naming the option and what is valid.
"""
from __future__ import annotations

import math
import numbers

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.evaluate.models import Bounds, get_model
from fmbrdf_mi.fit.inputs.observations import IRRADIANCE_RANGE


def _num(name, value, *, lo=None, lo_incl=True, hi=None, hi_incl=True, integer=False, none_ok=True):
    """``value`` as a float/int within the range, or InputError naming ``name``."""
    if value is None:
        if none_ok:
            return None
        raise InputError(f"{name}: a value is needed")
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name}: expected {kind}, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or (integer and v != int(v)):
        raise InputError(f"{name}: expected a finite {kind[3:] if integer else 'number'}, got {value!r}")
    below = lo is not None and (v < lo if lo_incl else v <= lo)
    above = hi is not None and (v > hi if hi_incl else v >= hi)
    if below or above:
        rng = f"{'[' if lo_incl else '('}{'-inf' if lo is None else f'{lo:g}'}, " \
              f"{'inf' if hi is None else f'{hi:g}'}{']' if hi_incl and hi is not None else ')'}"
        raise InputError(f"{name}: {value!r} is outside the valid range {rng}")
    return int(v) if integer else v


def reported_names(model):
    """Names of the parameters a fit of ``model`` reports (and --init must give)."""
    if model.name == "fmbrdf":
        return tuple(model.shape_names) + ("k_s", "r_k")
    return tuple(model.shape_names) + (model.surface_name, model.body_name)


#: The albedo layouts a fit can be asked for (``FitOptions.albedo``, ``--albedo``).
ALBEDO_LAYOUTS = ("shared",) + PER_PIXEL_LAYOUTS


def check_fit_options(*, model="fmbrdf", optimizer="lm", path="pixel", bounds=None, init=None, max_iter=40,
                      tol=1e-4, time_limit=None, max_time=None, max_pixels=20000, erode=2, seed=0,
                      lr=0.02, spp=16, rounds=3, loss="auto", starts=2, fixed=None, free_power=False,
                      power_start="ratio", area_points=None, albedo="shared", albedo_smooth=None,
                      flag=lambda name: name, **_ignored):
    """Raise InputError for the first invalid fit option.  ``flag`` maps an option name to
    how the user wrote it (``--max-pixels`` on the command line)."""

    if not isinstance(model, str):
        raise InputError(f"{flag('model')}: expected fmbrdf, pplastic, lambert_ts or oren_nayar_ts, got {model!r}")
    m = get_model(model)
    if optimizer not in ("lm", "adam"):
        raise InputError(f"{flag('optimizer')}: expected 'lm' or 'adam', got {optimizer!r}")
    if path not in ("pixel", "render"):
        raise InputError(f"{flag('path')}: expected 'pixel' or 'render', got {path!r}")
    _num(flag("max_iter"), max_iter, lo=1, integer=True, none_ok=False)
    _num(flag("tol"), tol, lo=0.0, none_ok=False)
    _num(flag("time_limit"), time_limit, lo=0.0, lo_incl=False)
    _num(flag("max_time"), max_time, lo=0.0)
    _num(flag("max_pixels"), max_pixels, lo=0, integer=True)
    _num(flag("erode"), erode, lo=0, integer=True, none_ok=False)
    _num(flag("seed"), seed, lo=0, integer=True, none_ok=False)
    _num(flag("lr"), lr, lo=0.0, lo_incl=False, none_ok=False)
    _num(flag("spp"), spp, lo=1, integer=True, none_ok=False)
    _num(flag("rounds"), rounds, lo=1, integer=True, none_ok=False)
    if loss not in ("auto", "likelihood", "paper", "intensity", "dolp"):
        raise InputError(f"{flag('loss')}: expected 'auto', 'likelihood', 'paper', 'intensity' or 'dolp', "
                         f"got {loss!r}")
    _num(flag("starts"), starts, lo=1, integer=True, none_ok=False)
    _num(flag("area_points"), area_points, lo=1, hi=16, integer=True)
    if not isinstance(free_power, bool):
        raise InputError(f"{flag('free_power')}: expected True or False, got {free_power!r}")
    if free_power and loss == "dolp":
        raise InputError(f"{flag('free_power')}: not with {flag('loss')} dolp (the DoLP does not depend on the "
                         "light's power, so the powers would be undetermined)")
    if albedo not in ALBEDO_LAYOUTS:
        raise InputError(f"{flag('albedo')}: expected {' or '.join(map(repr, ALBEDO_LAYOUTS))}, got {albedo!r}")
    if albedo in PER_PIXEL_LAYOUTS and (loss not in ("auto", "likelihood") or optimizer != "lm" or path != "pixel"):
        raise InputError(f"{flag('albedo')} {albedo}: needs the likelihood of the camera's samples ("
                         f"{flag('loss')} likelihood or auto with the camera noise known, the pixel path, optimizer "
                         "lm): the albedo maps are solved per pixel from its raw samples")
    if albedo in PER_PIXEL_LAYOUTS and free_power:
        raise InputError(f"{flag('albedo')} {albedo}: not with {flag('free_power')} (give the relative light "
                         "powers)")
    if albedo_smooth is not None:
        check_albedo_smooth(albedo_smooth, albedo, flag)
    if power_start not in ("ratio", "given"):
        raise InputError(f"{flag('power_start')}: expected 'ratio' or 'given', got {power_start!r}")
    if fixed is not None:
        if not isinstance(fixed, dict):
            raise InputError(f"{flag('fix')}: expected {{name: value}}, got {fixed!r}")
        lims = Bounds(m, None).lims
        for name, v in fixed.items():
            if name not in m.shape_names:
                raise InputError(f"{flag('fix')}: '{name}' is not a shape parameter of {m.name} "
                                 f"({', '.join(m.shape_names)})")
            v = _num(f"{flag('fix')} {name}", v, none_ok=False)
            lo, hi = lims[name][2], lims[name][3]
            if not lo <= v <= hi:
                raise InputError(f"{flag('fix')} {name}: {v:g} is outside the fit's bounds [{lo:g}, {hi:g}]")
    if bounds is not None:
        if not isinstance(bounds, dict):
            raise InputError(f"{flag('bounds')}: expected {{name: (lo, hi)}}, got {bounds!r}")
        for name, pair in bounds.items():
            try:
                lo, hi = pair
            except (TypeError, ValueError):
                raise InputError(f"{flag('bounds')} {name}: expected (lo, hi), got {pair!r}") from None
            _num(f"{flag('bounds')} {name} low", lo, none_ok=False)
            _num(f"{flag('bounds')} {name} high", hi, none_ok=False)
        try:
            Bounds(m, bounds)
        except ValueError as e:
            raise InputError(f"{flag('bounds')}: {e}") from None
    if init is not None:
        if not isinstance(init, dict):
            raise InputError(f"{flag('init')}: expected {{name: value}}, got {init!r}")
        names = reported_names(m)
        unknown = [k for k in init if k not in names]
        if unknown:
            raise InputError(f"{flag('init')}: unknown parameter '{unknown[0]}' of {m.name}; "
                             f"give all of {', '.join(names)}")
        missing = [k for k in names if k not in init]
        if missing:
            raise InputError(f"{flag('init')}: missing {', '.join(missing)} (give all of {', '.join(names)})")
        lims = Bounds(m, None).lims
        for k in names:
            v = _num(f"{flag('init')} {k}", init[k], none_ok=False)
            if k in lims:
                lo, hi = lims[k][2], lims[k][3]
                if not lo <= v <= hi:
                    raise InputError(f"{flag('init')} {k}: {v:g} is outside the fit's bounds [{lo:g}, {hi:g}]")
            elif v < 0:
                raise InputError(f"{flag('init')} {k}: {v:g} must be >= 0")


def check_albedo_smooth(value, albedo, flag=lambda name: name):
    """``albedo_smooth``: tau > 0 and finite, or a pair (tau_s, tau_b), with a per-pixel albedo layout."""
    name = flag("albedo_smooth")
    if albedo not in PER_PIXEL_LAYOUTS:
        raise InputError(f"{name}: the albedo maps' smoothness prior needs {flag('albedo')} "
                         f"{' or '.join(PER_PIXEL_LAYOUTS)} (got {albedo!r})")
    vals = list(value) if isinstance(value, (tuple, list)) else [value]
    if len(vals) not in (1, 2):
        raise InputError(f"{name}: expected tau or (tau_s, tau_b), got {value!r}")
    for v in vals:
        _num(name, v, lo=0.0, lo_incl=False, none_ok=False)


def check_input_options(*, black_level=0.0, conversion_gain=None, read_noise=None, irradiance=None,
                        fov=None, relight_irradiance=None, white_level=None, dark_level=None,
                        flag=lambda name: name, **_ignored):
    """Raise InputError for the first invalid option about the image and the light."""
    _num(flag("black_level"), black_level, lo=0.0)
    _num(flag("white_level"), white_level, lo=0.0, lo_incl=False)
    _num(flag("dark_level"), dark_level, lo=0.0)
    if white_level is not None and dark_level is not None and not dark_level < white_level:
        raise InputError(f"{flag('dark_level')} {dark_level:g} must be below {flag('white_level')} {white_level:g}")
    _num(flag("conversion_gain"), conversion_gain, lo=0.0, lo_incl=False)
    _num(flag("read_noise"), read_noise, lo=0.0)
    if (conversion_gain is None) != (read_noise is None):
        given, other = ("read_noise", "conversion_gain") if conversion_gain is None else \
            ("conversion_gain", "read_noise")
        raise InputError(f"{flag(given)} needs {flag(other)} too: the camera noise is known only "
                         "with both (electrons per image unit and read noise in electrons)")
    _num(flag("irradiance"), irradiance, lo=IRRADIANCE_RANGE[0], hi=IRRADIANCE_RANGE[1])
    _num(flag("relight_irradiance"), relight_irradiance, lo=IRRADIANCE_RANGE[0], hi=IRRADIANCE_RANGE[1])
    _num(flag("fov"), fov, lo=0.0, lo_incl=False, hi=180.0, hi_incl=False)
