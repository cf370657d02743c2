"""Joint fits of several colour polarisation mosaics (fit/outputs/colour.py, fit_colour with lists)."""
import json

import numpy as np

from conftest import figures_not_drawn

from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor.camera import CameraModel, capture


def _cli(*argv):
    from fmbrdf_mi.cli import main

    try:
        return main(list(argv))
    except SystemExit as exc:
        return exc.code


def _sphere_capture(R, light, seed, noiseless=False):
    from fmbrdf_mi.synthetic.spheres import ideal_sphere
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.sensor.samples import colour_samples

    shape = dict(eta=1.5, alpha=0.25, beta=0.4, kappa=1.0)
    alb = {"R": (0.6, 0.8), "G": (0.4, 1.5), "B": (0.5, 0.4)}
    st = np.stack([ideal_sphere({**shape, "k_s": ks, "r_k": rk}, res=2 * R, light=light)["stokes"]
                   for ks, rk in alb.values()])
    cam = CameraModel(cfa=mosaic.BAYER_RGGB, bits=12, full_well=10000, read_noise=2.5)
    cap = capture(st, cam, peak_fraction=0.8, seed=seed, noiseless=noiseless)
    smp = colour_samples(cap["raw"], cam.layout, cam.cfa, cam.black_level, cam.white_level)
    n, m, v = G.sphere_normals((R, R), (R / 2, R / 2), R / 2 - 0.5)
    geom = G.SphereGeometry((R, R), (R / 2, R / 2), R / 2 - 0.5)
    obs = ob.Observation(np.ones((3, R, R)), ob.erode(m, 1), n, v, np.asarray(light, float),
                         cap["exposure"] / cam.conversion_gain, geometry=geom)
    return obs, smp, cam


def test_joint_colour_fit_of_one_image_twice_halves_the_variance():
    """The same capture given twice: the joint likelihood is twice the single one, so the estimates are the
    single fit's and every standard error is the single one's / sqrt(2) (the Fisher information doubles).
    Independent of the fit's internals: it fails if the images' samples are not all counted, or counted
    with the wrong geometry.  Tolerances: both fits stop within ~0.1 SE of the same optimum (LM decrement
    < 0.01), so estimates agree to 0.15 SE; SE ratios to 2 % (the two stop at slightly different points)."""
    from fmbrdf_mi.fit.api.colour import fit_colour
    from fmbrdf_mi.sensor.noise import NoiseModel

    obs, smp, cam = _sphere_capture(12, (0.45, 0.35, 1.0), seed=3)
    noise = NoiseModel(cam.conversion_gain, cam.read_noise, 1.0)
    one = fit_colour(obs, smp, noise, intervals="fisher", starts=1)    # standard errors are compared, not intervals
    two = fit_colour([obs, obs], [smp, smp], noise, intervals="fisher", starts=1)
    assert one["converged"] and two["converged"] and two["n_samples"] == 2 * one["n_samples"]
    for k, v in one["params"].items():
        s1, s2 = one["std_errors"][k], two["std_errors"][k]
        for c in (v if isinstance(v, dict) else [None]):
            a, b = (v, two["params"][k]) if c is None else (v[c], two["params"][k][c])
            e1, e2 = (s1, s2) if c is None else (s1[c], s2[c])
            assert abs(a - b) < 0.15 * e1, (k, c, a, b, e1)
            assert abs(e2 / e1 * np.sqrt(2) - 1) < 0.02, (k, c, e1, e2)
    assert len(two["chi2_per_sample"]) == 2 and np.allclose(*two["chi2_per_sample"])


