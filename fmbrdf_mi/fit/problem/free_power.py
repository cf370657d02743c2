"""Relative light powers as free parameters of a joint fit (``fit_joint(..., free_power=True)``, ``--free-power``).

Image k of a joint fit (:mod:`fmbrdf_mi.fit.api.joint`) is predicted as

    S_k(x) = (P_k / G_k) E_k (k_s f_s(x; eta, alpha, beta) + k_b f_b(x; eta, kappa)),

with E_k the irradiance the image was given (its ``irradiance`` times its
given relative power G_k: the manifest's ``power``, the authors'
``intensities.npy`` / max, 1 if none) and P_k its light power.  Without
``free_power`` P_k = G_k.  With it, P_1 .. P_{K-1} are estimated with the
six material parameters and **P_0 stays at G_0**: k_s and k_b already scale
every image, so one power must be fixed.  The reference is the *first*
image (not the brightest) because the estimate does not depend on the
choice -- fixing image j instead multiplies k_s, k_b and every P_k by the
same factor (the likelihood is invariant to that rescaling) -- so only the
presentation changes, and the first image is the one the user chose and can
reorder (the manifest's first entry, the authors' lowest index).

**Parameterisation.**  Each free power is one more non-linear parameter of
the optimiser (:class:`PowerModel`): log P_k through the same bounded
sigmoid as the shape parameters (:class:`~fmbrdf_mi.fit.evaluate.models.Bounds`,
``scale="log"``) on [G_k / 1000, 1000 G_k], so every iterate is positive.
The prediction is linear in P_k, so its derivative is the image's own
prediction divided by G_k (:class:`PowerEvaluator`): no BSDF evaluation, no
table rebuild; a step that changes only the powers reuses the last BSDF
evaluation.  The standard errors come from the same covariance as the six
parameters (:mod:`fmbrdf_mi.fit.uncertainty`: inverse Fisher information
for the likelihood, sandwich for the paper's loss), with the power
columns in J.

**Starting values** (``power_start``): ``given`` starts every P_k at G_k
(the coarse search runs at the given powers); ``ratio`` (default) solves,
at every coarse-search grid point, the albedos and the powers together in
closed form -- alternating the two-albedo non-negative least squares and,
per image, the least-squares ratio of the observed intensities (the
likelihood: the samples, weighted by 1 / variance) to the prediction at
unit power -- so the search ranks shapes with the powers that suit them.
Both are measured in ``tools/bench_fit_lights.py --free-power`` (docs/benchmarks.md).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmbrdf_mi.fit.evaluate.models import Bounds, ModelView, ShapeParam, State
from fmbrdf_mi.fit.evaluate.pixel_model import Parts
from fmbrdf_mi.fit.problem.problem import Problem

#: The free powers are searched in [G / POWER_RANGE, G * POWER_RANGE].
POWER_RANGE = 1000.0


#: Starting values: ``ratio`` (closed form at each grid point) or ``given``.
POWER_STARTS = ("ratio", "given")


def power_names(k):
    """Names of the free powers of a K-image fit: power_1 .. power_{K-1} (image 0 is the reference)."""
    return tuple(f"power_{j}" for j in range(1, k))


class PowerModel(ModelView):
    """A :class:`~fmbrdf_mi.fit.evaluate.models.Model` with the powers P_1 .. P_{K-1} as extra shape parameters.

    ``given``: G_0 .. G_{K-1}.  :meth:`report` adds ``power_k`` (P_k) to
    the model's parameters; :meth:`split` takes them from the reported
    values, else from :attr:`start`.  Everything else is the model's
    (:class:`~fmbrdf_mi.fit.evaluate.models.ModelView`).
    """

    def __init__(self, base, given):
        super().__init__(base)
        self.given = [float(g) for g in given]
        self.power_names = power_names(len(self.given))
        self.start = {n: g for n, g in zip(self.power_names, self.given[1:])}

    def _power_param(self, name):
        g = self.given[int(name.split("_")[1])]
        return ShapeParam(name, None, g / POWER_RANGE, g * POWER_RANGE, "log", (self.start[name],))

    @property
    def shape(self):
        return tuple(self.base.shape) + tuple(self._power_param(n) for n in self.power_names)

    @property
    def shape_names(self):
        return tuple(self.base.shape_names) + self.power_names

    def param(self, name):
        return self._power_param(name) if name in self.power_names else self.base.param(name)

    def report(self, shape_values, a_s, a_b):
        out = self.base.report(shape_values, a_s, a_b)
        out.update({n: float(shape_values[n]) for n in self.power_names})
        return out

    def split(self, reported):
        shape, a_s, a_b = self.base.split(reported)
        shape.update({n: float(reported.get(n, self.start[n])) for n in self.power_names})
        return shape, a_s, a_b

    def factors(self, shape_values):
        """P_k / G_k for every image (1 for the reference)."""
        return np.array([1.0] + [shape_values[n] / g for n, g in zip(self.power_names, self.given[1:])])


class PowerEvaluator:
    """An evaluator's parts with image k's points scaled by P_k / G_k, and d/dP_k analytically.

    ``base``: the joint fit's :class:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator`
    (at the given irradiances); ``pixels_per_image``: fitted (super-)pixels
    of each image, in the order of the evaluator's points (each pixel has
    the same number of points: its samples or footprint).
    """

    def __init__(self, base, model, pixels_per_image):
        self.base, self.model = base, model
        self.counts = np.asarray(pixels_per_image, int)
        self._cache = None   # (shape key, wrt, Parts) of the last BSDF evaluation

    def image_of(self, m):
        """Image index of each of the ``m`` points (pixel-major)."""
        pts = m // int(self.counts.sum())
        return np.repeat(np.arange(len(self.counts)), self.counts * pts)

    def base_parts(self, shape_values, wrt=()):
        names = self.model.base.shape_names
        key = tuple(round(float(shape_values[n]), 12) for n in names)
        wrt = tuple(n for n in wrt if n in names)
        c = self._cache
        if c is not None and c[0] == key and set(wrt) <= set(c[1]):
            return c[2]
        p = self.base.parts({n: shape_values[n] for n in names}, wrt)
        self._cache = (key, wrt, p)
        return p

    def parts(self, shape_values, wrt=()):
        p = self.base_parts(shape_values, wrt)
        img = self.image_of(p.surface.shape[1])
        f = self.model.factors(shape_values)[img]
        out = Parts(p.surface * f, p.body * f, {n: d * f for n, d in p.d_surface.items()},
                    {n: d * f for n, d in p.d_body.items()}, p.nonfinite)
        for n in wrt:
            if n in self.model.power_names:
                k = int(n.split("_")[1])
                on = (img == k) / self.model.given[k]       # d (P_k / G_k) / d P_k on image k's points
                out.d_surface[n] = p.surface * on
                out.d_body[n] = p.body * on
        return out


class PowerProblem(Problem):
    """A :class:`~fmbrdf_mi.fit.problem.problem.Problem` whose coarse-search points solve the powers too
    (``start="ratio"``: module docstring); ``pixel_slices``: (start, stop) of each image's pixels
    among the objective's."""

    def __init__(self, *args, pixel_slices, start="ratio", **kw):
        super().__init__(*args, **kw)
        self.slices = list(pixel_slices)
        self.start = start

    def _pairs(self, pred):
        """(observed, predicted, weight), one row per fitted pixel, of what the powers scale."""
        obj = self.obj
        if obj.is_likelihood:
            return obj.y, obj._mu_of(pred), 1.0 / obj.var
        i = obj.target.intensity[:, None]
        return i, pred[0][:, None], np.ones_like(i)

    def closed_form_powers(self, shape, a_s, a_b, base):
        """P_1 .. P_{K-1} (dict) that best scale the prediction at unit power onto each image."""
        y, mu, w = self._pairs(a_s * base.surface + a_b * base.body)
        out = {}
        for n, (a, b) in zip(self.model.power_names, self.slices[1:]):
            k = int(n.split("_")[1])
            den = float(np.sum(w[a:b] * mu[a:b] ** 2))
            f = float(np.sum(w[a:b] * y[a:b] * mu[a:b])) / den if den > 0 else 1.0
            _, _, lo, hi = self.bounds.lims[n]
            out[n] = min(max(self.model.given[k] * f, lo), hi) if math.isfinite(f) else shape[n]
        return out

    def closed_form(self, shape):
        if self.start != "ratio":
            return super().closed_form(shape)
        base = self.ev.base_parts(shape)
        shape = dict(shape)
        a_s = a_b = None
        for _ in range(30):   # block coordinate descent of one weighted least-squares criterion
            parts = self.ev.parts(shape)
            a_s, a_b = self.obj.albedos(parts)
            new = self.closed_form_powers(shape, a_s, a_b, base)
            moved = max(abs(math.log(new[n] / shape[n])) for n in new)
            shape.update(new)
            if moved < 1e-6:
                break
        parts = self.ev.parts(shape)
        a_s, a_b = self.obj.albedos(parts)
        return State(shape, a_s, a_b), parts

    def state(self, shape, a_s, a_b):
        """A start given as parameters (``init``): powers in closed form at those albedos (``ratio``)."""
        st = super().state(shape, a_s, a_b)
        if self.start == "ratio":
            st.shape.update(self.closed_form_powers(st.shape, a_s, a_b, self.ev.base_parts(st.shape)))
        return st


