"""The ``render`` subcommand: a scene of FMBRDF material to a Stokes EXR and PNG previews.

    fmbrdf-mi render out/sphere.exr                       # built-in sphere scene
    fmbrdf-mi render -s scenes/spheres.xml -D alpha_1=0.5 --res 384x128 out/spheres.exr
    fmbrdf-mi render --list-params [-s scene.xml]

:func:`add_render_arguments` and :func:`run_render` follow the subcommand
protocol of :mod:`fmbrdf_mi.cli`: problems the user can fix are raised as
:class:`CLIError` (or ValueError, OSError), which the dispatcher prints as one
line.  Mitsuba is imported only after the arguments and inputs are checked.
"""
from __future__ import annotations

import math
import os
import re
import shlex
import sys
import time

import numpy as np

from . import __version__
from . import scene as S
from ._paths import PROG, CLIError, StageProgress, resolve_builtin, staged_outputs
from .params import ParameterError

HELP = "render spheres of FMBRDF material to a Stokes EXR and PNG previews"

POLARISED_VARIANTS = ("llvm_ad_spectral_polarized", "llvm_ad_mono_polarized",
                      "cuda_ad_spectral_polarized", "cuda_ad_mono_polarized")


#: ``render --raw`` renders with at least this many samples per pixel unless ``--spp`` is given: the
#: renderer's Monte Carlo noise, which no camera has and the fit's noise model does not know, biases
#: the fitted kappa at the scene's default sample count (docs/benchmarks/coverage.md).
RAW_MIN_SPP = 1024

#: Errors of a parameter's value (:func:`parse_value`).
VALUE_ERRORS = (CLIError, ValueError, OSError)


def warn(command, message):
    """A one-line warning on stderr, like the error lines."""
    print(f"{PROG} {command}: warning: {message}", file=sys.stderr)


def parse_defines(items):
    """``["name=value", ...]`` from ``-D`` options -> dict (later ones win)."""
    out = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise CLIError(f"-D {item!r}: expected NAME=VALUE, e.g. -D eta=1.6")
        out[name] = value.strip()
    return out


