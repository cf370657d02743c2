"""Closed-form physical limits (DESIGN.md section 2), independent of the package's code."""
import numpy as np
import pytest
from _common import directions, dolp, eval_mueller
from conftest import fresnel_T, make
from reference import Reference


@pytest.mark.parametrize("eta", [1.3, 1.5, 2.2])
def test_smooth_body_is_fresnel_lambertian(variant, eta):
    """alpha -> 0: body BRDF (k_b/pi) T(theta_L) T(theta_V), DoLP (Tp-Ts)/(Tp+Ts) at theta_V."""
    mi = variant
    bsdf = make(mi, eta=eta, alpha=0.01, beta=2.0, kappa=20.0, k_b=0.7)
    thL = np.array([0, 20, 40, 60, 75, 10, 50])
    thV = np.array([30, 0, 55, 70, 15, 80, 45])
    L, V = directions(thL, np.full(7, 10.0)), directions(thV, np.array([100, 0, -40, 170, 60, -120, 30]))
    Mb, _, _ = eval_mueller(bsdf, L, V, component=1)
    TsL, TpL = fresnel_T(np.radians(thL), eta)
    TsV, TpV = fresnel_T(np.radians(thV), eta)
    expect = 0.7 / np.pi * (TsL + TpL) / 2 * (TsV + TpV) / 2 * np.cos(np.radians(thL))
    # alpha = 0.01 rad still blurs the Fresnel factors: 0.5 % covers it at 80 deg
    np.testing.assert_allclose(Mb[:, 0, 0], expect, rtol=5e-3)
    np.testing.assert_allclose(dolp(Mb), (TpV - TsV) / (TpV + TsV), atol=2e-3)


@pytest.mark.parametrize("theta", [10, 35, 56.3, 70, 85])
def test_specular_dolp_at_mirror(variant, theta):
    """alpha -> 0, mirror configuration: surface DoLP (R_s - R_p)/(R_s + R_p)."""
    mi = variant
    eta = 1.5
    bsdf = make(mi, eta=eta, alpha=0.02, beta=2.0)
    L = directions(np.array([theta]), np.array([0.0]))
    V = directions(np.array([theta]), np.array([180.0]))
    Ms, _, _ = eval_mueller(bsdf, L, V, component=0)
    Ts, Tp = fresnel_T(np.radians(theta), eta)
    Rs, Rp = 1 - Ts, 1 - Tp
    assert abs(dolp(Ms)[0] - (Rs - Rp) / (Rs + Rp)) < 1e-4


def test_kappa_zero_factorises(variant):
    """kappa = 0: f is uniform and the double integral is the product of two single ones."""
    mi = variant
    eta, alpha, beta = 1.6, 0.5, 1.5
    bsdf = make(mi, eta=eta, alpha=alpha, beta=beta, kappa=0.0)
    rng = np.random.default_rng(3)
    L = directions(rng.uniform(0, 85, 6), rng.uniform(-180, 180, 6))
    V = directions(rng.uniform(0, 85, 6), rng.uniform(-180, 180, 6))
    Mb, x_in, x_out = eval_mueller(bsdf, L, V, component=1)
    ref = Reference(eta, alpha, beta, 0.0, n_s=128, n_phi=256)
    for k in range(6):
        a = ref._outgoing_vectors(V[k], x_out[k]).sum(0)   # int a(n) d omega
        b = ref._incident_vectors(L[k], x_in[k]).sum(0)    # int b(n_i) d omega
        # f = 1 / int D = 1 / Z, Z = int D(n) d omega
        M = np.outer(a, b) / ref.wD.sum() / np.pi * ref.G1(L[k]) * ref.G1(V[k]) / V[k][2]
        np.testing.assert_allclose(Mb[k, :3, :3], M[:3, :3], atol=3e-3 * M[0, 0])


def test_body_reciprocal_at_kappa_zero(variant):
    """Only at kappa = 0 is the body term reciprocal: swapping L and V leaves the intensity."""
    mi = variant
    bsdf = make(mi, eta=1.5, alpha=0.8, beta=1.0, kappa=0.0)
    rng = np.random.default_rng(4)
    L = directions(rng.uniform(0, 80, 8), rng.uniform(-180, 180, 8))
    V = directions(rng.uniform(0, 80, 8), rng.uniform(-180, 180, 8))
    a, _, _ = eval_mueller(bsdf, L, V, component=1)
    b, _, _ = eval_mueller(bsdf, V, L, component=1)
    # eval includes cos(theta_L): compare the BRDFs
    np.testing.assert_allclose(a[:, 0, 0] / L[:, 2], b[:, 0, 0] / V[:, 2], rtol=3e-3)


def test_importance_mode_is_the_same_light_path_times_cos_wo(variant):
    """Mitsuba's BSDFs return f * |cos theta(wo)| in both transport modes; in
    importance mode si.wi points to the light and wo to the viewer.  So
    eval(Importance, wi=A, wo=B) describes the same physical path as
    eval(Radiance, wi=B, wo=A) (light from A seen from B, same Stokes bases),
    and differs from it only by the factor cos(B) / cos(A).  The two
    directions are far from equal, so a factor of cos(A) in place of cos(B)
    (the old behaviour) fails by up to 8x."""
    import drjit as dr
    mi = variant
    bsdf = make(mi, eta=1.6, alpha=0.35, beta=1.5, kappa=20.0)
    rng = np.random.default_rng(4)
    A = directions(rng.uniform(5, 80, 64), rng.uniform(0, 360, 64))
    B = directions(rng.uniform(5, 80, 64), rng.uniform(0, 360, 64))
    out = {}
    for mode, wi, wo in ((mi.TransportMode.Radiance, B, A), (mi.TransportMode.Importance, A, B)):
        si = dr.zeros(mi.SurfaceInteraction3f, len(A))
        si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))
        si.wavelengths = 550.0 if mi.is_spectral else si.wavelengths
        M = bsdf.eval(mi.BSDFContext(mode), si, mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32)))
        out[mode] = np.array([[np.asarray(M[i, j]).reshape(-1, len(A))[0] for j in range(4)] for i in range(4)]) \
            if mi.is_polarized else np.asarray(M).reshape(-1, len(A))[0]
    ratio = B[:, 2] / A[:, 2]
    rad, imp = out[mi.TransportMode.Radiance], out[mi.TransportMode.Importance]
    assert np.allclose(imp, rad * ratio, rtol=1e-5, atol=1e-7)
