"""The paper authors' captured-data layout (fit/authors_layout.py), the joint-fit command, and an end-to-end
recovery on a synthetic non-spherical object written in that layout (fit/synthetic_object.py).
"""
import json
import math
import os

import numpy as np
import pytest

TRUE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8), (0.0, 0.1, 1.0)]
POWERS = [1.0, 0.7, 1.2, 0.9]


def _their_stokes(raw):
    """The authors' observed Stokes of a uniform mosaic, as their scripts describe it (independent NumPy):
    s1 = I0 - I90, s2 = I45 - I135, AoLP = atan2(s2, s1) / 2, then (S0, S0 DoLP cos(-2 AoLP), S0 DoLP sin(-2 AoLP))
    with the 2x2 layout 90 45 / 135 0."""
    p090, p045 = raw[0::2, 0::2].mean(), raw[0::2, 1::2].mean()
    p135, p000 = raw[1::2, 0::2].mean(), raw[1::2, 1::2].mean()
    s0 = (p000 + p090 + p045 + p135) / 2
    s1, s2 = p000 - p090, p045 - p135
    dolp, aolp = math.hypot(s1, s2) / s0, -0.5 * math.atan2(s2, s1)
    return np.array([s0, s0 * dolp * math.cos(2 * aolp), s0 * dolp * math.sin(2 * aolp)]), aolp


@pytest.mark.parametrize("psi_deg", [30.0, -60.0, 80.0])
def test_their_negated_aolp_is_ours_measured_with_y_down(psi_deg):
    """A linear polarisation at psi (ours: counter-clockwise from image right as displayed, y up) through
    this package's camera model: the authors' convention gives -psi, i.e. S2 theirs = -S2 ours, S0 and S1
    equal.  (Noise-free capture: exact to the ADC's rounding, 1 DN of ~2000.)"""
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    psi = math.radians(psi_deg)
    ours = np.array([1.0, 0.6 * math.cos(2 * psi), 0.6 * math.sin(2 * psi)])
    st = np.broadcast_to(ours[:, None, None], (3, 8, 8)).copy()
    cam = CameraModel(bits=16, full_well=60000.0, read_noise=0.0)
    cap = capture(st, cam, exposure=2000.0 * cam.conversion_gain, noiseless=True)
    theirs, aolp = _their_stokes(cap["raw"].astype(float) / 2000.0)
    np.testing.assert_allclose(theirs, ours * np.array([1, 1, -1]), atol=2e-3)
    assert abs(math.remainder(aolp + psi, math.pi)) < 2e-3
    # and the package's own reading of that mosaic is ours, unchanged
    from fmbrdf_mi.sensor.mosaic import stokes_from_raw

    s = stokes_from_raw(cap["raw"], ((90, 45), (135, 0)), 0.0, "superpixel")[:, 2, 2] / 2000.0
    np.testing.assert_allclose(s, ours, atol=2e-3)


def test_opencv_axes_conversion():
    from fmbrdf_mi.fit.inputs.authors import cv_to_ours, rays_from_intrinsics

    # a normal facing an OpenCV camera (towards -z), tilted to image right and image top (-y in OpenCV)
    n_cv = np.array([0.3, -0.4, -math.sqrt(0.75)])
    n = cv_to_ours(n_cv)
    np.testing.assert_allclose(n, [0.3, 0.4, math.sqrt(0.75)])   # right, up, towards the camera
    np.testing.assert_allclose(np.cross(cv_to_ours([1, 0, 0]), cv_to_ours([0, 1, 0])), cv_to_ours([0, 0, 1]))
    # rays through the super-pixel centres: the principal point's super-pixel looks along the axis
    K = np.array([[100.0, 0, 9.5], [0, 100.0, 9.5], [0, 0, 1]])
    v = rays_from_intrinsics(K, (10, 10))
    assert v.shape == (10, 10, 3) and np.allclose(np.linalg.norm(v, axis=-1), 1)
    # super-pixel (4, 4) is centred at raw (8.5, 8.5), one raw pixel left of and above (9.5, 9.5):
    # the view direction (towards the camera) then points right and down in ours
    assert v[4, 4, 0] > 0 and v[4, 4, 1] < 0 and v[4, 4, 2] > 0.99
    np.testing.assert_allclose(v[4, 4, :2], [1 / 100.0, -1 / 100.0], rtol=1e-3)


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object

    root = tmp_path_factory.mktemp("authors") / "blob"
    truth = write_authors_object(root, TRUE, LIGHTS, res=40, fov=12.0, powers=POWERS, seed=11)
    return root, truth


