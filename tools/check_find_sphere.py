"""Error of ``find_sphere`` (``--sphere auto``) over radii and sub-pixel centres.

    python tools/check_find_sphere.py [--radii 3,5,7,10,20,40,80] [--centres 200] [--seed 0]

Masks are discs rasterised as a renderer's coverage mask is: a pixel is in
the mask when its centre lies inside the circle (``sphere_normals``).  For
each radius, ``--centres`` random sub-pixel centres (uniform in a pixel) in a
frame with a margin of 3 pixels; reported: mean radius error ± its standard
error, the largest |radius error| and the largest centre error, in pixels.
Also a sphere cut by the frame (centre 0.3 r inside the left edge).
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def disc(shape, centre, r):
    h, w = shape
    X, Y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return (X - centre[0]) ** 2 + (Y - centre[1]) ** 2 < r * r


def measure(radii, n_centres, seed=0, cut=False):
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


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--radii", default="3,5,7,10,20,40,80")
    p.add_argument("--centres", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    radii = [float(x) for x in a.radii.split(",")]
    for cut in (False, True):
        print(f"\n{'cut by the frame' if cut else 'inside the frame'}: {a.centres} sub-pixel centres per radius")
        print("| radius | mean radius error ± SE | max abs radius error | max centre error |")
        print("|---|---|---|---|")
        for r, m, s, mx, cx in measure(radii, a.centres, a.seed, cut):
            print(f"| {r:g} | {m:+.4f} ± {s:.4f} | {mx:.4f} | {cx:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
