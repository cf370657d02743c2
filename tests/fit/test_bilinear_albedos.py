"""Bilinear per-pixel albedos (``albedo="per-pixel-bilinear"``, issue 25): the interpolation weights, the
coupled least squares, Kaufman's projection and each pixel's covariance against dense linear algebra; a
noise-free continuous texture recovered where the one-pair-per-super-pixel layout is not; the option's
wiring and refusals."""
import dataclasses

import numpy as np
import pytest

from conftest import one_line_error

SHAPE = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
OFFSETS = np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])   # a mono raw mosaic's


def _layout(mask, offsets=OFFSETS):
    """The layout of every pixel of ``mask`` (H, W), one cell per pixel, and the dense interpolation matrix
    (N, groups) built here from the weights."""
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
    from fmbrdf_mi.fit.evaluate.bilinear_albedos import bilinear_weights

    H, W = mask.shape
    pixels = np.flatnonzero(mask)

    def present(r, c):
        inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        return inside & mask.ravel()[np.where(inside, r * W + c, 0)]

    rows, cols = np.divmod(pixels, W)
    corners, wts = bilinear_weights(rows, cols, offsets, present)
    groups = np.searchsorted(pixels, corners[..., 0] * W + corners[..., 1])
    n, m = len(pixels), len(offsets)
    lay = PixelAlbedos(np.repeat(np.arange(n)[:, None], m, 1), n, pixels, corner_groups=groups, corner_weights=wts,
                       name="per-pixel-bilinear")
    assert lay.coupled
    dense = np.zeros((n * m, n))
    np.add.at(dense, (np.repeat(np.arange(n * m), 4), groups.ravel()), wts.ravel())
    return lay, dense, corners, wts


def _disc(H=7, W=9, hole=True):
    yy, xx = np.mgrid[0:H, 0:W]
    mask = (yy - 3) ** 2 + (xx - 4) ** 2 <= 10
    if hole:
        mask[3, 4] = False      # an inner edge: pixels whose neighbour is missing on every side
    return mask


def test_weights_interior_and_edges():
    """Interior sample: 9/16 own, 3/16 each edge neighbour, 1/16 the diagonal.  A linear albedo
    a + b x + c y is reproduced exactly at every sample's point (raw pixel centre) along each axis in which
    its pixel has a neighbour on either side (interpolated, or extrapolated from the other side; a missing
    off-axis corner: the plane through the other three), and held constant along an axis with none (the
    pixel's centre coordinate).  Weights sum to 1 everywhere."""
    mask = _disc()
    mask[0, :] = False
    mask[0, 4] = True                # a pixel with no neighbour left or right
    lay, dense, corners, wts = _layout(mask)
    np.testing.assert_allclose(wts.sum(-1), 1.0, atol=1e-15)
    H, W = mask.shape
    pixels = np.flatnonzero(mask)
    i = np.searchsorted(pixels, 2 * W + 4)          # every neighbour present
    np.testing.assert_allclose(np.sort(wts[i, 0]), [1 / 16, 3 / 16, 3 / 16, 9 / 16])
    pr, pc = np.divmod(pixels, W)
    val = (dense @ (0.3 + 0.05 * pc - 0.02 * pr)).reshape(-1, 4)

    def have(rr, cc):
        ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        return ok & mask[np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)]

    any_x = (have(pr, pc - 1) | have(pr, pc + 1))[:, None]
    any_y = (have(pr - 1, pc) | have(pr + 1, pc))[:, None]
    assert (~any_x).any() and (any_x & any_y).all(axis=1).sum() > 20
    x = np.where(any_x, pc[:, None] + OFFSETS[None, :, 0], pc[:, None])
    y = np.where(any_y, pr[:, None] + OFFSETS[None, :, 1], pr[:, None])
    np.testing.assert_allclose(val, 0.3 + 0.05 * x - 0.02 * y, atol=1e-14)


