"""Joint fits: K images of one object (different lights, possibly different views) sharing one material.

    from fmbrdf_mi.fit.api.joint import fit_joint
    res = fit_joint([obs_1, obs_2, obs_3])       # Observations: each its own light, geometry, mask
    res.params, res.std_errors                   # the six parameters, from the joint likelihood
    res.images[k]["chi2_per_dof"]                # how well image k is explained

Each image is an :class:`~fmbrdf_mi.fit.inputs.observations.Observation` with its
own light direction, irradiance (relative light power: ``irradiance`` of
image k is its power relative to the others; the albedos absorb a common
factor), normals, view directions, mask, samples and footprint.  What they
share is the material: eta, alpha, beta, kappa, k_s, r_k.  The images are
independent measurements, so

* the **likelihood** (:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`)
  of all images is the product of theirs: the samples of every image's
  fitted super-pixels are stacked into one objective, with one camera noise
  model (one camera: gain and read noise must agree, or be unknown for all,
  then estimated from all residuals together);
* the **paper's loss** and its variants (:mod:`fmbrdf_mi.fit.objectives.loss_variants`)
  are computed over the union of the images' pixels (one intensity scale,
  one DoLP-term threshold, one inlier / outlier balance);
* the model is evaluated for all images in **one** BSDF evaluation (one
  table build per parameter change, one light direction per direction:
  :class:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator`), so K images cost
  about as much as one image with K times the pixels.

With ``free_power`` the relative powers of images 1 .. K-1 are estimated
too (:mod:`fmbrdf_mi.fit.problem.free_power`; image 0's is the reference).

The standard errors are the inverse of the joint Fisher information
(:mod:`fmbrdf_mi.fit.uncertainty`): J^T J over the standardised residuals of
all images.  ``max_pixels`` is split evenly between the images (each draws
its random subset with seed ``seed + k``).
"""
from __future__ import annotations

import dataclasses
import math
import numpy as np

from fmbrdf_mi.fit.api.fitting import FitOptions, fit, resolve_loss, select_pixels
from fmbrdf_mi.fit.api.options import check_fit_options
from fmbrdf_mi.fit.camera import samples as SM
from fmbrdf_mi.fit.camera.noise import NoiseModel
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.evaluate.predict import predict_image
from fmbrdf_mi.fit.objectives import loss as L, loss_variants as LV
from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective, PaperObjective
from fmbrdf_mi.fit.problem.problem import FitData


def same_noise(observations):
    """One camera: the images' noise models must agree (or all be unknown)."""
    noises = [o.noise for o in observations]
    known = [n is not None and n.known for n in noises]
    if any(known) and not all(known):
        raise InputError("joint fit: the camera noise (gain, read noise) is known for some images and not for "
                         "others; give it for all or none")
    if all(known):
        ref = noises[0]
        for k, n in enumerate(noises[1:], 1):
            if not (math.isclose(n.gain, ref.gain, rel_tol=1e-9) and math.isclose(n.read_noise, ref.read_noise,
                                                                                   rel_tol=1e-9, abs_tol=1e-12)
                    and n.step == ref.step):
                raise InputError(f"joint fit: image {k} has camera noise {n.describe()}, image 0 {ref.describe()}; "
                                 "a joint fit assumes one camera (scale a different exposure into the light "
                                 "power instead)")
        return dataclasses.replace(ref)
    return None


