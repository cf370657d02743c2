"""The albedo maps' smoothness prior (``albedo_smooth``, issue 25): the penalised elimination of the albedos,
Kaufman's projected Jacobian with the prior's rows, the per-pixel posterior covariance and the effective
number of parameters against dense NumPy on the augmented least squares; the chi^2 degrees-of-freedom rule
checked by simulation; tau -> infinity gives the unpenalised maps; a noise-free fit of constant maps
(which the prior does not penalise); the option's refusals."""
import dataclasses

import numpy as np
import pytest

from conftest import one_line_error

SHAPE = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
OFFSETS = np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])


def _disc(H=7, W=9):
    yy, xx = np.mgrid[0:H, 0:W]
    mask = (yy - 3) ** 2 + (xx - 4) ** 2 <= 10
    mask[3, 4] = False          # an inner edge
    mask[0, :] = False
    mask[0, 0] = True           # an isolated pixel: a component of its own
    return mask


def _pairs_brute(mask):
    """4-neighbour pairs of fitted pixels (group indices in row-major order), by a double loop."""
    H, W = mask.shape
    pix = np.flatnonzero(mask)
    g = {p: i for i, p in enumerate(pix)}
    out = []
    for r in range(H):
        for c in range(W):
            if not mask[r, c]:
                continue
            for rr, cc in ((r, c + 1), (r + 1, c)):
                if rr < H and cc < W and mask[rr, cc]:
                    out.append((g[r * W + c], g[rr * W + cc]))
    return out


def _prior_dense(pairs, G, tau, f):
    """R (2E, 2G): the prior's rows f (a_i - a_j) / tau, interleaved unknowns."""
    R = np.zeros((2 * len(pairs), 2 * G))
    for e, (i, j) in enumerate(pairs):
        for k in (0, 1):
            R[2 * e + k, 2 * i + k] = f / tau[k]
            R[2 * e + k, 2 * j + k] = -f / tau[k]
    return R


def _layout(mask, kind, tau=(0.05, 0.02), f=0.5):
    """(layout with the prior, dense mixing M (N, G) of each sample's albedo from the groups, dense R)."""
    from fmbrdf_mi.fit.evaluate.albedo_prior import SmoothPrior, neighbour_pairs
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos
    from fmbrdf_mi.fit.evaluate.bilinear_albedos import bilinear_weights

    H, W = mask.shape
    pixels = np.flatnonzero(mask)
    n, m = len(pixels), len(OFFSETS)
    prior = SmoothPrior(neighbour_pairs(pixels, W), n, tau, f)
    own = np.repeat(np.arange(n)[:, None], m, 1)
    if kind == "per-pixel":
        lay = PixelAlbedos(own, n, pixels, prior=prior)
        mix = np.zeros((n * m, n))
        mix[np.arange(n * m), own.ravel()] = 1.0
    else:
        def present(r, c):
            inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
            return inside & mask.ravel()[np.where(inside, r * W + c, 0)]

        rows, cols = np.divmod(pixels, W)
        corners, wts = bilinear_weights(rows, cols, OFFSETS, present)
        groups = np.searchsorted(pixels, corners[..., 0] * W + corners[..., 1])
        lay = PixelAlbedos(own, n, pixels, corner_groups=groups, corner_weights=wts, name="per-pixel-bilinear",
                           prior=prior)
        mix = np.zeros((n * m, n))
        np.add.at(mix, (np.repeat(np.arange(n * m), 4), groups.ravel()), wts.ravel())
    R = _prior_dense(_pairs_brute(mask), n, tau, f)
    return lay, mix, R


def _problem(mask, kind, seed=1, p=3, **kw):
    lay, mix, R = _layout(mask, kind, **kw)
    rng = np.random.default_rng(seed)
    N = mix.shape[0]
    S, B = rng.uniform(0.2, 1.0, N), rng.uniform(0.1, 0.6, N)
    M = np.zeros((N, 2 * lay.n_groups))          # d mu / d a, interleaved
    M[:, 0::2], M[:, 1::2] = mix * S[:, None], mix * B[:, None]
    y = M @ np.tile([0.7, 0.4], lay.n_groups) + rng.normal(0, 0.05, N)
    J = rng.normal(size=(N, p))
    return lay, M, R, S, B, y, J


