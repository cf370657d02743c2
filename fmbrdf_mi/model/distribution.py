"""Microfacet distribution D, its normalisation and Smith masking (paper sec. 3.1).

* D(theta) = c exp(-(theta/alpha)^beta), with c fixed by the slope-area
  normalisation  int_Omega D(theta_m) cos(theta_m) d omega_m = 1.
* Smith's separable masking (Heitz 2014): G1(w) = chi+ / (1 + Lambda(w)) with
  1 + Lambda(w) = P(w) / cos(theta_w), where
  P(w) = int_Omega max(0, w.m) D(m) d omega_m  is the projected microfacet area.
  There is no closed form for the generalised normal; P is integrated
  numerically (the azimuthal part in closed form, the polar part by
  Gauss-Legendre split at the kink theta_m = pi/2 - theta_w) and tabulated.
  Tabulating P rather than Lambda keeps the table bounded at grazing angles,
  and G1(w)/cos(theta_w) = 1/P(w) is what the BRDF needs.
"""
import math

import drjit as dr
import numpy as np

from .interp import gather
from .quadrature import PolarMap, gauss_legendre_array, gennormal_unnormalised



def azimuthal_clamped_cosine(theta_m, theta_w):
    """int_0^{2pi} max(0, w.m) dphi for m at polar angle theta_m, w at theta_w.

    With a = sin sin >= 0, b = cos cos: 2 pi b where the whole circle is lit
    (b >= a), 0 where none of it is (b <= -a), else 2 (b phi0 + a sin phi0)
    with cos phi0 = -b / a.  The branches meet continuously, so the partial
    case is kept to |b| < a (1 - 1e-6) and fed harmless values elsewhere:
    reverse-mode AD multiplies an unselected branch's partial derivatives by
    a zero adjoint, and 0 * inf (from -b / a at a = 0, or acos' at +-1) is NaN.
    """
    a = dr.sin(theta_w) * dr.sin(theta_m)
    b = dr.cos(theta_w) * dr.cos(theta_m)
    edge = a * (1.0 - 1e-6)
    full, dark = b >= edge, b <= -edge
    part = ~(full | dark)
    ratio = dr.select(part, -b / dr.select(part, a, 1.0), 0.0)
    phi0 = dr.acos(ratio)
    partial = 2.0 * (b * phi0 + a * dr.sqrt(1.0 - ratio * ratio))
    return dr.select(full, 2.0 * math.pi * b, dr.select(dark, 0.0, partial))


class Distribution:
    """D, its normalisation constant and the projected-area table P for one (alpha, beta).

    ``Float`` is the Dr.Jit array type to compute with (it carries AD).
    """

    #: Gauss-Legendre order of the 1D normalisation integral.
    N_NORM = 256
    #: Gauss-Legendre order of each of the two pieces of the P integral.
    N_PROJ = 96
    #: Nodes of the P table over theta_w in [0, pi/2].
    N_PTAB = 257

    def __init__(self, Float, alpha, beta):
        self.Float, self.alpha, self.beta = Float, alpha, beta
        self.map = PolarMap(alpha, beta)
        u, w = gauss_legendre_array(Float, self.N_NORM)
        th = self.map.theta(u)
        integrand = gennormal_unnormalised(th, alpha, beta) * dr.sin(th) * dr.cos(th)
        self.norm = 1.0 / (2.0 * math.pi * dr.sum(w * self.map.dtheta_du(u) * integrand))
        self.theta_tab = np.linspace(0.0, 0.5 * math.pi, self.N_PTAB)
        self.p_tab = self.projected_area(Float(self.theta_tab))

    def D(self, m):
        """Normalised D at the microfacet normal ``m`` (local frame, unit length).

        The polar angle comes from atan2, not acos(m.z): in float32 acos loses
        all precision within 1e-3 rad of the pole, where D of a small alpha
        (and the cusp of beta < 1) changes fastest.
        """
        th = dr.atan2(dr.sqrt(m.x * m.x + m.y * m.y), m.z)
        return dr.select(m.z > 0, self.norm * gennormal_unnormalised(th, self.alpha, self.beta), 0.0)

    def projected_area(self, theta_w):
        """P(theta_w) = int max(0, w.m) D(m) d omega_m, evaluated by quadrature."""
        Float = self.Float
        n = self.N_PROJ
        u, w = gauss_legendre_array(Float, n)
        theta_w = Float(theta_w)
        m = dr.width(theta_w)
        # Split [0, theta_cut] at the kink of the azimuthal integral.
        u_k = dr.clip(self.map.u_of_theta(dr.clip(0.5 * math.pi - theta_w, 0.0, self.map.theta_cut)), 0.0, 1.0)
        idx = dr.arange(dr.uint32_array_t(Float), m * 2 * n)
        row = idx // (2 * n)
        col = idx % (2 * n)
        piece = col // n
        j = col % n
        uu = dr.gather(Float, u, j)
        ww = dr.gather(Float, w, j)
        uk = dr.gather(Float, u_k, row)
        lo = dr.select(piece == 0, 0.0, uk)
        hi = dr.select(piece == 0, uk, 1.0)
        us = lo + (hi - lo) * uu
        th = self.map.theta(us)
        tw = dr.gather(Float, theta_w, row)
        f = (ww * (hi - lo) * self.map.dtheta_du(us) * dr.sin(th)
             * gennormal_unnormalised(th, self.alpha, self.beta)
             * azimuthal_clamped_cosine(th, tw))
        return self.norm * dr.block_sum(f, 2 * n)

    def scalar_copy(self):
        """A copy whose D and proj_area_lookup take Python floats (scalar variants)."""
        out = object.__new__(Distribution)
        val = lambda x: float(np.asarray(dr.detach(x)).ravel()[0])
        out.Float, out.alpha, out.beta = float, val(self.alpha), val(self.beta)
        out.map = PolarMap(out.alpha, out.beta)
        out.norm = val(self.norm)
        out.theta_tab = self.theta_tab
        out.p_tab = np.asarray(dr.detach(self.p_tab), dtype=np.float64)
        return out

    def proj_area_lookup(self, cos_theta):
        """P at cos(theta_w) by linear interpolation in the table."""
        Float = self.Float
        th = dr.acos(dr.clip(cos_theta, 0.0, 1.0))
        x = th * ((self.N_PTAB - 1) / (0.5 * math.pi))
        i0 = dr.minimum(dr.uint32_array_t(Float)(dr.floor(x)), self.N_PTAB - 2)
        t = x - Float(i0)
        p0 = gather(Float, self.p_tab, i0)
        p1 = gather(Float, self.p_tab, i0 + 1)
        return dr.fma(t, p1 - p0, p0)
