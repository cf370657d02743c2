"""eval() against the brute-force NumPy reference of the paper's equations.

Tolerances are the accuracy targets (body intensity 0.5 % relative, body DoLP
0.002 absolute, surface 0.1 % of the surface intensity for every Mueller
element).  At the reference resolution used here (96 x 192 nodes, midpoint
rule) the reference itself moves by less than a tenth of those between this
and twice the resolution (tools/check_accuracy.py --ref-convergence).
"""
import numpy as np
import pytest
from _common import directions, dolp, eval_mueller
from conftest import make
from reference import Reference

MATERIALS = [
    (1.5, 0.3, 2.0, 10.0),
    (1.8, 0.05, 1.0, 0.0),
    (2.3, 1.2, 0.7, 80.0),
    (1.2, 0.6, 3.5, 40.0),
]


@pytest.mark.parametrize("mat", MATERIALS)
def test_eval_matches_reference(variant, mat):
    mi = variant
    eta, alpha, beta, kappa = mat
    rng = np.random.default_rng(hash(mat) % 2**32)
    n = 8
    L = directions(rng.uniform(0, 85, n), rng.uniform(-180, 180, n))
    V = directions(rng.uniform(0, 85, n), rng.uniform(-180, 180, n))
    # two pairs near the mirror direction so that the surface lobe is exercised
    V[:2] = L[:2] * [-1, -1, 1] + rng.normal(0, min(alpha, 0.2) / 2, (2, 3))
    V[:2] /= np.linalg.norm(V[:2], axis=1, keepdims=True)
    bsdf = make(mi, eta=eta, alpha=alpha, beta=beta, kappa=kappa)
    Mb, x_in, x_out = eval_mueller(bsdf, L, V, component=1)
    Ms, _, _ = eval_mueller(bsdf, L, V, component=0)
    M, _, _ = eval_mueller(bsdf, L, V)
    pairs = [(L[k], V[k], x_in[k], x_out[k]) for k in range(n)]
    ref = Reference(eta, alpha, beta, kappa, n_s=96, n_phi=192)
    Rb = ref.body(pairs)
    Rs = np.array([ref.surface(*p) for p in pairs])

    np.testing.assert_allclose(Mb[:, 0, 0], Rb[:, 0, 0], rtol=5e-3)
    assert np.max(np.abs(dolp(Mb) - dolp(Rb))) < 2e-3
    # circular rows/columns of the body term vanish (depolariser D_p)
    assert np.all(np.abs(Mb[:, 3, :]) < 1e-6) and np.all(np.abs(Mb[:, :, 3]) < 1e-6)
    sig = Rs[:, 0, 0] > 1e-4
    assert sig.any()
    err = np.abs(Ms - Rs).max(axis=(1, 2))[sig] / Rs[sig, 0, 0]
    assert err.max() < 1e-3
    # the full eval is the sum of both components
    np.testing.assert_allclose(M, Ms + Mb, atol=1e-6 * np.abs(M).max())
