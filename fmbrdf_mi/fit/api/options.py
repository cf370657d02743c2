"""The one option schema of a fit, :data:`OPTIONS`, from which :class:`FitOptions`, the command line
(:func:`add_arguments`), the checks and the keys a record keeps (:func:`record_keys`) are generated."""
from __future__ import annotations

import dataclasses

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.evaluate.models import MODELS, get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import FIT_VARIANTS
from fmbrdf_mi.fit.inputs.files import check_image_options
from fmbrdf_mi.fit.inputs.options import IMAGE_OPTIONS, RECORDS, Option
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed, parse_init
from fmbrdf_mi.fit.objectives.loss_variants import VARIANTS
from fmbrdf_mi.fit.uncertainty import INTERVALS

#: The albedo layouts a fit can be asked for (``FitOptions.albedo``, ``--albedo``).
ALBEDO_LAYOUTS = ("shared",) + PER_PIXEL_LAYOUTS

#: The albedo prior's smallest smoothness scale tau: below it 1 / tau^2 drowns the data in double precision.
SMOOTH_MIN = 1e-6

_IMAGE, _GEOMETRY = IMAGE_OPTIONS[0].group, IMAGE_OPTIONS[-1].group
_FIT = "fit"
_JOINT = "several images of one object (joint fit: shared material, one light each)"
_NORMALS = "normal refinement (a joint fit of K >= 3 images of one view)"
_RELIGHT = "relighting check"
_OUTPUT = "output"
_ALL = RECORDS
_SJ = ("single", "joint")
_REFINE = ("refine",)

#: The command line's help sections, in order.
GROUPS = (_IMAGE, _GEOMETRY, _FIT, _JOINT, _NORMALS, _RELIGHT, _OUTPUT)

