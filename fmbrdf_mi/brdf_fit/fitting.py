"""Fitting FMBRDF to a measured BRDF: shared eta, alpha, beta, kappa; per-channel k_s, k_b.

The error is the authors' (their released ``MERL_fitting.py``): the RMS over
samples and channels of log10(f_model + eps) - log10(f_measured + eps), so
that the specular peak (values up to ~1e4 1/sr) does not outweigh the body
reflection (~0.01-1).  Samples: every bin measured in all three channels with
both directions above the horizon (cos > ``min_cos``), except those within
arccos(0.9999) (0.81 deg) of the specular peak in theta_h, the authors' cut
(the first 9 theta_h bins, where the finite size of the light source and the
sensor dominate what was measured); a seeded random subset of
``max_samples`` of them is fitted, and the error is also reported over all.

Procedure:

1. start grid (the authors'): eta in {1.2, ..., 1.9}, alpha log-spaced from
   0.01 rad to the upper bound, beta log-spaced in [0.5, 4], kappa 0; at each
   point the per-channel albedos minimise the relative squared error
   sum ((k_s S + k_b B) / f - 1)^2, k_s, k_b >= 0 (closed form; the authors
   grid them instead), and the grid points are ranked by the log error.
   Searched coarse to fine by default (:func:`grid_search`: every other
   index, then the neighbourhoods of the best points until they are all
   evaluated; 130-150 of the 320 points, and the same best three as the full
   grid on the 16 synthetic cases tried, docs/benchmarks.md); each point is
   one table build (values.py: unpolarised tables) and one evaluation of all
   samples at once;
   for the ``starts`` best, kappa is then scanned over ``kappa_scan`` (the
   image fits' coarse search does the same; a start at kappa = 0 sits where
   the bounded reparameterisation is flat, and from there the refinement was
   seen to run to the bound kappa = 100 and stop at a log error of 0.045 on
   data made with kappa = 15);
2. from the ``starts`` best, Levenberg-Marquardt (Marquardt's diagonal
   scaling) on the log residuals, the shape parameters through the bounded
   reparameterisation of the image fits and the albedos in log space;
   Jacobian: albedo columns analytic, shape columns by forward differences
   (one table build each).

Bounds: alpha in [0.01, pi/2].  The authors search alpha up to pi.  Here
alpha stops at pi/2 because that is the plugin's valid range, over which
the accuracy of its tables was measured (``tools/check_accuracy.py``); at
alpha = pi/2 the distribution of facet angles in [0, pi/2] is already within
a factor e^-1 (beta = 2) of flat, so larger values change the BRDF little, and
a fit that ends at the bound says so (``at_bound``).
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import time

import numpy as np

from fmbrdf_mi.fit.solve import lm as LM

from . import merl

CHANNELS = ("r", "g", "b")
SHAPE = ("eta", "alpha", "beta", "kappa")
#: The authors' cut near the specular peak: theta_h > arccos(0.9999).
THETA_H_MIN = math.acos(0.9999)
EPS = 1e-10
ALPHA_MAX = 0.5 * math.pi


@dataclasses.dataclass
class BRDFFitOptions:
    eta_grid: tuple = (1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9)
    alpha_grid: tuple = tuple(np.round(np.logspace(-2, math.log10(ALPHA_MAX), 8), 6))
    beta_grid: tuple = tuple(np.round(np.logspace(math.log10(0.5), math.log10(4.0), 5), 6))
    kappa_start: float = 0.0
    kappa_scan: tuple = (0.5, 5.0, 20.0, 60.0)
    starts: int = 2
    #: "local": the coarse-to-fine search of :func:`grid_search`; "full": every point of the grid
    grid_search: str = "local"
    max_samples: int = 50_000
    max_evals: int = 60
    min_cos: float = 1e-3
    theta_h_min: float = THETA_H_MIN
    seed: int = 0


@dataclasses.dataclass
class BRDFFitResult:
    params: dict            # eta, alpha, beta, kappa, k_s: [r, g, b], k_b: [r, g, b]
    log_rmse: float         # on the fitted samples
    log_rmse_channels: list
    log_rmse_all: float     # on every usable bin
    n_samples: int
    n_usable: int
    at_bound: list
    history: list
    timings: dict
    converged: bool = True  # the best start's refinement converged (else it stopped at max_evals)
    stop_reason: str = ""   # why the best start's refinement stopped


def _shape_model():
    """The bounded reparameterisation of the image fits, with alpha up to pi/2."""
    from fmbrdf_mi.fit.evaluate.models import FMBRDF

    shape = tuple(dataclasses.replace(p, hi=ALPHA_MAX) if p.name == "alpha" else p for p in FMBRDF.shape)
    return dataclasses.replace(FMBRDF, shape=shape)


def usable_bins(brdf, options=None):
    """Flat indices into the (90, 90, 180) grid of the bins a fit uses, and their (w_in, w_out)."""
    o = options or BRDFFitOptions()
    th, td, pd = merl.bin_angles()
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    w_in, w_out = merl.half_diff_to_dirs(TH, TD, PD)
    ok = np.all(np.isfinite(brdf) & (np.nan_to_num(brdf) > 0), axis=-1)
    ok &= TH > o.theta_h_min
    ok &= (w_in[..., 2] > o.min_cos) & (w_out[..., 2] > o.min_cos)
    idx = np.flatnonzero(ok.ravel())
    return idx, w_in.reshape(-1, 3)[idx], w_out.reshape(-1, 3)[idx]


def log_residuals(pred, obs):
    return np.log10(pred + EPS) - np.log10(obs + EPS)


def closed_form_albedos(S, B, f):
    """Per channel (k_s, k_b) >= 0 minimising sum ((k_s S + k_b B) / f - 1)^2."""
    ks, kb = np.zeros(f.shape[1]), np.zeros(f.shape[1])
    for c in range(f.shape[1]):
        a = np.stack([S / f[:, c], B / f[:, c]], axis=1)
        sol = np.linalg.lstsq(a, np.ones(len(S)), rcond=None)[0]
        if (sol < 0).any():  # on the boundary: the better one-term solution
            cands = []
            for j in range(2):
                x = max(a[:, j].sum() / max((a[:, j] ** 2).sum(), 1e-300), 0.0)
                s = np.zeros(2)
                s[j] = x
                cands.append((np.sum((a @ s - 1) ** 2), s))
            sol = min(cands, key=lambda t: t[0])[1]
        ks[c], kb[c] = sol
    return np.maximum(ks, 1e-12), np.maximum(kb, 1e-12)


def grid_albedos(S, B, f, weights=None):
    """:func:`closed_form_albedos` for all channels at once, by the 2 x 2 normal equations: what the
    start grid ranks its points by (several times faster than the per-channel ``lstsq``; the two agree to
    the rounding of the normal equations, ~1e-12 relative for the grid's well-conditioned S and B).
    ``weights``: (1 / f, 1 / f^2), each (channels, n) C-contiguous, if already computed (the samples of
    a fit stay the same).  The starts that are refined get ``closed_form_albedos``' own values
    (:func:`fit_brdf`)."""
    w, w2 = weights if weights is not None else grid_weights(f)
    ss, sb, bb = w2 @ (S * S), w2 @ (S * B), w2 @ (B * B)
    rs, rb = w @ S, w @ B
    det = ss * bb - sb * sb
    with np.errstate(divide="ignore", invalid="ignore"):
        ks, kb = (bb * rs - sb * rb) / det, (ss * rb - sb * rs) / det
    bad = ~(np.isfinite(ks) & np.isfinite(kb) & (det > 0)) | (ks < 0) | (kb < 0)
    if bad.any():  # the boundary (or singular) case: the per-channel solution
        k2s, k2b = closed_form_albedos(S, B, f[:, bad])
        ks[bad], kb[bad] = k2s, k2b
    return np.maximum(ks, 1e-12), np.maximum(kb, 1e-12)


def grid_weights(f):
    """(1 / f, 1 / f^2) of samples f (n, channels), each (channels, n): :func:`grid_albedos`' ``weights``."""
    w = np.ascontiguousarray((1.0 / f).T)
    return w, w * w


def coarse_axes(dims):
    """The coarse stage of :func:`grid_search`, per axis: every other index and the last one."""
    return [sorted(set(range(0, n, 2)) | {n - 1}) for n in dims]


def coarse_points(dims):
    """The points of the coarse stage of :func:`grid_search`."""
    return list(itertools.product(*coarse_axes(dims)))


def _box(p, dims, step=None):
    """The neighbours of grid point ``p`` in its 3 x 3 x 3 box (``step``: per axis, the sorted indices
    that are neighbours, e.g. the coarse lattice), inside the grid."""
    out = []
    for d in itertools.product((-1, 0, 1), repeat=len(dims)):
        if not any(d):
            continue
        if step is None:
            q = tuple(a + b for a, b in zip(p, d))
        else:
            pos = [ax.index(a) + b for a, b, ax in zip(p, d, step)]
            if not all(0 <= x < len(ax) for x, ax in zip(pos, step)):
                continue
            q = tuple(ax[x] for x, ax in zip(pos, step))
        if all(0 <= x < n for x, n in zip(q, dims)):
            out.append(q)
    return out


def grid_search(dims, error, keep, mode="local", progress=None):
    """{grid index (i, j, k): error} of the start grid points evaluated.

    ``mode`` "full": every point.  "local" (coarse to fine): the points of :func:`coarse_points` (every
    other index per axis), then the unevaluated neighbours (the 3 x 3 x 3 box on the full grid) of the
    ``keep`` best points so far and of the ``keep`` best local minima of the coarse lattice (one per
    valley, so that a second valley is looked into even when its coarse points are not among the best), then repeatedly
    the unevaluated neighbours of the ``keep`` best points, until all of those are evaluated.  The
    ``keep`` best found are then each the best of their own neighbourhood, which is where the full grid's
    best lie when the error varies smoothly over the grid (each axis log-spaced or near it); a narrow
    valley between coarse points that is worse than another valley at every coarse point can be missed
    (``mode="full"``, the CLI's ``--full-grid``, evaluates everything).  The order of evaluation is
    fixed (no randomness).  ``progress(done, total)``: after every point, ``total`` the points known to
    come so far."""
    if mode not in ("full", "local"):
        raise ValueError(f"grid search: mode must be 'full' or 'local', got {mode!r}")
    errors = {}
    order = lambda p: (errors[p], int(np.ravel_multi_index(p, dims)))
    todo = list(itertools.product(*(range(n) for n in dims))) if mode == "full" else coarse_points(dims)
    first = True
    while todo:
        total = len(errors) + len(todo)
        for p in todo:
            errors[p] = error(p)
            if progress:
                progress(len(errors), total)
        if mode == "full":
            break
        seeds = sorted(errors, key=order)[:keep]
        if first:   # and the best local minima of the coarse lattice
            lattice = coarse_axes(dims)
            minima = []   # the best of each valley: no two neighbours on the lattice (ties make plateaus)
            for p in sorted(errors, key=order):
                box = _box(p, dims, lattice)
                if all(errors[p] <= errors[q] for q in box) and not any(q in box for q in minima):
                    minima.append(p)
            seeds += [p for p in minima[:keep] if p not in seeds]
            first = False
        todo = []
        for p in seeds:
            todo += [q for q in _box(p, dims) if q not in errors and q not in todo]
    return errors


class Progress:
    """Progress lines with an estimate of the time left, at most one every ``every`` seconds (and the last).
    ``bound``: ``total`` is a budget that may not be used up, and the estimate an upper bound."""

    def __init__(self, say, what, total, every=2.0, bound=False):
        self.say, self.what, self.total, self.every = say, what, total, every
        self.left_word = "at most about" if bound else "about"
        self.t0 = self.last = time.time()

    def step(self, done, detail=""):
        now = time.time()
        if done < self.total and now - self.last < self.every:
            return
        self.last = now
        el = now - self.t0
        left = el / max(done, 1) * (self.total - done)
        self.say(f"[fit-brdf] {self.what} {done}/{self.total}{', ' + detail if detail else ''}; "
                 f"{el:.1f} s, {self.left_word} {left:.0f} s left" if done < self.total else
                 f"[fit-brdf] {self.what} {done}/{self.total}{', ' + detail if detail else ''}; {el:.1f} s")


def _predict(S, B, ks, kb):
    return S[:, None] * ks[None, :] + B[:, None] * kb[None, :]


def levenberg_marquardt(fun, jac, x0, max_evals=60, rtol=1e-9, max_step=1.0):
    """Minimise |fun(x)|^2 with the one Levenberg-Marquardt (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`):
    (x, residuals, evaluations of fun, stop reason).

    What this fit adds through the LM's hooks: a budget of ``max_evals``
    evaluations of ``fun``; a Jacobian ``jac(x)`` after every accepted step;
    converged at the first relative decrease below ``rtol`` or an RMS
    residual below 1e-6; and a step shortened to at most ``max_step`` in every
    coordinate: where a parameter barely moves the residuals (kappa near 0 on
    its sigmoid scale) the Gauss-Newton step is huge, and one such step was
    seen to throw kappa onto the flat end of its reparameterisation, where it
    stayed."""
    x0 = np.asarray(x0, dtype=np.float64).copy()
    r0 = fun(x0)
    state = {"nfev": 1, "r": r0, "why": ""}

    def solve(lin, lam):     # Marquardt's scaling, then the step clipped to max_step
        r, J = lin
        A, g = J.T @ J, J.T @ r
        step = -np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-12)), g)
        return step * min(1.0, max_step / max(np.abs(step).max(), 1e-300))

    def trial(x, step, lin):
        r_new = fun(x + step)
        state["nfev"] += 1
        return x + step, float(r_new @ r_new), r_new

    def moved(lin, x_new, r_new):
        state["r"] = r_new
        return lin

    def small(cost, cost_new):
        state["why"] = ("relative decrease below 1e-9" if cost - cost_new <= rtol * cost else
                        "RMS residual below 1e-6" if cost_new <= 1e-12 * len(r0) else "")
        return bool(state["why"])

    res = LM.levenberg_marquardt(x0, float(r0 @ r0), lambda x: (state["r"], jac(x)), solve, trial,
                                 max_iter=max_evals + 1, refresh=1, moved=moved, small=small, small_count=1,
                                 budget=lambda: state["nfev"] >= max_evals, final_linearise=False)
    status = {"small_decrease": f"converged: {state['why']}", "no_step": "converged: no step lowers the error"}.get(
        res.reason, f"stopped after {max_evals} evaluations")
    return res.x, state["r"], state["nfev"], status


