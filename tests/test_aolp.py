"""AoLP against physics: specular reflection is polarised perpendicular to the
plane of incidence, light transmitted out of the body parallel to the plane
holding the normal and the view direction."""
import numpy as np
import pytest
from _common import directions, eval_mueller
from conftest import make


def polarisation_direction(M, V, x_out):
    """3D unit vector of the linear polarisation of M @ [1, 0, 0, 0] (Mitsuba's basis: y = V x x)."""
    s1, s2 = M[:, 1, 0], M[:, 2, 0]
    psi = 0.5 * np.arctan2(s2, s1)
    y = np.cross(V, x_out)
    return np.cos(psi)[:, None] * x_out + np.sin(psi)[:, None] * y


def test_specular_perpendicular_to_plane_of_incidence(variant):
    mi = variant
    bsdf = make(mi, eta=1.6, alpha=0.1, beta=2.0)
    rng = np.random.default_rng(0)
    n = 16
    th = rng.uniform(15, 80, n)
    ph = rng.uniform(-180, 180, n)
    L = directions(th, ph)
    V = directions(th + rng.normal(0, 2, n), ph + 180 + rng.normal(0, 2, n))
    Ms, _, x_out = eval_mueller(bsdf, L, V, component=0)
    e = polarisation_direction(Ms, V, x_out)
    plane_normal = np.cross(L, V)
    plane_normal /= np.linalg.norm(plane_normal, axis=1, keepdims=True)
    # |cos| between polarisation and the plane's normal: 1 = perpendicular to the plane
    assert np.all(np.abs(np.sum(e * plane_normal, 1)) > 0.999)


@pytest.mark.parametrize("alpha", [0.02, 0.7])
def test_body_parallel_to_exit_plane(variant, alpha):
    mi = variant
    # kappa = 0: exit-side facets are distributed symmetrically about the (N, V) plane
    bsdf = make(mi, eta=1.6, alpha=alpha, beta=2.0, kappa=0.0)
    rng = np.random.default_rng(1)
    n = 16
    L = directions(rng.uniform(0, 80, n), rng.uniform(-180, 180, n))
    V = directions(rng.uniform(20, 80, n), rng.uniform(-180, 180, n))
    Mb, _, x_out = eval_mueller(bsdf, L, V, component=1)
    e = polarisation_direction(Mb, V, x_out)
    exit_plane_normal = np.cross([0, 0, 1.0], V)
    exit_plane_normal /= np.linalg.norm(exit_plane_normal, axis=1, keepdims=True)
    assert np.all(np.abs(np.sum(e * exit_plane_normal, 1)) < 0.01)