def _random_problem(seed=1):
    mask = _disc()
    lay, dense, _, _ = _layout(mask)
    rng = np.random.default_rng(seed)
    n = lay.n_groups
    S, B = rng.uniform(0.1, 1, (n, 4)), rng.uniform(0.1, 1, (n, 4))
    y, w = rng.uniform(0, 1, (n, 4)), rng.uniform(0.5, 2, (n, 4))
    return lay, dense, S, B, y, w, rng


def test_solve_is_the_dense_least_squares():
    """The coupled solve against numpy.linalg.lstsq of the dense design (mask edges and a hole included):
    to 1e-10 (measured 6e-14; the system's condition number here is ~1e3)."""
    lay, dense, S, B, y, w, _ = _random_problem()
    a_s, a_b = lay.solve(S, B, y, w)
    sw = np.sqrt(w.ravel())
    A = np.concatenate([dense * S.ravel()[:, None], dense * B.ravel()[:, None]], 1) * sw[:, None]
    x = np.linalg.lstsq(A, y.ravel() * sw, rcond=None)[0]
    n = lay.n_groups
    np.testing.assert_allclose(a_s, x[:n], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a_b, x[n:], rtol=0, atol=1e-10)
    s, b = lay.sample_albedos(a_s, a_b)
    np.testing.assert_allclose((s * S + b * B).ravel(), (dense @ a_s) * S.ravel() + (dense @ a_b) * B.ravel(),
                               atol=1e-14)


def test_projection_and_covariance_are_the_dense_ones():
    """Kaufman's projected Jacobian (I - A (A^T A)^-1 A^T) J and each pixel's (a_s, a_b) covariance, the 2 x 2
    diagonal block of the inverse of the full information matrix [[A^T A, A^T J], [J^T A, J^T J]], against
    dense NumPy (inverse of the whole matrix): to 1e-9 relative."""
    lay, dense, S, B, y, w, rng = _random_problem(2)
    n = lay.n_groups
    J = rng.normal(size=(4 * n, 3))
    us, ub = -(S * np.sqrt(w)).ravel(), -(B * np.sqrt(w)).ravel()
    lay.solve(S, B, y, w)                      # the factor the projection reuses
    Jp, K = lay.project(J, us, ub)
    A = np.concatenate([dense * us[:, None], dense * ub[:, None]], 1)
    Jp_ref = J - A @ np.linalg.solve(A.T @ A, A.T @ J)
    np.testing.assert_allclose(Jp, Jp_ref, rtol=0, atol=1e-10 * np.abs(J).max())
    cov_z = np.linalg.inv(Jp.T @ Jp)
    C = lay.covariance(us, ub, J, cov_z, 1.0)
    F = np.block([[A.T @ A, A.T @ J], [J.T @ A, J.T @ J]])
    Fi = np.linalg.inv(F)
    ref = np.stack([np.stack([np.diag(Fi)[:n], Fi[np.arange(n), n + np.arange(n)]], -1),
                    np.stack([Fi[np.arange(n), n + np.arange(n)], np.diag(Fi)[n:2 * n]], -1)], 1)
    np.testing.assert_allclose(C, ref, rtol=1e-9, atol=0)


def _incidental_problem(seed=3, p=3):
    lay, dense, _, _ = _layout(_disc())
    N = 4 * lay.n_groups
    rng = np.random.default_rng(seed)
    us, ub = rng.uniform(0.3, 1, N), rng.uniform(0.3, 1, N)
    dcols = [(rng.normal(size=N), rng.normal(size=N)) for _ in range(p)]
    return lay, dense, us, ub, dcols


