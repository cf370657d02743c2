"""``fmbrdf-mi fit``: files in, estimates, plots and relighting errors out.

:func:`fmbrdf_mi.fit.outputs.single.fit_files` (``fmbrdf_mi.fit.fit_files``) is the
Python function behind the command for one image; it takes the same options
(names with underscores).  :func:`add_fit_arguments` and :func:`run_fit` plug
into :mod:`fmbrdf_mi.cli`: the option checks (:mod:`fmbrdf_mi.fit.cli.checks`),
the mode (:func:`fit_mode`), its run (:data:`RUN`), the summary.
"""
from __future__ import annotations

import sys
import time

from fmbrdf_mi.fit.cli.checks import check_args, check_colour_args
from fmbrdf_mi.fit.cli.joint import run_joint
from fmbrdf_mi.fit.cli.layout_check import mirrored_layout_hint
from fmbrdf_mi.fit.cli.normals import add_arguments as add_normal_arguments
from fmbrdf_mi.fit.cli.normals import check as check_normal_args
from fmbrdf_mi.fit.cli.request import request
from fmbrdf_mi.fit.api.options import ALBEDO_LAYOUTS
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import MODELS
from fmbrdf_mi.fit.inputs.colour import colour_sidecar
from fmbrdf_mi.fit.inputs.parse import parse_vector
from fmbrdf_mi.fit.outputs.colour import fit_colour_files
from fmbrdf_mi.fit.outputs.rerun import rerun
from fmbrdf_mi.fit.outputs.single import fit_files
from fmbrdf_mi.fit.outputs.summary import print_summary
from fmbrdf_mi.fit.uncertainty import INTERVALS


