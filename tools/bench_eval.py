"""Speed of fmbrdf's eval against the built-in pplastic, in one run.

Evaluates both BSDFs on the same 1M random direction pairs in
llvm_ad_spectral_polarized (full Mueller matrices), after a warm-up that
compiles the kernels, and times the rebuild after a parameter change
(mi.traverse + update: the Smith table and the body table).
The two BSDFs are timed in interleaved rounds; each keeps its best.

    python tools/bench_eval.py [--n 1000000] [--repeats 5] [--variant ...] [--grid NT NP] [--decompose]

``--decompose``: where eval's time goes.  The same fmbrdf evaluated with its body-table coordinates
squeezed into a corner of 4 % of each axis (the same arithmetic, every table read from a few texels that
stay in the L1 cache: what eval would cost if no read missed the cache), and with every coordinate at one
point (constants: the compiler then drops the lookup's arithmetic too, so this is about what eval costs
without the body table).  full - cached is the cost of the table reads missing the caches; cached - one
texel the lookup's arithmetic and its gathers from the L1 cache.

``--pixel-evaluator``: instead, the CPU time of one evaluation of the fit's pixel evaluator with the
derivatives in every shape parameter (:meth:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator.parts`) at
``--n`` random normals (4 footprint directions each) in chunks of ``--chunk`` directions, three times at nearby
shapes; reported: the least CPU time (user + system, all threads) of the second and third (the first compiles
the kernels), also as ``--json``'s ``time``, so that ``tools/bench_interleave.py`` compares two checkouts::

    python tools/bench_interleave.py --old ../old --rounds 2 -- tools/bench_eval.py --pixel-evaluator \
        --n 4000000 --chunk 2000000
"""
import argparse
import json
import os
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--variant", default="llvm_ad_spectral_polarized")
    ap.add_argument("--grid", type=int, nargs=2, action="append", default=[],
                    metavar=("NT", "NP"),
                    help="also time fmbrdf with a body table of (NT, NP) nodes "
                         "(repeatable): how eval's cost depends on the tables' size")
    ap.add_argument("--decompose", action="store_true",
                    help="also time fmbrdf with its table reads kept in the L1 cache, and at one point")
    ap.add_argument("--pixel-evaluator", action="store_true", help="time the fit's pixel evaluator instead")
    ap.add_argument("--chunk", type=int, default=2_000_000, help="--pixel-evaluator: directions per chunk")
    ap.add_argument("--json", metavar="OUT.json", help="--pixel-evaluator: the CPU time as {'runs': [{'time': s}]}")
    args = ap.parse_args()
    if args.pixel_evaluator:
        return pixel_evaluator(args)

    import drjit as dr
    import mitsuba as mi
    mi.set_variant(args.variant)
    import fmbrdf_mi  # noqa: F401
    from _common import cpu_name

    print(f"bench_eval: {time.strftime('%Y-%m-%d')}, {cpu_name()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}; {args.variant}, best of {args.repeats} interleaved rounds")

    rng = np.random.default_rng(0)

    def hemi(n):
        v = rng.normal(size=(3, n))
        v /= np.linalg.norm(v, axis=0)
        v[2] = np.abs(v[2])
        return mi.Vector3f(v.astype(np.float32))

    si = dr.zeros(mi.SurfaceInteraction3f, args.n)
    si.wi = hemi(args.n)
    si.wavelengths = mi.Float(550.0) if not mi.is_spectral else mi.UnpolarizedSpectrum(450, 520, 600, 680)
    wo = hemi(args.n)
    dr.eval(si, wo)
    ctx = mi.BSDFContext()

    bsdfs = {
        "fmbrdf": mi.load_dict({"type": "fmbrdf", "eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0,
                                "k_s": 1.0, "r_k": 1.0}),
        "pplastic": mi.load_dict({"type": "pplastic", "alpha": 0.3, "int_ior": 1.5}),
    }
    from fmbrdf_mi.model.body import BodyGrid

    def table_kib(b):
        return sum(dr.width(t.values) * dr.itemsize_v(t.values) for t in (b.table, b.factors)) / 1024

    g = bsdfs["fmbrdf"].grid
    print(f"fmbrdf's tables: {g.table[0]}x{g.table[0]}x{g.table[1]} nodes + {g.n_factor} 1-D factors, "
          f"{table_kib(bsdfs['fmbrdf']):.0f} KiB")
    for nt, nph in args.grid:
        b = mi.load_dict({"type": "fmbrdf", "eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0,
                          "k_s": 1.0, "r_k": 1.0})
        b.grid = BodyGrid(b.grid.n_theta, b.grid.n_phi, (nt, nph), b.grid.n_factor)
        b.parameters_changed(["alpha"])
        bsdfs[f"fmbrdf {nt}x{nt}x{nph} ({table_kib(b):.0f} KiB)"] = b
    cls = type(bsdfs["fmbrdf"])
    coords = {name: cls.table_coords for name in bsdfs}
    if args.decompose:  # the same BSDF, its table coordinates squeezed (traced anew for each)
        full = cls.table_coords

        def cached(self, cos_l, cos_v, phi):
            return tuple(0.5 + 0.04 * (u - 0.5) for u in full(self, cos_l, cos_v, phi))

        def one_point(self, cos_l, cos_v, phi):
            return tuple(0.5 + 0.0 * u for u in full(self, cos_l, cos_v, phi))

        for name, f in (("fmbrdf, reads cached", cached), ("fmbrdf, one texel", one_point)):
            bsdfs[name], coords[name] = bsdfs["fmbrdf"], f
    for name, bsdf in bsdfs.items():
        cls.table_coords = coords[name]
        dr.eval(bsdf.eval(ctx, si, wo))  # compile
    times = {name: np.inf for name in bsdfs}
    for _ in range(args.repeats):  # interleaved rounds: both see the same machine state
        for name, bsdf in bsdfs.items():
            cls.table_coords = coords[name]
            dr.sync_thread()
            t = time.perf_counter()
            dr.eval(bsdf.eval(ctx, si, wo))
            dr.sync_thread()
            times[name] = min(times[name], time.perf_counter() - t)
    for name, best in times.items():
        print(f"{name:20s} eval: {best * 1e3:8.1f} ms for {args.n} pairs = {args.n / best / 1e6:6.2f} M Mueller evals/s"
              f"  (ratio {best / times['pplastic']:.2f})")
    print(f"ratio fmbrdf / pplastic: {times['fmbrdf'] / times['pplastic']:.2f}  (target <= 1.4)")

    cls.table_coords = coords["fmbrdf"]
    params = mi.traverse(bsdfs["fmbrdf"])
    rebuild = []
    for i in range(args.repeats + 1):
        params["alpha"] = 0.3 + 0.01 * (i + 1)
        t = time.perf_counter()
        params.update()
        dr.sync_thread()
        rebuild.append(time.perf_counter() - t)
    print(f"rebuild after a parameter change: first {rebuild[0] * 1e3:.0f} ms, "
          f"then best {min(rebuild[1:]) * 1e3:.0f} ms (Smith table + body table)")


