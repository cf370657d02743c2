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

from fmbrdf_mi.fit import fit
from fmbrdf_mi.fit.api.fitting import FitOptions
from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
from fmbrdf_mi.sensor.camera import CameraModel

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


def _check_inflated(honest, wrong, keys, u_wrong, u_honest):
    """The honest fit is not flagged; the misstated one is, says so in its method, and its inflated errors of
    ``keys`` are the honest ones within 0.8-1.25 (without the inflation: about 1/3)."""
    assert not u_honest["misfit"] and "inflated" not in u_honest["method"]
    assert u_wrong["misfit"] and u_wrong["chi2_per_dof"] > 4 and "inflated by chi^2/dof" in u_wrong["method"]
    for k in keys:
        ratio = wrong[k] / honest[k]
        assert 0.8 < ratio < 1.25, (k, ratio)


def test_misfit_with_free_powers_and_per_pixel_albedos():
    """The same rule where the unknowns differ: a joint fit with its light powers free (the powers' errors come
    through the same inflation), and a per-pixel albedo fit (chi^2/dof counts every pixel's two albedos, which
    the projection eliminates: without that count the honest fit would read as a misfit, chi^2/dof ~ 1.5 here)."""
    from fmbrdf_mi.fit.api.fitting import fit_joint

    cam = CameraModel(full_well=3000.0, read_noise=2.0, bits=12)
    obs = [capture_observation(ideal_sphere(TRUE, res=16, light=l), cam, seed=7 + k)[0] for k, l in enumerate(LIGHTS)]
    fixed = {k: SHAPE[k] for k in ("beta", "kappa")}
    lines = []
    # from the truth, Fisher intervals: the rule is about the standard errors at the optimum
    kw = dict(free_power=True, fixed=fixed, starts=1, init=TRUE, intervals="fisher")
    honest = fit_joint(obs, progress=False, **kw)
    wrong = fit_joint([_misstated(o) for o in obs], progress=lines.append, **kw)
    assert honest.converged and wrong.converged
    _check_inflated(honest.std_errors, wrong.std_errors, ["eta", "alpha", "r_k"], wrong.uncertainty,
                    honest.uncertainty)
    ratio = wrong.powers["std_errors"][1] / honest.powers["std_errors"][1]   # image 0 is the reference
    assert 0.8 < ratio < 1.25, ratio
    assert any("warning: chi^2/dof" in s for s in lines), lines

    opts = FitOptions(loss="likelihood", fixed=fixed, starts=1, albedo="per-pixel", init=SHAPE, intervals="fisher")
    honest = fit(obs[0], opts, progress=False)
    lines = []
    wrong = fit(_misstated(obs[0]), opts, progress=lines.append)
    assert honest.converged and wrong.converged
    _check_inflated(honest.std_errors, wrong.std_errors, ["eta", "alpha"], wrong.uncertainty, honest.uncertainty)
    assert any("warning: chi^2/dof" in s for s in lines), lines
    # the per-pixel albedo maps' errors are inflated by the same factor
    sel = np.isfinite(honest.maps["k_b_se"]) & np.isfinite(wrong.maps["k_b_se"])
    ratio = np.median(wrong.maps["k_b_se"][sel] / honest.maps["k_b_se"][sel])
    assert 0.8 < ratio < 1.25, ratio


