"""sample()/pdf() pass Mitsuba's own chi-square goodness-of-fit test, and the
sample weight equals eval/pdf.

mitsuba.chi2.BSDFAdapter expects an unpolarised sample weight, so the
chi-square test runs in llvm_ad_rgb; sample() and pdf() are the same code in
every variant (only eval's Mueller assembly differs).
"""
import numpy as np
import pytest


@pytest.mark.parametrize("mat,wi", [
    ((1.5, 0.3, 2.0, 10.0), [0.0, 0.0, 1.0]),
    ((1.8, 0.1, 1.0, 0.0), [0.5, 0.0, 0.866]),
    ((1.3, 1.0, 0.7, 50.0), [0.0, 0.8, 0.6]),
    ((2.2, 0.05, 4.0, 5.0), [0.9, 0.0, 0.436]),
])
def test_chi2(mat, wi):
    import mitsuba as mi

    import fmbrdf_mi

    mi.set_variant("llvm_ad_rgb")
    fmbrdf_mi.register()
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    eta, alpha, beta, kappa = mat
    extra = {"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta, "kappa": kappa,
             "k_s": 1.0, "r_k": 0.5}
    wi = np.array(wi) / np.linalg.norm(wi)
    sample_func, pdf_func = BSDFAdapter("fmbrdf", extra, wi=mi.Vector3f(*[float(c) for c in wi]))
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, res=101, ires=8)
    assert chi2.run(), chi2.messages


def test_sample_weight_is_eval_over_pdf(variant):
    mi = variant
    import drjit as dr

    bsdf = mi.load_dict({"type": "fmbrdf", "eta": 1.5, "alpha": 0.3, "k_s": 1.0, "r_k": 1.0})
    n = 1000
    rng = np.random.default_rng(0)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(0.3, 0.2, 0.93)
    si.wi = dr.normalize(si.wi)
    ctx = mi.BSDFContext()
    bs, w = bsdf.sample(ctx, si, mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n)))
    val, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    ok = np.asarray(bs.pdf) > 0
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.asarray(bs.pdf)[ok], np.asarray(pdf)[ok], rtol=1e-4)
    w00 = np.asarray(w[0, 0]).ravel()[ok]
    np.testing.assert_allclose(w00, (np.asarray(val[0, 0]).ravel() / np.asarray(pdf))[ok], rtol=1e-4)
