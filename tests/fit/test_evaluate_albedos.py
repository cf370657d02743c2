"""The albedo layouts against NumPy's least squares and the dense information matrix."""
import numpy as np

from fmbrdf_mi.fit.evaluate.albedos import GroupAlbedos
from fmbrdf_mi.sensor.mosaic import COLOURS


def _data(seed=0):
    rng = np.random.default_rng(seed)
    chan = np.array([0, 0, 1, 1, 1, 1, 2, 2] * 2)            # 16 samples per cell, as a colour period
    S, B = rng.uniform(0.1, 1.0, (50, 16)), rng.uniform(0.1, 1.0, (50, 16))
    a_s, a_b = np.array([0.6, 0.4, 0.5]), np.array([0.3, 0.2, 0.45])
    y = a_s[chan] * S + a_b[chan] * B + rng.normal(0, 0.01, S.shape)
    w = rng.uniform(0.5, 2.0, S.shape)
    return GroupAlbedos("per-channel", chan, COLOURS), S, B, y, w, a_s, a_b


def test_solve_is_each_channels_weighted_least_squares():
    lay, S, B, y, w, a_s, a_b = _data()
    got_s, got_b = lay.solve(S, B, y, w)
    for g in range(3):
        m = lay.groups == g
        X = np.stack([S[:, m].ravel(), B[:, m].ravel()], 1) * np.sqrt(w[:, m].ravel())[:, None]
        ref = np.linalg.lstsq(X, y[:, m].ravel() * np.sqrt(w[:, m].ravel()), rcond=None)[0]
        assert np.allclose([got_s[g], got_b[g]], ref, rtol=1e-10), (g, got_s, got_b, ref)
        assert abs(got_s[g] - a_s[g]) < 0.02 and abs(got_b[g] - a_b[g]) < 0.02   # and near the truth


def test_joint_covariance_is_the_dense_inverse_information():
    """The eliminated channels' joint covariance of (shape, a_s[0], a_b[0], ...) against the inverse of the
    dense information of all unknowns (2 shape columns, then each channel's albedo columns)."""
    lay, S, B, y, w, _, _ = _data(1)
    sd = 1.0 / np.sqrt(w)
    us, ub = (-S / sd).ravel(), (-B / sd).ravel()
    J = np.random.default_rng(2).normal(size=(S.size, 2))
    U = np.zeros((S.size, 6))
    g = np.broadcast_to(lay.groups, S.shape).ravel()
    U[np.arange(S.size), 2 * g], U[np.arange(S.size), 2 * g + 1] = us, ub
    Cfull = np.linalg.inv(np.concatenate([J, U], 1).T @ np.concatenate([J, U], 1))
    Jp = lay.project(J, us, ub)[0]
    for scale in (1.0, 2.5):
        got = lay.joint_covariance(us, ub, J, scale * np.linalg.inv(Jp.T @ Jp), scale)
        assert np.allclose(got, scale * Cfull, rtol=1e-8, atol=1e-14), scale


# ---------------------------------------------------------------- per-pixel albedos (textured objects)
def _pixel_data(seed=0, n_cells=40, m=4):
    """A per-pixel layout of ``n_cells`` cells of m samples, one group per cell, and data y = a_s S + a_b B
    (+ noise) with a shape unknown theta scaling B's polarisation (a stand-in for the BSDF's shape)."""
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos

    rng = np.random.default_rng(seed)
    S, B = rng.uniform(0.1, 1.0, (n_cells, m)), rng.uniform(0.1, 1.0, (n_cells, m))
    a_s, a_b = rng.uniform(0.2, 1.0, n_cells), rng.uniform(0.2, 1.0, n_cells)
    y = a_s[:, None] * S + a_b[:, None] * B + rng.normal(0, 0.01, S.shape)
    w = rng.uniform(0.5, 2.0, S.shape)
    lay = PixelAlbedos(np.repeat(np.arange(n_cells)[:, None], m, axis=1), n_cells, np.arange(n_cells) * 3)
    return lay, S, B, y, w


def test_pixel_albedos_are_each_groups_least_squares():
    """The closed-form step (PairBlocks, all groups at once) against NumPy's least squares of each group,
    unconstrained (some groups built to have a negative albedo: nuisance parameters are not clipped), and
    a group with parallel columns (B = 2 S) gets the minimum-norm solution and counts one free albedo."""
    lay, S, B, y, w = _pixel_data(2)
    y[:5] = 0.8 * S[:5] - 0.3 * B[:5]          # a_b < 0
    y[5:8] = -0.2 * S[5:8] + 0.6 * B[5:8]      # a_s < 0
    B[8] = 2.0 * S[8]                          # degenerate
    got_s, got_b = lay.solve(S, B, y, w)
    for g in range(lay.n_groups):
        X = np.stack([S[g], B[g]], 1) * np.sqrt(w[g])[:, None]
        ref = np.linalg.lstsq(X, y[g] * np.sqrt(w[g]), rcond=1e-10)[0]
        assert np.allclose([got_s[g], got_b[g]], ref, rtol=1e-8, atol=1e-12), (g, got_s[g], got_b[g], ref)
    assert np.all(got_b[:5] < 0) and np.all(got_s[5:8] < 0)
    sd = 1.0 / np.sqrt(w)
    lay.project(np.ones((S.size, 1)), (-S / sd).ravel(), (-B / sd).ravel())
    assert lay.free() == 2 * lay.n_groups - 1


