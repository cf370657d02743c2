"""Several images of one object from files: a manifest, the command's outputs per image.

A **manifest** (JSON or TOML; paths relative to it) lists the images of a
joint fit (:mod:`fmbrdf_mi.fit.joint`) and the options they share::

    # capture.toml
    [defaults]                 # any input option of `fmbrdf-mi fit`, shared by every image
    normals = "normal.npy"     # geometry (camera frame), or sphere = "auto" with mask
    mask = "mask.png"
    conversion_gain = 2.44     # the camera (one camera for all images)
    read_noise = 2.5

    [[image]]
    input = "light0.png"       # raw mosaic, Stokes EXR, (4, H, W) .npy, or a list of four angle images
    light = [-0.42, 0.31, 0.85]
    power = 1.0                # relative light power (default 1): multiplies the irradiance

    [[image]]
    input = "light1.png"
    light = [0.5, 0.1, 0.86]
    power = 0.8
    normals = "view2_normal.npy"   # per-image geometry: another view of the object
    mask = "view2_mask.png"

    [[image]]
    input = "light2.png"
    light = [0.1, -0.6, 0.8]
    holdout = true             # not fitted: predicted from the estimates (relighting check)

Keys of an image entry: ``input`` (required), ``light`` (required unless
the input carries it), ``power``, ``holdout``, ``name`` (default: the input's
file stem) and any key of ``[defaults]``, which it overrides: ``normals``,
``mask``, ``view``, ``sphere``, ``camera``, ``fov``, ``irradiance``,
``layout``, ``black_level``, ``white_level``, ``dark_level``, ``channel``,
``demosaic``, ``footprint``, ``conversion_gain``, ``read_noise``.  Unknown
keys are refused, naming them.

:func:`fit_images` fits the images (optionally the baselines too, with the
same loss) and writes ``fit.json`` (the shared estimate, its uncertainty
from the joint Fisher information, per-image diagnostics and relighting
errors), ``images_NAME.png`` and ``profiles_NAME.png`` per fitted image,
``relight_NAME.png`` per held-out image and ``history.png``.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re

import numpy as np

from .observations import InputError

#: Options an image entry (or [defaults]) may give: :func:`fmbrdf_mi.fit.cli.build_observation`'s.
INPUT_KEYS = ("normals", "mask", "view", "sphere", "camera", "fov", "irradiance", "layout", "black_level",
              "white_level", "dark_level", "channel", "demosaic", "footprint", "conversion_gain", "read_noise")
PATH_KEYS = ("input", "normals", "mask", "view")
ENTRY_KEYS = ("input", "light", "power", "holdout", "name") + INPUT_KEYS


@dataclasses.dataclass
class ImageSpec:
    """One image of a joint fit: its input and the options that build its Observation."""

    input: object                   # path, list of four paths, or an Observation already built
    light: object = None
    power: float = 1.0
    holdout: bool = False
    name: str = None
    options: dict = dataclasses.field(default_factory=dict)


def file_stem(p):
    p = p[0] if isinstance(p, (list, tuple)) else p
    return os.path.splitext(os.path.basename(os.fspath(p)))[0]


def read_manifest(path):
    """[ImageSpec] from a JSON or TOML manifest (paths made relative to the manifest's directory)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"manifest {path}: no such file")
    try:
        if path.lower().endswith(".toml"):
            import tomllib

            with open(path, "rb") as f:
                d = tomllib.load(f)
        else:
            with open(path) as f:
                d = json.load(f)
    except (ValueError, OSError) as exc:
        raise InputError(f"manifest {path}: not readable ({exc})") from None
    return parse_manifest(d, os.path.dirname(os.path.abspath(path)), path)


def parse_manifest(d, base=".", where="manifest"):
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a table with [defaults] and [[image]] entries")
    unknown = [k for k in d if k not in ("defaults", "image", "images")]
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)} (expected defaults, image)")
    defaults = d.get("defaults", {}) or {}
    if not isinstance(defaults, dict):
        raise InputError(f"{where}: defaults must be a table")
    bad = [k for k in defaults if k not in INPUT_KEYS]
    if bad:
        raise InputError(f"{where}: defaults: unknown key(s) {', '.join(bad)} (valid: {', '.join(INPUT_KEYS)})")
    entries = d.get("image", d.get("images"))
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where}: no images (give [[image]] entries with input and light)")

    def rel(v):
        if isinstance(v, str):
            return v if os.path.isabs(v) else os.path.join(base, v)
        if isinstance(v, list):
            return [rel(x) for x in v]
        return v

    specs = []
    for k, e in enumerate(entries):
        if not isinstance(e, dict) or "input" not in e:
            raise InputError(f"{where}: image {k}: expected a table with at least 'input'")
        bad = [x for x in e if x not in ENTRY_KEYS]
        if bad:
            raise InputError(f"{where}: image {k}: unknown key(s) {', '.join(bad)} (valid: {', '.join(ENTRY_KEYS)})")
        opts = {**defaults, **{x: e[x] for x in INPUT_KEYS if x in e}}
        for x in PATH_KEYS[1:]:
            if x in opts and isinstance(opts[x], (str, list)):
                opts[x] = rel(opts[x])
        power = e.get("power", 1.0)
        if isinstance(power, bool) or not isinstance(power, (int, float)) or not (np.isfinite(power) and power > 0):
            raise InputError(f"{where}: image {k}: power must be a positive number, got {power!r}")
        if not isinstance(e.get("holdout", False), bool):
            raise InputError(f"{where}: image {k}: holdout must be true or false")
        specs.append(ImageSpec(rel(e["input"]), e.get("light"), float(power), bool(e.get("holdout", False)),
                               e.get("name"), opts))
    return specs


