"""Several images of one object from files: :func:`fit_images` fits them jointly and writes fit.json and the
figures per image; :func:`run_images` is the command's entry (the manifest's format: docs/howto/fit-joint.md)."""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi.fit.api.fitting import fit_joint
from fmbrdf_mi.fit.api.options import (FIT_NAMES, OPTION, check_fit_options, check_resolved_loss, fit_options, flag,
                                        record_keys)
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.colour import is_colour
from fmbrdf_mi.fit.inputs.manifest import build_observations, given_power, image_names
from fmbrdf_mi.fit.inputs.observations import check_direction
from fmbrdf_mi.fit.inputs.parse import check_keys, parse_vector
from fmbrdf_mi.fit.outputs.colour import fit_colour_images
from fmbrdf_mi.fit.outputs.record import joint_block, sha256
from fmbrdf_mi.fit.inputs.labels import read_labels
from fmbrdf_mi.fit.api.find_materials import parse_auto
from fmbrdf_mi.fit.outputs.single import ImageFits
from fmbrdf_mi.fit.outputs.job import joint_outputs
from fmbrdf_mi.fit.problem.data import check_footprint, resolve_loss


#: The keywords :func:`fit_images` takes besides its own: the joint record's options and :class:`FitOptions`'.
TAKES = tuple(dict.fromkeys(k for k in record_keys("joint") + FIT_NAMES if k not in ("model", "baselines")))


def check_distinct(specs):
    """InputError unless the fitted images of ``specs`` are distinct: the same file (path or SHA-256 content)
    under the same light (not given: the input's own) would count its pixels twice."""
    names, seen = image_names(specs), {}
    for k, s in enumerate(specs):
        paths = [os.fspath(p) for p in (s.input if isinstance(s.input, (list, tuple)) else [s.input])
                 if isinstance(p, (str, os.PathLike))]
        if s.holdout or not paths or not all(os.path.isfile(p) for p in paths):
            continue
        light = None if s.light is None else check_direction(parse_vector(s.light, f"image {k}: light"),
                                                              f"image {k}: light")
        key = tuple(sha256(p) for p in paths)
        for j, other, where in seen.get(key, []):
            if (light is None) != (other is None) or (light is not None and not np.allclose(light, other, rtol=0,
                                                                                            atol=1e-12)):
                continue
            same = [os.path.realpath(p) for p in paths] == [os.path.realpath(p) for p in where]
            how = (f"the same file {paths[0]}" if same
                   else f"files of the same content (SHA-256), {where[0]} and {paths[0]},")
            shown = "the input's own" if light is None else [round(float(x), 6) for x in light]
            raise InputError(f"images {j} ({names[j]}) and {k} ({names[k]}): {how} under the same light ({shown}); a "
                             "joint fit would count its pixels twice: give each image once")
        seen.setdefault(key, []).append((k, light, paths))


def fit_images(specs, out, *, model="fmbrdf", baselines=False, force=False, progress=True, command=None,
               observations=None, reproduce=None, **fit_kw):
    """Joint fit of the non-held-out images of ``specs``, the held-out ones relit; writes the outputs to ``out``.

    ``fit_kw``: :class:`~fmbrdf_mi.fit.api.options.FitOptions` fields; ``reproduce``: observations -> fit.json's
    ``reproduce`` block (default: the images as given, ``kind`` ``lights``).  Returns fit.json's dict plus
    ``outputs`` (the files written) and ``wall_s``."""
    return Joint(specs, out, model=model, baselines=baselines, force=force, progress=progress, command=command,
                 observations=observations, reproduce=reproduce, **fit_kw).run()


class Joint(ImageFits):
    """:func:`fit_images` as a :class:`~fmbrdf_mi.fit.outputs.job.FitJob`."""

    def __init__(self, specs, out, *, model, baselines, observations, reproduce, **kw):
        fit_kw = {k: kw.pop(k) for k in list(kw) if k not in ("force", "progress", "command")}
        super().__init__(out, **kw)
        self.specs, self.model, self.baselines, self.fit_kw, self.obs = specs, model, baselines, fit_kw, observations
        self.reproduce = reproduce or (lambda obs: joint_block("lights", specs, self.names, obs,
                                                               dict(fit_kw, model=model, baselines=baselines),
                                                               self.command))

    def check(self):
        check_distinct(self.specs)
        if parse_auto(self.fit_kw.get("materials")):
            raise InputError(f"--materials {self.fit_kw['materials']}: finding the materials is for single-image "
                             "fits so far; for several images give a label image (e.g. the labels.png of a "
                             "single-image fit with auto:M)")
        check_keys(self.fit_kw, TAKES, "fit_images()", "option(s)")
        check_fit_options(model=self.model, **self.fit_kw)

    def files(self):
        self.names, self.holdout = image_names(self.specs), [s.holdout for s in self.specs]
        return joint_outputs(self.out, self.names, self.holdout, self.fit_kw.get("albedo", OPTION["albedo"].default),
                             self.fit_kw.get("materials"))

    def read(self):
        path = self.fit_kw.get("materials")
        self.labels = None if path is None else read_labels(path)
        if self.obs is None:
            self.obs = build_observations(self.specs)

    def fit(self):
        specs, obs, holdout, model = self.specs, self.obs, self.holdout, self.model
        fit_obs = [o for o, h in zip(obs, holdout) if not h]
        fit_names = [n for n, h in zip(self.names, holdout) if not h]
        self.opts = opts = fit_options(self.fit_kw, model=model)
        for n, s, o in zip(self.names, specs, obs):
            fp = (s.options or {}).get("footprint")
            loss = resolve_loss(o, opts)
            check_resolved_loss(self.fit_kw, loss, f"image {n} has no camera noise model" if o.noise is None
                                or not o.noise.known else f"--loss {opts.loss}", flag)
            check_footprint(fp, loss, "--loss likelihood" if opts.loss == "likelihood" else
                            f"the camera noise from {o.meta.get('sidecar') or 'conversion_gain'}",
                            name=f"image {n}: the manifest's (or --footprint's) footprint")
        given = [given_power(s, o) for s, o, h in zip(specs, obs, holdout) if not h]
        self.fit_models(("pplastic", "lambert_ts") if self.baselines else (),
                        lambda name, o: fit_joint(fit_obs, o, names=fit_names, progress=self.progress, powers=given,
                                                  materials=self.labels))


def run_images(kind, specs, out, fit_kw, *, command, force=False, progress=True, manifest=None, authors=None,
               info=None):
    """The joint fit of ``specs`` as the command and ``--from`` run it (colour mosaics:
    :func:`~fmbrdf_mi.fit.outputs.colour.fit_colour_images`), recording how the images were given (``kind``,
    ``manifest``, ``authors``, ``info``; :func:`~fmbrdf_mi.fit.outputs.record.joint_block`); returns fit.json's dict."""
    names = image_names(specs)
    return (fit_colour_images if is_colour(specs) else fit_images)(
        specs, out, force=force, progress=progress, command=command,
        reproduce=lambda obs: joint_block(kind, specs, names, obs, fit_kw, command, manifest=manifest, authors=authors,
                                          info=info), **fit_kw)
