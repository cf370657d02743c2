"""Checks of the ``fmbrdf-mi fit`` command line made before any file is read, one line per mistake, and the
entry points' keyword arguments from it (:func:`request`).

The options' values are checked by :mod:`fmbrdf_mi.fit.api.options`; here are the modes' rules: what a
mode refuses (:data:`REFUSED`), what needs another option (:data:`NEEDS`), what goes with ``--from``.
"""
from __future__ import annotations

import argparse
import os

from fmbrdf_mi.fit.api.options import (OPTION, add_arguments, check_fit_options, check_input_options, flag,
                                        record_keys)
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.parse import parse_vector

#: The options each flag of the command line sets: ``--max-pixels`` -> ``max_pixels``.
DEST = {flag(o.name): o.name for o in OPTION.values() if o.flag is not None and o.flag.startswith("-")}

#: The parser's defaults (what an option that is not given holds).
DEFAULTS = {o.name: o.cli.get("default", o.default) for o in OPTION.values() if o.flag is not None}


def check_args(args):
    """Validate the command line's options."""
    values = vars(args)
    for o in OPTION.values():    # a list written as comma-separated text, recorded as the list
        if o.name in values:
            values[o.name] = o.split(values[o.name], flag(o.name))
    check_input_options(**values, flag=flag)
    check_fit_options(**values, flag=flag)
    if args.from_json:
        check_rerun_args(args)
    check_needs(args)
    if args.manifest and args.authors:
        raise InputError("--manifest and --authors: give one of them")
    for mode in ("manifest", "authors"):
        if values[mode]:
            refuse(args, mode)
    check_footprint_args(args)


#: What goes with ``--from``: the output directory, --force, -q.
RERUN_TAKES = ("out", "force", "quiet", "from_json")


class Unset(list):
    """The marker of an option not typed (a list, so that options given repeatedly append to it)."""


def typed_options(argv):
    """The options typed on the command line ``argv``, whatever their value (argparse replaces the
    :class:`Unset` marker only for the options given)."""
    p = argparse.ArgumentParser(add_help=False)
    add_arguments(p)
    ns = argparse.Namespace(**{name: Unset() for name in DEFAULTS})
    ns, _ = p.parse_known_args(argv, namespace=ns)
    return [name for name, v in vars(ns).items() if name in DEFAULTS and not (isinstance(v, Unset) and not v)]


def given_options(args, keep=RERUN_TAKES):
    """The options typed (from ``args.argv``, else those not at their default) as flags, less ``keep``."""
    if "argv" in vars(args):
        names = typed_options(args.argv)
    else:
        names = [k for k, v in vars(args).items() if k in DEFAULTS and v != DEFAULTS[k]]
    names = [n for n in names if n not in keep and not (n == "inputs" and not args.inputs)]
    return sorted("INPUT files" if n == "inputs" else flag(n) for n in names)


def check_rerun_args(args):
    """Refuse every option typed with ``--from`` (even at its default): the record is rerun as it is."""
    bad = given_options(args)
    if bad:
        raise InputError(f"--from: give no {', '.join(bad)} (the fit.json's inputs and options are rerun as "
                         "recorded; only -o/--out, --force and -q go with --from)")


def check_footprint_args(args):
    """Refuse ``--footprint`` when the command line alone resolves the loss to the likelihood (a sidecar's
    noise: :func:`fmbrdf_mi.fit.problem.data.check_footprint`)."""
    if args.footprint == "auto":
        return
    auto = args.loss == "auto" and args.conversion_gain is not None and args.path == "pixel" \
        and args.optimizer == "lm"
    if args.loss == "likelihood" or auto:
        why = "--loss likelihood" if args.loss == "likelihood" else "--loss auto with --conversion-gain"
        raise InputError(f"--footprint {args.footprint}: only the paper's loss uses it; the likelihood ({why}) "
                         "models each sample over its own pixel with --area-points (or give --loss paper)")


#: Options a message names with their value (``--path render``).
WITH_VALUE = tuple(n for n, o in OPTION.items() if o.kind == "choice") + ("channel",)

