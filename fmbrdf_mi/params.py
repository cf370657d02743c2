"""The six FMBRDF parameters: names, defaults, valid ranges and validation.

The ranges are those over which the implementation's accuracy was measured
(tools/check_accuracy.py); k_s and the body albedo are unbounded above because,
as in the paper's estimation, they absorb light irradiance and camera gain.
"""
import math

#: name -> (default, low, high, low_inclusive, description)
SCALAR_PARAMS = {
    "eta": (1.5, 1.0, 3.0, False, "index of refraction mu"),
    "alpha": (0.3, 0.01, 0.5 * math.pi, True, "roughness alpha (radians)"),
    "beta": (2.0, 0.4, 5.0, True, "shape beta of the generalised normal distribution"),
    "kappa": (10.0, 0.0, 100.0, True, "vMF microfacet correlation kappa"),
}
DEFAULT_K_S = 1.0
DEFAULT_R_K = 1.0


class ParameterError(ValueError):
    """A material parameter is outside its valid range or not a number."""


def range_text(name):
    _, lo, hi, lo_incl, _ = SCALAR_PARAMS[name]
    return f"{'[' if lo_incl else '('}{lo:g}, {hi:g}]"


def _f32(x):
    import numpy as np

    return float(np.float32(x))


def check_scalar(name, value, single=False):
    """Raise ParameterError unless ``value`` is a finite number in the range of ``name``.

    ``single``: ``value`` is stored in single precision (a ``mi.Float`` of a JIT
    variant).  Inclusive bounds are then compared in single precision too, so
    that the float32 rounding of a valid bound (alpha = 0.01 -> 0.0099999998,
    pi/2 -> 1.5707964) is accepted; a float32 value passes exactly when it is
    the rounding of some valid double.  Exclusive bounds stay strict.  Values
    given as doubles (load time, the command line) are checked as doubles.
    """
    _, lo, hi, lo_incl, desc = SCALAR_PARAMS[name]
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"fmbrdf: '{name}' ({desc}) must be a number, got {value!r}") from None
    if single:
        lo = _f32(lo) if lo_incl else lo
        hi = _f32(hi)
    ok = math.isfinite(v) and (v >= lo if lo_incl else v > lo) and v <= hi
    if not ok:
        raise ParameterError(
            f"fmbrdf: '{name}' ({desc}) = {v:g} is outside its valid range {range_text(name)}")
    return v


def check_albedo(name, values):
    """Raise ParameterError unless every value of an albedo is finite and >= 0."""
    import numpy as np

    arr = np.asarray(values, dtype=np.float64).ravel()
    bad = ~np.isfinite(arr) | (arr < 0)
    if bad.any():
        raise ParameterError(
            f"fmbrdf: '{name}' must be finite and >= 0 (valid range [0, inf)), got {arr[bad][0]:g}")
