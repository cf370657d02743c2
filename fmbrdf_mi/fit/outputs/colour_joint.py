"""Joint fits of several colour polarisation mosaics of one object (``--manifest`` / repeated ``--light``).

The colour counterpart of :func:`fmbrdf_mi.fit.outputs.joint.fit_images`: the
images (each its own light, relative power, geometry; one camera) share
eta, alpha, beta, kappa and the per-channel k_s, r_k, fitted by
:func:`fmbrdf_mi.fit.api.colour.fit_colour` on all their raw samples at once.
Held-out images are predicted from the estimates (relighting check).

Outputs in ``out``: ``fit.json`` (the shared estimate and its standard
errors from the joint Fisher information, per image its light, power,
irradiance and chi^2 per raw sample, relighting errors, the ``reproduce``
block of :func:`fmbrdf_mi.fit.outputs.record.joint_block`, so ``--from`` reruns
it), ``colour_fit_NAME.png`` per fitted image and ``relight_NAME.png`` per
held-out image (observed, predicted and their difference in intensity and
DoLP per channel).  With ``albedo="per-pixel"`` (the images of one view): the albedo maps per period and
colour channel too (k_s.exr, k_b.exr, k_s_se.exr, k_b_se.exr with channels R, G, B; albedo_maps.png), and the
held-out images are relit with them.
"""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi.fit.api.colour import fit_colour, format_result, predict_samples
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.inputs.colour import read_colour_inputs
from fmbrdf_mi.fit.outputs.colour import Colour, model_entry
from fmbrdf_mi.fit.outputs.job import FitJob
from fmbrdf_mi.fit.outputs.plots import plot_colour_fit
from fmbrdf_mi.fit.outputs.single import write_maps
from fmbrdf_mi.fit.outputs.writer import prepare_outputs
from fmbrdf_mi.sensor.mosaic import COLOURS


def sample_rmse(smp, pred, sel, channel):
    """RMSE / mean of the raw samples in ``sel`` (all, and per colour channel): the held-out images' error (over
    the periods with a prediction: a per-pixel albedo fit predicts the periods it fitted)."""

    sel = sel & np.all(np.isfinite(pred), axis=0)
    o, p = smp.values[:, sel], pred[:, sel]
    out = {"rel_rmse": float(np.sqrt(np.mean((p - o) ** 2)) / np.mean(o)), "n_periods": int(sel.sum())}
    for c, name in enumerate(COLOURS):
        m = np.asarray(channel) == c
        out[f"rel_rmse_{name}"] = float(np.sqrt(np.mean((p[m] - o[m]) ** 2)) / np.mean(o[m]))
    return out


def fit_colour_images(specs, out, *, model="fmbrdf", force=False, progress=True, command=None, extra=None,
                      reproduce=None, baselines=False, loss="auto", init=None, fixed=None, bounds=None, starts=2,
                      max_iter=40, max_time=None, max_pixels=None, erode=2, seed=0, tol=None, time_limit=None,
                      free_power=False, power_start=None, intervals="auto", albedo="shared"):
    """Joint colour fit of the non-held-out images of ``specs`` (module docstring); returns fit.json's dict.

    ``specs``: :class:`~fmbrdf_mi.fit.inputs.manifest.ImageSpec` s of colour
    mosaics.  Keywords as :func:`~fmbrdf_mi.fit.outputs.joint.fit_images`'s;
    ``baselines``, ``init`` and losses other than the likelihood are refused
    (the colour fit has none of them), as is ``free_power`` (not yet for colour
    mosaics: give the powers); ``albedo``: ``"shared"`` (per-channel albedos shared
    by the pixels) or ``"per-pixel"`` (maps per period and channel: the images must
    be of one view); ``tol`` and ``time_limit`` do not apply.
    """
    refused = [f for f, on in (("baselines", baselines), ("init", init), ("free_power (--free-power)", free_power),
                               (f"loss {loss}", loss not in ("auto", "likelihood", None)),
                               (f"albedo {albedo!r} (--albedo; expected 'shared' or 'per-pixel')",
                                albedo not in ("shared", "per-pixel"))) if on]
    if refused:
        raise InputError(f"colour joint fit: {', '.join(refused)} not supported (the colour fit is the likelihood "
                         "of the raw samples)")
    return ColourJoint(specs, out, force=force, progress=progress, command=command, extra=extra,
                       reproduce=reproduce, model=model, fixed=fixed, bounds=bounds, starts=starts,
                       max_iter=max_iter, max_time=max_time, max_pixels=max_pixels, erode=erode, seed=seed,
                       intervals=intervals, albedo=albedo).run()


