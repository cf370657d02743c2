"""Round trips of the Mueller BRDF fit over noise seeds: coverage of the reported intervals and time per wavelength.

For each model (fmbrdf, pplastic) and each seed: a table of the model at known parameters on a goniometric scan
(:func:`fmbrdf_mi.brdf_fit.mueller_fit.goniometer_geometries`), with the fit's noise model (relative sigma_f on
f_r11, additive sigma_m on the normalised elements), written in the SCATMECH/NIST layout or as the plain NPZ table
(alternating with the seed), read back and fitted with the default options.  Reported per model and parameter:
the share of seeds whose interval holds the true value (coverage, at the fit's level), the mean estimate, the
spread of the estimates over the seeds against the mean reported standard error, the estimated sigmas against
the true ones, and the seconds per fit (one wavelength).

    python tools/bench_fit_mueller.py --seeds 20 --models pplastic,fmbrdf -o bench_mueller.json
    python tools/bench_fit_mueller.py --seeds 30 --models fmbrdf --linearised 400 -o fm30.json
    python tools/bench_fit_mueller.py --table fm30.json --linearised 400   # the same, added to a result
    python tools/bench_fit_mueller.py --dense --seeds 2 --models pplastic,fmbrdf   # times on a few thousand rows
    python tools/bench_fit_mueller.py --times --seeds 2      # seconds per wavelength per model, both scans
    python tools/bench_fit_mueller.py --table bench_mueller.json      # the markdown table of a result
    python tools/bench_fit_mueller.py --share-check --models pplastic,fmbrdf --seed0 10   # shared over wavelengths
    python tools/bench_fit_mueller.py --make-comparison cmp && fmbrdf-mi fit-brdf cmp/fmbrdf_scan.csv --holdout cmp/fmbrdf_random.npz
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

TRUTH = {
    "fmbrdf": {"eta": 1.5, "alpha": 0.2, "beta": 2.0, "kappa": 5.0, "k_s": 0.8, "k_b": 0.3},
    "pplastic": {"eta": 1.55, "alpha": 0.12, "specular_reflectance": 0.7, "diffuse_reflectance": 0.35},
}


#: The dense scan of ``--dense``: four incidence angles, exit angles every 2 degrees in twelve planes.
DENSE = {"theta_i": (10.0, 30.0, 50.0, 70.0), "theta_o": tuple(range(-79, 80, 2)), "phi_o": tuple(range(0, 180, 15))}


def linearised(model, truth, w_in, w_out, noise_f, noise_m, seeds):
    """Standardised errors (estimate - truth) / SE of the model linearised at ``truth``, for the noise draws of
    ``seeds`` (those of ``synthetic_table``): {parameter: [z per seed]}.  Parameters: the shape parameters'
    values and the albedos' logarithms (the fit's covariance coordinates)."""
    from fmbrdf_mi.brdf_fit import mueller_fit as F
    from fmbrdf_mi.brdf_fit.mueller_values import get_model

    m = get_model(model)
    names = F.parameter_names(model)
    M0 = F.predict(model, truth, w_in, w_out)

    def residuals(M, data):
        f, fd = M[:, 0, 0], data[:, 0, 0]
        e = (M / f[:, None, None] - data / fd[:, None, None]).reshape(-1, 16)[:, 1:]
        return np.concatenate([np.log(f / fd) / noise_f, e.ravel() / noise_m])

    cols = []
    for k in names:
        albedo = k in m.albedo_names
        h = 1e-4 if albedo else 1e-3 * max(abs(truth[k]), 1e-2)
        side = []
        for sgn in (1, -1):
            p = dict(truth)
            p[k] = truth[k] * np.exp(sgn * h) if albedo else truth[k] + sgn * h
            side.append(residuals(F.predict(model, p, w_in, w_out), M0))
        cols.append((side[0] - side[1]) / (2 * h))
    J = np.stack(cols, axis=1)
    cov = np.linalg.inv(J.T @ J)
    se = np.sqrt(np.diag(cov))
    z = []
    for s in seeds:
        r = residuals(M0, F.synthetic_table(model, truth, w_in, w_out, noise_f, noise_m, s))
        z.append(-(cov @ (J.T @ r)) / se)
    return dict(zip(names, np.array(z).T.tolist()))


def run(models, seeds, seed0, noise_f, noise_m, dense=False, n_linear=0):
    from fmbrdf_mi.brdf_fit import mueller as T
    from fmbrdf_mi.brdf_fit import mueller_fit as F

    w_in, w_out = F.goniometer_geometries(**(DENSE if dense else {}))
    out = {"rows": len(w_in), "noise_f": noise_f, "noise_m": noise_m, "seeds": seeds, "seed0": seed0,
           "dense": dense,
           "level": F.MuellerFitOptions().level, "models": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for model in models:
            truth = TRUTH[model]
            runs = []
            for s in range(seed0, seed0 + seeds):
                M = F.synthetic_table(model, truth, w_in, w_out, noise_f, noise_m, s)
                path = os.path.join(tmp, f"t{s}." + ("csv" if s % 2 == 0 else "npz"))
                (T.write_scatmech if s % 2 == 0 else T.write_plain)(path, w_in, w_out, M, 0.633)
                tab = T.read_table(path)
                t0 = time.time()
                r = F.fit_model(model, tab)
                runs.append({"seed": s, "format": "scatmech" if s % 2 == 0 else "plain npz",
                             "seconds": time.time() - t0, "params": r.params, "se": r.se, "interval": r.interval,
                             "interval_kind": r.interval_kind, "builds": r.builds,
                             "sigma_f": r.noise["sigma_f"], "sigma_m": r.noise["sigma_m"], "converged": r.converged})
                print(f"{model} seed {s}: {time.time() - t0:.1f} s, " + ", ".join(
                    f"{k} {v:.4g}±{r.se[k]:.2g}" for k, v in r.params.items()), file=sys.stderr, flush=True)
            summary = {}
            for k, v in truth.items():
                est = np.array([r["params"][k] for r in runs])
                se = np.array([r["se"][k] for r in runs])
                cover = np.mean([r["interval"][k][0] <= v <= r["interval"][k][1] for r in runs])
                summary[k] = {"true": v, "mean": float(est.mean()), "coverage": float(cover),
                              "covered": int(round(cover * len(runs))),
                              "spread": float(est.std(ddof=1)) if len(est) > 1 else None,
                              "mean_se": float(se.mean())}
            out["models"][model] = {"truth": truth, "summary": summary, "runs": runs,
                                    "seconds_median": float(np.median([r["seconds"] for r in runs])),
                                    "converged": int(sum(r["converged"] for r in runs)),
                                    "sigma_f_mean": float(np.mean([r["sigma_f"] for r in runs])),
                                    "sigma_m_mean": float(np.mean([r["sigma_m"] for r in runs]))}
    if n_linear:
        add_linearised(out, n_linear)
    return out


def add_linearised(res, n):
    """Adds to a result of :func:`run` its models' linearised coverage over ``n`` noise seeds (from its first
    seed; at least its fitted ones) and each fit's distance from its linearisation, per parameter."""
    from statistics import NormalDist

    from fmbrdf_mi.brdf_fit import mueller_fit as F

    w_in, w_out = F.goniometer_geometries(**(DENSE if res.get("dense") else {}))
    zq = NormalDist().inv_cdf(0.5 + res["level"] / 2)
    for model, m in res["models"].items():
        runs, truth = m["runs"], m["truth"]
        seeds = [r["seed"] for r in runs]
        lin = linearised(model, truth, w_in, w_out, res["noise_f"], res["noise_m"],
                         seeds + [s for s in range(res["seed0"], res["seed0"] + n) if s not in seeds])
        for k, v in truth.items():
            est = np.array([r["params"][k] for r in runs])
            se = np.array([r["se"][k] for r in runs])
            log = k in F.get_model(model).albedo_names
            z_fit = np.log(est / v) * est / se if log else (est - v) / se
            zl = np.array(lin[k])
            m["summary"][k].update({"linear_seeds": len(zl), "linear_covered": int(np.sum(np.abs(zl) < zq)),
                                    "linear_covered_fitted": int(np.sum(np.abs(zl[:len(runs)]) < zq)),
                                    "linear_z_std": float(zl.std(ddof=1)),
                                    "fit_minus_linear_z_max": float(np.max(np.abs(z_fit - zl[:len(runs)])))})
    return res


