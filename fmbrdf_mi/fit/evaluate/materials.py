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


class CachedParts:
    """``evaluator``'s :class:`Parts` at the shape values ``names``, evaluated again only when they change or
    derivatives not held are asked for."""

    def __init__(self, evaluator, names):
        self.evaluator, self.names, self.last = evaluator, tuple(names), None   # last: (key, wrt, Parts)

    def parts(self, values, wrt=()):
        key = tuple(round(float(values[n]), 12) for n in self.names)
        wrt = tuple(n for n in wrt if n in self.names)
        if self.last is None or self.last[0] != key or not set(wrt) <= set(self.last[1]):
            self.last = (key, wrt, self.evaluator.parts({n: values[n] for n in self.names}, wrt))
        return self.last[2]


class MaterialEvaluator:
    """:class:`Parts` of all points from one evaluator per material (``columns``: each one's points); an
    unchanged material is not evaluated again."""

    def __init__(self, params, evaluators, columns, n_points):
        self.params = params
        self.evaluators = [CachedParts(ev, params.model.shape_names) for ev in evaluators]
        self.columns = [np.asarray(c, dtype=np.int64) for c in columns]
        self.n_points = int(n_points)

    def parts(self, shape_values, wrt=()):
        N = self.n_points
        surface, body = np.zeros((3, N)), np.zeros((3, N))
        d_s, d_b, bad = {}, {}, None
        for m, (cols, values) in enumerate(zip(self.columns, self.params.per_material(shape_values))):
            rows = [r for r in self.params.shape if r.material == m and r.name in wrt]
            sub_wrt = [r.base for r in rows]
            p = self.evaluators[m].parts(values, sub_wrt)
            surface[:, cols], body[:, cols] = p.surface, p.body
            for r in rows:
                ds, db = np.zeros((3, N)), np.zeros((3, N))
                ds[:, cols], db[:, cols] = p.d_surface[r.base], p.d_body[r.base]
                d_s[r.name], d_b[r.name] = ds, db
            if p.nonfinite is not None and sub_wrt:
                bad = np.zeros(N, bool) if bad is None else bad
                bad[cols] |= p.nonfinite
        return Parts(surface, body, d_s, d_b, bad)
