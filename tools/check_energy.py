"""Largest directional albedo of fmbrdf with k_s = k_b = 1 over a grid of the parameter box.

The albedo int f(L, V) cos(theta_L) d omega_L is integrated with the same
Gauss-Legendre x uniform rule as tests/test_energy.py.  Its excess over 1
comes from the separable Smith masking-shadowing (which ignores the
correlation of masking and shadowing) and from the body term sharing G1(L)G1(V).

    python tools/check_energy.py
"""
import itertools
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))


def main():
    import mitsuba as mi
    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi  # noqa: F401
    from test_energy import albedo

    worst = (0, None)
    for eta, alpha, beta, kappa in itertools.product([1.1, 1.5, 2.5], [0.02, 0.3, 0.8, 1.5], [0.5, 2.0, 4.0], [0.0, 100.0]):
        bsdf = mi.load_dict({"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta, "kappa": kappa,
                             "k_s": 1.0, "k_b": 1.0})
        for tv in [0, 30, 60, 80, 85]:
            a = albedo(mi, bsdf, np.radians(tv))
            if a > worst[0]:
                worst = (a, (eta, alpha, beta, kappa, tv))
        print(f"eta={eta} alpha={alpha} beta={beta} kappa={kappa}: max so far {worst[0]:.4f}", flush=True)
    print(f"\nlargest albedo {worst[0]:.4f} at eta, alpha, beta, kappa, theta_V = {worst[1]}")


if __name__ == "__main__":
    main()
