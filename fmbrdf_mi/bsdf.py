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
from .model.body import BodyGrid, body_table, table_x_of_theta
from .model.distribution import Distribution
from .model.fresnel import reflection_mueller_terms
from .model.sampling import MicrofacetSampler

_SCALARS = ("eta", "alpha", "beta", "kappa")


def _scalar_value(x):
    arr = dr.detach(x)
    if dr.width(arr) != 1:
        raise P.ParameterError(f"fmbrdf: parameters must be single numbers, got an array of width {dr.width(arr)}")
    return arr[0]


def _texture_values(tex):
    """All numeric values a texture holds (for validation)."""
    import numpy as np

    out = []
    for key, value in mi.traverse(tex).items():
        try:
            out.append(np.asarray(dr.detach(value)).ravel())
        except Exception:
            pass
    return np.concatenate(out) if out else np.zeros(0)


def _axis(v, fallback=(1.0, 0.0, 0.0)):
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-14
    return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), mi.Vector3f(*fallback))


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
        self.dist = Distribution(mi.Float, self.alpha, self.beta)
        table = body_table(self.dist, self.eta, self.kappa, self.grid)
        if not self.polarized:
            table = mi.TensorXf(dr.gather(mi.Float, table.array,
                                          dr.arange(mi.UInt32, dr.width(table.array) // 9) * 9),
                                shape=table.shape[:3] + (1,))
        self.table = mi.Texture3f(table, use_accel=False, filter_mode=dr.FilterMode.Linear,
                                  wrap_mode=dr.WrapMode.Clamp)
        with dr.suspend_grad():
            self.sampler = MicrofacetSampler(self.dist)
        dr.eval(self.dist.p_tab, self.dist.norm)

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

    def _table_coords(self, cos_l, cos_v, phi):
        nt, nph = self.grid.n_table_theta, self.grid.n_table_phi
        x_l = table_x_of_theta(dr.acos(dr.clip(cos_l, 0.0, 1.0)))
        x_v = table_x_of_theta(dr.acos(dr.clip(cos_v, 0.0, 1.0)))
        # node i of n sits at texel centre (i + 0.5) / n
        u = lambda x, n: (x * (n - 1) + 0.5) / n
        return mi.Point3f(u(phi * (1.0 / math.pi), nph), u(x_v, nt), u(x_l, nt))

    def _eval_parts(self, ctx, si, wo, active):
        """Surface and body contributions as (scale, Mueller-or-None) pairs."""
        L, V = self._directions(ctx, si, wo)
        cos_l, cos_v = L.z, V.z
        active = active & (cos_l > 0) & (cos_v > 0)
        has_spec = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)
        has_body = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1)
        p_l = self.dist.proj_area_lookup(cos_l)
        p_v = self.dist.proj_area_lookup(cos_v)
        out = {}
        if has_spec:
            H = dr.normalize(L + V)
            cos_d = dr.dot(L, H)
            d = self.dist.D(H)
            scale = d * cos_l / (4.0 * p_l * p_v)  # k_s D G1(L) G1(V) / (4 N.V), G1 = cos/P
            rp, rm, rc = reflection_mueller_terms(cos_d, self.eta)
            if self.polarized:
                M = mi.Matrix4f(rp, rm, 0, 0,
                                rm, rp, 0, 0,
                                0, 0, rc, 0,
                                0, 0, 0, rc)
                s_in = _axis(dr.cross(H, -L))
                s_out = _axis(dr.cross(H, V))
                M = mi.mueller.rotate_mueller_basis(M, -L, s_in, mi.mueller.stokes_basis(-L),
                                                    V, s_out, mi.mueller.stokes_basis(V))
                out["spec"] = (dr.select(active, scale, 0.0), M)
            else:
                out["spec"] = (dr.select(active, scale * rp, 0.0), None)
        if has_body:
            phi_l = dr.atan2(L.y, L.x)
            phi = dr.atan2(V.y, V.x) - phi_l
            phi = dr.select(phi > math.pi, phi - 2 * math.pi, dr.select(phi < -math.pi, phi + 2 * math.pi, phi))
            mirrored = phi < 0
            vals = self.table.eval(self._table_coords(cos_l, cos_v, dr.abs(phi)))
            if self.polarized:
                flip = dr.select(mirrored, -1.0, 1.0)
                y = [vals[i] for i in range(9)]
                for i in (2, 5, 6, 7):  # elements with exactly one s2 index change sign
                    y[i] = y[i] * flip
                M = mi.Matrix4f(y[0], y[1], y[2], 0,
                                y[3], y[4], y[5], 0,
                                y[6], y[7], y[8], 0,
                                0, 0, 0, 0)
                sp, cp = dr.sincos(phi_l)
                x_in = mi.Vector3f(-sp, cp, 0.0)
                x_out = _axis(x_in - dr.dot(x_in, V) * V, (cp, sp, 0.0))
                M = mi.mueller.rotate_mueller_basis(M, -L, x_in, mi.mueller.stokes_basis(-L),
                                                    V, x_out, mi.mueller.stokes_basis(V))
                out["body"] = (dr.select(active, cos_l, 0.0), M)
            else:
                out["body"] = (dr.select(active, cos_l * vals[0], 0.0), None)
        return out

    def _combine(self, parts, si, active):
        ks, kb = self._albedos(si, active)
        if not self.polarized:
            value = mi.UnpolarizedSpectrum(0.0)
            if "spec" in parts:
                value += ks * parts["spec"][0]
            if "body" in parts:
                value += kb * parts["body"][0]
            return value
        result = dr.zeros(mi.Spectrum)
        terms = []
        if "spec" in parts:
            terms.append((ks * parts["spec"][0], parts["spec"][1]))
        if "body" in parts:
            terms.append((kb * parts["body"][0], parts["body"][1]))
        for i in range(4):
            for j in range(4):
                entry = mi.UnpolarizedSpectrum(0.0)
                for weight, M in terms:
                    entry += weight * M[i, j]
                result[i, j] = entry
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
