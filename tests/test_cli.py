"""The fmbrdf-mi command line: mistakes give one clear line and a non-zero exit;
a render writes a readable Stokes EXR with its metadata and the previews."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fmbrdf_mi import cli, stokes_io

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPHERES = os.path.join(ROOT, "scenes", "spheres.xml")


def run(capsys, *argv):
    rc = cli.main(["render", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_line_error(rc, err, *words):
    assert rc != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("fmbrdf-mi render: error: ")
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


@pytest.mark.parametrize("argv, words", [
    (["-s", "no/such/scene.xml"], ["no/such/scene.xml", "not found"]),
    (["-D", "roughness=0.2"], ["unknown parameter 'roughness'", "eta"]),
    (["-s", SPHERES, "-D", "eta=1.6"], ["unknown parameter 'eta'", "eta_0"]),
    (["-D", "eta=0.9"], ["'eta'", "0.9", "(1, 3]"]),
    (["-s", SPHERES, "-D", "kappa_2=200"], ["'kappa'", "[0, 100]"]),
    (["-D", "alpha=abc"], ["'alpha'", "abc"]),
    (["-D", "k_s=-1"], ["'k_s'", ">= 0"]),
    (["-D", "light_dir=0,0,0"], ["light_dir", "zero"]),
    (["-D", "light_dir=1,2"], ["light_dir", "3 number"]),
    (["-D", "camera=fisheye"], ["camera", "orthographic"]),
    (["-D", "eta"], ["NAME=VALUE"]),
    (["--res", "0"], ["--res"]),
    (["--spp", "0"], ["spp", ">= 1"]),
])
def test_bad_arguments_are_rejected(capsys, tmp_path, argv, words):
    rc, _, err = run(capsys, *argv, str(tmp_path / "x.exr"))
    assert_one_line_error(rc, err, *words)
    assert not os.listdir(tmp_path)


def test_output_must_be_exr_and_not_exist(capsys, tmp_path):
    rc, _, err = run(capsys, str(tmp_path / "x.png"))
    assert_one_line_error(rc, err, ".exr")
    out = tmp_path / "x.exr"
    out.write_bytes(b"keep me")
    rc, _, err = run(capsys, str(out))
    assert_one_line_error(rc, err, "x.exr exists", "--force")
    (tmp_path / "y_dolp.png").write_bytes(b"keep me")  # a preview counts too
    rc, _, err = run(capsys, str(tmp_path / "y.exr"))
    assert_one_line_error(rc, err, "y_dolp.png exists")
    assert out.read_bytes() == b"keep me"
    rc, _, err = run(capsys)
    assert_one_line_error(rc, err, "no output")


def test_list_params(capsys):
    rc, out, _ = run(capsys, "--list-params")
    assert rc == 0 and "eta" in out and "light_dir" in out and "orthographic" in out
    rc, out, _ = run(capsys, "--list-params", "-s", SPHERES)
    assert rc == 0 and "alpha_2" in out and "0.6" in out


def test_no_subcommand_prints_help(capsys):
    assert cli.main([]) == 2
    assert "render" in capsys.readouterr().err


def test_render_xml_scene_mono(capsys, tmp_path):
    out = tmp_path / "s.exr"
    rc, stdout, err = run(capsys, "-s", SPHERES, "--variant", "llvm_ad_mono_polarized", "--res", "24x8",
                          "--spp", "4", "-D", "alpha_1=0.5", "-q", str(out))
    assert rc == 0, err
    stokes, meta = stokes_io.read_stokes_exr(out)
    assert stokes.shape == (4, 8, 24, 1) and stokes.dtype == np.float32
    assert meta["variant"] == "llvm_ad_mono_polarized" and meta["spp"] == 4
    assert meta["parameters"]["alpha_1"] == 0.5 and meta["parameters"]["eta_2"] == 2.0
    assert abs(meta["materials"]["sphere_1"]["alpha"] - 0.5) < 1e-6
    assert "<scene" in meta["scene_xml"] and meta["resolution"] == [24, 8]
    for kind in ("intensity", "dolp", "aolp"):
        assert (tmp_path / f"s_{kind}.png").stat().st_size > 0
    assert "wrote" in stdout


def test_python_m_render_default_scene(tmp_path):
    """The real entry point, in the default (spectral) variant, with all previews."""
    out = tmp_path / "sub" / "sphere.exr"
    cmd = [sys.executable, "-m", "fmbrdf_mi", "render", str(out), "--res", "24", "--spp", "4",
           "--angles", "--mosaic", "--aolp-dolp", "-D", "eta=1.6", "-D", "light_dir=0,0.5,1"]
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    stokes, meta = stokes_io.read_stokes_exr(out)
    assert stokes.shape == (4, 24, 24, 3)
    assert stokes[0].max() > 0.1 and np.all(stokes[0] >= 0)
    assert meta["scene"] == "builtin:sphere" and meta["variant"] == "llvm_ad_spectral_polarized"
    assert meta["materials"]["sphere"]["eta"] == pytest.approx(1.6)
    assert np.allclose(meta["parameters"]["light_dir"], np.array([0, 0.5, 1]) / np.sqrt(1.25))
    assert np.allclose(meta["lights"][0]["light_dir"], np.array([0, 0.5, 1]) / np.sqrt(1.25), atol=1e-6)
    assert meta["camera"]["type"] == "OrthographicCamera" and meta["fmbrdf_mi_version"]
    json.dumps(meta)
    # plain OpenEXR sees named float32 channels
    import OpenEXR

    with OpenEXR.File(str(out), separate_channels=True) as f:
        ch = f.channels()
        assert {f"S{k}.{c}" for k in range(4) for c in "RGB"} <= set(ch)
        assert ch["S0.G"].pixels.dtype == np.float32
    for kind in ("intensity", "dolp", "aolp", "angles", "mosaic"):
        assert (tmp_path / "sub" / f"sphere_{kind}.png").stat().st_size > 0
    # again: refused without --force, through the real entry point too
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(tmp_path))
    assert p.returncode == 1 and "exists" in p.stderr and "Traceback" not in p.stderr
