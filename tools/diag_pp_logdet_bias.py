"""Issue 23/25 diagnostic: the bias the integrated-likelihood (log det) adjustment would add, at the truth.

    python tools/diag_pp_logdet_bias.py [--res 24,48] [--lights 1]

With the variances known and independent of the shape (Gaussian, or frozen IRLS weights), the expected
profile chi^2 of the per-pixel albedo fit is E chi^2_p(theta) = sum_i (n_i - 2) + mu0^T W (I - P_theta) mu0,
minimal at the truth: its estimating equation has zero mean, whatever the number of pixels.  Adding
L(theta) = sum_i log det(A_i^T W_i A_i) moves the stationary point by about
delta = -(2 J^T J)^-1 dL/dz (J: Kaufman's projected Jacobian, J^T J the Fisher information), i.e. by
a fixed amount while the standard error shrinks as 1/sqrt(pixels): an inconsistent estimator.  This
prints delta / SE per shape parameter at the truth of tools/bench_textured.py's object (noise-free data,
the fit's model = the data's: --area-points 4).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from bench_textured import SHAPE, TRUTH, lights, texture  # noqa: E402
from pp_logdet import logdet  # noqa: E402


def at_truth(res, K, area_points=4, tex="smooth"):
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, textured_sphere
    from fmbrdf_mi.fit.problem.data import prepare

    ks, kb = texture(tex, res)
    cam = CameraModel()
    obs = []
    for j, light in enumerate(lights(K)[0]):
        o, _ = capture_observation(textured_sphere(TRUTH, ks, kb, res=res, light=light), cam, seed=0,
                                   noiseless=True, exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
    opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=None, area_points=area_points)
    data = prepare(obs, opts, "likelihood", single=(K == 1))
    problem = data.problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
    st, parts = problem.projected(dict(TRUTH))
    problem.set_weights(parts, st)
    parts = problem.parts(st, jac=True)
    z = problem.to_z(st)
    r, J = problem.residuals_and_jacobian(parts, st, z)
    _, g = logdet(problem.obj, parts, problem.names, problem.bounds, z)
    F = J.T @ J
    cov = np.linalg.inv(F)
    delta = -cov @ g / 2
    se = np.sqrt(np.diag(cov))
    return problem.names, delta / se, len(data.pixels), float(r @ r)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", default="24,48")
    p.add_argument("--lights", type=int, default=1)
    a = p.parse_args(argv)
    print("| size | lights | pixels | " + " | ".join(f"{n}: shift / SE" for n in SHAPE) + " |")
    print("|---|---|---|" + "---|" * len(SHAPE))
    for res in (int(x) for x in a.res.split(",")):
        names, ratio, n, chi2 = at_truth(res, a.lights)
        d = dict(zip(names, ratio))
        print(f"| {res}² | {a.lights} | {n} | " + " | ".join(f"{d[n]:+.2f}" for n in SHAPE) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
