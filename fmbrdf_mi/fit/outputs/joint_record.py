"""What fit.json records so that a joint fit can be rerun: ``fmbrdf-mi fit --from fit.json -o DIR``.

The joint counterpart of :mod:`fmbrdf_mi.fit.outputs.record`.  A joint fit
(:mod:`fmbrdf_mi.fit.outputs.joint`: ``--manifest``, ``--authors`` or repeated
``--light``) writes a ``reproduce`` block with

* ``command``, ``cwd``, ``versions`` (as a single-image fit);
* ``arguments``: the fit options as resolved (model, baselines, loss, fixed,
  bounds, init, starts, max_iter, tol, time limits, max_pixels, erode, seed,
  free_power, power_start);
* ``joint``: how the images were given (``kind`` ``manifest``, ``authors`` or
  ``lights``) and, per image, its name, input file(s) with SHA-256 (and
  the capture sidecar's), the light (this package's camera frame), the
  relative power, the irradiance used, the held-out flag, the geometry
  source (normal / mask / view files, a sphere and what ``--sphere auto``
  found, the built-in scene's metadata, or the authors' calibration files)
  and the settings the input implied (layout, black / white / dark level,
  demosaicking, footprint, gain, read noise);
* ``files_sha256``: every file the fit read (images, sidecars, geometry, the
  manifest, the authors' ``calibration/*``).

A rerun checks every hash first and refuses, in one line naming the file, an
input that changed or disappeared; then it rebuilds the images from the
record (the manifest's images with absolute paths and the options they
resolved to; an authors' object by reading its directory again with the
recorded options) and fits with the recorded options: same data, same pixel
subsets (same seed), same estimates.
"""
from __future__ import annotations

import os

from fmbrdf_mi.camera import sidecar_path
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.inputs.manifest import (INPUT_KEYS, ImageSpec, check_entry, check_input, check_light,
                                           check_options, image_names)
from fmbrdf_mi.fit.outputs.joint import fitter
from fmbrdf_mi.fit.outputs.record import check_recorded, jsonable, load, sha256, versions

#: fit_images keywords that define a joint fit (not where it writes or how it talks).
FIT_KEYS = ("model", "baselines", "loss", "fixed", "bounds", "init", "starts", "max_iter", "tol", "time_limit",
            "max_time", "max_pixels", "erode", "seed", "free_power", "power_start", "area_points", "intervals")


#: read_object keywords recorded for an authors' object.
AUTHORS_KEYS = ("mask", "holdout", "conversion_gain", "read_noise", "white_level", "dark_level", "black_level",
                "demosaic", "footprint")


def _abs(v):
    if isinstance(v, (str, os.PathLike)):
        return os.path.abspath(os.fspath(v))
    if isinstance(v, (list, tuple)):
        return [_abs(x) for x in v]
    return v


def _with_sidecar(paths):
    """The files of an input (a path or a list) and the capture sidecar beside each, if there is one."""

    out = []
    for p in (paths if isinstance(paths, (list, tuple)) else [paths]):
        if isinstance(p, str) and os.path.isfile(p):
            out.append(p)
            side = sidecar_path(p)
            if side != p and os.path.isfile(side) and not p.lower().endswith(".exr"):
                out.append(side)
    return out


def _hashes(paths):
    return {os.path.abspath(p): sha256(p) for p in paths if isinstance(p, str) and os.path.isfile(p)}


def _geometry(spec, obs):
    """Where image ``spec``'s normals, mask and view directions came from."""
    o = spec.options
    if o.get("normals") is not None:
        g = {"source": "normal map", "normals": o.get("normals"), "mask": o.get("mask")}
        g.update({"view": o["view"]} if o.get("view") is not None else
                 {"camera": o.get("camera", "orthographic"), "fov": o.get("fov")})
        return g
    if o.get("sphere") is not None:
        return {"source": "sphere", "sphere": o["sphere"], "mask": o.get("mask"), "view": o.get("view"),
                "camera": o.get("camera", "orthographic"), "fov": o.get("fov"), "found": obs.meta.get("sphere")}
    if obs.meta.get("truth") is not None:
        return {"source": "the input's metadata (fmbrdf-mi render, built-in sphere)"}
    return {"source": "unknown"}


def block(kind, specs, names, observations, fit_kw, command, *, manifest=None, authors=None, info=None):
    """The ``reproduce`` block of a joint fit (see the module docstring).

    ``specs``: the :class:`~fmbrdf_mi.fit.inputs.manifest.ImageSpec` s as fitted
    (paths resolved); ``observations``: the Observations built from them;
    ``authors``: read_object's keywords for ``kind == "authors"`` with
    ``info`` its description of what it read.
    """
    images, files = [], []
    if kind == "authors":
        root = info["root"]
        cal = os.path.join(root, "calibration")
        files += [os.path.join(cal, f) for f in ("L.txt", "vpL_img.npy", "IntrinsicL.npy", "intensities.npy")]
        files += [os.path.join(root, "normal", "normal_GT.npy"), _abs(info["mask"])]
    if manifest is not None:
        files.append(_abs(manifest))
    for k, (s, n, o) in enumerate(zip(specs, names, observations)):
        if kind == "authors":
            inp = o.meta["authors_layout"]["file"]
            geo = {"source": "authors' layout", "normals": os.path.join(root, "normal", "normal_GT.npy"),
                   "view": os.path.join(cal, info["view_rays"]), "mask": _abs(info["mask"])}
            entry = {}
            power = info["intensities"][k] if info.get("intensities") else 1.0   # intensities.npy / max
        else:
            inp = s.input
            geo = _geometry(s, o)
            entry = {"spec": {"input": inp, "light": s.light, "power": s.power, "holdout": s.holdout,
                              "name": s.name, "options": s.options}}
            power = s.power
        mine = _with_sidecar(inp)
        geo_files = [geo.get(x) for x in ("normals", "mask", "view") if isinstance(geo.get(x), str)]
        files += mine + geo_files
        images.append({"name": n, "input": inp, "files_sha256": _hashes(mine + geo_files),
                       "light": [float(x) for x in o.light_dir], "power": float(power),
                       "irradiance": float(o.irradiance), "holdout": bool(s.holdout), "geometry": geo,
                       "settings": o.meta.get("settings"), "sidecar": o.meta.get("sidecar"), **entry})
    joint = {"kind": kind, "images": images}
    if manifest is not None:
        joint["manifest"] = _abs(manifest)
    if kind == "authors":
        joint["authors"] = {"root": info["root"], **authors}
    return jsonable({"command": command, "cwd": os.getcwd(), "arguments": {k: fit_kw.get(k) for k in FIT_KEYS
                                                                            if k in fit_kw},
                      "joint": joint, "files_sha256": _hashes(files), "versions": versions()})


