"""Accuracy of the fmbrdf BSDF against the brute-force NumPy reference (tests/reference.py).

Draws random materials from the box eta in [1.1, 2.5], alpha in [0.02, 1.5],
beta in [0.5, 4], kappa in [0, 100] and random light/view directions up to
85 degrees from the normal, and prints the worst body-intensity relative
error, body-DoLP absolute error and surface relative error (largest Mueller
element error / surface intensity).

    python tools/check_accuracy.py --materials 24 --pairs 16 --seed 1
    python tools/check_accuracy.py --ref-convergence   # how converged the reference is
    python tools/check_accuracy.py --full-range        # the whole valid range, not the box
    python tools/check_accuracy.py --forward-grazing   # only pairs near grazing, in forward scattering

``--table-only`` isolates the body table's interpolation error, fast: it evaluates the body quadrature
(fmbrdf_mi.model.body_direct.body_matrices, the code the table is built with) directly at random angles
and compares it with the plugin's table lookup there: relative error of the intensity, absolute error of
the DoLP for unpolarised light, and the largest error of any Mueller element relative to M00 (what
polarised light sees).  Its defaults: 12 materials, seed 0.

    python tools/check_accuracy.py --table-only --materials 12 --points 4000 [--full-range]
    python tools/check_accuracy.py --table-only --triangulations   # each of the four triangulations, the one picked
    python tools/check_accuracy.py --table-only --materials 0 --forward-grazing   # the box's corners

``--find-sphere`` measures the error of ``find_sphere`` (``--sphere auto``) over radii and sub-pixel centres
instead.  Masks are discs rasterised as a renderer's coverage mask is: a pixel is in the mask when its centre
lies inside the circle (``sphere_normals``).  For each radius, ``--centres`` random sub-pixel centres (uniform
in a pixel) in a frame with a margin of 3 pixels, and a sphere cut by the frame (centre 0.3 r inside the left
edge); reported: mean radius error ± its standard error, the largest |radius error| and the largest centre
error, in pixels.  Its default seed: 0.

    python tools/check_accuracy.py --find-sphere [--radii 3,5,7,10,20,40,80] [--centres 200]
"""
import argparse
import math
import time

import numpy as np

from _common import directions, dolp, eval_mueller, set_body_grid

#: The parameter box of the accuracy targets (docs/benchmarks/accuracy.md).
BOX = {"eta": (1.1, 2.5), "alpha": (0.02, 1.5), "beta": (0.5, 4.0), "kappa": (0.0, 100.0)}


def full_box():
    """The whole valid parameter range of fmbrdf_mi.params (eta's open end at 1.01)."""
    from fmbrdf_mi.params import SCALAR_PARAMS
    return {k: (max(lo, 1.01) if k == "eta" else lo, hi) for k, (_, lo, hi, _, _) in SCALAR_PARAMS.items()}


def random_materials(rng, n, box=BOX):
    mats = [tuple(rng.uniform(*box[k]) for k in box) for _ in range(n)]
    # corners of the box, where quadrature and tables are hardest
    (e0, e1), (a0, a1), (b0, b1), (k0, k1) = (box[k] for k in ("eta", "alpha", "beta", "kappa"))
    corners = [(e0, a0, b1, k1), (e1, a1, b0, k1), (e1, a0, b0, k0), (e0, a1, b1, k0)]
    return corners + mats


def random_pairs(rng, n, alpha):
    """Direction pairs: half uniform in angles, a quarter near the mirror
    configuration (where the surface lobe is), a quarter near backscatter
    (where a large kappa makes the body lobe sharp)."""
    thL, phL = rng.uniform(0, 85, n), rng.uniform(-180, 180, n)
    thV, phV = rng.uniform(0, 85, n), rng.uniform(-180, 180, n)
    q = n // 4
    spread = np.degrees(min(alpha, 0.3))
    thV[n - 2 * q:n - q] = np.clip(thL[n - 2 * q:n - q] + rng.normal(0, spread, q), 0, 85)
    phV[n - 2 * q:n - q] = phL[n - 2 * q:n - q] + 180 + rng.normal(0, spread, q)
    thV[n - q:] = np.clip(thL[n - q:] + rng.normal(0, 5, q), 0, 85)
    phV[n - q:] = phL[n - q:] + rng.normal(0, 5, q)
    return directions(thL, phL), directions(thV, phV)


