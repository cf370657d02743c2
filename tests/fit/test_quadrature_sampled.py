"""The pixel-area quadrature's bias estimated from a sample of the pixels (uncertainty.quadrature_sample,
uncertainty.sampled_quadrature_bias, checks.check_footprint above its pixel threshold) against the check on
all pixels (uncertainty.quadrature_bias) of the same fit and data."""
import numpy as np
import pytest

from fmbrdf_mi.fit import fit
from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.api.checks import check_footprint
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.sensor.camera import CameraModel
from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere

GLOSSY = dict(eta=1.5, alpha=0.06, beta=1.4, kappa=30.0, k_s=0.9, r_k=1.0)
LIGHT = (-0.5, 0.5, 1.0)


@pytest.fixture(scope="module")
def obs():
    # the camera integrates each raw pixel over 8 x 8 points: a sharp highlight the 2 x 2 quadrature biases
    return capture_observation(ideal_sphere(GLOSSY, res=28, light=LIGHT, area=8), CameraModel(), seed=3)[0]


def two_by_two(obs, albedo):
    init = GLOSSY if albedo == "shared" else {k: v for k, v in GLOSSY.items() if k not in ("k_s", "r_k")}
    return fit(obs, progress=False, area_points=2, intervals="fisher", init=init, starts=1, albedo=albedo)


@pytest.fixture(scope="module")
def fits(obs):
    return {}


@pytest.fixture(scope="module", params=["shared", "per-pixel"])
def case(request, obs, fits):
    """(2 x 2 fit, its J and r, the whole check's bias, the predicted terms) for shared albedos and for
    albedo maps."""
    res = fits[request.param] = two_by_two(obs, request.param)
    fx = res.fitted
    problem, data, st, opts = fx.problem, fx.data, fx.solution.state, fx.options
    r, J = problem.residuals_and_jacobian(problem.parts(st, jac=True), st, problem.to_z(st))
    fine = data.remake(4).problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
    coarser = data.remake(1).problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
    g_hat = U.predicted_quadrature_terms(problem, coarser, st, J, r, 2, 1)
    return res, J, r, U.quadrature_bias(problem, fine, st, J, r), g_hat


def draw(case, n, seed):
    res, J, _, _, g_hat = case
    return U.quadrature_sample(res.fitted.problem, J, g_hat, n, np.random.default_rng(seed))


def sampled(case, cells, pi):
    res, J, r, _, g_hat = case
    fx = res.fitted
    opts = fx.options
    sub = fx.data.remake(4, cells=cells).problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
    return U.sampled_quadrature_bias(fx.problem, sub, fx.solution.state, J, r, cells, pi, g_hat)


def test_every_pixel_sampled_is_the_whole_check(case):
    """A sample of all cells (every inclusion probability 1) reproduces the whole check and has no sampling
    error: the sampled cells' rows, data and albedos are the whole check's."""
    res, full = case[0], case[3]
    n = len(res.fitted.data.pixels)
    cells, pi = draw(case, n, 0)
    assert len(cells) == n and np.all(pi == 1.0)
    bias, spread = sampled(case, cells, pi)
    for k in full:
        assert bias[k] == pytest.approx(full[k], rel=1e-6, abs=1e-9), k
        assert spread[k] == 0.0


def test_inclusion_probabilities_sum_to_the_sample_size(case):
    n = len(case[0].fitted.data.pixels) // 4
    counts = [len(draw(case, n, seed)[0]) for seed in range(200)]
    # Poisson sampling: the sample size's mean is n, its SD at most sqrt(n)
    assert abs(np.mean(counts) - n) < 4 * np.sqrt(n / 200)


def test_a_quarter_of_the_pixels_agrees_with_the_whole_check_within_its_sampling_se(case):
    """Five seeds' samples of about a quarter of the cells: each parameter's sampled bias lies within 4 of its
    own sampling SE of the whole check's (a Horvitz-Thompson estimate: unbiased), and over seeds and
    parameters the squared deviations in sampling SE average below 3 (about 1 for a calibrated SE)."""
    res, full = case[0], case[3]
    n = len(res.fitted.data.pixels) // 4
    z = []
    for seed in range(5):
        cells, pi = draw(case, n, seed)
        assert len(cells) < len(res.fitted.data.pixels) / 2
        bias, spread = sampled(case, cells, pi)
        for k in full:
            assert spread[k] > 0
            z.append((bias[k] - full[k]) / spread[k])
            assert abs(z[-1]) < 4, (seed, k, bias[k], full[k], spread[k])
    assert np.mean(np.square(z)) < 3


def test_a_bias_over_the_tolerance_is_caught_by_the_sampled_check(obs, fits, case):
    """The whole check finds the 2 x 2 quadrature biased (alpha over 0.2 SE here); with the pixel threshold
    lowered, the sampled check refits with 4 x 4 points on all pixels too, and records its sample; at the
    threshold the whole check runs."""
    if case[0] is not fits.get("shared"):
        pytest.skip("once, with shared albedos")
    two, full = case[0], case[3]
    n = len(two.fitted.data.pixels)
    assert max(abs(v) for v in full.values()) > U.QUADRATURE_TOL
    q = check_footprint(two, progress=lambda s: None, sample_above=n - 1, sample_pixels=n // 4)
    q = q.uncertainty["quadrature"]
    first = q["checks"][0]
    assert first["sampled"]["of"] == n and 0 < first["sampled"]["pixels"] < n
    assert set(first["sampled"]["sampling_se"]) == set(first["bias_se"])
    assert q["area_points"] >= 4
    below = check_footprint(two, progress=lambda s: None, sample_above=n)
    assert "sampled" not in below.uncertainty["quadrature"]["checks"][0]
    assert below.uncertainty["quadrature"]["checks"][0]["bias_se"] == full
