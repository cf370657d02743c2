"""What more lights buy: joint likelihood fits of K = 1, 3, 6 images of one object (fmbrdf_mi.fit.api.fitting).

    python tools/bench_fit_lights.py [--materials glossy,rough] [--lights 1,3,6] [--seeds 10] [--size 40]
                                     [--json out.json]
    python tools/bench_fit_lights.py --table out.json      # the Markdown table of a saved run
    python tools/bench_fit_lights.py --free-power [--power-start ratio,given,fixed] [--true-powers ...]

The sibling of ``tools/bench_fit_noise.py`` with the same materials, camera
and data: an orthographic sphere filling a SIZE x SIZE super-pixel image,
the model evaluated at every raw pixel's centre, captured by
:func:`fmbrdf_mi.sensor.camera.capture` (IMX250MZR, 10 000 e- full well, 2.5 e- read
noise, 12 bits, each image's brightest raw pixel at 80 % of full scale; the
fit knows the gain and read noise and each image's exposure).  Six lights
35 degrees from the view direction at azimuths 135 + 60 j degrees (light 0 is
within 0.3 degrees of the noise bench's (-0.5, 0.5, 1) direction); K = 1 fits light 0, K = 3
lights 0, 2, 4, K = 6 all.  Image j of seed s has camera-noise seed
1000 s + j, so the K = 1 data are part of the K = 3 data, which are part of
the K = 6 data (nested: the comparison is between designs, not noise draws).
Every fit: :func:`fmbrdf_mi.fit.api.fitting.fit_joint` with the defaults (coarse
search from no prior, 2 starts, LM, likelihood, all six parameters free,
20 000 super-pixels at most).

Per material x K x parameter, over the seeds: mean relative error +- its
standard error, spread (std of the relative error), mean reported relative
standard error, spread / reported SE, coverage of the reported 95 %
intervals, the mean fit time; the JSON also keeps each fit's reported
k_s / r_k correlation (about -1 whatever K: r_k = k_b / k_s makes it
structural, so it does not measure the split).  kappa = 0 (``rough``):
absolute errors.

``--free-power``: light j of the ring is ``--true-powers[j]`` times as bright
(default 1, 0.8, 0.6, 1.2, 1.7, 0.9: K = 3 sees 1, 0.6, 1.7), each capture
still exposed to 80 % of full scale, and the fit is told the exposure but
power 1 for every image, so the powers relative to the first image are
unknown.  Each seed is fitted once per ``--power-start`` mode: ``ratio`` and
``given`` (``fit_joint(free_power=True, power_start=...)``:
fmbrdf_mi.fit.problem.free_power), and ``fixed`` (the powers held at the wrong
given values: what ignoring them costs).  The table gains the fitted powers
(``power_j``: image j of the subset; truth its power over image 0's) and a
``start`` column; the JSON keeps the evaluations and the final objective of
every fit (which start reaches the better optimum, at what cost).
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

from bench_fit_noise import MATERIALS, NAMES, stat_cells  # noqa: E402

TILT_DEG = 35.0


def light_ring(k=6, tilt=TILT_DEG):
    """k unit light directions ``tilt`` degrees from the view axis, azimuths 135 + 360 j / k degrees."""
    t = math.radians(tilt)
    return [(math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t))
            for a in (math.radians(135.0 + 360.0 * j / k) for j in range(k))]


def subsets(ks, n=6):
    return {k: list(range(0, n, n // k)) if n % k == 0 else list(range(k)) for k in ks}


def ideal_images(truth, size, powers=(1.0,) * 6):
    """The six ring lights' noise-free images of the sphere, light j ``powers[j]`` times as bright."""
    from fmbrdf_mi.synthetic.spheres import ideal_sphere

    ideals = [ideal_sphere(truth, res=size, light=l) for l in light_ring(6)]
    for i, p in zip(ideals, powers):   # the capture's exposure (what the fit is told) ignores p
        i["stokes"] = i["stokes"] * p
    return ideals


def capture_seed(ideals, cam, seed):
    """Seed ``seed``'s captures of the six images (image j: camera-noise seed 1000 seed + j)."""
    from fmbrdf_mi.synthetic.spheres import capture_observation

    return [capture_observation(i, cam, seed=1000 * seed + j)[0] for j, i in enumerate(ideals)]


