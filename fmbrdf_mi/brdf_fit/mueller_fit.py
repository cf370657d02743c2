"""Fitting models to a Mueller-matrix BRDF table, per wavelength or with chosen parameters common to every
wavelength: weighted least squares on f_r11 and the normalised Mueller elements, with the solver of the MERL fits.

Residuals of a row (observed f_r11 and normalised elements m_ij = f_ij / f_r11,
15 of them, in the package's frames; the model's from
:class:`.mueller_values.MuellerValues`):

* f_r11: ln(f_model / f_obs) ("log", default) or f_model / f_obs - 1
  ("relative"), divided by sigma_f;
* each normalised element: (m_model - m_obs) / sigma_m.

**Noise model**: independent Gaussian errors, relative with standard
deviation sigma_f on f_r11 and additive with sigma_m on every normalised
element.  The two are given (``noise_f``, ``noise_m``) or estimated from the
data: by default from the fit's own residuals (each group's sum of squares at
the optimum over its degrees of freedom, its size less the parameters it
absorbs, :func:`leverages`: chi^2 / dof = 1 per group; the fit is repeated
with those weights), or, with ``noise="vanishing"``,
sigma_m from the elements that must vanish for an isotropic surface in the
plane of incidence (in the s/p bases of the planes of incidence and exit, the
off-diagonal 2 x 2 blocks m13, m14, m23, m24, m31, m32, m41, m42 are odd
under the mirror symmetry about that plane; :func:`vanishing_noise`), which
assumes nothing about the model.  Intervals: the Gauss-Newton covariance
(J^T J)^-1 of the weighted residuals at the optimum, J by forward differences
in the shape parameters' values and the albedos' logarithms (so that it holds
at a bound too, where the bounded reparameterisation is flat), value +- z SE
cut at the bounds (``interval_kind`` "fisher").  A shape parameter that ends at
a bound (``at_bound``) gets a one-sided interval instead (``interval_kind``
"profile (at bound)", :func:`profile_limit`): from the bound to where the
profiled cost, the others refitted with it held, rises by the chi-square
quantile of one degree of freedom at the level, with the sigmas the fit
estimates (a Fisher interval cut at the bound would cover only values within
z SE of the bound, whatever the data say); one inside its bounds whose Fisher
interval a bound cuts gets both ends from the profile ("profile (near
bound)"), an end at the bound where the profiled cost rises less than the
quantile up to it.  The intervals are as honest as the noise
model: a systematic model error inflates the residual-based sigmas, which
then widen the intervals accordingly.

Procedure per model: a start grid over the shape parameters (the albedos at
each point by the relative least squares of f_r11, as the MERL fit's grid),
ranked by the weighted cost; from the ``starts`` best, Levenberg-Marquardt
(:func:`.fitting.levenberg_marquardt`, i.e. :mod:`fmbrdf_mi.fit.solve.lm`) on
the shape parameters through the bounded reparameterisation of the image fits
and the albedos in log space, Jacobian by forward differences (one table build
per shape column); then the noise is re-estimated and the best start refined
again from its optimum.

Parameters common to every wavelength (``share``, ``fit_shared``): one
joint least squares over all the wavelengths' rows, the common parameters one
column each and the others one per wavelength, by the same solver from the
separate fits; the joint covariance gives a common parameter the information
of every wavelength.

A depolarising material (normalised elements near 0) leaves the shape
parameters to f_r11 alone: eta is then fixed mainly by the Fresnel factor of
the surface term's magnitude, its interval is wide, and a Lambertian is
close in its error; the comparison table shows it.
"""
from __future__ import annotations

import collections
import dataclasses
import itertools
import math
import time

import numpy as np

from . import mueller as T
from fmbrdf_mi.fit.solve import lm as LM
from .mueller_values import MuellerValues, combine, get_model, polarised_variant

#: Start grids of the shape parameters, per model (coarse: each point is one table build).
START_GRIDS = {
    "fmbrdf": {"eta": (1.3, 1.6, 2.0), "alpha": (0.03, 0.1, 0.3, 0.8), "beta": (1.0, 2.5), "kappa": (0.0, 10.0)},
    "pplastic": {"eta": (1.3, 1.6, 2.0), "alpha": (0.02, 0.05, 0.12, 0.3, 0.6)},
    "lambert": {},
    "lambert_ts": {"eta": (1.3, 1.6, 2.0), "alpha": (0.02, 0.05, 0.12, 0.3, 0.6)},
    "oren_nayar_ts": {"eta": (1.3, 1.6, 2.0), "alpha": (0.02, 0.05, 0.12, 0.3, 0.6), "sigma": (0.0, 0.5)},
}
#: The 0-based (i, j) of the elements that vanish in the plane of incidence (s/p bases, isotropic surface).
VANISHING = ((0, 2), (0, 3), (1, 2), (1, 3), (2, 0), (2, 1), (3, 0), (3, 1))
#: Flat indices 1..15 of the normalised elements (all but m11).
ELEMENTS = tuple(range(1, 16))
#: Memory for the terms of the shape points a fit has built (:meth:`_Problem.parts`, most recently used kept).
PARTS_KEPT_BYTES = 64 * 2 ** 20
#: z beyond which a bounded parameter counts as at its bound.
AT_BOUND_Z = 9.0
#: Kinds of interval (``MuellerFitResult.interval_kind``, named as the image fits' ``interval_kind``): value +- z SE
#: from the Gauss-Newton (Fisher) covariance, cut at the bounds; and, for a shape parameter at a bound, from the
#: bound to the profile likelihood's limit (:func:`profile_limit`).
INTERVAL_FISHER = "fisher"
INTERVAL_PROFILE = "profile (at bound)"
#: Both ends from the profile likelihood: a shape parameter inside its bounds whose Fisher interval one cuts.
INTERVAL_PROFILE_NEAR = "profile (near bound)"
#: A profile end is found when the profiled cost's rise is within this of the quantile (chi^2 units: the
#: refits' own convergence tolerance, :data:`fmbrdf_mi.fit.solve.lm.DECREMENT_TOL`).
PROFILE_RISE_TOL = 0.01


