"""The ``fmbrdf`` Mitsuba 3 BSDF: Mitsuba plumbing around :mod:`fmbrdf_mi.model`.

eval() returns what Mitsuba expects of a BSDF: the BRDF times cos(theta) of
the light direction, as a Mueller matrix mapping the Stokes basis of the
incident direction (Mitsuba's ``stokes_basis(-wo)`` in radiance mode) to that
of the outgoing one (``stokes_basis(wi)``), both in the local shading frame.
That quantity is exactly the paper's s_s / E_o and s_b / E_o.
"""
import math

import drjit as dr
import mitsuba as mi

from . import params as P
from .model.body import BodyGrid, body_tables, table_x_of_theta
from .model.distribution import Distribution
from .model.interp import PackedTetraTable
from .model.fresnel import reflection_mueller_terms
from .model.sampling import MicrofacetSampler

_SCALARS = ("eta", "alpha", "beta", "kappa")


def _scalar_value(x):
    if isinstance(x, (int, float)):  # scalar variants
        return float(x)
    arr = dr.detach(x)
    if dr.width(arr) != 1:
        raise P.ParameterError(f"fmbrdf: parameters must be single numbers, got an array of width {dr.width(arr)}")
    return arr[0]


def _texture_values(tex):
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
    return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), mi.Vector3f(*fallback))


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
    """Fresnel Microfacet BRDF (Ichikawa et al., CVPR 2023); see the README for parameters.

    Its methods become a subclass of the ``mi.BSDF`` of the
    current variant in :func:`make_plugin_class`: each variant has its own base
    class, and nanobind types take a single base.
    """

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        self.polarized = mi.is_polarized
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
        self.m_components = [mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
                             mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide]
        self.m_flags = self.m_components[0] | self.m_components[1]
        self._check_albedos()
        self._rebuild()

    # ------------------------------------------------------------ parameters
    def traverse(self, callback):
        for name in _SCALARS:
            callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)
        callback.put("k_s", self.k_s, mi.ParamFlags.Differentiable)
        callback.put(self.body_key, self.body, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        for name in _SCALARS:
            P.check_scalar(name, _scalar_value(getattr(self, name)))
        self._check_albedos()
        if not keys or any(k in _SCALARS for k in keys):
            self._rebuild()

    def _check_albedos(self):
        P.check_albedo("k_s", _texture_values(self.k_s))
        P.check_albedo(self.body_key, _texture_values(self.body))

    def _rebuild(self):
        """Everything that depends on (eta, alpha, beta, kappa) only (paper sec. 3-4)."""
        if not dr.is_jit_v(mi.Float):
            return self._rebuild_scalar()
        # opaque: a new parameter value must not be baked into (and recompile) every kernel
        dr.make_opaque(self.eta, self.alpha, self.beta, self.kappa)
        self.dist = Distribution(mi.Float, self.alpha, self.beta)
        self.primary, self.secondary = body_tables(self.dist, self.eta, self.kappa, self.grid, self.polarized)
        if self.polarized and not dr.grad_enabled(self.eta, self.alpha, self.beta, self.kappa):
            # No derivatives wanted: the response to polarised light in 16-bit fixed point (within
            # 3.1e-5 of M00), half the bytes for eval's random-access reads (interp.py).  What
            # unpolarised light sees (the primary table, all a fit uses) stays float32, so finite
            # differences of it remain as smooth as float32 allows.
            self.secondary = PackedTetraTable(self.secondary)
        with dr.suspend_grad():
            self.sampler = MicrofacetSampler(self.dist)
        tables = [self.primary.values] + ([self.secondary.values] if self.secondary else [])
        dr.eval(self.dist.p_tab, self.dist.norm, *tables)

    def _rebuild_scalar(self):
        """Scalar variants: the tables are built with Dr.Jit's LLVM backend, then
        read from NumPy copies by the same lookup code."""
        from drjit.llvm.ad import Float

        dist = Distribution(Float, Float(self.alpha), Float(self.beta))
        primary, _ = body_tables(dist, Float(self.eta), Float(self.kappa), self.grid, polarized=False)
        self.dist = dist.scalar_copy()
        self.primary, self.secondary = primary.scalar_copy(), None
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
        (phi / pi, x(theta_L), x(theta_V)), for (cos theta_L, cos theta_V, |phi|)."""
        x_l = table_x_of_theta(dr.acos(dr.clip(cos_l, 0.0, 1.0)))
        x_v = table_x_of_theta(dr.acos(dr.clip(cos_v, 0.0, 1.0)))
        return phi * (1.0 / math.pi), x_l, x_v

    def _surface(self, L, V):
        """Surface reflection (eq:Torrance-Sparrow, sec. 4.2): (scale, 3x3 block, M33)."""
        H = dr.normalize(L + V)
        p_l = self.dist.proj_area_lookup(L.z)
        p_v = self.dist.proj_area_lookup(V.z)
        scale = self.dist.D(H) * L.z / (4.0 * p_l * p_v)  # D G1(L) G1(V) / (4 N.V), G1 = cos/P
        rp, rm, rc = reflection_mueller_terms(dr.dot(L, H), self.eta)
        if not self.polarized:
            return scale * rp, None, None
        M = [[rp, rm, 0.0], [rm, rp, 0.0], [0.0, 0.0, rc]]
        # from the s axes of the plane of reflection to Mitsuba's Stokes bases
        out_rot = _rotation(V, _axis(dr.cross(H, V)), mi.mueller.stokes_basis(V))
        in_rot = _rotation(-L, _axis(dr.cross(H, -L)), mi.mueller.stokes_basis(-L))
        return scale, _rotate_block(M, out_rot, in_rot), rc

    def _body(self, L, V):
        """Body reflection (eq:observed body reflection Stokes vector): (scale, 3x3 block)."""
        lx, ly = _unit_xy(L)
        vx, vy = _unit_xy(V)
        sin_phi = lx * vy - ly * vx  # phi = phi_V - phi_L
        phi = dr.acos(dr.clip(lx * vx + ly * vy, -1.0, 1.0))
        u = self.table_coords(L.z, V.z, phi)
        primary = self.primary.eval(*u)
        m00 = dr.exp(primary[0])
        if not self.polarized:
            return L.z * m00, None
        r10, r20 = primary[1], primary[2]
        r01, r02, r11, r12, r21, r22 = self.secondary.eval(*u)
        flip = dr.select(sin_phi < 0, -1.0, 1.0)  # mirror image: s2 changes sign on one side
        M = [[1.0, r01, flip * r02], [r10, r11, flip * r12], [flip * r20, flip * r21, r22]]
        # table bases: s axes of the planes of incidence and exit
        x_in = mi.Vector3f(-ly, lx, 0.0)
        x_out = mi.Vector3f(-vy, vx, 0.0)
        out_rot = _rotation(V, x_out, mi.mueller.stokes_basis(V))
        in_rot = _rotation(-L, x_in, mi.mueller.stokes_basis(-L))
        return L.z * m00, _rotate_block(M, out_rot, in_rot)

    def _eval_parts(self, ctx, si, wo, active):
        """Surface and body contributions: {name: (scale, 3x3 block or None, M33)}."""
        L, V = self._directions(ctx, si, wo)
        active = active & (L.z > 0) & (V.z > 0)
        out = {}
        if ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
            scale, M, m33 = self._surface(L, V)
            out["spec"] = (dr.select(active, scale, 0.0), M, m33)
        if ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1):
            scale, M = self._body(L, V)
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
        return self._pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self._pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
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
