"""The reflectance models a fit can use (:data:`MODELS`): Mitsuba BSDFs linear in a *surface* and a *body*
albedo and non-linear in a few named *shape* parameters, evaluated only through Mitsuba.

* ``fmbrdf``: this package's FMBRDF, reported as (eta, alpha, beta, kappa, k_s, r_k = k_b / k_s).
* ``pplastic``: Mitsuba's polarised plastic (Baek et al. pBRDF, GGX).
* ``lambert_ts``: Lambertian + Torrance-Sparrow (Beckmann, Smith, dielectric Fresnel) as a ``blendbsdf`` of
  weight 1/2; albedos reported as the effective ones.
* ``oren_nayar_ts``: ``lambert_ts`` with the qualitative ``orennayar`` (the full form is quadratic in the
  albedo); shape eta, alpha, sigma (radians)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmbrdf_mi.fit.evaluate.parameters import Param


def shape_param(name, key, lo, hi, scale, grid):
    """A shape :class:`~fmbrdf_mi.fit.evaluate.parameters.Param`: traverse key, bounds, scale, search grid."""
    return Param(name, name, "shape", key, lo, hi, scale, tuple(grid))


@dataclasses.dataclass(frozen=True)
class Model:
    name: str
    description: str
    shape: tuple            # Param rows of kind shape (shape_param)
    surface_key: str        # traverse key of the surface albedo
    body_key: str           # traverse key of the body albedo
    base_dict: dict         # BSDF dict with placeholders filled by bsdf_dict()
    albedo_factor: float = 1.0  # reported albedo = factor * BSDF albedo
    surface_name: str = "k_s"   # reported name of the surface albedo
    body_name: str = "k_b"      # ... of the body albedo (or of k_b / k_s: ``body_ratio``)
    body_ratio: bool = False    # the body albedo is reported as its ratio to the surface's

    @property
    def shape_names(self):
        return tuple(p.name for p in self.shape)

    def param(self, name):
        return {p.name: p for p in self.shape}[name]

    def bsdf_dict(self, shape_values=None):
        """The BSDF dict at ``shape_values`` (defaults: middle of the grid), unit albedos."""
        vals = {p.name: p.grid[len(p.grid) // 2] for p in self.shape}
        vals.update(shape_values or {})
        return _fill(self.base_dict, vals)


def _fill(template, vals):
    if isinstance(template, dict):
        return {k: _fill(v, vals) for k, v in template.items()}
    if isinstance(template, str) and template.startswith("$"):
        return float(vals[template[1:]])
    return template


FMBRDF = Model(
    name="fmbrdf",
    description="Fresnel Microfacet BRDF (this package)",
    shape=(
        shape_param("eta", "eta", 1.01, 3.0, "log_minus_1", (1.2, 1.4, 1.6, 1.9, 2.3)),
        shape_param("alpha", "alpha", 0.01, 1.5, "log", (0.03, 0.06, 0.12, 0.25, 0.5, 1.0)),
        shape_param("beta", "beta", 0.4, 5.0, "log", (0.8, 1.6, 3.2)),
        shape_param("kappa", "kappa", 0.0, 100.0, "log1p", (0.0, 10.0, 40.0)),
    ),
    surface_key="k_s.value",
    body_key="k_b.value",
    # float32 tables: residuals and derivatives smooth in the parameters (the compact ones round)
    base_dict={"type": "fmbrdf", "eta": "$eta", "alpha": "$alpha", "beta": "$beta",
               "kappa": "$kappa", "k_s": 1.0, "k_b": 1.0, "tables": "float32"},
    body_name="r_k",
    body_ratio=True,
)


PPLASTIC = Model(
    name="pplastic",
    description="Mitsuba pplastic (Baek et al. 2018 pBRDF, GGX)",
    shape=(
        shape_param("eta", "eta.value", 1.01, 3.0, "log_minus_1", (1.2, 1.35, 1.5, 1.7, 2.0, 2.4)),
        shape_param("alpha", "alpha.value", 0.01, 1.0, "log", (0.02, 0.04, 0.08, 0.15, 0.3, 0.6)),
    ),
    surface_key="specular_reflectance.value",
    body_key="diffuse_reflectance.value",
    base_dict={"type": "pplastic", "eta": "$eta", "alpha": "$alpha", "distribution": "ggx",
               "specular_reflectance": 1.0, "diffuse_reflectance": 1.0},
    surface_name="specular_reflectance",
    body_name="diffuse_reflectance",
)


LAMBERT_TS = Model(
    name="lambert_ts",
    description="Lambertian + Torrance-Sparrow (Beckmann, Smith, dielectric Fresnel)",
    shape=(
        shape_param("eta", "bsdf_1.eta.value", 1.01, 3.0, "log_minus_1", (1.2, 1.5, 2.0)),
        shape_param("alpha", "bsdf_1.alpha.value", 0.01, 1.0, "log", (0.02, 0.04, 0.08, 0.15, 0.3, 0.6)),
    ),
    surface_key="bsdf_1.specular_reflectance.value",
    body_key="bsdf_0.reflectance.value",
    albedo_factor=0.5,
    base_dict={"type": "blendbsdf", "weight": 0.5,
               "bsdf_0": {"type": "diffuse", "reflectance": 1.0},
               "bsdf_1": {"type": "roughconductor", "distribution": "beckmann", "alpha": "$alpha",
                          "eta": "$eta", "k": 0.0, "specular_reflectance": 1.0}},
    body_name="k_d",
)


OREN_NAYAR_TS = Model(
    name="oren_nayar_ts",
    description="Oren-Nayar (qualitative form) + Torrance-Sparrow (Beckmann, Smith, dielectric Fresnel)",
    shape=(
        shape_param("eta", "bsdf_1.eta.value", 1.01, 3.0, "log_minus_1", (1.2, 1.5, 2.0)),
        shape_param("alpha", "bsdf_1.alpha.value", 0.01, 1.0, "log", (0.02, 0.04, 0.08, 0.15, 0.3, 0.6)),
        shape_param("sigma", "bsdf_0.sigma", 0.0, 1.5, "linear", (0.0, 0.25, 0.5, 0.9)),
    ),
    surface_key="bsdf_1.specular_reflectance.value",
    body_key="bsdf_0.reflectance.value",
    albedo_factor=0.5,
    base_dict={"type": "blendbsdf", "weight": 0.5,
               "bsdf_0": {"type": "orennayar", "form": "qualitative", "sigma": "$sigma", "reflectance": 1.0},
               "bsdf_1": {"type": "roughconductor", "distribution": "beckmann", "alpha": "$alpha",
                          "eta": "$eta", "k": 0.0, "specular_reflectance": 1.0}},
    body_name="k_d",
)


MODELS = {m.name: m for m in (FMBRDF, PPLASTIC, LAMBERT_TS, OREN_NAYAR_TS)}


#: The models fitted beside the chosen one by ``--baselines``.
BASELINES = ("pplastic", "lambert_ts", "oren_nayar_ts")


def get_model(name):
    if isinstance(name, str) and name in MODELS:
        return MODELS[name]
    raise ValueError(f"model: expected one of {sorted(MODELS)}, got {name!r}")


#: A parameter's scales: (to the scale, back, d back / d scale).
SCALES = {"linear": (lambda x: x, lambda t: t, lambda t: 1.0),
          "log": (math.log, np.exp, np.exp),
          "log1p": (math.log1p, np.expm1, np.exp),
          "log_minus_1": (lambda x: math.log(x - 1.0), lambda t: 1.0 + np.exp(t), np.exp)}


#: |z| is kept below this so that sigmoid(z) stays away from 0 and 1 in float32.
Z_MAX = 12.0


class Bounds:
    """Maps unconstrained z to parameters inside [lo, hi] by a sigmoid on the parameter's scale; ``model``: a
    :class:`Model` or :class:`~fmbrdf_mi.fit.evaluate.parameters.Parameters`."""

    def __init__(self, model):
        #: {name: (lo, hi on the parameter's scale, lo, hi)}
        self.scales = {p.name: SCALES[p.scale] for p in model.shape}
        self.lims = {p.name: (self.scales[p.name][0](p.lo), self.scales[p.name][0](p.hi), p.lo, p.hi)
                     for p in model.shape}

    def _sigmoid(self, name, z):
        """(sigmoid of ``z`` clipped to Z_MAX, the point t it maps to on the parameter's scale, the scale's range)."""
        tlo, thi, _, _ = self.lims[name]
        s = 1.0 / (1.0 + math.exp(-float(np.clip(z, -Z_MAX, Z_MAX))))
        return s, tlo + (thi - tlo) * s, thi - tlo

    def to_value(self, name, z):
        _, _, lo, hi = self.lims[name]
        return min(max(float(self.scales[name][1](self._sigmoid(name, z)[1])), lo), hi)

    def derivative(self, name, z):
        """d value / d z."""
        s, t, span = self._sigmoid(name, z)
        return float(self.scales[name][2](t)) * span * s * (1 - s)

    def to_z(self, name, value):
        tlo, thi, lo, hi = self.lims[name]
        v = min(max(float(value), lo), hi)
        s = (self.scales[name][0](v) - tlo) / (thi - tlo)
        s = min(max(s, 1e-5), 1 - 1e-5)
        return math.log(s / (1 - s))

    def to_scale(self, name, value):
        """``value`` on the parameter's scale (log, log1p, ...: where the sigmoid of :meth:`to_value` is linear)."""
        return float(self.scales[name][0](float(value)))

    def from_scale(self, name, t):
        return float(self.scales[name][1](float(t)))

    def clip_grid(self, name, grid):
        _, _, lo, hi = self.lims[name]
        return sorted({min(max(float(x), lo), hi) for x in grid})


@dataclasses.dataclass
class State:
    """A point of the search: shape values and albedos."""

    shape: dict
    a_s: float
    a_b: float

    def copy(self):
        return State(dict(self.shape), self.a_s, self.a_b)
