"""Normal refinement, final step (:func:`refine_joint`): one Levenberg-Marquardt on the material and every
pixel's normal together, since an alternation converges slowly where they trade off.  Energy: the samples'
likelihood plus ``lam c`` times the smoothness prior (:func:`fmbrdf_mi.fit.problem.normals.stencils`), c
converting ``lam`` (Stokes residuals over the mean intensity) to chi^2 units.  The material's covariance
(:func:`fmbrdf_mi.fit.solve.normal_system.material_covariance`) omits the prior's bias, so the material is
re-estimated at the weaker ``lam_material``, calibrated for ``lam_material <= LAM_MATERIAL``."""
from __future__ import annotations

import math
import time

import numpy as np

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.inputs.normal_maps import check_views
from fmbrdf_mi.fit.inputs.observations import check_mask, erode
from fmbrdf_mi.fit.problem.normals import NormalProblem
from fmbrdf_mi.fit.result import FitResult
from fmbrdf_mi.fit.solve import lm as LM
from fmbrdf_mi.fit.solve import normal_system as NS

#: The smoothness weight of the material's estimate and covariance, after the refinement at ``lam``.
LAM_MATERIAL = 0.03


def round_time_left(decreases, per_iter, most, tol=0.01):
    """Seconds a round of :func:`refine_joint` probably has left: the last three energy ``decreases``
    extrapolated geometrically below ``tol``; None until three decreases shrink."""
    d = decreases[-3:]
    if len(d) < 3 or min(d) <= 0 or d[2] >= d[0]:
        return None
    rho = math.sqrt(d[2] / d[0])
    n = 1 if d[2] < tol else math.ceil(math.log(tol / d[2]) / math.log(rho)) + 1
    return min(n, most) * per_iter


def refinement_time_left(left, round_times, elapsed, rounds_after):
    """Seconds the whole refinement probably has left: this round's ``left`` plus ``rounds_after`` rounds of
    the finished ones' mean duration (errs long); None when nothing is known yet."""
    if rounds_after <= 0:
        return left
    if round_times:
        per_round = sum(round_times) / len(round_times)
    elif left is not None:
        per_round = elapsed + left
    else:
        return None
    return (left or 0.0) + rounds_after * per_round


