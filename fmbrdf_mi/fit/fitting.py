"""``fit()``: estimate a model's parameters from one :class:`Observation` (paper section 5)."""
from __future__ import annotations

import dataclasses
import json
import math
import time

import numpy as np

from . import loss as L
from . import optimise as O
from .models import Bounds, get_model
from .options import check_fit_options
from .observations import InputError, erode as erode_mask
from .pixel_model import PixelEvaluator, RenderEvaluator

#: Pixels whose view or light direction is within this angle (degrees) of the
#: normal are left out of the fit: the BSDF's reverse-mode derivative with
#: respect to alpha is NaN there for some alpha (see the README).
POLE_EXCLUSION_DEG = 3.0


@dataclasses.dataclass
class FitOptions:
    model: str = "fmbrdf"
    path: str = "pixel"               # "pixel" or "render"
    optimizer: str = "lm"             # "lm" or "adam"
    bounds: dict = None               # {name: (lo, hi)} narrowing the model's bounds
    init: dict = None                 # reported parameters to start from (skips the coarse search)
    max_iter: int = 40
    tol: float = 1e-4
    time_limit: float = None          # seconds for each refinement round
    max_time: float = 110.0           # seconds for the whole fit: refinement stops when exceeded
    rounds: int = 3                   # inlier/outlier refresh rounds
    max_pixels: int = 20000           # random subset of the usable pixels (None: all)
    erode: int = 2                    # pixels removed from the mask's border
    min_cos_view: float = 0.1         # n . v above this
    min_cos_light: float = 0.02       # n . l above this
    dolp_min_intensity: float = 0.02  # DoLP term: observed I > this x 99th percentile
    seed: int = 0
    lr: float = 0.02                  # Adam (step in the reparameterised variables)
    spp: int = 16                     # render path
    bsdf_prefix: str = "sphere.bsdf"  # render path: traverse prefix of the object's BSDF


@dataclasses.dataclass
class FitResult:
    model: str
    params: dict
    loss: float
    loss_terms: dict
    std_errors: dict
    history: list
    stop_reason: str
    n_pixels: int
    n_outliers: int
    timings: dict
    options: dict
    weakly_identified: list = dataclasses.field(default_factory=list)
    pixels: np.ndarray = dataclasses.field(repr=False, default=None)

    def to_json(self):
        d = dataclasses.asdict(self)
        d.pop("pixels")
        return d

    def save_json(self, path, extra=None):
        d = self.to_json()
        d.update(extra or {})
        with open(path, "w") as f:
            json.dump(d, f, indent=2, default=_json_default)


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


#: A parameter is reported as weakly identified when its Gauss-Newton standard
#: error exceeds this fraction of max(|value|, WEAK_FLOOR[name]): the image
#: does not pin it down to 5 %.
WEAK_REL = 0.05
WEAK_FLOOR = {"kappa": 10.0}


def weakly_identified(params, std):
    return [k for k, v in params.items()
            if k in std and std[k] > WEAK_REL * max(abs(v), WEAK_FLOOR.get(k, 0.0))]


def usable_pixels(obs, opts):
    """Flat indices of the pixels a fit uses (see :class:`FitOptions` for the criteria)."""
    m = erode_mask(obs.mask, opts.erode)
    n = obs.normals
    cos_v = np.sum(n * obs.view_dirs, axis=-1)
    cos_l = n @ obs.light_dir
    pole = math.cos(math.radians(POLE_EXCLUSION_DEG))
    m = m & (cos_v > opts.min_cos_view) & (cos_l > opts.min_cos_light) & (cos_v < pole) & (cos_l < pole)
    m &= np.all(np.isfinite(obs.stokes), axis=0)
    idx = np.flatnonzero(m.ravel())
    if len(idx) < 20:
        raise InputError(f"only {len(idx)} usable pixels (mask eroded by {opts.erode}, n.v > "
                         f"{opts.min_cos_view}, n.l > {opts.min_cos_light}); need at least 20")
    if opts.max_pixels and len(idx) > opts.max_pixels:
        rng = np.random.default_rng(opts.seed)
        idx = np.sort(rng.choice(idx, opts.max_pixels, replace=False))
    return idx


