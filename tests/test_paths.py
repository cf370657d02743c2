"""Output locking and staging (fmbrdf_mi/_paths.py): a staged directory is all or none, a lock refuses a live
holder and replaces a dead one's.
"""
import json
import os
import subprocess
import sys

import pytest

from fmbrdf_mi._paths import LOCK_NAME, PathError, release_lock, staged_directory, take_lock


# ---------------------------------------------------------------- staging and locks
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
