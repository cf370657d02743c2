"""Standard errors, 95 % intervals and correlations of the estimates (fit.json's ``uncertainty``).

:func:`covariance` composes the estimators (inverse Fisher information, :func:`paper_sandwich`, :func:`incidental`),
:func:`summary` makes fit.json's block; covariances are of the reported parameters.  Design: docs/computed.md.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit.solve.driver import refit_fixed
from fmbrdf_mi.fit.solve.optimise import time_left

Z95 = 1.959963984540054
#: 95 % quantiles of chi^2 with 1 ... 8 degrees of freedom.
CHI2_95 = (3.841458820694124, 5.991464547107979, 7.814727903251178, 9.487729036781154, 11.070497693516351,
           12.591587243743977, 14.067140449340169, 15.507313055865453)

#: Weakly identified: SE > this fraction of max(|value|, WEAK_FLOOR[name]), or at a bound.
WEAK_REL = 0.05
WEAK_FLOOR = {"kappa": 10.0}
#: A shape parameter within this fraction of its range (optimiser's scale) of a bound is at it.
AT_BOUND_FRAC = 1e-3
#: ``interval_kind`` of an end cut at the parameter's bound: the data do not rule the bound out.
FISHER_AT_BOUND = "fisher, open at the bound"
#: An albedo is *determined* where SE <= this fraction of it; a split is *identified* where k_s and k_b are.
SPLIT_REL = 0.5

#: ``FitOptions.intervals``' values.
INTERVALS = ("auto", "profile", "fisher")
#: Relative tolerance on chi^2's rise at a Fisher interval's end (:func:`profile_intervals`).
PROFILE_TOL = 0.15
#: Relative tolerance of a profile end's chi^2 rise (:func:`profile_end`).
PROFILE_ROOT_TOL = 0.1
#: A profile refit stops when its predicted decrease of chi^2 is below this x PROFILE_ROOT_TOL x the rise.
PROFILE_REFIT_TOL = 0.25
#: A start's end this many SE from the estimate in some shape parameter is another optimum.
MODE_SEPARATION_SE = 2.0

#: The pixel-area quadrature is refined while its bias (:func:`quadrature_bias`) exceeds this many SE.
QUADRATURE_TOL = 0.2
#: The finest quadrature: points per raw-pixel side.
MAX_AREA_POINTS = 8
#: A sampled check refines while |bias| plus this many sampling SEs exceeds :data:`QUADRATURE_TOL`.
QUADRATURE_SAMPLING_SE = 2.0


def dtheta_dz(problem, st, names, h=1e-6):
    """(p, p): derivatives of the reported free parameters with respect to z (central differences)."""

    def at(z):
        s = problem.from_z(z)
        rp = problem.params.report(s.shape, s.a_s, s.a_b)
        return np.array([rp[n] for n in names])

    z = problem.to_z(st)
    G = np.zeros((len(names), len(z)))
    for j, e in enumerate(np.eye(len(z)) * h):
        G[:, j] = (at(z + e) - at(z - e)) / (2 * h)
    return G


def bound_distance(problem, st):
    """{free shape parameter: (distance to its nearest bound, that as a fraction of its optimiser-scale range)}."""
    out = {}
    for n in problem.names:
        tlo, thi, lo, hi = problem.bounds.lims[n]
        v, t = st.shape[n], problem.bounds.to_scale(n, st.shape[n])
        out[n] = (min(v - lo, hi - v), min(t - tlo, thi - t) / (thi - tlo))
    return out


def at_bound(problem, st, sd=None):
    """Free shape parameters within :data:`AT_BOUND_FRAC` of a bound (:func:`bound_distance`) or, given ``sd``
    {name: SE}, closer to it than 1.96 SE: their interval is not a confidence interval."""
    sd = sd or {}
    return [n for n, (d, frac) in bound_distance(problem, st).items()
            if frac <= AT_BOUND_FRAC or (math.isfinite(sd.get(n, math.nan)) and d < Z95 * sd[n])]


def jacobian_in_reported(problem, st, J):
    """(names, J_theta): the residuals' Jacobian with respect to the reported free parameters."""
    names = list(problem.names) + ([] if problem.projects else list(problem.params.albedo_names))
    return names, J @ np.linalg.inv(dtheta_dz(problem, st, names))


#: Floor of 1 - lambda in :func:`incidental_sandwich`: no SE inflated more than 1 / this over Fisher's.
INCIDENTAL_FLOOR = 0.1