def make_evaluator(model, obs, idx, opts, scene=None):
    if opts.path == "pixel":
        n, v, w = obs.sample_geometry(idx)
        return PixelEvaluator(model, n, v, obs.light_dir, obs.irradiance, weights=None if len(w) == 1 else w)
    if opts.path == "render":
        if scene is None:
            raise InputError("path 'render' needs a Mitsuba scene (scene=...) containing the model's BSDF")
        ev = RenderEvaluator(model, scene, opts.bsdf_prefix, idx, spp=opts.spp, seed=opts.seed)
        if ev.shape != obs.shape:
            raise InputError(f"scene renders {ev.shape[1]}x{ev.shape[0]} pixels but the observation "
                             f"is {obs.shape[1]}x{obs.shape[0]}")
        return ev
    raise InputError(f"path: expected 'pixel' or 'render', got {opts.path!r}")


def fit(obs, options=None, *, scene=None, progress=True, **kw):
    """Estimate the parameters of ``options.model`` from ``obs``; returns a :class:`FitResult`.

    Keyword arguments override fields of :class:`FitOptions` (the CLI's
    options have the same names).  ``progress``: True prints to stderr, a
    callable receives each progress line, False is silent.
    """
    opts = dataclasses.replace(options or FitOptions(), **kw)
    check_fit_options(**dataclasses.asdict(opts))
    if opts.optimizer not in ("lm", "adam"):
        raise ValueError(f"optimizer: expected 'lm' or 'adam', got {opts.optimizer!r}")
    if opts.path == "render" and opts.optimizer != "adam":
        raise InputError("path 'render' works with optimizer 'adam' only (reverse-mode gradient through "
                         "mi.render; its forward-mode derivatives, which 'lm' needs, miss the body term)")
    report = O.default_progress if progress is True else (progress or (lambda m: None))
    model = get_model(opts.model)
    t0 = time.time()
    idx = usable_pixels(obs, opts)
    var = None if obs.lin_variance is None else obs.lin_variance.ravel()[idx]
    target = L.Target.from_stokes(obs.stokes.reshape(3, -1)[:, idx], opts.dolp_min_intensity, var)
    ev = make_evaluator(model, obs, idx, opts, scene)
    problem = O.Problem(model, ev, target, Bounds(model, opts.bounds), report)
    report(f"[fit] {model.name} on {len(idx)} pixels ({opts.path} path), "
           f"{int(target.dolp_valid.sum())} in the DoLP term"
           + ("" if var is None else ", DoLP term with the given noise variance (Rice mean)"))
    history = []
    if opts.init:
        shape, a_s, a_b = model.split(opts.init)
        st = O.State(shape, a_s, a_b)
        t_search, cands = 0.0, []
    else:
        cands = O.coarse_search(problem)
        st = cands[0][1]
        t_search = time.time() - t0
        history.append({"stage": "search", "iter": 0, "loss": cands[0][0], "time": t_search,
                        "params": model.report(st.shape, st.a_s, st.a_b)})
        report(f"[search] start: loss {cands[0][0]:.4e}  {O._fmt(problem, st)}")
    st, reason, J, r = _refine(problem, st, opts, target, t0, history, report)
    if not opts.init and _albedo_at_bound(problem, st):
        # A start where one lobe is switched off (albedo ~ 0) can trap the refinement: with the
        # lobe's albedo near zero its shape barely moves the loss.  Refine again from the best
        # coarse candidate that has both lobes, and keep whichever ends with the lower loss.
        alt = next((c for _, c in cands[1:11] if not _albedo_at_bound(problem, c)), None)
        if alt is not None:
            report(f"[fit] one albedo ended at ~0; refining again from {O._fmt(problem, alt)}")
            saved = (problem.outliers.copy(), problem.w.copy())
            first = _own_split_loss(problem, st)
            st2, reason2, J2, r2 = _refine(problem, alt, opts, target, t0, history, report)
            if _own_split_loss(problem, st2) < first:
                st, reason, J, r = st2, reason2, J2, r2
            else:
                problem.outliers, problem.w = saved
    can_jac = opts.path == "pixel"
    parts = problem.parts(st, jac=(J is None and can_jac))
    if J is None and can_jac:
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
    i, rho = L.predict(parts.surface, parts.body, st.a_s, st.a_b, target.lin_sigma)
    li, lr = L.loss_terms(target, problem.w, i, rho)
    std = O.standard_errors(problem, st, J, r) if J is not None else {}
    if problem.n_nonfinite:
        report(f"[fit] {problem.n_nonfinite} pixels had non-finite BSDF derivatives; their Jacobian rows were zeroed")
    weak = weakly_identified(model.report(st.shape, st.a_s, st.a_b), std)
    if weak:
        report(f"[fit] weakly identified (standard error > {WEAK_REL:.0%}): {', '.join(weak)}")
    t_total = time.time() - t0
    report(f"[fit] done in {t_total:.1f} s: loss {li + lr:.6e} ({reason})  {O._fmt(problem, st)}")
    return FitResult(model=model.name, params=model.report(st.shape, st.a_s, st.a_b), loss=li + lr,
                     loss_terms={"intensity": li, "dolp": lr}, std_errors=std, history=history,
                     stop_reason=reason, n_pixels=len(idx),
                     n_outliers=int((problem.outliers & target.dolp_valid).sum()),
                     timings={"search": t_search, "total": t_total, "evaluations": problem.n_evals,
                              "nonfinite_derivative_pixels": problem.n_nonfinite},
                     options=dataclasses.asdict(opts), weakly_identified=weak, pixels=idx)


