"""Minimising an objective on an unconstrained z (every iterate a valid material): :func:`coarse_search`,
then :func:`levenberg_marquardt` or :func:`adam` (the paper's optimiser)."""
from __future__ import annotations

import itertools
import math
import sys
import time

import numpy as np

from fmbrdf_mi.fit.objectives import loss as L
from fmbrdf_mi.fit.solve import lm as LM


#: A lobe contributing less than this fraction of the other's mean intensity counts as switched off.
ALBEDO_BOUND = 1e-3


def staged_search(shape_names, grids, first, later, mids, evaluate, *, shape_of, keep=2, progress=None):
    """The coarse search's stages, [(score, point)] best first: the ``first`` parameters on their grids, then
    each ``later`` one on its grid for the ``keep`` best points (bounding the BSDF table rebuilds)."""
    results, say, t = {}, progress or (lambda m: None), time.time()

    def try_point(shape):
        key = tuple(round(shape[n], 9) for n in shape_names)
        if key not in results:
            results[key] = evaluate(shape)

    def best():
        return min(results.values(), key=lambda x: x[0])

    combos = list(itertools.product(*[grids[n] for n in first]))
    most = len(combos) + keep * sum(len(grids[n]) for n in later)

    def left():
        return time_left(time.time() - t, len(results), most, "in the search", bound=True)

    for j, combo in enumerate(combos):
        try_point({**mids, **dict(zip(first, combo))})
        if (j + 1) % 6 == 0 or j + 1 == len(combos):
            say(f"[search] stage 1 ({', '.join(first)}): {j + 1}/{len(combos)} grid points, "
                f"best {best()[0]:.6e} ({time.time() - t:.1f} s, {left()})")
    for stage, name in enumerate(later, start=2):
        for _, point in sorted(results.values(), key=lambda x: x[0])[:keep]:
            for value in grids[name]:
                try_point({**shape_of(point), name: value})
        say(f"[search] stage {stage} ({name}): best {best()[0]:.6e} "
            f"({time.time() - t:.1f} s, {len(results)} grid points"
            + (f", {left()})" if stage <= len(later) else ")"))
    return sorted(results.values(), key=lambda x: x[0])


#: How many combined candidates the search of several materials returns (each costs one evaluation).
MATERIAL_CANDIDATES = 6


