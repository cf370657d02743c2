"""The parametric bootstrap of one-image per-pixel fits (docs/benchmarks/coverage.md, "One image, per-pixel
albedos"): :func:`~fmbrdf_mi.fit.uncertainty.bootstrap_draws` against the closed-form sampling distribution of
a linear-Gaussian model with one intercept per group of two samples (the incidental parameters), and a fit
whose sandwich is unreliable reporting the bootstrap's errors and intervals."""
import math

import numpy as np


def _within(x, g, y):
    """The slope of y on x with one free intercept per group (the groups' means removed): the MLE."""
    n = int(g.max()) + 1
    xc = x - (np.bincount(g, x, n) / np.bincount(g, minlength=n))[g]
    yc = y - (np.bincount(g, y, n) / np.bincount(g, minlength=n))[g]
    return np.array([xc @ yc / (xc @ xc)])


def test_bootstrap_matches_the_closed_form_spread_of_a_slope_with_group_intercepts():
    """y_gi = a_g + theta x_gi + sigma_gi e: the slope's exact sampling SD with the intercepts profiled out is
    1 / sqrt(sum (x - xbar_g)^2 / sigma^2) (here sigma equal within each group, unequal between them: the
    weighted within-group estimator's); the bootstrap at the estimate with the known sigma reproduces it and its
    percentile interval is theta_hat +- 1.96 of it (the estimate is linear in y: the distribution is normal)."""
    from fmbrdf_mi.fit.uncertainty import bootstrap_draws, bootstrap_summary

    rng = np.random.default_rng(3)
    G = 300
    g = np.repeat(np.arange(G), 2)
    x = rng.normal(size=2 * G)
    sig = np.repeat(rng.uniform(0.5, 2.0, G), 2)
    a = rng.normal(size=G)[g]
    y = a + 0.7 * x + sig * rng.normal(size=2 * G)

    def refit(yy):      # the weighted within estimator: sigma is constant in each group
        return _within(x / sig, g, yy / sig)

    theta = refit(y)[0]
    xc = x - (np.bincount(g, x) / 2)[g]
    exact = 1.0 / math.sqrt(np.sum((xc / sig) ** 2))
    mu = (a - a.mean()) + theta * x      # any intercepts: the slope's distribution does not depend on them
    B = 4000
    v = bootstrap_draws(mu, sig, refit, draws=B, seed=11)
    s = bootstrap_summary(["theta"], {"theta": theta}, v)
    tol = 4.0 / math.sqrt(2 * B)        # 4 standard errors of an SD from B draws
    assert abs(s["std_errors"]["theta"] / exact - 1) < tol, (s["std_errors"]["theta"], exact)
    assert abs(np.mean(v) - theta) < 4 * exact / math.sqrt(B)
    lo, hi = s["ci95"]["theta"]
    for end, ref in ((lo, theta - 1.959964 * exact), (hi, theta + 1.959964 * exact)):
        assert abs(end - ref) < 0.1 * exact, (end, ref, exact)


def test_bootstrap_draws_are_seeded_and_reported_with_the_time_left():
    from fmbrdf_mi.fit.uncertainty import bootstrap_draws

    said = []
    a = bootstrap_draws(np.zeros(5), np.ones(5), lambda y: y[:2], draws=3, seed=1, progress=said.append)
    b = bootstrap_draws(np.zeros(5), np.ones(5), lambda y: y[:2], draws=3, seed=1)
    assert a.shape == (3, 2) and np.array_equal(a, b)
    assert len(said) == 3 and "draw 1/3" in said[0] and "left in the bootstrap" in said[0], said


def _one_image_fit(progress=False):
    """One noisy image of a small sphere with per-pixel albedos, beta and kappa fixed: its noise share is above
    NOISE_SHARE_MAX (tests/fit/test_uncertainty_incidental.py)."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
    from fmbrdf_mi.sensor.camera import CameraModel

    true = {"eta": 1.55, "alpha": 0.35, "beta": 1.4, "kappa": 30.0, "k_s": 0.9, "r_k": 1.7}
    obs = capture_observation(ideal_sphere(true, res=16, light=(0.45, 0.35, 1.0)),
                              CameraModel(full_well=3000.0, read_noise=2.0, bits=12), seed=7)[0]
    return fit(obs, FitOptions(loss="likelihood", fixed={"beta": 1.4, "kappa": 30.0}, starts=1, albedo="per-pixel",
                               intervals="fisher"), progress=progress)


def test_unreliable_sandwich_is_replaced_by_the_bootstrap(monkeypatch):
    """The fit refits bootstrap captures (fewer draws here, for time): each shape SE is max(sandwich SE,
    bootstrap SD), each interval holds the bootstrap's percentile one and +- 1.96 SE, interval_kind says
    bootstrap, and the method names it instead of the unreliable label."""
    from fmbrdf_mi.fit import uncertainty as U

    monkeypatch.setattr(U, "BOOTSTRAP_DRAWS", 6)
    said = []
    r = _one_image_fit(said.append)
    u = r.uncertainty
    assert r.converged and u["incidental"]["noise_share"] > 0.5, u.get("incidental")
    boot = u["bootstrap"]
    assert boot["draws"] == 6 and set(boot["std_errors"]) == {"eta", "alpha"}
    assert boot["pixels"] == boot["of_pixels"] == r.n_pixels
    for n in ("eta", "alpha"):
        se, sw, bsd = r.std_errors[n], boot["sandwich_std_errors"][n], boot["std_errors"][n]
        assert math.isclose(se, max(sw, bsd), rel_tol=1e-12), (n, se, sw, bsd)
        lo, hi = u["ci95"][n]
        blo, bhi = boot["ci95"][n]
        assert lo <= min(blo, r.params[n] - U.Z95 * se) + 1e-12 and hi >= max(bhi, r.params[n] + U.Z95 * se) - 1e-12
        assert u["interval_kind"][n] == "bootstrap"
    assert "parametric bootstrap at the estimate (6 draws;" in u["method"], u["method"]
    assert "not confidence intervals" not in u["method"]
    assert any("bootstrap: draw" in m and "left" in m for m in said)


def test_many_pixels_bootstrap_on_a_subsample(monkeypatch):
    """Above BOOTSTRAP_PIXELS the draws are refitted on a seeded subsample of that many pixels, and the
    method says so."""
    from fmbrdf_mi.fit import uncertainty as U

    monkeypatch.setattr(U, "BOOTSTRAP_DRAWS", 3)
    monkeypatch.setattr(U, "BOOTSTRAP_PIXELS", 50)
    r = _one_image_fit()
    boot = r.uncertainty["bootstrap"]
    assert boot["pixels"] == 50 and boot["of_pixels"] == r.n_pixels > 50, boot
    assert "3 draws on 50 of the" in r.uncertainty["method"], r.uncertainty["method"]
