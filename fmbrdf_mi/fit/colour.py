"""Fits to colour polarisation mosaics (IMX250MYR type): shared eta, alpha, beta, kappa, per-channel albedos.

    smp = colour_samples(raw, camera)                     # 16 raw samples per 4x4 period
    res = fit_colour(obs, smp, noise)                     # obs: geometry on the period grid
    res["params"]["k_s"]   # {"R": ..., "G": ..., "B": ...}; res["std_errors"] likewise

The colour filter changes how much light reaches a pixel, not the geometry
of reflection: FMBRDF's shape parameters (eta, alpha, beta, kappa; paper
eq:fmbrdf) are one material's, while its two albedos k_s and k_b = r_k k_s
are per colour channel.  The model of raw sample k (colour c_k, polariser
phi_k, at its own point in the 4x4 period) is

    mu_ik = 1/2 (1, cos 2 phi_k, sin 2 phi_k) . (a_s[c_k] S_ik + a_b[c_k] B_ik)

with S, B the unit-albedo surface and body Stokes vectors
(:class:`~fmbrdf_mi.fit.pixel_model.Parts`), and the likelihood is that of
:class:`~fmbrdf_mi.fit.objective.LikelihoodObjective` (Gaussian,
Poisson-Gaussian variance, iteratively reweighted): every raw sample, of
every channel, is one independent measurement.

Unknowns: z = (shape parameters through :class:`~fmbrdf_mi.fit.models.Bounds`,
log a_s[R, G, B], log a_b[R, G, B]).  Start: a staged grid over the shape
parameters (as :func:`~fmbrdf_mi.fit.optimise.coarse_search`) with each
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

from .. import polcam
from .models import Bounds, get_model
from .objective import NoiseModel, nnls2
from .observations import InputError
from .optimise import search_grids

CHANNELS = polcam.COLOURS


class _TimeUp(Exception):
    """The fit's wall-clock limit passed (raised from the model evaluation once an estimate exists)."""


class ColourSamples:
    """The 16 raw samples of each 4x4 period: values (16, H, W) image units, channel, angle, offset per sample."""

    def __init__(self, values, channel, angles, offsets, usable):
        self.values, self.channel, self.angles = values, np.asarray(channel), tuple(angles)
        self.offsets, self.usable = np.asarray(offsets, float), usable

    def analyser(self):
        t = np.radians(np.asarray(self.angles, dtype=np.float64))
        return 0.5 * np.stack([np.ones_like(t), np.cos(2 * t), np.sin(2 * t)], axis=1)


def colour_samples(raw, layout=polcam.IMX250MZR_LAYOUT, cfa=polcam.BAYER_RGGB, black_level=0.0,
                   white_level=None):
    """:class:`ColourSamples` of a raw colour mosaic (4H, 4W) in DN; a period with a clipped sample is unusable."""
    from ..camera import default_white_level

    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 4 or raw.shape[1] % 4:
        raise InputError(f"raw colour mosaic: expected a 2-D image with height and width multiples of 4, "
                         f"got {raw.shape}")
    white = default_white_level(raw) if white_level is None else float(white_level)
    r = raw.astype(np.float64)
    vals, chans, angles, offs = [], [], [], []
    for cr, cc, ch in polcam.colour_cells(cfa):
        for dr in range(2):
            for dc in range(2):
                R, C = 2 * cr + dr, 2 * cc + dc
                vals.append(r[R::4, C::4])
                chans.append(ch)
                angles.append(layout[dr][dc])
                offs.append(((C + 0.5) / 4 - 0.5, (R + 0.5) / 4 - 0.5))   # (dx right, dy down) in periods
    v = np.stack(vals)
    usable = ~np.any(v >= white, axis=0)
    if float(black_level) == 0:
        usable &= ~np.any(v <= 0, axis=0)
    return ColourSamples(v - float(black_level), chans, angles, offs, usable)


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
        self.deadline = None     # time.time() past which parts() raises _TimeUp (once self.last is set)
        self.last = None         # z of the best estimate so far (coarse point or accepted LM step)

    def parts(self, shape, jac=False):
        if self.deadline is not None and self.last is not None and time.time() > self.deadline:
            raise _TimeUp()
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
    """Staged grid (optimise.coarse_search's stages) with per-channel closed-form albedos.

    Returns the grid points [(shape, a_s, a_b)], best first."""
    model = prob.model
    grids, first, later, mids = search_grids(model, prob.bounds, prob.fixed, prob.names)
    results = {}

    def try_point(shape):
        key = tuple(round(shape[n], 9) for n in model.shape_names)
        if key not in results:
            p = prob.parts(shape)
            a_s, a_b = prob.albedos(p)
            results[key] = (prob.chi2(p, a_s, a_b), dict(shape), a_s, a_b)
            best = min(results.values(), key=lambda x: x[0])
            if best is results[key] and np.all(a_s > 0) and np.all(a_b > 0):
                prob.last = prob.to_z(shape, a_s, a_b)

    import itertools
    for combo in itertools.product(*[grids[n] for n in first]):
        try_point({**mids, **dict(zip(first, combo))})
    for name in later:
        for _, shape, _, _ in sorted(results.values(), key=lambda x: x[0])[:2]:
            for value in grids[name]:
                try_point({**shape, name: value})
    ranked = sorted(results.values(), key=lambda x: x[0])
    say(f"[colour] coarse search: {len(results)} grid points, best chi2 {ranked[0][0]:.6e}")
    return [r[1:] for r in ranked]


