"""``fmbrdf-mi fit`` on one image as a function: :func:`fit_files` reads, fits and writes."""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from fmbrdf_mi import scene as S
from fmbrdf_mi import stokes_io
from fmbrdf_mi.fit.api.find_materials import find_materials, parse_auto
from fmbrdf_mi.fit.api.fitting import fit, usable_pixels
from fmbrdf_mi.fit.api.options import arguments as arguments_of
from fmbrdf_mi.fit.api.options import (check_fit_options, check_input_options, check_resolved_loss,
                                        fit_options, flag)
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.evaluate.materials import check_labels
from fmbrdf_mi.fit.evaluate.models import BASELINES
from fmbrdf_mi.fit.evaluate.pixel_model import set_variant
from fmbrdf_mi.fit.evaluate.predict import predict_image, relight_error
from fmbrdf_mi.fit.inputs.files import build_observation
from fmbrdf_mi.fit.inputs.labels import read_labels, write_labels
from fmbrdf_mi.fit.inputs.options import IMAGE_KEYS
from fmbrdf_mi.fit.outputs import plots, record
from fmbrdf_mi.fit.outputs.job import FitJob
from fmbrdf_mi.fit.outputs.job import MAP_OUTPUTS, MATERIAL_OUTPUTS
from fmbrdf_mi.fit.problem.data import check_footprint, resolve_loss
from fmbrdf_mi.fit.problem.free_power import fitted_observation, power_text

OUTPUTS = ("fit.json", "profiles.png", "images.png", "history.png", "fitted_stokes.exr")


def output_files(out, relight, albedo="shared", materials=None):
    """The files a fit of one image writes, by name; ``materials="auto:M"`` writes the labels it found too
    (labels.png: 8-bit, 255 not labelled, so that ``--materials labels.png`` reruns with them)."""
    names = OUTPUTS + (("relight.png",) if relight else ()) + (MAP_OUTPUTS if albedo in PER_PIXEL_LAYOUTS else ()) \
        + (MATERIAL_OUTPUTS if materials is not None else ()) + (("labels.png",) if parse_auto(materials) else ())
    return {n: os.path.join(out, n) for n in names}


def fit_files(inputs, out, *, force=False, progress=True, command=None, **options):
    """Fit ``model`` (with ``baselines``, the baselines too) to one polarimetric image; writes the outputs to ``out``.

    ``inputs``: a Stokes EXR (one from ``fmbrdf-mi render`` brings geometry, light and true parameters), a raw mosaic
    (.npy, 16-bit .png, .tif), a (4, H, W) .npy or four angle images (0, 45, 90, 135 degrees).  ``options``: the
    single-image options of :data:`fmbrdf_mi.fit.api.options.OPTIONS`.  Returns fit.json's dict plus ``outputs``
    (the files written) and ``wall_s``."""
    arguments = arguments_of("single", dict(options, inputs=inputs), "fit_files()")
    return SingleImage(arguments, out, force=force, progress=progress, command=command).run()