def fit_brdf(brdf, options=None, progress=None):
    """Fit FMBRDF to a (90, 90, 180, 3) BRDF (1/sr, NaN = not measured): :class:`BRDFFitResult`.

    ``progress``: called with one line of text at each stage, and every few seconds in the long ones
    with an estimate of the time left."""
    from .values import evaluation_variant

    with evaluation_variant():  # once, not per evaluation (values.py)
        return _fit_brdf(brdf, options or BRDFFitOptions(), progress)


def _fit_brdf(brdf, o, progress):
    from fmbrdf_mi.fit.evaluate.models import Bounds
    from .values import FMBRDFValues

    say = progress or (lambda msg: None)
    t0 = time.time()
    idx_all, w_in_all, w_out_all = usable_bins(brdf, o)
    if len(idx_all) < 100:
        raise ValueError(f"fit-brdf: only {len(idx_all)} usable bins (measured in all three channels, both "
                         "directions above the horizon); need at least 100")
    obs_all = brdf.reshape(-1, 3)[idx_all]
    rng = np.random.default_rng(o.seed)
    pick = np.sort(rng.choice(len(idx_all), size=min(o.max_samples, len(idx_all)), replace=False))
    obs = obs_all[pick]
    ev = FMBRDFValues(w_in_all[pick], w_out_all[pick])
    model = _shape_model()
    bounds = Bounds(model)
    history = []

    # 1. start grid: one table build per point, all samples evaluated at once (values.py); the albedos by
    #    the normal equations, then those of the starts refined again exactly as before (closed_form_albedos)
    axes = (o.eta_grid, o.alpha_grid, o.beta_grid)
    dims = tuple(len(a) for a in axes)
    n_grid = int(np.prod(dims))
    say(f"[fit-brdf] {len(pick)} of {len(idx_all)} usable bins; start grid of {n_grid} points"
        + (" (coarse to fine)" if o.grid_search == "local" else ""))
    log_obs = np.log10(obs + EPS)
    weights = grid_weights(obs)
    bar = Progress(say, "start grid point", n_grid if o.grid_search == "full" else len(coarse_points(dims)))
    best_err = [math.inf]

    def grid_error(p):
        eta, alpha, beta = (ax[i] for ax, i in zip(axes, p))
        shape = {"eta": eta, "alpha": min(alpha, ALPHA_MAX), "beta": beta, "kappa": o.kappa_start}
        S, B = ev.parts(shape)
        ks, kb = grid_albedos(S, B, obs, weights)
        err = float(np.sqrt(np.mean((np.log10(_predict(S, B, ks, kb) + EPS) - log_obs) ** 2)))
        best_err[0] = min(best_err[0], err)
        return err

    def grid_progress(done, total):
        bar.total = total
        bar.step(done, f"best log10 RMSE so far {best_err[0]:.4f}")

    errors = grid_search(dims, grid_error, max(1, o.starts) + 1, o.grid_search, grid_progress)
    grid = sorted((e, int(np.ravel_multi_index(p, dims)), p) for p, e in errors.items())
    grid = [(e, i, {"eta": axes[0][p[0]], "alpha": min(axes[1][p[1]], ALPHA_MAX), "beta": axes[2][p[2]],
                    "kappa": o.kappa_start}) for e, i, p in grid]
    starts = []
    for _, _, shape in grid[:max(1, o.starts)]:
        S, B = ev.parts(shape)
        ks, kb = closed_form_albedos(S, B, obs)
        starts.append((float(np.sqrt(np.mean(log_residuals(_predict(S, B, ks, kb), obs) ** 2))), shape, ks, kb))
    t_grid = time.time() - t0
    history.append({"stage": "grid", "best": starts[0][0], "shape": starts[0][1], "points": len(grid)})

    # 2. refinement
    nsh = len(SHAPE)
    cache = {}

    def parts_at(x):
        key = tuple(np.round(x[:nsh], 12))
        if key not in cache:
            if len(cache) > 16:
                cache.clear()
            shape = {n: bounds.to_value(n, x[k]) for k, n in enumerate(SHAPE)}
            cache[key] = ev.parts(shape)
        return cache[key]

    def unpack(x):
        return np.exp(x[nsh:nsh + 3]), np.exp(x[nsh + 3:nsh + 6])

    bar = None

    def fun(x):
        S, B = parts_at(x)
        ks, kb = unpack(x)
        r = log_residuals(_predict(S, B, ks, kb), obs).ravel()
        if bar is not None:
            bar.n += 1
            bar.step(bar.n, f"log10 RMSE {math.sqrt(np.mean(r ** 2)):.4f}")
        return r

    def jac(x):
        S, B = parts_at(x)
        ks, kb = unpack(x)
        pred = _predict(S, B, ks, kb) + EPS
        J = np.zeros((obs.size, nsh + 6))
        inv = 1.0 / (pred * math.log(10.0))
        for c in range(3):
            col = np.zeros_like(pred)
            col[:, c] = S * ks[c] * inv[:, c]
            J[:, nsh + c] = col.ravel()
            col[:, c] = B * kb[c] * inv[:, c]
            J[:, nsh + 3 + c] = col.ravel()
        r0 = np.log10(pred)
        for k in range(nsh):
            h = 1e-3
            xp = x.copy()
            xp[k] += h
            Sp, Bp = parts_at(xp)
            J[:, k] = ((np.log10(_predict(Sp, Bp, ks, kb) + EPS) - r0) / h).ravel()
        return J

    best = None
    for s, (err0, shape, ks, kb) in enumerate(starts):
        for kappa in o.kappa_scan:
            trial = dict(shape, kappa=kappa)
            S, B = ev.parts(trial)
            ks_t, kb_t = closed_form_albedos(S, B, obs)
            e = float(np.sqrt(np.mean(log_residuals(_predict(S, B, ks_t, kb_t), obs) ** 2)))
            if e < err0:
                err0, shape, ks, kb = e, trial, ks_t, kb_t
        x0 = np.concatenate([[bounds.to_z(n, shape[n]) for n in SHAPE], np.log(ks), np.log(kb)])
        t1 = time.time()
        bar = Progress(say, f"start {s + 1}/{len(starts)}: evaluation", o.max_evals, bound=True)
        bar.n = 0
        xs, r, nfev, status = levenberg_marquardt(fun, jac, x0, o.max_evals)
        bar = None
        err = float(np.sqrt(np.mean(r ** 2)))
        history.append({"stage": "refine", "start": s, "start_error": err0, "error": err, "evals": nfev,
                        "seconds": time.time() - t1, "status": status})
        say(f"[fit-brdf] start {s + 1}: log10 RMSE {err0:.4f} -> {err:.4f} ({nfev} evaluations, "
            f"{time.time() - t1:.1f} s, {status})")
        if best is None or err < best[0]:
            best = (err, xs, status)
    err, x, status = best
    shape = {n: bounds.to_value(n, x[k]) for k, n in enumerate(SHAPE)}
    ks, kb = unpack(x)
    S, B = ev.parts(shape)
    res = log_residuals(_predict(S, B, ks, kb), obs)
    at_bound = [n for k, n in enumerate(SHAPE) if abs(x[k]) > 9.0]
    # every usable bin, in chunks
    sq, t2 = 0.0, time.time()
    for lo in range(0, len(idx_all), 400_000):
        sl = slice(lo, lo + 400_000)
        ev_all = FMBRDFValues(w_in_all[sl], w_out_all[sl])
        Sa, Ba = ev_all.parts(shape)
        sq += float(np.sum(log_residuals(_predict(Sa, Ba, ks, kb), obs_all[sl]) ** 2))
    err_all = math.sqrt(sq / obs_all.size)
    params = {**{n: float(v) for n, v in shape.items()}, "k_s": [float(v) for v in ks],
              "k_b": [float(v) for v in kb]}
    return BRDFFitResult(params=params, log_rmse=float(np.sqrt(np.mean(res ** 2))),
                         log_rmse_channels=[float(np.sqrt(np.mean(res[:, c] ** 2))) for c in range(3)],
                         log_rmse_all=err_all, n_samples=len(pick), n_usable=len(idx_all), at_bound=at_bound,
                         history=history, timings={"grid": t_grid, "total": time.time() - t0,
                                                   "error_all": time.time() - t2},
                         converged=status.startswith("converged"), stop_reason=status)


