"""``fit()``: estimate a model's parameters from one :class:`Observation` or several of one object (paper sec. 5)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.api.assemble import Fitted, assemble
from fmbrdf_mi.fit.api.checks import check_footprint, check_intervals, find_other_optima
from fmbrdf_mi.fit.api.options import FitOptions, check_fit_options, check_resolved_loss, fit_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS
from fmbrdf_mi.fit.evaluate.models import State, get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import RenderEvaluator
from fmbrdf_mi.fit.inputs.observations import check_observations
from fmbrdf_mi.fit.problem import free_power as FP
from fmbrdf_mi.fit.problem.data import prepare, resolve_loss, select_pixels
from fmbrdf_mi.fit.problem.free_power import power_text, split_result
from fmbrdf_mi.fit.solve import optimise as O

__all__ = ["FitOptions", "fit", "fit_joint", "check_footprint", "check_intervals", "find_other_optima",
           "usable_pixels", "select_pixels", "diagnose"]


def usable_pixels(obs, opts):
    """Flat indices of the pixels a fit uses (:func:`select_pixels`)."""
    return select_pixels(obs, opts)[0]


def fit(obs, options=None, *, scene=None, progress=True, evaluator=None, data=None, names=None, powers=None,
        materials=None, **kw):
    """Estimate the parameters of ``options.model`` from ``obs``; returns a :class:`~fmbrdf_mi.fit.result.FitResult`.

    ``obs``: an :class:`~fmbrdf_mi.fit.inputs.observations.Observation`, or a list of them of one material
    (:func:`fit_joint`).  Keywords override :class:`FitOptions` fields.  ``progress``: True prints to stderr, a
    callable receives each line, False is silent.  ``evaluator``: a reusable
    :func:`~fmbrdf_mi.fit.problem.data.prepare` evaluator of the same pixels; ``data``: a caller-built
    :class:`~fmbrdf_mi.fit.problem.problem.FitData` (``obs`` then gives only its noise model and pixel grid).
    ``materials``: integer labels on ``obs.shape`` or a raw mosaic's sensor grid, 0 .. M-1 the materials, < 0
    not fitted; each material gets its own ``eta[m]``, ... and, with ``albedo="shared"``, ``k_s[m]``,
    ``r_k[m]``.  ``max_time`` stops with the latest accepted estimate, ``converged=False`` and no standard
    errors."""
    t0, opts = time.time(), fit_options(options, **kw)
    check_fit_options(**dataclasses.asdict(opts))
    joint = isinstance(obs, (list, tuple))
    images = check_observations(obs, "fit()", least=0)
    K, say = len(images), progress_callable(progress)
    names = list(names) if names is not None else [f"image{k}" for k in range(K)]
    given, loss = check_call(images, joint, names, powers, opts)
    if data is None:
        if opts.path == "render":
            evaluator = render_evaluator(images[0], scene, opts)
        data = prepare(images, opts, loss, single=not joint, evaluator=evaluator, materials=materials)
    table = Parameters(get_model(opts.model), powers=given) if opts.free_power else None
    if table is not None:
        def powered(d):     # the free powers' evaluator and problem, remakes included
            pev = FP.PowerEvaluator(d.evaluator, table, [b - a for a, b in d.slices])
            remake = None if d.remake is None else (lambda m, f=d.remake: powered(f(m)))
            return dataclasses.replace(d, evaluator=pev, remake=remake,
                                       make_problem=FP.problem_factory(pev, d.slices, opts.power_start))

        data = powered(data)
    if joint:
        say(f"[joint] {K} images, " + ", ".join(f"{n}: {b - a} px, light {np.round(o.light_dir, 3).tolist()}"
                                                for n, o, (a, b) in zip(names, images, data.slices)))
    fx = Fitted(None, data, None, opts, say, deadline=t0 + float(opts.max_time) if opts.max_time else None,
                image_shape=images[0].shape, labels=materials, t0=t0)
    fx.problem = problem = fx.problem_of(data)
    report_start(problem, data, opts, say)
    init = None
    if opts.init:   # per-pixel albedos take no start: solved at the start's shape (solve projects)
        start = dict.fromkeys(problem.params.albedo_pair, 1.0) if opts.albedo in PER_PIXEL_LAYOUTS else {}
        init = problem.state(*problem.params.split({**start, **opts.init}))
    explore = None if data.subsample is None or data.make_problem is not None else (
        len(data.pixels), lambda n: fx.problem_of(data.subsample(n)), max(map(len, data.image_pixels)))
    fx.solution = fx.solve(problem, init=init, starts=opts.starts, history=fx.history, explore=explore)
    res = assemble(fx)
    if opts.area_points is None:
        res = check_footprint(res)
    if opts.intervals in ("auto", "profile"):
        res = check_intervals(res, every=opts.intervals == "profile")
    res = report_end(find_other_optima(res))
    if joint:
        diagnose(res, images, names, table, given, say)
    return res


def render_evaluator(obs, scene, opts):
    """The render path's evaluator: ``scene`` rendered, the fit's pixels of ``obs`` read off."""
    if scene is None:
        raise InputError("path 'render' needs a Mitsuba scene (scene=...) containing the model's BSDF")
    evaluator = RenderEvaluator(get_model(opts.model), scene, opts.bsdf_prefix, select_pixels(obs, opts)[0],
                                spp=opts.spp, seed=opts.seed)
    if evaluator.shape != obs.shape:
        raise InputError(f"scene renders {evaluator.shape[1]}x{evaluator.shape[0]} pixels but the "
                         f"observation is {obs.shape[1]}x{obs.shape[0]}")
    return evaluator


def check_call(images, joint, names, powers, opts):
    """Refuses a call whose images, names, powers and options do not go together (one :class:`InputError`
    line); returns the light powers (1 each unless given) and the one loss the images resolve to."""
    K = len(images)
    try:
        given = [1.0] * K if powers is None else [float(p) for p in powers]
    except (TypeError, ValueError):
        given = []
    losses = {resolve_loss(o, opts) for o in images}
    for bad, text in ((not K, "joint fit: no images"),
                      (joint and (opts.path != "pixel" or opts.optimizer != "lm"),
                       "joint fit: works with the pixel path and optimizer 'lm'"),
                      (len(names) != K, f"joint fit: {len(names)} names for {K} images"),
                      (len(losses) > 1, "joint fit: the camera noise is known for some images and not for others "
                                        f"(loss 'auto' resolves to {sorted(losses)}); give it for all, or choose "
                                        "--loss"),
                      (opts.free_power and not joint, "free_power: the relative light powers are estimated in joint "
                                                      "fits of two or more images (fit_joint; fmbrdf-mi fit "
                                                      "--free-power with --manifest, --authors or several --light)"),
                      (opts.free_power and K < 2, "free_power: needs two or more fitted images (one image's power "
                                                  "is not separable from k_s and k_b)"),
                      (len(given) != K or not all(math.isfinite(p) and p > 0 for p in given),
                       f"powers: expected {K} positive numbers, got {powers!r}")):
        if bad:
            raise InputError(text)
    loss = losses.pop()
    check_resolved_loss(dataclasses.asdict(opts), loss, "loss 'paper'" if opts.loss == "paper" else
                        "the observation has no camera noise model")
    return given, loss


def fit_joint(observations, options=None, **kw):
    """:func:`fit` of K images of one object, each its own light, geometry and mask, sharing one material
    (pixel path, ``lm`` only); ``max_pixels`` is split evenly.  ``names``: the images' labels (default
    ``image0``, ...); ``free_power=True`` estimates the light powers of images 1 .. K-1 relative to image 0's
    (:mod:`fmbrdf_mi.fit.problem.free_power`); ``powers``: the relative powers the irradiances already include
    (default 1 each).  The result adds ``images`` (:func:`~fmbrdf_mi.fit.api.fitting.diagnose`) and ``pixels``
    per image."""
    return fit(check_observations(observations, "fit_joint()", least=0), options, **kw)


def progress_callable(progress):
    """``fit``'s ``progress``: True prints to stderr, a callable receives each line, False is silent."""
    return O.default_progress if progress is True else (progress or (lambda m: None))


