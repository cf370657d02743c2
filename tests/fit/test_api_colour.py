"""Colour polarisation sensors (IMX250MYR type): mosaic layout, simulated capture, demosaicking, colour fit."""
import json
import statistics

import numpy as np
import pytest

from conftest import figures_not_drawn

from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor.camera import CameraModel, capture, read_sidecar, write_sidecar


def _random_stokes(rng, h, w):
    """(3 channels, 3, h, w) physically valid Stokes (DoLP < 1), different per channel."""
    s0 = rng.uniform(0.2, 1.0, (3, h, w))
    dolp = rng.uniform(0.0, 0.9, (3, h, w))
    phi = rng.uniform(0, np.pi, (3, h, w))
    return np.stack([s0, s0 * dolp * np.cos(2 * phi), s0 * dolp * np.sin(2 * phi)], axis=1)


def test_colour_layout_by_hand():
    # independent reference: the raw pixel (row, col) of a 4x4 period, written out from the sensor's datasheet
    # picture: rows 0-1 / cols 0-1 the R block, cols 2-3 G; rows 2-3 cols 0-1 G, cols 2-3 B; in every block
    # 90 45 / 135 0.
    imgs = np.zeros((3, 4, 1, 1))
    for ch in range(3):
        for a in range(4):
            imgs[ch, a] = 10 * ch + a   # value = 10 * channel + index of the angle in (0, 45, 90, 135)
    raw = mosaic.colour_mosaic_from_angle_images(imgs)
    angle_idx = {90: 2, 45: 1, 135: 3, 0: 0}
    expected = np.array([[10 * ch + angle_idx[a] for ch, a in row] for row in [
        [(0, 90), (0, 45), (1, 90), (1, 45)],
        [(0, 135), (0, 0), (1, 135), (1, 0)],
        [(1, 90), (1, 45), (2, 90), (2, 45)],
        [(1, 135), (1, 0), (2, 135), (2, 0)]]], float)
    np.testing.assert_array_equal(raw, expected)


def test_colour_round_trip():
    # render -> mosaic -> demosaic equals the per-channel Stokes (exact up to float rounding: 3 free
    # parameters are recovered from 4 noise-free samples)
    rng = np.random.default_rng(1)
    s = _random_stokes(rng, 5, 7)
    imgs = np.stack([mosaic.angle_images_from_stokes(s[c]) for c in range(3)])
    raw = mosaic.colour_mosaic_from_angle_images(imgs)
    assert raw.shape == (20, 28)
    back = mosaic.stokes_from_colour_mosaic(raw)
    np.testing.assert_allclose(back[:, :3], s, atol=1e-12)
    np.testing.assert_array_equal(back[:, 3], 0)
    # the simulated camera (noise-free, 16-bit, no clipping) samples the same mosaic
    cam = CameraModel(full_well=1e9, bits=16, read_noise=0.0, cfa=mosaic.BAYER_RGGB)
    up = np.repeat(np.repeat(s, 4, axis=2), 4, axis=3)   # constant over each 4x4 period
    cap = capture(up, cam, exposure=1.0, noiseless=True)
    g = cam.conversion_gain
    # noise-free capture = round(I * exposure / g): the Stokes back within half a DN per sample
    got = mosaic.stokes_from_colour_mosaic(cap["raw"].astype(float) * g)
    np.testing.assert_allclose(got[:, :3], s, atol=2 * g)   # |dS| <= sum of 4 samples' rounding, each <= g / 2


