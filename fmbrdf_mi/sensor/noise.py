"""The noise of a sample in image units (:class:`NoiseModel`), of a demosaicked Stokes image, and the footprints
of demosaicked and box-filtered pixels: what the fits weight and blur their model with."""
from __future__ import annotations

import dataclasses

import numpy as np


#: Variance factor of bilinear demosaicking (weights 9, 3, 3, 1 / 16 per angle).
DEMOSAIC_VARIANCE = {"bilinear": (81 + 9 + 9 + 1) / 256.0, "superpixel": 1.0}


def linear_stokes_variance(s0, gain, read_noise, demosaic="bilinear", adc_step_e=None):
    """Per-pixel variance of S1 (and of S2) of a demosaicked capture, in the units of ``s0``.

    ``gain``: electrons per unit of ``s0`` (for raw images in DN: the camera's
    conversion gain, e-/DN); ``read_noise``: electrons rms; ``adc_step_e``:
    the ADC step in electrons, adding step^2 / 12 (None: no quantisation
    term).  Each polariser pixel behind S1 = I0 - I90 passes about S0 / 2, so
    var(S1) = f * 2 * (gain S0 / 2 + read_noise^2 + step^2 / 12) / gain^2, with
    f the demosaicking's variance factor (:data:`DEMOSAIC_VARIANCE`).
    This is what :class:`fmbrdf_mi.fit.objectives.loss.Target` subtracts to remove the
    upward bias that noise gives the DoLP of dim, weakly polarised pixels.
    """
    if not (gain > 0 and read_noise >= 0):
        raise ValueError(f"noise: need gain > 0 (electrons per unit) and read noise >= 0, got {gain}, {read_noise}")
    e = np.clip(np.asarray(s0, dtype=np.float64), 0.0, None) * gain / 2.0
    var_e = e + read_noise ** 2 + (adc_step_e ** 2 / 12.0 if adc_step_e else 0.0)
    return DEMOSAIC_VARIANCE[demosaic] * 2.0 * var_e / gain ** 2


def demosaic_footprint(demosaic="bilinear"):
    """Where a demosaicked super-pixel's S0 comes from: (offsets (K, 2), weights (K,)).

    Offsets (dx right, dy down) are in super-pixels from the super-pixel
    centre, at the centres of the raw pixels that contribute.  ``bilinear``
    (:func:`fmbrdf_mi.sensor.mosaic.angle_images_at_superpixel_centres`):
    each raw pixel of the 4 x 4 neighbourhood serves exactly one angle, with
    weight (3/4 or 1/4) x (3/4 or 1/4) per axis, i.e. [1, 3, 3, 1] / 8 at
    -0.75, -0.25, 0.25, 0.75 along each axis.  ``superpixel``: the 2 x 2 raw
    pixels, 1/4 each.  A fit that evaluates its model over this footprint
    sees the same blur as the data (:class:`fmbrdf_mi.fit.Observation`).
    """
    if demosaic == "bilinear":
        pos, w = np.array([-0.75, -0.25, 0.25, 0.75]), np.array([1.0, 3.0, 3.0, 1.0]) / 8.0
    elif demosaic == "superpixel":
        pos, w = np.array([-0.25, 0.25]), np.array([0.5, 0.5])
    else:
        raise ValueError(f"demosaic: expected 'bilinear' or 'superpixel', got {demosaic!r}")
    X, Y = np.meshgrid(pos, pos)
    return np.stack([X.ravel(), Y.ravel()], 1), np.outer(w, w).ravel()


def box_footprint(n=3):
    """An n x n grid over the pixel, equal weights: a pixel that averages over its area."""
    pos = (np.arange(n) + 0.5) / n - 0.5
    X, Y = np.meshgrid(pos, pos)
    return np.stack([X.ravel(), Y.ravel()], 1), np.full(n * n, 1.0 / (n * n))


# ---------------------------------------------------------------- noise
@dataclasses.dataclass
class NoiseModel:
    """Variance of one sample, in image units: v(mu) = mu / gain + (read_noise / gain)^2 + step^2 / 12.

    ``gain``: electrons per image unit (e-/DN for raw images); ``read_noise``
    electrons rms; ``step``: quantisation step in image units (1 for DN, 0
    for float images).  ``gain=None``: unknown; v = a mu + b with (a, b)
    estimated from residuals (:meth:`estimate`).
    """

    gain: float = None
    read_noise: float = 0.0
    step: float = 1.0
    a: float = 0.0          # unknown-gain model: v = a mu + b
    b: float = 1.0
    estimated: bool = False

    @property
    def known(self):
        return self.gain is not None

    def variance(self, mu):
        mu = np.clip(np.asarray(mu, dtype=np.float64), 0.0, None)
        if self.known:
            return mu / self.gain + (self.read_noise / self.gain) ** 2 + self.step ** 2 / 12.0
        return self.a * mu + self.b

    def estimate(self, mu, resid2, dof_factor=1.0):
        """Fit v = a mu + b (a, b >= 0) to squared residuals: the Gaussian quasi-likelihood of e = r^2,
        E[e] = v, var[e] = 2 v^2, solved by iterated weighted least squares to its fixed point (so the
        estimate is a function of the residuals alone and does not oscillate between IRLS rounds)."""
        mu = np.clip(np.asarray(mu, dtype=np.float64).ravel(), 0.0, None)
        e = np.asarray(resid2, dtype=np.float64).ravel() / dof_factor
        # work in normalised units (noise-free data have residuals of float32 size)
        mscale = max(float(np.mean(mu)), 1e-300)
        escale = max(float(np.mean(e)), 1e-30 * mscale ** 2, 1e-300)
        mu, e = mu / mscale, e / escale
        floor = 1e-9
        X = np.stack([mu, np.ones_like(mu)], 1)
        a, b = 0.0, 1.0
        for _ in range(50):
            v = np.maximum(a * mu + b, floor)
            sw = 1.0 / v
            a1, b1 = np.linalg.lstsq(X * sw[:, None], e * sw, rcond=None)[0]
            if b1 < floor:  # keep v > 0: a alone
                a1, b1 = float(np.sum(sw * sw * mu * e) / max(np.sum(sw * sw * mu * mu), 1e-300)), floor
            if a1 < 0:
                a1, b1 = 0.0, max(float(np.sum(sw * sw * e) / np.sum(sw * sw)), floor)
            done = abs(a1 - a) <= 1e-6 * abs(a1) + 1e-12 and abs(b1 - b) <= 1e-6 * abs(b1) + 1e-12
            a, b = float(a1), float(b1)
            if done:
                break
        a, b = a * escale / mscale, b * escale
        self.a, self.b, self.estimated = a, b, True

    def describe(self):
        if self.known:
            return (f"known: gain {self.gain:g} e-/unit, read noise {self.read_noise:g} e-, "
                    f"step {self.step:g} unit")
        if self.estimated:
            g = f"{1 / self.a:.4g}" if self.a > 0 else "inf"
            return (f"estimated from the residuals: variance = {self.a:.4g} I + {self.b:.4g} "
                    f"(gain ~ {g} e-/unit)")
        return "unknown (equal weights)"

    def to_dict(self):
        d = dataclasses.asdict(self)
        d["description"] = self.describe()
        return d
