"""A fit of several materials (``fit(..., materials=labels)``, ``fmbrdf-mi fit --materials``): its fit.json block.

The model, evaluator and albedo layout are :mod:`fmbrdf_mi.fit.evaluate.materials`'; the problem is a
:class:`~fmbrdf_mi.fit.problem.problem.Problem` that knows each cell's material, so that the coarse search
ranks each material's grid points on its own pixels (:func:`fmbrdf_mi.fit.solve.optimise.coarse_search`).

With the camera noise known and per-material (or per-pixel) albedos, each
material's unknowns enter only its own pixels' terms, so the fit of M
materials equals the M separate fits solved together (cross-material
covariances are 0); with unknown noise the noise model couples them.
"""
from __future__ import annotations


def material_block(params, reported, std_errors, ci95, pixels):
    """fit.json's ``materials`` block: ``{"count": M, "pixels": [fitted pixels of each], "parameters": [{eta:
    ..} per material], "std_errors": [...], "ci95": [...]}`` from a fit's reported parameters, standard errors
    and intervals, by the rows of its parameter table ``params`` (one material: the rows' own names)."""
    return {"count": params.count or 1, "pixels": [int(p) for p in pixels],
            "parameters": params.per_material(reported), "std_errors": params.per_material(std_errors),
            "ci95": params.per_material(ci95)}