def _lm(prob, z, say, max_iter=40, tag=""):
    """Levenberg-Marquardt from ``z`` with the albedos projected out at every trial (:meth:`_Colour.project`);
    returns (z, r, J, converged)."""
    z, _ = prob.project(z)
    r, J = prob.jacobian(z)
    f = float(r @ r)
    lam = 1e-3
    converged = False
    for it in range(1, max_iter + 1):
        g = J.T @ r
        A = J.T @ J
        try:
            dec = float(g @ np.linalg.lstsq(A, g, rcond=None)[0])
        except np.linalg.LinAlgError:
            dec = math.inf
        if dec < 0.01:  # optimum within ~0.1 standard error (optimise.DECREMENT_TOL)
            converged = True
            break
        D = np.diag(A).copy()
        D[D <= 0] = 1e-12
        while lam < 1e10:
            z_new, r_new = prob.project(np.clip(z + np.linalg.solve(A + lam * np.diag(D), -g), -40, 40))
            f_new = float(r_new @ r_new)
            if np.isfinite(f_new) and f_new < f:
                break
            lam *= 4
        else:
            converged = True     # no step lowers chi2 at any damping: a minimum to rounding
            break
        z, lam = z_new, max(lam / 3, 1e-9)
        prob.last = z
        r, J = prob.jacobian(z)
        f = float(r @ r)
        say(f"[colour{tag}] iter {it:2d}  chi2 {f:.6e}")
    return z, r, J, converged


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
               irls_rounds=4, progress=None, max_time=None, max_iter=40, starts=2):
    """Fit one material with per-channel albedos to a colour mosaic's samples (module docstring).

    ``obs``: an :class:`~fmbrdf_mi.fit.observations.Observation` whose grid is
    the mosaic's 4x4 periods (its ``stokes`` is only used for its shape),
    ``samples``: :func:`colour_samples`.  Several images of one object (a
    joint fit: each its own light, irradiance, view and geometry; one camera):
    lists of both, one entry per mosaic; they share every parameter, and
    ``max_pixels`` is split evenly between them.  ``noise``: a
    :class:`~fmbrdf_mi.fit.objective.NoiseModel` (None: unknown, estimated from
    the residuals).  ``max_time``: hard wall-clock limit in seconds; a fit it
    stops returns the last accepted estimate with ``converged`` False and no
    standard errors (as does one that runs out of ``max_iter`` LM iterations).
    ``starts``: Levenberg-Marquardt runs from this many of the best grid
    points (as the one-channel fit's ``--starts``); the lowest chi^2 wins.
    Returns a dict: params, std_errors (per-channel entries as {"R", "G", "B"}
    dicts; None when not converged), chi2_per_dof, n_pixels, noise, time_s,
    converged, stop_reason, pixels (the fitted flat period indices; a list
    per image for lists), chi2_per_sample (chi^2 / samples, per image for
    lists), internal (shape and unit albedos for :func:`predict_samples`).
    """
    from .pixel_model import PixelEvaluator

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
        n, v, _ = o.sample_geometry(idx, footprint=(smp.offsets, np.full(16, 1 / 16)))
        geo.append((n, v, np.tile(np.asarray(o.light_dir, float), (len(n), 1)), np.full(len(n), o.irradiance)))
        ys.append(smp.values.reshape(16, -1)[:, idx].T)
        idxs.append(idx)
    n, v, lights, irr = (np.concatenate([g[j] for g in geo]) for j in range(4))
    ev = PixelEvaluator(m, n, v, lights if joint else obs_l[0].light_dir,
                        irr if joint else obs_l[0].irradiance)
    y = np.concatenate(ys)
    samples = smp_l[0]
    known = noise is not None and noise.known
    noise = noise if noise is not None else NoiseModel(step=1.0)
    prob = _Colour(m, ev, y, samples.analyser(), samples.channel, noise, fixed, bounds)
    if max_time is not None:
        prob.deadline = t0 + float(max_time)
    converged, stop = False, "iteration limit"
    r = J = None
    try:
        cands = _coarse(prob, say)
        z = prob.floored_z(*cands[0])      # the grid's albedos are already the closed-form ones
        prob.last = z
        for rnd in range(irls_rounds):
            z_old = z.copy()
            if rnd == 0:      # LM from the best `starts` grid points; the lowest chi2 goes on
                ends = [_lm(prob, prob.floored_z(*c), say, max_iter=max_iter, tag=f" {rnd}.{j}")
                        for j, c in enumerate(cands[:max(1, int(starts))])]
                z, r, J, converged = min(ends, key=lambda e: float(e[1] @ e[1]))
            else:
                z, r, J, converged = _lm(prob, z, say, max_iter=max_iter, tag=f" {rnd}")
            shape, a_s, a_b = prob.from_z(z)
            mu = prob.mu(prob.parts(shape), a_s, a_b)
            if not known:
                noise.estimate(mu, (y - mu) ** 2)
            prob.var = np.maximum(noise.variance(mu), 1e-300)
            r, J = prob.jacobian(z)
            cov_z = np.linalg.pinv(J.T @ J)
            step = np.abs(z - z_old) / np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
            if rnd > 0 and float(np.max(step)) < 0.05:
                break
        stop = "converged" if converged else f"iteration limit ({max_iter} LM iterations)"
    except _TimeUp:
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
    out = {"model": m.name, "params": params, "std_errors": std, "chi2": chi2, "chi2_per_dof": chi2 / dof,
           "n_pixels": int(sum(len(i) for i in idxs)), "n_samples": int(r.size), "noise": noise.to_dict(),
           "evaluations": prob.evals, "time_s": time.time() - t0, "channels": list(CHANNELS),
           "converged": bool(converged), "stop_reason": stop, "pixels": idxs if joint else idxs[0],
           "chi2_per_sample": per_chi2 if joint else per_chi2[0],
           "internal": {"shape": {k: float(x) for k, x in shape.items()}, "a_s": a_s.tolist(),
                        "a_b": a_b.tolist()}}
    if std is not None:
        say("[colour] " + format_result(out))
    return out


def predict_samples(obs, samples, res):
    """The fitted model's 16 samples (16, H, W) per period (image units, NaN outside mask & usable)."""
    from .pixel_model import PixelEvaluator

    m = get_model(res["model"])
    idx = np.flatnonzero((obs.mask & samples.usable).ravel())
    out = np.full(samples.values.shape, np.nan)
    if len(idx) == 0:
        return out
    n, v, _ = obs.sample_geometry(idx, footprint=(samples.offsets, np.full(16, 1 / 16)))
    p = PixelEvaluator(m, n, v, obs.light_dir, obs.irradiance).parts(res["internal"]["shape"], ())
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