def test_read_object_geometry_lights_and_powers(blob):
    from fmbrdf_mi.fit.inputs.authors import read_object

    root, truth = blob
    specs, info = read_object(root, holdout=[3])
    assert info["images"] == 4 and info["view_rays"] == "vpL_img.npy" and info["non_unit_normals_left_out"] == 0
    np.testing.assert_allclose(info["intensities"], np.array(POWERS) / max(POWERS))
    for s, l, p in zip(specs, LIGHTS, POWERS):
        np.testing.assert_allclose(s.input.light_dir, np.array(l) / np.linalg.norm(l), atol=1e-12)
        assert math.isclose(s.input.irradiance, p / max(POWERS))
    assert [s.holdout for s in specs] == [False, False, False, True]
    o = specs[0].input
    # the object faces the camera: normals and views (ours) have z > 0 on the mask
    assert np.all(o.normals[o.mask][:, 2] > 0) and np.all(o.view_dirs[o.mask][:, 2] > 0.98)
    # view rays from IntrinsicL.npy alone agree with vpL_img.npy
    os.rename(root / "calibration" / "vpL_img.npy", root / "vpL.bak")
    try:
        specs2, info2 = read_object(root)
    finally:
        os.rename(root / "vpL.bak", root / "calibration" / "vpL_img.npy")
    assert info2["view_rays"] == "IntrinsicL.npy"
    np.testing.assert_allclose(specs2[0].input.view_dirs[o.mask], o.view_dirs[o.mask], atol=1e-6)


def test_read_object_errors(blob, tmp_path):
    import shutil

    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.inputs.authors import read_object

    root, _ = blob
    with pytest.raises(InputError, match="no such directory"):
        read_object(tmp_path / "nothing")
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    with pytest.raises(InputError, match="holdout: image index 9"):
        read_object(bad, holdout=[9])
    with open(bad / "calibration" / "L.txt", "a") as f:
        f.write("0,0,-1\n")
    with pytest.raises(InputError, match="4 .png images but 5 lights"):
        read_object(bad)
    shutil.copy(root / "calibration" / "L.txt", bad / "calibration" / "L.txt")
    np.save(bad / "mask_ud.npy", np.ones((7, 7)))
    with pytest.raises(InputError, match="matches neither"):
        read_object(bad)


def test_authors_object_end_to_end_through_the_command(blob, tmp_path, capsys, no_figures):
    """`fmbrdf-mi fit --authors DIR --holdout 3` with the camera's gain and read noise: a joint likelihood fit
    of three 16-bit raw mosaics of a non-spherical mesh object (pinhole camera, per-pixel viewing rays,
    unequal light powers) recovers the six parameters within 4.5 of its reported standard errors (two-sided
    7e-6 per parameter for a calibrated estimator: the noise bench shows the reported errors match the
    spread), every image's chi^2 / dof is near 1, and the held-out image is predicted to within its noise."""
    from fmbrdf_mi.cli import main

    root, truth = blob
    out = tmp_path / "fit"
    argv = ["fit", "--authors", str(root), "--holdout", "3", "--conversion-gain",
            str(truth["camera"]["conversion_gain"]), "--read-noise", "2.5", "--starts", "1", "-q", "-o", str(out)]
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    assert "relighting 003 (fmbrdf)" in stdout
    rep = json.loads((out / "fit.json").read_text())
    m = rep["models"]["fmbrdf"]
    assert m["objective"] == "likelihood" and m["converged"]
    # k_s comes back in DN per unit irradiance of the brightest light (intensities.npy / max)
    scale = {"k_s": truth["irradiance_dn"] * max(POWERS)}
    for k, v in TRUE.items():
        est, se = m["params"][k] / scale.get(k, 1.0), m["std_errors"][k] / scale.get(k, 1.0)
        assert abs(est - v) < 4.5 * se, (k, est, se)
        assert se < 0.05 * max(v, 10.0 if k == "kappa" else 0.0), (k, se)
    for im in m["images"]:
        assert 0.8 < im["chi2_per_dof"] < 1.3, im
    # the held-out image: shot noise alone gives RMSE / mean of about 1 / sqrt(electrons per pixel) ~ 0.5 %
    assert rep["relight"]["003"]["fmbrdf"]["rel_rmse"] < 0.01
    for f in ("fit.json", "history.png", "images_000.png", "profiles_002.png", "relight_003.png"):
        assert (out / f).is_file(), f
    assert main(argv) == 1
    assert "exists; pass --force" in capsys.readouterr().err


