"""Fit inputs (fmbrdf_mi/fit/inputs) that are refused: light powers and irradiances, directions, the authors'
layout, paths that are not regular files, manifests, masks, the render metadata's fov, and API misuse.  Each is
one line naming the parameter or file and what is valid (exit status 1 from ``fmbrdf-mi fit``).
"""
import dataclasses
import os

import numpy as np
import pytest

from conftest import one_line_error, run


# ---------------------------------------------------------------- inputs, manifests and the authors' layout
def raw_input(tmp_path):
    """A flat 32 x 32 raw mosaic (16 x 16 super-pixels) fitted with --sphere 8,8,6."""
    np.save(tmp_path / "raw.npy", np.full((32, 32), 100.0))
    return str(tmp_path / "raw.npy")


def authors_object(root, *, lights="0,0,-1\n0.3,0,-1\n", intensities=None, normals=None, intrinsics=None,
                   view_rays=True):
    """A minimal object in the authors' layout (2 flat 16 x 16 mosaics, normals facing the camera)."""
    from PIL import Image

    for d in ("calibration", "normal", "image/img_ud"):
        os.makedirs(root / d, exist_ok=True)
    (root / "calibration" / "L.txt").write_text(lights)
    for k in range(2):
        Image.fromarray(np.full((16, 16), 1000, np.uint16)).save(root / "image" / "img_ud" / f"{k:03d}.png")
    n = np.zeros((8, 8, 3))
    n[..., 2] = -1.0                      # OpenCV axes: facing the camera is z < 0
    np.save(root / "normal" / "normal_GT.npy", n if normals is None else normals)
    if view_rays:
        vp = np.zeros((8, 8, 3))
        vp[..., 2] = 1.0
        np.save(root / "calibration" / "vpL_img.npy", vp)
    if intrinsics is not None:
        np.save(root / "calibration" / "IntrinsicL.npy", intrinsics)
    if intensities is not None:
        np.save(root / "calibration" / "intensities.npy", np.asarray(intensities, float))
    np.save(root / "mask_ud.npy", np.ones((16, 16)))
    return str(root)


@pytest.mark.parametrize("extra,words", [
    (["--irradiance", "1e200"], ["--irradiance", "1e+200", "[1e-20, 1e+20]"]),
    (["--irradiance", "1e-200"], ["--irradiance", "[1e-20, 1e+20]"]),
])
def test_extreme_irradiance_is_refused(capsys, tmp_path, extra, words):
    """Before: "'eta' (index of refraction mu) = nan is outside its valid range" (1e200) or a Dr.Jit
    traceback (1e-200), after the fit had run."""
    rc, _, err = run(capsys, "fit", raw_input(tmp_path), "--sphere", "8,8,6", "--light", "0,0,1", *extra,
                     "-o", str(tmp_path / "out"), "-q", "--max-iter", "2")
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("image0,words", [
    ("power = 1e308", ["image 0", "power", "1e+308", "[1e-20, 1e+20]"]),
    ("power = 1e15\nirradiance = 1e10", ["image 0", "power 1e+15", "irradiance 1e+10", "[1e-20, 1e+20]"]),
])
def test_huge_manifest_power_is_refused(capsys, tmp_path, image0, words):
    """Before: "'eta' (index of refraction mu) = nan is outside its valid range (1, 3]"."""
    raw_input(tmp_path)
    (tmp_path / "m.toml").write_text(f'[defaults]\nsphere = "8,8,6"\n[[image]]\ninput = "raw.npy"\nlight = [0, 0, 1]\n'
                                     f'{image0}\n[[image]]\ninput = "raw.npy"\nlight = [0, 0.3, 1]\n')
    rc, _, err = run(capsys, "fit", "--manifest", str(tmp_path / "m.toml"), "-o", str(tmp_path / "out"), "-q",
                     "--max-iter", "2")
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_observation_irradiance_out_of_range():
    from fmbrdf_mi.fit import InputError, Observation
    from fmbrdf_mi import geometry as G

    n, m, v = G.sphere_normals((16, 16), (8, 8), 6)
    s = np.stack([np.ones((16, 16)), np.zeros((16, 16)), np.zeros((16, 16))])
    for e in (1e40, 1e-200):
        with pytest.raises(InputError, match=r"irradiance: expected a finite number in \[1e-20, 1e\+20\]"):
            Observation(s, m, n, v, [0, 0, 1], irradiance=e)


@pytest.mark.parametrize("v,want", [([1e308, 0, 0], [1, 0, 0]), ([0, 1e-320, 0], [0, 1, 0]),
                                    ([1e308, 1e308, 0], [2 ** -0.5, 2 ** -0.5, 0])])