class ImageFits(FitJob):
    """What single-image and joint fits share: the models fitted, fit.json's dict, each image's figures and the
    whole fit's.  Subclasses set ``model``, ``opts``, ``labels``, ``results``, the images ``obs`` (held-out ones
    too) with their ``holdout`` flags and ``names`` in the file names (a single image's: None) and ``reproduce``
    (the images -> fit.json's ``reproduce`` block)."""

    def fit_models(self, baselines, solve):
        """``results``: ``solve(name, options)`` for ``model`` and each baseline (:func:`baseline_options`)."""
        names = [self.model] + [m for m in baselines if m != self.model]
        self.results = {n: solve(n, self.opts if n == self.model else baseline_options(self.opts, n)) for n in names}

    def report(self):
        truth = next((o.meta.get("truth") for o in self.obs if o.meta.get("truth")), None)
        return {"sensor": "mono", "truth": truth, "models": model_entries(self.results, self.model, truth),
                "relight": {}, "reproduce": self.reproduce(self.obs)}

    def write(self, report):
        """Each image's figures (:meth:`write_image`; ``fitted``: the first fitted image's prediction), history.png,
        and ``model``'s albedo maps (:func:`write_maps`) and materials.png when it has them."""
        results, model, out = self.results, self.model, self.out
        main = results[model]
        per_image = main.pixels if isinstance(main.pixels, list) else [main.pixels]
        pixels, self.fitted = iter(per_image), None
        for n, o, h, rec in zip(self.names, self.obs, self.holdout, report["reproduce"]["images"]):
            if h:
                report["relight"][rec["name"]] = self.write_image(o, name=n, holdout=True)
                continue
            pred = self.write_image(o, name=n, pixels=next(pixels), im=None if n is None else {
                m: next(x for x in r.images if x["name"] == n) for m, r in results.items()})
            self.fitted = pred if self.fitted is None else self.fitted
        plots.plot_loss_history({n: r.history for n, r in results.items()}, os.path.join(out, "history.png"))
        self.wrote("history.png")
        write_maps(main, model, out, report, wrote=self.wrote)
        if main.materials is not None:
            plots.plot_materials(check_labels(self.labels, self.obs[0].shape), per_image[0], main.materials,
                                 os.path.join(out, "materials.png"),
                                 title=f"{model}: {main.materials['count']} material(s) (faint: labelled, not fitted)")
            self.wrote("materials.png")

    def write_image(self, o, name=None, pixels=None, holdout=False, im=None):
        """The figures of image ``o`` (``name``: a joint fit's): a ``holdout``'s relight.png, returning each fit's
        errors, else profiles.png and images.png on ``pixels`` (``im``: each fit's ``images`` entry), returning
        ``model``'s prediction."""
        results, model, labels, out = self.results, self.model, self.labels, self.out
        main = results[model]
        if holdout:
            errs, relit = {}, None
            for n, res in results.items():
                e = relight_error(n, res.params, o, erode=self.opts.erode, maps=res.maps,
                                  labels=labels_of(res, labels, o.shape))
                errs[n] = {k: v for k, v in e.items() if k != "predicted"}
                relit = e["predicted"] if n == model else relit
            title = (f"relighting with the {model} estimates: RMSE/mean = " if name is None
                     else f"{name}: relit with the {model} estimates, RMSE/mean = ")
            path = os.path.join(out, "relight.png" if name is None else f"relight_{name}.png")
            plots.plot_images(o.stokes, relit, o.mask, path, title=f"{title}{errs[model]['rel_rmse']:.4f}",
                              label="relit", lin_variance=o.lin_variance)
            self.wrote(path)
            return errs
        preds = {n: predict_image(n, r.params, o if im is None else fitted_observation(o, im[n]), maps=r.maps,
                                  labels=labels_of(r, labels, o.shape)) for n, r in results.items()}
        pred = preds.pop(model)
        power = "" if im is None or main.powers is None else "; " + power_text(im[model])
        shown = shown_pixels(o, pixels, self.opts, labels_of(main, labels, o.shape))
        tail = "" if name is None else f"_{name}"
        plots.plot_profiles(o, pred, os.path.join(out, f"profiles{tail}.png"), pixels=shown,
                            title=f"{model if name is None else name}: "
                                  + ", ".join(f"{k}={v:.3g}" for k, v in main.params.items()) + power,
                            others={f"{n} (baseline)": p for n, p in preds.items()})
        self.wrote(f"profiles{tail}.png")
        plots.plot_images(o.stokes, pred, o.mask, os.path.join(out, f"images{tail}.png"),
                          title=(f"{model} fit" if name is None else f"{name}: joint {model} fit")
                                + f" (per-pixel re-render){power}", lin_variance=o.lin_variance, pixels=shown)
        self.wrote(f"images{tail}.png")
        return pred


