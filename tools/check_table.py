"""Interpolation error of the body table alone, against the same quadrature evaluated directly.

The body term is tabulated over (theta_L, theta_V, phi) per material and
interpolated in eval; tests/reference.py and check_accuracy.py measure the
whole error against an independent brute force but are slow.  This script
isolates the table: it evaluates the body quadrature (fmbrdf_mi.model.body.
body_matrices, the code the table is built with) directly at random angles
and compares it with the plugin's table lookup there: relative error of the
intensity, absolute error of the DoLP for unpolarised light, and the largest
error of any Mueller element relative to M00 (what polarised light sees).

    python tools/check_table.py --materials 12 --points 4000 --seed 0 [--full-range]
    python tools/check_table.py --triangulations   # each of the four triangulations, and the one picked
    python tools/check_table.py --materials 0 --forward-grazing   # the box's corners, near grazing, forward
"""
import argparse
import math
import time

import numpy as np

from _common import set_body_grid
from check_accuracy import BOX, full_box, random_materials


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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--materials", type=int, default=12)
    ap.add_argument("--points", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full-range", action="store_true",
                    help="sample the whole valid parameter range instead of the targets' box")
    ap.add_argument("--n-phi", type=int, default=None,
                    help="microfacet node azimuths of the body quadrature (default: the package's)")
    ap.add_argument("--table", type=int, nargs=2, default=None, metavar=("N_THETA", "N_PHI"),
                    help="nodes of the body table (default: the package's)")
    ap.add_argument("--float32", action="store_true",
                    help="read the float32 table instead of the compact (fixed-point) one eval uses")
    ap.add_argument("--forward-grazing", action="store_true",
                    help="every point near grazing and near forward scattering")
    ap.add_argument("--triangulations", action="store_true",
                    help="also the intensity error with each of the four triangulations of the cells "
                         "(interp.orientation), the one the table picked marked *")
    args = ap.parse_args()

    import drjit as dr
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
                                               "kappa": kappa, "tables": tables}), args.n_phi, args.table)

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


if __name__ == "__main__":
    main()
