"""Several materials in one fit: a label image assigns each fitted pixel one of M materials, each with its
own shape parameters and albedos (paper: s_s + s_b), all in one objective (:class:`MaterialEvaluator`).
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.pixel_model import Parts

#: Fewest fitted (super-)pixels a material must have: as many as a whole fit needs.
MIN_MATERIAL_PIXELS = 20


def check_labels(labels, shape, what="materials"):
    """``labels`` (H, W), or (2H, 2W) sensor pixels (a super-pixel takes its 2 x 2 block's label when the four
    agree, else -1), as an int array on the pixel grid ``shape``; 0 .. M-1 are materials, < 0 not fitted."""
    H, W = shape
    try:
        lab = np.asarray(labels)
    except Exception:   # noqa: BLE001 - anything that is not an array
        raise InputError(f"{what}: expected an integer array of shape ({H}, {W}), got {type(labels).__name__}") \
            from None
    if lab.ndim != 2 or lab.shape not in ((H, W), (2 * H, 2 * W)):
        raise InputError(f"{what}: shape {lab.shape} is neither the fit's pixel grid ({H}, {W}) nor the raw "
                         f"sensor's ({2 * H}, {2 * W}); give one integer label per pixel")
    if lab.dtype.kind not in "iuf":     # booleans too
        raise InputError(f"{what}: expected integer labels, got dtype {lab.dtype}")
    if lab.dtype.kind == "f" and (not np.all(np.isfinite(lab)) or np.any(lab != np.round(lab))):
        raise InputError(f"{what}: labels must be integers (0 .. M-1, < 0 for pixels not fitted)")
    lab = lab.astype(np.int64)
    if lab.shape == (2 * H, 2 * W):
        b = lab.reshape(H, 2, W, 2).transpose(0, 2, 1, 3).reshape(H, W, 4)
        agree = np.all(b == b[..., :1], axis=-1)
        lab = np.where(agree, b[..., 0], -1)
    return lab


def material_count(labels, what="materials"):
    """M: the largest label + 1 of a checked label image; InputError when no pixel has a label >= 0."""
    top = int(labels.max()) if labels.size else -1
    if top < 0:
        raise InputError(f"{what}: no pixel has a label >= 0 (0 .. M-1 are the materials)")
    return top + 1


class MaterialEvaluator:
    """:class:`Parts` of all points from one evaluator per material (``columns``: each one's points); an
    unchanged material is not evaluated again."""


    def __init__(self, params, evaluators, columns, n_points):
        self.params = params
        self.evaluators = list(evaluators)
        self.columns = [np.asarray(c, dtype=np.int64) for c in columns]
        self.n_points = int(n_points)
        self._cache = [None] * len(self.evaluators)   # (shape key, wrt, Parts) per material

    def _material_parts(self, m, values, wrt):
        key = tuple(round(float(values[n]), 12) for n in self.params.model.shape_names)
        c = self._cache[m]
        if c is None or c[0] != key or not set(wrt) <= set(c[1]):
            c = self._cache[m] = (key, tuple(wrt), self.evaluators[m].parts(values, tuple(wrt)))
        return c[2]

    def parts(self, shape_values, wrt=()):
        N = self.n_points
        surface, body = np.zeros((3, N)), np.zeros((3, N))
        d_s, d_b, bad = {}, {}, None
        for m, cols in enumerate(self.columns):
            rows = [r for r in self.params.shape if r.material == m and r.name in wrt]
            sub_wrt = [r.base for r in rows]
            p = self._material_parts(m, self.params.of(shape_values, m), sub_wrt)
            surface[:, cols], body[:, cols] = p.surface, p.body
            for r in rows:
                ds, db = np.zeros((3, N)), np.zeros((3, N))
                ds[:, cols], db[:, cols] = p.d_surface[r.base], p.d_body[r.base]
                d_s[r.name], d_b[r.name] = ds, db
            if p.nonfinite is not None and sub_wrt:
                bad = np.zeros(N, bool) if bad is None else bad
                bad[cols] |= p.nonfinite
        return Parts(surface, body, d_s, d_b, bad)
