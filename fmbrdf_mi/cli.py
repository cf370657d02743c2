"""The ``fmbrdf-mi`` command line (also ``python -m fmbrdf_mi``).

    fmbrdf-mi render out/sphere.exr                       # built-in sphere scene
    fmbrdf-mi render -s scenes/spheres.xml -D alpha_1=0.5 --res 384x128 out/spheres.exr
    fmbrdf-mi render --list-params [-s scene.xml]
    fmbrdf-mi dataset --config scenes/dataset_example.toml --out data/ds [--shard I/N]

The dispatcher: each subcommand lives in its own module (``render``:
:mod:`fmbrdf_mi.render`; ``fit``: :mod:`fmbrdf_mi.fit.cli.command`; ``dataset``:
:mod:`fmbrdf_mi.dataset.command`; ``fit-brdf``: :mod:`fmbrdf_mi.brdf_fit.command`;
``example-data``: :mod:`fmbrdf_mi.synthetic.examples`).
Adding a subcommand ``NAME``: write ``add_NAME_arguments(parser)`` and
``run_NAME(args) -> int``, then add one line to :data:`SUBCOMMANDS`.  Raise
:class:`CLIError` (or any of :data:`USER_ERRORS`) for problems the user can
fix: :func:`main` prints them as one line ``fmbrdf-mi NAME: error: ...`` on
stderr and returns 1, without a traceback (set ``FMBRDF_MI_TRACEBACK=1`` to see
one).  Import Mitsuba inside ``run_NAME`` only after the arguments are checked,
so that mistakes are reported at once.
"""
from __future__ import annotations

import argparse
import os
import sys

from . import __version__
from ._llvm import LLVMTooOldError
from ._paths import PROG, CLIError
from .brdf_fit.command import HELP as FIT_BRDF_HELP, add_fit_brdf_arguments, run_fit_brdf
from .dataset.command import HELP as DATASET_HELP, add_dataset_arguments, run_dataset
from .fit.cli.command import add_fit_arguments, run_fit
from .params import ParameterError
from .render import HELP as RENDER_HELP, add_render_arguments, run_render
from .synthetic.examples import HELP as EXAMPLE_DATA_HELP, add_example_data_arguments, run_example_data

__all__ = ["CLIError", "USER_ERRORS", "SUBCOMMANDS", "build_parser", "main", "console_main"]

#: Exceptions reported as a one-line error message (no traceback).  OSError covers
#: the operating system's errors (permissions, a full disk, ...): they name the path.
USER_ERRORS = (CLIError, ParameterError, ValueError, OSError, LLVMTooOldError)


def _error_text(e):
    """One line for a user error; an OSError names its path."""
    if isinstance(e, OSError) and e.filename is not None and e.strerror:
        return f"{e.filename}: {e.strerror}"
    return " ".join(str(e).split()) or type(e).__name__


#: (name, help, add_arguments, run): one line per subcommand.
SUBCOMMANDS = [
    ("render", RENDER_HELP, add_render_arguments, run_render),
    ("fit", "estimate FMBRDF parameters from one polarimetric image (inverse rendering)",
     add_fit_arguments, run_fit),
    ("dataset", DATASET_HELP, add_dataset_arguments, run_dataset),
    ("fit-brdf", FIT_BRDF_HELP, add_fit_brdf_arguments, run_fit_brdf),
    ("example-data", EXAMPLE_DATA_HELP, add_example_data_arguments, run_example_data),
]


def build_parser():
    parser = argparse.ArgumentParser(
        prog=PROG, description="Fresnel Microfacet BRDF for Mitsuba 3: polarimetric rendering.")
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_, add_arguments, run in SUBCOMMANDS:
        p = sub.add_parser(name, help=help_, description=help_)
        add_arguments(p)
        p.set_defaults(run=run)
    return parser


def main(argv=None):
    """Run the command line; returns the exit status (0 on success)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    args.argv = argv[argv.index(args.command) + 1:]
    try:
        return int(args.run(args) or 0)
    except USER_ERRORS as e:
        if os.environ.get("FMBRDF_MI_TRACEBACK"):
            raise
        print(f"{PROG} {args.command}: error: {_error_text(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        return 130
    except RuntimeError as e:
        from .interrupt import interrupted

        if not interrupted(e) or os.environ.get("FMBRDF_MI_TRACEBACK"):
            raise
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        return 130


def console_main():
    """Entry point of the ``fmbrdf-mi`` console script."""
    sys.exit(main())
