"""Differentiable evaluation of a model's Stokes output at given pixels as :class:`Parts`, a prediction
being ``a_s * surface + a_b * body`` (paper: s_s + s_b): :class:`PixelEvaluator` calls ``bsdf.eval`` per pixel
of a normal map, :class:`RenderEvaluator` renders with the ``stokes`` integrator.  Stokes vectors are in the
camera's frame (x = image right perpendicular to the view, y = image up), as in :mod:`fmbrdf_mi.sensor.mosaic`."""
from __future__ import annotations

import dataclasses

import numpy as np

#: Variants in which fits run: monochrome (channels are averaged before the fit), polarised, AD; the CUDA one
#: evaluates the model on a GPU, the linear algebra stays in NumPy.
FIT_VARIANTS = ("llvm_ad_mono_polarized", "cuda_ad_mono_polarized")


def set_variant(variant=None):
    """Mitsuba set to ``variant`` (one of :data:`FIT_VARIANTS`) with the plugin registered.  None: the current
    variant where it is a fit variant (a caller's ``mi.set_variant`` chooses the device), else the LLVM one, or the
    CUDA one on a machine whose Dr.Jit has a CUDA backend and no LLVM backend."""
    import drjit as dr
    import mitsuba as mi

    if variant is None:
        variant = mi.variant()
        if variant not in FIT_VARIANTS:
            gpu_only = dr.has_backend(dr.JitBackend.CUDA) and not dr.has_backend(dr.JitBackend.LLVM)
            variant = FIT_VARIANTS[gpu_only]
    if mi.variant() != variant:
        mi.set_variant(variant)
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


@dataclasses.dataclass
class Parts:
    """The (S0, S1, S2) that the surface and the body term send to the camera at unit albedos under
    unpolarised light, each (3, n) float64, and their derivatives per shape parameter."""

    surface: np.ndarray
    body: np.ndarray
    d_surface: dict = dataclasses.field(default_factory=dict)
    d_body: dict = dataclasses.field(default_factory=dict)
    #: pixels where some derivative came out NaN / inf (the BSDF's AD has a few such directions: docs/computed.md)
    nonfinite: np.ndarray = None


#: Albedo that switches a term "off" (at exactly 0 a render's forward-mode derivatives all come out 0).
OFF = 1e-20
UNIT_ALBEDOS = ((1.0, OFF), (OFF, 1.0))


