"""Differentiable evaluation of a model's Stokes output at given pixels: two paths, one BSDF.

Both evaluators return :class:`Parts`: the (S0, S1, S2) that the surface and the body term send to the
camera at unit albedos under unpolarised light, and their forward-mode derivatives in the shape parameters;
a prediction is ``a_s * surface + a_b * body`` (paper eq:fmbrdf).

* :class:`PixelEvaluator`: ``bsdf.eval`` per pixel from a normal map, no ray tracing (captured data).
* :class:`RenderEvaluator`: ``mi.render`` with the ``stokes`` integrator (synthetic scenes; reverse-mode
  gradients only, :func:`optimise.loss_and_grad_reverse`).

Stokes vectors are in the camera's frame (x = image right perpendicular to the view, y = image up), that
of the ``stokes`` integrator and :mod:`fmbrdf_mi.sensor.mosaic`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

#: Variant in which fits run: monochrome (channels are averaged before the fit), polarised, AD.
FIT_VARIANT = "llvm_ad_mono_polarized"


def set_variant(variant=None):
    import mitsuba as mi

    variant = variant or FIT_VARIANT
    if mi.variant() != variant:
        mi.set_variant(variant)
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


@dataclasses.dataclass
class Parts:
    """Stokes (S0, S1, S2) at unit albedos, each (3, n) float64; derivatives per shape parameter."""

    surface: np.ndarray
    body: np.ndarray
    d_surface: dict = dataclasses.field(default_factory=dict)
    d_body: dict = dataclasses.field(default_factory=dict)
    #: pixels where some derivative came out NaN / inf (the BSDF's AD has a few such directions: docs/computed.md)
    nonfinite: np.ndarray = None


#: Albedo that switches a term "off".  Not 0: with k_s exactly 0 the forward-mode derivatives of a render
#: come out 0 (body included); 1e-20 is 0 to float32 precision.
OFF = 1e-20


UNIT_ALBEDOS = ((1.0, OFF), (OFF, 1.0))


class _Evaluator:
    """Shared plumbing: a model's BSDF, its traversed parameters, albedo toggling."""

    def __init__(self, model, params, prefix=""):
        self.model = model
        self.params = params
        self.prefix = prefix
        self._current = {}

    def _assign(self, key, value):
        import mitsuba as mi

        self.params[self.prefix + key] = mi.Float(value) if isinstance(value, (int, float)) else value

    def set_shape(self, values):
        """Set shape parameters (only those that changed: each change of an FMBRDF one rebuilds its table)."""
        changed = False
        for p in self.model.shape:
            v = float(values[p.name])
            if self._current.get(p.name) != v:
                self._assign(p.key, v)
                self._current[p.name] = v
                changed = True
        if changed:
            self.params.update()

    def set_albedos(self, a_s, a_b):
        self._assign(self.model.surface_key, float(a_s))
        self._assign(self.model.body_key, float(a_b))
        self.params.update()

    def _stokes(self):  # -> (S0, S1, S2) Dr.Jit Float arrays
        raise NotImplementedError

    def parts(self, shape_values, wrt=()):
        """:class:`Parts` at ``shape_values``; derivatives for the shape parameters in ``wrt``."""
        import drjit as dr
        import mitsuba as mi

        self.set_shape(shape_values)
        out = []
        for a in UNIT_ALBEDOS:
            self.set_albedos(*a)
            s = self._stokes()
            dr.eval(s)
            out.append(np.stack([np.asarray(c, dtype=np.float64) for c in s]))
        parts = Parts(out[0], out[1])
        if not wrt:
            return parts
        # one table build with gradients on all of ``wrt``, then one forward pass per parameter
        xs = {}
        for name in wrt:
            xs[name] = mi.Float(float(shape_values[name]))
            dr.enable_grad(xs[name])
            self._assign(self.model.param(name).key, xs[name])
        self.params.update()
        s_all = []
        for a in UNIT_ALBEDOS:
            self.set_albedos(*a)
            s_all.append(self._stokes())
        outputs = [c for s in s_all for c in s]
        g = {}
        for name in wrt:
            dr.set_grad(xs[name], 1.0)
            dr.forward_to(*outputs, flags=dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput)
            g[name] = [[dr.grad(c) for c in s] for s in s_all]
            for c in outputs:
                dr.clear_grad(c)
        dr.eval(g)      # one kernel for all derivatives
        for name in wrt:
            grads = [np.stack([np.asarray(c, dtype=np.float64) for c in s]) for s in g[name]]
            parts.d_surface[name], parts.d_body[name] = grads
            bad = ~(np.all(np.isfinite(grads[0]), 0) & np.all(np.isfinite(grads[1]), 0))
            parts.nonfinite = parts.nonfinite | bad if parts.nonfinite is not None else bad
        del g
        del outputs, s_all
        # detached values: no graph kept alive
        for name in wrt:
            self._assign(self.model.param(name).key, float(shape_values[name]))
            self._current[name] = float(shape_values[name])
        self.params.update()
        return parts


