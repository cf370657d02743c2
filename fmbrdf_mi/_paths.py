"""Checks made before rendering or fitting, so that foreseeable operating-system
problems and impossible sizes are reported at once, in one line naming the path;
outputs written all or none (:func:`staged_directory`) and output directories
locked while a run writes them (:func:`take_lock`), and the progress of their writing
(:class:`StageProgress`)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time

#: The command line's name, as its messages and the metadata of its outputs spell it.
PROG = "fmbrdf-mi"


class CLIError(Exception):
    """A mistake in the command line or its inputs, reported by the command line as one line."""


class PathError(OSError):
    """An output path that cannot be written (the message names it and says why)."""


def check_output_dir(path, what="output directory"):
    """Raise PathError unless directory ``path`` exists and is writable, or can be created."""
    path = os.fspath(path)
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise PathError(f"{what} {path}: exists and is not a directory")
        if not os.access(path, os.W_OK | os.X_OK):
            raise PathError(f"{what} {path}: not writable (permission denied)")
        return
    parent = os.path.abspath(path)
    while not os.path.exists(parent):
        up = os.path.dirname(parent)
        if up == parent:
            break
        parent = up
    if not os.path.isdir(parent):
        raise PathError(f"{what} {path}: cannot be created, {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PathError(f"{what} {path}: cannot be created in {parent} (permission denied)")


def check_output_file(path, what="output"):
    """Raise PathError unless file ``path`` can be written (its directory exists or can be created)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise PathError(f"{what} {path}: is a directory")
    check_output_dir(os.path.dirname(os.path.abspath(path)), f"{what} {path}: directory")


#: How a file shipped with the package (fmbrdf_mi/scenes/) is named on the command line: ``builtin:NAME``.
BUILTIN = "builtin:"


def builtin_dir():
    """The directory of the scenes and configs shipped with the package (installed by pip as package data)."""
    from importlib.resources import files

    return files("fmbrdf_mi") / "scenes"


def builtin_names(suffixes):
    """``builtin:NAME`` of every shipped file ending in one of ``suffixes`` (e.g. ``(".xml",)``), sorted."""
    return sorted(BUILTIN + os.path.splitext(p.name)[0] for p in builtin_dir().iterdir()
                  if p.name.endswith(tuple(suffixes)))


def resolve_builtin(path, suffixes, what):
    """``builtin:NAME`` (or ``builtin:NAME.ext``) -> the path of the shipped file; any other path unchanged.

    ValueError naming ``what`` and listing the valid names for an unknown one.
    """
    if not isinstance(path, str) or not path.startswith(BUILTIN):
        return path
    name = path[len(BUILTIN):]
    for suffix in ("",) + tuple(suffixes):
        entry = builtin_dir() / (name + suffix)
        if (name + suffix).endswith(tuple(suffixes)) and os.path.basename(name) == name and entry.is_file():
            return os.fspath(entry)
    raise ValueError(f"{what} {path}: no such built-in; valid: {', '.join(builtin_names(suffixes))}")


def available_memory():
    """Bytes of memory available to a new allocation (MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


#: Rough upper estimate of the memory one pixel of a Stokes render costs: Mitsuba's
#: film (about 20 float32 channels), the developed image, the running sum of the
#: passes, the NumPy Stokes array and the previews' float64 copies.
BYTES_PER_PIXEL = 512


def _size(n):
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024


def check_render_size(width, height, what="resolution", extra_per_pixel=0):
    """Raise ValueError if a width x height render cannot fit in the available memory."""
    need = int(width) * int(height) * (BYTES_PER_PIXEL + extra_per_pixel)
    avail = available_memory()
    if avail is not None and need > avail:
        raise ValueError(f"{what} {width}x{height}: rendering it needs about {_size(need)} of memory "
                         f"({BYTES_PER_PIXEL + extra_per_pixel} bytes per pixel), more than the "
                         f"{_size(avail)} available; choose a smaller resolution")
    return need


# ------------------------------------------------------------------ all-or-none outputs
@contextlib.contextmanager
def staged_directory(directory, last=(), remove=()):
    """Write a set of files all or none: yields a hidden staging directory inside ``directory`` (made if
    needed); when the block ends, the files ``remove`` (paths in ``directory``: a previous run's outputs
    that this one does not write) are deleted and the files written into the staging directory replace
    their namesakes in ``directory``, the names in ``last`` after the others (a record that says the rest
    is complete), with Ctrl-C held back until every file is in place.  When the block raises (Ctrl-C, a
    refused input) the staging directory is deleted, ``directory`` is left as it was, and the directories
    made for it are removed again: no file half-written and no earlier output lost."""
    directory = os.path.abspath(directory)
    made = directory
    while not os.path.exists(os.path.dirname(made)) and os.path.dirname(made) != made:
        made = os.path.dirname(made)
    made = None if os.path.exists(directory) else made
    stage = None
    try:
        with _sigint_held():      # a Ctrl-C now arrives inside the try, which removes what was made
            os.makedirs(directory, exist_ok=True)
            stage = tempfile.mkdtemp(prefix=".staging.", suffix=".partial", dir=directory)
        yield stage
        names = sorted(n for n in os.listdir(stage) if not n.startswith("."))  # a writer's own temporary file
        names = [n for n in names if n not in last] + [n for n in last if n in names]
        with _sigint_held():
            for p in remove:
                if os.path.basename(p) not in names and os.path.isfile(p):
                    os.remove(p)
            for name in names:
                os.replace(os.path.join(stage, name), os.path.join(directory, name))
            shutil.rmtree(stage, ignore_errors=True)
    except BaseException:
        with _sigint_held():
            if stage is not None:
                shutil.rmtree(stage, ignore_errors=True)
            if made is not None:
                shutil.rmtree(made, ignore_errors=True)
        raise


@contextlib.contextmanager
def staged_outputs(output):
    """:func:`staged_directory` for a file ``output`` and the files written beside it: yields the path to
    write ``output`` to, in the staging directory."""
    with staged_directory(os.path.dirname(os.path.abspath(output))) as stage:
        yield os.path.join(stage, os.path.basename(output))


@contextlib.contextmanager
def _sigint_held():
    """Hold Ctrl-C back until the block ends, so that a group of renames is not cut in two.  The SIGINT
    handler is swapped for one that only notes the signal (a Python handler runs in the main thread
    whichever thread the operating system delivers the signal to, which a signal mask does not ensure with
    Dr.Jit's worker threads running); the old handler then runs once if a Ctrl-C came."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: came.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if came:
            if callable(old):
                old(signal.SIGINT, came[0])
            elif old == signal.SIG_DFL:
                os.kill(os.getpid(), signal.SIGINT)


# ------------------------------------------------------------------ locks
def lock_info(**extra):
    """What a lock file records of the process that holds it (this one)."""
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            **extra}


