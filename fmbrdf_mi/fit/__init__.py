"""Inverse rendering: estimate FMBRDF parameters from one polarimetric image (paper section 5).

    from fmbrdf_mi.fit import Observation, fit
    result = fit(obs)                     # obs: Observation (see observations.py)
    result.params                         # eta, alpha, beta, kappa, k_s, r_k
"""
from .fitting import FitOptions, FitResult, fit, predict_image, usable_pixels
from .observations import InputError, Observation

__all__ = ["fit", "FitOptions", "FitResult", "predict_image", "usable_pixels", "Observation", "InputError"]