def test_manifest_and_repeated_light_give_the_authors_fit(blob, tmp_path, capsys, no_figures):
    """The same three images through a TOML manifest (normals and view rays in this package's frame,
    powers, a held-out image) and through repeated --light give the estimates of --authors to 1e-6
    (same pixels, same data, same options); manifest mistakes are one line naming the key."""
    from fmbrdf_mi.cli import main

    root, truth = blob
    g, init = _write_manifest(tmp_path, root, truth, str(root))
    common = ["--max-pixels", "300", "-q", "--init", init, "--intervals", "fisher", "--area-points", "2"]
    assert main(["fit", "--manifest", str(tmp_path / "m.toml"), "-o", str(tmp_path / "a")] + common) == 0
    assert main(["fit", "--authors", str(root), "--holdout", "3", "--conversion-gain", repr(g), "--read-noise",
                 "2.5", "-o", str(tmp_path / "b")] + common) == 0
    pa = json.loads((tmp_path / "a" / "fit.json").read_text())["models"]["fmbrdf"]["params"]
    pb = json.loads((tmp_path / "b" / "fit.json").read_text())["models"]["fmbrdf"]["params"]
    for k in TRUE:
        assert math.isclose(pa[k], pb[k], rel_tol=1e-6), (k, pa[k], pb[k])
    # repeated --light: one light per INPUT (powers all 1 here, so only the shape parameters compare)
    imgs = [f"{root}/image/img_ud/{k:03d}.png" for k in range(2)]
    argv = ["fit", *imgs, "--normals", str(tmp_path / "n.npy"), "--view", str(tmp_path / "v.npy"), "--mask",
            str(tmp_path / "m.npy"), "--conversion-gain", repr(g), "--read-noise", "2.5", "--white-level", "65535",
            "-o", str(tmp_path / "c")] + common
    for l in LIGHTS[:2]:
        argv.append("--light=" + ",".join(map(str, l)))
    assert main(argv) == 0
    assert (tmp_path / "c" / "images_001.png").is_file()
    # ... and reruns from its fit.json to the same estimates
    assert main(["fit", "--from", str(tmp_path / "c" / "fit.json"), "-o", str(tmp_path / "c2"), "-q"]) == 0
    pc, pc2 = (json.loads((tmp_path / d / "fit.json").read_text())["models"]["fmbrdf"]["params"] for d in ("c", "c2"))
    assert pc2 == pc
    capsys.readouterr()
    assert main(argv[:-1] + ["--force"]) == 1
    assert "--light given 1 times for 2 INPUT images" in capsys.readouterr().err
    (tmp_path / "bad.toml").write_text('[[image]]\ninput = "x.png"\ncolour = 1\n')
    assert main(["fit", "--manifest", str(tmp_path / "bad.toml"), "-o", str(tmp_path / "d")]) == 1
    assert "image 0: unknown key(s) colour" in capsys.readouterr().err