#: Every option, declared once.
OPTIONS = (
    Option("inputs", None, flag="inputs", group=_IMAGE, records=("single", "colour"),
           cli={"nargs": "*", "metavar": "INPUT", "default": []},
           help="Stokes .exr; raw quad-Bayer mosaic (.npy, 16-bit .png/.tif); (4,H,W) .npy of angle images; or "
                "four angle images in the order 0 45 90 135 deg"),
    *IMAGE_OPTIONS,
    Option("loss", "auto", kind="choice", choices=("auto", "likelihood", "paper", "intensity", "dolp"), fit=True,
           records=_SJ, refused_by=_REFINE, flag="--loss", group=_IMAGE,
           help="likelihood of the camera's samples (Poisson-Gaussian noise) or the paper's loss (intensity MSE + "
                "weighted DoLP MSE); auto: likelihood when the camera noise is known (--conversion-gain / a capture "
                "sidecar), else paper; intensity, dolp: one term of the paper's loss alone (docs: computed.md)"),
    Option("light", None, flag="--light", group=_GEOMETRY, records=("single", "colour"),
           cli={"metavar": "X,Y,Z", "action": "append"},
           help="direction from the surface towards the light; repeated, one per INPUT: a joint fit of several "
                "images of the object (one raw mosaic or Stokes EXR each)"),
    Option("model", "fmbrdf", kind="choice", choices=tuple(MODELS), fit=True, records=_ALL, flag="--model",
           group=_FIT, help="the model fitted"),
    Option("baselines", False, kind="bool", records=_SJ, refused_by=_REFINE, flag="--baselines", group=_FIT,
           cli={"action": "store_true"},
           help="also fit pplastic, Lambertian + Torrance-Sparrow and Oren-Nayar + Torrance-Sparrow the same way"),
    Option("optimizer", "lm", kind="choice", choices=("lm", "adam"), fit=True, records=("single",),
           flag="--optimizer", group=_FIT,
           help="Levenberg-Marquardt (forward-mode AD Jacobian) or Adam (reverse-mode gradient); the render path "
                "needs adam"),
    Option("path", "pixel", kind="choice", choices=("pixel", "render"), fit=True, records=("single",), flag="--path",
           group=_FIT,
           help="per-pixel BSDF evaluation, or rendering the scene (synthetic EXRs of the built-in sphere)"),
    Option("bounds", None, fit=True, records=_ALL, flag="--bounds", group=_FIT, parse=parse_bounds,
           cli={"action": "append", "metavar": "NAME=LO:HI"},
           help="narrow a parameter's bounds (repeatable): {name: (lo, hi)}"),
    Option("init", None, fit=True, records=_SJ, flag="--init", group=_FIT, parse=parse_init,
           cli={"metavar": "NAME=V,..."},
           help="start from these parameters instead of the coarse search (all the reported ones; with "
                "per-pixel albedos the shape parameters)"),
    Option("max_iter", 40, kind="int", lo=1, fit=True, records=_ALL, flag="--max-iter", group=_FIT,
           help="iterations per refinement round"),
    Option("tol", 1e-4, kind="number", lo=0.0, fit=True, records=_SJ, flag="--tol", group=_FIT,
           help="stop when the loss falls by less than this (relative) twice (the paper's loss)"),
    Option("time_limit", None, kind="number", lo=0.0, lo_open=True, fit=True, records=_SJ, flag="--time-limit",
           group=_FIT, help="seconds per refinement round"),
    Option("max_time", None, kind="number", lo=0.0, fit=True, records=_ALL, flag="--max-time", group=_FIT,
           help="hard wall-clock limit in seconds for each model's fit (default: none, the fit runs until it "
                "converges); a fit it stops exits with status 3"),
    Option("fixed", None, fit=True, records=_ALL, flag="--fix", group=_FIT, parse=parse_fixed,
           cli={"action": "append", "metavar": "NAME=VALUE"},
           help="hold a shape parameter fixed, e.g. --fix kappa=0 (repeatable)"),
    Option("starts", 2, kind="int", lo=1, fit=True, records=_ALL, flag="--starts", group=_FIT,
           help="refine from this many of the best distinct coarse-search points and keep the best "
                "(default %(default)s)"),
    Option("intervals", "auto", kind="choice", choices=INTERVALS, fit=True, records=_ALL, flag="--intervals",
           group=_FIT,
           help="likelihood fits: auto checks each shape parameter's Fisher 95 %% interval against the profile "
                "likelihood and gives the profile's ends where it fails; profile: the profile's ends for every shape "
                "parameter (slower); fisher: Fisher intervals only (default %(default)s; docs: computed.md)"),
    Option("albedo", "shared", kind="choice", choices=ALBEDO_LAYOUTS, fit=True, records=_ALL, refused_by=_REFINE,
           flag="--albedo", group=_FIT,
           help="likelihood fits: one k_s, r_k for the whole object (default), or k_s, k_b maps with their standard "
                "errors, the shape parameters shared: per-pixel (one pair per super-pixel) or per-pixel-bilinear (the "
                "pairs at the super-pixel centres, interpolated at each raw sample) (docs: how-to 'Fit a textured "
                "object')"),
    Option("albedo_smooth", None, kind="number", lo=SMOOTH_MIN, many=2, fit=True, records=_SJ, if_given=("joint",),
           refused_by=_REFINE, flag="--albedo-smooth", group=_FIT, cli={"metavar": "TAU[,TAU_B]"},
           help="with --albedo per-pixel or per-pixel-bilinear: a Gaussian smoothness prior on the maps, TAU the "
                "expected difference of 4-neighbouring pixels' k_s (and k_b; TAU_B for k_b apart) in the maps' "
                f"units, at least {SMOOTH_MIN:g}; added to chi^2, the maps and the shape's "
                "errors are then posterior ones (docs: how-to 'Fit a textured object'); default: no prior"),
    Option("materials", None, records=_SJ, if_given=("joint",), refused_by=_REFINE, flag="--materials", group=_FIT,
           cli={"metavar": "LABELS.png|npy|auto:M"},
           help="likelihood fits: a label image of each pixel's material (0 .. M-1 on the fit's grid; not fitted: "
                "255 / 65535 in a PNG, < 0 in a .npy), each with its own eta, alpha, beta, kappa (and, with --albedo "
                "shared, k_s, r_k); or auto:M: find M materials in one image, writing labels.png (docs: how-to 'Fit "
                "a textured object')"),
    Option("area_points", None, kind="int", lo=1, hi=16, fit=True, records=_SJ, if_given=("joint",),
           flag="--area-points", group=_FIT, cli={"metavar": "M"},
           help="likelihood: model each raw sample as the BSDF's mean over M x M points of its pixel (default: 2 "
                "for raw mosaics, raised to 4 or 8 where 2 would bias a shape parameter, fit.json "
                "uncertainty.quadrature; 1 (the centre) for angle and Stokes images) (docs: computed.md)"),
    Option("variant", None, kind="choice", choices=FIT_VARIANTS, flag="--variant", group=_FIT,
           help="the Mitsuba variant that evaluates the model: cuda_ad_mono_polarized on a GPU (default: "
                "llvm_ad_mono_polarized, or the CUDA one where Dr.Jit has no LLVM backend)"),
    Option("max_pixels", 20000, kind="int", lo=0, fit=True, records=_ALL, flag="--max-pixels", group=_FIT,
           help="random subset of usable pixels (0: all)"),
    Option("erode", 2, kind="int", lo=0, fit=True, records=_ALL, flag="--erode", group=_FIT,
           help="pixels removed from the mask border"),
    Option("seed", 0, kind="int", lo=0, fit=True, records=_ALL, flag="--seed", group=_FIT,
           help="seed of the random pixel subset"),
    Option("rounds", 3, kind="int", lo=1, fit=True, help="paper's loss: inlier/outlier refresh rounds; likelihood: "
                                                        "reweighting rounds + 2"),
    Option("min_cos_view", 0.1, kind="number", lo=-1.0, hi=1.0, fit=True, help="pixels with n . v above this"),
    Option("min_cos_light", 0.02, kind="number", lo=-1.0, hi=1.0, fit=True, help="pixels with n . l above this"),
    Option("dolp_min_intensity", 0.02, kind="number", lo=0.0, fit=True,
           help="the DoLP term's pixels: observed I above this times its 99th percentile"),
    Option("lr", 0.02, kind="number", lo=0.0, lo_open=True, fit=True,
           help="Adam's step in the reparameterised variables"),
    Option("spp", 16, kind="int", lo=1, fit=True, help="render path: samples per pixel"),
    Option("bsdf_prefix", "sphere.bsdf", fit=True, help="render path: traverse prefix of the object's BSDF"),
    Option("manifest", None, flag="--manifest", group=_JOINT, cli={"metavar": "FILE.toml|json"},
           help="images, lights, relative powers, geometry and held-out images (fmbrdf_mi.fit.outputs.joint)"),
    Option("authors", None, flag="--authors", group=_JOINT, cli={"metavar": "OBJECT_DIR"},
           help="an object in the paper authors' captured-data layout (calibration/L.txt, image/img_ud/*.png, "
                "normal/normal_GT.npy, ...: fmbrdf_mi.fit.inputs.authors)"),
    Option("holdout", None, flag="--holdout", group=_JOINT, cli={"metavar": "I,J,..."},
           help="with --authors: image indices not fitted but predicted (relighting check)"),
    Option("free_power", False, kind="bool", fit=True, records=("joint",), refused_by=_REFINE, flag="--free-power",
           group=_JOINT, cli={"action": "store_true"},
           help="estimate the relative light power of every fitted image but the first (the reference, held at its "
                "given power; the given powers are then starting values): fmbrdf_mi.fit.problem.free_power"),
    Option("power_start", "ratio", kind="choice", choices=("ratio", "given"), fit=True, records=("joint",),
           flag="--power-start", group=_JOINT,
           help="with --free-power: start the powers in closed form at every coarse-search point (ratio, default) "
                "or at the given powers"),
    Option("refine_normals", False, kind="bool", flag="--refine-normals", group=_NORMALS, cli={"action": "store_true"},
           help="refine per-pixel normals and the material together (outputs normals.npy and plots)"),
    Option("normals_start", "ps", flag="--normals-start", group=_NORMALS, cli={"metavar": "ps|sphere|FILE.npy"},
           help="start map: photometric stereo (default), the mask's sphere, or a normal map file"),
    Option("smooth", 0.3, kind="number", lo=0.0, flag="--smooth", group=_NORMALS, cli={"metavar": "LAMBDA"},
           help="smoothness weight (units of Stokes residuals / image mean; default %(default)s)"),
    Option("relight", None, records=("single",), flag="--relight", group=_RELIGHT,
           cli={"nargs": "+", "metavar": "INPUT"}, help="a second image of the object under another light"),
    Option("relight_light", None, records=("single",), flag="--relight-light", group=_RELIGHT,
           cli={"metavar": "X,Y,Z"}, help="its light direction"),
    Option("relight_irradiance", None, kind="number", lo=IMAGE_OPTIONS[-1].lo, hi=IMAGE_OPTIONS[-1].hi,
           records=("single",), flag="--relight-irradiance", group=_RELIGHT,
           help="its light's irradiance in image units"),
    Option("out", None, flag="-o", group=_OUTPUT, cli={"required": True, "metavar": "DIR"}, help="output directory"),
    Option("from_json", None, flag="--from", group=_OUTPUT, cli={"metavar": "FIT.json"},
           help="rerun the fit recorded in a fit.json (same inputs, checked by SHA-256, and options)"),
    Option("force", False, flag="--force", group=_OUTPUT, cli={"action": "store_true"},
           help="overwrite existing outputs"),
    Option("quiet", False, flag="-q", group=_OUTPUT, cli={"action": "store_true"}, help="no progress output"),
)

