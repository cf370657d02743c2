"""Bias of the raw-sample likelihood on the package's own raw captures (issue 23): render --raw -> fit.

    python tools/bench_raw_kappa.py --res 128 --seeds 8
    python tools/bench_raw_kappa.py --res 256 --seeds 4 --configs before,after

For each seed S: ``fmbrdf-mi render OUT.exr --variant llvm_ad_mono_polarized -D alpha=0.15 --res RES
--raw --raw-seed S --seed S`` (``render --raw``'s samples per pixel: 1024 since 2026-11-26, 64 before:
``--spp 64`` repeats the older rows) (a new Mitsuba sample set and a new camera noise per seed;
``--render-seed 0`` keeps the render of the issue's runs and varies only the camera noise), then the
likelihood fit of ``OUT_raw.png`` (its JSON sidecar: gain, read noise, white level, geometry, light)
in each configuration:

* ``before``: the geometry of each raw sample bilinearly interpolated from the super-pixel normal map
  (the 2x2 pooled normals of the render's pixel centres) and each raw sample modelled at its
  pixel's centre (``area_points=1``): what the package did before issue 23;
* ``geometry``: the exact sphere at each raw sample's centre, ``area_points=1``;
* ``after``: the exact sphere, each raw sample the mean of the model over 2 x 2 points of its pixel
  (the default since issue 23);
* ``m3``, ``m4``: the exact sphere, 3 x 3 or 4 x 4 points;
* ``erode0``, ``erode4``: ``after`` keeping every super-pixel of the mask, or leaving out those within 4
  of its edge (the fit's default leaves out 2: the silhouette, where the render's samples estimate each
  pixel's coverage).

``--spp N`` and ``--render-args "..."`` (more ``render`` options, e.g. ``--full-well 1e8 --read-noise 0
--bits 16`` for an almost noise-free capture) change the render: where the bias of kappa comes from
(a model difference stays without noise; a noise-driven bias goes).

Printed per configuration and parameter: mean estimate - truth, its standard error over seeds
(std / sqrt(seeds)), the mean of the fits' own standard errors, the fraction of 95 % intervals
(estimate +- 1.96 reported standard errors) that contain the truth, and the mean fit time (the
fit only, not the render; the machine's load moves it).  ``--json FILE`` writes every fit.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

from bench_rebuild import cpu_name  # noqa: E402

NAMES = ("eta", "alpha", "beta", "kappa", "k_s", "r_k")
CONFIGS = {"before": (False, 1), "geometry": (True, 1), "after": (True, 2), "m3": (True, 3), "m4": (True, 4),
           "erode0": (True, 2, 0), "erode4": (True, 2, 4)}


def render(tmp, res, seed, render_seed, alpha, extra=()):
    out = os.path.join(tmp, f"r{res}_{seed}.exr")
    cmd = [sys.executable, "-m", "fmbrdf_mi", "render", out, "--variant", "llvm_ad_mono_polarized",
           "-D", f"alpha={alpha}", "--res", str(res), "--raw", "--raw-seed", str(seed),
           "--seed", str(seed if render_seed is None else render_seed), "--no-previews", "-q", "--force", *extra]
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return out[:-4] + "_raw.png"


def fit_one(path, exact, m, erode=None):
    from fmbrdf_mi.fit.api.fitting import fit
    from fmbrdf_mi.fit.inputs.files import build_observation

    obs = build_observation(path, layout=None, black_level=None)
    if not exact:
        obs.geometry = None  # interpolate the pooled normal map (the package before issue 23)
    t0 = time.perf_counter()
    r = fit(obs, progress=False, area_points=m, **({} if erode is None else {"erode": erode}))
    dt = time.perf_counter() - t0
    return {"params": {k: float(r.params[k]) for k in NAMES},
            "std": {k: float(r.std_errors.get(k, float("nan"))) for k in NAMES},
            "truth": {k: float(obs.meta["truth"][k]) for k in NAMES}, "time": dt,
            "n_pixels": int(r.n_pixels), "chi2_per_dof": r.uncertainty.get("chi2_per_dof")}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--seeds", type=int, default=8, help="seeds 1..N (from --seed0 on)")
    ap.add_argument("--seed0", type=int, default=1, help="first seed (default 1)")
    ap.add_argument("--alpha", type=float, default=0.15)
    ap.add_argument("--render-seed", type=int, help="one render seed for all (default: the seed itself)")
    ap.add_argument("--configs", default="before,geometry,after", help=f"of {', '.join(CONFIGS)}")
    ap.add_argument("--spp", type=int, help="render samples per pixel (default: the scene's)")
    ap.add_argument("--render-args", default="", help="more render options, one string")
    ap.add_argument("--json", help="write every fit here")
    args = ap.parse_args()
    configs = args.configs.split(",")
    for c in configs:
        if c not in CONFIGS:
            ap.error(f"--configs: unknown {c!r}")
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip()
    except OSError:
        commit = "?"
    print(f"# {datetime.datetime.now().isoformat(timespec='seconds')}  {cpu_name()}  "
          f"({os.cpu_count()} cores)  commit {commit}")
    print(f"# render --res {args.res} -D alpha={args.alpha} --raw, seeds {args.seed0}..{args.seed0 + args.seeds - 1}, "
          f"render seed "
          f"{'= seed' if args.render_seed is None else args.render_seed}")
    extra = shlex.split(args.render_args) + (["--spp", str(args.spp)] if args.spp else [])
    if extra:
        print(f"# render options: {' '.join(extra)}")
    runs = {c: [] for c in configs}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seed0, args.seed0 + args.seeds):
            path = render(tmp, args.res, seed, args.render_seed, args.alpha, extra)
            for c in configs:
                r = fit_one(path, *CONFIGS[c])
                r["seed"] = seed
                runs[c].append(r)
                print(f"seed {seed:3d} {c:9s} " + "  ".join(f"{k} {r['params'][k]:.4g}+-{r['std'][k]:.2g}"
                                                              for k in NAMES) + f"  [{r['time']:.1f} s]",
                      flush=True)
    print()
    print(f"{'config':9s} {'param':6s} {'truth':>7s} {'bias':>9s} {'+-se':>8s} {'bias/sd':>8s} "
          f"{'mean std':>9s} {'cover95':>7s}")
    for c in configs:
        rs = runs[c]
        for k in NAMES:
            est = np.array([r["params"][k] for r in rs])
            sd = np.array([r["std"][k] for r in rs])
            truth = rs[0]["truth"][k]
            bias = est.mean() - truth
            se = est.std(ddof=1) / np.sqrt(len(est)) if len(est) > 1 else float("nan")
            cover = np.mean(np.abs(est - truth) <= 1.96 * sd)
            print(f"{c:9s} {k:6s} {truth:7.4g} {bias:+9.4g} {se:8.2g} {bias / sd.mean():+8.2f} "
                  f"{sd.mean():9.3g} {cover:7.2f}")
        print(f"{c:9s} fit time {np.mean([r['time'] for r in rs]):.1f} s (mean), "
              f"{np.min([r['time'] for r in rs]):.1f} s (min), {rs[0]['n_pixels']} super-pixels")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "cpu": cpu_name(), "commit": commit, "runs": runs}, f, indent=1)


if __name__ == "__main__":
    main()
