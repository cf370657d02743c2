"""Fits of many pixels search and run their starts on a seeded subsample, then continue on all pixels
(:func:`fmbrdf_mi.fit.solve.driver.explore_then_polish`): the estimate is the all-pixel optimum, never the
subsample's; below the threshold the fit is the one without a subsample, number for number.  Small captures
with the threshold lowered through :func:`~fmbrdf_mi.fit.solve.driver.solve`'s parameters."""
import dataclasses

import numpy as np
import pytest

from conftest import textured_capture

from fmbrdf_mi.fit.api.options import FitOptions
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.problem.data import prepare
from fmbrdf_mi.fit.solve import driver as D
from fmbrdf_mi.fit.solve import lm as LM

SHAPE = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
RES = 32


@pytest.fixture(scope="module")
def obs():
    """A textured sphere under camera noise: each subsample's optimum differs from all pixels' by its noise."""
    return textured_capture(SHAPE, RES, seed=3)


def problem_of(obs, max_pixels=None, report=None):
    """A fresh problem (its own objective and weights) of ``max_pixels`` seeded pixels of ``obs`` (None: all)."""
    opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=max_pixels)
    data = prepare([obs], opts, "likelihood", single=True)
    return data.problem(get_model(opts.model), opts.bounds, report, opts.fixed, None), len(data.pixels)


def obs_pixels(obs):
    return prepare([obs], dataclasses.replace(FitOptions(), max_pixels=None), "likelihood", single=True).pixels


def run(problem, **kw):
    return D.solve(problem, starts=2, rounds=3, max_iter=40, tol=1e-4, **kw)


def sandwich_se(problem, sol):
    """The reported standard errors of the free shape parameters in z: the incidental sandwich H^-1 F H^-1
    (F = J^T J, H = F - C) at the solution, whose inverse is the metric of LM's Gauss-Newton decrement."""
    from fmbrdf_mi.fit import uncertainty as U

    C = U.incidental_term(problem, sol.state, problem.parts(sol.state, jac=True))
    return np.sqrt(np.diag(U.incidental_sandwich(sol.J.T @ sol.J, C)[0]))


def irls_optimum(problem, st, se, rounds=3):
    """The reweighting's fixed point near ``st``: the weights refreshed at each end and the profiled LM run with
    its decrement stop 100 times tighter (the Newton step 0.01 of ``se``) and no chi^2-decrease stop, until a round
    moves no parameter by 0.01 ``se`` (or after ``rounds``)."""
    from fmbrdf_mi.fit.solve import optimise as O

    problem.obj.small_decrease = lambda *a: False
    for _ in range(rounds):
        old = problem.to_z(st)
        problem.obj.refresh(problem.parts(st), st)
        st = O.levenberg_marquardt(problem, st, max_iter=60, profiled=True, decrement_tol=1e-4)[0]
        if np.all(np.abs(problem.to_z(st) - old) < 0.01 * se):
            break
    return st


def score(problem, st):
    return problem.obj.score(problem.parts(st), st)


