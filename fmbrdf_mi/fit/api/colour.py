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
(:class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts`), and the likelihood is that of
:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective` (Gaussian,
Poisson-Gaussian variance, iteratively reweighted): every raw sample, of
every channel, is one independent measurement.

Unknowns: z = (shape parameters through :class:`~fmbrdf_mi.fit.evaluate.models.Bounds`,
log a_s[R, G, B], log a_b[R, G, B]).  Start: a staged grid over the shape
parameters (as :func:`~fmbrdf_mi.fit.solve.optimise.coarse_search`) with each
channel's two albedos in closed form (non-negative weighted least squares of
that channel's samples); then Levenberg-Marquardt from the best ``starts``
grid points, with the shape columns of the Jacobian from forward-mode AD and
the albedo columns analytic, and the albedos re-solved in closed form at
every trial point (variable projection, :meth:`_Colour.project`).  Standard
errors: (J^T J)^-1 of the standardised residuals at the optimum (the Fisher
information), mapped to the reported parameters by the delta method.
"""
from __future__ import annotations

import math
import time

import numpy as np

from fmbrdf_mi.fit.camera.colour_samples import CHANNELS
from fmbrdf_mi.fit.camera.noise import NoiseModel
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import Bounds, get_model
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.objectives.objective import nnls2
from fmbrdf_mi.fit.problem.data import RAW_AREA_POINTS
from fmbrdf_mi.fit.problem.problem import TimeUp
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import lm as LM
from fmbrdf_mi.fit.solve.irls import reweighted
from fmbrdf_mi.fit.solve.optimise import search_grids, staged_search


def _unit_mu(A, stokes, n):
    """(n, 16) intensities behind each sample's polariser of a (3, 16 n) pixel-major Stokes array."""
    return np.einsum("kc,cik->ik", A, stokes.reshape(3, n, -1))


def _floored(a_s, a_b):
    """The albedos with those at 0 raised to 1e-9 of the largest (so that their logs stay finite)."""
    floor = 1e-9 * max(float(np.max(a_s)), float(np.max(a_b)), 1e-300)
    return np.maximum(a_s, floor), np.maximum(a_b, floor)


class _Colour:
    def __init__(self, model, ev, y, A, chan, noise, fixed=None, bounds=None):
        self.model, self.ev, self.y, self.A, self.chan, self.noise = model, ev, y, A, chan, noise
        self.n = len(y)
        self.fixed = dict(fixed or {})
        self.names = tuple(p for p in model.shape_names if p not in self.fixed)
        self.bounds = Bounds(model, bounds)
        self.var = np.maximum(noise.variance(y), 1e-300)
        self.masks = [chan == c for c in range(3)]
        self.evals = 0
        self.deadline = None     # time.time() past which parts() raises TimeUp (once self.last is set)
        self.last = None         # z of the best estimate so far (coarse point or accepted LM step)

    def parts(self, shape, jac=False):
        if self.deadline is not None and self.last is not None and time.time() > self.deadline:
            raise TimeUp()
        self.evals += 1
        return self.ev.parts(shape, self.names if jac else ())

    def mu(self, p, a_s, a_b):
        S, B = _unit_mu(self.A, p.surface, self.n), _unit_mu(self.A, p.body, self.n)
        return a_s[self.chan] * S + a_b[self.chan] * B

    def albedos(self, p):
        S, B = _unit_mu(self.A, p.surface, self.n), _unit_mu(self.A, p.body, self.n)
        out = [nnls2(S[:, m].ravel(), B[:, m].ravel(), self.y[:, m].ravel(), 1.0 / self.var[:, m].ravel())
               for m in self.masks]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    def project(self, z):
        """(z with its albedos replaced by the closed-form optimum for its shape parameters, its residuals).

        Variable projection: the model is linear in the six albedos, so for
        given shape parameters their best values follow from each channel's
        non-negative least squares.  Without this, a channel whose albedo
        the first steps drive towards 0 stays there (the log-albedo's
        Jacobian column vanishes with it) and the fit ends at a wrong point
        (a 24-period sphere did, every time, before this).  An albedo at 0 is
        kept at 1e-9 of the largest so that z stays finite.  One model
        evaluation.
        """
        shape, _, _ = self.from_z(z)
        p = self.parts(shape)
        a_s, a_b = self.albedos(p)
        a_s, a_b = _floored(a_s, a_b)
        return self.to_z(shape, a_s, a_b), ((self.y - self.mu(p, a_s, a_b)) / np.sqrt(self.var)).ravel()

    def floored_z(self, shape, a_s, a_b):
        """z of (shape, a_s, a_b) with albedos at 0 raised to 1e-9 of the largest (z stays finite)."""
        return self.to_z(shape, *_floored(a_s, a_b))

    def chi2(self, p, a_s, a_b):
        r = (self.y - self.mu(p, a_s, a_b)) / np.sqrt(self.var)
        return float(np.sum(r * r))

    # z <-> (shape, a_s, a_b)
    def to_z(self, shape, a_s, a_b):
        return np.array([self.bounds.to_z(n, shape[n]) for n in self.names] + list(np.log(a_s)) + list(np.log(a_b)))

    def from_z(self, z):
        shape = dict(self.fixed)
        shape.update({n: self.bounds.to_value(n, z[i]) for i, n in enumerate(self.names)})
        k = len(self.names)
        return ({n: shape[n] for n in self.model.shape_names}, np.exp(np.clip(z[k:k + 3], -60, 60)),
                np.exp(np.clip(z[k + 3:k + 6], -60, 60)))

    def residuals(self, z):
        shape, a_s, a_b = self.from_z(z)
        return ((self.y - self.mu(self.parts(shape), a_s, a_b)) / np.sqrt(self.var)).ravel()

    def jacobian(self, z):
        shape, a_s, a_b = self.from_z(z)
        p = self.parts(shape, jac=True)
        sd = np.sqrt(self.var)
        r = ((self.y - self.mu(p, a_s, a_b)) / sd).ravel()
        J = np.empty((r.size, len(z)))
        for j, n in enumerate(self.names):
            dmu = (a_s[self.chan] * _unit_mu(self.A, p.d_surface[n], self.n)
                   + a_b[self.chan] * _unit_mu(self.A, p.d_body[n], self.n))
            J[:, j] = (-dmu / sd).ravel() * self.bounds.derivative(n, z[j])
        k = len(self.names)
        S, B = _unit_mu(self.A, p.surface, self.n), _unit_mu(self.A, p.body, self.n)
        for c, m in enumerate(self.masks):
            J[:, k + c] = (-(a_s[c] * S * m) / sd).ravel()
            J[:, k + 3 + c] = (-(a_b[c] * B * m) / sd).ravel()
        J[~np.isfinite(J)] = 0.0
        return r, J


def _coarse(prob, say):
    """The coarse search's stages (:func:`~fmbrdf_mi.fit.solve.optimise.staged_search`) with per-channel
    closed-form albedos.  Returns the grid points [(shape, a_s, a_b)], best first."""
    model = prob.model
    grids, first, later, mids = search_grids(model, prob.bounds, prob.fixed, prob.names)

    def evaluate(shape):
        p = prob.parts(shape)
        a_s, a_b = prob.albedos(p)
        return prob.chi2(p, a_s, a_b), (dict(shape), a_s, a_b)

    def on_point(key, results):
        best = min(results.values(), key=lambda x: x[0])
        shape, a_s, a_b = results[key][1]
        if best is results[key] and np.all(a_s > 0) and np.all(a_b > 0):
            prob.last = prob.to_z(shape, a_s, a_b)

    ranked = staged_search(model.shape_names, grids, first, later, mids, evaluate, shape_of=lambda pt: pt[0],
                           on_point=on_point)
    say(f"[colour] coarse search: {len(ranked)} grid points, best chi2 {ranked[0][0]:.6e}")
    return [r[1] for r in ranked]


class _Linear:
    """The colour fit's linearisation: standardised residuals, Jacobian, chi^2."""

    def __init__(self, r, J):
        self.r, self.J, self.f = r, J, float(r @ r)


def _lm(prob, z, say, max_iter=40, tag=""):
    """Levenberg-Marquardt (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`) from ``z`` with the albedos
    projected out at every trial (:meth:`_Colour.project`); returns (z, r, J, converged)."""

    def linearise(z):
        return _Linear(*prob.jacobian(z))

    def trial(z, delta, lin):
        z_new, r_new = prob.project(np.clip(z + delta, -40, 40))
        return z_new, float(r_new @ r_new), r_new

    def on_accept(it, z, f):
        prob.last = z
        say(f"[colour{tag}] iter {it:2d}  chi2 {f:.6e}")

    z, _ = prob.project(z)
    lin = linearise(z)
    res = LM.levenberg_marquardt(z, lin.f, linearise, lambda lin, lam: LM.dense_step(lin.J, lin.r, lam), trial,
                                 max_iter=max_iter, lin=lin, refresh=1,
                                 decrement=lambda lin: LM.gn_decrement(lin.J, lin.r), on_accept=on_accept)
    return res.x, res.lin.r, res.lin.J, res.converged


def report(model, shape, a_s, a_b):
    """Reported parameters: the shape values, and k_s and r_k (fmbrdf; else the model's albedo names) per channel."""
    out = {n: float(shape[n]) for n in model.shape_names}
    per = [model.report(shape, a_s[c], a_b[c]) for c in range(3)]
    for key in per[0]:
        if key not in model.shape_names:
            out[key] = {CHANNELS[c]: per[c][key] for c in range(3)}
    return out


def _reported_jacobian(prob, z):
    """d(reported, flat) / dz: rows eta.. (free shape), then per albedo name per channel."""
    shape, a_s, a_b = prob.from_z(z)
    k = len(prob.names)
    rows, labels = [], []
    for j, n in enumerate(prob.names):
        row = np.zeros(len(z))
        row[j] = prob.bounds.derivative(n, z[j])
        rows.append(row)
        labels.append((n, None))
    f = prob.model.albedo_factor
    sn, bn = ("k_s", "r_k") if prob.model.name == "fmbrdf" else (prob.model.surface_name, prob.model.body_name)
    for c in range(3):
        row = np.zeros(len(z))
        row[k + c] = f * a_s[c]              # d k_s / d log a_s
        rows.append(row)
        labels.append((sn, CHANNELS[c]))
    for c in range(3):
        row = np.zeros(len(z))
        if prob.model.name == "fmbrdf":      # r_k = a_b / a_s
            rk = a_b[c] / a_s[c]
            row[k + c], row[k + 3 + c] = -rk, rk
        else:
            row[k + 3 + c] = f * a_b[c]
        rows.append(row)
        labels.append((bn, CHANNELS[c]))
    return np.array(rows), labels


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
    known = noise is not None and noise.known
    noise = noise if noise is not None else NoiseModel(step=1.0)
    prob = _Colour(m, ev, y, samples.analyser(), samples.channel, noise, fixed, bounds)
    if max_time is not None:
        prob.deadline = t0 + float(max_time)
    converged, stop = False, "iteration limit"
    r = None
    try:
        cands = _coarse(prob, say)
        z = prob.floored_z(*cands[0])      # the grid's albedos are already the closed-form ones
        prob.last = z
        last = {}

        def minimise(z, k):
            last["z_old"] = z.copy()
            if k == 0:      # LM from the best `starts` grid points; the lowest chi2 goes on
                ends = [_lm(prob, prob.floored_z(*c), say, max_iter=max_iter, tag=f" {k}.{j}")
                        for j, c in enumerate(cands[:max(1, int(starts))])]
                z, _, _, converged = min(ends, key=lambda e: float(e[1] @ e[1]))
            else:
                z, _, _, converged = _lm(prob, z, say, max_iter=max_iter, tag=f" {k}")
            return z, converged

        def after(z, k):    # variances (and an unknown noise model) from the fit; settled: a step < 0.05 SE
            shape, a_s, a_b = prob.from_z(z)
            mu = prob.mu(prob.parts(shape), a_s, a_b)
            if not known:
                noise.estimate(mu, (y - mu) ** 2)
            prob.var = np.maximum(noise.variance(mu), 1e-300)
            last["r"], last["J"] = prob.jacobian(z)
            last["cov_z"] = np.linalg.pinv(last["J"].T @ last["J"])
            step = np.abs(z - last["z_old"]) / np.sqrt(np.maximum(np.diag(last["cov_z"]), 1e-300))
            return k > 0 and float(np.max(step)) < 0.05

        z, converged, _, _ = reweighted(z, minimise, rounds=irls_rounds, after=after, stop_unconverged=False)
        r, cov_z = last["r"], last["cov_z"]
        stop = "converged" if converged else f"iteration limit ({max_iter} LM iterations)"
    except TimeUp:
        converged, stop = False, f"time limit (max_time {float(max_time):g} s)"
        z = prob.last
        prob.deadline = None
        r = prob.residuals(z)
    shape, a_s, a_b = prob.from_z(z)
    params = report(m, shape, a_s, a_b)
    std = None
    if converged:
        D, labels = _reported_jacobian(prob, z)
        cov = D @ cov_z @ D.T
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        std = {n: None for n in m.shape_names}
        for (name, ch), s in zip(labels, se):
            if ch is None:
                std[name] = float(s)
            else:
                std.setdefault(name, {})[ch] = float(s)
    chi2 = float(r @ r)
    dof = max(r.size - len(z), 1)
    bounds_k = np.cumsum([0] + [len(i) for i in idxs])
    rr = r.reshape(len(y), -1)
    per_chi2 = [float(np.sum(rr[a:b] ** 2) / max((b - a) * rr.shape[1], 1)) for a, b in zip(bounds_k, bounds_k[1:])]
    t_total = time.time() - t0
    out = FitResult(model=m.name, params=params, loss=chi2, loss_terms={"chi2": chi2, "samples": int(r.size)},
                    std_errors=std, history=[], stop_reason=stop, n_pixels=int(sum(len(i) for i in idxs)),
                    n_outliers=0, timings={"total": t_total, "evaluations": prob.evals},
                    options={"model": model, "fixed": fixed, "bounds": bounds, "max_pixels": max_pixels, "seed": seed,
                             "irls_rounds": irls_rounds, "max_time": max_time, "max_iter": max_iter,
                             "starts": starts, "area_points": int(area_points)},
                    converged=bool(converged), objective="likelihood", noise=noise.to_dict(),
                    pixels=idxs if joint else idxs[0], channels=list(CHANNELS),
                    details={"chi2": chi2, "chi2_per_dof": chi2 / dof, "n_samples": int(r.size),
                             "evaluations": prob.evals, "time_s": t_total,
                             "chi2_per_sample": per_chi2 if joint else per_chi2[0],
                             "internal": {"shape": {k: float(x) for k, x in shape.items()}, "a_s": a_s.tolist(),
                                          "a_b": a_b.tolist()}})
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
    A, chan = samples.analyser(), samples.channel
    a_s, a_b = np.asarray(res["internal"]["a_s"]), np.asarray(res["internal"]["a_b"])
    mu = a_s[chan] * _unit_mu(A, p.surface, len(idx)) + a_b[chan] * _unit_mu(A, p.body, len(idx))
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
