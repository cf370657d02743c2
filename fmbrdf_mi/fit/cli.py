"""``fmbrdf-mi fit``: files in, estimates, plots and relighting errors out.

:func:`fit_files` is the Python function behind the command; it takes the
same options (names with underscores).  :func:`add_fit_arguments` and
:func:`run_fit` plug into :mod:`fmbrdf_mi.cli`.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

from .. import polcam
from .models import BASELINES, MODELS
from .observations import (InputError, Observation, check_direction, downsample_geometry,
                           geometry_from_sphere, load_polarisation, parse_layout, pixel_rays,
                           read_mask, read_vectors)

OUTPUTS = ("fit.json", "profiles.png", "images.png", "history.png", "fitted_stokes.exr")
RELIGHT_OUTPUTS = ("relight.png",)


def parse_vector(text, name, n=3):
    if text is None:
        return None
    if isinstance(text, str):
        try:
            vals = [float(x) for x in text.replace(" ", "").split(",") if x]
        except ValueError:
            raise InputError(f"{name}: expected {n} comma-separated numbers, got {text!r}") from None
    else:
        vals = [float(x) for x in text]
    if len(vals) != n:
        raise InputError(f"{name}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def parse_bounds(items):
    """``["alpha=0.05:0.5", ...]`` -> {"alpha": (0.05, 0.5)}."""
    if isinstance(items, dict) or items is None:
        return items
    out = {}
    for item in items:
        name, sep, rng = str(item).partition("=")
        lo, sep2, hi = rng.partition(":")
        try:
            out[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise InputError(f"--bounds {item!r}: expected NAME=LO:HI, e.g. alpha=0.05:0.5") from None
        if not (sep and sep2):
            raise InputError(f"--bounds {item!r}: expected NAME=LO:HI, e.g. alpha=0.05:0.5")
    return out


def parse_init(text):
    """``"eta=1.5,alpha=0.3,..."`` -> dict (all reported parameters of the model)."""
    if isinstance(text, dict) or text is None:
        return text
    out = {}
    for item in str(text).split(","):
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise InputError(f"--init {text!r}: expected NAME=VALUE,..., e.g. eta=1.5,alpha=0.3,beta=2,"
                             "kappa=10,k_s=1,r_k=1") from None
    return out


def parse_fixed(items):
    """``["kappa=0", "eta=1.5"]`` or ``"kappa=0,eta=1.5"`` -> {"kappa": 0.0, "eta": 1.5} (shape parameters held fixed)."""
    if isinstance(items, dict) or items is None:
        return items
    items = [items] if isinstance(items, str) else list(items)
    out = {}
    for item in ",".join(items).split(","):
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise InputError(f"--fix {item!r}: expected NAME=VALUE, e.g. kappa=0") from None
        if not sep:
            raise InputError(f"--fix {item!r}: expected NAME=VALUE, e.g. kappa=0")
    return out


def _builtin_sphere(meta):
    """Geometry, light, irradiance and true material of an EXR from ``fmbrdf-mi render`` (built-in scene)."""
    if meta.get("scene") != "builtin:sphere" or "parameters" not in meta:
        return None
    from .. import scene as S

    p = meta["parameters"]
    n, v, m = S.sphere_geometry((int(p["width"]), int(p["height"])), camera=p["camera"],
                                fov=p["fov"], distance=p["distance"])
    truth = {k: p[k] for k in ("eta", "alpha", "beta", "kappa", "k_s", "r_k", "k_b") if k in p}
    return {"normals": n, "view_dirs": v, "mask": m, "light_dir": p["light_dir"],
            "irradiance": p["irradiance"], "truth": truth}


def build_observation(inputs, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                      fov=None, light=None, irradiance=None, layout=polcam.IMX250MZR_LAYOUT, black_level=0.0,
                      channel="mean", geometry=None, demosaic="bilinear", conversion_gain=None,
                      read_noise=None, footprint="auto", white_level=None, dark_level=None):
    """An :class:`Observation` from files (see :func:`fit_files` for the options).

    ``geometry``: (normals, mask, view_dirs) reused from another observation of the same object.
    A raw mosaic with a capture sidecar (:func:`fmbrdf_mi.camera.read_sidecar`,
    written by ``fmbrdf-mi render --raw``) supplies the layout, black level,
    gain, read noise and white level that were not given, and the scene's
    geometry and light.  ``meta["settings"]`` records what was used.
    """
    from .. import camera as C
    from . import samples as SM
    from .objective import NoiseModel

    sidecar = None
    if isinstance(inputs, (str, os.PathLike)) and not os.fspath(inputs).lower().endswith(".exr"):
        try:
            sidecar = C.read_sidecar(inputs)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    if sidecar is not None:
        cam = sidecar["sensor"]
        if cam.cfa is not None:
            raise InputError(f"{inputs}: a colour polarisation mosaic (sidecar {sidecar['path']}: cfa "
                             f"{''.join(c for r in cam.cfa for c in r)}); the fit command takes monochrome "
                             "mosaics only so far: fit it with fmbrdf_mi.fit.colour.fit_colour (README, "
                             "'Colour polarisation sensors')")
        layout = cam.layout if layout is None else layout
        black_level = cam.black_level if black_level is None else black_level
        if conversion_gain is None:
            conversion_gain, read_noise = cam.conversion_gain, cam.read_noise if read_noise is None else read_noise
        white_level = cam.white_level if white_level is None else white_level
    layout = polcam.IMX250MZR_LAYOUT if layout is None else layout
    black_level = 0.0 if black_level is None else float(black_level)
    if isinstance(layout, str):
        layout = parse_layout(layout)
    stokes, meta = load_polarisation(inputs, layout=layout, channel=channel, black_level=black_level,
                                     demosaic=demosaic)
    array = meta.pop("_array", None)
    if sidecar is not None:
        meta.update({k: v for k, v in sidecar.items() if k not in ("sensor", "path", C.SIDECAR_KEY)})
        meta["sidecar"] = sidecar["path"]
    shape = stokes.shape[1:]
    builtin = _builtin_sphere(meta) if (normals is None and sphere is None and geometry is None) else None
    exact = None
    if builtin is not None:
        n, m, v = builtin["normals"], builtin["mask"], builtin["view_dirs"]
        if meta.get("source") == "raw mosaic" and n.shape[:2] == (2 * shape[0], 2 * shape[1]):
            n, m, v = downsample_geometry(n, m, v)
        light = builtin["light_dir"] if light is None else light
        if irradiance is None:
            # a raw capture's DN are the Stokes image's units times the capture's DN per unit
            irradiance = builtin["irradiance"] * float(meta.get("capture", {}).get("dn_per_input_unit", 1.0))
        meta = dict(meta, truth=builtin["truth"])
        if n.shape[:2] != shape:
            raise InputError(f"{inputs}: metadata describe a {n.shape[1]}x{n.shape[0]} image, the file is "
                             f"{shape[1]}x{shape[0]}")
    elif geometry is not None:
        n, m, v = geometry
    elif normals is not None:
        if mask is None:
            raise InputError("normals: give the object mask too (--mask, .npy or .png, non-zero = object)")
        n = read_vectors(normals, "normals")
        m = read_mask(mask)
        if view is not None:
            v = read_vectors(view, "view")
        else:
            v = pixel_rays(n.shape[:2], camera, fov)
        if n.shape[:2] == (2 * shape[0], 2 * shape[1]):  # geometry at raw-sensor resolution
            n, m, v = downsample_geometry(n, m, v)
        for name, a in (("normals", n), ("mask", m), ("view", v)):
            if a.shape[:2] != shape:
                raise InputError(f"{name}: shape {a.shape[:2]} does not match the polarisation image "
                                 f"{shape} (a raw mosaic gives half its resolution)")
    elif sphere is not None:
        if isinstance(sphere, str) and sphere == "auto":
            if mask is None:
                raise InputError("--sphere auto: needs --mask to find the sphere in")
            centre = radius = None
        else:
            cx, cy, radius = parse_vector(sphere, "sphere (cx,cy,r in pixels)")
            centre = (cx, cy)
        mk = None
        if mask is not None:
            mk = read_mask(mask)
            if mk.shape == (2 * shape[0], 2 * shape[1]):  # mask of the raw mosaic: super-pixels inside it
                mk = mk.reshape(shape[0], 2, shape[1], 2).all(axis=(1, 3))
            elif mk.shape != tuple(shape):
                raise InputError(f"mask: shape {mk.shape} matches neither the polarisation image {tuple(shape)} "
                                 f"nor its raw mosaic {(2 * shape[0], 2 * shape[1])}")
        if centre is None:
            from .observations import find_sphere

            centre, radius = find_sphere(mk)
        n, m, v = geometry_from_sphere(shape, centre, radius, mk, camera, fov)
        meta["sphere"] = {"centre": [float(c) for c in centre], "radius": float(radius),
                          "found_from_mask": sphere == "auto"}
        if view is not None:
            v = read_vectors(view, "view", shape)
        else:
            from .observations import SphereGeometry

            exact = SphereGeometry(shape, centre, radius, camera, fov)
    else:
        raise InputError("geometry: give a normal map (--normals N.npy --mask M.png) or a sphere "
                         "(--sphere cx,cy,r or --sphere auto --mask M.png)")
    if light is None:
        raise InputError("light: give the light direction (--light x,y,z, from the surface towards the light; "
                         "x image right, y image up, z towards the camera)")
    light = check_direction(light, "light")
    var = None
    if conversion_gain is not None:
        from .camera_noise import linear_stokes_variance

        if not (conversion_gain > 0) or read_noise is None or not (read_noise >= 0):
            raise InputError(f"noise: --conversion-gain must be > 0 and --read-noise >= 0 given with it, got "
                             f"{conversion_gain}, {read_noise}")
        src = meta.get("source")
        var = linear_stokes_variance(stokes[0], float(conversion_gain), float(read_noise),
                                     demosaic if src == "raw mosaic" else "superpixel",
                                     adc_step_e=float(conversion_gain) if src in ("raw mosaic", "angle images")
                                     else None)
    from .camera_noise import box_footprint, demosaic_footprint

    if footprint == "auto":
        footprint = "demosaic" if meta.get("source") == "raw mosaic" else "point"
    fp = {"point": lambda: None, "box": lambda: box_footprint(3),
          "demosaic": lambda: demosaic_footprint(demosaic)}.get(footprint)
    if fp is None:
        raise InputError(f"footprint: expected auto, point, box or demosaic, got {footprint!r}")
    src = meta.get("source")
    samples = None
    if src == "raw mosaic":
        samples = SM.from_raw(array, layout, black_level, white_level, dark_level)
    elif src == "angle images":
        integer = np.issubdtype(np.asarray(array).dtype, np.integer)
        samples = SM.from_angle_images(array, black_level, white_level, dark_level, integer=integer)
    noise = None
    if conversion_gain is not None:
        noise = NoiseModel(float(conversion_gain), float(read_noise),
                           samples.step if samples is not None else 0.0)
    meta["settings"] = {"layout": [list(r) for r in layout], "black_level": black_level,
                        "demosaic": demosaic if src == "raw mosaic" else None, "footprint": footprint,
                        "white_level": None if samples is None else samples.white_level,
                        "dark_level": None if samples is None else samples.dark_level,
                        "conversion_gain": conversion_gain, "read_noise": read_noise,
                        "light": [float(x) for x in light],
                        "irradiance": 1.0 if irradiance is None else float(irradiance)}
    return Observation(stokes, m, n, v, light, 1.0 if irradiance is None else float(irradiance), meta,
                       lin_variance=var, footprint=fp(), samples=samples, noise=noise, geometry=exact)


def _outputs(out, relight):
    names = OUTPUTS + (RELIGHT_OUTPUTS if relight else ())
    return {n: os.path.join(out, n) for n in names}


def fit_files(inputs, out, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
              fov=None, light=None, irradiance=None, layout=None, black_level=None, channel="mean",
              demosaic="bilinear", conversion_gain=None, read_noise=None, footprint="auto", model="fmbrdf",
              baselines=False, optimizer="lm", path="pixel", bounds=None, init=None, loss="auto",
              white_level=None, dark_level=None, fixed=None, starts=2,
              max_iter=40, tol=1e-4, time_limit=None, max_time=None, max_pixels=20000, erode=2, seed=0, relight=None,
              relight_light=None, relight_irradiance=None, force=False, progress=True, command=None):
    """Fit ``model`` (and with ``baselines`` the two baselines) to a polarimetric image; write the outputs.

    Inputs: ``inputs`` a Stokes EXR, a raw mosaic (.npy / 16-bit .png / .tif,
    ``layout`` row-major 2x2 polariser angles, default IMX250MZR ``90,45,135,0``),
    a (4, H, W) .npy of angle images or four angle-image files (0, 45, 90, 135).
    Geometry: ``normals`` (.npy, H x W x 3, unit, camera frame) with ``mask``,
    or ``sphere`` ``"cx,cy,r"`` (pixels) or ``"auto"`` (found from ``mask``);
    view directions from ``view`` (.npy) or ``camera`` (``orthographic``, or
    ``perspective`` with ``fov`` degrees).  ``light`` x,y,z towards the light.
    An EXR written by ``fmbrdf-mi render`` (built-in sphere) brings its own
    geometry, light and true parameters.  ``conversion_gain`` (electrons per
    image unit) and ``read_noise`` (electrons): the DoLP term then compares the
    observed DoLP with the mean DoLP a camera with that noise measures.
    ``footprint``: ``point`` (pixel centres), ``box`` (3 x 3 over the pixel),
    ``demosaic`` (the raw pixels a demosaicked super-pixel comes from) or
    ``auto``.  ``relight``: a second image of the same object under
    ``relight_light`` for the relighting check.

    Writes ``out``/fit.json, profiles.png, images.png, history.png,
    fitted_stokes.exr (and relight.png); refuses to overwrite them without
    ``force``.  Returns the dict written to fit.json.
    """
    from . import plots, record
    from .fitting import FitOptions, fit, predict_image

    arguments = {k: v for k, v in locals().items() if k in record.ARGUMENTS}
    from .models import get_model
    from .relight import relight_error
    from .. import stokes_io

    from .options import check_fit_options, check_input_options
    from .._paths import check_output_dir

    get_model(model)
    check_input_options(black_level=black_level, conversion_gain=conversion_gain, read_noise=read_noise,
                        irradiance=irradiance, fov=fov, relight_irradiance=relight_irradiance)
    check_fit_options(model=model, optimizer=optimizer, path=path, bounds=parse_bounds(bounds),
                      init=parse_init(init), max_iter=max_iter, tol=tol, time_limit=time_limit,
                      max_time=max_time, max_pixels=max_pixels, erode=erode, seed=seed)
    check_output_dir(out)
    outs = _outputs(out, relight)
    if not force:
        for p in outs.values():
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")
    obs = build_observation(inputs, normals=normals, mask=mask, view=view, sphere=sphere, camera=camera,
                            fov=fov, light=light, irradiance=irradiance, layout=layout,
                            black_level=black_level, channel=channel, demosaic=demosaic,
                            conversion_gain=conversion_gain, read_noise=read_noise, footprint=footprint,
                            white_level=white_level, dark_level=dark_level)
    obs2 = None
    if relight is not None:
        geom = None if (normals is None and sphere is None and "truth" in obs.meta) \
            else (obs.normals, obs.mask, obs.view_dirs)
        obs2 = build_observation(relight, light=relight_light, irradiance=relight_irradiance,
                                 layout=layout, black_level=black_level, channel=channel, geometry=geom,
                                 demosaic=demosaic, conversion_gain=conversion_gain, read_noise=read_noise,
                                 footprint=footprint)
        if obs2.shape != obs.shape:
            raise InputError(f"relight image: shape {obs2.shape} differs from the fitted image {obs.shape}")
    opts = FitOptions(model=model, path="pixel", optimizer=optimizer, bounds=parse_bounds(bounds),
                      init=parse_init(init), max_iter=int(max_iter), tol=float(tol), time_limit=time_limit,
                      max_time=max_time or None, loss=loss, fixed=parse_fixed(fixed), starts=int(starts),
                      max_pixels=max_pixels, erode=int(erode), seed=int(seed))
    scene = None
    if path == "render":
        scene, opts.path = _render_scene(obs, model), "render"
    elif path != "pixel":
        raise InputError(f"path: expected 'pixel' or 'render', got {path!r}")
    os.makedirs(out, exist_ok=True)
    models = [model] + ([m for m in BASELINES if m != model] if baselines else [])
    results, preds = {}, {}
    report = {"inputs": inputs if isinstance(inputs, str) else list(inputs), "truth": obs.meta.get("truth"),
              "reproduce": record.reproduce_block(arguments, inputs, command, obs, relight), "models": {}}
    for name in models:
        o = opts if name == model else FitOptions(**{**opts.__dict__, "model": name, "bounds": None,
                                                      "init": None, "path": "pixel", "fixed": None})
        res = fit(obs, o, scene=scene if name == model else None, progress=progress)
        results[name] = res
        preds[name] = predict_image(name, res.params, obs)
        entry = res.to_json()
        if name == model and obs.meta.get("truth"):
            t = obs.meta["truth"]
            entry["relative_error"] = {k: (res.params[k] - t[k]) / t[k] for k in res.params
                                       if k in t and isinstance(t[k], (int, float)) and t[k] != 0}
        report["models"][name] = entry
    if obs2 is not None:
        report["relight"] = {"light_dir": obs2.light_dir.tolist()}
        relit = {}
        for name, res in results.items():
            err = relight_error(name, res.params, obs2, erode=opts.erode)
            relit[name] = err["predicted"]
            report["relight"][name] = {k: v for k, v in err.items() if k != "predicted"}
        plots.plot_images(obs2.stokes, relit[model], obs2.mask, outs["relight.png"],
                          title=f"relighting with the {model} estimates: RMSE/mean = "
                                f"{report['relight'][model]['rel_rmse']:.4f}", label="relit",
                          lin_variance=obs2.lin_variance)
    main = results[model]
    fitted = preds[model]
    plots.plot_profiles(obs, fitted, outs["profiles.png"], pixels=main.pixels,
                        title=f"{model}: " + ", ".join(f"{k}={v:.3g}" for k, v in main.params.items()),
                        others={f"{n} (baseline)": preds[n] for n in models[1:]})
    plots.plot_images(obs.stokes, fitted, obs.mask, outs["images.png"], title=f"{model} fit (per-pixel re-render)",
                      lin_variance=obs.lin_variance, pixels=main.pixels)
    plots.plot_loss_history({n: r.history for n, r in results.items()}, outs["history.png"])
    s4 = np.concatenate([fitted, np.zeros_like(fitted[:1])])[..., None]
    stokes_io.write_stokes_exr(outs["fitted_stokes.exr"], s4, {"fit": main.params, "model": model},
                               force=True)
    with open(outs["fit.json"], "w") as f:
        json.dump(report, f, indent=2, default=json_default)
    return report


def json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, tuple):
        return list(x)
    raise TypeError(f"not JSON serialisable: {type(x)}")


def _render_scene(obs, model):
    """The built-in sphere scene of a synthetic EXR, with the model's BSDF, for the render path."""
    meta = obs.meta
    if model != "fmbrdf" or meta.get("scene") != "builtin:sphere":
        raise InputError("path 'render' needs a Stokes EXR written by `fmbrdf-mi render` for the built-in "
                         "sphere (the scene is rebuilt from its metadata) and the fmbrdf model")
    from .. import scene as S
    from .pixel_model import set_variant

    mi = set_variant()
    p = meta["parameters"]
    d = S.sphere_scene({"k_s": 1.0, "k_b": 1.0}, light_dir=p["light_dir"], irradiance=p["irradiance"],
                       resolution=(int(p["width"]), int(p["height"])), spp=int(p.get("spp", 16)),
                       camera=p["camera"], fov=p["fov"], distance=p["distance"])
    return mi.load_dict(d)


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
    g.add_argument("--max-pixels", type=int, default=20000, help="random subset of usable pixels (0: all)")
    g.add_argument("--erode", type=int, default=2, help="pixels removed from the mask border")
    g.add_argument("--seed", type=int, default=0)
    g = p.add_argument_group("several images of one object (joint fit: shared material, one light each)")
    g.add_argument("--manifest", metavar="FILE.toml|json",
                   help="images, lights, relative powers, geometry and held-out images (fmbrdf_mi.fit.manifest)")
    g.add_argument("--authors", metavar="OBJECT_DIR",
                   help="an object in the paper authors' captured-data layout (calibration/L.txt, "
                        "image/img_ud/*.png, normal/normal_GT.npy, ...: fmbrdf_mi.fit.authors_layout)")
    g.add_argument("--holdout", metavar="I,J,...",
                   help="with --authors: image indices not fitted but predicted (relighting check)")
    g.add_argument("--free-power", action="store_true",
                   help="estimate the relative light power of every fitted image but the first (the "
                        "reference, held at its given power; the given powers are then starting values): "
                        "fmbrdf_mi.fit.free_power")
    g.add_argument("--power-start", default="ratio", choices=("ratio", "given"),
                   help="with --free-power: start the powers in closed form at every coarse-search point "
                        "(ratio, default) or at the given powers")
    from .normals_cli import add_arguments as add_normal_arguments

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


