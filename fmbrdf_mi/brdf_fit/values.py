"""Unpolarised FMBRDF values f(w_in, w_out) for many direction pairs, through the ``fmbrdf`` plugin.

The unpolarised BRDF is the Mueller element M00 of the paper's model
(eq:Torrance-Sparrow for the surface term, eq:observed body reflection Stokes
vector for the body term), i.e. what the plugin's ``eval`` returns in M00
divided by the cosine Mitsuba multiplies in: eval = f * cos(theta) of the
light direction (``wo`` in radiance mode).  It is evaluated with the same
tables the plugin renders with (float32 tables, as the image fits use), in
the fit variant, one Dr.Jit kernel for all pairs.
"""
from __future__ import annotations

import numpy as np

#: Mitsuba component flags of the two terms.
_TERMS = ("surface", "body")


class FMBRDFValues:
    """The surface and body BRDF values at unit albedos for fixed direction pairs.

    ``w_in`` (towards the light) and ``w_out`` (towards the viewer): (n, 3)
    arrays in the local frame (z = normal), both above the surface.
    """

    def __init__(self, w_in, w_out):
        import drjit as dr

        from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

        mi = self.mi = set_variant()
        w_in = np.asarray(w_in, dtype=np.float64)
        w_out = np.asarray(w_out, dtype=np.float64)
        if w_in.shape != w_out.shape or w_in.ndim != 2 or w_in.shape[1] != 3:
            raise ValueError(f"directions: expected two (n, 3) arrays, got {w_in.shape} and {w_out.shape}")
        if (w_in[:, 2] <= 0).any() or (w_out[:, 2] <= 0).any():
            raise ValueError("directions: every pair must be above the surface (z > 0)")
        self.n = len(w_in)
        self.cos_in = w_in[:, 2]
        self.si = dr.zeros(mi.SurfaceInteraction3f, self.n)
        self.si.wi = mi.Vector3f(*(mi.Float(w_out[:, k].astype(np.float32)) for k in range(3)))
        self.wo = mi.Vector3f(*(mi.Float(w_in[:, k].astype(np.float32)) for k in range(3)))
        self.bsdf = mi.load_dict({"type": "fmbrdf", "k_s": 1.0, "k_b": 1.0, "tables": "float32"})
        self.params = mi.traverse(self.bsdf)
        self._shape = None
        self.ctx = {}
        for name, flag in zip(_TERMS, (mi.BSDFFlags.GlossyReflection, mi.BSDFFlags.DiffuseReflection)):
            ctx = mi.BSDFContext()
            ctx.type_mask = +flag
            self.ctx[name] = ctx

    def set_shape(self, shape):
        """Set (eta, alpha, beta, kappa) (a dict); rebuilds the tables when they changed."""
        vals = tuple(float(shape[k]) for k in ("eta", "alpha", "beta", "kappa"))
        if vals != self._shape:
            for k, v in zip(("eta", "alpha", "beta", "kappa"), vals):
                self.params[k] = v
            self.params.update()
            self._shape = vals

    def parts(self, shape):
        """(surface, body): BRDF values (1/sr) at unit albedos, each (n,) float64."""
        self.set_shape(shape)
        out = []
        for name in _TERMS:
            v = self.bsdf.eval(self.ctx[name], self.si, self.wo)
            m00 = np.asarray(v[0, 0] if self.mi.is_polarized else v, dtype=np.float64).reshape(-1)
            out.append(m00 / self.cos_in)
        return tuple(out)
