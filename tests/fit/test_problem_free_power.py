"""Relative light powers as free parameters of a joint fit (fmbrdf_mi.fit.problem.free_power, ``--free-power``).

References independent of the code under test: synthetic captures whose true
powers are known (the sphere rendered with each image's light scaled by its
power, one exposure for all), and the joint fit's plain code path (no power
wrapper) at scaled irradiances for finite differences of the power columns.
"""
import json
import math

import numpy as np
import pytest

TRUE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)]
POWERS = [1.0, 0.6, 1.7]
NEAR = {"eta": 1.5, "alpha": 0.22, "beta": 1.2, "kappa": 14.0, "k_s": 0.8, "r_k": 0.6}


@pytest.fixture(scope="module")
def variant():
    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    set_variant()


def _captures(res=16, powers=POWERS, seed=0):
    """(observations, raw captures): one exposure for all images, image k's light ``powers[k]`` times as
    bright; every observation's irradiance is the same (the fit is told power 1 for all)."""
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    cam = CameraModel()
    ideals = [ideal_sphere(TRUE, res=res, light=l) for l in LIGHTS]
    for i, p in zip(ideals, powers):
        i["stokes"] = i["stokes"] * p
    exposure = 0.8 * cam.full_well / max(i["stokes"][0].max() for i in ideals)
    obs, caps = [], []
    for k, i in enumerate(ideals):
        o, cap = capture_observation(i, cam, seed=seed + k, exposure=exposure)
        obs.append(o)
        caps.append(cap)
    return obs, caps, cam


def test_free_powers_are_recovered_and_fixed_powers_bias_the_fit(variant):
    """True powers 1, 0.6, 1.7, given 1, 1, 1.  With free powers: powers and the six parameters within
    4 reported standard errors of the truth (two-sided 6e-5 each if the errors are right; their
    calibration over seeds is measured by tools/bench_fit_lights.py --free-power), the reference's
    power exactly its given value.  Without: from the truth itself the fit moves many standard errors
    away and chi^2 / dof is far above 1 (the data are not explained)."""
    from fmbrdf_mi.fit.api.fitting import fit_joint

    obs, _, _ = _captures()
    res = fit_joint(obs, free_power=True, progress=False, names=["a", "b", "c"], intervals="fisher")
    f = res
    assert f.converged and f.objective == "likelihood"
    assert set(f.params) == set(TRUE)          # the powers are reported apart from the material
    p = res.powers
    assert p["reference"] == "a" and p["values"][0] == 1.0 and p["std_errors"][0] == 0.0
    for k in (1, 2):
        se = p["std_errors"][k]
        assert 0 < se < 0.02 and abs(p["values"][k] - POWERS[k]) < 4 * se, (k, p["values"][k], se)
        lo, hi = p["ci95"][k]
        assert lo < p["values"][k] < hi and math.isclose(hi - lo, 2 * 1.959964 * se, rel_tol=1e-6)
        assert res.images[k]["power"] == p["values"][k] and res.images[k]["power_se"] == se
    for k, v in TRUE.items():
        assert abs(f.params[k] - v) < 4 * f.std_errors[k], (k, f.params[k], f.std_errors[k])
    for im in res.images:
        assert abs(im["chi2_per_dof"] - 1.0) < 0.3, im
    assert "power_1" in f.uncertainty["correlation"]["names"]

    fixed = fit_joint(obs, init=TRUE, progress=False, intervals="fisher")
    assert fixed.powers is None and "power" not in fixed.images[0]
    chi2 = max(im["chi2_per_dof"] for im in fixed.images)
    assert chi2 > 3.0, chi2
    off = max(abs(fixed.params[k] - v) / f.std_errors[k] for k, v in TRUE.items())
    assert off > 8.0, off


def test_power_start_given_converges_to_the_same_estimate(variant):
    """Starting the powers at the given (wrong) values instead of the closed form reaches the same optimum
    (to 0.05 standard errors: the likelihood's stopping rule is ~0.1 SE)."""
    from fmbrdf_mi.fit.api.fitting import fit_joint

    obs, _, _ = _captures(res=12, seed=10)
    a = fit_joint(obs, free_power=True, init=NEAR, progress=False)
    b = fit_joint(obs, free_power=True, init=NEAR, power_start="given", progress=False)
    assert a.converged and b.converged
    for k in TRUE:
        assert abs(a.params[k] - b.params[k]) < 0.1 * a.std_errors[k], k
    for k in (1, 2):
        assert abs(a.powers["values"][k] - b.powers["values"][k]) < 0.1 * a.powers["std_errors"][k]


