"""The joint normal refinement's material estimates over noise seeds: bias, spread, reported standard errors, coverage.

    python tools/bench_normal_refine_seeds.py [--seeds 6] [--res 40] [--lights 4] [--lam 0.3[,0.03,...]] [--json OUT.json]

The object and camera of tools/bench_normal_refine.py (the same mesh, lights
and `medium` material); each seed draws new shot and read noise.  Each seed:
photometric stereo, a joint fit of the material on it, then
:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint` (what ``fmbrdf-mi fit
--refine-normals`` does).  Reported per parameter (k_s relative to the
truth's scale): the mean error over seeds with its standard error, the
standard deviation of the estimates, the mean reported standard error (their
ratio should be ~1), and how many 95 % intervals cover the truth; and the
normals' mean and median angle to the ray-cast ones.  Several ``--lam`` values
refine from the same start (one table each); coverage is given with its
95 % Wilson binomial interval, per parameter and pooled.  ``--json`` is
rewritten after every seed.
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


def normal_fits(seed, res=40, lights=4, lams=(0.3,), threads=0):
    """One noise seed: the object written and read back, photometric stereo, a joint fit, then
    :func:`refine_joint` at each smoothness weight in ``lams`` from the same start; returns one record per
    weight (k_s and its SE relative to the truth's scale)."""
    from fmbrdf_mi.fit.inputs.authors import read_object
    from fmbrdf_mi.fit.api.joint import fit_joint
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.fit.api.normal_refine import angular_error_deg, photometric_stereo
    from fmbrdf_mi.fit.evaluate.synthetic_object import write_authors_object

    if threads:
        import drjit as dr
        dr.set_thread_count(threads)
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
    # the start's estimate; its intervals are not used (Fisher ones: no profile-likelihood refits)
    params = fit_joint(obs, progress=False, intervals="fisher").params
    t_start = time.time() - t
    out = []
    for lam in lams:
        t = time.time()
        j = refine_joint(obs, n0, params, lam=lam)
        e = angular_error_deg(j.normals, gt, j.mask)
        u = j.uncertainty or {}
        rel = lambda k: scale if k == "k_s" else 1.0  # noqa: E731
        out.append({"seed": seed, "lam": lam, "params": {k: v / rel(k) for k, v in j.params.items()},
                    "std_errors": {k: v / rel(k) for k, v in j.std_errors.items()},
                    "ci95": {k: [x / rel(k) for x in v] for k, v in u.get("ci95", {}).items()},
                    "converged": j.converged, "chi2_per_dof": u.get("chi2_per_dof"), "misfit": u.get("misfit"),
                    "calibrated": u.get("calibrated"), "normal_mean": float(e.mean()),
                    "normal_median": float(np.median(e)), "time": time.time() - t + t_start})
    return out


def normal_fit(seed, res=40, lights=4, lam=0.3):
    """:func:`normal_fits` at one smoothness weight (the bench over modes, tools/bench_modes.py)."""
    return normal_fits(seed, res=res, lights=lights, lams=(lam,))[0]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--res", type=int, default=40)
    p.add_argument("--lights", type=int, default=4)
    p.add_argument("--lam", default="0.3", help="smoothness weight(s), comma-separated (default %(default)s)")
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--threads", type=int, default=0, help="Dr.Jit threads (default: all)")
    args = p.parse_args(argv)
    lams = [float(v) for v in str(args.lam).split(",")]
    runs = {lam: [] for lam in lams}
    t_all = time.time()
    for seed in range(args.seeds):
        for rec in normal_fits(100 + seed, res=args.res, lights=args.lights, lams=lams, threads=args.threads):
            runs[rec["lam"]].append(rec)
            print(f"# seed {100 + seed}, lam {rec['lam']:g}: normals {rec['normal_mean']:.2f} / "
                  f"{rec['normal_median']:.2f} deg, " + ", ".join(f"{k} {v:.4g}" for k, v in rec["params"].items())
                  + f", chi2/dof {rec['chi2_per_dof'] or math.nan:.3f} ({rec['time']:.0f} s)", file=sys.stderr,
                  flush=True)
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"config": vars(args), "runs": {str(k): v for k, v in runs.items()}}, f, indent=1)
    for lam in lams:
        table(runs[lam], lam)
    print(f"{time.time() - t_all:.0f} s in all")
    return 0


def wilson(k, n, z=1.959964):
    """The 95 % Wilson score interval of a binomial proportion k / n."""
    if n == 0:
        return math.nan, math.nan
    p, d = k / n, 1 + z * z / n
    c, h = (p + z * z / (2 * n)) / d, z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return c - h, c + h


def table(runs, lam):
    ok = [r for r in runs if r["converged"] and r["std_errors"]]
    n = len(ok)
    print(f"\nλ = {lam:g}:\n")
    print(f"| parameter | truth | mean error ± its SE | spread (SD) | mean reported SE | SD / SE | 95 % intervals "
          f"covering ({n} seeds) | Wilson 95 % |")
    print("|---|---|---|---|---|---|---|---|")
    total = 0
    for k, v in TRUTH.items():
        x = np.array([r["params"][k] for r in ok])
        s = np.array([r["std_errors"][k] for r in ok])
        sd = float(x.std(ddof=1)) if n > 1 else math.nan
        cover = int(np.sum(np.abs(x - v) <= 1.959964 * s))
        total += cover
        lo, hi = wilson(cover, n)
        print(f"| {k} | {v:g} | {x.mean() - v:+.3g} ± {sd / math.sqrt(n):.2g} | {sd:.2g} | {s.mean():.2g} | "
              f"{sd / s.mean():.2f} | {cover}/{n} | {lo:.2f}–{hi:.2f} |")
    lo, hi = wilson(total, len(TRUTH) * n)
    nm = np.array([r["normal_mean"] for r in runs])
    nd = np.array([r["normal_median"] for r in runs])
    chi = [r["chi2_per_dof"] for r in ok if r["chi2_per_dof"]]
    print(f"\nall parameters: {total}/{len(TRUTH) * n} intervals cover ({total / max(len(TRUTH) * n, 1):.3f}, "
          f"Wilson {lo:.3f}–{hi:.3f}); normals: mean angle {nm.mean():.2f}° (seeds {nm.min():.2f}–{nm.max():.2f}), "
          f"median {nd.mean():.2f}°; χ²/dof {np.mean(chi):.2f} (misfit flagged in "
          f"{sum(bool(r.get('misfit')) for r in ok)}); {len(runs) - n} of {len(runs)} runs not converged")


if __name__ == "__main__":
    sys.exit(main())
