"""Minimising an objective (:mod:`fmbrdf_mi.fit.objective`): bounded reparameterisation, coarse search, LM or Adam.

Unknowns: the model's free shape parameters (for FMBRDF eta, alpha, beta,
kappa, less any held fixed) and its two albedos a_s, a_b (FMBRDF: k_s and
k_b = r_k k_s).  The optimiser works on unconstrained z: shape parameters
through a sigmoid onto their bounds (on a log scale for those spanning
decades, :class:`models.Bounds`), albedos through exp.  So every iterate is
a valid material.

1. **Coarse search** (needs no answer): shape parameters on a grid over the
   box; at each grid point the albedos follow in closed form (the model is
   linear in them: a two-unknown non-negative weighted least squares), and
   the objective decides.  The grid is searched in stages to bound the
   number of BSDF table rebuilds.
2. **Refinement** on the same objective:
   * ``lm`` (default): Levenberg-Marquardt on the objective's residuals, the
     Jacobian from forward-mode Dr.Jit AD through the BSDF for each shape
     parameter and analytic for the albedos;
   * ``adam`` (paper's loss only): Adam (the paper's optimiser) on the
     reverse-mode Dr.Jit gradient of the loss.
3. **Stopping rule** (:func:`levenberg_marquardt`): converged when the
   decrease falls below tolerance twice in a row (the paper's loss:
   relative ``tol``; the likelihood: 0.01 in chi^2) or the Gauss-Newton
   decrement says the optimum is within ~0.1 standard error; *not*
   converged at ``max_iter`` or a time limit.  The wall-clock deadline of
   :class:`Problem` is checked before every model evaluation.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import time

import numpy as np

from . import loss as L
from .models import Bounds


@dataclasses.dataclass
class State:
    """A point of the search: shape values and albedos."""

    shape: dict
    a_s: float
    a_b: float

    def copy(self):
        return State(dict(self.shape), self.a_s, self.a_b)


class TimeUp(Exception):
    """The fit's wall-clock limit would be passed by the next model evaluation."""


class Problem:
    """A model, an evaluator at the fitted pixels, the objective, the bounds, the clock.

    ``objective``: :class:`fmbrdf_mi.fit.objective.PaperObjective` or
    :class:`~fmbrdf_mi.fit.objective.LikelihoodObjective` (a
    :class:`fmbrdf_mi.fit.loss.Target` is wrapped in the former).
    ``fixed``: {shape name: value} held fixed (not estimated).  ``deadline``:
    absolute ``time.time()`` after which no model evaluation may end: each
    evaluation first checks that the slowest one of its kind so far would
    still finish in time, else raises :class:`TimeUp` (so the limit holds
    inside every loop, coarse search included).
    """

    def __init__(self, model, evaluator, objective, bounds=None, progress=None, fixed=None, deadline=None):
        from .objective import PaperObjective

        self.model, self.ev = model, evaluator
        self.obj = PaperObjective(objective) if isinstance(objective, L.Target) else objective
        self.bounds = bounds if isinstance(bounds, Bounds) else Bounds(model, bounds)
        self.progress = progress or (lambda msg: None)
        self.fixed = dict(fixed or {})
        unknown = [k for k in self.fixed if k not in model.shape_names]
        if unknown:
            raise ValueError(f"fixed: {model.name} has no shape parameter {', '.join(unknown)} "
                             f"(it has {', '.join(model.shape_names)})")
        self.names = tuple(n for n in model.shape_names if n not in self.fixed)
        self.n_evals = 0
        self.n_nonfinite = 0
        self.t0 = time.time()
        self.deadline = deadline
        self._cost = {False: 0.0, True: 0.0}
        self._cache = []
        self.current = None     # latest accepted state (what a fit stopped by the clock reports)
        self.both_lobes = {}    # coarse-search point -> both albedos switched on

    # the paper objective's weights, as before (tests and Adam use them)
    @property
    def target(self):
        return self.obj.target

    @property
    def w(self):
        return self.obj.w

    @property
    def outliers(self):
        return self.obj.outliers

    # ---- z <-> state
    def to_z(self, st):
        return np.array([self.bounds.to_z(n, st.shape[n]) for n in self.names]
                        + [math.log(max(st.a_s, 1e-30)), math.log(max(st.a_b, 1e-30))])

    def from_z(self, z):
        shape = dict(self.fixed)
        shape.update({n: self.bounds.to_value(n, z[i]) for i, n in enumerate(self.names)})
        shape = {n: shape[n] for n in self.model.shape_names}
        k = len(self.names)
        return State(shape, math.exp(np.clip(z[k], -60, 60)), math.exp(np.clip(z[k + 1], -60, 60)))

    def state(self, shape, a_s, a_b):
        """A State with the fixed values imposed."""
        return State({n: float(self.fixed.get(n, shape[n])) for n in self.model.shape_names}, a_s, a_b)

    # ---- evaluation
    def time_left(self):
        return None if self.deadline is None else self.deadline - time.time()

    def check_time(self, jac=False):
        if self.deadline is not None and time.time() + self._cost[jac] > self.deadline:
            raise TimeUp()

    def parts(self, st, jac=False):
        key = tuple(round(float(st.shape[n]), 12) for n in self.model.shape_names)
        for k, j, p in self._cache:
            if k == key and (j or not jac):
                return p
        self.check_time(jac)
        t = time.time()
        self.n_evals += 1
        p = self.ev.parts(st.shape, self.names if jac else ())
        self._cost[jac] = max(self._cost[jac], time.time() - t)
        self._cache = [(key, jac, p)] + self._cache[:1]
        return p

    def closed_form(self, shape):
        """(State, parts) of a coarse-search point: the shape values with the albedos in closed form."""
        parts = self.parts(State(shape, 1.0, 1.0))
        a_s, a_b = self.obj.albedos(parts)
        return State(dict(shape), a_s, a_b), parts

    def set_weights(self, parts, st):
        self.obj.refresh(parts, st)

    def loss(self, parts, st, w=None):
        return self.obj.value(parts, st) if w is None else self.obj.value(parts, st, w)

    def residuals_and_jacobian(self, parts, st, z):
        """r (m,) and dr/dz (m, k + 2) of the objective's residuals."""
        r, J, bad = self.obj.residuals_and_jacobian(parts, st, z, self.names, self.bounds)
        if bad is not None and bad.any():
            # a few directions where the BSDF's forward-mode derivative is NaN: those rows are
            # left out of the Jacobian (their residuals still count in the loss)
            J[bad] = 0.0
            self.n_nonfinite = max(self.n_nonfinite, int(parts.nonfinite.sum()))
        J[~np.isfinite(J)] = 0.0
        return r, J