@dataclasses.dataclass
class MuellerFitOptions:
    models: tuple = ("fmbrdf", "pplastic", "lambert")
    residual: str = "log"           # "log" or "relative" on f_r11
    noise: str = "residuals"        # "residuals" or "vanishing" (sigma_m), unless given
    noise_f: float = None           # given sigma_f (relative)
    noise_m: float = None           # given sigma_m (normalised elements)
    starts: int = 2
    max_evals: int = 60
    noise_rounds: int = 2           # re-estimations of the noise (each followed by a refinement)
    level: float = 0.95             # interval level
    max_rows: int = 50_000          # rows fitted per wavelength (a seeded subset beyond)
    seed: int = 0
    start_grids: dict = None        # {model: {shape parameter: values}} replacing START_GRIDS' entries
    share: tuple = ()               # parameters common to every wavelength (of the models that have them)

    def check(self):
        for m in self.models:
            get_model(m)
        if self.residual not in ("log", "relative"):
            raise ValueError(f"residual: must be 'log' or 'relative', got {self.residual!r}")
        if self.noise not in ("residuals", "vanishing"):
            raise ValueError(f"noise: must be 'residuals' or 'vanishing', got {self.noise!r}")
        for name in ("noise_f", "noise_m"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name}: must be a number > 0, got {v}")
        known = [n for m in self.models for n in parameter_names(m)]
        unknown = [n for n in self.share if n not in known]
        if unknown:
            raise ValueError(f"share: {unknown[0]!r} is not a parameter of {', '.join(self.models)}; valid: "
                             f"{', '.join(dict.fromkeys(known)) or 'none'}")


def parameter_names(model):
    """The fitted parameters of a model: its shape parameters, then its albedos."""
    m = get_model(model)
    return m.shape_names + m.albedo_names


@dataclasses.dataclass
class MuellerFitResult:
    model: str
    wavelength: float                # micrometres (NaN: none in the table)
    params: dict                     # shape parameters and albedos
    se: dict                         # standard errors
    interval: dict                   # name -> [lo, hi] at options.level
    interval_kind: dict              # name -> INTERVAL_FISHER, INTERVAL_PROFILE or INTERVAL_PROFILE_NEAR
    noise: dict                      # sigma_f, sigma_m, how they were obtained
    rmse: dict                       # log10 f_r11, normalised elements (unweighted)
    chi2: float
    dof: int
    n_rows: int
    at_bound: list
    converged: bool
    stop_reason: str
    history: list
    seconds: float                   # of this wavelength's fit (a joint fit: its share of the joint time)
    builds: int = 0                  # model evaluations at a shape point (MuellerValues.parts) of this fit
    shared: list = dataclasses.field(default_factory=list)   # parameters fitted jointly over the wavelengths


def solve_lm(prob, x0, max_evals, refresh=3, max_step=1.0, final=True):
    """Minimise |prob.fun|^2 from ``x0`` with the package's Levenberg-Marquardt (:mod:`fmbrdf_mi.fit.solve.lm`):
    (x, residuals, Jacobian at x, trials, converged, stop reason).  ``final``: end on a fresh Jacobian; else the
    Jacobian is None unless the last one is fresh (``prob.jac(x)`` gives it, the same, when it is needed).

    What this fit plugs in: a forward-difference Jacobian (one table build per shape parameter) refreshed after
    ``refresh`` accepted steps and carried between by Broyden's update from every trial (a trial costs one
    table build, a Jacobian four for FMBRDF); converged when the Gauss-Newton decrement of chi^2 on a fresh
    Jacobian is below ``lm.DECREMENT_TOL`` (the estimate within ~0.1 standard error of the optimum), or a step
    from a fresh Jacobian lowered chi^2 by less than that, or three steps in a row did (one secant step's small
    decrease says little; three say that the iteration creeps along a flat valley, as kappa's); steps shortened to ``max_step`` in every coordinate (as the MERL
    fit's, :func:`.fitting.levenberg_marquardt`); a budget of ``max_evals`` trials."""
    state = {"trials": 0, "fresh_step": True, "n_small": 0}
    r0 = prob.fun(x0)

    def linearise(x):     # (residuals, Jacobian, fresh)
        return (prob.fun(x), prob.jac(x), True)

    def solve(lin, lam):
        r, J, fresh = lin
        state["fresh_step"] = fresh
        step = LM.dense_step(J, r, lam)
        return step * min(1.0, max_step / max(np.abs(step).max(), 1e-300))

    def trial(x, step, lin):
        state["trials"] += 1
        r_new = prob.fun(x + step)
        return x + step, float(r_new @ r_new), r_new

    def secant(lin, x, x_new, r_new):
        r, J, _ = lin
        return (r, LM.broyden(J, x_new - x, r_new - r), False)

    def small(f, f_new):  # a step from a fresh Jacobian that barely lowers chi^2, or three in a row of any
        tiny = f - f_new < LM.DECREMENT_TOL
        state["n_small"] = state["n_small"] + 1 if tiny else 0
        return tiny and (state["fresh_step"] or state["n_small"] >= 3)

    res = LM.levenberg_marquardt(
        x0, float(r0 @ r0), linearise, solve, trial, max_iter=max_evals, refresh=refresh, secant=secant,
        moved=lambda lin, x_new, r_new: (r_new, lin[1], False),
        decrement=lambda lin: LM.gn_decrement(lin[1], lin[0]), small=small, small_count=1,
        budget=lambda: state["trials"] >= max_evals, final_linearise=final)
    r, J, fresh = res.lin
    J = J if fresh else None
    why = {"decrement": "converged: Gauss-Newton decrement below 0.01",
           "small_decrease": "converged: chi^2 decrease below 0.01",
           "no_step": "converged: no step lowers chi^2"}.get(res.reason, f"stopped: {res.reason} ({max_evals} trials)")
    return res.x, r, J, state["trials"], res.converged, why


