"""``fit()``: estimate a model's parameters from one :class:`Observation` (paper section 5)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.api.options import FitOptions, check_fit_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import State, get_model
from fmbrdf_mi.fit.evaluate.pixel_model import RenderEvaluator
from fmbrdf_mi.fit.inputs.observations import check_observations
from fmbrdf_mi.fit.objectives import loss_variants as LV
from fmbrdf_mi.fit.problem import free_power as FP
from fmbrdf_mi.fit.problem.data import prepare, resolve_loss, select_pixels
from fmbrdf_mi.fit.problem.materials import material_block
from fmbrdf_mi.fit.problem.free_power import power_text, split_result
from fmbrdf_mi.fit.problem.problem import TimeUp
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import optimise as O
from fmbrdf_mi.fit.solve.driver import refit_fixed, solve
from fmbrdf_mi.fit.uncertainty import WEAK_REL


def weakly_identified(params, std, at_bound=()):
    return U.weakly_identified(params, std, at_bound)


def usable_pixels(obs, opts):
    """Flat indices of the pixels a fit uses (:func:`select_pixels`)."""
    return select_pixels(obs, opts)[0]


def render_evaluator(model, obs, idx, opts, scene):
    """The render path's evaluator: the scene rendered, the pixels ``idx`` read off."""
    if scene is None:
        raise InputError("path 'render' needs a Mitsuba scene (scene=...) containing the model's BSDF")
    ev = RenderEvaluator(model, scene, opts.bsdf_prefix, idx, spp=opts.spp, seed=opts.seed)
    if ev.shape != obs.shape:
        raise InputError(f"scene renders {ev.shape[1]}x{ev.shape[0]} pixels but the observation "
                         f"is {obs.shape[1]}x{obs.shape[0]}")
    return ev


