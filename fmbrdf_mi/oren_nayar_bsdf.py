"""The ``orennayar`` Mitsuba 3 BSDF: Mitsuba plumbing around :mod:`fmbrdf_mi.model.oren_nayar`.

Properties: ``reflectance`` (texture, default 0.5), ``sigma`` (standard
deviation of the facet slope angle, radians, in [0, pi/2], default 0.3) and
``form`` (``"full"``, the default: the SIGGRAPH 1994 model with its
interreflection term; or ``"qualitative"``).

eval() returns the BRDF times cos(theta) of ``wo`` (the Mitsuba convention;
the model is reciprocal, so the transport mode does not matter).  In
polarised variants the BSDF is a depolariser: the Mueller matrix has the
intensity in M00 and zeros elsewhere, which is the same matrix in every
Stokes basis (so in the frame conventions of the ``fmbrdf`` plugin too).
Importance sampling: cosine-weighted hemisphere, pdf = cos(theta_o) / pi.
"""
import math

import drjit as dr
import mitsuba as mi

from . import params as P
from .bsdf import texture_values
from .model.oren_nayar import FORMS, oren_nayar_terms

_PROPERTIES = ("reflectance", "sigma", "form")
SIGMA_RANGE = (0.0, 0.5 * math.pi)
DEFAULT_SIGMA = 0.3


def check_sigma(value, single=False):
    """Raise ParameterError unless ``value`` is a finite number in [0, pi/2]."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise P.ParameterError(f"orennayar: 'sigma' (facet slope deviation, radians) must be a number, "
                               f"got {value!r}") from None
    hi = P._f32(SIGMA_RANGE[1]) if single else SIGMA_RANGE[1]
    if not (math.isfinite(v) and SIGMA_RANGE[0] <= v <= hi):
        raise P.ParameterError(f"orennayar: 'sigma' (facet slope deviation, radians) = {v:g} is outside "
                               f"its valid range [0, {SIGMA_RANGE[1]:g}]")
    return v


def _check_reflectance(values):
    try:
        P.check_albedo("reflectance", values)
    except P.ParameterError as e:
        raise P.ParameterError(str(e).replace("fmbrdf:", "orennayar:", 1)) from None


class _OrenNayarMethods:
    """Oren-Nayar rough diffuse reflection (Oren & Nayar, SIGGRAPH 1994); see the module docstring."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        unknown = [k for k in props.keys() if k not in _PROPERTIES]
        if unknown:
            raise P.ParameterError(f"orennayar: unknown property '{unknown[0]}'; expected some of "
                                   f"{', '.join(_PROPERTIES)}")
        if "reflectance" in props and props.type("reflectance") == mi.Properties.Type.Color:
            _check_reflectance(list(props.get("reflectance")))
        self.form = props.get("form", "full") if "form" in props else "full"
        if self.form not in FORMS:
            raise P.ParameterError(f"orennayar: 'form' = {self.form!r} is not one of {', '.join(FORMS)}")
        sigma = props.get("sigma", DEFAULT_SIGMA) if "sigma" in props else DEFAULT_SIGMA
        self.sigma = mi.Float(check_sigma(sigma))
        self.reflectance = props.get_texture("reflectance", 0.5) if "reflectance" in props else \
            mi.load_dict({"type": "uniform", "value": 0.5})
        _check_reflectance(texture_values(self.reflectance))
        self.polarized = mi.is_polarized
        self.m_components = [mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide]
        self.m_flags = self.m_components[0]
        self._valid_sigma = type(self.sigma)(self.sigma) if dr.is_jit_v(mi.Float) else self.sigma

    def traverse(self, callback):
        callback.put("sigma", self.sigma, mi.ParamFlags.Differentiable)
        callback.put("reflectance", self.reflectance, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        """Validate sigma; on a bad value put the last valid one back and raise ParameterError."""
        try:
            value = self.sigma if isinstance(self.sigma, (int, float)) else dr.detach(self.sigma)
            if not isinstance(value, (int, float)) and dr.width(value) != 1:
                raise P.ParameterError("orennayar: 'sigma' must be a single number")
            check_sigma(value if isinstance(value, (int, float)) else value[0], single=True)
        except BaseException:
            if isinstance(self.sigma, (int, float)):
                self.sigma = self._valid_sigma
            else:
                mi.set_property(self.sigma, self._valid_sigma)
            raise
        self._valid_sigma = type(self.sigma)(self.sigma) if dr.is_jit_v(mi.Float) else self.sigma

    def _value(self, ctx, si, wo, active):
        """BRDF * cos(theta_o) as an unpolarised spectrum (0 where a direction is below the surface)."""
        active = active & (si.wi.z > 0) & (wo.z > 0) & ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)
        rho = self.reflectance.eval(si, active)
        direct, inter = oren_nayar_terms(si.wi, wo, self.sigma, self.form)
        value = (rho * direct + rho * rho * inter) * wo.z
        return dr.select(active, value, 0.0)

    def _spectrum(self, value, si):
        if not self.polarized:
            return value
        result = dr.zeros(mi.Spectrum, max(dr.width(value), dr.width(si.wi)))
        result[0, 0] = value  # a depolariser: every other element stays zero
        return result

    def _pdf(self, ctx, si, wo, active):
        ok = active & (si.wi.z > 0) & (wo.z > 0) & ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)
        return dr.select(ok, wo.z * (1.0 / math.pi), 0.0)

    def eval(self, ctx, si, wo, active=True):
        return self._spectrum(self._value(ctx, si, wo, active), si)

    def pdf(self, ctx, si, wo, active=True):
        return self._pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self._pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        active = active & (si.wi.z > 0) & ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)
        bs = mi.BSDFSample3f()
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        bs.eta = 1.0
        bs.sampled_component = mi.UInt32(0)
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        active = active & (bs.wo.z > 0)
        pdf = self._pdf(ctx, si, bs.wo, active)
        bs.pdf = dr.select(active, pdf, 0.0)
        value = self._value(ctx, si, bs.wo, active)
        weight = value * dr.select(active, dr.rcp(dr.select(active, pdf, 1.0)), 0.0)
        return bs, self._spectrum(weight, si)

    def to_string(self):
        s = self.sigma if isinstance(self.sigma, (int, float)) else dr.detach(self.sigma)[0]
        return f"OrenNayar[sigma={s:g}, form={self.form}, reflectance={self.reflectance}]"


_classes = {}


def make_plugin_class():
    """The ``orennayar`` BSDF class for the current Mitsuba variant."""
    variant = mi.variant()
    if variant not in _classes:
        body = {k: v for k, v in vars(_OrenNayarMethods).items() if k not in ("__dict__", "__weakref__")}
        _classes[variant] = type("OrenNayar", (mi.BSDF,), body)
    return _classes[variant]