def test_joint_fits_rerun_from_fit_json(blob, tmp_path, capsys, no_figures):
    """`fmbrdf-mi fit --from fit.json` reruns a joint fit made through a manifest and through --authors: the
    record names every image with its SHA-256, light, power, geometry and held-out flag, and the rerun gives
    the same estimates (same files, same options, same seed: bit for bit); a changed image, sidecar-free raw
    mosaic or manifest, is refused in one line naming the file, before anything is written."""
    import shutil

    from fmbrdf_mi.cli import main
    from fmbrdf_mi.fit.outputs.record import sha256

    src, truth = blob
    root = tmp_path / "obj"             # a copy: the test changes an image
    shutil.copytree(src, root)
    g, init = _write_manifest(tmp_path, root, truth, "obj")
    common = ["--max-pixels", "100", "-q", "--init", init, "--seed", "3", "--intervals", "fisher"]
    assert main(["fit", "--manifest", str(tmp_path / "m.toml"), "-o", str(tmp_path / "a")] + common) == 0
    assert main(["fit", "--authors", str(root), "--holdout", "3", "--conversion-gain", repr(g), "--read-noise",
                 "2.5", "-o", str(tmp_path / "b")] + common) == 0
    img1 = str(root / "image" / "img_ud" / "001.png")
    for run, kind in (("a", "manifest"), ("b", "authors")):
        rep = json.loads((tmp_path / run / "fit.json").read_text())
        r = rep["reproduce"]
        assert r["kind"] == kind and r["arguments"]["seed"] == 3 and r["versions"]["mitsuba"]
        ims = r["images"]
        assert [im["holdout"] for im in ims] == [False, False, False, True]
        for im, l, p in zip(ims, LIGHTS, POWERS):
            np.testing.assert_allclose(im["light"], np.array(l) / np.linalg.norm(l), atol=1e-12)
            assert math.isclose(im["power"], p / max(POWERS)) and math.isclose(im["irradiance"], p / max(POWERS))
        assert ims[1]["input"] == img1 and r["files_sha256"][img1] == sha256(img1)
        normals = ims[0]["spec"]["options"]["normals"] if kind == "manifest" else str(root / "normal" / "normal_GT.npy")
        assert normals.endswith("n.npy" if kind == "manifest" else "normal_GT.npy") and normals in r["files_sha256"]
        assert ims[0]["settings"]["conversion_gain"] == g
        # rerun from another directory: the record holds absolute paths
        cwd = os.getcwd()
        os.chdir(tmp_path / run)
        try:
            assert main(["fit", "--from", "fit.json", "-o", str(tmp_path / (run + "2")), "-q"]) == 0
        finally:
            os.chdir(cwd)
        again = json.loads((tmp_path / (run + "2") / "fit.json").read_text())
        m, m2 = rep["models"]["fmbrdf"], again["models"]["fmbrdf"]
        assert m2["params"] == m["params"] and m2["std_errors"] == m["std_errors"]
        assert [im["n_pixels"] for im in m2["images"]] == [im["n_pixels"] for im in m["images"]]
        assert again["relight"] == rep["relight"]
        assert again["reproduce"]["files_sha256"] == r["files_sha256"]
    # --from takes no other inputs
    capsys.readouterr()
    assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "--manifest", str(tmp_path / "m.toml"),
                 "-o", str(tmp_path / "x"), "-q"]) == 1
    assert "--from: give no --manifest" in capsys.readouterr().err
    # a changed image: refused, one line naming it, nothing written
    from PIL import Image

    from fmbrdf_mi.fit.inputs.observations import read_array

    original = open(img1, "rb").read()
    im = read_array(img1, "image").astype(np.uint16)
    im[0, 0] ^= 1                                       # one raw sample one DN off
    Image.fromarray(im).save(img1)
    for run in ("a", "b"):
        assert main(["fit", "--from", str(tmp_path / run / "fit.json"), "-o", str(tmp_path / (run + "3"))]) == 1
        err = capsys.readouterr().err
        assert f"input {img1} has changed since the fit" in err and err.count("\n") == 1, err
        assert not (tmp_path / (run + "3")).exists()
    # a changed manifest too (the image restored)
    open(img1, "wb").write(original)
    (tmp_path / "m.toml").write_text((tmp_path / "m.toml").read_text() + "# edited\n")
    assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "a4")]) == 1
    assert f"input {tmp_path / 'm.toml'} has changed" in capsys.readouterr().err


def _write_manifest(tmp_path, root, truth, image_dir):
    """m.toml in tmp_path for the object at ``root`` (images under ``image_dir``, as the manifest
    names them), its first view's geometry as n.npy, v.npy, m.npy; returns (conversion gain,
    an --init near the truth: no coarse search, a quick test)."""
    from fmbrdf_mi.fit.inputs.authors import read_object

    specs, _ = read_object(root)
    o = specs[0].input
    np.save(tmp_path / "n.npy", o.normals)
    np.save(tmp_path / "v.npy", o.view_dirs)
    np.save(tmp_path / "m.npy", o.mask)
    g = truth["camera"]["conversion_gain"]
    lines = ["[defaults]", 'normals = "n.npy"', 'view = "v.npy"', 'mask = "m.npy"', f"conversion_gain = {g!r}",
             "read_noise = 2.5", "white_level = 65535.0"]
    for k, (l, p) in enumerate(zip(LIGHTS, POWERS)):
        lines += ["[[image]]", f'input = "{image_dir}/image/img_ud/{k:03d}.png"', f"light = {list(l)}",
                  f"power = {p / max(POWERS)!r}"] + (["holdout = true"] if k == 3 else [])
    (tmp_path / "m.toml").write_text("\n".join(lines) + "\n")
    ks = truth["irradiance_dn"] * max(POWERS)
    return g, f"eta=1.5,alpha=0.22,beta=1.2,kappa=14,k_s={0.8 * ks!r},r_k=0.6"
