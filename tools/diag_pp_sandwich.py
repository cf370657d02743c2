"""Issue 23/25 diagnostic: the one-image per-pixel albedo fit's spread against its Fisher errors, and
the incidental-parameter correction of the information.

    python tools/diag_pp_sandwich.py RUNS.json [--res 24] [--noise camera|gauss]
    python tools/diag_pp_sandwich.py --truth 24,48 [--lights 1|3]

RUNS.json: tools/diag_pp_bias.py's runs (same --res and --noise).  For every seed the data and the
problem are rebuilt and evaluated at that fit's estimate (weights from the model there, as at the IRLS
fixed point).  With the albedos eliminated the Gauss-Newton information is J^T J = sum_i D_i^T M_i D_i,
D_i = dA_i/dz a_i (whitened), M_i = I - P_i, evaluated at the *estimated* albedos a_i.  Their noise
(covariance G_i^-1 = (A_i^T W_i A_i)^-1, O(1) per pixel from one image) enters it quadratically:

    E[J^T J] = H + C,   C_jk = sum_i tr(A_ij^T M_i A_ik G_i^-1),   A_ij = dA_i/dz_j (whitened, n_i x 2),

while the profile score's mean derivative is H (E chi^2_p(theta) - const = sum mu0^T W (I - P_theta) mu0).
So the estimate's covariance is H^-1 (H + C) H^-1, not (H + C)^-1 (the Fisher errors): the
incidental-parameter inflation, which does not shrink with more pixels.  This prints per parameter the
spread over seeds / mean Fisher SE and / mean corrected SE (sqrt of diag H^-1 J^T J H^-1, H = J^T J - C).

Measured 2026-11-26 (tools/diag_pp_bias.py runs, one light, smooth texture, Fisher intervals):

    | data | eta | alpha | beta | kappa |   spread / Fisher SE -> spread / corrected SE; 95 % cover Fisher -> corrected
    | 24², camera, 48 seeds | 5.57 -> 1.43, 36 -> 44 | 2.52 -> 0.80, 23 -> 45 | 4.23 -> 0.99, 21 -> 43 | 2.53 -> 0.69, 27 -> 38 |
    | 24², Gaussian, 24 seeds | 4.48 -> 1.92, 17 -> 23 | 1.83 -> 0.75, 17 -> 23 | 2.88 -> 0.89, 11 -> 23 | 2.72 -> 0.40, 15 -> 19 |
    | 32², camera, 24 seeds | 3.20 -> 1.48, 11 -> 19 | 2.14 -> 1.02, 15 -> 23 | 3.73 -> 1.22, 9 -> 20 | 2.78 -> 0.76, 8 -> 20 |

(H estimated per seed is noisy: not positive definite in 3 of 24 - 6 of 48 seeds.)  At the truth
(--truth), predicted spread / Fisher SE: one light 24² 3.9-16, 48² 2.3-4.5, 64² 2.5-3.9 (it levels off:
not a small-sample effect); two lights 48² 1.5-3.1; three lights 24² 1.04-1.10, 48² 1.09-1.24.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from bench_textured import LIGHT0, SHAPE, TRUTH, texture  # noqa: E402


def corrected(problem, st, refresh=True):
    """(Fisher SE, corrected SE, H positive definite, inflation) in z per free shape parameter at ``st``.
    Samples are gathered per albedo group (several images: a pixel's cells in every image); groups with
    fewer samples than the most common count are left out of C (pixels missing from an image)."""
    parts = problem.parts(st, jac=True)
    if refresh:
        problem.set_weights(parts, st)
    obj = problem.obj
    z = problem.to_z(st)
    r, J = problem.residuals_and_jacobian(parts, st, z)
    g = obj.layout.groups.ravel()
    counts = np.bincount(g, minlength=obj.layout.n_groups)
    m = int(np.bincount(counts).argmax())
    order = np.argsort(g, kind="stable")
    keep = np.repeat(counts == m, counts)     # rows sorted by group: keep the groups with m samples
    rows = order[keep]

    def per(x):
        return x.ravel()[rows].reshape(-1, m)

    sd = np.sqrt(obj.var)
    S, B = (per(x / sd) for x in obj.unit_samples(parts))
    U = np.stack([S, B], -1)                                # (groups, m, 2)
    G = np.einsum("cma,cmb->cab", U, U)
    Gi = np.linalg.inv(G)
    M = np.eye(m)[None] - np.einsum("cma,cab,cnb->cmn", U, Gi, U)
    A = []
    for j, n in enumerate(problem.names):
        f = problem.bounds.derivative(n, z[j])
        A.append(np.stack([per(obj._mu_of(parts.d_surface[n]) / sd), per(obj._mu_of(parts.d_body[n]) / sd)], -1) * f)
    p = len(A)
    C = np.zeros((p, p))
    for j in range(p):
        for k in range(p):
            C[j, k] = np.einsum("cma,cmn,cnb,cba->", A[j], M, A[k], Gi)
    F = J.T @ J
    return F, C


def ses(F, C, at_truth=False):
    """(Fisher SE, corrected SE, H positive definite): at an estimate F = J^T J estimates H + C; at the
    truth (``at_truth``: J from the true albedos) F is H itself."""
    if at_truth:
        H, Fe = F, F + C          # what the fit would report on average: (H + C)^-1
    else:
        H, Fe = F - C, F
    Hi = np.linalg.inv(H)
    return (np.sqrt(np.diag(np.linalg.inv(Fe))), np.sqrt(np.abs(np.diag(Hi @ Fe @ Hi))),
            bool(np.linalg.eigvalsh(H).min() > 0))


def truth_table(sizes, K):
    """Per size: the predicted spread / Fisher SE at the truth, sqrt(diag H^-1 (H + C) H^-1 / diag (H + C)^-1)
    (noise-free data, the fit's model = the data's: 4 x 4 points per raw pixel)."""
    from bench_textured import lights
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, textured_sphere
    from fmbrdf_mi.fit.problem.data import prepare

    print("| size | lights | pixels | " + " | ".join(f"{n}" for n in SHAPE) + " |  (predicted spread / Fisher SE "
          "at the truth)\n|---|---|---|" + "---|" * len(SHAPE))
    for res in sizes:
        ks, kb = texture("smooth", res)
        obs = []
        for j, light in enumerate(lights(K)[0]):
            o, _ = capture_observation(textured_sphere(TRUTH, ks, kb, res=res, light=light), CameraModel(), seed=0,
                                       noiseless=True,
                                       exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
            obs.append(o)
        opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=None, area_points=4)
        data = prepare(obs, opts, "likelihood", single=(K == 1))
        problem = data.problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
        st = problem.projected(dict(TRUTH))[0]
        F, C = corrected(problem, st)
        se_f, se_c, _ = ses(F, C, at_truth=True)
        d = dict(zip(problem.names, se_c / se_f))
        print(f"| {res}² | {K} | {problem.layout.n_groups} | " + " | ".join(f"{d[n]:.2f}" for n in SHAPE) + " |",
              flush=True)


def main(argv=None):
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.camera.noise import NoiseModel
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, textured_sphere
    from fmbrdf_mi.fit.problem.data import prepare

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="?")
    p.add_argument("--truth", metavar="SIZES", help="e.g. 24,48: the prediction at the truth instead")
    p.add_argument("--lights", type=int, default=1, help="with --truth: 1 or 3 images")
    p.add_argument("--res", type=int, default=24)
    p.add_argument("--noise", default="camera", choices=("camera", "gauss"))
    a = p.parse_args(argv)
    if a.truth:
        truth_table([int(x) for x in a.truth.split(",")], a.lights)
        return 0
    runs = json.load(open(a.runs))["runs"]
    ks, kb = texture("smooth", a.res)
    ideal = textured_sphere(TRUTH, ks, kb, res=a.res, light=LIGHT0)
    ratio = {n: [] for n in SHAPE}
    posdef = 0
    for run in runs:
        seed = run["seed"]
        obs, _ = capture_observation(ideal, CameraModel(), seed=1000 * seed, noiseless=(a.noise != "camera"))
        if a.noise == "gauss":   # as tools/diag_pp_bias.py
            smp = obs.samples
            var = float(np.mean(obs.noise.variance(smp.values)[:, ideal["mask"]]))
            vals = smp.values + np.random.default_rng(7919 + seed).normal(0.0, math.sqrt(var), smp.values.shape)
            obs = dataclasses.replace(obs, samples=dataclasses.replace(smp, values=vals, step=0.0),
                                      noise=NoiseModel(1e15, math.sqrt(var) * 1e15, 0.0))
        opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=None)
        data = prepare([obs], opts, "likelihood", single=True)
        problem = data.problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
        st = problem.projected({n: run["params"][n] for n in SHAPE})[0]
        se_f, se_c, ok = ses(*corrected(problem, st))
        posdef += ok
        for j, n in enumerate(problem.names):
            ratio[n].append(se_c[j] / se_f[j])
        print(f"seed {seed}: corrected / Fisher SE " + " ".join(f"{n} {ratio[n][-1]:.2f}" for n in problem.names)
              + ("" if ok else " (H not positive definite)"), file=sys.stderr, flush=True)
    print(f"| parameter | spread / Fisher SE | mean corrected / Fisher SE | spread / corrected SE | Fisher cover "
          f"| corrected cover |  ({len(runs)} seeds, {a.res}², {a.noise}; H positive definite in {posdef})"
          "\n|---|---|---|---|---|---|")
    for n in SHAPE:
        err = np.array([(r["params"][n] - TRUTH[n]) / TRUTH[n] for r in runs])
        se = np.array([r["se"][n] / TRUTH[n] for r in runs])
        sc = se * np.array(ratio[n])
        # the estimate +- 1.96 SE (Fisher: the run's own; corrected: times the ratio), not cut at the bounds
        cf, cc = int(np.sum(np.abs(err) <= 1.96 * se)), int(np.sum(np.abs(err) <= 1.96 * sc))
        print(f"| {n} | {err.std(ddof=1) / se.mean():.2f} | {np.mean(ratio[n]):.2f} | "
              f"{err.std(ddof=1) / sc.mean():.2f} | {cf}/{len(runs)} | {cc}/{len(runs)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
