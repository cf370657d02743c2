"""fit-brdf on two synthetic MERL files: one made by FMBRDF (recovery), one it cannot represent (error).

    python tools/check_fit_brdf.py [--samples 50000] [--plot docs/images/fit_brdf_slices.png]

1. FMBRDF with eta 1.55, alpha 0.23, beta 1.7, kappa 15, k_s (0.5, 0.6, 0.7), k_b (0.3, 0.1, 0.05),
   tabulated on the MERL grid by the package's evaluator and written as a MERL binary;
2. Lambert (k_d 0.4, 0.2, 0.1) + GGX (alpha 0.15, Schlick F0 0.04, separable Smith G, k_s 1), in NumPy.
Both are fitted with fit-brdf's defaults (start grid of 320 points searched coarse to fine, 2 starts, log10
error), and the parameters, the log10 RMSE over every usable bin and the time are printed; --plot saves the
slices of 2.
"""
import argparse
import math
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

TRUE = {"eta": 1.55, "alpha": 0.23, "beta": 1.7, "kappa": 15.0, "k_s": [0.5, 0.6, 0.7], "k_b": [0.3, 0.1, 0.05]}


def lambert_ggx(w_in, w_out, kd, ks, a=0.15, f0=0.04):
    h = (w_in + w_out) / np.linalg.norm(w_in + w_out, axis=-1, keepdims=True)
    c = h[..., 2]
    d = a * a / (math.pi * (c * c * (a * a - 1) + 1) ** 2)
    g1 = lambda z: 2 / (1 + np.sqrt(1 + a * a * (1 - z * z) / (z * z)))
    f = f0 + (1 - f0) * (1 - np.sum(w_in * h, -1)) ** 5
    spec = d * g1(w_in[..., 2]) * g1(w_out[..., 2]) * f / (4 * w_in[..., 2] * w_out[..., 2])
    return kd[None, :] / math.pi + ks[None, :] * spec[..., None]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=50_000)
    ap.add_argument("--plot", help="save the slices of the Lambert + GGX fit here")
    args = ap.parse_args()
    from fmbrdf_mi.brdf_fit import merl
    from fmbrdf_mi.brdf_fit.fitting import BRDFFitOptions, fit_brdf, model_brdf
    from fmbrdf_mi.brdf_fit.plots import slice_plot

    th, td, pd = merl.bin_angles()
    w_in, w_out = merl.half_diff_to_dirs(*np.meshgrid(th, td, pd, indexing="ij"))
    ok = (w_in[..., 2] > 0) & (w_out[..., 2] > 0)
    ggx = np.full(merl.DIMS + (3,), np.nan)
    ggx[ok] = lambert_ggx(w_in[ok], w_out[ok], np.array([0.4, 0.2, 0.1]), np.ones(3))
    cases = [("fmbrdf", model_brdf(TRUE)), ("lambert_ggx", ggx)]
    with tempfile.TemporaryDirectory() as tmp:
        for name, table in cases:
            path = merl.write_merl(os.path.join(tmp, name + ".binary"), table)
            data = merl.read_merl(path)
            t = time.time()
            res = fit_brdf(data, BRDFFitOptions(max_samples=args.samples))
            dt = time.time() - t
            p = res.params
            print(f"{name}: eta {p['eta']:.5g}, alpha {p['alpha']:.5g}, beta {p['beta']:.5g}, "
                  f"kappa {p['kappa']:.5g}, k_s {np.round(p['k_s'], 5).tolist()}, k_b {np.round(p['k_b'], 5).tolist()}")
            print(f"  log10 RMSE {res.log_rmse_all:.4g} over {res.n_usable} bins (fitted samples {res.log_rmse:.4g}, "
                  f"per channel {np.round(res.log_rmse_channels, 4).tolist()}); at bound: {res.at_bound or 'none'}; "
                  f"{dt:.1f} s (start grid {res.timings['grid']:.1f} s, {res.history[0].get('points', 320)} points)")
            if name == "fmbrdf":
                for k in ("eta", "alpha", "beta", "kappa"):
                    print(f"  {k}: relative error {(p[k] - TRUE[k]) / TRUE[k]:+.2e}")
            if name == "lambert_ggx" and args.plot:
                slice_plot(data, model_brdf(p), args.plot,
                           title=f"Lambert + GGX (not FMBRDF) fitted by FMBRDF: log10 RMSE {res.log_rmse_all:.3f}")
                print(f"  slices -> {args.plot}")


if __name__ == "__main__":
    main()