# ---------------------------------------------------------------- command line
def add_fit_arguments(p):
    g = p.add_argument_group("polarimetric image")
    g.add_argument("inputs", nargs="*", metavar="INPUT",
                   help="Stokes .exr; raw quad-Bayer mosaic (.npy, 16-bit .png/.tif); (4,H,W) .npy of "
                        "angle images; or four angle images in the order 0 45 90 135 deg")
    g.add_argument("--layout", default=None,
                   help="mosaic polariser angles, 2x2 row-major from the top left (default: the capture "
                        "sidecar's, else IMX250MZR 90,45,135,0)")
    g.add_argument("--black-level", type=float, default=None,
                   help="subtracted from raw / angle images (default: the sidecar's, else 0)")
    g.add_argument("--white-level", type=float, metavar="DN",
                   help="raw samples at or above this are clipped: their super-pixel is left out (default: "
                        "the sidecar's, else the smallest 2^b - 1, b in 8,10,12,14,16, holding the data)")
    g.add_argument("--dark-level", type=float, metavar="DN",
                   help="raw samples at or below this (raw value, black level included) are clipped: their "
                        "super-pixel is left out (default: 0 when the black level is 0, else none)")
    g.add_argument("--demosaic", default="bilinear", choices=("bilinear", "superpixel"),
                   help="raw mosaics: interpolate each angle to the super-pixel centre (default) or take "
                        "the 2x2 pixels as they are")
    g.add_argument("--channel", default="mean", help="colour channel of an RGB Stokes EXR: mean, R, G or B")
    g.add_argument("--conversion-gain", type=float, metavar="E_PER_UNIT",
                   help="camera gain in electrons per image unit (e-/DN for raw images); with --read-noise, "
                        "the DoLP term accounts for the noise bias of the observed DoLP")
    g.add_argument("--read-noise", type=float, metavar="E", help="read noise in electrons rms")
    g.add_argument("--loss", default="auto", choices=("auto", "likelihood", "paper", "intensity", "dolp"),
                   help="likelihood of the camera's samples (Poisson-Gaussian noise), or the paper's loss "
                        "(intensity MSE + weighted DoLP MSE); auto: likelihood when the camera noise is "
                        "known (--conversion-gain / a capture sidecar), else paper.  The paper's comparison: "
                        "intensity (its intensity term alone: radiometric fits) or dolp (its DoLP term "
                        "alone, overall albedo from the mean intensity); for the baselines too")
    g.add_argument("--footprint", default="auto", choices=("auto", "point", "box", "demosaic"),
                   help="what a pixel integrates over, modelled by averaging the BSDF over it: the pixel "
                        "centre, a 3x3 box, or the demosaicking's raw pixels (auto: demosaic for raw "
                        "mosaics, point otherwise)")
    g = p.add_argument_group("geometry and light (camera frame: x image right, y image up, z towards the camera)")
    g.add_argument("--normals", metavar="N.npy", help="normal map, H x W x 3 unit vectors")
    g.add_argument("--mask", metavar="M", help="object mask (.npy or .png, non-zero = object)")
    g.add_argument("--sphere", metavar="CX,CY,R|auto",
                   help="a sphere: centre and radius in pixels (pixel centres at +0.5), or auto (from --mask)")
    g.add_argument("--view", metavar="V.npy", help="view directions, H x W x 3 (default: from --camera)")
    g.add_argument("--camera", default="orthographic", choices=("orthographic", "perspective"))
    g.add_argument("--fov", type=float, help="horizontal field of view (degrees) of a perspective camera")
    g.add_argument("--light", metavar="X,Y,Z", action="append",
                   help="direction from the surface towards the light; repeated, one per INPUT: a joint fit of "
                        "several images of the object (one raw mosaic or Stokes EXR each)")
    g.add_argument("--irradiance", type=float, help="light irradiance in image units (default 1: absorbed by k_s)")
    g = p.add_argument_group("fit")
    g.add_argument("--model", default="fmbrdf", choices=tuple(MODELS))
    g.add_argument("--baselines", action="store_true",
                   help="also fit pplastic, Lambertian + Torrance-Sparrow and Oren-Nayar + Torrance-Sparrow "
                        "the same way")
    g.add_argument("--optimizer", default="lm", choices=("lm", "adam"),
                   help="Levenberg-Marquardt (forward-mode AD Jacobian) or Adam (reverse-mode gradient); "
                        "the render path needs adam")
    g.add_argument("--path", default="pixel", choices=("pixel", "render"),
                   help="per-pixel BSDF evaluation, or rendering the scene (synthetic EXRs of the built-in sphere)")
    g.add_argument("--bounds", action="append", metavar="NAME=LO:HI", help="narrow a parameter's bounds (repeatable)")
    g.add_argument("--init", metavar="NAME=V,...", help="start from these parameters instead of the coarse search")
    g.add_argument("--max-iter", type=int, default=40)
    g.add_argument("--tol", type=float, default=1e-4, help="stop when the loss falls by less than this (relative) twice")
    g.add_argument("--time-limit", type=float, help="seconds per refinement round")
    g.add_argument("--max-time", type=float, default=None,
                   help="hard wall-clock limit in seconds for each model's fit (default: none, the fit runs "
                        "until it converges); a fit it stops exits with status 3")
    g.add_argument("--fix", action="append", metavar="NAME=VALUE",
                   help="hold a shape parameter fixed, e.g. --fix kappa=0 (repeatable)")
    g.add_argument("--starts", type=int, default=2,
                   help="refine from this many of the best distinct coarse-search points and keep the best "
                        "(default %(default)s)")
    g.add_argument("--intervals", default="auto", choices=INTERVALS,
                   help="likelihood fits: auto checks each shape parameter's Fisher 95 %% interval against the "
                        "likelihood and gives the profile likelihood's ends where it fails (refits: slower on "
                        "weakly identified parameters); profile: the profile likelihood's ends for every shape "
                        "parameter (two or more refits per end); fisher: Fisher intervals only "
                        "(default %(default)s)")
    g.add_argument("--albedo", default="shared", choices=ALBEDO_LAYOUTS,
                   help="likelihood fits: one k_s, r_k for the whole object (default), or per-pixel k_s and k_b "
                        "maps (a textured object: written as k_s.exr, k_b.exr with their standard errors, the "
                        "shape parameters shared; --max-pixels 0 maps every pixel); per-pixel: one pair for the "
                        "four raw samples of a super-pixel; per-pixel-bilinear: the pairs at the super-pixel "
                        "centres, each raw sample's albedo interpolated bilinearly at its own point (textures that "
                        "change within a super-pixel, as a camera sees them)")
    g.add_argument("--albedo-smooth", metavar="TAU[,TAU_B]",
                   help="with --albedo per-pixel or per-pixel-bilinear: a Gaussian smoothness prior on the maps, "
                        "TAU the expected difference of 4-neighbouring pixels' k_s (and k_b; TAU_B for k_b "
                        "apart) in the maps' units; added to chi^2, the maps and the shape's errors are then "
                        "posterior ones (docs: how-to 'Fit a textured object'); default: no prior")
    g.add_argument("--materials", metavar="LABELS.png|npy|auto:M",
                   help="likelihood fits: a label image giving each pixel's material, each with its own eta, "
                        "alpha, beta, kappa (and, with --albedo shared, k_s, r_k): one integer per pixel of the "
                        "fit's grid (a raw mosaic's super-pixels, or its sensor pixels), 0 .. M-1; not fitted: "
                        "255 in an 8-bit PNG, 65535 in a 16-bit one, < 0 in a .npy; or auto:M: find M materials "
                        "from the image (per-pixel albedos clustered, refined on the model; refused when they "
                        "do not separate; writes labels.png; single-image fits) (docs: how-to 'Fit a textured "
                        "object')")
    g.add_argument("--area-points", type=int, metavar="M",
                   help="likelihood: model each raw sample as the mean of the BSDF over M x M points of its "
                        "pixel, as a sensor pixel integrates over its area (default: 2 for raw mosaics, raised "
                        "to 4 or 8 where 2 would bias a shape parameter by more than 0.2 standard errors, e.g. "
                        "a glossy highlight a few pixels wide, fit.json uncertainty.quadrature; 1 = the "
                        "pixel's centre for angle images and Stokes images)")
    g.add_argument("--max-pixels", type=int, default=20000, help="random subset of usable pixels (0: all)")
    g.add_argument("--erode", type=int, default=2, help="pixels removed from the mask border")
    g.add_argument("--seed", type=int, default=0)
    g = p.add_argument_group("several images of one object (joint fit: shared material, one light each)")
    g.add_argument("--manifest", metavar="FILE.toml|json",
                   help="images, lights, relative powers, geometry and held-out images (fmbrdf_mi.fit.outputs.joint)")
    g.add_argument("--authors", metavar="OBJECT_DIR",
                   help="an object in the paper authors' captured-data layout (calibration/L.txt, "
                        "image/img_ud/*.png, normal/normal_GT.npy, ...: fmbrdf_mi.fit.inputs.authors)")
    g.add_argument("--holdout", metavar="I,J,...",
                   help="with --authors: image indices not fitted but predicted (relighting check)")
    g.add_argument("--free-power", action="store_true",
                   help="estimate the relative light power of every fitted image but the first (the "
                        "reference, held at its given power; the given powers are then starting values): "
                        "fmbrdf_mi.fit.problem.free_power")
    g.add_argument("--power-start", default="ratio", choices=("ratio", "given"),
                   help="with --free-power: start the powers in closed form at every coarse-search point "
                        "(ratio, default) or at the given powers")

    add_normal_arguments(p)
    g = p.add_argument_group("relighting check")
    g.add_argument("--relight", nargs="+", metavar="INPUT", help="a second image of the object under another light")
    g.add_argument("--relight-light", metavar="X,Y,Z", help="its light direction")
    g.add_argument("--relight-irradiance", type=float)
    g = p.add_argument_group("output")
    g.add_argument("-o", "--out", required=True, metavar="DIR", help="output directory")
    g.add_argument("--from", dest="from_json", metavar="FIT.json",
                   help="rerun the fit recorded in a fit.json (same inputs, checked by SHA-256, and options)")
    g.add_argument("--force", action="store_true", help="overwrite existing outputs")
    g.add_argument("-q", "--quiet", action="store_true")


