"""Per-pixel albedos on textures that change within a super-pixel: ``per-pixel`` (one pair per 2 x 2 block)
against ``per-pixel-bilinear`` (the pairs at the super-pixel centres, each raw sample interpolated).

    python tools/bench_textured_bilinear.py --work /tmp/btb [--sizes 64,128] [--seeds 3] [--lights 1,3]
                                            [--exact-res 32] [--exact-seeds 3] [--json out.json]
    python tools/bench_textured_bilinear.py --table out.json[,more.json]
    python tools/bench_textured_bilinear.py --sizes '' --lights 3 --exact-res 128 --exact-kinds continuous \
                                            --layouts per-pixel-bilinear --exact-seeds 6 --seed0 6 --json b.json
    python tools/bench_textured_bilinear.py --sizes 128 --lights 3 --exact-res '' --layouts per-pixel-bilinear \
                                            --render-seeds [--spp 4096] [--seed0 0] --seeds 6 --json own.json
    python tools/bench_textured_bilinear.py --sizes '' --lights 1 --exact-res 32 --exact-kinds uniform \
                                            --layouts per-pixel --exact-seeds 20 --intervals auto --json u.json
    python tools/bench_textured_bilinear.py --table u.json --coverage

``--intervals``: the fits' ``intervals`` option (default fisher; ``auto`` is the command's: profile-likelihood
ends where the Fisher ones fail the check; the record keeps the Fisher ends too).  ``--coverage``: the table of
:func:`coverage_rows` (bias, spread, spread / SE and the coverage of the reported 95 % intervals) instead of
the z table.

``--render-seeds``: each raw seed's images rendered with their own sampler seed (raw seed + 1), so that the
renderer's Monte Carlo noise differs between seeds as the camera's does (by default every raw seed of one
size and light is the same render: its Monte Carlo noise is common to all of them).

Two kinds of data, the `medium` material (eta 1.45, alpha 0.25, beta 1, kappa 10), lights as in
tools/bench_textured.py (K = 1: (-0.5, 0.5, 1); K = 3: that one and two 35 degrees from the view at
azimuths 60 and 300 degrees):

* ``render``: the renderer (``fmbrdf-mi render --raw``, 1024 spp, the built-in orthographic sphere,
  ``--res 2 S`` for an S x S super-pixel grid) with uv textures whose image on the sphere (pole towards the
  camera) is tools/bench_textured.py's ``smooth`` texture over the image (k_s = 0.6 + 0.4 sin(6x) cos(4y),
  k_b = 0.4 + 0.1 cos(5x + 3y), x, y in [0, 1] across the sphere's disc), 4096 x 2048 texels, bilinear;
  raw seeds 0 .. N-1 (``--raw-seed``; the rendered Stokes image is the same for every seed).  Fitted
  with ``fmbrdf_mi.fit.inputs.files.build_observation`` of each OUT_raw.png (its sidecar: the camera, the
  light), every usable pixel, intervals +- 1.96 reported SE (no profile check); the maps against the
  render's OUT_raw_k_*.exr.
* ``exact``: model-exact captures (:func:`fmbrdf_mi.synthetic.spheres.textured_sphere`, 4 x 4 points
  per raw pixel), with the same smooth texture either per super-pixel (``constant``: the four raw pixels
  share the super-pixel's value) or ``continuous`` (each area point its own value), or no texture
  (``uniform``: k_s 0.6, k_b 0.4, which every layout models exactly), camera noise seeds.

Reported per data kind x size x K x layout: for eta, alpha, beta, kappa the mean of (estimate - truth) /
reported SE and the RMS of it (1 when the SEs are right and there is no bias), chi^2/dof, the maps' RMS
of (estimate - truth) / SE for k_s and k_b, and the mean fit time.  The renders are made with
DRJIT_NUM_THREADS=1 and not pinned with taskset (a textured render under ``taskset -c`` hung in a futex
on this machine); the fits run in this process.
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

TRUTH = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
SHAPE = tuple(TRUTH)
T = math.radians(35.0)
LIGHTS = [(-0.5, 0.5, 1.0)] + [(math.sin(T) * math.cos(math.radians(a)), math.sin(T) * math.sin(math.radians(a)),
                                math.cos(T)) for a in (60.0, 300.0)]
LAYOUTS = ("per-pixel", "per-pixel-bilinear")


def smooth(x, y):
    """bench_textured's smooth texture at x, y in [0, 1]: (k_s, k_b)."""
    return 0.6 + 0.4 * np.sin(6 * x) * np.cos(4 * y), 0.4 + 0.1 * np.cos(5 * x + 3 * y)


