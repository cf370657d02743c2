"""Checks of the ``fmbrdf-mi fit`` command line made before any file is read: one line per mistake."""
from __future__ import annotations

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init


def check_args(args):
    """Validate the command line's options before any file is read (one line per mistake)."""
    from fmbrdf_mi.fit.api.options import check_fit_options, check_input_options

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
                      starts=args.starts, fixed=parse_fixed(args.fix), flag=flag)
    if args.relight_light is not None and not args.relight:
        raise InputError("--relight-light needs --relight IMAGE")
    if args.holdout is not None and not args.authors:
        raise InputError("--holdout needs --authors (in a manifest, mark images with holdout = true)")
    if args.manifest and args.authors:
        raise InputError("--manifest and --authors: give one of them")


def check_colour_args(args):
    """Options the colour path does not take: one line naming them."""
    bad = [flag for flag, on in (("--baselines", args.baselines), ("--relight", args.relight),
                                 ("--path render", args.path != "pixel"), ("--optimizer adam", args.optimizer != "lm"),
                                 ("--init", args.init), ("--loss " + str(args.loss), args.loss not in ("auto", "likelihood")),
                                 ("--layout", args.layout), ("--dark-level", args.dark_level is not None),
                                 ("--footprint " + str(args.footprint), args.footprint != "auto"))
           if on]
    if bad:
        raise InputError(f"colour polarisation mosaic: {', '.join(bad)} not supported (the colour fit is the "
                         "likelihood of the raw samples, layout and cfa from the sidecar, pixel path, LM)")
