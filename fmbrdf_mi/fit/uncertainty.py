"""Standard errors, 95 % intervals and correlations of the estimates.

* **likelihood** (:class:`fmbrdf_mi.fit.objective.LikelihoodObjective`): the
  inverse Fisher information.  The residuals are standardised,
  r = (y - mu) / sd, so with J their Jacobian the Fisher information is
  J^T J (Gauss-Newton, exact for a Gaussian with known variances at the
  IRLS fixed point).  When the noise level was estimated from the residuals
  the covariance is multiplied by chi^2 / (N - p) (N the independent
  samples), which is then ~1 by construction;
* **paper's loss**: it is not a likelihood, so J^T J says nothing about the
  spread of its minimiser.  The sandwich (robust, "HC0") estimate
  H^-1 M H^-1 with H = J^T J and M = sum over pixels of u_p u_p^T,
  u_p = sum of J^T r over the pixel's residual rows (its intensity and DoLP
  residuals are correlated, so they are grouped), times n / (n - p); for a
  bilinear-demosaicked mosaic M also sums u_p u_q^T over neighbouring
  pixels (:func:`_neighbour_meat`), whose values share raw samples.  It
  describes the spread of the estimate, not its bias (the DoLP of a noisy
  pixel is biased: README).

**Transforms and bounds.**  The optimiser works in unconstrained z (sigmoid
onto the bounds, log albedos); the covariance is computed for the reported
parameters directly: J_theta = J_z (d theta / d z)^-1, so the standard
errors are those of the reported parameters at the optimum (delta method),
not of z.  Intervals are theta +- 1.96 SE, cut at the parameter's bounds;
a parameter within 1e-3 (relative to its range) of a bound is listed in
``at_bound``: its interval is not a confidence interval there.
"""
from __future__ import annotations

import math

import numpy as np

Z95 = 1.959963984540054

#: A parameter is weakly identified when its standard error exceeds this
#: fraction of max(|value|, WEAK_FLOOR[name]) (the image does not pin it
#: down to 5 %), or when it ended at a bound.
WEAK_REL = 0.05
WEAK_FLOOR = {"kappa": 10.0}


def _free_names(problem):
    rep = problem.model.report({n: 1.5 for n in problem.model.shape_names}, 1.0, 1.0)
    albedo_names = [k for k in rep if k not in problem.model.shape_names]
    return list(problem.names) + albedo_names


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
            rp = problem.model.report(sp.shape, sp.a_s, sp.a_b)
            vals.append(np.array([rp[n] for n in names]))
        G[:, j] = (vals[0] - vals[1]) / (2 * h)
    return G


def at_bound(problem, st):
    out = []
    for n in problem.names:
        _, _, lo, hi = problem.bounds.lims[n]
        v = st.shape[n]
        if min(v - lo, hi - v) <= 1e-3 * (hi - lo):
            out.append(n)
    return out


def jacobian_in_reported(problem, st, J):
    """(names, J_theta): the residuals' Jacobian with respect to the reported free parameters."""
    names = _free_names(problem)
    G = dtheta_dz(problem, st, names)
    return names, J @ np.linalg.inv(G)


def covariance(problem, st, J, r, n_independent=None):
    """Covariance of the reported free parameters; returns (names, cov (p, p), info dict)."""
    try:
        names, Jt = jacobian_in_reported(problem, st, J)
    except np.linalg.LinAlgError:
        return _free_names(problem), None, {"method": "singular reparameterisation"}
    p = Jt.shape[1]
    H = Jt.T @ Jt
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return names, None, {"method": "singular information matrix"}
    obj = problem.obj
    info = {}
    if obj.is_likelihood:
        n = int(n_independent if n_independent is not None else len(r))
        chi2 = float(r @ r)
        info["chi2_per_dof"] = chi2 / max(n - p, 1)
        if obj.noise.known:
            scale, info["method"] = 1.0, "inverse Fisher information (known camera noise)"
            # chi^2 / dof has standard deviation sqrt(2 / dof): far above 1, the model or the stated
            # noise does not explain the data, and these errors are too small
            info["misfit"] = bool(info["chi2_per_dof"] > 1.0 + max(0.1, 5.0 * math.sqrt(2.0 / max(n - p, 1))))
        else:
            scale = info["chi2_per_dof"]
            info["method"] = "inverse Fisher information, noise level estimated from the residuals"
        cov = scale * Hi
    else:
        pix = obj.row_pixels(len(r))
        npx = int(pix.max()) + 1
        U = np.zeros((npx, p))
        np.add.at(U, pix, Jt * r[:, None])
        grid = getattr(obj, "grid", None)
        if grid is None:
            M = U.T @ U
            info["method"] = "sandwich (robust) estimate for the paper's loss"
        else:
            M = _neighbour_meat(U, *grid)
            info["method"] = ("sandwich (robust) estimate for the paper's loss, with the correlation of "
                              "neighbouring pixels (demosaicking) included")
        cov = Hi @ M @ Hi * npx / max(npx - p, 1)
    return names, cov, info


def _neighbour_meat(U, rows, cols):
    """sum_p u_p (sum_{q: |dr|, |dc| <= 1} u_q)^T, symmetrised, negative eigenvalues removed.

    Bilinear demosaicking builds each super-pixel from raw samples it shares
    with its 8 neighbours, so their residuals are correlated; beyond that
    they are independent.  The uniform 3 x 3 window is unbiased for such a
    correlation range.
    """
    rows, cols = np.asarray(rows), np.asarray(cols)
    r0, c0 = rows.min(), cols.min()
    G = np.zeros((rows.max() - r0 + 3, cols.max() - c0 + 3, U.shape[1]))
    G[rows - r0 + 1, cols - c0 + 1] = U
    S = sum(G[1 + dr:G.shape[0] - 1 + dr, 1 + dc:G.shape[1] - 1 + dc]
            for dr in (-1, 0, 1) for dc in (-1, 0, 1))
    M = U.T @ S[rows - r0, cols - c0]
    M = 0.5 * (M + M.T)
    w, V = np.linalg.eigh(M)
    return (V * np.clip(w, 0.0, None)) @ V.T


def summarise(problem, st, J, r, n_independent=None):
    """The uncertainty block of fit.json: std_errors, ci95, correlation, at_bound, method."""
    names, cov, info = covariance(problem, st, J, r, n_independent)
    rep = problem.model.report(st.shape, st.a_s, st.a_b)
    bound = at_bound(problem, st)
    out = {"std_errors": {}, "ci95": {}, "correlation": None, "at_bound": bound, **info}
    if cov is None:
        return out
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    for i, n in enumerate(names):
        lo, hi = rep[n] - Z95 * sd[i], rep[n] + Z95 * sd[i]
        if n in problem.names:
            _, _, blo, bhi = problem.bounds.lims[n]
            lo, hi = max(lo, blo), min(hi, bhi)
        elif n == "r_k" or n in ("k_s", "k_b", "k_d", "specular_reflectance", "diffuse_reflectance"):
            lo = max(lo, 0.0)
        out["std_errors"][n] = float(sd[i])
        out["ci95"][n] = [float(lo), float(hi)]
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    out["correlation"] = {"names": names, "matrix": np.round(np.nan_to_num(corr), 4).tolist()}
    return out


def weakly_identified(params, std, at_bound_=()):
    return [k for k, v in params.items()
            if (k in std and (not math.isfinite(std[k]) or std[k] > WEAK_REL * max(abs(v), WEAK_FLOOR.get(k, 0.0))))
            or k in at_bound_]