#: Exit status of a fit that stopped before it converged (time limit, iteration limit).
EXIT_NOT_CONVERGED = 3


def check_args(args):
    """Validate the command line's options before any file is read (one line per mistake)."""
    from .options import check_fit_options, check_input_options

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


def _colour_sidecar(path):
    from .colour_cli import colour_sidecar

    return colour_sidecar(path)


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


def run_fit(args):
    import shlex
    import sys

    t0 = time.time()
    check_args(args)
    command = shlex.join(["fmbrdf-mi", "fit", *getattr(args, "argv", [])])
    lights = args.light or []
    n_in = len(args.inputs or [])
    joint = bool(args.manifest or args.authors or len(lights) > 1 or n_in not in (0, 1, 4))
    if getattr(args, "free_power", False) and not joint:
        raise InputError("--free-power: with --from the fit.json's options apply (give none)" if args.from_json
                         else "--free-power: needs a joint fit of two or more images (--manifest, --authors, "
                              "or several INPUTs with one --light each)")
    from .normals_cli import check as check_normal_args

    check_normal_args(args, joint and not args.from_json)
    if joint:
        from .manifest import run_joint

        report = run_joint(args, command)
        if report.get("sensor") == "colour":
            from .colour_cli import print_colour

            return print_colour(report)
    elif args.from_json:
        from . import record

        if args.inputs:
            raise InputError("--from: give no INPUT files (they come from the fit.json)")
        from . import joint_record

        from .colour_cli import fit_colour_files, is_colour_record, print_colour

        if joint_record.is_joint(args.from_json):
            report = joint_record.rerun(args.from_json, args.out, force=args.force, progress=not args.quiet,
                                        command=command)
            if report.get("sensor") == "colour":
                return print_colour(report)
        elif is_colour_record(args.from_json):
            kw = record.rerun_arguments(args.from_json)
            report = fit_colour_files(out=args.out, force=args.force, progress=not args.quiet, command=command,
                                      **kw)
            return print_colour(report)
        else:
            kw = record.rerun_arguments(args.from_json)
            report = fit_files(out=args.out, force=args.force, progress=not args.quiet, command=command, **kw)
    elif len(args.inputs or []) == 1 and _colour_sidecar(args.inputs[0]) is not None:
        from .colour_cli import fit_colour_files, print_colour

        check_colour_args(args)
        report = fit_colour_files(args.inputs[0], args.out, normals=args.normals, mask=args.mask, view=args.view,
                                  sphere=args.sphere, camera=args.camera, fov=args.fov,
                                  light=parse_vector(lights[0] if lights else None, "--light"), irradiance=args.irradiance,
                                  black_level=args.black_level, white_level=args.white_level,
                                  conversion_gain=args.conversion_gain, read_noise=args.read_noise,
                                  model=args.model, bounds=args.bounds, fixed=args.fix, max_time=args.max_time,
                                  max_iter=args.max_iter, max_pixels=args.max_pixels or None, erode=args.erode,
                                  seed=args.seed, starts=args.starts, force=args.force, progress=not args.quiet,
                                  command=command)
        return print_colour(report)
    else:
        if not args.inputs:
            raise InputError("no INPUT given: a Stokes .exr, a raw mosaic, angle images, or --from fit.json")
        inputs = args.inputs if len(args.inputs) > 1 else args.inputs[0]
        relight = None if not args.relight else (args.relight if len(args.relight) > 1 else args.relight[0])
        report = fit_files(inputs, args.out, normals=args.normals, mask=args.mask, view=args.view,
                           sphere=args.sphere, camera=args.camera, fov=args.fov,
                           light=parse_vector(lights[0] if lights else None, "--light"),
                           irradiance=args.irradiance, layout=args.layout, black_level=args.black_level,
                           channel=args.channel, demosaic=args.demosaic, conversion_gain=args.conversion_gain,
                           read_noise=args.read_noise, footprint=args.footprint, model=args.model,
                           baselines=args.baselines, optimizer=args.optimizer, path=args.path, bounds=args.bounds,
                           init=args.init, loss=args.loss, white_level=args.white_level,
                           dark_level=args.dark_level, fixed=args.fix, starts=args.starts,
                           max_iter=args.max_iter, tol=args.tol, time_limit=args.time_limit,
                           max_time=args.max_time, max_pixels=args.max_pixels or None, erode=args.erode,
                           seed=args.seed, relight=relight,
                           relight_light=parse_vector(args.relight_light, "--relight-light"),
                           relight_irradiance=args.relight_irradiance, force=args.force,
                           progress=not args.quiet, command=command)
    if report.get("refine_normals"):
        from .normals_cli import print_report

        print_report(report)
        print(f"wrote {', '.join(report['refine_normals']['outputs'])} ({time.time() - t0:.1f} s)")
        return 0 if report["refine_normals"]["converged"] else EXIT_NOT_CONVERGED
    from .fitting import WEAK_REL

    status = 0
    for name, m in report["models"].items():
        unc = m.get("uncertainty") or {}
        print(f"{name}: {m['objective']} {m['loss']:.6e}  ({'converged' if m['converged'] else 'NOT converged'}: "
              f"{m['stop_reason']})")
        if m.get("noise"):
            print(f"  camera noise {m['noise']['description']}")
        ex = m.get("pixels_excluded") or {}
        if ex.get("saturated") or ex.get("dark"):
            print(f"  excluded {ex['saturated']} saturated and {ex['dark']} dark super-pixels of "
                  f"{ex['candidates']}; fitted {ex['used']}")
        std, ci = unc.get("std_errors", {}), unc.get("ci95", {})
        for k, v in m["params"].items():
            line = f"  {k:<6} {v:10.5g}"
            if k in std:
                line += f"  +- {std[k]:.3g}  95% [{ci[k][0]:.5g}, {ci[k][1]:.5g}]"
            if "relative_error" in m and k in m["relative_error"]:
                line += f"  (vs metadata {m['relative_error'][k]:+.2%})"
            print(line)
        if unc.get("method"):
            print(f"  uncertainty: {unc['method']}"
                  + (f"; chi2/dof {unc['chi2_per_dof']:.3f}" if "chi2_per_dof" in unc else "")
                  + (" (the model or the stated noise does not explain the data: errors too small)"
                     if unc.get("misfit") else ""))
        if unc.get("correlation"):
            c = unc["correlation"]
            big = [(c["names"][i], c["names"][j], c["matrix"][i][j]) for i in range(len(c["names"]))
                   for j in range(i + 1, len(c["names"])) if abs(c["matrix"][i][j]) > 0.9]
            if big:
                print("  strongly correlated: " + ", ".join(f"{a}/{b} {x:+.2f}" for a, b, x in big))
        if m.get("weakly_identified"):
            print(f"  weakly identified (standard error > {WEAK_REL:.0%} of the value, or at a bound): "
                  f"{', '.join(m['weakly_identified'])}")
        if not m["converged"]:
            print(f"fmbrdf-mi fit: {name}: stopped before convergence ({m['stop_reason']}); the estimates are "
                  f"the last accepted ones and have no standard errors (exit status {EXIT_NOT_CONVERGED})",
                  file=sys.stderr)
            status = EXIT_NOT_CONVERGED
    if report.get("joint"):
        from .manifest import print_joint

        print_joint(report)
        print(f"wrote {', '.join(report['joint']['outputs'])} ({time.time() - t0:.1f} s)")
        return status
    if "relight" in report:
        for name, r in report["relight"].items():
            if isinstance(r, dict):
                print(f"relighting {name}: RMSE / mean intensity = {r['rel_rmse']:.4f}")
    print(f"wrote {', '.join(_outputs(args.out, report.get('reproduce', {}).get('arguments', {}).get('relight')))} "
          f"({time.time() - t0:.1f} s)")
    return status


def main(argv=None):
    """Stand-alone entry: ``python -m fmbrdf_mi.fit ...`` (same as ``fmbrdf-mi fit``)."""
    import argparse

    p = argparse.ArgumentParser(prog="fmbrdf-mi fit", description=__doc__)
    add_fit_arguments(p)
    return run_fit(p.parse_args(argv))
