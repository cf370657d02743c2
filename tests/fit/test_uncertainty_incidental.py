"""The per-pixel albedo fit's incidental-parameter sandwich (docs/benchmarks/textured.md):
PixelAlbedos.incidental's C against a per-group dense computation and against its meaning (the mean
excess of Kaufman's information at noisy albedos), and uncertainty.incidental_sandwich against the spread
of a variable-projection estimate over noise draws, where the Fisher errors are far too small (per-pixel
and bilinear albedos; the bilinear layout's C against dense algebra: tests/fit/test_bilinear_albedos.py)."""
import math

import numpy as np
import pytest


def _groups(rng, sizes):
    g = np.repeat(np.arange(len(sizes)), sizes)
    return g, len(g)


def _layout(g):
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos

    n = int(g.max()) + 1
    return PixelAlbedos(g[:, None], n, np.arange(n))


def test_incidental_term_matches_the_dense_per_group_trace():
    """C_jk = sum_g tr(A_gj^T (I - U_g G_g^-1 U_g^T) A_gk G_g^-1), groups of 3 to 8 samples (the bincount
    sums against a loop over groups with dense matrices)."""
    rng = np.random.default_rng(1)
    g, N = _groups(rng, [3, 4, 4, 8, 5, 4, 6])
    lay = _layout(g)
    us, ub = rng.normal(size=N), rng.normal(size=N)
    p = 3
    dcols = [(rng.normal(size=N), rng.normal(size=N)) for _ in range(p)]
    got = lay.incidental(us, ub, dcols)
    ref = np.zeros((p, p))
    for k in range(lay.n_groups):
        m = g == k
        U = np.stack([us[m], ub[m]], 1)
        Gi = np.linalg.inv(U.T @ U)
        M = np.eye(m.sum()) - U @ Gi @ U.T
        A = [np.stack([d[0][m], d[1][m]], 1) for d in dcols]
        for j in range(p):
            for i in range(p):
                ref[j, i] += np.trace(A[j].T @ M @ A[i] @ Gi)
    assert np.allclose(got, ref, rtol=1e-10, atol=1e-12)
    assert np.linalg.eigvalsh(got).min() > -1e-12          # positive semi-definite


def test_incidental_term_is_the_mean_excess_of_kaufman_information():
    """Groups of 4 samples, y_g = U_g a_g + e (unit noise), A_gj = d U_g / d z_j: Kaufman's Jacobian at the
    estimated albedos, J_j = -(I - P) A_j a_hat, has E[J^T J] = H + C (H: the same at the true albedos).
    Over 4000 draws each entry's mean is within 4 of its standard errors of H + C, and C is many of them
    (the test fails if C were dropped or wrong by a fraction)."""
    rng = np.random.default_rng(2)
    n_g, m, p = 30, 4, 2
    g = np.repeat(np.arange(n_g), m)
    lay = _layout(g)
    U = rng.normal(size=(n_g * m, 2))
    A = [rng.normal(size=(n_g * m, 2)) for _ in range(p)]
    a = rng.uniform(0.5, 1.5, (n_g, 2))
    C = lay.incidental(U[:, 0], U[:, 1], [(Aj[:, 0], Aj[:, 1]) for Aj in A])

    def kaufman(ahat):
        cols = np.stack([np.einsum("nb,nb->n", Aj, ahat[g]) for Aj in A], 1)
        return lay.project(-cols, U[:, 0], U[:, 1])[0]

    J0 = kaufman(a)
    H = J0.T @ J0
    y0 = np.einsum("nb,nb->n", U, a[g])
    draws = []
    for _ in range(4000):
        y = y0 + rng.normal(size=y0.shape)
        ahat = np.stack(lay.solve(U[:, 0], U[:, 1], y, np.ones_like(y)), 1)
        J = kaufman(ahat)
        draws.append((J.T @ J).ravel())
    draws = np.array(draws)
    mean, se = draws.mean(0), draws.std(0, ddof=1) / np.sqrt(len(draws))
    assert np.all(np.abs(mean - (H + C).ravel()) < 4 * se), ((mean - (H + C).ravel()) / se)
    assert np.all(np.abs(np.diag(C)) > 10 * se.reshape(p, p).diagonal())


