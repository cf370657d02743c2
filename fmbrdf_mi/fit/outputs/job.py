"""The skeleton of every mode of ``fmbrdf-mi fit`` (:class:`FitJob`) and the names of the files fits write.
:meth:`FitJob.run` writes into a staging directory whose files replace the old ones (``fit.json`` last, stale
outputs removed) only once all are written: a failed or interrupted run leaves ``out`` as it was."""
from __future__ import annotations

import json
import os
import time

from fmbrdf_mi._paths import StageProgress, check_output_dir, locked_directory, staged_directory
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.result import json_default

#: Every file a fit writes whatever its mode (single image, colour mosaic, joint, normal refinement), by name.
FIXED_OUTPUTS = ("fit.json", "profiles.png", "images.png", "history.png", "fitted_stokes.exr", "relight.png",
                 "k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png", "materials.png", "labels.png",
                 "colour_fit.png", "normals.npy", "normals.png", "normals_change.png")
#: The files a joint fit writes per image (``{}``: the image's name, as its fit.json's ``reproduce.images`` has it).
PER_IMAGE_OUTPUTS = ("relight_{}.png", "images_{}.png", "profiles_{}.png", "colour_fit_{}.png")
#: A fit with per-pixel albedos (``albedo="per-pixel"``) writes the maps too.
MAP_OUTPUTS = ("k_s.exr", "k_b.exr", "k_s_se.exr", "k_b_se.exr", "albedo_maps.png")
#: A fit of several materials (``materials``: a label image) writes the label map it used.
MATERIAL_OUTPUTS = ("materials.png",)


class FitJob:
    """One run of a fit into ``out``.  Subclasses fill in :meth:`check` (the options, before any file is read),
    :meth:`files` (``fit.json`` first), :meth:`read`, :meth:`fit`, :meth:`report` (fit.json's dict) and
    :meth:`write` (the other outputs, each passed to :meth:`wrote`; ``report`` may grow)."""

    def __init__(self, out, *, force=False, progress=True, command=None):
        self.out, self.force, self.progress, self.command = out, force, progress, command
        self.t0, self.bar = time.time(), None

    def check(self):
        pass

    def read(self):
        pass

    def write(self, report):
        pass

    def wrote(self, path):
        if self.bar is not None:
            self.bar.step(os.path.basename(path))

    def run(self):
        """Run the steps; returns the report plus the files written and the wall time (not in fit.json)."""
        self.check()
        with locked_directory(self.out):
            out, paths = self.out, list(self.files())
            check_output_dir(out)
            for p in () if self.force else paths:
                if os.path.exists(p):
                    raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")
            self.read()
            self.fit()
            report = self.report()
            with staged_directory(out, last=("fit.json",), remove=stale_outputs(out, paths)) as stage:
                self.out = stage
                self.bar = StageProgress("writing", len(paths), enabled=bool(self.progress))
                try:
                    self.write(report)
                    report = relocate(report, stage, out)
                    write_json(os.path.join(stage, "fit.json"), report)
                    self.wrote("fit.json")
                finally:
                    self.out, self.bar = out, None
        report["outputs"], report["wall_s"] = paths, time.time() - self.t0
        return report


def stale_outputs(out, paths):
    """The outputs of the earlier fit in ``out`` (by its fit.json) that a fit writing ``paths`` does not replace."""
    record = os.path.join(out, "fit.json")
    if not os.path.isfile(record):
        return []
    names = set(FIXED_OUTPUTS)
    try:
        with open(record, encoding="utf-8") as f:
            earlier = json.load(f)
    except (OSError, ValueError):
        earlier = None
    images = ((earlier.get("reproduce") or {}).get("images") or earlier.get("images")) if isinstance(earlier, dict) \
        else None   # (before one layout for every kind: a joint fit's "images")
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


def joint_outputs(out, names, holdout, albedo="shared", materials=None, colour=False):
    """The files a joint fit of the images ``names`` writes (``colour``: of colour mosaics; ``[None]``: a colour
    fit of one mosaic), ``fit.json`` first; refuses an all-held-out set."""
    if all(holdout):
        raise InputError("joint fit: every image is held out; fit at least one")
    files = ["fit.json"] + ([] if colour else ["history.png"])
    for n, h in zip(names, holdout):
        tail = "" if n is None else f"_{n}"
        files += ([f"relight{tail}.png"] if h else [f"colour_fit{tail}.png"] if colour
                  else [f"images{tail}.png", f"profiles{tail}.png"])
    files += list(MAP_OUTPUTS) if albedo in PER_PIXEL_LAYOUTS else []
    files += list(MATERIAL_OUTPUTS) if materials is not None else []
    return [os.path.join(out, f) for f in files]