def image_names(specs):
    names, seen = [], {}
    for k, s in enumerate(specs):
        n = s.name or (file_stem(s.input) if not hasattr(s.input, "stokes") else f"image{k}")
        n = re.sub(r"[^A-Za-z0-9_.-]", "_", str(n)) or f"image{k}"
        if n in seen:
            n = f"{n}_{k}"
        seen[n] = 1
        names.append(n)
    return names


def build_observations(specs):
    """Observations of the specs (each with irradiance x power)."""
    from .cli import parse_vector, build_observation

    out = []
    for k, s in enumerate(specs):
        if hasattr(s.input, "stokes"):
            o = s.input
        else:
            opts = dict(s.options)
            opts.setdefault("layout", None)        # None: the capture sidecar's, else IMX250MZR
            opts.setdefault("black_level", None)
            try:
                light = parse_vector(s.light, f"image {k}: light") if s.light is not None else None
                o = build_observation(s.input, light=light, **opts)
            except InputError as exc:
                raise InputError(f"image {k} ({file_stem(s.input)}): {exc}") from None
        if s.power != 1.0:
            o = dataclasses.replace(o, irradiance=o.irradiance * s.power)
        out.append(o)
    return out


def outputs(out, names, holdout):
    files = ["fit.json", "history.png"]
    for n, h in zip(names, holdout):
        files += [f"relight_{n}.png"] if h else [f"images_{n}.png", f"profiles_{n}.png"]
    return [os.path.join(out, f) for f in files]


def prepare_outputs(specs, out, outputs_fn, force):
    """(names, held-out flags, output files) of a joint fit; refuses an all-held-out set, an unusable ``out``
    and, without ``force``, existing outputs (before anything is read or written)."""
    from .._paths import check_output_dir

    names = image_names(specs)
    holdout = [s.holdout for s in specs]
    if all(holdout):
        raise InputError("joint fit: every image is held out; fit at least one")
    check_output_dir(out)
    files = outputs_fn(out, names, holdout)
    if not force:
        for p in files:
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")
    return names, holdout, files


