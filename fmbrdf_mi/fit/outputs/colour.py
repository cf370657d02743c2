"""``fmbrdf-mi fit`` on colour polarisation mosaics: :func:`fit_colour_files` (one), :func:`fit_colour_images` (several
of one object), by :func:`fmbrdf_mi.fit.api.colour.fit_colour`; geometry on the grid of 4x4 periods."""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi.fit.api.colour import RECORD_OPTIONS, fit_colour, format_result, predict_samples
from fmbrdf_mi.fit.api.options import arguments as arguments_of
from fmbrdf_mi.fit.api.options import OPTION, check_fit_options, check_input_options, flag, record_keys
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.inputs.colour import COLOUR_KEYS, colour_sidecar, read_colour_input, read_colour_inputs
from fmbrdf_mi.fit.inputs.parse import parse_bounds, parse_fixed
from fmbrdf_mi.fit.outputs import record
from fmbrdf_mi.fit.inputs.manifest import image_names
from fmbrdf_mi.fit.outputs.job import FitJob, joint_outputs
from fmbrdf_mi.fit.outputs.plots import plot_colour_fit
from fmbrdf_mi.fit.outputs.single import relative_errors, write_maps
from fmbrdf_mi.sensor.mosaic import COLOURS

#: The keywords of :func:`~fmbrdf_mi.fit.api.colour.fit_colour` the command sets.
FIT_KEYS = tuple(k for k in RECORD_OPTIONS if k != "model")

#: Options of a joint fit that a colour joint fit ignores.
IGNORED = ("tol", "time_limit", "power_start")

#: The values a colour fit takes of the options it limits (the likelihood; albedos shared or per pixel).
TAKES = {"loss": ("auto", "likelihood"), "albedo": ("shared", "per-pixel")}


def model_entry(res, truth, fixed):
    """fit.json's ``models[model]`` of a colour fit result, with its ``relative_error`` to ``truth`` if any."""
    unc = res.uncertainty or {}
    entry = {k: res[k] for k in ("model", "params", "std_errors", "chi2", "chi2_per_dof", "n_pixels", "n_samples",
                                 "noise", "evaluations", "time_s", "channels", "converged", "stop_reason")}
    entry.update(ci95=None if res.std_errors is None else unc.get("ci95"),
                 uncertainty={k: v for k, v in unc.items() if k not in ("std_errors", "ci95")},
                 weakly_identified=res.weakly_identified, fixed=fixed or {})
    entry.update({} if res.albedo is None else {"albedo": res.albedo})
    if truth:
        entry["relative_error"] = relative_errors(res.params, truth, res.channels)
    return entry


def sample_rmse(smp, pred, sel):
    """RMSE / mean of the raw samples in ``sel`` with a prediction (all, and per colour channel)."""
    sel = sel & np.all(np.isfinite(pred), axis=0)
    o, p = smp.values[:, sel], pred[:, sel]
    rel = lambda m: float(np.sqrt(np.mean((p[m] - o[m]) ** 2)) / np.mean(o[m]))   # noqa: E731
    return {"rel_rmse": rel(slice(None)), "n_periods": int(sel.sum()),
            **{f"rel_rmse_{name}": rel(np.asarray(smp.channel) == c) for c, name in enumerate(COLOURS)}}


def fit_colour_files(inputs, out, *, force=False, progress=True, command=None, **options):
    """Fit one colour mosaic; returns fit.json's dict.  ``options``: the colour record's (defaults if not given)."""
    a = arguments_of("colour", dict(options, inputs=inputs), "fit_colour_files()")
    return ColourFit(None, out, a, force=force, progress=progress, command=command).run()


def fit_colour_images(specs, out, *, force=False, progress=True, command=None, reproduce=None, **options):
    """Joint colour fit of the non-held-out images of ``specs``; returns fit.json's dict.  ``options``: the joint
    record's (``max_pixels`` default None: every period) less those the colour fit refuses or ignores;
    ``reproduce``: as :func:`~fmbrdf_mi.fit.outputs.joint.fit_images`'."""
    a = arguments_of("joint", {"max_pixels": None, **options}, "fit_colour_images()")
    refused = [f"{k} {a[k]!r} ({flag(k)}; expected {' or '.join(map(repr, TAKES[k]))})" for k in TAKES
               if a[k] not in TAKES[k]] + [f"{k} ({flag(k)})" for k in record_keys("joint")
                                           if k not in record_keys("colour") + IGNORED + tuple(TAKES)
                                           and a[k] != OPTION[k].default]
    if refused:
        raise InputError(f"colour joint fit: {', '.join(refused)} not supported (the colour fit is the likelihood "
                         "of the raw samples)")
    return ColourFit(specs, out, a, force=force, progress=progress, command=command, reproduce=reproduce).run()