def share_check(model, noise_f, noise_m, seed0):
    """Parameters shared over wavelengths: a three-wavelength table of ``model`` (TRUTH's shape but eta 0.05
    above, at and below TRUTH's, and the first albedo 1.1, 1, 0.9 times TRUTH's; the goniometric scan, noise seeds
    seed0, seed0 + 1, seed0 + 2) fitted with every shape parameter but eta common: the common parameters' joint
    standard errors against the separate fits' and their inverse-variance combination; every estimate's
    distance from its truth in SE.  Returns the markdown lines."""
    from fmbrdf_mi.brdf_fit import mueller as T
    from fmbrdf_mi.brdf_fit import mueller_fit as F
    from fmbrdf_mi.brdf_fit.mueller_values import get_model

    m = get_model(model)
    first = m.albedo_names[0]
    truths = [dict(TRUTH[model], eta=TRUTH[model]["eta"] + de, **{first: TRUTH[model][first] * f})
              for de, f in ((0.05, 1.1), (0.0, 1.0), (-0.05, 0.9))]
    w_in, w_out = F.goniometer_geometries()
    M = np.concatenate([F.synthetic_table(model, t, w_in, w_out, noise_f, noise_m, seed0 + k)
                        for k, t in enumerate(truths)])
    wl = np.repeat([0.45, 0.55, 0.65], len(w_in))
    share = tuple(n for n in m.shape_names if n != "eta")
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "three.npz")
        T.write_plain(path, np.tile(w_in, (3, 1)), np.tile(w_out, (3, 1)), M, wl)
        tab = T.read_table(path)
        t0 = time.time()
        res = F.fit_table(tab, F.MuellerFitOptions(models=(model,), share=share))
        seconds = time.time() - t0
    rs = [res[w][model] for w in (0.45, 0.55, 0.65)]
    sep = rs[0].history[0]["separate"]
    lines = [f"{model}: {len(w_in)} rows x 3 wavelengths, sigma_f {noise_f:g}, sigma_m {noise_m:g}, noise seeds "
             f"{seed0}-{seed0 + 2}; {', '.join(share)} common; {seconds:.0f} s in all "
             f"({'converged' if rs[0].converged else 'NOT converged'})", "",
             "| parameter | true | joint estimate | joint SE | separate SEs | inverse-variance combination "
             "| joint SE / mean separate SE |", "|---|---|---|---|---|---|---|"]
    for k in share:
        se = np.array(sep[k]["se"])
        lines.append(f"| {k} | {TRUTH[model][k]:g} | {rs[0].params[k]:.4g} | {rs[0].se[k]:.3g} | "
                     f"{', '.join(f'{v:.3g}' for v in se)} | {1 / np.sqrt(np.sum(1 / se ** 2)):.3g} | "
                     f"{rs[0].se[k] / se.mean():.3f} (1/sqrt(3) = 0.577) |")
    lines += ["", "| wavelength | " + " | ".join(f"{k}: (estimate - true) / SE" for k in rs[0].params) + " |",
              "|---|" + "---|" * len(rs[0].params)]
    for w, r, t in zip((0.45, 0.55, 0.65), rs, truths):
        lines.append(f"| {w} | " + " | ".join(f"{(r.params[k] - t[k]) / r.se[k]:+.2f}" for k in r.params) + " |")
    return lines


