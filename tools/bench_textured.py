"""Textured objects: per-pixel albedo fits (``albedo="per-pixel"``) over camera-noise seeds.

    python tools/bench_textured.py [--res 32] [--seeds 16] [--textures smooth,high] [--lights 1,3]
                                   [--objects sphere,mesh] [--json out.json]
    python tools/bench_textured.py --table out.json [more.json ...]
    python tools/bench_textured.py --res 24 --seeds 24 --textures smooth --lights 1 --per-pixel-only \
                                   --albedo-smooth 0.04,0.012 [--json s.json]
    python tools/bench_textured.py --sensor colour --res 24 --seeds 12 --textures smooth --lights 3 [--json c.json]

Data, as a camera makes them: an orthographic sphere filling a RES x RES
super-pixel image (:func:`fmbrdf_mi.synthetic.spheres.textured_sphere`: each raw pixel the mean of
the model over 4 x 4 points of its area; the fit models it with 2 x 2), or (``--objects mesh``) the
non-spherical blob mesh of :mod:`fmbrdf_mi.synthetic.mesh_object` seen by a pinhole camera
(fov 20 degrees, about 30 % of the image; :func:`~fmbrdf_mi.synthetic.mesh_object.ideal_object`,
exact ray-cast geometry at every point the fit evaluates), the
`medium` material's eta, alpha, beta, kappa, and albedo maps per super-pixel:

* ``smooth``: k_s = 0.6 + 0.4 sin(6x) cos(4y), k_b = 0.4 + 0.1 cos(5x + 3y) (x, y in [0, 1));
* ``high``: a checkerboard of 3 x 3 super-pixel squares, k_s in {0.4, 1.0}, k_b in {0.25, 0.55}
  (uncorrelated with k_s: the squares of k_b are offset by one),

captured by :func:`fmbrdf_mi.sensor.camera.capture` (IMX250MZR, 10 000 e- full well,
2.5 e- read noise, 12 bits, brightest raw pixel at 80 % of full scale); K = 1
(light (-0.5, 0.5, 1)) or 3 lights (that one and two more, 35 degrees from
the view at azimuths 60 and 300 degrees), one more light held out (azimuth
180 degrees) for relighting.  Per seed, the same pixels are fitted twice:
``albedo="per-pixel"`` and the uniform (shared) fit, both with the camera's
gain and read noise known, every usable pixel, Fisher intervals (``--intervals auto``: the
per-pixel fit's profile-likelihood check); and the same
object with its textures' mean albedos everywhere is fitted uniformly (the
time of a uniform fit of the same pixels).

Reported per texture x K: for eta, alpha, beta, kappa the mean relative
error +- its standard error, spread / mean reported SE, coverage of the 95 %
intervals (Wilson interval); for the maps the RMS over pixels of
(estimate - truth) / reported SE for k_s and k_b (1 when the SEs are right),
and the median relative error; the held-out light's relighting error
(RMSE / mean intensity) of the per-pixel fit and of the uniform fit of the
same data; the mean time of the per-pixel fit against the uniform object's.

``--sensor colour``: a colour polarisation mosaic (IMX250MYR type, RGGB; the same camera otherwise) of RES x
RES 4x4 periods (:func:`fmbrdf_mi.synthetic.spheres.textured_sphere` with (3, RES, RES) maps,
:func:`~fmbrdf_mi.synthetic.spheres.capture_colour`), the maps per channel (:func:`colour_texture`),
fitted by :func:`fmbrdf_mi.fit.api.colour.fit_colour` with ``albedo="per-pixel"`` (one k_s, k_b per period
and channel) and, for the relighting comparison, ``albedo="shared"`` (per-channel albedos, uniform); the map
rows are per channel (RMS z, 95 % cover, median relative error), the relighting error the held-out mosaic's
raw-sample RMSE / mean over the periods both fits predict.

``--albedo-smooth TAU[,TAU_B]``: the per-pixel fits with the albedo maps' smoothness prior
(``FitOptions.albedo_smooth``, :mod:`fmbrdf_mi.fit.evaluate.albedo_prior`); the map rows then add the RMS
error of k_s, k_b against the truth (also reported without the prior), and each run records the prior's
penalty, the effective number of albedo parameters and chi^2 / dof.  The smooth texture's RMS difference of
4-neighbouring pixels is about 0.043 (k_s) and 0.012 (k_b) at 24^2 (the checkerboard's: 0.6 and 0.3 at its
squares' edges, 0 inside).
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

from fmbrdf_mi.synthetic.spheres import smooth_texture  # noqa: E402

TRUTH = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
SHAPE = ("eta", "alpha", "beta", "kappa")
LIGHT0 = (-0.5, 0.5, 1.0)


def lights(k):
    """K fitted lights and the held-out one (directions towards the light)."""
    t = math.radians(35.0)
    ring = [(math.sin(t) * math.cos(math.radians(a)), math.sin(t) * math.sin(math.radians(a)), math.cos(t))
            for a in (60.0, 300.0)]
    held = (math.sin(t) * math.cos(math.pi), 0.0, math.cos(t))
    return [LIGHT0] + ring[:k - 1], held


def texture(name, res):
    if name == "smooth":
        return smooth_texture(res)
    if name == "high":
        iy, ix = np.mgrid[0:res, 0:res] // 3
        return np.where((iy + ix) % 2, 1.0, 0.4), np.where((iy + ix + 1) % 2 == 0, 0.55, 0.25)
    raise SystemExit(f"--textures: unknown {name!r} (smooth, high)")


def colour_texture(name, res):
    """(3, res, res) k_s and k_b maps of a colour object: the mono texture's pattern, another scale and phase per
    channel (the channels' maps differ, so a channel mixed up with another shows in the maps' errors)."""
    y, x = np.mgrid[0:res, 0:res] / res
    if name == "smooth":
        ks = np.stack([0.6 + 0.3 * np.sin(6 * x) * np.cos(4 * y), 0.4 + 0.2 * np.cos(3 * x + 2 * y),
                       0.5 + 0.2 * np.sin(5 * y)])
        kb = np.stack([0.4 + 0.1 * np.cos(5 * x + 3 * y), 0.7 + 0.2 * np.sin(4 * x), 0.3 + 0.1 * np.cos(2 * y)])
        return ks, kb
    ks, kb = texture(name, res)
    return np.stack([ks, 0.7 * ks[::-1], 0.5 * ks.T]), np.stack([kb, 1.5 * kb[:, ::-1], 0.8 * kb.T])


def one_colour(tex, K, seed, res, intervals="fisher", modes=("per-pixel", "shared")):
    """One noise seed of the colour bench (module docstring): the per-pixel and the shared colour fit."""
    from fmbrdf_mi.fit.api.colour import fit_colour, predict_samples
    from fmbrdf_mi.synthetic.spheres import capture_colour, textured_sphere
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.camera import CameraModel

    ks, kb = colour_texture(tex, res)
    fitted, held = lights(K)
    cam = CameraModel(cfa=mosaic.BAYER_RGGB)
    caps = []
    for j, light in enumerate(fitted + [held]):
        o, s, noise, _ = capture_colour(textured_sphere(TRUTH, ks, kb, res=res, light=light), cam,
                                        seed=1000 * seed + j,
                                        exposure=None if j == 0 else caps[0][0].meta["capture"]["exposure"])
        caps.append((o, s))
    obs, smp = [c[0] for c in caps[:K]], [c[1] for c in caps[:K]]
    (ho, hs) = caps[K]
    out = {"seed": seed}
    preds = {}
    for mode in modes:
        t = time.time()
        r = fit_colour(obs if K > 1 else obs[0], smp if K > 1 else smp[0], noise, intervals=intervals,
                       albedo=mode)
        dt = time.time() - t
        rec = {"time": dt, "converged": r.converged, "params": {n: r.params[n] for n in SHAPE},
               "se": {n: (r.std_errors or {}).get(n) for n in SHAPE},
               "ci95": {n: (r.uncertainty or {}).get("ci95", {}).get(n) for n in SHAPE},
               "quadrature": (r.uncertainty or {}).get("quadrature")}
        preds[mode] = predict_samples(ho, hs, r)
        if mode == "per-pixel" and r.maps is not None:
            m, maps = r.maps, {}
            for c, name in enumerate("RGB"):
                f = np.isfinite(m["k_s"][c]) & np.isfinite(m["k_s_se"][c]) & np.isfinite(m["k_b_se"][c])
                zs = (m["k_s"][c][f] - ks[c][f]) / m["k_s_se"][c][f]
                zb = (m["k_b"][c][f] - kb[c][f]) / m["k_b_se"][c][f]
                maps[name] = {"pixels": int(f.sum()), "z_rms_k_s": float(np.sqrt(np.mean(zs ** 2))),
                              "z_rms_k_b": float(np.sqrt(np.mean(zb ** 2))),
                              "med_rel_k_s": float(np.median(np.abs(m["k_s"][c][f] / ks[c][f] - 1))),
                              "med_rel_k_b": float(np.median(np.abs(m["k_b"][c][f] / kb[c][f] - 1))),
                              "cover_k_s": float(np.mean(np.abs(zs) <= 1.96)),
                              "cover_k_b": float(np.mean(np.abs(zb) <= 1.96)),
                              "identified": float(np.mean(m["identified"][c][f]))}
            rec["maps"] = maps
        out[mode] = rec
    sel = np.all([np.all(np.isfinite(p), axis=0) for p in preds.values()], axis=0)
    o = hs.values[:, sel]
    for mode in preds:
        out[mode]["relight"] = float(np.sqrt(np.mean((preds[mode][:, sel] - o) ** 2)) / np.mean(o))
    return out


def wilson(k, n, z=1.959963984540054):
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (c - h, c + h)


def ideal_of(obj, res, light):
    """The noise-free object of ``--objects``: params -> its ideal capture dict."""
    from fmbrdf_mi.synthetic.spheres import ideal_sphere
    from fmbrdf_mi.synthetic.mesh_object import ideal_object

    if obj == "sphere":
        return lambda p: ideal_sphere(p, res=res, light=light)
    if obj == "mesh":
        return lambda p: ideal_object(p, res=res, light=light)
    raise SystemExit(f"--objects: unknown {obj!r} (sphere, mesh)")


def one(tex, K, seed, res, area_points=None, modes=("per-pixel", "shared", "uniform"), intervals="fisher",
        obj="sphere", smooth=None):
    from fmbrdf_mi.fit import fit
    from fmbrdf_mi.fit.evaluate.predict import relight_error
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured
    from fmbrdf_mi.sensor.camera import CameraModel

    ks, kb = texture(tex, res)
    fitted, held = lights(K)
    cam = CameraModel()
    obs = []
    for j, light in enumerate(fitted + [held]):
        ideal = textured(ideal_of(obj, res, light), TRUTH, ks, kb, res)
        # one exposure for all images (the brightest of the first), so the albedos are in one unit
        o, cap = capture_observation(ideal, cam, seed=1000 * seed + j,
                                     exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
    fit_obs, held_obs = obs[:K], obs[K]
    scale = 1.0     # the albedos come back in the units of the truth (the fit knows each exposure)
    out = {"seed": seed}
    # the time of a uniform fit of the same pixels: the object with its textures' mean albedos
    uni = [capture_observation(textured(ideal_of(obj, res, light), TRUTH, np.full_like(ks, ks.mean()),
                                        np.full_like(kb, kb.mean()), res), cam, seed=1000 * seed + j,
                               exposure=obs[j].meta["capture"]["exposure"])[0] for j, light in enumerate(fitted)]
    if "uniform" in modes:
        t = time.time()
        u = fit(uni if K > 1 else uni[0], max_pixels=None, intervals="fisher", progress=False, area_points=area_points)
        out["uniform_time"], out["uniform_converged"] = time.time() - t, u.converged
    for mode in [m for m in ("per-pixel", "shared") if m in modes]:
        t = time.time()
        res_ = fit(fit_obs if K > 1 else fit_obs[0], albedo=mode, max_pixels=None,
                   intervals=intervals if mode == "per-pixel" else "fisher", progress=False, area_points=area_points,
                   albedo_smooth=smooth if mode == "per-pixel" else None)
        dt = time.time() - t
        e = relight_error(res_.model, res_.params, held_obs, maps=res_.maps)
        rec = {"time": dt, "converged": res_.converged, "params": res_.params, "se": res_.std_errors,
               "interval_kind": (res_.uncertainty or {}).get("interval_kind"),
               "ci95": (res_.uncertainty or {}).get("ci95", {}), "relight": e["rel_rmse"],
               "quadrature": (res_.uncertainty or {}).get("quadrature"),
               "fisher_se": (res_.uncertainty or {}).get("incidental", {}).get("fisher_std_errors"),
               "other_optima": (res_.uncertainty or {}).get("other_optima")}
        if mode == "per-pixel" and res_.maps is not None:
            m = res_.maps
            f = np.isfinite(m["k_s"]) & np.isfinite(m["k_s_se"]) & np.isfinite(m["k_b_se"])
            zs = (m["k_s"][f] / scale - ks[f]) / (m["k_s_se"][f] / scale)
            zb = (m["k_b"][f] / scale - kb[f]) / (m["k_b_se"][f] / scale)
            rec["maps"] = {"pixels": int(f.sum()), "z_rms_k_s": float(np.sqrt(np.mean(zs ** 2))),
                           "z_rms_k_b": float(np.sqrt(np.mean(zb ** 2))),
                           "med_rel_k_s": float(np.median(np.abs(m["k_s"][f] / scale / ks[f] - 1))),
                           "med_rel_k_b": float(np.median(np.abs(m["k_b"][f] / scale / kb[f] - 1))),
                           "cover_k_s": float(np.mean(np.abs(zs) <= 1.96)),
                           "cover_k_b": float(np.mean(np.abs(zb) <= 1.96)),
                           "identified": float(np.mean(m["identified"][f])),
                           "rms_k_s": float(np.sqrt(np.mean((m["k_s"][f] / scale - ks[f]) ** 2))),
                           "rms_k_b": float(np.sqrt(np.mean((m["k_b"][f] / scale - kb[f]) ** 2)))}
            rec["chi2_per_dof"] = (res_.uncertainty or {}).get("chi2_per_dof")
            rec["misfit"] = (res_.uncertainty or {}).get("misfit")
            if (res_.albedo or {}).get("prior"):
                pr = res_.albedo["prior"]
                rec["prior"] = {k: pr[k] for k in ("tau_s", "tau_b", "penalty", "effective_parameters",
                                                   "parameters", "null_dims")}
        out[mode] = rec
    return out


def summarise(runs):
    rows = []
    def key_of(r):
        return (r.get("object", "sphere"), r["res"], r["texture"], r["K"], smooth_text(r.get("albedo_smooth")))

    for key in sorted({key_of(r) for r in runs}):
        rs = [r for r in runs if key_of(r) == key]
        pp = [r["per-pixel"] for r in rs if r["per-pixel"]["converged"]]
        row = {"object": key[0], "res": key[1], "texture": key[2], "K": key[3], "smooth": key[4], "n": len(pp),
               "not_converged": len(rs) - len(pp), "params": {}}
        for n in SHAPE:
            err = np.array([(r["params"][n] - TRUTH[n]) / TRUTH[n] for r in pp])
            se = np.array([r["se"][n] / TRUTH[n] for r in pp])
            cov = sum(r["ci95"][n][0] <= TRUTH[n] <= r["ci95"][n][1] for r in pp)
            row["params"][n] = {"bias": float(err.mean()), "bias_se": float(err.std(ddof=1) / math.sqrt(len(err))),
                                "spread": float(err.std(ddof=1)), "se": float(se.mean()),
                                "spread_over_se": float(err.std(ddof=1) / se.mean()), "cover": int(cov),
                                "wilson": wilson(cov, len(pp))}
        mp = [r["maps"] for r in pp if "maps" in r]
        if mp and "R" in mp[0]:      # colour: per channel
            row["maps"] = {c: {k: float(np.mean([m[c][k] for m in mp])) for k in mp[0][c]} for c in mp[0]}
        else:
            row["maps"] = {k: float(np.mean([m[k] for m in mp])) for k in mp[0]} if mp else {}
        extra = [r for r in pp if r.get("chi2_per_dof") is not None]
        row["chi2_per_dof"] = float(np.mean([r["chi2_per_dof"] for r in extra])) if extra else math.nan
        row["misfit"] = int(sum(bool(r.get("misfit")) for r in extra))
        pri = [r["prior"] for r in pp if r.get("prior")]
        row["edf"] = float(np.mean([p["effective_parameters"] for p in pri])) if pri else math.nan
        row["n_albedos"] = float(np.mean([p["parameters"] for p in pri])) if pri else math.nan
        row["relight_per_pixel"] = float(np.mean([r["per-pixel"]["relight"] for r in rs]))
        row["relight_shared"] = float(np.mean([r["shared"]["relight"] for r in rs])) if "shared" in rs[0] else math.nan
        row["time_per_pixel"] = float(np.mean([r["per-pixel"]["time"] for r in rs]))
        row["time_shared"] = float(np.mean([r["shared"]["time"] for r in rs])) if "shared" in rs[0] else math.nan
        row["time_uniform"] = float(np.mean([r["uniform_time"] for r in rs])) if "uniform_time" in rs[0] else math.nan
        rows.append(row)
    return rows


def smooth_text(v):
    """The prior's tau as the table shows it ("none" without a prior)."""
    if v is None:
        return "none"
    return ",".join(f"{float(t):g}" for t in (v if isinstance(v, (list, tuple)) else [v]))