def prepare(observations, opts, loss):
    """The :class:`~fmbrdf_mi.fit.problem.problem.FitData` of several images (one objective over all their
    pixels, one evaluator), with each image's pixels and slice."""
    K = len(observations)
    per_image = None if not opts.max_pixels else max(1, int(math.ceil(opts.max_pixels / K)))
    idxs, excl = [], []
    for k, o in enumerate(observations):
        try:
            idx, ex = select_pixels(o, dataclasses.replace(opts, max_pixels=per_image, seed=opts.seed + k))
        except InputError as exc:
            raise InputError(f"image {k}: {exc}") from None
        idxs.append(idx)
        excl.append(ex)
    starts = np.cumsum([0] + [len(i) for i in idxs])
    slices = [(int(starts[k]), int(starts[k + 1])) for k in range(K)]
    excluded = {"candidates": sum(e["candidates"] for e in excl), "saturated": sum(e["saturated"] for e in excl),
                "dark": sum(e["dark"] for e in excl), "used": int(starts[-1]), "per_image": excl,
                "white_level": excl[0].get("white_level"), "dark_level": excl[0].get("dark_level")}
    geo = []  # (normals, views, lights, irradiances) per image
    if loss == "likelihood":
        smps = [o.samples if o.samples is not None else SM.from_stokes(o.stokes) for o in observations]
        A = smps[0].analyser()
        for k, s in enumerate(smps[1:], 1):
            if not np.allclose(s.analyser(), A) or s.dof != smps[0].dof:
                raise InputError(f"joint fit: image {k} ({s.source}, polariser order {s.angles}) and image 0 "
                                 f"({smps[0].source}, {smps[0].angles}) differ in their samples; a joint "
                                 "likelihood needs one layout (or use --loss paper)")
        per_point = any(np.any(s.offsets) for s in smps)
        ys = []
        for o, s, idx in zip(observations, smps, idxs):
            if per_point:
                n, v, _ = o.sample_geometry(idx, footprint=s.footprint())  # 4 points per super-pixel
            else:
                n, v, _ = o.sample_geometry(idx, footprint=None)
            geo.append((n, v))
            ys.append(s.at(idx))
        noise = same_noise(observations) or NoiseModel(step=smps[0].step)
        objective = LikelihoodObjective(np.concatenate(ys), A, noise, smps[0].dof)
        smp = smps[0]
        weights = None
    else:
        fps = [o.footprint for o in observations]
        for k, f in enumerate(fps[1:], 1):
            same = (f is None and fps[0] is None) or (f is not None and fps[0] is not None and
                                                     np.allclose(f[0], fps[0][0]) and np.allclose(f[1], fps[0][1]))
            if not same:
                raise InputError(f"joint fit: image {k}'s pixel footprint differs from image 0's; give all "
                                 "images the same kind (raw mosaics with one demosaicking, or all Stokes images)")
        stokes, var = [], []
        for o, idx in zip(observations, idxs):
            n, v, w = o.sample_geometry(idx)
            geo.append((n, v))
            stokes.append(o.stokes.reshape(3, -1)[:, idx])
            var.append(None if o.lin_variance is None else o.lin_variance.ravel()[idx])
        if any(x is None for x in var) and not all(x is None for x in var):
            raise InputError("joint fit: the camera noise is known for some images and not for others")
        target = L.Target.from_stokes(np.concatenate(stokes, axis=1), opts.dolp_min_intensity,
                                      None if var[0] is None else np.concatenate(var))
        objective = PaperObjective(target) if loss == "paper" else LV.make(loss, target)
        # neighbouring super-pixels of a bilinear-demosaicked mosaic are correlated (uncertainty.py):
        # stack the images' pixel grids one below the other, apart, so no two images are neighbours
        if all(o.samples is not None and o.samples.source == "raw mosaic" and o.meta.get("demosaic") != "superpixel"
               for o in observations):
            rows, cols, off = [], [], 0
            for o, idx in zip(observations, idxs):
                r, c = np.divmod(np.asarray(idx), o.shape[1])
                rows.append(r + off)
                cols.append(c)
                off += o.shape[0] + 2
            objective.grid = (np.concatenate(rows), np.concatenate(cols))
        smp = None
        w = observations[0].sample_geometry(idxs[0][:1])[2]
        weights = None if len(w) == 1 else w
    normals = np.concatenate([g[0] for g in geo])
    views = np.concatenate([g[1] for g in geo])
    lights = np.concatenate([np.tile(o.light_dir, (len(g[0]), 1)) for o, g in zip(observations, geo)])
    irr = np.concatenate([np.full(len(g[0]), o.irradiance) for o, g in zip(observations, geo)])
    model = get_model(opts.model)
    if np.allclose(irr, irr[0]):
        irr = float(irr[0])
    ev = PixelEvaluator(model, normals, views, lights, irr, weights=weights)
    flat_idx = np.concatenate(idxs)
    return FitData(loss, flat_idx, excluded, objective, smp, ev, image_pixels=idxs, slices=slices)


