"""The command line of joint fits (``--manifest``, ``--authors``, repeated ``--light``)."""
from __future__ import annotations

import os

from fmbrdf_mi.fit.cli.checks import refuse, request
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.options import IMAGE_KEYS
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.inputs.colour import is_colour
from fmbrdf_mi.fit.inputs.manifest import (PATH_KEYS, ImageSpec, absolute_paths, build_observations, image_names,
                                           read_manifest)
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init, parse_vector
from fmbrdf_mi.fit.outputs.joint import check_distinct, run_images
from fmbrdf_mi.fit.outputs.normals import NormalRefinement


def image_options(args):
    """The image options given (:data:`~fmbrdf_mi.fit.inputs.options.IMAGE_KEYS`): every image's defaults."""
    values = vars(args)
    return {k: values[k] for k in IMAGE_KEYS if values[k] is not None}


def run_joint(args, command):
    """``fmbrdf-mi fit --manifest M | --authors DIR | IMG1 IMG2 ... --light L1 --light L2 ...``."""

    if args.relight:
        raise InputError("--relight: in a joint fit, mark held-out images instead (holdout = true in the "
                         "manifest, --holdout with --authors)")
    if args.optimizer != "lm" or args.path != "pixel":
        raise InputError("joint fits use --optimizer lm and --path pixel")
    cli_opts = image_options(args)
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
        authors = dict(mask=None if args.mask is None else os.path.abspath(args.mask), holdout=hold,
                       conversion_gain=args.conversion_gain, read_noise=args.read_noise,
                       white_level=65535.0 if args.white_level is None else args.white_level,
                       dark_level=args.dark_level, black_level=0.0 if args.black_level is None else args.black_level,
                       demosaic=args.demosaic, footprint=args.footprint)
        specs, info = read_object(args.authors, **authors)
    else:
        if len(args.light or []) != len(args.inputs):
            raise InputError(f"--light given {len(args.light or [])} times for {len(args.inputs)} INPUT images: a joint "
                             "fit takes one light per image (four angle images of one light: use a (4, H, W) "
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
    for k in ("materials", "area_points", "albedo_smooth"):   # recorded only when given
        if fit_kw[k] is None:
            del fit_kw[k]
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