@pytest.mark.parametrize("kind", ["per-pixel", "per-pixel-bilinear"])
def test_pairs_solve_and_projection_are_the_dense_augmented_ones(kind):
    """The neighbour pairs are the brute-force ones; the albedos solve min |y - M a|^2 + |R a|^2 (dense
    lstsq of [M; R] a = [y; 0]); Kaufman's Jacobian is (I - P) [J; 0], P the projection onto the columns of
    the residuals' derivative [-M; R] (N + 2E rows); the prior's residuals are R a.  To 1e-9."""
    mask = _disc()
    lay, M, R, S, B, y, J = _problem(mask, kind)
    got = np.sort(lay.prior.pairs, axis=1)
    want = np.sort(np.array(_pairs_brute(mask)), axis=1)
    assert sorted(map(tuple, got)) == sorted(map(tuple, want))
    a_s, a_b = lay.solve(S, B, y, np.ones_like(y))
    ref = np.linalg.lstsq(np.vstack([M, R]), np.concatenate([y, np.zeros(len(R))]), rcond=None)[0]
    np.testing.assert_allclose(np.stack([a_s, a_b], 1).ravel(), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    # the prior's residuals, in the layout's row order (all k_s pairs, then all k_b pairs) against R's (interleaved)
    r_prior = lay.prior.residuals(a_s, a_b)
    E = len(lay.prior.pairs)
    np.testing.assert_allclose(np.sort(r_prior[:E]), np.sort((R @ ref)[0::2]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.sort(r_prior[E:]), np.sort((R @ ref)[1::2]), rtol=1e-12, atol=1e-12)
    # Kaufman's Jacobian: the layout's prior rows are ordered (k_s pairs, k_b pairs): reorder R alike
    order = np.concatenate([np.arange(0, len(R), 2), np.arange(1, len(R), 2)])
    srt = np.lexsort((lay.prior.pairs[:, 1], lay.prior.pairs[:, 0]))
    assert np.array_equal(srt, np.arange(E))        # the layout's pairs are sorted, as the brute force's
    Ja = np.vstack([-M, R[order]])
    Jz = np.vstack([J, np.zeros((len(R), J.shape[1]))])
    P = Ja @ np.linalg.pinv(Ja)
    Jp, K = lay.project(J, -S, -B)
    assert Jp.shape == Jz.shape
    np.testing.assert_allclose(Jp, Jz - P @ Jz, rtol=0, atol=1e-9 * np.abs(Jz).max())


@pytest.mark.parametrize("kind", ["per-pixel", "per-pixel-bilinear"])
def test_posterior_covariance_and_effective_parameters_are_the_dense_ones(kind):
    """Each pair's covariance is the 2 x 2 block of the inverse of the full penalised information matrix
    [J_z, J_a]^T [J_z, J_a] (rows: data, then the prior's), the shape's covariance its shape block (the
    inverse of J_proj^T J_proj); the effective number of albedo parameters is tr(M (M^T M + R^T R)^-1 M^T)."""
    mask = _disc()
    lay, M, R, S, B, y, J = _problem(mask, kind, seed=3)
    Jp, _ = lay.project(J, -S, -B)
    cov_z = np.linalg.inv(Jp.T @ Jp)
    C = lay.covariance(-S, -B, J, cov_z)
    full = np.hstack([np.vstack([J, np.zeros((len(R), J.shape[1]))]), np.vstack([-M, R])])
    inv = np.linalg.inv(full.T @ full)
    p = J.shape[1]
    np.testing.assert_allclose(cov_z, inv[:p, :p], rtol=1e-9)
    blocks = np.stack([inv[p + 2 * g:p + 2 * g + 2, p + 2 * g:p + 2 * g + 2] for g in range(lay.n_groups)])
    np.testing.assert_allclose(C, blocks, rtol=1e-9, atol=1e-12 * np.abs(blocks).max())
    edf = np.trace(M @ np.linalg.solve(M.T @ M + R.T @ R, M.T))
    assert lay.effective_parameters(-S, -B) == pytest.approx(edf, rel=1e-9)


def test_null_dims_count_components():
    """2 per connected set of pixels: brute force by flood fill."""
    from fmbrdf_mi.fit.evaluate.albedo_prior import components

    mask = _disc()
    pairs = _pairs_brute(mask)
    n = int(mask.sum())
    seen, comps = set(), 0
    adj = {i: set() for i in range(n)}
    for i, j in pairs:
        adj[i].add(j)
        adj[j].add(i)
    for s in range(n):
        if s in seen:
            continue
        comps += 1
        stack = [s]
        while stack:
            u = stack.pop()
            if u not in seen:
                seen.add(u)
                stack.extend(adj[u])
    assert components(n, np.array(pairs)) == comps


def test_huge_tau_gives_the_unpenalised_albedos():
    """tau = 1e6 (k units, albedos ~0.5): the per-pixel layout's banded penalised solve gives the block-wise
    unpenalised solution of :class:`PixelAlbedos` to 1e-8 relative (the penalty's weight 1e-12 of G's)."""
    from fmbrdf_mi.fit.evaluate.albedos import PixelAlbedos

    mask = _disc()
    lay, M, R, S, B, y, J = _problem(mask, "per-pixel", tau=(1e6, 1e6))
    n, m = lay.n_groups, 4
    plain = PixelAlbedos(np.repeat(np.arange(n)[:, None], m, 1), n, lay.pixels)
    w = np.ones_like(y)
    a = np.stack(lay.solve(S, B, y, w), 1)
    b = np.stack(plain.solve(S.reshape(n, m), B.reshape(n, m), y.reshape(n, m), w.reshape(n, m)), 1)
    np.testing.assert_allclose(a, b, rtol=1e-8)


def test_chi2_degrees_of_freedom_rule_by_simulation():
    """With the maps drawn from the prior (a ~ N(0, Lambda^+), plus constants) and unit Gaussian noise, the
    penalised chi^2 at the optimum has mean N - n0 (n0 = null_dims: the rule of fit.json's albedo.prior,
    here with no shape parameters); maps that are exactly constant give N - edf instead (less).  400 draws:
    the mean within 4 of its standard errors."""
    mask = _disc()
    lay, M, R, S, B, y, J = _problem(mask, "per-pixel", tau=(0.05, 0.05), f=1.0)
    N = len(y)
    rng = np.random.default_rng(7)
    Rp = np.linalg.pinv(R)
    A = np.vstack([M, R])
    Q = np.eye(N + len(R)) - A @ np.linalg.pinv(A)
    w = np.ones(N)
    chi = []
    for _ in range(400):
        a = Rp @ rng.normal(size=len(R)) + np.tile([0.7, 0.4], lay.n_groups)
        yy = M @ a + rng.normal(size=N)
        a_s, a_b = lay.solve(S, B, yy, w)
        x = np.stack([a_s, a_b], 1).ravel()
        chi.append(np.sum((yy - M @ x) ** 2) + np.sum((R @ x) ** 2))
    chi = np.array(chi)
    n0 = lay.prior.null_dims()
    assert abs(chi.mean() - (N - n0)) < 4 * chi.std() / np.sqrt(len(chi)), (chi.mean(), N - n0)
    # constant maps: E = N - edf (the hat matrix's trace), below N - n0
    edf = lay.effective_parameters(-S, -B)
    assert n0 < edf < 2 * lay.n_groups
    c0 = [float(np.concatenate([e, np.zeros(len(R))]) @ Q @ np.concatenate([e, np.zeros(len(R))]))
          for e in rng.normal(size=(400, N))]
    assert abs(np.mean(c0) - (N - edf)) < 4 * np.std(c0) / 20


# ---------------------------------------------------------------- fits
def _constant_exact(res=12, lights=((-0.5, 0.5, 1.0),)):
    """Noise-free exact raw samples of a sphere with constant maps (area 1)."""
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere
    from fmbrdf_mi.sensor import samples as SM
    from fmbrdf_mi.sensor.camera import CameraModel, intensity_at_each_pixel

    out = []
    for L in lights:
        ideal = textured_sphere(SHAPE, lambda x, y: 0.6 + 0 * x, lambda x, y: 0.35 + 0 * x, res=res, light=L, area=1)
        cam = CameraModel(bits=16, full_well=1e6)
        obs, cap = capture_observation(ideal, cam, noiseless=True)
        exact = intensity_at_each_pixel(ideal["stokes"], cam.layout) * cap["exposure"] / cam.conversion_gain
        out.append((dataclasses.replace(obs, samples=SM.from_raw(exact, cam.layout, 0.0, cam.white_level)), ideal))
    return out


def test_noise_free_constant_maps_cost_nothing():
    """Constant maps are in the prior's null space: a noise-free fit with a tight prior (tau 0.01) recovers
    eta, alpha, beta within 0.1 % and the maps within 1e-3, its penalty ~0; fit.json's albedo.prior says
    what was used, the method says posterior."""
    from fmbrdf_mi.fit import fit

    (obs, ideal), = _constant_exact()
    res = fit(obs, albedo="per-pixel", albedo_smooth=0.01, max_pixels=None, intervals="fisher", progress=False,
              area_points=1)
    assert res.converged
    for k in ("eta", "alpha", "beta"):
        assert res.params[k] == pytest.approx(SHAPE[k], rel=1e-3), (k, res.params)
    f = np.isfinite(res.maps["k_s"])
    np.testing.assert_allclose(res.maps["k_s"][f], ideal["k_s_map"][f], rtol=1e-3)
    np.testing.assert_allclose(res.maps["k_b"][f], ideal["k_b_map"][f], rtol=1e-3)
    pr = res.albedo["prior"]
    assert pr["tau_s"] == pr["tau_b"] == 0.01 and pr["null_dims"] == 2
    assert pr["penalty"] < 1e-6 and pr["null_dims"] < pr["effective_parameters"] < pr["parameters"]
    assert res.uncertainty["method"].startswith("posterior covariance")
    assert "incidental" not in res.uncertainty and "not computed" in res.uncertainty["method"]
    assert res.loss_terms["albedo_prior"] == pytest.approx(pr["penalty"])
    assert np.all(np.isfinite(res.maps["k_s_se"][f]))
    assert "posterior" in res.albedo["warning"] and "sandwich" not in res.albedo["warning"]   # one image


def test_joint_fit_with_the_prior_and_bilinear_layout():
    """Two noisy lights of one view (camera noise), the bilinear layout with the prior: the fit's chi^2 is data
    chi^2 + penalty, the per-image diagnosis counts the samples' residuals only (their chi^2 sums to the data
    chi^2), and constant maps give eta, alpha, beta within 5 of their (posterior) standard errors."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel

    obs, exposure = [], None
    for k, L in enumerate(((-0.5, 0.5, 1.0), (0.287, 0.497, 0.819))):
        ideal = textured_sphere(SHAPE, lambda x, y: 0.6 + 0 * x, lambda x, y: 0.35 + 0 * x, res=12, light=L)
        o, cap = capture_observation(ideal, CameraModel(), seed=11 + k, exposure=exposure)
        exposure = cap["exposure"]
        obs.append(o)
    res = fit(obs, albedo="per-pixel-bilinear", albedo_smooth=0.02, max_pixels=None, intervals="fisher",
              starts=1, progress=False)
    assert res.converged and res.albedo["layout"] == "per-pixel-bilinear"
    for k in ("eta", "alpha", "beta"):
        assert abs(res.params[k] - SHAPE[k]) < 5 * res.std_errors[k], (k, res.params, res.std_errors)
    pr = res.albedo["prior"]
    assert pr["penalty"] > 0 and pr["data_chi2"] > 100
    assert sum(im["chi2"] for im in res.images) == pytest.approx(pr["data_chi2"], rel=1e-9)
    assert res.loss == pytest.approx(pr["data_chi2"] + pr["penalty"], rel=1e-9)


def test_refusals(tmp_path, capsys):
    """albedo_smooth: only with a per-pixel layout; tau > 0 and finite, one or two values; in one line naming
    the option (API and CLI, nothing written)."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError

    (obs, _), = _constant_exact(res=12)
    with pytest.raises(InputError, match="albedo_smooth: .*needs albedo per-pixel"):
        fit(obs, albedo_smooth=0.1, progress=False)
    for bad in (0.0, -1.0, float("inf"), float("nan"), (0.1, 0.0), (0.1, 0.1, 0.1), "x"):
        with pytest.raises(InputError, match="albedo_smooth"):
            fit(obs, albedo="per-pixel", albedo_smooth=bad, progress=False)
    labels = np.zeros(obs.shape, int)
    labels[:, 6:] = 1
    with pytest.raises(InputError, match="materials: not with albedo_smooth"):
        fit(obs, albedo="per-pixel", albedo_smooth=0.1, materials=labels, max_pixels=None, progress=False)
    raw = tmp_path / "raw.npy"
    np.save(raw, np.ones((16, 16)))
    base = ["fit", str(raw), "--sphere", "4,4,3", "--light=-0.5,0.5,1", "--conversion-gain", "1",
            "--read-noise", "2.5", "-q"]
    for extra, name in ((["--albedo-smooth", "0.1"], "--albedo-smooth"),
                        (["--albedo", "per-pixel", "--albedo-smooth", "0"], "--albedo-smooth"),
                        (["--albedo", "per-pixel", "--albedo-smooth", "0.1,x"], "--albedo-smooth"),
                        (["--albedo", "per-pixel", "--albedo-smooth", "0.1,0.2,0.3"], "--albedo-smooth")):
        capsys.readouterr()
        rc = main(base + extra + ["-o", str(tmp_path / "o")])
        one_line_error(rc, capsys.readouterr().err, "fit", name)
        assert not (tmp_path / "o").exists()


def test_cli_writes_the_prior_and_reruns_it(tmp_path, no_figures):
    """``fmbrdf-mi fit --albedo per-pixel --albedo-smooth TAU_S,TAU_B`` fits with the prior (fit.json's albedo.prior
    and the posterior method), and ``--from`` reruns it with the same prior (the same maps)."""
    import json

    from fmbrdf_mi.cli import main
    from fmbrdf_mi.synthetic.spheres import textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    ideal = textured_sphere(SHAPE, lambda x, y: 0.5 + 0.01 * x, lambda x, y: 0.35 + 0 * x, res=12,
                            light=(-0.5, 0.5, 1.0))
    cam = CameraModel()
    raw = tmp_path / "raw.npy"
    np.save(raw, capture(ideal["stokes"], cam, peak_fraction=0.8, seed=2)["raw"])
    args = ["fit", str(raw), "--sphere", "6,6,5", "--light=-0.5,0.5,1", "--conversion-gain",
            str(cam.conversion_gain), "--read-noise", "2.5", "--albedo", "per-pixel", "--albedo-smooth", "0.05,0.02",
            "--max-pixels", "0", "--intervals", "fisher", "--starts", "1", "-q"]
    assert main(args + ["-o", str(tmp_path / "a")]) == 0
    rep = json.load(open(tmp_path / "a" / "fit.json"))
    m = rep["models"]["fmbrdf"]
    assert m["albedo"]["prior"]["tau_s"] == 0.05 and m["albedo"]["prior"]["tau_b"] == 0.02
    assert m["uncertainty"]["method"].startswith("posterior covariance")
    assert (tmp_path / "a" / "k_s_se.exr").exists()
    assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "b"), "-q"]) == 0
    again = json.load(open(tmp_path / "b" / "fit.json"))["models"]["fmbrdf"]
    assert again["albedo"]["prior"] == m["albedo"]["prior"]
    assert again["params"] == m["params"]
