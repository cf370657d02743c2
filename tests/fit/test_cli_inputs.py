"""``fmbrdf-mi fit``'s inputs that were accepted and then ignored or fitted as nonsense: --mask with the built-in
sphere, --max-pixels below the minimum, non-numeric samples, one image twice in a joint fit, the authors'
viewing rays.  Each is applied or refused in one line naming the option or file and what is valid.
"""
import json

import numpy as np
import pytest

from conftest import one_line_error

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.files import build_observation


# ---------------------------------------------------------------- inputs
def _capture(tmp_path, size=16):
    """A raw PNG of the built-in sphere's render with its capture sidecar (``fmbrdf-mi render --raw``)."""
    from PIL import Image

    from fmbrdf_mi.sensor import camera as C

    raw = np.random.default_rng(0).integers(100, 3000, (size, size)).astype(np.uint16)
    path = tmp_path / "cap_raw.png"
    Image.fromarray(raw).save(path)
    extra = {"scene": "builtin:sphere", "capture": {"dn_per_input_unit": 100.0},
             "parameters": {"width": size, "height": size, "camera": "orthographic", "fov": 25.0,
                            "distance": 5.0, "light_dir": [0.0, 0.0, 1.0], "irradiance": 3.14}}
    C.write_sidecar(path, C.CameraModel(), extra)
    return path


def _fit_cli(capsys, *argv):
    from fmbrdf_mi.cli import main

    rc = main(["fit", *argv])
    return rc, capsys.readouterr().err


def _save_png(path, a, mode=None):
    from PIL import Image

    Image.fromarray(a, mode).save(path)
    return path


def test_mask_is_applied_to_the_builtin_sphere(tmp_path):
    """Before: the sidecar's geometry replaced --mask, which was ignored."""
    raw = _capture(tmp_path, 32)
    whole = build_observation(str(raw)).mask
    half = np.zeros((32, 32), np.uint8)
    half[:, :16] = 255                                   # left half of the raw mosaic: super-pixel columns 0..7
    for name, a in (("m.npy", half), ("m.png", half), ("rgb.png", np.stack([half] * 3, axis=-1)),
                    ("small.npy", half[::2, ::2])):      # a mask of the super-pixel grid
        p = tmp_path / name
        np.save(p, a) if name.endswith(".npy") else _save_png(p, a)
        m = build_observation(str(raw), mask=str(p)).mask
        assert m.sum() > 0 and not m[:, 8:].any() and np.array_equal(m, whole & (np.arange(16) < 8)), name