def param_lines(rows, heads, cells):
    """The shape parameters' table: per row of ``rows`` and parameter, the leading cells ``cells(row)`` (under
    the column names ``heads``), then bias ± SE, spread / SE and coverage with its Wilson interval."""
    lines = ["| " + " | ".join(heads + ["parameter", "bias ± SE", "spread / SE", "coverage (Wilson 95 %)"]) + " |",
             "|" + "---|" * (len(heads) + 4)]
    for r in rows:
        for n, p in r["params"].items():
            lo, hi = p["wilson"]
            lines.append("| " + " | ".join(cells(r)) + f" | {n} | {100 * p['bias']:+.2f} ± {100 * p['bias_se']:.2f} % "
                         f"| {p['spread_over_se']:.2f} | {p['cover']}/{r['n']} ({100 * lo:.0f}–{100 * hi:.0f} %) |")
    return lines


def prior_table(rows):
    """The albedo-prior comparison (``--albedo-smooth``): per texture x tau, the shape parameters and the maps."""
    lines = param_lines(rows, ["texture", "tau (k_s, k_b)", "fits"],
                        lambda r: [r["texture"], r["smooth"], f"{r['n']} ({r['not_converged']})"])
    lines += ["", "| texture | tau (k_s, k_b) | maps: RMS z k_s, k_b | maps: 95 % cover k_s, k_b | RMS error k_s, k_b | "
                  "effective albedo parameters / albedos | chi² / dof (misfit flagged) | time |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["maps"]
        edf = "–" if math.isnan(r.get("edf", math.nan)) else f"{r['edf']:.0f} / {r['n_albedos']:.0f}"
        lines.append(f"| {r['texture']} | {r['smooth']} | {m.get('z_rms_k_s', math.nan):.2f}, "
                     f"{m.get('z_rms_k_b', math.nan):.2f} | {100 * m.get('cover_k_s', math.nan):.0f} %, "
                     f"{100 * m.get('cover_k_b', math.nan):.0f} % | {m.get('rms_k_s', math.nan):.4f}, "
                     f"{m.get('rms_k_b', math.nan):.4f} | {edf} | {r.get('chi2_per_dof', math.nan):.3f} "
                     f"({r.get('misfit', 0)}) | {r['time_per_pixel']:.1f} s |")
    return "\n".join(lines)


def table(rows):
    if any(r.get("smooth", "none") != "none" for r in rows):
        return prior_table(rows)
    lines = param_lines(rows, ["object", "size", "texture", "K"],
                        lambda r: [r["object"], f"{r['res']}²", r["texture"], str(r["K"])])
    lines += ["", "| object | size | texture | K | fits (not converged) | maps: RMS z k_s, k_b | maps: 95 % cover k_s, k_b | "
                  "median rel. error k_s, k_b | split identified | relight per-pixel / shared | time per-pixel / "
                  "uniform object (ratio) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["maps"]
        if "R" in m:        # colour: one row per channel
            for c, mc in m.items():
                lines.append(f"| {r['object']} (colour) | {r['res']}² | {r['texture']} ({c}) | {r['K']} | "
                             f"{r['n']} ({r['not_converged']}) | "
                             f"{mc['z_rms_k_s']:.2f}, {mc['z_rms_k_b']:.2f} | {100 * mc['cover_k_s']:.0f} %, "
                             f"{100 * mc['cover_k_b']:.0f} % | {100 * mc['med_rel_k_s']:.1f} %, "
                             f"{100 * mc['med_rel_k_b']:.1f} % | {100 * mc['identified']:.0f} % | "
                             f"{r['relight_per_pixel']:.4f} / {r['relight_shared']:.4f} | "
                             f"{r['time_per_pixel']:.1f} s / {r['time_shared']:.1f} s (shared fit) |")
            continue
        lines.append(f"| {r['object']} | {r['res']}² | {r['texture']} | {r['K']} | {r['n']} ({r['not_converged']}) | {m.get('z_rms_k_s', math.nan):.2f}, "
                     f"{m.get('z_rms_k_b', math.nan):.2f} | {100 * m.get('cover_k_s', math.nan):.0f} %, "
                     f"{100 * m.get('cover_k_b', math.nan):.0f} % | {100 * m.get('med_rel_k_s', math.nan):.1f} %, "
                     f"{100 * m.get('med_rel_k_b', math.nan):.1f} % | {100 * m.get('identified', math.nan):.0f} % | "
                     f"{r['relight_per_pixel']:.4f} / {r['relight_shared']:.4f} | {r['time_per_pixel']:.1f} s / "
                     f"{r['time_uniform']:.1f} s ({r['time_per_pixel'] / r['time_uniform']:.2f}) |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--seeds", type=int, default=16)
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--textures", default="smooth,high")
    p.add_argument("--objects", default="sphere", help="sphere (orthographic) and/or mesh (the blob mesh of "
                   "fmbrdf_mi.synthetic.mesh_object, pinhole camera, fov 20 degrees)")
    p.add_argument("--lights", default="1,3", help="numbers of fitted lights (1 or 3)")
    p.add_argument("--area-points", type=int, default=None,
                   help="the fits' points per raw pixel side (default: the fit's, 2; the data average 4 x 4)")
    p.add_argument("--per-pixel-only", action="store_true", help="skip the shared and uniform-object fits")
    p.add_argument("--intervals", default="fisher", choices=("fisher", "auto"),
                   help="the per-pixel fits' intervals (auto: profile likelihood where the Fisher ones fail)")
    p.add_argument("--sensor", default="mono", choices=("mono", "colour"),
                   help="colour: a colour polarisation mosaic, maps per channel (module docstring)")
    p.add_argument("--albedo-smooth", metavar="TAU[,TAU_B]",
                   help="the per-pixel fits with the albedo maps' smoothness prior (FitOptions.albedo_smooth)")
    p.add_argument("--json", metavar="OUT.json", help="runs and summary, written after every fit (resumed)")
    p.add_argument("--table", metavar="IN.json", nargs="+", help="the table of saved runs (several files: merged)")
    a = p.parse_args(argv)
    if a.table:
        print(table(summarise([r for f in a.table for r in json.load(open(f))["runs"]])))
        return 0
    runs = []
    if a.json and os.path.exists(a.json):
        runs = json.load(open(a.json))["runs"]
    smooth = None
    if a.albedo_smooth:
        vals = [float(v) for v in a.albedo_smooth.split(",")]
        smooth = vals[0] if len(vals) == 1 else tuple(vals)
    st = smooth_text(smooth)
    done = {(r.get("object", "sphere"), r["res"], r["texture"], r["K"], r["seed"], smooth_text(r.get("albedo_smooth")))
            for r in runs}
    t0 = time.time()
    cells = [(obj, tex, int(K)) for obj in a.objects.split(",") for tex in a.textures.split(",")
             for K in a.lights.split(",")]
    if a.sensor == "colour" and smooth is not None:
        raise SystemExit("--albedo-smooth: mono sensor only in this bench")
    if a.sensor == "colour" and any(obj != "sphere" for obj, _, _ in cells):
        raise SystemExit("--sensor colour: the sphere only (--objects sphere)")
    for obj, tex, K in cells:
        for seed in range(a.seed0, a.seed0 + a.seeds):
            if (obj, a.res, tex, K, seed, st) in done:
                continue
            if a.sensor == "colour":
                r = one_colour(tex, K, seed, a.res, a.intervals,
                               ("per-pixel",) if a.per_pixel_only else ("per-pixel", "shared"))
            else:
                r = one(tex, K, seed, a.res, a.area_points,
                        ("per-pixel",) if a.per_pixel_only else ("per-pixel", "shared", "uniform"), a.intervals,
                        obj, smooth)
            r.update(texture=tex, K=K, res=a.res, object=obj, sensor=a.sensor, albedo_smooth=smooth)
            runs.append(r)
            pp = r["per-pixel"]
            print(f"[{time.time() - t0:.0f} s] {obj} {a.res}² {tex} K={K} seed {seed}: "
                  + " ".join(f"{n}={pp['params'][n]:.4g}" for n in SHAPE)
                  + f" ({pp['time']:.1f} s, prior {st})", file=sys.stderr, flush=True)
            if a.json:
                with open(a.json + ".tmp", "w") as f:
                    json.dump({"runs": runs}, f)
                os.replace(a.json + ".tmp", a.json)
    print(table(summarise(runs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
