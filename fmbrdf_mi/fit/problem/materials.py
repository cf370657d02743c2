"""The problem of a fit of several materials (``fit(..., materials=labels)``, ``fmbrdf-mi fit --materials``).

The model, evaluator and albedo layout are
:mod:`fmbrdf_mi.fit.evaluate.materials`'; this module adds what the solver
needs: the objective's score per material (the coarse search ranks each
material's grid points on its own pixels:
:func:`fmbrdf_mi.fit.solve.optimise.coarse_search`), the problem with
parameters held fixed (the profile likelihood), and the ``materials`` block
of fit.json.

With the camera noise known and per-material (or per-pixel) albedos, each
material's unknowns enter only its own pixels' terms, so the fit of M
materials equals the M separate fits solved together (cross-material
covariances are 0); with unknown noise the noise model couples them.
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.problem.problem import Problem


class MaterialProblem(Problem):
    """A :class:`~fmbrdf_mi.fit.problem.problem.Problem` over M materials (its parameter table's
    ``count``): ``cell_material`` (cells,) each fitted cell's material."""

    def __init__(self, *args, cell_material, **kw):
        super().__init__(*args, **kw)
        self.cell_material = np.asarray(cell_material, dtype=np.int64)

    def with_fixed(self, values):
        return MaterialProblem(self.params.with_fixed(values), self.ev, self.obj, self.progress,
                               cell_material=self.cell_material)

    def material_scores(self, parts, st):
        """(M,) the objective's score (for the likelihood its negative log) of each material's own cells:
        their sum is the score of the whole."""
        per_cell = 0.5 * np.sum(self.obj.nll_terms(parts, st), axis=1)
        return np.bincount(self.cell_material, weights=per_cell, minlength=self.params.count)


def problem_factory(cell_material, count, maps):
    """What :class:`~fmbrdf_mi.fit.problem.problem.FitData` calls to build the problem of a fit of ``count``
    materials; ``maps``: whether the albedos are maps (the per-pixel layout), else one pair per material."""

    def make(base, evaluator, objective, bounds, progress, fixed, deadline):
        params = Parameters(base, materials=count, maps=maps, bounds=bounds, fixed=fixed)
        return MaterialProblem(params, evaluator, objective, progress, deadline, cell_material=cell_material)

    return make


def material_block(params, reported, std_errors, ci95, pixels):
    """fit.json's ``materials`` block: ``{"count": M, "pixels": [fitted pixels of each], "parameters": [{eta:
    ..} per material], "std_errors": [...], "ci95": [...]}`` from a fit's reported parameters, standard errors
    and intervals, by the rows of its parameter table ``params`` (one material: the rows' own names)."""
    return {"count": params.count or 1, "pixels": [int(p) for p in pixels],
            "parameters": params.per_material(reported), "std_errors": params.per_material(std_errors),
            "ci95": params.per_material(ci95)}