class _Evaluator:
    """Shared plumbing: a model's BSDF, its traversed parameters, albedo toggling."""

    def __init__(self, model, params, prefix=""):
        self.model = model
        self.params = params
        self.prefix = prefix
        self._current = {}
        self._chunk_geometry = None      # (chunk, its geometry) while :meth:`parts` evaluates that chunk

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

    def _points(self, chunk=None):  # -> the (S0, S1, S2) Dr.Jit arrays at the points of ``chunk`` (None: all)
        raise NotImplementedError

    def _reduce(self, s):     # the outputs of the values _points gives
        return s

    def _stokes(self, chunk=None):
        """The outputs (S0, S1, S2) of ``chunk`` as Dr.Jit arrays (the reverse-mode gradient differentiates them)."""
        return self._reduce(self._points(chunk))

    def _chunks(self):      # (chunk, slice of the outputs) pairs; one chunk (None) of everything
        return [(None, slice(None))]

    def parts(self, shape_values, wrt=()):
        """:class:`Parts` at ``shape_values`` with forward-mode derivatives in the shape parameters ``wrt``,
        evaluated chunk by chunk (:meth:`_chunks`) to bound the Dr.Jit arrays; a chunk's geometry is made once
        for both terms of each pass."""
        try:
            return self._parts(shape_values, wrt)
        finally:
            self._chunk_geometry = None

    def _parts(self, shape_values, wrt):
        import drjit as dr
        import mitsuba as mi

        self.set_shape(shape_values)
        chunks = self._chunks()
        parts = Parts(np.empty((3, self.n)), np.empty((3, self.n)))
        for chunk, sl in chunks:
            for out, a in zip((parts.surface, parts.body), UNIT_ALBEDOS):
                self.set_albedos(*a)
                s = self._points(chunk)
                dr.eval(s)
                s = self._reduce(s)
                dr.eval(s)
                for i, c in enumerate(s):
                    out[i, sl] = np.asarray(c, dtype=np.float64)
                del s
        if not wrt:
            return parts
        # one table build with gradients on all of ``wrt``, then per chunk one forward pass per parameter
        xs = {}
        for name in wrt:
            xs[name] = mi.Float(float(shape_values[name]))
            dr.enable_grad(xs[name])
            self._assign(self.model.param(name).key, xs[name])
            parts.d_surface[name], parts.d_body[name] = np.empty((3, self.n)), np.empty((3, self.n))
        self.params.update()
        for chunk, sl in chunks[::-1]:      # the last chunk first: its geometry is still held
            s_all = []
            for a in UNIT_ALBEDOS:
                self.set_albedos(*a)
                s_all.append(self._points(chunk))
            outputs = [c for s in s_all for c in s]
            g = {}
            for name in wrt:
                dr.set_grad(xs[name], 1.0)
                dr.forward_to(*outputs, flags=dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput)
                g[name] = [[dr.grad(c) for c in s] for s in s_all]
                for c in outputs:
                    dr.clear_grad(c)
            dr.eval(g)      # one kernel for all derivatives of the chunk
            g = {name: [self._reduce(tuple(s)) for s in g[name]] for name in wrt}
            dr.eval(g)
            for name in wrt:
                for d, s in zip((parts.d_surface[name], parts.d_body[name]), g[name]):
                    for i, c in enumerate(s):
                        d[i, sl] = np.asarray(c, dtype=np.float64)
            del g, outputs, s_all
        parts.nonfinite = ~np.all([np.isfinite(d).all(0) for n in wrt for d in (parts.d_surface[n], parts.d_body[n])],
                                  0)
        # detached values: no graph kept alive
        for name in wrt:
            self._assign(self.model.param(name).key, float(shape_values[name]))
            self._current[name] = float(shape_values[name])
        self.params.update()
        return parts


#: Directions made and converted to float32 at a time (:class:`Directions`), bounding the float64 arrays.
PIECE_DIRECTIONS = 1 << 18


