"""Scene-level derivative of a render with respect to alpha: reverse-mode AD against central differences.

A sphere of the fmbrdf BSDF under a directional light (the built-in scene,
``stokes`` over ``direct``, monochrome polarised variant); the objective is
the sum of S0 over the image, summed in float64.  ``mi.render`` renders the
gradient pass with its own seed (``seed_grad``; by default one derived from
``seed``, so that primal and gradient samples are decorrelated), so its
reverse-mode derivative is that of the image rendered with the gradient
pass's samples: central differences of renders at ``seed`` differ from it by
Monte Carlo noise of the pixel-area sampling, those at the gradient pass's
seed agree.  Then the body table alone: forward-mode AD of the float32 table
against central differences of the table built in float32 and in float64
(fmbrdf_mi.model.body.body_tables), which shows the float32 round-off that
small steps amplify.

    python tools/check_scene_gradient.py --res 24 --spp 4 16 64 256 --seed 5
"""
import argparse

import numpy as np

MAT = {"eta": 1.5, "alpha": 0.31, "beta": 1.7, "kappa": 20.0, "k_s": 1.0}
LIGHT = [0.4, 0.3, 1.0]
STEPS = (4e-2, 2e-2, 1e-2, 5e-3, 1e-3, 1e-4)


def scene_check(mi, k_b, tables, res, spp, seed, k_s=1.0):
    import drjit as dr

    from fmbrdf_mi import scene as S

    d = S.sphere_scene({**MAT, "k_s": k_s, "k_b": k_b}, light_dir=LIGHT, irradiance=1.0, resolution=res, spp=spp)
    d["sphere"]["bsdf"]["tables"] = tables
    sc = mi.load_dict(d)
    p = mi.traverse(sc)
    key = "sphere.bsdf.alpha"
    mi.render(sc, spp=1)
    names = [f.name for f in sc.sensors()[0].film().bitmap().struct_()]
    ch = names.index("S0.R")

    def s0(img):
        n = img.shape[0] * img.shape[1]
        return dr.gather(mi.Float, img.array, dr.arange(mi.UInt32, n) * img.shape[2] + ch)

    x0 = MAT["alpha"]
    x = mi.Float(x0)
    dr.enable_grad(x)
    p[key] = x
    p.update()
    y = dr.sum(s0(mi.render(sc, p, spp=spp, seed=seed)))
    dr.backward(y)
    ad = float(dr.grad(x)[0])
    seed_grad = int(mi.sample_tea_32(seed, 1)[0])  # what mi.render uses when seed_grad is not given
    fd = {}
    for label, sd in (("primal seed", seed), ("gradient seed", seed_grad)):
        for h in STEPS:
            v = []
            for s in (1, -1):
                p[key] = x0 * (1 + s * h)
                p.update()
                v.append(float(np.sum(np.asarray(s0(mi.render(sc, spp=spp, seed=sd)), dtype=np.float64))))
            fd[label, h] = (v[0] - v[1]) / (2 * h * x0)
    p[key] = x0
    p.update()
    return ad, fd


def table_check():
    import drjit as dr
    from drjit.llvm.ad import Float as F32
    from drjit.llvm.ad import Float64 as F64

    from fmbrdf_mi.model.body import BodyGrid, body_tables
    from fmbrdf_mi.model.distribution import Distribution

    grid = BodyGrid()

    def build(F, a):
        t, f = body_tables(Distribution(F, a, F(MAT["beta"])), F(MAT["eta"]), F(MAT["kappa"]), grid)
        return t.values, f.values

    a = F32(MAT["alpha"])
    dr.enable_grad(a)
    tv, fv = build(F32, a)
    dr.set_grad(a, 1.0)
    dr.forward_to(tv, fv)
    ad = np.concatenate([np.asarray(dr.grad(tv), np.float64), np.asarray(dr.grad(fv), np.float64)])

    def values(F, x):
        return np.concatenate([np.asarray(v, np.float64) for v in build(F, F(x))])

    out = {}
    for h in STEPS:
        for name, F in (("float32", F32), ("float64", F64)):
            x0 = MAT["alpha"]
            fd = (values(F, x0 * (1 + h)) - values(F, x0 * (1 - h))) / (2 * h * x0)
            out[name, h] = float(np.max(np.abs(fd - ad)) / np.max(np.abs(ad)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=24)
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64, 256])
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    import mitsuba as mi

    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi  # noqa: F401  registers the plugin

    print("alpha derivative of sum(S0), relative difference AD / FD - 1 for steps h/alpha = "
          + ", ".join(f"{h:g}" for h in STEPS))
    for spp in args.spp:
        for k_b in (0.0, 1.0):
            for tables in ("float32", "compact"):
                if k_b == 0.0 and tables == "compact":
                    continue  # no body table
                ad, fd = scene_check(mi, k_b, tables, args.res, spp, args.seed)
                row = "; ".join(label + " " + ", ".join(f"{ad / fd[label, h] - 1:+.1e}" for h in STEPS)
                                for label in ("primal seed", "gradient seed"))
                print(f"spp {spp:4d}  k_b {k_b:g}  tables {tables:8s} AD {ad:.5f}   {row}", flush=True)
    spp = args.spp[0]
    ad, fd = scene_check(mi, 1.0, "float32", args.res, spp, args.seed, k_s=0.0)
    print(f"body only (k_s 0), spp {spp}: AD {ad:.3g}; FD at the gradient seed "
          + ", ".join(f"{fd['gradient seed', h]:.3g}" for h in STEPS))
    print("body table alone: max |FD - AD of the float32 table| / max |AD|")
    for (name, h), err in table_check().items():
        print(f"  h/alpha {h:g}  {name} table: {err:.1e}")


if __name__ == "__main__":
    main()
