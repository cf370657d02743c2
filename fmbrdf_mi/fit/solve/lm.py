"""The one Levenberg-Marquardt of every fit, with a pluggable linearisation, linear solve and trial step.

Each fit supplies what differs and nothing else:

* ``linearise(x)``: the system at point ``x`` (residuals and Jacobian, or
  the blocks of the normal refinement's Schur complement); may carry ``.f``,
  the objective it implies (then it replaces the trial's value after a
  re-linearisation);
* ``solve(lin, lam)``: the damped step for damping ``lam`` (dense
  :func:`dense_step`, or :func:`fmbrdf_mi.fit.solve.normal_system.solve_step`);
  a ``numpy.linalg.LinAlgError`` raises the damping;
* ``trial(x, step, lin)``: ``(x_new, f_new, r_new)``, the point a step leads
  to, its objective and residuals (a trial may also re-solve linear unknowns:
  the colour fit's variable projection);
* optionally ``secant(lin, x, x_new, r_new)``: a rank-one update of the
  Jacobian from what every trial taught (Broyden), and ``moved(lin, x_new,
  r_new)``: the linearisation carried to an accepted point (its residuals
  there), so that ``refresh`` > 1 accepted steps can share one Jacobian;
* stopping rules: a Gauss-Newton ``decrement(lin)`` below ``decrement_tol``
  on a fresh linearisation, ``small(f_old, f_new)`` ``small_count`` times in
  a row (2), ``step_small(x_old, x_new)``, ``time_up()``, ``max_iter``, a
  spent ``budget()`` (checked before every linearisation and trial: a
  budget of objective evaluations); and no step lowering the objective at
  any damping (converged to rounding).

The damping starts at ``lam``, falls by 3 after an accepted step (not
below 1e-9) and rises by 4 after a rejected one (giving up at 1e10).  A
rejected step on a secant Jacobian re-linearises before it raises the
damping.  The result says why it stopped (:data:`REASONS`) and whether that
counts as converged; the caller words it.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

#: Converged when a full Gauss-Newton step would lower chi^2 by less than this (the estimate is then
#: within ~0.1 standard error of the optimum).
DECREMENT_TOL = 0.01

#: Why the iteration stopped: code -> converged.
REASONS = {"decrement": True, "no_step": True, "small_decrease": True, "small_step": True, "time_limit": False,
           "max_iter": False, "budget": False}


@dataclasses.dataclass
class LMResult:
    x: object
    f: float
    lin: object          # the linearisation at x when ``fresh``
    fresh: bool
    reason: str          # a key of REASONS
    iterations: int

    @property
    def converged(self):
        return REASONS[self.reason]


def gn_decrement(J, r):
    """Decrease of r.r a full Gauss-Newton step predicts: g^T (J^T J)^-1 g, g = J^T r."""
    g = J.T @ r
    try:
        return float(g @ np.linalg.lstsq(J.T @ J, g, rcond=None)[0])
    except np.linalg.LinAlgError:
        return math.inf


def dense_step(J, r, lam):
    """The Levenberg-Marquardt step -(J^T J + lam diag(J^T J))^-1 J^T r (Marquardt's scaling)."""
    A, g = J.T @ J, J.T @ r
    D = np.diag(A).copy()
    D[D <= 0] = 1e-12
    return np.linalg.solve(A + lam * np.diag(D), -g)


def broyden(J, dz, dr):
    """Broyden's rank-one secant update of J from a trial that moved z by ``dz`` and r by ``dr``."""
    if dz @ dz > 0 and np.all(np.isfinite(dr)):
        return J + np.outer(dr - J @ dz, dz) / (dz @ dz)
    return J


def levenberg_marquardt(x, f, linearise, solve, trial, *, max_iter=40, lin=None, refresh=1, secant=None,
                        moved=None, decrement=None, decrement_tol=DECREMENT_TOL, small=None, small_count=2,
                        step_small=None, time_up=None, budget=None, on_accept=None, final_linearise=True, lam=1e-3):
    """Minimise from ``x`` (objective ``f``); returns :class:`LMResult` (module docstring).

    ``lin``: the linearisation at ``x`` if the caller has it (else made here).
    ``final_linearise``: end with a fresh linearisation at the result (the
    uncertainty needs one).  ``on_accept(it, x, f)`` is called after every
    accepted step.
    """
    if lin is None:
        lin = linearise(x)
    fresh, since, n_small = True, 0, 0
    reason, it = "max_iter", 0
    for it in range(1, max_iter + 1):
        if budget is not None and budget():
            reason = "budget"
            break
        if not fresh and since >= refresh:
            lin = linearise(x)
            fresh, since = True, 0
            if getattr(lin, "f", None) is not None:
                f = lin.f
        if decrement is not None and fresh and decrement(lin) < decrement_tol:
            reason = "decrement"
            break
        accepted = spent = False
        while lam < 1e10:
            if budget is not None and budget():
                spent = True
                break
            try:
                step = solve(lin, lam)
            except np.linalg.LinAlgError:
                lam *= 4
                continue
            x_new, f_new, r_new = trial(x, step, lin)
            if secant is not None:
                lin = secant(lin, x, x_new, r_new)
            if np.isfinite(f_new) and f_new < f:
                accepted = True
                break
            if not fresh:
                lin = linearise(x)
                fresh, since = True, 0
            else:
                lam *= 4
        if not accepted:
            reason = "budget" if spent else "no_step"
            break
        was_small = small is not None and small(f, f_new)
        tiny = step_small is not None and step_small(x, x_new)
        x, f = x_new, f_new
        if moved is not None:
            lin = moved(lin, x_new, r_new)
        fresh = False
        since += 1
        lam = max(lam / 3, 1e-9)
        if on_accept is not None:
            on_accept(it, x, f)
        n_small = n_small + 1 if was_small else 0
        if n_small >= small_count:
            reason = "small_decrease"
            break
        if tiny:
            reason = "small_step"
            break
        if time_up is not None and time_up():
            reason = "time_limit"
            break
    if final_linearise and not fresh:
        lin = linearise(x)
        fresh = True
    return LMResult(x, f, lin, fresh, reason, it)