# ---------------------------------------------------------------- closed-form albedos
def solve_albedos(parts, target):
    """Non-negative least squares of the intensities over (a_s, a_b); returns (a_s, a_b)."""
    from .objective import nnls2

    return nnls2(parts.surface[0], parts.body[0], target.intensity)


def _score(problem, parts, st):
    """Objective of a candidate with its own weights (the paper's split; the likelihood's variances)."""
    return problem.obj.score(parts, st)


#: An albedo whose lobe contributes less than this fraction of the other's
#: mean intensity over the fitted pixels counts as switched off.
ALBEDO_BOUND = 1e-3


def search_grids(model, bounds, fixed, names):
    """The coarse search's grids: ({shape parameter: its grid values (one if fixed)},
    the stage-1 parameters, the later ones (eta, kappa, when free), their middle values)."""
    grids = {n: ([fixed[n]] if n in fixed else bounds.clip_grid(n, model.param(n).grid))
             for n in model.shape_names}
    later = [n for n in ("eta", "kappa") if n in names]
    first = [n for n in model.shape_names if n not in later]
    return grids, first, later, {n: grids[n][len(grids[n]) // 2] for n in later}


def coarse_search(problem, keep=2):
    """Grid search in stages; returns candidates [(score, State)] best first.

    Stage 1: every free shape parameter but eta and kappa on its grid, eta
    and kappa at their middle grid values; stage 2: eta on its grid for the
    ``keep`` best; stage 3: kappa on its grid for the ``keep`` best (kappa
    changes the body term least, and is often weakly identifiable: README).
    Each grid point costs one BSDF table rebuild; the albedos follow in
    closed form (the objective's weighted least squares) and the objective
    with the candidate's own weights decides.
    """
    model = problem.model
    grids, first, later, mids = search_grids(model, problem.bounds, problem.fixed, problem.names)
    results = {}

    def try_point(shape):
        key = tuple(round(shape[n], 9) for n in model.shape_names)
        if key in results:
            return
        st, parts = problem.closed_form(shape)
        a_s, a_b = st.a_s, st.a_b
        results[key] = (problem.obj.score(parts, st), st)
        c_s, c_b = a_s * float(np.mean(parts.surface[0])), a_b * float(np.mean(parts.body[0]))
        problem.both_lobes[key] = min(c_s, c_b) >= ALBEDO_BOUND * max(c_s, c_b)
        b = min(results.values(), key=lambda x: x[0])
        problem.current = b[1]

    def best():
        return min(results.values(), key=lambda x: x[0])

    t = time.time()
    combos = list(itertools.product(*[grids[n] for n in first]))
    for j, combo in enumerate(combos):
        try_point({**mids, **dict(zip(first, combo))})
        if (j + 1) % 6 == 0 or j + 1 == len(combos):
            problem.progress(f"[search] stage 1 ({', '.join(first)}): {j + 1}/{len(combos)} grid points, "
                             f"best {best()[0]:.6e} ({time.time() - t:.1f} s)")
    for stage, name in enumerate(later, start=2):
        top = sorted(results.values(), key=lambda x: x[0])[:keep]
        for _, st in top:
            for value in grids[name]:
                try_point({**st.shape, name: value})
        problem.progress(f"[search] stage {stage} ({name}): best {best()[0]:.6e} "
                         f"({time.time() - t:.1f} s, {len(results)} grid points)")
    return sorted(results.values(), key=lambda x: x[0])


# ---------------------------------------------------------------- refinement
def _fmt(problem, st):
    rep = problem.model.report(st.shape, st.a_s, st.a_b)
    return " ".join(f"{k}={v:.4g}" for k, v in rep.items())


#: Likelihood: converged when a full Gauss-Newton step would lower chi^2 by less than this
#: (the estimate is then within ~0.1 standard error of the optimum).
DECREMENT_TOL = 0.01


def gn_decrement(J, r):
    """Decrease of r.r a full Gauss-Newton step predicts: g^T (J^T J)^-1 g, g = J^T r."""
    g = J.T @ r
    try:
        return float(g @ np.linalg.lstsq(J.T @ J, g, rcond=None)[0])
    except np.linalg.LinAlgError:
        return math.inf


def levenberg_marquardt(problem, st, *, max_iter=40, tol=1e-5, time_limit=None, history=None,
                        round_no=0, refresh=3):
    """Minimise the objective from ``st`` with its current weights.

    The Jacobian comes from forward-mode AD at the start and at least every
    ``refresh`` accepted steps; in between it is kept current with Broyden's
    rank-one secant update from every trial point (each AD Jacobian costs one
    table rebuild with AD per shape parameter, a trial point one without).
    A step that fails on a secant Jacobian triggers a fresh AD Jacobian
    before the damping is raised.  Converged: the objective's small-decrease
    test twice in a row, or (likelihood) a Gauss-Newton decrement below
    :data:`DECREMENT_TOL` on a fresh Jacobian, or no step lowers the
    objective at float32 precision.  Returns (State, value, stop reason,
    converged, J, r) with an AD Jacobian at the result.
    """
    obj = problem.obj

    def ad_jacobian(st, z):
        return problem.residuals_and_jacobian(problem.parts(st, jac=True), st, z)

    def trial(st):
        r = obj.residuals(problem.parts(st), st)
        return r, float(r @ r)

    z = problem.to_z(st)
    r, J = ad_jacobian(st, z)
    problem.current = st
    fresh, since_ad = True, 0
    f = float(r @ r)
    lam, small, reason, converged = 1e-3, 0, f"max_iter ({max_iter}) reached", False
    t0 = time.time()
    for it in range(1, max_iter + 1):
        if obj.is_likelihood and fresh and gn_decrement(J, r) < DECREMENT_TOL:
            reason, converged = f"Gauss-Newton decrement < {DECREMENT_TOL:g}", True
            break
        accepted = False
        while lam < 1e10:
            A, g = J.T @ J, J.T @ r
            D = np.diag(A).copy()
            D[D <= 0] = 1e-12
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), -g)
            except np.linalg.LinAlgError:
                lam *= 4
                continue
            z_new = np.clip(z + delta, -40, 40)
            st_new = problem.from_z(z_new)
            r_new, f_new = trial(st_new)
            dz = z_new - z
            if np.all(np.isfinite(r_new)) and dz @ dz > 0:  # Broyden update with what the trial taught
                J = J + np.outer(r_new - r - J @ dz, dz) / (dz @ dz)
            if np.isfinite(f_new) and f_new < f:
                accepted = True
                break
            if not fresh:
                r, J = ad_jacobian(st, z)
                fresh, since_ad = True, 0
            else:
                lam *= 4
        if not accepted:
            reason, converged = "no step lowers the objective (converged to float32 precision)", True
            break
        step = float(np.max(np.abs(z_new - z)))
        was_small = obj.small_decrease(f, f_new, tol)
        z, st, f, r = z_new, st_new, f_new, r_new
        problem.current = st
        fresh = False
        since_ad += 1
        lam = max(lam / 3, 1e-9)
        if history is not None:
            history.append({"stage": f"lm{round_no}", "iter": it, "loss": f,
                            "time": time.time() - problem.t0,
                            "params": problem.model.report(st.shape, st.a_s, st.a_b)})
        problem.progress(f"[lm {round_no}] iter {it:2d}  {obj.name} {f:.6e}  {_fmt(problem, st)}  "
                         f"({time.time() - problem.t0:.1f} s)")
        small = small + 1 if was_small else 0
        if small >= 2:
            reason, converged = "objective decrease below tolerance twice in a row", True
            break
        if step < 1e-4 and not obj.is_likelihood:
            reason, converged = "step in z < 1e-4", True
            break
        if time_limit is not None and time.time() - t0 > time_limit:
            reason = f"time limit {time_limit:g} s per round reached"
            break
        if since_ad >= refresh:
            r, J = ad_jacobian(st, z)
            fresh, since_ad = True, 0
    if not fresh:
        r, J = ad_jacobian(st, z)
    return st, f, reason, converged, J, r


