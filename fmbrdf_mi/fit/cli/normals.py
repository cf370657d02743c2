"""The command line of normal refinement (``--refine-normals``): the checks of its mode (its options are the
schema's, :mod:`fmbrdf_mi.fit.api.options`)."""
from __future__ import annotations

import os

from fmbrdf_mi.fit.cli.checks import check_needs, refuse
from fmbrdf_mi.fit.errors import InputError


def check(args, joint):
    """One line per mistake, before any file is read."""
    if not args.refine_normals:
        check_needs(args, ("--normals-start", "--smooth"))
        return
    if not joint:
        raise InputError("--refine-normals: needs K >= 3 images of one view under different lights (--manifest, "
                         "--authors, or INPUT files with one --light each)")
    refuse(args, "refine")
    start = args.normals_start
    if start not in ("ps", "sphere") and not (start.endswith(".npy") and os.path.isfile(start)):
        raise InputError(f"--normals-start {start!r}: expected ps, sphere or an existing .npy file")
