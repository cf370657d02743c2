"""fit.json's ``reproduce`` block, one format for every kind of fit, from which ``fmbrdf-mi fit --from`` reruns it:
``kind`` (``single``, ``colour``: one image's arguments; ``manifest``, ``authors``, ``lights``: how a joint fit's
images were given), ``command``, ``cwd``, the resolved options in ``arguments`` (so a changed default does not change
the rerun), the SHA-256 of every file read in ``files_sha256``, per image in ``images`` its name, input, light,
power, irradiance, held-out flag and the settings its input implied, and ``versions``."""
from __future__ import annotations

import hashlib
import os
import sys

from fmbrdf_mi import __version__
from fmbrdf_mi.fit.api.options import record_keys
from fmbrdf_mi.fit.inputs.manifest import ImageSpec, absolute_paths, given_power, image_names
from fmbrdf_mi.sensor.camera import sidecar_path

#: The kinds of a ``reproduce`` block that rerun one image's arguments; the others are joint fits'.
ONE_IMAGE = ("single", "colour")

#: The arguments of a single-image or colour fit that name files it reads.
FILE_KEYS = ("inputs", "normals", "mask", "view", "relight", "materials")

#: read_object keywords recorded for an authors' object.
AUTHORS_KEYS = ("mask", "holdout", "conversion_gain", "read_noise", "white_level", "dark_level", "black_level",
                "demosaic", "footprint")


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


def command_block(command, kind=None, arguments=None, files=(), images=(), **more):
    """A ``reproduce`` block: command line, directory, versions; for ``--from``, the ``kind`` of fit, its
    ``arguments``, ``files``' SHA-256 and the ``images`` (:func:`image_record`)."""
    block = {"command": command, "cwd": os.getcwd()}
    if arguments is not None:
        block.update(kind=kind, arguments=arguments, files_sha256={
            os.path.abspath(p): sha256(p) for p in files if isinstance(p, str) and os.path.isfile(p)},
            images=list(images), **more)
    return jsonable(dict(block, versions=versions()))


def image_record(name, spec, obs, input=None):
    """``reproduce.images``' entry of one image: its ``spec`` (:class:`~fmbrdf_mi.fit.inputs.manifest.ImageSpec`)
    and its observation ``obs``: the light, power, irradiance used and the settings its input implied."""
    return {"name": name, "input": spec.input if input is None else input, "light": [float(x) for x in obs.light_dir],
            "power": given_power(spec, obs), "irradiance": float(obs.irradiance), "holdout": bool(spec.holdout),
            **{k: obs.meta.get(k) for k in ("settings", "sphere", "sidecar")}}


def one_image_block(kind, arguments, command, observations):
    """The ``reproduce`` block of a single-image or colour fit of ``arguments``: ``observations`` are the fitted
    image's and, with ``relight``, the held-out image's."""
    inputs = [arguments["inputs"]] + ([arguments["relight"]] if arguments.get("relight") is not None else [])
    specs = [ImageSpec(x, holdout=k > 0) for k, x in enumerate(inputs)]
    return command_block(command, kind, arguments, single_files(arguments),
                         map(image_record, image_names(specs), specs, observations))


def joint_block(kind, specs, names, observations, fit_kw, command, *, manifest=None, authors=None, info=None):
    """The ``reproduce`` block of a joint fit given as ``kind``: ``specs`` as fitted (paths resolved; each image's
    ``spec`` recorded but an authors' object's), ``authors``: read_object's keywords, ``info`` what it read."""
    images = []
    for s, n, o in zip(specs, names, observations):
        if kind == "authors":
            images.append(image_record(n, s, o, input=o.meta["authors_layout"]["file"]))
        else:
            images.append(dict(image_record(n, s, o), spec={"input": s.input, "light": s.light, "power": s.power,
                                                             "holdout": s.holdout, "name": s.name,
                                                             "options": s.options}))
    more = {} if manifest is None else {"manifest": absolute_paths(manifest)}
    if kind == "authors":
        more.update(authors={"root": info["root"], **authors}, authors_layout=info)
    files = read_files(kind, specs, info) + [absolute_paths(p) for p in (manifest, fit_kw.get("materials"))
                                             if p is not None]
    arguments = {k: absolute_paths(fit_kw[k]) if k == "materials" else fit_kw[k] for k in record_keys("joint")
                 if k in fit_kw}
    return command_block(command, kind, arguments, files, images, **more)


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
