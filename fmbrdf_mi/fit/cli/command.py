"""``fmbrdf-mi fit``: the option checks (:mod:`fmbrdf_mi.fit.cli.checks`), the mode (:func:`fit_mode`), its run
(:data:`RUN`) and the summary."""
from __future__ import annotations

import sys

from fmbrdf_mi.fit.cli.checks import check_args, check_normals, refuse, request
from fmbrdf_mi.fit.cli.joint import run_joint
from fmbrdf_mi.fit.cli.layout_check import mirrored_layout_hint
from fmbrdf_mi.fit.api.options import add_arguments
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.colour import colour_sidecar
from fmbrdf_mi.fit.outputs.colour import fit_colour_files
from fmbrdf_mi.fit.outputs.rerun import rerun
from fmbrdf_mi.fit.outputs.single import fit_files
from fmbrdf_mi.fit.outputs.summary import print_summary


add_fit_arguments = add_arguments


def is_joint(args):
    """Whether the arguments give several images of one object (a manifest, an authors' object, several lights
    or inputs that are not one image or four angle images)."""
    n_in = len(args.inputs or [])
    return bool(args.manifest or args.authors or len(args.light or []) > 1 or n_in not in (0, 1, 4))


def fit_mode(args):
    """The mode the arguments ask for: ``joint``, ``rerun`` (``--from``), ``colour`` or ``single``."""
    if is_joint(args):
        return "joint"
    if args.from_json:
        return "rerun"
    if len(args.inputs or []) == 1 and colour_sidecar(args.inputs[0]) is not None:
        return "colour"
    return "single"


def run_rerun(args, command):
    """``--from fit.json``: the recorded fit again (single image, colour or joint)."""
    return rerun(args.from_json, args.out, force=args.force, progress=not args.quiet, command=command)


def run_colour(args, command):
    """A colour polarisation mosaic (its capture sidecar says so)."""
    refuse(args, "colour")
    return fit_colour_files(**request("colour", args, inputs=args.inputs[0]), out=args.out, force=args.force,
                            progress=not args.quiet, command=command)


def run_single(args, command):
    """One polarimetric image (a Stokes EXR, a raw mosaic, angle images)."""
    if not args.inputs:
        raise InputError("no INPUT given: a Stokes .exr, a raw mosaic, angle images, or --from fit.json")
    kw = request(
        "single", args, out=args.out, force=args.force, inputs=args.inputs if len(args.inputs) > 1 else args.inputs[0],
        relight=None if not args.relight else (args.relight if len(args.relight) > 1 else args.relight[0]),
        progress=not args.quiet, command=command)
    report = fit_files(**kw)
    hint = mirrored_layout_hint(report, kw, fit_files, progress=not args.quiet)
    if hint:
        print(f"fmbrdf-mi fit: {hint}", file=sys.stderr, flush=True)
    return report


#: The function that runs each mode: (arguments, command line) -> the report written to fit.json.
RUN = {"joint": run_joint, "rerun": run_rerun, "colour": run_colour, "single": run_single}


def run_fit(args):
    """``fmbrdf-mi fit``: the option checks (before any file is read), the mode, its run, the summary."""
    import shlex

    check_args(args)
    command = shlex.join(["fmbrdf-mi", "fit", *args.argv])
    joint = is_joint(args)
    if args.free_power and not joint:
        raise InputError("--free-power: needs a joint fit of two or more images (--manifest, --authors, or several "
                         "INPUTs with one --light each)")
    check_normals(args, joint)
    report = RUN[fit_mode(args)](args, command)
    return print_summary(report)

