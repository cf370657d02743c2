"""The Oren-Nayar body reflection model, as a BRDF of two directions.

M. Oren and S. K. Nayar, "Generalization of Lambert's Reflectance Model",
SIGGRAPH 1994, pp. 239-246 (and IJCV 14:227-251, 1995, the paper's
reference [Oren1995]): V-cavities of Lambertian facets whose slopes are
Gaussian with standard deviation ``sigma`` (radians), with masking,
shadowing and one bounce of interreflection.

Two forms (``form``):

* ``"full"``: the functional approximation of the SIGGRAPH paper, sec. 4,
  direct term plus interreflection term (E0 = irradiance at normal incidence)::

      L1 = rho/pi E0 cos(ti) [C1 + cos(dphi) C2 tan(b) + (1 - |cos(dphi)|) C3 tan((a + b)/2)]
      L2 = 0.17 rho^2/pi E0 cos(ti) s2/(s2 + 0.13) [1 - cos(dphi) (2 b/pi)^2]
      C1 = 1 - 0.5 s2/(s2 + 0.33)
      C2 = 0.45 s2/(s2 + 0.09) sin(a)                  if cos(dphi) >= 0
           0.45 s2/(s2 + 0.09) (sin(a) - (2 b/pi)^3)    otherwise
      C3 = 0.125 s2/(s2 + 0.09) (4 a b / pi^2)^2

  with s2 = sigma^2, a = max(ti, tr), b = min(ti, tr), dphi = phi_r - phi_i.
  The interreflection term is quadratic in rho.
* ``"qualitative"``: the simplified model of the same paper (sec. 4, the one
  most renderers implement), linear in rho::

      f = rho/pi [A + B max(0, cos(dphi)) sin(a) tan(b)],
      A = 1 - 0.5 s2/(s2 + 0.33),  B = 0.45 s2/(s2 + 0.09)

Both are symmetric in the two directions (reciprocal) and are exactly
Lambert (rho/pi) at sigma = 0.  The functions work on Dr.Jit arrays (and on
Python floats); directions are in the local frame (z = normal).
"""
import math

import drjit as dr

FORMS = ("full", "qualitative")


def _angles(wi, wo):
    """(cos dphi, sin a, tan b, a, b) of two upper-hemisphere directions (x, y, z).

    a = max(theta_i, theta_o), b = min(theta_i, theta_o).  cos dphi is set to 0
    when a direction is the normal, where it is undefined and every term it
    multiplies vanishes (b = 0)."""
    sin_i = dr.sqrt(dr.maximum(wi[0] * wi[0] + wi[1] * wi[1], 0.0))
    sin_o = dr.sqrt(dr.maximum(wo[0] * wo[0] + wo[1] * wo[1], 0.0))
    cos_i, cos_o = dr.maximum(wi[2], 0.0), dr.maximum(wo[2], 0.0)
    denom = sin_i * sin_o
    ok = denom > 1e-12
    cos_dphi = dr.select(ok, (wi[0] * wo[0] + wi[1] * wo[1]) / dr.select(ok, denom, 1.0), 0.0)
    cos_dphi = dr.clip(cos_dphi, -1.0, 1.0)
    sin_a = dr.maximum(sin_i, sin_o)
    sin_b = dr.minimum(sin_i, sin_o)
    cos_b = dr.maximum(cos_i, cos_o)
    tan_b = sin_b / dr.maximum(cos_b, 1e-12)
    a = dr.atan2(sin_a, dr.minimum(cos_i, cos_o))
    b = dr.atan2(sin_b, cos_b)
    return cos_dphi, sin_a, tan_b, a, b


def oren_nayar_terms(wi, wo, sigma, form="full"):
    """(direct, interreflection): the BRDF is ``rho * direct + rho**2 * interreflection``.

    ``direct`` is the SIGGRAPH 1994 L1 / (rho E0 cos ti) (full) or the
    qualitative model / rho; ``interreflection`` is L2 / (rho^2 E0 cos ti) for
    the full form and 0 for the qualitative one.  Zero below the horizon.
    """
    if form not in FORMS:
        raise ValueError(f"oren_nayar: form must be one of {', '.join(FORMS)}, got {form!r}")
    cos_dphi, sin_a, tan_b, a, b = _angles(wi, wo)
    s2 = sigma * sigma
    inv_pi = 1.0 / math.pi
    c1 = 1.0 - 0.5 * s2 / (s2 + 0.33)
    g = s2 / (s2 + 0.09)
    above = (wi[2] > 0) & (wo[2] > 0)
    if form == "qualitative":
        direct = inv_pi * (c1 + 0.45 * g * dr.maximum(cos_dphi, 0.0) * sin_a * tan_b)
        return dr.select(above, direct, 0.0), 0.0 * direct
    two_b_pi = 2.0 * b * inv_pi
    c2 = 0.45 * g * dr.select(cos_dphi >= 0, sin_a, sin_a - two_b_pi * two_b_pi * two_b_pi)
    four_ab = 4.0 * a * b * inv_pi * inv_pi
    c3 = 0.125 * g * four_ab * four_ab
    tan_mid = dr.tan(0.5 * (a + b))
    direct = inv_pi * (c1 + cos_dphi * c2 * tan_b + (1.0 - dr.abs(cos_dphi)) * c3 * tan_mid)
    inter = 0.17 * inv_pi * s2 / (s2 + 0.13) * (1.0 - cos_dphi * two_b_pi * two_b_pi)
    return dr.select(above, direct, 0.0), dr.select(above, inter, 0.0)


def oren_nayar_brdf(wi, wo, sigma, rho, form="full"):
    """The Oren-Nayar BRDF value f(wi, wo) (not times a cosine) for albedo ``rho``."""
    direct, inter = oren_nayar_terms(wi, wo, sigma, form)
    return rho * direct + rho * rho * inter