def lights_fits(obs, k, sets, *, material, seed, truth, powers=(1.0,) * 6, free_power=False,
                power_start=("ratio", "given", "fixed"), max_time=None, intervals="auto"):
    """Yield (record, FitResult) of the fits of one seed's K images (with ``free_power``: one per start mode)."""
    from fmbrdf_mi.fit.api.fitting import fit_joint

    sub = [obs[j] for j in sets[k]]
    modes = list(power_start) if free_power else [None]
    for mode in modes:
        kw = {} if mode in (None, "fixed") else {"free_power": True, "power_start": mode}
        f = r = fit_joint(sub, progress=False, max_time=max_time, intervals=intervals, **kw)
        corr = (f.uncertainty or {}).get("correlation")
        c_ks_rk = None
        if corr:
            nm = corr["names"]
            c_ks_rk = corr["matrix"][nm.index("k_s")][nm.index("r_k")]
        rec = {"material": material, "K": k, "lights": sets[k], "seed": seed, "truth": dict(truth),
               "params": dict(f.params), "std_errors": dict(f.std_errors),
               "ci95": dict(f.uncertainty.get("ci95", {})),
               "ci95_fisher": dict(f.uncertainty.get("profile", {}).get("fisher_ci95", f.uncertainty.get("ci95", {}))),
               "interval_kind": dict(f.uncertainty.get("interval_kind", {})),
               "converged": f.converged, "stop_reason": f.stop_reason, "time": f.timings["total"],
               "n_pixels": f.n_pixels, "corr_ks_rk": c_ks_rk,
               "chi2_per_dof": f.uncertainty.get("chi2_per_dof"), "start": mode,
               "evaluations": f.timings["evaluations"], "loss": f.loss}
        if free_power:
            for j in range(1, k):
                rec["truth"][f"power_{j}"] = powers[sets[k][j]] / powers[sets[k][0]]
                if r.powers is not None:
                    rec["params"][f"power_{j}"] = r.powers["values"][j]
                    if r.powers["std_errors"][j] is not None:
                        rec["std_errors"][f"power_{j}"] = r.powers["std_errors"][j]
                    if r.powers["ci95"][j] is not None:
                        rec["ci95"][f"power_{j}"] = r.powers["ci95"][j]
        yield rec, r


def run(args):
    from fmbrdf_mi.sensor.camera import CameraModel

    cam = CameraModel(full_well=args.full_well, read_noise=args.read_noise, bits=args.bits)
    sets = subsets(args.lights)
    powers = args.true_powers if args.free_power else [1.0] * 6
    runs = []
    for mat in args.materials:
        truth = MATERIALS[mat]
        t = time.time()
        ideals = ideal_images(truth, args.size, powers)
        print(f"# {mat}: 6 ideal images {time.time() - t:.1f} s", file=sys.stderr, flush=True)
        for seed in range(args.seed0, args.seed0 + args.seeds):
            obs = capture_seed(ideals, cam, seed)
            for k in args.lights:
                for rec, f in lights_fits(obs, k, sets, material=mat, seed=seed, truth=truth, powers=powers,
                                          free_power=args.free_power, power_start=args.power_start,
                                          max_time=args.max_time):
                    runs.append(rec)
                    mode = rec["start"]
                    print(f"{mat:7s} K={k} {mode or ''} seed {seed:3d} {f.timings['total']:6.1f} s "
                          f"{'ok ' if f.converged else 'NC '}"
                          + " ".join(f"{n}={v:.4g}" for n, v in rec["params"].items()), file=sys.stderr, flush=True)
                    if args.json:
                        _save(args, runs)
    return runs


_RUNS = []


def summarise(runs):
    _RUNS[:] = runs
    groups = {}
    for r in runs:
        groups.setdefault((r["material"], r["K"], r.get("start")), []).append(r)
    rows = []
    for (mat, k, start), rs in groups.items():
        ok = [r for r in rs if r["converged"]]
        t = float(np.mean([r["time"] for r in rs]))
        corr = [r["corr_ks_rk"] for r in ok if r.get("corr_ks_rk") is not None]
        powers = [n for n in rs[0]["truth"] if n.startswith("power_") and n in rs[0]["params"]]
        for name in list(NAMES) + powers:
            tv = rs[0]["truth"][name]
            denom = tv if tv != 0 else 1.0
            e = np.array([(r["params"][name] - tv) / denom for r in ok])
            se = np.array([r["std_errors"].get(name, np.nan) / abs(denom) for r in ok])
            cov = [r["ci95"][name][0] <= tv <= r["ci95"][name][1] for r in ok if name in r.get("ci95", {})]
            n = len(e)
            spread = float(e.std(ddof=1)) if n > 1 else np.nan
            rep = float(np.nanmean(se)) if n else np.nan
            rows.append({"material": mat, "K": k, "start": start, "param": name, "n": n,
                         "not_converged": len(rs) - n,
                         "relative": tv != 0, "mean_error": float(e.mean()) if n else np.nan,
                         "se_mean": spread / math.sqrt(n) if n > 1 else np.nan, "spread": spread,
                         "mean_reported_se": rep, "ratio": spread / rep if rep else np.nan,
                         "coverage": float(np.mean(cov)) if cov else np.nan, "time": t,
                         "corr_ks_rk": float(np.mean(corr)) if corr else np.nan,
                         "evaluations": float(np.mean([r.get("evaluations", np.nan) for r in rs]))})
    order = list(NAMES) + sorted({r["param"] for r in rows if r["param"] not in NAMES})
    starts = ["ratio", "given", "fixed", None]
    rows.sort(key=lambda r: (r["material"], starts.index(r["start"]), order.index(r["param"]), r["K"]))
    return rows