def test_incidental_term_is_the_dense_trace():
    """The coupled layout's C_jk = tr(G^-1 A_j^T (I - P) A_k) (mask edges and a hole; A_j the design at the
    columns' derivatives) against dense NumPy: the Monte Carlo estimate with 20,000 draws within 2 % of
    sqrt(C_jj C_kk) (its standard deviation there: ~0.3 %), positive semi-definite, the same at every call;
    at the default draws its relative spread over seeds is the sqrt(6 / (pairs x draws)) that
    PixelAlbedos.INCIDENTAL_DRAWS is sized by (within 0.6-1.5x: 40 seeds estimate a standard
    deviation to ~11 %), and its mean over those seeds is within 4 of its standard errors of the trace."""
    lay, dense, us, ub, dcols = _incidental_problem()
    p, N = len(dcols), len(us)
    A = np.concatenate([dense * us[:, None], dense * ub[:, None]], 1)
    Gi = np.linalg.inv(A.T @ A)
    M = np.eye(N) - A @ Gi @ A.T
    Aj = [np.concatenate([dense * d[0][:, None], dense * d[1][:, None]], 1) for d in dcols]
    ref = np.array([[np.trace(Gi @ Aj[j].T @ M @ Aj[k]) for k in range(p)] for j in range(p)])
    got = lay.incidental(us, ub, dcols, draws=20000, seed=1)
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
    assert np.all(np.abs(got - ref) < 0.02 * scale), (got - ref) / scale
    assert np.linalg.eigvalsh(got).min() > -1e-12
    assert np.array_equal(lay.incidental(us, ub, dcols), lay.incidental(us, ub, dcols))
    diag = np.array([np.diag(lay.incidental(us, ub, dcols, seed=s)) for s in range(40)])
    rel_sd = diag.std(0, ddof=1) / np.diag(ref)
    predicted = np.sqrt(6.0 / (lay.n_groups * lay.incidental_draws))
    assert np.all((rel_sd > 0.6 * predicted) & (rel_sd < 1.5 * predicted)), (rel_sd, predicted)
    assert np.all(np.abs(diag.mean(0) - np.diag(ref)) < 4 * diag.std(0, ddof=1) / np.sqrt(40))


def test_one_corner_through_the_banded_algebra_is_the_block_diagonal_one():
    """Per-pixel albedos are the design with one corner of weight 1 per sample: G is block diagonal, and
    PixelAlbedos inverts its 2 x 2 blocks in closed form.  The same design through the banded algebra
    (``coupled`` set: BandCholesky, its selected inverse, the Monte Carlo C) gives the same albedos,
    projected Jacobian and pair covariances to 1e-9 relative, and C (20,000 draws) within 2 % of
    sqrt(C_jj C_kk) of the exact per-group one; with the smoothness prior the term is not computed (None:
    the uncertainty reports the posterior covariance and says so)."""
    from fmbrdf_mi.fit.evaluate.albedo_prior import SmoothPrior
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos

    lay, _, us, ub, dcols = _incidental_problem(4, 2)
    n = lay.n_groups
    own = np.repeat(np.arange(n)[:, None], 4, 1)
    block, banded = PixelAlbedos(own, n, lay.pixels), PixelAlbedos(own, n, lay.pixels)
    assert not block.coupled
    banded.coupled = True
    rng = np.random.default_rng(5)
    S, B = rng.uniform(0.1, 1, (n, 4)), rng.uniform(0.1, 1, (n, 4))
    y, w = rng.uniform(0, 1, (n, 4)), rng.uniform(0.5, 2, (n, 4))
    for a, b in zip(block.solve(S, B, y, w), banded.solve(S, B, y, w)):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=0)
    J = rng.normal(size=(4 * n, 3))
    vs, vb = -(S * np.sqrt(w)).ravel(), -(B * np.sqrt(w)).ravel()
    (Jp0, K0), (Jp1, K1) = block.project(J, vs, vb), banded.project(J, vs, vb)
    np.testing.assert_allclose(Jp1, Jp0, rtol=0, atol=1e-10 * np.abs(J).max())
    np.testing.assert_allclose(K1, K0, rtol=1e-9, atol=0)
    cov_z = np.linalg.inv(Jp0.T @ Jp0)
    np.testing.assert_allclose(banded.covariance(vs, vb, J, cov_z), block.covariance(vs, vb, J, cov_z), rtol=1e-9)
    ref = block.incidental(us, ub, dcols)
    got = banded.incidental(us, ub, dcols, draws=20000, seed=2)
    assert np.all(np.abs(got - ref) < 0.02 * np.sqrt(np.outer(np.diag(ref), np.diag(ref)))), (got, ref)
    assert block.incidental_method is None and "Monte Carlo" in banded.incidental_method
    pairs = np.array([[i, i + 1] for i in range(n - 1)])
    with_prior = PixelAlbedos(own, n, lay.pixels, prior=SmoothPrior(pairs, n, (0.1, 0.1)))
    assert with_prior.coupled and with_prior.incidental(us, ub, dcols) is None
    assert "not computed" in with_prior.incidental_reason


