"""Unpolarised variants return the intensity part of the polarised Mueller matrix."""
import numpy as np
import pytest
from _common import directions


def _eval(mi, L, V, **kw):
    import drjit as dr

    import fmbrdf_mi

    fmbrdf_mi.register()
    bsdf = mi.load_dict({"type": "fmbrdf", **kw})
    si = dr.zeros(mi.SurfaceInteraction3f, len(L))
    si.wi = mi.Vector3f(np.ascontiguousarray(V.T, dtype=np.float32))
    val = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(np.ascontiguousarray(L.T, dtype=np.float32)))
    return val


@pytest.mark.parametrize("unpolarised", ["llvm_ad_rgb", "llvm_ad_mono"])
def test_unpolarised_is_m00(unpolarised):
    import mitsuba as mi

    rng = np.random.default_rng(2)
    L = directions(rng.uniform(0, 85, 32), rng.uniform(-180, 180, 32))
    V = directions(rng.uniform(0, 85, 32), rng.uniform(-180, 180, 32))
    kw = dict(eta=1.7, alpha=0.25, beta=1.5, kappa=30.0, k_s=0.9, r_k=0.8)
    mi.set_variant("llvm_ad_spectral_polarized")
    pol = np.asarray(_eval(mi, L, V, **kw)[0, 0])[0]
    mi.set_variant(unpolarised)
    unp = np.asarray(_eval(mi, L, V, **kw))[0]
    np.testing.assert_allclose(unp, pol, rtol=1e-5, atol=1e-7)
    mi.set_variant("llvm_ad_mono_polarized")


def _scalar_run(mi, L, V, kw):
    """eval, pdf and a sample, one direction pair at a time (scalar calls)."""
    import drjit as dr

    import fmbrdf_mi

    fmbrdf_mi.register()
    bsdf = mi.load_dict({"type": "fmbrdf", **kw})
    ctx = mi.BSDFContext()
    rows = []
    for k, (l, v) in enumerate(zip(L, V)):
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*map(float, v))
        wo = mi.Vector3f(*map(float, l))
        bs, w = bsdf.sample(ctx, si, (k + 0.5) / len(L), mi.Point2f(0.3, (2 * k + 1) / (2 * len(L))))
        rows.append([np.asarray(bsdf.eval(ctx, si, wo)).ravel()[0], np.asarray(bsdf.pdf(ctx, si, wo)).ravel()[0],
                     *np.asarray(bs.wo).ravel(), np.asarray(w).ravel()[0]])
    return np.array(rows)


def test_scalar_variant_matches_jit():
    """scalar_rgb builds its tables with the LLVM backend and looks them up in
    NumPy: eval, pdf and sample must agree with llvm_ad_rgb call by call."""
    import mitsuba as mi

    rng = np.random.default_rng(5)
    L = directions(rng.uniform(0, 85, 12), rng.uniform(-180, 180, 12))
    V = directions(rng.uniform(0, 85, 12), rng.uniform(-180, 180, 12))
    kw = dict(eta=1.6, alpha=0.2, beta=1.5, kappa=20.0, k_s=0.7, r_k=0.5)
    mi.set_variant("llvm_ad_rgb")
    jit = _scalar_run(mi, L, V, kw)
    mi.set_variant("scalar_rgb")
    try:
        scalar = _scalar_run(mi, L, V, kw)
    finally:
        mi.set_variant("llvm_ad_mono_polarized")
    # float32 (JIT) against float64 (NumPy lookups) arithmetic
    np.testing.assert_allclose(scalar, jit, rtol=2e-5, atol=1e-6)
    assert np.all(jit[:, 0] > 0)
