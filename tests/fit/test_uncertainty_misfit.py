"""A misfit (chi^2/dof far above 1 with the stated camera noise) warns and inflates, in every mode.

The reference for "inflated enough" is independent of the inflation: the same captures fitted with the
camera noise stated correctly, whose Fisher standard errors the noise bench shows to be honest
(tests/fit/test_objectives_likelihood.py: coverage over 150 seeds).  Stating a gain 9 times too high
makes the stated variance of these shot-noise-limited samples about 9 times too small: the Fisher
errors alone would then be about 3 times too small, the inflated ones come back to the honest ones.
"""
import dataclasses
import math

import numpy as np
import pytest

from fmbrdf_mi.camera import CameraModel
from fmbrdf_mi.fit import fit
from fmbrdf_mi.fit.api.fitting import FitOptions
from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, ideal_sphere

TRUE = {"eta": 1.55, "alpha": 0.35, "beta": 1.4, "kappa": 30.0, "k_s": 0.9, "r_k": 1.7}
SHAPE = {k: TRUE[k] for k in ("eta", "alpha", "beta", "kappa")}
LIGHTS = [(0.45, 0.35, 1.0), (-0.3, 0.2, 1.0)]


def _misstated(obs, factor=9.0):
    return dataclasses.replace(obs, noise=dataclasses.replace(obs.noise, gain=obs.noise.gain * factor))


@pytest.mark.parametrize("mode", ["single", "joint"])
def test_misfit_warns_and_inflates_to_the_honest_errors(mode):
    cam = CameraModel(full_well=3000.0, read_noise=2.0, bits=12)
    lights = LIGHTS[:1] if mode == "single" else LIGHTS
    obs = [capture_observation(ideal_sphere(TRUE, res=16, light=l), cam, seed=7 + k)[0] for k, l in enumerate(lights)]
    data = obs[0] if mode == "single" else obs
    bad = _misstated(obs[0]) if mode == "single" else [_misstated(o) for o in obs]
    opts = FitOptions(loss="likelihood", fixed=SHAPE, starts=1)
    lines = []
    honest = fit(data, opts, progress=False)
    wrong = fit(bad, opts, progress=lines.append)
    assert honest.converged and wrong.converged
    assert not honest.uncertainty["misfit"] and "inflated" not in honest.uncertainty["method"]
    u = wrong.uncertainty
    assert u["misfit"] and u["chi2_per_dof"] > 4 and "inflated by chi^2/dof" in u["method"]
    assert any("warning: chi^2/dof" in s and "inflated by sqrt(chi^2/dof)" in s for s in lines), lines
    for k in ("k_s", "r_k"):
        # the same estimate (IRLS weights differ only by a common factor where shot noise dominates)
        assert abs(wrong.params[k] - honest.params[k]) < 0.5 * honest.std_errors[k], k
        ratio = wrong.std_errors[k] / honest.std_errors[k]
        assert 0.8 < ratio < 1.25, (k, ratio)                 # without inflation: ~1/3
        lo, hi = u["ci95"][k]
        assert math.isclose(hi - lo, 2 * 1.959964 * wrong.std_errors[k], rel_tol=1e-5) or lo == 0.0


def test_no_misfit_leaves_the_fisher_errors_alone():
    """chi^2/dof near 1: the covariance is the inverse Fisher information, not scaled (the flag's threshold
    is 5 standard deviations of chi^2/dof above 1)."""
    cam = CameraModel(full_well=3000.0, read_noise=2.0, bits=12)
    obs = capture_observation(ideal_sphere(TRUE, res=16, light=LIGHTS[0]), cam, seed=3)[0]
    r = fit(obs, FitOptions(loss="likelihood", fixed=SHAPE, starts=1), progress=False)
    u = r.uncertainty
    n = r.n_pixels * 4
    assert abs(u["chi2_per_dof"] - 1) < 5 * math.sqrt(2 / n) + 0.1 and not u["misfit"]
    assert u["method"] == "inverse Fisher information (known camera noise)"
    assert np.isfinite([r.std_errors["k_s"], r.std_errors["r_k"]]).all()