def test_huge_and_tiny_directions_are_normalised(v, want):
    """Before: the norm overflowed (1e308 -> "got array([0., 0., 0.])") or underflowed (zero vector)."""
    from fmbrdf_mi.fit.inputs.observations import check_direction

    np.testing.assert_allclose(check_direction(v, "light"), want, atol=1e-15)


@pytest.mark.parametrize("v", [np.zeros(3), np.array([np.nan, 0, 1])])
def test_direction_message_shows_the_value_not_numpy(v):
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.inputs.observations import check_direction

    with pytest.raises(InputError) as e:
        check_direction(v, "light")
    assert "array(" not in str(e.value) and "light:" in str(e.value)


@pytest.mark.parametrize("kw,words", [
    (dict(lights="0,0,-1\nnan,0,-1\n"), ["L.txt", "row 2", "finite"]),
    (dict(lights="0,0,-1\n0,0,0\n"), ["L.txt", "row 2", "not all zero"]),
    (dict(intensities=[1.0, 0.0]), ["intensities.npy", "entry 1 is 0", "> 0"]),
    (dict(intensities=[1.0, -2.0]), ["intensities.npy", "entry 1 is -2", "> 0"]),
    (dict(intensities=[np.nan, 1.0]), ["intensities.npy", "entry 0 is nan"]),
    (dict(normals=np.full((8, 8, 3), np.nan)), ["normal_GT.npy", "no unit normal"]),
    (dict(normals=np.zeros((8, 8, 3))), ["normal_GT.npy", "no unit normal"]),
    (dict(view_rays=False, intrinsics=np.zeros((3, 3))), ["IntrinsicL.npy", "invertible"]),
    (dict(view_rays=False, intrinsics=np.array([[1.0, 0, 4], [2.0, 0, 8], [0, 0, 1]])), ["IntrinsicL.npy", "invertible"]),
])
def test_authors_layout_files_are_named(capsys, tmp_path, kw, words):
    """Before: NaN in L.txt and bad intensities were shape errors ("got (2,)"), broken normals an "empty
    mask", a singular camera matrix "Singular matrix" with no file named."""
    root = authors_object(tmp_path / "obj", **kw)
    rc, _, err = run(capsys, "fit", "--authors", root, "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_authors_object_helper_is_valid(tmp_path):
    """The object above reads (so the refusals are the files' doing)."""
    from fmbrdf_mi.fit.inputs.authors import read_object

    specs, info = read_object(authors_object(tmp_path / "obj", intensities=[1.0, 2.0]))
    assert info["images"] == 2 and info["mask_pixels"] == 64


@pytest.mark.parametrize("which", ["directory", "/dev/null"])
def test_input_that_is_not_a_regular_file(capsys, tmp_path, which):
    """Before: "polarisation image ...: no such file" for a directory or /dev/null that exist."""
    if which == "directory":
        path, words = str(tmp_path / "adir"), ["adir", "is a directory"]
        os.mkdir(path)
    else:
        if not os.path.exists("/dev/null"):
            pytest.skip("no /dev/null")
        path, words = "/dev/null", ["/dev/null", "not a regular file"]
    rc, _, err = run(capsys, "fit", path, "--sphere", "8,8,6", "--light", "0,0,1", "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", *words)


def test_stokes_exr_that_is_a_directory(capsys, tmp_path):
    os.mkdir(tmp_path / "s.exr")
    rc, _, err = run(capsys, "fit", str(tmp_path / "s.exr"), "--sphere", "8,8,6", "--light", "0,0,1",
                     "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", "s.exr", "is a directory")


def test_authors_directory_that_is_a_file(capsys, tmp_path):
    (tmp_path / "obj").write_text("x")
    rc, _, err = run(capsys, "fit", "--authors", str(tmp_path / "obj"), "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", "obj", "not a directory")


def test_manifest_that_is_a_directory(capsys, tmp_path):
    os.mkdir(tmp_path / "m.toml")
    rc, _, err = run(capsys, "fit", "--manifest", str(tmp_path / "m.toml"), "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", "m.toml", "is a directory")


@pytest.mark.parametrize("name", ["m.yaml", "m.yml"])
def test_yaml_manifest_is_refused_by_name(capsys, tmp_path, name):
    """Before: parsed as JSON: "not readable (Expecting value: line 1 column 1 (char 0))"."""
    (tmp_path / name).write_text("image:\n  - input: raw.npy\n    light: [0, 0, 1]\n")
    rc, _, err = run(capsys, "fit", "--manifest", str(tmp_path / name), "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", name, "TOML", "JSON")


def test_manifest_of_another_name_says_it_was_read_as_json(capsys, tmp_path):
    (tmp_path / "m.txt").write_text("[[image]]\n")
    rc, _, err = run(capsys, "fit", "--manifest", str(tmp_path / "m.txt"), "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", "m.txt", "as JSON", ".toml")


def test_nan_mask_file_is_refused(capsys, tmp_path):
    """Before: NaN != 0, so a NaN mask pixel was object."""
    m = np.ones((16, 16))
    m[3, 4] = np.nan
    np.save(tmp_path / "mask.npy", m)
    rc, _, err = run(capsys, "fit", raw_input(tmp_path), "--sphere", "8,8,6", "--mask", str(tmp_path / "mask.npy"),
                     "--light", "0,0,1", "-o", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "fit", "mask.npy", "NaN")


@pytest.mark.parametrize("fov,words", [("wide", r"fov: expected a number in \(0, 180\), got 'wide'"),
                                       (None, r"fov: a perspective camera needs .* \(0, 180\) degrees")])
@pytest.mark.parametrize("geometry", ["sphere", "normals"])
def test_fov_as_a_word_is_named(tmp_path, fov, words, geometry):
    """Before: "could not convert string to float: 'wide'" with no key."""
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.inputs.files import build_observation
    from fmbrdf_mi.geometry import sphere_normals

    n, m, _ = sphere_normals((16, 16), (8, 8), 6)
    np.save(tmp_path / "n.npy", n)
    np.save(tmp_path / "m.npy", m)
    given = dict(sphere="8,8,6") if geometry == "sphere" else dict(normals=str(tmp_path / "n.npy"),
                                                                    mask=str(tmp_path / "m.npy"))
    with pytest.raises(InputError, match=words):
        build_observation(raw_input(tmp_path), camera="perspective", fov=fov, light=[0, 0, 1], **given)


def test_render_metadata_fov_is_named():
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.inputs.parse import check_render_parameters

    p = {"width": 8, "height": 8, "camera": "perspective", "fov": "wide", "distance": 5}
    with pytest.raises(InputError, match=r"^x.json: parameters.fov: expected a number in \(0, 180\), got 'wide'$"):
        check_render_parameters(p, "x.json")
    assert check_render_parameters(dict(p, fov=30), "x.json")["fov"] == 30


def _obs():
    from fmbrdf_mi.fit import Observation
    from fmbrdf_mi import geometry as G

    n, m, v = G.sphere_normals((16, 16), (8, 8), 6)
    s = np.stack([np.ones((16, 16)), np.zeros((16, 16)), np.zeros((16, 16))])
    return Observation(s, m, n, v, [0, 0, 1]), (s, m, n, v)


PARAMS = dict(eta=1.5, alpha=0.3, beta=2.0, kappa=1.0, k_s=1.0, r_k=1.0)


def _photometric_stereo(obs, mask):
    from fmbrdf_mi.fit.inputs.normal_maps import photometric_stereo

    return photometric_stereo([obs] * 3, mask=mask)


@pytest.mark.parametrize("call,words", [
    (lambda f, o, a: f.Observation(a[0], np.full((16, 16), np.nan), *a[2:], [0, 0, 1]), ["mask", "NaN"]),
    (lambda f, o, a: dataclasses.replace(o, light_dir="up"), ["light_dir", "three numbers", "'up'"]),
    (lambda f, o, a: f.fit("image.png", progress=False), ["fit()", "Observation", "'image.png'", "fit_files"]),
    (lambda f, o, a: f.fit_joint([o, "x"], progress=False), ["fit_joint()", "item 1", "Observation", "'x'"]),
    (lambda f, o, a: f.fit_joint("x", progress=False), ["fit_joint()", "Observation", "'x'"]),
    (lambda f, o, a: f.refine_joint([o] * 3, o.normals, dict(eta=9)), ["parameters", "missing alpha", "r_k"]),
    (lambda f, o, a: f.refine_joint([o] * 3, o.normals, dict(PARAMS, k_s="1")), ["k_s must be a number"]),
    (lambda f, o, a: f.refine_joint([o] * 3, o.normals, PARAMS, mask=a[1][:8]), ["mask", "(8, 16)"]),
    (lambda f, o, a: f.refine_joint([o, o, "x"], o.normals, PARAMS), ["item 2", "Observation"]),
    (lambda f, o, a: _photometric_stereo(o, a[1][:, :8]), ["mask", "(16, 8)"]),
    (lambda f, o, a: f.predict_image("fmbrdf", dict(eta=9), o), ["parameters", "missing alpha"]),
])
def test_api_misuse_is_one_clear_error(call, words):
    """Before: AttributeError ('str' object has no attribute 'noise'), KeyError 'alpha', NumPy's
    "could not convert string to float" / boolean index errors, or nothing (a NaN mask, a mask of the wrong
    shape given to the normal refinement)."""
    import fmbrdf_mi.fit as f
    from fmbrdf_mi.fit import InputError

    obs, arrays = _obs()
    with pytest.raises(InputError) as e:
        call(f, obs, arrays)
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)