def fit_joint(observations, options=None, *, names=None, progress=True, powers=None, **kw):
    """Estimate one material from several :class:`Observation` s of the same object.

    Returns a :class:`~fmbrdf_mi.fit.result.FitResult` with ``images``
    (per-image diagnostics) and ``pixels`` (one array per image).

    ``options`` / keywords: :class:`~fmbrdf_mi.fit.api.fitting.FitOptions` (the
    pixel path and the Levenberg-Marquardt optimiser).  ``names``: labels of
    the images in the result (default ``image0``, ...).

    ``free_power=True`` (an option) estimates the light powers of images
    1 .. K-1 relative to image 0's (:mod:`fmbrdf_mi.fit.problem.free_power`);
    ``powers``: the relative powers the observations' irradiances already
    include (default 1 each): image 0's stays fixed, the others are where
    the search starts (``power_start="given"``) and what the fitted powers
    are reported against.  The result's ``powers`` and each
    image's ``power`` / ``power_se`` then hold them.
    """
    observations = list(observations)
    if not observations:
        raise InputError("joint fit: no images")
    opts = dataclasses.replace(options or FitOptions(), **kw)
    if opts.path != "pixel" or opts.optimizer != "lm":
        raise InputError("joint fit: works with the pixel path and optimizer 'lm'")
    names = list(names) if names is not None else [f"image{k}" for k in range(len(observations))]
    if len(names) != len(observations):
        raise InputError(f"joint fit: {len(names)} names for {len(observations)} images")
    losses = {resolve_loss(o, opts) for o in observations}
    if len(losses) != 1:
        raise InputError("joint fit: the camera noise is known for some images and not for others "
                         f"(loss 'auto' resolves to {sorted(losses)}); give it for all, or choose --loss")
    loss = losses.pop()
    if opts.free_power and len(observations) < 2:
        raise InputError("free_power: needs two or more fitted images (one image's power is not separable "
                         "from k_s and k_b)")
    try:
        given = [1.0] * len(observations) if powers is None else [float(p) for p in powers]
    except (TypeError, ValueError):
        given = []
    if len(given) != len(observations) or not all(math.isfinite(p) and p > 0 for p in given):
        raise InputError(f"powers: expected {len(observations)} positive numbers, got {powers!r}")
    check_fit_options(**dataclasses.asdict(opts))
    data = prepare(observations, opts, loss)
    idxs, slices = data.image_pixels, data.slices
    pmodel = None
    if opts.free_power:
        from fmbrdf_mi.fit.problem import free_power as FP

        pmodel = FP.PowerModel(get_model(opts.model), given)
        pev = FP.PowerEvaluator(data.evaluator, pmodel, [b - a for a, b in slices])
        data = dataclasses.replace(data, evaluator=pev,
                                   make_problem=FP.problem_factory(pmodel, pev, slices, opts.power_start))
    report = progress
    if progress is True:
        from fmbrdf_mi.fit.solve.optimise import default_progress as report
    say = report or (lambda m: None)
    say(f"[joint] {len(observations)} images, " + ", ".join(
        f"{n}: {b - a} px, light {np.round(o.light_dir, 3).tolist()}"
        for n, o, (a, b) in zip(names, observations, slices)))
    res = fit(observations[0], opts, progress=progress, data=data)
    images = diagnose(res, data, observations, names, pmodel)
    block = None
    if pmodel is not None:
        from fmbrdf_mi.fit.problem.free_power import split_result

        block = split_result(res, pmodel, names)
        for k, im in enumerate(images):
            im.update({"power": block["values"][k], "power_given": given[k], "power_se": block["std_errors"][k],
                       "power_ci95": block["ci95"][k], "power_reference": k == 0})
    for im in images:
        say(f"[joint] {im['name']}: " + ", ".join(f"{k} {im[k]:.4g}" for k in ("chi2_per_dof", "intensity_rel_rmse",
                                                                             "dolp_rmse") if im.get(k) is not None)
            + ("" if pmodel is None else ", " + power_text(im)))
    res.images, res.powers, res.pixels = images, block, idxs
    return res