#: :data:`OPTIONS` by name.
OPTION = {o.name: o for o in OPTIONS}

#: Flags with a short form: the long one.
LONG = {"-o": "--out", "-q": "--quiet"}


def flag(name):
    """How the command line names the option ``name`` (``max_pixels`` -> ``--max-pixels``)."""
    o = OPTION.get(name)
    if o is None or o.flag is None or not o.flag.startswith("-"):
        return "--" + name.replace("_", "-")
    return LONG.get(o.flag, o.flag)


def record_keys(record):
    """The options the ``record`` (``single``, ``colour``, ``joint``) of fit.json keeps, in schema order."""
    return tuple(o.name for o in OPTIONS if record in o.records)


def arguments(record, given, where):
    """``given`` checked against ``record``'s options, completed by the defaults (``reproduce.arguments``)."""
    keys = record_keys(record)
    unknown = [k for k in given if k not in keys]
    if unknown:
        raise InputError(f"{where}: unknown option(s) {', '.join(map(str, unknown))} (valid: {', '.join(keys)})")
    return {k: given.get(k, OPTION[k].default) for k in keys}


def _doc():
    rows = [f"* ``{o.name}`` (default ``{o.default!r}``{f', ``{o.flag}``' if o.flag else ''}): {o.help}"
            for o in OPTIONS if o.fit]
    return ("The options of a fit (:func:`fmbrdf_mi.fit.fit`), generated from "
            ":data:`fmbrdf_mi.fit.api.options.OPTIONS`:\n\n" + "\n".join(rows).replace("%%", "%")
            .replace(" (default %(default)s)", "") + "\n")


