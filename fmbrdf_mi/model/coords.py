"""Table coordinates over the polar angle and the azimuth difference.

The body tables (body.py) are read at (x(phi), x(theta_L), x(theta_V)) in
[0, 1]^3 and the 1-D table of the grazing factors at x(theta); their nodes
sit uniformly in x.  The projected area P of distribution.py is tabulated
uniformly in theta and read at b (below), nearly theta / (pi/2).  The warps
are those the tables were designed with:

* polar: theta = (pi/2) sin(A x) / sin(A), A = TABLE_WARP: near grazing,
  where Fresnel transmittance and masking change fastest, the spacing is
  cos(A) = 0.17 times the spacing at the pole;
* azimuth: phi = pi sin(B x) / sin(B), B = PHI_WARP: near forward scattering
  (phi = pi), where a large kappa makes the body term of grazing directions
  fall steeply (light must leave through a facet near the one it entered by,
  and the facets that both grazing directions see shrink to a band), the
  spacing is cos(B) = 0.12 times the spacing at phi = 0;

but eval computes them from the cosines it has (and |sin phi|) with square
roots and polynomials, without Dr.Jit's acos and asin:

* theta / (pi/2) and phi / pi become b = q(s) and (1 + q(u)) / 2, with
  s = sqrt(1 - cos theta) = sqrt(2) sin(theta/2), u = sqrt(2) sin(phi/2 - pi/4)
  = -cos phi / sqrt(1 + |sin phi|) (no cancellation near phi = pi/2), and q an
  odd polynomial of degree 9, q(1) = 1, within 5.8e-6 of
  (4/pi) asin(t / sqrt(2)), which is what they are in those variables;
* x = asin(sin(A) b) / A with the arcsine of Abramowitz and Stegun 4.4.46
  (a square root times a polynomial of degree 7, within 2e-8), rescaled to
  map [0, 1] onto [0, 1].

The nodes are the exact inverse of that map (NumPy, float64, Newton's method,
cached per resolution); they lie within 0.0012 cells of where the warps above
put them, so the tables interpolate what they did before.
"""
import functools
import math

import drjit as dr
import numpy as np

#: The warps: polar A, azimuthal B (see the module docstring).
TABLE_WARP = 1.4
PHI_WARP = 1.45
#: q(t) = t (Q1 + t^2 (Q3 + t^2 (Q5 + t^2 (Q7 + Q9 t^2)))), least squares to (4/pi) asin(t/sqrt(2))
#: on [0, 1] with q(1) = 1: within 5.8e-6 of it
Q1, Q3, Q5, Q7 = 0.9003404552800567, 0.07454516809133303, 0.019470885954750085, -0.00034929685336289453
Q9 = 1.0 - Q1 - Q3 - Q5 - Q7


def _q(t):
    t2 = t * t
    return t * (Q1 + t2 * (Q3 + t2 * (Q5 + t2 * (Q7 + Q9 * t2))))


def _dq(t):
    t2 = t * t
    return Q1 + t2 * (3.0 * Q3 + t2 * (5.0 * Q5 + t2 * (7.0 * Q7 + 9.0 * Q9 * t2)))


def _q_inverse(y):
    """The t in [-1, 1] with q(t) = y (NumPy float64, Newton's method; q is increasing)."""
    y = np.asarray(y, dtype=np.float64)
    t = y.copy()
    for _ in range(40):
        t = np.clip(t - (_q(t) - y) / _dq(t), -1.0, 1.0)
    return t


#: asin(z) ~ pi/2 - sqrt(1 - z) (S0 + S1 z + ... + S7 z^7) on [0, 1], within 2e-8 (Abramowitz and
#: Stegun 4.4.46): the warps' arcsine without Dr.Jit's asin
S = (1.5707963050, -0.2145988016, 0.0889789874, -0.0501743046, 0.0308918810, -0.0170881256, 0.0066700901,
     -0.0012624911)


def _asin_poly(z):
    poly = S[7]
    for c in S[6::-1]:
        poly = poly * z + c
    return poly


def _asin_approx(z):
    """Dr.Jit arrays or Python floats."""
    return 0.5 * math.pi - dr.sqrt(dr.maximum(1.0 - z, 0.0)) * _asin_poly(z)


def _asin_approx_np(z):
    return 0.5 * math.pi - np.sqrt(np.maximum(1.0 - z, 0.0)) * _asin_poly(z)


