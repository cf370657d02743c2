"""Normal refinement: per-pixel normals and the material from K >= 3 images of one view (beyond the paper's fit).

    from fmbrdf_mi.fit.api.normal_refine import refine_normals
    res = refine_normals(observations, initial_normals)   # same camera, K lights
    res.normals, res.params, res["alternation"]           # a FitResult

The authors' ``shape_reconstruction`` alternates between the material and the
normals; so does this, with the package's own pieces:

1. **material**: a joint fit (:func:`fmbrdf_mi.fit.api.joint.fit_joint`) of the
   K images with the current normal map (the first one from the coarse
   search, later ones from the previous estimate);
2. **normals**, the material held fixed: every pixel's normal moves in its
   tangent plane, n = normalise(n0 + u t1 + v t2), to lower

       E_i = sum_k || (S_ik(n) - Sbar_ik) / s_k ||^2  +  lam sum_{j in N(i)} || n_i - n_j ||^2

   with S_ik the model's (S0, S1, S2) of pixel i under light k at the
   pixel centre, Sbar_ik the observed (demosaicked) Stokes vector, s_k image
   k's mean observed intensity over the pixels, N(i) the 4-neighbours in
   the mask and ``lam`` the smoothness weight.  Pixels are coupled only
   through the prior, so ``steps`` iterations of the one Levenberg-Marquardt
   (:mod:`fmbrdf_mi.fit.solve.lm`) solve a damped 2 x 2 system per pixel
   with the neighbours at their current values (Jacobi); the data Jacobian
   comes from central differences taken for all pixels at once (one BSDF
   evaluation per perturbation: a pixel's prediction depends on its own
   normal only).  A trial keeps a pixel's step where it lowers its E_i; a
   trial that lowers none raises the damping (:func:`_normal_step`).

Normals that turn away from the camera (n . v < 0.05) are not accepted.
The polarisation pins the normal's azimuth (AoLP) and the intensity and
DoLP its zenith, so K >= 3 lights make the per-pixel problem well posed
without the prior; the prior suppresses noise.
"""
from __future__ import annotations

import dataclasses
import math
import time
import types

import numpy as np

from fmbrdf_mi.fit.api.fitting import FitOptions
from fmbrdf_mi.fit.api.joint import fit_joint
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.inputs.observations import check_mask, check_observations, erode
from fmbrdf_mi.fit.problem.normals import tangent_bases
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import lm as LM
from fmbrdf_mi.fit.solve.optimise import default_progress


class _Predictor:
    """(K, 3, n) model Stokes of n pixels under each of K lights; one BSDF, normals exchanged per call."""

    def __init__(self, model, views, lights, irr):
        self.model, self.views, self.K = model, views, len(lights)
        self.lights = np.repeat(np.asarray(lights, float), len(views), axis=0)
        self.irr = np.repeat(np.asarray(irr, float), len(views))
        self.ev = None

    def __call__(self, shape, a_s, a_b, normals):
        nn = np.tile(normals / np.linalg.norm(normals, axis=1, keepdims=True), (self.K, 1))
        vv = np.tile(self.views, (self.K, 1))
        if self.ev is None:
            self.ev = PixelEvaluator(self.model, nn, vv, self.lights, self.irr)
        else:
            self.ev.set_geometry(nn, vv, self.lights)
        return self.ev.parts(shape)


def _predict(pred, shape, a_s, a_b, normals):
    K, n = pred.K, len(normals)
    p = pred(shape, a_s, a_b, normals)
    s = a_s * p.surface + a_b * p.body
    return s.reshape(3, K, n).transpose(1, 0, 2)


def _neighbours(mask):
    """Flat indices (into the mask's pixels) of each pixel's 4-neighbours in the mask, -1 where none."""
    h, w = mask.shape
    pos = -np.ones((h, w), int)
    ys, xs = np.nonzero(mask)
    pos[ys, xs] = np.arange(len(ys))
    nb = -np.ones((len(ys), 4), int)
    for j, (dy, dx) in enumerate(((-1, 0), (1, 0), (0, -1), (0, 1))):
        y2, x2 = ys + dy, xs + dx
        ok = (y2 >= 0) & (y2 < h) & (x2 >= 0) & (x2 < w)
        nb[ok, j] = pos[y2[ok], x2[ok]]
    return nb