def fit(obs, options=None, *, scene=None, progress=True, evaluator=None, data=None, names=None, powers=None,
        materials=None, **kw):
    """Estimate the parameters of ``options.model`` from ``obs``; returns a :class:`FitResult`.

    ``obs``: one :class:`~fmbrdf_mi.fit.inputs.observations.Observation`, or
    a list of them: several images of one object sharing the material (a
    joint fit, :func:`fmbrdf_mi.fit.api.joint.fit_joint`: ``names``,
    ``powers`` and the ``free_power`` option are for lists).  One image is the
    list of one: both run on :func:`~fmbrdf_mi.fit.problem.data.prepare`.

    Keyword arguments override fields of :class:`FitOptions` (the CLI's
    options have the same names).  ``progress``: True prints to stderr, a
    callable receives each progress line, False is silent.  ``evaluator``:
    the evaluator of :func:`~fmbrdf_mi.fit.problem.data.prepare` for the same
    geometry, pixels and objective (reused across noise seeds by the benchmarks).
    ``data``: a :class:`~fmbrdf_mi.fit.problem.problem.FitData` built by
    the caller for data that are not one observation (several images of one
    object, which :func:`~fmbrdf_mi.fit.problem.data.prepare` builds); ``obs`` is
    then only used for its noise model.

    ``materials``: a label image assigning each pixel to one of M materials
    (:mod:`fmbrdf_mi.fit.evaluate.materials`): an integer array on the fit's
    pixel grid (``obs.shape``: for a raw mosaic the super-pixel grid; its
    sensor grid, twice as large, is accepted too:
    :func:`~fmbrdf_mi.fit.evaluate.materials.check_labels`), 0 .. M-1 the
    materials, < 0 pixels not fitted.  Each material gets its own shape
    parameters (``eta[m]``, ...) and, with ``albedo="shared"``, its own
    ``k_s[m]``, ``r_k[m]``; ``params`` holds them flat, ``materials`` (and
    fit.json) per material.  One camera noise model for all: the likelihood
    is needed.  M = 1 is the ordinary fit over the labelled pixels.

    A fit stopped by ``max_time`` (a hard wall-clock limit, checked before
    every model evaluation) returns the latest accepted estimate with
    ``converged=False`` and no standard errors.
    """
    fields = [f.name for f in dataclasses.fields(FitOptions)]
    unknown = [k for k in kw if k not in fields]
    if unknown:
        raise InputError(f"fit(): unknown option(s) {', '.join(unknown)} (FitOptions: {', '.join(fields)}; the "
                         "light, irradiance, geometry and noise are the Observation's)")
    if isinstance(obs, (list, tuple)):
        return _fit_images(check_observations(obs, "fit()", least=0), options, names=names, progress=progress,
                           powers=powers, materials=materials, **kw)
    opts = dataclasses.replace(options or FitOptions(), **kw)
    check_fit_options(**dataclasses.asdict(opts))
    check_observations(obs, "fit()")
    if opts.optimizer not in ("lm", "adam"):
        raise ValueError(f"optimizer: expected 'lm' or 'adam', got {opts.optimizer!r}")
    if opts.path == "render" and opts.optimizer != "adam":
        raise InputError("path 'render' works with optimizer 'adam' only (reverse-mode gradient through "
                         "mi.render; its forward-mode derivatives, which 'lm' needs, miss the body term)")
    if opts.free_power and (data is None or data.make_problem is None):
        raise InputError("free_power: the relative light powers are estimated in joint fits of two or more "
                         "images (fit_joint; fmbrdf-mi fit --free-power with --manifest, --authors or several "
                         "--light)")
    if opts.intervals not in U.INTERVALS:
        raise InputError(f"intervals: expected one of {', '.join(U.INTERVALS)}, got {opts.intervals!r}")
    loss = resolve_loss(obs, opts)
    if loss == "likelihood" and (opts.optimizer != "lm" or opts.path != "pixel"):
        raise InputError("loss 'likelihood' works with the pixel path and optimizer 'lm' (use --loss paper "
                         "for adam or the render path)")
    if loss in LV.VARIANTS and opts.optimizer != "lm":
        raise InputError(f"loss '{loss}' works with optimizer 'lm' (Adam minimises the full paper's loss)")
    report = O.default_progress if progress is True else (progress or (lambda m: None))
    model = get_model(opts.model)
    t0 = time.time()
    deadline = None if not opts.max_time else t0 + float(opts.max_time)
    if data is None and opts.path == "render":
        idx, _ = select_pixels(obs, opts)
        evaluator = render_evaluator(model, obs, idx, opts, scene)
    elif opts.path not in ("pixel", "render"):
        raise InputError(f"path: expected 'pixel' or 'render', got {opts.path!r}")
    if data is None:
        data = prepare([obs], opts, loss, single=True, evaluator=evaluator, materials=materials)
    loss, idx, excluded, objective, smp = data.loss, data.pixels, data.excluded, data.objective, data.samples
    if excluded.get("saturated") or excluded.get("dark"):
        report(f"[fit] excluded {excluded['saturated']} super-pixels with a sample at or above the white level "
               f"{excluded['white_level']:g} and {excluded['dark']} with a sample at or below the dark level "
               f"{excluded['dark_level']} (of {excluded['candidates']})")
    problem = data.problem(model, opts.bounds, report, opts.fixed, deadline)
    model = problem.model      # free light powers: a model that reports them too
    if loss != "likelihood":
        what = {"paper": "paper's loss", "intensity": "intensity term of the paper's loss only",
                "dolp": "DoLP term of the paper's loss only"}[loss]
        report(f"[fit] {model.name} on {len(idx)} pixels ({opts.path} path), {what}, "
               f"{int(objective.target.dolp_valid.sum())} in the DoLP term"
               + ("" if objective.target.lin_sigma is None else
                  ", DoLP term with the given noise variance (Rice mean)"))
    else:
        report(f"[fit] {model.name} on {len(idx)} super-pixels x {objective.m} {smp.source} samples, likelihood; "
               f"camera noise {objective.noise.describe()}")
    history = []
    init = None
    if opts.init:
        shape, a_s, a_b = model.split(opts.init)
        init = problem.state(shape, a_s, a_b)
    sol = solve(problem, init=init, starts=opts.starts, rounds=max(1, opts.rounds) + (2 if loss == "likelihood" else 0),
                optimizer=opts.optimizer, max_iter=opts.max_iter, tol=opts.tol, time_limit=opts.time_limit,
                lr=opts.lr, max_time=opts.max_time, history=history, report=report)
    st, reason, converged, J, r = sol.state, sol.reason, sol.converged, sol.J, sol.r
    can_jac = opts.path == "pixel"
    quadrature, coarse_evals = None, 0
    if converged and can_jac and opts.area_points is None and data.remake is not None and data.area_points > 1:
        coarse = problem
        problem, data, quadrature, fine_sol = refine_quadrature(problem, data, st, opts, get_model(opts.model),
                                                                report, deadline, history)
        if fine_sol is not None:
            coarse_evals = coarse.n_evals
            st, reason, converged, J, r = (fine_sol.state, fine_sol.reason, fine_sol.converged, fine_sol.J,
                                           fine_sol.r)
            objective = data.objective
    unc = {}
    parts = groups = None
    if converged and can_jac:
        problem.deadline = None  # the fit is done; its uncertainty is part of the answer
        parts = problem.parts(st, jac=True)
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
        n_ind = None if loss != "likelihood" else len(idx) * objective.dof - problem.n_eliminated(st)
        unc = U.summarise(problem, st, J, r, n_ind, parts)
        if loss == "likelihood" and opts.intervals in ("auto", "profile"):
            if deadline is not None and time.time() > deadline:
                unc["method"] += "; intervals not checked against the profile likelihood (max_time reached)"
            else:
                unc = U.profile_intervals(problem, st, unc, J, r, lambda n, v, s: refit_fixed(problem, st, n, v, s),
                                          every=opts.intervals == "profile")
                prof = {n: k for n, k in unc.get("interval_kind", {}).items() if k != "fisher"}
                if prof:
                    report("[fit] profile-likelihood 95 % intervals (the Fisher ones fail there): "
                           + ", ".join(f"{n} ({k})" for n, k in prof.items()))
        if unc.get("misfit"):
            report("[fit] warning: " + U.misfit_text(unc))
        optima, threshold = U.other_optima(sol.starts, st.shape, unc, problem.names)
        if optima:
            unc["other_optima"] = {"optima": optima, "threshold": threshold,
                                   "separation_se": U.MODE_SEPARATION_SE}
            text = U.optima_text(optima, threshold)
            if text:
                unc["other_optima"]["warning"] = text
                report("[fit] warning: " + text)
            U.widen_for_optima(unc, st.shape, optima, {n: problem.bounds.lims[n][2:] for n in problem.names})
        if problem.eliminates:
            groups = U.pixel_albedos(problem, st, parts, J, unc)
        if quadrature is not None:
            unc["quadrature"] = quadrature
            first, m_used = quadrature["checks"][0], quadrature["area_points"]
            if m_used != first["area_points"]:
                worst = max(first["bias_se"], key=lambda n: abs(first["bias_se"][n]))
                unc["method"] = unc.get("method", "") + (
                    f"; pixel-area quadrature {m_used} x {m_used} points per raw pixel ({first['area_points']} x "
                    f"{first['area_points']} would bias {worst} by about {first['bias_se'][worst] / 0.75:+.2f} SE)")
    elif not converged:
        unc = {"std_errors": {}, "method": "not computed: the fit did not converge"}
    if parts is None:
        try:
            parts = problem.parts(st)
        except TimeUp:
            problem.deadline = None
            parts = problem.parts(st)
    terms = problem.obj.loss_terms(parts, st)
    value = problem.obj.value(parts, st)
    std = unc.get("std_errors", {})
    if problem.n_nonfinite:
        report(f"[fit] {problem.n_nonfinite} pixels had non-finite BSDF derivatives; their Jacobian rows were zeroed")
    params = model.report(st.shape, st.a_s, st.a_b)
    albedo = maps = None
    if problem.eliminates:
        if groups is None:     # not converged: the maps' values without standard errors
            f, nan = float(model.albedo_factor), np.full(problem.layout.n_groups, np.nan)
            groups = {"k_s": f * np.asarray(st.a_s), "k_b": f * np.asarray(st.a_b), "k_s_se": nan, "k_b_se": nan,
                      "correlation": nan, "identified": np.zeros(problem.layout.n_groups, bool)}
        albedo, maps = albedo_maps(problem.layout, obs.shape, groups)
        if problem.layout.prior is not None:
            albedo["prior"] = prior_block(problem, st, parts)
            if albedo.get("warning"):   # no sandwich with the prior: the posterior errors (docs/howto/fit-textured.md)
                albedo["warning"] = albedo["warning"].replace(
                    "which the reported incidental-parameter sandwich corrects for the most part",
                    "the smoothness prior narrows, at the cost of its bias (the reported errors are posterior ones)")
            report(f"[fit] albedo smoothness prior: penalty {albedo['prior']['penalty']:.4g} of chi^2 "
                   f"{value:.6g}, effective albedo parameters {albedo['prior']['effective_parameters']:.1f} of "
                   f"{albedo['prior']['parameters']}")
        report(f"[fit] albedo maps: {albedo['pixels']} pixels, surface / body split identified in "
               f"{albedo['identified_fraction']:.0%} (median k_s {albedo['k_s_median']:.4g}, k_b "
               f"{albedo['k_b_median']:.4g})")
        if albedo.get("warning"):
            report("[fit] warning: " + albedo["warning"])
    weak = weakly_identified(params, std, unc.get("at_bound", ()))
    if weak:
        report(f"[fit] weakly identified (standard error > {WEAK_REL:.0%} or at a bound): {', '.join(weak)}")
    t_total = time.time() - t0
    report(f"[fit] done in {t_total:.1f} s: {loss} {value:.6e} ({reason})  {O.format_state(problem, st)}")
    n_out = int((objective.outliers & objective.target.dolp_valid).sum()) if loss != "likelihood" else 0
    block = None
    if data.materials is not None:
        block = material_block(params, std, unc.get("ci95"), data.materials["count"], data.materials["pixels"])
    elif materials is not None:     # one material: the ordinary fit of the labelled pixels
        block = material_block(params, std, unc.get("ci95"), 1, [len(idx)], base_names=tuple(params))
    if block is not None:
        for m, p in enumerate(block["parameters"]):
            report(f"[fit] material {m} ({block['pixels'][m]} px): "
                   + " ".join(f"{k}={v:.4g}" for k, v in p.items()))
    return FitResult(model=model.name, params=params, loss=value, loss_terms=terms, std_errors=std,
                     history=history, stop_reason=reason, n_pixels=len(idx), n_outliers=n_out,
                     timings={"search": sol.t_search, "total": t_total, "evaluations": problem.n_evals + coarse_evals,
                              "nonfinite_derivative_pixels": problem.n_nonfinite},
                     options=dataclasses.asdict(opts), weakly_identified=weak, converged=bool(converged),
                     objective=loss, uncertainty=unc,
                     noise=objective.noise.to_dict() if loss == "likelihood" else None,
                     pixels_excluded=excluded, starts=sol.starts, pixels=idx, albedo=albedo, maps=maps,
                     materials=block,
                     details={"internal": {"shape": dict(st.shape), "a_s": np.asarray(st.a_s).tolist(),
                                           "a_b": np.asarray(st.a_b).tolist()},
                              "residuals": data_residuals(problem.obj, parts, st),
                              "n_free": len(problem.to_z(st)) + problem.n_eliminated(st)})


