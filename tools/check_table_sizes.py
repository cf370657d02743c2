"""Interpolation error of the body table against its resolution, on the same materials and points.

tools/check_table.py measures the plugin's table against the direct quadrature for one resolution;
this script computes the direct quadrature once per material and reads tables of several
resolutions at the same points, so that their errors compare point for point (how much accuracy
a smaller table -- one that fits a cache -- costs).  Materials: the box's 4 corners and
--materials random ones (check_accuracy.random_materials); per material --points random angles
(check_table.random_angles) and --points forward-grazing ones (check_table.forward_grazing_angles).

    python tools/check_table_sizes.py --materials 6 --points 1000 --table 49 81 --table 41 67 --table 33 57
"""
import argparse
import time

import numpy as np

from _common import set_body_grid
from check_accuracy import BOX, random_materials
from check_table import forward_grazing_angles, random_angles


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--materials", type=int, default=6)
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--table", type=int, nargs=2, action="append", default=[], metavar=("N_THETA", "N_PHI"),
                    help="a table resolution (repeatable; default: 49 81)")
    args = ap.parse_args()
    tables = [tuple(t) for t in args.table] or [(49, 81)]

    import mitsuba as mi
    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi  # noqa: F401  (registers the plugin)
    from fmbrdf_mi.model.body_direct import body_matrices

    rng = np.random.default_rng(args.seed)
    worst = {t: [0.0, 0.0, 0.0] for t in tables}
    t0 = time.time()
    for eta, alpha, beta, kappa in random_materials(rng, args.materials, BOX):
        for name, draw in (("random", random_angles), ("forward-grazing", forward_grazing_angles)):
            thL, thV, ph = draw(rng, args.points)
            bsdf = mi.load_dict({"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta, "kappa": kappa})
            direct = np.empty((args.points, 9))
            for s in range(0, args.points, 500):
                sl = slice(s, min(args.points, s + 500))
                Y = body_matrices(bsdf.dist, bsdf.eta, bsdf.kappa, bsdf.grid, thL[sl], thV[sl], ph[sl])
                Y = np.asarray(Y).reshape(Y.shape[0], Y.shape[1], 9)
                k = np.arange(Y.shape[0])
                direct[sl] = Y[k, k]
            coords = (mi.Float(np.cos(thL)), mi.Float(np.cos(thV)), mi.Float(ph))
            line = []
            for t in tables:
                set_body_grid(bsdf, None, t)
                m00, col, sec = bsdf.body_ratios(*coords)
                m00, col, sec = np.asarray(m00), [np.asarray(c) for c in col], [np.asarray(c) for c in sec]
                look = m00[:, None] * np.stack([np.ones_like(m00), sec[0], sec[1], col[0], sec[2], sec[3],
                                                col[1], sec[4], sec[5]], axis=1)
                eI = np.abs(look[:, 0] / direct[:, 0] - 1).max()
                dol = lambda M: np.hypot(M[:, 3], M[:, 6]) / M[:, 0]
                eD = np.abs(dol(look) - dol(direct)).max()
                eM = (np.abs(look - direct).max(axis=1) / direct[:, 0]).max()
                w = worst[t]
                w[0], w[1], w[2] = max(w[0], eI), max(w[1], eD), max(w[2], eM)
                line.append(f"{t[0]}x{t[1]}: I {eI:.2e} DoLP {eD:.2e}")
            print(f"eta={eta:.2f} alpha={alpha:.3f} beta={beta:.2f} kappa={kappa:5.1f} {name:15s} "
                  + " | ".join(line) + f"  ({time.time() - t0:.0f} s)", flush=True)
    print("\nworst over the materials and points (intensity, DoLP, any element / M00):")
    for t in tables:
        kib = t[0] * t[0] * t[1] * 16 / 1024
        print(f"  {t[0]} x {t[0]} x {t[1]} ({kib:.0f} KiB compact): " + ", ".join(f"{x:.2e}" for x in worst[t]))


if __name__ == "__main__":
    main()
