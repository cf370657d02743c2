"""Issue 24, "tracebacks instead of one line": a render scene without a sensor, Ctrl-C during a render,
plugin dicts Mitsuba would crash on (None segfaulted), dataset configs and directories of the wrong type.
Each test failed on the code before the fix (a traceback, a segfault or exit status 1 instead of 130)."""
import json
import os
import subprocess
import sys

import pytest

from conftest import one_line_error, run



# ------------------------------------------------------------------ render
NO_SENSOR = """<scene version="3.0.0">
  <integrator type="stokes"><integrator type="direct"/></integrator>
  <shape type="sphere"><bsdf type="fmbrdf"/></shape>
  <emitter type="directional"><vector name="direction" value="0,0,-1"/></emitter>
</scene>"""


@pytest.mark.parametrize("extra", [[], ["--res", "16"], ["--spp", "2"]])
def test_xml_scene_without_a_sensor(capsys, tmp_path, extra):
    """Before: IndexError from scene.sensors()[0] (or, with --res, 'has no width/height parameters')."""
    p = tmp_path / "nosensor.xml"
    p.write_text(NO_SENSOR)
    rc, _, err = run(capsys, "render", "-s", str(p), "--variant", "llvm_ad_mono_polarized", "-q", *extra,
                     str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", str(p), "no <sensor>")
    assert sorted(os.listdir(tmp_path)) == ["nosensor.xml"]


def test_render_stokes_without_a_sensor(variant):
    from fmbrdf_mi import scene as S

    mi = variant
    sc = mi.load_dict({"type": "scene", "integrator": {"type": "stokes", "nested": {"type": "direct"}}})
    with pytest.raises(ValueError, match="no sensor"):
        S.render_stokes(sc, progress=False)


def test_ctrl_c_during_render_is_interrupted_130(capsys, tmp_path, monkeypatch):
    """A KeyboardInterrupt inside Dr.Jit's render operation (where Ctrl-C lands while the Python BSDF
    runs) arrives as RuntimeError('drjit.custom(...)'); before, the command printed that traceback
    and exited 1."""
    from mitsuba.python import util

    def eval_(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(util._RenderOp, "eval", eval_)
    out = tmp_path / "x.exr"
    rc, _, err = run(capsys, "render", "--variant", "llvm_ad_mono_polarized", "--res", "8", "--spp", "1", "-q",
                     str(out))
    assert rc == 130, err
    assert err.strip().splitlines()[-1] == "fmbrdf-mi render: interrupted"
    assert "Traceback" not in err and "drjit.custom" not in err
    assert not os.listdir(tmp_path)


def test_interrupted_sees_through_the_wrapping():
    from fmbrdf_mi.interrupt import interrupted

    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("drjit.custom(<_RenderOp>): error while performing a custom operation") from e
    except RuntimeError as e:
        assert interrupted(e)
    assert not interrupted(RuntimeError("something else"))
    assert interrupted(KeyboardInterrupt())


# ------------------------------------------------------------------ load_dict
@pytest.mark.parametrize("d,words", [
    ({"type": "fmbrdf", "eta": None}, ["fmbrdf", "'eta' is None"]),
    ({"type": "fmbrdf", "k_s": None}, ["'k_s' is None"]),
    ({"type": "scene", "s": {"type": "sphere", "bsdf": {"type": "fmbrdf", "alpha": None}}},
     ["s.bsdf", "'alpha' is None"]),
    ({"type": "orennayar", "sigma": None}, ["orennayar", "'sigma' is None"]),
    ({"type": "diffuse", "reflectance": None}, ["diffuse", "'reflectance' is None"]),
])
def test_load_dict_refuses_none_instead_of_segfaulting(d, words):
    """Before: mi.load_dict segfaulted (exit -11), taking the Python process with it: run in a child."""
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_mono_polarized'); import fmbrdf_mi\n"
            "try:\n"
            f"    fmbrdf_mi.load_dict({d!r})\n"
            "except fmbrdf_mi.ParameterError as e:\n"
            "    print('REFUSED', e)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    line = p.stdout.strip().splitlines()[-1]
    assert line.startswith("REFUSED ")
    for w in words:
        assert w in line, (w, line)


@pytest.mark.parametrize("d,words", [
    ({"type": "fmbrdf", "eta": [1, 2]}, ["'eta' must be a number"]),
    ({"type": "fmbrdf", "eta": "abc"}, ["'eta'", "must be a number"]),
    ({"type": "fmbrdf", "eta": True}, ["'eta' must be a number"]),
    ({"type": "fmbrdf", "kappa": float("nan")}, ["'kappa'", "valid range"]),
    ({"type": "fmbrdf", "k_s": "abc"}, ["'k_s' must be a number >= 0", "texture"]),
    ({"type": "fmbrdf", "k_b": [0.5, 0.5, 0.5]}, ["'k_b' must be a number >= 0", "'rgb'"]),
    ({"type": "fmbrdf", "r_k": float("nan")}, ["'r_k'", ">= 0"]),
    ({"type": "fmbrdf", "tables": 5}, ["'tables' must be text"]),
    ({"type": "orennayar", "reflectance": "x"}, ["orennayar", "'reflectance'"]),
    ({"type": "orennayar", "sigma": [0.3]}, ["orennayar", "'sigma' must be a number"]),
])
def test_load_dict_refuses_values_mitsuba_reports_with_a_traceback(variant, d, words):
    """Before: RuntimeError with Mitsuba's multi-line message (lists, k_s as a word)."""
    import fmbrdf_mi

    with pytest.raises(fmbrdf_mi.ParameterError) as e:
        fmbrdf_mi.load_dict(d)
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_load_dict_still_takes_numeric_text_and_textures(variant):
    import fmbrdf_mi

    fmbrdf_mi.load_dict({"type": "fmbrdf", "eta": "1.5", "k_b": {"type": "rgb", "value": [0.1, 0.2, 0.3]}})


# ------------------------------------------------------------------ dataset
def test_dataset_api_config_and_out_of_the_wrong_type(tmp_path):
    """Before: TypeError from os.fspath / 'dictionary update sequence element' for a list."""
    from fmbrdf_mi import dataset

    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"samples": 1}))
    for call in (lambda: dataset.generate([str(cfg)], tmp_path / "out"),
                 lambda: dataset.load_config([str(cfg)]),
                 lambda: dataset.read_config_file([str(cfg)]),
                 lambda: dataset.load_config({"samples": 1}, base_dir=[str(tmp_path)])):
        with pytest.raises(dataset.DatasetConfigError) as e:
            call()
        assert "expected" in str(e.value) and ("config" in str(e.value) or "base_dir" in str(e.value))
    with pytest.raises(ValueError, match="out: expected a directory name"):
        dataset.generate(str(cfg), [str(tmp_path / "out")])
    assert sorted(os.listdir(tmp_path)) == ["c.json"]


@pytest.mark.parametrize("shape", [["sphere"], {"choice": [["a.ply"]]}])
def test_dataset_config_list_where_a_mesh_path_is_expected(capsys, tmp_path, shape):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"samples": 1, "shape": {"type": shape}}))
    rc, _, err = run(capsys, "dataset", "--config", str(cfg), "--out", str(tmp_path / "ds"))
    one_line_error(rc, err, "dataset", "shape.type", ".ply/.obj")
    assert not (tmp_path / "ds").exists()
