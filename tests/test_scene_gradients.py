"""Scene-level reverse-mode derivatives through mi.render, and what finite differences must match.

``mi.render(scene, params, seed=s)`` renders the gradient pass with its own
seed (Mitsuba's ``seed_grad``, derived from ``s`` when not given, so that
primal and gradient samples are decorrelated): the derivative it returns is
that of the image rendered with the gradient pass's samples.  Under a
directional light (sampled exactly; the BSDF's parameters move no edge) that
derivative is exact for those samples, with and without the body term:
central differences of renders at the gradient pass's seed agree with it to
float32 round-off, while those at ``s`` differ by the Monte Carlo noise of the
pixel-area sampling.  The body table is rebuilt for every alpha (it is not
interpolated in the parameters), and its reverse/forward-mode derivative is
that of the float32 computation: central differences of the same table built
in float64 agree with it; those of the float32 table carry round-off that
grows as 1 / step (docs/bsdf.md, Gradients).
"""
import numpy as np
import pytest

MAT = {"eta": 1.5, "alpha": 0.31, "beta": 1.7, "kappa": 20.0, "k_s": 1.0}


@pytest.mark.parametrize("k_b", [0.0, 1.0])
def test_render_gradient_is_the_derivative_of_the_gradient_pass_render(variant, k_b):
    mi = variant
    import drjit as dr

    from fmbrdf_mi import scene as S

    d = S.sphere_scene({**MAT, "k_b": k_b}, light_dir=[0.4, 0.3, 1.0], irradiance=1.0, resolution=16, spp=4)
    d["sphere"]["bsdf"]["tables"] = "float32"
    sc = mi.load_dict(d)
    p = mi.traverse(sc)
    key, seed = "sphere.bsdf.alpha", 5

    def s0(img):
        return np.asarray(img, dtype=np.float64)[..., 1]  # channels Y, S0, S1, ... (mono: one each)

    x = mi.Float(MAT["alpha"])
    dr.enable_grad(x)
    p[key] = x
    p.update()
    img = mi.render(sc, p, spp=4, seed=seed)
    names = [f.name for f in sc.sensors()[0].film().bitmap().struct_()]
    assert names[1] == "S0.R", names
    dr.backward(dr.sum(img[..., 1]))
    ad = float(dr.grad(x)[0])
    seed_grad = int(mi.sample_tea_32(seed, 1)[0])  # mi.render's default gradient seed

    def fd(sd, h=1e-2 * MAT["alpha"]):
        v = []
        for s in (1, -1):
            p[key] = MAT["alpha"] + s * h
            p.update()
            v.append(s0(mi.render(sc, spp=4, seed=sd)).sum())
        return (v[0] - v[1]) / (2 * h)

    assert abs(ad) > 0.1
    at_gradient_seed, at_primal_seed = fd(seed_grad), fd(seed)
    # tolerance: the body's part of this derivative is small and strongly curved in alpha, so a central
    # difference carries truncation and the body table's float32 round-off (docs/bsdf.md, Gradients)
    assert ad == pytest.approx(at_gradient_seed, rel=5e-3), (ad, at_gradient_seed, at_primal_seed)
    # the primal's samples are other samples: their derivative differs by sampling noise
    assert abs(at_primal_seed - at_gradient_seed) > 10 * abs(ad - at_gradient_seed)


def test_body_table_derivative_is_that_of_the_float32_computation():
    from check_scene_gradient import table_check   # tools/ (on the path: tests/conftest.py)

    err = table_check()   # max |central difference - AD| / max |AD| over the body tables, per (dtype, relative step)
    assert err["float64", 1e-3] < 1e-4  # the same table in float64: its differences converge to the AD
    assert err["float32", 1e-4] > 1e-3  # float32 round-off over a small step: the differences, not the AD, are off
