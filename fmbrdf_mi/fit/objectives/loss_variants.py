"""The loss variants of the paper's relighting comparison: :class:`IntensityObjective` (the intensity term
of eq:optimization alone) and :class:`DolpObjective` (the DoLP term alone, "ours without radiance").

Both are linear maps of :class:`PaperObjective`'s residuals, so the same optimiser and covariance apply.
"""
from __future__ import annotations

import math

import numpy as np

from fmbrdf_mi.fit.evaluate.models import State
from fmbrdf_mi.fit.objectives.objective import PaperObjective

class _Rows(PaperObjective):
    """A loss that is r' . r' of a linear map r' = :meth:`rows` (r) of :class:`PaperObjective`'s residuals r."""

    def residuals(self, parts, st, w=None):
        return self.rows(super().residuals(parts, st, w))

    def residuals_and_jacobian(self, parts, st, z, names, bounds):
        r, J, bad = super().residuals_and_jacobian(parts, st, z, names, bounds)
        if bad is None:
            return self.rows(r), self.rows(J), None
        # a row with a non-finite derivative stays out of every combined row
        return self.rows(r), self.rows(J, ~bad), self.rows(bad, ~bad).astype(bool)


class IntensityObjective(_Rows):
    """Intensity MSE of eq:optimization alone (no DoLP term, no inlier / outlier weights)."""

    name = "intensity"

    def refresh(self, parts, st):
        pass

    def settled(self, old, parts, st, **_):
        return True

    def describe_round(self):
        return "intensity only"

    def rows(self, x, keep=None):
        return x[:len(self.target.intensity)]

    def loss_terms(self, parts, st):
        return {"intensity": self.value(parts, st)}


class DolpObjective(_Rows):
    """DoLP term of eq:optimization alone, plus one residual, (mean predicted - mean observed intensity) /
    scale, that fixes the overall albedo the DoLP leaves undetermined (0 at the optimum)."""

    name = "dolp"
    #: albedo ratios a_b / a_s tried by the coarse search
    RATIOS = np.logspace(-3, 3, 37)

    def describe_round(self):
        return super().describe_round() + " (DoLP only)"

    def rows(self, x, keep=None):
        """The DoLP rows, then the sum of the intensity rows (those in ``keep``) / sqrt(M)."""
        m = len(self.target.intensity)
        head = x[:m] if keep is None else x[:m][keep[:m]]
        return np.concatenate([x[m:], [head.sum(axis=0) / math.sqrt(m)]])

    def loss_terms(self, parts, st):
        r = self.residuals(parts, st)
        return {"dolp": float(r[:-1] @ r[:-1]), "scale": float(r[-1] ** 2)}

    def row_pixels(self, n_rows):
        return np.concatenate([np.arange(n_rows - 1) % len(self.target.intensity), [0]])

    def albedos(self, parts):
        """Ratio a_b / a_s minimising the DoLP term (a log grid), overall scale from the mean intensity."""
        t = min((float(t) for t in self.RATIOS), key=lambda t: self.score(parts, State({}, 1.0, t)))
        i = parts.surface[0] + t * parts.body[0]
        c = float(np.mean(self.target.intensity)) / max(float(np.mean(i)), 1e-300)
        return c, c * t


#: The loss variants a fit accepts beside ``likelihood`` and ``paper``, by name.
VARIANTS = {c.name: c for c in (IntensityObjective, DolpObjective)}
