"""The estimators under camera noise: bias, spread, reported standard errors and interval coverage.

    python tools/bench_fit_noise.py [--materials glossy,rough,...] [--sizes 40,100,256] [--seeds 16]
                                    [--losses likelihood,paper] [--fix kappa=..] [--json out.json]
    python tools/bench_fit_noise.py --table out.json        # Markdown tables from a saved run

For each material (``MATERIALS``: spread over the box, alpha 0.06 to 0.6,
kappa 0 to 50) x object size (an orthographic sphere filling a SIZE x SIZE
super-pixel image, radius SIZE/2 - 1) x camera-noise seed x loss:

* data: the model evaluated at every raw pixel's centre (the per-pixel path
  of :mod:`fmbrdf_mi.fit.evaluate.pixel_model`, exact sphere geometry), captured by
  :func:`fmbrdf_mi.sensor.camera.capture` (IMX250MZR layout, full well 10 000 e-,
  read noise 2.5 e-, 12-bit ADC, brightest raw pixel at 80 % of full
  scale; seed = the noise seed).  The data thus follow the fitted model up
  to the camera's noise: what is measured is the estimator, not model
  mismatch or the renderer's sampling noise (``tools/bench_fit.py`` covers
  those);
* fit: :func:`fmbrdf_mi.fit.fit` with its defaults (coarse search from no
  prior, 2 starts, LM until converged, 20 000 random super-pixels at most)
  and the camera's gain and read noise known, with ``--loss likelihood``
  (the raw samples) and ``--loss paper`` (bilinear-demosaicked Stokes
  image, DoLP term with the Rice mean of that noise, demosaicking
  footprint: the command's defaults for a raw mosaic).

Per material x size x loss x parameter it reports, over the seeds: the
mean relative error +- its standard error (std / sqrt(n)), the spread (std
of the relative error), the mean reported relative standard error, the
coverage of the reported 95 % intervals, and the mean fit time; fits that
did not converge are counted and left out.  Each row's coverage carries its
binomial (Wilson) 95 % interval, and a second table pools the coverage over
the materials per (loss, size, parameter), so that "between 88 % and 99 %"
can be judged with more than 16 fits.  Timings are wall clock on this
machine, whatever else runs on it.
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

MATERIALS = {
    "glossy": dict(eta=1.50, alpha=0.06, beta=1.4, kappa=30.0, k_s=0.9, r_k=1.0),
    "rough": dict(eta=1.60, alpha=0.60, beta=2.0, kappa=0.0, k_s=0.7, r_k=2.0),
    "medium": dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0, k_s=1.0, r_k=0.5),
    "dense": dict(eta=2.00, alpha=0.15, beta=3.0, kappa=50.0, k_s=0.6, r_k=3.0),
    # the render command's default sphere at -D alpha=0.15 (the captures of ``render --raw``)
    "render": dict(eta=1.50, alpha=0.15, beta=2.0, kappa=10.0, k_s=1.0, r_k=1.0),
}
NAMES = ("eta", "alpha", "beta", "kappa", "k_s", "r_k")
LIGHT = (-0.5, 0.5, 1.0)


def noise_fit(obs, cap, *, material, size, seed, loss, truth, fixed=None, max_time=None, starts=2, cache=None,
              intervals="auto", area_points=None):
    """One fit of the bench: ``obs`` (a :func:`capture_observation` of the ideal sphere) fitted with ``loss``;
    returns (its record, as kept in the JSON, the FitResult).  ``cache``: a dict that keeps the evaluator
    across noise seeds (the same geometry, pixels and objective).  ``area_points``: the likelihood's m x m
    points per raw sample (None: the fit's default)."""
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.problem.data import prepare, select_pixels

    opts = FitOptions(loss=loss, fixed=fixed or None, max_time=max_time, starts=starts, intervals=intervals,
                      area_points=area_points)
    idx, _ = select_pixels(obs, opts)
    key = (loss, area_points, tuple(idx))
    cache = {} if cache is None else cache
    if key not in cache:
        cache.clear()
        cache[key] = prepare([obs], opts, loss, single=True).evaluator
    r = fit(obs, opts, evaluator=cache[key], progress=False)
    rec = {"material": material, "size": size, "seed": seed, "loss": loss, "truth": truth,
           "params": r.params, "std_errors": r.std_errors,
           "ci95": r.uncertainty.get("ci95", {}), "converged": r.converged,
           "ci95_fisher": r.uncertainty.get("profile", {}).get("fisher_ci95", r.uncertainty.get("ci95", {})),
           "interval_kind": r.uncertainty.get("interval_kind", {}),
           "stop_reason": r.stop_reason, "time": r.timings["total"], "n_pixels": r.n_pixels,
           "evaluations": r.timings["evaluations"],
           "saturated": cap["saturated"], "fixed": fixed or {},
           "chi2_per_dof": r.uncertainty.get("chi2_per_dof"), "area_points": area_points}
    return rec, r


def run(args):
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
    from fmbrdf_mi.fit.inputs.parse import parse_fixed
    from fmbrdf_mi.sensor.camera import CameraModel

    cam = CameraModel(full_well=args.full_well, read_noise=args.read_noise, bits=args.bits)
    fixed = parse_fixed(args.fix) or {}
    runs = []
    for mat in args.materials:
        truth = MATERIALS[mat]
        fx = {k: truth[k] if v is None or (isinstance(v, float) and math.isnan(v)) else v for k, v in fixed.items()}
        for size in args.sizes:
            t = time.time()
            ideal = ideal_sphere(truth, res=size, light=LIGHT)
            print(f"# {mat} {size}x{size}: ideal capture {time.time() - t:.1f} s", file=sys.stderr, flush=True)
            evs = {}
            for seed in range(args.seed0, args.seed0 + args.seeds):
                obs, cap = capture_observation(ideal, cam, seed=seed)
                for loss in args.losses:
                    rec, r = noise_fit(obs, cap, material=mat, size=size, seed=seed, loss=loss, truth=truth,
                                       fixed=fx, max_time=args.max_time, starts=args.starts, cache=evs)
                    runs.append(rec)
                    print(f"{mat:7s} {size:4d} seed {seed:3d} {loss:10s} {r.timings['total']:7.1f} s "
                          f"{'ok ' if r.converged else 'NC '} "
                          + " ".join(f"{k}={v:.4g}" for k, v in r.params.items()), file=sys.stderr, flush=True)
                    if args.json:
                        _save(args, runs)
    return runs


def summarise(runs):
    """Rows: (material, size, loss, parameter, n, mean rel. error, its SE, spread, mean rel. SE, coverage, time)."""
    groups = {}
    for r in runs:
        groups.setdefault((r["material"], r["size"], r["loss"]), []).append(r)
    rows = []
    for (mat, size, loss), rs in groups.items():
        ok = [r for r in rs if r["converged"]]
        t = float(np.mean([r["time"] for r in rs]))
        for k in NAMES:
            if k in rs[0].get("fixed", {}):
                continue
            tv = rs[0]["truth"][k]
            denom = tv if tv != 0 else 1.0   # kappa = 0: absolute error
            e = np.array([(r["params"][k] - tv) / denom for r in ok])
            se = np.array([r["std_errors"].get(k, np.nan) / abs(denom) for r in ok])
            cov = [r["ci95"][k][0] <= tv <= r["ci95"][k][1] for r in ok if k in r.get("ci95", {})]
            # the Fisher intervals alone (before the profile-likelihood check replaced some ends)
            cov_f = [r.get("ci95_fisher", r["ci95"])[k][0] <= tv <= r.get("ci95_fisher", r["ci95"])[k][1]
                     for r in ok if k in r.get("ci95", {})]
            profiled = sum(1 for r in ok if "profile" in r.get("interval_kind", {}).get(k, ""))
            n = len(e)
            lo, hi = wilson(int(np.sum(cov)), len(cov))
            rows.append({"material": mat, "size": size, "loss": loss, "param": k, "n": n,
                         "not_converged": len(rs) - n, "relative": tv != 0,
                         "mean_error": float(e.mean()) if n else np.nan,
                         "se_mean": float(e.std(ddof=1) / math.sqrt(n)) if n > 1 else np.nan,
                         "spread": float(e.std(ddof=1)) if n > 1 else np.nan,
                         "mean_reported_se": float(np.nanmean(se)) if n else np.nan,
                         "coverage": float(np.mean(cov)) if cov else np.nan, "covered": int(np.sum(cov)),
                         "coverage_n": len(cov), "coverage_ci95": [lo, hi], "time": t,
                         "coverage_fisher": float(np.mean(cov_f)) if cov_f else np.nan, "profiled": profiled})
    return rows


def wilson(k, n, z=1.959963984540054):
    """Wilson score 95 % interval of a binomial proportion k / n ((nan, nan) for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return float(max(c - h, 0.0)), float(min(c + h, 1.0))


def pooled(rows):
    """Coverage pooled over the materials per (loss, size, parameter), with its Wilson 95 % interval."""
    groups = {}
    for r in rows:
        g = groups.setdefault((r["loss"], r["size"], r["param"]), {"k": 0, "n": 0, "materials": 0, "nc": 0})
        g["k"] += r.get("covered", 0)
        g["n"] += r.get("coverage_n", 0)
        g["materials"] += 1
        g["nc"] += r["not_converged"]
    out = []
    for (loss, size, param), g in groups.items():
        lo, hi = wilson(g["k"], g["n"])
        out.append({"loss": loss, "size": size, "param": param, "materials": g["materials"], "covered": g["k"],
                    "n": g["n"], "not_converged": g["nc"], "coverage": g["k"] / g["n"] if g["n"] else np.nan,
                    "ci95": [lo, hi], "inside_88_99": bool(g["n"] and lo <= 0.99 and hi >= 0.88),
                    "whole_ci_inside": bool(g["n"] and lo >= 0.88 and hi <= 0.99)})
    return sorted(out, key=lambda x: (x["loss"], x["size"], NAMES.index(x["param"])))


def pooled_table(prow):
    out = ["| loss | size | param | materials | covered / fits (NC) | coverage | binomial 95 % interval | "
           "consistent with 88-99 % |", "|---|---|---|---|---|---|---|---|"]
    for r in prow:
        verdict = "yes" if r["inside_88_99"] else "**no**"
        out.append(f"| {r['loss']} | {r['size']}² | {r['param']} | {r['materials']} | {r['covered']} / {r['n']} "
                   f"({r['not_converged']}) | {100 * r['coverage']:.1f} % | {100 * r['ci95'][0]:.1f}-"
                   f"{100 * r['ci95'][1]:.1f} % | {verdict} |")
    return "\n".join(out)


def stat_cells(r):
    """The cells 'n (NC) | mean error ± SE | spread | mean reported SE' of a summary row
    (relative errors in %, absolute ones where the truth is 0)."""
    pct = (lambda x: f"{100 * x:+.2f} %") if r["relative"] else (lambda x: f"{x:+.3g}")
    pc = (lambda x: f"{100 * x:.2f} %") if r["relative"] else (lambda x: f"{x:.3g}")
    return (f"{r['n']} ({r['not_converged']}) | {pct(r['mean_error'])} ± {pc(r['se_mean'])} | "
            f"{pc(r['spread'])} | {pc(r['mean_reported_se'])}")


def table(rows):
    out = ["| material | size | loss | param | n (NC) | mean error ± SE | spread | mean reported SE | "
           "95 % coverage (binomial 95 % interval) | Fisher intervals only: coverage (fits profiled) | "
           "fit time (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fisher = (f"{100 * r['coverage_fisher']:.0f} % ({r['profiled']})" if "coverage_fisher" in r else "-")
        out.append(f"| {r['material']} | {r['size']}² | {r['loss']} | {r['param']} | {stat_cells(r)} | "
                   f"{100 * r['coverage']:.0f} % ({_ci(r)}) | {fisher} | {r['time']:.1f} |")
    return "\n".join(out)


def _ci(r):
    lo, hi = r.get("coverage_ci95", (np.nan, np.nan))
    return f"{100 * lo:.0f}-{100 * hi:.0f} %"


def report(runs):
    """Both tables: per row, then coverage pooled over the materials."""
    rows = summarise(runs)
    return (table(rows) + "\n\nCoverage pooled over the materials per (loss, size, parameter); "
            "'consistent with 88-99 %': the binomial 95 % interval of the pooled coverage overlaps 88-99 %:\n\n"
            + pooled_table(pooled(rows)))


def _save(args, runs):
    with open(args.json, "w") as f:
        rows = summarise(runs)
        json.dump({"config": {k: v for k, v in vars(args).items() if k != "table"}, "runs": runs,
                   "summary": rows, "pooled_coverage": pooled(rows)}, f, indent=1)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--materials", default="glossy,rough,medium,dense", help=f"comma-separated of {', '.join(MATERIALS)}")
    p.add_argument("--sizes", default="40,100,256", help="image sizes in super-pixels (default %(default)s)")
    p.add_argument("--seeds", type=int, default=16, help="camera-noise seeds per case (default %(default)s)")
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--losses", default="likelihood,paper")
    p.add_argument("--fix", action="append", metavar="NAME[=VALUE]",
                   help="hold shape parameters fixed (at the truth when no value), e.g. --fix eta,beta,kappa")
    p.add_argument("--starts", type=int, default=2)
    p.add_argument("--max-time", type=float, default=None, help="per fit (default: none)")
    p.add_argument("--full-well", type=float, default=10000.0)
    p.add_argument("--read-noise", type=float, default=2.5)
    p.add_argument("--bits", type=int, default=12)
    p.add_argument("--json", metavar="OUT.json", help="write runs and summary (updated after every fit)")
    p.add_argument("--table", metavar="IN.json", help="print the Markdown table of a saved run and exit")
    args = p.parse_args(argv)
    if args.table:
        with open(args.table) as f:
            d = json.load(f)
        print(report(d["runs"]))
        return 0
    args.materials = [m for m in args.materials.split(",") if m]
    bad = [m for m in args.materials if m not in MATERIALS]
    if bad:
        p.error(f"--materials: unknown {', '.join(bad)} (have {', '.join(MATERIALS)})")
    args.sizes = [int(s) for s in args.sizes.split(",")]
    args.losses = [x for x in args.losses.split(",") if x]
    if args.fix:
        items = ",".join(args.fix).split(",")
        args.fix = [i if "=" in i else f"{i}=nan" for i in items if i]
    bad = [x for x in args.losses if x not in ("likelihood", "paper")]
    if bad or not args.losses:
        p.error(f"--losses: expected a comma-separated subset of likelihood,paper, got {','.join(bad) or 'nothing'}")
    runs = run(args)
    print(report(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
