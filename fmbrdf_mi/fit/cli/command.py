"""``fmbrdf-mi fit``: the command line's checks before any file is read (one line per mistake), the mode
(:func:`fit_mode`), its run (:data:`RUN`) and the summary.  The modes' rules are here (:data:`REFUSED`,
:data:`NEEDS`, :data:`RERUN_TAKES`); the values' checks are :mod:`fmbrdf_mi.fit.api.options`'."""
from __future__ import annotations

import argparse
import os
import shlex
import sys

from fmbrdf_mi.fit.api.options import (OPTION, add_arguments, check_fit_options, check_input_options, flag,
                                        record_keys)
from fmbrdf_mi.fit.cli.layout_check import mirrored_layout_hint
from fmbrdf_mi import check_variant
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.pixel_model import set_variant
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

#: The options each flag of the command line sets: ``--max-pixels`` -> ``max_pixels``.
DEST = {flag(o.name): o.name for o in OPTION.values() if o.flag is not None and o.flag.startswith("-")}

#: The parser's defaults (what an option that is not given holds).
DEFAULTS = {o.name: o.cli.get("default", o.default) for o in OPTION.values() if o.flag is not None}

#: What goes with ``--from``: the output directory, --force, -q, --variant.
RERUN_TAKES = ("out", "force", "quiet", "from_json", "variant")

#: Options a message names with their value (``--path render``).
WITH_VALUE = tuple(n for n, o in OPTION.items() if o.kind == "choice") + ("channel",)

#: Values of an option that a mode taking only the likelihood accepts besides the default.
ALSO_TAKEN = {"loss": ("likelihood",)}

#: The options each mode refuses: mode -> (flags, the message's head, why).
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


def check_args(args):
    values = vars(args)
    for o in OPTION.values():    # a list written as comma-separated text, recorded as the list
        if o.name in values:
            values[o.name] = o.split(values[o.name], flag(o.name))
    check_input_options(**values, flag=flag)
    check_fit_options(**values, flag=flag)
    bad = given_options(args) if args.from_json else None
    if bad:    # the record is rerun as it is: every other option typed is refused, even at its default
        raise InputError(f"--from: give no {', '.join(bad)} (the fit.json's inputs and options are rerun as "
                         "recorded; only -o/--out, --force and -q go with --from)")
    check_needs(args)
    if args.manifest and args.authors:
        raise InputError("--manifest and --authors: give one of them")
    for mode in ("manifest", "authors"):
        if values[mode]:
            refuse(args, mode)
    if args.footprint != "auto" and (args.loss == "likelihood" or (
            args.loss == "auto" and args.conversion_gain is not None and args.path == "pixel"
            and args.optimizer == "lm")):   # the likelihood from the command line alone (a sidecar's: later)
        why = "--loss likelihood" if args.loss == "likelihood" else "--loss auto with --conversion-gain"
        raise InputError(f"--footprint {args.footprint}: only the paper's loss uses it; the likelihood ({why}) "
                         "models each sample over its own pixel with --area-points (or give --loss paper)")


def check_needs(args):
    """One line for the first option given without the one it needs (:data:`NEEDS`)."""
    for f, (needed, text) in NEEDS.items():
        if given(args, f) and not given(args, needed):
            raise InputError(f"{f} needs {text}")


class Unset(list):
    """The marker of an option not typed (a list, so that options given repeatedly append to it)."""


def typed_options(argv):
    """The options typed on the command line ``argv``, whatever their value (argparse replaces :class:`Unset` s)."""
    p = argparse.ArgumentParser(add_help=False)
    add_arguments(p)
    ns, _ = p.parse_known_args(argv, namespace=argparse.Namespace(**{name: Unset() for name in DEFAULTS}))
    return [name for name, v in vars(ns).items() if name in DEFAULTS and not (isinstance(v, Unset) and not v)]


def given_options(args, keep=RERUN_TAKES):
    """The options typed (from ``args.argv``, else those not at their default) as flags, less ``keep``."""
    names = typed_options(args.argv) if "argv" in vars(args) else [
        k for k, v in vars(args).items() if k in DEFAULTS and v != DEFAULTS[k]]
    return sorted("INPUT files" if n == "inputs" else flag(n) for n in names
                  if n not in keep and not (n == "inputs" and not args.inputs))


def given(args, option):
    """Whether the flag ``option`` holds a value other than its default (or :data:`ALSO_TAKEN`)."""
    name = DEST[option]
    v = vars(args)[name]
    return not (v is None or v is False or v == [] or v == DEFAULTS[name] or v in ALSO_TAKEN.get(name, ()))