#: The options of :func:`fmbrdf_mi.fit.fit`: the schema's ``fit`` options, their defaults.
FitOptions = dataclasses.make_dataclass(
    "FitOptions", [(o.name, object, dataclasses.field(default=o.default)) for o in OPTIONS if o.fit],
    namespace={"__doc__": _doc(), "__module__": __name__})

#: The names of :class:`FitOptions`' fields.
FIT_NAMES = tuple(o.name for o in OPTIONS if o.fit)


def fit_options(values=None, **changes):
    """``values`` (:class:`FitOptions`, a dict to check, None: the defaults) with the fit options ``changes``."""
    unknown = [k for k in changes if k not in FIT_NAMES]
    if unknown:
        raise InputError(f"fit(): unknown option(s) {', '.join(unknown)} (FitOptions: {', '.join(FIT_NAMES)}; the "
                         "light, irradiance, geometry and noise are the Observation's)")
    if not isinstance(values, FitOptions):
        values = FitOptions(**check_values({k: x for k, x in (values or {}).items() if k in FIT_NAMES}))
    return dataclasses.replace(values, **changes)


def add_arguments(p, groups=GROUPS):
    """The command line of ``fmbrdf-mi fit`` on the parser ``p``: every option with a flag, in its section."""
    for title in groups:
        g = p.add_argument_group(title)
        for o in OPTIONS:
            if o.group != title or o.flag is None:
                continue
            kw = {"default": o.default, **({"choices": o.choices} if o.kind == "choice" else {}), **o.cli}
            if o.kind in ("int", "number") and o.many == 1:      # a number's text converted by argparse
                kw.setdefault("type", int if o.kind == "int" else float)
            if o.flag.startswith("-"):
                flags = [o.flag] + ([LONG[o.flag]] if o.flag in LONG else [])
                g.add_argument(*flags, dest=o.name, help=o.help, **kw)
            else:
                g.add_argument(o.name, help=o.help, **kw)


