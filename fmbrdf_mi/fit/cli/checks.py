"""Checks of the ``fmbrdf-mi fit`` command line made before any file is read: one line per mistake."""
from __future__ import annotations

from fmbrdf_mi.fit.api.options import check_fit_options, check_input_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init


def check_args(args):
    """Validate the command line's options before any file is read (one line per mistake)."""

    def flag(name):
        return "--" + name.replace("_", "-")

    check_input_options(black_level=args.black_level, conversion_gain=args.conversion_gain,
                        read_noise=args.read_noise, irradiance=args.irradiance, fov=args.fov,
                        relight_irradiance=args.relight_irradiance, white_level=args.white_level,
                        dark_level=args.dark_level, flag=flag)
    check_fit_options(model=args.model, optimizer=args.optimizer, path=args.path,
                      bounds=parse_bounds(args.bounds), init=parse_init(args.init), max_iter=args.max_iter,
                      tol=args.tol, time_limit=args.time_limit, max_time=args.max_time,
                      max_pixels=args.max_pixels, erode=args.erode, seed=args.seed, loss=args.loss,
                      starts=args.starts, fixed=parse_fixed(args.fix), area_points=args.area_points, flag=flag)
    check_needs(args, ("--relight-light", "--holdout"))
    if args.manifest and args.authors:
        raise InputError("--manifest and --authors: give one of them")


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
}

#: The one table of which options a mode refuses: mode -> (options, the message's head, why).
REFUSED = {
    "colour": (("--baselines", "--relight", "--path", "--optimizer", "--init", "--loss", "--layout", "--dark-level",
                "--footprint", "--area-points"), "colour polarisation mosaic",
               "the colour fit is the likelihood of the raw samples, layout and cfa from the sidecar, pixel path, LM"),
    "refine": (("--baselines", "--free-power", "--loss"), "--refine-normals",
               "the refinement is the likelihood of the camera samples, one model, the given light powers"),
}

#: Options that need another one: flag -> (given?, what it needs).
NEEDS = {
    "--relight-light": (lambda a: a.relight_light is not None and not a.relight, "--relight IMAGE"),
    "--holdout": (lambda a: a.holdout is not None and not a.authors,
                  "--authors (in a manifest, mark images with holdout = true)"),
    "--normals-start": (lambda a: a.normals_start != "ps" and not a.refine_normals, "--refine-normals"),
    "--smooth": (lambda a: a.smooth != 0.3 and not a.refine_normals, "--refine-normals"),
    "--rounds": (lambda a: a.rounds != 0 and not a.refine_normals, "--refine-normals"),
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