class SingleImage(ImageFits):
    """:func:`fit_files` as a :class:`~fmbrdf_mi.fit.outputs.job.FitJob` (``a``: its arguments by name)."""

    def __init__(self, arguments, out, **kw):
        super().__init__(out, **kw)
        self.a = dict(arguments)
        self.model = self.a["model"]

    def check(self):
        a = self.a
        check_input_options(**a)
        check_fit_options(**a)
        parse_auto(a["materials"])   # auto:M well formed (a label file is read in read())

    def files(self):
        return list(output_files(self.out, self.a["relight"], self.a["albedo"], self.a["materials"]).values())

    def read(self):
        a = self.a
        self.auto = parse_auto(a["materials"])
        self.found = None
        self.labels = None if a["materials"] is None or self.auto else read_labels(a["materials"])
        obs = build_observation(a["inputs"], light=a["light"], **{k: a[k] for k in IMAGE_KEYS})
        self.obs = [obs]
        if a["relight"] is not None:
            geom = None if (a["normals"] is None and a["sphere"] is None and "truth" in obs.meta) \
                else (obs.normals, obs.mask, obs.view_dirs)
            self.obs.append(build_observation(a["relight"], light=a["relight_light"],
                                              irradiance=a["relight_irradiance"], geometry=geom,
                                              **{k: a[k] for k in ("layout", "black_level", "channel", "demosaic",
                                                                   "conversion_gain", "read_noise", "footprint")}))
            if self.obs[1].shape != obs.shape:
                raise InputError(f"relight image: shape {self.obs[1].shape} differs from the fitted image {obs.shape}")
        self.names, self.holdout = [None] * len(self.obs), [False, True][:len(self.obs)]
        self.reproduce = lambda obs: record.one_image_block("single", a, self.command, obs)

    def fit(self):
        a, obs, model = self.a, self.obs[0], self.model
        self.opts = opts = fit_options(a, max_time=a["max_time"] or None)
        loss = resolve_loss(obs, opts)
        check_resolved_loss(a, loss, "--loss likelihood" if a["loss"] == "likelihood" else
                            "the input has no camera noise model" if obs.noise is None or not obs.noise.known else
                            f"--path {a['path']}, --optimizer {a['optimizer']}", flag)
        check_footprint(a["footprint"], loss, "--loss likelihood" if a["loss"] == "likelihood" else
                        f"the camera noise from {obs.meta.get('sidecar') or '--conversion-gain'}")
        scene = _render_scene(obs, model) if opts.path == "render" else None
        if self.auto:
            self.found = find_materials(obs, self.auto, opts, seed=int(a["seed"]), progress=self.progress)
            self.labels = self.found.labels

        def solve(name, o):
            if self.found is not None and name == model and scene is None \
                    and o == dataclasses.replace(o, albedo="shared", intervals="fisher"):
                return self.found.fit    # find_materials' last fit: these labels and these options
            return fit(obs, o, scene=scene if name == model else None, progress=self.progress, materials=self.labels)

        self.fit_models(BASELINES if a["baselines"] else (), solve)

    def report(self):
        report = super().report()
        if self.found is not None:
            report["materials_found"] = dict(self.found.record, labels=os.path.join(self.out, "labels.png"))
        return report

    def write(self, report):
        super().write(report)
        s4 = np.concatenate([self.fitted, np.zeros_like(self.fitted[:1])])[..., None]
        stokes_io.write_stokes_exr(os.path.join(self.out, "fitted_stokes.exr"), s4,
                                   {"fit": self.results[self.model].params, "model": self.model}, force=True)
        self.wrote("fitted_stokes.exr")
        if self.found is not None:
            write_labels(os.path.join(self.out, "labels.png"), self.labels)
            self.wrote("labels.png")


