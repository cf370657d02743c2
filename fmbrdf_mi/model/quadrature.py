"""Quadrature rules adapted to the generalised-normal microfacet distribution.

The distribution D(theta) = c exp(-(theta/alpha)^beta) (paper eq:gennormal)
ranges from a spike of width 0.02 rad at the pole to an almost flat lobe over
the hemisphere, with a cusp at the pole when beta < 1.  Polar angles are
therefore sampled through a map theta(u) = theta_cut sinh(lam u) / sinh(lam),
u in [0, 1]: nearly uniform when alpha is large, geometrically refined towards
the pole when alpha is small.  theta_cut is where D has fallen by e^-32 (or the
horizon), so no node is wasted where D vanishes.  All node positions and
weights are smooth Dr.Jit expressions of (alpha, beta): integrals computed with
them are differentiable in both.
"""
import functools
import math

import drjit as dr
import numpy as np

#: ln of the dynamic range of D kept inside theta_cut.
TAIL = 32.0


@functools.lru_cache(maxsize=None)
def _leggauss(n):
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = w.flags.writeable = False
    return x, w


_CONSTANTS = {}


def constant(Type, key, make):
    """``Type(make())`` (a Dr.Jit array or tensor type; ``make`` returns a NumPy
    array), made once per (Type, key) and kept: quadrature rules and transform
    matrices depend on resolutions only, and converting them anew on every
    table rebuild cost a good part of it."""
    k = (Type, key)
    if k not in _CONSTANTS:
        if len(_CONSTANTS) >= 256:  # callers with ever new keys (arbitrary azimuths) must not grow it
            _CONSTANTS.clear()
        arr = np.asarray(make(), dtype=np.float64)
        if dr.is_tensor_v(Type):
            value = Type(dr.array_t(Type)(arr.ravel()), shape=arr.shape)
        else:
            value = Type(arr)
        dr.eval(value)
        _CONSTANTS[k] = value
    return _CONSTANTS[k]


def gauss_legendre_array(Float, n):
    """:func:`gauss_legendre` on [0, 1] as Dr.Jit arrays (cached)."""
    return (constant(Float, ("gl_x", n), lambda: gauss_legendre(n)[0]),
            constant(Float, ("gl_w", n), lambda: gauss_legendre(n)[1]))


def gauss_legendre(n, a=0.0, b=1.0):
    """Gauss-Legendre nodes and weights on [a, b] (NumPy, float64).

    The rule of each order is computed once (an eigenvalue problem, which
    would otherwise dominate a table rebuild)."""
    x, w = _leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


class PolarMap:
    """theta(u) on [0, 1] for given (alpha, beta); see the module docstring."""

    def __init__(self, alpha, beta):
        self.theta_cut = dr.minimum(0.5 * math.pi, alpha * dr.power(TAIL, 1.0 / beta))
        self.lam = dr.log(1.0 + self.theta_cut / alpha)
        self.sinh_lam = dr.sinh(self.lam)

    def theta(self, u):
        return self.theta_cut * dr.sinh(self.lam * u) / self.sinh_lam

    def dtheta_du(self, u):
        return self.theta_cut * self.lam * dr.cosh(self.lam * u) / self.sinh_lam

    def u_of_theta(self, theta):
        return dr.asinh(theta / self.theta_cut * self.sinh_lam) / self.lam


def gennormal_unnormalised(theta, alpha, beta):
    """exp(-(theta/alpha)^beta): the shape of D (paper eq:gennormal).

    theta is clamped to >= 1e-30 (which changes no float32 value): at the pole
    d/dbeta of 0^beta is 0 * log(0), NaN in floating point, and a NaN
    derivative there would poison every gradient summed with it."""
    return dr.exp(-dr.power(dr.maximum(theta, 1e-30) / alpha, beta))
