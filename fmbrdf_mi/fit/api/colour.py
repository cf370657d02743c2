"""Fits to colour polarisation mosaics (IMX250MYR type), :func:`fit_colour`: one material's shape (paper:
s_s + s_b), albedos per colour channel.  Raw sample k (colour c_k, polariser phi_k) of pixel i is

    mu_ik = 1/2 (1, cos 2 phi_k, sin 2 phi_k) . (a_s[c_k] S_ik + a_b[c_k] B_ik)

with S, B the unit-albedo Stokes vectors (:class:`~fmbrdf_mi.fit.evaluate.albedos.GroupAlbedos`)."""
from __future__ import annotations

import dataclasses

import numpy as np

from fmbrdf_mi.fit.api.fitting import fit
from fmbrdf_mi.fit.api.options import FIT_NAMES, fit_options, record_keys
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.problem.data import prepare
from fmbrdf_mi.sensor.mosaic import COLOURS
from fmbrdf_mi.sensor.noise import NoiseModel


#: The colour record's fit options that :func:`fit_colour` takes (the caller erodes the mask).
RECORD_OPTIONS = tuple(k for k in record_keys("colour") if k in FIT_NAMES and k != "erode")

#: The options of :func:`fit_colour`.
COLOUR_OPTIONS = RECORD_OPTIONS + ("rounds", "area_points")

#: Where :func:`fit_colour`'s defaults differ from the schema's: every usable period, two reweighting rounds.
DEFAULTS = {"max_pixels": None, "rounds": 2}


def fit_colour(obs, samples, noise=None, *, progress=None, **options):
    """:func:`~fmbrdf_mi.fit.api.fitting.fit` of a colour mosaic's ``samples``
    (:func:`~fmbrdf_mi.sensor.samples.colour_samples`), ``obs`` on the 4x4-period grid; lists of both: a joint
    fit of one object and camera.  ``noise``: a :class:`~fmbrdf_mi.sensor.noise.NoiseModel` (None: estimated
    from the residuals); ``options``: ``COLOUR_OPTIONS``.  Returns a :class:`~fmbrdf_mi.fit.result.FitResult`
    whose ``params``, ``std_errors`` (None unless converged) and ``uncertainty["ci95"]`` are nested per channel."""
    unknown = [k for k in options if k not in COLOUR_OPTIONS]
    if unknown:
        raise InputError(f"fit_colour(): unknown option(s) {', '.join(unknown)} (valid: {', '.join(COLOUR_OPTIONS)})")
    joint = isinstance(obs, (list, tuple))
    obs_l, smp_l = (list(obs), list(samples)) if joint else ([obs], [samples])
    if len(obs_l) != len(smp_l) or not obs_l:
        raise InputError(f"colour fit: {len(obs_l)} geometries for {len(smp_l)} mosaics; give one per mosaic")
    noise = noise if noise is not None else NoiseModel(step=1.0)
    obs_l = [dataclasses.replace(o, samples=smp, noise=noise) for o, smp in zip(obs_l, smp_l)]
    opts = fit_options({**DEFAULTS, **options}, loss="likelihood", erode=0)
    data = prepare(obs_l, opts, "likelihood", single=not joint)
    res = fit(obs_l[0], opts, progress=progress or False, data=data)
    m = get_model(opts.model)
    nest = Parameters(m, channels=data.objective.layout.labels).nest
    res.params, res.std_errors = nest(res.params), None
    if res.converged:
        res.std_errors = {**dict.fromkeys(m.shape_names), **nest(res.uncertainty["std_errors"])}
        res.uncertainty["ci95"] = nest(res.uncertainty["ci95"])
    r = res.details.pop("residuals").reshape(len(data.pixels), -1)
    per_chi2 = [float(np.sum(r[a:b] ** 2) / max(r[a:b].size, 1)) for a, b in data.slices]
    res.channels = list(COLOURS)
    res.pixels = data.image_pixels if joint else data.image_pixels[0]
    res.details.update({"chi2": res.loss, "chi2_per_dof": res.loss / max(r.size - res.details.pop("n_free"), 1),
                        "n_samples": int(r.size), "evaluations": res.timings["evaluations"],
                        "time_s": res.timings["total"], "chi2_per_sample": per_chi2 if joint else per_chi2[0]})
    if res.std_errors is not None and progress:
        progress("[colour] " + format_result(res))
    return res


def predict_samples(obs, samples, res):
    """The fitted model's 16 samples (16, H, W) per period of a mosaic of the fitted object (image units, each
    at the fit's pixel-area quadrature; NaN outside mask & usable and, for albedo maps, off the fitted periods)."""
    m, out = get_model(res["model"]), np.full(samples.values.shape, np.nan)
    idx = np.flatnonzero((obs.mask & samples.usable).ravel())
    if len(idx) == 0:
        return out
    n, v, w = obs.sample_geometry(idx, footprint=samples.footprint(res.fitted.data.area_points))
    p = PixelEvaluator(m, n, v, obs.light_dir, obs.irradiance,
                       weights=None if len(w) == 1 else w).parts(res["internal"]["shape"], ())
    A, n = samples.analyser(), len(idx)
    unit = [np.einsum("kc,cik->ik", A, s.reshape(3, n, -1)) for s in (p.surface, p.body)]
    if res.maps is not None:
        if np.shape(res.maps["k_s"])[1:] != obs.mask.shape:
            raise InputError(f"per-pixel albedos: the maps are {np.shape(res.maps['k_s'])[2]}x"
                             f"{np.shape(res.maps['k_s'])[1]} periods, this mosaic {obs.mask.shape[1]}x"
                             f"{obs.mask.shape[0]}; the maps predict images of the fitted view only")
        a_s, a_b = (np.asarray(res.maps[k], float).reshape(len(COLOURS), -1)[:, idx] / float(m.albedo_factor)
                    for k in ("k_s", "k_b"))
    else:
        a_s, a_b = (np.asarray(res["internal"][k], float)[:, None] for k in ("a_s", "a_b"))
    ch = np.asarray(samples.channel)
    out.reshape(16, -1)[:, idx] = (a_s[ch].T * unit[0] + a_b[ch].T * unit[1]).T
    return out


def format_result(res):
    """One line per parameter: value +- SE (per channel for the albedos)."""
    def one(v, s, head=""):
        return f"{head}{v:.5g}" + ("" if s is None else f" +- {s:.2g}")

    ses = res["std_errors"] or {}
    return "\n".join(f"{k}: " + (", ".join(one(v[c], None if ses.get(k) is None else ses[k][c], f"{c} ") for c in v)
                                  if isinstance(v, dict) else one(v, ses.get(k))) for k, v in res["params"].items())