class ColourFit(FitJob):
    """A colour fit of one mosaic (``specs`` None) or of the images ``specs``; ``a``: the entry function's arguments."""

    def __init__(self, specs, out, a, *, reproduce=None, **kw):
        super().__init__(out, **kw)
        self.specs, self.a, self.model = specs, a, a["model"]
        self.reproduce = reproduce or (lambda obs: record.joint_block("lights", specs, self.names, obs, a,
                                                                      self.command))
        self.kw = {k: a[k] for k in FIT_KEYS}

    def check(self):
        if self.specs is not None:
            return get_model(self.model)
        inputs = self.a["inputs"]
        self.path = os.fspath(inputs[0] if isinstance(inputs, (list, tuple)) else inputs)
        if colour_sidecar(self.path) is None:
            raise InputError(f"{self.path}: no colour capture sidecar ({os.path.splitext(self.path)[0]}.json "
                             "with \"cfa\")")
        check_input_options(**self.a)
        check_fit_options(**self.a)
        self.kw.update(bounds=parse_bounds(self.a["bounds"]), fixed=parse_fixed(self.a["fixed"]))

    def files(self):
        one, specs = self.specs is None, self.specs or ()
        self.names, self.holdout = [None] if one else image_names(specs), [False] if one else [s.holdout for s in specs]
        return joint_outputs(self.out, self.names, self.holdout, self.kw["albedo"], colour=True)

    def read(self):
        a = self.a
        if self.specs is not None:
            self.inputs = read_colour_inputs(self.specs, a["erode"])
            return
        c = read_colour_input(self.path, light=a["light"], erode=a["erode"], **{k: a[k] for k in COLOUR_KEYS})
        self.inputs = [c]
        if self.progress:
            print(f"colour fit of {self.path}: {c.obs.shape[1]}x{c.obs.shape[0]} periods, "
                  f"{int((c.obs.mask & c.samples.usable).sum())} usable in the mask (eroded by {a['erode']}), "
                  f"cfa {''.join(x for r in c.camera.cfa for x in r)}", flush=True)

    def fit(self):
        fit_in = [c for c, h in zip(self.inputs, self.holdout) if not h]
        if self.progress and self.specs is not None:
            print(f"colour joint fit: {len(fit_in)} image(s) fitted, {sum(self.holdout)} held out; "
                  + ", ".join(f"{n}: {int((c.obs.mask & c.samples.usable).sum())} periods"
                              for n, c, h in zip(self.names, self.inputs, self.holdout) if not h), flush=True)
        one = self.specs is None
        obs, smp = [c.obs for c in fit_in], [c.samples for c in fit_in]
        kw = dict(self.kw, max_pixels=self.kw["max_pixels"] or None, starts=int(self.kw["starts"]))
        self.res = fit_colour(obs[0] if one else obs, smp[0] if one else smp, fit_in[0].noise, model=self.model,
                              progress=(lambda s: print(s, flush=True)) if self.progress else None, **kw)

    def report(self):
        inputs, res = self.inputs, self.res
        truth = next((c.truth for c in inputs if c.truth), None)
        entry = model_entry(res, truth, self.kw["fixed"])
        if self.specs is not None:
            entry["chi2_per_sample"] = dict(zip([n for n, h in zip(self.names, self.holdout) if not h],
                                                res["chi2_per_sample"]))
        obs = [c.obs for c in inputs]
        return {"sensor": "colour", "truth": truth, "models": {self.model: entry}, "relight": {},
                "reproduce": record.one_image_block("colour", self.a, self.command, obs) if self.specs is None
                else self.reproduce(obs)}

    def write(self, report):
        out, model, res = self.out, self.model, self.res
        title = f"{model}: " + format_result(res).replace("\n", "; ")
        for n, c, h in zip(self.names, self.inputs, self.holdout):
            pred = predict_samples(c.obs, c.samples, res)
            sel = c.obs.mask & c.samples.usable
            if h:
                err = report["relight"][n] = {model: sample_rmse(c.samples, pred, sel)}
                path, head = os.path.join(out, f"relight_{n}.png"), (
                    f"{n}: relit with the joint estimates, raw-sample RMSE/mean {err[model]['rel_rmse']:.4f}")
            else:
                path = os.path.join(out, "colour_fit.png" if n is None else f"colour_fit_{n}.png")
                head = title if n is None else f"{n}: {title}"
            plot_colour_fit(c.samples, pred, sel, c.camera, path, title=head)
            self.wrote(path)
        write_maps(res, model, out, report, wrote=self.wrote)
