"""The ``fmbrdf`` Mitsuba 3 BSDF: Mitsuba plumbing around :mod:`fmbrdf_mi.model`.

eval() returns what Mitsuba expects of a BSDF: the BRDF times cos(theta) of
the light direction, as a Mueller matrix mapping the Stokes basis of the
incident direction (Mitsuba's ``stokes_basis(-wo)`` in radiance mode) to that
of the outgoing one (``stokes_basis(wi)``), both in the local shading frame.
That quantity is exactly the paper's s_s / E_o and s_b / E_o.
"""
import math
import struct

import drjit as dr
import mitsuba as mi

from . import params as P
from .model.body import BodyGrid, body_tables, table_x_of_phi, table_x_of_theta
from .model.distribution import Distribution
from .model.interp import PackedTetraTable
from .model.fresnel import reflection_mueller_terms
from .model.sampling import MicrofacetSampler

_SCALARS = ("eta", "alpha", "beta", "kappa")
#: Compact tables: which channels of body.CHANNELS go into each 64-bit word of
#: a texel, with their bits (interp.PackedTetraTable).  log M00 gets 20 bits,
#: what unpolarised light sees besides (M10, M20) 16, the rest 12-13.
PACKING = (((0, 20), (3, 16), (6, 16), (1, 12)), ((2, 13), (4, 13), (5, 13), (7, 13), (8, 12)))
_PROPERTIES = _SCALARS + ("k_s", "k_b", "r_k", "tables")
#: Values of the string property ``tables`` (see :meth:`_rebuild`).
TABLE_MODES = ("compact", "float32")
#: Builds without gradients kept per BSDF (the most recently used), for parameter values that come back
#: (a fit's Jacobian builds the tables with gradients, then again at the same values without).
TABLES_KEPT = 2


def _scalar_value(x):
    if isinstance(x, (int, float)):  # scalar variants
        return float(x)
    arr = dr.detach(x)
    if dr.width(arr) != 1:
        raise P.ParameterError(f"fmbrdf: parameters must be single numbers, got an array of width {dr.width(arr)}")
    return arr[0]


def _keep(x):
    """A new reference to the variable of ``x`` (same JIT and AD index), or its value."""
    try:
        return type(x)(x)
    except Exception:
        return x


def _fingerprint(x):
    """What identifies the variable behind a parameter: (JIT index, AD index), or the value."""
    if isinstance(x, (int, float)):
        return float(x)
    return (x.index, x.index_ad)


class _Watch(dr.CustomOp):
    """Identity on a parameter that calls ``on_use`` when an AD pass goes through it.

    The tables are built from watched copies of the parameters: after a
    ``dr.backward``/``dr.forward`` has traversed them, Dr.Jit has cleared the
    edges between the parameters and the tables, so the tables must be rebuilt
    before their derivatives are used again.
    """

    def eval(self, x, on_use):
        self.on_use = on_use
        return type(x)(x)

    def forward(self):
        self.on_use()
        self.set_grad_out(self.grad_in("x"))

    def backward(self):
        self.on_use()
        self.set_grad_in("x", self.grad_out())

    def name(self):
        return "fmbrdf_watch"


