"""The one Levenberg-Marquardt (fmbrdf_mi/fit/solve/lm.py) on problems whose answers are known in closed form.

The fits (mono, joint, free powers, colour, normal refinement) all run this
loop with their own linearisation, linear solve and trial step; here it runs
on small NumPy least-squares problems, each checked against an independent
answer: the generating parameters of noise-free data, a linear least-squares
solution from ``numpy.linalg.lstsq``, the secant condition, and the stopping
rules' contracts.
"""
from __future__ import annotations

import numpy as np
import pytest

from fmbrdf_mi.fit.solve import lm as LM

T = np.linspace(0.0, 4.0, 25)
TRUTH = np.array([2.0, 0.7, 0.3])          # y = a exp(-b t) + c


def model(p):
    return p[0] * np.exp(-p[1] * T) + p[2]


def jac(p):
    e = np.exp(-p[1] * T)
    return np.stack([e, -p[0] * T * e, np.ones_like(T)], 1)


class Lin:
    def __init__(self, r, J):
        self.r, self.J = r, J


def problem(y, count=None):
    def linearise(p):
        if count is not None:
            count.append(1)
        return Lin(model(p) - y, jac(p))

    def trial(p, step, lin):
        q = p + step
        r = model(q) - y
        return q, float(r @ r), r

    return linearise, trial


def dense(lin, lam):
    return LM.dense_step(lin.J, lin.r, lam)


def test_recovers_noise_free_parameters_and_stops_on_the_decrement():
    y = model(TRUTH)
    linearise, trial = problem(y)
    p0 = np.array([1.0, 0.2, 0.0])
    r0 = model(p0) - y
    res = LM.levenberg_marquardt(p0, float(r0 @ r0), linearise, dense, trial, max_iter=100,
                                 decrement=lambda lin: LM.gn_decrement(lin.J, lin.r), decrement_tol=1e-20)
    assert res.converged and res.reason in ("decrement", "no_step")
    np.testing.assert_allclose(res.x, TRUTH, rtol=1e-7)
    assert res.fresh    # the uncertainty needs a linearisation at the result