def test_other_cfa_and_bad_cfa():
    rng = np.random.default_rng(2)
    s = _random_stokes(rng, 2, 3)
    imgs = np.stack([mosaic.angle_images_from_stokes(s[c]) for c in range(3)])
    cfa = mosaic.parse_cfa("BGGR")
    raw = mosaic.colour_mosaic_from_angle_images(imgs, cfa=cfa)
    np.testing.assert_allclose(mosaic.stokes_from_colour_mosaic(raw, cfa=cfa)[:, :3], s, atol=1e-12)
    # read with the wrong arrangement: R and B swap
    np.testing.assert_allclose(mosaic.stokes_from_colour_mosaic(raw)[::-1, :3], s, atol=1e-12)
    for bad in ("RGGG", "RGB", "RGGBX"):
        with pytest.raises(ValueError, match="cfa"):
            mosaic.parse_cfa(bad)
    with pytest.raises(ValueError, match="cfa"):
        CameraModel(cfa=(("R", "R"), ("G", "B")))
    with pytest.raises(ValueError, match="multiples of 4"):
        mosaic.stokes_from_colour_mosaic(np.zeros((6, 8)))


def test_colour_capture_mean_and_variance():
    # per-pixel mean and variance over many captures of a constant scene against the camera model's law:
    # mean = exposure * I / g (DN), var = mu / g + (read / g)^2 + 1/12 (camera.py's docstring)
    cam = CameraModel(full_well=4000.0, read_noise=3.0, bits=12, black_level=64, cfa=mosaic.BAYER_RGGB)
    s = np.zeros((3, 3, 4, 4))
    for ch, (i0, d, phi) in enumerate([(0.3, 0.5, 0.3), (0.8, 0.2, 1.1), (0.5, 0.7, 2.0)]):
        s[ch] = np.array([i0, i0 * d * np.cos(2 * phi), i0 * d * np.sin(2 * phi)])[:, None, None]
    exposure = 3000.0
    n = 4000
    raws = np.stack([capture(s, cam, exposure=exposure, seed=k)["raw"] for k in range(n)]).astype(float)
    # the ideal intensity of each raw pixel, by hand: its colour from the period position, its angle from
    # the block position
    colour = {(0, 0): 0, (0, 1): 1, (1, 0): 1, (1, 1): 2}
    angle = {(0, 0): 90, (0, 1): 45, (1, 0): 135, (1, 1): 0}
    for r in range(4):
        for c in range(4):
            ch = colour[(r // 2, c // 2)]
            t = np.radians(angle[(r % 2, c % 2)])
            i = 0.5 * (s[ch, 0, 0, 0] + np.cos(2 * t) * s[ch, 1, 0, 0] + np.sin(2 * t) * s[ch, 2, 0, 0])
            mu = exposure * i / cam.conversion_gain
            var = cam.variance(mu)
            x = raws[:, r, c] - cam.black_level
            # mean: 5 standard errors of the mean; variance: 5 SEs of a sample variance (sqrt(2 / n) var,
            # Gaussian approximation, which the Poisson law at > 400 electrons meets)
            assert abs(x.mean() - mu) < 5 * np.sqrt(var / n), (r, c)
            assert abs(x.var(ddof=1) - var) < 5 * np.sqrt(2.0 / n) * var, (r, c)


def test_colour_sidecar_round_trip(tmp_path):
    cam = CameraModel(cfa=mosaic.BAYER_RGGB)
    p = tmp_path / "c_raw.png"
    write_sidecar(p, cam)
    d = read_sidecar(p)
    assert d["sensor"].cfa == mosaic.BAYER_RGGB and d["sensor"].period == 4
    # a monochrome sidecar has no cfa key and reads back monochrome (files written before colour sensors)
    write_sidecar(tmp_path / "m_raw.png", CameraModel())
    assert "cfa" not in json.load(open(tmp_path / "m_raw.json"))["sensor"]
    assert read_sidecar(tmp_path / "m_raw.png")["sensor"].cfa is None
    # a malformed colour arrangement: one clear error naming the file
    bad = json.load(open(tmp_path / "c_raw.json"))
    bad["sensor"]["cfa"] = [["R", "G"], ["B", "X"]]
    json.dump(bad, open(tmp_path / "c_raw.json", "w"))
    with pytest.raises(ValueError, match=r"c_raw\.json.*cfa"):
        read_sidecar(p)


def _cli(*argv):
    from fmbrdf_mi.cli import main
    return main(list(argv))


def test_render_raw_colour(tmp_path, capsys):
    from PIL import Image

    from fmbrdf_mi.stokes_io import read_stokes_exr

    out = str(tmp_path / "s.exr")
    assert _cli("render", out, "--raw", "--sensor", "colour", "--res", "32", "--spp", "16",
                "--read-noise", "0") == 0
    raw = np.array(Image.open(out[:-4] + "_raw.png"))
    side = read_sidecar(out[:-4] + "_raw.png")
    assert side["sensor"].cfa == mosaic.BAYER_RGGB
    stokes = np.asarray(read_stokes_exr(out)[0])           # (4, H, W, 3)
    # each raw pixel's expected DN, by hand: colour from its place in the 4x4 period, polariser angle from its
    # place in the 2x2 block, intensity from the EXR's channel at that pixel
    rr, cc = np.mgrid[0:32, 0:32]
    colour = np.array([[0, 1], [1, 2]])[(rr % 4) // 2, (cc % 4) // 2]
    t = np.radians(np.array([[90, 45], [135, 0]])[rr % 2, cc % 2])
    s = np.take_along_axis(stokes[:3], colour[None, :, :, None], axis=3)[..., 0].astype(float)
    expected = 0.5 * (s[0] + np.cos(2 * t) * s[1] + np.sin(2 * t) * s[2]) * side["capture"]["dn_per_input_unit"]
    g = side["sensor"].conversion_gain
    for ch in range(3):
        m = colour == ch
        # per channel: sum of raw against sum of expected; the shot noise of the sum is sqrt(sum / g) DN
        # (>= ~1e5 electrons in each channel here): 5 of those plus rounding (0.5 DN per pixel at most)
        tol = 5 * np.sqrt(expected[m].sum() / g) + 0.5 * m.sum()
        assert abs(raw[m].astype(float).sum() - expected[m].sum()) < tol, ch
    # the colours differ (the built-in sphere is not grey), so a swapped channel would be caught
    # (channel means differ by ~4.5 % here, > 10 shot-noise SEs of a channel sum)
    assert np.ptp([expected[colour == ch].mean() for ch in range(3)]) > 0.02 * expected.mean()


@pytest.mark.parametrize("args,msg", [(("--res", "30"), "multiples of 4"), (("--cfa", "RGGX"), "--cfa"),
                                      (("--variant", "llvm_ad_mono_polarized"), "colour variant")])
def test_render_raw_colour_bad_input(tmp_path, capsys, args, msg):
    out = str(tmp_path / "s.exr")
    assert _cli("render", out, "--raw", "--sensor", "colour", "--spp", "4", *args) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg in err[0]
    assert not list(tmp_path.iterdir())   # nothing written


@pytest.mark.parametrize("R", [12, 24])
def test_colour_fit_recovers_per_channel_albedos(R):
    """Noise-free colour capture (16-bit ADC: quantisation only) of a 12- and a 24-period sphere, k_s and r_k
    different per channel: all ten parameters recovered.  (Before the albedos were projected out of the LM steps,
    the 24-period fit ended at eta -22 %, alpha +157 %, k_s[G] -> 0 and called that converged.)  Tolerance: the fit stops when a Gauss-Newton step would lower chi^2
    by < 0.01, i.e. within ~0.1 standard error of the optimum; the noise-free optimum is the truth up to the
    16-bit rounding (<< 1 SE).  So |error| < 0.3 SE (the SEs are those of a real capture with this camera's
    shot and read noise), and the SEs themselves must be small enough for that to mean something (< 25 %
    for the albedos, < 50 % for the shape parameters)."""
    from fmbrdf_mi.fit.api.colour import fit_colour
    from fmbrdf_mi.synthetic.spheres import ideal_sphere
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.sensor.noise import NoiseModel
    from fmbrdf_mi.sensor.samples import colour_samples

    shape = dict(eta=1.5, alpha=0.25, beta=0.4, kappa=1.0)
    alb = {"R": (0.6, 0.8), "G": (0.4, 1.5), "B": (0.5, 0.4)}
    light = (0.45, 0.35, 1.0)
    st = np.stack([ideal_sphere({**shape, "k_s": ks, "r_k": rk}, res=2 * R, light=light)["stokes"]
                   for ks, rk in alb.values()])
    cam = CameraModel(cfa=mosaic.BAYER_RGGB, bits=16, full_well=60000, read_noise=2.5)
    cap = capture(st, cam, peak_fraction=0.8, noiseless=True)
    smp = colour_samples(cap["raw"], cam.layout, cam.cfa, cam.black_level, cam.white_level)
    n, m, v = G.sphere_normals((R, R), (R / 2, R / 2), R / 2 - 0.5)
    geom = G.SphereGeometry((R, R), (R / 2, R / 2), R / 2 - 0.5)
    obs = ob.Observation(np.ones((3, R, R)), ob.erode(m, 1), n, v, np.asarray(light, float),
                         cap["exposure"] / cam.conversion_gain, geometry=geom)
    # ideal_sphere averages each raw pixel over 4 x 4 points: the same points in the fit make the model exact
    # (the default 2 x 2 leaves chi2/dof 0.02 on this small sphere, its estimates still within 0.3 SE)
    # (its checks are of the estimates and standard errors: the profile-likelihood intervals, which cost refits
    # on a sphere this small, are tested in tests/fit/test_uncertainty_profile.py)
    res = fit_colour(obs, smp, NoiseModel(cam.conversion_gain, cam.read_noise, 1.0), area_points=4,
                     intervals="fisher", starts=1)
    p, se = res["params"], res["std_errors"]
    for k, truth in shape.items():
        assert abs(p[k] - truth) < 0.3 * se[k], (k, p[k], se[k])
        assert se[k] < 0.5 * truth   # alpha is the loosest on 58 periods (SE ~ 0.085)
    for c, (ks, rk) in alb.items():
        assert abs(p["k_s"][c] - ks) < 0.3 * se["k_s"][c], (c, p["k_s"], se["k_s"])
        assert abs(p["r_k"][c] - rk) < 0.3 * se["r_k"][c], (c, p["r_k"], se["r_k"])
        assert se["k_s"][c] < 0.25 * ks and se["r_k"][c] < 0.25 * rk
    assert res["chi2_per_dof"] < 0.01   # quantisation only: far below 1


def test_fit_cli_colour_recovers_per_channel_albedos(tmp_path, capsys):
    """`fmbrdf-mi fit` on a rendered colour mosaic (built-in sphere, 64 px = 16 periods, k_s different per channel,
    r_k grey so that the spectral render's channels are exactly k_s[c] times one grey image), eta, beta, kappa
    fixed.  Truth: the render's parameters (independent of the fit's per-pixel model: Mitsuba's spectral path
    tracer).  Tolerances: each estimate within 4 of its standard errors inflated by sqrt(chi2/dof) (the render's
    Monte Carlo noise at 256 spp adds scatter the camera model does not know: chi2/dof ~2-3); and the channel
    ratios k_s[R]/k_s[G], k_s[B]/k_s[G] within 3 %: the alpha-albedo correlation moves the channels together
    (seen: +8..10 % in all three at another raw seed on 48 px) and cancels in the ratios, whose errors are
    ~1 % here; a swapped channel (ratios 1.5 and 1.25) fails both."""
    src = str(tmp_path / "s.exr")
    assert _cli("render", src, "--raw", "--sensor", "colour", "--res", "64", "--spp", "256", "-q",
                "-D", "k_s=0.6,0.4,0.5", "-D", "r_k=0.7", "--no-previews") == 0
    raw = src[:-4] + "_raw.png"
    out = tmp_path / "fit"
    capsys.readouterr()
    assert _cli("fit", raw, "-o", str(out), "--fix", "eta=1.5", "--fix", "beta=2", "--fix", "kappa=10",
                "--erode", "1", "--starts", "1") == 0
    text = capsys.readouterr().out
    assert "[search] stage 1" in text and "k_s[G]" in text   # progress and summary
    rep = json.load(open(out / "fit.json"))
    m = rep["models"]["fmbrdf"]
    assert m["converged"] and rep["sensor"] == "colour"
    assert set(rep["reproduce"]["files_sha256"]) >= {str(tmp_path / "s_raw.png"), str(tmp_path / "s_raw.json")}
    p, se, ci = m["params"], m["std_errors"], m["ci95"]
    infl = np.sqrt(max(m["chi2_per_dof"], 1.0))
    assert m["chi2_per_dof"] < 5
    assert p["eta"] == 1.5 and p["kappa"] == 10 and p["beta"] == 2
    assert abs(p["alpha"] - 0.3) < 4 * infl * se["alpha"]
    for c, ks in zip("RGB", (0.6, 0.4, 0.5)):
        assert abs(p["k_s"][c] - ks) < 4 * infl * se["k_s"][c], (c, p["k_s"], se["k_s"])
        assert abs(p["r_k"][c] - 0.7) < 4 * infl * se["r_k"][c], (c, p["r_k"], se["r_k"])
        assert se["k_s"][c] < 0.05 * ks and se["r_k"][c] < 0.05 * 0.7
        lo, hi = ci["k_s"][c]
        z95 = statistics.NormalDist().inv_cdf(0.975)
        assert abs((lo + hi) / 2 - p["k_s"][c]) < 1e-9 and abs((hi - lo) / 2 - z95 * se["k_s"][c]) < 1e-9
    # the one uncertainty path: Fisher information, correlations in the flat per-channel names
    assert m["uncertainty"]["method"].startswith("inverse Fisher information")
    names = m["uncertainty"]["correlation"]["names"]
    assert names == ["alpha", "k_s[R]", "k_s[G]", "k_s[B]", "r_k[R]", "r_k[G]", "r_k[B]"], names
    assert abs(p["k_s"]["R"] / p["k_s"]["G"] / 1.5 - 1) < 0.03
    assert abs(p["k_s"]["B"] / p["k_s"]["G"] / 1.25 - 1) < 0.03
    assert (out / "colour_fit.png").stat().st_size > 10000
    # --from reruns it: the same estimates; a changed input is refused in one line
    again = tmp_path / "again"
    with figures_not_drawn():
        assert _cli("fit", "--from", str(out / "fit.json"), "-o", str(again), "-q") == 0
    m2 = json.load(open(again / "fit.json"))["models"]["fmbrdf"]
    assert m2["params"] == m["params"] and m2["std_errors"] == m["std_errors"]
    # outputs are not overwritten without --force: one line, files untouched
    before = (out / "fit.json").read_bytes()
    assert _cli("fit", raw, "-o", str(out), "--fix", "eta=1.5,beta=2,kappa=10", "-q") != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0]
    assert (out / "fit.json").read_bytes() == before
    # --max-time far below the fit's time: exit 3, converged false, no standard errors
    assert _cli("fit", raw, "-o", str(out), "--fix", "eta=1.5,beta=2,kappa=10", "--max-time", "0.05", "-q",
                "--force") == 3
    m = json.load(open(out / "fit.json"))["models"]["fmbrdf"]
    assert not m["converged"] and "max_time 0.05 s reached" in m["stop_reason"] and m["std_errors"] is None


@pytest.mark.parametrize("extra,msg", [(("--sphere", "1,2"), "--sphere"), (("--mask", "nope.png", "--sphere", "auto"),
                                                                         "nope.png"),
                                       (("--fix", "gamma=1"), "gamma"), (("--baselines",), "--baselines")])
def test_fit_cli_colour_bad_input_one_line(tmp_path, capsys, extra, msg):
    out = str(tmp_path / "s.exr")
    assert _cli("render", out, "--raw", "--sensor", "colour", "--res", "16", "--spp", "4", "-q") == 0
    capsys.readouterr()
    assert _cli("fit", out[:-4] + "_raw.png", "--out", str(tmp_path / "fit"), *extra) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg in err[0], err
    assert not (tmp_path / "fit").exists()
