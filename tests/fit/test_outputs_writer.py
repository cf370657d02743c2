"""``fmbrdf-mi fit``'s output directory: locked against a second fit, no stale files of another mode, all or none
under Ctrl-C.  The interrupts are real: ``python -m fmbrdf_mi`` runs in a subprocess and receives SIGINT at a
point read from the outside, and the earlier output is checked afterwards, byte for byte.
"""
import json
import os
import signal
import time

import pytest

from fmbrdf_mi._paths import LOCK_NAME
from fmbrdf_mi.cli import main

from conftest import finish_command, start_command


# ---------------------------------------------------------------- the fit's outputs


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


def test_two_fits_into_one_directory_do_not_both_succeed(tmp_path, stokes_exr, capsys):
    out = str(tmp_path / "fit")
    first = start_command("fit", stokes_exr, "--starts", "1", "-o", out, "-q")
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
        rc1, err1 = finish_command(first, 300)
    assert rc1 == 0, err1
    assert sorted(os.listdir(out)) == ["fit.json", "fitted_stokes.exr", "history.png", "images.png", "profiles.png"]


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
    assert main(["fit", stokes_exr, "--starts", "1", "-o", str(out), "--force", "-q"]) == 0
    assert sorted(os.listdir(out)) == sorted(kept + ["fit.json", "fitted_stokes.exr", "history.png", "images.png",
                                                     "profiles.png"])
    for n in kept:
        assert (out / n).read_text() == "the user's"
    assert "albedo_maps" not in json.loads((out / "fit.json").read_text())


def test_known_output_names_cover_every_mode():
    from fmbrdf_mi.fit.outputs import normals, single
    from fmbrdf_mi.fit.outputs.job import FIXED_OUTPUTS, joint_outputs

    colour = joint_outputs("o", [None], [False], "per-pixel", colour=True)   # a colour fit of one mosaic
    names = set(single.output_files("o", True, "per-pixel", "auto:2")) | {os.path.basename(p) for p in colour} \
        | set(normals.OUTPUTS)
    assert names <= set(FIXED_OUTPUTS)


def test_ctrl_c_in_the_write_phase_keeps_the_earlier_output(tmp_path, stokes_exr):
    out = str(tmp_path / "fit")
    assert main(["fit", stokes_exr, "--starts", "1", "-o", out, "-q"]) == 0
    before = _snapshot(out)
    mtimes = {n: os.stat(os.path.join(out, n)).st_mtime_ns for n in before}
    proc = start_command("fit", stokes_exr, "--starts", "1", "-o", out, "--force", "-q", "--baselines")

    def writing():   # a new entry besides the lock and its temporary file (a staging directory, a new file) or
        try:         # a file rewritten
            names = {n for n in os.listdir(out) if not n.startswith(LOCK_NAME)}
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
    rc, err = finish_command(proc, 60)
    assert rc is not None and time.time() - t0 < 60, err     # stopped promptly
    after = _snapshot(out)
    if after == before:                      # stopped before the new files moved in: every earlier file as it
        assert rc != 0, err                  # was, nothing added (no hidden file), and a failure status
        return
    # Ctrl-C came while the new files were being moved into place: it is held back until they all are, so the
    # directory holds exactly what an uninterrupted run writes (all, not none; never a mix of the two fits)
    ref = str(tmp_path / "reference")
    assert main(["fit", stokes_exr, "--starts", "1", "-o", ref, "-q", "--baselines"]) == 0
    assert sorted(after) == sorted(os.listdir(ref)), (sorted(after), sorted(os.listdir(ref)))
    assert json.loads(after["fit.json"])["reproduce"]["arguments"]["baselines"] is True
    assert all(after[n] != before[n] for n in before if n.endswith(".json")), "an earlier record was kept"