def test_misfit_of_a_colour_fit():
    """A colour mosaic (per-channel albedos) fitted with its gain stated 9 times too high: flagged and inflated
    to the honest errors, as the mono fit (the colour path once reported chi^2/dof 6 with no warning)."""
    from fmbrdf_mi.fit.api.colour import fit_colour
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.camera import capture
    from fmbrdf_mi.sensor.noise import NoiseModel
    from fmbrdf_mi.sensor.samples import colour_samples

    R, light = 12, (0.45, 0.35, 1.0)
    shape = dict(eta=1.5, alpha=0.25, beta=0.4, kappa=1.0)
    st = np.stack([ideal_sphere({**shape, "k_s": ks, "r_k": rk}, res=2 * R, light=light)["stokes"]
                   for ks, rk in ((0.6, 0.8), (0.4, 1.5), (0.5, 0.4))])
    cam = CameraModel(cfa=mosaic.BAYER_RGGB, bits=12, full_well=3000, read_noise=2.0)
    cap = capture(st, cam, peak_fraction=0.8, seed=5)
    smp = colour_samples(cap["raw"], cam.layout, cam.cfa, cam.black_level, cam.white_level)
    n, m, v = G.sphere_normals((R, R), (R / 2, R / 2), R / 2 - 0.5)
    geom = G.SphereGeometry((R, R), (R / 2, R / 2), R / 2 - 0.5)
    obs = ob.Observation(np.ones((3, R, R)), ob.erode(m, 1), n, v, np.asarray(light, float),
                         cap["exposure"] / cam.conversion_gain, geometry=geom)
    kw = dict(fixed={"beta": 0.4, "kappa": 1.0}, intervals="fisher")
    honest = fit_colour(obs, smp, NoiseModel(cam.conversion_gain, cam.read_noise, 1.0), **kw)
    wrong = fit_colour(obs, smp, NoiseModel(9 * cam.conversion_gain, cam.read_noise, 1.0), **kw)
    flat = lambda se: {f"{k}[{c}]" if isinstance(v, dict) else k: (v[c] if isinstance(v, dict) else v)  # noqa: E731
                       for k, v in se.items() for c in (v if isinstance(v, dict) else [None])}
    _check_inflated(flat(honest["std_errors"]), flat(wrong["std_errors"]), ["eta", "k_s[G]", "r_k[R]"],
                    wrong["uncertainty"], honest["uncertainty"])


def test_misfit_of_the_normal_refinement():
    """The joint refinement of material and normals (its covariance the sandwich of the penalised likelihood):
    the same flag and inflation, on a 16^2 mesh object read with its gain stated 9 times too high."""
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object
    from fmbrdf_mi.fit.inputs.authors import read_object
    import tempfile

    true = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
    lights, powers = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)], [1.0, 0.7, 1.2]
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        truth = write_authors_object(tmp + "/o", true, lights, res=16, fov=12.0, powers=powers, seed=3)
        for name, factor in (("honest", 1.0), ("wrong", 9.0)):
            specs, _ = read_object(tmp + "/o", conversion_gain=factor * truth["camera"]["conversion_gain"],
                                   read_noise=2.5)
            obs = [s.input for s in specs]
            gt = obs[0].normals.copy()
            start = dict(true, k_s=truth["irradiance_dn"] * max(powers))
            res[name] = refine_joint(obs, gt, start, lam=0.3, max_iter=15)
    honest, wrong = res["honest"], res["wrong"]
    assert honest.converged and wrong.converged
    u_w = wrong.uncertainty
    # the honest refinement's chi^2/dof is 1.1-1.5 (the normals' bilinear model on this strongly curved 16^2
    # object), so only the misstated one is required to be flagged, and the ratio is to the honest errors
    # inflated by the honest fit's own factor where it has one
    assert u_w["misfit"] and u_w["chi2_per_dof"] > 4 and "inflated by chi^2/dof" in u_w["method"]
    for k in ("k_s", "r_k", "eta"):
        ratio = wrong.std_errors[k] / honest.std_errors[k]
        assert 0.8 < ratio < 1.25, (k, ratio)


