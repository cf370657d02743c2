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
"""
import argparse
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--materials", type=int, default=16)
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--seed", type=int, default=1)
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
    args = ap.parse_args()

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