#: Above this noise share (:func:`incidental_sandwich`) the sandwich understates the spread over captures.
NOISE_SHARE_MAX = 0.5


#: The estimators (one per fit), as ``uncertainty.method`` names them.
ESTIMATORS = {
    "fisher": "inverse Fisher information",
    "incidental": "incidental-parameter sandwich H^-1 (J^T J) H^-1, H = J^T J - C (the per-pixel albedos' noise "
                  "removed from the information)",
    "posterior": "posterior covariance (Bayesian): the inverse of the information penalised by the albedo maps' "
                 "smoothness prior (J^T J of the residuals with the prior's rows, the albedos eliminated)",
    "paper-sandwich": "sandwich estimate for the paper's loss, leave-neighbourhood-out residuals (CR3)",
    "not-converged": "not computed: the fit did not converge",
    "singular-reparameterisation": "singular reparameterisation",
    "singular-information": "singular information matrix",
}

#: Qualifiers of the estimator: the covariance's scale or the residuals' correlation.
QUALIFIERS = {
    "known-noise": " (known camera noise)",
    "estimated-noise": ", noise level estimated from the residuals",
    "misfit": ", inflated by chi^2/dof (misfit)",
    "demosaic": ", with the correlation of neighbouring pixels (demosaicking)",
}

#: Notes on other mechanisms, in the method text's order (``{}``: the entry's detail).
NOTES = {
    "incidental-layout": "{}",
    "incidental-capped": "H not positive definite in {} direction(s): their inflation capped at "
                         f"{1 / INCIDENTAL_FLOOR:g}x the Fisher standard error",
    "incidental-unreliable": "in one direction {} of the information J^T J is the per-pixel albedos' noise "
                             f"(above {NOISE_SHARE_MAX:g}): these standard errors and intervals understate the "
                             "spread over captures and are not confidence intervals; fit several lights of "
                             "the same view",
    "incidental-not-computed": "{}",
    "profile-skipped": "intervals not checked against the profile likelihood (max_time reached)",
    "profile": "profile-likelihood 95 % intervals where the Fisher ones fail (interval_kind)",
    "optima": "95 % intervals widened over a competing optimum of the likelihood (interval_kind 'optima', "
              "other_optima)",
    "quadrature": "pixel-area quadrature {}",
}


def method_text(applied):
    """fit.json's ``uncertainty.method`` from ``applied`` [(kind, detail)], in the tables' order."""
    done = dict(applied)
    unknown = [k for k in done if k not in ESTIMATORS and k not in QUALIFIERS and k not in NOTES]
    estimators = [k for k in ESTIMATORS if k in done]
    if unknown or len(estimators) != 1:
        raise ValueError(f"method_text: expected one estimator and known mechanisms, got {', '.join(done)}")
    head = ESTIMATORS[estimators[0]] + "".join(QUALIFIERS[k] for k in QUALIFIERS if k in done)
    return "; ".join([head] + [NOTES[k].format(done[k]) for k in NOTES if k in done])


def incidental_term(problem, st, parts):
    """C (p, p) in z of an eliminating layout (:meth:`PixelAlbedos.incidental`) at ``st``, else None."""
    if not problem.eliminates:
        return None
    obj = problem.obj
    z = problem.to_z(st)
    dcols = obj.albedo_column_derivatives(parts, z, problem.names, problem.bounds)
    return problem.layout.incidental(*obj.albedo_columns(parts), dcols)


def incidental_sandwich(F, C):
    """(cov, capped, share): H^-1 F H^-1, H = F - C, with 1 - lambda (lambda the eigenvalues of
    F^-1/2 C F^-1/2) floored at :data:`INCIDENTAL_FLOOR` (C from few samples per albedo is noisy), the number
    of directions floored, and the noise share max lambda: the largest share, in one direction, of the
    information that is the eliminated albedos' noise.  LinAlgError if F is singular."""
    w, V = np.linalg.eigh(F)
    if w.min() <= 0:
        raise np.linalg.LinAlgError("singular information matrix")
    R = V / np.sqrt(w)
    lam, Q = np.linalg.eigh(R.T @ C @ R)
    d = 1.0 - lam
    capped = int(np.sum(d < INCIDENTAL_FLOOR))
    T = R @ Q
    return (T / np.maximum(d, INCIDENTAL_FLOOR) ** 2) @ T.T, capped, float(lam.max())


