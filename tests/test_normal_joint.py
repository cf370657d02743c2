"""The joint material + normals refinement (fit/normal_joint.py, fit/normal_system.py) and
`fmbrdf-mi fit --refine-normals` (fit/normals_cli.py)."""
import json
import os

import numpy as np
import pytest

TRUE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)]
POWERS = [1.0, 0.7, 1.2]


def _dense_system(pix, val, st, coef, t1, t2, w, ridge):
    """H_nn as a dense matrix, from the definitions (independent of NormalBlock's index tricks)."""
    N = len(t1)
    Jd = np.zeros((len(pix), 2 * N))
    for r in range(len(pix)):
        for q, p in enumerate(pix[r]):
            if p >= 0:
                Jd[r, 2 * p:2 * p + 2] += val[r, q]
    Jp = np.zeros((3 * len(st), 2 * N))
    for e, s in enumerate(st):
        for c, p in zip(coef, s):
            Jp[3 * e:3 * e + 3, 2 * p] += np.sqrt(w) * c * t1[p]
            Jp[3 * e:3 * e + 3, 2 * p + 1] += np.sqrt(w) * c * t2[p]
    return Jd, Jd.T @ Jd + Jp.T @ Jp + np.diag(ridge.ravel())


@pytest.mark.parametrize("prior", ["curvature", "membrane"])
def test_normal_block_and_schur_step_match_dense_algebra(prior):
    """NormalBlock's product, its CG solve, the Schur-complement step and the Schur complement itself against
    dense NumPy on a 4 x 5 mask with a hole (random Jacobians; 2 x 2 bilinear stencils with fixed pixels).
    CG stops at a relative residual of 1e-10 on a system of condition < 1e4: 1e-6 relative is generous."""
    from fmbrdf_mi.fit.normal_joint import stencils
    from fmbrdf_mi.fit.normal_refine import _tangents
    from fmbrdf_mi.fit.normal_system import NormalBlock, data_products, schur, solve_step

    rng = np.random.default_rng(4)
    mask = np.ones((4, 5), bool)
    mask[1, 2] = False
    st, coef = stencils(mask, prior)
    N = int(mask.sum())
    # stencil count from the definition: pairs (membrane) or triples (curvature) along rows and columns
    L = len(coef)
    expect = sum(all(mask[y, x + k] for k in range(L)) for y in range(4) for x in range(5 - L + 1)) + \
        sum(all(mask[y + k, x] for k in range(L)) for y in range(4 - L + 1) for x in range(5))
    assert len(st) == expect
    n = rng.normal(size=(N, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = _tangents(n)
    m, p = 60, 6
    pix = rng.integers(-1, N, size=(m, 4))
    val = rng.normal(size=(m, 4, 2))
    Jm = rng.normal(size=(m, p))
    r = rng.normal(size=m)
    w, mu = 0.7, 0.05
    blk = NormalBlock(pix, val, st, coef, t1, t2, w, mu)
    Jd, H = _dense_system(pix, val, st, coef, t1, t2, w, blk.ridge)
    x = rng.normal(size=(N, 2, 3))
    np.testing.assert_allclose(blk.apply(x).reshape(2 * N, 3), H @ x.reshape(2 * N, 3), rtol=1e-10, atol=1e-10)
    b = rng.normal(size=(N, 2, 2))
    np.testing.assert_allclose(blk.solve(b).reshape(2 * N, 2), np.linalg.solve(H, b.reshape(2 * N, 2)), rtol=1e-6,
                               atol=1e-8)
    Hmm, Hmn, gm, gn = data_products(pix, val, Jm, r, N)
    np.testing.assert_allclose(Hmn.reshape(p, 2 * N), Jm.T @ Jd, atol=1e-10)
    np.testing.assert_allclose(gn.ravel(), Jd.T @ r, atol=1e-10)
    dm, dn = solve_step(Hmm, Hmn, blk, gm, gn, mu)
    A = np.block([[Hmm + mu * np.diag(np.diag(Hmm)), Jm.T @ Jd], [Jd.T @ Jm, H]])
    ref = np.linalg.solve(A, -np.concatenate([gm, gn.ravel()]))
    np.testing.assert_allclose(np.concatenate([dm, dn.ravel()]), ref, rtol=1e-6, atol=1e-8)
    blk0 = NormalBlock(pix, val, st, coef, t1, t2, w, 0.0)
    _, H0 = _dense_system(pix, val, st, coef, t1, t2, w, blk0.ridge)
    S = Hmm - (Jm.T @ Jd) @ np.linalg.solve(H0, Jd.T @ Jm)
    np.testing.assert_allclose(schur(Hmm, Hmn, blk0), S, rtol=1e-6, atol=1e-6 * np.abs(S).max())


def test_curvature_prior_is_zero_on_a_linear_normal_field():
    """Second differences vanish where the normal changes linearly across the image (a cylinder-like
    slope field before normalisation); first differences do not."""
    from fmbrdf_mi.fit.normal_joint import stencils

    mask = np.ones((5, 6), bool)
    y, x = np.mgrid[0:5, 0:6]
    n = np.stack([0.05 * x, -0.03 * y, np.ones_like(x, float)], -1)[mask]
    for prior, zero in (("curvature", True), ("membrane", False)):
        st, coef = stencils(mask, prior)
        d = sum(c * n[st[:, s]] for s, c in enumerate(coef))
        assert (np.abs(d).max() < 1e-12) == zero
    with pytest.raises(Exception, match="prior: expected one of"):
        stencils(mask, "tv")
