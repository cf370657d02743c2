"""Importance sampling of the generalised-normal microfacet normal (surface lobe).

The slope-area density p(m) = D(m) cos(theta_m) (unit mass by the
normalisation of D) has no closed-form inverse, so its polar marginal is
tabulated on bins equispaced in the PolarMap variable u.  Inside a bin the
sampled density is uniform in cos(theta), i.e. piecewise constant per solid
angle, and ``pdf`` returns exactly the density ``sample`` draws from.  Bin
edges are kept as v = 1 - cos(theta) = 2 sin^2(theta/2) to stay accurate in
float32 when alpha is small.
"""
import math

import drjit as dr
import numpy as np

from .interp import gather
from .quadrature import gauss_legendre, gennormal_unnormalised


class MicrofacetSampler:
    N_BINS = 512
    N_SUB = 4

    def __init__(self, dist):
        Float = dist.Float
        UInt = dr.uint32_array_t(Float)
        self.Float, self.dist = Float, dist
        with dr.suspend_grad():
            n, s = self.N_BINS, self.N_SUB
            x, w = gauss_legendre(s)
            idx = dr.arange(UInt, n * s)
            k, j = idx // s, idx % s
            u = (Float(k) + dr.gather(Float, Float(x), j)) / n
            th = dist.map.theta(u)
            f = (dr.gather(Float, Float(w), j) / n * dist.map.dtheta_du(u) * dr.sin(th) * dr.cos(th)
                 * gennormal_unnormalised(th, dist.alpha, dist.beta))
            mass = dr.block_sum(f, s)
            mass = mass / dr.sum(mass)
            cdf = dr.cumsum(mass)
            self.cdf = dr.concat([Float(0.0), cdf / dr.gather(Float, cdf, UInt(n - 1))])
            edges = dist.map.theta(dr.linspace(Float, 0.0, 1.0, n + 1))
            self.v_edges = 2.0 * dr.square(dr.sin(0.5 * edges))
            dr.eval(self.cdf, self.v_edges)

    def scalar_copy(self, dist):
        """A copy for Python floats (scalar variants), drawing on ``dist.scalar_copy()``."""
        out = object.__new__(MicrofacetSampler)
        out.Float, out.dist = float, dist
        out.cdf = np.asarray(dr.detach(self.cdf), dtype=np.float64)
        out.v_edges = np.asarray(dr.detach(self.v_edges), dtype=np.float64)
        return out

    def sample(self, xi1, xi2):
        """Microfacet normal (local frame) from two uniform variates."""
        Float, UInt = self.Float, dr.uint32_array_t(self.Float)
        n = self.N_BINS
        k = dr.binary_search(0, n - 1, lambda i: gather(Float, self.cdf, i + 1) <= xi1)
        k = dr.minimum(k, n - 1)
        c0 = gather(Float, self.cdf, k)
        c1 = gather(Float, self.cdf, k + 1)
        t = dr.clip((xi1 - c0) / dr.maximum(c1 - c0, 1e-30), 0.0, 1.0)
        v0 = gather(Float, self.v_edges, k)
        v1 = gather(Float, self.v_edges, k + 1)
        v = v0 + t * (v1 - v0)
        cos_t = 1.0 - v
        sin_t = dr.safe_sqrt(v * (2.0 - v))
        s, c = dr.sincos(2.0 * math.pi * xi2)
        return c * sin_t, s * sin_t, cos_t

    def pdf(self, cos_theta):
        """Density per solid angle of ``sample`` at a normal with cos(theta) = ``cos_theta``."""
        Float, UInt = self.Float, dr.uint32_array_t(self.Float)
        n = self.N_BINS
        th = dr.acos(dr.clip(cos_theta, -1.0, 1.0))
        u = self.dist.map.u_of_theta(th)
        inside = (cos_theta > 0) & (u < 1.0)
        k = dr.minimum(UInt(dr.maximum(u * n, 0.0)), n - 1)
        mass = gather(Float, self.cdf, k + 1) - gather(Float, self.cdf, k)
        dv = gather(Float, self.v_edges, k + 1) - gather(Float, self.v_edges, k)
        return dr.select(inside & (dv > 0), mass / (2.0 * math.pi * dr.maximum(dv, 1e-30)), 0.0)
