"""Small end-to-end fits: parameters come back from noise-free images.

* per-pixel path, full pipeline (coarse search from nothing + Levenberg-Marquardt);
* rendering path: the parts a Mitsuba render gives agree with the per-pixel
  path, the reverse-mode gradient of the loss through ``mi.render`` agrees
  with finite differences of renders, and Adam through it lowers the loss;
* a baseline (pplastic) recovers its own parameters;
* the command line writes its outputs.
"""
import json

import numpy as np
import pytest
from conftest import small_sphere_paths

# off every coarse-search grid value
TRUE = {"eta": 1.55, "alpha": 0.35, "beta": 1.4, "kappa": 30.0, "k_s": 0.9, "r_k": 1.7}
LIGHT = (0.45, 0.35, 1.0)


def _sphere_obs(params, res=40, model="fmbrdf", light=LIGHT):
    from fmbrdf_mi.fit import Observation, predict_image
    from fmbrdf_mi import geometry as G

    n, m, v = G.sphere_normals((res, res), (res / 2, res / 2), res / 2 - 1)
    obs = Observation(np.ones((3, res, res)), m, n, v, light)
    return Observation(predict_image(model, params, obs), m, n, v, light, meta={"truth": params})


def test_noise_free_fit_recovers_all_six_parameters(variant):
    from fmbrdf_mi.fit import fit

    res = fit(_sphere_obs(TRUE), starts=1, progress=False)
    for k, t in TRUE.items():
        tol = 0.1 if k == "kappa" else 0.02
        assert res.params[k] == pytest.approx(t, rel=tol), (k, res.params)
    assert res.loss < 1e-8
    assert res.history[0]["stage"] == "search"


def test_pplastic_baseline_recovers_its_parameters(variant):
    from fmbrdf_mi.fit import fit

    true = {"eta": 1.7, "alpha": 0.12, "specular_reflectance": 0.8, "diffuse_reflectance": 0.4}
    res = fit(_sphere_obs(true, model="pplastic"), model="pplastic", progress=False)
    for k, t in true.items():
        assert res.params[k] == pytest.approx(t, rel=0.01), (k, res.params)


@pytest.fixture(scope="module")
def render_setup():
    return small_sphere_paths(LIGHT, spp=16)


def test_render_path_agrees_with_pixel_path(render_setup):
    _, _, _, rev, pev = render_setup
    shape = {k: TRUE[k] for k in ("eta", "alpha", "beta", "kappa")}
    pr, pp = rev.parts(shape), pev.parts(shape)
    for a, b in ((pr.surface, pp.surface), (pr.body, pp.body)):
        # pixel-area averaging of the render vs pixel centres: a few % at the highlight
        assert np.abs(a[0] - b[0]).max() < 0.06 * np.abs(b[0]).max()
        assert np.corrcoef(a[1], b[1])[0, 1] > 0.99
    with pytest.raises(NotImplementedError, match="forward-mode"):
        rev.parts(shape, wrt=("kappa",))


def _render_problem(render_setup):
    from fmbrdf_mi.fit import Observation
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, State
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.evaluate.pixel_model import RenderEvaluator
    from fmbrdf_mi.fit.objectives import loss as L
    from fmbrdf_mi.fit.problem.problem import Problem

    scene, obs, idx, rev, _ = render_setup
    # observation: the same scene rendered at the true parameters with other samples
    ev = RenderEvaluator(FMBRDF, scene, "sphere.bsdf", None, spp=64, seed=11)
    shape, a_s, a_b = Parameters(FMBRDF).split(TRUE)
    p = ev.parts(shape)
    img = (a_s * p.surface + a_b * p.body).reshape(3, *obs.shape)
    obs_t = Observation(img, obs.mask, obs.normals, obs.view_dirs, LIGHT)
    target = L.Target.from_stokes(img.reshape(3, -1)[:, idx])
    pb = Problem(FMBRDF, rev, target)
    start = {**TRUE, "eta": 1.45, "alpha": 0.3, "kappa": 20.0, "r_k": 1.5}
    st = State(*Parameters(FMBRDF).split(start))
    pb.set_weights(pb.parts(st), st)
    return pb, st, start, obs_t, scene