def forward_grazing_pairs(rng, n):
    """Direction pairs with theta_L, theta_V in [75, 85] deg and phi_V - phi_L within
    20 deg of 180: where a large kappa makes the body term vary fastest in phi
    (the corner that random_pairs rarely samples)."""
    thL, thV = rng.uniform(75, 85, n), rng.uniform(75, 85, n)
    phL = rng.uniform(-180, 180, n)
    phV = phL + rng.uniform(160, 180, n) * rng.choice([-1.0, 1.0], n)
    return directions(thL, phL), directions(thV, phV)


def random_angles(rng, n):
    """theta_L, theta_V up to 85 deg, phi in [0, pi]; a quarter near backscatter
    (phi ~ 0, theta_V ~ theta_L), a quarter near the grazing view."""
    thL = np.radians(rng.uniform(0, 85, n))
    thV = np.radians(rng.uniform(0, 85, n))
    ph = rng.uniform(0, math.pi, n)
    q = n // 4
    thV[:q] = np.clip(thL[:q] + np.radians(rng.normal(0, 4, q)), 0, np.radians(85))
    ph[:q] = np.abs(np.radians(rng.normal(0, 6, q)))
    thV[q:2 * q] = np.radians(rng.uniform(75, 85, q))
    return thL, thV, ph


def forward_grazing_angles(rng, n):
    """theta_L, theta_V in [75, 85] deg and phi in [160, 180] deg: the corner
    where a large kappa makes the body term vary fastest in phi."""
    return (np.radians(rng.uniform(75, 85, n)), np.radians(rng.uniform(75, 85, n)),
            np.radians(rng.uniform(160, 180, n)))


def table_check(args):
    """``--table-only``: the body table against the same quadrature evaluated directly (module docstring)."""
    import mitsuba as mi
    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi  # noqa: F401
    from fmbrdf_mi.model.body_direct import body_matrices

    rng = np.random.default_rng(args.seed)
    worst = {"I": (0.0, None), "dolp": (0.0, None), "M": (0.0, None)}
    t0 = time.time()
    for eta, alpha, beta, kappa in random_materials(rng, args.materials, full_box() if args.full_range else BOX):
        def build(tables):
            return set_body_grid(mi.load_dict({"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta,
                                               "kappa": kappa, "tables": tables}), args.n_phi, args.table_nodes)

        bsdf = build("float32" if args.float32 else "compact")
        thL, thV, ph = (forward_grazing_angles if args.forward_grazing else random_angles)(rng, args.points)
        # direct quadrature, one light angle per point (diagonal of the (n_L, n_V) product)
        n = args.points
        direct = np.empty((n, 9))
        for s in range(0, n, 500):
            sl = slice(s, min(n, s + 500))
            Y = body_matrices(bsdf.dist, bsdf.eta, bsdf.kappa, bsdf.grid, thL[sl], thV[sl], ph[sl])
            Y = np.asarray(Y).reshape(Y.shape[0], Y.shape[1], 9)
            k = np.arange(Y.shape[0])
            direct[sl] = Y[k, k]
        coords = (mi.Float(np.cos(thL)), mi.Float(np.cos(thV)), mi.Float(ph))
        line = ""
        if args.triangulations:
            from fmbrdf_mi.model.interp import orientation
            picked = bsdf.table.orient
            # the estimated sums of squared errors, from the float32 table (the packed one holds bits)
            _, cost = orientation((bsdf if args.float32 else build("float32")).table, costs=True)
            cost = [float(c[0]) for c in cost]
            for p in range(4):
                bsdf.table.orient = mi.UInt32(p)
                e = np.abs(np.asarray(bsdf.body_ratios(*coords)[0]) / direct[:, 0] - 1)
                line += f"{'*' if p == picked[0] else ' '}{p}: {e.max():.2e} (cost {cost[p]:.2f}) "
            bsdf.table.orient = picked
        m00, col, sec = bsdf.body_ratios(*coords)
        m00, col, sec = np.asarray(m00), [np.asarray(c) for c in col], [np.asarray(c) for c in sec]
        # M00, (M10, M20) and (M01, M02, M11, M12, M21, M22) over M00 -> row-major 3x3
        look = m00[:, None] * np.stack([np.ones_like(m00), sec[0], sec[1], col[0], sec[2], sec[3],
                                        col[1], sec[4], sec[5]], axis=1)
        eM = np.abs(look - direct).max(axis=1) / direct[:, 0]
        eI = np.abs(look[:, 0] / direct[:, 0] - 1)
        dol = lambda M: np.hypot(M[:, 3], M[:, 6]) / M[:, 0]
        eD = np.abs(dol(look) - dol(direct))
        for key, e in (("I", eI), ("dolp", eD), ("M", eM)):
            k = int(np.argmax(e))
            if e[k] > worst[key][0]:
                worst[key] = (e[k], (eta, alpha, beta, kappa, *np.degrees([thL[k], thV[k], ph[k]])))
        print(f"eta={eta:.2f} alpha={alpha:.3f} beta={beta:.2f} kappa={kappa:5.1f}: "
              f"I max {eI.max():.2e} p99 {np.quantile(eI, 0.99):.2e} | DoLP max {eD.max():.2e} "
              f"p99 {np.quantile(eD, 0.99):.2e} | M {eM.max():.2e}  ({time.time() - t0:.0f} s)", flush=True)
        if line:
            print("    I max by triangulation " + line, flush=True)
    for key, (e, where) in worst.items():
        print(f"worst {key:4s} {e:.2e} at eta={where[0]:.2f} alpha={where[1]:.3f} beta={where[2]:.2f} "
              f"kappa={where[3]:.1f} theta_L={where[4]:.1f} theta_V={where[5]:.1f} phi={where[6]:.1f}")


