"""What a fit runs on (:func:`prepare`): the pixels of K >= 1 images, one objective over them and one
evaluator at them."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.albedo_prior import SmoothPrior, neighbour_pairs
from fmbrdf_mi.fit.evaluate.albedos import GroupAlbedos, PixelAlbedos
from fmbrdf_mi.fit.evaluate.bilinear_albedos import PER_PIXEL_LAYOUTS, bilinear_weights
from fmbrdf_mi.sensor import samples as SM
from fmbrdf_mi.sensor.mosaic import COLOURS
from fmbrdf_mi.sensor.noise import NoiseModel
from fmbrdf_mi.fit.evaluate.materials import MIN_MATERIAL_PIXELS, MaterialEvaluator, check_labels
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import Directions, PixelEvaluator
from fmbrdf_mi.fit.inputs.observations import erode as erode_mask, validate
from fmbrdf_mi.fit.objectives import loss as L
from fmbrdf_mi.fit.objectives import loss_variants as LV
from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective, PaperObjective
from fmbrdf_mi.fit.problem.problem import FitData

#: Pixels whose view or light direction is within this angle (degrees) of the normal are not fitted:
#: the BSDF's reverse-mode derivative in alpha is NaN there for some alpha (docs/computed.md).
POLE_EXCLUSION_DEG = 3.0


#: Fewest super-pixels a fit accepts.
MIN_PIXELS = 20


def check_max_pixels(max_pixels, images=1):
    """InputError unless ``max_pixels`` (0 or None: every usable pixel) leaves each of ``images`` images
    at least :data:`MIN_PIXELS` pixels."""
    if not max_pixels:
        return
    per_image = int(math.ceil(max_pixels / images))
    if per_image < MIN_PIXELS:
        split = f" per image of {images}" if images > 1 else ""
        raise InputError(f"max_pixels (--max-pixels) {max_pixels}: {per_image} pixels{split} are fewer than the "
                         f"{MIN_PIXELS} a fit needs from each image; give at least {MIN_PIXELS * images}, or 0 for "
                         "every usable pixel")


def select_pixels(obs, opts, use_samples=True, keep=None):
    """Flat indices of the pixels a fit uses and the counts of what was excluded; ``keep``: (H, W) bool, a
    label image's pixels, applied after the mask's erosion so material borders are not eroded."""
    validate(obs)
    check_max_pixels(opts.max_pixels)
    m = erode_mask(obs.mask, opts.erode)
    if keep is not None:
        m = m & keep
    n = obs.normals
    cos_v = np.sum(n * obs.view_dirs, axis=-1)
    cos_l = n @ obs.light_dir
    pole = math.cos(math.radians(POLE_EXCLUSION_DEG))
    m = m & (cos_v > opts.min_cos_view) & (cos_l > opts.min_cos_light) & (cos_v < pole) & (cos_l < pole)
    m &= np.all(np.isfinite(obs.stokes), axis=0)
    excluded = {"candidates": int(m.sum()), "saturated": 0, "dark": 0}
    smp = obs.samples if use_samples else None
    if smp is not None:
        excluded["saturated"] = int((m & smp.saturated).sum())
        excluded["dark"] = int((m & smp.dark & ~smp.saturated).sum())
        excluded["white_level"], excluded["dark_level"] = smp.white_level, smp.dark_level
        m &= smp.usable
    idx = np.flatnonzero(m.ravel())
    if len(idx) < MIN_PIXELS:
        why = ""
        if excluded["saturated"] or excluded["dark"]:
            why = (f" after excluding {excluded['saturated']} super-pixels with a sample at or above the white "
                   f"level {smp.white_level:g} and {excluded['dark']} with a sample at or below the dark level "
                   f"{smp.dark_level} (lower the exposure, or set --white-level / --dark-level)")
        raise InputError(f"only {len(idx)} usable pixels (mask eroded by {opts.erode}, n.v > "
                         f"{opts.min_cos_view}, n.l > {opts.min_cos_light}){why}; need at least {MIN_PIXELS}")
    if opts.max_pixels and len(idx) > opts.max_pixels:
        rng = np.random.default_rng(opts.seed)
        idx = np.sort(rng.choice(idx, opts.max_pixels, replace=False))
    excluded["used"] = int(len(idx))
    return idx, excluded


def resolve_loss(obs, opts):
    """``auto`` -> ``likelihood`` when the camera noise is known and the fit runs LM on the pixel path, else
    ``paper``."""
    if opts.loss == "auto":
        ok = opts.path == "pixel" and opts.optimizer == "lm"
        return "likelihood" if (ok and obs.noise is not None and obs.noise.known) else "paper"
    if opts.loss not in ("likelihood", "paper", *LV.VARIANTS):
        raise InputError(f"loss: expected 'likelihood', 'paper', 'intensity', 'dolp' or 'auto', got {opts.loss!r}")
    return opts.loss


def check_footprint(footprint, loss, why="the camera noise is known", name="--footprint"):
    """Refuse a footprint with the likelihood, which uses ``area_points`` instead."""
    if footprint not in (None, "auto") and loss == "likelihood":
        raise InputError(f"{name} {footprint}: only the paper's loss uses it; the likelihood ({why}) models "
                         "each sample over its own pixel with --area-points (or give --loss paper)")


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


#: A raw mosaic's default points per axis over which each sample's model value is averaged
#: (:meth:`~fmbrdf_mi.sensor.samples.Samples.footprint`).
RAW_AREA_POINTS = 2


def area_points(samples, opts):
    """m of the likelihood's m x m points per sample: ``opts.area_points``, else :data:`RAW_AREA_POINTS`
    for a raw mosaic (a sensor pixel integrates over its area) and 1 otherwise."""
    if opts.area_points is not None:
        return int(opts.area_points)
    return RAW_AREA_POINTS if samples.source in ("raw mosaic", "colour raw mosaic") else 1


def one_view(observations, what, why):
    """The first of ``observations``; InputError naming ``what`` and ``why`` unless all are of its view."""
    o0 = observations[0]
    for k, o in enumerate(observations[1:], 1):
        if o.shape != o0.shape or not np.allclose(o.view_dirs, o0.view_dirs):
            raise InputError(f"{what}: image {k} is not of the same view as image 0 (pixel grid and view "
                             f"directions must agree: {why})")
    return o0


def pixel_layout(observations, idxs, samples, bilinear=False, smooth=None, factor=1.0):
    """The :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos` of the cells ``idxs`` (per image, one view):
    one group per pixel and channel, shared by every image.  ``smooth``: tau of the smoothness prior
    (:mod:`fmbrdf_mi.fit.evaluate.albedo_prior`) in reported units, or None; ``bilinear``: each sample
    interpolates the pixel centres' albedos at its own point."""
    o0 = one_view(observations, "albedo per-pixel", "a pixel's albedo is that of one point of the object")
    flat = np.concatenate(idxs)
    pixels = np.unique(flat)
    cell = np.searchsorted(pixels, flat)
    H, W = o0.shape
    colour = samples.channel is not None
    C = len(COLOURS) if colour else 1
    gch = np.tile(np.arange(C), len(pixels))
    groups = cell[:, None] * C + (np.asarray(samples.channel, dtype=np.int64) if colour else np.zeros(samples.n, int))
    corners = weights = None
    if bilinear:
        if colour:
            raise InputError("albedo per-pixel-bilinear: not for colour mosaics (mono captures, raw or angle images)")
        have = np.zeros(H * W, bool)
        have[pixels] = True

        def present(r, c):
            inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
            return inside & have[np.where(inside, r * W + c, 0)]

        rows, cols = np.divmod(flat.astype(np.int64), W)
        corners, weights = bilinear_weights(rows, cols, samples.offsets, present)
        corners = np.searchsorted(pixels, corners[..., 0] * W + corners[..., 1])
    gpix = np.repeat(pixels, C)
    prior = None if smooth is None else SmoothPrior(neighbour_pairs(gpix, W, gch), len(gpix), smooth, factor)
    return PixelAlbedos(groups, len(gpix), gpix, corner_groups=corners, corner_weights=weights, prior=prior,
                        name="per-pixel-bilinear" if bilinear else "per-pixel", channel_of=gch if colour else None,
                        labels=COLOURS if colour else None)


def material_labels(observations, materials, loss, opts, evaluator=None):
    """(checked label image, M) of a fit of several materials; InputError for what materials do not work with."""
    o0 = one_view(observations, "materials", "one label image labels the pixels of one view")
    if loss != "likelihood":
        raise InputError("materials: needs the likelihood of the camera's samples (loss likelihood, or auto with "
                         f"the camera noise known; got loss {loss!r})")
    if opts.path != "pixel":
        raise InputError("materials: works on the pixel path (one evaluator per material), not the render path")
    lab = check_labels(materials, o0.shape)
    count = int(lab.max(initial=-1)) + 1
    if not count:
        raise InputError("materials: no pixel has a label >= 0 (0 .. M-1 are the materials)")
    if count > 1 and evaluator is not None:
        raise InputError("materials: the fit builds one evaluator per material; give no evaluator")
    if count > 1 and opts.free_power:
        raise InputError("materials: not with free_power (give the relative light powers)")
    return lab, count


def pixel_evaluator(model, geo):
    """The :class:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator` of ``geo`` ((observation, pixels,
    footprint) per image) with one light and irradiance when the images share them (no per-direction copies)."""
    directions, counts, weights = Directions.of_images(geo)
    obs = [o for o, _, _ in geo]
    irr_img = np.array([float(o.irradiance) for o in obs])
    irr = (float(irr_img[0]) if np.allclose(irr_img, irr_img[0]) else
           np.concatenate([np.full(c, o.irradiance) for o, c in zip(obs, counts)]))
    same_light = all(np.array_equal(o.light_dir, obs[0].light_dir) for o in obs)
    lights = (np.asarray(obs[0].light_dir, dtype=np.float64) if same_light else
              np.concatenate([np.tile(o.light_dir, (c, 1)) for o, c in zip(obs, counts)]))
    return PixelEvaluator(model, directions, None, lights, irr, weights=weights)


def prepare(observations, opts, loss, *, single=False, evaluator=None, materials=None, only=None):
    """The :class:`~fmbrdf_mi.fit.problem.problem.FitData` of K >= 1 images; ``single``: messages name no
    image; ``materials``: a label image (< 0: not fitted); ``only``: per image, the selected pixels to keep."""
    K, model = len(observations), get_model(opts.model)
    check_max_pixels(opts.max_pixels, K)
    lab = count = keep = None
    if materials is not None and opts.albedo_smooth is not None:
        raise InputError("materials: not with albedo_smooth (the albedo maps' smoothness prior) yet")
    if materials is not None:
        lab, count = material_labels(observations, materials, loss, opts, evaluator)
        keep = lab >= 0
        if count == 1:      # one material: the ordinary fit of the labelled pixels
            lab = None
    per_image = None if not opts.max_pixels else int(math.ceil(opts.max_pixels / K))
    idxs, excl = [], []
    for k, o in enumerate(observations):
        try:
            idx, ex = select_pixels(o, dataclasses.replace(opts, max_pixels=per_image, seed=opts.seed + k),
                                    keep=keep)
        except InputError as exc:
            if single:
                raise
            raise InputError(f"image {k}: {exc}") from None
        if only is not None:
            idx = idx[np.isin(idx, only[k])]
        idxs.append(idx)
        excl.append(ex)
    cell_material = None
    if lab is not None:
        cell_material = np.concatenate([lab.ravel()[i] for i in idxs])
        n_mat = np.bincount(cell_material, minlength=count)
        few = [m for m in range(count) if n_mat[m] < MIN_MATERIAL_PIXELS]
        if few:
            raise InputError(f"materials: label {few[0]} has {n_mat[few[0]]} fitted pixels, need at least "
                             f"{MIN_MATERIAL_PIXELS} per material (labels 0 .. {count - 1}; each material's shape "
                             "is estimated from its own pixels): merge it, or mark its pixels -1 (not fitted)")
    starts = np.cumsum([0] + [len(i) for i in idxs])
    slices = [(int(starts[k]), int(starts[k + 1])) for k in range(K)]
    excluded = excl[0] if single else {
        **{k: sum(e[k] for e in excl) for k in ("candidates", "saturated", "dark")}, "used": int(starts[-1]),
        "per_image": excl, "white_level": excl[0].get("white_level"), "dark_level": excl[0].get("dark_level")}
    geo = []  # (observation, pixels, footprint) per image
    if loss == "likelihood":
        smps = [o.samples if o.samples is not None else SM.from_stokes(o.stokes) for o in observations]
        A = smps[0].analyser()
        for k, s in enumerate(smps[1:], 1):
            if (s.analyser().shape != A.shape or not np.allclose(s.analyser(), A) or s.dof != smps[0].dof
                    or not np.array_equal(s.channel if s.channel is not None else [],
                                          smps[0].channel if smps[0].channel is not None else [])):
                raise InputError(f"joint fit: image {k} ({s.source}, polariser order {s.angles}) and image 0 "
                                 f"({smps[0].source}, {smps[0].angles}) differ in their samples; a joint "
                                 "likelihood needs one camera: one polariser layout and colour filter (or use "
                                 "--loss paper)")
        m = area_points(smps[0], opts)
        per_point = m > 1 or any(np.any(s.offsets) for s in smps)
        ys = []
        for o, s, idx in zip(observations, smps, idxs):
            geo.append((o, idx, s.footprint(m) if per_point else None))
            ys.append(s.at(idx))
        noise = same_noise(observations)
        if noise is None:
            o0 = observations[0]
            noise = dataclasses.replace(o0.noise) if single and o0.noise is not None else NoiseModel(step=smps[0].step)
        layout = None if smps[0].channel is None else GroupAlbedos("per-channel", smps[0].channel, COLOURS)
        if lab is not None and layout is not None:
            raise InputError("materials: not yet for colour mosaics (mono captures, raw or angle images)")
        if opts.albedo in PER_PIXEL_LAYOUTS:
            if lab is not None and opts.albedo == "per-pixel-bilinear":
                raise InputError("materials: not with albedo per-pixel-bilinear yet (use albedo per-pixel)")
            layout = pixel_layout(observations, idxs, smps[0], bilinear=opts.albedo == "per-pixel-bilinear",
                                  smooth=opts.albedo_smooth, factor=model.albedo_factor)
        elif lab is not None:
            layout = GroupAlbedos("per-material", np.repeat(cell_material[:, None], smps[0].n, axis=1),
                                  [str(m) for m in range(count)])
        objective = LikelihoodObjective(np.concatenate(ys), A, noise, smps[0].dof, layout=layout)
        smp = smps[0]
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
            geo.append((o, idx, "own"))
            stokes.append(o.stokes.reshape(3, -1)[:, idx])
            var.append(None if o.lin_variance is None else o.lin_variance.ravel()[idx])
        if any(x is None for x in var) and not all(x is None for x in var):
            raise InputError("joint fit: the camera noise is known for some images and not for others")
        target = L.Target.from_stokes(np.concatenate(stokes, axis=1), opts.dolp_min_intensity,
                                      None if var[0] is None else np.concatenate(var))
        objective = PaperObjective(target) if loss == "paper" else LV.VARIANTS[loss](target)
        # demosaicked neighbours are correlated: stack the grids apart so no two images neighbour
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
    own, mat = evaluator is None, None      # own: the evaluator is made here (a subsample makes its own)
    if lab is not None:     # one evaluator per material, of its cells' points
        evs = [pixel_evaluator(model, [(o, i[lab.ravel()[i] == m], fp) for o, i, fp in geo]) for m in range(count)]
        outs = evs[0].n // int(np.sum(cell_material == 0))      # outputs per cell
        cols = [(np.flatnonzero(cell_material == m)[:, None] * outs + np.arange(outs)).ravel() for m in range(count)]
        evaluator = MaterialEvaluator(Parameters(model, materials=count), evs, cols, len(cell_material) * outs)
        mat = {"labels": lab, "count": count, "cell_material": cell_material,
               "pixels": np.bincount(cell_material, minlength=count).tolist()}
    elif evaluator is None:
        evaluator = pixel_evaluator(model, geo)
    flat_idx = np.concatenate(idxs)

    def remake(m_new, cells=None):
        # m_new x m_new points per sample; ``cells``: sorted positions among the fitted pixels to keep
        c = None if cells is None else np.asarray(cells)
        keep = None if c is None else [idx[c[(c >= a) & (c < b)] - a] for idx, (a, b) in zip(idxs, slices)]
        return prepare(observations, dataclasses.replace(opts, area_points=int(m_new)), loss, single=single,
                       materials=materials, only=keep)

    def subsample(n):
        if K > 1 and opts.albedo in PER_PIXEL_LAYOUTS:    # the same pixels in every image

            view = np.unique(flat_idx)
            keep = np.random.default_rng(opts.seed).choice(view, min(len(view), -(-int(n) // K)), replace=False)
            return prepare(observations, opts, loss, single=single, only=[np.sort(keep)] * K)
        return prepare(observations, dataclasses.replace(opts, max_pixels=int(n)), loss, single=single)

    # a subsample is the same problem of fewer pixels where no pixel's unknowns couple to its neighbours'
    independent = opts.albedo != "per-pixel-bilinear" and opts.albedo_smooth is None
    return FitData(loss, flat_idx, excluded, objective, smp, evaluator, image_pixels=idxs, slices=slices,
                   materials=mat, area_points=m if loss == "likelihood" else None,
                   remake=remake if loss == "likelihood" else None,
                   subsample=subsample if own and lab is None and independent else None)