class PixelEvaluator(_Evaluator):
    """Per-pixel BSDF evaluation at normals ``(n, 3)``, view directions ``(n, 3)`` and one light direction.

    With ``weights`` (K,) the directions are (n K, 3), K footprint samples per pixel
    (:meth:`Observation.sample_geometry`) summed with those weights.  ``light_dir`` (n K, 3) and
    ``irradiance`` (n K,) give one light per direction (:mod:`fmbrdf_mi.fit.api.joint`).
    """

    def __init__(self, model, normals, view_dirs, light_dir, irradiance=1.0, variant=None, weights=None):
        mi = set_variant(variant)
        import drjit as dr

        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        view_dirs = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
        light = np.asarray(light_dir, dtype=np.float64)
        light = light.reshape(3) if light.size == 3 else light.reshape(-1, 3)
        if normals.shape != view_dirs.shape:
            raise ValueError(f"normals {normals.shape} and view_dirs {view_dirs.shape} differ in shape")
        if light.ndim == 2 and light.shape != normals.shape:
            raise ValueError(f"light_dir {light.shape}: one direction, or one per normal {normals.shape}")
        # unit length to float64 precision (a cosine above 1 gives NaN derivatives in the BSDF)
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        view_dirs = view_dirs / np.linalg.norm(view_dirs, axis=1, keepdims=True)
        light = light / np.linalg.norm(light, axis=-1, keepdims=True)
        self.k = 1 if weights is None else len(weights)
        if len(normals) % self.k:
            raise ValueError(f"{len(normals)} directions are not a multiple of {self.k} samples per pixel")
        self.n = len(normals) // self.k
        n_dirs = len(normals)
        self._w = None if self.k == 1 else mi.Float(np.tile(np.asarray(weights, np.float32), self.n))
        bsdf = mi.load_dict(model.bsdf_dict())
        super().__init__(model, mi.traverse(bsdf))
        self.bsdf = bsdf
        irr = np.asarray(irradiance, dtype=np.float64)
        if irr.size == 1:
            self.irradiance = float(irr)
        elif irr.shape == (n_dirs,):
            self.irradiance = mi.Float(irr.astype(np.float32))
        else:
            raise ValueError(f"irradiance {irr.shape}: one value, or one per direction ({n_dirs},)")
        self.ctx = mi.BSDFContext()
        self.set_geometry(normals, view_dirs, light)
        if not isinstance(self.irradiance, float):
            dr.eval(self.irradiance)

    def set_geometry(self, normals, view_dirs, light):
        """Directions (unit, float64 arrays as in the constructor) of the same count; the BSDF is kept."""
        import drjit as dr
        import mitsuba as mi

        n_dirs = len(normals)
        frame = mi.Frame3f(mi.Vector3f(np.ascontiguousarray(normals.T, dtype=np.float32)))
        si = dr.zeros(mi.SurfaceInteraction3f, n_dirs)
        si.sh_frame = frame
        si.n = frame.n
        si.wi = frame.to_local(mi.Vector3f(np.ascontiguousarray(view_dirs.T, dtype=np.float32)))
        lights = light if light.ndim == 2 else np.tile(light, (n_dirs, 1))
        self.wo = frame.to_local(mi.Vector3f(np.ascontiguousarray(lights.T, dtype=np.float32)))
        self.si = si
        # the camera's Stokes x axis at each direction: image right, orthogonal to the view direction
        ex = np.array([1.0, 0.0, 0.0])
        xc = ex[None, :] - (view_dirs @ ex)[:, None] * view_dirs
        bad = np.linalg.norm(xc, axis=1) < 1e-6
        xc[bad] = (0.0, 1.0, 0.0)
        xc /= np.linalg.norm(xc, axis=1, keepdims=True)
        xl = frame.to_local(mi.Vector3f(np.ascontiguousarray(xc.T, dtype=np.float32)))
        rot = mi.mueller.rotate_stokes_basis(si.wi, mi.mueller.stokes_basis(si.wi), xl)
        self._rot = (rot[1, 1], rot[1, 2], rot[2, 1], rot[2, 2])
        dr.eval(self.si, self.wo, self._rot)

    def _stokes(self):
        import drjit as dr

        M = self.bsdf.eval(self.ctx, self.si, self.wo)
        s0, s1, s2 = (M[i, 0][0] * self.irradiance for i in range(3))   # M @ [1, 0, 0, 0], first channel
        r11, r12, r21, r22 = self._rot
        s = (s0, r11 * s1 + r12 * s2, r21 * s1 + r22 * s2)  # in the camera's Stokes frame
        if self._w is None:
            return s
        return tuple(dr.block_sum(c * self._w, self.k) for c in s)


