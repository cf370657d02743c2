"""The azimuthal (Fourier) construction of the body tables against the dense double sum.

fmbrdf_mi.model.body builds sum_pq a_p(V) K_pq b_q(L)^T through a DFT over the
node azimuths (DESIGN.md section 2).  At view azimuths on the node grid that
is the same finite sum as the dense one, so the two must agree to float32
rounding.  The dense sum here is an independent float64 NumPy code path: the
explicit 4x4 Mueller matrices, atan2 rotation angles and N x N coupling of
tests/reference.py, evaluated on the package's node set (polar angles and
weights copied out of fmbrdf_mi, N = 32 x 64 normals).  Both are divided by
the same pi P(L) P(V) (the package's Smith table, not under test here).

Tolerance: the fast path sums ~N^2 positive float32 terms through matrix
products; rounding then leaves relative errors of order sqrt(N) eps ~ 1e-5
of the largest element.  1e-4 of the largest M00 of the material (plus 2e-4
of the element's own M00, for the grazing views where M00 is small) is well
inside what any error of the construction produces: a wrong Fourier sign,
mode weight or basis rotation moves elements by 1e-2 or more of M00.
"""
import math

import numpy as np
import pytest

from reference import Reference

CORNERS = [  # (eta, alpha, beta, kappa) at the corners of the valid range, and a middle one
    (1.01, 0.01, 0.4, 0.0),
    (1.01, 0.01, 5.0, 100.0),
    (3.0, math.pi / 2, 0.4, 100.0),
    (3.0, math.pi / 2, 5.0, 0.0),
    (1.01, math.pi / 2, 5.0, 100.0),
    (3.0, 0.01, 0.4, 100.0),
    (1.5, 0.3, 2.0, 10.0),
]
THETA_L = np.array([0.0, 0.4, 1.1, 1.5])
THETA_V = np.array([0.05, 0.8, 1.45])


@pytest.fixture(scope="module")
def jit():
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_mono_polarized")
    from drjit.llvm.ad import Float
    return dr, Float


def _material(Float, eta, alpha, beta):
    from fmbrdf_mi.model.distribution import Distribution
    return Distribution(Float, Float(alpha), Float(beta)), Float(eta)


def dense_sum(dist, grid, eta, kappa, theta_l, theta_v, phi):
    """sum_pq a_p K_pq b_q^T over the package's nodes, in float64 NumPy: (nL, nV, nphi, 3, 3)."""
    from fmbrdf_mi.model.body import node_azimuths, polar_nodes

    th_j, w_j = (np.asarray(x, dtype=np.float64) for x in polar_nodes(dist, grid))
    ph_k = node_azimuths(grid)
    TH, PH = np.meshgrid(th_j, ph_k, indexing="ij")
    ref = Reference(float(eta), 0.5, 2.0, float(kappa), n_s=2, n_phi=2)  # nodes replaced below
    ref.n = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
    ref.wD = np.repeat(w_j, len(ph_k))
    pairs = []
    for tl in theta_l:
        for tv in theta_v:
            for ph in phi:
                L = np.array([math.sin(tl), 0.0, math.cos(tl)])
                V = np.array([math.sin(tv) * math.cos(ph), math.sin(tv) * math.sin(ph), math.cos(tv)])
                pairs.append((L, V, np.array([0.0, 1.0, 0.0]), np.array([-math.sin(ph), math.cos(ph), 0.0])))
    out = ref.body(pairs)
    # undo the reference's Smith factor k_b/pi G1(L) G1(V) / V.z: the bare double sum
    for k, (L, V, _, _) in enumerate(pairs):
        out[k] /= ref.G1(L) * ref.G1(V) / V[2] / math.pi
    return out[:, :3, :3].reshape(len(theta_l), len(theta_v), len(phi), 3, 3)