def _normal_step(n, energy, predict, sbar, scale, nb, views, lam, steps, h):
    """Up to ``steps`` iterations of the one Levenberg-Marquardt (:mod:`fmbrdf_mi.fit.solve.lm`) on the normals
    ``n`` (n, 3), the material held: returns (normals, pixel steps accepted).

    Pixels are coupled only through the prior, so the linear solve is one damped 2 x 2 system per pixel
    (its tangent-plane unknowns, the neighbours at their current values: Jacobi), and the trial keeps each
    pixel's step only where it lowers that pixel's E_i (and keeps the normal facing the camera): the
    objective, the sum of the E_i, falls whenever one pixel's does.  A trial in which no pixel improves
    raises the damping, which shortens every pixel's step.  The data Jacobian is central differences for
    all pixels at once (one BSDF evaluation per perturbation).
    """
    has = (nb >= 0)[..., None]

    def linearise(n):
        nbv = np.where(has, n[np.maximum(nb, 0)], 0.0)
        data, prior, pred = energy(n, nbv)
        t1, t2 = tangent_bases(n)
        r = ((pred - sbar) / scale).transpose(2, 0, 1).reshape(len(n), -1)   # (n, 3K)
        J = np.zeros((len(n), r.shape[1], 2))
        for j, t in enumerate((t1, t2)):
            cols = []
            for d in (h, -h):
                nn = n + d * t
                nn /= np.linalg.norm(nn, axis=1, keepdims=True)
                cols.append(((predict(nn) - sbar) / scale).transpose(2, 0, 1).reshape(len(n), -1))
            J[:, :, j] = (cols[0] - cols[1]) / (2 * h)
        # prior: lam sum_j |n_i - n_j|^2, gradient 2 lam sum_j (n_i - n_j) projected on (t1, t2)
        cnt = (nb >= 0).sum(axis=1)
        g_prior = np.sum(np.where(has, n[:, None, :] - nbv, 0.0), axis=1)
        A = np.einsum("nri,nrj->nij", J, J) + (lam * cnt)[:, None, None] * np.eye(2)
        b = -(np.einsum("nri,nr->ni", J, r) + lam * np.stack([np.sum(g_prior * t1, 1), np.sum(g_prior * t2, 1)], 1))
        e = data + prior
        return types.SimpleNamespace(A=A, b=b, t1=t1, t2=t2, nbv=nbv, e=e, f=float(e.sum()))

    def solve(lin, mu):     # per pixel (A + mu diag(A)) delta = b
        D = np.einsum("nii->ni", lin.A)
        A = lin.A + (mu * D + 1e-9)[:, :, None] * np.eye(2)
        return np.linalg.solve(A, lin.b[..., None])[..., 0]

    def trial(n, delta, lin):
        cand = n + delta[:, :1] * lin.t1 + delta[:, 1:] * lin.t2
        cand /= np.linalg.norm(cand, axis=1, keepdims=True)
        d2, p2, _ = energy(cand, lin.nbv)
        ok = (d2 + p2 < lin.e) & (np.sum(cand * views, 1) > 0.05)
        count[0] = int(ok.sum())
        return np.where(ok[:, None], cand, n), float(np.where(ok, d2 + p2, lin.e).sum()), None

    count, accepted = [0], [0]
    lin = linearise(n)
    res = LM.levenberg_marquardt(n, lin.f, linearise, solve, trial, lin=lin, max_iter=steps, refresh=1,
                                 final_linearise=False, on_accept=lambda it, x, f: accepted.__setitem__(
                                     0, accepted[0] + count[0]))
    return res.x, accepted[0]


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