def pixel_evaluator(args):
    """The ``--pixel-evaluator`` bench (module docstring)."""
    from fmbrdf_mi.fit.evaluate import pixel_model as PM
    from fmbrdf_mi.fit.evaluate.models import get_model

    rng = np.random.default_rng(0)
    n = rng.normal(size=(args.n, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1.0
    v = np.array([0.0, 0.0, 1.0]) + 0.1 * rng.normal(size=(args.n, 3))
    model = get_model("fmbrdf")
    PM.PixelEvaluator.CHUNK_DIRECTIONS = args.chunk
    ev = PM.PixelEvaluator(model, n, v, (-0.5, 0.5, 1.0), weights=np.full(4, 0.25))
    shape = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
    cpu = []
    for i in range(3):
        c = time.process_time()
        ev.parts({k: x * (1 + 0.01 * i) for k, x in shape.items()}, wrt=[p.name for p in model.shape])
        cpu.append(time.process_time() - c)
    print(f"pixel evaluator: {min(cpu[1:]):.2f} s CPU per evaluation with derivatives, {args.n} directions in "
          f"chunks of {args.chunk}; {time.strftime('%Y-%m-%d')}, DRJIT_NUM_THREADS="
          f"{os.environ.get('DRJIT_NUM_THREADS', 'default')}, load average {os.getloadavg()[0]:.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"runs": [{"time": min(cpu[1:])}]}, f)


if __name__ == "__main__":
    main()
