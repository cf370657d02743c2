"""``fit()``: estimate a model's parameters from one :class:`Observation` (paper section 5)."""
from __future__ import annotations

import dataclasses
import math
import numpy as np
import time

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.api.options import check_fit_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator, RenderEvaluator
from fmbrdf_mi.fit.inputs.observations import erode as erode_mask
from fmbrdf_mi.fit.objectives import loss as L, loss_variants as LV
from fmbrdf_mi.fit.problem.problem import FitData, TimeUp
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import optimise as O
from fmbrdf_mi.fit.uncertainty import WEAK_REL


#: Pixels whose view or light direction is within this angle (degrees) of the
#: normal are left out of the fit: the BSDF's reverse-mode derivative with
#: respect to alpha is NaN there for some alpha (see the README).
POLE_EXCLUSION_DEG = 3.0


@dataclasses.dataclass
class FitOptions:
    model: str = "fmbrdf"
    path: str = "pixel"               # "pixel" or "render"
    optimizer: str = "lm"             # "lm" or "adam"
    loss: str = "auto"                # "likelihood", "paper" or "auto" (likelihood when the camera noise is known);
                                      # "intensity" / "dolp": one term of the paper's loss (loss_variants.py)
    bounds: dict = None               # {name: (lo, hi)} narrowing the model's bounds
    fixed: dict = None                # {shape name: value} held fixed (not estimated)
    init: dict = None                 # reported parameters to start from (skips the coarse search)
    starts: int = 2                   # refine from this many of the best distinct coarse-search points
    max_iter: int = 40
    tol: float = 1e-4                 # paper's loss: relative decrease (likelihood: 0.01 in chi^2, fixed)
    time_limit: float = None          # seconds for each refinement round
    max_time: float = None            # seconds for the whole fit: a hard limit (None: until converged)
    rounds: int = 3                   # paper: inlier/outlier refresh rounds; likelihood: IRLS rounds + 2
    max_pixels: int = 20000           # random subset of the usable pixels (None: all)
    erode: int = 2                    # pixels removed from the mask's border
    min_cos_view: float = 0.1         # n . v above this
    min_cos_light: float = 0.02       # n . l above this
    dolp_min_intensity: float = 0.02  # DoLP term: observed I > this x 99th percentile
    seed: int = 0
    lr: float = 0.02                  # Adam (step in the reparameterised variables)
    spp: int = 16                     # render path
    bsdf_prefix: str = "sphere.bsdf"  # render path: traverse prefix of the object's BSDF
    free_power: bool = False          # joint fits: estimate the relative light powers (free_power.py)
    power_start: str = "ratio"        # ... starting from "ratio" (closed form) or "given"


def weakly_identified(params, std, at_bound=()):
    return U.weakly_identified(params, std, at_bound)


#: Fewest super-pixels a fit accepts.
MIN_PIXELS = 20


def select_pixels(obs, opts, use_samples=True):
    """Flat indices of the pixels a fit uses, and what was excluded (see :class:`FitOptions`).

    With raw samples (:attr:`Observation.samples`), super-pixels with a
    sample at or above the white level or at or below the dark level are
    excluded (:mod:`fmbrdf_mi.fit.camera.samples`) and counted.
    """
    m = erode_mask(obs.mask, opts.erode)
    n = obs.normals
    cos_v = np.sum(n * obs.view_dirs, axis=-1)
    cos_l = n @ obs.light_dir
    pole = math.cos(math.radians(POLE_EXCLUSION_DEG))
    m = m & (cos_v > opts.min_cos_view) & (cos_l > opts.min_cos_light) & (cos_v < pole) & (cos_l < pole)
    m &= np.all(np.isfinite(obs.stokes), axis=0)
    excluded = {"candidates": int(m.sum()), "saturated": 0, "dark": 0}
    smp = obs.samples if use_samples else None
    if smp is not None:
        excluded["saturated"] = int((m & smp.saturated).sum())
        excluded["dark"] = int((m & smp.dark & ~smp.saturated).sum())
        excluded["white_level"], excluded["dark_level"] = smp.white_level, smp.dark_level
        m &= smp.usable
    idx = np.flatnonzero(m.ravel())
    if len(idx) < MIN_PIXELS:
        why = ""
        if excluded["saturated"] or excluded["dark"]:
            why = (f" after excluding {excluded['saturated']} super-pixels with a sample at or above the white "
                   f"level {smp.white_level:g} and {excluded['dark']} with a sample at or below the dark level "
                   f"{smp.dark_level} (lower the exposure, or set --white-level / --dark-level)")
        raise InputError(f"only {len(idx)} usable pixels (mask eroded by {opts.erode}, n.v > "
                         f"{opts.min_cos_view}, n.l > {opts.min_cos_light}){why}; need at least {MIN_PIXELS}")
    if opts.max_pixels and len(idx) > opts.max_pixels:
        rng = np.random.default_rng(opts.seed)
        idx = np.sort(rng.choice(idx, opts.max_pixels, replace=False))
    excluded["used"] = int(len(idx))
    return idx, excluded


