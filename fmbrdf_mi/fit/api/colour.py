"""Fits to colour polarisation mosaics (IMX250MYR type): shared eta, alpha, beta, kappa, per-channel albedos.

    smp = colour_samples(raw, camera)                     # 16 raw samples per 4x4 period
    res = fit_colour(obs, smp, noise)                     # obs: geometry on the period grid
    res.params["k_s"]      # {"R": ..., "G": ..., "B": ...}; res.std_errors likewise

The colour filter changes how much light reaches a pixel, not the geometry
of reflection: FMBRDF's shape parameters (eta, alpha, beta, kappa; paper
eq:fmbrdf) are one material's, while its two albedos k_s and k_b = r_k k_s
are per colour channel.  The model of raw sample k (colour c_k, polariser
phi_k, at its own point in the 4x4 period) is

    mu_ik = 1/2 (1, cos 2 phi_k, sin 2 phi_k) . (a_s[c_k] S_ik + a_b[c_k] B_ik)

with S, B the unit-albedo surface and body Stokes vectors
(:class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts`) and the per-channel
albedo layout :class:`~fmbrdf_mi.fit.evaluate.albedos.ChannelAlbedos`; every
raw sample of every channel is one independent measurement of the mono fit's
likelihood (:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`).

The fit is :func:`~fmbrdf_mi.fit.api.fitting.fit` of the observations
carrying these samples (:func:`~fmbrdf_mi.fit.problem.data.prepare` gives the
objective the per-channel layout); pixel selection, search, solver and
uncertainty are every fit's.  This module adds the colour fit's reporting:
nested per-channel parameters, chi^2 per sample of each image, the predicted
samples.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from fmbrdf_mi.fit.api.fitting import FitOptions, fit
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.albedos import ChannelAlbedos
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.problem.data import RAW_AREA_POINTS, prepare
from fmbrdf_mi.sensor.mosaic import COLOURS
from fmbrdf_mi.sensor.noise import NoiseModel


def fit_colour(obs, samples, noise=None, *, model="fmbrdf", fixed=None, bounds=None, max_pixels=None, seed=0,
               irls_rounds=4, progress=None, max_time=None, max_iter=40, starts=2, area_points=None,
               intervals="auto", albedo="shared"):
    """Fit one material with per-channel albedos to a colour mosaic's samples (module docstring).

    ``obs``: an :class:`~fmbrdf_mi.fit.inputs.observations.Observation` whose grid is
    the mosaic's 4x4 periods (its ``stokes`` is only used for its shape),
    ``samples``: :func:`colour_samples`.  Several images of one object (a
    joint fit: each its own light, irradiance, view and geometry; one camera):
    lists of both, one entry per mosaic; they share every parameter, and
    ``max_pixels`` is split evenly between them.  ``noise``: a
    :class:`~fmbrdf_mi.sensor.noise.NoiseModel` (None: unknown, estimated from
    the residuals).  ``max_time``: hard wall-clock limit in seconds; a fit it
    stops returns the last accepted estimate with ``converged`` False and no
    standard errors (as does one that runs out of ``max_iter`` LM iterations).
    ``starts``: Levenberg-Marquardt from this many distinct coarse-search
    points (as the one-channel fit's ``--starts``); the best end wins.
    ``irls_rounds``: at most this many reweighting rounds (at least 3).
    ``area_points``: each raw sample is the mean of the model over this
    many points squared of its pixel (as a sensor pixel integrates; 1: its
    centre), as in the one-channel likelihood; None (the default): 2, checked and raised where
    the 2 x 2 quadrature would bias a shape parameter (:func:`~fmbrdf_mi.fit.api.checks.check_footprint`,
    fit.json's ``uncertainty.quadrature``).  ``intervals``: as
    :class:`~fmbrdf_mi.fit.api.fitting.FitOptions`' (profile-likelihood ends where the Fisher ones fail).
    ``albedo``: ``"shared"`` (one k_s, r_k per channel for the whole object) or ``"per-pixel"``: albedo
    maps, one k_s and k_b per period and colour channel (a textured object: the per-pixel layout,
    :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`, with one group per period and channel; the
    albedos eliminated by variable projection, their standard errors and the shape's incidental-parameter
    sandwich as in a mono per-pixel fit).  Several mosaics must then be of one view.

    The caller erodes the mask; grazing and polar periods are left out.  Returns a :class:`~fmbrdf_mi.fit.result.FitResult`: params, std_errors
    (per-channel entries as {"R", "G", "B"} dicts; None when not converged),
    loss (chi^2), n_pixels, noise, converged, stop_reason, pixels (the fitted
    flat period indices; a list per image for lists), channels, and in
    ``details`` (read as ``res["key"]``): chi2, chi2_per_dof, n_samples,
    evaluations, time_s, chi2_per_sample (chi^2 / samples, per image for
    lists), internal (shape and unit albedos for :func:`predict_samples`).  With ``albedo="per-pixel"``
    ``params`` and ``std_errors`` hold the shape parameters only; ``maps`` the albedo maps (each
    (3, H, W): R, G, B on the period grid, NaN where no period was fitted) and ``albedo`` their summary
    (fit.json's ``albedo`` block, with ``per_channel``), as :func:`~fmbrdf_mi.fit.api.fitting.fit`'s.
    """
    t0 = time.time()
    joint = isinstance(obs, (list, tuple))
    obs_l, smp_l = (list(obs), list(samples)) if joint else ([obs], [samples])
    if len(obs_l) != len(smp_l) or not obs_l:
        raise InputError(f"colour fit: {len(obs_l)} geometries for {len(smp_l)} mosaics; give one per mosaic")
    for k, (o, smp) in enumerate(zip(obs_l, smp_l)):
        tag = f"colour fit, image {k}" if joint else "colour fit"
        if smp.values.shape[1:] != o.mask.shape:
            raise InputError(f"{tag}: the mosaic has {smp.values.shape[2]}x{smp.values.shape[1]} periods, "
                             f"the geometry {o.mask.shape[1]}x{o.mask.shape[0]} pixels; they must agree")
        if k and (smp.angles != smp_l[0].angles or not np.array_equal(smp.channel, smp_l[0].channel)):
            raise InputError(f"{tag}: its polariser layout or colour filter differs from image 0's; a joint fit "
                             "takes one camera")
    noise = noise if noise is not None else NoiseModel(step=1.0)
    obs_l = [dataclasses.replace(o, samples=smp, noise=noise) for o, smp in zip(obs_l, smp_l)]
    opts = FitOptions(model=model, loss="likelihood", fixed=fixed, bounds=bounds, max_pixels=max_pixels, seed=seed,
                      rounds=max(1, int(irls_rounds) - 2), max_time=max_time, max_iter=max_iter, starts=starts,
                      area_points=area_points, erode=0, intervals=intervals, albedo=albedo)
    data = prepare(obs_l, opts, "likelihood", single=not joint)
    res = fit(obs_l[0], opts, progress=progress or False, data=data)
    layout, m = data.objective.layout, get_model(model)
    nest = Parameters(m, channels=layout.labels).nest
    res.params = nest(res.params)
    res.std_errors = None
    if res.converged:
        res.std_errors = {n: None for n in m.shape_names}
        res.std_errors.update(nest(res.uncertainty["std_errors"]))
        res.uncertainty["ci95"] = nest(res.uncertainty["ci95"])
    r = res.details.pop("residuals").reshape(len(data.pixels), -1)
    per_chi2 = [float(np.sum(r[a:b] ** 2) / max(r[a:b].size, 1)) for a, b in data.slices]
    res.channels = list(COLOURS)
    res.pixels = data.image_pixels if joint else data.image_pixels[0]
    res.options = {"model": model, "fixed": fixed, "bounds": bounds, "max_pixels": max_pixels, "seed": seed,
                   "irls_rounds": irls_rounds, "max_time": max_time, "max_iter": max_iter, "starts": starts,
                   "area_points": None if area_points is None else int(area_points), "intervals": intervals,
                   "albedo": albedo}
    res.details.update({"chi2": res.loss, "chi2_per_dof": res.loss / max(r.size - res.details.pop("n_free"), 1),
                        "n_samples": int(r.size), "evaluations": res.timings["evaluations"],
                        "time_s": time.time() - t0, "chi2_per_sample": per_chi2 if joint else per_chi2[0]})
    if res.std_errors is not None and progress:
        progress("[colour] " + format_result(res))
    return res


def used_area_points(res):
    """m of the m x m points per raw pixel a colour fit ``res`` modelled its samples with: the refined
    quadrature's (fit.json ``uncertainty.quadrature``), else the one asked for, else :data:`RAW_AREA_POINTS`."""
    q = (res.uncertainty or {}).get("quadrature") or {}
    m = q.get("area_points", (res.options or {}).get("area_points"))
    return int(RAW_AREA_POINTS if m is None else m)


def predict_samples(obs, samples, res):
    """The fitted model's 16 samples (16, H, W) per period (image units, NaN outside mask & usable, and for
    a per-pixel albedo fit where its maps have no value: periods it did not fit)."""

    m = get_model(res["model"])
    idx = np.flatnonzero((obs.mask & samples.usable).ravel())
    out = np.full(samples.values.shape, np.nan)
    if len(idx) == 0:
        return out
    n, v, w = obs.sample_geometry(idx, footprint=samples.footprint(used_area_points(res)))
    p = PixelEvaluator(m, n, v, obs.light_dir, obs.irradiance,
                       weights=None if len(w) == 1 else w).parts(res["internal"]["shape"], ())
    A, n = samples.analyser(), len(idx)
    unit = [np.einsum("kc,cik->ik", A, s.reshape(3, n, -1)) for s in (p.surface, p.body)]
    if getattr(res, "maps", None) is not None:
        if np.shape(res.maps["k_s"])[1:] != obs.mask.shape:
            raise InputError(f"per-pixel albedos: the maps are {np.shape(res.maps['k_s'])[2]}x"
                             f"{np.shape(res.maps['k_s'])[1]} periods, this mosaic {obs.mask.shape[1]}x"
                             f"{obs.mask.shape[0]}; the maps predict images of the fitted view only")
        f, ch = float(m.albedo_factor), np.asarray(samples.channel)
        a_s, a_b = (np.asarray(res.maps[k], float).reshape(len(COLOURS), -1)[:, idx] / f for k in ("k_s", "k_b"))
        mu = a_s[ch].T * unit[0] + a_b[ch].T * unit[1]
    else:
        mu = ChannelAlbedos(samples.channel).mu(*unit, res["internal"]["a_s"], res["internal"]["a_b"])
    flat = out.reshape(16, -1)
    flat[:, idx] = mu.T
    return out


def format_result(res):
    """One line per parameter: value +- SE (per channel for the albedos)."""
    lines = []
    for k, v in res["params"].items():
        s = (res["std_errors"] or {}).get(k)
        if isinstance(v, dict):
            lines.append(f"{k}: " + ", ".join(f"{c} {v[c]:.5g}" + ("" if s is None else f" +- {s[c]:.2g}")
                                              for c in v))
        else:
            lines.append(f"{k}: {v:.5g}" + ("" if s is None else f" +- {s:.2g}"))
    return "\n".join(lines)