def _numbers(name, text, count=None):
    parts = [p for p in re.split(r"[,\s]+", str(text).strip()) if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise CLIError(f"{name}={text!r}: expected numbers") from None
    if count is not None and len(vals) not in count:
        want = " or ".join(str(c) for c in count)
        raise CLIError(f"{name}={text!r}: expected {want} number(s), got {len(vals)}")
    return vals


def _int(name, text, low=1):
    try:
        v = int(str(text).strip())
    except ValueError:
        raise CLIError(f"{name}={text!r}: expected an integer") from None
    if v < low:
        raise CLIError(f"{name}={text!r}: expected an integer >= {low}")
    return v


def _positive(name, text):
    (v,) = _numbers(name, text, (1,))
    if not (math.isfinite(v) and v > 0):
        raise CLIError(f"{name}={text!r}: expected a positive number")
    return v


def parse_value(name, text):
    """Typed value of scene parameter ``name`` given as text, validated.

    Material parameters may carry a sphere index suffix (``eta_1``).  Names not
    known here are returned as text (an XML scene may declare anything).
    """
    base = re.sub(r"_\d+$", "", name)
    base = base if base in S.MATERIAL_KEYS else name
    if base in ("eta", "alpha", "beta", "kappa"):
        from .params import check_scalar

        try:
            value = float(str(text).strip())
        except ValueError:
            raise ParameterError(f"fmbrdf: '{name}' must be a number, got {text!r}") from None
        try:
            check_scalar(base, value)
        except ParameterError as e:
            raise ParameterError(str(e) if base == name else f"{name}: {e}") from None
        return value
    if base in ("k_s", "r_k", "k_b"):
        from .params import check_albedo

        path = str(text).strip()
        if os.path.splitext(path)[1].lower() in S.TEXTURE_EXTENSIONS:
            if not os.path.isfile(path):
                raise CLIError(f"{name}={text}: no such texture file (an albedo is a number, r,g,b, or an image "
                               f"file: {', '.join(S.TEXTURE_EXTENSIONS)})")
            try:
                S.texture_bitmap(path)      # an unusable file: say so now, not from inside Mitsuba
            except ValueError as e:
                raise CLIError(f"{name}={text}: {str(e).removeprefix(f'texture {path}: ')}") from None
            return S.texture_file_dict(path)
        try:
            vals = _numbers(name, text, (1, 3))
        except CLIError:
            kind = "is a directory" if os.path.isdir(path) else "is a file of another kind" if os.path.exists(path) \
                else "is neither numbers nor an image file"
            raise CLIError(f"{name}={text}: {kind} (an albedo is a number, r,g,b, or an image file: "
                           f"{', '.join(S.TEXTURE_EXTENSIONS)})") from None
        check_albedo(name, vals)
        return vals[0] if len(vals) == 1 else tuple(vals)
    if name == "light_dir":
        try:
            return S.check_light_dir(_numbers(name, text, (3,)))
        except ValueError as e:
            raise CLIError(f"light_dir={text!r}: {str(e).split(': ', 1)[-1]}") from None
    if name == "irradiance":
        (v,) = _numbers(name, text, (1,))
        if not (math.isfinite(v) and v >= 0):
            raise CLIError(f"irradiance={text!r}: expected a finite number >= 0")
        return v
    if name in ("width", "height", "spp"):
        return _int(name, text)
    if name == "seed":
        return _int(name, text, low=0)
    if name == "fov":
        v = _positive(name, text)
        if v >= 180:
            raise CLIError(f"fov={text!r}: expected an angle in (0, 180) degrees")
        return v
    if name in ("distance", "half_width", "spacing"):
        return _positive(name, text)
    if name == "camera":
        if text not in S.CAMERAS:
            raise CLIError(f"camera={text!r}: expected one of {', '.join(S.CAMERAS)}")
        return text
    return text


def _text(value):
    """A parameter value as Mitsuba's XML substitution wants it."""
    if isinstance(value, tuple):
        return ", ".join(repr(float(v)) for v in value)
    return repr(value) if isinstance(value, float) else str(value)


#: Parameters of the built-in scene (fmbrdf_mi.scene.sphere_scene): name -> (default, help).
BUILTIN_PARAMS = {
    "eta": (S.DEFAULT_MATERIAL["eta"], "index of refraction, (1, 3]"),
    "alpha": (S.DEFAULT_MATERIAL["alpha"], "roughness (radians), [0.01, pi/2]"),
    "beta": (S.DEFAULT_MATERIAL["beta"], "shape of the generalised normal distribution, [0.4, 5]"),
    "kappa": (S.DEFAULT_MATERIAL["kappa"], "vMF microfacet correlation, [0, 100]"),
    "k_s": (S.DEFAULT_MATERIAL["k_s"], "surface albedo, >= 0 (one number or r,g,b)"),
    "r_k": (S.DEFAULT_MATERIAL["r_k"], "body albedo ratio k_b / k_s, >= 0"),
    "k_b": (None, "body albedo, instead of r_k"),
    "light_dir": (S.DEFAULT_LIGHT_DIR, "x,y,z from the surface towards the light (x right, y up, z to camera)"),
    "irradiance": (S.DEFAULT_IRRADIANCE, "irradiance of the directional light"),
    "camera": (S.DEFAULT_CAMERA, "orthographic or perspective"),
    "fov": (S.DEFAULT_FOV, "horizontal field of view in degrees (framing of both cameras)"),
    "distance": (S.DEFAULT_DISTANCE, "camera distance from the sphere centre"),
    "width": (S.DEFAULT_RESOLUTION, "image width (pixels)"),
    "height": (S.DEFAULT_RESOLUTION, "image height (pixels)"),
    "spp": (S.DEFAULT_SPP, "samples per pixel"),
    "seed": (0, "sampler seed"),
}


#: What an XML scene without a camera is told.
NO_SENSOR = ("no <sensor> to render from; add a camera with a film, e.g. <sensor type=\"orthographic\"> "
             "... <film type=\"hdrfilm\"> ... </sensor> (see builtin:sphere, fmbrdf_mi/scenes/sphere.xml)")


def check_meshes(root, path):
    """CLIError for a .ply / .obj shape of the XML scene ``path`` whose file exists but holds no mesh (Mitsuba's
    own message is an I/O error or "Could not map"); names with $parameters and missing files are Mitsuba's."""
    for shape in root.iter("shape"):
        if shape.get("type") not in ("ply", "obj"):
            continue
        for el in shape.findall("string"):
            name = el.get("value", "")
            if el.get("name") != "filename" or "$" in name:
                continue
            full = name if os.path.isabs(name) else os.path.join(os.path.dirname(os.path.abspath(path)), name)
            if os.path.exists(full):
                try:
                    S.check_mesh_file(full)
                except (OSError, ValueError) as e:
                    raise CLIError(f"scene file {path}: shape '{shape.get('id') or shape.get('type')}': {e}") from None


def check_exr_textures(root, path):
    """CLIError for an EXR bitmap texture in the XML scene ``path`` when this process may use one CPU only:
    Mitsuba reads the scene's textures itself, and its EXR reader never returns there.  (``-D k_s=FILE`` on
    the built-in sphere reads EXR textures without it.)"""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):    # not on Linux: the hang is not known there
        return
    if cpus > 1:
        return
    for tex in root.iter("texture"):
        for el in tex.findall("string"):
            name = el.get("value", "")
            if tex.get("type") == "bitmap" and el.get("name") == "filename" and name.lower().endswith(".exr"):
                raise CLIError(f"scene file {path}: bitmap texture {name}: Mitsuba's EXR reader does not return in a "
                               "process allowed one CPU (taskset, a one-core cluster job); allow two CPUs, or give "
                               "the texture as PNG")