def test_fit_cli_colour_joint_manifest(tmp_path, capsys):
    """`fmbrdf-mi fit --manifest` on three rendered colour mosaics of one sphere (lights left, right, top;
    one held out), eta, beta, kappa fixed as in the single-image CLI test.  Truth: the renders' parameters
    (Mitsuba's spectral path tracer, independent of the fit's per-pixel model).  Checks: estimates within 4
    standard errors inflated by sqrt(chi2/dof) (render noise); the channel ratios of k_s too (their relative
    SE from the two channels' as if independent: about 1.7 %, an overestimate, since alpha correlates the
    channels positively; a swapped or mixed channel is off by 30 % and more); the held-out
    image's raw-sample RMSE / mean within 2.5x what shot and read noise alone give (the render's Monte Carlo
    noise adds ~1.5x at 256 spp); per-image plots; --from reruns to the same estimates; mixing in a mono
    image is refused in one line."""
    lights = [(0.5, 0.3, 1.0), (-0.5, 0.2, 1.0), (0.1, 0.6, 1.0)]
    raws = []
    for k, li in enumerate(lights):
        src = str(tmp_path / f"l{k}.exr")
        assert _cli("render", src, "--raw", "--sensor", "colour", "--res", "64", "--spp", "256", "-q",
                    "--no-previews", "--seed", str(k), "-D", "k_s=0.6,0.4,0.5", "-D", "r_k=0.7",
                    "-D", "light_dir=" + ",".join(map(str, li))) == 0
        raws.append(src[:-4] + "_raw.png")
    lines = []
    for k, (r, li) in enumerate(zip(raws, lights)):
        lines += ["[[image]]", f'input = "{r}"', f"light = {list(li)}"] + (["holdout = true"] if k == 2 else [])
    (tmp_path / "m.toml").write_text("\n".join(lines) + "\n")
    out = tmp_path / "fit"
    capsys.readouterr()
    assert _cli("fit", "--manifest", str(tmp_path / "m.toml"), "-o", str(out), "--fix", "eta=1.5,beta=2,kappa=10",
                "--erode", "1", "--starts", "1") == 0
    text = capsys.readouterr().out
    assert "colour joint fit" in text and "relighting l2_raw" in text
    rep = json.load(open(out / "fit.json"))
    m = rep["models"]["fmbrdf"]
    assert rep["sensor"] == "colour" and m["converged"] and set(m["chi2_per_sample"]) == {"l0_raw", "l1_raw"}
    p, se = m["params"], m["std_errors"]
    infl = np.sqrt(max(m["chi2_per_dof"], 1.0))
    assert m["chi2_per_dof"] < 5
    assert abs(p["alpha"] - 0.3) < 4 * infl * se["alpha"]
    for c, ks in zip("RGB", (0.6, 0.4, 0.5)):
        assert abs(p["k_s"][c] - ks) < 4 * infl * se["k_s"][c], (c, p["k_s"], se["k_s"])
        assert abs(p["r_k"][c] - 0.7) < 4 * infl * se["r_k"][c], (c, p["r_k"], se["r_k"])
    for c, ratio in (("R", 1.5), ("B", 1.25)):  # the ratio's relative SE, channels taken as independent
        rel_se = np.hypot(se["k_s"][c] / p["k_s"][c], se["k_s"]["G"] / p["k_s"]["G"])
        assert abs(p["k_s"][c] / p["k_s"]["G"] / ratio - 1) < 4 * infl * rel_se, (c, p["k_s"], rel_se)
    # held-out image: its error against what the camera noise alone gives at its own samples
    from fmbrdf_mi.fit.inputs.colour import read_colour_input

    ci = read_colour_input(raws[2], light=lights[2], erode=1)
    sel = ci.obs.mask & ci.samples.usable
    o = ci.samples.values[:, sel]
    noise_only = np.sqrt(np.mean(ci.noise.variance(o))) / np.mean(o)
    err = rep["relight"]["l2_raw"]["fmbrdf"]["rel_rmse"]
    assert err < 2.5 * noise_only, (err, noise_only)
    for name in ("colour_fit_l0_raw.png", "colour_fit_l1_raw.png", "relight_l2_raw.png"):
        assert (out / name).stat().st_size > 10000
    # --from reruns the joint colour fit
    with figures_not_drawn():
        assert _cli("fit", "--from", str(out / "fit.json"), "-o", str(tmp_path / "again"), "-q") == 0
    m2 = json.load(open(tmp_path / "again" / "fit.json"))["models"]["fmbrdf"]
    assert m2["params"] == m["params"] and m2["std_errors"] == m["std_errors"]
    # a mono image among colour ones: one line
    assert _cli("render", str(tmp_path / "mono.exr"), "--raw", "--res", "64", "--spp", "4", "-q",
                "--no-previews") == 0
    capsys.readouterr()
    assert _cli("fit", raws[0], str(tmp_path / "mono_raw.png"), "--light", "0.5,0.3,1", "--light", "0,0,1",
                "-o", str(tmp_path / "mixed")) != 0
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert len(err_lines) == 1 and "colour" in err_lines[0] and "image 1" in err_lines[0]
    assert not (tmp_path / "mixed").exists()


def test_colour_joint_fit_takes_the_albedo_layouts(tmp_path):
    """The joint command passes every fit key to the colour joint fit (one request, FIT_KEYS): 'shared' and
    'per-pixel' are its layouts (per-pixel: tests/fit/test_api_colour_per_pixel.py); any other is refused in one
    line naming the option, before anything is read or written (the specs are not looked at), as are
    free_power, the joint options the colour fit does not take and names outside the schema."""
    import pytest

    from fmbrdf_mi.fit.errors import InputError
    from fmbrdf_mi.fit.outputs.colour import fit_colour_images

    with pytest.raises(InputError, match=r"albedo 'per-channel' \(--albedo; expected 'shared' or 'per-pixel'\)"):
        fit_colour_images([], str(tmp_path / "out"), albedo="per-channel")
    with pytest.raises(InputError, match=r"free_power \(--free-power\)"):
        fit_colour_images([], str(tmp_path / "out"), albedo="per-pixel", free_power=True)
    with pytest.raises(InputError, match=r"materials \(--materials\) not supported"):   # the joint record's, not the colour fit's
        fit_colour_images([], str(tmp_path / "out"), materials="labels.png")
    with pytest.raises(InputError, match=r"fit_colour_images\(\): unknown option\(s\) bogus"):
        fit_colour_images([], str(tmp_path / "out"), bogus=1)
    assert not (tmp_path / "out").exists()
