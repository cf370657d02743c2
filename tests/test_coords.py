"""Table coordinates (fmbrdf_mi/model/coords.py): eval's square-root forms invert the
nodes' float64 arcsine forms, cover the ranges monotonically, and refine where the
docstring says; the projected-area table read through them matches its quadrature."""
import math

import numpy as np
import pytest


@pytest.fixture
def Float(variant):
    return variant.Float


def test_polar_coordinate_inverts_the_nodes(Float):
    from fmbrdf_mi.model.coords import theta_of_x, x_of_cos_theta, x_of_theta
    x = np.linspace(0.0, 1.0, 1001)
    th = theta_of_x(x)
    assert th[0] == 0.0 and abs(th[-1] - 0.5 * math.pi) < 1e-12
    assert np.all(np.diff(th) > 0)
    # float32 eval of the forward map against the float64 nodes; near the pole float32 resolves
    # 1 - cos theta only to 6e-8, i.e. theta to 3.5e-4 rad (as acos did)
    back = np.asarray(x_of_cos_theta(Float(np.cos(th))))
    inner = (th > 0.05)
    assert np.abs(back - x)[inner].max() < 2e-6
    assert np.abs(back - x).max() < 3e-4  # at the pole 1 - cos theta is below float32's resolution
    assert np.abs(np.asarray(x_of_theta(Float(th))) - x)[inner].max() < 2e-6
    # float64 (Python floats): the two forms invert each other to rounding
    assert max(abs(x_of_cos_theta(float(np.cos(t))) - xi) for t, xi in zip(th[1:], x[1:])) < 1e-9


def test_azimuth_coordinate_inverts_the_nodes(Float):
    from fmbrdf_mi.model.coords import phi_of_x, x_of_cos_phi, x_of_phi
    x = np.linspace(0.0, 1.0, 1001)
    ph = phi_of_x(x)
    assert ph[0] == 0.0 and abs(ph[-1] - math.pi) < 1e-12
    assert np.all(np.diff(ph) > 0)
    for sign in (1.0, -1.0):  # the sign of sin phi is ignored (mirror symmetry)
        back = np.asarray(x_of_cos_phi(Float(np.cos(ph)), Float(sign * np.sin(ph))))
        inner = (ph > 0.05) & (ph < math.pi - 0.05)
        assert np.abs(back - x)[inner].max() < 2e-6
        assert np.abs(back - x).max() < 1e-3
    assert max(abs(x_of_cos_phi(float(np.cos(p)), float(np.sin(p))) - xi) for p, xi in zip(ph, x)) < 1e-9
    assert np.abs(np.asarray(x_of_phi(Float(ph))) - x)[inner].max() < 2e-6


def test_nodes_follow_the_design_warps():
    """The nodes lie where the warps theta = (pi/2) sin(A x) / sin(A) and phi = pi sin(B x) / sin(B)
    put them, to within a hundredth of their finest spacing (q approximates the exact half-angle
    relation to 5.8e-6): the spacing refines 0.17x towards grazing and 0.12x towards phi = pi."""
    from fmbrdf_mi.model.coords import PHI_WARP, TABLE_WARP, phi_of_x, theta_of_x
    x = np.linspace(0.0, 1.0, 4001)
    th_design = 0.5 * math.pi * np.sin(TABLE_WARP * x) / math.sin(TABLE_WARP)
    ph_design = math.pi * np.sin(PHI_WARP * x) / math.sin(PHI_WARP)
    fine = np.linspace(0.0, 1.0, 81)
    for got, design, n in ((theta_of_x, th_design, 49), (phi_of_x, ph_design, 81)):
        xs = np.linspace(0.0, 1.0, n)
        finest = np.diff(np.interp(xs, x, design)).min()
        assert np.abs(got(x) - design).max() < 0.01 * finest
    dth, dph = np.diff(theta_of_x(fine)), np.diff(phi_of_x(fine))
    assert dth[-1] / dth[0] == pytest.approx(math.cos(TABLE_WARP), rel=0.1)
    assert dph[-1] / dph[0] == pytest.approx(math.cos(PHI_WARP), rel=0.1)


@pytest.mark.parametrize("alpha,beta", [(0.02, 4.0), (0.3, 2.0), (1.5, 0.5)])
def test_projected_area_lookup_matches_its_quadrature(Float, alpha, beta):
    """P read from the 257-node table through coords.b_of_cos_theta (no acos) against the
    Gauss-Legendre quadrature it is built from, evaluated directly at random angles, and against
    linear interpolation in theta between nodes exactly uniform in theta (NumPy)."""
    from fmbrdf_mi.model.distribution import Distribution
    dist = Distribution(Float, Float(alpha), Float(beta))
    th = np.random.default_rng(0).uniform(0.0, 0.5 * math.pi * 0.999, 2000)
    direct = np.asarray(dist.projected_area(Float(th)), dtype=np.float64)
    look = np.asarray(dist.proj_area_lookup(Float(np.cos(th))), dtype=np.float64)
    nodes = np.linspace(0.0, 0.5 * math.pi, dist.N_PTAB)
    uniform = np.interp(th, nodes, np.asarray(dist.projected_area(Float(nodes)), dtype=np.float64))
    # b is theta / (pi/2) to 9e-6 rad; float32 cos theta limits it to ~3e-4 rad at the pole
    assert np.abs(look - uniform).max() < 2e-5
    err = np.abs(look / direct - 1)
    # linear interpolation over 0.35 deg: second order where P is smooth; at 90 deg - alpha P
    # bends (alpha 0.02: 2.5e-2 at 89.9 deg, as with the acos lookup before)
    assert err[th <= np.radians(85.0)].max() < 1e-4


def test_coordinates_are_the_arcsine_warps():
    """x from the cosines (float64 Python floats: the square roots and polynomials alone) against
    the design warps' closed form x = asin(theta sin(A) / (pi/2)) / A, x = asin(phi sin(B) / pi) / B
    (NumPy): q's 5.8e-6 times the warps' steepest slope, 4.2 near grazing, bounds the difference."""
    from fmbrdf_mi.model.coords import PHI_WARP, TABLE_WARP, x_of_cos_phi, x_of_cos_theta
    th = np.linspace(0.0, 0.5 * math.pi, 2001)
    ph = np.linspace(0.0, math.pi, 2001)
    got_t = np.array([x_of_cos_theta(float(np.cos(t))) for t in th])
    got_p = np.array([x_of_cos_phi(float(np.cos(p)), float(np.sin(p))) for p in ph])
    exact_t = np.arcsin(th * math.sin(TABLE_WARP) / (0.5 * math.pi)) / TABLE_WARP
    exact_p = np.arcsin(ph * math.sin(PHI_WARP) / math.pi) / PHI_WARP
    assert np.abs(got_t - exact_t).max() < 3e-5
    assert np.abs(got_p - exact_p).max() < 3e-5