def make_comparison(out_dir):
    """The inputs of the comparison on the benchmark page: FMBRDF at TRUTH on the goniometric scan (noise seed 1,
    SCATMECH layout) and on 400 random direction pairs (seed 2, plain NPZ), both with sigma_f 0.03, sigma_m 0.01."""
    from fmbrdf_mi.brdf_fit import mueller as T
    from fmbrdf_mi.brdf_fit import mueller_fit as F

    os.makedirs(out_dir, exist_ok=True)
    truth = TRUTH["fmbrdf"]
    w_in, w_out = F.goniometer_geometries()
    T.write_scatmech(os.path.join(out_dir, "fmbrdf_scan.csv"), w_in, w_out,
                     F.synthetic_table("fmbrdf", truth, w_in, w_out, 0.03, 0.01, 1), 0.633)
    w_in, w_out = F.random_geometries(400, seed=2)
    T.write_plain(os.path.join(out_dir, "fmbrdf_random.npz"), w_in, w_out,
                  F.synthetic_table("fmbrdf", truth, w_in, w_out, 0.03, 0.01, 2), 0.633)


def times(models, seeds, seed0, noise_f, noise_m):
    """Seconds per wavelength of each model on the goniometric scan and on the dense one (``DENSE``): each
    model's table at TRUTH (the Lambertian's: FMBRDF's) with noise seeds seed0 ... seed0 + seeds - 1, fitted
    with the default options, one fit after another in this process, after an untimed evaluation of the model
    (its kernels' compilation).  Returns the markdown lines."""
    from fmbrdf_mi.brdf_fit import mueller_fit as F

    lines = ["| scan | rows | model | median s per wavelength | min s | max s | builds per fit (mean) | converged |",
             "|---|---|---|---|---|---|---|---|"]
    for scan, geo in (("goniometric", {}), ("dense", DENSE)):
        w_in, w_out = F.goniometer_geometries(**geo)
        for model in models:
            data = "fmbrdf" if model == "lambert" else model
            tabs = [_plain_table(F.synthetic_table(data, TRUTH[data], w_in, w_out, noise_f, noise_m, s), w_in, w_out)
                    for s in range(seed0, seed0 + seeds)]
            F.predict(model, TRUTH.get(model, {"reflectance": 0.5}), w_in, w_out)   # warm-up: kernel compilation
            secs, builds, ok = [], [], 0
            for tab in tabs:
                t0 = time.perf_counter()
                r = F.fit_model(model, tab)
                secs.append(time.perf_counter() - t0)
                builds.append(r.builds)
                ok += r.converged
                print(f"{scan} {len(w_in)} rows {model}: {secs[-1]:.2f} s, {r.builds} builds", file=sys.stderr,
                      flush=True)
            lines.append(f"| {scan} | {len(w_in)} | {model} | {np.median(secs):.2f} | {min(secs):.2f} | "
                         f"{max(secs):.2f} | {np.mean(builds):.0f} | {ok}/{len(tabs)} |")
    return lines


