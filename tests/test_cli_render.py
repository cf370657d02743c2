"""``fmbrdf-mi render``: scene files, options, outputs, textures, interrupts and variants.  Each mistake is one
line naming the file or option and what is valid (exit status 1), and a refused or interrupted render leaves
nothing behind.
"""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import one_line_error, run

from fmbrdf_mi.cli import main
from fmbrdf_mi.render import RAW_MIN_SPP


# ---------------------------------------------------------------- scene files
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


# ---------------------------------------------------------------- scene files: binary, directories, empty meshes
def test_binary_xml_scene_names_the_file(capsys, tmp_path):
    """Before: "'utf-8' codec can't decode byte 0x80 in position 128" with no file named."""
    p = tmp_path / "bin.xml"
    p.write_bytes(bytes(range(256)) * 4)
    rc, _, err = run(capsys, "render", "-s", str(p), "--variant", "llvm_ad_mono_polarized", "-q",
                     str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", "bin.xml", "UTF-8")


def test_scene_that_is_a_directory(capsys, tmp_path):
    os.mkdir(tmp_path / "s.xml")
    rc, _, err = run(capsys, "render", "-s", str(tmp_path / "s.xml"), "-q", str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", "s.xml", "is a directory")


EMPTY_PLY_HEADER = "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nelement face 0\n" \
                   "property list uchar int vertex_indices\nend_header\n"


@pytest.mark.parametrize("name,text,words", [
    ("m.ply", "", ["m.ply", "empty (0 bytes)"]),
    ("m.obj", "", ["m.obj", "empty (0 bytes)"]),
    ("m.ply", EMPTY_PLY_HEADER, ["m.ply", "no vertices"]),
    ("m.obj", "# nothing\nvn 0 0 1\n", ["m.obj", "no vertices"]),
])
def test_empty_mesh_in_an_xml_scene(capsys, tmp_path, name, text, words):
    """Before: Mitsuba's "I/O error ... No such file or directory" (the file exists) or "Could not map"."""
    (tmp_path / name).write_text(text)
    kind = name[-3:]
    (tmp_path / "s.xml").write_text(f"""<scene version="3.0.0">
  <integrator type="stokes"><integrator type="direct"/></integrator>
  <sensor type="orthographic"><film type="hdrfilm"><integer name="width" value="8"/>
    <integer name="height" value="8"/></film></sensor>
  <shape type="{kind}" id="mesh"><string name="filename" value="{name}"/><bsdf type="fmbrdf"/></shape>
  <emitter type="directional"><vector name="direction" value="0,0,-1"/></emitter>
</scene>""")
    rc, _, err = run(capsys, "render", "-s", str(tmp_path / "s.xml"), "--variant", "llvm_ad_mono_polarized", "-q",
                     str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", "s.xml", *words)


def test_valid_meshes_pass_the_check(tmp_path):
    from fmbrdf_mi import scene as S

    (tmp_path / "t.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "t.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    for f in ("t.obj", "t.ply"):
        assert S.check_mesh_file(tmp_path / f) == str(tmp_path / f)


# ---------------------------------------------------------------- options and output paths
HUGE = 100000  # 100000 x 100000 pixels: terabytes, more than any machine here


@pytest.mark.parametrize("argv,words", [
    (["--res", str(HUGE)], [f"{HUGE}x{HUGE}", "TiB", "memory"]),
    (["--res", "16000"], ["16000x16000", "GiB", "memory"]),
    (["-D", f"width={HUGE}", "-D", "height=60000"], [f"{HUGE}x60000", "memory"]),
    (["--exposure", "nan"], ["--exposure"]),
    (["--dolp-max", "nan"], ["--dolp-max"]),
    (["--seed", "-1"], ["seed", ">= 0"]),
    (["-D", "distance=-1"], ["distance", "positive"]),
])
def test_render_options_checked_before_work(capsys, tmp_path, monkeypatch, argv, words):
    from fmbrdf_mi import _paths

    # as on a machine with 16 GiB free, so that 16000 x 16000 (about 122 GiB) is refused anywhere
    monkeypatch.setattr(_paths, "available_memory", lambda: 16 << 30)
    rc, _, err = run(capsys, "render", *argv, str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", *words)
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("where", ["under_file", "deeper_under_file", "is_dir"])
def test_render_output_path_problems_name_the_path(capsys, tmp_path, a_file, where):
    """Before: an output under a regular file gave '[Errno 17] File exists' (or a traceback)
    after rendering."""
    out = {"under_file": a_file / "x.exr", "deeper_under_file": a_file / "sub" / "x.exr",
           "is_dir": tmp_path / "d.exr"}[where]
    if where == "is_dir":
        out.mkdir()
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", str(out))
    one_line_error(rc, err, "render", str(a_file) if where != "is_dir" else str(out))
    assert "File exists" not in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_unwritable_output_dir(capsys, tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", str(d / "x.exr"))
        one_line_error(rc, err, "render", str(d), "permission")
        rc, _, err = run(capsys, "dataset", "--config", "x.toml", "--out", str(d / "ds"))
    finally:
        d.chmod(0o700)


@pytest.mark.parametrize("argv,words", [
    (["-D", "light_dir=0,0,-1"], ["light_dir", "behind", "black"]),
    (["-D", "distance=0.5", "-D", "camera=perspective"], ["inside", "black"]),
])
def test_black_image_warns(capsys, tmp_path, argv, words):
    rc, _, err = run(capsys, "render", "--res", "8", "--spp", "1", "-q", *argv, str(tmp_path / "x.exr"))
    assert rc == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fmbrdf-mi render: warning: "), err
    for w in words:
        assert w in lines[0]


def _xml(tmp_path, bsdf_extra="", shape_extra=""):
    p = tmp_path / "s.xml"
    p.write_text(f"""<scene version="3.0.0">
  <integrator type="stokes"><integrator type="direct"/></integrator>
  <sensor type="orthographic"><film type="hdrfilm"><integer name="width" value="8"/>
    <integer name="height" value="8"/></film></sensor>
  <shape type="sphere">{shape_extra}<bsdf type="fmbrdf">{bsdf_extra}</bsdf></shape>
</scene>""")
    return p


@pytest.mark.parametrize("bsdf_extra,shape_extra,words", [
    ('<float name="roughness_of_the_microfacets" value="0.3"/>', "",
     ["unknown property 'roughness_of_the_microfacets'", "alpha"]),
    ("", '<float name="radius_of_the_sphere_in_metres" value="2"/>', ["radius_of_the_sphere_in_metres"]),
    ('<float name="eta" value="0.5"/>', "", ["'eta'", "(1, 3]"]),
])
def test_xml_scene_errors_carry_full_names(capsys, tmp_path, bsdf_extra, shape_extra, words):
    """Before: an unknown fmbrdf property's name was cut off (only the first line of
    Mitsuba's message was shown)."""
    p = _xml(tmp_path, bsdf_extra, shape_extra)
    rc, _, err = run(capsys, "render", "-s", str(p), "--variant", "llvm_ad_mono_polarized", "-q",
                     str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", *words)


# ---------------------------------------------------------------- options the render would ignore
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


# ---------------------------------------------------------------- --raw: the sample count
@pytest.mark.parametrize("extra, raw, want", [
    ([], True, RAW_MIN_SPP),          # --raw without --spp: at least RAW_MIN_SPP
    (["--spp", "2"], True, 2),        # the user's --spp wins
    ([], False, 64),                  # no --raw: the scene's own 64
])
def test_raw_render_sample_count(tmp_path, capsys, extra, raw, want):
    out = tmp_path / "x.exr"
    args = ["render", str(out), "--variant", "llvm_ad_mono_polarized", "--res", "8", "--no-previews",
            *(["--raw"] if raw else []), *extra]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"{want} spp" in printed, printed
    if raw:
        side = json.loads((tmp_path / "x_raw.json").read_text())
        assert side["parameters"]["spp"] == want and side["spp"] == want


# ---------------------------------------------------------------- Ctrl-C
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


# ---------------------------------------------------------------- textures, outputs and variants
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _exr(path, channels):
    """An EXR of float32 ``channels`` {name: (H, W)} written by the OpenEXR package itself."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


def _checker(path):
    tex = np.where((np.arange(4)[:, None] + np.arange(8)[None]) % 2, 0.9, 0.3)
    return _exr(path, {"Y": tex})


def _listing(directory):
    return sorted(os.listdir(directory)) if os.path.isdir(directory) else []


@pytest.mark.skipif(shutil.which("taskset") is None or shutil.which("timeout") is None,
                    reason="needs taskset and timeout (util-linux, coreutils)")
def test_textured_render_pinned_to_one_core(tmp_path):
    """A render with an EXR albedo texture, the process pinned to one CPU (a cluster job's share): it
    finishes (Mitsuba's own EXR reader never returns there) and writes the capture and the true maps."""
    tex = _checker(tmp_path / "ks.exr")
    out = tmp_path / "out.exr"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    cmd = ["timeout", "300", "taskset", "-c", "0", sys.executable, "-m", "fmbrdf_mi", "render", str(out),
           "-D", f"k_s={tex}", "--variant", "llvm_ad_mono_polarized", "--res", "16", "--spp", "2",
           "--no-previews", "-q"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert out.exists() and (tmp_path / "out_k_s.exr").exists()


SCENE_WITH_EXR_TEXTURE = """<scene version="3.0.0">
  <integrator type="stokes"><integrator type="direct"/></integrator>
  <sensor type="orthographic">
    <sampler type="independent"><integer name="sample_count" value="2"/></sampler>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere">
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="ks.exr"/></texture></bsdf>
  </shape>
  <emitter type="constant"/>
</scene>
"""


@pytest.mark.skipif(shutil.which("taskset") is None or shutil.which("timeout") is None,
                    reason="needs taskset and timeout (util-linux, coreutils)")
def test_xml_scene_with_an_exr_texture_on_one_core_is_one_line(tmp_path):
    """An XML scene's bitmap textures are read by Mitsuba itself: pinned to one CPU, an EXR one is refused in
    one line instead of never returning."""
    _checker(tmp_path / "ks.exr")
    (tmp_path / "scene.xml").write_text(SCENE_WITH_EXR_TEXTURE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    cmd = ["timeout", "300", "taskset", "-c", "0", sys.executable, "-m", "fmbrdf_mi", "render",
           str(tmp_path / "out.exr"), "-s", str(tmp_path / "scene.xml"), "--no-previews", "-q"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, (proc.returncode, proc.stderr[-2000:])
    assert "ks.exr" in lines[0] and "one CPU" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "out.exr").exists()


def test_texture_values_are_the_files(tmp_path):
    """The bitmap a texture file becomes holds the file's values: a one-channel and an RGB EXR (written by
    OpenEXR, read back exactly), and an 8-bit PNG (the bytes PIL writes)."""
    from PIL import Image

    from fmbrdf_mi import scene as S

    rng = np.random.default_rng(0)
    grey = rng.uniform(0, 1, (5, 7)).astype(np.float32)
    got = np.asarray(S.texture_bitmap(_exr(tmp_path / "g.exr", {"Y": grey})))
    np.testing.assert_array_equal(got.reshape(5, 7), grey)
    rgb = rng.uniform(0, 1, (3, 5, 7)).astype(np.float32)
    got = np.asarray(S.texture_bitmap(_exr(tmp_path / "c.exr", dict(zip("BGR", rgb[::-1])))))
    np.testing.assert_array_equal(got, np.moveaxis(rgb, 0, -1))     # R, G, B whatever the file's order
    assert S.texture_channels(tmp_path / "g.exr") == 1 and S.texture_channels(tmp_path / "c.exr") == 3
    png = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    Image.fromarray(png).save(tmp_path / "p.png")
    np.testing.assert_array_equal(np.asarray(S.texture_bitmap(tmp_path / "p.png")).reshape(5, 7), png)


def _bad_textures(tmp_path):
    """{name: (path, words of the error)} of texture files that are not usable albedo textures."""
    (tmp_path / "text.png").write_text("not an image\n")
    (tmp_path / "empty.exr").write_bytes(b"")
    big = tmp_path / "big.exr"
    _exr(big, {"Y": np.random.default_rng(1).uniform(0, 1, (256, 256))})
    data = big.read_bytes()
    (tmp_path / "truncated.exr").write_bytes(data[:len(data) // 2])     # header whole, pixels cut
    _exr(tmp_path / "twelve.exr", {f"C{i}": np.full((4, 8), 0.5) for i in range(12)})
    return {"text": ("text.png", ["not a readable image"]),
            "empty": ("empty.exr", ["not a readable EXR"]),
            "truncated": ("truncated.exr", ["not a readable EXR"]),
            "twelve": ("twelve.exr", ["12 channels"])}


@pytest.mark.parametrize("case", ["text", "empty", "truncated", "twelve"])
def test_unusable_texture_files_are_one_line(capsys, tmp_path, case):
    name, words = _bad_textures(tmp_path)[case]
    out = tmp_path / "out" / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "-D", f"k_s={tmp_path / name}", "--res", "16", "--spp", "2", "-q")
    one_line_error(rc, err, "render", "k_s=", name, *words, "one channel (Y) or three (R, G, B)")
    assert _listing(tmp_path / "out") == []


@pytest.mark.parametrize("kind,words", [("dir", ["is a directory"]), ("txt", ["is a file of another kind"]),
                                        ("missing", ["is neither numbers nor an image file"])])
def test_an_albedo_that_is_no_texture_file_says_what_it_is(capsys, tmp_path, kind, words):
    """``-D k_s=PATH`` naming a directory or a file of another type.  Before: "expected numbers"."""
    path = tmp_path / {"dir": "tex", "txt": "tex.txt", "missing": "tex.txt"}[kind]
    if kind == "dir":
        path.mkdir()
    elif kind == "txt":
        path.write_text("0.5\n")
    out = tmp_path / "out" / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "-D", f"k_s={path}", "--res", "16", "--spp", "2", "-q")
    one_line_error(rc, err, "render", f"k_s={path}", *words, ".exr, .png")
    assert _listing(tmp_path / "out") == []


def test_rgb_texture_in_a_spectral_variant_is_one_line(capsys, tmp_path):
    """A spectral variant takes an albedo texture's values raw, so an RGB texture is no albedo there (Mitsuba
    failed mid-render); the monochrome variant renders it (its luminance)."""
    tex = _exr(tmp_path / "rgb.exr", {c: np.full((4, 8), v) for c, v in zip("RGB", (0.9, 0.3, 0.3))})
    out = tmp_path / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "-D", f"k_s={tex}", "--res", "16", "--spp", "2", "-q",
                     "--variant", "llvm_ad_spectral_polarized")
    one_line_error(rc, err, "render", "rgb.exr", "RGB texture", "one-channel", "llvm_ad_mono_polarized")
    assert not out.exists()
    rc, _, err = run(capsys, "render", str(out), "-D", f"k_s={tex}", "--res", "16", "--spp", "2", "-q",
                     "--no-previews", "--variant", "llvm_ad_mono_polarized")
    assert rc == 0 and out.exists(), err


@pytest.mark.parametrize("which", ["exr", "preview"])
def test_render_refuses_to_overwrite_its_own_texture(capsys, tmp_path, which):
    """``render OUT -D k_s=OUT --force`` (or a texture named as one of OUT's previews): refused before
    rendering, the texture untouched."""
    out = tmp_path / "t.exr"
    tex = _checker(out) if which == "exr" else tmp_path / "t_intensity.png"
    if which == "preview":
        from PIL import Image

        Image.fromarray(np.full((4, 8), 128, np.uint8)).save(tex)
    before = tex.read_bytes()
    rc, _, err = run(capsys, "render", str(out), "-D", f"k_s={tex}", "--force", "--res", "16", "--spp", "2", "-q")
    one_line_error(rc, err, "render", "k_s=", tex.name, "also an output")
    assert tex.read_bytes() == before
    assert _listing(tmp_path) == [tex.name]


def test_interrupted_render_leaves_nothing(capsys, tmp_path, monkeypatch):
    """Ctrl-C while the previews are written (the EXR and two PNGs done): exit 130, no output and no
    temporary file left, and an earlier output of the same name kept as it was."""
    from fmbrdf_mi import previews

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(previews, "save_aolp", interrupt)
    out = tmp_path / "out" / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "--res", "16", "--spp", "2", "-q")
    assert rc == 130 and "interrupted" in err
    assert not (tmp_path / "out").exists()          # the directory it made is gone too
    (tmp_path / "out").mkdir()
    out.write_bytes(b"earlier")
    rc, _, err = run(capsys, "render", str(out), "--res", "16", "--spp", "2", "-q", "--force")
    assert rc == 130
    assert _listing(tmp_path / "out") == ["t.exr"] and out.read_bytes() == b"earlier"


def test_interrupted_exr_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    """An EXR writer interrupted after its temporary file is written (before the rename) removes it."""
    from fmbrdf_mi import stokes_io

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(stokes_io.os, "replace", interrupt)
    with pytest.raises(KeyboardInterrupt):
        stokes_io.write_map_exr(tmp_path / "m.exr", np.ones((4, 4)))
    monkeypatch.undo()
    assert _listing(tmp_path) == []


def test_refused_black_capture_leaves_nothing(capsys, tmp_path):
    """``--raw`` with the light behind the sphere: the black image is refused (no exposure to choose), and no
    EXR or preview of it is left behind."""
    out = tmp_path / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "--res", "16", "--spp", "2", "-q", "--raw",
                     "-D", "light_dir=0,0,-1")
    assert rc == 1 and "black" in err and "Traceback" not in err, err
    assert _listing(tmp_path) == []


def test_unsupported_scalar_polarised_variant_says_so():
    """In a scalar polarised variant the plugin cannot run: loading it names the variant and the supported
    ones (not Mitsuba's "plugin not found"), through fmbrdf_mi.load_dict (one line) and mi.load_dict."""
    import mitsuba as mi

    import fmbrdf_mi

    scalar_pol = [v for v in mi.variants() if v.startswith("scalar") and v.endswith("polarized")]
    if not scalar_pol:
        pytest.skip("this Mitsuba build has no scalar polarised variant")
    try:
        mi.set_variant(scalar_pol[0])
        with pytest.raises(ValueError) as e:
            fmbrdf_mi.load_dict({"type": "fmbrdf"})
        msg = str(e.value)
        assert "\n" not in msg and scalar_pol[0] in msg and "not supported" in msg
        assert "llvm_ad_spectral_polarized" in msg and "llvm_ad_mono_polarized" in msg
        with pytest.raises(RuntimeError) as e:
            mi.load_dict({"type": "fmbrdf"})
        assert "not supported" in str(e.value) and "not found" not in str(e.value)
    finally:
        mi.set_variant("llvm_ad_mono_polarized")
    assert fmbrdf_mi.load_dict({"type": "fmbrdf"}) is not None


def test_unsupported_variant_set_before_import_says_so(tmp_path):
    """The variant set before ``import fmbrdf_mi``: the first load says why (a fresh interpreter)."""
    import mitsuba as mi

    scalar_pol = [v for v in mi.variants() if v.startswith("scalar") and v.endswith("polarized")]
    if not scalar_pol:
        pytest.skip("this Mitsuba build has no scalar polarised variant")
    code = (f"import mitsuba as mi; mi.set_variant({scalar_pol[0]!r}); import fmbrdf_mi\n"
            "try:\n    mi.load_dict({'type': 'fmbrdf'})\nexcept RuntimeError as e:\n    print(e)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert "not supported" in proc.stdout and "not found" not in proc.stdout, proc.stdout + proc.stderr


def test_cuda_variant_without_a_device_is_one_line(capsys, tmp_path):
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA device is present")
    out = tmp_path / "t.exr"
    rc, _, err = run(capsys, "render", str(out), "--variant", "cuda_ad_mono_polarized", "--res", "16", "-q")
    one_line_error(rc, err, "render", "cuda_ad_mono_polarized", "no CUDA device", "llvm_ad_mono_polarized")
    assert not out.exists()
