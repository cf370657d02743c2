"""The joint normal refinement started from the truth: where does it drift to?

    python tools/check_normal_refine_truth.py [--res 16] [--lights 3] [--lam 0.3,0.03]

The record's `e_refine_normals` object (tools/record_fits.py's own copy of the
mesh object writer, its material and first three lights, seed 3), read back through the authors' layout; the material is fitted jointly on
the ray-cast normals (`normal_GT.npy`), its shape parameters are then set to the
truth, and :func:`fmbrdf_mi.fit.api.normal_joint.refine_joint` runs from the
true normals at each smoothness weight.  A model that represents the data stays
near the truth; one with a model error drifts (printed: the normals' mean and
median angle to the ray-cast ones, the data chi^2 and prior, the material).
Run it at an older commit to compare models (docs/developer.md, 2026-11-26).
"""
import argparse
import os
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

from record_fits import OBJECT_LIGHTS, OBJECT_MATERIAL, OBJECT_POWERS, write_authors_object  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=16)
    p.add_argument("--lights", type=int, default=3)
    p.add_argument("--lam", default="0.3,0.03", help="smoothness weights, comma-separated (default %(default)s)")
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.api.joint import fit_joint
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.fit.api.normal_refine import angular_error_deg
    from fmbrdf_mi.fit.inputs.authors import read_object
    from fmbrdf_mi.fit.inputs.manifest import build_observations

    K = args.lights
    with tempfile.TemporaryDirectory() as tmp:
        gain = write_authors_object(os.path.join(tmp, "o"), OBJECT_MATERIAL, OBJECT_LIGHTS[:K], OBJECT_POWERS[:K],
                                    res=args.res, seed=args.seed)
        specs, _ = read_object(os.path.join(tmp, "o"), conversion_gain=gain, read_noise=2.5)
        obs = build_observations(specs)
    gt = obs[0].normals.copy()
    for o in obs:
        o.normals, o.geometry = gt, None
    res = fit_joint(obs, FitOptions(), progress=False)
    print("joint fit on the ray-cast normals:", {k: round(v, 4) for k, v in res.params.items()})
    start = dict(res.params, **{k: OBJECT_MATERIAL[k] for k in ("eta", "alpha", "beta", "kappa")})
    for lam in (float(v) for v in args.lam.split(",")):
        j = refine_joint(obs, gt.copy(), start, lam=lam, max_iter=20)
        e = angular_error_deg(j.normals, gt, j.mask)
        print(f"lam {lam:g}, from the truth ({int(j.mask.sum())} pixels): normals mean {e.mean():.3f} deg, median "
              f"{np.median(e):.3f}; data chi2 {j.loss_terms['data_chi2']:.1f}, prior {j.loss_terms['prior']:.1f}; "
              + ", ".join(f"{k} {v:.4g}" for k, v in j.params.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
