"""Relative light powers as free parameters of a joint fit (``fit_joint(..., free_power=True)``, ``--free-power``).

Image k is predicted as (P_k / G_k) E_k (k_s f_s + k_b f_b), G_k its given relative power; P_1 .. P_{K-1} are
``power`` rows of the parameter table, and P_0 stays at G_0 since k_s and k_b already scale every image.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmbrdf_mi.fit.evaluate.materials import CachedParts
from fmbrdf_mi.fit.evaluate.models import State
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import Parts
from fmbrdf_mi.fit.problem.problem import Problem


class PowerEvaluator:
    """An evaluator's parts with image k's points scaled by P_k / G_k, and d/dP_k analytically (linear)."""

    def __init__(self, base, params, pixels_per_image):
        self.base, self.params = CachedParts(base, params.model.shape_names), params
        self.counts = np.asarray(pixels_per_image, int)

    def parts(self, shape_values, wrt=()):
        p = self.base.parts(shape_values, wrt)
        # points pixel-major, the same number per pixel; f: P_k / G_k (1 for the reference image)
        img = np.repeat(np.arange(len(self.counts)), self.counts * (p.surface.shape[1] // int(self.counts.sum())))
        f = np.array([1.0] + [shape_values[r.name] / self.params.given[r.image] for r in self.params.powers])[img]
        out = Parts(p.surface * f, p.body * f, {n: d * f for n, d in p.d_surface.items()},
                    {n: d * f for n, d in p.d_body.items()}, p.nonfinite)
        for r in self.params.powers:
            if r.name in wrt:
                on = (img == r.image) / self.params.given[r.image]    # d (P_k / G_k) / d P_k
                out.d_surface[r.name] = p.surface * on
                out.d_body[r.name] = p.body * on
        return out


class PowerProblem(Problem):
    """A :class:`~fmbrdf_mi.fit.problem.problem.Problem` whose coarse-search points solve the powers too
    (``start="ratio"``: in closed form; ``given``: the given powers)."""

    def __init__(self, *args, pixel_slices, start="ratio", **kw):
        super().__init__(*args, **kw)
        self.slices = list(pixel_slices)
        self.start = start

    def _pairs(self, pred):
        """(observed, predicted, weight), one row per fitted pixel, of what the powers scale."""
        obj = self.obj
        if obj.is_likelihood:
            return obj.y, obj.samples_of(pred), 1.0 / obj.var
        i = obj.target.intensity[:, None]
        return i, pred[0][:, None], np.ones_like(i)

    def closed_form_powers(self, shape, a_s, a_b, base):
        """P_1 .. P_{K-1} (dict): per image the weighted least-squares ratio of observed to predicted at unit
        power, clipped to the bounds."""
        y, mu, w = self._pairs(a_s * base.surface + a_b * base.body)
        out = {}
        for r in self.params.powers:
            n, k, (a, b) = r.name, r.image, self.slices[r.image]
            den = float(np.sum(w[a:b] * mu[a:b] ** 2))
            f = float(np.sum(w[a:b] * y[a:b] * mu[a:b])) / den if den > 0 else 1.0
            _, _, lo, hi = self.bounds.lims[n]
            out[n] = min(max(self.params.given[k] * f, lo), hi) if math.isfinite(f) else shape[n]
        return out

    def closed_form(self, shape, jac=False):
        if self.start != "ratio":
            return super().closed_form(shape, jac)
        base = self.ev.base.parts(shape)
        shape = dict(shape)
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
            st.shape.update(self.closed_form_powers(st.shape, a_s, a_b, self.ev.base.parts(st.shape)))
        return st


def problem_factory(evaluator, pixel_slices, start="ratio"):
    """The problem builder :func:`fmbrdf_mi.fit.api.fitting.fit` calls for a free-power joint fit;
    ``evaluator``: its :class:`PowerEvaluator`."""

    def make(base, _ev, objective, bounds, progress, fixed, deadline):
        params = Parameters(base, powers=evaluator.params.given, bounds=bounds, fixed=fixed)
        return PowerProblem(params, evaluator, objective, progress, deadline, pixel_slices=pixel_slices,
                            start=start)

    return make


def split_result(res, params, names):
    """Move the powers out of a fit's params / std_errors; returns the ``powers`` block of fit.json."""
    ci, given = (res.uncertainty or {}).get("ci95", {}), params.given
    values, ses, cis = [given[0]], [0.0], [[given[0], given[0]]]
    for n in (r.name for r in params.powers):
        values.append(float(res.params.pop(n)))
        se = res.std_errors.pop(n, None)
        ses.append(None if se is None else float(se))
        cis.append(ci.get(n))
    return {"reference": names[0], "names": list(names), "given": list(given), "values": values,
            "std_errors": ses, "ci95": cis, "parameters": {names[r.image]: r.name for r in params.powers}}


def power_text(im):
    """``power P +- SE (given G)`` of one image of a free-power fit (its entry of ``images``)."""
    if im.get("power_reference"):
        return f"power {im['power']:.4g} (reference, fixed)"
    se = im.get("power_se")
    return f"power {im['power']:.4g}" + ("" if se is None else f" +- {se:.2g}") + f" (given {im['power_given']:.4g})"


def fitted_observation(obs, im):
    """``obs`` with the irradiance of the fitted light power (``im``: its entry of ``images``), else itself."""
    if im.get("power") is None or im["power"] == im["power_given"]:
        return obs
    return dataclasses.replace(obs, irradiance=obs.irradiance * im["power"] / im["power_given"])
