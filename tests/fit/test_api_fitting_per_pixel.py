"""Per-pixel albedos (``albedo="per-pixel"``, issue: textured objects): a noise-free textured sphere is
recovered, maps and shape; the command writes the maps and reruns from fit.json; bad combinations are
refused in one line."""
import dataclasses
import json

import numpy as np
import pytest

from conftest import figures_not_drawn, one_line_error

SHAPE = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)


def _texture(res):
    y, x = np.mgrid[0:res, 0:res] / res
    return 0.6 + 0.4 * np.sin(6 * x) * np.cos(4 * y), 0.4 + 0.1 * np.cos(5 * x + 3 * y)


def _exact_observation(res=16, light=(-0.5, 0.5, 1.0)):
    """A textured sphere captured without noise and without rounding: the raw samples are the model's
    exact values (2 x 2 points per raw pixel, as the fit models them), the camera's noise stated."""
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere
    from fmbrdf_mi.sensor import samples as SM
    from fmbrdf_mi.sensor.camera import CameraModel, intensity_at_each_pixel

    ks, kb = _texture(res)
    ideal = textured_sphere(SHAPE, ks, kb, res=res, light=light, area=2)
    cam = CameraModel(bits=16, full_well=1e6)
    obs, cap = capture_observation(ideal, cam, noiseless=True)
    exact = intensity_at_each_pixel(ideal["stokes"], cam.layout) * cap["exposure"] / cam.conversion_gain
    return dataclasses.replace(obs, samples=SM.from_raw(exact, cam.layout, 0.0, cam.white_level)), ks, kb


def test_noise_free_textured_sphere_is_recovered():
    """eta, alpha, beta within 0.01 %, kappa within 0.1 % (its standard error at this size and noise is
    14 %: the fit stops within ~0.01 of it); every pixel's k_b within 1e-3 of the truth (relative) and
    its k_s within 1e-3 of the pixel's brightness (|dk_s| mean S <= 1e-3 (k_s mean S + k_b mean B): where
    the surface lobe is dark k_s is weakly determined, which its standard error says); the maps' errors
    are far inside their standard errors (the noise the camera would have)."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.evaluate.predict import predict_image

    obs, ks, kb = _exact_observation()
    res = fit(obs, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False, area_points=2,
              starts=1)
    assert res.converged
    for k in ("eta", "alpha", "beta"):
        assert abs(res.params[k] / SHAPE[k] - 1) < 1e-4, (k, res.params)
    assert abs(res.params["kappa"] / SHAPE["kappa"] - 1) < 1e-3, res.params
    m = res.maps
    f = np.isfinite(m["k_s"])
    assert f.sum() == res.albedo["pixels"] == len(res.pixels) > 80
    assert np.all(np.abs(m["k_b"][f] / kb[f] - 1) < 1e-3)
    # each pixel's surface and body brightness at unit albedo, from the model itself (the truth's geometry)
    unit_s = predict_image("fmbrdf", SHAPE, obs, maps={"k_s": np.ones_like(ks), "k_b": np.zeros_like(kb)})[0]
    unit_b = predict_image("fmbrdf", SHAPE, obs, maps={"k_s": np.zeros_like(ks), "k_b": np.ones_like(kb)})[0]
    bright = ks * unit_s + kb * unit_b
    assert np.all(np.abs(m["k_s"][f] - ks[f]) * unit_s[f] <= 1e-3 * bright[f])
    assert np.all(np.abs(m["k_s"][f] - ks[f]) < 0.05 * m["k_s_se"][f])
    assert np.all(np.abs(m["k_b"][f] - kb[f]) < 0.05 * m["k_b_se"][f])
    # the split is identified where both albedos' standard errors are at most half their values
    both = (m["k_s_se"][f] <= 0.5 * m["k_s"][f]) & (m["k_b_se"][f] <= 0.5 * m["k_b"][f])
    assert np.array_equal(m["identified"][f], both) and res.albedo["identified_fraction"] == both.mean()
    # one image of each pixel: the shared parameters' bias is measured and said (fit.json, progress, summary)
    assert res.albedo["images_per_pixel"] == 1.0 and "fewer than 3 images" in res.albedo["warning"]


def test_every_shape_parameter_fixed_leaves_only_the_maps():
    """With eta, alpha, beta, kappa all fixed (at the truth) only the albedo maps are estimated, in closed
    form: the fit ran into an empty step-size check (``zero-size array``); now it returns the maps, every
    pixel's k_b within 1e-3 of the truth (noise-free, exact samples as above)."""
    from fmbrdf_mi.fit import fit

    obs, ks, kb = _exact_observation(res=12)
    res = fit(obs, albedo="per-pixel", fixed=dict(SHAPE), max_pixels=None, progress=False, area_points=2)
    assert res.params == SHAPE
    f = np.isfinite(res.maps["k_b"])
    assert f.sum() == len(res.pixels) > 25 and np.all(np.abs(res.maps["k_b"][f] / kb[f] - 1) < 1e-3)


def test_pixel_albedo_fit_is_refused_where_it_cannot_run():
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError

    obs, _, _ = _exact_observation(res=8)
    with pytest.raises(InputError, match="per-pixel: needs the likelihood"):
        fit(obs, albedo="per-pixel", loss="paper", progress=False)
    with pytest.raises(InputError, match="albedo: expected one of shared, per-pixel"):
        fit(obs, albedo="pixel", progress=False)


