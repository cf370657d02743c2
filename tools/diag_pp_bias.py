"""Issue 23/25 diagnostic: which mechanism biases the one-image per-pixel albedo fit's shared parameters.

    python tools/diag_pp_bias.py --noise none|gauss|camera [--res 24] [--seeds 8] [--area-points 4]
                                 [--adjust logdet] [--json OUT.json]

Data as tools/bench_textured.py makes them (smooth texture, one light, `medium` material), then:

* ``none``: the capture without shot or read noise (quantisation stays);
* ``gauss``: the noiseless capture plus Gaussian noise of one constant variance (the camera's mean
  variance over the object), fitted with that constant variance known (weights independent of the model);
* ``camera``: the camera's Poisson-Gaussian capture (the bench's data), weights from the model (IRLS).

Reports per parameter the mean relative error +- SE over seeds, spread / mean SE, and coverage of
the Fisher intervals; and the fraction of pixels whose closed-form albedos are negative.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from bench_textured import LIGHT0, SHAPE, TRUTH, texture  # noqa: E402


def one(seed, res, noise, area_points, adjust, tex="smooth"):
    from fmbrdf_mi.camera import CameraModel
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.camera.noise import NoiseModel
    from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, textured_sphere

    ks, kb = texture(tex, res)
    cam = CameraModel()
    ideal = textured_sphere(TRUTH, ks, kb, res=res, light=LIGHT0)
    obs, cap = capture_observation(ideal, cam, seed=1000 * seed, noiseless=(noise != "camera"))
    if noise == "gauss":
        smp = obs.samples
        v = obs.noise.variance(smp.values)
        var = float(np.mean(v[:, ideal["mask"]]))
        rng = np.random.default_rng(7919 + seed)
        vals = smp.values + rng.normal(0.0, math.sqrt(var), smp.values.shape)
        obs = dataclasses.replace(obs, samples=dataclasses.replace(smp, values=vals, step=0.0),
                                  noise=NoiseModel(1e15, math.sqrt(var) * 1e15, 0.0))
    kw = {}
    t = time.time()
    r = fit(obs, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False,
            area_points=area_points, **kw)
    out = {"seed": seed, "params": r.params, "se": r.std_errors, "converged": r.converged,
           "ci95": (r.uncertainty or {}).get("ci95", {}), "time": time.time() - t}
    m = r.maps
    if m is not None:
        f = np.isfinite(m["k_s"])
        out["neg_k_s"] = float(np.mean(m["k_s"][f] < 0))
        out["neg_k_b"] = float(np.mean(m["k_b"][f] < 0))
    return out


def summary(runs):
    lines = ["| parameter | bias ± SE | spread / SE | Fisher coverage |", "|---|---|---|---|"]
    for n in SHAPE:
        err = np.array([(r["params"][n] - TRUTH[n]) / TRUTH[n] for r in runs])
        se = np.array([r["se"][n] / TRUTH[n] for r in runs])
        cov = sum(r["ci95"][n][0] <= TRUTH[n] <= r["ci95"][n][1] for r in runs if n in r["ci95"])
        sd = err.std(ddof=1) if len(err) > 1 else math.nan
        lines.append(f"| {n} | {100 * err.mean():+.2f} ± {100 * sd / math.sqrt(len(err)):.2f} % | "
                     f"{sd / se.mean():.2f} | {cov}/{len(runs)} |")
    neg = [(r.get("neg_k_s", math.nan), r.get("neg_k_b", math.nan)) for r in runs]
    lines.append(f"\nnegative k_s / k_b pixels: {100 * np.nanmean([a for a, _ in neg]):.1f} % / "
                 f"{100 * np.nanmean([b for _, b in neg]):.1f} %; mean time {np.mean([r['time'] for r in runs]):.1f} s")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--noise", default="camera", choices=("none", "gauss", "camera"))
    p.add_argument("--res", type=int, default=24)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--area-points", type=int, default=None)
    p.add_argument("--adjust", default=None, help="logdet: the integrated-likelihood adjustment (tools/pp_logdet.py)")
    p.add_argument("--json")
    p.add_argument("--table")
    a = p.parse_args(argv)
    if a.adjust == "logdet":
        import pp_logdet
        pp_logdet.install()
    if a.table:
        print(summary(json.load(open(a.table))["runs"]))
        return 0
    runs = json.load(open(a.json))["runs"] if a.json and os.path.exists(a.json) else []
    done = {r["seed"] for r in runs}
    for seed in range(a.seed0, a.seed0 + a.seeds):
        if seed in done:
            continue
        r = one(seed, a.res, a.noise, a.area_points, a.adjust)
        runs.append(r)
        print(f"seed {seed}: " + " ".join(f"{n}={r['params'][n]:.4g}" for n in SHAPE) + f" ({r['time']:.1f} s)",
              file=sys.stderr, flush=True)
        if a.json:
            with open(a.json, "w") as f:
                json.dump({"runs": runs}, f)
    print(summary(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