@pytest.mark.parametrize("make,words", [
    (lambda d: np.save(d / "m.npy", np.ones((5, 7))), ["m.npy", "(5, 7)", "(16, 16)", "(32, 32)"]),
    (lambda d: np.save(d / "m.npy", np.zeros((32, 32))), ["m.npy", "selects no pixel"]),
    (lambda d: np.save(d / "m.npy", np.pad(np.ones((2, 2)), ((0, 30), (0, 30)))),
     ["m.npy", "selects no pixel of the sphere"]),
    (lambda d: np.save(d / "m.npy", np.full((32, 32), np.nan)), ["m.npy", "NaN"]),
    (lambda d: (d / "m.npy").mkdir(), ["m.npy", "directory"]),
    (lambda d: (d / "m.npy").write_text("not a mask"), ["m.npy", "not a readable"]),
])
def test_a_bad_mask_with_the_builtin_sphere_is_one_line(tmp_path, capsys, make, words):
    """Before: each was ignored and the fit ran on the whole sphere (exit 0)."""
    raw = _capture(tmp_path, 32)
    make(tmp_path)
    rc, err = _fit_cli(capsys, str(raw), "--mask", str(tmp_path / "m.npy"), "-o", str(tmp_path / "out"),
                       "--max-iter", "1")
    one_line_error(rc, err, "fit", "mask", *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("n", [1, 2, 3, 19])
def test_max_pixels_below_the_minimum_is_refused_by_the_api(tmp_path, n):
    """Before: max_pixels 1..3 fitted that many super-pixels and said "converged"."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.problem.data import MIN_PIXELS

    obs = build_observation(str(_capture(tmp_path, 64)))
    with pytest.raises(InputError, match=rf"max_pixels \(--max-pixels\) {n}: .*at least {MIN_PIXELS}\b"):
        fit(obs, max_pixels=n, max_iter=1, progress=False)


def test_max_pixels_below_the_minimum_is_one_line(tmp_path, capsys):
    raw = _capture(tmp_path, 64)
    rc, err = _fit_cli(capsys, str(raw), "--max-pixels", "2", "-o", str(tmp_path / "out"), "--max-iter", "1")
    one_line_error(rc, err, "fit", "(--max-pixels) 2", "at least 20", "0 for every usable pixel")
    assert not (tmp_path / "out").exists()


def test_max_pixels_split_over_a_joint_fit_is_refused_per_image(tmp_path, capsys):
    """Two images and --max-pixels 30: 15 per image, fewer than a fit accepts from one image's mask."""
    raw = _capture(tmp_path, 64)
    (tmp_path / "m.json").write_text(json.dumps({"image": [{"input": str(raw)},
                                                           {"input": str(raw), "light": [0.3, 0.0, 1.0]}]}))
    rc, err = _fit_cli(capsys, "--manifest", str(tmp_path / "m.json"), "--max-pixels", "30", "-o",
                       str(tmp_path / "out"), "--max-iter", "1")
    one_line_error(rc, err, "fit", "(--max-pixels) 30", "15 pixels per image of 2", "at least 40")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("array", [
    np.random.default_rng(1).random((16, 16)) > 0.5,                       # a boolean raw mosaic
    np.random.default_rng(1).random((16, 16)) * (1 + 1j),                 # complex
    np.random.default_rng(1).random((4, 16, 16)) > 0.5,                    # boolean angle images
    np.full((16, 16), "12", dtype="<U2"),                                   # strings
    np.full((16, 16), np.datetime64("2020-01-01")),                         # dates
])
def test_a_polarisation_image_of_non_numeric_samples_is_refused(tmp_path, capsys, array):
    """Before: a boolean or complex .npy was fitted as a raw mosaic (complex parts dropped with a
    warning), exit 0."""
    np.save(tmp_path / "raw.npy", array)
    rc, err = _fit_cli(capsys, str(tmp_path / "raw.npy"), "--sphere", "8,8,6", "--light", "0,0,1", "-o",
                       str(tmp_path / "out"), "--max-iter", "1")
    one_line_error(rc, err, "fit", "raw.npy", str(array.dtype), "integers or real numbers")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("shape", [(16, 16), (4, 16, 16)])
def test_a_polarisation_image_without_a_finite_sample_is_named(tmp_path, capsys, shape):
    """An all-NaN raw mosaic (or angle images): the file named.  Before: "stokes: non-finite values inside the
    mask", naming neither the file nor what is wrong with it."""
    np.save(tmp_path / "raw.npy", np.full(shape, np.nan))
    rc, err = _fit_cli(capsys, str(tmp_path / "raw.npy"), "--sphere", "8,8,6", "--light", "0,0,1", "-o",
                       str(tmp_path / "out"), "--max-iter", "1")
    one_line_error(rc, err, "fit", "raw.npy", "no finite sample")
    assert not (tmp_path / "out").exists()


def test_four_angle_files_of_booleans_are_refused(tmp_path):
    paths = []
    for k in range(4):
        np.save(tmp_path / f"a{k}.npy", np.ones((8, 8), bool))
        paths.append(str(tmp_path / f"a{k}.npy"))
    with pytest.raises(InputError, match=r"angle image .*a0.npy: samples of dtype bool; .*integers or real"):
        build_observation(paths, sphere="4,4,3", light=(0, 0, 1))


@pytest.mark.parametrize("second,light2,words", [
    ("same", [0.0, 0.0, 1.0], ["images 0 (cap_raw) and 1", "the same file", "cap_raw.png", "twice"]),
    ("copy", [0.0, 0.0, 2.0], ["images 0 (cap_raw) and 1 (copy)", "same content", "copy.png", "twice"]),
    ("same", None, ["images 0 (cap_raw) and 1", "the same file", "the input's own", "twice"]),
])
def test_the_same_image_twice_in_a_joint_fit_is_refused(tmp_path, capsys, second, light2, words):
    """Before: the manifest's two entries of one file and light were fitted as two images (each pixel
    counted twice, standard errors too small by sqrt(2)), exit 0."""
    import shutil

    raw = _capture(tmp_path, 32)
    other = raw
    if second == "copy":
        other = tmp_path / "copy.png"
        shutil.copy(raw, other)
        shutil.copy(tmp_path / "cap_raw.json", tmp_path / "copy.json")
    first = {"input": str(raw)} if light2 is None else {"input": str(raw), "light": [0.0, 0.0, 1.0]}
    entry = {"input": str(other)} if light2 is None else {"input": str(other), "light": light2}
    (tmp_path / "m.json").write_text(json.dumps({"image": [first, entry]}))
    rc, err = _fit_cli(capsys, "--manifest", str(tmp_path / "m.json"), "-o", str(tmp_path / "out"),
                       "--max-iter", "1")
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_distinct_lights_or_a_held_out_copy_are_accepted():
    from fmbrdf_mi.fit.inputs.manifest import ImageSpec
    from fmbrdf_mi.fit.outputs.joint import check_distinct

    here = __file__
    check_distinct([ImageSpec(here, [0, 0, 1]), ImageSpec(here, [0.1, 0, 1])])
    check_distinct([ImageSpec(here, [0, 0, 1]), ImageSpec(here, [0, 0, 1], holdout=True)])
    with pytest.raises(InputError, match="the same file"):
        check_distinct([ImageSpec(here, [0, 0, 1]), ImageSpec(here, [0, 0, 3])])
    with pytest.raises(InputError, match="images 0 .* and 2"):
        check_distinct([ImageSpec([here] * 4, [1, 0, 1]), ImageSpec(here, [1, 0, 1]),
                        ImageSpec([here] * 4, [1, 0, 1])])


@pytest.fixture(scope="module")
def authors_object(tmp_path_factory):
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object

    root = tmp_path_factory.mktemp("authors") / "obj"
    write_authors_object(root, {"eta": 1.5, "alpha": 0.2, "beta": 0.5, "kappa": 2.0, "k_s": 1.0, "r_k": 1.0},
                         [[0.3, 0.2, 1.0], [-0.3, 0.1, 1.0]], res=24, fov=12.0, seed=1)
    return root


@pytest.mark.parametrize("fill,words", [
    (lambda v, m: np.full_like(v, np.nan), ["vpL_img.npy", "no viewing ray", "NaN, infinite or zero"]),
    (lambda v, m: np.zeros_like(v), ["vpL_img.npy", "no viewing ray"]),
    (lambda v, m: np.full_like(v, np.inf), ["vpL_img.npy", "no viewing ray"]),
    (lambda v, m: np.where(m[..., None] & (np.arange(v.shape[1]) < 3)[None, :, None], np.nan, v),
     ["vpL_img.npy", "pixels of the mask", "no viewing ray"]),
])
def test_authors_viewing_rays_that_are_not_rays_are_refused(authors_object, tmp_path, fill, words):
    """Before: NaN (or zero) rays were replaced by (0, 0, 1), the orthographic view, silently."""
    import shutil

    from fmbrdf_mi.fit.inputs.authors import read_object

    bad = tmp_path / "bad"
    shutil.copytree(authors_object, bad)
    specs, _ = read_object(bad)
    m = specs[0].input.mask
    vfile = bad / "calibration" / "vpL_img.npy"
    v = np.load(vfile)
    m = np.pad(m, ((0, v.shape[0] - m.shape[0]), (0, v.shape[1] - m.shape[1])))
    np.save(vfile, fill(v, m))
    with pytest.raises(InputError) as exc:
        read_object(bad)
    assert all(w in str(exc.value) for w in words) and "\n" not in str(exc.value), str(exc.value)


def test_a_zero_light_of_a_duplicate_is_one_line(tmp_path, capsys):
    raw = _capture(tmp_path, 32)
    (tmp_path / "m.json").write_text(json.dumps({"image": [{"input": str(raw), "light": [0, 0, 1]},
                                                           {"input": str(raw), "light": [0, 0, 0]}]}))
    rc, err = _fit_cli(capsys, "--manifest", str(tmp_path / "m.json"), "-o", str(tmp_path / "out"), "--max-iter", "1")
    one_line_error(rc, err, "fit", "image 1: light", "non-zero")