def fit_images(specs, out, *, model="fmbrdf", baselines=False, force=False, progress=True, command=None,
               observations=None, extra=None, reproduce=None, **fit_kw):
    """Joint fit of the non-held-out images of ``specs``, relighting check on the held-out ones; write outputs.

    ``fit_kw``: :class:`~fmbrdf_mi.fit.fitting.FitOptions` fields (loss,
    fixed, bounds, init, max_pixels, ...).  ``reproduce``: called with the
    observations, returns fit.json's ``reproduce`` block (the command's:
    :func:`fmbrdf_mi.fit.joint_record.block`).  Returns the dict written to fit.json.
    """
    from . import plots
    from .fitting import FitOptions, predict_image
    from .joint import fit_joint, fitted_observation, power_text
    from .options import check_fit_options
    from .relight import relight_error

    check_fit_options(model=model, **fit_kw)
    names, holdout, files = prepare_outputs(specs, out, outputs, force)
    obs = observations if observations is not None else build_observations(specs)
    fit_obs = [o for o, h in zip(obs, holdout) if not h]
    fit_names = [n for n, h in zip(names, holdout) if not h]
    opts = FitOptions(model=model, **fit_kw)
    if opts.free_power and len(fit_obs) < 2:
        raise InputError(f"--free-power (free_power): needs two or more fitted images, got {len(fit_obs)} (one "
                         "image's light power is not separable from k_s and k_b)")
    given = [given_power(s, o) for s, o, h in zip(specs, obs, holdout) if not h]
    models = [model] + ([m for m in ("pplastic", "lambert_ts") if m != model] if baselines else [])
    results = {}
    for name in models:
        o = opts if name == model else dataclasses.replace(opts, model=name, bounds=None, init=None, fixed=None)
        results[name] = fit_joint(fit_obs, o, names=fit_names, progress=progress, powers=given)
    main = results[model]
    truth = next((o.meta.get("truth") for o in obs if o.meta.get("truth")), None)
    report = {"images": [{"name": n, "input": (s.input if isinstance(s.input, (str, list)) else None),
                          "light_dir": o.light_dir.tolist(), "irradiance": o.irradiance,
                          "power": given_power(s, o), "holdout": s.holdout} for n, s, o in zip(names, specs, obs)],
              "truth": truth, "models": {}, "relight": {}}
    if main.powers is not None:
        for im in report["images"]:
            fitted = next((x for x in main.images if x["name"] == im["name"]), None)
            if fitted is not None:
                im.update({"power_fitted": fitted["power"], "power_se": fitted["power_se"],
                           "power_reference": fitted["power_reference"]})
    if reproduce is not None:
        report["reproduce"] = reproduce(obs)
    elif command is not None:
        from .record import versions

        report["reproduce"] = {"command": command, "cwd": os.getcwd(), "versions": versions()}
    report.update(extra or {})
    os.makedirs(out, exist_ok=True)
    for name, res in results.items():
        entry = res.to_json()
        if name == model and truth:
            entry["relative_error"] = {k: (res.params[k] - truth[k]) / truth[k] for k in res.params
                                       if isinstance(truth.get(k), (int, float)) and truth[k] != 0}
        report["models"][name] = entry
    for n, o, h, idx in zip(names, obs, holdout, _pixels_of(main, holdout)):
        if h:
            errs, relit = {}, None
            for name, res in results.items():
                e = relight_error(name, res.params, o, erode=opts.erode)
                errs[name] = {k: v for k, v in e.items() if k != "predicted"}
                if name == model:
                    relit = e["predicted"]
            report["relight"][n] = errs
            plots.plot_images(o.stokes, relit, o.mask, os.path.join(out, f"relight_{n}.png"),
                              title=f"{n}: relit with the {model} estimates, RMSE/mean = "
                                    f"{errs[model]['rel_rmse']:.4f}", label="relit", lin_variance=o.lin_variance)
        else:
            im = {m: next(x for x in r.images if x["name"] == n) for m, r in results.items()}
            pred = predict_image(model, main.params, fitted_observation(o, im[model]))
            others = {f"{m} (baseline)": predict_image(m, r.params, fitted_observation(o, im[m]))
                      for m, r in results.items() if m != model}
            power = "" if main.powers is None else "; " + power_text(im[model])
            plots.plot_profiles(o, pred, os.path.join(out, f"profiles_{n}.png"), pixels=idx,
                                title=f"{n}: " + ", ".join(f"{k}={v:.3g}" for k, v in main.params.items()) + power,
                                others=others)
            plots.plot_images(o.stokes, pred, o.mask, os.path.join(out, f"images_{n}.png"),
                              title=f"{n}: joint {model} fit (per-pixel re-render){power}",
                              lin_variance=o.lin_variance, pixels=idx)
    plots.plot_loss_history({n: r.fit.history for n, r in results.items()}, os.path.join(out, "history.png"))
    from .cli import json_default

    with open(os.path.join(out, "fit.json"), "w") as f:
        json.dump(report, f, indent=2, default=json_default)
    return report