def table(rows):
    free = any(r.get("start") for r in rows)
    out = ["| material |" + (" start |" if free else "") + " param | K | n (NC) | mean error ± SE | spread | "
           "mean reported SE | spread / SE | 95 % coverage | fit time (s) |" + (" BSDF evaluations |" if free else ""),
           "|---|" + ("---|" if free else "") + "---|---|---|---|---|---|---|---|---|" + ("---|" if free else "")]
    for r in rows:
        out.append(f"| {r['material']} |" + (f" {r['start']} |" if free else "") + f" {r['param']} | {r['K']} | "
                   f"{stat_cells(r)} | {r['ratio']:.2f} | {100 * r['coverage']:.0f} % | {r['time']:.1f} |"
                   + (f" {r['evaluations']:.0f} |" if free else ""))
    if free:   # which start reaches the better optimum: the final objective, paired by seed
        by = {}
        for r in _RUNS:
            by.setdefault((r["material"], r["K"], r["seed"]), {})[r["start"]] = r["loss"]
        d = [v["given"] - v["ratio"] for v in by.values() if "given" in v and "ratio" in v]
        if d:
            out.append(f"\nfinal objective (the likelihood: chi^2 with IRLS variances), given start minus ratio start, "
                       f"over {len(d)} paired fits: mean {np.mean(d):+.3g}, min {np.min(d):+.3g}, max {np.max(d):+.3g}")
    return "\n".join(out)


def _save(args, runs):
    with open(args.json, "w") as f:
        json.dump({"config": {k: v for k, v in vars(args).items() if k != "table"}, "runs": runs,
                   "summary": summarise(runs)}, f, indent=1)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--materials", default="glossy,rough", help=f"comma-separated of {', '.join(MATERIALS)}")
    p.add_argument("--lights", default="1,3,6", help="numbers of lights K (1, 2, 3 or 6; default %(default)s)")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--size", type=int, default=40, help="super-pixels across the image (default %(default)s)")
    p.add_argument("--max-time", type=float, default=None)
    p.add_argument("--full-well", type=float, default=10000.0)
    p.add_argument("--read-noise", type=float, default=2.5)
    p.add_argument("--bits", type=int, default=12)
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--table", metavar="IN.json")
    p.add_argument("--free-power", action="store_true", help="unknown light powers (module docstring)")
    p.add_argument("--power-start", default="ratio,given,fixed",
                   help="with --free-power: comma-separated of ratio, given, fixed (default %(default)s)")
    p.add_argument("--true-powers", default="1,0.8,0.6,1.2,1.7,0.9",
                   help="with --free-power: the six ring lights' powers (default %(default)s)")
    args = p.parse_args(argv)
    if args.table:
        with open(args.table) as f:
            print(table(summarise(json.load(f)["runs"])))
        return 0
    args.materials = [m for m in args.materials.split(",") if m]
    bad = [m for m in args.materials if m not in MATERIALS]
    if bad:
        p.error(f"--materials: unknown {', '.join(bad)} (have {', '.join(MATERIALS)})")
    args.lights = [int(k) for k in args.lights.split(",")]
    args.power_start = [m for m in args.power_start.split(",") if m]
    if any(m not in ("ratio", "given", "fixed") for m in args.power_start):
        p.error("--power-start: each of ratio, given, fixed")
    try:
        args.true_powers = [float(x) for x in args.true_powers.split(",")]
    except ValueError:
        p.error("--true-powers: six comma-separated positive numbers")
    if len(args.true_powers) != 6 or not all(x > 0 for x in args.true_powers):
        p.error("--true-powers: six comma-separated positive numbers")
    if args.free_power and 1 in args.lights:
        p.error("--free-power: K = 1 has no power to estimate; use --lights 2, 3 or 6")
    if any(k not in (1, 2, 3, 6) for k in args.lights):
        p.error("--lights: each K must be 1, 2, 3 or 6 (subsets of the ring of six)")
    t0 = time.time()
    runs = run(args)
    print(table(summarise(runs)))
    print(f"# {len(runs)} fits in {time.time() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
