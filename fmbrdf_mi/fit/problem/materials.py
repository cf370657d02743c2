"""The problem of a fit of several materials (``fit(..., materials=labels)``, ``fmbrdf-mi fit --materials``).

The model, evaluator and albedo layout are
:mod:`fmbrdf_mi.fit.evaluate.materials`'; this module adds what the solver
needs: the objective's score per material (the coarse search ranks each
material's grid points on its own pixels:
:func:`fmbrdf_mi.fit.solve.optimise.material_search`), the problem with
parameters held fixed (the profile likelihood), and the ``materials`` block
of fit.json.

With the camera noise known the likelihood is a sum over pixels, and with
per-material (or per-pixel) albedos each material's unknowns enter only its
own pixels' terms: the fit of M materials is then the M fits of each
material's pixels, solved together (one optimiser, one covariance; the
cross-material covariances are 0 up to rounding).  With unknown noise the
noise model's two parameters, estimated from all pixels, couple them.
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.evaluate.materials import MaterialModel
from fmbrdf_mi.fit.evaluate.models import Bounds
from fmbrdf_mi.fit.problem.problem import Problem


class MaterialProblem(Problem):
    """A :class:`~fmbrdf_mi.fit.problem.problem.Problem` over M materials: ``materials`` the
    :class:`~fmbrdf_mi.fit.evaluate.materials.MaterialModel`, ``cell_material`` (cells,) each fitted
    cell's material."""

    def __init__(self, *args, materials, cell_material, **kw):
        super().__init__(*args, **kw)
        self.materials = materials
        self.cell_material = np.asarray(cell_material, dtype=np.int64)

    def with_fixed(self, values):
        return MaterialProblem(self.model, self.ev, self.obj, self.bounds, self.progress,
                               fixed={**self.fixed, **values}, materials=self.materials,
                               cell_material=self.cell_material)

    def material_scores(self, parts, st):
        """(M,) the objective's score (the likelihood's negative log, :meth:`LikelihoodObjective.nll`) of each
        material's own cells: their sum is the score of the whole."""
        obj = self.obj
        mu = obj.mu(parts, st)
        v = np.maximum(obj.noise.variance(mu), 1e-300)
        per_cell = 0.5 * np.sum((obj.y - mu) ** 2 / v + np.log(v), axis=1)
        return np.bincount(self.cell_material, weights=per_cell, minlength=self.materials.count)


def problem_factory(cell_material, count, wrap):
    """What :class:`~fmbrdf_mi.fit.problem.problem.FitData` calls to build the problem of a fit of ``count``
    materials; ``wrap(model)``: the model the problem reports with (the per-pixel layout's
    :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelModel`, else the material model itself)."""

    def make(base, evaluator, objective, bounds, progress, fixed, deadline):
        mm = MaterialModel(base, count)
        return MaterialProblem(wrap(mm), evaluator, objective, Bounds(mm, mm.expand(bounds)), progress,
                               fixed=mm.expand(fixed), deadline=deadline, materials=mm,
                               cell_material=cell_material)

    return make


def material_block(params, std_errors, ci95, count, pixels, base_names=None):
    """fit.json's ``materials`` block: ``{"count": M, "pixels": [fitted pixels of each], "parameters": [{eta:
    ..} per material], "std_errors": [...], "ci95": [...]}`` from the flat ``eta[m]`` names of a fit (or, one
    material, the model's own names: ``base_names`` given)."""

    def nest(flat):
        out = [{} for _ in range(count)]
        for k, v in (flat or {}).items():
            if base_names is not None:
                if k in base_names:
                    out[0][k] = v
            elif k.endswith("]") and "[" in k:
                name, label = k[:-1].split("[", 1)
                if label.isdigit() and int(label) < count:
                    out[int(label)][name] = v
        return out

    return {"count": int(count), "pixels": [int(p) for p in pixels], "parameters": nest(params),
            "std_errors": nest(std_errors), "ci95": nest(ci95)}