def test_projected_jacobian_and_covariance_match_the_dense_information_matrix():
    """Kaufman's projection (I - P) J and the per-group covariance against the dense Fisher information of
    all unknowns (2 shape columns + 2 albedos per group), inverted as one matrix."""
    lay, S, B, y, w = _pixel_data(3, n_cells=12)
    rng = np.random.default_rng(4)
    sd = 1.0 / np.sqrt(w)
    a_s, a_b = lay.solve(S, B, y, w)
    us, ub = (-S / sd).ravel(), (-B / sd).ravel()
    Jt = rng.normal(size=(S.size, 2))                      # d r / d shape (any full-rank columns)
    Jp, K = lay.project(Jt, us, ub)
    # dense: the albedo columns of every group, then the shape's
    U = np.zeros((S.size, 2 * lay.n_groups))
    g = lay.groups.ravel()
    U[np.arange(S.size), 2 * g] = us
    U[np.arange(S.size), 2 * g + 1] = ub
    P = U @ np.linalg.pinv(U)
    assert np.allclose(Jp, Jt - P @ Jt, atol=1e-10)
    F = np.concatenate([Jt, U], 1)
    Cfull = np.linalg.inv(F.T @ F)
    cov_z = np.linalg.inv(Jp.T @ Jp)
    assert np.allclose(cov_z, Cfull[:2, :2], rtol=1e-9)   # the Schur complement: shape with albedos free
    C = lay.covariance(us, ub, Jt, cov_z)
    for k in range(lay.n_groups):
        blk = Cfull[2 + 2 * k:4 + 2 * k, 2 + 2 * k:4 + 2 * k]
        assert np.allclose(C[k], blk, rtol=1e-8, atol=1e-14), k


def test_degenerate_pixels_are_flagged_not_identified():
    """Groups whose body signature is the surface's (B = 0.7 S behind every polariser: the split of their
    brightness is undetermined) are flagged, the others are not (uncertainty.pixel_albedos, through a
    Problem with the per-pixel layout)."""
    import types

    from fmbrdf_mi.sensor.noise import NoiseModel
    from fmbrdf_mi.fit.evaluate.models import State, get_model
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective
    from fmbrdf_mi.fit.problem.problem import Problem
    from fmbrdf_mi.fit.uncertainty import pixel_albedos
    from fmbrdf_mi.sensor.noise import NoiseModel

    rng = np.random.default_rng(5)
    n, m = 30, 4
    angles = np.radians([90, 45, 135, 0])
    A = 0.5 * np.stack([np.ones(4), np.cos(2 * angles), np.sin(2 * angles)], 1)
    surf = np.stack([np.ones(n), 0.3 * np.ones(n), np.zeros(n)])         # polarised along x
    body = np.stack([np.ones(n), np.zeros(n), 0.2 * np.ones(n)])         # along the diagonal
    body[:, :10] = 0.7 * surf[:, :10]                                    # degenerate: the surface's signature
    parts = types.SimpleNamespace(surface=surf * 1000.0, body=body * 1000.0, nonfinite=None,
                                  d_surface={}, d_body={})
    a_s, a_b = np.full(n, 0.8), np.full(n, 0.5)
    y = np.einsum("kc,ci->ik", A, a_s * parts.surface + a_b * parts.body)
    y = y + rng.normal(0, 1.0, y.shape)
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
    lay = PixelAlbedos(np.repeat(np.arange(n)[:, None], m, axis=1), n, np.arange(n))
    obj = LikelihoodObjective(y, A, NoiseModel(1.0, 1.0, 0.0), 4, layout=lay)
    base = get_model("fmbrdf")
    fixed = {k: 1.5 if k == "eta" else 0.3 if k == "alpha" else 1.0 if k == "beta" else 0.0
             for k in base.shape_names}
    prob = Problem(Parameters(base, maps=True, fixed=fixed), None, obj)
    st = State(dict(fixed), *obj.albedos(parts))
    J = np.zeros((y.size, 0))
    out = pixel_albedos(prob, st, parts, J, {"chi2_per_dof": 1.0})
    assert not out["identified"][:10].any(), out["k_s_se"][:10]
    assert out["identified"][10:].all(), out["k_s_se"][10:]


def test_pair_blocks_are_numpys_pseudo_inverse_and_rank():
    """PairBlocks' one eigendecomposition gives NumPy's pinv (rcond 1e-10) and matrix_rank of every 2 x 2 block,
    to the last bit, also for singular, zero, tied and nearly parallel blocks."""
    from fmbrdf_mi.fit.evaluate.albedos import PairBlocks

    rng = np.random.default_rng(3)
    X = rng.normal(size=(200, 6, 2))
    X[10:20, :, 1] = 0.7 * X[10:20, :, 0]                            # parallel columns: rank 1
    X[20:30, :, 1] = X[20:30, :, 0] * (1 + 1e-9)                     # nearly parallel
    X[30:35] = 0.0                                                   # empty
    blocks = np.einsum("gna,gnb->gab", X, X)
    blocks[35:40] = np.eye(2) * 3.0                                  # tied eigenvalues
    blocks[40:45] = [[1.0, 0.0], [0.0, 1e-12]]                       # below the cutoff
    fac = PairBlocks(blocks)
    assert np.array_equal(fac.inverse, np.linalg.pinv(blocks, rcond=1e-10, hermitian=True))
    assert np.array_equal(fac.rank, np.linalg.matrix_rank(blocks, rtol=1e-10, hermitian=True))
    assert set(fac.rank[10:20]) == {1} and set(fac.rank[30:35]) == {0} and set(fac.rank[40:45]) == {1}