def check_files(path, rep):
    """Refuse (one line naming the file) when a recorded input changed or disappeared."""
    for p, digest in rep.get("files_sha256", {}).items():
        if not os.path.isfile(p):
            raise InputError(f"--from {path}: input {p} no longer exists")
        if sha256(p) != digest:
            raise InputError(f"--from {path}: input {p} has changed since the fit (SHA-256 differs)")


def read_files(kind, specs, info):
    """The files a rerun of these images reads: images with their sidecars, geometry files, and for an
    authors' object its calibration, normal map, mask and images."""
    files = []
    if kind == "authors":
        cal = os.path.join(info["root"], "calibration")
        files += [os.path.join(cal, f) for f in ("L.txt", "vpL_img.npy", "IntrinsicL.npy", "intensities.npy")
                  if os.path.isfile(os.path.join(cal, f))]
        files += [os.path.join(info["root"], "normal", "normal_GT.npy"), _abs(info["mask"])]
        files += [s.input.meta["authors_layout"]["file"] for s in specs]
        return files
    for s in specs:
        files += [p for p in (s.input if isinstance(s.input, list) else [s.input]) if isinstance(p, str)]
        files += _with_sidecar(s.input)
        files += [s.options[k] for k in ("normals", "mask", "view") if isinstance(s.options.get(k), str)]
    return files


def is_joint(path):
    """Whether ``path`` (a fit.json) records a joint fit; refuses files without a ``reproduce`` block."""
    return "joint" in load(path)


def rerun(path, out, *, force=False, progress=True, command=None):
    """Rerun the joint fit recorded in ``path`` into ``out``; returns the dict written to fit.json."""

    rep = load(path)
    joint = rep.get("joint")
    if not isinstance(joint, dict) or joint.get("kind") not in ("manifest", "authors", "lights"):
        raise InputError(f"--from {path}: not the record of a joint fit")
    check_files(path, rep)
    fit_kw = dict(rep["arguments"])
    unknown = [k for k in fit_kw if k not in FIT_KEYS]
    if unknown:
        raise InputError(f"--from {path}: reproduce.arguments: unknown key(s) {', '.join(map(str, unknown))} "
                         f"(valid for a joint fit: {', '.join(FIT_KEYS)})")
    info = None
    try:
        if joint["kind"] == "authors":
            a = dict(joint["authors"])
            bad = [k for k in a if k not in AUTHORS_KEYS + ("root",)]
            if bad:
                raise InputError(f"--from {path}: reproduce.joint.authors: unknown key(s) {', '.join(bad)} "
                                 f"(valid: root, {', '.join(AUTHORS_KEYS)})")
            specs, info = read_object(a.pop("root"), **a)
        else:
            specs = []
            for k, im in enumerate(joint["images"]):
                where = f"--from {path}: reproduce.joint.images[{k}].spec"
                spec = ImageSpec(**im["spec"])
                check_input(spec.input, where)
                check_light(spec.light, where)
                check_entry(spec.power, spec.holdout, spec.name, where)
                if not isinstance(spec.options, dict):
                    raise InputError(f"{where}: options: expected a table, got {spec.options!r}")
                bad = [x for x in spec.options if x not in INPUT_KEYS]
                if bad:
                    raise InputError(f"{where}: options: unknown key(s) {', '.join(map(str, bad))} "
                                     f"(valid: {', '.join(INPUT_KEYS)})")
                spec.options = check_options(spec.options, f"{where}: options")
                specs.append(spec)
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"--from {path}: the joint-fit record is incomplete ({exc})") from None
    check_recorded(path, rep, read_files(joint["kind"], specs, info))
    authors = {k: v for k, v in (joint.get("authors") or {}).items() if k != "root"}
    names = image_names(specs)
    recorded = [im["name"] for im in joint["images"]]
    if names != recorded:
        raise InputError(f"--from {path}: the images are now {names}, the fit had {recorded}")
    fit_fn, outputs_fn = fitter(specs)
    files = outputs_fn(out, names, [s.holdout for s in specs])
    return fit_fn(specs, out, force=force, progress=progress, command=command,
                      extra={"joint": {"outputs": files, "authors_layout": info, "rerun_of": os.path.abspath(path)}},
                      reproduce=lambda obs: block(joint["kind"], specs, names, obs, fit_kw, command,
                                                  manifest=joint.get("manifest"), authors=authors, info=info),
                      **fit_kw)
