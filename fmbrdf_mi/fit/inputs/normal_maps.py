"""Normal maps of K >= 3 images of one view: the shared-view check, the photometric-stereo start, angular errors."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.observations import check_mask, check_observations


def check_views(obs, normals):
    """K >= 3 observations of one view; returns the normal map as a float64 copy (H, W, 3)."""
    obs = check_observations(obs, "normal refinement", least=0)
    if len(obs) < 3:
        raise InputError(f"normal refinement: needs K >= 3 images under different lights, got {len(obs)}")
    shape = obs[0].shape
    for k, o in enumerate(obs[1:], 1):
        if o.shape != shape or not np.allclose(o.view_dirs, obs[0].view_dirs):
            raise InputError(f"normal refinement: image {k} is not of the same view as image 0 (pixel grid and "
                             "view directions must agree)")
    n_map = np.asarray(normals, dtype=np.float64).copy()
    if n_map.shape != shape + (3,):
        raise InputError(f"normals: expected shape {shape + (3,)}, got {n_map.shape}")
    if not np.all(np.isfinite(n_map[obs[0].mask])):
        raise InputError("normals: non-finite values inside the mask")
    return n_map


def angular_error_deg(n, n_ref, mask=None):
    """Angles (degrees) between two normal maps, on the ``mask`` if given (a zero vector's: 90)."""
    a, b = (n, n_ref) if mask is None else (n[mask], n_ref[mask])
    c = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def photometric_stereo(observations, mask=None):
    """Lambertian photometric stereo (Woodham 1980) from K >= 3 images of one view: (H, W, 3) unit normals b / |b|,
    b per pixel the least-squares solution of S0_k / E_k = l_k . b, flipped to face the camera; highlights bias it."""
    obs = check_observations(observations, "photometric stereo", least=0)
    if len(obs) < 3:
        raise InputError(f"photometric stereo: needs K >= 3 images, got {len(obs)}")
    m = obs[0].mask if mask is None else check_mask(mask, obs[0].shape)
    Lm = np.stack([o.light_dir for o in obs])                                  # (K, 3)
    I = np.stack([o.stokes[0][m] / o.irradiance for o in obs])                 # (K, n)
    b = np.linalg.lstsq(Lm, I, rcond=None)[0].T                                 # (n, 3)
    nrm = np.linalg.norm(b, axis=1, keepdims=True)
    n = np.where(nrm > 0, b / np.where(nrm > 0, nrm, 1.0), np.array([0.0, 0.0, 1.0]))
    out = np.zeros(obs[0].shape + (3,)) + np.array([0.0, 0.0, 1.0])
    out[m] = np.where((np.sum(n * obs[0].view_dirs[m], 1) < 0)[:, None], -n, n)
    return out