def test_render_path_reverse_gradient_matches_finite_differences(render_setup):
    from fmbrdf_mi.fit.evaluate.models import State
    from fmbrdf_mi.fit.solve.optimise import loss_and_grad_reverse

    pb, st, start, _, _ = _render_problem(render_setup)
    f, g = loss_and_grad_reverse(pb, st)
    grad = {n: g[n] for n in ("eta", "alpha", "beta", "kappa")}
    grad["k_s"] = g["a_s"] + start["r_k"] * g["a_b"]
    grad["r_k"] = start["k_s"] * g["a_b"]
    for name in grad:
        h = 1e-2 * start[name]
        vals = []
        for d in (1, -1):
            s2 = State(*pb.params.split({**start, name: start[name] + d * h}))
            vals.append(pb.obj.value(pb.parts(s2), s2))
        fd = (vals[0] - vals[1]) / (2 * h)
        assert abs(fd) > 1e-5, name
        assert grad[name] == pytest.approx(fd, rel=0.05, abs=0.02 * abs(fd) + 1e-5), name


def test_short_adam_fit_through_the_renderer(render_setup):
    from fmbrdf_mi.fit import fit

    pb, st, start, obs_t, scene = _render_problem(render_setup)
    f0 = pb.obj.value(pb.parts(st), st)
    res = fit(obs_t, path="render", optimizer="adam", scene=scene, init=start, erode=1, spp=16,
              max_iter=5, rounds=1, progress=False)
    assert res.loss < 0.7 * f0
    with pytest.raises(ValueError, match="path render works with optimizer adam only"):
        fit(obs_t, path="render", scene=scene, init=start, progress=False)


def test_cli_writes_estimates_plots_and_relighting(tmp_path, capsys):
    from fmbrdf_mi import stokes_io
    from fmbrdf_mi.cli import main

    true = {"eta": 1.6, "alpha": 0.2, "specular_reflectance": 0.7, "diffuse_reflectance": 0.5}
    a = _sphere_obs(true, res=32, model="pplastic")
    b = _sphere_obs(true, res=32, model="pplastic", light=(-0.6, 0.1, 1.0))
    for name, o in (("a", a), ("b", b)):
        stokes_io.write_stokes_exr(tmp_path / f"{name}.exr", np.concatenate([o.stokes, 0 * o.stokes[:1]]))
    np.save(tmp_path / "n.npy", a.normals)
    np.save(tmp_path / "m.npy", a.mask)
    args = ["fit", str(tmp_path / "a.exr"), "--normals", str(tmp_path / "n.npy"), "--mask",
            str(tmp_path / "m.npy"), "--light", ",".join(map(str, LIGHT)), "--model", "pplastic",
            "--relight", str(tmp_path / "b.exr"), "--relight-light=-0.6,0.1,1", "-o", str(tmp_path / "out"), "-q"]
    assert main(args) == 0, capsys.readouterr().err
    rep = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert rep["models"]["pplastic"]["params"]["eta"] == pytest.approx(1.6, rel=0.01)
    assert rep["relight"]["b"]["pplastic"]["rel_rmse"] < 0.01
    np.testing.assert_allclose(rep["reproduce"]["images"][1]["light"], np.array([-0.6, 0.1, 1]) / np.sqrt(1.37))
    assert rep["reproduce"]["images"][1]["holdout"] and rep["reproduce"]["images"][1]["name"] == "b"
    assert "loss" in rep["models"]["pplastic"]["history"][-1]
    for f in ("profiles.png", "images.png", "history.png", "relight.png", "fitted_stokes.exr"):
        assert (tmp_path / "out" / f).stat().st_size > 1000
    assert main(args) == 1  # no overwrite without --force
    assert main(args + ["--force"]) == 0