def refine_quadrature(problem, data, st, opts, model, report, deadline, history):
    """The pixel-area quadrature of a converged likelihood fit of raw samples, checked and refined: while a
    shape parameter's bias from averaging the model over m x m points of each raw pixel
    (:func:`fmbrdf_mi.fit.uncertainty.quadrature_bias`: against 2m x 2m) exceeds
    :data:`~fmbrdf_mi.fit.uncertainty.QUADRATURE_TOL` standard errors, the data are remade with 2m x 2m and the
    fit resumed from its estimate, up to :data:`~fmbrdf_mi.fit.uncertainty.MAX_AREA_POINTS` (a highlight a few
    pixels wide: glossy materials on small objects; tools/bench_modes.py --material glossy).  Returns
    (problem, data, fit.json's ``uncertainty.quadrature`` block, the refined Solution or None)."""
    m, fine_sol, t0 = data.area_points, None, time.time()
    block = {"area_points": m, "tolerance_se": U.QUADRATURE_TOL, "checks": []}
    while m < U.MAX_AREA_POINTS:
        parts = problem.parts(st, jac=True)
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
        fine_data = data.remake(2 * m)
        fine = fine_data.problem(model, opts.bounds, report, opts.fixed, deadline)
        bias = U.quadrature_bias(problem, fine, st, J, r)
        block["checks"].append({"area_points": m, "against": 2 * m, "bias_se": bias})
        worst = max(bias, key=lambda n: abs(bias[n])) if bias else None
        if worst is None or abs(bias[worst]) <= U.QUADRATURE_TOL:
            break
        report(f"[fit] pixel-area quadrature: {m} x {m} points per raw pixel bias {worst} by about "
               f"{bias[worst] / 0.75:+.2f} standard errors here (the highlight spans few pixels); the fit goes on "
               f"with {2 * m} x {2 * m}")
        try:
            sol = solve(fine, init=st, starts=1, rounds=max(1, opts.rounds) + 2, optimizer=opts.optimizer,
                        max_iter=opts.max_iter, tol=opts.tol, time_limit=opts.time_limit, lr=opts.lr,
                        max_time=opts.max_time, history=history, report=report)
        except InputError:      # max_time: not even one evaluation with the finer points fits
            sol = None
        if sol is None or not sol.converged:    # keep the converged coarser fit, and say so
            block["refinement"] = f"stopped: the fit with {2 * m} x {2 * m} points did not converge" + (
                "" if sol is None else f" ({sol.reason})")
            report(f"[fit] warning: {block['refinement']}; the estimate is the one with {m} x {m} points")
            break
        problem, data, m, fine_sol, st = fine, fine_data, 2 * m, sol, sol.state
        block["area_points"] = m
    block["seconds"] = time.time() - t0
    return problem, data, block, fine_sol


