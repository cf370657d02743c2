"""The mean length of a noisy 2-vector (the Rice distribution), for the DoLP a noisy camera measures.

A camera measures the linear Stokes components (S1, S2) with independent
noise of standard deviation sigma in each; the length of the noisy vector
it reports, L, follows a Rice distribution whose mean is larger than the
true length nu:

    E[L] = sigma sqrt(pi / 2) L_{1/2}(-nu^2 / (2 sigma^2))
         = sigma sqrt(pi / 2) [(1 + 2y) i0e(y) + 2y i1e(y)],   y = nu^2 / (4 sigma^2),

with i0e, i1e the exponentially scaled modified Bessel functions
(i0e(y) = exp(-y) I0(y)).  Its derivative follows from
d/dt L_{1/2}(-t) = (1/2) exp(-t/2) (I0(t/2) + I1(t/2)):

    dE[L]/dnu = sqrt(pi / 2) nu / (2 sigma) (i0e(y) + i1e(y)),

which tends to 1 as nu / sigma grows.  The Bessel functions use the
polynomial approximations of Abramowitz & Stegun 9.8.1-9.8.4 (relative
error below 1e-6), written with operators only so that the same code runs
on NumPy arrays and on Dr.Jit arrays (which differentiate through it).
"""
from __future__ import annotations

import math

import numpy as np

_SMALL_I0 = (1.0, 3.5156229, 3.0899424, 1.2067492, 0.2659732, 0.0360768, 0.0045813)


_SMALL_I1 = (0.5, 0.87890594, 0.51498869, 0.15084934, 0.02658733, 0.00301532, 0.00032411)


_LARGE_I0 = (0.39894228, 0.01328592, 0.00225319, -0.00157565, 0.00916281, -0.02057706, 0.02635537,
             -0.01647633, 0.00392377)


_LARGE_I1 = (0.39894228, -0.03988024, -0.00362018, 0.00163801, -0.01031555, 0.02282967, -0.02895312,
             0.01787654, -0.00420059)


_C = math.sqrt(math.pi / 2.0)


def _poly(coeffs, x):
    acc = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        acc = acc * x + c
    return acc


def _i01e(y, where, sqrt, exp):
    """(exp(-y) I0(y), exp(-y) I1(y)) for y >= 0."""
    small = y < 3.75
    ys = where(small, y, 3.75)             # each branch evaluated where it is valid
    yl = where(small, 3.75, y)
    t2 = (ys / 3.75) ** 2
    e = exp(-ys)
    i0_small = _poly(_SMALL_I0, t2) * e
    i1_small = _poly(_SMALL_I1, t2) * ys * e
    u = 3.75 / yl
    r = 1.0 / sqrt(yl)
    return (where(small, i0_small, _poly(_LARGE_I0, u) * r),
            where(small, i1_small, _poly(_LARGE_I1, u) * r))


#: sigma is raised to at least this fraction of nu: the mean then differs from
#: nu by less than (1e-4)^2 / 2 relative, and y stays finite in float32.
SIGMA_FLOOR = 1e-4


def _y(nu, sigma, maximum):
    s = maximum(sigma, SIGMA_FLOOR * nu)
    return s, nu * nu / (4.0 * s * s)


def mean_length(nu, sigma):
    """E[L] (NumPy): the mean measured length of a vector of true length ``nu`` > 0 (``sigma`` per component)."""
    nu = np.asarray(nu, dtype=np.float64)
    s, y = _y(nu, np.asarray(sigma, dtype=np.float64), np.maximum)
    i0, i1 = _i01e(y, np.where, np.sqrt, np.exp)
    return s * _C * ((1.0 + 2.0 * y) * i0 + 2.0 * y * i1)


def mean_length_derivative(nu, sigma):
    """dE[L]/dnu (NumPy)."""
    nu = np.asarray(nu, dtype=np.float64)
    s, y = _y(nu, np.asarray(sigma, dtype=np.float64), np.maximum)
    i0, i1 = _i01e(y, np.where, np.sqrt, np.exp)
    return _C * nu / (2.0 * s) * (i0 + i1)


def mean_length_dr(nu, sigma):
    """E[L] for Dr.Jit arrays (differentiable in ``nu`` > 0)."""
    import drjit as dr

    s, y = _y(nu, sigma, dr.maximum)
    i0, i1 = _i01e(y, dr.select, dr.sqrt, dr.exp)
    return s * _C * ((1.0 + 2.0 * y) * i0 + 2.0 * y * i1)
