"""Checks after a fit, each a function of its result (:func:`~fmbrdf_mi.fit.api.fitting.fit` applies those
its options ask for): :func:`check_footprint`, :func:`check_intervals`, :func:`find_other_optima`.  Each
extends a converged pixel-path result's uncertainty block; any other result is returned as it is."""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.api.assemble import assemble, settle
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.solve.driver import EXPLORE_ABOVE, EXPLORE_PIXELS


def checkable(res):
    """Whether ``res`` is a converged pixel-path fit with its ``fitted``."""
    fx = res.fitted
    return fx is not None and res.converged and fx.solution.J is not None


def check_intervals(res, every=False, progress=None):
    """Fisher 95 % intervals of a likelihood fit checked by :func:`~fmbrdf_mi.fit.uncertainty.profile_intervals`
    (``every``: profile every end); skipped past the fit's ``max_time``."""
    if not checkable(res) or not res.fitted.problem.obj.is_likelihood:
        return res
    fx = res.fitted
    say = progress or fx.report
    if fx.deadline is not None and time.time() > fx.deadline:
        fx.applied.append(("profile-skipped", ""))
        return settle(res)
    sol = fx.solution
    fx.applied += U.profile_intervals(fx.problem, sol.state, res.uncertainty, sol.J, sol.r, every=every,
                                      progress=say)
    kinds = res.uncertainty.get("interval_kind", {})
    prof = {n: kinds[n] for n in U.profiled(kinds)}
    if prof:
        say("[fit] profile-likelihood 95 % intervals (the Fisher ones fail there): "
            + ", ".join(f"{n} ({k})" for n, k in prof.items()))
    return settle(res)


def find_other_optima(res, progress=None):
    """The starts' competing optima (:func:`~fmbrdf_mi.fit.uncertainty.other_optima`), intervals widened over them."""
    if not checkable(res):
        return res
    fx, unc = res.fitted, res.uncertainty
    problem, st = fx.problem, fx.solution.state
    optima, threshold = U.other_optima(res.starts, st.shape, unc, problem.names)
    if not optima:
        return res
    unc["other_optima"] = {"optima": optima, "threshold": threshold, "separation_se": U.MODE_SEPARATION_SE}
    text = U.optima_text(optima, threshold)
    if text:
        unc["other_optima"]["warning"] = text
        (progress or fx.report)("[fit] warning: " + text)
    if U.widen_for_optima(unc, st.shape, optima, {n: problem.bounds.lims[n][2:] for n in problem.names}):
        fx.applied.append(("optima", ""))
    return settle(res)


def samplable(data, problem):
    """Whether the quadrature's bias can be estimated from a subset of ``data``'s cells (each cell's residuals
    depend on its own albedos only)."""
    return (data.subsample is not None and data.make_problem is None and data.materials is None
            and problem.obj.prior is None)


