"""The paper's loss (eq:optimization) and its residual form.

    loss = 1/M sum_i (Ibar_i - I_i)^2  +  sum_i w_i (rhobar_i - rho_i)^2 / sum_i w_i

I the intensity, rho the DoLP (observed: bar).  Where the paper is silent:

* intensities are divided by the mean observed intensity (``scale``);
* a pixel is an *outlier* where surface reflection dominates its predicted intensity; outliers and inliers
  carry equal total weight in the DoLP term, refreshed between rounds;
* only pixels brighter than ``dolp_min_intensity`` x the 99th percentile enter the DoLP term;
* with the noise of S1, S2 known the model side is the Rice mean (:mod:`fmbrdf_mi.sensor.rice`), since the
  noise biases the observed DoLP upwards.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fmbrdf_mi.sensor import rice

DOLP_EPS = 1e-12


@dataclasses.dataclass
class Target:
    """The observed side of the loss at the fitted pixels."""

    intensity: np.ndarray      # (n,) observed S0, image units
    dolp: np.ndarray           # (n,) observed DoLP, as measured
    dolp_valid: np.ndarray     # (n,) bool: pixel enters the DoLP term
    scale: float               # intensity unit (mean observed intensity)
    lin_sigma: np.ndarray = None  # (n,) noise standard deviation of S1 and S2, if known

    @classmethod
    def from_stokes(cls, stokes_px, dolp_min_intensity=0.02, lin_variance=None):
        """From observed (3, n) Stokes values of the fitted pixels (and var(S1) = var(S2), (n,), if known)."""
        s = np.asarray(stokes_px, dtype=np.float64)
        i = s[0]
        rho = np.sqrt(s[1] ** 2 + s[2] ** 2) / np.where(i > 0, i, 1.0)
        rho = np.where(i > 0, rho, 0.0)
        scale = float(np.mean(i))
        if not scale > 0:
            raise ValueError("observation: the fitted pixels are black (mean intensity <= 0)")
        valid = i > dolp_min_intensity * np.percentile(i, 99)
        if not valid.any():
            raise ValueError("observation: no pixel is bright enough for the DoLP term")
        sigma = None
        if lin_variance is not None:
            sigma = np.sqrt(np.clip(np.broadcast_to(np.asarray(lin_variance, dtype=np.float64), i.shape),
                                    0.0, None))
        return cls(i, rho, valid, scale, sigma)


def predict(parts_surface, parts_body, a_s, a_b, lin_sigma=None):
    """Intensity and DoLP (n,) of a_s * surface + a_b * body (3, n); with ``lin_sigma`` the DoLP's Rice mean."""
    s = a_s * parts_surface + a_b * parts_body
    i = s[0]
    lin = np.sqrt(s[1] ** 2 + s[2] ** 2 + DOLP_EPS ** 2)
    if lin_sigma is not None:
        lin = rice.mean_length(lin, lin_sigma)
    return i, lin / np.where(i > 0, i, 1.0)


def outlier_mask(surface_i, body_i, a_s, a_b):
    """Pixels where surface reflection dominates the predicted intensity."""
    return a_s * np.asarray(surface_i) > a_b * np.asarray(body_i)


def weights(outliers, dolp_valid):
    """The paper's w_i over the DoLP-term pixels (0 elsewhere)."""
    out = np.asarray(outliers, bool) & dolp_valid
    inl = ~np.asarray(outliers, bool) & dolp_valid
    n_out, n_in = int(out.sum()), int(inl.sum())
    w = dolp_valid.astype(np.float64)
    if n_out and n_in:
        w[out] = n_in / n_out
    return w


def residuals(target, w, i_pred, rho_pred):
    """Vector r with r . r = loss: intensity part first, then DoLP part (zeros where w = 0)."""
    m = len(target.intensity)
    r_i = (i_pred - target.intensity) / (target.scale * np.sqrt(m))
    r_rho = np.sqrt(w / w.sum()) * (rho_pred - target.dolp)
    return np.concatenate([r_i, r_rho])


def loss_dr(target, w, s0, s1, s2):
    """The same loss as a Dr.Jit expression of predicted Dr.Jit (S0, S1, S2) (for reverse-mode AD)."""
    import drjit as dr
    import mitsuba as mi

    m = len(target.intensity)
    i_obs = mi.Float(target.intensity.astype(np.float32))
    rho_obs = mi.Float(target.dolp.astype(np.float32))
    wt = mi.Float((w / w.sum()).astype(np.float32))
    safe_i = dr.select(s0 > 0, s0, 1.0)
    lin = dr.sqrt(s1 * s1 + s2 * s2 + DOLP_EPS ** 2)
    if target.lin_sigma is not None:
        lin = rice.mean_length_dr(lin, mi.Float(target.lin_sigma.astype(np.float32)))
    rho = lin / safe_i
    li = dr.sum(dr.square((s0 - i_obs) * (1.0 / target.scale))) * (1.0 / m)
    lr = dr.sum(wt * dr.square(rho - rho_obs))
    return li + lr