@pytest.mark.parametrize("mat", CORNERS)
def test_fourier_equals_dense_sum_on_grid_azimuths(jit, mat):
    dr, Float = jit
    from fmbrdf_mi.model.body import BodyGrid, body_grid_matrices

    eta, alpha, beta, kappa = mat
    grid = BodyGrid()
    dist, eta_ = _material(Float, eta, alpha, beta)
    step = 2 * math.pi / grid.n_phi
    phi = np.array([0, 1, 3, 8, 16, 25, 31, 32]) * step  # on the node grid, 0 .. pi
    fast = body_grid_matrices(dist, eta_, Float(kappa), grid, THETA_L, THETA_V, phi).numpy()
    fast = fast.transpose(1, 2, 0, 3, 4).astype(np.float64)  # (l, v, t, r, s)
    PL = np.asarray(dist.projected_area(Float(THETA_L)), dtype=np.float64)
    PV = np.asarray(dist.projected_area(Float(THETA_V)), dtype=np.float64)
    dense = dense_sum(dist, grid, eta, kappa, THETA_L, THETA_V, phi)
    dense /= math.pi * PL[:, None, None, None, None] * PV[None, :, None, None, None]
    m00 = np.abs(dense[..., :1, :1])
    tol = 1e-4 * m00.max() + 2e-4 * m00
    err = np.abs(fast - dense)
    worst = np.unravel_index(np.argmax(err / tol), err.shape)
    assert np.all(err <= tol), (mat, worst, fast[worst], dense[worst])
    if eta > 1.4 and kappa > 0:  # polarised incidence is exercised: some element off the first column is not small
        assert np.abs(dense[..., 1:, 1:]).max() > 1e-2 * m00.max()


def test_off_grid_azimuths_interpolate_the_series(jit):
    """Between grid azimuths the tables hold the trigonometric interpolant; it
    stays within the azimuthal quadrature error of the dense sum there (the
    dense sum at an off-grid view is itself only one quadrature of the integral)."""
    dr, Float = jit
    from fmbrdf_mi.model.body import BodyGrid, body_grid_matrices

    grid = BodyGrid()
    dist, eta_ = _material(Float, 1.5, 0.3, 2.0)
    phi = (np.array([0.5, 5.25, 20.5, 31.5])) * 2 * math.pi / grid.n_phi
    fast = body_grid_matrices(dist, eta_, Float(10.0), grid, THETA_L, THETA_V, phi).numpy()
    fast = fast.transpose(1, 2, 0, 3, 4).astype(np.float64)
    PL = np.asarray(dist.projected_area(Float(THETA_L)), dtype=np.float64)
    PV = np.asarray(dist.projected_area(Float(THETA_V)), dtype=np.float64)
    dense = dense_sum(dist, grid, 1.5, 10.0, THETA_L, THETA_V, phi)
    dense /= math.pi * PL[:, None, None, None, None] * PV[None, :, None, None, None]
    m00 = np.abs(dense[..., :1, :1])
    assert np.abs(fast - dense).max() < 1e-3 * m00.max()


# ------------------------------------------------------------------ derivatives
BASE = {"eta": 1.6, "alpha": 0.4, "beta": 1.7, "kappa": 20.0}
PICK = np.array([0, 7, 1234, 40000, 123456, 300001, 545000, 1000003, 1700000])  # flat indices into each table


def _tables(Float, p):
    from fmbrdf_mi.model.body import BodyGrid, body_tables
    from fmbrdf_mi.model.distribution import Distribution

    dist = Distribution(Float, p["alpha"], p["beta"])
    return body_tables(dist, p["eta"], p["kappa"], BodyGrid())


def _picked(dr, Float, tables):
    from drjit.llvm.ad import UInt32
    table, fac = tables
    n = dr.width(table.values)
    return dr.concat([dr.gather(Float, table.values, UInt32(PICK * 9 % n)),  # the log channel
                      dr.gather(Float, table.values, UInt32(PICK % n)),  # every kind of channel
                      dr.gather(Float, fac.values, UInt32(PICK % dr.width(fac.values)))])


