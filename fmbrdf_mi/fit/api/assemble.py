"""A solved problem made into a :class:`~fmbrdf_mi.fit.result.FitResult` (:func:`assemble`); :func:`settle`
redoes what derives from the uncertainty block after a check (:mod:`fmbrdf_mi.fit.api.checks`)."""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve.driver import solve


@dataclasses.dataclass
class Fitted:
    """What the checks after a fit need (a result's ``fitted``, not serialised); ``solution``'s ``J``, ``r``
    are at the estimate once the covariance is computed."""

    problem: object
    data: object
    solution: object
    options: object
    report: object
    deadline: float = None
    image_shape: tuple = None
    labels: object = None
    history: list = dataclasses.field(default_factory=list)
    applied: list = dataclasses.field(default_factory=list)
    evaluations: int = 0
    t0: float = dataclasses.field(default_factory=time.time)

    def problem_of(self, data):
        """The problem of ``data`` (the fit's, remade or subsampled) under the fit's options and deadline."""
        o = self.options
        return data.problem(get_model(o.model), o.bounds, self.report, o.fixed, self.deadline)

    def solve(self, problem, **kw):
        """:func:`~fmbrdf_mi.fit.solve.driver.solve` of ``problem`` under the fit's options and progress."""
        o = self.options
        return solve(problem, rounds=max(1, o.rounds) + 2 * (self.data.loss == "likelihood"), optimizer=o.optimizer,
                     max_iter=o.max_iter, tol=o.tol, time_limit=o.time_limit, lr=o.lr, max_time=o.max_time,
                     report=self.report, **kw)


def assemble(fx):
    """The :class:`~fmbrdf_mi.fit.result.FitResult` of ``fx``, with a converged pixel-path fit's covariance."""
    problem, sol, data, report = fx.problem, fx.solution, fx.data, fx.report
    st, loss, objective = sol.state, data.loss, data.objective
    unc, groups = {}, None
    problem.deadline = None  # the uncertainty is part of the answer: no time limit
    parts = problem.parts(st, jac=sol.converged and fx.options.path == "pixel")
    if sol.converged and fx.options.path == "pixel":
        r, J = problem.residuals_and_jacobian(parts, st, problem.to_z(st))
        fx.solution = dataclasses.replace(sol, J=J, r=r)
        n_ind = None if loss != "likelihood" else len(data.pixels) * objective.dof - problem.n_eliminated(st)
        c = U.covariance(problem, st, J, r, n_ind, parts)
        fx.applied, unc = c.applied, U.summary(problem, st, c)
        if U.noise_flagged(unc):
            report("[fit] warning: " + U.misfit_text(unc))
        if problem.eliminates:
            groups = U.pixel_albedos(problem, st, parts, J, unc, c.cov_z)
    elif not sol.converged:
        fx.applied, unc = [("not-converged", "")], {"std_errors": {}}
    value = problem.obj.value(parts, st)
    if problem.n_nonfinite:
        report(f"[fit] {problem.n_nonfinite} pixels had non-finite BSDF derivatives; their Jacobian rows were zeroed")
    model = problem.model
    params = problem.params.report(st.shape, st.a_s, st.a_b)
    albedo = maps = None
    if problem.eliminates:
        albedo, maps = albedo_block(problem, st, parts, groups, fx.image_shape, value, report)
    n_out = int((objective.outliers & objective.target.dolp_valid).sum()) if loss != "likelihood" else 0
    res = FitResult(model=model.name, params=params, loss=value, loss_terms=problem.obj.loss_terms(parts, st),
                    std_errors=unc.get("std_errors", {}), history=fx.history, stop_reason=sol.reason,
                    n_pixels=len(data.pixels), n_outliers=n_out,
                    timings={"search": sol.t_search, "total": time.time() - fx.t0,
                             "evaluations": problem.n_evals + fx.evaluations,
                             "nonfinite_derivative_pixels": problem.n_nonfinite},
                    options=dataclasses.asdict(fx.options), converged=bool(sol.converged), objective=loss,
                    uncertainty=unc, noise=objective.noise.to_dict() if loss == "likelihood" else None,
                    pixels_excluded=data.excluded, starts=sol.starts, pixels=data.pixels, albedo=albedo, maps=maps,
                    details={"internal": {"shape": dict(st.shape), "a_s": np.asarray(st.a_s).tolist(),
                                          "a_b": np.asarray(st.a_b).tolist()},
                             "residuals": data_residuals(problem.obj, parts, st),
                             "n_free": len(problem.to_z(st)) + problem.n_eliminated(st)},
                    fitted=fx)
    return settle(res)


def settle(res):
    """``res`` with its method text, weakly identified parameters and materials block redone."""
    fx, unc = res.fitted, res.uncertainty
    if fx.applied:
        unc["method"] = U.method_text(fx.applied)
    table = fx.problem.params
    res.weakly_identified = U.weakly_identified(table, res.params, res.std_errors, unc.get("at_bound", ()))
    mat = fx.data.materials
    if mat is not None or fx.labels is not None:    # fit.json's materials block (mat None: the labelled pixels)
        pixels = [res.n_pixels] if mat is None else mat["pixels"]
        res.materials = {"count": table.count or 1, "pixels": [int(p) for p in pixels],
                         "parameters": table.per_material(res.params),
                         "std_errors": table.per_material(res.std_errors), "ci95": table.per_material(unc.get("ci95"))}
    return res