def data_residuals(obj, parts, st):
    """The objective's residuals of the data (without the albedo prior's rows, :mod:`fmbrdf_mi.fit.evaluate.albedo_prior`)."""
    r = obj.residuals(parts, st)
    return r if obj.prior is None else r[:obj.y.size]


#: How a fit with the albedo maps' smoothness prior counts chi^2's degrees of freedom (fit.json albedo.prior).
PRIOR_DOF_RULE = ("chi^2 (data + penalty) has N - p - n0 degrees of freedom, N the independent samples, p the "
                  "free shape parameters, n0 the prior's null space (2 per connected set of pixels: each set's "
                  "mean k_s, k_b): its expectation at the optimum when the maps' neighbour differences follow the "
                  "prior; maps smoother than tau give less (down to N - p - effective_parameters), rougher ones "
                  "more (the misfit check then flags a tau too small)")


def prior_block(problem, st, parts):
    """fit.json's ``albedo.prior``: the maps' smoothness prior (:mod:`fmbrdf_mi.fit.evaluate.albedo_prior`), its
    penalty at ``st``, the albedos' effective number of parameters (the hat matrix's trace) and the rule of
    chi^2's degrees of freedom."""
    lay, obj = problem.layout, problem.obj
    pr = lay.prior
    return {"kind": pr.describe(), "tau_s": pr.tau[0], "tau_b": pr.tau[1], "pairs": int(len(pr.pairs)),
            "penalty": obj.penalty(st), "data_chi2": float(np.sum(data_residuals(obj, parts, st) ** 2)),
            "effective_parameters": lay.effective_parameters(*obj.albedo_columns(parts)),
            "parameters": 2 * int(lay.n_groups), "null_dims": int(pr.null_dims()), "dof_rule": PRIOR_DOF_RULE}