def textures(work):
    """The uv textures (the sphere's pole faces the camera: u the azimuth, v in [0, 0.5] the visible half)."""
    from fmbrdf_mi.stokes_io import write_map_exr

    paths = [os.path.join(work, "ks.exr"), os.path.join(work, "kb.exr")]
    if all(os.path.exists(p) for p in paths):
        return paths
    W, H = 4096, 2048
    U, V = np.meshgrid((np.arange(W) + 0.5) / W, (np.arange(H) + 0.5) / H)
    rho = np.sin(np.pi * np.minimum(V, 0.5))
    ks, kb = smooth((1 + rho * np.cos(2 * np.pi * U)) / 2, (1 + rho * np.sin(2 * np.pi * U)) / 2)
    for p, m in zip(paths, (ks, kb)):
        write_map_exr(p, m, force=True)
    return paths


def render(work, size, j, seed, sampler_seed=0, spp=None):
    """OUT_raw.png of light j at an S x S super-pixel grid, raw seed ``seed`` (rendered once per seed), the
    renderer's sampler seed ``sampler_seed`` and ``spp`` samples per pixel (None: render --raw's 1024)."""
    ks, kb = textures(work)
    tag = (f"_m{sampler_seed}" if sampler_seed else "") + (f"_spp{spp}" if spp else "")
    out = os.path.join(work, f"s{size}_l{j}_r{seed}{tag}.exr")
    if not os.path.exists(out[:-4] + "_raw.png"):
        env = dict(os.environ, DRJIT_NUM_THREADS="1", PYTHONPATH=ROOT)
        cmd = [os.path.join(os.path.dirname(sys.executable), "fmbrdf-mi"), "render", out, "--variant", "llvm_ad_mono_polarized",
               "--res", str(2 * size), "-D", "eta=1.45", "-D", "alpha=0.25", "-D", "beta=1", "-D", "kappa=10",
               "-D", f"k_s={ks}", "-D", f"k_b={kb}", "-D", "light_dir=" + ",".join(f"{v:.7f}" for v in LIGHTS[j]),
               "--raw", "--raw-seed", str(seed), "--no-previews", "--force", "-q", "--seed", str(sampler_seed)]
        cmd += ["--spp", str(spp)] if spp else []
        # the render is not pinned to this process's cores: under an affinity of one core a textured render
        # hung in a futex (mitsuba 3.9.1 on the 2-core bench machine); DRJIT_NUM_THREADS=1 keeps it to one thread
        subprocess.run(cmd, check=True, env=env,
                       preexec_fn=lambda: os.sched_setaffinity(0, range(os.cpu_count() or 1)))
    return out[:-4] + "_raw.png", out[:-4] + "_raw_k_s.exr", out[:-4] + "_raw_k_b.exr"


def read_map(path):
    import OpenEXR

    with OpenEXR.File(path, separate_channels=True) as f:
        return np.asarray(f.channels()["Y"].pixels, dtype=np.float64)


