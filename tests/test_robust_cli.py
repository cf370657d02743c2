"""Issue 12, commands and datasets: every option is checked before work starts, operating-
system problems and impossible sizes are one line naming the path or the size, black images
warn, dataset directories are locked per shard and back faces are out of the mask.
Each test failed on the code before the fix."""
import json
import math
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from conftest import one_line_error, run


HUGE = 100000  # 100000 x 100000 pixels: terabytes, more than any machine here


@pytest.fixture
def a_file(tmp_path):
    f = tmp_path / "plain_file"
    f.write_text("not a directory")
    return f


# ------------------------------------------------------------------ render
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


# ------------------------------------------------------------------ fit
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


# ------------------------------------------------------------------ dataset
def _cfg(tmp_path, **over):
    cfg = {"samples": 2, "render": {"resolution": 8, "spp": 1, "variant": "llvm_ad_mono_polarized"}}
    for k, v in over.items():
        cfg.setdefault(k, {}).update(v) if isinstance(v, dict) else cfg.__setitem__(k, v)
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps(cfg))
    return p


@pytest.mark.parametrize("over,words", [
    ({"render": {"resolution": HUGE}}, ["render.resolution", "memory"]),
    ({"samples": 0}, ["samples", ">= 1"]),
])
def test_dataset_config_refused_up_front(capsys, tmp_path, monkeypatch, over, words):
    from fmbrdf_mi import _paths

    monkeypatch.setattr(_paths, "available_memory", lambda: 16 << 30)
    rc, _, err = run(capsys, "dataset", "--config", str(_cfg(tmp_path, **over)), "--out", str(tmp_path / "ds"))
    one_line_error(rc, err, "dataset", *words)
    assert not (tmp_path / "ds").exists()


def test_dataset_out_under_a_file(capsys, tmp_path, a_file):
    rc, _, err = run(capsys, "dataset", "--config", str(_cfg(tmp_path)), "--out", str(a_file / "ds"))
    one_line_error(rc, err, "dataset", str(a_file))


def test_dataset_inclusive_bounds_drawn(tmp_path):
    """Before: a dataset drawing alpha = 0.01 (or pi/2) was refused by the BSDF's update
    (float32 rounding), and loguniform could draw exp(log(0.01)) < 0.01."""
    from fmbrdf_mi.dataset import generate, read_sample

    cfg = json.loads(_cfg(tmp_path).read_text())
    cfg["material"] = {"alpha": {"choice": [0.01, 0.5 * math.pi]}, "beta": {"loguniform": [0.4, 0.4]}}
    cfg["samples"] = 4
    generate(cfg, tmp_path / "ds", progress=False)
    alphas = {read_sample(tmp_path / "ds", i)["label"]["material"]["alpha"] for i in range(4)}
    assert alphas <= {0.01, 0.5 * math.pi} and alphas


def _write_lock(out, k, n, pid, host=None):
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f".lock.shard-{k}-of-{n}"), "w") as f:
        json.dump({"pid": pid, "host": host or socket.gethostname(), "shard": f"{k}/{n}",
                   "started": "2026-01-01T00:00:00"}, f)


@pytest.mark.parametrize("held,mine,refused", [
    ((0, 1), None, True), ((0, 2), None, True), ((0, 2), "0/2", True), ((0, 2), "1/2", False),
    ((1, 3), "0/3", False),
])
def test_dataset_lock_per_shard(capsys, tmp_path, held, mine, refused):
    """Before: two generators on one directory silently rendered the same samples twice."""
    out = tmp_path / "ds"
    _write_lock(out, *held, pid=os.getppid())  # a live process on this host
    argv = ["dataset", "--config", str(_cfg(tmp_path)), "--out", str(out), "-q"]
    rc, _, err = run(capsys, *argv, *(["--shard", mine] if mine else []))
    if refused:
        one_line_error(rc, err, "dataset", f"pid {os.getppid()}", socket.gethostname(), "2026-01-01",
                       f".lock.shard-{held[0]}-of-{held[1]}")
        assert not os.path.exists(out / "samples" / "000000.json")
    else:
        assert rc == 0, err
        assert not os.path.exists(out / f".lock.shard-{mine.replace('/', '-of-')}")  # released


