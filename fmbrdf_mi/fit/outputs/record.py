"""fit.json's ``reproduce`` block, from which ``fmbrdf-mi fit --from`` reruns a fit: ``command``, ``cwd``,
``versions``, the resolved options in ``arguments`` (so a changed default does not change the rerun) and the
SHA-256 of every file read in ``files_sha256``."""
from __future__ import annotations

import hashlib
import os
import sys

from fmbrdf_mi import __version__
from fmbrdf_mi.fit.api.options import record_keys
from fmbrdf_mi.fit.inputs.manifest import absolute_paths
from fmbrdf_mi.sensor.camera import sidecar_path


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


#: The arguments of a single-image or colour fit that name files it reads.
FILE_KEYS = ("inputs", "normals", "mask", "view", "relight", "materials")


def existing_files(paths, sidecars=True):
    """The files among ``paths`` (one or a list) and, with ``sidecars``, the capture sidecar beside each but an EXR."""
    out = []
    for p in (paths if isinstance(paths, (list, tuple)) else [paths]):
        if isinstance(p, (str, os.PathLike)) and os.path.isfile(p):
            out.append(os.fspath(p))
            side = sidecar_path(p)
            if sidecars and side != out[-1] and os.path.isfile(side) and not out[-1].lower().endswith(".exr"):
                out.append(side)
    return out


def single_files(arguments):
    """The files a single-image or colour fit with ``arguments`` reads, its images' capture sidecars included."""
    return [f for k in FILE_KEYS for f in existing_files(arguments.get(k), k in ("inputs", "relight"))]


def versions():
    v = {"fmbrdf_mi": __version__, "python": sys.version.split()[0]}
    for mod in ("mitsuba", "drjit", "numpy"):
        try:
            v[mod] = __import__(mod).__version__
        except Exception:  # pragma: no cover
            v[mod] = None
    return v


def command_block(command, arguments=None, files=(), **more):
    """A ``reproduce`` block: command line, directory, versions; for ``--from``, ``arguments``, ``files``' SHA-256."""
    block = {"command": command, "cwd": os.getcwd()}
    if arguments is not None:
        block.update(arguments=arguments, files_sha256=_hashes(files), **more)
    return jsonable(dict(block, versions=versions()))


def reproduce_block(arguments, command, meta):
    """The ``reproduce`` block of a single-image or colour fit, with ``settings`` etc. of the input's ``meta``."""
    return command_block(command, arguments, single_files(arguments),
                         **{k: meta.get(k) for k in ("settings", "sphere", "sidecar")})


#: read_object keywords recorded for an authors' object.
AUTHORS_KEYS = ("mask", "holdout", "conversion_gain", "read_noise", "white_level", "dark_level", "black_level",
                "demosaic", "footprint")


def _hashes(paths):
    return {os.path.abspath(p): sha256(p) for p in paths if isinstance(p, str) and os.path.isfile(p)}


def _geometry(spec, obs):
    """Where image ``spec``'s normals, mask and view directions came from."""
    o = spec.options
    if o.get("normals") is not None:
        return {"source": "normal map", "normals": o.get("normals"), "mask": o.get("mask"),
                **({"view": o["view"]} if o.get("view") is not None else
                   {"camera": o.get("camera", "orthographic"), "fov": o.get("fov")})}
    if o.get("sphere") is not None:
        return {"source": "sphere", "sphere": o["sphere"], "mask": o.get("mask"), "view": o.get("view"),
                "camera": o.get("camera", "orthographic"), "fov": o.get("fov"), "found": obs.meta.get("sphere")}
    if obs.meta.get("truth") is not None:
        return {"source": "the input's metadata (fmbrdf-mi render, built-in sphere)"}
    return {"source": "unknown"}


def joint_block(kind, specs, names, observations, fit_kw, command, *, manifest=None, authors=None, info=None):
    """The ``reproduce`` block of a joint fit, with ``joint``: how the images were given, each one's files and
    settings; ``specs`` as fitted (paths resolved), ``authors``: read_object's keywords, ``info`` what it read."""
    images = []
    for k, (s, n, o) in enumerate(zip(specs, names, observations)):
        if kind == "authors":
            inp, entry = o.meta["authors_layout"]["file"], {}
            geo = {"source": "authors' layout", "normals": os.path.join(info["root"], "normal", "normal_GT.npy"),
                   "view": os.path.join(info["root"], "calibration", info["view_rays"]),
                   "mask": absolute_paths(info["mask"])}
            power = info["intensities"][k] if info.get("intensities") else 1.0   # intensities.npy / max
        else:
            inp, geo, power = s.input, _geometry(s, o), s.power
            entry = {"spec": {"input": inp, "light": s.light, "power": s.power, "holdout": s.holdout,
                              "name": s.name, "options": s.options}}
        geo_files = [geo.get(x) for x in ("normals", "mask", "view") if isinstance(geo.get(x), str)]
        images.append({"name": n, "input": inp, "files_sha256": _hashes(existing_files(inp) + geo_files),
                       "light": [float(x) for x in o.light_dir], "power": float(power),
                       "irradiance": float(o.irradiance), "holdout": bool(s.holdout), "geometry": geo,
                       "settings": o.meta.get("settings"), "sidecar": o.meta.get("sidecar"), **entry})
    joint = {"kind": kind, "images": images, **({} if manifest is None else {"manifest": absolute_paths(manifest)}),
             **({"authors": {"root": info["root"], **authors}} if kind == "authors" else {})}
    files = read_files(kind, specs, info) + [absolute_paths(p) for p in (manifest, fit_kw.get("materials"))
                                             if p is not None]
    arguments = {k: absolute_paths(fit_kw[k]) if k == "materials" else fit_kw[k] for k in record_keys("joint")
                 if k in fit_kw}
    return command_block(command, arguments, files, joint=joint)


def read_files(kind, specs, info):
    """The files a rerun of these images reads (an authors' object: its calibration, normal map, mask, images)."""
    if kind == "authors":
        cal = os.path.join(info["root"], "calibration")
        return [os.path.join(cal, f) for f in ("L.txt", "vpL_img.npy", "IntrinsicL.npy", "intensities.npy")
                if os.path.isfile(os.path.join(cal, f))] + [os.path.join(info["root"], "normal", "normal_GT.npy"),
                                                           absolute_paths(info["mask"])] \
            + [s.input.meta["authors_layout"]["file"] for s in specs]
    files = []
    for s in specs:
        files += [p for p in (s.input if isinstance(s.input, list) else [s.input]) if isinstance(p, str)]
        files += existing_files(s.input)
        files += [s.options[k] for k in ("normals", "mask", "view") if isinstance(s.options.get(k), str)]
    return files
