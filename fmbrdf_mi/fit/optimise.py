"""Minimising the paper's loss: bounded reparameterisation, coarse search, Levenberg-Marquardt or Adam.

Unknowns: the model's shape parameters (for FMBRDF eta, alpha, beta, kappa)
and its two albedos a_s, a_b (FMBRDF: k_s and k_b = r_k k_s).  The optimiser
works on unconstrained z: shape parameters through a sigmoid onto their
bounds (on a log scale for those spanning decades, :class:`models.Bounds`),
albedos through exp.  So every iterate is a valid material.

1. **Coarse search** (needs no answer): shape parameters on a grid over the
   box; at each grid point the albedos that best explain the intensities
   follow in closed form (intensity is linear in them: a two-unknown
   non-negative least squares), and the paper's loss decides.  The grid is
   searched in two stages to bound the number of BSDF table rebuilds:
   everything but eta at the middle eta, then eta for the best few.
2. **Refinement** on the same loss:
   * ``lm`` (default): Levenberg-Marquardt on the loss's residual form, the
     Jacobian from forward-mode Dr.Jit AD through the BSDF for each shape
     parameter and analytic for the albedos (the model is linear in them);
   * ``adam``: Adam (the paper's optimiser) on the reverse-mode Dr.Jit
     gradient of the loss with all parameters live in the BSDF.
3. **Stopping rule**: stop when an accepted step lowers the loss by less
   than ``tol`` (relative) twice in a row, when the step in z is below 1e-6,
   at ``max_iter`` iterations or after ``time_limit`` seconds (Adam: when
   the best loss has not improved by ``tol`` over ``patience`` iterations).
   The inlier/outlier classification of the loss is refreshed after each
   round and the refinement repeated (at most three rounds) until it no
   longer changes.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import time

import numpy as np

from . import loss as L
from . import rice
from .models import Bounds


@dataclasses.dataclass
class State:
    """A point of the search: shape values and albedos."""

    shape: dict
    a_s: float
    a_b: float

    def copy(self):
        return State(dict(self.shape), self.a_s, self.a_b)


class Problem:
    """A model, an evaluator at the fitted pixels, the observed target and the bounds."""

    def __init__(self, model, evaluator, target, bounds=None, progress=None):
        self.model, self.ev, self.target = model, evaluator, target
        self.bounds = bounds if isinstance(bounds, Bounds) else Bounds(model, bounds)
        self.progress = progress or (lambda msg: None)
        self.names = model.shape_names
        self.w = target.dolp_valid.astype(np.float64)
        self.outliers = np.zeros(len(target.intensity), bool)
        self.n_evals = 0
        self.n_nonfinite = 0
        self.t0 = time.time()

    # ---- z <-> state
    def to_z(self, st):
        return np.array([self.bounds.to_z(n, st.shape[n]) for n in self.names]
                        + [math.log(max(st.a_s, 1e-30)), math.log(max(st.a_b, 1e-30))])

    def from_z(self, z):
        shape = {n: self.bounds.to_value(n, z[i]) for i, n in enumerate(self.names)}
        k = len(self.names)
        return State(shape, math.exp(np.clip(z[k], -60, 60)), math.exp(np.clip(z[k + 1], -60, 60)))

    # ---- evaluation
    def parts(self, st, jac=False):
        self.n_evals += 1
        return self.ev.parts(st.shape, self.names if jac else ())

    def set_weights(self, parts, st):
        self.outliers = L.outlier_mask(parts.surface[0], parts.body[0], st.a_s, st.a_b)
        self.w = L.weights(self.outliers, self.target.dolp_valid)

    def loss(self, parts, st, w=None):
        i, rho = L.predict(parts.surface, parts.body, st.a_s, st.a_b, self.target.lin_sigma)
        return L.loss(self.target, self.w if w is None else w, i, rho)

    def residuals_and_jacobian(self, parts, st, z):
        """r (m,) and dr/dz (m, k + 2)."""
        S, B = parts.surface, parts.body
        a_s, a_b = st.a_s, st.a_b
        s = a_s * S + a_b * B
        i = s[0]
        nu = np.sqrt(s[1] ** 2 + s[2] ** 2 + L.DOLP_EPS ** 2)
        sigma = self.target.lin_sigma
        # the DoLP's numerator: |(S1, S2)|, or its mean as a noisy camera measures it (loss.py)
        lin = nu if sigma is None else rice.mean_length(nu, sigma)
        dlin = 1.0 if sigma is None else rice.mean_length_derivative(nu, sigma)
        safe_i = np.where(i > 0, i, 1.0)
        rho = lin / safe_i
        r = L.residuals(self.target, self.w, i, rho)
        m = len(i)
        ci = 1.0 / (self.target.scale * math.sqrt(m))
        cr = np.sqrt(self.w / self.w.sum())

        def cols(ds):  # derivative of the Stokes prediction -> residual column
            d_i = ds[0]
            d_rho = dlin * (s[1] * ds[1] + s[2] * ds[2]) / (nu * safe_i) - rho * d_i / safe_i
            return np.concatenate([ci * d_i, cr * d_rho])

        J = np.empty((len(r), len(z)))
        for j, n in enumerate(self.names):
            J[:, j] = cols(a_s * parts.d_surface[n] + a_b * parts.d_body[n]) * self.bounds.derivative(n, z[j])
        k = len(self.names)
        J[:, k] = cols(a_s * S)       # d/d log a_s
        J[:, k + 1] = cols(a_b * B)   # d/d log a_b
        if parts.nonfinite is not None and parts.nonfinite.any():
            # a few directions where the BSDF's forward-mode derivative is NaN: those pixels'
            # rows are left out of the Jacobian (their residuals still count in the loss)
            bad = np.concatenate([parts.nonfinite, parts.nonfinite])
            J[bad] = 0.0
            self.n_nonfinite = max(self.n_nonfinite, int(parts.nonfinite.sum()))
        return r, J


# ---------------------------------------------------------------- closed-form albedos
def solve_albedos(parts, target):
    """Non-negative least squares of the intensities over (a_s, a_b); returns (a_s, a_b)."""
    S, B, I = parts.surface[0], parts.body[0], target.intensity
    A = np.array([[S @ S, S @ B], [S @ B, B @ B]])
    b = np.array([S @ I, B @ I])
    cands = []
    try:
        x = np.linalg.solve(A, b)
        if np.all(x >= 0):
            cands.append(x)
    except np.linalg.LinAlgError:
        pass
    if A[0, 0] > 0:
        cands.append(np.array([max(b[0] / A[0, 0], 0.0), 0.0]))
    if A[1, 1] > 0:
        cands.append(np.array([0.0, max(b[1] / A[1, 1], 0.0)]))
    if not cands:
        return 1e-6, 1e-6
    best = min(cands, key=lambda x: float(x @ A @ x - 2 * x @ b))
    # keep both strictly positive (log reparameterisation); tiny floor relative to the other
    floor = 1e-6 * max(best.max(), 1e-12)
    return float(max(best[0], floor)), float(max(best[1], floor))


def _score(problem, parts, st):
    """Loss of a coarse candidate with its own inlier/outlier split."""
    out = L.outlier_mask(parts.surface[0], parts.body[0], st.a_s, st.a_b)
    w = L.weights(out, problem.target.dolp_valid)
    return problem.loss(parts, st, w)


def coarse_search(problem, keep=2):
    """Grid search in stages; returns candidates [(loss, State)] best first.

    Stage 1: every shape parameter but eta and kappa on its grid, eta and
    kappa at their middle grid values; stage 2: eta on its grid for the
    ``keep`` best; stage 3: kappa on its grid for the best (kappa changes the
    body term least, and is often weakly identifiable: README).  Each grid
    point costs one BSDF table rebuild.
    """
    model, bounds = problem.model, problem.bounds
    grids = {p.name: bounds.clip_grid(p.name, p.grid) for p in model.shape}
    later = [n for n in ("eta", "kappa") if n in grids]
    first = [n for n in problem.names if n not in later]
    mids = {n: grids[n][len(grids[n]) // 2] for n in later}
    results = {}

    def try_point(shape):
        key = tuple(round(shape[n], 9) for n in problem.names)
        if key in results:
            return
        parts = problem.parts(State(shape, 1.0, 1.0))
        a_s, a_b = solve_albedos(parts, problem.target)
        st = State(dict(shape), a_s, a_b)
        results[key] = (_score(problem, parts, st), st)

    def best():
        return min(results.values(), key=lambda x: x[0])

    t = time.time()
    combos = list(itertools.product(*[grids[n] for n in first]))
    for j, combo in enumerate(combos):
        try_point({**mids, **dict(zip(first, combo))})
        if (j + 1) % 6 == 0 or j + 1 == len(combos):
            problem.progress(f"[search] stage 1 ({', '.join(first)}): {j + 1}/{len(combos)} grid points, "
                             f"best loss {best()[0]:.4e} ({time.time() - t:.1f} s)")
    for stage, name in enumerate(later, start=2):
        top = sorted(results.values(), key=lambda x: x[0])[:keep if name == "eta" else 1]
        for _, st in top:
            for value in grids[name]:
                try_point({**st.shape, name: value})
        problem.progress(f"[search] stage {stage} ({name}): best loss {best()[0]:.4e} "
                         f"({time.time() - t:.1f} s, {len(results)} grid points)")
    return sorted(results.values(), key=lambda x: x[0])


# ---------------------------------------------------------------- refinement
def _fmt(problem, st):
    rep = problem.model.report(st.shape, st.a_s, st.a_b)
    return " ".join(f"{k}={v:.4g}" for k, v in rep.items())


def levenberg_marquardt(problem, st, *, max_iter=40, tol=1e-5, time_limit=None, history=None,
                        round_no=0, refresh=3):
    """Minimise the loss from ``st`` with the current weights.

    The Jacobian comes from forward-mode AD at the start and at least every
    ``refresh`` accepted steps; in between it is kept current with Broyden's
    rank-one secant update from every trial point (each AD Jacobian costs one
    table rebuild with AD per shape parameter, a trial point one without).
    A step that fails on a secant Jacobian triggers a fresh AD Jacobian
    before the damping is raised.
    Returns (State, loss, stop reason, J, r) with an AD Jacobian at the result.
    """
    def ad_jacobian(st, z):
        return problem.residuals_and_jacobian(problem.parts(st, jac=True), st, z)

    def trial(st):
        p = problem.parts(st)
        i, rho = L.predict(p.surface, p.body, st.a_s, st.a_b, problem.target.lin_sigma)
        r = L.residuals(problem.target, problem.w, i, rho)
        return r, float(r @ r)

    z = problem.to_z(st)
    r, J = ad_jacobian(st, z)
    fresh, since_ad = True, 0
    f = float(r @ r)
    lam, small, reason = 1e-3, 0, f"max_iter ({max_iter})"
    t0 = time.time()
    for it in range(1, max_iter + 1):
        accepted = False
        while lam < 1e10:
            A, g = J.T @ J, J.T @ r
            D = np.diag(A).copy()
            D[D <= 0] = 1e-12
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), -g)
            except np.linalg.LinAlgError:
                lam *= 4
                continue
            z_new = np.clip(z + delta, -40, 40)
            st_new = problem.from_z(z_new)
            r_new, f_new = trial(st_new)
            dz = z_new - z
            if np.all(np.isfinite(r_new)) and dz @ dz > 0:  # Broyden update with what the trial taught
                J = J + np.outer(r_new - r - J @ dz, dz) / (dz @ dz)
            if np.isfinite(f_new) and f_new < f:
                accepted = True
                break
            if not fresh:
                r, J = ad_jacobian(st, z)
                fresh, since_ad = True, 0
            else:
                lam *= 4
        if not accepted:
            reason = "no step lowers the loss (converged to float32 precision)"
            break
        rel = (f - f_new) / max(f, 1e-300)
        step = float(np.max(np.abs(z_new - z)))
        z, st, f, r = z_new, st_new, f_new, r_new
        fresh = False
        since_ad += 1
        lam = max(lam / 3, 1e-9)
        if history is not None:
            history.append({"stage": f"lm{round_no}", "iter": it, "loss": f,
                            "time": time.time() - problem.t0,
                            "params": problem.model.report(st.shape, st.a_s, st.a_b)})
        problem.progress(f"[lm {round_no}] iter {it:2d}  loss {f:.6e}  {_fmt(problem, st)}  "
                         f"({time.time() - problem.t0:.1f} s)")
        small = small + 1 if rel < tol else 0
        if small >= 2:
            reason = f"relative loss decrease < {tol:g} twice in a row"
            break
        if step < 1e-4:
            reason = "step in z < 1e-4"
            break
        if time_limit is not None and time.time() - t0 > time_limit:
            reason = f"time limit {time_limit:g} s"
            break
        if since_ad >= refresh:
            r, J = ad_jacobian(st, z)
            fresh, since_ad = True, 0
    if not fresh:
        r, J = ad_jacobian(st, z)
    return st, f, reason, J, r


def loss_and_grad_reverse(problem, st):
    """Loss and its gradient (dict over shape names, 'a_s', 'a_b') by reverse-mode AD through the BSDF."""
    import drjit as dr
    import mitsuba as mi

    ev = problem.ev
    xs = {}
    for p in problem.model.shape:
        x = mi.Float(float(st.shape[p.name]))
        dr.enable_grad(x)
        ev._assign(p.key, x)
        xs[p.name] = x
    for name, key, v in (("a_s", problem.model.surface_key, st.a_s), ("a_b", problem.model.body_key, st.a_b)):
        x = mi.Float(float(v))
        dr.enable_grad(x)
        ev._assign(key, x)
        xs[name] = x
    ev.params.update()
    s0, s1, s2 = ev._stokes()
    val = L.loss_dr(problem.target, problem.w, s0, s1, s2)
    dr.backward(val)
    grad = {k: float(dr.grad(x)[0]) for k, x in xs.items()}
    f = float(val[0])
    # restore detached values
    for p in problem.model.shape:
        ev._assign(p.key, float(st.shape[p.name]))
        ev._current[p.name] = float(st.shape[p.name])
    ev.set_albedos(st.a_s, st.a_b)
    return f, grad


def adam(problem, st, *, max_iter=300, lr=0.02, tol=1e-4, patience=40, time_limit=None, history=None,
         round_no=0):
    """Adam on z with the reverse-mode gradient; returns (best State, loss, reason)."""
    z = problem.to_z(st)
    m = np.zeros_like(z)
    v = np.zeros_like(z)
    b1, b2, eps = 0.9, 0.999, 1e-8
    best = (math.inf, st)
    since, reason, t0 = 0, "max_iter", time.time()
    for it in range(1, max_iter + 1):
        st = problem.from_z(z)
        f, g = loss_and_grad_reverse(problem, st)
        gz = np.array([g[n] * problem.bounds.derivative(n, z[j]) for j, n in enumerate(problem.names)]
                      + [g["a_s"] * st.a_s, g["a_b"] * st.a_b])
        if not np.all(np.isfinite(gz)):
            reason = "non-finite gradient"
            break
        if f < best[0] * (1 - tol):
            since = 0
        else:
            since += 1
        if f < best[0]:
            best = (f, st.copy())
        if history is not None:
            history.append({"stage": f"adam{round_no}", "iter": it, "loss": f,
                            "time": time.time() - problem.t0,
                            "params": problem.model.report(st.shape, st.a_s, st.a_b)})
        if it % 5 == 0 or it == 1:
            problem.progress(f"[adam {round_no}] iter {it:3d}  loss {f:.6e}  {_fmt(problem, st)}  "
                             f"({time.time() - problem.t0:.1f} s)")
        if since >= patience:
            reason = f"best loss not improved by {tol:g} (relative) in {patience} iterations"
            break
        if time_limit is not None and time.time() - t0 > time_limit:
            reason = f"time limit {time_limit:g} s"
            break
        m = b1 * m + (1 - b1) * gz
        v = b2 * v + (1 - b2) * gz * gz
        mh, vh = m / (1 - b1 ** it), v / (1 - b2 ** it)
        z = np.clip(z - lr * mh / (np.sqrt(vh) + eps), -40, 40)
    return best[1], best[0], reason


def standard_errors(problem, st, J, r):
    """Gauss-Newton standard errors of the reported parameters (residual variance from the fit).

    The covariance of z is s^2 (J^T J)^-1 with s^2 = r.r / (m - p) over the
    non-zero residuals; it is mapped to the reported parameters by their
    Jacobian (finite differences of the reparameterisation).
    """
    z = problem.to_z(st)
    nz = np.count_nonzero(np.any(J != 0, axis=1))
    p = len(z)
    s2 = float(r @ r) / max(nz - p, 1)
    try:
        cov_z = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return {}
    base = problem.model.report(st.shape, st.a_s, st.a_b)
    names = list(base)
    G = np.zeros((len(names), p))
    for j in range(p):
        h = 1e-6
        zp = z.copy()
        zp[j] += h
        sp = problem.from_z(zp)
        rp = problem.model.report(sp.shape, sp.a_s, sp.a_b)
        G[:, j] = [(rp[n] - base[n]) / h for n in names]
    cov = G @ cov_z @ G.T
    return {n: float(math.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}


def default_progress(msg):
    print(msg, file=sys.stderr, flush=True)