def test_samples_at_their_cells_centres_are_the_one_corner_design():
    """Bilinear corners of samples at their cells' centres (zero offsets: Stokes or angle images) have
    weight 1 on the own pixel and 0 elsewhere: the layout drops the unused corners, so it is the per-pixel
    design and is solved as one (block diagonal G, the exact incidental term), with the same albedos,
    projection and covariances bit for bit."""
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
    from fmbrdf_mi.fit.evaluate.bilinear_albedos import bilinear_weights

    mask = _disc()
    H, W = mask.shape
    pixels = np.flatnonzero(mask)
    n = len(pixels)
    rows, cols = np.divmod(pixels, W)
    corners, wts = bilinear_weights(rows, cols, np.zeros((4, 2)), lambda r, c: np.ones(np.shape(r), bool))
    assert np.all(wts[..., 0] == 1) and not np.any(wts[..., 1:])
    own = np.repeat(np.arange(n)[:, None], 4, 1)
    bil = PixelAlbedos(own, n, pixels, corner_groups=np.searchsorted(pixels, corners[..., 0] * W + corners[..., 1]),
                       corner_weights=wts, name="per-pixel-bilinear")
    per = PixelAlbedos(own, n, pixels)
    assert not bil.coupled and bil.corner_groups.shape == (n, 4, 1)
    rng = np.random.default_rng(3)
    S, B = rng.uniform(0.1, 1, (n, 4)), rng.uniform(0.1, 1, (n, 4))
    y, w = rng.uniform(0, 1, (n, 4)), rng.uniform(0.5, 2, (n, 4))
    for a, b in zip(per.solve(S, B, y, w), bil.solve(S, B, y, w)):
        assert np.array_equal(a, b)
    J = rng.normal(size=(4 * n, 2))
    vs, vb = -(S * np.sqrt(w)).ravel(), -(B * np.sqrt(w)).ravel()
    for a, b in zip(per.project(J, vs, vb), bil.project(J, vs, vb)):
        assert np.array_equal(a, b)
    cov_z = np.eye(2)
    assert np.array_equal(per.covariance(vs, vb, J, cov_z), bil.covariance(vs, vb, J, cov_z))
    assert bil.incidental_method is None


