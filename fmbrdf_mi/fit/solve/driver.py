"""The solver of every fit (:func:`solve`): coarse search, multistart, reweighting rounds, deadline; a fit of
many more pixels than the search needs explores on a subsample first (:func:`explore_then_polish`)."""
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
    other than eta and kappa (tuned last by the search, so only locally different)."""
    first = [k for k in problem.names if problem.params.row[k].kind == "shape"
             and k not in ("eta", "kappa")] or list(problem.names)
    chosen = [cands[0][1]]
    # both lobes on first; sorted is stable, so the score order stays
    pool = sorted((c for _, c in cands[1:]), key=lambda c: not problem.both_lobes.get(
        tuple(round(c.shape[k], 9) for k in problem.params.shape_names), True))
    for c in pool:
        if len(chosen) >= n:
            break
        if all(any(abs(c.shape[k] - o.shape[k]) > 1e-9 for k in first) for o in chosen):
            chosen.append(c)
    return chosen


#: Fits of more super-pixels than this (the largest image's) search and run their starts on a subsample of
#: :data:`EXPLORE_PIXELS` pixels first.
EXPLORE_ABOVE = 100_000

#: The pixels of that subsample.
EXPLORE_PIXELS = 30_000

#: Two ends on the subsample at most this many of its standard errors apart (:func:`step_in_se`) are one
#: optimum, continued on all pixels once.
SAME_END_SE = 1.0


def step_in_se(problem, st_old, st_new, J):
    """Largest |change| of z between two states in standard errors (from J^T J); 0 with no iterated unknown."""
    if J.shape[1] == 0:
        return 0.0
    try:
        sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 1e-300, None))
    except np.linalg.LinAlgError:
        return math.inf
    return float(np.max(np.abs(problem.to_z(st_new) - problem.to_z(st_old)) / sd))


def refine(problem, st, *, rounds, optimizer="lm", max_iter=40, tol=1e-4, time_limit=None, lr=0.02, history=None,
           report=None, label="lm", profiled=False):
    """A :class:`Solution` after at most ``rounds`` reweighting rounds from ``st``
    (:func:`~fmbrdf_mi.fit.solve.lm.reweighted`); ``label``: LM's progress tag; ``profiled``: LM's steps on the
    profiled curvature (:func:`~fmbrdf_mi.fit.solve.optimise.levenberg_marquardt`).
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
                problem, st_old, max_iter=max_iter, tol=tol, time_limit=time_limit, history=history, round_no=k + 1,
                label=f"{label} {k + 1}", profiled=profiled)
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
          max_time=None, history=None, report=None, explore=None, explore_above=None, explore_pixels=None):
    """The best :class:`Solution` of ``init`` (a State) or up to ``starts`` :func:`distinct_starts` of the
    coarse search, each refined by :func:`refine`; a deadline ends at the latest accepted estimate, not
    converged.  ``history`` gets the search's best point and every accepted step.  ``explore``: (pixels,
    ``make(n)``: a subsample problem, the largest image's pixels), for :func:`explore_then_polish`.
    """
    explore_above = EXPLORE_ABOVE if explore_above is None else explore_above
    explore_pixels = EXPLORE_PIXELS if explore_pixels is None else explore_pixels
    say = report or (lambda m: None)
    params = problem.params
    history = [] if history is None else history
    ends, done, chosen, t_search, t0 = [], {}, [], 0.0, time.time()
    try:
        sub = None
        if init is not None:
            chosen = [problem.closed_form(init.shape)[0] if problem.projects else init]
        else:
            if (explore is not None and explore[2] > explore_above and problem.deadline is None
                    and optimizer == "lm"):
                sub = explore[1](int(explore_pixels))
                if sub is not None:
                    sub.t0 = problem.t0
                    say(f"[fit] search and starts on a fixed subsample of {int(explore_pixels)} of the {explore[0]} "
                        "pixels; the best ends continue on all of them")
            where = problem if sub is None else sub
            cands = O.coarse_search(where)
            t_search = time.time() - t0
            history.append({"stage": "search", "iter": 0, "loss": cands[0][0], "time": t_search,
                            "params": where.params.report(cands[0][1].shape, cands[0][1].a_s, cands[0][1].a_b)})
            chosen = distinct_starts(where, cands, max(1, int(starts)))
        kw = dict(rounds=rounds, optimizer=optimizer, max_iter=max_iter, tol=tol, time_limit=time_limit, lr=lr,
                  history=history, report=say)
        if sub is not None:
            out, ends = explore_then_polish(problem, sub, chosen, explore[0], say, **kw)
        else:
            out = done[run_starts(problem, enumerate(chosen), done, say, f"/{len(chosen)}", **kw)][1]
    except TimeUp:
        if problem.current is None:
            raise InputError(f"max_time {max_time:g} s: no model evaluation fits in that time") from None
        out = Solution(problem.current, f"max_time {max_time:g} s reached", False)
    ends = ends or [end_record(params, chosen[k], end, score) for k, (score, end) in done.items()]
    return dataclasses.replace(out, starts=ends, t_search=t_search)