def _bilinear(H, W):
    """The bilinear layout (:class:`PixelAlbedos` with bilinear corners) of every pixel of an H x W grid, a mono raw
    mosaic's four samples per pixel, and its dense interpolation matrix (4 H W, H W)."""
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
    from fmbrdf_mi.fit.evaluate.bilinear_albedos import bilinear_weights

    offsets = np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])
    n = H * W
    rows, cols = np.divmod(np.arange(n), W)
    corners, wts = bilinear_weights(rows, cols, offsets,
                                    lambda r, c: (r >= 0) & (r < H) & (c >= 0) & (c < W))
    groups = corners[..., 0] * W + corners[..., 1]
    dense = np.zeros((4 * n, n))
    np.add.at(dense, (np.repeat(np.arange(4 * n), 4), groups.ravel()), wts.ravel())
    return PixelAlbedos(np.repeat(np.arange(n)[:, None], 4, 1), n, np.arange(n), corner_groups=groups,
                        corner_weights=wts, name="per-pixel-bilinear"), dense


@pytest.mark.parametrize("layout", ["per-pixel", "per-pixel-bilinear"])
def test_sandwich_matches_the_spread_over_noise_draws(layout):
    """A one-image-like variable-projection problem (4 samples and 2 free albedos per pixel, 2 shared
    non-linear parameters: unit-albedo columns U(z) = U0 + z_1 A1 + z_2 A2), fitted by Gauss-Newton on
    Kaufman's Jacobian from 200 noise draws; each sample's albedos its pixel's (``per-pixel``: 60 pixels) or
    interpolated between the pixel centres of an 8 x 10 grid (``per-pixel-bilinear``: the pairs coupled, C
    the Monte Carlo estimate).  The spread / mean Fisher SE is > 1.3 (the Fisher errors too small);
    the spread / mean sandwich SE is within 15 % of 1 (the standard error of a standard deviation from 200
    draws is 5 %, and the estimate's tails add to it: 3 of them), and the sandwich's 95 % intervals
    cover at least 8 draws more than the Fisher ones (binomial sd of a count ~3-5 at 200).  (Coverage
    stays below 95 %: each draw's SE is itself noisy, as in the package's measurements.)"""
    from fmbrdf_mi.fit.uncertainty import incidental_sandwich

    rng = np.random.default_rng(3)
    sigma = 0.8
    if layout == "per-pixel":
        g = np.repeat(np.arange(60), 4)
        lay, interp = _layout(g), np.eye(60)[g]
    else:
        lay, interp = _bilinear(8, 10)
    N, n_g = interp.shape
    U0 = rng.normal(size=(N, 2))
    A = [rng.normal(size=(N, 2)) * 0.5 for _ in range(2)]
    a = rng.uniform(0.5, 1.5, (n_g, 2))
    z_true = np.array([0.3, -0.2])

    def design(z):
        return U0 + z[0] * A[0] + z[1] * A[1]

    y0 = np.einsum("nb,nb->n", design(z_true), interp @ a)
    est, se_f, se_s = [], [], []
    for _ in range(200):
        y = (y0 + sigma * rng.normal(size=y0.shape)) / sigma        # whitened
        z = z_true.copy()
        for _ in range(30):
            Uw = design(z) / sigma
            ahat = interp @ np.stack(lay.solve(Uw[:, 0], Uw[:, 1], y, np.ones_like(y)), 1)   # each sample's
            r = y - np.einsum("nb,nb->n", Uw, ahat)
            cols = np.stack([-np.einsum("nb,nb->n", Aj / sigma, ahat) for Aj in A], 1)
            J = lay.project(cols, Uw[:, 0], Uw[:, 1])[0]
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
            z = z + step
            if np.abs(step).max() < 1e-10:
                break
        C = lay.incidental(Uw[:, 0], Uw[:, 1], [(Aj[:, 0] / sigma, Aj[:, 1] / sigma) for Aj in A])
        cov = incidental_sandwich(J.T @ J, C)[0]
        est.append(z)
        se_f.append(np.sqrt(np.diag(np.linalg.inv(J.T @ J))))
        se_s.append(np.sqrt(np.diag(cov)))
    err = np.array(est) - z_true
    se_f, se_s = np.array(se_f), np.array(se_s)
    cover_f = np.sum(np.abs(err) <= 1.96 * se_f, 0)
    cover_s = np.sum(np.abs(err) <= 1.96 * se_s, 0)
    ratio = err.std(0, ddof=1) / se_s.mean(0)
    ratio_f = err.std(0, ddof=1) / se_f.mean(0)
    # measured: per-pixel 1.43, 1.76 / bilinear 1.32, 1.41 (the Fisher errors too small: without C the
    # next check fails); the sandwich's 1.00, 1.07 / 0.93, 0.96; coverage 163 -> 185, 145 -> 170 /
    # 168 -> 192, 168 -> 191
    assert np.all(ratio_f > (1.3 if layout == "per-pixel" else 1.2)), ratio_f
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    assert np.all(cover_s >= cover_f + 8), (cover_f, cover_s)