def check_values(values, flag=str):
    """``values`` checked against their options' kind and range and parsed (names outside the schema kept)."""
    out = dict(values)
    for name, v in values.items():
        o = OPTION.get(name)
        if o is None:
            continue
        if v is not None:
            out[name] = v = o.split(v, flag(name)) if o.parse is None else o.parse(v, flag(name))
        o.check(v, flag(name))
    return out


def check_fit_options(*, flag=str, **values):
    """Raise InputError for the first invalid fit option (``flag``: the name as the user wrote it)."""
    v = {k: OPTION[k].default for k in FIT_NAMES + ("baselines", "materials")}
    v.update({k: x for k, x in values.items() if k in OPTION})
    for k in ("model", "max_iter", "tol", "erode", "seed", "lr", "spp", "rounds", "starts"):
        if v[k] is None:
            raise InputError(f"{flag(k)}: a value is needed")
    v = check_values(v, flag)
    check_relations(v, flag)


def check_relations(v, flag=str):
    """The relations between the parsed fit options ``v``: incompatible pairs, parameter tables in bounds."""
    m = get_model(v["model"])
    albedo, materials, power = v["albedo"], v.get("materials"), v["free_power"]
    likelihood, per_pixel = v["loss"] in ("auto", "likelihood"), albedo in PER_PIXEL_LAYOUTS
    needs = (f"needs the likelihood of the camera's samples ({flag('loss')} likelihood or auto with the camera "
             "noise known")
    mat, alb, smooth = f"{flag('materials')} {materials}", f"{flag('albedo')} {albedo}", flag("albedo_smooth")
    refused = (
        (power and v["loss"] == "dolp", f"{flag('free_power')}: not with {flag('loss')} dolp (the DoLP does not "
                                        "depend on the light's power, so the powers would be undetermined)"),
        (v["path"] == "render" and v["optimizer"] != "adam",
         f"{flag('path')} render works with {flag('optimizer')} adam only (reverse-mode gradient through mi.render; "
         "its forward-mode derivatives, which 'lm' needs, miss the body term)"),
        (per_pixel and (not likelihood or v["optimizer"] != "lm" or v["path"] != "pixel"),
         f"{alb}: {needs}, the pixel path, optimizer lm): the albedo maps are solved per pixel from its raw samples"),
        (per_pixel and power, f"{alb}: not with {flag('free_power')} (give the relative light powers)"),
        (v["albedo_smooth"] is not None and not per_pixel,
         f"{smooth}: the albedo maps' smoothness prior needs {flag('albedo')} {' or '.join(PER_PIXEL_LAYOUTS)} "
         f"(got {albedo!r})"),
        (materials is not None and v["albedo_smooth"] is not None,
         f"{mat}: not with {smooth} (the smoothness prior is for one material)"),
        (materials is not None and albedo == "per-pixel-bilinear",
         f"{mat}: not with {flag('albedo')} per-pixel-bilinear (use per-pixel)"),
        (materials is not None and power, f"{mat}: not with {flag('free_power')} (give the relative light powers)"),
        (materials is not None and (not likelihood or v["path"] != "pixel"), f"{mat}: {needs}) on the pixel path"),
    )
    for bad, text in refused:
        if bad:
            raise InputError(text)
    for name, x in table(v["fixed"], flag("fixed"), "value").items():
        if name not in m.shape_names:
            raise InputError(f"{flag('fixed')}: '{name}' is not a shape parameter of {m.name} "
                             f"({', '.join(m.shape_names)})")
        number(f"{flag('fixed')} {name}", x, m.param(name).lo, m.param(name).hi)
    for name, pair in table(v["bounds"], flag("bounds"), "(lo, hi)").items():
        try:
            lo, hi = pair
        except (TypeError, ValueError):
            raise InputError(f"{flag('bounds')} {name}: expected (lo, hi), got {pair!r}") from None
        for end, x in (("low", lo), ("high", hi)):
            Option(name, kind="number").check(x, f"{flag('bounds')} {name} {end}")
    try:
        Parameters(m, bounds=v["bounds"])
    except ValueError as e:
        raise InputError(f"{flag('bounds')}: {e}") from None
    if v["init"] is not None:
        check_init(v["init"], m, flag, albedo)