def test_power_columns_of_the_jacobian_are_the_derivative(variant):
    """The Fisher information's power columns: the analytic d residual / d P_k (no BSDF evaluation) against
    central finite differences of the residuals computed by the joint fit's plain path (no power
    wrapper) with image k's irradiance scaled by P_k, variances frozen.  The prediction is linear in
    P_k, so the difference quotient is exact up to rounding of float32 BSDF values (1e-5 relative)."""
    import dataclasses

    from fmbrdf_mi.fit import FitOptions
    from fmbrdf_mi.fit import uncertainty as U
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, State
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.problem import free_power as FP
    from fmbrdf_mi.fit.problem.data import prepare
    from fmbrdf_mi.fit.problem.problem import Problem

    obs, _, _ = _captures(res=12)
    opts = FitOptions(loss="likelihood", max_pixels=None)
    given = [1.0, 0.8, 1.3]
    obs = [dataclasses.replace(o, irradiance=o.irradiance * g) for o, g in zip(obs, given)]
    data = prepare(obs, opts, "likelihood")
    slices = data.slices
    pm = Parameters(FMBRDF, powers=given)
    pev = FP.PowerEvaluator(data.evaluator, pm, [b - a for a, b in slices])
    pb = FP.problem_factory(pev, slices)(FMBRDF, pev, data.objective, None, None, None, None)
    powers = {"power_1": 0.7, "power_2": 1.9}
    shape, a_s, a_b = pm.split({**NEAR, **powers})
    st = State(shape, a_s, a_b)
    pb.obj.refresh(pb.parts(st), st)
    var = pb.obj.var.copy()
    r, J = pb.residuals_and_jacobian(pb.parts(st, jac=True), st, pb.to_z(st))
    names, Jt = U.jacobian_in_reported(pb, st, J)

    def plain_residuals(p):   # the unwrapped joint path at irradiance x P_k / G_k
        scaled = [dataclasses.replace(o, irradiance=o.irradiance * pk / g) for o, pk, g in zip(obs, p, given)]
        prep = prepare(scaled, opts, "likelihood")
        plain = Problem(FMBRDF, prep.evaluator, prep.objective)
        plain.obj.var = var
        s = State(*Parameters(FMBRDF).split(NEAR))
        return plain.obj.residuals(plain.parts(s), s)

    p0 = [1.0, powers["power_1"], powers["power_2"]]
    np.testing.assert_allclose(plain_residuals(p0), r, rtol=1e-5, atol=1e-5 * np.abs(r).max())
    for k in (1, 2):
        h = 1e-3 * p0[k]
        up, dn = list(p0), list(p0)
        up[k] += h
        dn[k] -= h
        fd = (plain_residuals(up) - plain_residuals(dn)) / (2 * h)
        col = Jt[:, names.index(f"power_{k}")]
        assert np.abs(col - fd).max() < 1e-4 * np.abs(fd).max(), k
        a, b = slices[k]   # only image k's rows depend on its power
        rows = np.zeros(len(r), bool)
        rows[4 * a:4 * b] = True
        assert np.all(col[~rows] == 0) and np.abs(col[rows]).max() > 0


def test_free_power_input_errors(variant):
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.api.fitting import fit
    from fmbrdf_mi.fit.api.fitting import fit_joint

    obs, _, _ = _captures(res=12)
    with pytest.raises(InputError, match="free_power: needs two or more"):
        fit_joint(obs[:1], free_power=True, progress=False)
    with pytest.raises(InputError, match="free_power: the relative light powers are estimated in joint fits"):
        fit(obs[0], free_power=True, progress=False)
    with pytest.raises(InputError, match="not with loss dolp"):
        fit_joint(obs, free_power=True, loss="dolp", progress=False)
    with pytest.raises(InputError, match="power_start: expected"):
        fit_joint(obs, free_power=True, power_start="brightest", progress=False)
    with pytest.raises(InputError, match="powers: expected 3 positive"):
        fit_joint(obs, free_power=True, powers=[1.0, -1.0, 1.0], progress=False)


def test_cli_free_power_through_a_manifest_and_rerun(tmp_path, capsys, variant, no_figures):
    """Three raw mosaics (with capture sidecars: known noise) listed in a manifest with powers 1, 1, 1;
    --free-power reports the powers with standard errors in fit.json and the summary, within 4 SE of
    the truth; --from reproduces them; a single image with --free-power is refused in one line."""
    from PIL import Image

    from fmbrdf_mi.cli import main
    from fmbrdf_mi.sensor.camera import write_sidecar

    obs, caps, cam = _captures(res=12, seed=20)
    lines = ["[defaults]", 'sphere = "auto"', 'mask = "mask.npy"']
    np.save(tmp_path / "mask.npy", obs[0].mask)
    for k, (cap, l) in enumerate(zip(caps, LIGHTS)):
        Image.fromarray(cap["raw"]).save(tmp_path / f"cap{k}.png")
        write_sidecar(tmp_path / f"cap{k}.png", cam)
        lines += ["[[image]]", f'input = "cap{k}.png"', f"light = {list(l)}"]
    (tmp_path / "m.toml").write_text("\n".join(lines) + "\n")
    ks = obs[0].irradiance
    init = f"eta=1.5,alpha=0.22,beta=1.2,kappa=14,k_s={0.8 * ks!r},r_k=0.6"
    argv = ["fit", "--manifest", str(tmp_path / "m.toml"), "--free-power", "--init", init, "--erode", "1",
            "-o", str(tmp_path / "a")]
    assert main(argv) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "power 1 (reference, fixed)" in out and out.count("(given 1)") == 2
    rep = json.loads((tmp_path / "a" / "fit.json").read_text())
    m = rep["models"]["fmbrdf"]
    p = m["powers"]
    assert p["names"] == ["cap0", "cap1", "cap2"] and p["given"] == [1.0, 1.0, 1.0]
    for k in (1, 2):
        assert abs(p["values"][k] - POWERS[k]) < 4 * p["std_errors"][k], (k, p)
        assert m["images"][k]["power"] == p["values"][k] and rep["reproduce"]["images"][k]["power"] == 1.0
    assert rep["reproduce"]["arguments"]["free_power"] is True
    assert (tmp_path / "a" / "images_cap2.png").is_file()
    assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "b"), "-q"]) == 0
    again = json.loads((tmp_path / "b" / "fit.json").read_text())["models"]["fmbrdf"]
    assert again["powers"] == p and again["params"] == m["params"]
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "cap0.png"), "--sphere", "auto", "--mask", str(tmp_path / "mask.npy"),
                 "--light", "0,0,1", "--free-power", "-o", str(tmp_path / "c")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--free-power: needs a joint fit" in err[0]
    assert not (tmp_path / "c").exists()

