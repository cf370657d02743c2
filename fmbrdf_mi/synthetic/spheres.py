"""Synthetic raw captures of a sphere for tests and benchmarks (the camera model of :mod:`fmbrdf_mi.sensor.camera`).

    ideal = ideal_sphere(params, res=40, light=(0.45, 0.35, 1.0))   # noise-free, per raw pixel
    obs = capture_observation(ideal, CameraModel(), seed=3)        # one noisy capture -> Observation

The sphere is orthographic, centred, radius ``res/2 - 1`` super-pixels; the
Stokes image is the model averaged over each raw pixel's area (4 x 4 points:
each raw sample sees its own pixel, as a real mosaic does).
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi import geometry as G
from fmbrdf_mi.fit.evaluate.predict import predict_image
from fmbrdf_mi.fit.inputs import observations as ob
from fmbrdf_mi.sensor import samples as SM
from fmbrdf_mi.sensor.camera import CameraModel, capture
from fmbrdf_mi.sensor.mosaic import stokes_from_raw
from fmbrdf_mi.sensor.noise import NoiseModel, demosaic_footprint, linear_stokes_variance


def ideal_sphere(params, res=40, light=(0.45, 0.35, 1.0), model="fmbrdf", area=4):
    """Noise-free Stokes (3, 2 res, 2 res) of the raw pixels, and the super-pixel geometry.

    Each raw pixel is the mean of the model over ``area`` x ``area`` points
    of its area (sub-pixel centres; points off the sphere count 0), as a
    sensor pixel integrates and ``render --raw``'s box filter does;
    ``area=1``: the model at the pixel's centre.
    """
    a = int(area)
    r2 = 2 * res
    stokes = sphere_points(params, res, light, model, a).reshape(3, r2, a, r2, a).mean(axis=(2, 4))
    n, m, v = G.sphere_normals((res, res), (res / 2, res / 2), res / 2 - 1)
    geom = G.SphereGeometry((res, res), (res / 2, res / 2), res / 2 - 1)
    return {"stokes": stokes, "normals": n, "mask": m, "view_dirs": v, "light": np.asarray(light, float),
            "geometry": geom,
            "params": dict(params), "model": model}


def sphere_points(params, res=40, light=(0.45, 0.35, 1.0), model="fmbrdf", area=4):
    """The model's Stokes (3, 2 res area, 2 res area) at the ``area`` x ``area`` points of every raw pixel
    (sub-pixel centres; 0 off the sphere): what :func:`ideal_sphere` averages per raw pixel."""
    a = int(area)
    r2 = 2 * res
    n2, m2, v2 = G.sphere_normals((r2 * a, r2 * a), (r2 * a / 2, r2 * a / 2), (r2 / 2 - 2) * a)
    obs2 = ob.Observation(np.ones((3, r2 * a, r2 * a)), m2, n2, v2, light)
    return predict_image(model, params, obs2)


def capture_observation(ideal, camera=None, *, seed=0, exposure=None, peak_fraction=0.8, known_noise=True,
                        demosaic="bilinear", noiseless=False):
    """One noisy raw capture of ``ideal`` as an :class:`Observation` (samples, noise model, Stokes image).

    The likelihood uses the raw samples; the paper's loss the Stokes image demosaicked with ``demosaic``
    (default bilinear, with the matching footprint: the fit command's default for raw mosaics; with
    ``superpixel`` the four samples' different points make false polarisation at highlights that the
    footprint average does not model).  ``noiseless``: no shot or read noise (rounding and clipping stay).
    """

    cam = camera or CameraModel()
    cap = capture(ideal["stokes"], cam, exposure=exposure, peak_fraction=peak_fraction, seed=seed,
                  noiseless=noiseless)
    smp = SM.from_raw(cap["raw"], cam.layout, cam.black_level, cam.white_level)
    stokes = stokes_from_raw(cap["raw"], cam.layout, cam.black_level, demosaic)
    noise = NoiseModel(cam.conversion_gain, cam.read_noise, 1.0) if known_noise else None
    # irradiance in DN: the albedos come back in the units of ``ideal`` (DN = input * exposure / gain)
    irr = cap["exposure"] / cam.conversion_gain
    meta = {"truth": ideal["params"], "demosaic": demosaic, "capture": {"exposure": cap["exposure"], "saturated": cap["saturated"],
                                                  "seed": seed}}

    # the paper's loss gets what it can use of the known noise: the Rice mean of the DoLP
    var = (linear_stokes_variance(stokes[0], cam.conversion_gain, cam.read_noise, demosaic,
                                  adc_step_e=cam.conversion_gain) if known_noise else None)
    return ob.Observation(stokes, ideal["mask"], ideal["normals"], ideal["view_dirs"], ideal["light"], irr,
                          meta, samples=smp, noise=noise, geometry=ideal["geometry"], lin_variance=var,
                          footprint=demosaic_footprint(demosaic)), cap


def smooth_texture(height, width=None, amplitude=0.4):
    """(k_s, k_b) maps (height, width) of the benches' and tests' smooth texture, x = column / width and
    y = row / height: k_s = 0.6 + ``amplitude`` sin 6x cos 4y, k_b = 0.4 + 0.1 cos(5x + 3y)."""
    width = height if width is None else width
    i, j = np.mgrid[0:height, 0:width]
    x, y = j / width, i / height
    return 0.6 + amplitude * np.sin(6 * x) * np.cos(4 * y), 0.4 + 0.1 * np.cos(5 * x + 3 * y)


def textured_sphere(shape_params, k_s_map, k_b_map, res=40, light=(0.45, 0.35, 1.0), model="fmbrdf", area=4):
    """``ideal_sphere`` of a textured object: the shape parameters ``shape_params`` (eta, alpha, beta,
    kappa) everywhere and albedos ``k_s_map``, ``k_b_map``, either

    * arrays (res, res): per super-pixel albedos (each super-pixel's four raw pixels share them: the cells
      of the per-pixel albedo layout ``per-pixel``); ``stokes`` (3, 2 res, 2 res) and the geometry on the
      super-pixel grid, as ``ideal_sphere``;
    * arrays (3, res, res) (colour: R, G, B): one pair per 4x4 colour period and channel; ``stokes``
      (3 channels, 3, 4 res, 4 res) per raw pixel (each channel's model, to be sampled by a colour camera:
      ``capture_colour``), the geometry on the period grid (sphere radius res/2 - 1/2 periods:
      ``ideal_sphere`` of 2 res super-pixels); or
    * callables ``f(x, y)`` of the image point in super-pixel units (super-pixel (i, j) covers
      x in [j - 1/2, j + 1/2), y in [i - 1/2, i + 1/2): its centre is (j, i)): a *continuous* texture, as a
      camera sees one; every one of the ``area`` x ``area`` points of every raw pixel takes the texture's
      value at that point, and the raw pixel is the mean of albedo x model over its points (each
      polariser sample of a super-pixel sees its own albedos).

    The truth is in ``params`` (the shape) and ``k_s_map``, ``k_b_map`` (callables: the texture at the
    super-pixel centres, (res, res); ``k_s_mean``, ``k_b_mean``: the texture's mean over each super-pixel's
    area points)."""
    base = {k: v for k, v in shape_params.items() if k not in ("k_s", "r_k")}
    if callable(k_s_map) != callable(k_b_map):
        raise ValueError("k_s_map, k_b_map: give two arrays or two callables")
    if callable(k_s_map):
        a = int(area)
        surface = sphere_points(dict(base, k_s=1.0, r_k=0.0), res, light, model, a)
        both = sphere_points(dict(base, k_s=1.0, r_k=1.0), res, light, model, a)
        # point (r, c) of the (2 res a)^2 grid sits at ((c + 1/2) / (2 a) - 1/2, (r + 1/2) / (2 a) - 1/2)
        t = (np.arange(2 * res * a) + 0.5) / (2 * a) - 0.5
        X, Y = np.meshgrid(t, t)
        ks, kb = (np.broadcast_to(np.asarray(f(X, Y), dtype=np.float64), X.shape) for f in (k_s_map, k_b_map))
        pts = ks * surface + kb * (both - surface)
        stokes = pts.reshape(3, 2 * res, a, 2 * res, a).mean(axis=(2, 4))
        out = ideal_sphere(dict(base, k_s=1.0, r_k=0.0), res=res, light=light, model=model, area=1)
        j = np.arange(res, dtype=np.float64)
        C, R = np.meshgrid(j, j)
        out.update(stokes=stokes, params=dict(base),
                   k_s_map=np.broadcast_to(np.asarray(k_s_map(C, R), dtype=np.float64), C.shape).copy(),
                   k_b_map=np.broadcast_to(np.asarray(k_b_map(C, R), dtype=np.float64), C.shape).copy(),
                   k_s_mean=ks.reshape(res, 2 * a, res, 2 * a).mean(axis=(1, 3)),
                   k_b_mean=kb.reshape(res, 2 * a, res, 2 * a).mean(axis=(1, 3)))
        return out
    colour = np.ndim(k_s_map) == 3
    sub = 2 * res if colour else res             # ideal_sphere's super-pixel grid
    out = textured(lambda p: ideal_sphere(p, res=sub, light=light, model=model, area=area),
                   shape_params, k_s_map, k_b_map, res)
    if colour:
        n, m, v = G.sphere_normals((res, res), (res / 2, res / 2), res / 2 - 0.5)
        out.update(normals=n, mask=m, view_dirs=v,
                   geometry=G.SphereGeometry((res, res), (res / 2, res / 2), res / 2 - 0.5))
    return out


def textured(ideal_of, shape_params, k_s_map, k_b_map, res):
    """The textured capture of any ideal object: ``ideal_of(params)`` its noise-free dict
    (:func:`ideal_sphere`, :func:`fmbrdf_mi.synthetic.mesh_object.ideal_object`), evaluated with unit
    surface and body albedos and combined per cell with ``k_s_map``, ``k_b_map`` (the model is linear in them:
    paper: s_s + s_b): (res, res) per super-pixel (each 2 x 2 raw pixels), or (3, res, res) per colour channel
    and 4x4 period (``stokes`` then (3 channels, 3, 4 res, 4 res): ``ideal_of`` must give 4 res raw pixels)."""
    k_s_map, k_b_map = (np.asarray(m, dtype=np.float64) for m in (k_s_map, k_b_map))
    colour = k_s_map.ndim == 3
    want = (3, res, res) if colour else (res, res)
    if k_s_map.shape != want or k_b_map.shape != want:
        raise ValueError(f"k_s_map, k_b_map: expected ({res}, {res}) or (3, {res}, {res}), got {k_s_map.shape} "
                         f"and {k_b_map.shape}")
    base = {k: v for k, v in shape_params.items() if k not in ("k_s", "r_k")}
    surface = ideal_of(dict(base, k_s=1.0, r_k=0.0))
    both = ideal_of(dict(base, k_s=1.0, r_k=1.0))
    f = 4 if colour else 2
    up = (lambda m: np.repeat(np.repeat(m, f, axis=-2), f, axis=-1))
    S, B = surface["stokes"], both["stokes"] - surface["stokes"]
    out = dict(surface)
    if colour:
        stokes = up(k_s_map)[:, None] * S[None] + up(k_b_map)[:, None] * B[None]
    else:
        stokes = up(k_s_map) * S + up(k_b_map) * B
    out.update(stokes=stokes, params=dict(base), k_s_map=k_s_map, k_b_map=k_b_map)
    return out


def capture_colour(ideal, camera=None, *, seed=0, exposure=None, peak_fraction=0.8, noiseless=False, exact=False,
                   erode=1):
    """One capture of a colour ``ideal`` (:func:`textured_sphere` with (3, res, res) maps) by a colour camera
    (default: :class:`~fmbrdf_mi.sensor.camera.CameraModel` with an RGGB filter): ``(obs, samples, noise, cap)`` for
    :func:`fmbrdf_mi.fit.api.colour.fit_colour` (the observation's mask eroded by ``erode`` periods: the
    outermost periods are partly off the sphere, which each raw pixel's mean over its area models only where
    the whole period is on it).  ``noiseless``: no shot or read noise (rounding and clipping stay);
    ``exact``: the samples are the model's values themselves in DN (no noise, rounding or clipping)."""
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.camera import intensity_at_each_pixel_colour
    from fmbrdf_mi.sensor.samples import colour_samples

    cam = camera or CameraModel(cfa=mosaic.BAYER_RGGB)
    cap = capture(ideal["stokes"], cam, exposure=exposure, peak_fraction=peak_fraction, seed=seed,
                  noiseless=noiseless or exact)
    if exact:
        dn = intensity_at_each_pixel_colour(ideal["stokes"], cam.layout, cam.cfa) * cap["exposure"] / cam.conversion_gain
        smp = colour_samples(dn, cam.layout, cam.cfa, 0.0, cam.white_level)
    else:
        smp = colour_samples(cap["raw"], cam.layout, cam.cfa, cam.black_level, cam.white_level)
    R = ideal["mask"].shape[0]
    obs = ob.Observation(np.ones((3, R, R)), ob.erode(ideal["mask"], erode), ideal["normals"], ideal["view_dirs"],
                         np.asarray(ideal["light"], float), cap["exposure"] / cam.conversion_gain,
                         {"truth": ideal["params"], "capture": {"exposure": cap["exposure"], "seed": seed}},
                         geometry=ideal["geometry"])
    return obs, smp, NoiseModel(cam.conversion_gain, cam.read_noise, 1.0), cap


