"""The one writer of fit outputs: overwrite refusal, atomic JSON, the JSON encoder.

Every fit command (single image, joint, colour, normal refinement) checks
its output directory and refuses to overwrite any of its files without
``force`` *before* it reads an input (:func:`prepare`), and writes its
``fit.json`` atomically through a temporary file (:func:`write_json`), so a
fit stopped half-way leaves no half-written record.
"""
from __future__ import annotations

import json
import os

from fmbrdf_mi._paths import check_output_dir
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.manifest import image_names
from fmbrdf_mi.fit.result import json_default


def prepare(out, files, force):
    """Check ``out`` is a usable directory and, without ``force``, that none of ``files`` exists."""
    check_output_dir(out)
    if not force:
        for p in files:
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")
    return list(files)


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


def prepare_outputs(specs, out, outputs_fn, force):
    """(names, held-out flags, output files) of a joint fit; refuses an all-held-out set, an unusable ``out``
    and, without ``force``, existing outputs (before anything is read or written)."""
    names = image_names(specs)
    holdout = [s.holdout for s in specs]
    if all(holdout):
        raise InputError("joint fit: every image is held out; fit at least one")
    return names, holdout, prepare(out, outputs_fn(out, names, holdout), force)