def xml_parameters(path):
    """``({name: default text or None}, xml text)`` of an XML scene's parameters.

    Names come from its ``<default>`` elements and ``$name`` references; a
    reference without a default (None) must be given.
    """
    import xml.etree.ElementTree as ET

    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError as e:
        raise CLIError(f"scene file {path}: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise CLIError(f"scene file {path}: not a text (UTF-8) XML file: byte {e.start} is 0x{e.object[e.start]:02x} "
                       "(a binary file?); a Mitsuba scene is XML text") from None
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise CLIError(f"scene file {path}: not valid XML ({e})") from None
    if next(root.iter("sensor"), None) is None and next(root.iter("include"), None) is None:
        raise CLIError(f"scene file {path}: {NO_SENSOR}")
    check_meshes(root, path)
    check_exr_textures(root, path)
    found = {}
    for el in root.iter():
        for value in el.attrib.values():
            for name in re.findall(r"(?<!\\)\$([A-Za-z0-9_]+)", value):
                found.setdefault(name, None)
    for el in root.iter("default"):
        if "name" in el.attrib:
            found[el.attrib["name"]] = el.attrib.get("value")
    return found, text


def _check_output(path, force, preview_kinds):
    from .previews import preview_paths

    from ._paths import check_output_file

    if not str(path).lower().endswith(".exr"):
        raise CLIError(f"output {path!r}: expected a file name ending in .exr")
    previews = preview_paths(str(path)[:-4], preview_kinds)
    for p in [path, *previews.values()]:
        check_output_file(p)
        if not force and os.path.exists(p):
            raise CLIError(f"{p} exists; pass --force to overwrite it")
    return previews


def _parse_res(text):
    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX,]\s*(\d+)\s*)?", text or "")
    if not m or int(m.group(1)) < 1 or (m.group(2) and int(m.group(2)) < 1):
        raise CLIError(f"--res {text!r}: expected N or WxH, e.g. 256 or 512x256")
    return int(m.group(1)), int(m.group(2) or m.group(1))


def _mitsuba_message(exc):
    """One informative line out of a (multi-line) Mitsuba exception."""
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    if not lines:
        return type(exc).__name__
    last = lines[-1]
    if re.match(r"^[A-Za-z_.]*(Error|Exception): ", last):  # a Python error inside a plugin
        return last.split(": ", 1)[1]
    first = re.sub(r"^\[[\w.]+:\d+\]\s*", "", lines[0])
    if first.endswith(":") and len(lines) > 1:  # e.g. a list of unreferenced properties
        return " ".join([first] + [ln.lstrip("- ") for ln in lines[1:]])
    return first


def add_render_arguments(p):
    p.add_argument("output", nargs="?", help="Stokes EXR to write (previews go beside it: "
                   "NAME_intensity.png, NAME_dolp.png, NAME_aolp.png, ...)")
    p.add_argument("-s", "--scene", metavar="FILE",
                   help="Mitsuba XML scene, or one shipped with the package: builtin:sphere, builtin:spheres, "
                        "builtin:sphere_perspective (fmbrdf_mi/scenes/); default: the built-in sphere")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set a scene parameter, e.g. -D eta=1.6 -D light_dir=0,0.5,1 (repeatable)")
    p.add_argument("--spp", type=int, help=f"samples per pixel (default: the scene's, 64; with --raw at least "
                                           f"{RAW_MIN_SPP}, so that the capture's noise is the camera's)")
    p.add_argument("--res", metavar="N|WxH", help="resolution (default: the scene's, 256)")
    p.add_argument("--seed", type=int, help="sampler seed (default 0)")
    p.add_argument("--variant", default="llvm_ad_spectral_polarized", choices=POLARISED_VARIANTS,
                   help="Mitsuba variant; llvm_ad_mono_polarized for a monochrome polarisation camera "
                        "(default %(default)s)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--no-previews", action="store_true", help="write only the EXR")
    p.add_argument("--angles", action="store_true",
                   help="also write the four polariser-angle images (0, 45, 90, 135 deg)")
    p.add_argument("--mosaic", action="store_true",
                   help="also write the raw mosaic of a quad-Bayer polarisation sensor (IMX250MZR layout)")
    p.add_argument("--materials", metavar="UV_LABELS.png|npy",
                   help="built-in sphere: several materials; a label image over the sphere's uv (one-channel PNG or "
                        "integer .npy, 0 .. M-1 in every texel; the sphere's pole faces the camera: u is the azimuth around "
                        "the view axis, v in [0, 0.5] the visible hemisphere): material 0 takes -D NAME=..., material m also "
                        "-D NAME_m=... (e.g. -D eta_1=1.8); writes OUTPUT_labels.png (the material at each "
                        "pixel's centre, 255 off the object) and with --raw OUTPUT_raw_labels.png (super-pixels, "
                        "255 where the four raw pixels differ): fmbrdf-mi fit --materials takes either")
    g = p.add_argument_group("raw capture (--raw): the camera model of fmbrdf_mi.sensor.camera")
    g.add_argument("--raw", action="store_true",
                   help="also write OUTPUT_raw.png, a linear 16-bit quad-Bayer mosaic through the camera model "
                        "(shot and read noise, ADC), and OUTPUT_raw.json, its settings (read by fmbrdf-mi fit)")
    g.add_argument("--full-well", type=float, default=10000.0, help="electrons (default %(default)s)")
    g.add_argument("--conversion-gain", type=float, metavar="E_PER_DN",
                   help="electrons per DN (default: the ADC spans the full well)")
    g.add_argument("--read-noise", type=float, default=2.5, help="electrons rms (default %(default)s)")
    g.add_argument("--bits", type=int, default=12, help="ADC bits (default %(default)s)")
    g.add_argument("--black-level", type=float, default=0.0, help="DN offset (default %(default)s)")
    g.add_argument("--layout", default="90,45,135,0", help="2x2 polariser angles, row-major (default %(default)s)")
    g.add_argument("--sensor", choices=("mono", "colour"), default="mono",
                   help="mono: quad-Bayer polarisation sensor (IMX250MZR type, 2x2 period, the mean of the "
                        "channels); colour: colour polarisation sensor (IMX250MYR type: a Bayer colour filter "
                        "over 2x2 polariser blocks, 4x4 period, each colour seeing its own channel; needs a "
                        "colour variant) (default %(default)s)")
    g.add_argument("--cfa", default=None,
                   help="--sensor colour: Bayer arrangement of the 2x2 polariser blocks, row-major "
                        "(default RGGB)")
    g.add_argument("--raw-exposure", type=float, metavar="E_PER_UNIT",
                   help="electrons per unit of the Stokes image (default: the brightest raw pixel at 80%% "
                        "of the full well)")
    g.add_argument("--raw-seed", type=int, default=0, help="seed of the camera noise (default %(default)s)")
    p.add_argument("--aolp-dolp", action="store_true",
                   help="modulate the AoLP preview's brightness by the DoLP")
    p.add_argument("--exposure", type=float, help="intensity scale of the previews (default: automatic)")
    p.add_argument("--dolp-max", type=float, metavar="D",
                   help="top of the DoLP colour scale, e.g. 1 (default: automatic, 0.05 to 1)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.add_argument("--list-params", action="store_true",
                   help="list the scene's parameters and their defaults, then exit")


