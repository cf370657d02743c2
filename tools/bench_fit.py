"""Parameter recovery on synthetic spheres: noise-free and through a simulated polarisation camera.

    python tools/bench_fit.py [--res 256] [--sets 1,2,...] [--json out.json]

For each of 8 parameter sets spread over the box (eta 1.2-2.0, alpha 0.05-1.0,
beta 1-4, kappa 0-50, r_k 0.1-5, k_s 0.6-2):

* data: the sphere is *rendered through Mitsuba* (``fmbrdf_mi.scene``, stokes
  integrator over direct, orthographic camera, box filter, so each pixel is
  the average over its area) in ``llvm_ad_mono_polarized``;
  - noise-free: a res x res render at 64 spp;
  - noisy: a 2res x 2res render at 64 spp seen by the camera model of
    ``fmbrdf_mi.sensor.noise`` (IMX250MZR quad-Bayer sampling, full well
    10 000 e-, read noise 2.5 e-, 12-bit ADC, brightest raw pixel at 90 % of
    full scale, seeded), demosaicked to res x res super-pixels (bilinear);
    the fit knows the camera's gain and read noise (as from a data sheet) and
    compares the observed DoLP with the mean DoLP that camera measures
    (``fmbrdf_mi.sensor.rice``), and it averages its model
    over the raw pixels each super-pixel comes from (``demosaic_footprint``);
  The renderer's own pixel-sampling noise is not part of the camera model,
  so it must stay well below the camera's: at 16 spp it alone moved k_s of
  set 7, whose DoLP is below 0.01 everywhere, by +13 % (a fit to the
  noiseless camera pipeline); ``--noise-seeds K`` repeats the noisy
  condition with K camera-noise seeds on the same render;
* fit: ``fmbrdf_mi.fit.fit`` with its defaults, i.e. the *per-pixel* path
  (not the renderer that made the data; noise-free: at pixel centres), coarse search from no
  prior knowledge, Levenberg-Marquardt, 20 000 random pixels of the mask
  eroded by 2 pixels;
* relighting: the same sphere under a second light (noise-free, resp. through
  the same camera), predicted from the estimates of FMBRDF and of the three
  baselines (pplastic, lambert_ts, oren_nayar_ts) fitted to the same image the
  same way; RMSE / mean observed intensity.

Prints, per set and condition, true value, estimate, relative error and the
Gauss-Newton standard error of every parameter, and the fit time; then a
summary.  Timings are wall-clock on this machine, whatever else runs on it.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

SETS = [
    dict(eta=1.20, alpha=0.05, beta=2.0, kappa=0.0, k_s=1.0, r_k=0.5),
    dict(eta=1.35, alpha=0.10, beta=1.0, kappa=25.0, k_s=0.6, r_k=5.0),
    dict(eta=1.50, alpha=0.20, beta=3.0, kappa=10.0, k_s=1.5, r_k=0.1),
    dict(eta=1.65, alpha=0.30, beta=1.5, kappa=50.0, k_s=0.8, r_k=2.0),
    dict(eta=1.80, alpha=0.50, beta=4.0, kappa=5.0, k_s=1.2, r_k=1.0),
    dict(eta=2.00, alpha=0.75, beta=2.5, kappa=35.0, k_s=2.0, r_k=0.3),
    dict(eta=1.45, alpha=1.00, beta=1.2, kappa=20.0, k_s=0.7, r_k=3.0),
    dict(eta=1.90, alpha=0.15, beta=3.5, kappa=40.0, k_s=1.0, r_k=0.8),
]
BASELINES = ("pplastic", "lambert_ts", "oren_nayar_ts")
NAMES = ("eta", "alpha", "beta", "kappa", "k_s", "r_k")
LIGHT = (-0.5, 0.5, 1.0)        # fitted image: 35 deg from the view direction, upper left
LIGHT2 = (0.7, -0.2, 0.6)       # relighting: lower right, 51 deg from the view
IRRADIANCE = np.pi


def render(material, light, res, spp, seed):
    import mitsuba as mi

    from fmbrdf_mi import scene as S

    scene = mi.load_dict(S.sphere_scene(material, light_dir=light, irradiance=IRRADIANCE,
                                        resolution=res, spp=spp, seed=seed))
    return S.render_stokes(scene, spp=spp, seed=seed, progress=False)[:3, ..., 0].astype(np.float64)


def observe(material, light, res, noisy, seed, camera_seed=None, _cache={}):
    """(Stokes (3, res, res), var(S1) (res, res) or None, capture info) of the sphere under ``light``."""
    from fmbrdf_mi.sensor import noise as cn
    from fmbrdf_mi.sensor.camera import CameraModel, capture
    from fmbrdf_mi.sensor.mosaic import stokes_from_raw

    key = (tuple(sorted(material.items())), tuple(light), res, noisy, seed)
    if key not in _cache:
        if len(_cache) >= 4:  # the renders of one parameter set
            _cache.pop(next(iter(_cache)))
        _cache[key] = render(material, light, 2 * res if noisy else res, 64, seed)
    s = _cache[key]
    if not noisy:
        return s, None, None
    noise = CameraModel()
    cap = capture(s, noise, seed=seed if camera_seed is None else camera_seed)
    stokes = stokes_from_raw(cap["raw"], noise.layout) * cap["dn_to_input"]
    # what a user knows from the camera's data sheet: electrons per DN and read noise
    var = cn.linear_stokes_variance(stokes[0], cap["exposure"], noise.read_noise, "bilinear",
                                    adc_step_e=cap["exposure"] * cap["dn_to_input"])
    return stokes, var, cap


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--sets", help="comma-separated 1-based indices (default: all 8)")
    ap.add_argument("--conditions", default="noise-free,noisy")
    ap.add_argument("--json", help="also write all results to this JSON file")
    ap.add_argument("--no-baselines", action="store_true")
    ap.add_argument("--baselines", default=",".join(BASELINES),
                    help=f"comma-separated baselines to fit (default: {','.join(BASELINES)})")
    ap.add_argument("--noise-seeds", type=int, default=1, metavar="K",
                    help="repeat the noisy condition with K camera-noise seeds (same render)")
    ap.add_argument("--table", metavar="JSON", help="only print the summary and a Markdown table of the "
                    "results saved by an earlier run with --json")
    args = ap.parse_args()
    if args.table:
        with open(args.table) as f:
            rows = json.load(f)
        conditions = list(dict.fromkeys(r["condition"] for r in rows))
        summary(rows, conditions)
        markdown_table(rows)
        return

    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    set_variant()
    from fmbrdf_mi import scene as S
    from fmbrdf_mi.fit import Observation, fit
    from fmbrdf_mi.fit.evaluate.predict import relight_error
    from fmbrdf_mi.sensor import noise as cn

    n, v, m = S.sphere_geometry(args.res)
    which = [int(x) - 1 for x in args.sets.split(",")] if args.sets else range(len(SETS))
    conditions = args.conditions.split(",")
    rows = []
    print(f"bench_fit: {args.res}x{args.res} spheres, light {LIGHT}, relight {LIGHT2}; "
          f"per-pixel fit of Mitsuba renders", flush=True)
    for i in which:
        truth = SETS[i]
        runs = [(c, k) for c in conditions for k in range(args.noise_seeds if c == "noisy" else 1)]
        for cond, k_seed in runs:
            noisy = cond == "noisy"
            t = time.time()
            cam = None if k_seed == 0 else 1000 * k_seed + i
            s1, var1, cap = observe(truth, LIGHT, args.res, noisy, seed=100 + i, camera_seed=cam)
            s2, var2, _ = observe(truth, LIGHT2, args.res, noisy, seed=200 + i,
                                  camera_seed=None if cam is None else cam + 1)
            t_data = time.time() - t
            # noisy: the fit knows the camera pipeline, as `fmbrdf-mi fit` does for a raw mosaic
            fp = cn.demosaic_footprint("bilinear") if noisy else None
            obs = Observation(s1, m, n, v, LIGHT, IRRADIANCE, lin_variance=var1, footprint=fp)
            obs2 = Observation(s2, m, n, v, LIGHT2, IRRADIANCE, lin_variance=var2, footprint=fp)
            res = fit(obs, progress=False)
            row = {"set": i + 1, "condition": cond, "noise_seed": k_seed, "truth": truth, "estimate": res.params,
                   "std_error": res.std_errors, "fit_time": res.timings["total"],
                   "search_time": res.timings["search"], "loss": res.loss, "stop": res.stop_reason,
                   "n_pixels": res.n_pixels, "data_time": t_data,
                   "saturated": cap["saturated"] if cap else 0.0,
                   "relight": {"fmbrdf": relight_error("fmbrdf", res.params, obs2)["rel_rmse"]}}
            if not args.no_baselines:
                for b in args.baselines.split(","):
                    rb = fit(obs, model=b, progress=False)
                    row["relight"][b] = relight_error(b, rb.params, obs2)["rel_rmse"]
            rows.append(row)
            print(f"\nset {i + 1} ({cond}{'' if k_seed == 0 else f', noise seed {k_seed}'}): fit {res.timings['total']:.1f} s (coarse search "
                  f"{res.timings['search']:.1f} s), loss {res.loss:.3e}, {res.stop_reason}", flush=True)
            print(f"  {'param':<6} {'true':>8} {'estimate':>10} {'rel.err':>9} {'std.err':>9}")
            for k in NAMES:
                tv, ev = truth[k], res.params[k]
                rel = (ev - tv) / tv if tv else float("nan")
                rel_s = f"{rel:+9.2%}" if tv else f"{'abs ' + format(ev - tv, '+.2f'):>9}"
                print(f"  {k:<6} {tv:8.3f} {ev:10.4f} {rel_s} {res.std_errors.get(k, float('nan')):9.2g}")
            print("  relight RMSE/mean: " + "  ".join(f"{k} {x:.4f}" for k, x in row["relight"].items()),
                  flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    summary(rows, conditions)
    markdown_table(rows)


def _rel(r, k):
    """Relative error of parameter k (absolute for a true value of 0)."""
    t = r["truth"][k]
    return (r["estimate"][k] - t) / t if t else r["estimate"][k] - t


def summary(rows, conditions):
    print("\nsummary: worst |relative error| per parameter over the sets where it is not 0 "
          "(where it is 0: the largest estimate), max fit time")
    for cond in conditions:
        sel = [r for r in rows if r["condition"] == cond]
        worst = {}
        for k in NAMES:
            nz = [r for r in sel if r["truth"][k]]
            errs = [abs(_rel(r, k)) for r in nz]
            j = int(np.argmax(errs))
            worst[k] = f"{errs[j]:.2%} (set {nz[j]['set']})"
            zero = [r for r in sel if not r["truth"][k]]
            if zero:
                r0 = max(zero, key=lambda r: r["estimate"][k])
                worst[k] += f" [0 -> {r0['estimate'][k]:.3g} (set {r0['set']})]"
        print(f"  {cond:<10} " + "  ".join(f"{k} {w}" for k, w in worst.items())
              + f"  | max fit {max(r['fit_time'] for r in sel):.0f} s")
        rl = {k: np.mean([r["relight"][k] for r in sel]) for k in sel[0]["relight"]}
        print(f"  {'':<10} mean relight RMSE/mean: " + "  ".join(f"{k} {x:.4f}" for k, x in rl.items()))


def markdown_table(rows):
    """One row per set and condition: relative error (noisy: ± the fit's Gauss-Newton standard error;
    kappa = 0: the estimate), fit time, relighting errors."""
    base = [k for k in BASELINES if k in rows[0]["relight"]]
    head = ["set", "truth (eta, alpha, beta, kappa, k_s, r_k)", "noise", *NAMES, "fit (s)", "relight fmbrdf",
            *(f"relight {b}" for b in base)]
    print("\n| " + " | ".join(head) + " |")
    print("|" + "---|" * (5 + len(NAMES) + len(base)))
    for r in rows:
        t = r["truth"]
        cells = []
        for k in NAMES:
            e = _rel(r, k)
            se = r["std_error"].get(k)
            cells.append((f"{e:+.2%}" if t[k] else f"{r['estimate'][k]:.1f} (abs)")
                         + ("" if se is None or not t[k] or r["condition"] != "noisy" else f" ± {100 * se / t[k]:.2g}%"))
        cond = r["condition"] + (f" (seed {r['noise_seed']})" if r.get("noise_seed") else "")
        print(f"| {r['set']} | {', '.join(format(t[k], 'g') for k in NAMES)} | {cond} | "
              + " | ".join(cells) + f" | {r['fit_time']:.0f} | {r['relight']['fmbrdf']:.4f} |"
              + "".join(f" {r['relight'][b]:.4f} |" for b in base))


if __name__ == "__main__":
    main()