def is_joint(args):
    """Whether the arguments give several images of one object (a manifest, an authors' object, several lights
    or inputs that are not one image or four angle images)."""
    n_in = len(args.inputs or [])
    return bool(args.manifest or args.authors or len(args.light or []) > 1 or n_in not in (0, 1, 4))


def fit_mode(args):
    """The mode the arguments ask for: ``joint``, ``rerun`` (``--from``), ``colour`` (a colour mosaic) or
    ``single``; a colour sidecar is read only to tell the last two apart."""
    if is_joint(args):
        return "joint"
    if args.from_json:
        return "rerun"
    if len(args.inputs or []) == 1 and colour_sidecar(args.inputs[0]) is not None:
        return "colour"
    return "single"


def run_rerun(args, command):
    """``--from fit.json``: the recorded fit again (single image, colour or joint)."""
    if args.inputs:
        raise InputError("--from: give no INPUT files (they come from the fit.json)")
    return rerun(args.from_json, args.out, force=args.force, progress=not args.quiet, command=command)


def run_colour(args, command):
    """A colour polarisation mosaic (its capture sidecar says so)."""
    check_colour_args(args)
    lights = args.light or []
    return fit_colour_files(**request(fit_colour_files, args, inputs=args.inputs[0],
                                      light=parse_vector(lights[0] if lights else None, "--light"),
                                      max_pixels=args.max_pixels or None, progress=not args.quiet,
                                      command=command))


def run_single(args, command):
    """One polarimetric image (a Stokes EXR, a raw mosaic, angle images)."""
    if not args.inputs:
        raise InputError("no INPUT given: a Stokes .exr, a raw mosaic, angle images, or --from fit.json")
    lights = args.light or []
    kw = request(
        fit_files, args, inputs=args.inputs if len(args.inputs) > 1 else args.inputs[0],
        light=parse_vector(lights[0] if lights else None, "--light"),
        relight=None if not args.relight else (args.relight if len(args.relight) > 1 else args.relight[0]),
        relight_light=parse_vector(args.relight_light, "--relight-light"), max_pixels=args.max_pixels or None,
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

    t0 = time.time()
    check_args(args)
    command = shlex.join(["fmbrdf-mi", "fit", *getattr(args, "argv", [])])
    joint = is_joint(args)
    if getattr(args, "free_power", False) and not joint:
        raise InputError("--free-power: with --from the fit.json's options apply (give none)" if args.from_json
                         else "--free-power: needs a joint fit of two or more images (--manifest, --authors, "
                              "or several INPUTs with one --light each)")
    check_normal_args(args, joint and not args.from_json)
    report = RUN[fit_mode(args)](args, command)
    return print_summary(report, args.out, t0)


def main(argv=None):
    """Stand-alone entry: ``python -m fmbrdf_mi.fit ...`` (same as ``fmbrdf-mi fit``)."""
    import argparse

    p = argparse.ArgumentParser(prog="fmbrdf-mi fit", description=__doc__)
    add_fit_arguments(p)
    return run_fit(p.parse_args(argv))
