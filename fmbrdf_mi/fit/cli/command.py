"""``fmbrdf-mi fit``: the option checks (:mod:`fmbrdf_mi.fit.cli.checks`), the mode (:func:`fit_mode`), its run
(:data:`RUN`: one image, a colour mosaic, ``--from``, or several images through ``--manifest``, ``--authors`` or
repeated ``--light``) and the summary."""
from __future__ import annotations

import sys

from fmbrdf_mi.fit.api.options import add_arguments
from fmbrdf_mi.fit.cli.checks import check_args, check_normals, refuse, request
from fmbrdf_mi.fit.cli.layout_check import mirrored_layout_hint
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.inputs.colour import colour_sidecar, is_colour
from fmbrdf_mi.fit.inputs.manifest import (PATH_KEYS, ImageSpec, absolute_paths, build_observations, image_names,
                                           read_manifest)
from fmbrdf_mi.fit.inputs.options import IMAGE_KEYS
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init, parse_vector
from fmbrdf_mi.fit.outputs.colour import fit_colour_files
from fmbrdf_mi.fit.outputs.joint import check_distinct, run_images
from fmbrdf_mi.fit.outputs.normals import NormalRefinement
from fmbrdf_mi.fit.outputs.record import AUTHORS_KEYS
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


def run_joint(args, command):
    """``fmbrdf-mi fit --manifest M | --authors DIR | IMG1 IMG2 ... --light L1 --light L2 ...``."""
    if args.relight:
        raise InputError("--relight: in a joint fit, mark held-out images instead (holdout = true in the "
                         "manifest, --holdout with --authors)")
    if args.optimizer != "lm" or args.path != "pixel":
        raise InputError("joint fits use --optimizer lm and --path pixel")
    cli_opts = {k: v for k, v in vars(args).items() if k in IMAGE_KEYS and v is not None}   # every image's defaults
    info = authors = None
    if args.manifest:
        if args.inputs:
            raise InputError("--manifest: give no INPUT files (the manifest lists them)")
        specs = read_manifest(args.manifest)
        for s in specs:
            for k, v in cli_opts.items():
                s.options.setdefault(k, v)
    elif args.authors:
        if args.inputs:
            raise InputError("--authors: give no INPUT files (they are the directory's image/img_ud/*.png)")
        try:
            hold = [int(x) for x in str(args.holdout).split(",") if x.strip()] if args.holdout else []
        except ValueError:
            raise InputError(f"--holdout {args.holdout!r}: expected image indices such as 3,7") from None
        authors = dict({k: vars(args)[k] for k in AUTHORS_KEYS}, mask=absolute_paths(args.mask), holdout=hold,
                       white_level=65535.0 if args.white_level is None else args.white_level,
                       black_level=0.0 if args.black_level is None else args.black_level)
        specs, info = read_object(args.authors, **authors)
    else:
        if len(args.light or []) != len(args.inputs):
            raise InputError(f"--light given {len(args.light or [])} times for {len(args.inputs)} INPUT images: a "
                             "joint fit takes one light per image (four angle images of one light: use a (4, H, W) "
                             ".npy, or a manifest)")
        specs = [ImageSpec(inp, parse_vector(li, f"--light {k + 1}"), options=dict(cli_opts))
                 for k, (inp, li) in enumerate(zip(args.inputs, args.light))]
    check_distinct(specs)
    if is_colour(specs):
        refuse(args, "colour")
    if not args.authors:   # the record names files by absolute path (a rerun may start elsewhere)
        for s in specs:
            s.input = absolute_paths(s.input)
            s.options.update({k: absolute_paths(s.options[k]) for k in PATH_KEYS[1:] if k in s.options})
    fit_kw = request("joint", args, fixed=parse_fixed(args.fixed), bounds=parse_bounds(args.bounds),
                     init=parse_init(args.init))
    kind = "manifest" if args.manifest else "authors" if args.authors else "lights"
    if args.refine_normals:
        obs = build_observations(specs)
        # the authors' normals (normal/normal_GT.npy) are the ground truth
        gt = obs[0].normals.copy() if args.authors else None
        return NormalRefinement(specs, image_names(specs), obs, args.out, start=args.normals_start, lam=args.smooth,
                                model=args.model, fit_kw={k: v for k, v in fit_kw.items()
                                                          if k not in ("model", "baselines")},
                                ground_truth=gt, force=args.force, progress=not args.quiet, command=command).run()
    return run_images(kind, specs, args.out, fit_kw, command=command, force=args.force, progress=not args.quiet,
                      manifest=args.manifest, authors=authors, info=info)


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