class ColourJoint(FitJob):
    """:func:`fit_colour_images` as a :class:`~fmbrdf_mi.fit.outputs.job.FitJob` (``fit_kw``: fit_colour's options)."""

    def __init__(self, specs, out, *, force, progress, command, extra, reproduce, model, erode, **fit_kw):
        super().__init__(out, force=force, progress=progress, command=command)
        self.specs, self.extra, self.reproduce, self.model, self.erode, self.fit_kw = (
            specs, extra, reproduce, model, erode, fit_kw)

    def check(self):
        get_model(self.model)

    def files(self):
        self.names, self.holdout, files = prepare_outputs(self.specs, self.out, self.force, self.fit_kw["albedo"],
                                                          colour=True)
        return files

    def read(self):
        self.inputs = read_colour_inputs(self.specs, self.erode)

    def fit(self):
        names, holdout, kw = self.names, self.holdout, self.fit_kw
        fit_in = [c for c, h in zip(self.inputs, holdout) if not h]
        say = (lambda s: print(s, flush=True)) if self.progress else None
        if self.progress:
            print(f"colour joint fit: {len(fit_in)} image(s) fitted, {sum(holdout)} held out; "
                  + ", ".join(f"{n}: {int((c.obs.mask & c.samples.usable).sum())} periods"
                              for n, c, h in zip(names, self.inputs, holdout) if not h), flush=True)
        self.res = fit_colour([c.obs for c in fit_in], [c.samples for c in fit_in], fit_in[0].noise,
                              model=self.model, fixed=kw["fixed"], bounds=kw["bounds"],
                              max_pixels=kw["max_pixels"] or None, seed=kw["seed"], progress=say,
                              max_time=kw["max_time"], max_iter=kw["max_iter"], starts=int(kw["starts"]),
                              intervals=kw["intervals"], albedo=kw["albedo"])

    def report(self):
        names, holdout, inputs, res = self.names, self.holdout, self.inputs, self.res
        truth = next((c.truth for c in inputs if c.truth), None)
        entry = model_entry(self.model, res, self.fit_kw["bounds"], self.fit_kw["fixed"], truth)
        entry["chi2_per_sample"] = dict(zip([n for n, h in zip(names, holdout) if not h], res["chi2_per_sample"]))
        report = {"sensor": "colour", "truth": truth,
                  "images": [{"name": n, "input": s.input if isinstance(s.input, (str, list)) else None,
                              "light_dir": c.obs.light_dir.tolist(), "irradiance": c.obs.irradiance,
                              "power": s.power, "holdout": s.holdout} for n, s, c in zip(names, self.specs, inputs)],
                  "models": {self.model: entry}, "relight": {}}
        if self.reproduce is not None:
            report["reproduce"] = self.reproduce([c.obs for c in inputs])
        report.update(self.extra or {})
        return report

    def write(self, report):
        out, model, res = self.out, self.model, self.res
        title = f"{model}: " + format_result(res).replace("\n", "; ")
        for n, c, h in zip(self.names, self.inputs, self.holdout):
            pred = predict_samples(c.obs, c.samples, res)
            sel = c.obs.mask & c.samples.usable
            if h:
                err = sample_rmse(c.samples, pred, sel, c.samples.channel)
                report["relight"][n] = {model: err}
                plot_colour_fit(c.samples, pred, sel, c.camera, os.path.join(out, f"relight_{n}.png"),
                                title=f"{n}: relit with the joint estimates, raw-sample RMSE/mean {err['rel_rmse']:.4f}")
            else:
                plot_colour_fit(c.samples, pred, sel, c.camera, os.path.join(out, f"colour_fit_{n}.png"),
                                title=f"{n}: {title}")
        write_maps(res, model, out, report)

    finish = Colour.finish