def table(value, name, what):
    """``value``, a dict {parameter: ``what``} or None (an empty one), else InputError naming ``name``."""
    if value is not None and not isinstance(value, dict):
        raise InputError(f"{name}: expected {{name: {what}}}, got {value!r}")
    return value or {}


def check_init(init, m, flag, albedo="shared"):
    """``init``: a finite number in bounds (albedos >= 0) per parameter of ``m``; per-pixel albedos: shape only."""
    table(init, flag("init"), "value")
    params = Parameters(m)
    names = params.reported_names
    unknown = [k for k in init if k not in names]
    if unknown:
        raise InputError(f"{flag('init')}: unknown parameter '{unknown[0]}' of {m.name}; give all of "
                         f"{', '.join(names)}")
    if albedo in PER_PIXEL_LAYOUTS:
        names = [k for k in names if params.row[k].kind != "albedo"]
        given = [k for k in init if k not in names]
        if given:
            raise InputError(f"{flag('init')} {', '.join(given)}: {flag('albedo')} {albedo} solves the albedos per "
                             f"pixel, so they take no start; give {', '.join(names)}")
    missing = [k for k in names if k not in init]
    if missing:
        raise InputError(f"{flag('init')}: missing {', '.join(missing)} (give all of {', '.join(names)})")
    for k in names:
        row = params.row[k]
        number(f"{flag('init')} {k}", init[k], *((row.lo, row.hi) if row.kind == "shape" else (0.0, None)))


def number(name, value, lo=None, hi=None):
    """``value`` a finite number in [``lo``, ``hi``], else InputError naming ``name``."""
    o = Option(name, kind="number", lo=lo, hi=hi)
    try:
        if value is not None:
            return o.check(value)
    except InputError:
        pass
    raise InputError(f"{name}: expected a number within the fit's bounds {o.range_text()}, got {value!r}")


def check_input_options(*, flag=str, **values):
    """Raise InputError for the first invalid option about the image and the light."""
    v = check_values({k: x for k, x in values.items() if k in OPTION and not OPTION[k].fit}, flag)
    check_image_options(v, name=flag)
    if (v.get("conversion_gain") is None) != (v.get("read_noise") is None):
        given, other = ("read_noise", "conversion_gain") if v.get("conversion_gain") is None else \
            ("conversion_gain", "read_noise")
        raise InputError(f"{flag(given)} needs {flag(other)} too: the camera noise is known only with both "
                         "(electrons per image unit and read noise in electrons)")


def check_resolved_loss(values, loss, source, flag=str):
    """Refuse the options that do not work with the resolved ``loss`` (``source``: why it is that loss)."""
    optimizer = values.get("optimizer", "lm")
    if loss == "likelihood" and (optimizer != "lm" or values.get("path", "pixel") != "pixel"):
        raise InputError("loss 'likelihood' works with the pixel path and optimizer 'lm' (use --loss paper "
                         "for adam or the render path)")
    if loss in VARIANTS and optimizer != "lm":
        raise InputError(f"loss '{loss}' works with optimizer 'lm' (Adam minimises the full paper's loss)")
    if loss == "likelihood":
        return
    refused = {"albedo": values.get("albedo", "shared") != "shared", "albedo_smooth": values.get("albedo_smooth")
               is not None, "intervals": values.get("intervals") == "profile",
               "materials": values.get("materials") is not None, "area_points": values.get("area_points") is not None}
    for k in (k for k, bad in refused.items() if bad):
        given = flag(k) if k == "albedo_smooth" else f"{flag(k)} {values[k]}"
        raise InputError(f"{given}: needs the likelihood of the camera's samples, and the loss here is {loss} "
                         f"({source}): give the camera noise ({flag('conversion_gain')} and {flag('read_noise')}, or "
                         "a capture sidecar)")