def _refine(problem, st, opts, target, t0, history, report):
    """Refinement rounds from ``st``, refreshing the inlier/outlier split until it settles.

    Returns (State, stop reason, Jacobian or None, residuals or None).
    """
    reason, J, r = "", None, None
    for rnd in range(1, max(1, opts.rounds) + 1):
        parts = problem.parts(st)
        old_out, old_w = problem.outliers.copy(), problem.w.copy()
        problem.set_weights(parts, st)
        if rnd > 1:
            valid = target.dolp_valid
            changed = int(((old_out != problem.outliers) & valid).sum())
            smaller = min(int((problem.outliers & valid).sum()), int((~problem.outliers & valid).sum()))
            if changed <= max(5, 0.1 * smaller):  # the weighting is settled
                problem.outliers, problem.w = old_out, old_w
                break
        report(f"[fit] round {rnd}: {int((problem.outliers & target.dolp_valid).sum())} outliers "
               f"(surface-dominated) / {int((~problem.outliers & target.dolp_valid).sum())} inliers")
        left = None if opts.max_time is None else opts.max_time - (time.time() - t0)
        limit = min([x for x in (opts.time_limit, left) if x is not None], default=None)
        if limit is not None and limit <= 0:
            reason = f"max_time {opts.max_time:g} s reached"
            break
        if opts.optimizer == "lm":
            st, f, reason, J, r = O.levenberg_marquardt(problem, st, max_iter=opts.max_iter, tol=opts.tol,
                                                        time_limit=limit, history=history, round_no=rnd)
        else:
            st, f, reason = O.adam(problem, st, max_iter=opts.max_iter, lr=opts.lr, tol=opts.tol,
                                   time_limit=limit, history=history, round_no=rnd)
            J = r = None
    return st, reason, J, r


#: An albedo whose lobe contributes less than this fraction of the other's
#: mean intensity over the fitted pixels counts as switched off.
ALBEDO_BOUND = 1e-3


def _albedo_at_bound(problem, st):
    parts = problem.parts(st)
    c_s = st.a_s * float(np.mean(parts.surface[0]))
    c_b = st.a_b * float(np.mean(parts.body[0]))
    return min(c_s, c_b) < ALBEDO_BOUND * max(c_s, c_b)


def _own_split_loss(problem, st):
    return O._score(problem, problem.parts(st), st)


def predict_image(model_name, params, obs, pixels=None):
    """Predicted Stokes (3, H, W) of ``obs``'s geometry and light with reported ``params`` (pixel path).

    Pixels outside ``pixels`` (flat indices; default: the mask) are 0.
    """
    model = get_model(model_name)
    shape, a_s, a_b = model.split(params)
    idx = np.flatnonzero(obs.mask.ravel()) if pixels is None else np.asarray(pixels)
    n, v, w = obs.sample_geometry(idx)
    ev = PixelEvaluator(model, n, v, obs.light_dir, obs.irradiance, weights=None if len(w) == 1 else w)
    parts = ev.parts(shape)
    out = np.zeros((3, obs.shape[0] * obs.shape[1]))
    out[:, idx] = a_s * parts.surface + a_b * parts.body
    return out.reshape(3, *obs.shape)