def report_start(problem, data, opts, report):
    """The progress lines before the solve."""
    ex, obj = data.excluded, data.objective
    if ex.get("saturated") or ex.get("dark"):
        report(f"[fit] excluded {ex['saturated']} super-pixels with a sample at or above the white level "
               f"{ex['white_level']:g} and {ex['dark']} with a sample at or below the dark level "
               f"{ex['dark_level']} (of {ex['candidates']})")
    if data.loss == "likelihood":
        report(f"[fit] {problem.model.name} on {len(data.pixels)} super-pixels x {obj.m} {data.samples.source} "
               f"samples, likelihood; camera noise {obj.noise.describe()}")
        return
    what = {"paper": "paper's loss", "intensity": "intensity term of the paper's loss only",
            "dolp": "DoLP term of the paper's loss only"}[data.loss]
    report(f"[fit] {problem.model.name} on {len(data.pixels)} pixels ({opts.path} path), {what}, "
           f"{int(obj.target.dolp_valid.sum())} in the DoLP term"
           + ("" if obj.target.lin_sigma is None else ", DoLP term with the given noise variance (Rice mean)"))


def report_end(res):
    """``res`` with its total time and evaluations (the checks' included), after the closing progress lines."""
    fx = res.fitted
    if res.weakly_identified:
        fx.report(f"[fit] weakly identified (standard error > {U.WEAK_REL:.0%} or at a bound): "
                  f"{', '.join(res.weakly_identified)}")
    res.timings.update(total=time.time() - fx.t0, evaluations=fx.problem.n_evals + fx.evaluations)
    fx.report(f"[fit] done in {res.timings['total']:.1f} s: {res.objective} {res.loss:.6e} ({res.stop_reason})  "
              f"{O.format_state(fx.problem, fx.solution.state)}")
    for m, p in enumerate((res.materials or {}).get("parameters", [])):
        fx.report(f"[fit] material {m} ({res.materials['pixels'][m]} px): "
                  + " ".join(f"{k}={v:.4g}" for k, v in p.items()))
    return res


