"""``fmbrdf-mi fit RAW`` on a colour polarisation mosaic (a capture sidecar with ``"cfa"``).

:func:`fit_colour_files` reads the mosaic and its sidecar, builds the geometry
on the grid of 4x4 periods (the mono path's 2x2 super-pixels, one level
coarser), fits shared eta, alpha, beta, kappa with per-channel k_s, r_k by
:func:`fmbrdf_mi.fit.colour.fit_colour` and writes ``fit.json`` and
``colour_fit.png``; :func:`print_colour` is the stdout summary.

Geometry: ``--sphere cx,cy,r`` (period units: pixel centres at +0.5 periods)
or ``--sphere auto --mask M``, or ``--normals N --mask M``; maps at the raw
mosaic's resolution are pooled over each 4x4 period (mean normal, mask = all
16 pixels), maps at the period resolution are taken as they are.  Without
either, a sidecar written by ``fmbrdf-mi render --raw --sensor colour``
(built-in sphere) gives the scene's own sphere, light and irradiance.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np

from . import observations as ob
from .observations import InputError

OUTPUTS = ("fit.json", "colour_fit.png")


def colour_sidecar(inputs):
    """The capture sidecar of a single raw input when it describes a colour sensor, else None."""
    from .. import camera as C

    if isinstance(inputs, (list, tuple)):
        if len(inputs) != 1:
            return None
        inputs = inputs[0]
    if not isinstance(inputs, (str, os.PathLike)) or os.fspath(inputs).lower().endswith(".exr"):
        return None
    try:
        side = C.read_sidecar(inputs)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return side if side is not None and side["sensor"].cfa is not None else None


def is_colour_record(path):
    """Whether ``path`` (a fit.json with a ``reproduce`` block) records a colour fit (``--from`` reruns it)."""
    from . import record

    record.load(path)      # refuses files that are not fit.json records, in one line
    with open(path) as f:
        return json.load(f).get("sensor") == "colour"


def _pool4(n, m, v):
    """Raw-resolution maps -> 4x4-period maps (two 2x2 poolings: the mean of 16, mask = all 16)."""
    return ob.downsample_geometry(*ob.downsample_geometry(n, m, v))


def _mask_at(mask, shape):
    mk = ob.read_mask(mask)
    if mk.shape == (4 * shape[0], 4 * shape[1]):      # mask of the raw mosaic: periods wholly inside it
        return mk.reshape(shape[0], 4, shape[1], 4).all(axis=(1, 3))
    if mk.shape != tuple(shape):
        raise InputError(f"mask: shape {mk.shape} matches neither the mosaic's 4x4 periods {tuple(shape)} nor the "
                         f"raw mosaic {(4 * shape[0], 4 * shape[1])}")
    return mk


def colour_geometry(shape, side, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                    fov=None):
    """(normals, mask, view_dirs, exact geometry or None, meta) on the period grid ``shape``."""
    meta = {}
    params = side.get("parameters") if side.get("scene") == "builtin:sphere" else None
    if normals is not None:
        if mask is None:
            raise InputError("normals: give the object mask too (--mask, .npy or .png, non-zero = object)")
        n = ob.read_vectors(normals, "normals")
        m = ob.read_mask(mask)
        v = ob.read_vectors(view, "view") if view is not None else ob.pixel_rays(n.shape[:2], camera, fov)
        if n.shape[:2] == (4 * shape[0], 4 * shape[1]):
            n, m, v = _pool4(n, m, v)
        for name, a in (("normals", n), ("mask", m), ("view", v)):
            if a.shape[:2] != tuple(shape):
                raise InputError(f"{name}: shape {a.shape[:2]} matches neither the mosaic's 4x4 periods "
                                 f"{tuple(shape)} nor the raw mosaic {(4 * shape[0], 4 * shape[1])}")
        return n, m, v, None, meta
    if sphere is not None:
        mk = _mask_at(mask, shape) if mask is not None else None
        if isinstance(sphere, str) and sphere == "auto":
            if mk is None:
                raise InputError("--sphere auto: needs --mask to find the sphere in")
            centre, radius = ob.find_sphere(mk)
        else:
            from .cli import parse_vector

            cx, cy, radius = parse_vector(sphere, "--sphere (cx,cy,r in 4x4 periods)")
            centre = (cx, cy)
        n, m, v = ob.geometry_from_sphere(shape, centre, radius, mk, camera, fov)
        meta["sphere"] = {"centre": [float(c) for c in centre], "radius": float(radius),
                          "found_from_mask": sphere == "auto", "units": "4x4 periods"}
        if view is not None:
            return n, m, ob.read_vectors(view, "view", shape), None, meta
        return n, m, v, ob.SphereGeometry(shape, centre, radius, camera, fov), meta
    if params is not None:
        from .. import scene as S

        w, h = int(params["width"]), int(params["height"])
        if (h, w) != (4 * shape[0], 4 * shape[1]):
            raise InputError(f"{side['path']}: describes a {w}x{h} render, the mosaic is "
                             f"{4 * shape[1]}x{4 * shape[0]}")
        if params["camera"] == "orthographic":
            # the built-in scene: unit sphere at the origin, image half-width distance * tan(fov / 2)
            r = w / 2 / (params["distance"] * math.tan(math.radians(params["fov"]) / 2)) / 4
            centre = (shape[1] / 2, shape[0] / 2)
            n, m, v = ob.sphere_normals(shape, centre, r)
            meta["sphere"] = {"centre": list(centre), "radius": r, "from": "sidecar (built-in sphere)",
                              "units": "4x4 periods"}
            return n, m, v, ob.SphereGeometry(shape, centre, r), meta
        n, v, m = S.sphere_geometry((w, h), camera=params["camera"], fov=params["fov"],
                                    distance=params["distance"])
        n, m, v = _pool4(n, m, v)
        return n, m, v, None, meta
    raise InputError("geometry: give a normal map (--normals N.npy --mask M.png) or a sphere (--sphere cx,cy,r in "
                     "4x4 periods, or --sphere auto --mask M.png)")


def _ci95(model, name, value, se, bounds=None):
    """value +- 1.96 SE, cut at the parameter's bounds (albedos: at 0), as fit.json's mono intervals."""
    from .models import Bounds, get_model

    if isinstance(value, dict):
        return {c: [max(0.0, value[c] - 1.96 * se[c]), value[c] + 1.96 * se[c]] for c in value}
    lo, hi = Bounds(get_model(model), bounds).lims[name][2:]
    return [max(lo, value - 1.96 * se), min(hi, value + 1.96 * se)]


class ColourInput:
    """One colour mosaic read for a fit: its Observation on the period grid, samples, camera, noise and metadata."""

    def __init__(self, obs, samples, camera, noise, truth, side):
        self.obs, self.samples, self.camera, self.noise, self.truth, self.side = obs, samples, camera, noise, truth, side


def read_colour_input(path, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic", fov=None,
                      light=None, irradiance=None, power=1.0, black_level=None, white_level=None,
                      conversion_gain=None, read_noise=None, erode=2):
    """A :class:`ColourInput` of the raw colour mosaic ``path`` (its capture sidecar gives the camera).

    Light and irradiance default to the sidecar's built-in scene; the
    irradiance is multiplied by ``power`` (a joint fit's relative light power).
    The Observation's ``meta`` holds ``settings``, ``sphere``, ``sidecar`` and
    ``truth`` (the built-in scene's parameters) as the mono path's do.
    """
    from .colour import colour_samples
    from .objective import NoiseModel

    path = os.fspath(path)
    side = colour_sidecar(path)
    if side is None:
        raise InputError(f"{path}: no colour capture sidecar ({os.path.splitext(path)[0]}.json with \"cfa\")")
    cam = side["sensor"]
    raw = ob.read_array(path, "raw colour mosaic")
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number):
        raise InputError(f"{path}: expected a single-channel raw mosaic, got an array of shape {raw.shape}")
    black = cam.black_level if black_level is None else float(black_level)
    white = cam.white_level if white_level is None else float(white_level)
    smp = colour_samples(raw, cam.layout, cam.cfa, black, white)
    shape = smp.values.shape[1:]
    n, m, v, exact, gmeta = colour_geometry(shape, side, normals=normals, mask=mask, view=view, sphere=sphere,
                                            camera=camera, fov=fov)
    params = side.get("parameters") if side.get("scene") == "builtin:sphere" else {}
    if light is None:
        light = params.get("light_dir") if params else None
    if light is None:
        raise InputError("light: give the light direction (--light x,y,z, from the surface towards the light; "
                         "x image right, y image up, z towards the camera)")
    light = ob.check_direction(light, "light")
    if irradiance is None and params:
        # the raw DN are the render's units times the capture's DN per unit
        irradiance = params["irradiance"] * float(side.get("capture", {}).get("dn_per_input_unit", 1.0))
    irradiance = (1.0 if irradiance is None else float(irradiance)) * float(power)
    gain = cam.conversion_gain if conversion_gain is None else float(conversion_gain)
    rn = cam.read_noise if read_noise is None else float(read_noise)
    if not (gain > 0 and rn >= 0):
        raise InputError(f"noise: --conversion-gain must be > 0 and --read-noise >= 0, got {gain}, {rn}")
    truth = {k: params[k] for k in ("eta", "alpha", "beta", "kappa", "k_s", "r_k") if k in params} or None
    settings = {"layout": [list(r) for r in cam.layout], "cfa": [list(r) for r in cam.cfa], "black_level": black,
                "white_level": white, "conversion_gain": gain, "read_noise": rn,
                "light": [float(x) for x in light], "irradiance": irradiance, "erode": int(erode),
                "grid": "4x4 periods", "geometry": "exact sphere" if exact is not None else "maps"}
    meta = {"settings": settings, "sphere": gmeta.get("sphere"), "sidecar": side["path"], "truth": truth}
    obs = ob.Observation(np.ones((3,) + tuple(shape)), ob.erode(m, int(erode)), n, v, light, irradiance,
                         geometry=exact, meta=meta)
    return ColourInput(obs, smp, cam, NoiseModel(gain, rn, 1.0), truth, side)


def model_entry(model, res, bounds, fixed, truth):
    """fit.json's ``models[model]`` of a :func:`~fmbrdf_mi.fit.colour.fit_colour` result (intervals, errors)."""
    std = res["std_errors"]
    entry = {k: res[k] for k in ("model", "params", "std_errors", "chi2", "chi2_per_dof", "n_pixels", "n_samples",
                                 "noise", "evaluations", "time_s", "channels", "converged", "stop_reason")}
    entry["ci95"] = None if std is None else {k: _ci95(model, k, val, std.get(k), bounds)
                                              for k, val in res["params"].items() if std.get(k) is not None}
    entry["fixed"] = fixed or {}
    if truth:
        rel = {}
        for k, t in truth.items():
            val = res["params"].get(k)
            if isinstance(val, dict):
                tt = t if isinstance(t, (list, tuple)) else [t] * 3
                rel[k] = {c: (val[c] - tt[i]) / tt[i] for i, c in enumerate(res["channels"]) if tt[i]}
            elif val is not None and not isinstance(t, (list, tuple)) and t:
                rel[k] = (val - t) / t
        entry["relative_error"] = rel
    return entry


def fit_colour_files(inputs, out, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                     fov=None, light=None, irradiance=None, black_level=None, white_level=None,
                     conversion_gain=None, read_noise=None, model="fmbrdf", bounds=None, fixed=None,
                     max_time=None, max_iter=40, max_pixels=20000, erode=2, seed=0, starts=2, force=False,
                     progress=True, command=None):
    """Fit a colour polarisation mosaic (module docstring); write ``out``/fit.json and colour_fit.png.

    Returns the dict written to fit.json (``models[model]``: params with
    per-channel k_s and r_k, std_errors, ci95, converged, stop_reason ...).
    """
    import time

    from .._paths import check_output_dir
    from . import record
    from .cli import json_default, parse_bounds, parse_fixed
    from .colour import fit_colour, format_result, predict_samples
    from .models import get_model

    t0 = time.time()
    arguments = {k: v for k, v in locals().items() if k in record.ARGUMENTS}
    path = inputs[0] if isinstance(inputs, (list, tuple)) else inputs
    path = os.fspath(path)
    if colour_sidecar(path) is None:
        raise InputError(f"{path}: no colour capture sidecar ({os.path.splitext(path)[0]}.json with \"cfa\")")
    get_model(model)
    bounds, fixed = parse_bounds(bounds), parse_fixed(fixed)
    check_output_dir(out)
    outs = {n: os.path.join(out, n) for n in OUTPUTS}
    if not force:
        for p in outs.values():
            if os.path.exists(p):
                raise FileExistsError(f"{p} exists; pass --force (force=True) to overwrite it")
    ci = read_colour_input(path, normals=normals, mask=mask, view=view, sphere=sphere, camera=camera, fov=fov,
                           light=light, irradiance=irradiance, black_level=black_level, white_level=white_level,
                           conversion_gain=conversion_gain, read_noise=read_noise, erode=erode)
    obs, smp, cam = ci.obs, ci.samples, ci.camera
    say = (lambda s: print(s, flush=True)) if progress else None
    if progress:
        print(f"colour fit of {path}: {obs.shape[1]}x{obs.shape[0]} periods, {int((obs.mask & smp.usable).sum())} "
              f"usable in the mask (eroded by {erode}), cfa {''.join(c for r in cam.cfa for c in r)}", flush=True)
    res = fit_colour(obs, smp, ci.noise, model=model, fixed=fixed, bounds=bounds, max_pixels=max_pixels or None,
                     seed=seed, progress=say, max_time=max_time, max_iter=max_iter, starts=int(starts))
    meta = {k: obs.meta[k] for k in ("settings", "sphere", "sidecar")}
    report = {"inputs": path, "sensor": "colour", "truth": ci.truth,
              "reproduce": record.reproduce_block(arguments, path, command, type("O", (), {"meta": meta})),
              "models": {model: model_entry(model, res, bounds, fixed, ci.truth)}}
    pred = predict_samples(obs, smp, res)
    os.makedirs(out, exist_ok=True)
    plot_colour_fit(smp, pred, obs.mask & smp.usable, cam, outs["colour_fit.png"],
          title=f"{model}: " + format_result(res).replace("\n", "; "))
    tmp = outs["fit.json"] + ".part"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=2, default=json_default)
    os.replace(tmp, outs["fit.json"])
    report["outputs"] = list(outs.values())
    report["wall_s"] = time.time() - t0
    return report


def _channel_stokes(values, cam):
    """Per-channel Stokes (3, 3, H, W) of (16, H, W) samples, demosaicked as polcam.stokes_from_colour_mosaic."""
    from .. import polcam

    h, w = values.shape[1:]
    raw = np.empty((4 * h, 4 * w))
    k = 0
    for cr, cc, _ in polcam.colour_cells(cam.cfa):
        for dr in range(2):
            for dc in range(2):
                raw[2 * cr + dr::4, 2 * cc + dc::4] = values[k]
                k += 1
    return polcam.stokes_from_colour_mosaic(raw, cam.layout, cam.cfa)[:, :3]


def plot_colour_fit(smp, pred, sel, cam, path, title=""):
    """Observed vs fitted intensity and DoLP per channel, cropped to the fitted periods; errors beside."""
    from .. import stokes_io
    from .colour import CHANNELS
    from .plots import pyplot, scale_from

    plt = pyplot()
    obs_s = _channel_stokes(np.where(sel, smp.values, np.nan), cam)
    fit_s = _channel_stokes(pred, cam)
    rows, cols = np.nonzero(sel)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    fig, axes = plt.subplots(6, 3, figsize=(10, 17))
    for c, ch in enumerate(CHANNELS):
        for q, (name, f) in enumerate((("intensity", lambda s: s[0]), ("DoLP", stokes_io.dolp))):
            o = np.where(sel, f(obs_s[c]), np.nan)[r0:r1, c0:c1]
            p = np.where(sel, f(fit_s[c]), np.nan)[r0:r1, c0:c1]
            s = sel[r0:r1, c0:c1]
            vmax = scale_from(o, s)
            emax = scale_from(p - o, s)
            row = 2 * c + q
            for k, (img, t, kw) in enumerate(((o, f"{ch} observed {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                              (p, f"{ch} fitted {name}", dict(vmin=0, vmax=vmax, cmap="gray")),
                                              (p - o, f"{ch} fitted - observed",
                                               dict(vmin=-emax, vmax=emax, cmap="RdBu_r")))):
                im = axes[row, k].imshow(img, **kw)
                axes[row, k].set_title(t, fontsize=9)
                axes[row, k].axis("off")
                fig.colorbar(im, ax=axes[row, k], fraction=0.046)
    if title:
        fig.suptitle(title, fontsize=8, wrap=True)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def print_colour(report):
    """The stdout summary of a colour fit; returns the exit status (3: stopped before convergence)."""
    import sys

    from .cli import EXIT_NOT_CONVERGED

    status = 0
    for name, m in report["models"].items():
        print(f"{name} (colour, per-channel albedos): chi2/dof {m['chi2_per_dof']:.4f} over {m['n_samples']} raw "
              f"samples of {m['n_pixels']} periods  ({'converged' if m['converged'] else 'NOT converged'}: "
              f"{m['stop_reason']})")
        print(f"  camera noise {m['noise'].get('description', m['noise'])}")
        std, ci = m["std_errors"] or {}, m["ci95"] or {}
        rel = m.get("relative_error") or {}
        for k, v in m["params"].items():
            if isinstance(v, dict):
                for c, x in v.items():
                    line = f"  {k + '[' + c + ']':<8} {x:10.5g}"
                    if k in std:
                        line += f"  +- {std[k][c]:.3g}  95% [{ci[k][c][0]:.5g}, {ci[k][c][1]:.5g}]"
                    if isinstance(rel.get(k), dict) and c in rel[k]:
                        line += f"  (vs metadata {rel[k][c]:+.2%})"
                    print(line)
            else:
                line = f"  {k:<8} {v:10.5g}"
                if k in (m.get("fixed") or {}):
                    line += "  (fixed)"
                elif std.get(k) is not None:
                    line += f"  +- {std[k]:.3g}  95% [{ci[k][0]:.5g}, {ci[k][1]:.5g}]"
                if isinstance(rel.get(k), float):
                    line += f"  (vs metadata {rel[k]:+.2%})"
                print(line)
        if std:
            print("  uncertainty: inverse Fisher information of the raw samples (delta method)")
        for img, c2 in (m.get("chi2_per_sample") or {}).items():
            print(f"  {img}: chi2 per raw sample {c2:.3f}")
        if not m["converged"]:
            print(f"fmbrdf-mi fit: {name}: stopped before convergence ({m['stop_reason']}); the estimates are "
                  f"the last accepted ones and have no standard errors (exit status {EXIT_NOT_CONVERGED})",
                  file=sys.stderr)
            status = EXIT_NOT_CONVERGED
    for img, errs in report.get("relight", {}).items():
        for name, e in errs.items():
            print(f"relighting {img} ({name}): raw-sample RMSE / mean = {e['rel_rmse']:.4f} (R "
                  f"{e['rel_rmse_R']:.4f}, G {e['rel_rmse_G']:.4f}, B {e['rel_rmse_B']:.4f})")
    print(f"wrote {', '.join(report['outputs'])} ({report['wall_s']:.1f} s)")
    return status
