"""Issue 23/25 diagnostic: the integrated-likelihood adjustment of the per-pixel albedo fit, as a patch.

    import pp_logdet; pp_logdet.install()     # then fmbrdf_mi.fit.fit(..., albedo="per-pixel") is adjusted

-2 log L(theta) = chi^2_p(theta) + sum_i log det(A_i^T W_i A_i): the albedos integrated out under a
flat prior (A_i pixel i's n_i x 2 design matrix of unit-albedo surface and body samples, W_i its
inverse variances, frozen between reweighting rounds like the chi^2's).  Carried as one pseudo-residual
rho = sqrt(K + L(theta) - L_ref) (L_ref: L when the weights were last refreshed, K a constant that keeps
rho^2 > 0), so rho^2 moves exactly as L does and d(rho^2)/dz = dL/dz: the Levenberg-Marquardt's fixed
point is the adjusted likelihood's stationary point.  Kept out of the package: the adjustment did not
pass its test.  With the variances fixed, E chi^2_p(theta) = sum (n_i - 2) + mu0^T W (I - P_theta) mu0 is
already minimal at the truth (the profile's estimating equation has zero mean), and L(theta) is not
flat: det(A^T W A) scales with the unit-albedo intensities, which the shape parameters rescale (a flat
prior on k_s, k_b is a different prior at every theta), so L adds a pull of O(1) per pixel.
tools/diag_pp_logdet_bias.py: linearised shift at the truth eta -67, beta +49, kappa +65 SE (24², one
light), -214, +132, +200 SE (48²); -0.5 to -6.6 SE with three lights.  Fitted (tools/diag_pp_bias.py
--adjust logdet, camera noise, 24², seeds 0-3): all four end at the same point, eta 1.200, alpha 0.060,
beta 1.60, kappa 52, whatever the data.
"""
from __future__ import annotations

import numpy as np


def logdet(obj, parts, names=(), bounds=None, z=None):
    """(L, dL/dz): L = sum over groups of log det G_g, G_g = sum of w (S, B)^T (S, B) over the group's
    samples (w = 1 / var, frozen); dL/dz (len(names),) when names are given."""
    lay = obj.layout
    g = lay.groups.ravel()
    w = (1.0 / obj.var).ravel()
    S, B = (x.ravel() for x in obj.unit_samples(parts))

    def tot(v):
        return np.bincount(g, weights=v, minlength=lay.n_groups)

    a, b, c = tot(w * S * S), tot(w * S * B), tot(w * B * B)
    det = a * c - b * b
    ok = det > 1e-10 * np.maximum(a * c, 1e-300)
    L = float(np.sum(np.log(det[ok])))
    if not names:
        return L, None
    grad = np.zeros(len(names))
    for j, n in enumerate(names):
        dS = obj._mu_of(parts.d_surface[n]).ravel()
        dB = obj._mu_of(parts.d_body[n]).ravel()
        da, db, dc = tot(2 * w * S * dS), tot(w * (dS * B + S * dB)), tot(2 * w * B * dB)
        t = (c * da - 2 * b * db + a * dc) / np.where(ok, det, 1.0)
        grad[j] = float(np.sum(np.where(ok, t, 0.0))) * bounds.derivative(n, z[j])
    return L, grad


def install():
    from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective as LO

    base_res, base_rj, base_refresh, base_nll = LO.residuals, LO.residuals_and_jacobian, LO.refresh, LO.nll
    base_rows = LO.row_pixels

    def on(self):
        return getattr(self.layout, "eliminates", False)

    def ensure(self, parts):
        if not hasattr(self, "_ld_ref"):
            self._ld_ref = logdet(self, parts)[0]
            self._ld_K = 50.0 * self.layout.n_groups

    def rho(self, parts):
        ensure(self, parts)
        return np.sqrt(max(self._ld_K + logdet(self, parts)[0] - self._ld_ref, 1e-12))

    def residuals(self, parts, st):
        r = base_res(self, parts, st)
        return np.append(r, rho(self, parts)) if on(self) else r

    def residuals_and_jacobian(self, parts, st, z, names, bounds):
        r, J, bad = base_rj(self, parts, st, z, names, bounds)
        if not on(self):
            return r, J, bad
        r = r[:-1]      # the base calls the patched residuals: its r has the pseudo-residual already
        p = rho(self, parts)
        _, gz = logdet(self, parts, names, bounds, z)
        J = np.vstack([J, (gz / (2 * p))[None, :]])
        bad = None if bad is None else np.append(bad, False)
        return np.append(r, p), J, bad

    def refresh(self, parts, st):
        base_refresh(self, parts, st)
        if on(self):
            self._ld_ref = logdet(self, parts)[0]
            self._ld_K = 50.0 * self.layout.n_groups

    def nll(self, parts, st):
        v = base_nll(self, parts, st)
        return v + 0.5 * logdet(self, parts)[0] if on(self) else v

    def row_pixels(self, n_rows):
        return np.minimum(base_rows(self, n_rows), self.n - 1)

    LO.residuals, LO.residuals_and_jacobian, LO.refresh, LO.nll = residuals, residuals_and_jacobian, refresh, nll
    LO.row_pixels = row_pixels