class RenderEvaluator(_Evaluator):
    """The model's BSDF inside a Mitsuba scene, rendered with the ``stokes`` integrator.

    ``scene``: a loaded scene (``stokes`` integrator) whose object has the model's BSDF at traverse prefix
    ``bsdf_prefix`` (e.g. ``"sphere.bsdf."``); ``pixels``: flat row-major indices to return.  Every render
    uses the same ``seed`` and ``spp``, so the two parts add up to the full image exactly.
    """

    def __init__(self, model, scene, bsdf_prefix, pixels=None, spp=16, seed=0, variant=None):
        mi = set_variant(variant)
        import drjit as dr

        params = mi.traverse(scene)
        prefix = bsdf_prefix if bsdf_prefix.endswith(".") else bsdf_prefix + "."
        for k in (model.surface_key, model.body_key) + tuple(p.key for p in model.shape):
            if prefix + k not in params:
                raise ValueError(f"scene: no parameter {prefix + k!r}; is the object's BSDF a "
                                 f"{model.name!r} with k_b (not r_k) given?")
        super().__init__(model, params, prefix)
        self.scene, self.spp, self.seed = scene, int(spp), int(seed)
        img = mi.render(scene, spp=self.spp, seed=self.seed)
        film = scene.sensors()[0].film()
        names = [f.name for f in film.bitmap().struct_()]
        self.shape = tuple(img.shape[:2])
        idx = {n: i for i, n in enumerate(names)}
        cols = [c for c in ("R", "G", "B", "Y") if f"S0.{c}" in idx]
        if not cols:
            raise ValueError(f"scene: the film has no Stokes channels ({names}); use the 'stokes' integrator")
        # monochrome variants write S*.R/G/B with equal values: R is enough
        self.channels = [idx[f"S{k}.{cols[0]}"] for k in range(3)]
        npix = self.shape[0] * self.shape[1]
        self.pixels = np.arange(npix) if pixels is None else np.asarray(pixels, dtype=np.int64)
        self.n = len(self.pixels)
        self._gather = mi.UInt32(self.pixels.astype(np.uint32))
        self._nch = img.shape[2]
        dr.eval(self._gather)

    def parts(self, shape_values, wrt=()):
        if wrt:
            raise NotImplementedError(
                "render path: forward-mode derivatives through mi.render are wrong for the fmbrdf BSDF "
                "(the body term's contribution is missing: d/d kappa comes out 0), so the "
                "Levenberg-Marquardt Jacobian is not available here; use the reverse-mode gradient "
                "(optimizer 'adam'), which agrees with finite differences")
        return super().parts(shape_values)

    def _stokes(self):
        import drjit as dr
        import mitsuba as mi

        img = mi.render(self.scene, self.params, spp=self.spp, seed=self.seed)
        flat = img.array
        return tuple(dr.gather(mi.Float, flat, self._gather * self._nch + c) for c in self.channels)