def fitter(specs):
    """(fit function, outputs function) for the images of ``specs``: :func:`fit_images` and :func:`outputs`, or
    their colour counterparts in :mod:`fmbrdf_mi.fit.colour_joint` when the images are colour mosaics."""
    from . import colour_joint

    if colour_joint.is_colour(specs):
        return colour_joint.fit_colour_images, colour_joint.outputs
    return fit_images, outputs


def given_power(spec, obs):
    """The relative light power image ``spec`` was given: the manifest's ``power``, the authors'
    ``intensities.npy`` / max (both already in the observation's irradiance), 1 if none."""
    return float((obs.meta.get("authors_layout") or {}).get("power", spec.power))


def _pixels_of(res, holdout):
    it = iter(res.pixels)
    return [None if h else next(it) for h in holdout]


# ---------------------------------------------------------------- the command
def _cli_input_options(args):
    keys = {"normals": "normals", "mask": "mask", "view": "view", "sphere": "sphere", "camera": "camera",
            "fov": "fov", "irradiance": "irradiance", "layout": "layout", "black_level": "black_level",
            "white_level": "white_level", "dark_level": "dark_level", "channel": "channel",
            "demosaic": "demosaic", "footprint": "footprint", "conversion_gain": "conversion_gain",
            "read_noise": "read_noise"}
    return {k: getattr(args, a) for k, a in keys.items() if getattr(args, a, None) is not None}