#: Values of an option that a mode taking only the likelihood accepts besides the default.
ALSO_TAKEN = {"loss": ("likelihood",)}


def given(args, option):
    """Whether the flag ``option`` holds a value other than its default (or :data:`ALSO_TAKEN`)."""
    name = DEST[option]
    v = vars(args)[name]
    return not (v is None or v is False or v == [] or v == DEFAULTS[name] or v in ALSO_TAKEN.get(name, ()))


def named(args, option):
    """How a message names the option ``option`` as given: ``--path render``, ``--baselines``."""
    name = DEST[option]
    return f"{option} {vars(args)[name]}" if name in WITH_VALUE else option


#: The one table of which options a mode refuses: mode -> (options, the message's head, why).  A colour mosaic
#: refuses every option of a single-image fit that its own record does not keep, the normal refinement those the
#: schema says it refuses (``refused_by``).
REFUSED = {
    "colour": (tuple(flag(n) for n in record_keys("single") if n not in record_keys("colour")),
               "colour polarisation mosaic",
               "the colour fit is the likelihood of the raw samples, layout and cfa from the sidecar, pixel path, LM; "
               "several materials and the albedo smoothness prior are for mono captures so far"),
    "manifest": (("--light",), "--manifest", "the manifest gives each image's light"),
    "authors": (("--light",), "--authors", "the lights are the object's calibration/L.txt"),
    "refine": (tuple(flag(n) for n, o in OPTION.items() if "refine" in o.refused_by), "--refine-normals",
               "the refinement is the likelihood of the camera samples, one model, the given light powers, "
               "one pair of albedos, one material"),
}

#: Options that need another one: flag -> (the option needed, how the message names it).
NEEDS = {
    "--relight-light": ("--relight", "--relight IMAGE"),
    "--holdout": ("--authors", "--authors (in a manifest, mark images with holdout = true)"),
    "--normals-start": ("--refine-normals", "--refine-normals"),
    "--smooth": ("--refine-normals", "--refine-normals"),
    "--power-start": ("--free-power", "--free-power"),
}


def refuse(args, mode):
    """One line naming every option ``mode`` does not take (:data:`REFUSED`)."""
    flags, head, why = REFUSED[mode]
    bad = [named(args, f) for f in flags if given(args, f)]
    if bad:
        raise InputError(f"{head}: {', '.join(bad)} not supported ({why})")


def check_needs(args):
    """One line for the first option given without the one it needs (:data:`NEEDS`)."""
    for f in NEEDS:
        needed, text = NEEDS[f]
        if given(args, f) and not given(args, needed):
            raise InputError(f"{f} needs {text}")


def check_normals(args, joint):
    """The normal refinement's mode (``joint``: the arguments give several images)."""
    if not args.refine_normals:
        return
    if not joint:
        raise InputError("--refine-normals: needs K >= 3 images of one view under different lights (--manifest, "
                         "--authors, or INPUT files with one --light each)")
    refuse(args, "refine")
    start = args.normals_start
    if start not in ("ps", "sphere") and not (start.endswith(".npy") and os.path.isfile(start)):
        raise InputError(f"--normals-start {start!r}: expected ps, sphere or an existing .npy file")


def request(record, args, **converted):
    """The options of ``record`` (``single``, ``colour`` or ``joint``:
    :func:`~fmbrdf_mi.fit.api.options.record_keys`, less those it keeps only when given) as parsed,
    ``--max-pixels 0`` as None, ``--light`` and ``--relight-light`` parsed, then ``converted`` (values the
    command converts itself)."""
    values = vars(args)
    kw = {k: values[k] for k in record_keys(record) if values[k] is not None or record not in OPTION[k].if_given}
    kw["max_pixels"] = kw["max_pixels"] or None
    if "light" in kw:
        kw["light"] = parse_vector((kw["light"] or [None])[0], "--light")
    if "relight_light" in kw:
        kw["relight_light"] = parse_vector(kw["relight_light"], "--relight-light")
    return {**kw, **converted}