@pytest.mark.parametrize("name", sorted(BASE))
def test_table_gradients_match_central_differences(jit, name):
    """Forward- and reverse-mode derivatives of table entries (every kind of
    channel of the body table, and the 1-D grazing factors) against central differences of the same tables
    built in float64: h = 1e-2 x value, truncation ~1e-4 relative, far below
    the 2 % tolerance, which any missing or wrong derivative path exceeds.
    (The channels are ratios and logarithms less their kappa = 0 factors:
    float32 cancellation there leaves differences with noise of a few 1e-5
    of the largest derivative, too close to the tolerance.)"""
    dr, Float = jit
    p = {k: Float(v) for k, v in BASE.items()}
    dr.enable_grad(p[name])
    vals = _picked(dr, Float, _tables(Float, p))
    dr.forward(p[name])
    fwd = np.asarray(dr.grad(vals), dtype=np.float64)
    weights = np.linspace(-1.0, 2.0, dr.width(vals))
    p = {k: Float(v) for k, v in BASE.items()}
    dr.enable_grad(p[name])
    vals = _picked(dr, Float, _tables(Float, p))
    dr.backward(dr.sum(vals * Float(weights)))
    rev = float(dr.grad(p[name])[0])

    from drjit.llvm.ad import Float64
    h = 1e-2 * BASE[name]
    f = lambda x: np.asarray(_picked(dr, Float64, _tables(Float64, {**{k: Float64(v) for k, v in BASE.items()},
                                                                     name: Float64(x)})), dtype=np.float64)
    fd = (f(BASE[name] + h) - f(BASE[name] - h)) / (2 * h)
    big = np.abs(fd) > 1e-3 * np.abs(fd).max()
    assert big.sum() >= 5
    np.testing.assert_allclose(fwd[big], fd[big], rtol=2e-2, atol=2e-3 * np.abs(fd).max())
    assert rev == pytest.approx(float(weights @ fd), rel=2e-2)
    assert rev == pytest.approx(float(weights @ fwd), rel=1e-4)


# ------------------------------------------------------------------ grazing factors
@pytest.mark.parametrize("mat", [(1.01, 0.01, 5.0), (3.0, math.pi / 2, 0.4), (1.5, 0.3, 2.0), (2.5, 0.05, 0.6)])
def test_grazing_factors_are_the_kappa0_factorisation(jit, mat):
    """At kappa = 0 the dense double sum (float64 NumPy, independent code path)
    factorises as A(V) A(L)^T / Z: its M00 over theta_V is F(theta_V) P(theta_V)
    up to one constant, M10/M00 is d(theta_V) and M01/M00 is d(theta_L).
    Tolerance: float32 sums over 2048 nodes, ~1e-6 relative; 2e-5 (of F, and
    absolute for d, which is at most 1) is far inside what a wrong factor of P,
    a lost Fresnel term or a sign produces (1e-2 and more)."""
    dr, Float = jit
    from fmbrdf_mi.model.body import BodyGrid, grazing_factors

    eta, alpha, beta = mat
    grid = BodyGrid()
    dist, eta_ = _material(Float, eta, alpha, beta)
    theta = np.array([0.0, 0.3, 0.9, 1.2, 1.45, 1.55, 0.5 * math.pi])
    F, d = (np.asarray(x, dtype=np.float64) for x in grazing_factors(dist, eta_, grid, theta))
    P = np.asarray(dist.projected_area(Float(theta)), dtype=np.float64)
    dense = dense_sum(dist, grid, eta, 0.0, theta[[1]], theta, np.array([0.7]))[0, :, 0]  # (v, 3, 3)
    ratio = F * P / dense[:, 0, 0]
    np.testing.assert_allclose(ratio / ratio[0], 1.0, atol=2e-5)
    np.testing.assert_allclose(d, dense[:, 1, 0] / dense[:, 0, 0], atol=2e-5)
    dense_l = dense_sum(dist, grid, eta, 0.0, theta, theta[[2]], np.array([2.1]))[:, 0, 0]  # (l, 3, 3)
    np.testing.assert_allclose(d, dense_l[:, 0, 1] / dense_l[:, 0, 0], atol=2e-5)
    if eta >= 1.5 and alpha < 1:  # not trivial: grazing light is transmitted less, and polarised
        assert F[0] - F[-1] > 0.05 and d[-1] < -0.01


