"""``fmbrdf-mi fit``'s options: each is checked before any work (the image named need not exist), and an option
the fit would ignore (for its mode, or overridden by the capture) is refused in one line naming it.
"""
import math

import numpy as np
import pytest

from conftest import one_line_error, run

from fmbrdf_mi import cli


# ---------------------------------------------------------------- options checked before work
@pytest.mark.parametrize("argv,words", [
    (["--read-noise", "2.5"], ["--read-noise needs --conversion-gain"]),
    (["--conversion-gain", "2"], ["--conversion-gain needs --read-noise"]),
    (["--conversion-gain", "0", "--read-noise", "1"], ["--conversion-gain", "(0, inf)"]),
    (["--black-level", "-1"], ["--black-level", "[0, inf)"]),
    (["--erode", "-1"], ["--erode"]),
    (["--max-time", "-5"], ["--max-time"]),
    (["--tol", "nan"], ["--tol", "finite"]),
    (["--max-iter", "0"], ["--max-iter"]),
    (["--max-pixels=-1"], ["--max-pixels", "[0, inf)"]),
    (["--irradiance", "nan"], ["--irradiance"]),
    (["--fov", "200"], ["--fov"]),
    (["--init", "eta=1.5,alpha=0.3"], ["--init", "missing", "beta", "kappa", "k_s", "r_k"]),
    (["--init", "eta=1.5,alpha=0.3,beta=2,kappa=10,k_s=1,r_k=1,foo=2"], ["--init", "'foo'"]),
    (["--init", "eta=9,alpha=0.3,beta=2,kappa=10,k_s=1,r_k=1"], ["--init eta", "bounds"]),
    (["--albedo", "per-pixel", "--init", "eta=1.5,alpha=0.3,beta=2,kappa=10,k_s=1,r_k=1"],
     ["--init k_s, r_k", "--albedo per-pixel", "solves the albedos per pixel", "give eta, alpha, beta, kappa"]),
    (["--albedo", "per-pixel-bilinear", "--init", "eta=1.5,alpha=0.3"], ["--init", "missing beta, kappa"]),
    (["--bounds", "alpha=0.5:0.1"], ["--bounds", "alpha"]),
    (["--bounds", "gamma=0.1:0.5"], ["--bounds", "gamma"]),
])
def test_fit_options_checked_before_work(capsys, tmp_path, argv, words):
    """Before: --read-noise alone was ignored, negative --black-level/--erode/--max-time and
    --tol nan were accepted, an incomplete --init ended in KeyError, --max-pixels=-1 in a
    NumPy message; the image here does not even exist: options come first."""
    rc, _, err = run(capsys, "fit", str(tmp_path / "missing.exr"), "--light", "0,0,1",
                     "-o", str(tmp_path / "out"), *argv)
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_fit_output_under_a_file(capsys, tmp_path, a_file):
    rc, _, err = run(capsys, "fit", str(tmp_path / "missing.exr"), "--light", "0,0,1",
                     "-o", str(a_file / "out"))
    one_line_error(rc, err, "fit", str(a_file))


@pytest.mark.parametrize("kw,words", [
    ({"max_pixels": "many"}, ["max_pixels", "'many'"]), ({"tol": math.nan}, ["tol"]),
    ({"erode": -1}, ["erode"]), ({"init": {"eta": 1.5}}, ["init", "missing"]),
])
def test_fit_api_options(kw, words):
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.errors import InputError

    with pytest.raises(InputError) as e:
        fit(None, progress=False, **kw)
    for w in words:
        assert w in str(e.value)