def holder_alive(info):
    """Whether the process that wrote lock ``info`` may still run (on another host: assumed so)."""
    if info.get("host") != socket.gethostname():
        return True  # cannot tell: assume it runs
    try:
        os.kill(int(info["pid"]), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, KeyError, ValueError, TypeError):
        return True
    return True


def read_lock(path):
    """The JSON a lock file holds, or None if it is gone or unreadable."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def describe_lock(info, path):
    """The holder of a lock, as a message says it."""
    return (f"pid {info.get('pid')} on {info.get('host')}, started {info.get('started')} "
            f"(lock file {path}; delete it if that process is gone)")


def take_lock(path, what):
    """Create lock file ``path`` for this process, its content complete when it appears (a hard link of a
    written file); PathError naming ``what`` and the holder if a live process holds it.  A lock left by a
    process that is gone (on this host) is replaced.  Returns ``path``."""
    tmp = f"{path}.{os.getpid()}.{threading.get_ident()}"
    try:
        with _sigint_held():      # a Ctrl-C now arrives inside the try, whose finally removes tmp
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(json.dumps(lock_info()) + "\n")
        for _ in range(3):
            try:
                os.link(tmp, path)
                return path
            except FileExistsError:
                info = read_lock(path)
                if info is None:
                    continue  # released in the meantime
                if holder_alive(info):
                    raise PathError(f"{what}: another run is writing into it: {describe_lock(info, path)}")
                release_lock(path)  # stale: its process is gone
        raise PathError(f"{what}: could not take the lock {path}")
    finally:
        with _sigint_held():
            release_lock(tmp)


#: The lock file of an output directory a run is writing (:func:`locked_directory`).
LOCK_NAME = ".fmbrdf-mi.lock"


@contextlib.contextmanager
def locked_directory(directory, what="output directory"):
    """Hold the lock of output directory ``directory`` (made if needed) while the block runs: PathError
    naming the directory and the lock file if another live run holds it.  A directory made for it is
    removed again if the block raises and leaves it empty."""
    check_output_dir(directory, what)
    what = f"{what} {os.fspath(directory)}"
    directory = os.path.abspath(directory)
    made = []
    d = directory
    while not os.path.exists(d) and os.path.dirname(d) != d:
        made.append(d)
        d = os.path.dirname(d)
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, LOCK_NAME)
    ok = False
    try:
        try:
            yield take_lock(path, what)
            ok = True
        finally:
            with _sigint_held():   # ours however the block ended (a Ctrl-C just after the lock was taken too)
                info = read_lock(path)
                if info is not None and info.get("pid") == os.getpid() and info.get("host") == socket.gethostname():
                    release_lock(path)
    finally:
        if not ok:
            for d in made:           # deepest first; one that is not empty stays
                try:
                    os.rmdir(d)
                except OSError:
                    break


def release_lock(path):
    """Remove lock file ``path`` (nothing if it is gone)."""
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


class StageProgress:
    """Progress of the writing of a run's outputs (a render's files, a fit's), on stderr: a line per step once
    the steps have taken longer than ``delay`` seconds, with the time left at the mean time per step so far."""

    def __init__(self, label, n_steps, enabled=True, delay=2.0, stream=None, clock=time.perf_counter):
        self.label, self.n, self.done = label, n_steps, 0
        self.enabled, self.delay, self.clock = enabled, delay, clock
        self.stream = stream or sys.stderr
        self.t0 = clock()

    def step(self, name):
        self.done += 1
        t = self.clock() - self.t0
        if not self.enabled or t <= self.delay:
            return
        left = "done" if self.done == self.n else f"about {t / self.done * (self.n - self.done):.0f} s left"
        print(f"{self.label}: {self.done}/{self.n} {name}, {t:.1f} s ({left})", file=self.stream, flush=True)