def albedo_maps(layout, shape, groups):
    """(summary, maps) of per-pixel albedos: ``groups`` (:func:`fmbrdf_mi.fit.uncertainty.pixel_albedos`, one
    entry per group of ``layout``) put on the image grid ``shape`` (H, W): arrays (H, W), or (C, H, W) for a
    colour mosaic's channels, NaN where no pixel was fitted (``identified``: False); the summary is
    fit.json's ``albedo`` block."""
    H, W = shape
    C = 1 if layout.channel_of is None else len(layout.labels)
    ch = np.zeros(layout.n_groups, int) if layout.channel_of is None else layout.channel_of
    maps = {}
    for key, v in groups.items():
        img = np.zeros((C, H * W), bool) if key == "identified" else np.full((C, H * W), np.nan)
        img[ch, layout.pixels] = v
        maps[key] = img.reshape(C, H, W) if C > 1 else img.reshape(H, W)
    maps["channels"] = None if C == 1 else list(layout.labels)
    ident = np.asarray(groups["identified"], bool)
    n_pix = len(np.unique(layout.pixels))
    summary = {"layout": layout.name, "pixels": int(n_pix), "groups": int(layout.n_groups),
               "identified_fraction": float(ident.mean()) if ident.size else 0.0,
               "split_rule": f"identified where the standard error of the surface's and of the body's share of "
                             f"the pixel's brightness are at most {U.SPLIT_REL:g} of it",
               "k_s_median": float(np.nanmedian(groups["k_s"])), "k_b_median": float(np.nanmedian(groups["k_b"])),
               "k_s_determined_fraction": _determined(groups["k_s"], groups["k_s_se"]),
               "k_b_determined_fraction": _determined(groups["k_b"], groups["k_b_se"]),
               "channels": maps["channels"]}
    if C > 1:   # a colour mosaic: the same summary per channel (each channel's groups)
        summary["per_channel"] = {
            c: {"identified_fraction": float(ident[ch == j].mean()) if (ch == j).any() else 0.0,
                "k_s_median": float(np.nanmedian(groups["k_s"][ch == j])),
                "k_b_median": float(np.nanmedian(groups["k_b"][ch == j])),
                "k_s_determined_fraction": _determined(groups["k_s"][ch == j], groups["k_s_se"][ch == j]),
                "k_b_determined_fraction": _determined(groups["k_b"][ch == j], groups["k_b_se"][ch == j])}
            for j, c in enumerate(layout.labels)}
    # images (cells) per albedo pair: the median over the pairs (a pixel excluded from an image, e.g.
    # saturated or grazing there, has fewer)
    # (a colour mosaic's cell holds three groups, one per channel: count each group once per cell)
    cells = np.unique(np.stack([np.repeat(np.arange(len(layout.groups)), layout.groups.shape[1]),
                                layout.groups.ravel()]), axis=1)[1] if C > 1 else layout.groups[:, 0]
    per = float(np.median(np.bincount(cells, minlength=layout.n_groups))) if layout.n_groups else 0.0
    summary["images_per_pixel"] = per
    if per < MIN_IMAGES_PER_PIXEL:
        summary["warning"] = PER_PIXEL_FEW_IMAGES
    return summary, maps


