"""``fmbrdf-mi fit RAW`` on a colour polarisation mosaic (a capture sidecar with ``"cfa"``).

:func:`fit_colour_files` reads the mosaic and its sidecar, builds the geometry
on the grid of 4x4 periods (the mono path's 2x2 super-pixels, one level
coarser), fits shared eta, alpha, beta, kappa with per-channel k_s, r_k by
:func:`fmbrdf_mi.fit.api.colour.fit_colour` and writes ``fit.json`` and
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
import os

from fmbrdf_mi.fit.api.colour import fit_colour, format_result, predict_samples
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.inputs.colour import colour_sidecar, read_colour_input
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed
from fmbrdf_mi.fit.outputs import record
from fmbrdf_mi.fit.outputs.plots import plot_colour_fit
from fmbrdf_mi.fit.outputs.writer import prepare, write_json

OUTPUTS = ("fit.json", "colour_fit.png")


def is_colour_record(path):
    """Whether ``path`` (a fit.json with a ``reproduce`` block) records a colour fit (``--from`` reruns it)."""

    record.load(path)      # refuses files that are not fit.json records, in one line
    with open(path) as f:
        return json.load(f).get("sensor") == "colour"


def model_entry(model, res, bounds, fixed, truth):
    """fit.json's ``models[model]`` of a :func:`~fmbrdf_mi.fit.api.colour.fit_colour` result (intervals, errors)."""
    std = res["std_errors"]
    entry = {k: res[k] for k in ("model", "params", "std_errors", "chi2", "chi2_per_dof", "n_pixels", "n_samples",
                                 "noise", "evaluations", "time_s", "channels", "converged", "stop_reason")}
    unc = res.uncertainty or {}
    entry["ci95"] = None if std is None else unc.get("ci95")
    entry["uncertainty"] = {k: v for k, v in unc.items() if k not in ("std_errors", "ci95")}
    entry["weakly_identified"] = res.weakly_identified
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


    t0 = time.time()
    arguments = {k: v for k, v in locals().items() if k in record.ARGUMENTS}
    path = inputs[0] if isinstance(inputs, (list, tuple)) else inputs
    path = os.fspath(path)
    if colour_sidecar(path) is None:
        raise InputError(f"{path}: no colour capture sidecar ({os.path.splitext(path)[0]}.json with \"cfa\")")
    get_model(model)
    bounds, fixed = parse_bounds(bounds), parse_fixed(fixed)
    outs = {n: os.path.join(out, n) for n in OUTPUTS}
    prepare(out, outs.values(), force)
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
    write_json(outs["fit.json"], report)
    report["outputs"] = list(outs.values())
    report["wall_s"] = time.time() - t0
    return report