def check_footprint(res, progress=None, sample_above=None, sample_pixels=None, seed=None):
    """A likelihood fit of raw samples refitted with 2m x 2m pixel-area points while the bias of m x m
    (:func:`~fmbrdf_mi.fit.uncertainty.quadrature_bias`) exceeds ``QUADRATURE_TOL`` SE, up to
    ``MAX_AREA_POINTS``; records ``uncertainty.quadrature``.  Above ``sample_above`` super-pixels the bias is
    estimated from about ``sample_pixels`` of them (:func:`~fmbrdf_mi.fit.uncertainty.sampled_quadrature_bias`)."""
    if not checkable(res) or res.fitted.data.remake is None or res.fitted.data.area_points <= 1:
        return res
    import drjit as dr

    fx = res.fitted
    say = progress or fx.report
    sample_above = EXPLORE_ABOVE if sample_above is None else sample_above
    sample_pixels = EXPLORE_PIXELS if sample_pixels is None else sample_pixels
    problem, data, st, m, t0 = fx.problem, fx.data, fx.solution.state, fx.data.area_points, time.time()
    block = {"area_points": m, "tolerance_se": U.QUADRATURE_TOL, "checks": []}
    fine_fx, history, coarser_data = None, list(fx.history), None
    rng = np.random.default_rng(fx.options.seed if seed is None else seed)
    while m < U.MAX_AREA_POINTS:
        parts = problem.parts(st, jac=True)
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
        del parts       # its derivatives: a whole frame's, several times over, not wanted beside the finer data
        dr.flush_malloc_cache()     # the solve's freed Dr.Jit buffers, returned before the finer data are made
        cells = fine = None
        check = {"area_points": m, "against": 2 * m}
        if max(map(len, data.image_pixels)) > sample_above and samplable(data, problem):
            if coarser_data is None or coarser_data.area_points != m // 2:
                coarser_data = data.remake(m // 2)
            g_hat = U.predicted_quadrature_terms(problem, fx.problem_of(coarser_data), st, J, r, m, m // 2)
            cells, pi = U.quadrature_sample(problem, J, g_hat, sample_pixels, rng)
            if any(not np.any((cells >= a) & (cells < b)) for a, b in data.slices):
                cells = None        # an image without a sampled cell: the whole check
        if cells is None:
            fine = fx.problem_of(fine_data := data.remake(2 * m))
            check["bias_se"] = bias = U.quadrature_bias(problem, fine, st, J, r)
            worst = max(map(abs, bias.values()), default=0.0)
        else:
            bias, spread = U.sampled_quadrature_bias(problem, fx.problem_of(data.remake(2 * m, cells=cells)), st,
                                                     J, r, cells, pi, g_hat)
            check.update(bias_se=bias, sampled={"pixels": int(len(cells)), "of": int(len(data.pixels)),
                                                "sampling_se": spread})
            worst = max((abs(bias[n]) + U.QUADRATURE_SAMPLING_SE * spread[n] for n in bias), default=0.0)
            say(f"[fit] pixel-area quadrature checked on {len(cells)} of {len(data.pixels)} pixels: "
                f"{worst_bias(bias)} SE (sampling SE up to {max(spread.values(), default=0.0) / 0.75:.2f})")
        block["checks"].append(check)
        if not bias or worst <= U.QUADRATURE_TOL:
            break
        if fine is None:
            fine = fx.problem_of(fine_data := data.remake(2 * m))
        say(f"[fit] pixel-area quadrature: {m} x {m} points per raw pixel bias {worst_bias(bias)} standard errors "
            f"here (the highlight spans few pixels); the fit goes on with {2 * m} x {2 * m}")
        try:
            sol = fx.solve(fine, init=st, starts=1, history=history)
        except InputError:      # max_time reached before one evaluation
            sol = None
        if sol is None or not sol.converged:    # keep the converged coarser fit
            block["refinement"] = f"stopped: the fit with {2 * m} x {2 * m} points did not converge" + (
                "" if sol is None else f" ({sol.reason})")
            say(f"[fit] warning: {block['refinement']}; the estimate is the one with {m} x {m} points")
            break
        fine_fx = dataclasses.replace(
            fx, problem=fine, data=fine_data, history=history, applied=[],
            evaluations=fx.evaluations + problem.n_evals,
            solution=dataclasses.replace(sol, starts=fx.solution.starts, t_search=fx.solution.t_search))
        coarser_data = data        # the next check's prediction: m x m points of all pixels, at hand
        problem, data, m, st = fine, fine_data, 2 * m, sol.state
        block["area_points"] = m
    block["seconds"] = time.time() - t0
    if fine_fx is not None:
        res = assemble(fine_fx)
    res.uncertainty["quadrature"] = block
    m0 = block["checks"][0]["area_points"]
    if m != m0:
        res.fitted.applied.append(("quadrature", f"{m} x {m} points per raw pixel ({m0} x {m0} would bias "
                                                 f"{worst_bias(block['checks'][0]['bias_se'])} SE)"))
    return settle(res)


def worst_bias(bias):
    """'name by about +x.xx': the most biased parameter, its bias in SE (4/3 of
    :func:`~fmbrdf_mi.fit.uncertainty.quadrature_bias`)."""
    worst = max(bias, key=lambda n: abs(bias[n]))
    return f"{worst} by about {bias[worst] / 0.75:+.2f}"
