"""Normal refinement (fmbrdf_mi.fit.api.normal_joint) on a synthetic non-spherical object: angular errors before and after.

    python tools/bench_normal_refine.py [--res 40] [--lights 4] [--lam 0.3] [--prior curvature] [--starts ps,sphere]
    python tools/bench_normal_refine.py --seeds 6 [--res 40] [--lights 4] [--lam 0.3[,0.03,...]] [--json OUT.json]

The object (:mod:`fmbrdf_mi.synthetic.mesh_object`): a smooth mesh (ellipsoid
with a three-lobed bump, rotated), a pinhole camera (12 degree field of
view), RES x RES super-pixels, K lights of unequal power (the first K of
LIGHTS), the `medium` material of the noise bench, raw 16-bit mosaics with
shot and read noise (20 000 e- full well), written in the authors' layout
and read back with :func:`fmbrdf_mi.fit.inputs.authors.read_object` (gain and
read noise known).  Starting normal maps:

* ``ps``: Lambertian photometric stereo from the K images (as the authors'
  shape reconstruction starts);
* ``sphere``: the sphere whose outline best fits the mask (an orthographic
  sphere: a user's crude prior).

From each start, what ``fmbrdf-mi fit --refine-normals`` does: one joint fit
of the material on the start normals, then the joint Levenberg-Marquardt on
material and normals (:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint`,
prior PRIOR with weight LAM).  Reported: mean and median angle to the ray-cast normals over the refined
pixels (the mask eroded by one super-pixel), before and after, the final
material and the wall time.

``--seeds N``: the material estimates over N camera-noise seeds (seeds 100 to 100 + N - 1).  Each seed:
photometric stereo, a joint fit of the material on it, then
:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint` (what ``fmbrdf-mi fit
--refine-normals`` does).  Reported per parameter (k_s relative to the
truth's scale): the mean error over seeds with its standard error, the
standard deviation of the estimates, the mean reported standard error (their
ratio should be ~1), and how many 95 % intervals cover the truth (with the
95 % Wilson binomial interval, per parameter and pooled); and the
normals' mean and median angle to the ray-cast ones.  Several ``--lam`` values
refine from the same start (one table each).  ``--json`` is rewritten after every seed.
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

TRUTH = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8), (0.0, 0.1, 1.0), (-0.6, -0.3, 1.0), (0.4, 0.6, 1.0)]
POWERS = [1.0, 0.7, 1.2, 0.9, 1.1, 0.8]


def normal_fits(seed, res=40, lights=4, lams=(0.3,), threads=0):
    """One noise seed: the object written and read back, photometric stereo, a joint fit, then
    :func:`refine_joint` at each smoothness weight in ``lams`` from the same start; returns one record per
    weight (k_s and its SE relative to the truth's scale)."""
    from fmbrdf_mi.fit.inputs.authors import read_object
    from fmbrdf_mi.fit.api.fitting import fit_joint
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object
    from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg, photometric_stereo

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
    p.add_argument("--res", type=int, default=40)
    p.add_argument("--lights", type=int, default=4, help="K, 3 to 6 (default %(default)s)")
    p.add_argument("--lam", default="0.3", help="smoothness weight; with --seeds, comma-separated (default %(default)s)")
    p.add_argument("--prior", default="curvature", choices=("curvature", "membrane"))
    p.add_argument("--starts", default="ps,sphere")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--seeds", type=int, default=0, help="material estimates over this many noise seeds (see above)")
    p.add_argument("--threads", type=int, default=0, help="Dr.Jit threads with --seeds (default: all)")
    args = p.parse_args(argv)
    if args.seeds:
        return seeds_main(args)
    args.lam = float(args.lam.split(",")[0])
    from fmbrdf_mi.fit.inputs.authors import read_object
    from fmbrdf_mi.fit.api.fitting import fit_joint
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg, photometric_stereo
    from fmbrdf_mi.fit.solve.optimise import default_progress
    from fmbrdf_mi.fit.inputs.observations import find_sphere
    from fmbrdf_mi.geometry import sphere_normals
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object

    K = args.lights
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        root = os.path.join(tmp, "blob")
        truth = write_authors_object(root, TRUTH, LIGHTS[:K], res=args.res, fov=12.0, powers=POWERS[:K],
                                     seed=args.seed)
        ks_scale = truth["irradiance_dn"] * max(POWERS[:K])
        for start in args.starts.split(","):
            specs, _ = read_object(root, conversion_gain=truth["camera"]["conversion_gain"], read_noise=2.5)
            obs = [s.input for s in specs]
            gt = obs[0].normals.copy()
            if start == "ps":
                n0 = photometric_stereo(obs)
            elif start == "sphere":
                (cx, cy), r = find_sphere(obs[0].mask)
                ns, ms, _ = sphere_normals(obs[0].shape, (cx, cy), r)
                m = obs[0].mask & ms
                for o in obs:
                    o.mask = m
                n0 = np.where(m[..., None], ns, gt)
            else:
                p.error(f"--starts: unknown {start!r} (ps, sphere)")
            t = time.time()
            for o in obs:
                o.normals, o.geometry = n0, None
            p_start = fit_joint(obs, progress=False).params
            j = refine_joint(obs, n0, p_start, lam=args.lam, prior=args.prior, progress=default_progress)
            n1, params, mask, hist = j.normals, j.params, j.mask, j.history
            se = {k: v / (ks_scale if k == "k_s" else 1.0) for k, v in j.std_errors.items()}
            stop = {"converged": j.converged, "reason": j.stop_reason, "iterations": len(hist),
                    "chi2_per_dof": j.uncertainty.get("chi2_per_dof")}
            e0 = angular_error_deg(n0, gt, mask)
            e1 = angular_error_deg(n1, gt, mask)
            params = dict(params)
            params["k_s"] /= ks_scale
            rec = {"start": start, "pixels": int(mask.sum()), "std_errors": se, "stop": stop,
                   "before_mean": float(e0.mean()),
                   "before_median": float(np.median(e0)), "after_mean": float(e1.mean()),
                   "after_median": float(np.median(e1)), "params": params, "time": time.time() - t,
                   "history": [{k: v for k, v in h.items() if k != "params"} for h in hist]}
            out.append(rec)
            print(f"# {start}: {rec['before_mean']:.2f} / {rec['before_median']:.2f} deg -> {rec['after_mean']:.2f} / "
                  f"{rec['after_median']:.2f} deg (mean / median), {rec['time']:.0f} s", file=sys.stderr, flush=True)
    method = f"joint LM ({args.prior})"
    print(f"| start | K | method | pixels | before: mean / median | after: mean / median | "
          "material after (k_s relative to the truth's scale; ± SE) | joint LM: iterations, χ²/dof | time (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    def conv(r):
        st = r["stop"]
        c = f"{st['iterations']}" + ("" if st["converged"] else " (not converged)")
        return c + (f", {st['chi2_per_dof']:.2f}" if st.get("chi2_per_dof") else "")

    for r in out:
        se = r["std_errors"]
        mat = ", ".join(f"{k} {v:.3g}" + (f" ± {se[k]:.2g}" if k in se else "") for k, v in r["params"].items())
        print(f"| {r['start']} | {K} | {method}, λ {args.lam:g} | {r['pixels']} | {r['before_mean']:.2f}° / "
              f"{r['before_median']:.2f}° | {r['after_mean']:.2f}° / {r['after_median']:.2f}° | {mat} | {conv(r)} | "
              f"{r['time']:.0f} |")
    print(f"truth: " + ", ".join(f"{k} {v:.3g}" for k, v in TRUTH.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"config": vars(args), "runs": out}, f, indent=1)
    return 0


def seeds_main(args):
    """``--seeds``: the refinement over noise seeds, one table per smoothness weight."""
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
