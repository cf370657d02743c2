"""Output integrity of ``fmbrdf-mi fit`` and ``fit-brdf``: a locked output directory, no stale files of
another mode, all-or-none outputs under Ctrl-C, and a batch that stops at Ctrl-C.

The interrupts are real: ``python -m fmbrdf_mi`` runs in a subprocess and receives SIGINT at a point
read from the outside (the output directory changing, a progress line), and the invariants are checked
afterwards (the earlier output intact byte for byte, nothing half-written, a prompt non-zero exit).
"""
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from fmbrdf_mi._paths import LOCK_NAME, PathError, release_lock, staged_directory, take_lock
from fmbrdf_mi.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _env():
    return dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
                DRJIT_NUM_THREADS="1")


def _start(*argv, **kw):
    return subprocess.Popen([sys.executable, "-m", "fmbrdf_mi", *argv], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **kw)


def _finish(proc, timeout):
    """(exit status, stderr) of ``proc`` within ``timeout`` seconds; None as the status if it is still
    running then (its whole process group is killed)."""
    try:
        _, err = proc.communicate(timeout=timeout)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        return None, err


def _snapshot(d):
    out = {}
    for name in sorted(os.listdir(d)):
        p = os.path.join(d, name)
        with open(p, "rb") as f:
            out[name] = f.read()
    return out


@pytest.fixture(scope="module")
def stokes_exr(tmp_path_factory):
    d = tmp_path_factory.mktemp("capture")
    path = str(d / "sphere.exr")
    assert main(["render", "--res", "32", "--spp", "4", "-q", path]) == 0
    return path


# ------------------------------------------------------------------ the shared mechanisms
def test_staged_directory_is_all_or_none(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "gone.txt").write_text("an earlier run's")
    (tmp_path / "user.txt").write_text("the user's")
    with pytest.raises(KeyboardInterrupt):
        with staged_directory(tmp_path, remove=[str(tmp_path / "gone.txt")]) as stage:
            with open(os.path.join(stage, "a.txt"), "w") as f:
                f.write("new a")
            raise KeyboardInterrupt
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "gone.txt", "user.txt"]
    assert (tmp_path / "a.txt").read_text() == "old a"
    with staged_directory(tmp_path, last=("a.txt",), remove=[str(tmp_path / "gone.txt")]) as stage:
        for n in ("a.txt", "b.txt"):
            with open(os.path.join(stage, n), "w") as f:
                f.write("new " + n)
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt", "user.txt"]
    assert (tmp_path / "a.txt").read_text() == "new a.txt"


def test_lock_refuses_a_live_holder_and_replaces_a_dead_ones(tmp_path):
    path = str(tmp_path / LOCK_NAME)
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        with open(path, "w") as f:
            json.dump({"pid": holder.pid, "host": os.uname().nodename, "started": "then"}, f)
        with pytest.raises(PathError) as e:
            take_lock(path, f"output directory {tmp_path}")
        assert str(tmp_path) in str(e.value) and path in str(e.value) and str(holder.pid) in str(e.value)
    finally:
        holder.kill()
        holder.wait()
    assert take_lock(path, "x") == path            # its holder is gone: the lock is taken over
    assert json.load(open(path))["pid"] == os.getpid()
    release_lock(path)
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------ fit: the lock
def test_two_fits_into_one_directory_do_not_both_succeed(tmp_path, stokes_exr, capsys):
    out = str(tmp_path / "fit")
    first = _start("fit", stokes_exr, "-o", out, "-q")
    try:
        deadline = time.time() + 120
        while not os.path.exists(os.path.join(out, LOCK_NAME)) and first.poll() is None and time.time() < deadline:
            time.sleep(0.01)
        assert os.path.exists(os.path.join(out, LOCK_NAME)), "the first fit holds no lock on its directory"
        rc = main(["fit", stokes_exr, "-o", out, "--force", "-q"])
        err = capsys.readouterr().err.strip()
        assert rc != 0
        assert len(err.splitlines()) == 1, err
        assert out in err and LOCK_NAME in err and str(first.pid) in err
    finally:
        rc1, err1 = _finish(first, 300)
    assert rc1 == 0, err1
    assert sorted(os.listdir(out)) == ["fit.json", "fitted_stokes.exr", "history.png", "images.png", "profiles.png"]


# ------------------------------------------------------------------ fit: stale files of another mode
def test_a_forced_shared_fit_removes_an_earlier_per_pixel_fits_maps(tmp_path, stokes_exr):
    out = tmp_path / "fit"
    out.mkdir()
    earlier = {"inputs": "x", "images": [{"name": "left"}, {"name": "../escape"}]}
    (out / "fit.json").write_text(json.dumps(earlier))
    stale = ["k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png", "materials.png", "labels.png",
             "relight.png", "images_left.png", "profiles_left.png"]
    for n in stale:
        (out / n).write_bytes(b"earlier fit")
    kept = ["notes.txt", "images_right.png", "k_s.exr.bak"]   # not the package's (or not the earlier fit's)
    for n in kept:
        (out / n).write_text("the user's")
    assert main(["fit", stokes_exr, "-o", str(out), "--force", "-q"]) == 0
    assert sorted(os.listdir(out)) == sorted(kept + ["fit.json", "fitted_stokes.exr", "history.png", "images.png",
                                                     "profiles.png"])
    for n in kept:
        assert (out / n).read_text() == "the user's"
    assert "albedo_maps" not in json.loads((out / "fit.json").read_text())


