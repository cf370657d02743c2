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