# ---------------------------------------------------------------- options the fit would ignore
@pytest.mark.parametrize("argv,words", [
    (["--manifest", "{d}/missing.toml", "--light", "0,0,1"], ["--manifest: --light not supported"]),
    (["--authors", "{d}/missing_dir", "--light", "0,0,1"], ["--authors: --light not supported"]),
    (["{d}/missing.png", "--light", "0,0,1", "--power-start", "given"], ["--power-start needs --free-power"]),
    (["{d}/missing.png", "--light", "0,0,1", "--loss", "likelihood", "--footprint", "box"],
     ["--footprint box", "--area-points"]),
    (["{d}/missing.png", "--light", "0,0,1", "--conversion-gain", "2", "--read-noise", "1", "--footprint", "point"],
     ["--footprint point", "--area-points"]),
    (["--from", "{d}/fit.json", "--max-iter", "1"], ["--from", "--max-iter"]),
    (["--from", "{d}/fit.json", "--light", "0,0,1", "--loss", "paper"], ["--from", "--light", "--loss"]),
    (["--from", "{d}/fit.json", "--free-power"], ["--from", "--free-power"]),
    (["--from", "{d}/fit.json", "--refine-normals"], ["--from", "--refine-normals"]),
    # typed at their default values: still not what --from reruns
    (["--from", "{d}/fit.json", "--albedo", "shared"], ["--from", "--albedo"]),
    (["--from", "{d}/fit.json", "--max-pixels", "20000", "--seed", "0"], ["--from", "--max-pixels", "--seed"]),
    # pairs that do not go together: refused before the materials are searched or the fit starts
    (["{d}/missing.png", "--materials", "auto:2", "--albedo", "per-pixel", "--albedo-smooth", "0.1"],
     ["--materials auto:2", "--albedo-smooth"]),
    (["{d}/missing.png", "--materials", "auto:2", "--albedo", "per-pixel-bilinear"],
     ["--materials auto:2", "per-pixel-bilinear"]),
    (["{d}/missing.png", "--materials", "labels.png", "--loss", "paper"], ["--materials labels.png", "likelihood"]),
    # a smoothness scale the fit cannot resolve: the valid range named
    (["{d}/missing.png", "--albedo", "per-pixel", "--albedo-smooth", "1e-200"], ["--albedo-smooth", "1e-06", "1e-200"]),
    (["{d}/missing.png", "--albedo", "per-pixel", "--albedo-smooth", "0.1,1e-12"], ["--albedo-smooth", "1e-12"]),
])
def test_fit_ignored_options_refused_before_any_file_is_read(capsys, tmp_path, argv, words):
    """Before: each ran (or read its files) and dropped the option.  Nothing here exists: the options
    are refused first."""
    argv = [a.format(d=tmp_path) for a in argv]
    rc, _, err = run(capsys, "fit", *argv, "-o", str(tmp_path / "out"))
    one_line_error(rc, err, "fit", *words)
    assert "missing" not in err and not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """A mono and a colour raw capture of the built-in sphere (fmbrdf-mi render --raw) and a view map."""
    import numpy as np

    d = tmp_path_factory.mktemp("captures")
    for name, extra in (("m", []), ("c", ["--sensor", "colour"])):
        assert cli.main(["render", str(d / f"{name}.exr"), "--res", "32", "--spp", "2", "--raw", "-q",
                         "--no-previews", *extra]) == 0
    np.save(d / "view.npy", np.tile([0.0, 0.0, 1.0], (16, 16, 1)))
    return d


@pytest.mark.parametrize("image,argv,words", [
    ("m_raw.png", ["--footprint", "box"], ["--footprint box", "m_raw.json", "--area-points"]),
    ("m_raw.png", ["--footprint", "demosaic"], ["--footprint demosaic", "--area-points"]),
    ("m_raw.png", ["--view", "{d}/view.npy"], ["--view", "built-in sphere"]),
    ("m_raw.png", ["--camera", "perspective"], ["--camera perspective", "built-in sphere"]),
    ("m_raw.png", ["--fov", "30"], ["--fov", "built-in sphere"]),
    ("c_raw.png", ["--channel", "R"], ["colour polarisation mosaic", "--channel R"]),
    ("c_raw.png", ["--demosaic", "superpixel"], ["colour polarisation mosaic", "--demosaic superpixel"]),
    ("c_raw.png", ["--tol", "0.01", "--time-limit", "5"], ["colour polarisation mosaic", "--tol, --time-limit"]),
])
def test_fit_options_the_capture_overrides_are_refused(capsys, tmp_path, captures, image, argv, words):
    """Before: the fit ran with the sidecar's noise (the likelihood, which has no footprint), the render's
    exact geometry (not --view/--camera/--fov) and the colour mosaic's CFA (not --channel)."""
    argv = [a.format(d=captures) for a in argv]
    rc, _, err = run(capsys, "fit", str(captures / image), "-o", str(tmp_path / "out"), "--max-iter", "1",
                     "--starts", "1", "--max-pixels", "100", "-q", *argv)
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_fit_footprint_with_the_paper_loss_still_runs(capsys, tmp_path, captures, no_figures):
    rc, _, err = run(capsys, "fit", str(captures / "m_raw.png"), "-o", str(tmp_path / "out"), "--max-iter", "1",
                     "--starts", "1", "--max-pixels", "100", "-q", "--footprint", "box", "--loss", "paper")
    assert rc in (0, 3), err      # 3: stopped by --max-iter 1
    assert (tmp_path / "out" / "fit.json").exists()