def _scene_params(args):
    """(kind, {name: default}, xml text or None) of the chosen scene."""
    if args.scene is None:
        return "builtin", {k: v for k, (v, _) in BUILTIN_PARAMS.items()}, None
    args.scene = resolve_builtin(args.scene, (".xml",), "scene file")  # builtin:spheres -> the shipped file
    if os.path.isdir(args.scene):
        raise CLIError(f"scene file {args.scene}: is a directory, expected a Mitsuba XML file")
    if not os.path.isfile(args.scene):
        raise CLIError(f"scene file {args.scene} not found")
    params, text = xml_parameters(args.scene)
    return "xml", params, text


def _resolve(args, kind, declared):
    """The user's parameters (typed), after checking names and values."""
    where = "the built-in scene" if kind == "builtin" else args.scene
    given = parse_defines(args.defines)
    count = material_count_of(args, kind)
    for name in given:
        mat = re.fullmatch(r"(\w+?)_(\d+)", name)
        if count and mat and mat.group(1) in S.MATERIAL_KEYS:
            if not 1 <= int(mat.group(2)) < count:
                raise CLIError(f"-D {name}: --materials has materials 0 .. {count - 1}; material 0 takes "
                               f"-D {mat.group(1)}=..., material m -D {mat.group(1)}_m=... (m = 1 .. {count - 1})")
            continue
        if name not in declared:
            raise CLIError(f"unknown parameter '{name}' for {where}; known: {', '.join(sorted(declared))}")
    if args.res is not None:
        if "width" not in declared or "height" not in declared:
            raise CLIError(f"--res: {where} has no width/height parameters")
        given["width"], given["height"] = (str(v) for v in _parse_res(args.res))
    for name in ("spp", "seed"):  # also used without a scene parameter of that name
        value = getattr(args, name)
        if value is not None:
            given[name] = str(value)
    missing = [n for n, v in declared.items() if v is None and n not in given and kind == "xml"]
    if missing:
        raise CLIError(f"{args.scene} needs a value for '{missing[0]}': pass -D {missing[0]}=...")
    return {name: parse_value(name, text) for name, text in given.items()}


def material_count_of(args, kind):
    """M of ``render --materials`` (its uv label image read and checked: :func:`read_uv_labels`), else 0."""
    if getattr(args, "materials", None) is None:
        return 0
    if kind != "builtin":
        raise CLIError("--materials: the built-in sphere's option; in an XML scene give the shape a blendbsdf")
    if getattr(args, "sensor", "mono") == "colour":
        raise CLIError("--materials: not with --sensor colour (the fit of several materials takes mono captures)")
    labels = read_uv_labels(args.materials)
    args.uv_labels = labels
    return int(labels.max()) + 1


def read_uv_labels(path):
    """The uv label image of ``render --materials`` (:func:`fmbrdf_mi.fit.inputs.labels.read_uv_labels`)."""
    from fmbrdf_mi.fit.errors import InputError
    from fmbrdf_mi.fit.inputs.labels import read_uv_labels as read

    try:
        return read(path)
    except InputError as e:
        raise CLIError(str(e)) from None


def label_paths(output, raw):
    """The label images ``render --materials`` writes beside ``output``."""
    stem = str(output)[:-4]
    return {"labels": f"{stem}_labels.png", **({"raw_labels": f"{stem}_raw_labels.png"} if raw else {})}


