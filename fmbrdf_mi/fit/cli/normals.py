"""The command line of normal refinement (``--refine-normals``): its options and their checks."""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi.fit.cli.checks import check_needs, refuse
from fmbrdf_mi.fit.errors import InputError


def add_arguments(p):
    g = p.add_argument_group("normal refinement (a joint fit of K >= 3 images of one view)")
    g.add_argument("--refine-normals", action="store_true",
                   help="refine per-pixel normals and the material together (outputs normals.npy and plots)")
    g.add_argument("--normals-start", default="ps", metavar="ps|sphere|FILE.npy",
                   help="start map: photometric stereo (default), the mask's sphere, or a normal map file")
    g.add_argument("--smooth", type=float, default=0.3, metavar="LAMBDA",
                   help="smoothness weight (units of Stokes residuals / image mean; default %(default)s)")
    g.add_argument("--rounds", type=int, default=0,
                   help="alternation rounds (material fit, then normals) before the joint step (default %(default)s)")


def check(args, joint):
    """One line per mistake, before any file is read."""
    if not getattr(args, "refine_normals", False):
        check_needs(args, ("--normals-start", "--smooth", "--rounds"))
        return
    if args.from_json:
        raise InputError("--refine-normals: --from is not supported (rerun the command instead)")
    if not joint:
        raise InputError("--refine-normals: needs K >= 3 images of one view under different lights (--manifest, "
                         "--authors, or INPUT files with one --light each)")
    if not (np.isfinite(args.smooth) and args.smooth >= 0):
        raise InputError(f"--smooth: expected a finite value >= 0, got {args.smooth!r}")
    if args.rounds < 0:
        raise InputError(f"--rounds: expected an integer >= 0, got {args.rounds}")
    refuse(args, "refine")
    start = args.normals_start
    if start not in ("ps", "sphere") and not (start.endswith(".npy") and os.path.isfile(start)):
        raise InputError(f"--normals-start {start!r}: expected ps, sphere or an existing .npy file")