def usable_pixels(obs, opts):
    """Flat indices of the pixels a fit uses (:func:`select_pixels`)."""
    return select_pixels(obs, opts)[0]


def resolve_loss(obs, opts):
    """``auto`` -> ``likelihood`` when the camera noise is known (gain given or in a sidecar) and the fit
    runs LM on the pixel path (what the likelihood needs), else ``paper``."""
    if opts.loss == "auto":
        ok = opts.path == "pixel" and opts.optimizer == "lm"
        return "likelihood" if (ok and obs.noise is not None and obs.noise.known) else "paper"
    if opts.loss not in ("likelihood", "paper") + LV.VARIANTS:
        raise InputError(f"loss: expected 'likelihood', 'paper', 'intensity', 'dolp' or 'auto', got {opts.loss!r}")
    return opts.loss


def make_evaluator(model, obs, idx, opts, scene=None, samples=None):
    """The model evaluated at the pixels ``idx``: over their footprint, or (``samples``) at each sample's point."""
    if opts.path == "pixel":
        if samples is not None:
            off = samples.offsets
            if not np.any(off):  # all four samples at the pixel centre: evaluate once
                n, v, _ = obs.sample_geometry(idx, footprint=None)
            else:
                n, v, _ = obs.sample_geometry(idx, footprint=samples.footprint())
            return PixelEvaluator(model, n, v, obs.light_dir, obs.irradiance)
        n, v, w = obs.sample_geometry(idx)
        return PixelEvaluator(model, n, v, obs.light_dir, obs.irradiance, weights=None if len(w) == 1 else w)
    if opts.path == "render":
        if scene is None:
            raise InputError("path 'render' needs a Mitsuba scene (scene=...) containing the model's BSDF")
        ev = RenderEvaluator(model, scene, opts.bsdf_prefix, idx, spp=opts.spp, seed=opts.seed)
        if ev.shape != obs.shape:
            raise InputError(f"scene renders {ev.shape[1]}x{ev.shape[0]} pixels but the observation "
                             f"is {obs.shape[1]}x{obs.shape[0]}")
        return ev
    raise InputError(f"path: expected 'pixel' or 'render', got {opts.path!r}")


def _objective(obs, idx, opts, loss):
    """(objective, samples or None) for the pixels ``idx``."""
    from fmbrdf_mi.fit.camera import samples as SM
    from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective, PaperObjective
    from fmbrdf_mi.fit.camera.noise import NoiseModel

    if loss != "likelihood":
        var = None if obs.lin_variance is None else obs.lin_variance.ravel()[idx]
        target = L.Target.from_stokes(obs.stokes.reshape(3, -1)[:, idx], opts.dolp_min_intensity, var)
        obj = PaperObjective(target) if loss == "paper" else LV.make(loss, target)
        if obs.samples is not None and obs.samples.source == "raw mosaic" and obs.meta.get("demosaic") != "superpixel":
            # bilinear demosaicking: neighbours share raw samples (the sandwich covariance accounts for it)
            obj.grid = np.divmod(np.asarray(idx), obs.shape[1])
        return obj, None
    smp = obs.samples if obs.samples is not None else SM.from_stokes(obs.stokes)
    noise = dataclasses.replace(obs.noise) if obs.noise is not None else NoiseModel(step=smp.step)
    return LikelihoodObjective(smp.at(idx), smp.analyser(), noise, smp.dof), smp


