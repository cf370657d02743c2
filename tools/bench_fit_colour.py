"""The colour fit under camera noise: bias, spread, reported standard errors and interval coverage.

    python tools/bench_fit_colour.py [--periods 16] [--seeds 16] [--fix eta=1.5,...] [--noiseless] [--json out.json]
    python tools/bench_fit_colour.py --table a.json b.json      # saved runs of one configuration, pooled

One material (eta 1.5, alpha 0.25, beta 0.4, kappa 1; k_s / r_k 0.6 / 0.8, 0.4 / 1.5,
0.5 / 0.4 for R, G, B: the material of tests/fit/test_api_colour.py), an orthographic
sphere filling PERIODS x PERIODS 4x4 periods of an IMX250MYR-type colour
polarisation mosaic (RGGB), light (0.45, 0.35, 1).  The data are each
channel's model Stokes image evaluated at every raw pixel's centre
(:func:`fmbrdf_mi.synthetic.spheres.ideal_sphere`) captured by
:func:`fmbrdf_mi.sensor.camera.capture` (full well 10 000 e-, read noise 2.5 e-,
12 bits, brightest raw pixel at 80 %; seed = the noise seed), so only the
camera's noise separates data and model.  Each capture is fitted by
:func:`fmbrdf_mi.fit.api.colour.fit_colour` with the gain and read noise known.
Per parameter (per channel for the albedos): mean relative error +- its
standard error, spread, mean reported SE, coverage of the reported 95 %
intervals (with its binomial 95 % interval), fit time.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

SHAPE = dict(eta=1.5, alpha=0.25, beta=0.4, kappa=1.0)
ALBEDOS = {"R": (0.6, 0.8), "G": (0.4, 1.5), "B": (0.5, 0.4)}
LIGHT = (0.45, 0.35, 1.0)


def wilson(k, n, z=1.96):
    """Binomial 95 % interval of a proportion k / n (Wilson score)."""
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def summarise(runs, truth, fixed):
    """Print the Markdown table of ``runs`` (bias, spread, reported SE, coverage per parameter); its rows."""
    ok = [r for r in runs if r["converged"]]
    print(f"\n{len(ok)} of {len(runs)} fits converged; mean chi2/dof "
          f"{np.mean([r['chi2_per_dof'] for r in ok]):.3f}\n")
    print("| param | truth | mean error ± SE | spread | mean reported SE | 95 % coverage (binomial 95 % interval) |")
    print("|---|---|---|---|---|---|")
    rows = []
    for k, tv in truth.items():
        if k in fixed:
            continue
        e = np.array([r["params"][k] - tv for r in ok]) / tv
        s = np.array([r["std_errors"][k] for r in ok]) / tv
        cov = np.array([abs(r["params"][k] - tv) <= 1.96 * r["std_errors"][k] for r in ok])
        lo, hi = wilson(int(cov.sum()), len(cov))
        row = {"param": k, "truth": tv, "mean_error": e.mean(), "se_mean": e.std(ddof=1) / np.sqrt(len(e)),
               "spread": e.std(ddof=1), "mean_reported_se": s.mean(), "coverage": cov.mean(), "ci": (lo, hi)}
        rows.append(row)
        print(f"| {k} | {tv:g} | {100 * row['mean_error']:+.2f} % ± {100 * row['se_mean']:.2f} % | "
              f"{100 * row['spread']:.2f} % | {100 * row['mean_reported_se']:.2f} % | "
              f"{100 * row['coverage']:.0f} % ({100 * lo:.0f}-{100 * hi:.0f} %) |")
    pooled = np.concatenate([[abs(r["params"][k] - tv) <= 1.96 * r["std_errors"][k] for r in ok]
                             for k, tv in truth.items() if k not in fixed])
    lo, hi = wilson(int(pooled.sum()), len(pooled))
    print(f"\npooled coverage {100 * pooled.mean():.1f} % of {len(pooled)} intervals "
          f"(binomial 95 % interval {100 * lo:.1f}-{100 * hi:.1f} %); fit time "
          f"{min(r['time'] for r in runs):.1f}-{max(r['time'] for r in runs):.1f} s")
    return rows


def _truth(fixed):
    return {k: v for k, v in dict(SHAPE, **{f"k_s[{c}]": a[0] for c, a in ALBEDOS.items()},
                                  **{f"r_k[{c}]": a[1] for c, a in ALBEDOS.items()}).items()}


def table(paths):
    """The table of saved runs; the files must share periods, fixed parameters and noise setting."""
    runs, cfg, seeds = [], None, set()
    for p in paths:
        with open(p) as f:
            d = json.load(f)
        c = {k: d["config"][k] for k in ("periods", "fix", "noiseless")}
        if cfg is not None and c != cfg:
            sys.exit(f"bench_fit_colour: --table: {p} has {c}, {paths[0]} {cfg}; pool only one configuration")
        cfg = c
        new = [r for r in d["runs"] if r["seed"] not in seeds]
        if len(new) != len(d["runs"]):
            sys.exit(f"bench_fit_colour: --table: {p} repeats seeds of an earlier file")
        seeds |= {r["seed"] for r in new}
        runs += new
    fixed = {i.partition("=")[0] for i in filter(None, cfg["fix"].split(","))}
    print(f"bench_fit_colour --table: {len(runs)} runs from {len(paths)} file(s); {cfg['periods']} periods, "
          f"fixed {sorted(fixed) or 'none'}{', noiseless' if cfg['noiseless'] else ''}")
    summarise(runs, _truth(fixed), fixed)


def colour_case(periods):
    """The noise-free data of the bench: a sphere of ``periods`` x ``periods`` colour periods (module docstring)."""
    import mitsuba as mi  # noqa: F401  (the package sets its variant)
    from fmbrdf_mi.synthetic.spheres import ideal_sphere
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.camera import CameraModel

    R = periods
    st = np.stack([ideal_sphere({**SHAPE, "k_s": ks, "r_k": rk}, res=2 * R, light=LIGHT)["stokes"]
                   for ks, rk in ALBEDOS.values()])
    cam = CameraModel(cfa=mosaic.BAYER_RGGB, bits=12, full_well=10000.0, read_noise=2.5)
    centre, radius = (R / 2, R / 2), R / 2 - 0.5
    n, m, v = G.sphere_normals((R, R), centre, radius)
    return {"periods": R, "stokes": st, "camera": cam, "normals": n, "mask": m, "view_dirs": v,
            "geometry": G.SphereGeometry((R, R), centre, radius)}


def colour_fit(case, seed, fixed=None, noiseless=False, intervals="auto"):
    """One noise seed of ``case`` (:func:`colour_case`) captured and fitted; returns its record: params,
    std_errors and ci95 flattened to ``k_s[R]``, ..., converged, time, chi2_per_dof."""
    from fmbrdf_mi.fit.api.colour import fit_colour
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi.sensor.camera import capture
    from fmbrdf_mi.sensor.noise import NoiseModel
    from fmbrdf_mi.sensor.samples import colour_samples

    cam, R = case["camera"], case["periods"]
    cap = capture(case["stokes"], cam, peak_fraction=0.8, seed=seed, noiseless=noiseless)
    smp = colour_samples(cap["raw"], cam.layout, cam.cfa, cam.black_level, cam.white_level)
    obs = ob.Observation(np.ones((3, R, R)), ob.erode(case["mask"], 1), case["normals"], case["view_dirs"],
                         np.asarray(LIGHT, float), cap["exposure"] / cam.conversion_gain, geometry=case["geometry"])
    t = time.time()
    res = fit_colour(obs, smp, NoiseModel(cam.conversion_gain, cam.read_noise, 1.0), fixed=fixed or None,
                     intervals=intervals)
    t = time.time() - t
    flat = lambda d: {**{k: d[k] for k in SHAPE if k in d},  # noqa: E731
                      **{f"{a}[{c}]": d[a][c] for a in ("k_s", "r_k") for c in "RGB"}}
    est = flat(res.params)
    se = flat(res.std_errors) if res.converged else None
    ci = flat(res.uncertainty["ci95"]) if res.converged else None
    fis = None
    if ci is not None:   # the Fisher intervals before the profile-likelihood check (shape parameters only)
        fis = dict(ci, **{k: v for k, v in res.uncertainty.get("profile", {}).get("fisher_ci95", {}).items()
                          if k in SHAPE})
    return {"seed": seed, "converged": bool(res.converged), "time": t, "params": est,
            "std_errors": se, "ci95": ci, "ci95_fisher": fis,
            "interval_kind": dict(res.uncertainty.get("interval_kind", {})), "chi2_per_dof": res["chi2_per_dof"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--periods", type=int, default=16, help="sphere diameter in 4x4 periods (>= 8)")
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--fix", default="", help="e.g. eta=1.5,kappa=1 (fixed at these values)")
    ap.add_argument("--noiseless", action="store_true", help="capture without noise (quantisation only)")
    ap.add_argument("--json", metavar="OUT.json")
    ap.add_argument("--table", nargs="+", metavar="IN.json",
                    help="print the table of saved runs (several files of one configuration, other seeds: pooled)")
    args = ap.parse_args()
    if args.table:
        return table(args.table)
    if args.periods < 8 or args.seeds < 2:
        sys.exit("bench_fit_colour: --periods must be >= 8 and --seeds >= 2")
    fixed = {}
    for item in filter(None, args.fix.split(",")):
        name, _, value = item.partition("=")
        if name not in SHAPE:
            sys.exit(f"bench_fit_colour: --fix: {name!r} is not one of {', '.join(SHAPE)}")
        fixed[name] = float(value) if value else SHAPE[name]

    from _common import cpu_name

    R = args.periods
    print(f"bench_fit_colour: {time.strftime('%Y-%m-%d')}, {cpu_name()}, {os.cpu_count()} cores; "
          f"{R}x{R} periods, {args.seeds} seeds, fixed {fixed or 'none'}", flush=True)
    case = colour_case(R)
    truth = _truth(fixed)
    runs = []
    for seed in range(args.seed0, args.seed0 + args.seeds):
        rec = colour_fit(case, seed, fixed, noiseless=args.noiseless)
        runs.append(rec)
        print(f"seed {seed:3d}: {rec['time']:5.1f} s {'ok' if rec['converged'] else 'NC'}  "
              + " ".join(f"{k}={v:.4g}" for k, v in rec["params"].items()), flush=True)

    rows = summarise(runs, truth, fixed)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"config": vars(args), "runs": runs, "rows": rows}, f, indent=1, default=float)


if __name__ == "__main__":
    main()