def run_starts(problem, starts, done, say, head, where="", **kw):
    """Each (number, State) of ``starts`` refined from the same weights; ``done`` gets {number: (score,
    Solution)}.  Returns the best number, the objective left with its end's weights."""
    starts, best, t0 = list(starts), None, time.time()
    for i, (k, st0) in enumerate(starts):
        left = O.time_left(time.time() - t0, i, len(starts), "for the starts" + where)
        say(f"[fit] start {k + 1}{head}: {O.format_state(problem, st0)}" + (f" ({left})" if left else ""))
        saved = problem.obj.save()
        end = refine(problem, st0, **kw)
        score = problem.obj.score(problem.parts(end.state), end.state)
        done[k] = (score, end)
        say(f"[fit] start {k + 1} ended{where} at score {score:.6e} ({end.reason})")
        if best is None or score < done[best][0]:
            best, weights = k, problem.obj.save()
        problem.obj.restore(saved)
    problem.obj.restore(weights)
    return best


def end_record(params, st0, end, score, end_params=None):
    """A start's entry of :attr:`Solution.starts`: its start, end (reported by ``end_params``) and score."""
    return {"start": params.report(st0.shape, st0.a_s, st0.a_b),
            "end": (end_params or params).report(end.state.shape, end.state.a_s, end.state.a_b),
            "score": score, "converged": end.converged, "reason": end.reason}


def explore_then_polish(problem, sub, chosen, pixels, say, **kw):
    """The starts ``chosen`` refined on ``sub`` (a subsample of ``problem``'s pixels), then each distinct end
    (:func:`same_end`) continued on all pixels; returns (the best Solution of all pixels, the starts' entries).

    The subsample's objective is the same likelihood of fewer pixels, so it decides only where the fit starts;
    no estimate of the subsample is returned.  The continuation steps on the profiled curvature: its start lies
    a few standard errors off along the η–α–β–κ ridge, where Gauss-Newton converges slowly; it stops, as every
    fit does, when the Newton step is under 0.1 of the reported (incidental-sandwich) standard error.
    """
    sub_ends = {}
    run_starts(sub, enumerate(chosen), sub_ends, say, f"/{len(chosen)} on the subsample", " on the subsample",
               **dict(kw, label="subsample lm"))
    order = sorted(range(len(sub_ends)), key=lambda i: sub_ends[i][0])
    optimum = {}        # start -> the best start at its optimum
    for i in order:
        end = sub_ends[i][1]
        optimum[i] = next((j for j in dict.fromkeys(optimum.values())
                           if same_end(sub, sub_ends[j][1], end)), i)
    continued, polished = [], {}
    optima = list(dict.fromkeys(optimum[i] for i in order))
    for j in optima:        # albedos re-solved on all pixels (one optimum: with LM's first derivatives)
        e = sub_ends[j][1].state
        continued.append((j, problem.closed_form(e.shape, jac=len(optima) == 1)[0] if problem.projects
                          else problem.state(e.shape, e.a_s, e.a_b)))
    out = polished[run_starts(problem, continued, polished, say, f" continued on all {pixels} pixels",
                              " on all pixels", **dict(kw, profiled=True))][1]
    ends = [end_record(sub.params, st0, polished[optimum[k]][1], polished[optimum[k]][0], problem.params)
            for k, st0 in enumerate(chosen)]
    return out, ends


def same_end(sub, a, b):
    """Whether the ends ``a`` (the better), ``b`` are at most :data:`SAME_END_SE` of ``a``'s SE apart."""
    if a.J is None:
        return False
    return step_in_se(sub, a.state, b.state, a.J) <= SAME_END_SE


def refit_fixed(problem, st, name, value, start=None, max_iter=10, label=None, tol=LM.DECREMENT_TOL):
    """(chi^2, evaluations): one profile-likelihood point, chi^2 with ``name`` held at ``value`` and the rest
    refitted (to within ``tol``) from ``start`` or ``st``; None where
    :meth:`~fmbrdf_mi.fit.problem.problem.Problem.with_fixed` cannot hold it."""
    sub = problem.with_fixed({name: float(value)})
    if sub is None:
        return None
    if start is not None:
        start = sub.state(start.shape, start.a_s, start.a_b)
        if sub.projects:
            start = sub.closed_form(start.shape)[0]
    else:
        shape = dict(st.shape, **{name: float(value)})
        start = sub.closed_form(shape)[0]
    if not sub.names and not sub.projects:

        start = sub.closed_form(start.shape)[0]
        r = sub.obj.residuals(sub.parts(start), start)
        return float(r @ r), sub.n_evals
    end, f, *_ = O.levenberg_marquardt(sub, start, max_iter=max_iter, final_jacobian=False,
                                       label=label or f"profile {name}", profiled=True, decrement_tol=tol,
                                       exact_decrease=True)
    return float(f), sub.n_evals
