"""fit.json's block of a fit of several materials (``fit(..., materials=labels)``, ``--materials``).

The model, evaluator and albedo layout are in :mod:`fmbrdf_mi.fit.evaluate.materials`.  With known noise
and per-material albedos the M materials' unknowns do not interact (cross-material covariances are 0).
"""
from __future__ import annotations


def material_block(params, reported, std_errors, ci95, pixels):
    """fit.json's ``materials`` block: ``{"count": M, "pixels": [fitted pixels of each], "parameters": [{eta:
    ..} per material], "std_errors": [...], "ci95": [...]}`` from a fit's reported parameters, standard errors
    and intervals, by the rows of its parameter table ``params`` (one material: the rows' own names)."""
    return {"count": params.count or 1, "pixels": [int(p) for p in pixels],
            "parameters": params.per_material(reported), "std_errors": params.per_material(std_errors),
            "ci95": params.per_material(ci95)}
