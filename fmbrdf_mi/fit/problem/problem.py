"""A fit's problem: the data it runs on (:class:`FitData`) and the problem over the unconstrained z
(:class:`Problem`: model, evaluator, objective, bounds, clock)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
from fmbrdf_mi.fit.evaluate.models import Bounds, State
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.objectives import loss as L
from fmbrdf_mi.fit.objectives.objective import PaperObjective


class TimeUp(Exception):
    """The fit's wall-clock limit would be passed by the next model evaluation."""


class Problem:
    """A parameter table, an evaluator at the fitted pixels, the objective, the bounds, the clock; ``names``:
    the free shape parameters, ``deadline``: ``time.time()`` after which no model evaluation may end."""

    def __init__(self, params, evaluator, objective, progress=None, deadline=None, cell_material=None):
        self.params = params if isinstance(params, Parameters) else Parameters(params)
        self.model, self.ev = self.params.model, evaluator
        self.obj = PaperObjective(objective) if isinstance(objective, L.Target) else objective
        self.bounds = Bounds(self.params)
        self.progress = progress or (lambda msg: None)
        self.fixed = {r.name: r.fixed for r in self.params.shape if r.fixed is not None}
        self.names = tuple(r.name for r in self.params.shape if r.fixed is None)
        self.n_evals = 0
        self.n_nonfinite = 0
        self.t0 = time.time()
        self.deadline = deadline
        self._cost = {False: 0.0, True: 0.0}
        self._cache = []
        self.current = None     # latest accepted state
        self.both_lobes = {}    # coarse-search point -> both albedos switched on
        self.albedos_now = (1.0, 1.0)
        self.cell_material = None if cell_material is None else np.asarray(cell_material, dtype=np.int64)

    def with_fixed(self, values):
        """The same problem with ``values`` held fixed too and no deadline (None for subclasses), sharing
        this problem's cached evaluations."""
        if type(self) is not Problem:
            return None
        sub = Problem(self.params.with_fixed(values), self.ev, self.obj, self.progress,
                      cell_material=self.cell_material)
        sub._cache = list(self._cache)
        return sub

    def material_scores(self, parts, st):
        """(M,) the negative log-likelihood of each material's own cells; they sum to the whole's."""
        per_cell = 0.5 * np.sum(self.obj.nll_terms(parts, st), axis=1)
        return np.bincount(self.cell_material, weights=per_cell, minlength=self.params.count)

    # z = (free shape parameters through the bounds), with no layout then (log a_s, log a_b)
    @property
    def layout(self):
        return self.obj.layout

    @property
    def projects(self):
        """Whether the albedos are eliminated by variable projection: z is then the free shape parameters only."""
        return self.layout is not None

    @property
    def eliminates(self):
        """Whether the eliminated albedos are maps (no rows of the parameter table)."""
        return self.projects and not self.params.albedo_names

    def n_eliminated(self, st):
        """How many albedos the data spent unknowns on outside z."""
        return self.layout.free() if self.projects else 0

    def to_z(self, st):
        z = [self.bounds.to_z(n, st.shape[n]) for n in self.names]
        if self.projects:
            self.albedos_now = (st.a_s, st.a_b)
            return np.array(z)
        return np.array(z + [math.log(max(st.a_s, 1e-30)), math.log(max(st.a_b, 1e-30))])

    def from_z(self, z):
        shape = dict(self.fixed)
        shape.update({n: self.bounds.to_value(n, z[i]) for i, n in enumerate(self.names)})
        shape = {n: shape[n] for n in self.params.shape_names}
        k = len(self.names)
        if self.projects:
            return State(shape, *self.albedos_now)
        return State(shape, math.exp(np.clip(z[k], -60, 60)), math.exp(np.clip(z[k + 1], -60, 60)))

    def state(self, shape, a_s, a_b):
        """A State with the fixed values imposed."""
        return State({n: float(self.fixed.get(n, shape[n])) for n in self.params.shape_names}, a_s, a_b)

    def timed(self, jac, evaluate, *args):
        """``evaluate(*args)``; raises :class:`TimeUp` first if the slowest evaluation of its kind so far would
        end past the deadline."""
        if self.deadline is not None and time.time() + self._cost[jac] > self.deadline:
            raise TimeUp()
        t = time.time()
        out = evaluate(*args)
        self._cost[jac] = max(self._cost[jac], time.time() - t)
        return out

    def parts(self, st, jac=False):
        """The model's :class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts` at ``st``, from a two-entry cache."""
        key = tuple(round(float(st.shape[n]), 12) for n in self.params.shape_names)
        for k, j, p in self._cache:
            if k == key and (j or not jac):
                return p
        if jac:     # one point's derivatives held at a time (a frame's are large)
            self._cache = [e for e in self._cache if not e[1]]
        p = self.timed(jac, self.ev.parts, st.shape, self.names if jac else ())
        self.n_evals += 1
        self._cache = [(key, jac, p)] + self._cache[:1]
        return p

    def closed_form(self, shape, jac=False):
        """(State, parts) at ``shape`` with the albedos in closed form."""
        parts = self.parts(State(shape, 1.0, 1.0), jac)
        a_s, a_b = self.obj.albedos(parts)
        return State(dict(shape), a_s, a_b), parts

    def with_albedo_rows(self, st, parts, names, cov, scale, to_reported):
        """(names, covariance) of ``names`` (``cov``; ``to_reported``: d z / d theta) with the eliminated albedos
        appended as the table's rows (:meth:`~fmbrdf_mi.fit.evaluate.albedos.GroupAlbedos.joint_covariance`)."""
        J = self.obj.shape_jacobian(parts, st, self.to_z(st), self.names, self.bounds) @ to_reported
        J[~np.isfinite(J)] = 0.0
        C = self.layout.joint_covariance(*self.obj.albedo_columns(parts), J, cov, scale)
        a, rows, p = np.column_stack([st.a_s, st.a_b]).ravel(), self.params.albedo_names, len(names)

        def at(x):
            rp = self.params.report(st.shape, x[0::2], x[1::2])
            return np.array([rp[n] for n in rows])

        D = np.eye(p + len(rows), p + len(a))
        for j, e in enumerate(np.diag(1e-6 * np.maximum(np.abs(a), 1e-6))):   # a step also where an albedo is 0
            D[p:, p + j] = (at(a + e) - at(a - e)) / (2 * e[j])
        return list(names) + list(rows), D @ C @ D.T

    def set_weights(self, parts, st):
        self.obj.refresh(parts, st)

    def residuals_and_jacobian(self, parts, st, z):
        """r (m,) and dr/dz (m, len(z)) of the objective's residuals (Kaufman's projection with a layout)."""
        r, J, bad = self.obj.residuals_and_jacobian(parts, st, z, self.names, self.bounds)
        if bad is not None and bad.any():
            # NaN derivatives: the rows leave J, their residuals still count
            J[bad] = 0.0
            self.n_nonfinite = max(self.n_nonfinite, int(parts.nonfinite.sum()))
        J[~np.isfinite(J)] = 0.0
        return r, J


