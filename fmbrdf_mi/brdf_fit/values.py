"""Unpolarised FMBRDF values f(w_in, w_out) for many direction pairs, through the ``fmbrdf`` plugin.

The unpolarised BRDF is the Mueller element M00 of the paper's model
(eq:Torrance-Sparrow for the surface term, eq:observed body reflection Stokes
vector for the body term), i.e. what the plugin's ``eval`` returns divided by
the cosine Mitsuba multiplies in: eval = f * cos(theta) of the light direction
(``wo`` in radiance mode).  It is evaluated with the same tables the plugin
renders with (float32 tables, as the image fits use), one Dr.Jit kernel for
all pairs.

The plugin runs in the unpolarised AD variant :data:`VARIANT` (the fit
variant's LLVM backend, without polarisation), entered for each evaluation
and left again, so callers keep their variant (:func:`evaluation_variant`).
In it the body table holds only the log M00 channel (body.py,
:func:`fmbrdf_mi.model.body.body_tables` with ``polarized=False``): one ninth
of the Fourier series and of the synthesis of the polarised variant, the same
M00 (every element of the Mueller matrix is its own sum; the values of both
variants were compared bit for bit on 50 000 MERL direction pairs at four
parameter sets, tests/test_fit_brdf.py checks it), and a table build about three
times faster (10 ms against 32 ms on one core), which is most of the time of a
fit-brdf start grid (docs/benchmarks.md, Measured BRDFs).
"""
from __future__ import annotations

import contextlib

import numpy as np

#: Mitsuba variant of the evaluation: M00 only.
VARIANT = "llvm_ad_mono"

#: Mitsuba component flags of the two terms.
_TERMS = ("surface", "body")


@contextlib.contextmanager
def evaluation_variant(variant=VARIANT):
    """A context in ``variant`` (:data:`VARIANT`: M00 only), with the plugin registered there: yields the
    ``mitsuba`` module.

    The variant set before is set again on leaving (none was set: ``variant`` stays).  Nothing
    happens when ``variant`` is already set.  A switch costs as much as several table builds (Mitsuba
    rebinds its modules): callers that evaluate many times (:func:`.fitting.fit_brdf`)
    enter this once around all of it, and the methods of :class:`FMBRDFValues` then switch nothing."""
    import mitsuba as mi

    import fmbrdf_mi

    before = mi.variant()
    if before != variant:
        mi.set_variant(variant)
    try:
        fmbrdf_mi.register()
        yield mi
    finally:
        if before is not None and before != variant:
            mi.set_variant(before)


class FMBRDFValues:
    """The surface and body BRDF values at unit albedos for fixed direction pairs.

    ``w_in`` (towards the light) and ``w_out`` (towards the viewer): (n, 3)
    arrays in the local frame (z = normal), both above the surface.
    """

    def __init__(self, w_in, w_out):
        w_in = np.asarray(w_in, dtype=np.float64)
        w_out = np.asarray(w_out, dtype=np.float64)
        if w_in.shape != w_out.shape or w_in.ndim != 2 or w_in.shape[1] != 3:
            raise ValueError(f"directions: expected two (n, 3) arrays, got {w_in.shape} and {w_out.shape}")
        if (w_in[:, 2] <= 0).any() or (w_out[:, 2] <= 0).any():
            raise ValueError("directions: every pair must be above the surface (z > 0)")
        self.n = len(w_in)
        self.cos_in = w_in[:, 2]
        self._shape = None
        with self._variant() as mi:
            import drjit as dr

            self.si = dr.zeros(mi.SurfaceInteraction3f, self.n)
            self.si.wi = mi.Vector3f(*(mi.Float(w_out[:, k].astype(np.float32)) for k in range(3)))
            self.wo = mi.Vector3f(*(mi.Float(w_in[:, k].astype(np.float32)) for k in range(3)))
            self.bsdf = mi.load_dict({"type": "fmbrdf", "k_s": 1.0, "k_b": 1.0, "tables": "float32"})
            self.params = mi.traverse(self.bsdf)
            self.ctx = {}
            for name, flag in zip(_TERMS, (mi.BSDFFlags.GlossyReflection, mi.BSDFFlags.DiffuseReflection)):
                ctx = mi.BSDFContext()
                ctx.type_mask = +flag
                self.ctx[name] = ctx

    @staticmethod
    def _variant():
        return evaluation_variant()

    def _set_shape(self, shape):
        vals = tuple(float(shape[k]) for k in ("eta", "alpha", "beta", "kappa"))
        if vals != self._shape:
            for k, v in zip(("eta", "alpha", "beta", "kappa"), vals):
                self.params[k] = v
            self.params.update()
            self._shape = vals

    def set_shape(self, shape):
        """Set (eta, alpha, beta, kappa) (a dict); rebuilds the tables when they changed."""
        with self._variant():
            self._set_shape(shape)

    def parts(self, shape):
        """(surface, body): BRDF values (1/sr) at unit albedos, each (n,) float64."""
        with self._variant():
            self._set_shape(shape)
            out = []
            for name in _TERMS:
                v = self.bsdf.eval(self.ctx[name], self.si, self.wo)
                out.append(np.asarray(v, dtype=np.float64).reshape(-1) / self.cos_in)
        return tuple(out)