def test_footprint_average_equals_averaged_evaluations(variant):
    from fmbrdf_mi.fit import Observation
    from fmbrdf_mi.fit.evaluate.models import FMBRDF
    from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.sensor import noise as cn

    n, m, v = G.sphere_normals((20, 20), (10, 10), 9)
    obs = Observation(np.ones((3, 20, 20)), m, n, v, LIGHT, footprint=cn.demosaic_footprint())
    idx = np.flatnonzero(ob.erode(m, 2).ravel())[::7]
    N, V, w = obs.sample_geometry(idx)
    assert N.shape == (16 * len(idx), 3) and w.sum() == pytest.approx(1)
    # sub-sample normals agree with the analytic sphere (bilinear interpolation + renormalising
    # on a 9-pixel sphere: ~0.5 %; the error falls with the square of the radius)
    rows, cols = np.divmod(idx, 20)
    x = cols[:, None] + 0.5 + cn.demosaic_footprint()[0][None, :, 0]
    u = ((x - 10) / 9).ravel()
    assert np.abs(N[:, 0] - u).max() < 6e-3
    shape = {k: TRUE[k] for k in ("eta", "alpha", "beta", "kappa")}
    avg = PixelEvaluator(FMBRDF, N, V, LIGHT, weights=w).parts(shape)
    each = PixelEvaluator(FMBRDF, N, V, LIGHT).parts(shape)
    manual = (each.surface.reshape(3, len(idx), 16) * w).sum(-1)
    np.testing.assert_allclose(avg.surface, manual, rtol=1e-5, atol=1e-7)


def test_cli_raw_mosaic_with_camera_noise(tmp_path, capsys):
    """Raw 12-bit mosaic in, geometry at raw resolution, the noisy-DoLP model and the demosaicking footprint."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    true = {"eta": 1.5, "alpha": 0.25, "specular_reflectance": 0.8, "diffuse_reflectance": 0.5}
    raw_obs = _sphere_obs(true, res=96, model="pplastic")
    noise = CameraModel()
    cap = capture(raw_obs.stokes, noise, seed=2)
    np.save(tmp_path / "raw.npy", cap["raw"])
    np.save(tmp_path / "n.npy", raw_obs.normals)
    np.save(tmp_path / "m.npy", raw_obs.mask)
    args = ["fit", str(tmp_path / "raw.npy"), "--normals", str(tmp_path / "n.npy"), "--mask", str(tmp_path / "m.npy"),
            "--light", ",".join(map(str, LIGHT)), "--model", "pplastic", "-o", str(tmp_path / "out"), "-q",
            "--conversion-gain", str(noise.full_well / 4095), "--read-noise", str(noise.read_noise)]
    assert main(args) == 0, capsys.readouterr().err
    rep = json.loads((tmp_path / "out" / "fit.json").read_text())
    p = rep["models"]["pplastic"]["params"]
    assert p["eta"] == pytest.approx(1.5, rel=0.05) and p["alpha"] == pytest.approx(0.25, rel=0.05)
    assert rep["models"]["pplastic"]["options"]["max_pixels"] == 20000


def test_oren_nayar_ts_baseline_recovers_its_own_render(variant):
    """The Oren-Nayar + Torrance-Sparrow baseline, rendered by Mitsuba (stokes over direct, the orennayar
    plugin inside a blendbsdf) and fitted by the per-pixel path from the coarse search."""
    mi = variant
    from fmbrdf_mi import scene as S
    from fmbrdf_mi.fit import Observation, fit
    from fmbrdf_mi.fit.evaluate.models import OREN_NAYAR_TS as M
    from fmbrdf_mi.fit.evaluate.parameters import Parameters

    true = {"eta": 1.6, "alpha": 0.2, "sigma": 0.6, "k_s": 0.7, "k_d": 0.9}  # sigma off the search grid
    shape, a_s, a_b = Parameters(M).split(true)
    bsdf = M.bsdf_dict(shape)
    bsdf["bsdf_1"]["specular_reflectance"], bsdf["bsdf_0"]["reflectance"] = a_s, a_b
    res = 48
    d = S.sphere_scene(None, light_dir=LIGHT, irradiance=1.0, resolution=res, spp=32)
    d["sphere"]["bsdf"] = bsdf
    img = S.render_stokes(mi.load_dict(d), spp=32, seed=1, progress=False)[:3, ..., 0].astype(np.float64)
    n, v, m = S.sphere_geometry(res)
    est = fit(Observation(img, m, n, v, LIGHT, 1.0), model="oren_nayar_ts", progress=False).params
    for k, t in true.items():
        # render (pixel-area average, 32 spp) vs the fit's pixel centres: measured within 0.6 %
        assert est[k] == pytest.approx(t, rel=0.03), (k, est)


# ---------------------------------------------------------------- issue 24: nonsense fitted with exit 0
def _plain_obs(res=24):
    from fmbrdf_mi.fit import Observation
    from fmbrdf_mi import geometry as G

    n, m, v = G.sphere_normals((res, res), (res / 2, res / 2), res / 2 - 1)
    s = np.zeros((3, res, res))
    s[0] = 0.1 + np.clip(n[..., 2], 0, None)
    return Observation(s, m, n, v, LIGHT)


@pytest.mark.parametrize("change,match", [
    (lambda o: setattr(o, "irradiance", -1.0), r"irradiance: expected a finite number in \[1e-20, 1e\+20\]"),
    (lambda o: setattr(o, "irradiance", float("nan")), "irradiance"),
    (lambda o: setattr(o, "normals", (o.normals + 1) / 2), r"unit length.*\[0, 1\]"),
    (lambda o: setattr(o, "light_dir", np.array([0.0, 0.0, -1.0])), "below the horizon"),
])
def test_fit_refuses_an_observation_changed_after_it_was_built(change, match):
    """Before: fit() fitted an Observation whose irradiance was set to -1 or whose normals were
    replaced by their [0, 1] colours after construction, and returned estimates."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError

    obs = _plain_obs()
    change(obs)
    with pytest.raises(InputError, match=match):
        fit(obs, max_iter=1, starts=1, progress=False)
    with pytest.raises(InputError, match=r"image 1: .*" + match):
        fit([_plain_obs(), obs], max_iter=1, starts=1, progress=False)