def albedo_block(problem, st, parts, groups, shape, value, report):
    """:func:`albedo_maps` of ``groups`` (None: the values without errors) plus the smoothness prior's
    ``albedo.prior`` block (effective parameters: the hat matrix's trace)."""
    lay, obj, pr = problem.layout, problem.obj, problem.layout.prior
    if groups is None:
        groups = lay.maps(st.a_s, st.a_b, np.full((lay.n_groups, 2, 2), np.nan), problem.model.albedo_factor,
                          U.SPLIT_REL)
    albedo, maps = albedo_maps(lay, shape, groups, prior=pr is not None)
    if pr is not None:
        albedo["prior"] = p = {
            "kind": pr.describe(), "tau_s": pr.tau[0], "tau_b": pr.tau[1], "pairs": int(len(pr.pairs)),
            "penalty": obj.penalty(st), "data_chi2": float(np.sum(data_residuals(obj, parts, st) ** 2)),
            "effective_parameters": lay.effective_parameters(*obj.albedo_columns(parts)),
            "parameters": 2 * int(lay.n_groups), "null_dims": int(pr.null_dims()), "dof_rule": PRIOR_DOF_RULE}
        report(f"[fit] albedo smoothness prior: penalty {p['penalty']:.4g} of chi^2 {value:.6g}, effective albedo "
               f"parameters {p['effective_parameters']:.1f} of {p['parameters']}")
    report(f"[fit] albedo maps: {albedo['pixels']} pixels, surface / body split identified in "
           f"{albedo['identified_fraction']:.0%} (median k_s {albedo['k_s_median']:.4g}, k_b "
           f"{albedo['k_b_median']:.4g})")
    if albedo.get("warning"):
        report("[fit] warning: " + albedo["warning"])
    return albedo, maps


def data_residuals(obj, parts, st):
    """The objective's residuals without the albedo prior's rows."""
    r = obj.residuals(parts, st)
    return r if obj.prior is None else r[:obj.y.size]


#: chi^2's degrees of freedom under the albedo smoothness prior (fit.json ``albedo.prior``).
PRIOR_DOF_RULE = ("chi^2 (data + penalty) has N - p - n0 degrees of freedom (N independent samples, p free shape "
                  "parameters, n0 = 2 per connected set of pixels, the prior's null space) when the maps' neighbour "
                  "differences follow the prior; maps smoother than tau give less, rougher ones more")

#: Fewer images per pixel leave a per-pixel albedo fit's shape poorly determined (incidental parameters).
MIN_IMAGES_PER_PIXEL = 3


def albedo_maps(layout, shape, groups, prior=False):
    """(fit.json's ``albedo`` block, maps ``k_s``, ``k_b``, ``k_s_se``, ``k_b_se``, ``identified``): ``groups``
    on the grid ``shape``, (H, W) or (C, H, W), NaN where not fitted."""
    H, W = shape
    C = 1 if layout.channel_of is None else len(layout.labels)
    ch = np.zeros(layout.n_groups, int) if layout.channel_of is None else layout.channel_of
    maps = {}
    for key, v in groups.items():
        img = np.zeros((C, H * W), bool) if key == "identified" else np.full((C, H * W), np.nan)
        img[ch, layout.pixels] = v
        maps[key] = img.reshape(C, H, W) if C > 1 else img.reshape(H, W)
    maps["channels"] = None if C == 1 else list(layout.labels)

    def stats(sel):
        g = {k: np.asarray(v)[sel] for k, v in groups.items()}
        ok = {k: U.determined(g[k], g[k + "_se"]) for k in ("k_s", "k_b")}
        ident = np.asarray(g["identified"], bool)
        return {"identified_fraction": float(ident.mean()) if ident.size else 0.0,
                "k_s_median": float(np.nanmedian(g["k_s"])), "k_b_median": float(np.nanmedian(g["k_b"])),
                **{f"{k}_determined_fraction": float(v.mean()) if v.size else 0.0 for k, v in ok.items()}}

    every = stats(slice(None))
    summary = {"layout": layout.name, "pixels": int(len(np.unique(layout.pixels))), "groups": int(layout.n_groups),
               "identified_fraction": every.pop("identified_fraction"),
               "split_rule": f"identified where the standard errors of k_s and of k_b are at most {U.SPLIT_REL:g} "
                             "of their values", **every, "channels": maps["channels"]}
    if C > 1:
        summary["per_channel"] = {c: stats(ch == j) for j, c in enumerate(layout.labels)}
    # median images (cells) per albedo pair; a colour cell holds one group per channel, each counted once
    cells = np.unique(np.stack([np.repeat(np.arange(len(layout.groups)), layout.groups.shape[1]),
                                layout.groups.ravel()]), axis=1)[1] if C > 1 else layout.groups[:, 0]
    per = summary["images_per_pixel"] = (float(np.median(np.bincount(cells, minlength=layout.n_groups)))
                                         if layout.n_groups else 0.0)
    if per < MIN_IMAGES_PER_PIXEL:
        summary["warning"] = (f"per-pixel albedos from fewer than {MIN_IMAGES_PER_PIXEL} images of each pixel: "
                              "eta, alpha, beta, kappa are poorly determined (their errors: "
                              + ("the smoothness prior's posterior ones" if prior else
                                 "the incidental-parameter sandwich")
                              + "); fit several lights of the same view (docs/howto/fit-textured.md)")
    return summary, maps