def _distinct_starts(problem, cands, n):
    """Up to ``n`` starts: the best candidate, then the best ones differing from all chosen in a
    shape parameter other than eta and kappa (those the coarse search tuned last), preferring
    candidates with both lobes switched on."""
    material = getattr(problem.model, "base", problem.model).shape_names   # not the free light powers
    first = [k for k in problem.names if k in material and k not in ("eta", "kappa")] or list(problem.names)
    chosen = [cands[0][1]]
    pool = [c for _, c in cands[1:]]

    def off(c):  # from the coarse search's own evaluation (no new table rebuild)
        key = tuple(round(c.shape[n], 9) for n in problem.model.shape_names)
        return not problem.both_lobes.get(key, True)

    pool.sort(key=off)  # stable: keeps the score order otherwise
    for c in pool:
        if len(chosen) >= n:
            break
        if all(any(abs(c.shape[k] - o.shape[k]) > 1e-9 for k in first) for o in chosen):
            chosen.append(c)
    return chosen


def fit(obs, options=None, *, scene=None, progress=True, evaluator=None, data=None, **kw):
    """Estimate the parameters of ``options.model`` from ``obs``; returns a :class:`FitResult`.

    Keyword arguments override fields of :class:`FitOptions` (the CLI's
    options have the same names).  ``progress``: True prints to stderr, a
    callable receives each progress line, False is silent.  ``evaluator``:
    a pixel evaluator built by :func:`make_evaluator` for the same geometry,
    pixels and objective (reused across noise seeds by the benchmarks).
    ``data``: a :class:`~fmbrdf_mi.fit.problem.problem.FitData` built by
    the caller for data that are not one observation (several images of one
    object: :func:`fmbrdf_mi.fit.api.joint.fit_joint`, which builds it with
    :func:`~fmbrdf_mi.fit.api.joint.prepare`); ``obs`` is then only used for
    its noise model.

    A fit stopped by ``max_time`` (a hard wall-clock limit, checked before
    every model evaluation) returns the latest accepted estimate with
    ``converged=False`` and no standard errors.
    """
    opts = dataclasses.replace(options or FitOptions(), **kw)
    check_fit_options(**dataclasses.asdict(opts))
    if opts.optimizer not in ("lm", "adam"):
        raise ValueError(f"optimizer: expected 'lm' or 'adam', got {opts.optimizer!r}")
    if opts.path == "render" and opts.optimizer != "adam":
        raise InputError("path 'render' works with optimizer 'adam' only (reverse-mode gradient through "
                         "mi.render; its forward-mode derivatives, which 'lm' needs, miss the body term)")
    if opts.free_power and (data is None or data.make_problem is None):
        raise InputError("free_power: the relative light powers are estimated in joint fits of two or more "
                         "images (fit_joint; fmbrdf-mi fit --free-power with --manifest, --authors or several "
                         "--light)")
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
    if data is None:
        idx, excluded = select_pixels(obs, opts)
        objective, smp = _objective(obs, idx, opts, loss)
        ev = evaluator if evaluator is not None else make_evaluator(model, obs, idx, opts, scene, smp)
        data = FitData(loss, idx, excluded, objective, smp, ev)
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
        report(f"[fit] {model.name} on {len(idx)} super-pixels x 4 {smp.source} samples, likelihood; "
               f"camera noise {objective.noise.describe()}")
    history, cands, t_search = [], [], 0.0
    converged, reason, J, r, st = False, "", None, None, None
    starts_log = []
    try:
        if opts.init:
            shape, a_s, a_b = model.split(opts.init)
            starts = [problem.state(shape, a_s, a_b)]
        else:
            cands = O.coarse_search(problem)
            t_search = time.time() - t0
            history.append({"stage": "search", "iter": 0, "loss": cands[0][0], "time": t_search,
                            "params": model.report(cands[0][1].shape, cands[0][1].a_s, cands[0][1].a_b)})
            starts = _distinct_starts(problem, cands, max(1, int(opts.starts)))
        best = None
        for k, st0 in enumerate(starts):
            report(f"[fit] start {k + 1}/{len(starts)}: {O.format_state(problem, st0)}")
            saved = problem.obj.save()
            res = _refine(problem, st0, opts, t0, history, report)
            score = problem.obj.score(problem.parts(res[0]), res[0])
            starts_log.append({"start": model.report(st0.shape, st0.a_s, st0.a_b),
                               "end": model.report(res[0].shape, res[0].a_s, res[0].a_b),
                               "score": score, "converged": res[2], "reason": res[1]})
            report(f"[fit] start {k + 1} ended at score {score:.6e} ({res[1]})")
            if best is None or score < best[0]:
                best = (score, res, problem.obj.save())
            if k + 1 < len(starts):
                problem.obj.restore(saved)
        _, (st, reason, converged, J, r), state = best
        problem.obj.restore(state)
    except TimeUp:
        st = problem.current
        if st is None:
            raise InputError(f"max_time {opts.max_time:g} s: no model evaluation fits in that time") from None
        reason, converged, J, r = f"max_time {opts.max_time:g} s reached", False, None, None
    can_jac = opts.path == "pixel"
    unc = {}
    parts = None
    if converged and can_jac:
        problem.deadline = None  # the fit is done; its uncertainty is part of the answer
        parts = problem.parts(st, jac=True)
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
        n_ind = None if loss != "likelihood" else len(idx) * objective.dof
        unc = U.summarise(problem, st, J, r, n_ind)
        if unc.get("misfit"):
            report(f"[fit] warning: chi^2/dof = {unc['chi2_per_dof']:.3g} with the stated camera noise: the model "
                   "(geometry, light, BSDF) or the noise settings do not explain the data; the standard errors "
                   "are too small")
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
    weak = weakly_identified(params, std, unc.get("at_bound", ()))
    if weak:
        report(f"[fit] weakly identified (standard error > {WEAK_REL:.0%} or at a bound): {', '.join(weak)}")
    t_total = time.time() - t0
    report(f"[fit] done in {t_total:.1f} s: {loss} {value:.6e} ({reason})  {O.format_state(problem, st)}")
    n_out = int((objective.outliers & objective.target.dolp_valid).sum()) if loss != "likelihood" else 0
    return FitResult(model=model.name, params=params, loss=value, loss_terms=terms, std_errors=std,
                     history=history, stop_reason=reason, n_pixels=len(idx), n_outliers=n_out,
                     timings={"search": t_search, "total": t_total, "evaluations": problem.n_evals,
                              "nonfinite_derivative_pixels": problem.n_nonfinite},
                     options=dataclasses.asdict(opts), weakly_identified=weak, converged=bool(converged),
                     objective=loss, uncertainty=unc,
                     noise=objective.noise.to_dict() if loss == "likelihood" else None,
                     pixels_excluded=excluded, starts=starts_log, pixels=idx)