def named(args, option):
    """How a message names the option ``option`` as given: ``--path render``, ``--baselines``."""
    name = DEST[option]
    return f"{option} {vars(args)[name]}" if name in WITH_VALUE else option


def refuse(args, mode):
    """One line naming every option ``mode`` does not take (:data:`REFUSED`)."""
    flags, head, why = REFUSED[mode]
    bad = [named(args, f) for f in flags if given(args, f)]
    if bad:
        raise InputError(f"{head}: {', '.join(bad)} not supported ({why})")


def request(record, args, **converted):
    """The options of ``record`` (:func:`~fmbrdf_mi.fit.api.options.record_keys`, less those it keeps only when
    given) as parsed, ``--max-pixels 0`` as None, the lights as vectors, then ``converted``."""
    values = vars(args)
    kw = {k: values[k] for k in record_keys(record) if values[k] is not None or record not in OPTION[k].if_given}
    kw["max_pixels"] = kw["max_pixels"] or None
    if "light" in kw:
        kw["light"] = parse_vector((kw["light"] or [None])[0], "--light")
    if "relight_light" in kw:
        kw["relight_light"] = parse_vector(kw["relight_light"], "--relight-light")
    return {**kw, **converted}


def is_joint(args):
    """Whether the arguments give several images (a manifest, an authors' object, several lights, or INPUTs that are
    not one image or four angle images)."""
    return bool(args.manifest or args.authors or len(args.light or []) > 1 or len(args.inputs or []) not in (0, 1, 4))


def fit_mode(args):
    """The mode the arguments ask for: ``joint``, ``rerun`` (``--from``), ``colour`` or ``single``."""
    if is_joint(args):
        return "joint"
    if args.from_json:
        return "rerun"
    return "colour" if len(args.inputs or []) == 1 and colour_sidecar(args.inputs[0]) is not None else "single"


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
    one = lambda files: files if len(files) > 1 else files[0]   # noqa: E731
    kw = request("single", args, out=args.out, force=args.force, inputs=one(args.inputs),
                 relight=one(args.relight) if args.relight else None, progress=not args.quiet, command=command)
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
    if (args.manifest or args.authors) and args.inputs:
        raise InputError("--manifest: give no INPUT files (the manifest lists them)" if args.manifest else
                         "--authors: give no INPUT files (they are the directory's image/img_ud/*.png)")
    if args.manifest:
        specs = read_manifest(args.manifest)
        for s in specs:
            s.options.update({k: v for k, v in cli_opts.items() if k not in s.options})
    elif args.authors:
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
    if args.refine_normals:
        obs = build_observations(specs)
        return NormalRefinement(specs, image_names(specs), obs, args.out, start=args.normals_start, lam=args.smooth,
                                model=args.model, fit_kw={k: v for k, v in fit_kw.items()
                                                          if k not in ("model", "baselines")},
                                ground_truth=obs[0].normals.copy() if args.authors else None,  # normal_GT.npy
                                force=args.force, progress=not args.quiet, command=command).run()
    kind = "manifest" if args.manifest else "authors" if args.authors else "lights"
    return run_images(kind, specs, args.out, fit_kw, command=command, force=args.force, progress=not args.quiet,
                      manifest=args.manifest, authors=authors, info=info)


#: The function that runs each mode: (arguments, command line) -> the report written to fit.json.
RUN = {"joint": run_joint, "rerun": run_rerun, "colour": run_colour, "single": run_single}


def run_fit(args):
    """``fmbrdf-mi fit``: the option checks (before any file is read), the mode, its run, the summary."""
    check_args(args)
    if args.variant:    # a cuda_ variant without a device: one line, before any file is read
        check_variant(args.variant)
        set_variant(args.variant)
    command = shlex.join(["fmbrdf-mi", "fit", *args.argv])
    joint = is_joint(args)
    if args.free_power and not joint:
        raise InputError("--free-power: needs a joint fit of two or more images (--manifest, --authors, or several "
                         "INPUTs with one --light each)")
    if args.refine_normals:
        if not joint:
            raise InputError("--refine-normals: needs K >= 3 images of one view under different lights (--manifest, "
                             "--authors, or INPUT files with one --light each)")
        refuse(args, "refine")
        start = args.normals_start
        if start not in ("ps", "sphere") and not (start.endswith(".npy") and os.path.isfile(start)):
            raise InputError(f"--normals-start {start!r}: expected ps, sphere or an existing .npy file")
    return print_summary(RUN[fit_mode(args)](args, command))
