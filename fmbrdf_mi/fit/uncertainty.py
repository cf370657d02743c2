"""Standard errors, 95 % intervals and correlations of the estimates (fit.json's ``uncertainty``).

Entry point :func:`covariance` (then :func:`summary`); one function per mechanism: :func:`fisher`,
:func:`paper_sandwich`, :func:`incidental`, :func:`profile_intervals`, :func:`other_optima`.  Covariances are
of the reported parameters (delta method through d theta / d z); intervals are theta +- 1.96 SE cut at the
bounds.  The design: docs/computed.md.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from fmbrdf_mi.fit.solve.driver import refit_fixed
from fmbrdf_mi.fit.solve.optimise import time_left

Z95 = 1.959963984540054


#: Weakly identified: SE > this fraction of max(|value|, WEAK_FLOOR[name]), or at a bound.
WEAK_REL = 0.05
WEAK_FLOOR = {"kappa": 10.0}

#: A shape parameter within this fraction of its range (optimiser's scale) of a bound is at it.
AT_BOUND_FRAC = 1e-3


def _free_names(problem):
    return list(problem.names) + list(problem.params.albedo_names)


def dtheta_dz(problem, st, names):
    """(p, p): derivatives of the reported free parameters with respect to z (central differences)."""
    z = problem.to_z(st)
    G = np.zeros((len(names), len(z)))
    for j in range(len(z)):
        h = 1e-6
        vals = []
        for d in (h, -h):
            zp = z.copy()
            zp[j] += d
            sp = problem.from_z(zp)
            rp = problem.params.report(sp.shape, sp.a_s, sp.a_b)
            vals.append(np.array([rp[n] for n in names]))
        G[:, j] = (vals[0] - vals[1]) / (2 * h)
    return G


def bound_distance(problem, st):
    """{free shape parameter: (distance to its nearest bound in its units, as a fraction of its range on the
    optimiser's scale)}."""
    out = {}
    for n in problem.names:
        tlo, thi, lo, hi = problem.bounds.lims[n]
        v = st.shape[n]
        t = problem.bounds.to_scale(n, v)
        out[n] = (min(v - lo, hi - v), min(t - tlo, thi - t) / (thi - tlo))
    return out


def at_bound(problem, st, sd=None):
    """Free shape parameters within :data:`AT_BOUND_FRAC` of a bound (:func:`bound_distance`) or, given
    ``sd`` {name: SE}, closer to it than 1.96 SE: their interval is not a confidence interval."""
    out = []
    for n, (d, frac) in bound_distance(problem, st).items():
        se = (sd or {}).get(n)
        if frac <= AT_BOUND_FRAC or (se is not None and math.isfinite(se) and d < Z95 * se):
            out.append(n)
    return out


def jacobian_in_reported(problem, st, J):
    """(names, J_theta): the residuals' Jacobian with respect to the reported free parameters."""
    names = _free_names(problem)
    G = dtheta_dz(problem, st, names)
    return names, J @ np.linalg.inv(G)


#: Floor of 1 - lambda in :func:`incidental_sandwich`: no SE inflated more than 1 / this over Fisher's.
INCIDENTAL_FLOOR = 0.1

#: Above this :func:`noise_share` the sandwich's H = F - C is the small difference of two noisy matrices in
#: some direction (more of Kaufman's information there is the albedos' noise than the data's): its errors
#: understate the spread over captures (docs/benchmarks/coverage.md), and :func:`incidental` estimates H from
#: the albedos pooled over windows of the pixel grid instead (:func:`pooled_sandwich`).
NOISE_SHARE_MAX = 0.5

#: Half-width in pixels of :func:`pooling_windows`' square windows.
POOL_RADIUS = 2


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
    "incidental-pooled": "in one direction {} of the information J^T J is the per-pixel albedos' noise (above "
                         f"{NOISE_SHARE_MAX:g}): H is the information at the albedos pooled over "
                         f"{2 * POOL_RADIUS + 1} x {2 * POOL_RADIUS + 1}-pixel windows less their noise, the "
                         "covariance H^-1 (H + C) H^-1 (exact where the albedos are constant over each window)",
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
    """fit.json's ``uncertainty.method`` from ``applied`` [(kind, detail)]: one :data:`ESTIMATORS` kind, its
    :data:`QUALIFIERS`, then the :data:`NOTES`, in the tables' order."""
    done = dict(applied)
    unknown = [k for k in done if k not in ESTIMATORS and k not in QUALIFIERS and k not in NOTES]
    estimators = [k for k in ESTIMATORS if k in done]
    if unknown or len(estimators) != 1:
        raise ValueError(f"method_text: expected one estimator and known mechanisms, got {', '.join(done)}")
    head = ESTIMATORS[estimators[0]] + "".join(QUALIFIERS[k] for k in QUALIFIERS if k in done)
    return "; ".join([head] + [NOTES[k].format(done[k]) for k in NOTES if k in done])


def incidental_columns(problem, st, parts):
    """(us, ub, dcols) of an eliminating layout at ``st``: the whitened unit-albedo columns and their
    derivatives in z (:meth:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective.albedo_column_derivatives`)."""
    obj = problem.obj
    dcols = obj.albedo_column_derivatives(parts, problem.to_z(st), problem.names, problem.bounds)
    return (*obj.albedo_columns(parts), dcols)


def incidental_term(problem, st, parts):
    """C (p, p) in z of an eliminating layout (:meth:`PixelAlbedos.incidental`) at ``st``, else None."""
    if not problem.eliminates:
        return None
    return problem.layout.incidental(*incidental_columns(problem, st, parts))


def _shares(F, C):
    """(R, lambda, Q): F^-1/2 = R V^T and the eigen-decomposition of F^-1/2 C F^-1/2 in that basis.  Raises
    LinAlgError when F is singular."""
    w, V = np.linalg.eigh(F)
    if w.min() <= 0:
        raise np.linalg.LinAlgError("singular information matrix")
    R = V / np.sqrt(w)                        # F^-1/2 = R V^T, R = V w^-1/2
    lam, Q = np.linalg.eigh(R.T @ C @ R)      # in F's metric (symmetric: V^T F^-1/2 C F^-1/2 V)
    return R, lam, Q


def noise_share(F, C):
    """The largest eigenvalue of F^-1/2 C F^-1/2 (F = J^T J, C :func:`incidental_term` x scale): the largest
    fraction, along one direction of the shape, of Kaufman's information that is the eliminated albedos' noise
    (C) rather than the data's (H = F - C).  Raises LinAlgError when F is singular."""
    return float(_shares(F, C)[1].max()) if len(F) else 0.0


def incidental_sandwich(F, C):
    """(cov, capped): H^-1 F H^-1, H = F - C (F = J^T J, C :func:`incidental_term` x scale), and the number of
    directions capped: 1 - lambda (eigenvalues of F^-1/2 C F^-1/2) is floored at :data:`INCIDENTAL_FLOOR`
    because C from few samples per albedo is noisy.  Raises LinAlgError when F is singular."""
    R, lam, Q = _shares(F, C)
    d = 1.0 - lam
    capped = int(np.sum(d < INCIDENTAL_FLOOR))
    d = np.maximum(d, INCIDENTAL_FLOOR)
    T = R @ Q                                 # cov = F^-1/2 (I - L)^-2 F^-1/2 in these coordinates
    return (T / d ** 2) @ T.T, capped


def fisher(Jt):
    """(J^T J)^-1, ``Jt`` the whitened residuals' Jacobian in the reported parameters; LinAlgError if singular."""
    return np.linalg.inv(Jt.T @ Jt)


def noise_scale(problem, r, n_independent, p):
    """(scale, info, applied): the covariance's factor, fit.json's ``chi2_per_dof`` and ``misfit``, the
    mechanisms.  scale = chi^2 / (N - p) when the noise is estimated, or when it is known and chi^2/dof exceeds
    1 by more than max(0.1, 5 sqrt(2 / (N - p))) (``misfit``); as far below 1 it stays 1 (``noise_overstated``)."""
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
    """(cov_theta / scale, cov_z / scale, info, applied): the incidental-parameter sandwich
    (:func:`incidental_sandwich`) of an eliminating layout, the Fisher errors it replaces and the
    :func:`noise_share` in ``info``.  Above :data:`NOISE_SHARE_MAX` H comes from pooled albedos
    (:func:`pooled_sandwich`; ``difference_std_errors`` keeps those of H = J^T J - C), or where they cannot be
    pooled ``reliable`` is False and the method says the errors are not confidence intervals; a layout without
    the term keeps ``Hi`` (cov_z None).  ``J``: Kaufman's projected Jacobian in z.  Raises LinAlgError."""
    if problem.layout.incidental_reason is not None:
        reason = problem.layout.incidental_reason
        return Hi, None, {"incidental_not_computed": reason}, [("incidental-not-computed", reason)]
    if parts is None:
        parts = problem.parts(st, jac=True)
    Gd = dtheta_dz(problem, st, names)                   # theta = theta(z): cov_theta = G cov_z G^T
    F, C = J.T @ J, scale * incidental_term(problem, st, parts)
    cz, capped = incidental_sandwich(F, C)
    share = noise_share(F, C)
    pooled = pooled_information(problem, st, parts, scale) if share > NOISE_SHARE_MAX else None
    fisher_sd = np.sqrt(np.clip(np.diag(Hi), 0.0, None) * scale)
    info = {"incidental": {"fisher_std_errors": dict(zip(names, fisher_sd.tolist())), "capped_directions": capped,
                           "noise_share": share, "reliable": share <= NOISE_SHARE_MAX or pooled is not None}}
    if pooled is not None:
        diff_sd = np.sqrt(np.clip(np.diag(Gd @ cz @ Gd.T), 0.0, None) * scale)
        info["incidental"]["difference_std_errors"] = dict(zip(names, diff_sd.tolist()))
        cz, capped = pooled_sandwich(*pooled, C)
        info["incidental"]["capped_directions"] = capped
    applied = []
    if problem.layout.incidental_method:
        applied.append(("incidental-layout", problem.layout.incidental_method))
    if capped:
        applied.append(("incidental-capped", capped))
    if share > NOISE_SHARE_MAX:
        applied.append(("incidental-unreliable" if pooled is None else "incidental-pooled", f"{share:.2f}"))
    return Gd @ cz @ Gd.T, cz, info, applied


def pooling_windows(layout, radius=POOL_RADIUS):
    """The groups of each group's window: the same channel's pixels within ``radius`` pixels in x and in y of
    a per-pixel layout's (:class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`) pixel, as (2 radius + 1)^2
    arrays (n_groups,), -1 where that pixel is not fitted, the first the group itself; None when the layout
    has no pixel grid (``width`` None)."""
    width = layout.width
    if width is None:
        return None
    pix = np.asarray(layout.pixels, dtype=np.int64)
    ch = np.zeros_like(pix) if layout.channel_of is None else np.asarray(layout.channel_of, dtype=np.int64)
    nch = int(ch.max()) + 1 if len(ch) else 1
    lookup = np.full(int((pix * nch + ch).max()) + 1 if len(pix) else 1, -1)
    lookup[pix * nch + ch] = np.arange(len(pix))
    col = pix % width
    steps = [(0, 0)] + [(i, j) for i in range(-radius, radius + 1) for j in range(-radius, radius + 1) if i or j]
    out = []
    for i, j in steps:
        key = (pix + i * width + j) * nch + ch
        ok = (col + j >= 0) & (col + j < width) & (key >= 0) & (key < len(lookup))
        out.append(np.where(ok, lookup[np.where(ok, key, 0)], -1))
    return out


def pooled_information(problem, st, parts, scale):
    """(H_w, C_w) in z, C_w x ``scale``: :meth:`~fmbrdf_mi.fit.evaluate.albedos.AlbedoLayout.pooled_information`
    at the fitted albedos over :func:`pooling_windows`, or None (no pixel grid, coupled albedos)."""
    windows = pooling_windows(problem.layout)
    if windows is None:
        return None
    out = problem.layout.pooled_information(*incidental_columns(problem, st, parts), st.a_s, st.a_b, windows)
    return None if out is None else (out[0], scale * out[1])


def pooled_sandwich(Hw, Cw, C):
    """(cov, capped): H^-1 (H + C) H^-1, H = H_w - C_w (:func:`pooled_information`), C :func:`incidental_term`
    x scale, and the directions where 1 - (the share of C_w in H_w) is floored at :data:`INCIDENTAL_FLOOR`.

    With the albedos eliminated (mu = A(theta) a, linear in a: :mod:`~fmbrdf_mi.fit.evaluate.albedos`) the
    profile score of the shape has expected derivative H = sum_g a_g^T A_gj^T (I - P_g) A_gk a_g
    and variance H + C (Neyman and Scott; C depends on the shape only).  H depends on the true albedos, which
    one image's per-pixel estimates know so poorly that J^T J - C is the small difference of two noisy
    matrices (:func:`noise_share`); solved over a window of m pixels the albedos carry about 1 / m of that
    noise, and C_w removes its mean, so H_w - C_w estimates H without bias wherever the albedos are constant
    over each window (an albedo map smooth on that scale).  Raises LinAlgError when H_w is singular."""
    R, lam, Q = _shares(Hw, Cw)
    d = 1.0 - lam
    capped = int(np.sum(d < INCIDENTAL_FLOOR))
    T = R @ Q                                 # H^-1 = T (I - L)^-1 T^T in these coordinates
    Hinv = (T / np.maximum(d, INCIDENTAL_FLOOR)) @ T.T
    return Hinv + Hinv @ C @ Hinv, capped


def paper_sandwich(problem, Jt, r, Hi):
    """(cov, applied): the paper's loss's sandwich H^-1 M H^-1, H = J^T J, M :func:`block_meat` (spread, not
    bias: docs/computed.md)."""
    grid = problem.obj.grid
    M = block_meat(Jt, r, problem.obj.row_pixels(len(r)), Hi, grid)
    return Hi @ M @ Hi, [("paper-sandwich", "")] + ([("demosaic", "")] if grid is not None else [])


@dataclasses.dataclass
class Covariance:
    """:func:`covariance`'s result: ``cov`` of ``names`` (None if not computed), fit.json's ``info``, the
    mechanisms ``applied``, and for an eliminating layout the shape's ``cov_z`` in z."""

    names: list
    cov: object
    info: dict
    applied: list
    cov_z: object = None

    @property
    def method(self):
        return method_text(self.applied)


def covariance(problem, st, J, r, n_independent=None, parts=None):
    """The :class:`Covariance` of the reported free parameters: :func:`paper_sandwich` for the paper's loss;
    for a likelihood :func:`fisher` x :func:`noise_scale`, with :func:`incidental` for an eliminating layout."""
    try:
        names, Jt = jacobian_in_reported(problem, st, J)
    except np.linalg.LinAlgError:
        return Covariance(_free_names(problem), None, {}, [("singular-reparameterisation", "")])
    p = Jt.shape[1]
    try:
        Hi = fisher(Jt)
    except np.linalg.LinAlgError:
        return Covariance(names, None, {}, [("singular-information", "")])
    if not problem.obj.is_likelihood:
        cov, applied = paper_sandwich(problem, Jt, r, Hi)
        return Covariance(names, cov, {}, applied)
    scale, info, applied = noise_scale(problem, r, n_independent, p)
    estimator, cz = "posterior" if problem.obj.prior is not None else "fisher", None
    if problem.eliminates and p:
        try:
            Hi, cz, more, used = incidental(problem, st, J, names, Hi, scale, parts)
        except np.linalg.LinAlgError:
            return Covariance(names, None, {}, [("singular-information", "")])
        info.update(more)
        applied += used
        estimator = "incidental" if cz is not None else estimator
    return Covariance(names, scale * Hi, info, [(estimator, "")] + applied, None if cz is None else cz * scale)


def _blocks(row_pix, grid):
    """(rows (n, R) padded with -1: each pixel's residual rows, nb (n, K) padded with -1: its block's pixels)."""
    row_pix = np.asarray(row_pix)
    npx = int(row_pix.max()) + 1
    order = np.argsort(row_pix, kind="stable")
    counts = np.bincount(row_pix, minlength=npx)
    R = int(counts.max())
    rows = -np.ones((npx, R), int)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = np.arange(len(row_pix)) - np.repeat(start, counts)
    rows[row_pix[order], k] = order
    if grid is None:
        return rows, np.arange(npx)[:, None]
    pr, pc = (np.asarray(g) for g in grid)
    r0, c0 = pr.min(), pc.min()
    lut = -np.ones((pr.max() - r0 + 3, pc.max() - c0 + 3), int)
    lut[pr - r0 + 1, pc - c0 + 1] = np.arange(npx)
    nb = np.stack([lut[pr - r0 + 1 + dr, pc - c0 + 1 + dc] for dr in (0, -1, 1) for dc in (0, -1, 1)], 1)
    nb = np.stack([np.concatenate([row[row >= 0], row[row < 0]]) for row in nb])  # own pixel first
    return rows, nb


def block_meat(J, r, row_pix, Hi, grid=None):
    """M = sum_a u_a (sum_{b in N(a)} u_b)^T with leave-N(a)-out residuals (I - P_gg)^-1 r_g, P = J H^-1 J^T
    (cluster jackknife "CR3"), since the fit pulls plain residuals towards the data.  ``row_pix``: each row's
    pixel; ``grid``: the pixels' (rows, cols) when 3 x 3 neighbours are correlated, else None.  PSD-projected."""
    rows, nb = _blocks(row_pix, grid)
    npx, R = rows.shape
    p = J.shape[1]
    g = np.where(nb[:, :, None] >= 0, rows[np.clip(nb, 0, None)], -1).reshape(npx, -1)  # (n, K R)
    valid = g >= 0
    Jz = np.concatenate([J, np.zeros((1, p))])
    rz = np.concatenate([r, [0.0]])
    Jg = Jz[np.where(valid, g, -1)]                      # (n, B, p), zero rows where padded
    rg = rz[np.where(valid, g, -1)]                      # (n, B)
    P = np.einsum("nbi,ij,ncj->nbc", Jg, Hi, Jg)
    A = np.eye(Jg.shape[1])[None] - P
    try:
        rt = np.linalg.solve(A, rg[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a block that determines a parameter on its own (leverage 1)
        rt = np.einsum("nbc,nc->nb", np.linalg.pinv(A, rcond=1e-10), rg)
    ua = np.einsum("nbi,nb->ni", Jg[:, :R], rt[:, :R])   # the pixel's own rows
    ug = np.einsum("nbi,nb->ni", Jg, rt)                 # the whole block
    M = ua.T @ ug
    M = 0.5 * (M + M.T)
    w, V = np.linalg.eigh(M)
    return (V * np.clip(w, 0.0, None)) @ V.T


#: ``interval_kind`` of an interval end: value -+ 1.96 SE beyond the parameter's bound, cut there; the data do
#: not rule out the bound, so the interval is open there rather than narrow.
FISHER_AT_BOUND = "fisher, open at the bound"


def kind_of(ends):
    """One ``interval_kind`` from its two ends' kinds: the kind, or ``lower ..., upper ...``."""
    return ends[0] if ends[0] == ends[1] else f"lower {ends[0]}, upper {ends[1]}"


def profiled(kinds):
    """The names of ``kinds`` (``interval_kind``) with an end from the profile likelihood."""
    return [n for n, k in kinds.items() if "profile" in k]


def summarise(problem, st, J, r, n_independent=None, parts=None):
    """The uncertainty block of fit.json: :func:`summary` of :func:`covariance`."""
    return summary(problem, st, covariance(problem, st, J, r, n_independent, parts))


def summary(problem, st, c):
    """fit.json's uncertainty block from the :class:`Covariance` ``c``."""
    names, cov = c.names, c.cov
    rep = problem.params.report(st.shape, st.a_s, st.a_b)
    albedos = set(problem.params.albedo_names)
    out = {"std_errors": {}, "ci95": {}, "correlation": None, "at_bound": at_bound(problem, st), **c.info,
           "method": c.method}
    if cov is None:
        return out
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se = dict(zip(names, sd.tolist()))
    out["at_bound"] = at_bound(problem, st, se)
    out["bound_distance_se"] = {n: (float(d / se[n]) if se.get(n, 0.0) > 0 else math.inf)
                                for n, (d, _) in bound_distance(problem, st).items()}
    kinds = {}
    for i, n in enumerate(names):
        lo, hi = rep[n] - Z95 * sd[i], rep[n] + Z95 * sd[i]
        blo, bhi = problem.bounds.lims[n][2:] if n in problem.names else (0.0 if n in albedos else -math.inf, math.inf)
        cut = [lo <= blo, hi >= bhi]
        if any(cut):
            kinds[n] = kind_of([FISHER_AT_BOUND if c else "fisher" for c in cut])
        out["std_errors"][n] = float(sd[i])
        out["ci95"][n] = [float(max(lo, blo)), float(min(hi, bhi))]
    if kinds:
        out["interval_kind"] = kinds
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        corr = cov / np.outer(sd, sd)
    # a degenerate covariance (a noise-free fit) gives inf/nan; a correlation is in [-1, 1]
    corr = np.clip(np.nan_to_num(corr, nan=0.0, posinf=1.0, neginf=-1.0), -1.0, 1.0)
    out["correlation"] = {"names": names, "matrix": np.round(corr, 4).tolist()}
    return out


#: The pixel-area quadrature is refined while its bias (:func:`quadrature_bias`) exceeds this many SE.
QUADRATURE_TOL = 0.2

#: The finest quadrature: points per raw-pixel side.
MAX_AREA_POINTS = 8


def quadrature_bias(problem, fine, st, J, r):
    """{shape parameter: first-order shift / unscaled Fisher SE} between ``problem`` (m x m points; ``J``,
    ``r`` at ``st``) and ``fine`` (2m x 2m): -(J^T J)^-1 J^T (r - r_fine), 3/4 of the coarse bias (the
    midpoint rule's error falls 4x per halving)."""
    parts = fine.parts(st)
    fine.set_weights(parts, st)
    d = r - fine.obj.residuals(parts, st)
    return shift_in_se(problem, J, J.T @ d)


def shift_in_se(problem, J, g, V=None):
    """{shape parameter: -(J^T J)^-1 g / its unscaled Fisher SE}; with ``V`` (the covariance of ``g``) also
    {shape parameter: the shift's SE / that SE}."""
    Hi = np.linalg.pinv(J.T @ J)
    b = -Hi @ g
    se = np.sqrt(np.clip(np.diag(Hi), 1e-300, None))
    shift = {n: float(b[i] / se[i]) for i, n in enumerate(problem.names)}
    if V is None:
        return shift
    sb = np.sqrt(np.clip(np.diag(Hi @ V @ Hi), 0.0, None))
    return shift, {n: float(sb[i] / se[i]) for i, n in enumerate(problem.names)}


#: A sampled check (:func:`sampled_quadrature_bias`) refines while |bias| plus this many of its sampling
#: standard errors exceeds :data:`QUADRATURE_TOL`: a bias the sample cannot rule out is refined.
QUADRATURE_SAMPLING_SE = 2.0


def cell_terms(J, d, ms):
    """(cells, p) each cell's J_c^T d_c: ``J`` (cells ms, p), ``d`` (cells ms,), ``ms`` rows per cell."""
    return np.einsum("rp,r->rp", J, d).reshape(len(d) // ms, ms, -1).sum(1)


def predicted_quadrature_terms(problem, coarser, st, J, r, m, h):
    """(cells, p) each cell's J_c^T d_c (d: ``problem``'s residuals with m x m points less those with
    2m x 2m) predicted from ``coarser``, the same cells with h x h points (h < m): the midpoint rule's error
    falls as 1/m^2, so d = (r_h - r_m) (1/m^2 - 1/4m^2) / (1/h^2 - 1/m^2) to leading order (for h = m/2 a
    quarter), the residuals whitened by ``problem``'s variances.  Cheap (fewer points than ``problem``), and
    the control variate of :func:`sampled_quadrature_bias`."""
    r_h = ((coarser.obj.y - coarser.obj.mu(coarser.parts(st), st)) / np.sqrt(problem.obj.var)).ravel()
    factor = 0.75 / m ** 2 / (1.0 / h ** 2 - 1.0 / m ** 2)
    return cell_terms(J, factor * (r_h - r), problem.obj.m)


def quadrature_sample(problem, J, g_hat, n, rng):
    """Sorted positions of a Poisson sample of the fitted cells and their inclusion probabilities pi (> 0);
    every cell (pi = 1) when ``n`` is at least their number.

    ``g_hat``: (cells, p) each cell's predicted J_c^T d_c (:func:`predicted_quadrature_terms`); ``n``: the
    expected sample size.  A quarter of n is spread uniformly, three quarters in proportion to each cell's
    predicted shift of the shape estimate in SE units, |S^-1 (J^T J)^-1 g_hat_c| (S: the Fisher SEs; the highlight's
    cells), capped at 1: every cell can be taken, so the Horvitz-Thompson sum is unbiased."""
    N, k = len(g_hat), len(problem.names)
    if n >= N:
        return np.arange(N), np.ones(N)
    Hi = np.linalg.pinv(J.T @ J)
    se = np.sqrt(np.clip(np.diag(Hi), 1e-300, None))
    size = np.sqrt(np.sum((g_hat @ (Hi[:k] / se[:k, None]).T) ** 2, axis=1))
    w = 0.25 / N + (0.75 * size / size.sum() if size.sum() > 0 else 0.75 / N)
    c = float(n)
    for _ in range(50):                     # scale so that the capped probabilities sum to n
        pi = np.minimum(1.0, c * w)
        free = pi < 1.0
        if abs(pi.sum() - n) <= 1e-9 * n or not free.any():
            break
        c *= (n - (~free).sum()) / pi[free].sum()
    cells = np.flatnonzero(rng.random(N) < pi)
    return cells, pi[cells]


def sampled_quadrature_bias(problem, fine, st, J, r, cells, pi, g_hat):
    """({shape parameter: bias / SE}, {shape parameter: the bias's sampling SE / SE}) of
    :func:`quadrature_bias` with J^T (r - r_fine) estimated from the cells ``cells`` only (``fine``: the
    2m x 2m problem of those cells in that order; ``pi`` their inclusion probabilities,
    :func:`quadrature_sample`): the predicted sum over all cells, sum g_hat_c
    (:func:`predicted_quadrature_terms`), plus the Horvitz-Thompson sum of the sampled cells'
    (J_c^T d_c - g_hat_c) / pi_c (a difference estimator: unbiased whatever the prediction), with the
    variance sum (1 - pi_c) / pi_c^2 e_c e_c^T of Poisson sampling (e_c = J_c^T d_c - g_hat_c).  J^T J and
    the SE are the whole fit's.  The fine variances are the noise model's at the fine prediction, as
    :meth:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective.refresh` makes them, with the coarse fit's
    noise parameters (not re-estimated from the sample)."""
    ms = problem.obj.m
    st = sample_state(problem, fine, st)
    mu = fine.obj.mu(fine.parts(st), st)
    r_fine = ((fine.obj.y - mu) / np.sqrt(np.maximum(problem.obj.noise.variance(mu), 1e-300))).ravel()
    rows = (np.asarray(cells)[:, None] * ms + np.arange(ms)).ravel()
    e = cell_terms(J[rows], r[rows] - r_fine, ms) - g_hat[cells]
    G = g_hat.sum(0) + (e / pi[:, None]).sum(0)
    V = (e * ((1.0 - pi) / pi ** 2)[:, None]).T @ e
    return shift_in_se(problem, J, G, V)


def sample_state(problem, fine, st):
    """``st`` for ``fine``, a problem of a subset of ``problem``'s cells: with albedo maps (one pair per
    pixel and channel) the subset's own groups' albedos, else ``st`` itself."""
    if not problem.eliminates:
        return st
    full, sub = problem.layout, fine.layout
    C = 1 if full.channel_of is None else int(full.channel_of.max()) + 1

    def keys(lay):
        return lay.pixels * C + (0 if lay.channel_of is None else lay.channel_of)

    g = np.searchsorted(keys(full), keys(sub))
    return dataclasses.replace(st, a_s=np.asarray(st.a_s)[g], a_b=np.asarray(st.a_b)[g])


#: Relative tolerance on chi^2's rise at a Fisher interval's end (:func:`profile_intervals`).
PROFILE_TOL = 0.15

#: ``FitOptions.intervals``' values.
INTERVALS = ("auto", "profile", "fisher")

#: Relative tolerance of a profile end's chi^2 rise (:func:`profile_end`).
PROFILE_ROOT_TOL = 0.1


def interval_scale(problem, unc):
    """The covariance's scale (:func:`noise_scale`); a 95 % chi^2 rise is 1.96^2 times it."""
    if not unc.get("chi2_per_dof"):
        return 1.0
    return float(unc["chi2_per_dof"]) if unc.get("misfit") or not problem.obj.noise.known else 1.0


def sandwich_ratio(unc, name):
    """(SE / Fisher SE)^2 of ``name`` under the incidental sandwich, else 1 (chi^2's curvature is J^T J's)."""
    fse = unc.get("incidental", {}).get("fisher_std_errors") or {}
    return (unc["std_errors"][name] / fse[name]) ** 2 if fse.get(name) else 1.0


def chi2_along_covariance(problem, st, J, scale):
    """f(name, value): chi^2 with ``name`` at ``value`` and the other unknowns at their regression on it
    (scale (J^T J)^-1 in z): a quadratic likelihood's profile path, >= the profile.  ``f.state``: its State."""
    z0 = problem.to_z(st)
    # at a bound the z-variance is huge: regressing on it would throw a parameter to its other bound
    pinned = [i for i, (_, frac) in enumerate(bound_distance(problem, st).values()) if frac <= AT_BOUND_FRAC]
    cz = {}

    def path_cov(j):
        keep = [i for i in range(len(z0)) if i == j or i not in pinned]
        if len(keep) == len(z0):
            if "all" not in cz:
                cz["all"] = np.linalg.pinv(J.T @ J) * scale
            return cz["all"]
        if j not in cz:
            c = np.zeros((len(z0), len(z0)))
            c[np.ix_(keep, keep)] = np.linalg.pinv(J[:, keep].T @ J[:, keep]) * scale
            cz[j] = c
        return cz[j]

    def state(name, value):
        j = problem.names.index(name)
        zt = problem.bounds.to_z(name, value)
        if j in pinned:
            z = z0.copy()           # no regression on a pinned parameter: the others stay
            z[j] = zt
        else:
            c = path_cov(j)
            z = z0 + c[:, j] / c[j, j] * (zt - z0[j])
        s = problem.from_z(z)
        s.shape[name] = float(value)   # exactly: z is clipped to +-Z_MAX
        if problem.eliminates:
            s = problem.projected(s.shape)[0]
        return s

    def f(name, value):
        s = state(name, value)
        return problem.obj.value(problem.parts(s), s)

    f.state = state
    return f


def profile_end(problem, st, name, side, start, delta, chi2_min, path, max_refits=3):
    """One end of ``name``'s profile-likelihood 95 % interval on ``side`` (-1, +1) of ``st``: where chi^2
    refitted with ``name`` fixed (:func:`~fmbrdf_mi.fit.solve.driver.refit_fixed`) rises by ``delta``.
    Secant then false position on sqrt(rise), linear in the distance for a quadratic likelihood.  Returns
    (end, kind, [(value, rise)]), kind "profile", "profile, open at the bound" or "profile, at least"."""
    b = problem.bounds
    _, _, lo, hi = b.lims[name]
    value = st.shape[name]
    bound = lo if side < 0 else hi
    t0, tb = b.to_scale(name, value), b.to_scale(name, bound)
    room = abs(tb - t0)
    u = min(abs(b.to_scale(name, start) - t0), room)
    pts, inside, outside = [], (0.0, 0.0), None    # (|u|, sqrt(rise))
    g_target = math.sqrt(delta)
    for _ in range(max_refits):
        u = min(max(u, 1e-9 * max(room, 1.0)), room)
        v = b.from_scale(name, t0 + side * u) if u < room else bound
        rise = refit_fixed(problem, st, name, v, path.state(name, v),
                           label=f"profile {name} {'lower' if side < 0 else 'upper'}") - chi2_min
        pts.append((float(v), float(rise)))
        g = math.sqrt(max(rise, 0.0))
        if abs(rise / delta - 1.0) < PROFILE_ROOT_TOL:
            return float(v), "profile", pts
        if g < g_target:
            if u >= room:
                return float(bound), "profile, open at the bound", pts
            inside = (u, g)
        else:
            outside = (u, g)
        if outside is None:      # secant through the origin, at most x4
            u = min(u * (g_target / g if g > 0 else 4.0), 4.0 * u, room)
        else:
            (ua, ga), (ub, gb) = inside, outside
            u = ua + (g_target - ga) * (ub - ua) / (gb - ga) if gb > ga else 0.5 * (ua + ub)
    if outside is not None:
        (ua, ga), (ub, gb) = inside, outside
        u = ua + (g_target - ga) * (ub - ua) / (gb - ga) if gb > ga else ub
        return float(b.from_scale(name, t0 + side * u)), "profile", pts
    return float(pts[-1][0]), "profile, at least", pts


def profile_intervals(problem, st, unc, J, r, every=False, progress=None):
    """Replace each Fisher 95 % interval end where chi^2 along :func:`chi2_along_covariance` does not rise by
    delta = 1.96^2 x scale to within :data:`PROFILE_TOL` by the profile likelihood's (:func:`profile_end`).
    With the incidental sandwich delta is per parameter, x :func:`sandwich_ratio` (adjusted likelihood ratio,
    Varin, Reid and Firth 2011, sec. 4.2), and a profile end only widens (the profile of chi^2 with the
    albedos eliminated lacks their noise).  Sets ``unc``'s ``interval_kind``, ``profile`` and ``ci95``.
    Likelihood fits without extra unknowns only.  ``every``: profile every end.  ``progress``: a callable
    told after each parameter how many are checked, with the time left at the measured time per parameter.
    Returns the mechanisms applied.
    """
    if not problem.obj.is_likelihood or not unc.get("ci95") or problem.with_fixed({}) is None:
        return []
    chi2_min = float(r @ r)
    scale = interval_scale(problem, unc)
    delta = Z95 ** 2 * scale
    try:
        path = chi2_along_covariance(problem, st, J, scale)
    except np.linalg.LinAlgError:
        return []
    kinds, details, fisher = {}, {}, {n: list(v) for n, v in unc["ci95"].items()}
    fse = unc.get("incidental", {}).get("fisher_std_errors")
    thresholds, t0 = {}, time.time()
    names = [n for n in problem.names if unc["std_errors"].get(n) is not None
             and math.isfinite(unc["std_errors"][n]) and unc["std_errors"][n] > 0]
    if progress is not None:
        progress(f"[fit] interval check: {len(names)} parameters against the profile likelihood")
    for j, n in enumerate(names):
        if fse is not None:
            delta = thresholds[n] = Z95 ** 2 * scale * sandwich_ratio(unc, n)
        _, _, lo, hi = problem.bounds.lims[n]
        v = st.shape[n]
        ends, kind, tried = list(unc["ci95"][n]), [], {}
        for i, side in enumerate((-1, 1)):
            end = ends[i]
            at_bound = end <= lo or end >= hi
            rise = path(n, end) - chi2_min
            ok = rise <= delta * (1 + PROFILE_TOL) if at_bound else abs(rise / delta - 1) <= PROFILE_TOL
            tried["fisher_end_rise" if i else "fisher_start_rise"] = float(rise)
            fisher_kind = FISHER_AT_BOUND if at_bound else "fisher"
            if ok and not every:
                kind.append(fisher_kind)
                continue
            prof, k, pts = profile_end(problem, st, n, side, end, delta, chi2_min, path)
            tried["lower" if side < 0 else "upper"] = pts
            if fse is not None and side * (prof - end) < 0:
                k = fisher_kind
            else:
                ends[i] = prof
            kind.append(k)
        kinds[n] = kind_of(kind)
        details[n] = tried
        unc["ci95"][n] = [float(min(ends[0], v)), float(max(ends[1], v))]
        if progress is not None:
            progress(f"[fit] interval check: {n} done, {j + 1}/{len(names)} parameters ({time.time() - t0:.1f} s"
                     + (f", {time_left(time.time() - t0, j + 1, len(names), 'in the check')})" if j + 1 < len(names)
                        else ")"))
    unc["interval_kind"] = {**{n: k for n, k in unc.get("interval_kind", {}).items() if n not in kinds}, **kinds}
    unc["profile"] = {"threshold": Z95 ** 2 * scale, "rises": details, "fisher_ci95": fisher}
    if thresholds:
        unc["profile"]["thresholds"] = thresholds
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
    """Names of ``params`` whose SE exceeds :data:`WEAK_REL` of max(|value|, :data:`WEAK_FLOOR`), or in
    ``at_bound_`` (``table``: the :class:`~fmbrdf_mi.fit.evaluate.parameters.Parameters`)."""

    def floor(k):
        return WEAK_FLOOR.get(table.row[k].base if k in table.row else k, 0.0)

    return [k for k, v in params.items()
            if (k in std and (not math.isfinite(std[k]) or std[k] > WEAK_REL * max(abs(v), floor(k))))
            or k in at_bound_]


#: An albedo is *determined* where SE <= this fraction of it; a split is *identified* where k_s and k_b are.
SPLIT_REL = 0.5


def determined(value, se, rel=SPLIT_REL):
    """Where ``se`` <= ``rel`` x ``value``."""
    value, se = np.asarray(value, float), np.asarray(se, float)
    with np.errstate(invalid="ignore"):
        return np.isfinite(se) & (se <= rel * value)


def pixel_albedos(problem, st, parts, J, unc, cov_z=None):
    """Per group of an eliminating layout: the albedos with their errors
    (:meth:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos.maps`), ``identified`` where both are
    :func:`determined`; ``cov_z``: the shape's covariance in z (default (J^T J)^-1 x scale).
    """
    obj, lay = problem.obj, problem.layout
    z = problem.to_z(st)
    us, ub = obj.albedo_columns(parts)
    Jt = obj.shape_jacobian(parts, st, z, problem.names, problem.bounds)
    scale = interval_scale(problem, unc)
    try:
        if cov_z is None:
            cov_z = np.linalg.pinv(J.T @ J) * scale if J.shape[1] else np.zeros((0, 0))
    except np.linalg.LinAlgError:
        cov_z = np.full((J.shape[1], J.shape[1]), np.nan)
    return lay.maps(st.a_s, st.a_b, lay.covariance(us, ub, Jt, cov_z, scale), problem.model.albedo_factor,
                    SPLIT_REL)


#: 95 % quantiles of chi^2 with 1 ... 8 degrees of freedom.
CHI2_95 = (3.841458820694124, 5.991464547107979, 7.814727903251178, 9.487729036781154, 11.070497693516351,
           12.591587243743977, 14.067140449340169, 15.507313055865453)

#: A start's end this many SE from the estimate in some shape parameter is another optimum.
MODE_SEPARATION_SE = 2.0


def other_optima(starts, params, unc, names):
    """(optima, threshold): the ends of ``starts`` (:func:`fmbrdf_mi.fit.solve.driver.solve`) more than
    :data:`MODE_SEPARATION_SE` from ``params``, with delta_chi2 = 2 (score - best); one *competes* when
    converged and below :data:`CHI2_95` [p] x scale x the largest :func:`sandwich_ratio`.  ([], None) for
    one start or no standard errors."""
    se = unc.get("std_errors") or {}
    names = [n for n in names if se.get(n) and math.isfinite(se[n]) and se[n] > 0]
    scored = [s for s in starts if s.get("score") is not None and math.isfinite(s["score"])]
    if len(scored) < 2 or not names:
        return [], None
    best = min(s["score"] for s in scored)
    inflation = max([1.0] + [sandwich_ratio(unc, n) for n in names])
    scale = float(unc["chi2_per_dof"]) if unc.get("misfit") and unc.get("chi2_per_dof") else 1.0
    threshold = CHI2_95[min(len(names), len(CHI2_95)) - 1] * scale * inflation
    out = []
    for s in scored:
        end = s["end"]
        dist = max(abs(end[n] - params[n]) / se[n] for n in names)
        if dist <= MODE_SEPARATION_SE:
            continue
        d = 2.0 * (s["score"] - best)
        out.append({"params": {n: float(end[n]) for n in names}, "delta_chi2": float(d), "distance_se": float(dist),
                    "converged": bool(s.get("converged")),
                    "competing": bool(s.get("converged")) and d < threshold})
    return out, float(threshold)


def widen_for_optima(unc, params, optima, lims=None):
    """Widen each 95 % interval to the hull of its own and, around each competing optimum, one of the same
    half-widths, cut at ``lims`` {name: (lo, hi)}; records ``interval_kind`` "optima" and
    ``other_optima["widened"]``.  Returns the names widened."""
    comp = [o for o in optima if o["competing"]]
    ci = unc.get("ci95") or {}
    if not comp:
        return []
    before = {}
    for n in [n for n in ci if all(n in o["params"] for o in comp)]:
        lo, hi = ci[n]
        v = params[n]
        blo, bhi = (lims or {}).get(n, (-math.inf, math.inf))
        new_lo = max(blo, min([lo] + [o["params"][n] - (v - lo) for o in comp]))
        new_hi = min(bhi, max([hi] + [o["params"][n] + (hi - v) for o in comp]))
        if new_lo < lo or new_hi > hi:
            before[n] = [float(lo), float(hi)]
            ci[n] = [float(new_lo), float(new_hi)]
    if before:
        kinds = unc.setdefault("interval_kind", {n: "fisher" for n in ci})
        for n in before:
            kinds[n] = "optima"
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
