"""Mueller BRDFs of FMBRDF, ``pplastic`` and a Lambertian surface for many direction pairs: the polarised
counterpart of :class:`.values.FMBRDFValues`.

Each model is a Mitsuba BSDF in the polarised AD variant :data:`VARIANT`
(``fmbrdf`` with float32 tables, Mitsuba's ``pplastic`` with GGX facets,
Mitsuba's ``diffuse``), evaluated for all rows at once in one Dr.Jit call
through ``mi.BSDFPtr`` per term, at unit albedos: a term's Mueller BRDF is
linear in its albedo, so the model is sum_c k_c P_c with the terms P_c of
:meth:`MuellerValues.parts` (FMBRDF: the surface term of eq:Torrance-Sparrow
and the body term of eq:observed body reflection Stokes vector; ``pplastic``:
its specular and diffuse terms; Lambertian: one term).

What Mitsuba's ``eval`` returns is converted explicitly: it is the BRDF times
the cosine of the light direction (``wo`` in radiance mode), divided out here;
and its Mueller matrix maps Mitsuba's Stokes basis of the incident
propagation direction, ``stokes_basis(-w_in)``, to that of the outgoing one,
``stokes_basis(w_out)``, in the local frame (z = normal) with Mitsuba's sign of
S3: the package's frames, those of :class:`.mueller.MuellerTable`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .values import evaluation_variant

#: Mitsuba variant of the evaluation: polarised, monochrome.
VARIANT = "llvm_ad_mono_polarized"


def polarised_variant():
    """A context in :data:`VARIANT` with the plugin registered (:func:`.values.evaluation_variant`): yields
    ``mitsuba``; the variant set before is set again on leaving."""
    return evaluation_variant(VARIANT)


@dataclasses.dataclass(frozen=True)
class MuellerModel:
    """A model of :class:`MuellerValues`: its shape parameters (as fit.evaluate.models' models: name, traverse
    key, bounds, scale, coarse grid), its terms (name, Mitsuba component flag name, albedo name) and its BSDF."""

    name: str
    description: str
    shape: tuple
    terms: tuple            # ((albedo name, BSDFFlags name), ...)
    base: dict              # BSDF dict at unit albedos, "$name" where a shape parameter's value goes
    albedo_factor: float = 1.0   # a reported albedo = this x the BSDF's (a blend's weight)

    @property
    def shape_names(self):
        return tuple(p.name for p in self.shape)

    def param(self, name):
        """The shape parameter ``name`` (what :class:`fmbrdf_mi.fit.evaluate.models.Bounds` reads)."""
        for p in self.shape:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def albedo_names(self):
        return tuple(t[0] for t in self.terms)

    def bsdf_dict(self, shape):
        def fill(v):
            if isinstance(v, dict):
                return {k: fill(x) for k, x in v.items()}
            return float(shape[v[1:]]) if isinstance(v, str) and v.startswith("$") else v

        return fill(self.base)


def _models():
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, LAMBERT_TS, OREN_NAYAR_TS, PPLASTIC

    def of(m, surface, body):   # a model of the image fits: its BSDF template, parameters and albedo names
        return MuellerModel(m.name, m.description, m.shape,
                            ((surface, "GlossyReflection"), (body, "DiffuseReflection")), m.base_dict, m.albedo_factor)

    models = [of(FMBRDF, "k_s", "k_b"), of(PPLASTIC, "specular_reflectance", "diffuse_reflectance"),
              MuellerModel("lambert", "Mitsuba diffuse (Lambertian, depolarising)", (),
                           (("reflectance", "DiffuseReflection"),), {"type": "diffuse", "reflectance": 1.0}),
              of(LAMBERT_TS, "k_s", "k_d"), of(OREN_NAYAR_TS, "k_s", "k_d")]
    return {m.name: m for m in models}


#: The models, by name.
MODELS = _models()


def get_model(name):
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"model {name!r}: valid models are {', '.join(MODELS)}") from None


class MuellerValues:
    """The terms of a model's Mueller BRDF at unit albedos for fixed direction pairs.

    ``w_in`` (towards the light) and ``w_out`` (towards the viewer): (n, 3) in the local frame, above the
    surface.  Enter :func:`polarised_variant` around many calls to save the variant switches."""

    def __init__(self, model, w_in, w_out):
        self.model = get_model(model) if isinstance(model, str) else model
        w_in = np.asarray(w_in, dtype=np.float64)
        w_out = np.asarray(w_out, dtype=np.float64)
        if w_in.shape != w_out.shape or w_in.ndim != 2 or w_in.shape[1] != 3:
            raise ValueError(f"directions: expected two (n, 3) arrays, got {w_in.shape} and {w_out.shape}")
        if (w_in[:, 2] <= 0).any() or (w_out[:, 2] <= 0).any():
            raise ValueError("directions: every pair must be above the surface (z > 0)")
        self.n = len(w_in)
        self.cos_in = w_in[:, 2]
        self._shape = None
        #: Calls of :meth:`parts` (each builds the model at its shape: what a fit's time goes to).
        self.builds = 0
        with polarised_variant() as mi:
            import drjit as dr

            self.si = dr.zeros(mi.SurfaceInteraction3f, self.n)
            self.si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
            self.si.n = mi.Normal3f(0.0, 0.0, 1.0)
            self.si.wi = mi.Vector3f(*(mi.Float(w_out[:, k].astype(np.float32)) for k in range(3)))
            self.wo = mi.Vector3f(*(mi.Float(w_in[:, k].astype(np.float32)) for k in range(3)))
            start = {p.name: p.grid[len(p.grid) // 2] for p in self.model.shape}
            self.bsdf = mi.load_dict(self.model.bsdf_dict(start))
            self.ptr = mi.BSDFPtr(self.bsdf)
            self.params = mi.traverse(self.bsdf)
            self.ctx = []
            for _, flag in self.model.terms:
                ctx = mi.BSDFContext()
                ctx.type_mask = +getattr(mi.BSDFFlags, flag)
                self.ctx.append(ctx)

    def _set_shape(self, shape):
        vals = tuple(float(shape[p.name]) for p in self.model.shape)
        if vals != self._shape:
            for p, v in zip(self.model.shape, vals):
                self.params[p.key] = v
            self.params.update()
            self._shape = vals

    def parts(self, shape=None):
        """The terms' Mueller BRDFs (1/sr) at unit albedos, package frames: (terms, n, 4, 4) float64."""
        self.builds += 1
        with polarised_variant() as mi:
            if self.model.shape:
                self._set_shape(shape)
            out = np.empty((len(self.ctx), self.n, 4, 4))
            for k, ctx in enumerate(self.ctx):
                v = self.ptr.eval(ctx, self.si, self.wo, mi.Bool(True))
                out[k] = np.moveaxis(np.asarray(v, dtype=np.float64).reshape(4, 4, self.n), -1, 0)
        return out / (self.cos_in[None, :, None, None] * self.model.albedo_factor)


def combine(parts, albedos):
    """sum_c k_c P_c: (n, 4, 4) from :meth:`MuellerValues.parts` and the albedos (terms,)."""
    return np.tensordot(np.asarray(albedos, dtype=np.float64), parts, axes=(0, 0))