def problem_factory(model, evaluator, pixel_slices, start="ratio"):
    """What :func:`fmbrdf_mi.fit.api.fitting.fit` calls to build its problem for a free-power joint fit
    (``model``: a :class:`PowerModel`, ``evaluator``: its :class:`PowerEvaluator`)."""

    def make(_base, _ev, objective, bounds, progress, fixed, deadline):

        return PowerProblem(model, evaluator, objective, Bounds(model, bounds), progress, fixed=fixed,
                            deadline=deadline, pixel_slices=pixel_slices, start=start)

    return make


def split_result(res, model, names):
    """Move the powers out of a fit's params / std_errors; returns the ``powers`` block of fit.json.

    ``{"reference": name of image 0, "names": [...], "given": [...], "values": [...],
    "std_errors": [...] (0 for the reference), "ci95": [[lo, hi], ...], "parameters": {image: power_k}}``
    """
    unc = res.uncertainty or {}
    ci = unc.get("ci95", {})
    values, ses, cis = [model.given[0]], [0.0], [[model.given[0], model.given[0]]]
    for n in model.power_names:
        values.append(float(res.params.pop(n)))
        se = res.std_errors.pop(n, None)
        ses.append(None if se is None else float(se))
        cis.append(ci.get(n))
    return {"reference": names[0], "names": list(names), "given": list(model.given), "values": values,
            "std_errors": ses, "ci95": cis,
            "parameters": {nm: pn for nm, pn in zip(names[1:], model.power_names)}}


def power_text(im):
    """``power 0.61 +- 0.004 (given 1)`` of one image of a free-power fit (its entry of ``images``)."""
    if im.get("power_reference"):
        return f"power {im['power']:.4g} (reference, fixed)"
    se = im.get("power_se")
    return f"power {im['power']:.4g}" + ("" if se is None else f" +- {se:.2g}") + f" (given {im['power_given']:.4g})"


def fitted_observation(obs, im):
    """``obs`` with the irradiance of the fitted light power (``im``: its entry of ``images``), else itself."""
    if im.get("power") is None or im["power"] == im["power_given"]:
        return obs
    return dataclasses.replace(obs, irradiance=obs.irradiance * im["power"] / im["power_given"])