def test_known_output_names_cover_every_mode():
    from fmbrdf_mi.fit.outputs import colour, normals, single
    from fmbrdf_mi.fit.outputs.writer import FIXED_OUTPUTS

    names = set(single.output_files("o", True, "per-pixel", "auto:2")) | set(colour.output_names("per-pixel")) \
        | set(normals.OUTPUTS)
    assert names <= set(FIXED_OUTPUTS)


# ------------------------------------------------------------------ fit: Ctrl-C while writing
def test_ctrl_c_in_the_write_phase_keeps_the_earlier_output(tmp_path, stokes_exr):
    out = str(tmp_path / "fit")
    assert main(["fit", stokes_exr, "-o", out, "-q"]) == 0
    before = _snapshot(out)
    mtimes = {n: os.stat(os.path.join(out, n)).st_mtime_ns for n in before}
    proc = _start("fit", stokes_exr, "-o", out, "--force", "-q", "--baselines")

    def writing():   # a new entry besides the lock (a staging directory, a new file) or a file rewritten
        try:
            names = set(os.listdir(out)) - {LOCK_NAME}
            return names != set(before) or any(os.stat(os.path.join(out, n)).st_mtime_ns != t
                                               for n, t in mtimes.items())
        except FileNotFoundError:
            return True

    deadline = time.time() + 300
    while not writing() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.002)
    assert proc.poll() is None, "the fit ended before it was interrupted"
    proc.send_signal(signal.SIGINT)
    t0 = time.time()
    rc, err = _finish(proc, 60)
    assert rc is not None and time.time() - t0 < 60, err     # stopped promptly
    after = _snapshot(out)
    if after == before:                      # stopped before the new files moved in: every earlier file as it
        assert rc != 0, err                  # was, nothing added (no hidden file), and a failure status
        return
    # Ctrl-C came while the new files were being moved into place: it is held back until they all are, so the
    # directory holds exactly what an uninterrupted run writes (all, not none; never a mix of the two fits)
    ref = str(tmp_path / "reference")
    assert main(["fit", stokes_exr, "-o", ref, "-q", "--baselines"]) == 0
    assert sorted(after) == sorted(os.listdir(ref)), (sorted(after), sorted(os.listdir(ref)))
    assert json.loads(after["fit.json"])["reproduce"]["arguments"]["baselines"] is True
    assert all(after[n] != before[n] for n in before if n.endswith(".json")), "an earlier record was kept"


# ------------------------------------------------------------------ fit-brdf --jobs: Ctrl-C
@pytest.fixture(scope="module")
def merl_files(tmp_path_factory):
    import numpy as np

    from fmbrdf_mi.brdf_fit import merl
    from fmbrdf_mi.brdf_fit.fitting import model_brdf

    d = tmp_path_factory.mktemp("merl")
    table = model_brdf({"eta": 1.55, "alpha": 0.23, "beta": 1.7, "kappa": 15.0, "k_s": [0.5, 0.6, 0.7],
                        "k_b": [0.3, 0.1, 0.05]})
    table = table * np.exp(0.2 * np.random.default_rng(1).standard_normal(table.shape))   # not fitted exactly
    for name in ("a", "b", "c", "d"):
        merl.write_merl(d / f"{name}.binary", table)
    return d


def test_ctrl_c_stops_a_fit_brdf_batch_promptly(tmp_path, merl_files):
    out = tmp_path / "fits"
    (out / "a").mkdir(parents=True)
    (out / "a" / "params.json").write_text('{"earlier": true}')
    (out / "a" / "slices.png").write_bytes(b"earlier")
    proc = _start("fit-brdf", str(merl_files), "-o", str(out), "--jobs", "2", "--force", "--full-grid",
                  "--samples", "400000")
    line = "-"
    while line and "[fit-brdf] batch of" not in line:   # the batch's first line: the workers start now
        line = proc.stderr.readline()
    assert "[fit-brdf] batch of 4 materials" in line, line
    time.sleep(8)                            # the workers are fitting (each fit takes far longer)
    assert proc.poll() is None, "the batch ended before it was interrupted"
    proc.send_signal(signal.SIGINT)
    t0 = time.time()
    rc, err = _finish(proc, 45)
    assert rc is not None, "the batch went on fitting after Ctrl-C"
    assert rc != 0 and time.time() - t0 < 45
    assert (out / "a" / "params.json").read_text() == '{"earlier": true}'
    assert (out / "a" / "slices.png").read_bytes() == b"earlier"
    left = sorted(os.path.relpath(os.path.join(dp, f), out) for dp, ds, fs in os.walk(out) for f in fs + ds)
    assert left == ["a", os.path.join("a", "params.json"), os.path.join("a", "slices.png")], left
    assert not os.path.exists(out / "summary.tsv")