#: Below this many images of each pixel a per-pixel albedo fit's shared parameters are poorly determined: with
#: two free albedos per pixel the unknowns grow with the pixels (the incidental-parameter problem), and one
#: image's four polariser samples per pixel leave them too little.  Measured (tools/diag_pp_bias.py,
#: tools/diag_pp_sandwich.py: 24^2, smooth texture, camera noise, 48 seeds, 2026-11-26): from one image the
#: estimates' medians are roughly right, but their spread is 2.5-5.6x the Fisher standard errors (95 %
#: intervals covered 21-36 of 48) and the tails are heavy (a second mode at high eta / low kappa in ~4 % of
#: seeds).  The incidental-parameter sandwich (fmbrdf_mi.fit.uncertainty.covariance, reported since) brings
#: the coverage to 38-45 of 48; the second mode stays.  From three lights the sandwich changes the standard
#: errors by 4-24 %.  Two images were not measured.  At 100^2 (tools/bench_textured.py --res 100 --lights 1,
#: 11-12 seeds per object, 2026-11-26) the second optimum (alpha, beta ~50 % high, kappa ~40 % high on the
#: sphere) wins in about a third of the seeds, by a chi^2 difference of ~10 that the sandwich's 95 % region
#: cannot tell from noise: the mean errors of alpha, beta are +12 to +17 %, the medians +3 to +12 %
#: (:func:`fmbrdf_mi.fit.uncertainty.other_optima` warns when it sees such an optimum among its starts, and
#: :func:`~fmbrdf_mi.fit.uncertainty.widen_for_optima` stretches the intervals over it: 24 seeds per object,
#: alpha and beta covered 18-19 of 24 instead of 15-16).  Noise-free there is no second optimum
#: (tools/diag_one_image_ridge.py: a ridge along which chi^2 rises by 31 at 100^2, 114 at 200^2).
#: At 200^2 (24 seeds, --res 200 --lights 1) it did not occur on the sphere (27,000 fitted super-pixels):
#: eta -0.01 +- 0.06 %, alpha -2.0 +- 1.9 %, beta -1.1 +- 1.3 %, spread / SE 0.80-0.91, 23-24 of 24 intervals
#: cover; it did on the mesh (10,600: a competing optimum in 8 of 24, alpha +8 %).
MIN_IMAGES_PER_PIXEL = 3
PER_PIXEL_FEW_IMAGES = ("per-pixel albedos from fewer than 3 images of each pixel: eta, alpha, beta, kappa are "
                        "poorly determined (one image, measured: a spread 2.5-5.6x the Fisher standard errors, "
                        "which the reported incidental-parameter sandwich corrects for the most part, and heavy "
                        "tails: a second optimum that wins in up to a third of noise draws: 4 % at about 400 fitted "
                        "super-pixels, a third at 2,500-10,600, none of 24 at 27,000); fit several lights of the "
                        "same view")