@dataclasses.dataclass
class FitData:
    """What one fit runs on (:func:`fmbrdf_mi.fit.problem.data.prepare`): ``pixels`` the fitted super-pixels'
    flat indices, image by image, ``slices`` each image's (start, stop) among them."""

    loss: str
    pixels: np.ndarray
    excluded: dict
    objective: object
    samples: object
    evaluator: object
    image_pixels: list = None
    slices: list = None
    make_problem: object = None
    #: several materials: ``{"labels": (H, W), "count": M, "cell_material": (cells,), "pixels": [per material]}``
    materials: dict = None
    #: likelihood: m of the m x m points per sample over which the model is averaged
    area_points: int = None
    #: m -> the same data with m x m points per sample; None: cannot be remade
    remake: object = None
    #: n -> the same data on a seeded subsample of n pixels, or None
    subsample: object = None

    def problem(self, model, bounds, progress, fixed, deadline):
        """The :class:`Problem` of these data (``make_problem``'s when it is set)."""
        if self.make_problem is not None:
            return self.make_problem(model, self.evaluator, self.objective, bounds, progress, fixed, deadline)
        layout, mat = self.objective.layout, self.materials or {}
        maps = isinstance(layout, PixelAlbedos)
        params = Parameters(model, materials=mat.get("count"), maps=maps, bounds=bounds, fixed=fixed,
                            channels=None if layout is None or maps or mat else layout.labels)
        return Problem(params, self.evaluator, self.objective, progress, deadline, mat.get("cell_material"))