def noise_scale(problem, r, n_independent, p):
    """(scale, info, applied): scale = chi^2 / (N - p) when the noise is estimated or misfits (chi^2/dof more
    than max(0.1, 5 sqrt(2 / (N - p))) above 1), else 1; ``info``: fit.json's ``chi2_per_dof`` and flags."""
    n = int(n_independent if n_independent is not None else len(r))
    chi2 = float(r @ r)
    info = {"chi2_per_dof": chi2 / max(n - p, 1)}
    if not problem.obj.noise.known:
        return info["chi2_per_dof"], info, [("estimated-noise", "")]
    far = max(0.1, 5.0 * math.sqrt(2.0 / max(n - p, 1)))
    info["misfit"] = bool(info["chi2_per_dof"] > 1.0 + far)
    if info["chi2_per_dof"] < 1.0 - far:
        info["noise_overstated"] = True
        info["noise_warning"] = misfit_text(info)
    if info["misfit"]:
        return info["chi2_per_dof"], info, [("known-noise", ""), ("misfit", "")]
    return 1.0, info, [("known-noise", "")]


def incidental(problem, st, J, names, Hi, scale, parts=None):
    """(cov_theta / scale, cov_z / scale, info, applied): :func:`incidental_sandwich` from Kaufman's ``J``, or
    ``Hi`` for a layout without the term."""
    lay, why = problem.layout, problem.layout.incidental_reason
    if why is not None:
        return Hi, None, {"incidental_not_computed": why}, [("incidental-not-computed", why)]
    parts = problem.parts(st, jac=True) if parts is None else parts
    Gd = dtheta_dz(problem, st, names)
    cz, capped, share = incidental_sandwich(J.T @ J, scale * incidental_term(problem, st, parts))
    fisher_sd = np.sqrt(np.clip(np.diag(Hi), 0.0, None) * scale)
    info = {"incidental": {"fisher_std_errors": dict(zip(names, fisher_sd.tolist())), "capped_directions": capped,
                           "noise_share": share, "reliable": share <= NOISE_SHARE_MAX}}
    applied = [(k, v) for k, v, on in (("incidental-layout", lay.incidental_method, lay.incidental_method),
                                       ("incidental-capped", capped, capped),
                                       ("incidental-unreliable", f"{share:.2f}", share > NOISE_SHARE_MAX)) if on]
    return Gd @ cz @ Gd.T, cz, info, applied