def model_brdf(params, phi_d_index=None):
    """The fitted FMBRDF on the whole MERL grid: (90, 90, 180, 3), NaN below the horizon.

    ``phi_d_index``: only the bins of that phi_d index are evaluated (the others are NaN): what the
    slice plot (:func:`.plots.slice_plot`) reads, 1/180 of the grid; each bin's value is the same."""
    from .values import FMBRDFValues, evaluation_variant

    th, td, pd = merl.bin_angles()
    if phi_d_index is not None:
        pd = pd[phi_d_index:phi_d_index + 1]
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    w_in, w_out = merl.half_diff_to_dirs(TH, TD, PD)
    w_in, w_out = w_in.reshape(-1, 3), w_out.reshape(-1, 3)
    ok = (w_in[:, 2] > 1e-4) & (w_out[:, 2] > 1e-4)
    out = np.full((w_in.shape[0], 3), np.nan)
    with evaluation_variant():
        S, B = FMBRDFValues(w_in[ok], w_out[ok]).parts({n: params[n] for n in SHAPE})
    out[ok] = _predict(S, B, np.asarray(params["k_s"]), np.asarray(params["k_b"]))
    if phi_d_index is None:
        return out.reshape(merl.DIMS + (3,))
    full = np.full(merl.DIMS + (3,), np.nan)
    full[:, :, phi_d_index] = out.reshape(merl.DIMS[:2] + (3,))
    return full
