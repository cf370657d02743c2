"""The solver of every fit: coarse search, multistart, reweighting rounds, deadline.

:func:`solve` minimises a :class:`~fmbrdf_mi.fit.problem.problem.Problem` from ``init`` or from up to
``starts`` :func:`distinct_starts` of :func:`~fmbrdf_mi.fit.solve.optimise.coarse_search`, refines each
(:func:`refine`), and keeps the best end; a deadline
(:class:`~fmbrdf_mi.fit.problem.problem.TimeUp`) ends it at the latest accepted estimate, not converged.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.problem.problem import TimeUp
from fmbrdf_mi.fit.solve import lm as LM
from fmbrdf_mi.fit.solve import optimise as O


@dataclasses.dataclass
class Solution:
    """Where :func:`solve` ended; ``J``, ``r`` are None after a deadline or Adam."""

    state: object
    reason: str
    converged: bool
    J: object = None
    r: object = None
    starts: list = dataclasses.field(default_factory=list)
    t_search: float = 0.0


def distinct_starts(problem, cands, n):
    """Up to ``n`` starts: the best candidate, then the best differing from all chosen in a shape parameter
    other than eta and kappa (tuned last by the search, so only locally different), both lobes on first."""
    first = [k for k in problem.names if problem.params.row[k].kind == "shape"
             and k not in ("eta", "kappa")] or list(problem.names)
    chosen = [cands[0][1]]
    pool = [c for _, c in cands[1:]]

    def off(c):  # from the coarse search's own evaluation: no table rebuild
        key = tuple(round(c.shape[n], 9) for n in problem.params.shape_names)
        return not problem.both_lobes.get(key, True)

    pool.sort(key=off)  # stable: keeps the score order within each kind
    for c in pool:
        if len(chosen) >= n:
            break
        if all(any(abs(c.shape[k] - o.shape[k]) > 1e-9 for k in first) for o in chosen):
            chosen.append(c)
    return chosen


def step_in_se(problem, st_old, st_new, J):
    """Largest |change| of z between two states in standard errors (from J^T J); 0 with no iterated unknown."""
    if J.shape[1] == 0:
        return 0.0
    try:
        cov = np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.inf
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return float(np.max(np.abs(problem.to_z(st_new) - problem.to_z(st_old)) / sd))


def refine(problem, st, *, rounds, optimizer="lm", max_iter=40, tol=1e-4, time_limit=None, lr=0.02, history=None,
           report=None):
    """At most ``rounds`` reweighting rounds from ``st`` (:func:`~fmbrdf_mi.fit.solve.lm.reweighted`); the
    likelihood's are settled when a round moves the estimate by < 0.05 standard errors.  Returns a
    :class:`Solution` (``J``, ``r`` None for Adam).
    """
    obj = problem.obj
    say = report or (lambda m: None)
    last = Solution(st, "", False)
    step_se = None

    def before(st, k):
        parts = problem.parts(st)
        saved = obj.save()
        if k > 0 and obj.is_likelihood and obj.settled(saved, parts, st, step_se=step_se):
            return True
        obj.refresh(parts, st)
        if k > 0 and not obj.is_likelihood and obj.settled(saved, parts, st):
            obj.restore(saved)
            return True
        say(f"[fit] round {k + 1}: {obj.describe_round()}")
        return False

    def minimise(st_old, k):
        nonlocal step_se
        if optimizer == "lm":
            st, _, last.reason, converged, last.J, last.r = O.levenberg_marquardt(
                problem, st_old, max_iter=max_iter, tol=tol, time_limit=time_limit, history=history, round_no=k + 1)
            step_se = step_in_se(problem, st_old, st, last.J) if last.J is not None else None
        else:
            st, _, last.reason, converged = O.adam(problem, st_old, max_iter=max_iter, lr=lr, tol=tol,
                                                   time_limit=time_limit, history=history, round_no=k + 1)
        return st, converged

    last.state, last.converged, settled, _ = LM.reweighted(st, minimise, rounds=rounds, before=before)
    if obj.is_likelihood and last.converged and not settled and (step_se is None or step_se >= 0.05):
        last.converged = False
        last.reason = (f"IRLS weights not settled after {rounds} rounds (last round moved the estimate "
                       f"by {step_se:.2g} standard errors)")
    return last


def solve(problem, *, init=None, starts=2, rounds, optimizer="lm", max_iter=40, tol=1e-4, time_limit=None, lr=0.02,
          max_time=None, history=None, report=None):
    """Minimise ``problem`` (module docstring); returns a :class:`Solution`.

    ``init``: a State (no coarse search); ``rounds``: reweighting rounds per start; ``max_time``: the
    deadline in seconds, for the message only (the problem owns the deadline); ``history`` (a list) gets
    the search's best point and every accepted step.
    """
    say = report or (lambda m: None)
    params = problem.params
    history = [] if history is None else history
    ends, t_search, t0 = [], 0.0, time.time()
    try:
        if init is not None:
            chosen = [problem.projected(init.shape)[0] if problem.projects else init]
        else:
            cands = O.coarse_search(problem)
            t_search = time.time() - t0
            history.append({"stage": "search", "iter": 0, "loss": cands[0][0], "time": t_search,
                            "params": params.report(cands[0][1].shape, cands[0][1].a_s, cands[0][1].a_b)})
            chosen = distinct_starts(problem, cands, max(1, int(starts)))
        best, t_starts = None, time.time()
        for k, st0 in enumerate(chosen):
            left = O.time_left(time.time() - t_starts, k, len(chosen), "for the starts")
            say(f"[fit] start {k + 1}/{len(chosen)}: {O.format_state(problem, st0)}" + (f" ({left})" if left else ""))
            saved = problem.obj.save()
            end = refine(problem, st0, rounds=rounds, optimizer=optimizer, max_iter=max_iter, tol=tol,
                         time_limit=time_limit, lr=lr, history=history, report=say)
            score = problem.obj.score(problem.parts(end.state), end.state)
            ends.append({"start": params.report(st0.shape, st0.a_s, st0.a_b),
                         "end": params.report(end.state.shape, end.state.a_s, end.state.a_b),
                         "score": score, "converged": end.converged, "reason": end.reason})
            say(f"[fit] start {k + 1} ended at score {score:.6e} ({end.reason})")
            if best is None or score < best[0]:
                best = (score, end, problem.obj.save())
            if k + 1 < len(chosen):
                problem.obj.restore(saved)
        _, out, state = best
        problem.obj.restore(state)
    except TimeUp:
        if problem.current is None:
            raise InputError(f"max_time {max_time:g} s: no model evaluation fits in that time") from None
        out = Solution(problem.current, f"max_time {max_time:g} s reached", False)
    return dataclasses.replace(out, starts=ends, t_search=t_search)


def refit_fixed(problem, st, name, value, start=None, max_iter=10):
    """chi^2 with shape parameter ``name`` held at ``value``, the rest free, under the current weights: one
    point of the profile likelihood (:func:`fmbrdf_mi.fit.uncertainty.profile_intervals`).  From ``start``
    (a State) or ``st`` with ``name`` moved; few LM iterations, as the profile needs chi^2 only roughly.
    None where :meth:`~fmbrdf_mi.fit.problem.problem.Problem.with_fixed` cannot hold it."""
    sub = problem.with_fixed({name: float(value)})
    if sub is None:
        return None
    if start is not None:
        start = sub.state(start.shape, start.a_s, start.a_b)
        if sub.projects:
            start = sub.projected(start.shape)[0]
    else:
        shape = dict(st.shape, **{name: float(value)})
        start = (sub.projected(shape) if sub.projects else sub.closed_form(shape))[0]
    if not sub.names and not sub.projects:   # only the albedos free: closed form
        start = sub.closed_form(start.shape)[0]
        r = sub.obj.residuals(sub.parts(start), start)
        return float(r @ r)
    end, f, *_ = O.levenberg_marquardt(sub, start, max_iter=max_iter, final_jacobian=False)
    return float(f)
