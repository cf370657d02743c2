"""Table coordinates over the polar angle and the azimuth difference.

The body tables (body.py) are read at (x(phi), x(theta_L), x(theta_V)) in
[0, 1]^3 and the 1-D tables over a polar angle (the grazing factors, the
projected area P of distribution.py) at x(theta); their nodes sit uniformly
in x.  eval computes x from the cosines it has (and |sin phi|) with square
roots and a few products, without inverse trigonometric functions (which
cost eval about a tenth of pplastic's time, docs/benchmarks.md):

* polar: s = sqrt(1 - cos theta) = sqrt(2) sin(theta / 2) in [0, 1],
  b = (s + a s^3) / (1 + a) (a = 0.138 makes b nearly proportional to
  theta: db/dtheta is the same at the pole and at grazing), then the warp w
  below with k = THETA_K;
* azimuth (phi in [0, pi], the tables' range): u = sqrt(2) sin(phi/2 - pi/4)
  in [-1, 1], which is -+sqrt(1 - sin phi) = -cos phi / sqrt(1 + sin phi)
  (the form eval uses: no cancellation near phi = pi/2),
  b = (1 + (u + a u^3) / (1 + a)) / 2 (nearly
  proportional to phi for the same reason), then w with k = PHI_K;
* w(b) = (1 - sqrt(1 - k b)) / (1 - sqrt(1 - k)): node spacing in b
  proportional to sqrt(1 - k b), sqrt(1 - k) times as fine at b = 1 as at 0.

So the polar spacing near grazing (where Fresnel transmittance and masking
change fastest) is 0.12 of that at the pole, and the azimuthal spacing near
forward scattering (phi = pi, where a large kappa makes the body term of
grazing directions fall steeply: light must leave through a facet near the
one it entered by, and the facets both grazing directions see shrink to a
band) 0.14 of that at phi = 0.  The constants were chosen by the table's
interpolation error against the direct quadrature (docs/benchmarks.md,
"Evaluation"); the nodes (the inverse maps, NumPy float64) solve the cubic
in closed form.
"""
import functools
import math

import drjit as dr
import numpy as np

#: cubic term of the polar and azimuthal base coordinates b
CUBIC = 0.138
#: warp constants k of w(b), polar and azimuthal
THETA_K = 0.9856
PHI_K = 0.98


def _warp(b, k):
    return (1.0 - dr.sqrt(1.0 - k * b)) * (1.0 / (1.0 - math.sqrt(1.0 - k)))


def _unwarp(x, k):
    """Inverse of :func:`_warp` (NumPy)."""
    r = 1.0 - np.asarray(x, dtype=np.float64) * (1.0 - math.sqrt(1.0 - k))
    return (1.0 - r * r) / k


def _cubic(t):
    return (t + CUBIC * t * t * t) * (1.0 / (1.0 + CUBIC))


def _uncubic(y):
    """The real root t of t + a t^3 = (1 + a) y (NumPy; Cardano, one real root for a > 0)."""
    q = -(1.0 + CUBIC) * np.asarray(y, dtype=np.float64) / CUBIC
    p = 1.0 / CUBIC
    disc = np.sqrt(0.25 * q * q + p ** 3 / 27.0)
    return np.cbrt(-0.5 * q + disc) + np.cbrt(-0.5 * q - disc)


def x_of_cos_theta(cos_theta):
    """x(theta) from cos(theta) (Dr.Jit arrays or Python floats), clamped to [0, 1]."""
    s = dr.sqrt(1.0 - dr.clip(cos_theta, 0.0, 1.0))
    return _warp(_cubic(s), THETA_K)


def x_of_theta(theta):
    return x_of_cos_theta(dr.cos(theta))


def theta_of_x(x):
    """Polar angles (NumPy float64) at table coordinates ``x``: the inverse of :func:`x_of_cos_theta`."""
    s = np.clip(_uncubic(_unwarp(x, THETA_K)), 0.0, 1.0)
    return 2.0 * np.arcsin(s * math.sqrt(0.5))


def x_of_cos_phi(cos_phi, sin_phi):
    """x(phi) for phi in [0, pi] given as cos(phi) and sin(phi) (its sign ignored)."""
    # u = -+sqrt(1 - sin phi), written without the cancellation of 1 - sin phi near phi = pi/2
    u = dr.clip(-cos_phi * dr.rsqrt(1.0 + dr.minimum(dr.abs(sin_phi), 1.0)), -1.0, 1.0)
    return _warp(0.5 + 0.5 * _cubic(u), PHI_K)


def x_of_phi(phi):
    return x_of_cos_phi(dr.cos(phi), dr.sin(phi))


def phi_of_x(x):
    """Azimuths in [0, pi] (NumPy float64) at table coordinates ``x``: the inverse of :func:`x_of_cos_phi`."""
    u = np.clip(_uncubic(2.0 * _unwarp(x, PHI_K) - 1.0), -1.0, 1.0)
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