@pytest.mark.parametrize("argv,words", [
    (["--albedo", "per-pixel"], ["--albedo per-pixel", "no camera noise model", "--conversion-gain"]),
    (["--albedo", "per-pixel-bilinear"], ["--albedo per-pixel-bilinear", "no camera noise model"]),
    (["--intervals", "profile"], ["--intervals profile", "no camera noise model"]),
    (["--area-points", "4"], ["--area-points 4", "no camera noise model"]),
])
def test_fit_likelihood_options_on_an_input_without_noise_model_refused(capsys, tmp_path, captures, argv, words):
    """A Stokes EXR has no camera noise model: the loss resolves to the paper's.  Before: the option was dropped,
    the fit ran (exit 0) and fit.json recorded it as if applied.  Now refused before the fit, nothing written."""
    rc, _, err = run(capsys, "fit", str(captures / "m.exr"), "-o", str(tmp_path / "out"), "--max-iter", "1",
                     "--starts", "1", "--max-pixels", "100", "-q", *argv)
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


def test_manifest_footprint_is_named_as_the_manifest_gave_it(capsys, tmp_path, captures):
    """A manifest's footprint key with a likelihood fit: the line names the image and the key (it said
    '--footprint point', an option the user never gave)."""
    m = tmp_path / "m.toml"
    m.write_text(f'[[image]]\ninput = "{captures / "m_raw.png"}"\nfootprint = "point"\n'
                 f'[[image]]\ninput = "{captures / "m_raw.png"}"\nlight = [0.3, 0.0, 1.0]\n')
    rc, _, err = run(capsys, "fit", "--manifest", str(m), "-o", str(tmp_path / "out"), "--max-iter", "1", "-q")
    one_line_error(rc, err, "fit", "image m_raw", "manifest's", "footprint point", "--area-points")
    assert not (tmp_path / "out").exists()


def test_fit_channel_of_a_one_channel_input_refused(capsys, tmp_path, captures):
    """Before: --channel R on a mono raw mosaic was dropped and the fit ran on the mosaic as it is."""
    rc, _, err = run(capsys, "fit", str(captures / "m_raw.png"), "-o", str(tmp_path / "out"), "--channel", "R",
                     "-q", "--max-iter", "1")
    one_line_error(rc, err, "fit", "--channel R", "m_raw.png", "one channel")
    assert not (tmp_path / "out").exists()


def test_a_per_pixel_fit_starts_from_the_shape_parameters_alone(capsys, tmp_path, captures, no_figures):
    """Per-pixel albedos are solved per pixel at the start's shape: ``--init`` takes eta, alpha, beta, kappa.
    Before: it demanded k_s and r_k too (refused without them), which the fit then did not use."""
    import json

    rc, _, err = run(capsys, "fit", str(captures / "m_raw.png"), "--albedo", "per-pixel", "--init",
                     "eta=1.5,alpha=0.3,beta=2,kappa=10", "--starts", "1", "--max-iter", "1", "--intervals", "fisher",
                     "--max-pixels", "40", "-o", str(tmp_path / "out"), "-q")
    assert rc in (0, 3) and "error:" not in err, err
    rec = json.load(open(tmp_path / "out" / "fit.json"))
    start = rec["models"]["fmbrdf"]["starts"][0]["start"]
    assert start == {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0}, start


# ---------------------------------------------------------------- the device
def test_fit_cuda_variant_without_a_gpu(capsys, tmp_path):
    """--variant cuda_ad_mono_polarized where Dr.Jit has no CUDA backend: one line before any file is read."""
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA device")
    rc, _, err = run(capsys, "fit", str(tmp_path / "missing.exr"), "--light", "0,0,1", "-o", str(tmp_path / "out"),
                     "--variant", "cuda_ad_mono_polarized")
    one_line_error(rc, err, "fit", "cuda_ad_mono_polarized", "no CUDA device", "llvm_ad_mono_polarized")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("before,after", [("llvm_ad_spectral_polarized", "llvm_ad_mono_polarized"),
                                          ("llvm_ad_rgb", "llvm_ad_mono_polarized"),
                                          ("llvm_ad_mono_polarized", "llvm_ad_mono_polarized")])
def test_fit_variant_from_the_current_one(before, after):
    """A fit runs in the caller's variant when it is a fit variant (so ``mi.set_variant`` picks the device), else
    in the LLVM one (on a machine with Dr.Jit's LLVM backend)."""
    import mitsuba as mi

    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    mi.set_variant(before)
    assert set_variant().variant() == after