def diagnose(res, observations, names, table, given, say):
    """A joint fit's ``res.pixels`` and ``res.images``: per image its pixels, light, how well the shared
    estimate explains it and, with the free powers of ``table``, its power (``given``: the given ones)."""
    data = res.fitted.data
    loss, objective = data.loss, data.objective
    internal = res.details["internal"]
    st = State(internal["shape"], np.asarray(internal["a_s"]), np.asarray(internal["a_b"]))
    parts = data.evaluator.parts(st.shape)
    pts = parts.surface.shape[1] // max(sum(len(i) for i in data.image_pixels), 1)
    a_s, a_b = st.a_s, st.a_b
    if res.maps is not None or data.materials is not None:    # albedos per group / material: each cell's own
        cell = np.repeat(objective.layout.groups[:, 0], pts)
        a_s, a_b = a_s[cell], a_b[cell]
    pred = a_s * parts.surface + a_b * parts.body   # (3, points)
    r = objective.residuals(parts, st)[:objective.y.size].reshape(-1, 4) if loss == "likelihood" else None
    out = []
    for k, (o, idx, (a, b)) in enumerate(zip(observations, data.image_pixels, data.slices)):
        s = pred[:, a * pts:b * pts]
        if pts > 1 and loss == "likelihood":
            s = s.reshape(3, b - a, pts).mean(axis=2)  # the super-pixel's mean Stokes
        obs_s = o.stokes.reshape(3, -1)[:, idx]
        d_obs, d_pred = (np.hypot(x[1], x[2]) / np.where(x[0] > 0, x[0], 1.0) for x in (obs_s, s))
        bright = obs_s[0] > 0.02 * np.percentile(obs_s[0], 99)
        im = {"name": names[k], "light_dir": o.light_dir.tolist(), "irradiance": o.irradiance,
              "n_pixels": int(b - a), "pixels_excluded": data.excluded["per_image"][k],
              "intensity_rel_rmse": float(np.sqrt(np.mean((s[0] - obs_s[0]) ** 2)) / np.mean(obs_s[0])),
              "dolp_rmse": float(np.sqrt(np.mean((d_pred - d_obs)[bright] ** 2))) if bright.any() else None}
        if r is not None:
            im["chi2"] = float(np.sum(r[a:b] ** 2))
            im["chi2_per_dof"] = im["chi2"] / max((b - a) * objective.dof, 1)
        out.append(im)
    if table is not None:
        res.powers = split_result(res, table, names)
        for k, im in enumerate(out):
            im.update({"power": res.powers["values"][k], "power_given": given[k],
                       "power_se": res.powers["std_errors"][k], "power_ci95": res.powers["ci95"][k],
                       "power_reference": k == 0})
    for im in out:
        say(f"[joint] {im['name']}: " + ", ".join(f"{k} {im[k]:.4g}" for k in ("chi2_per_dof", "intensity_rel_rmse",
                                                                             "dolp_rmse") if im.get(k) is not None)
            + ("" if table is None else ", " + power_text(im)))
    res.images, res.pixels = out, data.image_pixels
