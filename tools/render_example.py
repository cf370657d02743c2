"""Render a sphere of FMBRDF material under a directional light to a Stokes EXR.

    python tools/render_example.py out/sphere.exr [--spp 64] [--res 256] [--force]

Stokes integrator over `direct`, llvm_ad_spectral_polarized.  The EXR holds
Mitsuba's multichannel film output (S0..S3 per colour channel); the stokes
integrator's frame is x = image right, y = image up.  Also prints the DoLP at
the image centre.  The full `fmbrdf-mi render` command comes with issue #3.
"""
import argparse
import os
import sys
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("output")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--force", action="store_true", help="overwrite an existing output")
    args = ap.parse_args()
    if os.path.exists(args.output) and not args.force:
        sys.exit(f"error: {args.output} exists; pass --force to overwrite it")

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral_polarized")
    import fmbrdf_mi  # noqa: F401  (registers 'fmbrdf')

    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "stokes", "integrator": {"type": "direct"}},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": args.res, "height": args.res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": args.spp}},
        "sphere": {"type": "sphere", "bsdf": {"type": "fmbrdf", "eta": 1.5, "alpha": 0.3, "beta": 2.0,
                                                  "kappa": 10.0, "k_s": 1.0, "r_k": 1.0}},
        "light": {"type": "directional", "direction": [-0.5, -0.3, -1.0], "irradiance": 3.0},
    })
    t = time.time()
    print(f"rendering {args.res}x{args.res} at {args.spp} spp ...", flush=True)
    mi.render(scene)
    bmp = scene.sensors()[0].film().bitmap()
    os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
    bmp.write(args.output)
    import numpy as np
    img = np.asarray(bmp)
    names = [field.name for field in bmp.struct_()]
    print(f"wrote {args.output} ({img.shape[1]}x{img.shape[0]}, {img.shape[2]} channels) in {time.time() - t:.1f} s")
    if names:
        c = img[args.res // 2, args.res // 2]
        s = {n: c[i] for i, n in enumerate(names)}
        if "S0.R" in s:
            dolp = np.hypot(s["S1.R"], s["S2.R"]) / max(s["S0.R"], 1e-12)
            print(f"centre pixel: S0.R = {s['S0.R']:.4f}, DoLP(R) = {dolp:.4f}")


if __name__ == "__main__":
    main()