def test_linear_problem_reaches_the_lstsq_solution():
    """A linear model: the minimum is numpy's least-squares solution, whatever the start."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 4))
    y = rng.normal(size=40)
    best = np.linalg.lstsq(A, y, rcond=None)[0]

    def linearise(p):
        return Lin(A @ p - y, A)

    def trial(p, step, lin):
        q = p + step
        r = A @ q - y
        return q, float(r @ r), r

    p0 = np.full(4, 10.0)
    r0 = A @ p0 - y
    # linear: the Gauss-Newton decrement is exactly f - f_min, so stopping below 1e-20 leaves |x - best| of
    # order sqrt(1e-20 / smallest eigenvalue of A^T A) ~ 1e-10
    res = LM.levenberg_marquardt(p0, float(r0 @ r0), linearise, dense, trial, max_iter=200,
                                 decrement=lambda lin: LM.gn_decrement(lin.J, lin.r), decrement_tol=1e-20)
    assert res.converged
    np.testing.assert_allclose(res.x, best, rtol=1e-8, atol=1e-9)


def test_a_different_linear_solve_gives_the_same_iterates():
    """The solve is pluggable: the normal equations solved by lstsq on the stacked damped system give the
    same step as the dense solve, hence the same path (as the normal refinement's Schur complement must),
    to the same optimum.  What the method guarantees is the path while the steps are above rounding: once
    an iterate's objective is within 1e-12 of the end's (relative), further accepted steps are rounding-level
    decreases whose number depends on the linear algebra library, so the paths are compared up to there."""
    y = model(TRUTH) + 0.01 * np.sin(7 * T)

    def stacked(lin, lam):
        A = lin.J.T @ lin.J
        D = np.sqrt(lam * np.maximum(np.diag(A), 1e-12))
        K = np.vstack([lin.J, np.diag(D)])
        return np.linalg.lstsq(K, -np.concatenate([lin.r, np.zeros(3)]), rcond=None)[0]

    out = []
    for solve in (dense, stacked):
        linearise, trial = problem(y)
        p0 = np.array([1.0, 0.2, 0.0])
        r0 = model(p0) - y
        path, values = [], []
        res = LM.levenberg_marquardt(p0, float(r0 @ r0), linearise, solve, trial, max_iter=30,
                                     on_accept=lambda it, x, f: (path.append(x.copy()), values.append(f)))
        assert res.reason != "max_iter", res.reason
        settled = next(k for k, f in enumerate(values) if f - values[-1] <= 1e-12 * values[-1])
        out.append((res, np.array(path[:settled + 1])))
    (a, pa), (b, pb) = out
    assert len(pa) == len(pb) >= 3
    np.testing.assert_allclose(pa, pb, rtol=1e-8)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-8)       # the same optimum


def test_secant_updates_share_linearisations_and_reach_the_same_minimum():
    y = model(TRUTH) + 0.02 * np.cos(5 * T)
    results = {}
    for refresh in (1, 3):
        calls, steps = [], []
        linearise, trial = problem(y, calls)
        p0 = np.array([1.0, 0.2, 0.0])
        r0 = model(p0) - y

        def secant(lin, x, x_new, r_new):
            return Lin(lin.r, LM.broyden(lin.J, x_new - x, r_new - lin.r))

        res = LM.levenberg_marquardt(p0, float(r0 @ r0), linearise, dense, trial, max_iter=200, refresh=refresh,
                                     secant=secant if refresh > 1 else None,
                                     moved=lambda lin, x_new, r_new: Lin(r_new, lin.J),
                                     decrement=lambda lin: LM.gn_decrement(lin.J, lin.r), decrement_tol=1e-16,
                                     on_accept=lambda it, x, f: steps.append(it))
        results[refresh] = (res, len(calls) / len(steps))
    (a, na), (b, nb) = results[1], results[3]
    assert a.converged and b.converged
    np.testing.assert_allclose(b.x, a.x, rtol=1e-6)
    assert nb < 0.8 * na, (na, nb)      # fewer linearisations per accepted step


def test_broyden_satisfies_the_secant_condition():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(6, 3))
    dz, dr = rng.normal(size=3), rng.normal(size=6)
    np.testing.assert_allclose(LM.broyden(J, dz, dr) @ dz, dr, rtol=1e-12)
    assert LM.broyden(J, np.zeros(3), dr) is J                  # no step: nothing learnt


def test_stopping_rules():
    y = model(TRUTH)
    linearise, trial = problem(y)
    p0 = np.array([1.0, 0.2, 0.0])
    r0 = model(p0) - y
    f0 = float(r0 @ r0)
    res = LM.levenberg_marquardt(p0, f0, linearise, dense, trial, max_iter=2)
    assert res.reason == "max_iter" and not res.converged and res.iterations == 2 and res.fresh
    res = LM.levenberg_marquardt(p0, f0, linearise, dense, trial, max_iter=50, time_up=lambda: True)
    assert res.reason == "time_limit" and not res.converged and res.iterations == 1
    res = LM.levenberg_marquardt(p0, f0, linearise, dense, trial, max_iter=50,
                                 step_small=lambda x, x_new: True)
    assert res.reason == "small_step" and res.converged
    # at the exact optimum no step lowers the objective: converged to rounding, x unchanged
    res = LM.levenberg_marquardt(TRUTH.copy(), 0.0, linearise, dense, trial, max_iter=50)
    assert res.reason == "no_step" and res.converged
    np.testing.assert_array_equal(res.x, TRUTH)


def test_a_singular_solve_raises_the_damping_instead_of_failing():
    y = model(TRUTH)
    linearise, trial = problem(y)
    lams = []

    def picky(lin, lam):
        lams.append(lam)
        if lam < 0.1:
            raise np.linalg.LinAlgError("singular")
        return dense(lin, lam)

    p0 = np.array([1.0, 0.2, 0.0])
    r0 = model(p0) - y
    res = LM.levenberg_marquardt(p0, float(r0 @ r0), linearise, picky, trial, max_iter=3)
    assert lams[:3] == pytest.approx([1e-3, 4e-3, 1.6e-2]) and res.f < float(r0 @ r0)


def test_profiled_curvature_is_f_minus_c_floored():
    """F - C where every eigenvalue of F^-1/2 C F^-1/2 is below 1 - floor; along a direction where C takes more
    than that share of F, F's curvature times the floor (checked in F's whitened coordinates)."""
    rng = np.random.default_rng(4)
    A = rng.standard_normal((3, 3))
    F = A @ A.T + 3 * np.eye(3)
    w, V = np.linalg.eigh(F)
    half = (V * np.sqrt(w)) @ V.T
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    for shares, want in (((0.2, 0.5, 0.7), (0.8, 0.5, 0.3)), ((0.2, 0.5, 0.97), (0.8, 0.5, LM.CURVATURE_FLOOR))):
        C = half @ (Q * np.array(shares)) @ Q.T @ half
        H = LM.profiled_curvature(F, C)
        assert np.allclose(H, half @ (Q * np.array(want)) @ Q.T @ half, rtol=1e-10, atol=1e-10)
        if max(shares) < 1 - LM.CURVATURE_FLOOR:
            assert np.allclose(H, F - C, rtol=1e-10, atol=1e-10)
    # the step and the decrement on it: Newton's on the quadratic of curvature H
    J, r = rng.standard_normal((20, 3)), rng.standard_normal(20)
    g = J.T @ r
    C = 0.3 * J.T @ J
    H = LM.profiled_curvature(J.T @ J, C)
    assert np.allclose(LM.dense_step(J, r, 0.0, C), -np.linalg.solve(H, g))
    assert LM.gn_decrement(J, r, C) == pytest.approx(g @ np.linalg.solve(H, g), rel=1e-10)