def disc(shape, centre, r):
    """The mask of the pixels whose centre lies inside the circle (centre, r)."""
    h, w = shape
    X, Y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return (X - centre[0]) ** 2 + (Y - centre[1]) ** 2 < r * r


def find_sphere_errors(radii, n_centres, seed=0, cut=False):
    """Per radius: (r, mean radius error, its SE, max |radius error|, max centre error) of ``find_sphere``."""
    from fmbrdf_mi.fit.inputs.observations import find_sphere

    rng = np.random.default_rng(seed)
    rows = []
    for r in radii:
        size = int(np.ceil(2 * r)) + 8
        er, ec = [], []
        for _ in range(n_centres):
            c = np.array([size / 2, size / 2]) + rng.uniform(-0.5, 0.5, 2)
            if cut:
                c[0] = 0.7 * r + rng.uniform(-0.5, 0.5)
            (cx, cy), rr = find_sphere(disc((size, size), c, r))
            er.append(rr - r)
            ec.append(np.hypot(cx - c[0], cy - c[1]))
        er, ec = np.array(er), np.array(ec)
        rows.append((r, er.mean(), er.std(ddof=1) / np.sqrt(len(er)), np.abs(er).max(), ec.max()))
    return rows


def find_sphere_check(args):
    radii = [float(x) for x in args.radii.split(",")]
    for cut in (False, True):
        print(f"\n{'cut by the frame' if cut else 'inside the frame'}: {args.centres} sub-pixel centres per radius")
        print("| radius | mean radius error ± SE | max abs radius error | max centre error |")
        print("|---|---|---|---|")
        for r, m, s, mx, cx in find_sphere_errors(radii, args.centres, args.seed, cut):
            print(f"| {r:g} | {m:+.4f} ± {s:.4f} | {mx:.4f} | {cx:.4f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--materials", type=int, default=None, help="random materials besides the box's corners "
                    "(default 16; --table-only 12)")
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--seed", type=int, default=None, help="default 1; --table-only and --find-sphere 0")
    ap.add_argument("--ref-res", type=int, nargs=2, default=(128, 256), metavar=("N_S", "N_PHI"))
    ap.add_argument("--variant", default="llvm_ad_mono_polarized")
    ap.add_argument("--full-range", action="store_true",
                    help="sample the whole valid parameter range instead of the targets' box")
    ap.add_argument("--forward-grazing", action="store_true",
                    help="draw every direction pair near grazing and near forward scattering")
    ap.add_argument("--n-phi", type=int, default=None,
                    help="microfacet node azimuths of the body quadrature (default: the package's)")
    ap.add_argument("--ref-convergence", action="store_true",
                    help="compare the reference at --ref-res with twice that resolution instead")
    ap.add_argument("--table-only", action="store_true",
                    help="the body table's interpolation error alone, against the direct quadrature")
    ap.add_argument("--points", type=int, default=4000, help="--table-only: random angle triples per material")
    ap.add_argument("--table-nodes", type=int, nargs=2, default=None, metavar=("N_THETA", "N_PHI"),
                    help="--table-only: nodes of the body table (default: the package's)")
    ap.add_argument("--float32", action="store_true",
                    help="--table-only: read the float32 table instead of the compact (fixed-point) one eval uses")
    ap.add_argument("--triangulations", action="store_true",
                    help="--table-only: also the intensity error with each of the four triangulations of the "
                         "cells (interp.orientation), the one the table picked marked *")
    ap.add_argument("--find-sphere", action="store_true",
                    help="the error of find_sphere (--sphere auto) on rasterised discs instead")
    ap.add_argument("--radii", default="3,5,7,10,20,40,80", help="--find-sphere: disc radii in pixels")
    ap.add_argument("--centres", type=int, default=200, help="--find-sphere: random sub-pixel centres per radius")
    args = ap.parse_args()
    if args.materials is None:
        args.materials = 12 if args.table_only else 16
    if args.seed is None:
        args.seed = 0 if args.table_only or args.find_sphere else 1
    if args.find_sphere:
        return find_sphere_check(args)
    if args.table_only:
        return table_check(args)

    import mitsuba as mi
    mi.set_variant(args.variant)
    import fmbrdf_mi  # noqa: F401  (registers the plugin)
    from reference import Reference

    rng = np.random.default_rng(args.seed)
    mats = random_materials(rng, args.materials, full_box() if args.full_range else BOX)
    worst = {"body_I": (0, None), "body_dolp": (0, None), "surface": (0, None)}
    t0 = time.time()
    for m, (eta, alpha, beta, kappa) in enumerate(mats):
        L, V = forward_grazing_pairs(rng, args.pairs) if args.forward_grazing else random_pairs(rng, args.pairs, alpha)
        bsdf = mi.load_dict({"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta,
                             "kappa": kappa, "k_s": 1.0, "k_b": 1.0})
        set_body_grid(bsdf, args.n_phi)
        Mb, x_in, x_out = eval_mueller(bsdf, L, V, component=1)
        Ms, _, _ = eval_mueller(bsdf, L, V, component=0)
        pairs = [(L[k], V[k], x_in[k], x_out[k]) for k in range(len(L))]
        ref = Reference(eta, alpha, beta, kappa, *args.ref_res)
        Rb = ref.body(pairs)
        if args.ref_convergence:
            Mb = Reference(eta, alpha, beta, kappa, 2 * args.ref_res[0], 2 * args.ref_res[1]).body(pairs)
            Ms = None
        errs = {"body_I": np.abs(Mb[:, 0, 0] / Rb[:, 0, 0] - 1), "body_dolp": np.abs(dolp(Mb) - dolp(Rb))}
        if Ms is not None:
            Rs = np.array([ref.surface(*p) for p in pairs])
            sig = Rs[:, 0, 0] > 1e-6  # surface term not vanishing (relative error defined)
            e = np.where(sig, np.abs(Ms - Rs).max(axis=(1, 2)) / np.where(sig, Rs[:, 0, 0], 1), 0)
            errs["surface"] = e
        line = []
        for key, e in errs.items():
            k = int(np.argmax(e))
            line.append(f"{key} {e[k]:.2e}")
            if e[k] > worst[key][0]:
                th = lambda v: np.degrees(np.arccos(v[2]))
                dphi = (np.degrees(np.arctan2(V[k, 1], V[k, 0]) - np.arctan2(L[k, 1], L[k, 0]))) % 360
                worst[key] = (e[k], f"eta={eta:.3f} alpha={alpha:.3f} beta={beta:.2f} kappa={kappa:.1f} "
                                    f"theta_L={th(L[k]):.1f} theta_V={th(V[k]):.1f} dphi={dphi:.1f}")
        print(f"[{m + 1}/{len(mats)}] eta={eta:.2f} alpha={alpha:.3f} beta={beta:.2f} kappa={kappa:5.1f}: "
              + ", ".join(line) + f"  ({time.time() - t0:.0f} s)", flush=True)
    print("\nworst case over", len(mats), "materials x", args.pairs, "direction pairs:")
    for key, (e, where) in worst.items():
        if where:
            print(f"  {key:10s} {e:.2e}  at {where}")


if __name__ == "__main__":
    main()
