"""``fmbrdf-mi fit --from fit.json -o DIR``: :func:`rerun` reruns a recorded fit from its ``reproduce`` block
(:mod:`fmbrdf_mi.fit.outputs.record`), refusing a changed or missing input in one line."""
from __future__ import annotations

import json
import os

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.api.find_materials import parse_auto
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.inputs.manifest import image_names, image_spec
from fmbrdf_mi.fit.inputs.parse import check_keys
from fmbrdf_mi.fit.outputs.colour import fit_colour_files
from fmbrdf_mi.fit.outputs.joint import run_images
from fmbrdf_mi.fit.api.options import record_keys
from fmbrdf_mi.fit.outputs.record import AUTHORS_KEYS, FILE_KEYS, ONE_IMAGE, read_files, sha256, single_files
from fmbrdf_mi.fit.outputs.single import fit_files

#: The kinds of fit a ``reproduce`` block records (:mod:`fmbrdf_mi.fit.outputs.record`).
KINDS = ONE_IMAGE + ("manifest", "authors", "lights")


def rerun(path, out, *, force=False, progress=True, command=None):
    """Rerun the fit recorded in ``path`` (a fit.json) into ``out``; returns the dict written to fit.json."""
    rep = load(path)
    kind = rep["kind"]
    args, given = recorded_arguments(path, rep, kind if kind in ONE_IMAGE else "joint")
    kw = dict(force=force, progress=progress, command=command)
    if kind in ONE_IMAGE:
        check_recorded(path, rep, given + single_files(args))
        return (fit_colour_files if kind == "colour" else fit_files)(out=out, **kw, **args)
    info = None
    try:
        if kind == "authors":
            a = dict(rep["authors"])
            check_keys(a, ("root",) + AUTHORS_KEYS, f"--from {path}: reproduce.authors")
            specs, info = read_object(a.pop("root"), **a)
        else:
            specs = [image_spec(**im["spec"], where=f"--from {path}: reproduce.images[{k}].spec", at=": options")
                     for k, im in enumerate(rep["images"])]
        recorded = [im["name"] for im in rep["images"]]
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"--from {path}: the joint-fit record is incomplete ({exc})") from None
    check_recorded(path, rep, read_files(kind, specs, info) + given)
    names = image_names(specs)
    if names != recorded:
        raise InputError(f"--from {path}: the images are now {names}, the fit had {recorded}")
    authors = {k: v for k, v in (rep.get("authors") or {}).items() if k != "root"}
    return run_images(kind, specs, out, args, **kw, manifest=rep.get("manifest"), authors=authors, info=info)


def load(path):
    """fit.json's ``reproduce`` block; refuses a record that cannot be rerun or whose inputs changed."""
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
        cmd = cmd if isinstance(cmd, str) else None
        rounds = cmd is not None and any(t == "--rounds" or t.startswith("--rounds=") for t in cmd.split())
        raise InputError(f"--from {path}: reruns of --refine-normals are not supported: rerun the command in its "
                         f"reproduce.command{f' ({cmd})' if cmd else ''}"
                         + (" without --rounds (no longer an option: the refinement is the joint step alone)"
                            if rounds else ""))
    if not isinstance(rep, dict) or "arguments" not in rep:
        raise InputError(f"--from {path}: no 'reproduce' block (written by an older fmbrdf-mi?)")
    if rep.get("kind") not in KINDS:
        raise InputError(f"--from {path}: reproduce.kind is " + (f"{rep['kind']!r}, not one of {', '.join(KINDS)}"
                                                                   if "kind" in rep else "missing")
                         + ": a fit.json of an older layout cannot be rerun; rerun the command in its "
                           "reproduce.command instead")
    if not isinstance(rep["arguments"], dict):
        raise InputError(f"--from {path}: reproduce.arguments: expected a table of the fit's options, "
                         f"got {rep['arguments']!r}")
    if "files_sha256" not in rep:
        raise InputError(f"--from {path}: reproduce.files_sha256 is missing: the record cannot be verified (no "
                         "SHA-256 of its input files); rerun the command in its reproduce.command instead")
    if not isinstance(rep["files_sha256"], dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                            for k, v in rep["files_sha256"].items()):
        raise InputError(f"--from {path}: reproduce.files_sha256: expected a table of file: SHA-256")
    for p, digest in rep["files_sha256"].items():
        if not os.path.isfile(p):
            raise InputError(f"--from {path}: input {p} no longer exists")
        if sha256(p) != digest:
            raise InputError(f"--from {path}: input {p} has changed since the fit (SHA-256 differs)")
    return rep


def check_recorded(path, rep, files):
    """Refuse (one line naming the file) an input the rerun would read whose SHA-256 the record lacks."""
    recorded = rep.get("files_sha256", {})
    for p in files:
        if os.path.abspath(os.fspath(p)) not in recorded:
            raise InputError(f"--from {path}: input {p} has no recorded SHA-256 (reproduce.files_sha256): the "
                             "record cannot be verified for it")


def recorded_arguments(path, rep, kind):
    """(the arguments recorded in ``rep``, the ``reproduce`` block of ``path``, for a fit of ``kind``; the files
    they name): relative file names are made relative to the directory the fit ran in (``auto:M`` names none)."""
    args, valid = dict(rep["arguments"]), record_keys(kind)
    check_keys(args, valid, f"--from {path}: reproduce.arguments",
               shown=f"valid{' for a joint fit' if kind == 'joint' else ''}: {', '.join(valid)}")
    bad = [k for k, v in args.items() if isinstance(v, dict) and "not_recorded" in v]
    if bad:
        raise InputError(f"--from {path}: arguments {', '.join(bad)} were arrays, not files; cannot rerun")
    cwd = rep.get("cwd")
    if cwd is not None and not isinstance(cwd, str):
        raise InputError(f"--from {path}: reproduce.cwd: expected the directory the fit ran in, got {cwd!r}")
    given = []
    for key in (k for k in FILE_KEYS if k in valid):
        v = args.get(key)
        paths = v if isinstance(v, list) else [v]
        if (v is None and key != "inputs") or (key == "materials" and parse_auto(v)):
            continue
        if not (paths and all(isinstance(p, str) and p for p in paths)):
            raise InputError(f"--from {path}: reproduce.arguments.{key}: expected a file name or a list of file "
                             f"names, got {v!r}")
        paths = [os.path.join(cwd or "", p) for p in paths]
        args[key] = paths if isinstance(v, list) else paths[0]
        given += paths
    return args, given