def power_text(im):
    """``power 0.61 +- 0.004 (given 1)`` of one image of a free-power fit (its entry of ``images``)."""
    if im.get("power_reference"):
        return f"power {im['power']:.4g} (reference, fixed)"
    se = im.get("power_se")
    return f"power {im['power']:.4g}" + ("" if se is None else f" +- {se:.2g}") + f" (given {im['power_given']:.4g})"


def fitted_observation(obs, im):
    """``obs`` with the irradiance of the fitted light power (``im``: its entry of ``images``), else itself."""
    if im.get("power") is None or im["power"] == im["power_given"]:
        return obs
    return dataclasses.replace(obs, irradiance=obs.irradiance * im["power"] / im["power_given"])


def diagnose(res, data, observations, names, power_model=None):
    """Per image: pixels, light, irradiance, and how well the shared estimate explains it."""
    from fmbrdf_mi.fit.evaluate.models import State

    loss, excluded, objective, ev = data.loss, data.excluded, data.objective, data.evaluator
    idxs, slices = data.image_pixels, data.slices
    model = power_model or get_model(res.model)
    shape, a_s, a_b = model.split(res.params)
    parts = ev.parts(shape)
    st = State(shape, a_s, a_b)
    pred = a_s * parts.surface + a_b * parts.body  # (3, points)
    pts = pred.shape[1] // max(sum(len(i) for i in idxs), 1)
    out = []
    for k, (o, idx, (a, b)) in enumerate(zip(observations, idxs, slices)):
        s = pred[:, a * pts:b * pts]
        if pts > 1 and loss == "likelihood":
            s = s.reshape(3, b - a, pts).mean(axis=2)  # the super-pixel's mean Stokes (for the summaries)
        obs_s = o.stokes.reshape(3, -1)[:, idx]
        i_obs, i_pred = obs_s[0], s[0]
        d_obs = np.hypot(obs_s[1], obs_s[2]) / np.where(i_obs > 0, i_obs, 1.0)
        d_pred = np.hypot(s[1], s[2]) / np.where(i_pred > 0, i_pred, 1.0)
        bright = i_obs > 0.02 * np.percentile(i_obs, 99)
        im = {"name": names[k], "light_dir": o.light_dir.tolist(), "irradiance": o.irradiance,
              "n_pixels": int(b - a), "pixels_excluded": excluded["per_image"][k],
              "intensity_rel_rmse": float(np.sqrt(np.mean((i_pred - i_obs) ** 2)) / np.mean(i_obs)),
              "dolp_rmse": float(np.sqrt(np.mean((d_pred - d_obs)[bright] ** 2))) if bright.any() else None}
        if loss == "likelihood":
            r = objective.residuals(parts, st).reshape(-1, 4)[a:b]
            im["chi2"] = float(np.sum(r ** 2))
            im["chi2_per_dof"] = im["chi2"] / max((b - a) * objective.dof, 1)
        out.append(im)
    return out


def predict(model_name, params, obs):
    """Predicted Stokes (3, H, W) of one image of the object (its light, irradiance and geometry)."""
    return predict_image(model_name, params, obs)
