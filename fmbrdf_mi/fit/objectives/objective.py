"""What a fit minimises, as squared residuals for one Levenberg-Marquardt: the paper's loss
(:class:`PaperObjective`, eq:optimization) or the likelihood of the camera's samples
(:class:`LikelihoodObjective`), y_ik ~ N(mu_ik, v(mu_ik)) with mu_ik = 1/2 (S0 + S1 cos 2 phi_k + S2 sin 2 phi_k)
and v(mu) = mu / g + sigma_read^2 + Delta^2 / 12 (:class:`~fmbrdf_mi.sensor.noise.NoiseModel`), minimised
by iteratively reweighted least squares (variances frozen between rounds, so J^T J is the Fisher information).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmbrdf_mi.fit.evaluate.albedos import nnls2
from fmbrdf_mi.fit.objectives import loss as L
from fmbrdf_mi.sensor import rice


class PaperObjective:
    """The paper's loss (eq:optimization, :mod:`fmbrdf_mi.fit.objectives.loss`): intensity MSE + weighted DoLP MSE."""

    name = "paper"
    is_likelihood = False
    #: no albedo layout: one shared pair in z (the DoLP term is not linear in it), no prior
    layout = prior = None

    def __init__(self, target):
        self.target = target
        self.w = target.dolp_valid.astype(np.float64)
        self.outliers = np.zeros(len(target.intensity), bool)
        self.grid = None    # (rows, cols) of the pixels when neighbours are correlated (uncertainty.py)

    def refresh(self, parts, st):
        """Reweight the DoLP term by the paper's inlier / outlier split at this prediction."""
        self.outliers = L.outlier_mask(parts.surface[0], parts.body[0], st.a_s, st.a_b)
        self.w = L.weights(self.outliers, self.target.dolp_valid)

    def save(self):
        return (self.outliers.copy(), self.w.copy())

    def restore(self, saved):
        self.outliers, self.w = saved

    def settled(self, old, parts, st, **_):
        """After a refresh: has the weighting stopped changing?"""
        valid = self.target.dolp_valid
        changed = int(((old[0] != self.outliers) & valid).sum())
        smaller = min(int((self.outliers & valid).sum()), int((~self.outliers & valid).sum()))
        return changed <= max(5, 0.1 * smaller)

    def describe_round(self):
        v = self.target.dolp_valid
        return (f"{int((self.outliers & v).sum())} outliers (surface-dominated) / "
                f"{int((~self.outliers & v).sum())} inliers")

    def _predict(self, parts, st):
        return L.predict(parts.surface, parts.body, st.a_s, st.a_b, self.target.lin_sigma)

    def residuals(self, parts, st, w=None):
        i, rho = self._predict(parts, st)
        return L.residuals(self.target, self.w if w is None else w, i, rho)

    def value(self, parts, st, w=None):
        r = self.residuals(parts, st, w)
        return float(r @ r)

    def score(self, parts, st):
        """Loss with the candidate's own inlier / outlier split (for comparing candidates)."""
        out = L.outlier_mask(parts.surface[0], parts.body[0], st.a_s, st.a_b)
        return self.value(parts, st, L.weights(out, self.target.dolp_valid))

    def albedos(self, parts):
        return nnls2(parts.surface[0], parts.body[0], self.target.intensity)

    def small_decrease(self, f_old, f_new, tol):
        return (f_old - f_new) / max(f_old, 1e-300) < tol

    def loss_terms(self, parts, st):
        r, m = self.residuals(parts, st), len(self.target.intensity)
        return {"intensity": float(r[:m] @ r[:m]), "dolp": float(r[m:] @ r[m:])}

    def row_pixels(self, n_rows):
        return np.arange(n_rows) % len(self.target.intensity)

    def residuals_and_jacobian(self, parts, st, z, names, bounds):
        """r (m,) and dr/dz (m, k + 2)."""
        s = st.a_s * parts.surface + st.a_b * parts.body
        nu = np.sqrt(s[1] ** 2 + s[2] ** 2 + L.DOLP_EPS ** 2)
        sigma = self.target.lin_sigma
        dlin = 1.0 if sigma is None else rice.mean_length_derivative(nu, sigma)
        i, rho = self._predict(parts, st)
        safe_i = np.where(i > 0, i, 1.0)
        r = L.residuals(self.target, self.w, i, rho)
        ci = 1.0 / (self.target.scale * math.sqrt(len(i)))
        cr = np.sqrt(self.w / self.w.sum())

        def cols(ds):
            d_i = ds[0]
            d_rho = dlin * (s[1] * ds[1] + s[2] * ds[2]) / (nu * safe_i) - rho * d_i / safe_i
            return np.concatenate([ci * d_i, cr * d_rho])

        J = _jacobian(cols, parts, st, z, names, bounds, len(r))
        bad = None if parts.nonfinite is None else np.concatenate([parts.nonfinite, parts.nonfinite])
        return r, J, bad


