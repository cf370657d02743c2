"""Render speed of fmbrdf against the built-in pplastic, in one run.

The same scene -- the default sphere of fmbrdf_mi.scene.sphere_scene under its
directional light, 512 x 512, 64 spp, `stokes` integrator over `direct`,
llvm_ad_spectral_polarized -- rendered with three BSDFs on the sphere:

* fmbrdf    the default material (eta 1.5, alpha 0.3, beta 2, kappa 10, k_s 1, r_k 1)
* pplastic  Mitsuba's polarised rough plastic (alpha 0.3, int_ior 1.5)
* diffuse   a Lambertian (reflectance 0.5): the cost of everything but the BSDF

Each BSDF runs in its own Python process (so that peak memory is its own) with
its own empty Dr.Jit kernel cache (HOME points at a fresh temporary folder), so
"first" includes tracing and LLVM compilation as on a fresh install; "steady"
is the median of the following renders (same kernel, taken from the cache).
"load" is mi.load_dict (for fmbrdf: building its Smith and body tables).
One render = mi.render(scene, spp=64) with all 16.8 M samples in one launch.

    python tools/bench_render.py [--res 512] [--spp 64] [--repeats 5] [--warm-cache]
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

BSDFS = {
    "fmbrdf": {"type": "fmbrdf", "eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0, "k_s": 1.0, "r_k": 1.0},
    "pplastic": {"type": "pplastic", "alpha": 0.3, "int_ior": 1.5},
    "diffuse": {"type": "diffuse", "reflectance": 0.5},
}


def maxrss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def worker(name, res, spp, repeats, variant):
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    import fmbrdf_mi
    from fmbrdf_mi import scene as S

    fmbrdf_mi.register()
    rss_import = maxrss_mib()
    d = S.sphere_scene(resolution=res, spp=spp)
    d["sphere"]["bsdf"] = BSDFS[name]
    t = time.perf_counter()
    scene = mi.load_dict(d)
    load = time.perf_counter() - t

    def render():
        dr.sync_thread()
        t = time.perf_counter()
        img = mi.render(scene, spp=spp, seed=0)
        dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t, img

    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        first, img = render()
        jit = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    compile_ms = sum(k.get("backend_time", 0.0) + k.get("codegen_time", 0.0) for k in jit)
    cache_hits = sum(bool(k.get("cache_hit")) for k in jit)
    steady = [render()[0] for _ in range(repeats)]
    s0 = float(np.asarray(img)[..., 3].mean())  # S0.R, a sanity check that something was rendered
    return {"bsdf": name, "load_s": load, "first_s": first, "steady_s": float(np.median(steady)),
            "steady_min_s": float(np.min(steady)), "peak_rss_mib": maxrss_mib(),
            "rss_after_import_mib": rss_import, "mean_S0_R": s0,
            "kernels": len(jit), "kernel_cache_hits": cache_hits, "codegen_backend_s": compile_ms / 1e3}


def interleaved(res, spp, repeats, variant):
    """Best render time of each BSDF's scene, all loaded in this process, in interleaved rounds."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    import fmbrdf_mi
    from fmbrdf_mi import scene as S

    fmbrdf_mi.register()
    scenes = {}
    for name, bsdf in BSDFS.items():
        d = S.sphere_scene(resolution=res, spp=spp)
        d["sphere"]["bsdf"] = bsdf
        scenes[name] = mi.load_dict(d)
        dr.eval(mi.render(scenes[name], spp=spp, seed=0))
    best = {name: float("inf") for name in scenes}
    for _ in range(repeats):
        for name, scene in scenes.items():
            dr.sync_thread()
            t = time.perf_counter()
            dr.eval(mi.render(scene, spp=spp, seed=0))
            dr.sync_thread()
            best[name] = min(best[name], time.perf_counter() - t)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--variant", default="llvm_ad_spectral_polarized")
    ap.add_argument("--warm-cache", action="store_true", help="keep the user's Dr.Jit kernel cache")
    ap.add_argument("--worker", choices=sorted(BSDFS), help=argparse.SUPPRESS)
    ap.add_argument("--interleaved", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.res, args.spp, args.repeats, args.variant)))
        return
    if args.interleaved:
        print(json.dumps(interleaved(args.res, args.spp, args.repeats, args.variant)))
        return

    import drjit
    import mitsuba

    from _common import cpu_name

    print(f"bench_render: {time.strftime('%Y-%m-%d')}, {cpu_name()}; {args.res}x{args.res}, {args.spp} spp, "
          f"stokes over direct, {args.variant}, "
          f"mitsuba {mitsuba.__version__}, drjit {drjit.__version__}, {os.cpu_count()} CPU cores, "
          f"load average {os.getloadavg()[0]:.1f}, "
          f"{'warm' if args.warm_cache else 'empty'} kernel cache, {args.repeats} steady repeats")
    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.path.dirname(here) + os.pathsep + env.get("PYTHONPATH", "")
    results = {}
    for name in BSDFS:
        with tempfile.TemporaryDirectory(prefix="bench_render_home_") as home:
            if not args.warm_cache:
                env["HOME"] = home  # Dr.Jit caches kernels in $HOME/.drjit
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", name, "--res", str(args.res),
                   "--spp", str(args.spp), "--repeats", str(args.repeats), "--variant", args.variant]
            p = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if p.returncode != 0:
                sys.exit(f"worker {name} failed:\n{p.stderr}")
            results[name] = json.loads(p.stdout.strip().splitlines()[-1])

    print(f"{'bsdf':9s} {'load':>7s} {'first':>8s} {'steady':>8s} {'(min)':>8s} {'peak RSS':>9s}"
          f"   first render's kernels: compile time, cache hits")
    for name, r in results.items():
        print(f"{name:9s} {r['load_s']:6.2f}s {r['first_s']:7.2f}s {r['steady_s']:7.3f}s "
              f"{r['steady_min_s']:7.3f}s {r['peak_rss_mib']:6.0f} MiB   "
              f"{r['codegen_backend_s']:.2f}s, {r['kernel_cache_hits']}/{r['kernels']}")
    f, p, d = results["fmbrdf"], results["pplastic"], results["diffuse"]
    print(f"separate processes: ratio fmbrdf / pplastic steady {f['steady_s'] / p['steady_s']:.2f}, "
          f"first {f['first_s'] / p['first_s']:.2f}; peak RSS {f['peak_rss_mib'] / p['peak_rss_mib']:.2f}")
    cmd = [sys.executable, os.path.abspath(__file__), "--interleaved", "--res", str(args.res),
           "--spp", str(args.spp), "--repeats", str(args.repeats), "--variant", args.variant]
    q = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if q.returncode != 0:
        sys.exit(f"interleaved run failed:\n{q.stderr}")
    best = json.loads(q.stdout.strip().splitlines()[-1])
    print("interleaved best: " + ", ".join(f"{k} {v:.3f}s" for k, v in best.items())
          + f"; ratio fmbrdf / pplastic {best['fmbrdf'] / best['pplastic']:.2f} (target <= 1.1)")
    print(f"BSDF share of the steady time (render minus the diffuse render): fmbrdf "
          f"{f['steady_s'] - d['steady_s']:.3f}s, pplastic {p['steady_s'] - d['steady_s']:.3f}s")


if __name__ == "__main__":
    main()