def test_command_writes_the_maps_and_reruns(tmp_path, capsys):
    """`fmbrdf-mi fit RAW --albedo per-pixel`: k_s.exr, k_b.exr and their standard errors (NaN outside the
    fitted pixels), albedo_maps.png and fit.json's albedo block; `--from` gives the same maps; the option
    with the paper's loss is one line and a non-zero exit, with no outputs."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.synthetic.spheres import textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    res = 16
    ks, kb = _texture(res)
    ideal = textured_sphere(SHAPE, ks, kb, res=res, light=(-0.5, 0.5, 1.0))
    cam = CameraModel()
    np.save(tmp_path / "raw.npy", capture(ideal["stokes"], cam, peak_fraction=0.8, seed=2)["raw"])
    args = ["fit", str(tmp_path / "raw.npy"), "--sphere", "8,8,7", "--light=-0.5,0.5,1", "--conversion-gain",
            str(cam.conversion_gain), "--read-noise", "2.5", "--albedo", "per-pixel", "--max-pixels", "0",
            "--starts", "1", "--intervals", "fisher", "-q"]
    with figures_not_drawn(keep=("albedo_maps.png",)):
        assert main(args + ["-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "albedo maps:" in out and "k_s.exr" in out
    import OpenEXR

    def read(name, d="a"):
        with OpenEXR.File(str(tmp_path / d / name), separate_channels=True) as f:
            return np.asarray(f.channels()["Y"].pixels, dtype=np.float64)

    k_s, k_b, se = read("k_s.exr"), read("k_b.exr"), read("k_b_se.exr")
    rep = json.loads((tmp_path / "a" / "fit.json").read_text())
    a = rep["models"]["fmbrdf"]["albedo"]
    assert k_s.shape == (res, res) and np.isfinite(k_s).sum() == a["pixels"] == np.isfinite(se).sum()
    assert np.all(np.isnan(k_b[~ideal["mask"]]))
    assert (tmp_path / "a" / "albedo_maps.png").stat().st_size > 10000
    assert rep["reproduce"]["arguments"]["albedo"] == "per-pixel"
    with figures_not_drawn():
        assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "b"), "-q"]) == 0
    np.testing.assert_array_equal(read("k_b.exr", "b"), k_b)
    capsys.readouterr()
    rc = main(["fit", str(tmp_path / "raw.npy"), "--sphere", "8,8,7", "--light=0,0,1", "--albedo", "per-pixel",
               "--loss", "paper", "-o", str(tmp_path / "c")])
    one_line_error(rc, capsys.readouterr().err, "fit", "--albedo per-pixel", "likelihood")
    assert not (tmp_path / "c").exists()


def test_joint_manifest_with_maps_relights_the_held_out_image(tmp_path, capsys, no_figures):
    """Three lights of a textured sphere (one view) and a fourth held out, through a manifest with
    `--albedo per-pixel`: the maps are written, the shape recovered within 4 standard errors, and the
    held-out image relit with the maps to RMSE / mean < 0.04 (noise alone: about 0.01; a uniform fit of
    these textures relights at about 0.12: tools/bench_textured.py, docs/benchmarks/textured.md)."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.synthetic.spheres import textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    res = 16
    ks, kb = _texture(res)
    cam = CameraModel()
    lights = [(-0.5, 0.5, 1.0), (0.29, 0.5, 0.82), (0.29, -0.5, 0.82), (-0.57, 0.0, 0.82)]
    exposure = None
    lines = ["[defaults]", 'sphere = "8,8,7"', f"conversion_gain = {cam.conversion_gain}", "read_noise = 2.5"]
    for k, light in enumerate(lights):
        ideal = textured_sphere(SHAPE, ks, kb, res=res, light=light)
        cap = capture(ideal["stokes"], cam, exposure=exposure, peak_fraction=0.8, seed=10 + k)
        exposure = cap["exposure"]
        np.save(tmp_path / f"l{k}.npy", cap["raw"])
        lines += ["[[image]]", f'input = "l{k}.npy"', f"light = {list(light)}"] + (["holdout = true"] if k == 3 else [])
    (tmp_path / "m.toml").write_text("\n".join(lines) + "\n")
    out = tmp_path / "fit"
    assert main(["fit", "--manifest", str(tmp_path / "m.toml"), "--albedo", "per-pixel", "--max-pixels", "0",
                 "--starts", "1", "--intervals", "fisher", "-o", str(out), "-q"]) == 0
    text = capsys.readouterr().out
    assert "albedo maps:" in text and "relighting l3" in text
    assert "fewer than 3 images" not in text     # three images of each pixel: no bias warning
    rep = json.loads((out / "fit.json").read_text())
    m = rep["models"]["fmbrdf"]
    assert m["albedo"]["images_per_pixel"] == 3.0 and "warning" not in m["albedo"]
    assert m["converged"] and set(m["params"]) == set(SHAPE)
    for k, v in SHAPE.items():
        assert abs(m["params"][k] - v) < 4 * m["std_errors"][k], (k, m["params"], m["std_errors"])
    assert rep["relight"]["l3"]["fmbrdf"]["rel_rmse"] < 0.04, rep["relight"]
    for f in ("k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png", "relight_l3.png"):
        assert (out / f).is_file(), f