def _determined(value, se, rel=0.5):
    """Fraction of the groups whose albedo has a relative standard error of at most ``rel``."""
    value, se = np.asarray(value, float), np.asarray(se, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(se) & (se <= rel * value)
    return float(ok.mean()) if ok.size else 0.0


def _fit_images(observations, options=None, *, names=None, progress=True, powers=None, materials=None, **kw):
    """:func:`fit` of a list of observations: the arguments and the result are
    :func:`fmbrdf_mi.fit.api.joint.fit_joint`'s."""
    observations = list(observations)
    if not observations:
        raise InputError("joint fit: no images")
    opts = dataclasses.replace(options or FitOptions(), **kw)
    if opts.path != "pixel" or opts.optimizer != "lm":
        raise InputError("joint fit: works with the pixel path and optimizer 'lm'")
    names = list(names) if names is not None else [f"image{k}" for k in range(len(observations))]
    if len(names) != len(observations):
        raise InputError(f"joint fit: {len(names)} names for {len(observations)} images")
    losses = {resolve_loss(o, opts) for o in observations}
    if len(losses) != 1:
        raise InputError("joint fit: the camera noise is known for some images and not for others "
                         f"(loss 'auto' resolves to {sorted(losses)}); give it for all, or choose --loss")
    loss = losses.pop()
    if opts.free_power and len(observations) < 2:
        raise InputError("free_power: needs two or more fitted images (one image's power is not separable "
                         "from k_s and k_b)")
    try:
        given = [1.0] * len(observations) if powers is None else [float(p) for p in powers]
    except (TypeError, ValueError):
        given = []
    if len(given) != len(observations) or not all(math.isfinite(p) and p > 0 for p in given):
        raise InputError(f"powers: expected {len(observations)} positive numbers, got {powers!r}")
    check_fit_options(**dataclasses.asdict(opts))
    data = prepare(observations, opts, loss, materials=materials)
    idxs, slices = data.image_pixels, data.slices
    pmodel = None
    if opts.free_power:
        pmodel = FP.PowerModel(get_model(opts.model), given)

        def powered(d):     # the data with the free powers' evaluator and problem (their remakes too)
            pev = FP.PowerEvaluator(d.evaluator, pmodel, [b - a for a, b in slices])
            remake = None if d.remake is None else (lambda m, f=d.remake: powered(f(m)))
            return dataclasses.replace(d, evaluator=pev, remake=remake,
                                       make_problem=FP.problem_factory(pmodel, pev, slices, opts.power_start))

        data = powered(data)
    report = O.default_progress if progress is True else progress
    say = report or (lambda m: None)
    say(f"[joint] {len(observations)} images, " + ", ".join(
        f"{n}: {b - a} px, light {np.round(o.light_dir, 3).tolist()}"
        for n, o, (a, b) in zip(names, observations, slices)))
    res = fit(observations[0], opts, progress=progress, data=data, materials=materials)
    m = (res.uncertainty or {}).get("quadrature", {}).get("area_points")
    if m is not None and m != data.area_points:     # the fit refined its pixel-area quadrature: diagnose on it
        data = data.remake(m)
    images = diagnose(res, data, observations, names, pmodel)
    block = None
    if pmodel is not None:
        block = split_result(res, pmodel, names)
        for k, im in enumerate(images):
            im.update({"power": block["values"][k], "power_given": given[k], "power_se": block["std_errors"][k],
                       "power_ci95": block["ci95"][k], "power_reference": k == 0})
    for im in images:
        say(f"[joint] {im['name']}: " + ", ".join(f"{k} {im[k]:.4g}" for k in ("chi2_per_dof", "intensity_rel_rmse",
                                                                             "dolp_rmse") if im.get(k) is not None)
            + ("" if pmodel is None else ", " + power_text(im)))
    res.images, res.powers, res.pixels = images, block, idxs
    return res


def diagnose(res, data, observations, names, power_model=None):
    """Per image: pixels, light, irradiance, and how well the shared estimate explains it."""
    loss, excluded, objective, ev = data.loss, data.excluded, data.objective, data.evaluator
    idxs, slices = data.image_pixels, data.slices
    model = power_model or get_model(res.model)
    if res.maps is not None or data.materials is not None:    # the fitted state (albedos per group / material)
        internal = res.details["internal"]
        shape, a_s, a_b = internal["shape"], np.asarray(internal["a_s"]), np.asarray(internal["a_b"])
    else:
        shape, a_s, a_b = model.split(res.params)
    parts = ev.parts(shape)
    pts = parts.surface.shape[1] // max(sum(len(i) for i in idxs), 1)
    st = State(shape, a_s, a_b)
    if res.maps is not None or data.materials is not None:    # each cell's own pair (its pixel's, its material's)
        cell = objective.layout.groups[:, 0]
        pred = np.repeat(a_s[cell], pts) * parts.surface + np.repeat(a_b[cell], pts) * parts.body
    else:
        pred = a_s * parts.surface + a_b * parts.body  # (3, points)
    out = []
    for k, (o, idx, (a, b)) in enumerate(zip(observations, idxs, slices)):
        s = pred[:, a * pts:b * pts]
        if pts > 1 and loss == "likelihood":
            s = s.reshape(3, b - a, pts).mean(axis=2)  # the super-pixel's mean Stokes (for the summaries)
        obs_s = o.stokes.reshape(3, -1)[:, idx]
        i_obs, i_pred = obs_s[0], s[0]
        d_obs = np.hypot(obs_s[1], obs_s[2]) / np.where(i_obs > 0, i_obs, 1.0)
        d_pred = np.hypot(s[1], s[2]) / np.where(i_pred > 0, i_pred, 1.0)
        bright = i_obs > 0.02 * np.percentile(i_obs, 99)
        im = {"name": names[k], "light_dir": o.light_dir.tolist(), "irradiance": o.irradiance,
              "n_pixels": int(b - a), "pixels_excluded": excluded["per_image"][k],
              "intensity_rel_rmse": float(np.sqrt(np.mean((i_pred - i_obs) ** 2)) / np.mean(i_obs)),
              "dolp_rmse": float(np.sqrt(np.mean((d_pred - d_obs)[bright] ** 2))) if bright.any() else None}
        if loss == "likelihood":
            r = objective.residuals(parts, st)[:objective.y.size].reshape(-1, 4)[a:b]   # the samples' rows
            im["chi2"] = float(np.sum(r ** 2))
            im["chi2_per_dof"] = im["chi2"] / max((b - a) * objective.dof, 1)
        out.append(im)
    return out


ALBEDO_BOUND = O.ALBEDO_BOUND
