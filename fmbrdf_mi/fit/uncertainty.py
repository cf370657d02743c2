"""Standard errors, 95 % intervals and correlations of the estimates.

* **likelihood** (:class:`fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`): the
  inverse Fisher information.  The residuals are standardised,
  r = (y - mu) / sd, so with J their Jacobian the Fisher information is
  J^T J (Gauss-Newton, exact for a Gaussian with known variances at the
  IRLS fixed point).  When the noise level was estimated from the residuals
  the covariance is multiplied by chi^2 / (N - p) (N the independent
  samples), which is then ~1 by construction; with the camera noise known,
  the same factor is applied when chi^2 / (N - p) is far above 1 (more
  than 5 of its standard deviations sqrt(2 / (N - p)), and at least 0.1:
  ``misfit``), in every mode, and the fit warns (:func:`misfit_text`);
* **paper's loss**: it is not a likelihood, so J^T J says nothing about the
  spread of its minimiser.  A sandwich estimate H^-1 M H^-1 with H = J^T J
  and M the covariance of the estimating equation J^T r, summed over pixel
  neighbourhoods: each pixel's rows (its intensity and DoLP residuals are
  correlated) and, for a bilinear-demosaicked mosaic, those of its 8
  neighbours, whose values share raw samples (:func:`block_meat`).  Plain
  residuals r at the estimate underestimate M: the fit has pulled them
  towards the data, and with the neighbour sums the loss is large when the
  object has few pixels (measured: 32 super-pixels, M 41 % too small, 95 %
  intervals covering 75 %; 88 super-pixels: 83 %).  The residuals of each
  neighbourhood g are therefore replaced by its leave-g-out prediction
  residuals (I - P_gg)^-1 r_g, P = J H^-1 J^T (the cluster jackknife, "CR3"
  of the econometrics literature; with one pixel per block the "HC3"
  estimate), which is unbiased to first order and slightly conservative for
  small objects; for large ones P_gg -> 0 and it is the plain sandwich.  It
  describes the spread of the estimate, not its bias (the DoLP of a noisy
  pixel is biased: README).
**Transforms and bounds.**  The optimiser works in unconstrained z (sigmoid
onto the bounds, log albedos); the covariance is computed for the reported
parameters directly: J_theta = J_z (d theta / d z)^-1, so the standard
errors are those of the reported parameters at the optimum (delta method),
not of z.  Intervals are theta +- 1.96 SE, cut at the parameter's bounds;
a parameter within 1e-3 of its range of a bound (on the scale the optimiser
works on: log for log-scale parameters), or closer to a bound than 1.96 SE,
is listed in ``at_bound``: its interval is not a confidence interval there.
``bound_distance_se`` gives each free shape parameter's distance from its
nearest bound in standard errors.
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


def bound_distance(problem, st):
    """{free shape parameter: (distance from its nearest bound in its own units, the same as a fraction of its
    range on the scale the optimiser works on: log for log-scale parameters, linear for linear ones)}."""
    out = {}
    for n in problem.names:
        tlo, thi, lo, hi = problem.bounds.lims[n]
        v = st.shape[n]
        t = problem.bounds.to_scale(n, v)
        out[n] = (min(v - lo, hi - v), min(t - tlo, thi - t) / (thi - tlo))
    return out


def at_bound(problem, st, sd=None):
    """Free shape parameters whose interval is not a confidence interval because of a bound: those within 1e-3
    of their range of a bound on the optimiser's scale (:func:`bound_distance`: a light power, searched over
    six decades, is at its bound near G / 1000, not anywhere below 1.001 G), and, given the standard errors
    ``sd`` {name: SE}, those closer to a bound than 1.96 SE (the 95 % interval is cut there)."""
    out = []
    for n, (d, frac) in bound_distance(problem, st).items():
        se = (sd or {}).get(n)
        if frac <= 1e-3 or (se is not None and math.isfinite(se) and d < Z95 * se):
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
            # noise does not explain the data, and the Fisher errors are too small: they are inflated
            # by chi^2 / dof (the quasi-likelihood scale, as when the noise level is estimated)
            info["misfit"] = bool(info["chi2_per_dof"] > 1.0 + max(0.1, 5.0 * math.sqrt(2.0 / max(n - p, 1))))
            if info["misfit"]:
                scale = info["chi2_per_dof"]
                info["method"] += ", inflated by chi^2/dof (misfit)"
        else:
            scale = info["chi2_per_dof"]
            info["method"] = "inverse Fisher information, noise level estimated from the residuals"
        cov = scale * Hi
    else:
        grid = getattr(obj, "grid", None)
        M = block_meat(Jt, r, obj.row_pixels(len(r)), Hi, grid)
        info["method"] = ("sandwich estimate for the paper's loss, leave-neighbourhood-out residuals (CR3)"
                          + (", with the correlation of neighbouring pixels (demosaicking)" if grid is not None else ""))
        cov = Hi @ M @ Hi
    return names, cov, info


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
    """M = sum_a u_a (sum_{b in N(a)} u_b)^T with leave-N(a)-out residuals (module docstring).

    ``row_pix``: the pixel of each residual row; ``grid``: (rows, cols) of the
    pixels when neighbours (|dr|, |dc| <= 1) are correlated, else None (one
    pixel per block).  Symmetrised, negative eigenvalues removed.
    """
    rows, nb = _blocks(row_pix, grid)
    npx, R = rows.shape
    p = J.shape[1]
    # the residual rows of each block: own pixel's rows first
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


def summarise(problem, st, J, r, n_independent=None):
    """The uncertainty block of fit.json: std_errors, ci95, correlation, at_bound, method."""
    names, cov, info = covariance(problem, st, J, r, n_independent)
    rep = problem.model.report(st.shape, st.a_s, st.a_b)
    out = {"std_errors": {}, "ci95": {}, "correlation": None, "at_bound": at_bound(problem, st), **info}
    if cov is None:
        return out
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    se = dict(zip(names, sd.tolist()))
    out["at_bound"] = at_bound(problem, st, se)
    # each free shape parameter's distance from its nearest bound in standard errors
    out["bound_distance_se"] = {n: (float(d / se[n]) if se.get(n, 0.0) > 0 else math.inf)
                                for n, (d, _) in bound_distance(problem, st).items()}
    for i, n in enumerate(names):
        lo, hi = rep[n] - Z95 * sd[i], rep[n] + Z95 * sd[i]
        if n in problem.names:
            _, _, blo, bhi = problem.bounds.lims[n]
            lo, hi = max(lo, blo), min(hi, bhi)
        elif n.split("[")[0] in ("r_k", "k_s", "k_b", "k_d", "specular_reflectance", "diffuse_reflectance"):
            lo = max(lo, 0.0)
        out["std_errors"][n] = float(sd[i])
        out["ci95"][n] = [float(lo), float(hi)]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        corr = cov / np.outer(sd, sd)
    # a degenerate covariance (a noise-free fit: sd ~ 1e-160) can give inf/nan; a correlation is in [-1, 1]
    corr = np.clip(np.nan_to_num(corr, nan=0.0, posinf=1.0, neginf=-1.0), -1.0, 1.0)
    out["correlation"] = {"names": names, "matrix": np.round(corr, 4).tolist()}
    return out


def misfit_text(unc):
    """The one-line warning of a misfit (``unc["misfit"]``: chi^2/dof far above 1 with the stated camera noise)."""
    c = unc["chi2_per_dof"]
    return (f"chi^2/dof = {c:.3g} with the stated camera noise: the model (geometry, light, BSDF) or the noise "
            f"settings do not explain the data; the standard errors are inflated by sqrt(chi^2/dof) = "
            f"{math.sqrt(c):.3g}")


def weakly_identified(params, std, at_bound_=()):
    return [k for k, v in params.items()
            if (k in std and (not math.isfinite(std[k]) or std[k] > WEAK_REL * max(abs(v), WEAK_FLOOR.get(k, 0.0))))
            or k in at_bound_]
