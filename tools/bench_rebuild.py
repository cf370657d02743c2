"""Cost of a material change against the cost of a render, in one process.

The default sphere of fmbrdf_mi.scene.sphere_scene (fmbrdf, eta 1.5, alpha
0.3, beta 2, kappa 10) at 256 x 256, 16 spp, `stokes` over `direct`,
llvm_ad_spectral_polarized.  After a warm-up (kernels compiled), interleaved
rounds time

* render    mi.render + dr.eval of the image
* eta, alpha, beta, kappa   params[name] = new value; params.update():
            everything a material change costs (validation, the Smith
            table, the body tables, the sampler), one parameter at a time
* AD        the same update with gradients enabled on all four shape
            parameters (what a fit's iteration builds), then reverse mode
            from a scalar of the rendered image back to the four parameters
            (dr.backward through render and table construction)

and prints the best of the rounds (timings on a shared machine vary; the
best is the least disturbed) and the ratio rebuild / render (issue 10's
target: at most 0.5).

    python tools/bench_rebuild.py [--res 256] [--spp 16] [--rounds 10]
"""
import argparse
import os
import platform
import time

import numpy as np

NAMES = ("eta", "alpha", "beta", "kappa")


def cpu_name():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--variant", default="llvm_ad_spectral_polarized")
    args = ap.parse_args()

    import drjit as dr
    import mitsuba as mi
    mi.set_variant(args.variant)
    import fmbrdf_mi
    from fmbrdf_mi import scene as S

    fmbrdf_mi.register()
    print(f"bench_rebuild: {time.strftime('%Y-%m-%d')}, {cpu_name()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}; {args.res}x{args.res}, {args.spp} spp, "
          f"stokes over direct, {args.variant}, mitsuba {mi.__version__}, drjit {dr.__version__}")
    scene = mi.load_dict(S.sphere_scene(resolution=args.res, spp=args.spp))
    params = mi.traverse(scene)
    key = {n: next(k for k in params.keys() if k.endswith("." + n)) for n in NAMES}
    base = {n: float(params[key[n]][0]) for n in NAMES}
    step = {"eta": 0.01, "alpha": 0.005, "beta": 0.02, "kappa": 0.5}

    def timed(f):
        dr.sync_thread()
        t = time.perf_counter()
        f()
        dr.sync_thread()
        return time.perf_counter() - t

    def render():
        dr.eval(mi.render(scene, spp=args.spp, seed=0))

    def change(name, k):
        params[key[name]] = base[name] + step[name] * (k % 2 + 1)
        params.update()

    def ad_round(k):
        for n in NAMES:
            params[key[n]] = mi.Float(base[n] + step[n] * (k % 2 + 1))
            dr.enable_grad(params[key[n]])
        params.update()
        img = mi.render(scene, params, spp=args.spp, seed=0)
        dr.backward(dr.mean(img.array))
        grads = [float(dr.grad(params[key[n]])[0]) for n in NAMES]
        for n in NAMES:
            params[key[n]] = mi.Float(base[n])
        params.update()
        if not np.all(np.isfinite(grads)):
            raise SystemExit(f"non-finite gradient {grads}")

    # warm-up: compile every kernel once
    render()
    for n in NAMES:
        change(n, 0)
    ad_round(0)
    ad_time = []
    times = {k: [] for k in ("render",) + NAMES}
    for k in range(args.rounds):
        times["render"].append(timed(render))
        for n in NAMES:
            times[n].append(timed(lambda: change(n, k)))
        ad_time.append(timed(lambda: ad_round(k)))
    best = {k: min(v) for k, v in times.items()}
    print(f"{'':10s} {'best':>9s} {'median':>9s} {'/ render':>9s}")
    for k, v in times.items():
        print(f"{k:10s} {best[k] * 1e3:7.1f}ms {np.median(v) * 1e3:7.1f}ms {best[k] / best['render']:9.2f}")
    worst = max(best[n] for n in NAMES)
    print(f"rebuild / render: {worst / best['render']:.2f} (slowest parameter, best of {args.rounds} rounds; "
          f"target <= 0.5)")
    print(f"AD round (update with grads on eta, alpha, beta, kappa + render + backward + reset): "
          f"best {min(ad_time) * 1e3:.0f} ms = {min(ad_time) / best['render']:.1f} renders")


if __name__ == "__main__":
    main()
