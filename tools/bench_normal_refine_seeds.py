"""The joint normal refinement's material estimates over noise seeds: bias, spread, reported standard errors, coverage.

    python tools/bench_normal_refine_seeds.py [--seeds 6] [--res 40] [--lights 4] [--lam 0.3] [--json OUT.json]

The object and camera of tools/bench_normal_refine.py (the same mesh, lights
and `medium` material); each seed draws new shot and read noise.  Each seed:
photometric stereo, a joint fit of the material on it, then
:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint` (what ``fmbrdf-mi fit
--refine-normals`` does).  Reported per parameter (k_s relative to the
truth's scale): the mean error over seeds with its standard error, the
standard deviation of the estimates, the mean reported standard error (their
ratio should be ~1), and how many 95 % intervals cover the truth; and the
normals' mean and median angle to the ray-cast ones.
"""
import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

from bench_normal_refine import LIGHTS, POWERS, TRUTH  # noqa: E402


def normal_fit(seed, res=40, lights=4, lam=0.3):
    """One noise seed: the object written and read back, photometric stereo, a joint fit, then
    :func:`refine_joint`; returns its record (k_s and its SE relative to the truth's scale)."""
    from fmbrdf_mi.fit.inputs.authors import read_object
    from fmbrdf_mi.fit.api.joint import fit_joint
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.fit.api.normal_refine import angular_error_deg, photometric_stereo
    from fmbrdf_mi.fit.evaluate.synthetic_object import write_authors_object

    K = lights
    t = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        root = os.path.join(tmp, "blob")
        truth = write_authors_object(root, TRUTH, LIGHTS[:K], res=res, fov=12.0, powers=POWERS[:K], seed=seed)
        specs, _ = read_object(root, conversion_gain=truth["camera"]["conversion_gain"], read_noise=2.5)
    scale = truth["irradiance_dn"] * max(POWERS[:K])
    obs = [s.input for s in specs]
    gt = obs[0].normals.copy()
    n0 = photometric_stereo(obs)
    for o in obs:
        o.normals, o.geometry = n0, None
    params = fit_joint(obs, progress=False).params
    j = refine_joint(obs, n0, params, lam=lam)
    e = angular_error_deg(j.normals, gt, j.mask)
    est = {k: v / (scale if k == "k_s" else 1.0) for k, v in j.params.items()}
    se = {k: v / (scale if k == "k_s" else 1.0) for k, v in j.std_errors.items()}
    ci = {k: [x / (scale if k == "k_s" else 1.0) for x in v] for k, v in j.uncertainty.get("ci95", {}).items()}
    return {"seed": seed, "params": est, "std_errors": se, "ci95": ci, "converged": j.converged,
            "chi2_per_dof": j.uncertainty.get("chi2_per_dof"), "calibrated": j.uncertainty.get("calibrated"),
            "normal_mean": float(e.mean()), "normal_median": float(np.median(e)), "time": time.time() - t}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--res", type=int, default=40)
    p.add_argument("--lights", type=int, default=4)
    p.add_argument("--lam", type=float, default=0.3)
    p.add_argument("--json", metavar="OUT.json")
    args = p.parse_args(argv)
    runs = []
    t_all = time.time()
    for seed in range(args.seeds):
        rec = normal_fit(100 + seed, res=args.res, lights=args.lights, lam=args.lam)
        runs.append(rec)
        print(f"# seed {100 + seed}: normals {rec['normal_mean']:.2f} / {rec['normal_median']:.2f} deg, "
              + ", ".join(f"{k} {v:.4g}" for k, v in rec["params"].items()) + f" ({rec['time']:.0f} s)",
              file=sys.stderr, flush=True)
    ok = [r for r in runs if r["converged"] and r["std_errors"]]
    n = len(ok)
    print(f"| parameter | truth | mean error ± its SE | spread (SD) | mean reported SE | SD / SE | 95 % intervals "
          f"covering ({n} seeds) |")
    print("|---|---|---|---|---|---|---|")
    for k, v in TRUTH.items():
        x = np.array([r["params"][k] for r in ok])
        s = np.array([r["std_errors"][k] for r in ok])
        sd = float(x.std(ddof=1)) if n > 1 else math.nan
        cover = int(np.sum(np.abs(x - v) <= 1.96 * s))
        print(f"| {k} | {v:g} | {x.mean() - v:+.3g} ± {sd / math.sqrt(n):.2g} | {sd:.2g} | {s.mean():.2g} | "
              f"{sd / s.mean():.2f} | {cover}/{n} |")
    nm = np.array([r["normal_mean"] for r in runs])
    nd = np.array([r["normal_median"] for r in runs])
    chi = [r["chi2_per_dof"] for r in ok if r["chi2_per_dof"]]
    print(f"normals: mean angle {nm.mean():.2f}° (seeds {nm.min():.2f}–{nm.max():.2f}), median {nd.mean():.2f}°; "
          f"χ²/dof {np.mean(chi):.2f}; {len(runs) - n} of {len(runs)} runs not converged; "
          f"{time.time() - t_all:.0f} s in all")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"config": vars(args), "runs": runs}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