def test_tables_are_constant_at_kappa0(jit):
    """With the grazing factors divided out, every tabulated channel is constant
    (the first) or zero (the others) at kappa = 0: the tables hold only the
    coupling between the two directions (to float32 rounding of the log and the
    ratios, 1e-5; a channel whose factor were not removed varies by 1e-1 or more)."""
    dr, Float = jit
    from fmbrdf_mi.model.body import BodyGrid, body_tables

    dist, eta_ = _material(Float, 1.7, 0.4, 1.5)
    table, fac = body_tables(dist, eta_, Float(0.0), BodyGrid())
    t = np.asarray(table.values, dtype=np.float64).reshape(-1, 9)
    assert np.ptp(t[:, 0]) < 1e-4
    assert np.abs(t[:, 1:]).max() < 1e-5
    f = np.asarray(fac.values, dtype=np.float64).reshape(-1, 2)
    assert np.ptp(f[:, 0]) > 0.1 and np.ptp(f[:, 1]) > 0.1  # the factors themselves are not flat


@pytest.mark.parametrize("mat", [(1.01, 0.01, 5.0, 100.0), (3.0, math.pi / 2, 0.4, 100.0), (1.5, 0.3, 2.0, 10.0)])
def test_table_channels_at_the_nodes(jit, mat):
    """Every texel of the body table, in both layouts (a texel's channels side
    by side; one array per channel, what the compact copy is packed from),
    against the body matrices at the table's nodes from body_grid_matrices
    (checked against the dense sum above) and the grazing factors at the same
    angles, transformed here in float64 NumPy as body.CHANNELS says: log M00
    less log F(theta_L) + log F(theta_V), the other elements over M00 less
    d(theta_L) (M01), d(theta_V) (M10), their product (M11).  Tolerance 2e-5:
    float32 rounding of a log of order 10 and of ratios of order 1; a swapped
    row and column, a wrong texel order or a missing factor moves channels by
    1e-2 or more.  Both layouts pick the same triangulation."""
    dr, Float = jit
    from fmbrdf_mi.model.body import (BodyGrid, body_grid_matrices, body_tables, grazing_factors,
                                      table_angles)

    eta, alpha, beta, kappa = mat
    grid = BodyGrid()
    dist, eta_ = _material(Float, eta, alpha, beta)
    th, ph = table_angles(*grid.table)
    M = body_grid_matrices(dist, eta_, Float(kappa), grid, th, th, ph).numpy().astype(np.float64)  # (t, l, v, 3, 3)
    F, d = (np.asarray(x, dtype=np.float64) for x in grazing_factors(dist, eta_, grid, th))
    m00 = M[..., 0, 0]
    want = M / m00[..., None, None]
    want[..., 0, 0] = np.log(m00) - np.log(F)[None, :, None] - np.log(F)[None, None, :]
    want[..., 0, 1] -= d[None, :, None]
    want[..., 1, 0] -= d[None, None, :]
    want[..., 1, 1] -= d[None, :, None] * d[None, None, :]
    want = want.reshape(-1, 9)
    inter, _ = body_tables(dist, eta_, Float(kappa), grid)
    planar, _ = body_tables(dist, eta_, Float(kappa), grid, planar=True)
    got_i = np.asarray(inter.values, dtype=np.float64).reshape(-1, 9)
    got_p = np.stack([np.asarray(x, dtype=np.float64) for x in planar.values], axis=1)
    for got in (got_i, got_p):
        err = np.abs(got - want)
        assert err.max() < 2e-5, (mat, np.unravel_index(np.argmax(err), err.shape), err.max())
    assert int(inter.orient[0]) == int(planar.orient[0])