def test_dataset_stale_lock_is_taken_over(capsys, tmp_path):
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()  # its pid is now free: the lock is stale
    out = tmp_path / "ds"
    _write_lock(out, 0, 1, pid=p.pid)
    rc, _, err = run(capsys, "dataset", "--config", str(_cfg(tmp_path)), "--out", str(out), "-q")
    assert rc == 0, err
    assert os.path.exists(out / "manifest.jsonl") and not os.path.exists(out / ".lock.shard-0-of-1")


def test_dataset_back_faces_not_in_mask(tmp_path):
    """The open cylinder seen along its axis: its inner surface faces away from the camera.
    Before: those pixels were in the mask with normals facing away (about a third of it)."""
    from fmbrdf_mi.dataset import generate, read_sample

    cfg = json.loads(_cfg(tmp_path).read_text())
    cfg["render"]["resolution"] = 32
    cfg["samples"] = 1
    cfg["shape"] = {"type": "cylinder"}
    cfg["camera"] = {"elevation": 0.0, "azimuth": 20.0}  # nearly along the axis (+z): sees inside
    generate(cfg, tmp_path / "ds", progress=False)
    s = read_sample(tmp_path / "ds", 0)
    n, m = s["normal"], s["mask"]
    assert m.any() and s["label"]["shape"]["back_face_pixels"] > 0
    # orthographic camera: every pixel looks along -z of the camera frame
    assert np.all(n[m][:, 2] > 0)
    assert np.all(n[~m] == 0)


# ---------------------------------------------------------------- fit-brdf: batch options with one file
def test_fit_brdf_force_with_skip_existing_refused(capsys, tmp_path):
    """Before: both taken, --force winning silently for one file and overwriting for a batch."""
    rc, _, err = run(capsys, "fit-brdf", str(tmp_path / "missing.binary"), "--force", "--skip-existing")
    one_line_error(rc, err, "fit-brdf", "--force and --skip-existing")


def _fitted(tmp_path):
    """A MERL file name and its output directory holding a params.json (an earlier fit)."""
    path = tmp_path / "gold.binary"
    path.write_bytes(b"")
    out = tmp_path / "gold_fit"
    out.mkdir()
    report = {"params": {"eta": 1.5, "alpha": 0.2, "beta": 1.0, "kappa": 3.0, "k_s": [1, 1, 1], "k_b": [1, 1, 1]},
              "at_bound": [], "log10_rmse": {"all_usable_bins": 0.1}, "n_usable_bins": 10}
    (out / "params.json").write_text(json.dumps(report))
    return path, out


def test_fit_brdf_skip_existing_with_one_file_skips_it(capsys, tmp_path):
    """Before: one FILE with --skip-existing was refused as existing (pass --force) although its fit exists."""
    path, out = _fitted(tmp_path)
    stamp = os.stat(out / "params.json").st_mtime_ns
    rc, stdout, err = run(capsys, "fit-brdf", str(path), "--skip-existing", "-q")
    assert rc == 0, err
    assert "gold: eta 1.5" in stdout and "skipped" in stdout and os.stat(out / "params.json").st_mtime_ns == stamp


def test_fit_brdf_jobs_with_one_file_says_what_it_does(capsys, tmp_path):
    """Before: --jobs dropped silently with one FILE; now one line says it is fitted in this process."""
    path, _ = _fitted(tmp_path)
    rc, _, err = run(capsys, "fit-brdf", str(path), "--skip-existing", "--jobs", "3", "-q")
    assert rc == 0 and "--jobs 3: one FILE is fitted in this process" in err