def _write_labels(args, scene, output):
    """OUTPUT_labels.png (each pixel centre's material, 255 off the object) and with --raw
    OUTPUT_raw_labels.png on the super-pixel grid (255 where the four raw pixels' labels differ), beside
    ``output`` (where :func:`staged_outputs` collects them)."""
    from fmbrdf_mi.fit.evaluate.materials import check_labels
    from fmbrdf_mi.fit.inputs.labels import write_labels

    lab = S.true_label_map(scene, args.uv_labels, int(args.uv_labels.max()) + 1)
    paths = label_paths(output, args.raw)
    write_labels(paths["labels"], lab)
    if args.raw:
        h, w = lab.shape
        write_labels(paths["raw_labels"], check_labels(lab, (h // 2, w // 2)))
    return paths


def _list_params(kind, declared, args):
    title = "built-in sphere scene" if kind == "builtin" else args.scene
    print(f"parameters of the {title} (set with -D NAME=VALUE):")
    width = max(len(n) for n in declared) if declared else 0
    for name, default in declared.items():
        help_ = BUILTIN_PARAMS[name][1] if kind == "builtin" else ""
        if isinstance(default, tuple):
            default = ",".join(f"{v:g}" for v in default)
        print(f"  {name:<{width}}  {'(none)' if default is None else default!s:<18}  {help_}".rstrip())
    return 0


def _check_size(kind, declared, given):
    """Refuse a resolution whose render cannot fit in memory, before anything is loaded."""
    from ._paths import check_render_size

    def value(name):
        if name in given:
            return given[name]
        default = BUILTIN_PARAMS[name][0] if kind == "builtin" else declared.get(name)
        try:
            return int(default)
        except (TypeError, ValueError):
            return None

    w, h = value("width"), value("height")
    if w is not None and h is not None:
        check_render_size(w, h, "--res" if "width" in given or "height" in given else "resolution")


def _warn_if_black(given):
    """The built-in sphere: warn when no pixel can be lit (light behind the sphere as seen
    from the camera, or the camera inside the sphere)."""
    values = {k: v for k, (v, _) in BUILTIN_PARAMS.items()}
    values.update(given)
    if values["distance"] <= 1.0:
        warn("render", f"distance={values['distance']:g}: the camera is inside the unit sphere; "
                       "the image will be black")
        return True
    n, _, m = S.sphere_geometry(64, camera=values["camera"], fov=values["fov"], distance=values["distance"])
    lit = m & (n @ np.asarray(S.check_light_dir(values["light_dir"])) > 0)
    if not lit.any():
        warn("render", f"light_dir={','.join(f'{x:g}' for x in values['light_dir'])}: the light is "
                       "behind the sphere as seen from the camera; the image will be black")
        return True
    return False


def _check_camera_options(args):
    """Options of the raw capture that would be ignored: one line naming them."""
    if args.sensor != "mono" and not args.raw:
        raise CLIError(f"--sensor {args.sensor}: a setting of the raw capture; give --raw too (without it "
                       "only the Stokes EXR is written)")
    raw_only = [flag for flag, given in (
        ("--full-well", args.full_well != 10000.0), ("--conversion-gain", args.conversion_gain is not None),
        ("--read-noise", args.read_noise != 2.5), ("--bits", args.bits != 12),
        ("--black-level", args.black_level != 0.0), ("--layout", args.layout != "90,45,135,0"),
        ("--raw-exposure", args.raw_exposure is not None), ("--raw-seed", args.raw_seed != 0)) if given]
    if raw_only and not args.raw:   # (the --mosaic preview has the IMX250MZR layout, not --layout)
        raise CLIError(f"{', '.join(raw_only)}: setting(s) of the raw capture; give --raw too (without it no raw "
                       "mosaic is captured and they would be ignored)")
    if args.cfa is not None and args.sensor != "colour":
        raise CLIError(f"--cfa {args.cfa}: the colour filter of a colour sensor; give --sensor colour (and --raw), "
                       "or drop --cfa for the mono quad-Bayer sensor")


def _check_rgb_values(args, given):
    """An RGB albedo (-D k_s=r,g,b) in a monochrome variant would be averaged silently, and an RGB texture
    (-D k_s=FILE) cannot be a spectral variant's albedo as it is (its values are used raw, not turned into
    spectra): refuse them."""
    for name, value in given.items():
        if re.sub(r"_\d+$", "", name) not in ("k_s", "r_k", "k_b"):
            continue
        if "mono" in args.variant and isinstance(value, tuple):
            raise CLIError(f"-D {name}={','.join(f'{v:g}' for v in value)}: an RGB value needs a spectral or RGB "
                           f"variant, --variant {args.variant} takes one number")
        if "spectral" in args.variant and isinstance(value, dict) and "filename" in value \
                and S.texture_channels(value["filename"]) == 3:
            raise CLIError(f"-D {name}={value['filename']}: an RGB texture (R, G, B channels) is not an albedo of "
                           f"--variant {args.variant}; give a one-channel (Y) texture, or --variant "
                           "llvm_ad_mono_polarized (which renders its luminance)")


def output_paths(args, given, kinds):
    """Every file this render writes: the Stokes EXR, the previews of ``kinds``, the raw capture, the true
    albedo maps of a textured render and the label images of ``--materials``."""
    from .previews import preview_paths

    out = [args.output, *preview_paths(str(args.output)[:-4], kinds).values()]
    if args.raw:
        out += [args.output[:-4] + "_raw.png", args.output[:-4] + "_raw.json"]
    if any(isinstance(v, dict) for v in given.values()):
        out += true_map_paths(args.output, args.raw).values()
    if getattr(args, "materials", None) is not None:
        out += label_paths(args.output, args.raw).values()
    return out


def _check_inputs_not_outputs(args, given, kinds):
    """Refuse a render that would overwrite one of its own inputs (a texture, the uv label image, the scene
    file), with or without --force, before anything is rendered."""
    inputs = [(f"-D {k}={v['filename']}", v["filename"]) for k, v in given.items()
              if isinstance(v, dict) and "filename" in v]
    inputs += [(f"--materials {args.materials}", args.materials)] if getattr(args, "materials", None) else []
    inputs += [(f"--scene {args.scene}", args.scene)] if args.scene is not None else []
    outputs = {os.path.realpath(p): p for p in output_paths(args, given, kinds)}
    for what, path in inputs:
        hit = outputs.get(os.path.realpath(path))
        if hit is not None:
            raise CLIError(f"{what}: is also an output of this render ({hit}) and would be overwritten; "
                           "write the render under another name")


def true_map_paths(output, raw):
    """The files of the true albedo maps a textured render writes beside ``output`` (:func:`_write_true_maps`)."""
    stem = str(output)[:-4]
    out = {f"true_{k}": f"{stem}_{k}.exr" for k in ("k_s", "k_b")}
    if raw:
        out.update({f"true_raw_{k}": f"{stem}_raw_{k}.exr" for k in ("k_s", "k_b")})
    return out


def _write_true_maps(args, scene, material, meta, output):
    """A render with albedo textures (``-D k_s=FILE``): the albedos at each pixel's centre, OUT_k_s.exr and
    OUT_k_b.exr (the render's pixels), and with ``--raw`` OUT_raw_k_s.exr, OUT_raw_k_b.exr on the grid a
    fit of the mosaic works on (the mean over each 2 x 2 super-pixel, 4 x 4 colour period): what
    ``fmbrdf-mi fit --albedo per-pixel`` estimates.  ``--sensor colour``: channels R, G, B (the maps per
    colour channel, as the colour fit estimates them); else one channel (an RGB texture's mean).  Written
    beside ``output`` (where :func:`staged_outputs` collects them)."""
    from .stokes_io import write_map_exr

    colour = args.raw and args.sensor == "colour"
    maps = S.true_albedo_maps(scene, material, channels=colour)
    paths = true_map_paths(output, args.raw)
    info = {"generator": meta["generator"], "command": meta["command"], "what": "true albedo at each pixel's centre"}
    for k in ("k_s", "k_b"):
        write_map_exr(paths[f"true_{k}"], maps[k], dict(info, map=k), force=True)
        if args.raw:
            p = 4 if args.sensor == "colour" else 2
            h, w = maps[k].shape[-2:]
            grid = maps[k].reshape(maps[k].shape[:-2] + (h // p, p, w // p, p)).mean(axis=(-3, -1))
            write_map_exr(paths[f"true_raw_{k}"], grid, dict(info, map=k, grid=f"{p}x{p} mean"), force=True)
    return paths


def run_render(args):
    kinds = [] if args.no_previews else ["intensity", "dolp", "aolp"]
    kinds += (["angles"] if args.angles else []) + (["mosaic"] if args.mosaic else [])
    if args.angles and args.no_previews or args.mosaic and args.no_previews:
        raise CLIError("--angles/--mosaic are previews: drop --no-previews")
    if args.exposure is not None and not (math.isfinite(args.exposure) and args.exposure > 0):
        raise CLIError(f"--exposure {args.exposure}: expected a positive number")
    if args.dolp_max is not None and not (0 < args.dolp_max <= 1):
        raise CLIError(f"--dolp-max {args.dolp_max}: expected a number in (0, 1]")
    _check_camera_options(args)
    kind, declared, xml_text = _scene_params(args)
    if args.list_params:
        return _list_params(kind, declared, args)
    if args.output is None:
        raise CLIError("no output file given, e.g. fmbrdf-mi render out/sphere.exr")
    from . import check_variant

    check_variant(args.variant)     # e.g. a cuda_ variant without a CUDA device: one line, before any work
    given = _resolve(args, kind, declared)
    _check_rgb_values(args, given)
    _check_inputs_not_outputs(args, given, kinds)
    _check_output(args.output, args.force, kinds)
    if getattr(args, "materials", None) is not None:
        if any(isinstance(v, dict) for v in given.values()):
            raise CLIError("--materials: not with albedo textures (-D k_s=FILE) yet")
        for p in label_paths(args.output, args.raw).values():
            if os.path.exists(p) and not args.force:
                raise FileExistsError(f"{p} exists; pass --force to overwrite it")
    if any(isinstance(v, dict) for v in given.values()):
        if kind != "builtin":
            raise CLIError("-D k_s=FILE (an albedo texture): the built-in sphere's parameter; in an XML scene put a "
                           "bitmap texture in the scene file")
        for p in true_map_paths(args.output, args.raw).values():
            if os.path.exists(p) and not args.force:
                raise FileExistsError(f"{p} exists; pass --force to overwrite it")
    _check_size(kind, declared, given)
    warned_black = kind == "builtin" and _warn_if_black(given)
    if args.raw:
        period = _raw_camera(args).period  # bad settings: say so before rendering
        try:
            w_, h_ = (int(given.get(k, declared.get(k))) for k in ("width", "height"))
        except (TypeError, ValueError):
            w_ = h_ = None
        if w_ is not None and (w_ % period or h_ % period):
            raise CLIError(f"--raw: the image's width and height must be multiples of {period} for the "
                           f"{'colour' if period == 4 else 'quad-Bayer'} mosaic period, got {w_}x{h_} (--res)")
        if args.sensor == "colour" and "mono" in args.variant:
            raise CLIError(f"--sensor colour: needs a colour variant (rgb or spectral), got "
                           f"--variant {args.variant}")
        for p in (args.output[:-4] + "_raw.png", args.output[:-4] + "_raw.json"):
            if os.path.exists(p) and not args.force:
                raise FileExistsError(f"{p} exists; pass --force to overwrite it")

    import mitsuba as mi

    try:
        mi.set_variant(args.variant)
    except Exception as e:  # e.g. a variant this Mitsuba build lacks
        raise CLIError(f"variant {args.variant} is not available here: {_mitsuba_message(e)}") from None
    import fmbrdf_mi

    fmbrdf_mi.register()
    spp = given.get("spp")  # None: the scene's sample count
    seed = given.get("seed", parse_value("seed", declared["seed"]) if declared.get("seed") is not None else 0)
    t0 = time.perf_counter()
    if kind == "builtin":
        values = {k: v for k, (v, _) in BUILTIN_PARAMS.items() if v is not None}
        if "k_b" in given and "r_k" not in given:
            values.pop("r_k")
        values.update(given)
        values["light_dir"] = S.check_light_dir(values["light_dir"])  # normalised, as used
        material = {k: values[k] for k in S.MATERIAL_KEYS if k in values}
        scene_dict = S.sphere_scene(material, light_dir=values["light_dir"], irradiance=values["irradiance"],
                                    resolution=(values["width"], values["height"]), spp=values["spp"],
                                    camera=values["camera"], fov=values["fov"], distance=values["distance"],
                                    seed=seed)
        if getattr(args, "materials", None) is not None:   # material m: material 0 with its own -D NAME_m
            mats = []
            for m in range(int(args.uv_labels.max()) + 1):
                mine = dict(material, **{k: given[f"{k}_{m}"] for k in S.MATERIAL_KEYS if f"{k}_{m}" in given})
                if f"k_b_{m}" in given and f"r_k_{m}" not in given:
                    mine.pop("r_k", None)
                mats.append(mine)
            scene_dict["sphere"]["bsdf"] = S.materials_bsdf(mats, args.uv_labels)
            values["materials"] = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in x.items()} for x in mats]
        scene = fmbrdf_mi.load_dict(scene_dict)
        resolved = dict(values, seed=seed)
        textured = any(isinstance(material.get(k), dict) for k in ("k_s", "k_b", "r_k"))
    else:
        if "pixel_format" in declared and "pixel_format" not in given and mi.is_monochromatic:
            given["pixel_format"] = "luminance"  # avoids Mitsuba's warning that it switches
        xml_given = {k: _text(v) for k, v in given.items() if k in declared}
        try:
            scene = fmbrdf_mi.load_file(args.scene, **xml_given)
        except ParameterError:
            raise
        except Exception as e:
            raise CLIError(f"{args.scene}: {_mitsuba_message(e)}") from None
        if not scene.sensors():
            raise CLIError(f"scene file {args.scene}: {NO_SENSOR}")
        textured, material = False, None
        resolved = {}
        for k, v in declared.items():
            try:
                resolved[k] = parse_value(k, v) if v is not None else None
            except VALUE_ERRORS:  # an odd default in a user's scene: keep its text
                resolved[k] = v
        resolved.update(given)
    from .stokes_io import write_stokes_exr
    from .previews import auto_exposure, write_previews

    if args.raw and spp is None and int(scene.sensors()[0].sampler().sample_count()) < RAW_MIN_SPP:
        spp = RAW_MIN_SPP    # the capture's noise is the camera's, not the renderer's (RAW_MIN_SPP)
    stokes = S.render_stokes(scene, spp=spp, seed=seed, progress=not args.quiet)
    _, h, w, c = stokes.shape
    if not warned_black and not np.any(stokes[0] > 0):
        warn("render", "the image is black: nothing lit is visible (a light behind the object, "
                       "a camera inside it, or no object in view)")
    spp_used = spp if spp is not None else int(scene.sensors()[0].sampler().sample_count())
    if "spp" in resolved:
        resolved["spp"] = spp_used      # what was rendered (--raw may have raised it)
    meta = {
        "generator": f"fmbrdf-mi {__version__}",
        "fmbrdf_mi_version": __version__,
        "mitsuba_version": mi.__version__,
        "variant": args.variant,
        "scene": "builtin:sphere" if kind == "builtin" else os.path.abspath(args.scene),
        "parameters": {k: (list(v) if isinstance(v, tuple) else v) for k, v in resolved.items()},
        "materials": S.scene_materials(scene),
        "lights": S.scene_lights(scene),
        "camera": S.scene_camera(scene),
        "resolution": [w, h],
        "spp": spp_used,
        "seed": seed,
        "stokes_frame": "x = image right, y = image up, light towards the camera; "
                        "AoLP from image right counter-clockwise",
        "command": shlex.join([PROG, "render", *args.argv]),
    }
    if xml_text is not None:
        meta["scene_xml"] = xml_text
    exposure = args.exposure if args.exposure is not None or not kinds else auto_exposure(stokes)  # all previews'

    def write_exr(out):
        write_stokes_exr(out, stokes, meta, force=True)
        return {}

    steps = [("Stokes EXR", write_exr)]
    steps += [(f"{kind} preview", lambda out, kind=kind: write_previews(
        out[:-4], stokes, [kind], exposure=exposure, dolp_max=args.dolp_max, modulate_aolp=args.aolp_dolp,
        force=True)) for kind in kinds]
    if args.raw:
        steps.append(("raw mosaic and sidecar",
                      lambda out: dict(zip(("raw", "raw_sidecar"), _write_raw(args, stokes, meta, out)))))
    if textured:
        steps.append(("true albedo maps", lambda out: _write_true_maps(args, scene, material, meta, out)))
    if getattr(args, "materials", None) is not None:
        steps.append(("label images", lambda out: _write_labels(args, scene, out)))
    written = {}
    with staged_outputs(args.output) as out:   # every file or none (Ctrl-C, a refused capture)
        bar = StageProgress("writing", len(steps), enabled=not args.quiet)
        for name, write in steps:
            written.update(write(out))
            bar.step(name)
    written = {k: os.path.join(os.path.dirname(args.output), os.path.basename(p)) for k, p in written.items()}
    cols = "Y" if c == 1 else "R,G,B"
    print(f"wrote {args.output}: Stokes S0-S3 x {cols}, {w}x{h}, {spp_used} spp, {args.variant}, "
          f"{time.perf_counter() - t0:.1f} s")
    for p in written.values():
        print(f"wrote {p}")
    return 0


def _raw_camera(args):
    from .sensor.camera import CameraModel
    from fmbrdf_mi.fit.errors import InputError
    from fmbrdf_mi.fit.inputs.parse import parse_layout
    from .sensor.mosaic import parse_cfa

    try:
        cfa = None
        if args.sensor == "colour":
            try:
                cfa = parse_cfa(args.cfa or "RGGB")
            except ValueError:
                raise ValueError(f"--cfa: expected four letters with one R, two G and one B, such as RGGB; "
                                 f"got {args.cfa!r}") from None
        return CameraModel(full_well=args.full_well, read_noise=args.read_noise, bits=args.bits,
                           conversion_gain=args.conversion_gain, black_level=args.black_level,
                           layout=parse_layout(args.layout), cfa=cfa)
    except (InputError, ValueError) as e:
        raise CLIError(f"--raw: {e}") from None


def _write_raw(args, stokes, meta, output):
    """OUTPUT_raw.png (uint16 mosaic) and OUTPUT_raw.json (camera settings + the EXR's metadata) beside
    ``output`` (where :func:`staged_outputs` collects them; the sidecar names the final Stokes EXR)."""
    import numpy as np
    from PIL import Image

    from .sensor.camera import capture, write_sidecar

    cam = _raw_camera(args)
    if cam.cfa is None:
        s = np.asarray(stokes)[:3].mean(axis=-1)  # one channel: the mean, as the fit uses
        channel = "mean"
    else:
        s = np.moveaxis(np.asarray(stokes)[:3], -1, 0)  # (R, G, B; 3; H, W): each colour sees its channel
        if s.shape[0] != 3:
            raise CLIError(f"--sensor colour: the render has {s.shape[0]} channel(s), need R, G, B "
                           "(a colour variant)")
        channel = "per colour (R, G, B)"
    p = cam.period
    if s.shape[-2] % p or s.shape[-1] % p:
        raise CLIError(f"--raw: the image's width and height must be multiples of {p} for the "
                       f"{'colour' if p == 4 else 'quad-Bayer'} mosaic period, got {s.shape[-1]}x{s.shape[-2]}")
    cap = capture(s, cam, exposure=args.raw_exposure, peak_fraction=0.8, seed=args.raw_seed)
    path = output[:-4] + "_raw.png"
    Image.fromarray(np.ascontiguousarray(cap["raw"], dtype=np.uint16)).save(path)
    extra = dict(meta, capture={"exposure_e_per_unit": cap["exposure"], "seed": args.raw_seed,
                                "dn_per_input_unit": 1.0 / cap["dn_to_input"], "saturated": cap["saturated"],
                                "channel": channel, "stokes_exr": os.path.abspath(args.output)})
    side = write_sidecar(path, cam, extra, force=True)
    return path, side