class _Held:
    """A least-squares problem (``fun``, ``jac(x, columns)``) with coordinate ``k`` held at ``coord``: the
    problem of the other coordinates, what a profile refits."""

    def __init__(self, problem, k, coord):
        self.problem, self.k, self.coord = problem, k, coord

    def full(self, y):
        return np.insert(y, self.k, self.coord)

    def fun(self, y):
        return self.problem.fun(self.full(y))

    def jac(self, y, columns=None):
        free = [j for j in range(y.size + 1) if j != self.k]
        return self.problem.jac(self.full(y), free if columns is None else [free[c] for c in columns])


def profile_reference(problem, x, k, max_evals):
    """The cost at the optimum ``x`` refitted with coordinate ``k`` held (the profile's minimum, with the same
    weights and tolerance as its other points): (cost, the other coordinates)."""
    y0, r, *_ = solve_lm(_Held(problem, k, x[k]), np.delete(x, k), max_evals, final=False)
    return float(r @ r), y0


def profile_limit(problem, x, k, coord, value, end, step, level, max_evals, max_points=12, reference=None):
    """One end of a parameter's profile-likelihood interval: the value on the side of ``step`` from the fit's
    optimum ``x`` where the profiled cost, the weighted sum of squares minimised over the other coordinates with
    this one held, rises above its minimum by the chi-square quantile of one degree of freedom at ``level`` (the
    likelihood-ratio interval with the noise scale as estimated, i.e. as the residuals are weighted).  For a
    parameter at a bound, the open end of its one-sided interval.

    ``problem``: ``fun(x)`` (weighted residuals) and ``jac(x, columns)``; ``k``: the held coordinate;
    ``coord(v)``: its coordinate at the parameter's value v; ``value``: the value at ``x``; ``end``: the bound on
    that side (the search stops there); ``step``: the first trial's distance from ``value`` (signed: the side).
    Each profile point is a refit by :func:`solve_lm` from the nearest point already refitted; the minimum is
    :func:`profile_reference`'s (``reference``, computed when None), so that both ends of the rise are minima
    with the same weights.  Returns (limit, [(value, rise of the cost), ...]): the limit is ``end`` when the rise
    stays below the quantile up to there; after ``max_points`` refits, the end of the bracket farther from
    ``value`` (the wider, conservative interval)."""
    q = _z_quantile(level) ** 2
    c0, y0 = reference or profile_reference(problem, x, k, max_evals)
    points = [(value, 0.0, y0)]

    def rise(v):   # g(v) = sqrt(rise) - sqrt(q): near linear in v where the cost is near quadratic
        y_near = min(points, key=lambda p: abs(p[0] - v))[2]
        y, r, *_ = solve_lm(_Held(problem, k, coord(v)), y_near, max_evals, final=False)
        d = float(r @ r) - c0
        points.append((v, d, y))
        return math.sqrt(max(d, 0.0)) - math.sqrt(q)

    # bracket: doubling the distance from value until the rise passes q or the bound on that side is reached
    a, ga = value, -math.sqrt(q)
    v = value + step
    while True:
        if (v - end) * step >= 0:
            v = end
        g = rise(v)
        if g >= 0:
            break
        if v == end or len(points) > max_points:
            return end, [(p[0], p[1]) for p in points[1:]]
        a, ga = v, g
        v = value + 2.0 * (v - value)
    b, gb = v, g
    # Illinois regula falsi on g between a (g < 0) and b (g >= 0)
    side = 0
    while len(points) <= max_points:
        v = b - gb * (b - a) / (gb - ga)
        g = rise(v)
        if abs(points[-1][1] - q) < PROFILE_RISE_TOL:
            return v, [(p[0], p[1]) for p in points[1:]]
        if g < 0:
            a, ga = v, g
            gb = gb / 2 if side == -1 else gb
            side = -1
        else:
            b, gb = v, g
            ga = ga / 2 if side == 1 else ga
            side = 1
    return b, [(p[0], p[1]) for p in points[1:]]


def _z_quantile(level):
    from statistics import NormalDist

    return NormalDist().inv_cdf(0.5 + level / 2)


def vanishing_noise(table, max_sin=1e-6):
    """Model-free sigma_m: RMS of the elements that vanish for an isotropic surface in the plane of incidence
    (``VANISHING``, in the s/p bases), over the table's in-plane rows: (sigma or None, rows used)."""
    w_in, w_out = table.w_in, table.w_out
    sin = np.abs(np.cross(w_in, w_out) @ np.array([0.0, 0.0, 1.0])) / np.maximum(
        np.linalg.norm(w_in[:, :2], axis=1) * np.linalg.norm(w_out[:, :2], axis=1), 1e-300)
    flat = (np.linalg.norm(w_in[:, :2], axis=1) < 1e-9) | (np.linalg.norm(w_out[:, :2], axis=1) < 1e-9)
    rows = (sin < max_sin) & ~flat
    if rows.sum() < 3:
        return None, int(rows.sum())
    M = T.package_to_sp(table.mueller[rows], w_in[rows], w_out[rows])
    Mn = M / M[:, :1, :1]
    v = np.array([Mn[:, i, j] for i, j in VANISHING])
    return float(np.sqrt(np.mean(v ** 2))), int(rows.sum())


