"""Synthetic datasets (fmbrdf_mi.dataset): determinism, resume, shards, labels vs images, config errors, locks
per shard, back faces out of the mask, configs and paths refused in one line.

One small dataset (6 samples: spheres, a cube and an .obj mesh, orthographic and
perspective cameras, random rotations, RGB body colours) is rendered once per
module and compared with a second run in another process, with shards and with
an interrupted-then-resumed run.
"""
import copy
import filecmp
import io
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from fmbrdf_mi.dataset import DatasetConfigError, generate, load_config, read_sample
from fmbrdf_mi.stokes_io import read_stokes_exr

from conftest import one_line_error, run

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

OCTAHEDRON = """\
v 1 0 0
v -1 0 0
v 0 1 0
v 0 -1 0
v 0 0 1
v 0 0 -1
f 1 3 5
f 3 2 5
f 2 4 5
f 4 1 5
f 3 1 6
f 2 3 6
f 4 2 6
f 1 4 6
"""

# seed 4 draws: octa.obj/persp, cube/persp, sphere/persp, sphere/persp, cube/ortho, sphere/ortho
CONFIG = {
    "samples": 6, "seed": 4,
    "render": {"resolution": [24, 20], "spp": 4},
    "shape": {"type": {"choice": ["sphere", "cube", "octa.obj"]}, "rotate": True},
    "camera": {"type": {"choice": ["orthographic", "perspective"]}, "elevation": {"uniform": [-60, 60]},
               "azimuth": {"uniform": [-180, 180]}, "fov": {"uniform": [22, 30]},
               "distance": {"uniform": [4, 6]}},
    "light": {"direction": {"cone": {"axis": [0, 0, 1], "angle": 70}}, "irradiance": {"loguniform": [1, 5]}},
    "material": {"eta": {"uniform": [1.2, 2.5]}, "alpha": {"loguniform": [0.05, 1.0]},
                 "beta": {"choice": [1.0, 2.0, 3.0]}, "kappa": {"uniform": [0, 80]},
                 "k_s": {"uniform": [0.3, 1.0]},
                 "k_b": [{"uniform": [0, 1]}, {"uniform": [0, 1]}, {"uniform": [0, 1]}]},
}


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _cli(config_path, out, *extra):
    return [sys.executable, "-m", "fmbrdf_mi", "dataset", "--config", str(config_path), "--out", str(out), *extra]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(config path, directory of the whole dataset, its progress output)."""
    d = tmp_path_factory.mktemp("dataset")
    (d / "octa.obj").write_text(OCTAHEDRON)
    cfg_path = d / "config.json"
    cfg_path.write_text(json.dumps(CONFIG))
    stream = io.StringIO()
    summary = generate(cfg_path, d / "whole", stream=stream)
    assert summary["rendered"] == 6 and summary["complete"]
    return cfg_path, d / "whole", stream.getvalue()


def _files(*dirs):
    """{relative path: directory} of every file under dirs (asserting they are disjoint)."""
    out = {}
    for d in dirs:
        for root, _, names in os.walk(d):
            for n in names:
                rel = os.path.relpath(os.path.join(root, n), d)
                if rel.startswith("manifest") or rel == "dataset.json":
                    continue
                assert rel not in out, f"{rel} in two directories"
                out[rel] = d
    return out


def _assert_same_samples(a, b_dirs):
    fa, fb = _files(a), _files(*b_dirs)
    assert sorted(fa) == sorted(fb)
    for rel in fa:
        pa, pb = os.path.join(a, rel), os.path.join(fb[rel], rel)
        if rel.endswith(".exr") and not filecmp.cmp(pa, pb, shallow=False):
            # allowed: last-bit differences of parallel accumulation (relative 1e-6);
            # measured: the EXRs were byte-identical in every run so far
            x, mx = read_stokes_exr(pa)
            y, my = read_stokes_exr(pb)
            assert mx == my
            np.testing.assert_allclose(x, y, rtol=1e-6, atol=0)
        else:
            assert filecmp.cmp(pa, pb, shallow=False), f"{rel} differs"


def test_determinism_two_runs(setup, tmp_path):
    """A second run in another process (through the command line) gives the same bytes."""
    cfg_path, whole, _ = setup
    r = subprocess.run(_cli(cfg_path, tmp_path / "again", "-q"), env=_env(), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    assert "6 samples rendered" in r.stdout
    _assert_same_samples(whole, [tmp_path / "again"])
    for name in ("manifest.jsonl", "dataset.json"):
        assert filecmp.cmp(whole / name, tmp_path / "again" / name, shallow=False)


def test_shards_union_equals_whole(setup, tmp_path):
    cfg_path, whole, _ = setup
    dirs = [tmp_path / f"s{k}" for k in range(2)]
    for k, d in enumerate(dirs):
        s = generate(cfg_path, d, shard=f"{k}/2", progress=False)
        assert s["rendered"] == 3 and not s["complete"]
        assert not (d / "manifest.jsonl").exists()
    _assert_same_samples(whole, dirs)  # disjoint, and together the whole set
    lines = []
    for k, d in enumerate(dirs):
        lines += (d / f"manifest.shard-{k}-of-2.jsonl").read_text().splitlines()
    whole_lines = (whole / "manifest.jsonl").read_text().splitlines()
    assert sorted(lines) == sorted(whole_lines) and len(whole_lines) == 6


def test_resume_after_interruption(setup, tmp_path):
    """Kill a run after two samples, leave a stray temporary file, rerun: finished
    samples are kept as they were, the set equals an uninterrupted run."""
    cfg_path, whole, _ = setup
    out = tmp_path / "resumed"
    proc = subprocess.Popen(_cli(cfg_path, out), env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    labels = []
    t0 = time.time()
    while proc.poll() is None and time.time() - t0 < 300:
        labels = sorted((out / "samples").glob("[0-9]*.json")) if (out / "samples").is_dir() else []
        if len(labels) >= 2:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = sorted(p.name[:-5] for p in (out / "samples").glob("[0-9]*.json"))
    assert 2 <= len(done) < 6, f"the run was not interrupted mid-way ({len(done)} samples done)"
    stamps = {p: (p.stat().st_ino, p.stat().st_mtime_ns)
              for sid in done for p in (out / "samples").glob(f"{sid}.*")}
    assert len(stamps) == 4 * len(done)
    todo = [i for i in range(6) if f"{i:06d}" not in done]
    stray = out / "samples" / f".{todo[-1]:06d}.json.tmp999999"
    stray.write_text('{"half": ')

    s = generate(cfg_path, out, progress=False)
    assert s["rendered"] == 6 - len(done) and s["skipped"] == len(done)
    for p, st in stamps.items():
        assert (p.stat().st_ino, p.stat().st_mtime_ns) == st, f"{p.name} was rewritten"
    assert not stray.exists()
    assert not [p for p in (out / "samples").iterdir() if p.name.startswith(".")]
    _assert_same_samples(whole, [out])
    assert filecmp.cmp(whole / "manifest.jsonl", out / "manifest.jsonl", shallow=False)
    # a third run has nothing to do
    assert generate(cfg_path, out, progress=False)["rendered"] == 0


def test_resume_refuses_another_config(setup, tmp_path):
    cfg_path, whole, _ = setup
    other = copy.deepcopy(CONFIG)
    other["seed"] = 5
    with pytest.raises(ValueError, match="different config"):
        generate(other, whole, base_dir=cfg_path.parent, progress=False)


def test_progress_and_summary(setup):
    _, _, text = setup
    assert "samples/s" in text and "left" in text
    assert "done: rendered 6 samples" in text and "manifest.jsonl lists all 6" in text


def test_labels_and_files(setup):
    cfg_path, whole, _ = setup
    manifest = [json.loads(x) for x in (whole / "manifest.jsonl").read_text().splitlines()]
    assert [m["index"] for m in manifest] == list(range(6))
    cfg = load_config(cfg_path)
    for m in manifest:
        s = read_sample(whole, m["index"])
        assert s["label"] == m
        draw = cfg.draw(m["index"])
        assert s["label"]["material"] == draw["material"] and s["label"]["render"]["seed"] == draw["render_seed"]
        _, meta = read_stokes_exr(whole / m["files"]["stokes"])
        assert meta == m
        st, n, mask = s["stokes"], s["normal"], s["mask"]
        assert st.shape == (4, 20, 24, 3) and n.shape == (20, 24, 3) and n.dtype == np.float32
        assert mask.any() and not mask.all()
        np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1.0, atol=1e-5)
        assert np.all(n[~mask] == 0)
        # the shape is lit and seen: some pixels inside the mask are bright
        assert st[0][mask].max() > 0
    assert {m["shape"]["type"] for m in manifest} == {"sphere", "cube", "octa.obj"}


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_sphere_normals_match_geometry(setup, camera):
    """Normal maps and masks of spheres agree with ray-sphere intersections (camera frame)."""
    _, whole, _ = setup
    labels = [read_sample(whole, i)["label"] for i in range(6)]
    idx = [lab["index"] for lab in labels if lab["shape"]["type"] == "sphere" and lab["camera"]["type"] == camera]
    assert idx
    for i in idx:
        s = read_sample(whole, i)
        cam = s["label"]["camera"]
        w, h = cam["resolution"]
        hw = cam["distance"] * math.tan(math.radians(cam["fov"]) / 2)
        x = (2 * (np.arange(w) + 0.5) / w - 1) * hw
        y = (1 - 2 * (np.arange(h) + 0.5) / h) * hw * h / w
        X, Y = np.meshgrid(x, y)
        if camera == "orthographic":
            o = np.stack([X, Y, np.full_like(X, cam["distance"])], -1)
            d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
        else:
            o = np.broadcast_to([0.0, 0.0, cam["distance"]], X.shape + (3,))
            d = np.stack([X, Y, np.full_like(X, -cam["distance"])], -1)
            d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        b = np.sum(o * d, -1)
        disc = b * b - (np.sum(o * o, -1) - 1.0)
        hit = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        n = o + t[..., None] * d
        sure = np.abs(disc) > 1e-3  # away from the rim
        assert np.array_equal(s["mask"][sure], hit[sure])
        both = hit & s["mask"] & sure
        np.testing.assert_allclose(s["normal"][both], n[both], atol=2e-3)


def _mueller_mono(material, L, V):
    """Mueller matrices (4, 4) of the fmbrdf BSDF of ``material`` for light L and view V in the
    local frame, one per body albedo in material["k_b"], from the monochrome polarised variant."""
    import mitsuba as mi

    from _common import eval_mueller

    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi

    fmbrdf_mi.register()
    bsdf = mi.load_dict({"type": "fmbrdf", "eta": material["eta"], "alpha": material["alpha"],
                         "beta": material["beta"], "kappa": material["kappa"],
                         "k_s": material["k_s"],
                         # its own object: in a dict, Mitsuba merges textures equal to k_s
                         "k_b": mi.load_dict({"type": "uniform", "value": 1.0})})
    params = mi.traverse(bsdf)
    out = []
    for k_b in material["k_b"]:
        params["k_b.value"] = k_b  # an albedo: no table rebuild
        params.update()
        out.append(eval_mueller(bsdf, L[None], V[None])[0][0])
    return out


def test_label_reproduces_centre_pixel(tmp_path):
    """Re-evaluating the BSDF from a sample's label at its centre pixel gives the rendered pixel.

    Rotated cubes seen head-on by an orthographic camera with a narrow field of
    view: the centre pixel lies on one flat face, so the normal, view and light
    directions are the same over the whole pixel and its expected value is exactly
    E * M00 (M the BSDF's Mueller matrix from the label).  What remains is Monte
    Carlo noise of the spectral rendering (wavelength sampling; about 35 % per
    path for saturated colours), estimated from the 3x3 pixels around the centre,
    which all see the same face: the tolerance is 5 sigma of one pixel plus 0.5 %
    for the RGB -> spectrum -> RGB round trip of the body colour (measured 0.1 %).
    """
    cfg = {"samples": 4, "seed": 11, "render": {"resolution": 9, "spp": 4096},
           "shape": {"type": "cube", "rotate": True},
           "camera": {"fov": 3.0, "elevation": {"uniform": [-30, 30]}, "azimuth": {"uniform": [-90, 90]}},
           "light": {"direction": {"cone": {"axis": [0, 0, 1], "angle": 60}}, "irradiance": {"uniform": [1, 4]}},
           "material": {"eta": {"uniform": [1.3, 2.0]}, "alpha": {"uniform": [0.1, 0.8]},
                        "beta": {"uniform": [1, 3]}, "kappa": {"uniform": [0, 50]},
                        "k_s": {"uniform": [0.5, 1.0]},
                        "k_b": [{"uniform": [0.1, 0.9]}, {"uniform": [0.1, 0.9]}, {"uniform": [0.1, 0.9]}]}}
    generate(cfg, tmp_path, progress=False)
    checked = 0
    for i in range(4):
        s = read_sample(tmp_path, i)
        lab, st, nmap = s["label"], s["stokes"], s["normal"]
        patch = nmap[3:6, 3:6].reshape(-1, 3)
        if not (s["mask"][3:6, 3:6].all() and np.allclose(patch, patch[0], atol=1e-5)):
            continue  # an edge of the cube crosses the centre: not one flat face
        n = nmap[4, 4].astype(np.float64)
        V = np.array([0.0, 0.0, 1.0])  # orthographic: towards the camera everywhere
        L = np.array(lab["light"]["direction"])
        t = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t /= np.linalg.norm(t)
        frame = np.stack([t, np.cross(n, t), n])  # rows: local x, y, z
        E = lab["light"]["irradiance"]
        for c, M in enumerate(_mueller_mono(lab["material"], frame @ L, frame @ V)):
            s0 = E * M[0, 0]
            dolp = math.hypot(M[1, 0], M[2, 0]) / M[0, 0]
            px = st[:, 3:6, 3:6, c].reshape(4, -1)
            px_dolp = np.hypot(px[1], px[2]) / px[0]
            sigma = px[0].std(ddof=1)
            assert sigma < 0.03 * s0, "noise estimate implausibly large"
            assert abs(st[0, 4, 4, c] - s0) <= 5 * sigma + 0.005 * s0, (i, c, st[0, 4, 4, c], s0, sigma)
            assert abs(px_dolp[4] - dolp) <= 5 * px_dolp.std(ddof=1) + 0.005 * dolp + 1e-4, (i, c)
        checked += 1
    assert checked >= 2


# ------------------------------------------------------------------ configuration errors
def _with(path, value):
    cfg = copy.deepcopy(CONFIG)
    node = cfg
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return cfg


_DELETE = object()


@pytest.mark.parametrize("path,value,message", [
    ("material.eta", {"uniform": [1.2, 3.5]}, "material.eta.uniform: high 3.5 outside (1, 3]"),
    ("material.eta", 1.0, "material.eta: 1 outside (1, 3]"),
    ("material.alpha", {"loguniform": [0.0, 0.5]}, "material.alpha.loguniform: low 0 outside [0.01, 1.5708]"),
    ("material.beta", {"choice": [1.0, 9.0]}, "material.beta.choice[1]: 9 outside [0.4, 5]"),
    ("material.kappa", {"uniform": [50, 10]}, "material.kappa.uniform: low 50 > high 10"),
    ("material.kappa", {"normal": [1, 2]}, "material.kappa.normal: unknown distribution"),
    ("material.k_s", -0.5, "material.k_s: -0.5 outside [0, inf)"),
    ("material.k_b", [0.5, -0.1, 0.2], "material.k_b[1]: -0.1 outside [0, inf)"),
    ("material.r_k", 0.5, "material: give the body albedo as k_b or as r_k"),
    ("material.etta", 1.5, "material.etta: unknown key"),
    ("sample", 3, "sample: unknown key"),
    ("samples", 0, "samples: expected an integer >= 1"),
    ("samples", _DELETE, "samples: missing"),
    ("seed", -1, "seed: expected an integer >= 0"),
    ("render.resolution", [0, 16], "render.resolution[0]: expected an integer >= 1"),
    ("render.spp", 2.5, "render.spp: expected an integer"),
    ("render.variant", "scalar_rgb", "render.variant: expected one of"),
    ("shape.type", "teapot", "shape.type: unknown shape 'teapot'"),
    ("shape.type", {"choice": ["sphere", "missing.ply"]}, "shape.type.choice[1]: mesh file 'missing.ply' not found"),
    ("shape.rotate", "yes", "shape.rotate: expected true or false"),
    ("camera.type", "fisheye", "camera.type: expected one of orthographic, perspective"),
    ("camera.distance", 0.5, "camera.distance: 0.5 outside (1, inf)"),
    ("camera.fov", {"uniform": [10, 180]}, "camera.fov.uniform: high 180 outside (0, 180)"),
    ("camera.elevation", 90, "camera.elevation: 90 outside (-90, 90)"),
    ("light.direction", [0, 0, 0], "light.direction: expected a finite non-zero vector"),
    ("light.direction", {"cone": {"axis": [0, 0, 1], "angle": 200}}, "light.direction.cone.angle: 200 outside (0, 180]"),
    ("light.irradiance", {"uniform": [-1, 2]}, "light.irradiance.uniform: low -1 outside [0, inf)"),
])
def test_bad_config_rejected_with_key(setup, path, value, message):
    cfg_path = setup[0]
    with pytest.raises(DatasetConfigError) as err:
        load_config(_with(path, value), base_dir=cfg_path.parent)
    assert message in str(err.value)


def test_rgb_albedo_needs_spectral_variant(setup):
    cfg = _with("render.variant", "llvm_ad_mono_polarized")
    with pytest.raises(DatasetConfigError, match=r"material\.k_b: an RGB albedo needs a spectral variant"):
        load_config(cfg, base_dir=setup[0].parent)


def test_config_files(tmp_path):
    """The documented example loads; TOML/JSON syntax errors and other file types are reported."""
    cfg = load_config(os.path.join(ROOT, "scenes", "dataset_example.toml"))
    assert cfg.samples == 1000 and cfg.resolution == [256, 256] and cfg.spp == 16
    d = cfg.draw(0)
    assert set(d["material"]) == {"eta", "alpha", "beta", "kappa", "k_s", "k_b"}
    assert len(d["material"]["k_b"]) == 3
    (tmp_path / "bad.toml").write_text("samples = = 3\n")
    with pytest.raises(DatasetConfigError, match="not valid TOML"):
        load_config(tmp_path / "bad.toml")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(DatasetConfigError, match="config: expected a table"):
        load_config(tmp_path / "list.json")
    (tmp_path / "c.yaml").write_text("samples: 3\n")
    with pytest.raises(DatasetConfigError, match=r"expected a \.toml or \.json file"):
        load_config(tmp_path / "c.yaml")


def test_command_line_reports_bad_config(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("samples = 3\n[material]\neta = {uniform = [1.2, 3.5]}\n")
    r = subprocess.run(_cli(p, tmp_path / "out"), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert "material.eta.uniform: high 3.5 outside (1, 3]" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_broken_mesh_refused_before_writing(tmp_path):
    (tmp_path / "bad.obj").write_text("v 1 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="shape.type: cannot load mesh 'bad.obj'"):
        generate({"samples": 2, "shape": {"type": "bad.obj"}}, tmp_path / "out", base_dir=tmp_path,
                 progress=False)
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- the dataset command and API: bad configs and paths
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


# ---------------------------------------------------------------- empty meshes
@pytest.mark.parametrize("name,text,words", [
    ("m.ply", "", ["shape.type", "m.ply", "empty (0 bytes)"]),
    ("m.obj", "v 0 0 0\nv 1 0 0\n", ["shape.type", "m.obj", "no faces"]),
])
def test_empty_mesh_in_a_dataset_config(capsys, tmp_path, name, text, words):
    """Before: "cannot load mesh ... [parser.cpp:1718] At dictionary node "root": ...", from Mitsuba."""
    (tmp_path / name).write_text(text)
    (tmp_path / "c.toml").write_text(f'samples = 1\n[render]\nresolution = 8\nspp = 1\n'
                                     f'variant = "llvm_ad_mono_polarized"\n[shape]\ntype = "{name}"\n')
    rc, _, err = run(capsys, "dataset", "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "dataset", *words)
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- configs refused up front, locks per shard, back faces
HUGE = 100000  # 100000 x 100000 pixels: terabytes, more than any machine here


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


# ---------------------------------------------------------------- the sample count
@pytest.mark.parametrize("samples", [10 ** 12, 10 ** 6 + 1, 2 ** 63])
def test_dataset_samples_above_the_maximum_are_refused(tmp_path, capsys, samples):
    """Before: samples = 10**12 was accepted and the run grew lists of every index before rendering."""
    from fmbrdf_mi.cli import main
    from fmbrdf_mi.dataset.config import MAX_SAMPLES, DatasetConfigError, load_config

    with pytest.raises(DatasetConfigError, match=rf"^samples: expected an integer in \[1, {MAX_SAMPLES}\]"):
        load_config({"samples": samples})
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"samples = {samples}\n")
    rc = main(["dataset", "--config", str(cfg), "--out", str(tmp_path / "ds"), "-q"])
    one_line_error(rc, capsys.readouterr().err, "dataset", "samples", f"[1, {MAX_SAMPLES}]", str(samples))
    assert not (tmp_path / "ds").exists()
    rc = main(["dataset", "--config", "builtin:dataset_example", "--out", str(tmp_path / "ds"), "--samples",
               str(samples), "-q"])
    one_line_error(rc, capsys.readouterr().err, "dataset", "samples", f"[1, {MAX_SAMPLES}]")
    assert not (tmp_path / "ds").exists()


def test_dataset_samples_at_the_maximum_are_accepted():
    from fmbrdf_mi.dataset.config import MAX_SAMPLES, load_config

    assert load_config({"samples": MAX_SAMPLES}).samples == MAX_SAMPLES


# ---------------------------------------------------------------- variants
def test_dataset_cuda_variant_without_a_device_is_one_line(capsys, tmp_path):
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA device is present")
    cfg = tmp_path / "ds.toml"
    cfg.write_text('samples = 1\n[render]\nresolution = 8\nspp = 1\nvariant = "cuda_ad_mono_polarized"\n')
    out = tmp_path / "ds"
    rc, _, err = run(capsys, "dataset", "--config", str(cfg), "--out", str(out), "-q")
    one_line_error(rc, err, "dataset", "cuda_ad_mono_polarized", "no CUDA device", "llvm_ad_mono_polarized")
    assert not out.exists()
