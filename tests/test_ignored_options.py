"""Issue 24, "Options and files silently ignored" and "--from integrity": an option the
command would ignore, or a fit.json whose rerun cannot be verified, is refused in one line
naming it (exit status 1, no traceback, nothing written).  Each test failed on the code
before the fix: the option was dropped and the command ran, or the rerun read files no
hash covered."""
import os

import pytest

from fmbrdf_mi import cli


def run(capsys, *argv):
    rc = cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def one_line_error(rc, err, command, *words):
    assert rc == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"fmbrdf-mi {command}: error: ") and "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


# ------------------------------------------------------------------ render
@pytest.mark.parametrize("argv,words", [
    (["--sensor", "colour"], ["--sensor colour", "--raw"]),
    (["--raw", "--cfa", "BGGR"], ["--cfa BGGR", "--sensor colour"]),
    (["--cfa", "RGGB"], ["--cfa RGGB", "--sensor colour"]),
    (["--variant", "llvm_ad_mono_polarized", "-D", "k_s=1,0.5,0.2"], ["k_s=1,0.5,0.2", "RGB", "mono"]),
    (["--variant", "llvm_ad_mono_polarized", "-D", "r_k=0.2,0.5,1"], ["r_k=0.2,0.5,1", "RGB"]),
])
def test_render_ignored_options_refused(capsys, tmp_path, argv, words):
    """Before: the EXR was written, the option dropped (no raw mosaic, the mono sensor, the RGB
    albedo averaged by the mono variant)."""
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", *argv, str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", *words)
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("argv", [
    ["--raw", "--sensor", "colour", "--cfa", "BGGR"],
    ["--variant", "llvm_ad_mono_polarized", "-D", "k_s=0.5"],
    ["-D", "k_s=1,0.5,0.2"],
])
def test_render_valid_camera_options_still_run(capsys, tmp_path, argv):
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", "--no-previews", *argv,
                     str(tmp_path / "x.exr"))
    assert rc == 0, err
    assert (tmp_path / "x.exr").exists()