def _plain_table(M, w_in, w_out):
    """A :class:`~fmbrdf_mi.brdf_fit.mueller.MuellerTable` of M read back from a plain NPZ table."""
    from fmbrdf_mi.brdf_fit import mueller as T

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "t.npz")
        T.write_plain(path, w_in, w_out, M, 0.633)
        return T.read_table(path)


def table(res):
    lines = [f"{res['rows']} rows (goniometric scan), sigma_f {res['noise_f']:g}, sigma_m {res['noise_m']:g}, "
             f"{res['seeds']} seeds from {res['seed0']}, intervals at {res['level']:.0%}", "",
             "| model | parameter | true | mean estimate | coverage | spread / mean SE | linearised, fitted seeds "
             "| linearised coverage | linearised z s.d. | max abs(z fit - z linearised) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for model, m in res["models"].items():
        for k, s in m["summary"].items():
            ratio = "" if s["spread"] is None else f"{s['spread'] / s['mean_se']:.2f}"
            n = len(m["runs"])
            lin = (f"{s['linear_covered_fitted']}/{n} | {s['linear_covered']}/{s['linear_seeds']} ({s['linear_covered'] / s['linear_seeds']:.1%}) | "
                   f"{s['linear_z_std']:.3f} | {s['fit_minus_linear_z_max']:.2f}") if "linear_seeds" in s else " | | |"
            lines.append(f"| {model} | {k} | {s['true']:g} | {s['mean']:.4g} | "
                         f"{s.get('covered', round(s['coverage'] * n))}/{n} ({s['coverage']:.0%}) | {ratio} | {lin} |")
    lines += ["", "| model | converged | median s per wavelength | mean sigma_f | mean sigma_m |", "|---|---|---|---|---|"]
    for model, m in res["models"].items():
        lines.append(f"| {model} | {m['converged']}/{len(m['runs'])} | {m['seconds_median']:.1f} | "
                     f"{m['sigma_f_mean']:.4g} | {m['sigma_m_mean']:.4g} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", default="pplastic,fmbrdf")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--noise-f", type=float, default=0.03)
    p.add_argument("--noise-m", type=float, default=0.01)
    p.add_argument("--linearised", type=int, default=0, metavar="N",
                   help="also the linearised estimator's coverage over N noise seeds (and each fit against it)")
    p.add_argument("--dense", action="store_true", help="the dense scan (DENSE, a few thousand rows) for timing")
    p.add_argument("-o", "--out", help="write the result as JSON")
    p.add_argument("--table", metavar="JSON", help="print the markdown table of a result (with --linearised: "
                   "that added, and written to --out when given) and exit")
    p.add_argument("--share-check", action="store_true",
                   help="fit a three-wavelength table with the shape parameters but eta common (share_check) and exit")
    p.add_argument("--make-comparison", metavar="DIR", help="write the comparison's two tables to DIR and exit")
    p.add_argument("--times", action="store_true",
                   help="seconds per wavelength per model (--models, lambert allowed) on the goniometric and the "
                        "dense scan, --seeds fits each (times) and exit")
    a = p.parse_args(argv)
    if a.times:
        models = [m.strip() for m in a.models.split(",") if m.strip()]
        bad = [m for m in models if m not in (*TRUTH, "lambert")]
        if bad or a.seeds < 1:
            p.error(f"--models: choose from {', '.join(TRUTH)}, lambert; --seeds >= 1")
        print(f"DRJIT_NUM_THREADS={os.environ.get('DRJIT_NUM_THREADS', 'unset')}, {os.cpu_count()} CPUs, "
              f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())} at the start\n")
        print("\n".join(times(models, a.seeds, a.seed0, a.noise_f, a.noise_m)))
        return 0
    if a.make_comparison:
        make_comparison(a.make_comparison)
        return 0
    if a.share_check:
        for m in [m.strip() for m in a.models.split(",") if m.strip()]:
            print("\n".join(share_check(m, a.noise_f, a.noise_m, a.seed0)) + "\n")
        return 0
    if a.table:
        res = json.load(open(a.table))
        if a.linearised:
            res = add_linearised(res, a.linearised)
            if a.out:
                with open(a.out + ".part", "w") as f:
                    json.dump(res, f, indent=1, default=float)
                os.replace(a.out + ".part", a.out)
        print(table(res))
        return 0
    models = [m.strip() for m in a.models.split(",") if m.strip()]
    bad = [m for m in models if m not in TRUTH]
    if bad or a.seeds < 1:
        p.error(f"--models: choose from {', '.join(TRUTH)}; --seeds >= 1")
    res = run(models, a.seeds, a.seed0, a.noise_f, a.noise_m, a.dense, a.linearised)
    if a.out:
        with open(a.out + ".part", "w") as f:
            json.dump(res, f, indent=1, default=float)
        os.replace(a.out + ".part", a.out)
    print(table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
