"""Dataset generation speed: samples per second at 256 x 256, 16 spp.

Renders the first N samples of scenes/dataset_example.toml (spheres, cubes and
cylinders with random rotations, camera poses, lights, materials and RGB body
colours; llvm_ad_spectral_polarized) into a temporary directory with
fmbrdf_mi.dataset.generate, twice:

* "varied":  the example as it is: every sample has its own eta, alpha, beta,
             kappa, so every sample rebuilds the BSDF's tables;
* "fixed":   the same with eta, alpha, beta, kappa held constant (colours,
             k_s, shapes, lights, cameras still vary): no table rebuilds.

The rate counts the whole run (scene loads and kernel compilation included;
the Dr.Jit kernel cache is the user's, warm after the first run) and the time
per sample is split into phases: load (scene loads, one per shape and camera
type), update (parameter update: the BSDF's tables), render (mi.render of the
Stokes image), geometry (normals and mask), write (EXR, .npy, .png, .json).

    python tools/bench_dataset.py [--samples 24] [--res 256] [--spp 16] [--only varied|fixed]
"""
import argparse
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def run(name, config, samples):
    from fmbrdf_mi.dataset import generate

    with tempfile.TemporaryDirectory() as d:
        s = generate(config, os.path.join(d, "ds"), samples=samples, progress=False,
                     base_dir=os.path.join(ROOT, "scenes"))
    ph = s["phase_seconds"]
    per = {k: 1000 * v / s["rendered"] for k, v in ph.items()}
    print(f"{name:6s}: {s['rendered']} samples in {s['render_seconds']:.1f} s = "
          f"{s['samples_per_second']:.2f} samples/s  |  per sample: "
          + ", ".join(f"{k} {v:.0f} ms" for k, v in per.items()), flush=True)
    return s


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--only", choices=("varied", "fixed"))
    args = ap.parse_args()

    from fmbrdf_mi.dataset.config import read_config_file

    base = read_config_file(os.path.join(ROOT, "scenes", "dataset_example.toml"))
    base["render"].update(resolution=args.res, spp=args.spp)
    fixed = dict(base, material=dict(base["material"], eta=1.5, alpha=0.3, beta=2.0, kappa=10.0))
    import mitsuba

    print(f"bench_dataset: scenes/dataset_example.toml, first {args.samples} samples, "
          f"{args.res}x{args.res}, {args.spp} spp, {base['render']['variant']}, "
          f"{os.cpu_count()} CPU cores (load average {os.getloadavg()[0]:.1f} before), "
          f"mitsuba {mitsuba.__version__}, {time.strftime('%Y-%m-%d')}", flush=True)
    for name, cfg in (("varied", base), ("fixed", fixed)):
        if args.only in (None, name):
            run(name, cfg, args.samples)


if __name__ == "__main__":
    main()