class Directions:
    """``count`` normals and view directions made in float64 blocks by ``pieces()``, never all at once."""

    def __init__(self, count, pieces):
        self.count = int(count)
        self.pieces = pieces

    @classmethod
    def of(cls, normals, view_dirs):
        step = PIECE_DIRECTIONS
        return cls(len(normals), lambda: ((normals[a:a + step], view_dirs[a:a + step])
                                          for a in range(0, len(normals), step)))

    @classmethod
    def of_images(cls, geo):
        """(directions, each image's direction count, footprint weights (K,) or None) of ``geo``, (observation,
        flat pixels, footprint) per image (:meth:`~fmbrdf_mi.fit.inputs.observations.Observation.sample_geometry`)."""
        first = [o.sample_geometry(idx[:1] if len(idx) else [0], footprint=fp) for o, idx, fp in geo]
        per = [len(f[0]) for f in first]

        def pieces():
            for (o, idx, fp), k in zip(geo, per):
                step = max(1, PIECE_DIRECTIONS // k)
                for a in range(0, len(idx), step):
                    n, v, _ = o.sample_geometry(idx[a:a + step], footprint=fp)
                    yield n, v

        counts = [len(idx) * k for (_, idx, _), k in zip(geo, per)]
        w = first[-1][2]
        return cls(sum(counts), pieces), counts, None if len(w) == 1 else w


class PixelEvaluator(_Evaluator):
    """Per-pixel BSDF evaluation at normals ``(n, 3)`` and view directions ``(n, 3)`` (or a :class:`Directions`
    as ``normals``, ``view_dirs`` None) under one light direction, or one per direction (``light_dir`` (n, 3),
    ``irradiance`` (n,)).  With ``weights`` (K,) the directions are (n K, 3), K footprint samples per pixel
    summed with those weights."""

    #: Directions per BSDF evaluation (whole pixels).  A chunk with derivatives rebuilds the tables with every
    #: parameter's tangent (as much work as as many directions as the tables have texels): more than twice that.
    CHUNK_DIRECTIONS = 1 << 22

    def __init__(self, model, normals, view_dirs, light_dir, irradiance=1.0, variant=None, weights=None):
        mi = set_variant(variant)

        if isinstance(normals, Directions):
            if view_dirs is not None:
                raise ValueError("view_dirs: None when the normals are Directions (they hold both)")
            directions = normals
        else:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
            view_dirs = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
            if normals.shape != view_dirs.shape:
                raise ValueError(f"normals {normals.shape} and view_dirs {view_dirs.shape} differ in shape")
            directions = Directions.of(normals, view_dirs)
        n_dirs = directions.count
        light = np.asarray(light_dir, dtype=np.float64)
        light = light.reshape(3) if light.size == 3 else light.reshape(-1, 3)
        if light.ndim == 2 and light.shape != (n_dirs, 3):
            raise ValueError(f"light_dir {light.shape}: one direction, or one per normal ({n_dirs}, 3)")
        self.k = 1 if weights is None else len(weights)
        if n_dirs % self.k:
            raise ValueError(f"{n_dirs} directions are not a multiple of {self.k} samples per pixel")
        self.n = n_dirs // self.k
        self._w32 = None if self.k == 1 else np.asarray(weights, np.float32)
        bsdf = mi.load_dict(model.bsdf_dict())
        super().__init__(model, mi.traverse(bsdf))
        self.bsdf = bsdf
        irr = np.asarray(irradiance, dtype=np.float64)
        if irr.size == 1:
            self.irradiance = float(irr)
        elif irr.shape == (n_dirs,):
            self.irradiance = irr.astype(np.float32)
        else:
            raise ValueError(f"irradiance {irr.shape}: one value, or one per direction ({n_dirs},)")
        self.ctx = mi.BSDFContext()
        # unit length to float64 precision (a cosine above 1 gives NaN derivatives in the BSDF)
        self._store(directions, light / np.linalg.norm(light, axis=-1, keepdims=True), True)

    def set_geometry(self, normals, view_dirs, light):
        """Directions (unit, float64 arrays as in the constructor) of the same count; the BSDF is kept."""
        self._store(Directions.of(np.asarray(normals, dtype=np.float64), np.asarray(view_dirs, dtype=np.float64)),
                    np.asarray(light, dtype=np.float64), False)

    def _store(self, directions, light, normalise):
        """Store ``directions``' normals, views (``normalise``: to unit length), lights and camera x axes."""
        n_dirs = directions.count
        self._whole = None      # the Dr.Jit geometry of all pixels, kept when they are one chunk
        self._normals = np.empty((n_dirs, 3), np.float32)
        self._views = np.empty((n_dirs, 3), np.float32)
        self._xc = np.empty((n_dirs, 3), np.float32)
        self._light = light.astype(np.float32)
        ex = np.array([1.0, 0.0, 0.0])
        a = 0
        for n, v in directions.pieces():     # a piece that overruns the count fails to broadcast
            b = a + len(n)
            if normalise:
                n = n / np.linalg.norm(n, axis=1, keepdims=True)
                v = v / np.linalg.norm(v, axis=1, keepdims=True)
            self._normals[a:b] = n
            self._views[a:b] = v
            # the camera's Stokes x axis at each direction: image right, orthogonal to the view direction
            xc = ex[None, :] - (v @ ex)[:, None] * v
            bad = np.linalg.norm(xc, axis=1) < 1e-6
            xc[bad] = (0.0, 1.0, 0.0)
            xc /= np.linalg.norm(xc, axis=1, keepdims=True)
            self._xc[a:b] = xc
            a = b
        if a != n_dirs:
            raise ValueError(f"directions: the pieces hold {a} of the {n_dirs} directions announced")

    def _chunks(self):
        most = max(1, self.CHUNK_DIRECTIONS // self.k)
        if most >= self.n:
            return [(None, slice(None))]
        count = -(-self.n // most)
        ends = [self.n * i // count for i in range(count + 1)]  # chunks of (nearly) equal size
        return [((p0, p1), slice(p0, p1)) for p0, p1 in zip(ends[:-1], ends[1:])]

    def _geometry(self, chunk):
        """The Dr.Jit surface interactions, local light directions, camera-frame rotations, irradiances and
        footprint weights of the pixels ``chunk`` = (first, end); None: all pixels, kept for the next call."""
        import drjit as dr
        import mitsuba as mi

        if chunk is None and self._whole is not None:
            return self._whole
        if self._chunk_geometry is not None and self._chunk_geometry[0] == chunk:
            return self._chunk_geometry[1]
        self._chunk_geometry = None     # one chunk's geometry held at a time
        p0, p1 = (0, self.n) if chunk is None else chunk
        d = slice(p0 * self.k, p1 * self.k)
        n_dirs = (p1 - p0) * self.k

        def vec(x):
            return mi.Vector3f(np.ascontiguousarray(x.T))

        frame = mi.Frame3f(vec(self._normals[d]))
        si = dr.zeros(mi.SurfaceInteraction3f, n_dirs)
        si.sh_frame = frame
        si.n = frame.n
        si.wi = frame.to_local(vec(self._views[d]))
        lights = self._light[d] if self._light.ndim == 2 else np.tile(self._light, (n_dirs, 1))
        wo = frame.to_local(vec(lights))
        xl = frame.to_local(vec(self._xc[d]))
        rot = mi.mueller.rotate_stokes_basis(si.wi, mi.mueller.stokes_basis(si.wi), xl)
        rot = (rot[1, 1], rot[1, 2], rot[2, 1], rot[2, 2])
        irr = self.irradiance if isinstance(self.irradiance, float) else mi.Float(self.irradiance[d])
        w = None if self._w32 is None else mi.Float(np.tile(self._w32, p1 - p0))
        dr.eval(si, wo, rot, irr, w)
        if chunk is None and self.n * self.k <= self.CHUNK_DIRECTIONS:
            self._whole = (si, wo, rot, irr, w)
        else:
            self._chunk_geometry = (chunk, (si, wo, rot, irr, w))
        return si, wo, rot, irr, w

    def _points(self, chunk=None):
        """(S0, S1, S2) at every direction of ``chunk``, in the camera's Stokes frame, times the footprint weight."""
        si, wo, (r11, r12, r21, r22), irr, w = self._geometry(chunk)
        M = self.bsdf.eval(self.ctx, si, wo)
        s0, s1, s2 = (M[i, 0][0] * irr for i in range(3))   # M @ [1, 0, 0, 0], first channel
        s = (s0, r11 * s1 + r12 * s2, r21 * s1 + r22 * s2)  # in the camera's Stokes frame
        return s if w is None else tuple(c * w for c in s)

    def _reduce(self, s):
        """Each pixel's weighted sum over its K directions."""
        import drjit as dr

        return s if self.k == 1 else tuple(dr.block_sum(c, self.k) for c in s)


class RenderEvaluator(_Evaluator):
    """The model's BSDF at traverse prefix ``bsdf_prefix`` (e.g. ``"sphere.bsdf."``) of ``scene``, rendered
    with the ``stokes`` integrator at ``pixels`` (flat row-major indices); every render uses the same ``seed``
    and ``spp``, so the two parts add up to the full image exactly (reverse-mode gradients only)."""

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

    def _points(self, chunk=None):
        import drjit as dr
        import mitsuba as mi

        img = mi.render(self.scene, self.params, spp=self.spp, seed=self.seed)
        flat = img.array
        return tuple(dr.gather(mi.Float, flat, self._gather * self._nch + c) for c in self.channels)
