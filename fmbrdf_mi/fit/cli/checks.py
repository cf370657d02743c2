"""Checks of the ``fmbrdf-mi fit`` command line made before any file is read: one line per mistake."""
from __future__ import annotations

from fmbrdf_mi.fit.api.options import check_fit_options, check_input_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init, parse_smooth


def check_args(args):
    """Validate the command line's options before any file is read (one line per mistake)."""

    def flag(name):
        return "--" + name.replace("_", "-")

    check_input_options(black_level=args.black_level, conversion_gain=args.conversion_gain,
                        read_noise=args.read_noise, irradiance=args.irradiance, fov=args.fov,
                        relight_irradiance=args.relight_irradiance, white_level=args.white_level,
                        dark_level=args.dark_level, flag=flag)
    if isinstance(getattr(args, "albedo_smooth", None), str):    # TAU[,TAU_B] -> tau or (tau_s, tau_b)
        args.albedo_smooth = parse_smooth(args.albedo_smooth, "--albedo-smooth")
    check_fit_options(model=args.model, optimizer=args.optimizer, path=args.path,
                      bounds=parse_bounds(args.bounds), init=parse_init(args.init), max_iter=args.max_iter,
                      tol=args.tol, time_limit=args.time_limit, max_time=args.max_time,
                      max_pixels=args.max_pixels, erode=args.erode, seed=args.seed, loss=args.loss,
                      starts=args.starts, fixed=parse_fixed(args.fix), area_points=args.area_points,
                      albedo=getattr(args, "albedo", "shared"), free_power=getattr(args, "free_power", False),
                      albedo_smooth=getattr(args, "albedo_smooth", None),
                      flag=flag)
    if getattr(args, "from_json", None):
        check_rerun_args(args)
    check_needs(args, ("--relight-light", "--holdout", "--power-start"))
    if args.manifest and args.authors:
        raise InputError("--manifest and --authors: give one of them")
    for mode in ("manifest", "authors"):
        if getattr(args, mode, None):
            refuse(args, mode)
    check_footprint_args(args)


#: The fit options' defaults that are not None, False or empty (an option differs from its default: given).
#: tests/fit/test_cli_checks.py checks this against the parser.
DEFAULTS = {"demosaic": "bilinear", "channel": "mean", "loss": "auto", "footprint": "auto",
            "camera": "orthographic", "model": "fmbrdf", "optimizer": "lm", "path": "pixel", "max_iter": 40,
            "tol": 1e-4, "starts": 2, "max_pixels": 20000, "erode": 2, "seed": 0, "power_start": "ratio",
            "normals_start": "ps", "smooth": 0.3, "rounds": 0, "intervals": "auto", "albedo": "shared"}

#: What goes with ``--from``: the output directory, --force, -q (and the command's own bookkeeping).
RERUN_TAKES = ("out", "force", "quiet", "from_json", "argv", "command", "run")


def given_options(args, keep=RERUN_TAKES):
    """The options of ``args`` given on the command line (their value is not the default), as flags."""
    bad = []
    for dest, value in vars(args).items():
        empty = value is None or value is False or (isinstance(value, (list, tuple)) and not value)
        if dest in keep or empty or (dest in DEFAULTS and value == DEFAULTS[dest]):
            continue
        bad.append("INPUT files" if dest == "inputs" else "--" + dest.replace("_", "-"))
    return bad


def check_rerun_args(args):
    """``--from fit.json`` reruns the recorded inputs and options: any other option would be ignored."""
    bad = given_options(args)
    if bad:
        raise InputError(f"--from: give no {', '.join(bad)} (the fit.json's inputs and options are rerun as "
                         "recorded; only -o/--out, --force and -q go with --from)")


def check_footprint_args(args):
    """``--footprint`` shapes only the paper's loss: refused when the loss is (or resolves to) the likelihood
    from the command line alone (a capture sidecar's noise: :func:`fmbrdf_mi.fit.problem.data.check_footprint`)."""
    if args.footprint == "auto":
        return
    auto = args.loss == "auto" and args.conversion_gain is not None and args.path == "pixel" \
        and args.optimizer == "lm"
    if args.loss == "likelihood" or auto:
        why = "--loss likelihood" if args.loss == "likelihood" else "--loss auto with --conversion-gain"
        raise InputError(f"--footprint {args.footprint}: only the paper's loss uses it; the likelihood ({why}) "
                         "models each sample over its own pixel with --area-points (or give --loss paper)")