def test_band_cholesky_selected_inverse_odd_band():
    """The selected inverse's 2 x 2 diagonal blocks (pairs straddling the factor's blocks: an odd half
    bandwidth) and the solve against numpy.linalg.inv of a random banded SPD matrix with a wide range of
    diagonal scales (the Jacobi scaling)."""
    from fmbrdf_mi.fit.evaluate.bilinear_albedos import BandCholesky

    rng = np.random.default_rng(3)
    n, b = 40, 5
    G = np.zeros((n, n))
    for d in range(b + 1):
        v = rng.normal(size=n - d)
        G[np.arange(d, n), np.arange(n - d)] = v
    G = G @ G.T                                          # SPD, half bandwidth 2b... keep only the band
    G = np.where(np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= b, G, 0.0) + 10 * np.eye(n)
    s = 10.0 ** rng.uniform(-6, 3, n)
    G = G * s[:, None] * s[None, :]
    band = np.zeros((n, b + 1))
    for d in range(b + 1):
        band[np.arange(d, n), d] = G[np.arange(d, n), np.arange(n - d)]
    fac = BandCholesky(band, b)
    Gi = np.linalg.inv(G)
    r = rng.normal(size=n)
    np.testing.assert_allclose(fac.solve(r), Gi @ r, rtol=1e-8)
    Z = fac.diagonal_blocks()
    for g in range(n // 2):
        np.testing.assert_allclose(Z[g], Gi[2 * g:2 * g + 2, 2 * g:2 * g + 2], rtol=1e-8)


# ---------------------------------------------------------------- fits of a noise-free continuous texture
def _texture_funcs():
    """A continuous texture (x, y in super-pixel units): k_s changes 3 % and k_b 1.5 % per super-pixel, about
    what the renders of issue 25 had within a super-pixel."""
    return (lambda x, y: 0.5 + 0.015 * x + 0.004 * y), (lambda x, y: 0.35 + 0.003 * x + 0.005 * y)


def _exact_continuous(res=16, light=(-0.5, 0.5, 1.0)):
    """A continuously textured sphere without noise and rounding: each raw pixel the model at its centre
    times the texture there (area 1: what a fit with ``area_points=1`` models exactly where the texture is
    linear), the camera's noise stated."""
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere
    from fmbrdf_mi.sensor import samples as SM
    from fmbrdf_mi.sensor.camera import CameraModel, intensity_at_each_pixel

    fs, fb = _texture_funcs()
    ideal = textured_sphere(SHAPE, fs, fb, res=res, light=light, area=1)
    cam = CameraModel(bits=16, full_well=1e6)
    obs, cap = capture_observation(ideal, cam, noiseless=True)
    exact = intensity_at_each_pixel(ideal["stokes"], cam.layout) * cap["exposure"] / cam.conversion_gain
    return dataclasses.replace(obs, samples=SM.from_raw(exact, cam.layout, 0.0, cam.white_level)), ideal


def _errors(res_, ideal):
    shape = max(abs(res_.params[k] / SHAPE[k] - 1) for k in ("eta", "alpha", "beta"))
    m = res_.maps
    f = np.isfinite(m["k_b"])
    return shape, float(np.max(np.abs(m["k_b"][f] / ideal["k_b_map"][f] - 1)))


@pytest.mark.slow
def test_noise_free_continuous_texture_is_recovered_bilinear_not_per_super_pixel():
    """Three lights, a linear texture, exact samples: the bilinear layout recovers eta, alpha, beta within
    0.1 % and k_b at every pixel within 1e-3 (relative; the model is exact for a linear texture), where one pair per super-pixel misses one of the two tolerances (the four samples'
    albedo differences read as polarisation)."""
    from fmbrdf_mi.fit import fit

    obs, ideal = zip(*[_exact_continuous(light=L) for L in
                       ((-0.5, 0.5, 1.0), (0.287, 0.497, 0.819), (0.287, -0.497, 0.819))])
    ideal = ideal[0]
    new = fit(list(obs), albedo="per-pixel-bilinear", max_pixels=None, intervals="fisher", progress=False,
              area_points=1)
    old = fit(list(obs), albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False, area_points=1)
    s_new, b_new = _errors(new, ideal)
    s_old, b_old = _errors(old, ideal)
    assert new.converged and s_new < 1e-3 and b_new < 1e-3, (s_new, b_new, new.params)
    assert s_old > 1e-3 or b_old > 1e-3, (s_old, b_old, old.params)
    # the shape errors are the incidental-parameter sandwich's (C by Monte Carlo), not below the Fisher ones
    u = new.uncertainty
    assert u["method"].startswith("incidental-parameter sandwich") and "Monte Carlo" in u["method"], u["method"]
    assert all(new.std_errors[k] >= u["incidental"]["fisher_std_errors"][k] * (1 - 1e-9) for k in SHAPE)
    assert new.albedo["layout"] == "per-pixel-bilinear"


def test_option_wiring_and_refusals(tmp_path, capsys, no_figures):
    """`--albedo per-pixel-bilinear` is an option value of the one pipeline (fit and CLI); with the paper's
    loss, free powers or several materials it is refused in one line; colour mosaics too (layout level)."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError
    from fmbrdf_mi.fit.problem.data import pixel_layout
    from fmbrdf_mi.sensor import samples as SM

    obs, _ = _exact_continuous(res=16)
    with pytest.raises(InputError, match="per-pixel-bilinear: needs the likelihood"):
        fit(obs, albedo="per-pixel-bilinear", loss="paper", progress=False)
    with pytest.raises(InputError, match="per-pixel-bilinear: not with free_power"):
        fit([obs, obs], albedo="per-pixel-bilinear", free_power=True, progress=False)
    labels = np.zeros(obs.shape, int)
    labels[:, 8:] = 1
    with pytest.raises(InputError, match="materials: not with albedo per-pixel-bilinear"):
        fit(obs, albedo="per-pixel-bilinear", materials=labels, max_pixels=None, progress=False)
    col = dataclasses.replace(obs.samples, channel=np.zeros(4, int))
    with pytest.raises(InputError, match="per-pixel-bilinear: not for colour mosaics"):
        pixel_layout([obs], [np.array([0])], col, bilinear=True)
    assert isinstance(obs.samples, SM.Samples)
    raw = tmp_path / "raw.npy"
    from fmbrdf_mi.synthetic.spheres import textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    fs, fb = _texture_funcs()
    ideal = textured_sphere(SHAPE, fs, fb, res=12, light=(-0.5, 0.5, 1.0))
    cam = CameraModel()
    np.save(raw, capture(ideal["stokes"], cam, peak_fraction=0.8, seed=2)["raw"])
    args = ["fit", str(raw), "--sphere", "6,6,5", "--light=-0.5,0.5,1", "--conversion-gain",
            str(cam.conversion_gain), "--read-noise", "2.5", "--albedo", "per-pixel-bilinear", "--max-pixels", "0",
            "--starts", "1", "--intervals", "fisher", "-q"]
    assert main(args + ["-o", str(tmp_path / "a")]) == 0
    assert (tmp_path / "a" / "k_s.exr").exists() and (tmp_path / "a" / "k_b_se.exr").exists()
    capsys.readouterr()
    rc = main(args[:-3] + ["--loss", "paper", "-o", str(tmp_path / "c")])
    one_line_error(rc, capsys.readouterr().err, "fit", "--albedo per-pixel-bilinear", "likelihood")
    assert not (tmp_path / "c").exists()


def test_textured_sphere_continuous_matches_per_super_pixel_for_a_step_texture():
    """``textured_sphere`` with callables evaluates the texture at each raw pixel's area points in
    super-pixel units (super-pixel (i, j) covers x in [j - 1/2, j + 1/2), y in [i - 1/2, i + 1/2)): a texture
    that is constant over each super-pixel (a step function of the point) gives the per-super-pixel
    arrays' image to rounding, and its centre maps are the arrays."""
    from fmbrdf_mi.synthetic.spheres import textured_sphere

    res = 8
    rng = np.random.default_rng(4)
    ks, kb = rng.uniform(0.2, 1.0, (res, res)), rng.uniform(0.1, 0.5, (res, res))

    def step(m):
        return lambda x, y: m[np.clip(np.floor(y + 0.5).astype(int), 0, res - 1),
                              np.clip(np.floor(x + 0.5).astype(int), 0, res - 1)]

    a = textured_sphere(SHAPE, ks, kb, res=res)
    b = textured_sphere(SHAPE, step(ks), step(kb), res=res)
    np.testing.assert_allclose(b["stokes"], a["stokes"], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(b["k_s_map"], ks)
    np.testing.assert_allclose(b["k_b_mean"], kb, rtol=1e-14)