def refine_normals(observations, normals, *, mask=None, lam=0.5, rounds=3, steps=4, h=1e-3, fit_options=None,
                   material=None, progress=True):
    """Refine ``normals`` (H, W, 3) and the material from K >= 3 :class:`Observation` s of one view.

    The observations share their pixel grid, mask and view directions (one
    camera) and differ in the light.  ``mask``: the pixels refined (default:
    the first observation's mask eroded by 1).  ``lam``: smoothness weight
    (in units of the normalised Stokes residuals).  ``material``: reported
    parameters to hold fixed (known material: only the normals are refined,
    no joint fits).  Returns the last joint fit's :class:`~fmbrdf_mi.fit.result.FitResult` with
    ``normals`` and ``mask`` (``material`` given: one with those and the material), the rounds in
    ``res["alternation"]``.
    """

    say = default_progress if progress is True else (progress or (lambda m: None))
    obs = list(observations)
    n_map = check_views(obs, normals)
    m = erode(obs[0].mask, 1) if mask is None else check_mask(mask, obs[0].shape)
    idx = np.flatnonzero(m.ravel())
    nb = _neighbours(m)
    views = obs[0].view_dirs.reshape(-1, 3)[idx]
    lights = [o.light_dir for o in obs]
    irr = [o.irradiance for o in obs]
    sbar = np.stack([o.stokes.reshape(3, -1)[:, idx] for o in obs])          # (K, 3, n)
    scale = sbar[:, 0].mean(axis=1)[:, None, None]                            # (K, 1, 1)
    opts = fit_options or FitOptions()
    history, init, res = [], opts.init, None
    t0 = time.time()
    n = n_map.reshape(-1, 3)[idx]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for rnd in range(1, rounds + 1):
        for o in obs:
            o.normals = n_map
            o.geometry = None
        if material is None:
            res = fit_joint(obs, dataclasses.replace(opts, init=init), progress=False)
            params = res.params
        else:
            params = dict(material)
        model = get_model(opts.model)
        init = dict(params)
        sh, a_s, a_b = Parameters(model).split(params)
        pred_fn = _Predictor(model, views, lights, irr)
        say(f"[normals] round {rnd}: material " + " ".join(f"{k}={v:.4g}" for k, v in params.items())
            + f" ({time.time() - t0:.1f} s)")

        def energy(nn, nbv):
            pred = _predict(pred_fn, sh, a_s, a_b, nn)
            data = np.sum(((pred - sbar) / scale) ** 2, axis=(0, 1))
            diff = nn[:, None, :] - nbv
            prior = lam * np.sum(np.where((nb >= 0)[..., None], diff ** 2, 0.0), axis=(1, 2))
            return data, prior, pred

        n, accepted = _normal_step(n, energy, lambda nn: _predict(pred_fn, sh, a_s, a_b, nn), sbar, scale, nb, views,
                                   lam, steps, h)
        n_map = n_map.copy()
        n_map.reshape(-1, 3)[idx] = n
        nbv = np.where((nb >= 0)[..., None], n[np.maximum(nb, 0)], 0.0)
        data, prior, _ = energy(n, nbv)
        history.append({"round": rnd, "time": time.time() - t0, "params": params,
                        "data_energy": float(data.mean()), "prior_energy": float(prior.mean()),
                        "accepted_steps": accepted})
        say(f"[normals] round {rnd}: mean data energy {data.mean():.4g}, prior {prior.mean():.4g}, "
            f"{accepted} pixel steps accepted")
    for o in obs:
        o.normals = n_map
    if material is None:
        res = fit_joint(obs, dataclasses.replace(opts, init=init), progress=False)
    else:
        res = FitResult(model=opts.model, params=dict(material), loss=math.nan, loss_terms={}, std_errors={},
                        history=[], stop_reason=f"material given: {rounds} round(s) of normals only", n_pixels=len(idx),
                        n_outliers=0, timings={}, options=dataclasses.asdict(opts), converged=False,
                        objective="none (material given)", pixels=idx)
    res.normals, res.mask = n_map, m
    res.details = dict(res.details or {}, alternation=history, time=time.time() - t0)
    return res


def angular_error_deg(n, n_ref, mask):
    """Angles (degrees) between two normal maps on the mask."""
    a, b = n[mask], n_ref[mask]
    c = np.sum(a * b, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def photometric_stereo(observations, mask=None):
    """Lambertian photometric stereo (Woodham 1980) from K >= 3 images of one view: (H, W, 3) unit normals.

    Per pixel, the least-squares b of I_k / E_k = l_k . b over the lights
    (E_k the image's irradiance, I_k its S0); n = b / |b|, flipped towards
    the camera when it points away.  The authors' shape reconstruction starts
    from the same; specular highlights bias it, which the refinement corrects.
    """
    obs = check_observations(observations, "photometric stereo", least=0)
    if len(obs) < 3:
        raise InputError(f"photometric stereo: needs K >= 3 images, got {len(obs)}")
    m = obs[0].mask if mask is None else check_mask(mask, obs[0].shape)
    Lm = np.stack([o.light_dir for o in obs])                                  # (K, 3)
    I = np.stack([o.stokes[0][m] / o.irradiance for o in obs])                 # (K, n)
    b = np.linalg.lstsq(Lm, I, rcond=None)[0].T                                 # (n, 3)
    nrm = np.linalg.norm(b, axis=1, keepdims=True)
    n = np.where(nrm > 0, b / np.where(nrm > 0, nrm, 1.0), np.array([0.0, 0.0, 1.0]))
    v = obs[0].view_dirs[m]
    n = np.where((np.sum(n * v, 1) < 0)[:, None], -n, n)
    out = np.zeros(obs[0].shape + (3,))
    out[..., 2] = 1.0
    out[m] = n
    return out
