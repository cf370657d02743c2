"""What fit.json records so that a fit can be rerun: ``fmbrdf-mi fit --from fit.json -o DIR``.

The ``reproduce`` block holds the command line, every argument of
:func:`fmbrdf_mi.fit.outputs.single.fit_files` as resolved (so defaults that change in a
later version do not change the rerun), the SHA-256 of every input file, the
settings the inputs implied (layout, black and white level, demosaicking,
footprint, gain and read noise, possibly from a capture sidecar), the light
and irradiance, the sphere that ``--sphere auto`` found, and the versions of
this package, Mitsuba and Dr.Jit.  A rerun checks the hashes first and
refuses files that changed.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys

from fmbrdf_mi import __version__
from fmbrdf_mi.fit.errors import InputError

#: Arguments of fit_files that define a fit (not where it writes or how it talks).
ARGUMENTS = ("inputs", "normals", "mask", "view", "sphere", "camera", "fov", "light", "irradiance", "layout",
             "black_level", "channel", "demosaic", "conversion_gain", "read_noise", "footprint", "model",
             "baselines", "optimizer", "path", "bounds", "init", "loss", "white_level", "dark_level", "fixed",
             "starts", "max_iter", "tol", "time_limit", "max_time", "max_pixels", "erode", "seed", "relight",
             "relight_light", "relight_irradiance", "area_points", "intervals")


#: The arguments of :func:`fmbrdf_mi.fit.outputs.colour.fit_colour_files` among them (a colour fit's record).
COLOUR_ARGUMENTS = ("inputs", "normals", "mask", "view", "sphere", "camera", "fov", "light", "irradiance",
                    "black_level", "white_level", "conversion_gain", "read_noise", "model", "bounds", "fixed",
                    "max_time", "max_iter", "max_pixels", "erode", "seed", "starts", "intervals")


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def jsonable(v):
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if hasattr(v, "tolist") and getattr(v, "size", 1000) <= 16:
        return v.tolist()
    if isinstance(v, os.PathLike):
        return os.fspath(v)
    return {"not_recorded": type(v).__name__}


def _files(arguments):
    out = []
    for key in ("inputs", "normals", "mask", "view", "relight"):
        v = arguments.get(key)
        for p in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(p, (str, os.PathLike)) and os.path.isfile(p):
                out.append(os.fspath(p))
                side = os.path.splitext(os.fspath(p))[0] + ".json"
                if key in ("inputs", "relight") and os.path.isfile(side) and not p.lower().endswith(".json"):
                    out.append(side)
    return out


def versions():

    v = {"fmbrdf_mi": __version__, "python": sys.version.split()[0]}
    for mod in ("mitsuba", "drjit", "numpy"):
        try:
            v[mod] = __import__(mod).__version__
        except Exception:  # pragma: no cover
            v[mod] = None
    return v


def command_block(command):
    """The part of every ``reproduce`` block that says how the fit was run: command line, directory, versions."""
    return {"command": command, "cwd": os.getcwd(), "versions": versions()}


def reproduce_block(arguments, inputs, command, obs, relight=None):
    """The ``reproduce`` block of a single-image fit (module docstring); ``--from`` reruns it."""
    files = _files(arguments)
    return {
        "command": command,
        "cwd": os.getcwd(),
        "arguments": jsonable(arguments),
        "files_sha256": {os.path.abspath(p): sha256(p) for p in files},
        "settings": jsonable(obs.meta.get("settings")),
        "sphere": jsonable(obs.meta.get("sphere")),
        "sidecar": obs.meta.get("sidecar"),
        "versions": versions(),
    }


def load(path):
    """The ``reproduce`` block of a fit.json."""
    try:
        with open(path) as f:
            d = json.load(f)
    except OSError as exc:
        raise InputError(f"--from {path}: cannot read it ({exc.strerror})") from None
    except ValueError as exc:
        raise InputError(f"--from {path}: not a JSON file ({exc})") from None
    rep = d.get("reproduce") if isinstance(d, dict) else None
    if isinstance(d, dict) and "refine_normals" in d:
        cmd = rep.get("command") if isinstance(rep, dict) else None
        raise InputError(f"--from {path}: reruns of --refine-normals are not supported: rerun the command in its "
                         f"reproduce.command{f' ({cmd})' if isinstance(cmd, str) else ''}")
    if not isinstance(rep, dict) or "arguments" not in rep:
        raise InputError(f"--from {path}: no 'reproduce' block (written by an older fmbrdf-mi?)")
    if not isinstance(rep["arguments"], dict):
        raise InputError(f"--from {path}: reproduce.arguments: expected a table of the fit's options, "
                         f"got {rep['arguments']!r}")
    if "files_sha256" not in rep:
        raise InputError(f"--from {path}: reproduce.files_sha256 is missing: the record cannot be verified (no "
                         "SHA-256 of its input files); rerun the command in its reproduce.command instead")
    if not isinstance(rep["files_sha256"], dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                            for k, v in rep["files_sha256"].items()):
        raise InputError(f"--from {path}: reproduce.files_sha256: expected a table of file: SHA-256")
    return rep


def check_recorded(path, rep, files):
    """Refuse (one line naming the file) an input the rerun would read whose SHA-256 the record lacks."""
    recorded = rep.get("files_sha256", {})
    for p in files:
        if os.path.abspath(os.fspath(p)) not in recorded:
            raise InputError(f"--from {path}: input {p} has no recorded SHA-256 (reproduce.files_sha256): the "
                             "record cannot be verified for it")


def rerun_arguments(path):
    """fit_files arguments recorded in ``path``; checks that the input files are unchanged."""
    rep = load(path)
    args = dict(rep["arguments"])
    with open(path) as f:
        colour = json.load(f).get("sensor") == "colour"
    valid = COLOUR_ARGUMENTS if colour else ARGUMENTS
    if "inputs" not in args and "joint" not in rep:
        raise InputError(f"--from {path}: reproduce has no 'joint' block (a joint fit) and no arguments.inputs "
                         "(a single-image fit): the record is incomplete")
    unknown = [k for k in args if k not in valid]
    if unknown:
        raise InputError(f"--from {path}: reproduce.arguments: unknown key(s) {', '.join(map(str, unknown))} "
                         f"(valid: {', '.join(valid)})")
    bad = [k for k, v in args.items() if isinstance(v, dict) and "not_recorded" in v]
    if bad:
        raise InputError(f"--from {path}: arguments {', '.join(bad)} were arrays, not files; cannot rerun")
    for key in ("inputs", "normals", "mask", "view", "relight"):
        v = args.get(key)
        paths = v if isinstance(v, list) else [v]
        if (v is None and key != "inputs") or (paths and all(isinstance(p, str) and p for p in paths)):
            continue
        raise InputError(f"--from {path}: reproduce.arguments.{key}: expected a file name or a list of file "
                         f"names, got {v!r}")
    cwd = rep.get("cwd")
    if cwd is not None and not isinstance(cwd, str):
        raise InputError(f"--from {path}: reproduce.cwd: expected the directory the fit ran in, got {cwd!r}")
    for p, digest in rep.get("files_sha256", {}).items():
        if not os.path.isfile(p):
            raise InputError(f"--from {path}: input {p} no longer exists")
        if sha256(p) != digest:
            raise InputError(f"--from {path}: input {p} has changed since the fit (SHA-256 differs)")
    # relative paths were relative to the directory the fit ran in
    if cwd:
        for key in ("inputs", "normals", "mask", "view", "relight"):
            v = args.get(key)
            if isinstance(v, str) and not os.path.isabs(v):
                args[key] = os.path.join(cwd, v)
            elif isinstance(v, list):
                args[key] = [os.path.join(cwd, x) if isinstance(x, str) and not os.path.isabs(x) else x for x in v]
    # every file the rerun reads (inputs, geometry, the capture sidecars beside them) must have been hashed
    given = [p for key in ("inputs", "normals", "mask", "view", "relight")
             for p in (args.get(key) if isinstance(args.get(key), list) else [args.get(key)]) if isinstance(p, str)]
    check_recorded(path, rep, given + _files(args))
    return args