def run_joint(args, command):
    """``fmbrdf-mi fit --manifest M | --authors DIR | IMG1 IMG2 ... --light L1 --light L2 ...``."""
    from .cli import parse_vector, parse_bounds, parse_fixed, parse_init

    if args.from_json:
        raise InputError("--from: give no --manifest, --authors or INPUT files (they come from the fit.json)")
    if args.relight:
        raise InputError("--relight: in a joint fit, mark held-out images instead (holdout = true in the "
                         "manifest, --holdout with --authors)")
    if args.optimizer != "lm" or args.path != "pixel":
        raise InputError("joint fits use --optimizer lm and --path pixel")
    cli_opts = _cli_input_options(args)
    info = authors = None
    if args.manifest:
        if args.inputs:
            raise InputError("--manifest: give no INPUT files (the manifest lists them)")
        specs = read_manifest(args.manifest)
        for s in specs:
            for k, v in cli_opts.items():
                s.options.setdefault(k, v)
    elif args.authors:
        if args.inputs:
            raise InputError("--authors: give no INPUT files (they are the directory's image/img_ud/*.png)")
        from .authors_layout import read_object

        try:
            hold = [int(x) for x in str(args.holdout).split(",") if x.strip()] if args.holdout else []
        except ValueError:
            raise InputError(f"--holdout {args.holdout!r}: expected image indices such as 3,7") from None
        authors = dict(mask=None if args.mask is None else os.path.abspath(args.mask), holdout=hold,
                       conversion_gain=args.conversion_gain, read_noise=args.read_noise,
                       white_level=65535.0 if args.white_level is None else args.white_level,
                       dark_level=args.dark_level, black_level=0.0 if args.black_level is None else args.black_level,
                       demosaic=args.demosaic, footprint=args.footprint)
        specs, info = read_object(args.authors, **authors)
    else:
        if len(args.light or []) != len(args.inputs):
            raise InputError(f"--light given {len(args.light or [])} times for {len(args.inputs)} INPUT images: a joint "
                             "fit takes one light per image (four angle images of one light: use a (4, H, W) "
                             ".npy, or a manifest)")
        specs = [ImageSpec(inp, parse_vector(li, f"--light {k + 1}"), options=dict(cli_opts))
                 for k, (inp, li) in enumerate(zip(args.inputs, args.light))]
    names = image_names(specs)
    fit_fn, outputs_fn = fitter(specs)
    if fit_fn is not fit_images:
        from .cli import check_colour_args

        check_colour_args(args)
    files = outputs_fn(args.out, names, [s.holdout for s in specs])
    if not args.authors:   # the record names files by absolute path (a rerun may start elsewhere)
        for s in specs:
            s.input = absolute_paths(s.input)
            s.options.update({k: absolute_paths(s.options[k]) for k in PATH_KEYS[1:] if k in s.options})
    fit_kw = dict(model=args.model, baselines=args.baselines, loss=args.loss, fixed=parse_fixed(args.fix),
                  bounds=parse_bounds(args.bounds), init=parse_init(args.init), starts=args.starts,
                  max_iter=args.max_iter, tol=args.tol, time_limit=args.time_limit, max_time=args.max_time,
                  max_pixels=args.max_pixels or None, erode=args.erode, seed=args.seed,
                  free_power=getattr(args, "free_power", False), power_start=getattr(args, "power_start", "ratio"))
    kind = "manifest" if args.manifest else "authors" if args.authors else "lights"
    if getattr(args, "refine_normals", False):
        from .normals_cli import run as refine

        obs = build_observations(specs)
        # the authors' layout carries the ground truth (normal/normal_GT.npy): it is the geometry read
        gt = obs[0].normals.copy() if args.authors else None
        return refine(specs, names, obs, args.out, start=args.normals_start, lam=args.smooth, rounds=args.rounds,
                      model=args.model, fit_kw={k: v for k, v in fit_kw.items() if k not in ("model", "baselines")},
                      ground_truth=gt, force=args.force, progress=not args.quiet, command=command)

    def reproduce(obs):
        from .joint_record import block

        return block(kind, specs, names, obs, fit_kw, command, manifest=args.manifest, authors=authors, info=info)

    report = fit_fn(specs, args.out, force=args.force, progress=not args.quiet, command=command,
                    extra={"joint": {"outputs": files, "authors_layout": info}}, reproduce=reproduce, **fit_kw)
    return report


def absolute_paths(v):
    if isinstance(v, str):
        return os.path.abspath(v)
    if isinstance(v, list):
        return [absolute_paths(x) for x in v]
    return v


def print_joint(report):
    for name, m in report["models"].items():
        for im in m.get("images", []):
            line = f"  {im['name']}: {im['n_pixels']} px, light {np.round(im['light_dir'], 3).tolist()}"
            if im.get("chi2_per_dof") is not None:
                line += f", chi2/dof {im['chi2_per_dof']:.3f}"
            line += f", intensity RMSE/mean {im['intensity_rel_rmse']:.4f}"
            if im.get("power") is not None:
                from .joint import power_text

                line += ", " + power_text(im)
            print(f"{name}{line}" if len(report["models"]) > 1 else line)
    for img, errs in report.get("relight", {}).items():
        for name, e in errs.items():
            print(f"relighting {img} ({name}): RMSE / mean intensity = {e['rel_rmse']:.4f}")
