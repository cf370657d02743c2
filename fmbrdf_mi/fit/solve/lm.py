"""The one Levenberg-Marquardt of every fit (:func:`levenberg_marquardt`, each fit plugging in its
linearisation, solve and trial) and the reweighting loop around it (IRLS, :func:`reweighted`)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

#: Converged when a full Gauss-Newton step would lower chi^2 by less than this (about 0.1 standard error).
DECREMENT_TOL = 0.01

#: Why the iteration stopped: code -> (converged, the words of :meth:`LMResult.describe`).
REASONS = {"decrement": (True, f"Gauss-Newton decrement < {DECREMENT_TOL:g}"),
           "no_step": (True, "no step lowers the {what} (converged to float32 precision)"),
           "small_decrease": (True, "{what} decrease below {small} twice in a row"),
           "small_step": (True, "step in z < 1e-4"),
           "time_limit": (False, "time limit {time_limit:g} s{per} reached"),
           "max_iter": (False, "max_iter ({max_iter}) reached"),
           "budget": (False, "evaluation budget spent")}


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
        return REASONS[self.reason][0]

    def describe(self, what, small, max_iter, time_limit=None, per=""):
        """Why it stopped, in words: ``what`` the objective's name, ``small`` the decrease tolerance's."""
        return REASONS[self.reason][1].format(what=what, small=small, max_iter=max_iter, time_limit=time_limit or 0,
                                              per=per)


def gn_decrement(J, r, C=None):
    """Decrease of r.r a full Gauss-Newton step predicts: g^T A^-1 g, g = J^T r, A = J^T J or with ``C`` the
    profiled curvature (:func:`profiled_curvature`)."""
    g, A = J.T @ r, J.T @ J
    if C is not None:
        A = profiled_curvature(A, C)
    try:
        return float(g @ np.linalg.lstsq(A, g, rcond=None)[0])
    except np.linalg.LinAlgError:
        return math.inf


#: Floor of 1 - lambda in :func:`profiled_curvature`: the step along a direction at most 1 / this of Gauss-Newton's.
CURVATURE_FLOOR = 0.1


def profiled_curvature(F, C, floor=CURVATURE_FLOOR):
    """F - C with 1 - lambda floored at ``floor`` (lambda the eigenvalues of F^-1/2 C F^-1/2): chi^2's expected
    curvature with the incidental albedos eliminated (C:
    :meth:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos.incidental`), where Gauss-Newton on F converges slowly."""
    w, V = np.linalg.eigh(F)
    if len(w) == 0 or w.min() <= 0:
        return F
    half, inv_half = (V * np.sqrt(w)) @ V.T, (V / np.sqrt(w)) @ V.T
    lam, Q = np.linalg.eigh(inv_half @ C @ inv_half)
    T = half @ Q
    H = (T * np.maximum(1.0 - lam, floor)) @ T.T
    return 0.5 * (H + H.T)


def dense_step(J, r, lam, C=None):
    """The Levenberg-Marquardt step -(A + lam diag(J^T J))^-1 J^T r (Marquardt's scaling), A = J^T J, or with
    ``C`` the incidental albedos' noise term the profiled curvature (:func:`profiled_curvature`)."""
    A, g = J.T @ J, J.T @ r
    D = np.diag(A).copy()
    D[D <= 0] = 1e-12
    if C is not None:
        A = profiled_curvature(A, C)
    return np.linalg.solve(A + lam * np.diag(D), -g)


def broyden(J, dz, dr):
    """Broyden's rank-one secant update of J from a trial that moved z by ``dz`` and r by ``dr``."""
    if dz @ dz > 0 and np.all(np.isfinite(dr)):
        return J + np.outer(dr - J @ dz, dz) / (dz @ dz)
    return J


def levenberg_marquardt(x, f, linearise, solve, trial, *, max_iter=40, lin=None, refresh=1, secant=None,
                        moved=None, decrement=None, decrement_tol=DECREMENT_TOL, small=None, small_count=2,
                        step_small=None, time_up=None, budget=None, on_accept=None, final_linearise=True, lam=1e-3):
    """Minimise from ``x`` (objective ``f``); returns :class:`LMResult`.

    * ``linearise(x)``: the system at ``x``; its ``.f``, if any, replaces the trial's objective;
    * ``solve(lin, lam)``: the damped step (:func:`dense_step`); ``LinAlgError`` raises the damping;

    * ``trial(x, step, lin)``: ``(x_new, f_new, r_new)`` (it may re-solve linear unknowns);
    * ``secant(lin, x, x_new, r_new)``: a Broyden update from every trial; ``moved(lin, x_new, r_new)``: the
      linearisation carried to an accepted point, so ``refresh`` accepted steps share one Jacobian;
    * stops: ``decrement(lin)`` < ``decrement_tol`` on a fresh linearisation, ``small(f_old, f_new)``
      ``small_count`` times in a row, ``step_small(x_old, x_new)``, ``time_up()``, ``max_iter``,
      ``budget()`` spent, or no step lowers f at any damping;
    * ``final_linearise``: end on a fresh linearisation (the uncertainty needs it).
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


def reweighted(x, minimise, *, rounds, before):
    """(x, converged, settled, rounds run) after at most ``rounds`` rounds: ``before(x, k)`` refreshes the
    weights (True: settled), ``minimise(x, k)`` -> (x, converged); a non-converged minimisation ends the rounds."""

    converged, k = False, 0
    for k in range(rounds):
        if before(x, k):
            return x, converged, True, k
        x, converged = minimise(x, k)
        if not converged:
            break
    return x, converged, False, k + 1