#: Options that only some modes take: flag -> (given?, how a message names it).
OPTIONS = {
    "--baselines": (lambda a: a.baselines, lambda a: "--baselines"),
    "--relight": (lambda a: a.relight, lambda a: "--relight"),
    "--path": (lambda a: a.path != "pixel", lambda a: "--path render"),
    "--optimizer": (lambda a: a.optimizer != "lm", lambda a: "--optimizer adam"),
    "--init": (lambda a: a.init, lambda a: "--init"),
    "--loss": (lambda a: a.loss not in ("auto", "likelihood"), lambda a: "--loss " + str(a.loss)),
    "--layout": (lambda a: a.layout, lambda a: "--layout"),
    "--dark-level": (lambda a: a.dark_level is not None, lambda a: "--dark-level"),
    "--footprint": (lambda a: a.footprint != "auto", lambda a: "--footprint " + str(a.footprint)),
    "--area-points": (lambda a: a.area_points is not None, lambda a: "--area-points"),
    "--free-power": (lambda a: getattr(a, "free_power", False), lambda a: "--free-power"),
    "--channel": (lambda a: a.channel != "mean", lambda a: "--channel " + str(a.channel)),
    "--light": (lambda a: bool(a.light), lambda a: "--light"),
    "--albedo": (lambda a: getattr(a, "albedo", "shared") != "shared", lambda a: "--albedo " + str(a.albedo)),
    "--materials": (lambda a: getattr(a, "materials", None) is not None, lambda a: "--materials"),
    "--albedo-smooth": (lambda a: getattr(a, "albedo_smooth", None) is not None, lambda a: "--albedo-smooth"),
}

#: The one table of which options a mode refuses: mode -> (options, the message's head, why).
REFUSED = {
    "colour": (("--baselines", "--relight", "--path", "--optimizer", "--init", "--loss", "--layout", "--dark-level",
                "--footprint", "--area-points", "--channel", "--materials", "--albedo-smooth"),
               "colour polarisation mosaic",
               "the colour fit is the likelihood of the raw samples, layout and cfa from the sidecar, pixel path, LM; "
               "several materials and the albedo smoothness prior are for mono captures so far"),
    "manifest": (("--light",), "--manifest", "the manifest gives each image's light"),
    "authors": (("--light",), "--authors", "the lights are the object's calibration/L.txt"),
    "refine": (("--baselines", "--free-power", "--loss", "--albedo", "--materials", "--albedo-smooth"),
               "--refine-normals",
               "the refinement is the likelihood of the camera samples, one model, the given light powers, "
               "one pair of albedos, one material"),
}

#: Options that need another one: flag -> (given?, what it needs).
NEEDS = {
    "--relight-light": (lambda a: a.relight_light is not None and not a.relight, "--relight IMAGE"),
    "--holdout": (lambda a: a.holdout is not None and not a.authors,
                  "--authors (in a manifest, mark images with holdout = true)"),
    "--normals-start": (lambda a: a.normals_start != "ps" and not a.refine_normals, "--refine-normals"),
    "--smooth": (lambda a: a.smooth != 0.3 and not a.refine_normals, "--refine-normals"),
    "--rounds": (lambda a: a.rounds != 0 and not a.refine_normals, "--refine-normals"),
    "--power-start": (lambda a: getattr(a, "power_start", "ratio") != "ratio" and not getattr(a, "free_power", False),
                      "--free-power"),
}


def refuse(args, mode):
    """One line naming every option ``mode`` does not take (:data:`REFUSED`)."""
    flags, head, why = REFUSED[mode]
    bad = [OPTIONS[f][1](args) for f in flags if OPTIONS[f][0](args)]
    if bad:
        raise InputError(f"{head}: {', '.join(bad)} not supported ({why})")


def check_needs(args, flags=None):
    """One line for the first option given without the one it needs (:data:`NEEDS`)."""
    for flag in (flags or NEEDS):
        given, needs = NEEDS[flag]
        if given(args):
            raise InputError(f"{flag} needs {needs}")


def check_colour_args(args):
    """Options the colour path does not take: one line naming them."""
    refuse(args, "colour")
