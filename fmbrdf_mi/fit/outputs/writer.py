"""The file handling of :class:`~fmbrdf_mi.fit.outputs.job.FitJob`: overwrite refusal (:func:`prepare`),
atomic ``fit.json`` (:func:`write_json`), an earlier fit's stale files (:func:`stale_outputs`) and a joint
fit's file names (:func:`joint_outputs`)."""
from __future__ import annotations

import json
import os

from fmbrdf_mi._paths import check_output_dir
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.inputs.manifest import given_power, image_names
from fmbrdf_mi.fit.result import json_default


def prepare(out, files, force):
    """Check ``out`` is a usable directory and, without ``force``, that none of ``files`` exists."""
    check_output_dir(out)
    if not force:
        for p in files:
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")


#: Every file a fit writes whatever its mode (single image, colour mosaic, joint, normal refinement), by name.
FIXED_OUTPUTS = ("fit.json", "profiles.png", "images.png", "history.png", "fitted_stokes.exr", "relight.png",
                 "k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png", "materials.png", "labels.png",
                 "colour_fit.png", "normals.npy", "normals.png", "normals_change.png")
#: The files a joint fit writes per image (``{}``: the image's name, as its fit.json's ``images`` lists it).
PER_IMAGE_OUTPUTS = ("relight_{}.png", "images_{}.png", "profiles_{}.png", "colour_fit_{}.png")


def stale_outputs(out, paths):
    """The files of the earlier fit in ``out`` (:data:`FIXED_OUTPUTS`, and :data:`PER_IMAGE_OUTPUTS` of the
    images its fit.json lists) that a new fit writing ``paths`` does not write; none without a fit.json."""
    record = os.path.join(out, "fit.json")
    if not os.path.isfile(record):
        return []
    names = set(FIXED_OUTPUTS)
    try:
        with open(record, encoding="utf-8") as f:
            earlier = json.load(f)
    except (OSError, ValueError):
        earlier = None
    images = earlier.get("images") if isinstance(earlier, dict) else None
    for im in images if isinstance(images, list) else ():
        name = im.get("name") if isinstance(im, dict) else None
        if isinstance(name, str) and name and os.path.basename(name) == name and name not in (".", ".."):
            names.update(p.format(name) for p in PER_IMAGE_OUTPUTS)
    keep = {os.path.basename(p) for p in paths}
    return sorted(os.path.join(out, n) for n in names - keep if os.path.isfile(os.path.join(out, n)))


def relocate(value, stage, out):
    """``value`` (a report: dicts, lists, strings) with the paths inside directory ``stage`` moved to ``out``."""
    if isinstance(value, dict):
        return {k: relocate(v, stage, out) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(relocate(v, stage, out) for v in value)
    if isinstance(value, str) and value.startswith(stage + os.sep):
        return os.path.join(out, value[len(stage) + 1:])
    return value


def write_json(path, report):
    """Write ``report`` to ``path`` as indented JSON, atomically (a ``.part`` file renamed over it)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".part"
    try:
        with open(tmp, "w") as f:
            json.dump(report, f, indent=2, default=json_default)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, path)


#: A fit with per-pixel albedos (``albedo="per-pixel"``) writes the maps too.
MAP_OUTPUTS = ("k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png")
#: A fit of several materials (``materials``: a label image) writes the label map it used.
MATERIAL_OUTPUTS = ("materials.png",)


def joint_outputs(out, names, holdout, albedo="shared", materials=None, colour=False):
    """The files a joint fit of the images ``names`` writes (``colour``: of colour mosaics; ``[None]``: a colour
    fit of one mosaic), ``fit.json`` first."""
    files = ["fit.json"] + ([] if colour else ["history.png"])
    for n, h in zip(names, holdout):
        tail = "" if n is None else f"_{n}"
        files += ([f"relight{tail}.png"] if h else [f"colour_fit{tail}.png"] if colour
                  else [f"images{tail}.png", f"profiles{tail}.png"])
    files += list(MAP_OUTPUTS) if albedo in PER_PIXEL_LAYOUTS else []
    files += list(MATERIAL_OUTPUTS) if materials is not None else []
    return [os.path.join(out, f) for f in files]


def image_entries(names, specs, observations):
    """fit.json's ``images`` of a joint fit: each image's name, input file(s), light, irradiance, given power and
    held-out flag."""
    return [{"name": n, "input": s.input if isinstance(s.input, (str, list)) else None,
             "light_dir": o.light_dir.tolist(), "irradiance": o.irradiance, "power": given_power(s, o),
             "holdout": s.holdout} for n, s, o in zip(names, specs, observations)]


def prepare_outputs(specs, out, albedo="shared", materials=None, colour=False):
    """(names, held-out flags, output files: :func:`joint_outputs`) of a joint fit; refuses an all-held-out set."""
    names = image_names(specs)
    holdout = [s.holdout for s in specs]
    if all(holdout):
        raise InputError("joint fit: every image is held out; fit at least one")
    return names, holdout, joint_outputs(out, names, holdout, albedo, materials, colour)