def test_fit_refuses_options_that_are_not_fit_options():
    """Before: TypeError from FitOptions' constructor (fit(obs, irradiance=-1))."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError

    with pytest.raises(InputError, match="unknown option.*irradiance.*Observation"):
        fit(_plain_obs(), irradiance=-1, progress=False)


@pytest.mark.parametrize("options,words", [
    ({"path": "render"}, "path render works with optimizer adam only"),
    ({"free_power": True, "loss": "dolp"}, "free_power: not with loss dolp"),
    ({"albedo": "per-pixel", "optimizer": "adam"}, "albedo per-pixel: needs the likelihood"),
    ({"albedo": "per-pixel", "free_power": True}, "albedo per-pixel: not with free_power"),
    ({"albedo_smooth": 0.1}, "albedo_smooth: the albedo maps' smoothness prior needs albedo per-pixel"),
    ({"materials": "m.png", "albedo": "per-pixel", "albedo_smooth": 0.1}, "materials m.png: not with albedo_smooth"),
    ({"materials": "m.png", "albedo": "per-pixel-bilinear"}, "materials m.png: not with albedo per-pixel-bilinear"),
    ({"materials": "m.png", "free_power": True}, "materials m.png: not with free_power"),
    ({"materials": "m.png", "loss": "paper"}, "materials m.png: needs the likelihood"),
])
def test_each_relation_between_options_is_refused_alone(options, words):
    """Every row of the options' relations: the combination refused in one line that names it."""
    from fmbrdf_mi.fit.api.options import check_fit_options
    from fmbrdf_mi.fit.errors import InputError

    check_fit_options()
    with pytest.raises(InputError, match=f"^{words}") as e:
        check_fit_options(**options)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("loss,values,words", [
    ("likelihood", {"optimizer": "adam"}, "loss 'likelihood' works with the pixel path and optimizer 'lm'"),
    ("likelihood", {"path": "render"}, "loss 'likelihood' works with the pixel path and optimizer 'lm'"),
    ("dolp", {"optimizer": "adam"}, "loss 'dolp' works with optimizer 'lm'"),
    ("paper", {"albedo": "per-pixel"}, "albedo per-pixel: needs the likelihood"),
    ("paper", {"intervals": "profile"}, "intervals profile: needs the likelihood"),
])
def test_the_resolved_loss_refuses_options_that_do_not_work_with_it(loss, values, words):
    from fmbrdf_mi.fit.api.options import check_resolved_loss
    from fmbrdf_mi.fit.errors import InputError

    check_resolved_loss({}, loss, "the source")
    with pytest.raises(InputError, match=f"^{words}"):
        check_resolved_loss(values, loss, "the source")
