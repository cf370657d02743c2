"""The polarised evaluator: Mueller BRDFs of fmbrdf, pplastic, a Lambertian and the image fits' blended
baselines (Lambertian or Oren-Nayar + Torrance-Sparrow) in the package's frames.

References: the facet's Fresnel reflection written as a Jones matrix in NumPy
between the facet's s/p bases and the planes of incidence and exit (SCATMECH's
psps bases, tests/test_mueller_table.py's Jones-to-Mueller construction), the
unpolarised evaluator of the MERL fits (M00), and 1/pi.
"""
import numpy as np
import pytest

from fmbrdf_mi.brdf_fit import mueller as T
from fmbrdf_mi.brdf_fit.mueller_values import MuellerValues, combine
from test_mueller_table import fresnel, jones_to_mueller, random_dirs


def _unit(v):
    return v / np.linalg.norm(v)


def facet_reflection_sp(w_in, w_out, eta):
    """Normalised Mueller matrix, in the psps bases of the planes of incidence and exit, of the Fresnel
    reflection off the facet with normal H = (w_in + w_out) / |..|."""
    H = _unit(w_in + w_out)
    k_in, k_out = -w_in, w_out
    rs, rp = fresnel(float(w_in @ H), eta)
    sf = _unit(np.cross(H, k_in))      # normal to the plane of reflection: the same for both beams
    basis = lambda k, s: (s, np.cross(k, s))
    sfi, pfi = basis(k_in, sf)
    sfo, pfo = basis(k_out, sf)
    si, pi_ = basis(k_in, _unit(np.cross([0, 0, 1.0], k_in)))
    so, po = basis(k_out, _unit(np.cross([0, 0, 1.0], k_out)))
    to_facet = np.array([[sfi @ si, sfi @ pi_], [pfi @ si, pfi @ pi_]])
    from_facet = np.array([[so @ sfo, so @ pfo], [po @ sfo, po @ pfo]])
    M = jones_to_mueller(from_facet @ np.diag([rs, rp]) @ to_facet)
    return M / M[0, 0]


@pytest.mark.parametrize("model, shape", [("fmbrdf", {"eta": 1.6, "alpha": 0.2, "beta": 1.5, "kappa": 3.0}),
                                          ("pplastic", {"eta": 1.45, "alpha": 0.15}),
                                          ("lambert_ts", {"eta": 1.45, "alpha": 0.5}),    # Beckmann: 0 far out
                                          ("oren_nayar_ts", {"eta": 1.7, "alpha": 0.5, "sigma": 0.3})])
def test_surface_term_is_facet_fresnel(model, shape):
    rng = np.random.default_rng(5)
    w_in = np.concatenate([T.directions(np.array([40.0, -25.0]), np.array([0.0, 0.0])), random_dirs(rng, 8)])
    w_out = np.concatenate([T.directions(np.array([-50.0, 60.0]), np.array([0.0, 0.0])), random_dirs(rng, 8)])
    P = MuellerValues(model, w_in, w_out).parts(shape)
    M_sp = T.package_to_sp(P[0], w_in, w_out)
    for k in range(len(w_in)):
        ref = facet_reflection_sp(w_in[k], w_out[k], shape["eta"])
        np.testing.assert_allclose(M_sp[k] / M_sp[k, 0, 0], ref, atol=2e-4)
    # in the plane of incidence: s-polarised forward (m12 > 0), no s/p-to-diagonal coupling
    assert M_sp[0, 1, 0] > 0.01 and abs(M_sp[0, 0, 2]) < 1e-6 * M_sp[0, 0, 0]


def test_fmbrdf_m00_is_the_unpolarised_evaluators():
    from fmbrdf_mi.brdf_fit.values import FMBRDFValues

    rng = np.random.default_rng(6)
    w_in, w_out = random_dirs(rng, 200), random_dirs(rng, 200)
    shape = {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0}
    P = MuellerValues("fmbrdf", w_in, w_out).parts(shape)
    S, B = FMBRDFValues(w_in, w_out).parts(shape)
    np.testing.assert_allclose(P[0, :, 0, 0], S, rtol=2e-5)
    np.testing.assert_allclose(P[1, :, 0, 0], B, rtol=2e-5)
    # the body term polarises (sec. body reflection): not a depolariser
    assert np.abs(P[1, :, 1:, 0] / P[1, :, :1, 0]).max() > 1e-3
    np.testing.assert_allclose(combine(P, [2.0, 0.5]), 2.0 * P[0] + 0.5 * P[1])


def test_blended_baselines_diffuse_terms_are_the_image_fits_albedos():
    """Lambertian + Torrance-Sparrow is a 50/50 blend reported with k_d = half the diffuse reflectance: its body
    term at unit k_d is 1/pi, depolarising; Oren-Nayar's (sigma 0) the same."""
    rng = np.random.default_rng(8)
    w_in, w_out = random_dirs(rng, 40), random_dirs(rng, 40)
    for model, shape in (("lambert_ts", {"eta": 1.5, "alpha": 0.2}),
                         ("oren_nayar_ts", {"eta": 1.5, "alpha": 0.2, "sigma": 0.0})):
        P = MuellerValues(model, w_in, w_out).parts(shape)
        np.testing.assert_allclose(P[1, :, 0, 0], 1 / np.pi, rtol=1e-6)
        assert np.abs(P[1].reshape(-1, 16)[:, 1:]).max() == 0.0


def test_lambert_is_one_over_pi_and_depolarising():
    rng = np.random.default_rng(7)
    w_in, w_out = random_dirs(rng, 30), random_dirs(rng, 30)
    P = MuellerValues("lambert", w_in, w_out).parts()
    ref = np.zeros((30, 4, 4))
    ref[:, 0, 0] = 1 / np.pi
    np.testing.assert_allclose(P[0], ref, atol=1e-7)


def test_rejects_directions_below_the_horizon():
    with pytest.raises(ValueError, match="above the surface"):
        MuellerValues("lambert", np.array([[0, 0, 1.0]]), np.array([[0, 0.6, -0.8]]))
    with pytest.raises(ValueError, match="valid models"):
        MuellerValues("phong", np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]))
