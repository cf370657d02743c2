"""Issue 24: the scenes and the dataset example ship with the package (fmbrdf_mi/scenes/, package data) and are
named ``builtin:NAME`` (``-s builtin:spheres``, ``--config builtin:dataset_example``), so that they work outside
the source tree; ``scenes/`` paths keep working in it.  Before: only ``scenes/`` existed, outside the package,
and ``-s scenes/spheres.xml`` failed after ``pip install``."""
import os
import subprocess
import sys

import pytest

from conftest import one_line_error, run

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
SCENES = ["builtin:sphere", "builtin:sphere_perspective", "builtin:spheres"]


def test_importlib_resources_finds_the_shipped_files():
    from importlib.resources import files

    d = files("fmbrdf_mi") / "scenes"
    for name in ("sphere.xml", "sphere_perspective.xml", "spheres.xml", "dataset_example.toml"):
        assert (d / name).is_file(), name


def test_builtin_names_resolve():
    from fmbrdf_mi._paths import builtin_names, resolve_builtin

    assert builtin_names((".xml",)) == SCENES
    for name in SCENES:
        p = resolve_builtin(name, (".xml",), "scene file")
        assert os.path.isfile(p) and p.endswith(name[len("builtin:"):] + ".xml")
    assert resolve_builtin("builtin:spheres.xml", (".xml",), "scene file").endswith("spheres.xml")
    assert resolve_builtin("scenes/spheres.xml", (".xml",), "scene file") == "scenes/spheres.xml"


def test_source_tree_paths_still_work():
    """scenes/ in the source tree is the package's folder (a link)."""
    for name in ("sphere.xml", "spheres.xml", "dataset_example.toml"):
        assert os.path.isfile(os.path.join(ROOT, "scenes", name))


def test_builtin_names_resolve_from_an_installed_copy(tmp_path):
    """The package as pip installs it (setuptools' build_py with the pyproject's package data) holds the files,
    and builtin: names resolve inside that copy, not the source tree."""
    pytest.importorskip("setuptools")
    lib = tmp_path / "lib"
    p = subprocess.run([sys.executable, "-c", "from setuptools import setup; setup()", "-q", "build_py",
                        "--build-lib", str(lib)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    code = ("import fmbrdf_mi._paths as P; print(P.__file__); "
            "print(P.resolve_builtin('builtin:spheres', ('.xml',), 's')); "
            "print(P.resolve_builtin('builtin:dataset_example', ('.toml', '.json'), 'c'))")
    env = dict(os.environ, PYTHONPATH=str(lib))
    q = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert q.returncode == 0, q.stderr[-2000:]
    mod, scene, config = q.stdout.split()
    for f in (mod, scene, config):
        assert f.startswith(str(lib)), (f, str(lib))
        assert os.path.isfile(f)


def test_unknown_builtin_scene_lists_the_valid_ones(capsys, tmp_path):
    rc, _, err = run(capsys, "render", "-s", "builtin:sphers", "-q", str(tmp_path / "x.exr"))
    one_line_error(rc, err, "render", "builtin:sphers", "no such built-in", *SCENES)
    assert not os.listdir(tmp_path)


def test_unknown_builtin_config_lists_the_valid_ones(capsys, tmp_path):
    rc, _, err = run(capsys, "dataset", "--config", "builtin:example", "--out", str(tmp_path / "out"), "-q")
    one_line_error(rc, err, "dataset", "builtin:example", "no such built-in", "builtin:dataset_example")
    assert not os.listdir(tmp_path)


def test_builtin_scene_and_config_are_used(capsys):
    rc, out, err = run(capsys, "render", "--list-params", "-s", "builtin:spheres")
    assert rc == 0, err
    assert "alpha_1" in out
    from fmbrdf_mi.dataset import load_config

    cfg = load_config("builtin:dataset_example")
    assert cfg.samples > 0