def _step_in_se(problem, st_old, st_new, J):
    """Largest |change| of z between two states in units of its standard error (from J^T J)."""
    try:
        cov = np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.inf
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return float(np.max(np.abs(problem.to_z(st_new) - problem.to_z(st_old)) / sd))


def _refine(problem, st, opts, t0, history, report):
    """Refinement rounds from ``st``: the objective's weights are refreshed between rounds until they settle.

    Paper's loss: the inlier/outlier split; likelihood: the variances from
    the model (IRLS), until a round moves the estimate by < 0.05 standard
    errors.  Returns (State, stop reason, converged, Jacobian or None, residuals or None).
    """
    obj = problem.obj
    reason, converged, J, r = "", False, None, None
    n_rounds = max(1, opts.rounds) + (2 if obj.is_likelihood else 0)
    step_se = None
    settled = False
    for rnd in range(1, n_rounds + 1):
        parts = problem.parts(st)
        saved = obj.save()
        if rnd > 1 and obj.is_likelihood and obj.settled(saved, parts, st, step_se=step_se):
            settled = True
            break
        obj.refresh(parts, st)
        if rnd > 1 and not obj.is_likelihood and obj.settled(saved, parts, st):
            obj.restore(saved)  # the weighting is settled
            settled = True
            break
        report(f"[fit] round {rnd}: {obj.describe_round()}")
        limit = opts.time_limit
        st_old = st
        if opts.optimizer == "lm":
            st, f, reason, converged, J, r = O.levenberg_marquardt(
                problem, st, max_iter=opts.max_iter, tol=opts.tol, time_limit=limit, history=history,
                round_no=rnd)
            step_se = _step_in_se(problem, st_old, st, J) if J is not None else None
        else:
            st, f, reason, converged = O.adam(problem, st, max_iter=opts.max_iter, lr=opts.lr, tol=opts.tol,
                                             time_limit=limit, history=history, round_no=rnd)
            J = r = None
        if not converged:
            break
    if obj.is_likelihood and converged and not settled:
        if step_se is not None and step_se < 0.05:
            settled = True
        else:
            converged = False
            reason = (f"IRLS weights not settled after {n_rounds} rounds (last round moved the estimate "
                      f"by {step_se:.2g} standard errors)")
    return st, reason, converged, J, r


ALBEDO_BOUND = O.ALBEDO_BOUND