def paper_sandwich(problem, Jt, r, Hi):
    """(cov, applied): the paper's loss's sandwich H^-1 M H^-1 from leave-N(a)-out residuals (cluster
    jackknife "CR3"), N(a) pixel a or, demosaicked, its 3 x 3 neighbours."""
    row_pix, grid = np.asarray(problem.obj.row_pixels(len(r))), problem.obj.grid
    npx = int(row_pix.max()) + 1
    order = np.argsort(row_pix, kind="stable")
    counts = np.bincount(row_pix, minlength=npx)
    rows = -np.ones((npx, int(counts.max())), int)         # padded with -1
    rows[row_pix[order], np.arange(len(row_pix)) - np.repeat(np.cumsum(counts) - counts, counts)] = order
    nb = np.arange(npx)[:, None]                            # each block's pixels, its own first
    if grid is not None:
        pr, pc = (np.asarray(x) - np.min(x) + 1 for x in grid)
        lut = -np.ones((pr.max() + 2, pc.max() + 2), int)
        lut[pr, pc] = np.arange(npx)
        nb = np.stack([lut[pr + dr, pc + dc] for dr in (0, -1, 1) for dc in (0, -1, 1)], 1)
        nb = np.take_along_axis(nb, np.argsort(nb < 0, axis=1, kind="stable"), 1)
    R = rows.shape[1]
    g = np.where(nb[:, :, None] >= 0, rows[np.clip(nb, 0, None)], -1).reshape(npx, -1)
    Jg = np.concatenate([Jt, np.zeros((1, Jt.shape[1]))])[g]   # padding (-1): the zero row
    rg = np.concatenate([r, [0.0]])[g]
    A = np.eye(Jg.shape[1])[None] - np.einsum("nbi,ij,ncj->nbc", Jg, Hi, Jg)
    try:
        rt = np.linalg.solve(A, rg[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a block that determines a parameter on its own (leverage 1)
        rt = np.einsum("nbc,nc->nb", np.linalg.pinv(A, rcond=1e-10), rg)
    M = np.einsum("nbi,nb->ni", Jg[:, :R], rt[:, :R]).T @ np.einsum("nbi,nb->ni", Jg, rt)
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    M = (V * np.clip(w, 0.0, None)) @ V.T
    return Hi @ M @ Hi, [("paper-sandwich", "")] + ([("demosaic", "")] if grid is not None else [])


@dataclasses.dataclass
class Covariance:
    """:func:`covariance`'s result; ``cov`` None if not computed, ``cov_z`` the shape's for an eliminating layout."""

    names: list
    cov: object
    info: dict
    applied: list
    cov_z: object = None

    @property
    def method(self):
        return method_text(self.applied)


def covariance(problem, st, J, r, n_independent=None, parts=None):
    """The :class:`Covariance` of the reported free parameters."""
    try:
        names, Jt = jacobian_in_reported(problem, st, J)
    except np.linalg.LinAlgError:
        names = list(problem.names) + list(problem.params.albedo_names)
        return Covariance(names, None, {}, [("singular-reparameterisation", "")])
    try:
        Hi = np.linalg.inv(Jt.T @ Jt)      # inverse Fisher information
        if not problem.obj.is_likelihood:
            cov, applied = paper_sandwich(problem, Jt, r, Hi)
            return Covariance(names, cov, {}, applied)
        scale, info, applied = noise_scale(problem, r, n_independent, Jt.shape[1])
        cz, estimator = None, "posterior" if problem.obj.prior is not None else "fisher"
        if problem.eliminates and Jt.shape[1]:
            Hi, cz, more, used = incidental(problem, st, J, names, Hi, scale, parts)
            info, applied = {**info, **more}, applied + used
            estimator = "incidental" if cz is not None else estimator
    except np.linalg.LinAlgError:
        return Covariance(names, None, {}, [("singular-information", "")])
    cov = scale * Hi
    if problem.projects and not problem.eliminates:
        names, cov = problem.with_albedo_rows(st, parts or problem.parts(st, jac=True), names, cov, scale,
                                              np.linalg.lstsq(J, Jt, rcond=None)[0])
    return Covariance(names, cov, info, [(estimator, "")] + applied, None if cz is None else cz * scale)


def kind_of(ends):
    """One ``interval_kind`` from its two ends' kinds: the kind, or ``lower ..., upper ...``."""
    return ends[0] if ends[0] == ends[1] else f"lower {ends[0]}, upper {ends[1]}"


def profiled(kinds):
    """The names of ``kinds`` (``interval_kind``) with an end from the profile likelihood."""
    return [n for n, k in kinds.items() if "profile" in k]


def summary(problem, st, c):
    """fit.json's uncertainty block from the :class:`Covariance` ``c``."""
    se = {} if c.cov is None else dict(zip(c.names, np.sqrt(np.clip(np.diag(c.cov), 0.0, None)).tolist()))
    out = {"std_errors": se, "ci95": {}, "correlation": None, "at_bound": at_bound(problem, st, se), **c.info,
           "method": c.method}
    if c.cov is None:
        return out
    out["bound_distance_se"] = {n: (float(d / se[n]) if se.get(n, 0.0) > 0 else math.inf)
                                for n, (d, _) in bound_distance(problem, st).items()}
    rep, kinds = problem.params.report(st.shape, st.a_s, st.a_b), {}
    for n, s in se.items():
        blo, bhi = problem.bounds.lims[n][2:] if n in problem.names else (
            0.0 if n in problem.params.albedo_names else -math.inf, math.inf)
        lo, hi = rep[n] - Z95 * s, rep[n] + Z95 * s
        out["ci95"][n] = [float(max(lo, blo)), float(min(hi, bhi))]
        if lo <= blo or hi >= bhi:
            kinds[n] = kind_of([FISHER_AT_BOUND if cut else "fisher" for cut in (lo <= blo, hi >= bhi)])
    if kinds:
        out["interval_kind"] = kinds
    sd = np.array(list(se.values()))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):     # a noise-free fit's: inf, nan
        corr = np.clip(np.nan_to_num(c.cov / np.outer(sd, sd), nan=0.0, posinf=1.0, neginf=-1.0), -1.0, 1.0)
    out["correlation"] = {"names": c.names, "matrix": np.round(corr, 4).tolist()}
    return out


def quadrature_bias(problem, fine, st, J, r):
    """{shape parameter: shift / Fisher SE} between ``problem`` (m x m points) and ``fine`` (2m x 2m):
    -(J^T J)^-1 J^T (r - r_fine), 3/4 of the coarse bias (the midpoint rule's error falls 4x per halving)."""
    parts = fine.parts(st)
    fine.set_weights(parts, st)
    return shift_in_se(problem, J, J.T @ (r - fine.obj.residuals(parts, st)))


def shift_in_se(problem, J, g, V=None):
    """{shape parameter: -(J^T J)^-1 g / its unscaled Fisher SE}; with ``V`` (the covariance of ``g``) also
    {shape parameter: the shift's SE / that SE}."""
    Hi = np.linalg.pinv(J.T @ J)
    b, se = -Hi @ g, np.sqrt(np.clip(np.diag(Hi), 1e-300, None))
    shift = {n: float(b[i] / se[i]) for i, n in enumerate(problem.names)}
    if V is None:
        return shift
    sb = np.sqrt(np.clip(np.diag(Hi @ V @ Hi), 0.0, None))
    return shift, {n: float(sb[i] / se[i]) for i, n in enumerate(problem.names)}


def predicted_quadrature_terms(problem, coarser, st, J, r, m, h):
    """(cells, p) each cell's J_c^T d_c, d (m x m less 2m x 2m residuals) extrapolated from ``coarser``
    (h x h points) by the midpoint rule's 1/m^2 error: the control variate of :func:`sampled_quadrature_bias`."""
    r_h = ((coarser.obj.y - coarser.obj.mu(coarser.parts(st), st)) / np.sqrt(problem.obj.var)).ravel()
    d, ms = 0.75 / m ** 2 / (1.0 / h ** 2 - 1.0 / m ** 2) * (r_h - r), problem.obj.m
    return np.einsum("rp,r->rp", J, d).reshape(len(d) // ms, ms, -1).sum(1)


def quadrature_sample(problem, J, g_hat, n, rng):
    """(cells, pi): a Poisson sample of about ``n`` cells and their inclusion probabilities, a quarter uniform
    and three quarters in proportion to each cell's predicted shift, capped at 1."""
    N, k = len(g_hat), len(problem.names)
    if n >= N:
        return np.arange(N), np.ones(N)
    Hi = np.linalg.pinv(J.T @ J)
    se = np.sqrt(np.clip(np.diag(Hi), 1e-300, None))
    size = np.sqrt(np.sum((g_hat @ (Hi[:k] / se[:k, None]).T) ** 2, axis=1))
    w = 0.25 / N + (0.75 * size / size.sum() if size.sum() > 0 else 0.75 / N)
    c = float(n)
    for _ in range(50):                     # capped probabilities sum to n
        pi = np.minimum(1.0, c * w)
        free = pi < 1.0
        if abs(pi.sum() - n) <= 1e-9 * n or not free.any():
            break
        c *= (n - (~free).sum()) / pi[free].sum()
    cells = np.flatnonzero(rng.random(N) < pi)
    return cells, pi[cells]


def sampled_quadrature_bias(problem, fine, st, J, r, cells, pi, g_hat):
    """(bias, sampling SE) of :func:`quadrature_bias` from ``cells`` only (``fine``: their 2m x 2m problem):
    the predicted terms plus the Horvitz-Thompson sum of their errors, unbiased whatever the prediction."""
    ms = problem.obj.m
    if problem.eliminates:      # the sampled cells' own albedos
        C = 1 if problem.layout.channel_of is None else int(problem.layout.channel_of.max()) + 1
        g = np.searchsorted(*[lay.pixels * C + (0 if lay.channel_of is None else lay.channel_of)
                              for lay in (problem.layout, fine.layout)])
        st = dataclasses.replace(st, a_s=np.asarray(st.a_s)[g], a_b=np.asarray(st.a_b)[g])
    mu = fine.obj.mu(fine.parts(st), st)
    r_fine = ((fine.obj.y - mu) / np.sqrt(np.maximum(problem.obj.noise.variance(mu), 1e-300))).ravel()
    rows = (np.asarray(cells)[:, None] * ms + np.arange(ms)).ravel()
    e = np.einsum("rp,r->rp", J[rows], r[rows] - r_fine).reshape(len(cells), ms, -1).sum(1) - g_hat[cells]
    G = g_hat.sum(0) + (e / pi[:, None]).sum(0)
    V = (e * ((1.0 - pi) / pi ** 2)[:, None]).T @ e
    return shift_in_se(problem, J, G, V)


def interval_scale(problem, unc):
    """The covariance's scale (:func:`noise_scale`) from ``unc``; a 95 % chi^2 rise is 1.96^2 times it."""
    c = unc.get("chi2_per_dof")
    return float(c) if c and (unc.get("misfit") or not problem.obj.noise.known) else 1.0


def sandwich_ratio(unc, name):
    """(SE / Fisher SE)^2 of ``name`` under the incidental sandwich, else 1 (chi^2's curvature is J^T J's)."""
    fse = unc.get("incidental", {}).get("fisher_std_errors") or {}
    return (unc["std_errors"][name] / fse[name]) ** 2 if fse.get(name) else 1.0


def chi2_along_covariance(problem, st, J, scale):
    """f(name, value): chi^2 with the other unknowns at their regression on ``name`` (>= the profile);
    ``f.state``: its State."""
    z0 = problem.to_z(st)
    # at a bound the z-variance is huge: regressing on it would throw a parameter to its other bound
    pinned = [i for i, (_, frac) in enumerate(bound_distance(problem, st).values()) if frac <= AT_BOUND_FRAC]
    covs = {}

    def state(name, value):
        j, z = problem.names.index(name), z0.copy()
        if j in pinned:
            z[j] = problem.bounds.to_z(name, value)
        else:
            keep = tuple(i for i in range(len(z0)) if i == j or i not in pinned)
            if keep not in covs:
                Jk = J if len(keep) == len(z0) else J[:, keep]
                covs[keep] = np.zeros((len(z0), len(z0)))
                covs[keep][np.ix_(keep, keep)] = np.linalg.pinv(Jk.T @ Jk) * scale
            c = covs[keep]
            z = z0 + c[:, j] / c[j, j] * (problem.bounds.to_z(name, value) - z0[j])
        s = problem.from_z(z)
        s.shape[name] = float(value)   # exactly: z is clipped to +-Z_MAX
        return problem.closed_form(s.shape)[0] if problem.projects else s

    def f(name, value):
        s = state(name, value)
        return problem.obj.value(problem.parts(s), s)

    f.state = state
    return f


def profile_end(problem, st, name, side, start, delta, chi2_min, path, max_refits=3):
    """(end, kind, [(value, rise)], evaluations): where chi^2 refitted with ``name`` fixed rises by ``delta`` on
    ``side`` (-1, +1); secant then false position on sqrt(rise), linear for a quadratic likelihood."""
    b = problem.bounds
    bound = b.lims[name][2 if side < 0 else 3]
    t0 = b.to_scale(name, st.shape[name])
    room = abs(b.to_scale(name, bound) - t0)
    u = min(abs(b.to_scale(name, start) - t0), room)
    pts, inside, outside, g_target = [], (0.0, 0.0), None, math.sqrt(delta)    # inside, outside: (|u|, sqrt(rise))
    evals = 0
    for k in range(max_refits):
        u = min(max(u, 1e-9 * max(room, 1.0)), room)
        v = b.from_scale(name, t0 + side * u) if u < room else bound
        chi2, n = refit_fixed(problem, st, name, v, path.state(name, v), tol=PROFILE_REFIT_TOL * PROFILE_ROOT_TOL
                              * delta, label=f"profile {name} {'lower' if side < 0 else 'upper'}")
        rise, evals = chi2 - chi2_min, evals + n
        pts.append((float(v), float(rise)))
        g = math.sqrt(max(rise, 0.0))
        if abs(rise / delta - 1.0) < PROFILE_ROOT_TOL:
            return float(v), "profile", pts, evals
        if g >= g_target:
            outside = (u, g)
        elif u >= room:
            return float(bound), "profile, open at the bound", pts, evals
        else:
            inside = (u, g)
        if outside is None:      # secant, at most x4
            u = min(u * (g_target / g if g > 0 else 4.0), 4.0 * u, room)
        else:
            (ua, ga), (ub, gb) = inside, outside
            fallback = 0.5 * (ua + ub) if k + 1 < max_refits else ub
            u = ua + (g_target - ga) * (ub - ua) / (gb - ga) if gb > ga else fallback
    if outside is None:
        return float(pts[-1][0]), "profile, at least", pts, evals
    return float(b.from_scale(name, t0 + side * u)), "profile", pts, evals


def profile_intervals(problem, st, unc, J, r, every=False, progress=None):
    """Replace each Fisher interval end where chi^2 does not rise by 1.96^2 x scale (within :data:`PROFILE_TOL`)
    by the profile likelihood's; with the incidental sandwich the rise is x :func:`sandwich_ratio` (adjusted
    likelihood ratio, Varin, Reid and Firth 2011, sec. 4.2) and ends only widen.  Returns the mechanisms."""
    if not problem.obj.is_likelihood or not unc.get("ci95") or problem.with_fixed({}) is None:
        return []
    chi2_min, scale = float(r @ r), interval_scale(problem, unc)
    try:
        path = chi2_along_covariance(problem, st, J, scale)
    except np.linalg.LinAlgError:
        return []
    sandwich = unc.get("incidental", {}).get("fisher_std_errors") is not None
    kinds, details, thresholds, fisher_ci = {}, {}, {}, {n: list(v) for n, v in unc["ci95"].items()}
    names, t0 = [n for n in problem.names if 0 < (unc["std_errors"].get(n) or 0) < math.inf], time.time()
    if progress is not None:
        progress(f"[fit] interval check: {len(names)} parameters against the profile likelihood")
    for j, n in enumerate(names):
        delta = Z95 ** 2 * scale * sandwich_ratio(unc, n)
        if sandwich:
            thresholds[n] = delta
        (lo, hi), ends, kind, tried = problem.bounds.lims[n][2:], list(unc["ci95"][n]), [], {}
        for i, side in enumerate((-1, 1)):
            cut = ends[i] <= lo or ends[i] >= hi
            rise = tried["fisher_end_rise" if i else "fisher_start_rise"] = float(path(n, ends[i]) - chi2_min)
            kind.append(FISHER_AT_BOUND if cut else "fisher")
            if every or not (rise <= delta * (1 + PROFILE_TOL) if cut else abs(rise / delta - 1) <= PROFILE_TOL):
                end, k, tried["upper" if i else "lower"], evals = profile_end(problem, st, n, side, ends[i], delta,
                                                                               chi2_min, path)
                tried.setdefault("evaluations", {})["upper" if i else "lower"] = evals
                if not (sandwich and side * (end - ends[i]) < 0):
                    ends[i], kind[i] = end, k
        kinds[n], details[n] = kind_of(kind), tried
        unc["ci95"][n] = [float(min(ends[0], st.shape[n])), float(max(ends[1], st.shape[n]))]
        if progress is not None:
            dt = time.time() - t0
            progress(f"[fit] interval check: {n} done, {j + 1}/{len(names)} parameters ({dt:.1f} s"
                     + (f", {time_left(dt, j + 1, len(names), 'in the check')})" if j + 1 < len(names) else ")"))
    unc["interval_kind"] = {**{n: k for n, k in unc.get("interval_kind", {}).items() if n not in kinds}, **kinds}
    unc["profile"] = {"threshold": Z95 ** 2 * scale, "rises": details, "fisher_ci95": fisher_ci,
                      **({"thresholds": thresholds} if thresholds else {})}
    return [("profile", "")] if profiled(kinds) else []


def noise_flagged(unc):
    """Whether ``unc`` flags chi^2/dof far from 1 with the stated noise (:func:`misfit_text`)."""
    return bool(unc.get("misfit") or unc.get("noise_overstated"))


def misfit_text(unc):
    """The one-line warning of chi^2/dof far above or below 1 with the stated camera noise."""
    c = unc["chi2_per_dof"]
    if unc.get("noise_overstated"):
        return (f"chi^2/dof = {c:.3g} with the stated camera noise: the data scatter less than that noise "
                f"(by sqrt(chi^2/dof) = {math.sqrt(c):.3g}); the noise settings (gain, read noise) or the noise "
                "model are wrong, and the standard errors, computed from the stated noise, are too large")
    return (f"chi^2/dof = {c:.3g} with the stated camera noise: the model (geometry, light, BSDF) or the noise "
            f"settings do not explain the data; the standard errors are inflated by sqrt(chi^2/dof) = "
            f"{math.sqrt(c):.3g}")


def weakly_identified(table, params, std, at_bound_=()):
    """Names of ``params`` with SE > :data:`WEAK_REL` x max(|value|, :data:`WEAK_FLOOR`), or in ``at_bound_``."""
    floor = {k: WEAK_FLOOR.get(table.row[k].base if k in table.row else k, 0.0) for k in params}
    return [k for k, v in params.items()
            if (k in std and (not math.isfinite(std[k]) or std[k] > WEAK_REL * max(abs(v), floor[k])))
            or k in at_bound_]


def determined(value, se, rel=SPLIT_REL):
    """Where ``se`` <= ``rel`` x ``value``."""
    value, se = np.asarray(value, float), np.asarray(se, float)
    with np.errstate(invalid="ignore"):
        return np.isfinite(se) & (se <= rel * value)


def pixel_albedos(problem, st, parts, J, unc, cov_z=None):
    """:meth:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos.maps` of an eliminating layout; ``cov_z``: the
    shape's covariance in z (default (J^T J)^+ x scale)."""
    obj, lay, scale = problem.obj, problem.layout, interval_scale(problem, unc)
    us, ub = obj.albedo_columns(parts)
    Jt = obj.shape_jacobian(parts, st, problem.to_z(st), problem.names, problem.bounds)
    try:
        if cov_z is None:
            cov_z = np.linalg.pinv(J.T @ J) * scale if J.shape[1] else np.zeros((0, 0))
    except np.linalg.LinAlgError:
        cov_z = np.full((J.shape[1], J.shape[1]), np.nan)
    return lay.maps(st.a_s, st.a_b, lay.covariance(us, ub, Jt, cov_z, scale), problem.model.albedo_factor,
                    SPLIT_REL)


def other_optima(starts, params, unc, names):
    """(optima, threshold): the ends of ``starts`` more than :data:`MODE_SEPARATION_SE` from ``params``; one
    *competes* when converged with delta_chi2 below :data:`CHI2_95` [p] x scale x :func:`sandwich_ratio`."""
    se = unc.get("std_errors") or {}
    names = [n for n in names if 0 < (se.get(n) or 0) < math.inf]
    scored = [s for s in starts if s.get("score") is not None and math.isfinite(s["score"])]
    if len(scored) < 2 or not names:
        return [], None
    best = min(s["score"] for s in scored)
    scale = float(unc["chi2_per_dof"]) if unc.get("misfit") and unc.get("chi2_per_dof") else 1.0
    inflation = max([1.0] + [sandwich_ratio(unc, n) for n in names])
    threshold = CHI2_95[min(len(names), len(CHI2_95)) - 1] * scale * inflation
    out = []
    for s in scored:
        dist, d = max(abs(s["end"][n] - params[n]) / se[n] for n in names), 2.0 * (s["score"] - best)
        if dist > MODE_SEPARATION_SE:
            out.append({"params": {n: float(s["end"][n]) for n in names}, "delta_chi2": float(d),
                        "distance_se": float(dist), "converged": bool(s.get("converged")),
                        "competing": bool(s.get("converged")) and d < threshold})
    return out, float(threshold)


def widen_for_optima(unc, params, optima, lims=None):
    """Widen each 95 % interval to cover the same half-widths around each competing optimum, cut at ``lims``;
    returns the names widened."""
    comp, ci, before = [o for o in optima if o["competing"]], unc.get("ci95") or {}, {}
    for n in [n for n in ci if comp and all(n in o["params"] for o in comp)]:
        (lo, hi), v = ci[n], params[n]
        blo, bhi = (lims or {}).get(n, (-math.inf, math.inf))
        new = [max(blo, min([lo] + [o["params"][n] - (v - lo) for o in comp])),
               min(bhi, max([hi] + [o["params"][n] + (hi - v) for o in comp]))]
        if new[0] < lo or new[1] > hi:
            before[n], ci[n] = [float(lo), float(hi)], [float(x) for x in new]
    if before:
        unc.setdefault("interval_kind", {n: "fisher" for n in ci}).update(dict.fromkeys(before, "optima"))
        unc.setdefault("other_optima", {})["widened"] = before
    return list(before)


def optima_text(optima, threshold):
    """One line for the warning about competing optima (:func:`other_optima`), or None."""
    comp = [o for o in optima if o["competing"]]
    if not comp:
        return None
    o = min(comp, key=lambda x: x["delta_chi2"])
    where = ", ".join(f"{n} {v:.4g}" for n, v in o["params"].items())
    return (f"another optimum of the likelihood ({where}) is only {o['delta_chi2']:.1f} worse in chi^2 "
            f"(below the joint 95 % threshold {threshold:.1f}): the data do not decide between the two; the 95 % "
            "intervals are widened to cover both; add images under other lights, or fix a parameter")
