"""Checks made before rendering or fitting, so that foreseeable operating-system
problems and impossible sizes are reported at once, in one line naming the path."""
from __future__ import annotations

import os

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
