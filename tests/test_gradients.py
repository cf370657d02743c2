"""Reverse-mode AD of eval with respect to each parameter against central differences.

The table depends smoothly on (eta, alpha, beta, kappa) (node positions and
weights are smooth in them), so the derivative of the discretised model is
what AD returns and what the differences approximate.  float32 round-off over
a step h = 1e-2 x value gives ~1e-5 relative noise; truncation O(h^2) is
~1e-4: a 2 % tolerance on a quantity that is not near zero is both safe and
able to catch a wrong or missing derivative.
"""
import numpy as np
import pytest
from conftest import make, make_float32

BASE = {"eta": 1.6, "alpha": 0.4, "beta": 1.7, "kappa": 20.0, "k_s": 0.8, "k_b": 0.6}


def objective(mi, bsdf):
    """A mix of intensity and polarisation terms of eval over a few direction pairs."""
    import drjit as dr

    rng = np.random.default_rng(0)
    n = 16
    th_l, th_v = rng.uniform(0.1, 1.3, n), rng.uniform(0.1, 1.3, n)
    ph_l, ph_v = rng.uniform(-3, 3, n), rng.uniform(-3, 3, n)
    L = np.stack([np.sin(th_l) * np.cos(ph_l), np.sin(th_l) * np.sin(ph_l), np.cos(th_l)])
    V = np.stack([np.sin(th_v) * np.cos(ph_v), np.sin(th_v) * np.sin(ph_v), np.cos(th_v)])
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(V.astype(np.float32))
    M = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(L.astype(np.float32)))
    v = M[0, 0] + 3.0 * M[1, 0] - 2.0 * M[2, 0] + M[1, 1]
    return dr.sum(v[0])  # first (only) wavelength channel


def value_with(mi, name, x):
    """The objective at ``name`` = x, on the float32 tables (conftest.make_float32)."""
    import drjit as dr

    return float(dr.detach(objective(mi, make_float32(mi, **{**BASE, name: x})))[0])


@pytest.mark.parametrize("name", ["eta", "alpha", "beta", "kappa", "k_s", "k_b"])
def test_gradient_matches_central_difference(variant, name):
    mi = variant
    import drjit as dr

    bsdf = make(mi, **BASE)
    params = mi.traverse(bsdf)
    key = name if name in params else f"{name}.value"
    dr.enable_grad(params[key])
    params.update()
    y = objective(mi, bsdf)
    dr.backward(y)
    ad = float(dr.grad(params[key])[0])
    h = 1e-2 * BASE[name]
    fd = (value_with(mi, name, BASE[name] + h) - value_with(mi, name, BASE[name] - h)) / (2 * h)
    assert abs(fd) > 1e-4
    assert ad == pytest.approx(fd, rel=2e-2), (name, ad, fd)