def coarse_search(problem, keep=2):
    """:func:`staged_search` with closed-form albedos; candidate j combines each material's j-th best point."""

    params, M = problem.params, problem.params.count or 1
    if M == 1:
        model, rows, clip, fixed, names = params, None, problem.bounds.clip_grid, problem.fixed, problem.names
    else:   # material 0's rows under the model's names (all materials share bounds and fixed values)
        model, rows = problem.model, params.shape
        row0 = {r.base: r.name for r in rows if r.material == 0}
        clip = lambda n, g: problem.bounds.clip_grid(row0[n], g)  # noqa: E731
        fixed = {n: problem.fixed[r] for n, r in row0.items() if r in problem.fixed}
        names = [n for n, r in row0.items() if r in problem.names]
    grids = {n: ([fixed[n]] if n in fixed else clip(n, model.param(n).grid)) for n in model.shape_names}
    later = [n for n in ("eta", "kappa") if n in names]
    first = [n for n in model.shape_names if n not in later]
    mids = {n: grids[n][len(grids[n]) // 2] for n in later}
    points, best = {}, [math.inf]

    def at(shape):   # (scores per material, State)
        key = tuple(round(shape[n], 9) for n in model.shape_names)
        if key not in points:
            st, parts = problem.closed_form(shape if rows is None else {r.name: shape[r.base] for r in rows})
            if M == 1:
                c_s, c_b = st.a_s * float(np.mean(parts.surface[0])), st.a_b * float(np.mean(parts.body[0]))
                problem.both_lobes[key] = bool(np.all(np.minimum(c_s, c_b) >= ALBEDO_BOUND * np.maximum(c_s, c_b)))
                points[key] = ([problem.obj.score(parts, st)], st)
            else:
                points[key] = (problem.material_scores(parts, st), st)
            if sum(points[key][0]) < best[0]:
                best[0], problem.current = sum(points[key][0]), st
        return points[key]

    if M == 1:     # the point is the State: the closed form may set more than the grid's values
        return staged_search(model.shape_names, grids, first, later, mids, lambda s: (at(s)[0][0], at(s)[1]),
                             shape_of=lambda st: st.shape, keep=keep, progress=problem.progress)
    ranked = [staged_search(model.shape_names, grids, first, later, mids, lambda s, m=m: (float(at(s)[0][m]), s),
                            shape_of=lambda s: s, keep=keep, progress=problem.progress if m == 0 else None)
              for m in range(M)]
    out = []
    for j in range(min(MATERIAL_CANDIDATES, *map(len, ranked))):
        st, parts = problem.closed_form({r.name: ranked[r.material][j][1][r.base] for r in rows})
        out.append((problem.obj.score(parts, st), st))
    out.sort(key=lambda x: x[0])
    problem.current = out[0][1]
    return out


# ---------------------------------------------------------------- refinement
def format_state(problem, st):
    return " ".join(f"{k}={v:.4g}" for k, v in problem.params.report(st.shape, st.a_s, st.a_b).items())


def time_left(elapsed, done, total, where, bound=False):
    """'~N s left ``where``' at the mean time per unit so far; empty before the first."""
    if done <= 0:
        return ""
    left = elapsed / done * max(total - done, 0)
    return f"{'at most ' if bound else ''}~{left:.{0 if left >= 10 else 1}f} s left {where}"


def log_step(problem, history, name, round_no, it, f, st, say=True, t0=None, max_iter=None, label=None):
    """Log an iterate of optimiser ``name`` to ``history`` (or None) and, if ``say``, to progress."""
    if history is not None:
        history.append({"stage": f"{name}{round_no}", "iter": it, "loss": f, "time": time.time() - problem.t0,
                        "params": problem.params.report(st.shape, st.a_s, st.a_b)})
    if say:
        left = "" if t0 is None else ", " + time_left(time.time() - t0, it, max_iter, "in this round", bound=True)
        tag = label or f"{name} {round_no}"
        problem.progress(f"[{tag}] iter {it:3d}  {problem.obj.name} {f:.6e}  {format_state(problem, st)}  "
                         f"({time.time() - problem.t0:.1f} s{left})")


def levenberg_marquardt(problem, st, *, max_iter=40, tol=1e-5, time_limit=None, history=None,
                        round_no=0, refresh=3, final_jacobian=True, label=None, profiled=False,
                        decrement_tol=LM.DECREMENT_TOL, exact_decrease=False):
    """(State, value, stop reason, converged, J, r) of :func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`
    from ``st`` with the objective's current weights.

    The AD Jacobian is refreshed every ``refresh`` accepted steps with Broyden updates between (every step
    when the albedos are projected: their coordinates jump).  ``profiled``: step on H = J^T J - C
    (:func:`~fmbrdf_mi.fit.solve.lm.profiled_curvature`), Newton's rate where Gauss-Newton's is linear.  A
    likelihood stops when g^T (J^T J)^-1 g, or with ``exact_decrease`` g^T H^-1 g, is below ``decrement_tol``.
    """
    obj, project = problem.obj, problem.projects
    profiled = profiled and problem.eliminates and problem.layout.incidental_reason is None

    def linearise(x):
        st, z = x
        parts = problem.parts(st, jac=True)
        r, J = problem.residuals_and_jacobian(parts, st, z)
        if not profiled:
            return r, J, None
        dcols = obj.albedo_column_derivatives(parts, z, problem.names, problem.bounds)
        return r, J, problem.layout.incidental(*obj.albedo_columns(parts), dcols)

    last = {"accepted": True}

    def trial(x, delta, lin):
        z_new = np.clip(x[1] + delta, -40, 40)
        st_new = problem.from_z(z_new)
        if project:     # an accepted trial is linearised from its own evaluation: after an accepted step the
            # next trial is likely accepted too and evaluates the derivatives with the values, after a rejected one not
            st_new, parts = problem.closed_form(st_new.shape, jac=last["accepted"])
            last["accepted"] = False
            z_new = problem.to_z(st_new)
        else:
            parts = problem.parts(st_new)
        r_new = obj.residuals(parts, st_new)
        return (st_new, z_new), float(r_new @ r_new), r_new

    def secant(lin, x, x_new, r_new):
        return lin[0], LM.broyden(lin[1], x_new[1] - x[1], r_new - lin[0]), None

    def on_accept(it, x, f):
        last["accepted"] = True
        problem.current = x[0]
        log_step(problem, history, "lm", round_no, it, f, x[0], t0=t0, max_iter=max_iter, label=label)

    if project:
        st = problem.closed_form(st.shape)[0]
    z = problem.to_z(st)
    lin, problem.current, t0 = linearise((st, z)), st, time.time()
    res = LM.levenberg_marquardt(
        (st, z), float(lin[0] @ lin[0]), linearise, lambda lin, lam: LM.dense_step(lin[1], lin[0], lam, lin[2]),
        trial, max_iter=max_iter, lin=lin, refresh=1 if project else refresh, secant=None if project else secant,
        moved=None if project else (lambda lin, x_new, r_new: (r_new, lin[1], None)),
        decrement=(lambda lin: LM.gn_decrement(lin[1], lin[0], lin[2] if exact_decrease else None))
        if obj.is_likelihood else None,
        decrement_tol=decrement_tol,
        small=lambda f, f_new: obj.small_decrease(f, f_new, tol),
        step_small=None if obj.is_likelihood else (lambda x, x_new: float(np.max(np.abs(x_new[1] - x[1]))) < 1e-4),
        time_up=None if time_limit is None else (lambda: time.time() - t0 > time_limit),
        on_accept=on_accept, final_linearise=final_jacobian)
    reason = res.describe("objective", "tolerance", max_iter, time_limit, " per round")
    return res.x[0], res.f, reason, res.converged, res.lin[1], res.lin[0]


def loss_and_grad_reverse(problem, st):
    """Loss and its gradient (dict over shape names, 'a_s', 'a_b') by reverse-mode AD through the BSDF."""
    import drjit as dr
    import mitsuba as mi

    ev, model = problem.ev, problem.model
    xs = {}
    for name, key, v in ([(p.name, p.key, st.shape[p.name]) for p in model.shape]
                         + [("a_s", model.surface_key, st.a_s), ("a_b", model.body_key, st.a_b)]):
        x = mi.Float(float(v))
        dr.enable_grad(x)
        ev._assign(key, x)
        xs[name] = x
    ev.params.update()
    s0, s1, s2 = ev._stokes()
    val = L.loss_dr(problem.obj.target, problem.obj.w, s0, s1, s2)
    dr.backward(val)
    grad, f = {k: float(dr.grad(x)[0]) for k, x in xs.items()}, float(val[0])
    for p in problem.model.shape:       # detached values: no graph kept alive
        ev._assign(p.key, float(st.shape[p.name]))
        ev._current[p.name] = float(st.shape[p.name])
    ev.set_albedos(st.a_s, st.a_b)
    return f, grad


def adam(problem, st, *, max_iter=300, lr=0.02, tol=1e-4, patience=40, time_limit=None, history=None,
         round_no=0):
    """:class:`drjit.opt.Adam` on z with the reverse-mode gradient; returns (best State, loss, reason, converged)."""
    import drjit as dr
    import mitsuba as mi

    opt = dr.opt.Adam(lr=lr)
    opt["z"] = mi.Float64(problem.to_z(st))
    best, since, reason, t0, converged = (math.inf, st), 0, "max_iter", time.time(), False
    for it in range(1, max_iter + 1):
        z = np.clip(np.array(opt["z"], dtype=np.float64), -40, 40)
        st = problem.from_z(z)
        f, g = problem.timed(True, loss_and_grad_reverse, problem, st)
        gz = np.array([g[n] * problem.bounds.derivative(n, z[j]) for j, n in enumerate(problem.names)]
                      + [g["a_s"] * st.a_s, g["a_b"] * st.a_b])
        if not np.all(np.isfinite(gz)):
            reason = "non-finite gradient"
            break
        since = 0 if f < best[0] * (1 - tol) else since + 1
        if f < best[0]:
            best = (f, st.copy())
            problem.current = best[1]
        log_step(problem, history, "adam", round_no, it, f, st, say=it % 5 == 0 or it == 1, t0=t0, max_iter=max_iter)
        if since >= patience:
            reason = f"best loss not improved by {tol:g} (relative) in {patience} iterations"
            converged = True
            break
        if time_limit is not None and time.time() - t0 > time_limit:
            reason = f"time limit {time_limit:g} s"
            break
        dr.set_grad(opt["z"], mi.Float64(gz))
        opt.step()
    return best[1], best[0], reason, converged


def default_progress(msg):
    print(msg, file=sys.stderr, flush=True)