@pytest.fixture(scope="module")
def fits(obs):
    full, n = problem_of(obs)
    ref = run(full)
    lines = []
    big, _ = problem_of(obs, report=lines.append)
    made = []

    def make(m):
        made.append(problem_of(obs, m, report=lines.append)[0])
        return made[-1]

    explored = run(big, explore=(n, make, n), explore_above=n // 2, explore_pixels=n // 2, report=lines.append)
    sub_alone = run(problem_of(obs, n // 2)[0])
    tight = irls_optimum(problem_of(obs)[0], explored.state, sandwich_se(full, ref))
    return dict(full=full, ref=ref, big=big, explored=explored, sub=made, sub_alone=sub_alone, n=n, lines=lines,
                tight=tight)


def test_explored_fit_ends_at_the_all_pixel_optimum(fits):
    """An optimum of all pixels at least as good as an independent fit's: a score no higher than that fit's
    (the η–α–β–κ ridge of this capture holds two optima about one standard error apart, and the two fits may
    end at different ones), each shape parameter within 0.2 of its reported standard error
    (:func:`sandwich_se`) in z of the reweighting's fixed point reached from it with LM's stop 100 times tighter
    (LM's decrement < 0.01 bounds the Newton step to 0.1 of it), and the decrement of all pixels'
    system at the explored estimate, computed here, below LM's tolerance."""
    full, ref, big, sol, tight = fits["full"], fits["ref"], fits["big"], fits["explored"], fits["tight"]
    assert len(fits["sub"]) == 1 and ref.converged and sol.converged
    se = sandwich_se(full, ref)
    dz = full.to_z(sol.state) - full.to_z(tight)
    assert np.all(np.abs(dz) <= 0.2 * se), (dz / se, sol.state.shape, tight.shape)
    # all pixels' residuals and Jacobian at the estimate, under the weights the fit ended with
    st = big.closed_form(sol.state.shape)[0]
    r, J = big.residuals_and_jacobian(big.parts(st, jac=True), st, big.to_z(st))
    assert len(r) == len(ref.r) == len(sol.r) and LM.gn_decrement(J, r) < LM.DECREMENT_TOL
    independent = score(full, ref.state)
    best = min(independent, score(full, tight))
    for s in sol.starts:        # each start's end is a converged end of all pixels, scored there
        assert s["converged"] and s["score"] >= best - 0.02, (s, best)
    assert min(s["score"] for s in sol.starts) <= independent + 0.02
    assert sol.state.shape in [s["end"] for s in sol.starts]


def test_the_subsample_estimate_is_never_returned(fits):
    """The subsample's own optimum (an independent fit of it alone) is many LM tolerances away from the
    explored estimate, which is all pixels' (test above): the subsample only chose the start."""
    full, ref, sol, alone = fits["full"], fits["ref"], fits["explored"], fits["sub_alone"]
    se = sandwich_se(full, ref)
    far = np.abs(full.to_z(alone.state) - full.to_z(sol.state)) / se
    near = np.abs(full.to_z(sol.state) - full.to_z(fits["tight"])) / se
    assert far.max() > 3 * max(near.max(), 0.1), (far, near)
    # the albedos too are all pixels': one pair per fitted pixel
    assert np.size(sol.state.a_s) == fits["n"] == np.size(ref.state.a_s)


def test_progress_says_where_each_phase_runs(fits):
    lines = fits["lines"]
    assert any(ln.startswith("[fit] search and starts on a fixed subsample") for ln in lines), lines
    assert any(ln.startswith("[subsample lm 1] iter") for ln in lines), lines
    assert any(ln.startswith("[lm 1] iter") for ln in lines), lines
    assert 1 <= sum("continued on all" in ln for ln in lines) <= 2, lines


def test_below_the_threshold_the_fit_is_the_plain_one(obs, fits):
    """With no more pixels than ``explore_above`` the subsample is never made: every number as without it."""
    p, n = problem_of(obs)
    sol = run(p, explore=(n, lambda m: pytest.fail("subsample made below the threshold"), n),
              explore_above=n)
    ref = fits["ref"]
    assert sol.state.shape == ref.state.shape and np.array_equal(sol.state.a_s, ref.state.a_s)
    assert sol.starts == ref.starts


def test_distinct_optima_on_the_subsample_are_each_continued():
    """Ends more than SAME_END_SE of the subsample's standard errors apart are continued separately; closer
    ones once, the better one's (the grouping of :func:`explore_then_polish`)."""
    J = np.eye(2)                     # unit standard errors in z

    class P:
        def to_z(self, st):
            return np.asarray(st, float)

    class S:
        def __init__(self, z):
            self.state, self.J = z, J

    assert D.same_end(P(), S([0.0, 0.0]), S([0.5, -0.5]))
    assert not D.same_end(P(), S([0.0, 0.0]), S([0.0, 1.5]))


@pytest.mark.parametrize("lights", [1, 3])
def test_fit_explores_above_the_threshold(obs, lights, monkeypatch):
    """``fit()`` of one image or a joint fit of several: above :data:`~fmbrdf_mi.fit.solve.driver.EXPLORE_ABOVE`
    pixels the search runs on a subsample of :data:`~fmbrdf_mi.fit.solve.driver.EXPLORE_PIXELS` of them (the
    data's own ``subsample``), and the fit ends converged on all of its pixels."""
    from fmbrdf_mi.fit import fit

    observations = obs if lights == 1 else [obs] * lights
    monkeypatch.setattr(D, "EXPLORE_ABOVE", 100)
    monkeypatch.setattr(D, "EXPLORE_PIXELS", 200)
    lines = []
    res = fit(observations, albedo="per-pixel", max_pixels=None, intervals="fisher", starts=1, progress=lines.append)
    assert res.converged and res.n_pixels == lights * len(obs_pixels(obs)) > 400, (res.stop_reason, res.n_pixels)
    assert any(ln.startswith("[fit] search and starts on a fixed subsample of 200 of the") for ln in lines), lines
    assert any(ln.startswith("[lm 1] iter") for ln in lines), lines


def test_a_joint_fit_counts_each_pixel_once(obs, monkeypatch):
    """The threshold is on the super-pixels of an image, as the albedo maps count them: three images of n
    super-pixels each (3n pixels in all) with the threshold at n run the plain fit, no subsample."""
    from fmbrdf_mi.fit import fit

    monkeypatch.setattr(D, "EXPLORE_ABOVE", len(obs_pixels(obs)))
    monkeypatch.setattr(D, "EXPLORE_PIXELS", 200)
    lines = []
    res = fit([obs] * 3, albedo="per-pixel", max_pixels=None, intervals="fisher", starts=1, progress=lines.append)
    assert res.converged and res.n_pixels == 3 * len(obs_pixels(obs)), (res.stop_reason, res.n_pixels)
    assert not any("subsample" in ln for ln in lines), lines


def test_a_start_near_the_optimum_converges_in_few_profiled_steps(obs):
    """The continuation's start lies a few standard errors from all pixels' optimum, mostly along the
    direction where the eliminated albedos' noise is most of J^T J (the subsample's error is largest there):
    Gauss-Newton on J^T J converges linearly there, the profiled step (J^T J - C) in fewer steps, to the same
    optimum (within LM's tolerance: a fraction of a standard error)."""
    from fmbrdf_mi.fit import uncertainty as U
    from fmbrdf_mi.fit.solve import optimise as O

    p, _ = problem_of(obs)
    st0 = p.closed_form(dict(SHAPE))[0]
    p.obj.refresh(p.parts(st0), st0)
    st, f, _, converged, J, _ = O.levenberg_marquardt(p, st0, max_iter=60)
    assert converged
    F = J.T @ J
    w, V = np.linalg.eigh(F)
    R = V / np.sqrt(w)                                  # F^-1/2 = R V^T
    share, Q = np.linalg.eigh(R.T @ U.incidental_term(p, st, p.parts(st, jac=True)) @ R)
    assert share[-1] > 0.5          # the slow direction exists: C is most of F's curvature along it
    v = R @ Q[:, -1]
    se = np.sqrt(np.diag(np.linalg.inv(F)))
    iterations = {}
    for profiled in (False, True):
        for sign in (-1, 1):
            z0 = p.to_z(st) + sign * 3 * v / np.sqrt(v @ F @ v)        # 3 standard errors along it
            hist = []
            end, f_end, _, ok, *_ = O.levenberg_marquardt(p, p.closed_form(p.from_z(z0).shape)[0], max_iter=60,
                                                          history=hist, profiled=profiled)
            assert ok and f_end < f + 0.1
            assert np.all(np.abs(p.to_z(end) - p.to_z(st)) < 0.5 * se)
            iterations[profiled, sign] = len(hist)
    assert all(iterations[True, s] <= 6 and iterations[True, s] + 3 <= iterations[False, s] for s in (-1, 1)), \
        iterations