class _Problem:
    """One model on one wavelength's rows: residuals, Jacobian, covariance."""

    def __init__(self, model, table, options):
        self.model = get_model(model)
        self.o = options
        self.values = MuellerValues(self.model, table.w_in, table.w_out)
        self.f_obs = table.f_r11
        self.m_obs = table.normalised.reshape(-1, 16)[:, 1:]
        self.n = len(table)
        self.nsh = len(self.model.shape)
        self.nal = len(self.model.terms)
        from fmbrdf_mi.fit.evaluate.models import Bounds

        self.bounds = Bounds(self.model)
        self.sigma_f, self.sigma_m = 1.0, 1.0
        self._cache = collections.OrderedDict()

    def shape_of(self, x):
        return {p.name: self.bounds.to_value(p.name, x[k]) for k, p in enumerate(self.model.shape)}

    def parts(self, x, parts=None):
        """The terms at x; ``parts``: those to keep for x (already evaluated).  The most recently used are kept
        (:data:`PARTS_KEPT_BYTES`): a fit comes back to points it built (a Jacobian's, after another start or
        when the noise re-weights the residuals; the optimum's, for the noise and the covariance), and a build
        is what a fit's time goes to.  Kept by the coordinates' exact values: a fit's numbers are those it
        computes without keeping anything."""
        key = np.asarray(x[:self.nsh], dtype=np.float64).tobytes()
        if key in self._cache:
            self._cache.move_to_end(key)
        else:
            P = self.values.parts(self.shape_of(x)) if parts is None else parts
            while self._cache and (len(self._cache) + 1) * P.nbytes > PARTS_KEPT_BYTES:
                self._cache.popitem(last=False)
            self._cache[key] = P
        return self._cache[key]

    def forget(self):
        """Drops the kept terms (the start grid's are those of its exact values, not of their coordinates'
        round trip, which the refinement starts from)."""
        self._cache.clear()

    def raw(self, x):
        """Unweighted residuals: (f_r11 residuals (n,), element residuals (n, 15))."""
        return self.residuals_of(self.parts(x), np.exp(x[self.nsh:]))

    def residuals_of(self, P, albedos):
        """Unweighted residuals of terms P at ``albedos``."""
        M = combine(P, albedos)
        f = M[:, 0, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            rf = np.log(f / self.f_obs) if self.o.residual == "log" else f / self.f_obs - 1.0
            rm = (M / f[:, None, None]).reshape(-1, 16)[:, 1:] - self.m_obs
        bad = ~np.isfinite(rf)
        if bad.any():   # a model value of 0 (outside its support): a large finite residual
            rf = np.where(bad, 50.0, rf)
            rm = np.where(bad[:, None], 0.0, rm)
        return rf, rm

    def fun(self, x):
        return self.weighted(*self.raw(x))

    def weighted(self, rf, rm):
        return np.concatenate([rf / self.sigma_f, rm.ravel() / self.sigma_m])

    def value_jacobian(self, x):
        """The weighted residuals' Jacobian in the reported parameters (shape values, ln albedos) at x, by forward
        differences (backward at an upper bound): what the covariance needs also at a bound, where the bounded
        reparameterisation's derivative vanishes."""
        shape, al = self.shape_of(x), np.exp(x[self.nsh:])
        P0 = self.parts(x)
        r0 = self.weighted(*self.residuals_of(P0, al))
        J = np.empty((r0.size, x.size))
        for k, p in enumerate(self.model.shape):
            v = shape[p.name]
            lo, hi = self.bounds.lims[p.name][2:]
            h = 1e-3 * max(abs(v), 1e-2 * (hi - lo))
            h = h if v + h <= hi else -h
            P = self.values.parts(dict(shape, **{p.name: v + h}))
            J[:, k] = (self.weighted(*self.residuals_of(P, al)) - r0) / h
        for j in range(self.nal):
            a = al.copy()
            a[j] *= math.exp(1e-6)
            J[:, self.nsh + j] = (self.weighted(*self.residuals_of(P0, a)) - r0) / 1e-6
        return r0, J

    def jac(self, x, columns=None):
        """Forward-difference Jacobian of :meth:`fun` at x in the fitted coordinates, of ``columns`` (all when
        None)."""
        cols = range(x.size) if columns is None else columns
        r0 = self.fun(x)
        J = np.empty((r0.size, len(cols)))
        for c, k in enumerate(cols):
            h = 1e-3 if k < self.nsh else 1e-6
            xp = x.copy()
            xp[k] += h
            J[:, c] = (self.fun(xp) - r0) / h
        return J

    def cost(self, x):
        r = self.fun(x)
        return float(r @ r)

    def albedos_at(self, shape):
        """Albedos >= 0 minimising sum (f_model / f_obs - 1)^2 at ``shape`` (the grid's start).  The terms at
        ``shape`` are kept as those of its point x: one table build for the start's albedos and cost."""
        P = self.values.parts(shape)
        self.parts(self.x_of(shape, np.ones(self.nal)), parts=P)
        P = P[:, :, 0, 0] / self.f_obs          # (terms, n)
        A = P.T
        sol = np.linalg.lstsq(A, np.ones(self.n), rcond=None)[0]
        if (sol <= 0).any():
            best = None
            for j in range(len(sol)):
                x = max(A[:, j].sum() / max((A[:, j] ** 2).sum(), 1e-300), 1e-12)
                s = np.full(len(sol), 1e-12)
                s[j] = x
                c = float(np.sum((A @ s - 1) ** 2))
                if best is None or c < best[0]:
                    best = (c, s)
            sol = best[1]
        return np.maximum(sol, 1e-12)

    def x_of(self, shape, albedos):
        return np.concatenate([[self.bounds.to_z(p.name, shape[p.name]) for p in self.model.shape],
                               np.log(albedos)])

    def estimate_noise(self, x, used):
        """sigma_f, sigma_m from the residuals at x: each group's sum of squares over its degrees of freedom, its
        number of residuals less ``used`` (the parameters it absorbs: :func:`leverages`)."""
        rf, rm = self.raw(x)
        dof_f = max(rf.size - used[0], 1.0)
        dof_m = max(rm.size - used[1], 1.0)
        return (max(float(np.sqrt(rf @ rf / dof_f)), 1e-6),
                max(float(np.sqrt(np.sum(rm ** 2) / dof_m)), 1e-6))


def leverages(J, groups):
    """The parameters that each group of residuals absorbs: the sums over its rows of the hat matrix
    J (J^T J)^+ J^T's diagonal (its trace is the number of identified parameters).  A group's sum of squared
    residuals at a linear least squares optimum has expectation sigma^2 (its size - this), so it is what an
    unbiased noise estimate subtracts from each group; a parameter at a bound (a vanishing column of the
    bounded coordinates) absorbs nothing.  ``groups``: the sizes of consecutive row groups."""
    h = np.einsum("ij,jk,ik->i", J, np.linalg.pinv(J.T @ J), J)
    edges = np.cumsum([0] + list(groups))
    return [float(h[a:b].sum()) for a, b in zip(edges[:-1], edges[1:])]


def fit_model(model, table, options=None, vanishing=None):
    """Fit one model to one wavelength's rows of a :class:`.mueller.MuellerTable`: :class:`MuellerFitResult`.
    ``vanishing``: :func:`~fmbrdf_mi.brdf_fit.mueller_fit.vanishing_noise`'s sigma (computed here when None and needed)."""
    o = options or MuellerFitOptions()
    t0 = time.time()
    with polarised_variant():
        prob = _Problem(model, table, o)
        m = prob.model
        # noise: given, else a first guess refined from the residuals
        sf = o.noise_f if o.noise_f is not None else 0.05
        sm = o.noise_m if o.noise_m is not None else 0.02
        fixed_m = o.noise_m is not None
        if not fixed_m and o.noise == "vanishing":
            if vanishing is None:
                vanishing = vanishing_noise(table)[0]
            if vanishing is None:
                raise ValueError(f"{table.path}: noise 'vanishing' needs at least 3 rows in the plane of incidence "
                                 f"(none or too few in this table); use the residual estimate or give the noise")
            sm, fixed_m = vanishing, True
        prob.sigma_f, prob.sigma_m = sf, sm
        # 1. start grid
        grid = (o.start_grids or {}).get(m.name, START_GRIDS[m.name])
        unknown = [k for k in grid if k not in m.shape_names] + [k for k in m.shape_names if k not in grid]
        if unknown:
            raise ValueError(f"start grid of {m.name}: needs exactly {', '.join(m.shape_names) or 'no parameters'}, "
                             f"got {', '.join(grid) or 'none'}")
        names = tuple(grid)
        cands = []
        for vals in itertools.product(*(grid[n] for n in names)) if names else [()]:
            shape = dict(zip(names, vals))
            x = prob.x_of(shape, prob.albedos_at(shape))
            cands.append((prob.cost(x), x))
        cands.sort(key=lambda t: t[0])
        prob.forget()
        history = [{"stage": "grid", "points": len(cands), "best_cost": cands[0][0]}]
        # 2. refinement from the best starts; converged when chi^2 falls by less than lm.DECREMENT_TOL.  The
        #    Jacobian at an optimum is computed only where the noise estimate needs it (not for a start that loses)
        best = None
        for s, (c0, x0) in enumerate(cands[:max(1, o.starts)]):
            x, r, J, nfev, ok, status = solve_lm(prob, x0, o.max_evals, final=False)
            c = float(r @ r)
            history.append({"stage": "refine", "start": s, "start_cost": c0, "cost": c, "trials": nfev,
                            "status": status})
            if best is None or c < best[0]:
                best = (c, x, r, J, ok, status)
        c, x, r, J, ok, status = best
        # 3. the noise from the residuals at the optimum, then refined again while the weights change
        if o.noise_f is None or not fixed_m:
            for _ in range(o.noise_rounds):
                J = prob.jac(x) if J is None else J
                ef, em = prob.estimate_noise(x, leverages(J, (prob.n, 15 * prob.n)))
                new = (o.noise_f if o.noise_f is not None else ef, sm if fixed_m else em)
                change = max(abs(math.log(a / b)) for a, b in zip(new, (prob.sigma_f, prob.sigma_m)))
                prob.sigma_f, prob.sigma_m = new
                if change < 0.05:   # weights within 5 %: the optimum moves by a small fraction of its error
                    history.append({"stage": "noise", "sigma_f": new[0], "sigma_m": new[1], "change": change})
                    break
                x, r, J, nfev, ok, status = solve_lm(prob, x, o.max_evals, final=False)
                history.append({"stage": "noise", "sigma_f": new[0], "sigma_m": new[1], "change": change,
                                "cost": float(r @ r), "trials": nfev, "status": status})
        # 4. covariance: the Gauss-Newton one of the weighted residuals with the final sigmas, in the reported
        #    parameters (delta method on the albedos' logarithms); at or near a bound: the profile likelihood's
        r, J = prob.value_jacobian(x)
        cov = _inverse(J.T @ J)
        profiles = _profiles(prob, x, {k: (prob.bounds, p.name) for k, p in enumerate(m.shape)}, cov, o, history)
        return _result(prob, table, x, cov, r, r.size - x.size, fixed_m, ok, status, history, time.time() - t0,
                       profiles=profiles)


def _profiles(problem, x, shape, cov, o, history):
    """Profile-likelihood intervals (:func:`profile_limit`) of the shape parameters whose Fisher interval a bound
    cuts: {coordinate k of ``problem``: ([lo, hi], kind)}.  At the bound (``at_bound``): from the bound to the
    profile's limit (:data:`INTERVAL_PROFILE`); else both ends from the profile, an end at the bound where the
    profiled cost rises less than the quantile up to it (:data:`INTERVAL_PROFILE_NEAR`).  ``shape``:
    {k: (bounds, name)} of the coordinates that are shape parameters (bounded coordinates); ``cov``: the
    covariance of their values (the Fisher intervals, and the first steps' sizes)."""
    out = {}
    zq = _z_quantile(o.level)
    for k, (bounds, name) in shape.items():
        lo, hi = bounds.lims[name][2:]
        value = bounds.to_value(name, x[k])
        se = math.sqrt(cov[k, k]) if cov[k, k] > 0 and math.isfinite(cov[k, k]) else math.nan
        at = abs(x[k]) > AT_BOUND_Z
        if not at and not (math.isfinite(se) and (value - zq * se < lo or value + zq * se > hi)):
            continue
        step = max(zq * se if math.isfinite(se) and se > 0 else 0.05 * (hi - lo), 1e-3 * (hi - lo))
        sides = [1 if x[k] < 0 else -1] if at else [-1, 1]     # at the lower bound: open upwards
        t0 = time.time()
        reference = profile_reference(problem, x, k, o.max_evals)
        ends, record = [lo, hi], {}
        for side in sides:
            limit, points = profile_limit(problem, x, k, lambda v, n=name: bounds.to_z(n, v), value,
                                          hi if side > 0 else lo, side * step, o.level, o.max_evals,
                                          reference=reference)
            ends[side > 0] = limit
            record["upper" if side > 0 else "lower"] = {"limit": limit, "points": points}
        out[k] = (ends, INTERVAL_PROFILE if at else INTERVAL_PROFILE_NEAR)
        history.append({"stage": "profile", "parameter": name, "kind": out[k][1], **record,
                        "seconds": time.time() - t0})
    return out


def _inverse(A):
    try:
        return np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(A)


def _result(prob, table, x, cov, r, dof, fixed_m, ok, status, history, seconds, shared=(), profiles=None,
            builds=0):
    """The :class:`MuellerFitResult` of ``prob`` at its optimum ``x`` with covariance ``cov`` of the reported
    parameters (shape values, the albedos' logarithms) and weighted residuals ``r``; ``profiles``: {k: ([lo, hi],
    kind)}, the profile-likelihood intervals of :func:`_profiles` (the others' are Fisher intervals)."""
    profiles = profiles or {}
    o, m = prob.o, prob.model
    how = ["sigma_f given" if o.noise_f is not None else "sigma_f from the fit residuals",
           "sigma_m given" if o.noise_m is not None else
           "sigma_m from the elements that vanish in the plane of incidence" if fixed_m else
           "sigma_m from the fit residuals"]
    if shared:
        how.append(f"{', '.join(shared)} common to every wavelength")
    with polarised_variant():
        rf, rm = prob.raw(x)
    se_v = np.sqrt(np.maximum(np.diag(cov), 0.0))
    zq = _z_quantile(o.level)
    params, se, interval, kind = {}, {}, {}, {}
    for k, p in enumerate(m.shape):
        v = prob.bounds.to_value(p.name, x[k])
        lo, hi = prob.bounds.lims[p.name][2:]
        params[p.name] = v
        se[p.name] = float(se_v[k])
        if k in profiles:
            interval[p.name], kind[p.name] = [float(e) for e in profiles[k][0]], profiles[k][1]
        else:
            interval[p.name] = [max(lo, v - zq * se_v[k]), min(hi, v + zq * se_v[k])]
            kind[p.name] = INTERVAL_FISHER
    for j, name in enumerate(m.albedo_names):
        k = prob.nsh + j
        params[name] = float(np.exp(x[k]))
        se[name] = params[name] * float(se_v[k])
        interval[name] = [float(np.exp(x[k] - zq * se_v[k])), float(np.exp(x[k] + zq * se_v[k]))]
        kind[name] = INTERVAL_FISHER
    log10_f = (rf if o.residual == "log" else np.log1p(np.maximum(rf, -0.999999))) / math.log(10.0)
    return MuellerFitResult(
        model=m.name, wavelength=float(table.wavelength[0]) if len(table) else math.nan, params=params, se=se,
        interval=interval, interval_kind=kind,
        noise={"sigma_f": prob.sigma_f, "sigma_m": prob.sigma_m, "residual": o.residual,
               "model": f"independent Gaussian: {'ln' if o.residual == 'log' else 'relative'} f_r11 with sigma_f, "
                        f"each normalised element with sigma_m ({'; '.join(how)})"},
        rmse={"log10_f_r11": float(np.sqrt(np.mean(log10_f ** 2))), "elements": float(np.sqrt(np.mean(rm ** 2)))},
        chi2=float(r @ r), dof=int(round(dof)), n_rows=prob.n,
        at_bound=[p.name for k, p in enumerate(m.shape) if abs(x[k]) > AT_BOUND_Z],
        converged=ok, stop_reason=status, history=history, seconds=seconds, shared=list(shared),
        builds=builds + prob.values.builds)


class _Joint:
    """One model on several wavelengths with some parameters common to all: the wavelengths' weighted residuals
    stacked, each wavelength's parameter vector (its :class:`_Problem`'s layout) a selection of the joint vector
    ``[common..., own of the first wavelength..., own of the second..., ...]``; the Jacobian is block-sparse (a
    wavelength's rows depend on the common columns and its own), built from each wavelength's own Jacobian."""

    def __init__(self, probs, common):
        self.probs = probs
        p = probs[0].nsh + probs[0].nal
        self.common = list(common)
        own = [k for k in range(p) if k not in self.common]
        self.index = []
        for w in range(len(probs)):
            idx = np.empty(p, dtype=int)
            idx[self.common] = np.arange(len(self.common))
            idx[own] = len(self.common) + w * len(own) + np.arange(len(own))
            self.index.append(idx)
        self.size = len(self.common) + len(probs) * len(own)

    def split(self, xj):
        return [xj[idx] for idx in self.index]

    def join(self, xs):
        xj = np.empty(self.size)
        for idx, x in zip(self.index, xs):
            xj[idx] = x
        return xj

    def fun(self, xj):
        return np.concatenate([p.fun(x) for p, x in zip(self.probs, self.split(xj))])

    def _stack(self, blocks):
        J = np.zeros((sum(b.shape[0] for b in blocks), self.size))
        row = 0
        for idx, b in zip(self.index, blocks):
            J[row:row + b.shape[0], idx] = b
            row += b.shape[0]
        return J

    def jac(self, xj, columns=None):
        if columns is None:
            return self._stack([p.jac(x) for p, x in zip(self.probs, self.split(xj))])
        want = set(columns)
        blocks = []
        for p, x, idx in zip(self.probs, self.split(xj), self.index):
            local = [k for k in range(idx.size) if idx[k] in want]
            block = np.zeros((16 * p.n, idx.size))
            block[:, local] = p.jac(x, local)
            blocks.append(block)
        return self._stack(blocks)[:, list(columns)]

    def value_jacobian(self, xj):
        parts = [p.value_jacobian(x) for p, x in zip(self.probs, self.split(xj))]
        return np.concatenate([r for r, _ in parts]), self._stack([J for _, J in parts])


def fit_shared(model, tables, share, options=None, vanishing=None):
    """Fit one model to several wavelengths' rows (:class:`.mueller.MuellerTable` each) with the parameters
    ``share`` common to all and the others per wavelength: [:class:`MuellerFitResult`] per table.

    One joint weighted least squares: the residuals of every wavelength with that wavelength's sigmas, minimised
    by the solver of :func:`fit_model` over the common parameters and every wavelength's own.  It starts from
    the wavelengths' separate fits (each :func:`fit_model`, which also gives each wavelength's first noise
    estimate): the common parameters at the inverse-variance mean of their separate estimates.  The sigmas estimated from the
    residuals are then re-estimated per wavelength at the joint optimum, each wavelength's residuals over their
    degrees of freedom (less the parameters they absorb, :func:`leverages`: its own and part of the common
    ones), and the joint fit repeated while they change.  The covariance
    is the Gauss-Newton one of the joint residuals: a common parameter's interval combines the information of
    every wavelength (n wavelengths of equal information: 1/sqrt(n) of one wavelength's standard error)."""
    o = options or MuellerFitOptions()
    t0 = time.time()
    m = get_model(model)
    names = parameter_names(model)
    unknown = [n for n in share if n not in names]
    if unknown or not share:
        raise ValueError(f"share: {unknown[0] if unknown else 'nothing'!r} is not a parameter of {m.name}; valid: "
                         f"{', '.join(names)}")
    vanishing = vanishing or [None] * len(tables)
    alone = [fit_model(model, t, o, vanishing=v) for t, v in zip(tables, vanishing)]
    share_names = [n for n in names if n in share]
    common = [names.index(n) for n in share_names]
    fixed_m = o.noise_m is not None or o.noise == "vanishing"
    with polarised_variant():
        probs = []
        for t, r in zip(tables, alone):
            prob = _Problem(model, t, o)
            prob.sigma_f, prob.sigma_m = r.noise["sigma_f"], r.noise["sigma_m"]
            probs.append(prob)
        joint = _Joint(probs, common)
        # the common parameters start at the inverse-variance mean of their separate estimates (inside the
        # bounds unless every wavelength ends at one: a start at a bound would hold the fit there)
        est = np.array([[r.params[n] for n in share_names] for r in alone])
        w = 1.0 / np.maximum(np.array([[r.se[n] for n in share_names] for r in alone]), 1e-300) ** 2
        start = dict(zip(share_names, (w * est).sum(axis=0) / w.sum(axis=0)))
        xs = [p.x_of(dict(r.params, **start), [start.get(n, r.params[n]) for n in m.albedo_names])
              for p, r in zip(probs, alone)]
        x = joint.join(xs)
        history = [{"stage": "separate", "seconds": time.time() - t0,
                    "separate": {n: {"estimates": [r.params[n] for r in alone], "se": [r.se[n] for r in alone]}
                                 for n in share}}]
        x, r, J, nfev, ok, status = solve_lm(joint, x, o.max_evals, final=False)
        history.append({"stage": "joint", "cost": float(r @ r), "trials": nfev, "status": status})
        if o.noise_f is None or not fixed_m:
            for _ in range(o.noise_rounds):
                old = [(p.sigma_f, p.sigma_m) for p in probs]
                J = joint.jac(x) if J is None else J
                used = leverages(J, [k for p in probs for k in (p.n, 15 * p.n)])
                for w, (p, xw) in enumerate(zip(probs, joint.split(x))):
                    ef, em = p.estimate_noise(xw, used[2 * w:2 * w + 2])
                    p.sigma_f = o.noise_f if o.noise_f is not None else ef
                    p.sigma_m = p.sigma_m if fixed_m else em
                change = max(abs(math.log(a / b)) for p, ob in zip(probs, old)
                             for a, b in zip((p.sigma_f, p.sigma_m), ob))
                sig = [{"sigma_f": p.sigma_f, "sigma_m": p.sigma_m} for p in probs]
                if change < 0.05:
                    history.append({"stage": "noise", "sigmas": sig, "change": change})
                    break
                x, r, J, nfev, ok, status = solve_lm(joint, x, o.max_evals, final=False)
                history.append({"stage": "noise", "sigmas": sig, "change": change, "cost": float(r @ r),
                                "trials": nfev, "status": status})
        r, J = joint.value_jacobian(x)
        cov = _inverse(J.T @ J)
        shape = {int(idx[k]): (p.bounds, sp.name) for p, idx in zip(probs, joint.index)
                 for k, sp in enumerate(m.shape)}
        profiles = _profiles(joint, x, shape, cov, o, history)
    seconds = (time.time() - t0) / len(probs)
    used = leverages(J, [16 * p.n for p in probs])
    out, row = [], 0
    for p, t, xw, idx, u, sep in zip(probs, tables, joint.split(x), joint.index, used, alone):
        n = p.n * 16
        own = {k: profiles[idx[k]] for k in range(p.nsh) if idx[k] in profiles}
        out.append(_result(p, t, xw, cov[np.ix_(idx, idx)], r[row:row + n], n - u, fixed_m, ok, status,
                           history, seconds, shared=share_names, profiles=own, builds=sep.builds))
        row += n
    return out


def fit_table(table, options=None, progress=None):
    """Fit every model of ``options.models`` at every wavelength: {wavelength: {model: MuellerFitResult}}.  The
    parameters of ``options.share`` that a model has are common to every wavelength (``fit_shared``); a
    model with none of them is fitted per wavelength (:func:`fit_model`)."""
    o = options or MuellerFitOptions()
    o.check()
    say = progress or (lambda msg: None)
    wls = table.wavelengths()
    for wl in wls:   # every wavelength checked before any is fitted
        n = len(table.at_wavelength(wl))
        if n < 8:
            raise ValueError(f"{table.path}: wavelength {wl:g} µm has {n} rows; a fit needs at least 8")
    if o.share and len(wls) < 2:
        raise ValueError(f"share: {table.path} has one wavelength; parameters are shared over two or more")
    subs = []
    for wl in wls:
        sub = table.at_wavelength(wl)
        if len(sub) > o.max_rows:
            pick = np.sort(np.random.default_rng(o.seed).choice(len(sub), o.max_rows, replace=False))
            sub = sub.subset(pick)
        subs.append(sub)
    vans = [vanishing_noise(sub)[0] for sub in subs]
    out = {wl: {} for wl in wls}
    for name in o.models:
        share = [n for n in parameter_names(name) if n in o.share]
        if share:
            results = fit_shared(name, subs, share, o, vanishing=vans)
        else:
            results = [fit_model(name, sub, o, vanishing=v) for sub, v in zip(subs, vans)]
        for wl, res in zip(wls, results):
            out[wl][name] = res
            say(f"[fit-brdf] {_wl(wl)}: {name}: log10 RMSE of f_r11 {res.rmse['log10_f_r11']:.4f}, RMSE of the "
                f"normalised elements {res.rmse['elements']:.4f} ({res.seconds:.1f} s, {res.stop_reason}"
                f"{'; ' + ', '.join(share) + ' shared' if share else ''})")
    return out


def _wl(wl):
    return "no wavelength" if math.isnan(wl) else f"{wl:g} µm"


def predict(model, params, w_in, w_out):
    """The Mueller BRDF (n, 4, 4), package frames, of ``model`` at fitted ``params`` (a result's ``params``)."""
    m = get_model(model)
    with polarised_variant():
        P = MuellerValues(m, w_in, w_out).parts({n: params[n] for n in m.shape_names})
    return combine(P, [params[n] for n in m.albedo_names])


def prediction_errors(M_model, table):
    """Errors of a predicted Mueller BRDF against a table's rows: log10 RMSE of f_r11; RMSE of the DoLP of
    reflected unpolarised light; RMSE of the normalised elements; and the signed polarisation element m21 in
    the s/p bases (> 0: s-polarised): its RMSE and the share of rows where its sign agrees with the data's
    (over rows where the data's ``|m21|`` exceeds 0.02)."""
    f_mod, f_obs = M_model[:, 0, 0], table.f_r11
    Mn_mod = M_model / f_mod[:, None, None]
    Mn_obs = table.normalised
    dolp = lambda Mn: np.hypot(Mn[:, 1, 0], Mn[:, 2, 0])
    sp_mod = T.package_to_sp(Mn_mod, table.w_in, table.w_out)
    sp_obs = T.package_to_sp(Mn_obs, table.w_in, table.w_out)
    m21_mod, m21_obs = sp_mod[:, 1, 0], sp_obs[:, 1, 0]
    big = np.abs(m21_obs) > 0.02
    return {"log10_f_r11": float(np.sqrt(np.mean(np.log10(f_mod / f_obs) ** 2))),
            "dolp": float(np.sqrt(np.mean((dolp(Mn_mod) - dolp(Mn_obs)) ** 2))),
            "elements": float(np.sqrt(np.mean((Mn_mod - Mn_obs).reshape(-1, 16)[:, 1:] ** 2))),
            "m21_sp": float(np.sqrt(np.mean((m21_mod - m21_obs) ** 2))),
            "m21_sign_agrees": float(np.mean(np.sign(m21_mod[big]) == np.sign(m21_obs[big]))) if big.any() else None,
            "n_rows": len(table)}


def synthetic_table(model, params, w_in, w_out, noise_f=0.0, noise_m=0.0, seed=0):
    """A model's Mueller BRDF at ``params`` with the noise model of this module (f_r11 times exp(noise_f e),
    normalised elements plus noise_m e, e standard normal): (n, 4, 4), package frames."""
    M = predict(model, params, w_in, w_out)
    rng = np.random.default_rng(seed)
    f = M[:, 0, 0] * np.exp(noise_f * rng.standard_normal(len(M)))
    Mn = M / M[:, :1, :1]
    Mn = Mn + noise_m * rng.standard_normal(Mn.shape)
    Mn[:, 0, 0] = 1.0
    return Mn * f[:, None, None]


def goniometer_geometries(theta_i=(20.0, 40.0, 60.0), theta_o=tuple(range(-75, 80, 10)),
                          phi_o=(0.0, 45.0, 90.0, 135.0)):
    """Direction pairs of a goniometric scan: the source at polar angles ``theta_i`` in the x-z plane (azimuth
    180 degrees, SCATMECH's), the viewer at signed polar angles ``theta_o`` in planes of azimuth ``phi_o``
    (0: the plane of incidence, positive angles forward): (w_in, w_out), each (n, 3)."""
    w_in, w_out = [], []
    for ti in theta_i:
        for po in phi_o:
            for to in theta_o:
                if to == 0 and po != phi_o[0]:
                    continue
                w_in.append(T.directions(-ti, 0.0))
                w_out.append(T.directions(to, po))
    return np.array(w_in), np.array(w_out)


def random_geometries(n, seed=0, max_theta=80.0):
    """``n`` direction pairs uniform in solid angle above the surface up to ``max_theta`` degrees."""
    rng = np.random.default_rng(seed)
    c0 = math.cos(math.radians(max_theta))

    def dirs():
        c = rng.uniform(c0, 1.0, n)
        p = rng.uniform(0, 2 * np.pi, n)
        s = np.sqrt(1 - c * c)
        return np.stack([s * np.cos(p), s * np.sin(p), c], axis=1)

    return dirs(), dirs()