def refine_joint(observations, normals, params, *, mask=None, lam=0.3, prior="curvature", model="fmbrdf",
                 bounds=None, fixed=None, max_iter=50, refreshes=2, h=1e-3, progress=None, time_limit=None,
                 lam_material=LAM_MATERIAL):
    """Jointly refine the material ``params`` (reported) and ``normals`` (H, W, 3) from ``observations``, K >= 3
    :class:`Observation` s of one view under different lights.  ``mask``: the pixels refined (default: the
    first mask eroded by 1, less clipped super-pixels); ``refreshes``: IRLS rounds; ``lam_material``: the
    material's smoothness weight (None: ``lam``).  Returns a :class:`~fmbrdf_mi.fit.result.FitResult` with
    ``normals`` and ``mask``; ``loss_terms``: data (chi^2) and prior at ``lam``."""
    say = progress or (lambda msg: None)
    obs = list(observations)
    n_map = check_views(obs, normals)
    m = erode(obs[0].mask, 1) if mask is None else check_mask(mask, obs[0].shape).copy()
    for o in obs:
        if o.samples is not None:
            m &= o.samples.usable
    if m.sum() < 2:
        raise InputError("normal refinement: fewer than 2 usable pixels in the mask")
    mdl = get_model(model)
    jp = NormalProblem(obs, m, Parameters(mdl, bounds=bounds, fixed=fixed), lam, prior)
    st = jp.state(*jp.params.split(params))
    norm = np.linalg.norm(n_map, axis=-1, keepdims=True)
    jp.nmap = nmap = (n_map / np.where(norm > 0, norm, 1.0)).reshape(-1, 3)   # flat; the refined pixels change
    t0, history, last, kept = time.time(), [], {}, {}
    n_rounds = refreshes + 1 + int(lam_material is not None and lam_material < lam)   # IRLS, then the material's
    round_times, pattern = [], {}    # pattern: H_nn's sparsity, the same at every linearisation (NormalBlock)

    def block(Jn, t, mu=0.0):
        return NS.NormalBlock(Jn[0], Jn[1], jp.stencils, jp.coef, t[0], t[1], jp.w_prior, mu, cache=pattern)

    def before(x, rnd):     # rounds 1 .. refreshes: variances and the prior's scale from the model; the last
        st, nmap = x        # round, if staged, the material's: the prior weakened, the refinement's end kept
        if rnd > refreshes:
            kept.update(last, normals=nmap)
            jp.lam = float(lam_material)
        elif rnd:
            jp.obj.refresh(jp.parts_at(st, nmap), st)
        if rnd:
            jp.set_scale()
        ed, ep, _ = jp.energy(st, nmap)
        last.update(ed=ed, ep=ep)
        say(f"[joint-normals] material: prior weakened to lam {lam_material:g}, energy {ed + ep:.6e} "
            f"({time.time() - t0:.1f} s)" if rnd > refreshes else
            f"[joint-normals] round {rnd}: energy {ed + ep:.6e} (data {ed:.6e}, prior {ep:.6e}), {jp.n} pixels, "
            f"variances {'from the data' if rnd == 0 else 'from the model'} ({time.time() - t0:.1f} s)")

    def linearise(x):
        t_lin, n = time.time(), x[1][jp.idx]
        r, Jm, Jn, t, z = jp.linearise(x[0], x[1], h)
        if not history:     # the first step's wait: a linearisation, then solves and trial energies
            say(f"[joint-normals] linearised {jp.n} pixels x {jp.K} images in {time.time() - t_lin:.1f} s; "
                f"solving for the first step ({time.time() - t0:.1f} s)")
        Hmm, Hmn, gm, gn = NS.data_products(Jn[0], Jn[1], Jm, r, jp.n)    # the data's, then the prior's gradient
        return ((Hmm, Hmn, gm, jp.prior_gradient(gn, t, n)), Jn, t, z, n, {})

    def solve(lin, mu):
        (Hmm, Hmn, gm, gn), Jn, t, _, _, cache = lin
        if "block" not in cache:    # assembled once per linearisation; each damping adds only its ridge
            cache["block"] = block(Jn, t)
        return NS.solve_step(Hmm, Hmn, cache["block"].damped(mu), gm, gn, mu)

    def trial(x, step, lin):
        dm, dn = step
        _, _, t, z, n, _ = lin
        st_new = jp.from_z(np.clip(z + dm, -40, 40))
        n_new = n + dn[:, :1] * t[0] + dn[:, 1:] * t[1]
        n_new /= np.linalg.norm(n_new, axis=1, keepdims=True)
        away = np.sum(n_new * jp.views, 1) < 0.05
        n_new[away] = n[away]
        nmap_new = jp.full(x[1], n_new)
        ed_new, ep_new, _ = jp.energy(st_new, nmap_new)
        return (st_new, nmap_new, ed_new, ep_new), ed_new + ep_new, None

    def minimise(x, rnd):
        t_round, decreases = time.time(), []
        label = "material round" if rnd == refreshes + 1 else f"round {rnd}"

        def on_accept(it, x, f):
            st, jp.nmap = x[0], x[1]
            rep = jp.params.report(st.shape, st.a_s, st.a_b)
            decreases.append((history[-1]["energy"] if history and history[-1]["round"] == rnd
                              else last["ed"] + last["ep"]) - f)
            history.append({"round": rnd, "iter": it, "energy": f, "data": x[2], "prior": x[3],
                            "time": time.time() - t0, "params": rep})
            per_iter = (time.time() - t_round) / it
            left = round_time_left(decreases, per_iter, max_iter - it)
            # until the decreases give a rate: the bound of max_iter iterations
            about = "about" if left is not None else "at most"
            left = (max_iter - it) * per_iter if left is None else left
            total = refinement_time_left(left, round_times, time.time() - t_round, n_rounds - rnd - 1)
            say(f"[joint-normals] {label} iter {it:2d}: energy {f:.6e} (data {x[2]:.6e}, prior {x[3]:.6e})  "
                + " ".join(f"{k}={v:.4g}" for k, v in rep.items()) + f"  ({time.time() - t0:.1f} s"
                + f"; this round {about} {left:.0f} s more"
                + ("" if total is None or total == left else
                   f"; {n_rounds - rnd - 1} more round{'s' if n_rounds - rnd > 2 else ''}, {about} {total:.0f} s "
                   "in all") + ")")

        res = LM.levenberg_marquardt(
            (x[0], x[1], last["ed"], last["ep"]), last["ed"] + last["ep"], linearise, solve, trial,
            max_iter=max_iter, refresh=1,
            small=lambda f_old, f_new: f_old - f_new < 0.01 or f_old - f_new < 1e-9 * f_new,
            time_up=None if time_limit is None else (lambda: time.time() - t0 > time_limit),
            on_accept=on_accept, final_linearise=False)
        st, nmap, ed, ep = res.x
        round_times.append(time.time() - t_round)
        last.update(f=res.f, ed=ed, ep=ep, reason=res.describe("energy", "0.01", max_iter, time_limit))
        return (st, nmap), res.converged

    (st, nmap), converged, _, _ = LM.reweighted((st, nmap), minimise, rounds=n_rounds, before=before)
    end = kept or last      # the refinement's end at lam, before the material's round
    f, ed, ep, reason, n_out = end["f"], end["ed"], end["ep"], end["reason"], end.get("normals", nmap)
    stage = None if not kept else {"lam": float(lam_material), "energy": last["f"], "data_chi2": last["ed"],
                                   "prior": last["ep"], "stop_reason": last["reason"]}
    unc = {"std_errors": {}, "method": "not computed: the refinement did not converge"}
    if converged:
        say(f"[joint-normals] the material's covariance: one linearisation and two solves ({time.time() - t0:.1f} s)")
        r, Jm, Jn, t, _ = jp.linearise(st, nmap, h)
        Hmm, Hmn, _, _ = NS.data_products(Jn[0], Jn[1], Jm, r, jp.n)
        w, V = np.linalg.eigh(NS.material_covariance(Hmm, Hmn, block(Jn, t), Jm))
        # a p x p "Jacobian" L^T with (L L^T)^-1 = C, so that the fit's summary applies unchanged
        L = V / np.sqrt(np.clip(w, 1e-300, None))
        n_ind = jp.K * jp.n * jp.obj.dof - 2 * jp.n   # the normals' unknowns take their share of the dof
        unc = U.summary(jp, st, U.covariance(jp, st, L.T, np.array([math.sqrt(float(r @ r))]), n_ind))
        unc["method"] = unc.get("method", "") + ("; sandwich of the penalised likelihood with the normals free "
                                                 "(the prior not counted as information)")
        if stage is not None:
            unc["method"] += f"; material with the prior weakened to lam {stage['lam']:g} (the normals: lam {lam:g})"
        unc["calibrated"] = jp.lam <= LAM_MATERIAL
        if not unc["calibrated"]:
            unc["warning"] = (f"the smoothness prior (lam {jp.lam:g}) biases the material by more than these "
                              f"standard errors; leave lam_material at its default to estimate the material at "
                              f"lam <= {LAM_MATERIAL:g} (docs: benchmarks, normal refinement)")
    out = n_out.reshape(n_map.shape)
    params_out = jp.params.report(st.shape, st.a_s, st.a_b)
    say(f"[joint-normals] done in {time.time() - t0:.1f} s ({reason}): "
        + " ".join(f"{k}={v:.4g}" for k, v in params_out.items()))
    return FitResult(model=mdl.name, params=params_out, loss=f, loss_terms={"data_chi2": ed, "prior": ep},
                     std_errors=unc.get("std_errors", {}), history=history, stop_reason=reason, n_pixels=int(m.sum()),
                     n_outliers=0, timings={"total": time.time() - t0},
                     options={"lam": lam, "prior": prior, "model": model, "bounds": bounds, "fixed": fixed,
                              "max_iter": max_iter, "refreshes": refreshes, "h": h, "time_limit": time_limit,
                              "lam_material": lam_material, "material_stage": stage},
                     converged=bool(converged), objective="penalised likelihood", uncertainty=unc,
                     noise=jp.obj.noise.to_dict(), pixels=jp.idx, normals=out, mask=m)