def test_misfit_of_a_colour_per_pixel_fit():
    """Per-pixel albedos of a colour mosaic (one pair per period and channel): the same flag and inflation
    through the same code path as the mono per-pixel fit (chi^2/dof counts the eliminated albedos, three pairs
    per period), for the shape parameters and for each channel's maps."""
    from fmbrdf_mi.fit.api.colour import fit_colour
    from fmbrdf_mi.synthetic.spheres import capture_colour, textured_sphere
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.noise import NoiseModel

    R = 12
    y, x = np.mgrid[0:R, 0:R] / R
    ks = np.stack([0.6 + 0.3 * np.sin(6 * x) * np.cos(4 * y), 0.4 + 0.2 * np.cos(3 * x), 0.5 + 0.2 * np.sin(5 * y)])
    kb = np.stack([0.4 + 0.1 * np.cos(5 * x + 3 * y), 0.7 + 0.2 * np.sin(4 * x), 0.3 + 0.1 * np.cos(2 * y)])
    cam = CameraModel(cfa=mosaic.BAYER_RGGB, bits=12, full_well=3000, read_noise=2.0)
    obs, smp = [], []
    for k, light in enumerate(LIGHTS):
        o, s, noise, _ = capture_colour(textured_sphere(SHAPE, ks, kb, res=R, light=light), cam, seed=11 + k,
                                        exposure=None if k == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
        smp.append(s)
    kw = dict(fixed={"beta": SHAPE["beta"], "kappa": SHAPE["kappa"]}, intervals="fisher", albedo="per-pixel",
              starts=1)
    lines = []
    honest = fit_colour(obs, smp, noise, **kw)
    wrong = fit_colour(obs, smp, NoiseModel(9 * cam.conversion_gain, cam.read_noise, 1.0), progress=lines.append,
                       **kw)
    assert honest.converged and wrong.converged
    _check_inflated(honest.std_errors, wrong.std_errors, ["eta", "alpha"], wrong.uncertainty, honest.uncertainty)
    assert "incidental" in honest.uncertainty["method"] and "incidental" in wrong.uncertainty["method"]
    assert any("warning: chi^2/dof" in s for s in lines), lines
    for key in ("k_s_se", "k_b_se"):
        for c in range(3):
            h, w = honest.maps[key][c], wrong.maps[key][c]
            sel = np.isfinite(h) & np.isfinite(w)
            ratio = np.median(w[sel] / h[sel])
            assert sel.sum() > 40 and 0.8 < ratio < 1.25, (key, c, ratio)


# ---------------------------------------------------------------- chi^2/dof far below 1 with the stated noise
def _noise_scale(sd, n=4000, p=5, known=True):
    from types import SimpleNamespace

    from fmbrdf_mi.fit import uncertainty as U

    problem = SimpleNamespace(obj=SimpleNamespace(noise=SimpleNamespace(known=known)))
    r = np.random.default_rng(2).normal(0.0, sd, n)       # standardised residuals: sd 1 when the noise is right
    return U.noise_scale(problem, r, None, p)


@pytest.mark.parametrize("sd", [np.sqrt(1e-5), 0.1, 0.9])
def test_chi2_far_below_one_is_flagged_and_the_errors_kept(sd):
    """Before: chi^2/dof 1e-5 with the camera noise known passed silently (the check was one-sided)."""
    from fmbrdf_mi.fit import uncertainty as U

    scale, info, applied = _noise_scale(sd)
    assert abs(info["chi2_per_dof"] - sd ** 2) < 0.1 * sd ** 2
    assert scale == 1.0 and not info["misfit"]            # the errors are those of the stated noise
    assert info["noise_overstated"] is True and U.noise_flagged(info)
    text = U.misfit_text(info)
    assert info["noise_warning"] == text and "scatter less than that noise" in text and "too large" in text
    assert f"{sd ** 2:.3g}"[:3] in text


@pytest.mark.parametrize("sd,misfit", [(1.0, False), (0.97, False), (1.03, False), (3.0, True)])
def test_chi2_near_or_above_one_is_not_flagged_as_overstated(sd, misfit):
    """The threshold mirrors the misfit's: 5 standard deviations of chi^2/dof (sqrt(2 / dof)), at least 0.1."""
    from fmbrdf_mi.fit import uncertainty as U

    scale, info, _ = _noise_scale(sd)
    assert "noise_overstated" not in info and info["misfit"] is misfit and U.noise_flagged(info) is misfit
    assert scale == (info["chi2_per_dof"] if misfit else 1.0)


def test_estimated_noise_is_never_flagged_overstated():
    scale, info, _ = _noise_scale(1e-3, known=False)
    assert "noise_overstated" not in info and scale == info["chi2_per_dof"]


def test_the_summary_prints_the_overstated_noise_warning(capsys):
    from fmbrdf_mi.fit import uncertainty as U
    from fmbrdf_mi.fit.outputs import summary

    _, info, _ = _noise_scale(np.sqrt(1e-5))
    model = {"chi2_per_dof": info["chi2_per_dof"], "n_samples": 4000, "n_pixels": 1000, "converged": True,
             "stop_reason": "tol", "noise": {"description": "known"}, "std_errors": {}, "ci95": {},
             "params": {"alpha": 0.1}, "uncertainty": info}
    summary.print_summary({"sensor": "colour", "models": {"fmbrdf": model}, "outputs": ["fit.json"], "wall_s": 1.0})
    assert "warning: " + U.misfit_text(info) in capsys.readouterr().out
