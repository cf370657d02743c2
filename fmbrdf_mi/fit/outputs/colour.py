"""``fmbrdf-mi fit RAW`` on a colour polarisation mosaic (a capture sidecar with ``"cfa"``).

:func:`fit_colour_files` reads the mosaic and its sidecar, builds the geometry
on the grid of 4x4 periods (the mono path's 2x2 super-pixels, one level
coarser), fits shared eta, alpha, beta, kappa with per-channel k_s, r_k by
:func:`fmbrdf_mi.fit.api.colour.fit_colour` and writes ``fit.json`` and
``colour_fit.png`` (with ``albedo="per-pixel"``: the albedo maps per period and
colour channel too, k_s.exr, k_b.exr, k_s_se.exr, k_b_se.exr with channels
R, G, B, and albedo_maps.png); :func:`print_colour` is the stdout summary.

Geometry: ``--sphere cx,cy,r`` (period units: pixel centres at +0.5 periods)
or ``--sphere auto --mask M``, or ``--normals N --mask M``; maps at the raw
mosaic's resolution are pooled over each 4x4 period (mean normal, mask = all
16 pixels), maps at the period resolution are taken as they are.  Without
either, a sidecar written by ``fmbrdf-mi render --raw --sensor colour``
(built-in sphere) gives the scene's own sphere, light and irradiance.
"""
from __future__ import annotations

import os
import time

from fmbrdf_mi.fit.api.colour import fit_colour, format_result, predict_samples
from fmbrdf_mi.fit.api.options import arguments as arguments_of
from fmbrdf_mi.fit.api.options import check_fit_options, check_input_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.colour import colour_sidecar, read_colour_input
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed
from fmbrdf_mi.fit.outputs import record
from fmbrdf_mi.fit.outputs.job import FitJob
from fmbrdf_mi.fit.outputs.plots import plot_colour_fit
from fmbrdf_mi.fit.outputs.single import write_maps
from fmbrdf_mi.fit.outputs.writer import MAP_OUTPUTS

OUTPUTS = ("fit.json", "colour_fit.png")


def output_names(albedo="shared"):
    """The files a colour fit writes (``albedo="per-pixel"``: the maps too)."""
    return OUTPUTS + (MAP_OUTPUTS if albedo == "per-pixel" else ())


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
    if getattr(res, "albedo", None) is not None:      # per-pixel albedos: the maps' summary (per channel)
        entry["albedo"] = res.albedo
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


def fit_colour_files(inputs, out, *, force=False, progress=True, command=None, **options):
    """Fit a colour polarisation mosaic (module docstring); write ``out``/fit.json and colour_fit.png.

    Returns the dict written to fit.json (``models[model]``: params with
    per-channel k_s and r_k, std_errors, ci95, converged, stop_reason ...).
    ``albedo="per-pixel"``: k_s and k_b per period and channel (maps; ``models[model]["albedo"]``
    their summary), the shape parameters shared.  ``options``: the colour record's options of
    :data:`fmbrdf_mi.fit.api.options.OPTIONS` (those not given take their defaults, others are refused).
    """
    arguments = arguments_of("colour", dict(options, inputs=inputs), "fit_colour_files()")
    return Colour(arguments, out, force=force, progress=progress, command=command).run()


class Colour(FitJob):
    """:func:`fit_colour_files` as a :class:`~fmbrdf_mi.fit.outputs.job.FitJob` (``a``: its arguments by name)."""

    def __init__(self, arguments, out, **kw):
        super().__init__(out, **kw)
        self.a = dict(arguments)
        inputs = self.a["inputs"]
        self.path = os.fspath(inputs[0] if isinstance(inputs, (list, tuple)) else inputs)

    def check(self):
        if colour_sidecar(self.path) is None:
            raise InputError(f"{self.path}: no colour capture sidecar ({os.path.splitext(self.path)[0]}.json "
                             "with \"cfa\")")
        check_input_options(**self.a)
        check_fit_options(**self.a)
        self.bounds, self.fixed = parse_bounds(self.a["bounds"]), parse_fixed(self.a["fixed"])

    def files(self):
        self.outs = {n: os.path.join(self.out, n) for n in output_names(self.a["albedo"])}
        return list(self.outs.values())

    def read(self):
        a = self.a
        self.ci = ci = read_colour_input(
            self.path, normals=a["normals"], mask=a["mask"], view=a["view"], sphere=a["sphere"], camera=a["camera"],
            fov=a["fov"], light=a["light"], irradiance=a["irradiance"], black_level=a["black_level"],
            white_level=a["white_level"], conversion_gain=a["conversion_gain"], read_noise=a["read_noise"],
            erode=a["erode"])
        if self.progress:
            obs, smp = ci.obs, ci.samples
            print(f"colour fit of {self.path}: {obs.shape[1]}x{obs.shape[0]} periods, "
                  f"{int((obs.mask & smp.usable).sum())} usable in the mask (eroded by {a['erode']}), "
                  f"cfa {''.join(c for r in ci.camera.cfa for c in r)}", flush=True)

    def fit(self):
        a, ci = self.a, self.ci
        say = (lambda s: print(s, flush=True)) if self.progress else None
        self.res = fit_colour(ci.obs, ci.samples, ci.noise, model=a["model"], fixed=self.fixed, bounds=self.bounds,
                              max_pixels=a["max_pixels"] or None, seed=a["seed"], progress=say,
                              max_time=a["max_time"], max_iter=a["max_iter"], starts=int(a["starts"]),
                              intervals=a["intervals"], albedo=a["albedo"])

    def report(self):
        obs, model = self.ci.obs, self.a["model"]
        return {"inputs": self.path, "sensor": "colour", "truth": self.ci.truth,
                "reproduce": record.reproduce_block(self.a, self.command, obs.meta),
                "models": {model: model_entry(model, self.res, self.bounds, self.fixed, self.ci.truth)}}

    def write(self, report):
        ci, res = self.ci, self.res
        pred = predict_samples(ci.obs, ci.samples, res)
        plot_colour_fit(ci.samples, pred, ci.obs.mask & ci.samples.usable, ci.camera, self.outs["colour_fit.png"],
                        title=f"{self.a['model']}: " + format_result(res).replace("\n", "; "))
        write_maps(res, self.a["model"], self.out, report)

    def finish(self, report):
        """The report and what :func:`~fmbrdf_mi.fit.outputs.summary.print_colour` prints besides: the files
        written and the run's wall time."""
        report["outputs"], report["wall_s"] = self.paths, time.time() - self.t0
        return report