def half_labels(res, count=2):
    """A (res, res) label image of ``count`` materials in vertical bands, left to right (two: left half 0,
    right half 1)."""
    col = np.arange(res) * count // res
    return np.broadcast_to(col[None, :], (res, res)).astype(np.int64).copy()


def material_sphere(params, labels, res=40, light=(0.45, 0.35, 1.0), model="fmbrdf", area=4):
    """``ideal_sphere`` of several materials: ``params`` a list of M parameter dicts, ``labels`` (res, res)
    the material of each super-pixel (its four raw pixels share it; a label < 0 shows material 0, and is
    not fitted when the labels are given to the fit).  Each raw pixel is its material's model averaged over
    the pixel's area.  The truth is ``params`` (the list) and ``labels``."""
    labels = np.asarray(labels, dtype=np.int64)
    if labels.shape != (res, res):
        raise ValueError(f"labels: expected ({res}, {res}), got {labels.shape}")
    if labels.max() >= len(params):
        raise ValueError(f"labels: {int(labels.max())} is not one of the {len(params)} materials")
    ideals = [ideal_sphere(p, res=res, light=light, model=model, area=area) for p in params]
    up = np.repeat(np.repeat(np.maximum(labels, 0), 2, axis=0), 2, axis=1)
    out = dict(ideals[0])
    out.update(stokes=np.choose(up[None], [i["stokes"] for i in ideals]), params=[dict(p) for p in params],
               labels=labels)
    return out
