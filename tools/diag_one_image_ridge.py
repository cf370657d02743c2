"""Issue 25 diagnostic: where the one-image per-pixel fit's second optimum comes from, and why it goes with size.

    python tools/diag_one_image_ridge.py [--objects sphere,mesh] [--sizes 100,200] [--other 1.42,0.37,1.47,13.8]
                                         [--noisy-seed 0] [--from-truth 3,5,6] [--json OUT.json]

Data as tools/bench_textured.py makes them (smooth texture, one light, the ``medium`` material, per-pixel
albedos fitted with ``albedo="per-pixel"``).  ``--other`` is the second optimum (eta, alpha, beta, kappa)
that noisy fits of the 100^2 sphere end at (seed 0 of ``bench_textured --res 100 --lights 1``).

1. *Noise-free* (the capture without shot or read noise; quantisation stays): one fit started at the other
   optimum, one at the truth.  Both end at the truth when the noise-free likelihood has one optimum only:
   the second optimum is then made by the noise.
2. *The ridge*: along the straight line from the truth to the other optimum in (alpha, beta), the noise-free
   chi^2 with eta and kappa profiled (fitted; the albedos always are), minus the truth's: how much worse the
   noise-free data say the other optimum is.  The per-pixel likelihood's 95 % region is this many chi^2
   units against a threshold of chi^2_4(0.95) x the sandwich's variance inflation (about 42 on the 100^2
   sphere): below it noise can make the other point an optimum that wins; it grows with the pixel count.
3. *Seeds without an optimum near the truth* (``--from-truth 3,5,6``: seeds of ``bench_textured --res 100
   --lights 1`` whose intervals missed): each noisy capture fitted once from the truth and once with 4 starts
   of the coarse search; where the fit from the truth slides to the high-alpha point there is no optimum near
   the truth to find, and no start, interval stretching or profile check built on this likelihood covers it.
4. *Non-negative albedos would not tell them apart* (``--noisy-seed``): the noisy capture of that seed fitted
   from the other optimum and from the truth (one start each); how many k_s, k_b come out below 0, and below
   -2 and -3 of their standard errors, at each.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from bench_textured import SHAPE, TRUTH, ideal_of, lights, texture  # noqa: E402


def capture(obj, res, seed, noiseless):
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, textured

    ks, kb = texture("smooth", res)
    fitted, _ = lights(1)
    return capture_observation(textured(ideal_of(obj, res, fitted[0]), TRUTH, ks, kb, res), CameraModel(),
                               seed=seed, noiseless=noiseless)[0]


def fit_from(o, start, **kw):
    from fmbrdf_mi.fit import fit

    return fit(o, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False, starts=1,
               init=dict(start, k_s=0.6, r_k=0.6), area_points=2, **kw)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--objects", default="sphere")
    p.add_argument("--sizes", default="100,200")
    p.add_argument("--other", default="1.42,0.37,1.47,13.8")
    p.add_argument("--steps", type=int, default=4, help="points along the line (besides the truth)")
    p.add_argument("--noisy-seed", type=int, default=0, help="-1: skip part 3")
    p.add_argument("--from-truth", default="", help="seeds (comma-separated) to fit from the truth and with 4 starts")
    p.add_argument("--json")
    a = p.parse_args()
    other = dict(zip(SHAPE, (float(x) for x in a.other.split(","))))
    out = {"other": other, "truth": {n: TRUTH[n] for n in SHAPE}, "runs": []}
    for obj in a.objects.split(","):
        for res in (int(s) for s in a.sizes.split(",")):
            t0 = time.time()
            o = capture(obj, res, 0, noiseless=True)
            run = {"object": obj, "res": res, "noise_free": {}, "ridge": []}
            for name, start in (("from_other", other), ("from_truth", {n: TRUTH[n] for n in SHAPE})):
                r = fit_from(o, start)
                run["noise_free"][name] = {"params": {n: float(r.params[n]) for n in SHAPE},
                                           "chi2": float(2 * r.loss)}
            base = run["noise_free"]["from_truth"]["chi2"]
            for i in range(1, a.steps + 1):
                t = i / a.steps
                pt = {n: TRUTH[n] + t * (other[n] - TRUTH[n]) for n in SHAPE}
                r = fit_from(o, pt, fixed={"alpha": pt["alpha"], "beta": pt["beta"]})
                run["ridge"].append({"t": t, "alpha": pt["alpha"], "beta": pt["beta"],
                                     "eta": float(r.params["eta"]), "kappa": float(r.params["kappa"]),
                                     "delta_chi2": float(2 * r.loss - base)})
            nf = run["noise_free"]
            print(f"{obj} {res}^2 noise-free: from the other optimum -> "
                  + ", ".join(f"{n} {nf['from_other']['params'][n]:.4g}" for n in SHAPE)
                  + f" (chi2 {nf['from_other']['chi2']:.2f}; from the truth {nf['from_truth']['chi2']:.2f})", flush=True)
            for q in run["ridge"]:
                print(f"  ridge t {q['t']:.2f}: alpha {q['alpha']:.4f} beta {q['beta']:.4f} -> eta {q['eta']:.4f} "
                      f"kappa {q['kappa']:.3f}, delta chi2 {q['delta_chi2']:.1f}", flush=True)
            if a.noisy_seed >= 0:
                o = capture(obj, res, 1000 * a.noisy_seed, noiseless=False)
                run["noisy"] = {}
                for name, start in (("from_other", other), ("from_truth", {n: TRUTH[n] for n in SHAPE})):
                    r = fit_from(o, start)
                    m = r.maps
                    ok = np.isfinite(m["k_s"]) & np.isfinite(m["k_s_se"])
                    zs, zb = m["k_s"][ok] / m["k_s_se"][ok], m["k_b"][ok] / m["k_b_se"][ok]
                    q = {"params": {n: float(r.params[n]) for n in SHAPE}, "chi2": float(2 * r.loss),
                         "pixels": int(ok.sum()), "k_s_below_0": int((zs < 0).sum()), "k_b_below_0": int((zb < 0).sum()),
                         "k_s_below_-2se": int((zs < -2).sum()), "k_s_below_-3se": int((zs < -3).sum()),
                         "k_b_below_-2se": int((zb < -2).sum()), "k_b_below_-3se": int((zb < -3).sum())}
                    run["noisy"][name] = q
                    print(f"  noisy seed {a.noisy_seed} {name}: " + ", ".join(f"{n} {q['params'][n]:.4g}" for n in SHAPE)
                          + f", chi2 {q['chi2']:.1f}; of {q['pixels']} pixels k_s < 0: {q['k_s_below_0']}, "
                          f"< -2 SE: {q['k_s_below_-2se']}, < -3 SE: {q['k_s_below_-3se']}; k_b < 0: {q['k_b_below_0']}, "
                          f"< -3 SE: {q['k_b_below_-3se']}", flush=True)
            run["from_truth"] = []
            for seed in (int(x) for x in a.from_truth.split(",") if x):
                from fmbrdf_mi.fit import fit

                o = capture(obj, res, 1000 * seed, noiseless=False)
                r = fit_from(o, {n: TRUTH[n] for n in SHAPE})
                r4 = fit(o, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False, starts=4)
                q = {"seed": seed, "from_truth": {n: float(r.params[n]) for n in SHAPE},
                     "starts4": {n: float(r4.params[n]) for n in SHAPE},
                     "starts4_ends_alpha": [float(st["end"]["alpha"]) for st in r4.starts]}
                run["from_truth"].append(q)
                print(f"  noisy seed {seed}: from the truth -> " + ", ".join(f"{n} {q['from_truth'][n]:.4g}" for n in SHAPE)
                      + "; 4 starts end at alpha " + ", ".join(f"{x:.3f}" for x in q["starts4_ends_alpha"]), flush=True)
            run["seconds"] = time.time() - t0
            out["runs"].append(run)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