def model_entries(results, model, truth):
    """fit.json's ``models``, ``model``'s with its ``relative_error`` to the input's ``truth`` (if rendered)."""
    entries = {name: res.to_json() for name, res in results.items()}
    if truth:
        entries[model]["relative_error"] = relative_errors(results[model].params, truth)
    return entries


def relative_errors(params, truth, channels=()):
    """(estimate - truth) / truth where the truth is not 0; a colour fit's per-channel estimates (dicts over
    ``channels``) against a true value per channel or one for all."""
    rel = {}
    for k, t in truth.items():
        v = params.get(k)
        if isinstance(v, dict):
            tt = t if isinstance(t, (list, tuple)) else [t] * len(channels)
            rel[k] = {c: (v[c] - tt[i]) / tt[i] for i, c in enumerate(channels) if tt[i]}
        elif v is not None and isinstance(t, (int, float)) and t:
            rel[k] = (v - t) / t
    return rel


def baseline_options(opts, name):
    """Options of the baseline ``name``: the model's loss and data, its own bounds and start, nothing fixed."""
    return dataclasses.replace(opts, model=name, bounds=None, init=None, fixed=None, path="pixel")


def labels_of(res, labels, shape):
    """The labels (on the grid ``shape``) to predict ``res`` with: None unless it fitted several materials."""
    if labels is None or res.materials is None or res.materials["count"] < 2:
        return None
    return check_labels(labels, shape)


def shown_pixels(o, pixels, opts, labels=None):
    """The pixels a fit's figures show: every usable, labelled pixel before the ``max_pixels`` draw, so the
    residual panels are images rather than a random speckle; ``pixels`` (those fitted) if not all among them."""
    if pixels is None:
        return None
    every = usable_pixels(o, dataclasses.replace(opts, max_pixels=0))
    if labels is not None:
        every = every[np.asarray(labels).reshape(-1)[every] >= 0]
    return every if np.isin(pixels, every).all() else pixels


def write_maps(res, model, out, report, wrote=lambda path: None):
    """:data:`~fmbrdf_mi.fit.outputs.job.MAP_OUTPUTS` of a per-pixel albedo fit ``res`` (NaN where not fitted),
    named in ``report["albedo_maps"]``; ``wrote``: called with each path written."""
    if res.maps is None:
        return
    outs = {f: os.path.join(out, f) for f in MAP_OUTPUTS}
    meta = {"fit": res.params, "model": model, "albedo": res.albedo}
    for key in ("k_s", "k_b", "k_s_se", "k_b_se"):
        stokes_io.write_map_exr(outs[f"{key}.exr"], res.maps[key], dict(meta, map=key), force=True)
        wrote(outs[f"{key}.exr"])
    a = res.albedo
    plots.plot_albedo_maps(res.maps, outs["albedo_maps.png"],
                           title=f"{model} per-pixel albedos: {a['pixels']} pixels, split identified in "
                                 f"{a['identified_fraction']:.0%}; " + ", ".join(f"{k}={v:.3g}"
                                                                                 for k, v in res.params.items()))
    wrote(outs["albedo_maps.png"])
    report["albedo_maps"] = outs


def _render_scene(obs, model):
    """The built-in sphere scene of a synthetic EXR, with the model's BSDF, for the render path."""
    if model != "fmbrdf" or obs.meta.get("scene") != "builtin:sphere":
        raise InputError("path 'render' needs a Stokes EXR written by `fmbrdf-mi render` for the built-in "
                         "sphere (the scene is rebuilt from its metadata) and the fmbrdf model")
    mi, p = set_variant(), obs.meta["parameters"]
    d = S.sphere_scene({"k_s": 1.0, "k_b": 1.0}, light_dir=p["light_dir"], irradiance=p["irradiance"],
                       resolution=(int(p["width"]), int(p["height"])), spp=int(p.get("spp", 16)),
                       camera=p["camera"], fov=p["fov"], distance=p["distance"])
    return mi.load_dict(d)
