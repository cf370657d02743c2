"""Issue 24, "Options and files silently ignored" and "--from integrity": an option the
command would ignore, or a fit.json whose rerun cannot be verified, is refused in one line
naming it (exit status 1, no traceback, nothing written).  Each test failed on the code
before the fix: the option was dropped and the command ran, or the rerun read files no
hash covered."""
import os

import pytest

from conftest import fit_record, one_line_error, run

from fmbrdf_mi import cli


# ------------------------------------------------------------------ render
@pytest.mark.parametrize("argv,words", [
    (["--sensor", "colour"], ["--sensor colour", "--raw"]),
    (["--raw", "--cfa", "BGGR"], ["--cfa BGGR", "--sensor colour"]),
    (["--cfa", "RGGB"], ["--cfa RGGB", "--sensor colour"]),
    (["--variant", "llvm_ad_mono_polarized", "-D", "k_s=1,0.5,0.2"], ["k_s=1,0.5,0.2", "RGB", "mono"]),
    (["--variant", "llvm_ad_mono_polarized", "-D", "r_k=0.2,0.5,1"], ["r_k=0.2,0.5,1", "RGB"]),
    (["--raw-seed", "3"], ["--raw-seed", "--raw"]),
    (["--full-well", "5000", "--bits", "10"], ["--full-well, --bits", "--raw"]),
    (["--layout", "90,135,45,0", "--mosaic"], ["--layout", "--raw"]),
    (["--conversion-gain", "2", "--raw-exposure", "100"], ["--conversion-gain, --raw-exposure", "--raw"]),
])
def test_render_ignored_options_refused(capsys, tmp_path, argv, words):
    """Before: the EXR was written, the option dropped (no raw mosaic, the mono sensor, the RGB
    albedo averaged by the mono variant)."""
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", *argv, str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", *words)
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("argv", [
    ["--raw", "--sensor", "colour", "--cfa", "BGGR"],
    ["--raw", "--raw-seed", "3", "--full-well", "5000"],
    ["--variant", "llvm_ad_mono_polarized", "-D", "k_s=0.5"],
    ["-D", "k_s=1,0.5,0.2"],
])
def test_render_valid_camera_options_still_run(capsys, tmp_path, argv):
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", "--no-previews", *argv,
                     str(tmp_path / "x.exr"))
    assert rc == 0, err
    assert (tmp_path / "x.exr").exists()


# ------------------------------------------------------------------ fit: the option table
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


def test_fit_footprint_with_the_paper_loss_still_runs(capsys, tmp_path, captures):
    rc, _, err = run(capsys, "fit", str(captures / "m_raw.png"), "-o", str(tmp_path / "out"), "--max-iter", "1",
                     "--starts", "1", "--max-pixels", "100", "-q", "--footprint", "box", "--loss", "paper")
    assert rc in (0, 3), err      # 3: stopped by --max-iter 1
    assert (tmp_path / "out" / "fit.json").exists()


@pytest.mark.parametrize("argv,words", [
    (["--albedo", "per-pixel"], ["--albedo per-pixel", "no camera noise model", "--conversion-gain"]),
    (["--albedo", "per-pixel-bilinear"], ["--albedo per-pixel-bilinear", "no camera noise model"]),
    (["--intervals", "profile"], ["--intervals profile", "no camera noise model"]),
])
def test_fit_likelihood_options_on_an_input_without_noise_model_refused(capsys, tmp_path, captures, argv, words):
    """A Stokes EXR has no camera noise model: the loss resolves to the paper's.  Before: the option was dropped,
    the fit ran (exit 0) and fit.json recorded it as if applied.  Now refused before the fit, nothing written."""
    rc, _, err = run(capsys, "fit", str(captures / "m.exr"), "-o", str(tmp_path / "out"), "--max-iter", "1",
                     "--starts", "1", "--max-pixels", "100", "-q", *argv)
    one_line_error(rc, err, "fit", *words)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ fit --from: integrity
def _edit(d, tmp_path, what):
    rep = d["reproduce"]
    if what == "inputs":
        rep["arguments"]["inputs"] = str(tmp_path / "other.npy")
    elif what == "relative inputs":
        rep["arguments"]["inputs"] = "other.npy"
    elif what == "mask":
        rep["arguments"]["mask"] = str(tmp_path / "other.npy")
    elif what == "joint input":
        rep["joint"]["images"][1]["spec"]["input"] = str(tmp_path / "other.npy")
    elif what == "joint mask":
        rep["joint"]["images"][0]["spec"]["options"]["mask"] = str(tmp_path / "other.npy")
    elif what == "no hashes":
        del rep["files_sha256"]
    elif what == "refine":
        d.clear()
        d.update({"refine_normals": {"start": "ps"}, "reproduce": {"command": "fmbrdf-mi fit --authors OBJ "
                                                                               "--refine-normals -o out"}})
    elif what == "refine rounds":       # a record of the alternation rounds that --rounds set before the joint step
        d.clear()
        d.update({"refine_normals": {"start": "ps", "rounds": 2, "alternation": []},
                  "reproduce": {"command": "fmbrdf-mi fit --authors OBJ --refine-normals --rounds 2 -o out"}})
    return d


@pytest.mark.parametrize("joint,what,words", [
    (False, "inputs", ["other.npy", "no recorded SHA-256"]),
    (False, "relative inputs", ["other.npy", "no recorded SHA-256"]),
    (False, "mask", ["other.npy", "no recorded SHA-256"]),
    (True, "joint input", ["other.npy", "no recorded SHA-256"]),
    (True, "joint mask", ["other.npy", "no recorded SHA-256"]),
    (False, "no hashes", ["files_sha256", "cannot be verified"]),
    (True, "no hashes", ["files_sha256", "cannot be verified"]),
    (False, "refine", ["--refine-normals are not supported", "reproduce.command"]),
    (False, "refine rounds", ["--refine-normals are not supported", "--rounds 2 -o out)", "without --rounds"]),
])
def test_from_record_that_cannot_be_verified_is_refused(capsys, tmp_path, joint, what, words):
    """Before: a record pointing at another file reran on it (its hash was never recorded), a record
    without files_sha256 reran unverified, a --refine-normals record was 'written by an older fmbrdf-mi?'."""
    import json

    path = tmp_path / "fit.json"
    path.write_text(json.dumps(_edit(fit_record(tmp_path, joint), tmp_path, what)))
    rc, _, err = run(capsys, "fit", "--from", str(path), "-o", str(tmp_path / "out"))
    one_line_error(rc, err, "fit", str(path), *words)
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