def _warp(b, w):
    """asin(sin(w) b) / w, normalised to map [0, 1] onto [0, 1] exactly (Dr.Jit arrays or Python
    floats): within 2e-8 of the exact arcsine warp."""
    k = math.sin(w)
    lo, hi = _asin_approx(0.0), _asin_approx(k)
    return (_asin_approx(dr.clip(b, 0.0, 1.0) * k) - lo) * (1.0 / (hi - lo))


def _unwarp(x, w):
    """Inverse of :func:`_warp` (NumPy float64, Newton's method from the exact arcsine's inverse)."""
    x = np.asarray(x, dtype=np.float64)
    k = math.sin(w)
    f = lambda b: _asin_approx_np(k * b)
    lo, hi = f(0.0), f(1.0)
    b = np.clip(np.sin(w * x) / k, 0.0, 1.0)
    for _ in range(40):
        h = 1e-7
        g = (f(b) - lo) / (hi - lo) - x
        d = ((f(np.minimum(b + h, 1.0)) - f(np.maximum(b - h, 0.0))) / (np.minimum(b + h, 1.0) - np.maximum(b - h, 0.0))
             / (hi - lo))
        b = np.clip(b - g / d, 0.0, 1.0)
    return b


def b_of_cos_theta(cos_theta):
    """q(sqrt(1 - cos theta)): theta / (pi/2) to within 9e-6 rad (Dr.Jit arrays or Python
    floats), clamped to [0, 1]; the coordinate of tables with nodes uniform in theta."""
    return _q(dr.sqrt(1.0 - dr.clip(cos_theta, 0.0, 1.0)))


@functools.lru_cache(maxsize=8)
def uniform_theta_nodes(n):
    """``n`` polar angles uniform in b (NumPy, read-only): theta within 9e-6 rad of uniform in [0, pi/2]."""
    th = theta_of_b(np.linspace(0.0, 1.0, int(n)))
    th.flags.writeable = False
    return th


def theta_of_b(b):
    """Polar angles (NumPy float64) at ``b``: the inverse of :func:`b_of_cos_theta`."""
    s = np.clip(_q_inverse(np.asarray(b, dtype=np.float64)), 0.0, 1.0)
    return np.clip(2.0 * np.arcsin(s * math.sqrt(0.5)), 0.0, 0.5 * math.pi)


def x_of_cos_theta(cos_theta):
    """x(theta) from cos(theta) (Dr.Jit arrays or Python floats), clamped to [0, 1]."""
    return _warp(b_of_cos_theta(cos_theta), TABLE_WARP)


def x_of_theta(theta):
    return x_of_cos_theta(dr.cos(theta))


def theta_of_x(x):
    """Polar angles (NumPy float64) at table coordinates ``x``: the inverse of :func:`x_of_cos_theta`."""
    return theta_of_b(_unwarp(x, TABLE_WARP))


def x_of_cos_phi(cos_phi, sin_phi):
    """x(phi) for phi in [0, pi] given as cos(phi) and sin(phi) (its sign ignored)."""
    u = dr.clip(-cos_phi * dr.rsqrt(1.0 + dr.minimum(dr.abs(sin_phi), 1.0)), -1.0, 1.0)
    return _warp(0.5 + 0.5 * _q(u), PHI_WARP)


def x_of_phi(phi):
    return x_of_cos_phi(dr.cos(phi), dr.sin(phi))


def phi_of_x(x):
    """Azimuths in [0, pi] (NumPy float64) at table coordinates ``x``: the inverse of :func:`x_of_cos_phi`."""
    u = _q_inverse(2.0 * _unwarp(x, PHI_WARP) - 1.0)
    return np.clip(0.5 * math.pi + 2.0 * np.arcsin(u * math.sqrt(0.5)), 0.0, math.pi)


@functools.lru_cache(maxsize=32)
def _nodes(n_theta, n_phi):
    th, ph = theta_of_x(np.linspace(0.0, 1.0, n_theta)), phi_of_x(np.linspace(0.0, 1.0, n_phi))
    th.flags.writeable = ph.flags.writeable = False
    return th, ph


def table_angles(n_theta, n_phi):
    """Nodes uniform in x: theta in [0, pi/2] and phi in [0, pi], both ends included (NumPy, read-only)."""
    return _nodes(int(n_theta), int(n_phi))


def polar_nodes(n):
    """``n`` polar angles uniform in x (NumPy, read-only): the nodes of the 1-D tables."""
    return _nodes(int(n), 2)[0]
