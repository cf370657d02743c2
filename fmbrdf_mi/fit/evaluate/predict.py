"""Relighting check (paper section 6.3): :func:`predict_image` under another light from the estimates and
its :func:`relight_error`."""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import Directions, PixelEvaluator
from fmbrdf_mi.fit.inputs.observations import erode as erode_mask


def predict_image(model_name, params, obs, pixels=None, maps=None, labels=None):
    """Predicted Stokes (3, H, W) of ``obs``'s geometry and light with reported ``params``; 0 outside
    ``pixels`` (flat indices; default: the mask).  ``maps``: ``k_s``, ``k_b`` (H, W) of a per-pixel fit
    (``params`` then shape only).  ``labels``: the label image of a fit of several materials (``params`` per
    material; label < 0 gives 0)."""
    idx = np.flatnonzero(obs.mask.ravel()) if pixels is None else np.asarray(pixels)
    if labels is not None:
        lab = np.asarray(labels).ravel()
        out = np.zeros((3, obs.shape[0] * obs.shape[1]))
        per = Parameters(get_model(model_name), materials=int(lab.max()) + 1).per_material(params)
        for m, pm in enumerate(per):
            sub = idx[lab[idx] == m]
            if len(sub):
                out[:, sub] = predict_image(model_name, pm, obs, sub, maps).reshape(3, -1)[:, sub]
        return out.reshape(3, *obs.shape)
    model = get_model(model_name)
    if maps is None:
        shape, a_s, a_b = Parameters(model).split(params)
    else:
        shape = {n: float(params[n]) for n in model.shape_names}
        a_s, a_b = (np.asarray(maps[k], dtype=np.float64).ravel()[idx] / model.albedo_factor
                    for k in ("k_s", "k_b"))
    directions, _, weights = Directions.of_images([(obs, idx, "own")])
    ev = PixelEvaluator(model, directions, None, obs.light_dir, obs.irradiance, weights=weights)
    parts = ev.parts(shape)
    out = np.zeros((3, obs.shape[0] * obs.shape[1]))
    out[:, idx] = a_s * parts.surface + a_b * parts.body
    return out.reshape(3, *obs.shape)


def relight_error(model_name, params, obs, erode=2, min_cos_view=0.1, maps=None, labels=None):
    """The paper's relighting error of ``obs`` (the object under a second light): ``rel_rmse`` (RMSE of the
    predicted intensity / mean observed one, on the mask eroded by ``erode``, n . v > ``min_cos_view``),
    ``rmse``, ``mean_observed``, ``n_pixels`` and ``predicted`` (3, H, W).  ``maps``, ``labels``: as
    :func:`predict_image`."""
    m = erode_mask(obs.mask, erode) & (np.sum(obs.normals * obs.view_dirs, axis=-1) > min_cos_view)
    idx = np.flatnonzero((m & np.all(np.isfinite(obs.stokes), axis=0)).ravel())
    if maps is not None:
        idx = idx[np.isfinite(np.asarray(maps["k_s"]).ravel()[idx])]
    if labels is not None:
        idx = idx[np.asarray(labels).ravel()[idx] >= 0]
    pred = predict_image(model_name, params, obs, idx, maps=maps, labels=labels)
    i_obs = obs.stokes[0].ravel()[idx]
    i_pred = pred[0].ravel()[idx]
    rmse = float(np.sqrt(np.mean((i_pred - i_obs) ** 2)))
    mean = float(np.mean(i_obs))
    return {"rel_rmse": rmse / mean, "rmse": rmse, "mean_observed": mean, "n_pixels": int(len(idx)),
            "predicted": pred}