def test_sandwich_caps_a_direction_where_h_is_not_positive_definite():
    """C larger than J^T J along one direction: that direction's inflation is capped at 1 / INCIDENTAL_FLOOR
    in standard error, the other direction's is exact ((1 - lambda)^-1)."""
    from fmbrdf_mi.fit.uncertainty import INCIDENTAL_FLOOR, incidental_sandwich

    F = np.diag([4.0, 1.0])
    C = np.diag([2.0, 1.5])            # lambda = 0.5 (SE x 2) and 1.5 (H < 0 there)
    cov, capped, _ = incidental_sandwich(F, C)
    assert capped == 1
    assert np.allclose(np.sqrt(np.diag(cov)), [0.5 * 2.0, 1.0 / INCIDENTAL_FLOOR])


def test_noise_share_is_the_largest_eigenvalue_of_c_relative_to_f():
    """C = F^1/2 Q diag(0.7, 0.2, 0.05) Q^T F^1/2 (F a rotated, unequally scaled SPD matrix, Q a rotation):
    the share of the information that is C is 0.7 in the worst direction (the largest eigenvalue of
    F^-1 C, here built in), whatever the parameters' scales; at 0.7 the sandwich labels its errors
    unreliable, at 0.2 not."""
    from fmbrdf_mi.fit.uncertainty import NOISE_SHARE_MAX, incidental_sandwich

    rng = np.random.default_rng(5)
    B = rng.normal(size=(3, 3)) * np.array([1.0, 30.0, 0.01])
    F = B @ B.T + np.diag([0.1, 50.0, 1e-4])
    w, V = np.linalg.eigh(F)
    Fh = (V * np.sqrt(w)) @ V.T                                   # F^1/2, symmetric
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for top, unreliable in ((0.7, True), (0.2, False)):
        C = Fh @ Q @ np.diag([top, 0.2 * top, 0.05]) @ Q.T @ Fh
        share = incidental_sandwich(F, C)[2]
        assert math.isclose(share, top, rel_tol=1e-9), (share, top)
        assert (share > NOISE_SHARE_MAX) == unreliable
    assert NOISE_SHARE_MAX == 0.5


def test_fit_reports_the_sandwich_for_per_pixel_albedos_only():
    """One noisy image, beta and kappa fixed: the per-pixel fit's shape errors are the sandwich's (at least
    the Fisher ones it keeps in ``incidental``; the method says so; the profile thresholds follow them), labelled
    not confidence intervals (``noise_share`` above ``NOISE_SHARE_MAX``);
    the shared-albedo fit of the same data has no ``incidental`` block and the plain Fisher method
    (its numbers: tools/record_fits.py, bit for bit)."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
    from fmbrdf_mi.sensor.camera import CameraModel

    true = {"eta": 1.55, "alpha": 0.35, "beta": 1.4, "kappa": 30.0, "k_s": 0.9, "r_k": 1.7}
    obs = capture_observation(ideal_sphere(true, res=16, light=(0.45, 0.35, 1.0)),
                              CameraModel(full_well=3000.0, read_noise=2.0, bits=12), seed=7)[0]
    fixed = {"beta": 1.4, "kappa": 30.0}
    pp = fit(obs, FitOptions(loss="likelihood", fixed=fixed, starts=1, albedo="per-pixel", intervals="auto"),
             progress=False)
    u = pp.uncertainty
    assert pp.converged and u["method"].startswith("incidental-parameter sandwich"), u["method"]
    fse = u["incidental"]["fisher_std_errors"]
    for k in ("eta", "alpha"):
        assert pp.std_errors[k] >= fse[k] * (1 - 1e-9) and fse[k] > 0, (k, pp.std_errors[k], fse[k])
        assert math.isclose(u["profile"]["thresholds"][k],
                            u["profile"]["threshold"] * (pp.std_errors[k] / fse[k]) ** 2, rel_tol=1e-9)
    assert np.isfinite(pp.maps["k_b_se"]).any()
    # one image of a small sphere: in its weakest direction most of J^T J is the albedos' noise, and the
    # method says that these errors are not confidence intervals (docs/benchmarks/coverage.md)
    share = u["incidental"]["noise_share"]
    assert 0.5 < share < 1.0 + 1e-9 and u["incidental"]["reliable"] is False, u["incidental"]
    assert "not confidence intervals" in u["method"], u["method"]
    sh = fit(obs, FitOptions(loss="likelihood", fixed=fixed, starts=1, intervals="fisher"), progress=False)
    assert "incidental" not in sh.uncertainty
    assert sh.uncertainty["method"] == "inverse Fisher information (known camera noise)"