def loss_and_grad_reverse(problem, st):
    """Loss and its gradient (dict over shape names, 'a_s', 'a_b') by reverse-mode AD through the BSDF."""
    import drjit as dr
    import mitsuba as mi

    ev = problem.ev
    xs = {}
    for p in problem.model.shape:
        x = mi.Float(float(st.shape[p.name]))
        dr.enable_grad(x)
        ev._assign(p.key, x)
        xs[p.name] = x
    for name, key, v in (("a_s", problem.model.surface_key, st.a_s), ("a_b", problem.model.body_key, st.a_b)):
        x = mi.Float(float(v))
        dr.enable_grad(x)
        ev._assign(key, x)
        xs[name] = x
    ev.params.update()
    s0, s1, s2 = ev._stokes()
    val = L.loss_dr(problem.obj.target, problem.obj.w, s0, s1, s2)
    dr.backward(val)
    grad = {k: float(dr.grad(x)[0]) for k, x in xs.items()}
    f = float(val[0])
    # restore detached values
    for p in problem.model.shape:
        ev._assign(p.key, float(st.shape[p.name]))
        ev._current[p.name] = float(st.shape[p.name])
    ev.set_albedos(st.a_s, st.a_b)
    return f, grad


def adam(problem, st, *, max_iter=300, lr=0.02, tol=1e-4, patience=40, time_limit=None, history=None,
         round_no=0):
    """Adam on z with the reverse-mode gradient; returns (best State, loss, reason, converged)."""
    z = problem.to_z(st)
    m = np.zeros_like(z)
    v = np.zeros_like(z)
    b1, b2, eps = 0.9, 0.999, 1e-8
    best = (math.inf, st)
    since, reason, t0 = 0, "max_iter", time.time()
    converged = False
    for it in range(1, max_iter + 1):
        st = problem.from_z(z)
        problem.check_time(True)
        t_it = time.time()
        f, g = loss_and_grad_reverse(problem, st)
        problem._cost[True] = max(problem._cost[True], time.time() - t_it)
        gz = np.array([g[n] * problem.bounds.derivative(n, z[j]) for j, n in enumerate(problem.names)]
                      + [g["a_s"] * st.a_s, g["a_b"] * st.a_b])
        if not np.all(np.isfinite(gz)):
            reason = "non-finite gradient"
            break
        if f < best[0] * (1 - tol):
            since = 0
        else:
            since += 1
        if f < best[0]:
            best = (f, st.copy())
            problem.current = best[1]
        if history is not None:
            history.append({"stage": f"adam{round_no}", "iter": it, "loss": f,
                            "time": time.time() - problem.t0,
                            "params": problem.model.report(st.shape, st.a_s, st.a_b)})
        if it % 5 == 0 or it == 1:
            problem.progress(f"[adam {round_no}] iter {it:3d}  loss {f:.6e}  {_fmt(problem, st)}  "
                             f"({time.time() - problem.t0:.1f} s)")
        if since >= patience:
            reason = f"best loss not improved by {tol:g} (relative) in {patience} iterations"
            converged = True
            break
        if time_limit is not None and time.time() - t0 > time_limit:
            reason = f"time limit {time_limit:g} s"
            break
        m = b1 * m + (1 - b1) * gz
        v = b2 * v + (1 - b2) * gz * gz
        mh, vh = m / (1 - b1 ** it), v / (1 - b2 ** it)
        z = np.clip(z - lr * mh / (np.sqrt(vh) + eps), -40, 40)
    return best[1], best[0], reason, converged


def default_progress(msg):
    print(msg, file=sys.stderr, flush=True)