def texture_values(tex):
    """Values of an albedo texture, for validation.

    The texture is evaluated on a 32 x 32 grid of uv (and, in spectral
    variants, across the visible range): spectral variants store an RGB value
    as upsampling coefficients, which may be negative for a valid reflectance.
    In RGB and mono variants the stored values are checked too (exhaustive for
    bitmaps).
    """
    import numpy as np

    n = 32 if dr.is_jit_v(mi.Float) else 8  # scalar variants evaluate one point per call
    with dr.suspend_grad():
        if dr.is_jit_v(mi.Float):
            idx = dr.arange(mi.UInt32, n * n)
            points = [dr.zeros(mi.SurfaceInteraction3f, n * n)]
            points[0].uv = mi.Point2f((mi.Float(idx % n) + 0.5) / n, (mi.Float(idx // n) + 0.5) / n)
        else:
            idx = 0
            points = []
            for i in range(n * n):
                points.append(dr.zeros(mi.SurfaceInteraction3f))
                points[-1].uv = mi.Point2f((i % n + 0.5) / n, (i // n + 0.5) / n)
        for k, si in enumerate(points):
            if mi.is_spectral:
                frac = lambda j: (lambda x: x - dr.floor(x))((idx + k) * 0.6180339887 + 0.25 * j)
                si.wavelengths = mi.UnpolarizedSpectrum(*[360.0 + 470.0 * frac(j) for j in range(4)])
        out = [np.asarray(tex.eval(si), dtype=np.float64).ravel() for si in points]
        if not mi.is_spectral:
            params = mi.traverse(tex)
            for key in params.keys():
                try:
                    out.append(np.asarray(dr.detach(params[key]), dtype=np.float64).ravel())
                except Exception:  # non-numeric parameters
                    pass
    return np.concatenate(out)


def _axis(v, fallback=(1.0, 0.0, 0.0)):
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-14
    if not isinstance(fallback, tuple):
        return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), fallback)
    return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), mi.Vector3f(*fallback))


def _s_axis(H, V):
    """s axis of reflection off a facet with normal H towards V: normal to the plane of
    H and V.  For H parallel to V (retro-reflection, where the plane is undefined)
    any axis perpendicular to V gives the same Mueller matrix (at normal facet
    incidence R_s = R_p); the one normal to the plane of V and the macro normal is
    taken, and (1, 0, 0) when V is the macro normal too."""
    fallback = _axis(mi.Vector3f(-V.y, V.x, 0.0))  # z x V
    return _axis(dr.cross(H, V), fallback)


def _rotation(forward, current, target):
    """(cos 2t, sin 2t) of ``mi.mueller.rotate_stokes_basis(forward, current, target)``
    for unit axes normal to ``forward``, without trigonometric functions."""
    c = dr.dot(current, target)
    s = dr.dot(forward, dr.cross(current, target))
    return c * c - s * s, 2.0 * c * s


def _rotate_block(M, out_rot, in_rot):
    """R_out M R_in^T for the 3x3 linear block M (list of rows), as
    ``mi.mueller.rotate_mueller_basis`` does for the whole matrix."""
    co, so = out_rot
    ci, si = in_rot
    r0, r1, r2 = M
    r1, r2 = ([co * a + so * b for a, b in zip(r1, r2)], [co * b - so * a for a, b in zip(r1, r2)])
    return [[row[0], ci * row[1] + si * row[2], ci * row[2] - si * row[1]] for row in (r0, r1, r2)]


def _unit_xy(v):
    """Azimuthal unit vector (cos phi, sin phi) of ``v``; (1, 0) at the pole."""
    r2 = v.x * v.x + v.y * v.y
    ok = r2 > 1e-14
    inv = dr.rsqrt(dr.select(ok, r2, 1.0))
    return dr.select(ok, v.x * inv, 1.0), dr.select(ok, v.y * inv, 0.0)


class _FMBRDFMethods:
    """Fresnel Microfacet BRDF (``fmbrdf``; Ichikawa et al., CVPR 2023).

    Surface and body reflection from the same mirror microfacets: a polarimetric
    Torrance-Sparrow surface lobe with a generalised-normal facet distribution,
    and the body term (Fresnel transmission, depolarising subsurface scattering,
    re-transmission over vMF-correlated facets) by quadrature, tabulated once
    per parameter change.  ``eval`` returns the Mueller matrix in polarised
    variants and its intensity element in the others.

    .. list-table:: Parameters
       :header-rows: 1
       :widths: 12 48 12 18

       * - name
         - meaning
         - default
         - valid range
       * - ``eta``
         - index of refraction μ (float)
         - 1.5
         - (1, 3]
       * - ``alpha``
         - roughness α of D(θ) ∝ exp(−(θ/α)^β), radians (float)
         - 0.3
         - [0.01, π/2]
       * - ``beta``
         - shape β of the generalised normal distribution (float)
         - 2.0
         - [0.4, 5]
       * - ``kappa``
         - von Mises–Fisher microfacet correlation κ (float)
         - 10
         - [0, 100]
       * - ``k_s``
         - surface albedo: float, spectrum or texture
         - 1.0
         - ≥ 0
       * - ``r_k`` *or* ``k_b``
         - body albedo as the ratio k_b / k_s (the paper's r_k), or directly
         - r_k = 1.0
         - ≥ 0
       * - ``tables``
         - storage of the body tables: ``compact`` or ``float32`` (a string, not a
           material parameter)
         - ``compact``
         -

    Every parameter but ``tables`` is differentiable and exposed by
    ``mi.traverse`` (``eta``, ``alpha``, ``beta``, ``kappa``, ``k_s.value``,
    ``r_k.value`` or ``k_b.value``).  A bad value raises
    :class:`fmbrdf_mi.ParameterError`, at load time and in ``params.update()``,
    which then restores the last valid state.

    Its methods become a subclass of the ``mi.BSDF`` of the
    current variant in :func:`make_plugin_class`: each variant has its own base
    class, and nanobind types take a single base.
    """

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        unknown = [k for k in props.keys() if k not in _PROPERTIES]
        if unknown:
            raise P.ParameterError(f"fmbrdf: unknown property '{unknown[0]}'; expected some of "
                                   f"{', '.join(_PROPERTIES)}")
        for name in ("k_s", "k_b", "r_k"):  # RGB values: checked before spectral upsampling hides a NaN
            if name in props and props.type(name) == mi.Properties.Type.Color:
                P.check_albedo(name, list(props.get(name)))
        self.polarized = mi.is_polarized
        self.table_mode = props.get("tables", "compact") if "tables" in props else "compact"
        if self.table_mode not in TABLE_MODES:
            raise P.ParameterError(f"fmbrdf: 'tables' = {self.table_mode!r} is not one of {', '.join(TABLE_MODES)}")
        for name in _SCALARS:
            default = P.SCALAR_PARAMS[name][0]
            value = props.get(name, default) if (name in props) else default
            setattr(self, name, mi.Float(P.check_scalar(name, value)))
        self.k_s = props.get_unbounded_texture("k_s", P.DEFAULT_K_S)
        if ("k_b" in props) and ("r_k" in props):
            raise P.ParameterError("fmbrdf: give the body albedo as 'k_b' or as 'r_k' (= k_b / k_s), not both")
        self.body_key = "k_b" if ("k_b" in props) else "r_k"
        self.body = props.get_unbounded_texture(self.body_key, P.DEFAULT_R_K)
        self.grid = BodyGrid()
        self._tables_cache = {}  # _build: {_cache_key: (dist, table, factors, sampler)}
        self.m_components = [mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
                             mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide]
        self.m_flags = self.m_components[0] | self.m_components[1]
        self._check_albedos()
        self._build()
        self._save_state()

    # ------------------------------------------------------------ parameters
    def traverse(self, callback):
        for name in _SCALARS:
            callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)
        callback.put("k_s", self.k_s, mi.ParamFlags.Differentiable)
        callback.put(self.body_key, self.body, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        """Validate, rebuild the tables if needed; on a bad value restore the last valid state.

        Every parameter (the four scalars and the albedo textures' own
        parameters) goes back to the values of the last successful load or
        update, so the BSDF keeps evaluating what it did before and later
        valid updates work; then the ParameterError is raised.
        """
        try:
            for name in _SCALARS:
                P.check_scalar(name, _scalar_value(getattr(self, name)), single=True)
            self._check_albedos()
            if not keys or any(k in _SCALARS for k in keys) or self._tables_stale():
                self._build()
        except BaseException:
            self._restore_state()
            raise
        self._save_state()

    def _save_state(self):
        """Remember the current (valid) parameters: references to their variables."""
        self._valid = {name: _keep(getattr(self, name)) for name in _SCALARS}
        self._valid_textures = {}
        for attr in ("k_s", "body"):
            tp = mi.traverse(getattr(self, attr))
            self._valid_textures[attr] = {k: _keep(tp[k]) for k in tp.keys()}

    def _restore_state(self):
        """Put back the parameters saved by :meth:`_save_state` (in place: traverse() holds them)."""
        for name, value in self._valid.items():
            cur = getattr(self, name)
            if isinstance(cur, (int, float)):
                setattr(self, name, value)
            else:
                mi.set_property(cur, value)
        for attr, values in self._valid_textures.items():
            tp = mi.traverse(getattr(self, attr))
            for k, v in values.items():
                try:
                    tp[k] = v
                except Exception:  # read-only or non-Mitsuba parameters
                    pass
            tp.update()
        if self._tables_stale():
            self._build()

    def _build(self):
        """:meth:`_rebuild`, remembering which variables the tables were built from.

        The references kept in ``_built_from`` stop Dr.Jit from reusing their
        JIT and AD indices, so that any later change of a parameter (its value,
        or its AD variable after ``dr.disable_grad``/``dr.enable_grad``) gives a
        new index: Mitsuba's change detection then calls parameters_changed, and
        :meth:`_tables_stale` sees it too.  With gradients enabled, the tables
        are built from watched copies (:class:`_Watch`) that mark them as used
        up once an AD pass has gone through them.  Without gradients, the last
        :data:`TABLES_KEPT` builds are kept by the exact values they came from
        (:meth:`_cache_key`) and reused when the parameters return to those
        values: they are what a new build would compute, bit for bit.
        """
        originals = {name: getattr(self, name) for name in _SCALARS}
        jit = dr.is_jit_v(mi.Float)
        if jit:
            dr.make_opaque(*originals.values())
        watch = jit and any(dr.grad_enabled(x) for x in originals.values())
        self._ad_used = False
        key = None if watch else self._cache_key(originals)
        cache = self._tables_cache
        if key in cache:
            cache[key] = cache.pop(key)  # most recently used last
            self.dist, self.table, self.factors, self.sampler = cache[key]
        else:
            if watch:
                def used():
                    self._ad_used = True

                for name, x in originals.items():
                    setattr(self, name, dr.custom(_Watch, x, used) if dr.grad_enabled(x) else x)
            try:
                self._rebuild()
            finally:
                for name, x in originals.items():
                    setattr(self, name, x)
            if key is not None:
                cache[key] = (self.dist, self.table, self.factors, self.sampler)
                while len(cache) > TABLES_KEPT:
                    cache.pop(next(iter(cache)))
        self._built_from = {name: _keep(x) for name, x in originals.items()}
        self._stale_warned = False

    def _cache_key(self, values):
        """What the tables are a function of when no parameter has gradients: the four values (their
        exact bits: the tables are a deterministic function of them), the storage and the resolution."""
        g = self.grid
        bits = tuple(struct.pack("<d", _scalar_value(values[name])) for name in _SCALARS)
        return bits, self.table_mode, self.polarized, (g.n_theta, g.n_phi, g.table, g.n_factor)

    def _tables_stale(self):
        """Whether the tables no longer belong to the parameters' current variables."""
        built = getattr(self, "_built_from", None)
        if built is None:
            return True
        return self._ad_used or any(_fingerprint(getattr(self, n)) != _fingerprint(built[n]) for n in _SCALARS)

    def _ensure_fresh(self):
        """Rebuild stale tables before an evaluation (a parameter's variable changed without
        params.update(), or an AD pass used up the tables' graph).  Inside a symbolic
        region (a render) nothing can be evaluated: warn once instead."""
        if not self._tables_stale():
            return
        if dr.is_jit_v(mi.Float) and dr.flag(dr.JitFlag.SymbolicScope):
            if not self._stale_warned:
                self._stale_warned = True
                mi.Log(mi.LogLevel.Warn,
                       "fmbrdf: eta/alpha/beta/kappa changed, or an AD pass used up the graph of the "
                       "tables, since they were built, and they cannot be rebuilt inside a render: "
                       "derivatives with respect to them from this render are incomplete. Call "
                       "params.set_dirty(KEY) and params.update() before rendering again.")
            return
        self.parameters_changed(list(_SCALARS))

    def _check_albedos(self):
        P.check_albedo("k_s", texture_values(self.k_s))
        P.check_albedo(self.body_key, texture_values(self.body))

    def _rebuild(self):
        """Everything that depends on (eta, alpha, beta, kappa) only (paper sec. 3-4)."""
        if not dr.is_jit_v(mi.Float):
            return self._rebuild_scalar()
        # opaque: a new parameter value must not be baked into (and recompile) every kernel
        dr.make_opaque(self.eta, self.alpha, self.beta, self.kappa)
        self.dist = Distribution(mi.Float, self.alpha, self.beta)
        compact = (self.table_mode == "compact" and self.polarized
                   and not dr.grad_enabled(self.eta, self.alpha, self.beta, self.kappa))
        self.table, self.factors = body_tables(self.dist, self.eta, self.kappa, self.grid, self.polarized,
                                               planar=compact)
        if compact:
            # No derivatives wanted: the nine channels in fixed point over their own range, 16 bytes
            # a texel (interp.py), far finer than the interpolation error (docs/benchmarks/accuracy.md).
            # The 1-D factors go in pairs into 64-bit words.  With
            # gradients, or tables="float32", both stay float32 (smooth in the parameters to float32
            # rounding, which finite differences with small steps need).
            self.table = PackedTetraTable(self.table, PACKING)
            self.factors = self.factors.paired()
        with dr.suspend_grad():
            self.sampler = MicrofacetSampler(self.dist)
        dr.eval(self.dist.p_tab, self.dist.norm, self.table.values, self.table.orient, self.factors.values)

    def _rebuild_scalar(self):
        """Scalar variants: the tables are built with Dr.Jit's LLVM backend, then
        read from NumPy copies by the same lookup code."""
        from drjit.llvm.ad import Float

        dist = Distribution(Float, Float(self.alpha), Float(self.beta))
        table, factors = body_tables(dist, Float(self.eta), Float(self.kappa), self.grid, polarized=False)
        self.dist = dist.scalar_copy()
        self.table, self.factors = table.scalar_copy(), factors.scalar_copy()
        self.sampler = MicrofacetSampler(dist).scalar_copy(self.dist)

    # ------------------------------------------------------------ evaluation
    def _albedos(self, si, active):
        ks = self.k_s.eval(si, active)
        kb = self.body.eval(si, active)
        if self.body_key == "r_k":
            kb = kb * ks
        return ks, kb

    def _directions(self, ctx, si, wo):
        """(L, V): towards the light and towards the viewer, for either transport mode."""
        if ctx.mode == mi.TransportMode.Radiance:
            return wo, si.wi
        return si.wi, wo

    def table_coords(self, cos_l, cos_v, phi):
        """Coordinates in [0, 1]^3 of the body tables, in their axis order
        (x(phi), x(theta_L), x(theta_V)), for (cos theta_L, cos theta_V, |phi|)."""
        x_l = table_x_of_theta(dr.acos(dr.clip(cos_l, 0.0, 1.0)))
        x_v = table_x_of_theta(dr.acos(dr.clip(cos_v, 0.0, 1.0)))
        return table_x_of_phi(phi), x_l, x_v

    def body_ratios(self, cos_l, cos_v, phi):
        """The body matrix over k_b cos(theta_L) from the tables, in their bases (body.py):
        (M00, [M10, M20] / M00, [M01, M02, M11, M12, M21, M22] / M00), for
        (cos theta_L, cos theta_V, |phi|); the ratios are None when not polarised."""
        u = self.table_coords(cos_l, cos_v, phi)
        log_fl, d_l = self.factors.eval(u[1])
        log_fv, d_v = self.factors.eval(u[2])
        c = self.table.eval(*u)  # the channels of body.CHANNELS
        m00 = dr.exp(c[0] + log_fl + log_fv)
        if not self.polarized:
            return m00, None, None
        return m00, [c[3] + d_v, c[6]], [c[1] + d_l, c[2], c[4] + d_v * d_l, c[5], c[7], c[8]]

    def _surface(self, L, V, cos_o):
        """Surface reflection (eq:Torrance-Sparrow, sec. 4.2) times ``cos_o``: (scale, 3x3 block, M33)."""
        H = dr.normalize(L + V)
        p_l = self.dist.proj_area_lookup(L.z)
        p_v = self.dist.proj_area_lookup(V.z)
        # f cos_o = D G1(L) G1(V) cos_o / (4 N.L N.V), G1 = cos / P
        scale = self.dist.D(H) * cos_o / (4.0 * p_l * p_v)
        rp, rm, rc = reflection_mueller_terms(dr.dot(L, H), self.eta)
        if not self.polarized:
            return scale * rp, None, None
        M = [[rp, rm, 0.0], [rm, rp, 0.0], [0.0, 0.0, rc]]
        # from the s axes of the plane of reflection to Mitsuba's Stokes bases
        s_axis = _s_axis(H, V)  # = H x (-L) / |...| away from retro-reflection
        out_rot = _rotation(V, s_axis, mi.mueller.stokes_basis(V))
        in_rot = _rotation(-L, s_axis, mi.mueller.stokes_basis(-L))
        return scale, _rotate_block(M, out_rot, in_rot), rc

    def _body(self, L, V, cos_o):
        """Body reflection (eq:observed body reflection Stokes vector) times ``cos_o``: (scale, 3x3 block)."""
        lx, ly = _unit_xy(L)
        vx, vy = _unit_xy(V)
        sin_phi = lx * vy - ly * vx  # phi = phi_V - phi_L
        phi = dr.acos(dr.clip(lx * vx + ly * vy, -1.0, 1.0))
        m00, column, rest = self.body_ratios(L.z, V.z, phi)
        if not self.polarized:
            return cos_o * m00, None
        r10, r20 = column
        r01, r02, r11, r12, r21, r22 = rest
        flip = dr.select(sin_phi < 0, -1.0, 1.0)  # mirror image: s2 changes sign on one side
        M = [[1.0, r01, flip * r02], [r10, r11, flip * r12], [flip * r20, flip * r21, r22]]
        # table bases: s axes of the planes of incidence and exit
        x_in = mi.Vector3f(-ly, lx, 0.0)
        x_out = mi.Vector3f(-vy, vx, 0.0)
        out_rot = _rotation(V, x_out, mi.mueller.stokes_basis(V))
        in_rot = _rotation(-L, x_in, mi.mueller.stokes_basis(-L))
        return cos_o * m00, _rotate_block(M, out_rot, in_rot)

    def _eval_parts(self, ctx, si, wo, active):
        """Surface and body contributions: {name: (scale, 3x3 block or None, M33)}.

        The BRDF of light arriving from L seen from V, times cos(theta) of
        ``wo`` as Mitsuba's BSDFs return in either transport mode (``wo`` is L
        in radiance mode, V in importance mode)."""
        L, V = self._directions(ctx, si, wo)
        active = active & (L.z > 0) & (V.z > 0)
        out = {}
        if ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
            scale, M, m33 = self._surface(L, V, wo.z)
            out["spec"] = (dr.select(active, scale, 0.0), M, m33)
        if ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1):
            scale, M = self._body(L, V, wo.z)
            out["body"] = (dr.select(active, scale, 0.0), M, 0.0)
        return out

    def _combine(self, parts, si, active):
        ks, kb = self._albedos(si, active)
        weights = {"spec": ks, "body": kb}
        if not self.polarized:
            value = mi.UnpolarizedSpectrum(0.0)
            for name, (scale, _, _) in parts.items():
                value += weights[name] * scale
            return value
        width = max([dr.width(scale) for scale, _, _ in parts.values()] + [dr.width(si.wi)])
        result = dr.zeros(mi.Spectrum, width)  # elements not set below stay zero
        terms = [(weights[name] * scale, M, m33) for name, (scale, M, m33) in parts.items()]
        for i in range(3):
            for j in range(3):
                entry = mi.UnpolarizedSpectrum(0.0)
                for weight, M, _ in terms:
                    entry += weight * M[i][j]
                result[i, j] = entry
        entry = mi.UnpolarizedSpectrum(0.0)
        for weight, _, m33 in terms:
            entry += weight * m33
        result[3, 3] = entry
        return result

    def eval(self, ctx, si, wo, active=True):
        self._ensure_fresh()
        return self._combine(self._eval_parts(ctx, si, wo, active), si, active)

    # ------------------------------------------------------------ sampling
    def _spec_weight(self, ctx, si, active):
        has_spec = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)
        has_body = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1)
        if not has_body:
            return mi.Float(1.0)
        if not has_spec:
            return mi.Float(0.0)
        ks, kb = self._albedos(si, active)
        rp, _, _ = reflection_mueller_terms(dr.abs(si.wi.z), dr.detach(self.eta))
        es = dr.mean(dr.detach(ks)) * rp
        eb = dr.mean(dr.detach(kb)) * (1.0 - rp)
        return dr.clip(es / dr.maximum(es + eb, 1e-12), 0.1, 0.9)

    def _pdf(self, ctx, si, wo, active):
        w_s = self._spec_weight(ctx, si, active)
        cos_i, cos_o = si.wi.z, wo.z
        active = active & (cos_i > 0) & (cos_o > 0)
        H = dr.normalize(wo + si.wi)
        pdf_s = self.sampler.pdf(H.z) / (4.0 * dr.abs(dr.dot(wo, H)))
        pdf_b = cos_o * (1.0 / math.pi)
        return dr.select(active, w_s * pdf_s + (1.0 - w_s) * pdf_b, 0.0)

    def pdf(self, ctx, si, wo, active=True):
        self._ensure_fresh()
        return self._pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        self._ensure_fresh()
        return self.eval(ctx, si, wo, active), self._pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        self._ensure_fresh()
        w_s = self._spec_weight(ctx, si, active)
        active = active & (si.wi.z > 0)
        pick_spec = sample1 < w_s
        hx, hy, hz = self.sampler.sample(sample2.x, sample2.y)
        H = mi.Vector3f(hx, hy, hz)
        wo_spec = 2.0 * dr.dot(si.wi, H) * H - si.wi
        wo_body = mi.warp.square_to_cosine_hemisphere(sample2)
        bs = mi.BSDFSample3f()
        bs.wo = dr.select(pick_spec, wo_spec, wo_body)
        bs.eta = 1.0
        bs.sampled_component = dr.select(pick_spec, mi.UInt32(0), mi.UInt32(1))
        bs.sampled_type = dr.select(pick_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        active = active & (bs.wo.z > 0)
        value, bs.pdf = self.eval_pdf(ctx, si, bs.wo, active)
        active = active & (bs.pdf > 0)
        bs.pdf = dr.select(active, bs.pdf, 0.0)
        weight = value * dr.select(active, dr.rcp(dr.select(active, bs.pdf, 1.0)), 0.0)
        return bs, weight

    def to_string(self):
        vals = ", ".join(f"{n}={_scalar_value(getattr(self, n)):g}" for n in _SCALARS)
        return f"FMBRDF[{vals}, k_s={self.k_s}, {self.body_key}={self.body}]"


_classes = {}


def make_plugin_class():
    """The ``fmbrdf`` BSDF class for the current Mitsuba variant."""
    variant = mi.variant()
    if variant not in _classes:
        body = {k: v for k, v in vars(_FMBRDFMethods).items() if k not in ("__dict__", "__weakref__")}
        _classes[variant] = type("FMBRDF", (mi.BSDF,), body)
    return _classes[variant]
