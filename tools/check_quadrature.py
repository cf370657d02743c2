"""The likelihood's pixel-area quadrature: how far its 2 x 2 points per raw pixel move the estimate.

    python tools/check_quadrature.py --materials glossy,medium,render --sizes 40,100,256
    python tools/check_quadrature.py --materials medium,glossy --sizes 40,100 --fits 2   # and the fits' times

For each material of ``tools/bench_fit_noise.py`` (``MATERIALS``, plus ``sharp``: glossy with alpha 0.03)
and object size (the orthographic sphere of that bench, light (-0.5, 0.5, 1), the camera's noise model),
the first-order bias of the shape parameters that the fit's 2 x 2 points per raw pixel cause against 4 x 4,
in units of one fit's standard error, at the truth:

    b = -(J^T J)^-1 J^T d,   d = (mu_4x4 - mu_2x2) / sd  (whitened, every raw sample of the fit)

(:func:`fmbrdf_mi.fit.uncertainty.quadrature_bias`, the check the fit itself makes at its estimate: where
|b| > 0.2 SE for a shape parameter the fit goes on with 4 x 4, then 8 x 8).  The midpoint rule's error falls
4x per halving, so the 2 x 2 quadrature's own bias is about b / 0.75.  No noise is drawn: the number is
the estimator's systematic error, which a bench over seeds sees as a mean z-score (tools/bench_modes.py).
"""
import argparse
import math
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)


def bias(truth, size, light):
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit import uncertainty as U
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, ideal_sphere
    from fmbrdf_mi.fit.problem.data import prepare

    obs, _ = capture_observation(ideal_sphere(truth, res=size, light=light, area=4), CameraModel(), seed=0,
                                 noiseless=True)
    model = get_model("fmbrdf")
    probs = []
    for m in (2, 4):
        opts = FitOptions(loss="likelihood", area_points=m)
        pb = prepare([obs], opts, "likelihood", single=True).problem(model, opts.bounds, lambda s: None,
                                                                      opts.fixed, None)
        probs.append(pb)
    coarse, fine = probs
    shape, a_s, a_b = model.split(truth)
    st = coarse.state(shape, a_s, a_b)
    parts = coarse.parts(st, jac=True)
    coarse.set_weights(parts, st)
    r, J = coarse.residuals_and_jacobian(parts, st, coarse.to_z(st))
    return U.quadrature_bias(coarse, fine, st, J, r)


def fit_times(truth, size, light, rounds):
    """Best-of-``rounds`` wall times of the default fit (the check, and the refinement where it triggers) and
    of the fit held at 2 x 2 (``area_points=2``), interleaved, on one camera-noise seed; and the check's own
    time and the points it ended with."""
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, ideal_sphere

    obs, _ = capture_observation(ideal_sphere(truth, res=size, light=light, area=4), CameraModel(), seed=1)
    best, q = {}, None
    for _ in range(rounds):
        for ap in (None, 2):
            t = time.time()
            r = fit(obs, progress=False, area_points=ap, intervals="fisher")
            best[ap] = min(best.get(ap, math.inf), time.time() - t)
            q = r.uncertainty.get("quadrature", q)
    return best[None], best[2], q


def main():
    from bench_fit_noise import LIGHT, MATERIALS
    from bench_rebuild import cpu_name

    mats = dict(MATERIALS, sharp=dict(MATERIALS["glossy"], alpha=0.03))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--materials", default="glossy,medium,rough,dense", help=f"of {', '.join(mats)}")
    ap.add_argument("--sizes", default="40,100")
    ap.add_argument("--fits", type=int, default=0, metavar="ROUNDS",
                    help="also time the default fit against the fit held at 2 x 2 (best of ROUNDS interleaved)")
    a = ap.parse_args()
    print(f"# check_quadrature: {time.strftime('%Y-%m-%d')}, {cpu_name()}; first-order bias of the 2 x 2 "
          "quadrature against 4 x 4, in standard errors (the fit refines where |b| > 0.2)")
    for name in a.materials.split(","):
        if name not in mats:
            ap.error(f"--materials: unknown {name!r} (have {', '.join(mats)})")
        for size in (int(s) for s in a.sizes.split(",")):
            t = time.time()
            b = bias(mats[name], size, LIGHT)
            print(f"{name:7s} {size:4d}²: " + " ".join(f"{k}={v:+.2f}" for k, v in b.items())
                  + f"  ({time.time() - t:.0f} s)", flush=True)
            if a.fits:
                t_auto, t_two, q = fit_times(mats[name], size, LIGHT, a.fits)
                print(f"          fit: default {t_auto:.1f} s ({q['area_points']} x {q['area_points']} points, the "
                      f"check and refinement {q['seconds']:.1f} s), held at 2 x 2 {t_two:.1f} s: ratio "
                      f"{t_auto / t_two:.2f}", flush=True)


if __name__ == "__main__":
    main()
