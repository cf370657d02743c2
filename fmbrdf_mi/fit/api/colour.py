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
(:class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts`): the per-channel albedo
layout (:class:`~fmbrdf_mi.fit.evaluate.albedos.ChannelAlbedos`) of the one
:class:`~fmbrdf_mi.fit.problem.problem.Problem` and of the mono fit's
likelihood (:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`:
Gaussian, Poisson-Gaussian variance, iteratively reweighted): every raw
sample, of every channel, is one independent measurement.

Unknowns: z = (shape parameters through :class:`~fmbrdf_mi.fit.evaluate.models.Bounds`,
log a_s[R, G, B], log a_b[R, G, B]).  Start: a staged grid over the shape
parameters (:func:`~fmbrdf_mi.fit.solve.optimise.staged_search`, as the mono
fit's coarse search) with each channel's two albedos in closed form
(non-negative weighted least squares of that channel's samples); then the
one Levenberg-Marquardt (:mod:`fmbrdf_mi.fit.solve.lm`) from the best
``starts`` grid points, with the shape columns of the Jacobian from
forward-mode AD and the albedo columns analytic, and the albedos re-solved
in closed form at every trial point (variable projection, :func:`_project`),
inside the one reweighting loop (:mod:`fmbrdf_mi.fit.solve.irls`).
Uncertainty: :func:`fmbrdf_mi.fit.uncertainty.summarise`, as every fit
(inverse Fisher information J^T J of the standardised residuals, in the
reported parameters ``k_s[R]`` ...; the same misfit flag and 95 % intervals).
"""
from __future__ import annotations

import math
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.camera.colour_samples import CHANNELS
from fmbrdf_mi.fit.camera.noise import NoiseModel
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.albedos import ChannelAlbedos, ChannelModel, floored
from fmbrdf_mi.fit.evaluate.models import Bounds, State, get_model
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective
from fmbrdf_mi.fit.problem.data import RAW_AREA_POINTS
from fmbrdf_mi.fit.problem.problem import Problem, TimeUp
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import lm as LM
from fmbrdf_mi.fit.solve.irls import reweighted
from fmbrdf_mi.fit.solve.optimise import search_grids, staged_search


def _project(problem, z):
    """(z with its albedos replaced by the closed-form optimum for its shape parameters, its residuals).

    Variable projection: the model is linear in the six albedos, so for
    given shape parameters their best values follow from each channel's
    non-negative least squares (:class:`~fmbrdf_mi.fit.evaluate.albedos.ChannelAlbedos`).
    Without this, a channel whose albedo the first steps drive towards 0
    stays there (the log-albedo's Jacobian column vanishes with it) and the
    fit ends at a wrong point (a 24-period sphere did, every time, before
    this).  An albedo at 0 is kept at 1e-9 of the largest so that z stays
    finite.  One model evaluation.
    """
    shape = problem.from_z(z).shape
    parts = problem.parts(State(shape, 1.0, 1.0))
    st = State(shape, *floored(*problem.obj.albedos(parts)))
    return problem.to_z(st), problem.obj.residuals(parts, st)


def _coarse(problem, say):
    """The coarse search's stages (:func:`~fmbrdf_mi.fit.solve.optimise.staged_search`) with per-channel
    closed-form albedos, ranked by chi^2.  Returns the grid points' States, best first."""
    grids, first, later, mids = search_grids(problem.model, problem.bounds, problem.fixed, problem.names)

    def evaluate(shape):
        st, parts = problem.closed_form(shape)
        return problem.loss(parts, st), st

    def on_point(key, results):
        best = min(results.values(), key=lambda x: x[0])
        st = results[key][1]
        if best is results[key] and np.all(st.a_s > 0) and np.all(st.a_b > 0):
            problem.current = st

    ranked = staged_search(problem.model.shape_names, grids, first, later, mids, evaluate,
                           shape_of=lambda st: st.shape, on_point=on_point)
    say(f"[colour] coarse search: {len(ranked)} grid points, best chi2 {ranked[0][0]:.6e}")
    return [r[1] for r in ranked]


class _Linear:
    """The colour fit's linearisation: standardised residuals, Jacobian, chi^2."""

    def __init__(self, r, J):
        self.r, self.J, self.f = r, J, float(r @ r)


def _linearise(problem, z):
    st = problem.from_z(z)
    return _Linear(*problem.residuals_and_jacobian(problem.parts(st, jac=True), st, z))


def _lm(problem, z, say, max_iter=40, tag=""):
    """Levenberg-Marquardt (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`) from ``z`` with the albedos
    projected out at every trial (:func:`_project`); returns (z, r, J, converged)."""

    def trial(z, delta, lin):
        z_new, r_new = _project(problem, np.clip(z + delta, -40, 40))
        return z_new, float(r_new @ r_new), r_new

    def on_accept(it, z, f):
        problem.current = problem.from_z(z)
        say(f"[colour{tag}] iter {it:2d}  chi2 {f:.6e}")

    z, _ = _project(problem, z)
    lin = _linearise(problem, z)
    res = LM.levenberg_marquardt(z, lin.f, lambda z: _linearise(problem, z),
                                 lambda lin, lam: LM.dense_step(lin.J, lin.r, lam), trial,
                                 max_iter=max_iter, lin=lin, refresh=1,
                                 decrement=lambda lin: LM.gn_decrement(lin.J, lin.r), on_accept=on_accept)
    return res.x, res.lin.r, res.lin.J, res.converged


def fit_colour(obs, samples, noise=None, *, model="fmbrdf", fixed=None, bounds=None, max_pixels=None, seed=0,
               irls_rounds=4, progress=None, max_time=None, max_iter=40, starts=2, area_points=RAW_AREA_POINTS):
    """Fit one material with per-channel albedos to a colour mosaic's samples (module docstring).

    ``obs``: an :class:`~fmbrdf_mi.fit.inputs.observations.Observation` whose grid is
    the mosaic's 4x4 periods (its ``stokes`` is only used for its shape),
    ``samples``: :func:`colour_samples`.  Several images of one object (a
    joint fit: each its own light, irradiance, view and geometry; one camera):
    lists of both, one entry per mosaic; they share every parameter, and
    ``max_pixels`` is split evenly between them.  ``noise``: a
    :class:`~fmbrdf_mi.fit.camera.noise.NoiseModel` (None: unknown, estimated from
    the residuals).  ``max_time``: hard wall-clock limit in seconds; a fit it
    stops returns the last accepted estimate with ``converged`` False and no
    standard errors (as does one that runs out of ``max_iter`` LM iterations).
    ``starts``: Levenberg-Marquardt runs from this many of the best grid
    points (as the one-channel fit's ``--starts``); the lowest chi^2 wins.
    ``area_points``: each raw sample is the mean of the model over this
    many points squared of its pixel (as a sensor pixel integrates; 1: its
    centre), as in the one-channel likelihood.
    Returns a :class:`~fmbrdf_mi.fit.result.FitResult`: params, std_errors
    (per-channel entries as {"R", "G", "B"} dicts; None when not converged),
    loss (chi^2), n_pixels, noise, converged, stop_reason, pixels (the fitted
    flat period indices; a list per image for lists), channels, and in
    ``details`` (read as ``res["key"]``): chi2, chi2_per_dof, n_samples,
    evaluations, time_s, chi2_per_sample (chi^2 / samples, per image for
    lists), internal (shape and unit albedos for :func:`predict_samples`).
    """

    say = progress or (lambda m: None)
    t0 = time.time()
    m = get_model(model)
    joint = isinstance(obs, (list, tuple))
    obs_l, smp_l = (list(obs), list(samples)) if joint else ([obs], [samples])
    if len(obs_l) != len(smp_l) or not obs_l:
        raise InputError(f"colour fit: {len(obs_l)} geometries for {len(smp_l)} mosaics; give one per mosaic")
    idxs, geo, ys = [], [], []
    per_image = None if not max_pixels else max(1, int(math.ceil(max_pixels / len(obs_l))))
    for k, (o, smp) in enumerate(zip(obs_l, smp_l)):
        tag = f"colour fit, image {k}" if joint else "colour fit"
        if smp.values.shape[1:] != o.mask.shape:
            raise InputError(f"{tag}: the mosaic has {smp.values.shape[2]}x{smp.values.shape[1]} periods, "
                             f"the geometry {o.mask.shape[1]}x{o.mask.shape[0]} pixels; they must agree")
        if k and (smp.angles != smp_l[0].angles or not np.array_equal(smp.channel, smp_l[0].channel)):
            raise InputError(f"{tag}: its polariser layout or colour filter differs from image 0's; a joint fit "
                             "takes one camera")
        idx = np.flatnonzero((o.mask & smp.usable).ravel())
        if per_image and len(idx) > per_image:
            idx = np.sort(np.random.default_rng(seed + k).choice(idx, per_image, replace=False))
        if len(idx) < 4:
            raise InputError(f"{tag}: only {len(idx)} usable periods inside the mask (need >= 4)")
        n, v, w = o.sample_geometry(idx, footprint=smp.footprint(area_points))
        geo.append((n, v, np.tile(np.asarray(o.light_dir, float), (len(n), 1)), np.full(len(n), o.irradiance)))
        ys.append(smp.values.reshape(16, -1)[:, idx].T)
        idxs.append(idx)
    n, v, lights, irr = (np.concatenate([g[j] for g in geo]) for j in range(4))
    ev = PixelEvaluator(m, n, v, lights if joint else obs_l[0].light_dir,
                        irr if joint else obs_l[0].irradiance, weights=None if len(w) == 1 else w)
    y = np.concatenate(ys)
    samples = smp_l[0]
    noise = noise if noise is not None else NoiseModel(step=1.0)
    layout = ChannelAlbedos(samples.channel)
    objective = LikelihoodObjective(y, samples.analyser(), noise, dof=samples.n, layout=layout)
    problem = Problem(ChannelModel(m, layout), ev, objective, Bounds(m, bounds), say, fixed=fixed,
                      deadline=None if max_time is None else t0 + float(max_time))
    converged, stop = False, "iteration limit"
    r = J = None
    try:
        cands = _coarse(problem, say)
        z = problem.to_z(State(cands[0].shape, *floored(cands[0].a_s, cands[0].a_b)))
        problem.current = problem.from_z(z)
        last = {}

        def minimise(z, k):
            last["z_old"] = z.copy()
            if k == 0:      # LM from the best `starts` grid points; the lowest chi2 goes on
                ends = [_lm(problem, problem.to_z(State(c.shape, *floored(c.a_s, c.a_b))), say,
                            max_iter=max_iter, tag=f" {k}.{j}")
                        for j, c in enumerate(cands[:max(1, int(starts))])]
                z, _, _, converged = min(ends, key=lambda e: float(e[1] @ e[1]))
            else:
                z, _, _, converged = _lm(problem, z, say, max_iter=max_iter, tag=f" {k}")
            return z, converged

        def after(z, k):    # variances (and an unknown noise model) from the fit; settled: a step < 0.05 SE
            st = problem.from_z(z)
            objective.refresh(problem.parts(st), st)
            lin = _linearise(problem, z)
            last["r"], last["J"] = lin.r, lin.J
            cov_z = np.linalg.pinv(lin.J.T @ lin.J)
            step = np.abs(z - last["z_old"]) / np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
            return k > 0 and float(np.max(step)) < 0.05

        z, converged, _, _ = reweighted(z, minimise, rounds=irls_rounds, after=after, stop_unconverged=False)
        r, J = last["r"], last["J"]
        stop = "converged" if converged else f"iteration limit ({max_iter} LM iterations)"
    except TimeUp:
        converged, stop = False, f"time limit (max_time {float(max_time):g} s)"
        if problem.current is None:
            raise InputError(f"max_time {float(max_time):g} s: no model evaluation fits in that time") from None
        z = problem.to_z(problem.current)
        problem.deadline = None
        r = problem.obj.residuals(problem.parts(problem.current), problem.current)
    st = problem.from_z(z)
    flat = problem.model.report(st.shape, st.a_s, st.a_b)
    params = problem.model.nest(flat)
    std, unc = None, {"std_errors": {}, "method": "not computed: the fit did not converge"}
    if converged:
        unc = U.summarise(problem, st, J, r, len(y) * samples.n)
        std = {n: None for n in m.shape_names}
        std.update(problem.model.nest(unc["std_errors"]))
        unc["ci95"] = problem.model.nest(unc["ci95"])
        if unc.get("misfit"):
            say("[colour] warning: " + U.misfit_text(unc))
    chi2 = float(r @ r)
    dof = max(r.size - len(z), 1)
    bounds_k = np.cumsum([0] + [len(i) for i in idxs])
    rr = r.reshape(len(y), -1)
    per_chi2 = [float(np.sum(rr[a:b] ** 2) / max((b - a) * rr.shape[1], 1)) for a, b in zip(bounds_k, bounds_k[1:])]
    t_total = time.time() - t0
    weak = U.weakly_identified(flat, unc["std_errors"], unc.get("at_bound", ())) if converged else []
    out = FitResult(model=m.name, params=params, loss=chi2, loss_terms={"chi2": chi2, "samples": int(r.size)},
                    std_errors=std, history=[], stop_reason=stop, n_pixels=int(sum(len(i) for i in idxs)),
                    n_outliers=0, timings={"total": t_total, "evaluations": problem.n_evals},
                    options={"model": model, "fixed": fixed, "bounds": bounds, "max_pixels": max_pixels, "seed": seed,
                             "irls_rounds": irls_rounds, "max_time": max_time, "max_iter": max_iter,
                             "starts": starts, "area_points": int(area_points)},
                    weakly_identified=weak, converged=bool(converged), objective="likelihood", uncertainty=unc,
                    noise=noise.to_dict(), pixels=idxs if joint else idxs[0], channels=list(CHANNELS),
                    details={"chi2": chi2, "chi2_per_dof": chi2 / dof, "n_samples": int(r.size),
                             "evaluations": problem.n_evals, "time_s": t_total,
                             "chi2_per_sample": per_chi2 if joint else per_chi2[0],
                             "internal": {"shape": {k: float(x) for k, x in st.shape.items()},
                                          "a_s": st.a_s.tolist(), "a_b": st.a_b.tolist()}})
    if std is not None:
        say("[colour] " + format_result(out))
    return out


def predict_samples(obs, samples, res):
    """The fitted model's 16 samples (16, H, W) per period (image units, NaN outside mask & usable)."""

    m = get_model(res["model"])
    idx = np.flatnonzero((obs.mask & samples.usable).ravel())
    out = np.full(samples.values.shape, np.nan)
    if len(idx) == 0:
        return out
    n, v, w = obs.sample_geometry(idx, footprint=samples.footprint((res.options or {}).get("area_points", 1)))
    p = PixelEvaluator(m, n, v, obs.light_dir, obs.irradiance,
                       weights=None if len(w) == 1 else w).parts(res["internal"]["shape"], ())
    A, n = samples.analyser(), len(idx)
    unit = [np.einsum("kc,cik->ik", A, s.reshape(3, n, -1)) for s in (p.surface, p.body)]
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
