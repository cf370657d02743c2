"""The paper's mesogeometry experiment: FMBRDF (kappa free, and kappa = 0), Lambert and Oren-Nayar fitted to the
mean intensity of a planar sample against the camera angle (normal, light and view coplanar).

    python tools/mesogeometry.py --csv plane.csv --light-angle 30 -o mesogeometry.png [--json fits.json]
    python tools/mesogeometry.py --synthetic --sigma 0.6 --rho 0.8 --light-angle 30 -o docs/images/mesogeometry.png

CSV: a header row with the columns camera_angle_deg (signed, positive on the light's side) and intensity.
--synthetic: the intensities are rendered by Mitsuba from a plane of the ``orennayar`` BSDF (full form).
The library code is fmbrdf_mi.mesogeometry; the figure is the paper's "ONfitting" one.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--csv", metavar="FILE")
    src.add_argument("--synthetic", action="store_true")
    ap.add_argument("--light-angle", type=float, default=30.0, metavar="DEG")
    ap.add_argument("--sigma", type=float, default=0.6, help="synthetic: Oren-Nayar sigma (radians)")
    ap.add_argument("--rho", type=float, default=0.8, help="synthetic: Oren-Nayar albedo")
    ap.add_argument("--angles", default="-80:80:5", metavar="A:B:STEP", help="synthetic: camera angles (deg)")
    ap.add_argument("-o", "--output", required=True, metavar="PNG")
    ap.add_argument("--json", metavar="FILE", help="also write the fitted parameters and errors")
    ap.add_argument("--force", action="store_true", help="overwrite existing outputs")
    args = ap.parse_args(argv)

    from fmbrdf_mi import mesogeometry as M

    try:
        for p in (args.output, args.json):
            if p and os.path.exists(p) and not args.force:
                raise M.MesoInputError(f"{p} exists; pass --force to overwrite it")
        if args.csv:
            angles, obs = M.read_csv(args.csv)
            source = os.path.basename(args.csv)
        else:
            try:
                a, b, step = (float(x) for x in args.angles.split(":"))
            except ValueError:
                raise M.MesoInputError(f"--angles: expected A:B:STEP in degrees, got {args.angles!r}") from None
            angles = np.arange(a, b + 0.5 * step, step)
            M.check_data(angles, np.ones_like(angles), args.light_angle, where="--angles")
            obs = M.render_oren_nayar_plane(args.sigma, args.rho, args.light_angle, angles)
            source = f"Mitsuba render of an Oren-Nayar plane (sigma {args.sigma:g}, rho {args.rho:g})"
        t = time.time()
        fits = M.run_experiment(angles, obs, args.light_angle, progress=lambda m: print(m, file=sys.stderr))
    except (M.MesoInputError, OSError) as e:
        print(f"mesogeometry: error: {e}", file=sys.stderr)
        return 1
    M.plot(angles, obs, args.light_angle, fits, args.output,
           title=f"{source}; light at {args.light_angle:g}°")
    print(f"{len(angles)} camera angles, light at {args.light_angle:g} deg; fits in {time.time() - t:.0f} s")
    print(f"{'model':<16} {'RMSE/mean':>10}  parameters")
    for name, f in fits.items():
        print(f"{name:<16} {f.rmse:10.4f}  " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                      for k, v in f.params.items()))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"source": source, "light_angle": args.light_angle, "angles": list(map(float, angles)),
                       "intensity": list(map(float, obs)),
                       "fits": {n: {"params": f.params, "rel_rmse": f.rmse} for n, f in fits.items()}}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