def exact_data(kind, res, K, seed):
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere
    from fmbrdf_mi.sensor.camera import CameraModel

    fks = (lambda x, y: smooth((x + 0.5) / res, (y + 0.5) / res)[0])   # super-pixel (i, j) centre: x = j
    fkb = (lambda x, y: smooth((x + 0.5) / res, (y + 0.5) / res)[1])
    if kind == "uniform":           # no texture: every layout's model is exact
        fks, fkb = (lambda x, y: 0.6 + 0.0 * x), (lambda x, y: 0.4 + 0.0 * x)
    C, R = np.meshgrid(np.arange(res) * 1.0, np.arange(res) * 1.0)
    obs = []
    for j in range(K):
        ideal = (textured_sphere(TRUTH, fks, fkb, res=res, light=LIGHTS[j]) if kind != "constant" else
                 textured_sphere(TRUTH, fks(C, R), fkb(C, R), res=res, light=LIGHTS[j]))
        o, _ = capture_observation(ideal, CameraModel(), seed=1000 * seed + j,
                                   exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
    return obs, ideal["k_s_map"], ideal["k_b_map"]


def one_fit(obs, layout, ks, kb, intervals="fisher"):
    from fmbrdf_mi.fit import fit

    t = time.time()
    r = fit(obs if len(obs) > 1 else obs[0], albedo=layout, max_pixels=None, intervals=intervals, progress=False)
    dt = time.time() - t
    m = r.maps
    f = np.isfinite(m["k_s"]) & np.isfinite(m["k_s_se"]) & np.isfinite(m["k_b_se"]) & (m["k_b_se"] > 0)
    zs = (m["k_s"][f] - ks[f]) / m["k_s_se"][f]
    zb = (m["k_b"][f] - kb[f]) / m["k_b_se"][f]
    return {"time": dt, "converged": bool(r.converged), "params": r.params, "se": r.std_errors,
            "chi2_per_dof": (r.uncertainty or {}).get("chi2_per_dof"), "pixels": int(f.sum()),
            "z_rms_k_s": float(np.sqrt(np.mean(zs ** 2))), "z_rms_k_b": float(np.sqrt(np.mean(zb ** 2))),
            "at_bound": list((r.uncertainty or {}).get("at_bound", [])),
            "ci95": {n: (r.uncertainty or {}).get("ci95", {}).get(n) for n in SHAPE},
            "ci95_fisher": {n: ((r.uncertainty or {}).get("profile", {}).get("fisher_ci95")
                                or (r.uncertainty or {}).get("ci95", {})).get(n) for n in SHAPE},
            "interval_kind": (r.uncertainty or {}).get("interval_kind"), "intervals": intervals}


def summarise(runs):
    rows = []
    for key in sorted({(r["data"], r["size"], r["K"], r["layout"]) for r in runs}):
        rs = [r for r in runs if (r["data"], r["size"], r["K"], r["layout"]) == key]
        row = dict(zip(("data", "size", "K", "layout"), key), n=len(rs),
                   converged=sum(r["converged"] for r in rs))
        for n in SHAPE:
            z = np.array([(r["params"][n] - TRUTH[n]) / r["se"][n] if r["se"].get(n) else np.nan for r in rs])
            row[n] = (float(np.nanmean(z)), float(np.sqrt(np.nanmean(z ** 2))))
        for k in ("chi2_per_dof", "z_rms_k_s", "z_rms_k_b", "time"):
            row[k] = float(np.mean([r[k] for r in rs]))
        row["at_bound"] = sum(bool(r["at_bound"]) for r in rs)
        rows.append(row)
    return rows


def table(rows):
    lines = ["| data | size | K | layout | fits (at a bound) | η z: mean, RMS | α z | β z | κ z | χ²/dof | "
             "maps RMS z k_s, k_b | time |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['data']} | {r['size']}² | {r['K']} | {r['layout']} | {r['n']} ({r['at_bound']}) | "
                     + " | ".join(f"{r[n][0]:+.1f}, {r[n][1]:.1f}" for n in SHAPE)
                     + f" | {r['chi2_per_dof']:.3f} | {r['z_rms_k_s']:.2f}, {r['z_rms_k_b']:.2f} | {r['time']:.0f} s |")
    return "\n".join(lines)


def coverage_rows(runs):
    """Per data x size x K x layout x intervals and shape parameter: the mean relative error +- its standard
    error, the spread (SD of the relative error), the mean reported relative SE, spread / SE, the mean z (error /
    the fit's own SE), the coverage of the reported 95 % intervals with its Wilson interval, and that of the
    Fisher intervals alone (the same where no end was profiled) with the number of fits profiled."""
    from bench_fit_noise import wilson

    rows = []
    key_of = (lambda r: (r["data"], r["size"], r["K"], r["layout"], r.get("intervals", "fisher")))
    for key in sorted({key_of(r) for r in runs}):
        rs = [r for r in runs if key_of(r) == key and r["converged"] and r.get("ci95")]
        for n in SHAPE:
            use = [r for r in rs if r["se"].get(n) and r["ci95"].get(n)]
            e = np.array([(r["params"][n] - TRUTH[n]) / TRUTH[n] for r in use])
            se = np.array([r["se"][n] / TRUTH[n] for r in use])
            k = sum(r["ci95"][n][0] <= TRUTH[n] <= r["ci95"][n][1] for r in use)
            kf = sum(c[0] <= TRUTH[n] <= c[1] for c in ((r.get("ci95_fisher") or r["ci95"])[n] for r in use))
            m = len(use)
            sd = float(e.std(ddof=1)) if m > 1 else math.nan
            rows.append(dict(zip(("data", "size", "K", "layout", "intervals"), key), param=n, n=m,
                             not_converged=sum(not r["converged"] for r in runs if key_of(r) == key),
                             bias=float(e.mean()) if m else math.nan, bias_se=sd / math.sqrt(m) if m else math.nan,
                             spread=sd, se=float(se.mean()) if m else math.nan,
                             ratio=sd / float(se.mean()) if m else math.nan,
                             z=float(np.mean(e / se)) if m else math.nan, covered=int(k),
                             wilson=wilson(int(k), m), covered_fisher=int(kf),
                             profiled=sum("profile" in (r.get("interval_kind") or {}).get(n, "") for r in use)))
    return rows


def coverage_table(rows):
    lines = ["| data | size | K | layout | intervals | param | fits (NC) | bias ± SE | spread | mean SE | spread / SE | "
             "mean z | 95 % coverage (Wilson) | Fisher only (fits profiled) |", "|" + "---|" * 14]
    for r in rows:
        lo, hi = r["wilson"]
        lines.append(f"| {r['data']} | {r['size']}² | {r['K']} | {r['layout']} | {r['intervals']} | {r['param']} | "
                     f"{r['n']} ({r['not_converged']}) | {100 * r['bias']:+.2f} ± {100 * r['bias_se']:.2f} % | "
                     f"{100 * r['spread']:.2f} % | {100 * r['se']:.2f} % | {r['ratio']:.2f} | {r['z']:+.2f} | "
                     f"{r['covered']}/{r['n']} ({100 * lo:.0f}–{100 * hi:.0f} %) | {r['covered_fisher']}/{r['n']} ({r['profiled']}) |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="/tmp/bench_textured_bilinear", help="renders go here (reused)")
    p.add_argument("--sizes", default="64,128", help="render super-pixel grids (empty: none)")
    p.add_argument("--seeds", type=int, default=3, help="raw seeds per render")
    p.add_argument("--lights", default="3,1")
    p.add_argument("--exact-res", default="32", help="model-exact data's grids (empty: none)")
    p.add_argument("--exact-seeds", type=int, default=3)
    p.add_argument("--exact-kinds", default="continuous,constant", help="the model-exact data's kinds")
    p.add_argument("--seed0", type=int, default=0, help="first seed (raw seed; camera-noise seed of exact data)")
    p.add_argument("--render-seeds", action="store_true",
                   help="render each raw seed with its own sampler seed (its own Monte Carlo noise; default: "
                        "every raw seed of one size and light shares one render)")
    p.add_argument("--spp", type=int, help="samples per pixel of the renders (default: render --raw's 1024)")
    p.add_argument("--layouts", default=",".join(LAYOUTS), help="the layouts fitted")
    p.add_argument("--intervals", default="fisher", choices=("fisher", "auto", "profile"),
                   help="the fits' intervals option (default %(default)s; auto: the command's, the profile "
                        "likelihood where the Fisher ones fail)")
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--table", metavar="IN.json[,IN2.json...]", help="print the table of these runs (merged)")
    p.add_argument("--coverage", action="store_true",
                   help="the table: bias, spread and coverage of the reported 95 %% intervals (coverage_rows)")
    a = p.parse_args(argv)
    show = (lambda runs: coverage_table(coverage_rows(runs))) if a.coverage else (lambda runs: table(summarise(runs)))
    layouts = [L for L in a.layouts.split(",") if L]
    if any(L not in LAYOUTS for L in layouts):
        p.error(f"--layouts: expected some of {', '.join(LAYOUTS)}")
    if any(k not in ("continuous", "constant", "uniform") for k in a.exact_kinds.split(",") if k):
        p.error("--exact-kinds: expected some of continuous, constant, uniform")
    data_name = "render" + (" (own MC seed)" if a.render_seeds else "") + (f" {a.spp} spp" if a.spp else "")
    if a.table:
        print(show([r for f in a.table.split(",") for r in json.load(open(f))["runs"]]))
        return 0
    os.makedirs(a.work, exist_ok=True)
    runs = json.load(open(a.json))["runs"] if a.json and os.path.exists(a.json) else []
    done = {(r["data"], r["size"], r["K"], r["seed"], r["layout"]) for r in runs
            if r.get("intervals", "fisher") == a.intervals}
    t0 = time.time()

    def record(rec):
        runs.append(rec)
        print(f"[{time.time() - t0:.0f} s] {rec['data']} {rec['size']} K={rec['K']} seed {rec['seed']} "
              f"{rec['layout']}: " + " ".join(f"{n}={rec['params'][n]:.4g}" for n in SHAPE)
              + f" chi2/dof={rec['chi2_per_dof']:.3f} ({rec['time']:.0f} s)", file=sys.stderr, flush=True)
        if a.json:
            with open(a.json + ".tmp", "w") as f:
                json.dump({"runs": runs}, f)
            os.replace(a.json + ".tmp", a.json)

    for K in (int(k) for k in a.lights.split(",")):
        for res in [int(s) for s in a.exact_res.split(",") if s]:
            for kind in [k for k in a.exact_kinds.split(",") if k]:
                for seed in range(a.seed0, a.seed0 + a.exact_seeds):
                    todo = [L for L in layouts if (f"exact-{kind}", res, K, seed, L) not in done]
                    if todo:
                        obs, ks, kb = exact_data(kind, res, K, seed)
                        for L in todo:
                            record(dict(one_fit(obs, L, ks, kb, a.intervals), data=f"exact-{kind}", size=res, K=K, seed=seed,
                                        layout=L))
        for size in [int(s) for s in a.sizes.split(",") if s]:
            for seed in range(a.seed0, a.seed0 + a.seeds):
                todo = [L for L in layouts if (data_name, size, K, seed, L) not in done]
                if not todo:
                    continue
                from fmbrdf_mi.fit.inputs.files import build_observation

                files = [render(a.work, size, j, seed, seed + 1 if a.render_seeds else 0, a.spp) for j in range(K)]
                obs = [build_observation(f[0]) for f in files]
                ks, kb = read_map(files[0][1]), read_map(files[0][2])
                for L in todo:
                    record(dict(one_fit(obs, L, ks, kb, a.intervals), data=data_name, size=size, K=K, seed=seed, layout=L))
    print(show(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