def _jacobian(cols, parts, st, z, names, bounds, m):
    """(m, len(z)) d r / d z of the shared pair's problem from ``cols`` (d r of a change of the Stokes parts)."""
    J = np.empty((m, len(z)))
    for j, n in enumerate(names):
        J[:, j] = cols(st.a_s * parts.d_surface[n] + st.a_b * parts.d_body[n]) * bounds.derivative(n, z[j])
    J[:, -2], J[:, -1] = cols(st.a_s * parts.surface), cols(st.a_b * parts.body)   # d / d log a_s, log a_b
    return J


class LikelihoodObjective:
    """Gaussian likelihood of the polariser samples with Poisson-Gaussian variance (module docstring).

    ``y``: (n, m) observed samples of the fitted cells; ``analyser`` (m, 3); ``dof``: independent values among
    a cell's m samples; ``layout``: the albedo layout eliminated (None: one shared pair in z).  Residuals are
    (y - mu) / sqrt(v), v frozen between :meth:`refresh` calls.
    """

    name = "likelihood"
    is_likelihood = True

    def __init__(self, y, analyser, noise, dof=4, layout=None):
        self.y = np.asarray(y, dtype=np.float64)
        self.A = np.asarray(analyser, dtype=np.float64)
        self.noise = noise
        self.dof = int(dof)
        self.layout = layout
        #: the albedo maps' smoothness prior (its rows are residuals too), or None
        self.prior = None if layout is None else layout.prior
        self.n, self.m = self.y.shape
        self.var = np.maximum(noise.variance(self.y), 1e-300)
        self._unit = (None, None)      # (parts.surface, parts.body) -> their samples, of the last parts seen

    def unit_samples(self, parts):
        """(S, B) = :meth:`samples_of` ``parts``' surface and body (n, m), kept for the last ``parts``."""
        if self._unit[0] is not parts.surface or self._unit[1] is not parts.body:
            self._unit = (parts.surface, parts.body, self.samples_of(parts.surface), self.samples_of(parts.body))
        return self._unit[2:]

    def samples_of(self, stokes):
        """The analysed samples (n, m) of Stokes values (3, m n) at the samples' points or (3, n) at the centres."""
        s = stokes.reshape(3, self.n, -1)
        if s.shape[2] == 1:
            return np.einsum("kc,ci->ik", self.A, s[:, :, 0])
        return np.einsum("kc,cik->ik", self.A, s)

    def mu(self, parts, st):
        if self.layout is None:
            return self.samples_of(st.a_s * parts.surface + st.a_b * parts.body)
        (S, B), (s, b) = self.unit_samples(parts), self.layout.sample_albedos(st.a_s, st.a_b)
        return s * S + b * B

    def refresh(self, parts, st):
        mu = self.mu(parts, st)
        if not self.noise.known:
            # m samples carry only self.dof independent values
            self.noise.estimate(mu, (self.y - mu) ** 2, self.dof / self.m)
        self.var = np.maximum(self.noise.variance(mu), 1e-300)

    def save(self):
        return (self.var.copy(), dataclasses.replace(self.noise))

    def restore(self, saved):
        self.var, self.noise = saved[0], saved[1]

    def settled(self, old, parts, st, step_se=None):
        """The IRLS weights have settled when the last round moved the estimate by < 0.05 standard errors."""
        return step_se is not None and step_se < 0.05

    def describe_round(self):
        return f"variances from the model ({self.noise.describe()})"

    def residuals(self, parts, st):
        """The whitened residuals (N,), then the albedo prior's rows if any: r @ r = data chi^2 + penalty."""
        r = ((self.y - self.mu(parts, st)) / np.sqrt(self.var)).ravel()
        if self.prior is None:
            return r
        return np.concatenate([r, self.prior.residuals(st.a_s, st.a_b)])

    def penalty(self, st):
        """The albedo prior's term of chi^2 at ``st`` (0 without a prior)."""
        return 0.0 if self.prior is None else self.prior.penalty(st.a_s, st.a_b)

    def value(self, parts, st):
        r = self.residuals(parts, st)
        return float(r @ r)

    def nll_terms(self, parts, st):
        """(n, m) twice each sample's NLL term, (y - mu)^2 / v + log v, v from this prediction."""
        mu = self.mu(parts, st)
        v = np.maximum(self.noise.variance(mu), 1e-300)
        return (self.y - mu) ** 2 / v + np.log(v)

    def nll(self, parts, st):
        """Negative log-likelihood (up to a constant) with the variance from this prediction."""
        return 0.5 * float(np.sum(self.nll_terms(parts, st))) + 0.5 * self.penalty(st)

    score = nll

    def albedos(self, parts):
        S, B = self.unit_samples(parts)
        if self.layout is not None:
            return self.layout.solve(S, B, self.y, 1.0 / self.var)
        return nnls2(S.ravel(), B.ravel(), self.y.ravel(), 1.0 / self.var.ravel())

    def small_decrease(self, f_old, f_new, tol):
        # chi^2 units: a decrease of 0.01 moves the estimate by ~0.1 standard error
        return f_old - f_new < 0.01

    def loss_terms(self, parts, st):
        chi2 = self.value(parts, st)
        out = {"chi2": chi2, "samples": int(self.y.size), "nll": self.nll(parts, st)}
        if self.prior is not None:
            out["albedo_prior"] = self.penalty(st)
            out["data_chi2"] = chi2 - out["albedo_prior"]
        return out

    def row_pixels(self, n_rows):
        return np.arange(n_rows) // self.m

    def residuals_and_jacobian(self, parts, st, z, names, bounds):
        r = self.residuals(parts, st)
        bad = None if parts.nonfinite is None else np.pad(   # the albedo prior's rows: finite (no BSDF derivative)
            np.repeat(parts.nonfinite.reshape(self.n, -1).any(axis=1), self.m), (0, len(r) - self.y.size))
        if self.layout is None:
            inv_sd = 1.0 / np.sqrt(self.var)

            def cols(ds):
                return (-self.samples_of(ds) * inv_sd).ravel()

            return r, _jacobian(cols, parts, st, z, names, bounds, len(r)), bad
        J = self.shape_jacobian(parts, st, z, names, bounds)
        return r, self.layout.project(J, *self.albedo_columns(parts))[0], bad

    def _white(self, mu):
        """d r / d mu of the samples' predictions ``mu`` (n, m): -mu / sd, raveled (N,)."""
        return (-mu / np.sqrt(self.var)).ravel()

    def shape_jacobian(self, parts, st, z, names, bounds):
        """d r / d z of the free shape parameters ``names`` (N, len(names)), the albedos held."""
        U, (s, b) = self.samples_of, self.layout.sample_albedos(st.a_s, st.a_b)
        J = np.empty((self.y.size, len(names)))
        for j, n in enumerate(names):
            J[:, j] = self._white(s * U(parts.d_surface[n]) + b * U(parts.d_body[n])) * bounds.derivative(n, z[j])
        return J

    def albedo_columns(self, parts):
        """(us, ub) (N,): each residual's derivative in its sample's unit albedos (the layout's design columns)."""
        return tuple(self._white(u) for u in self.unit_samples(parts))

    def albedo_column_derivatives(self, parts, z, names, bounds):
        """[(d us / d z_j, d ub / d z_j)] of :meth:`albedo_columns` per free shape parameter."""
        return [tuple(self._white(self.samples_of(d[n])) * bounds.derivative(n, z[j])
                      for d in (parts.d_surface, parts.d_body)) for j, n in enumerate(names)]
