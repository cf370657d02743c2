"""The normal maps of K >= 3 images of one view (fit/inputs/normal_maps.py): photometric stereo on Lambertian
images, the angle between two maps, and the check that the images share one view."""
import numpy as np
import pytest

from fmbrdf_mi.fit import InputError, Observation
from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg, check_views, photometric_stereo
from fmbrdf_mi.geometry import sphere_normals

LIGHTS = [(-0.4, 0.3, 1.0), (0.5, 0.1, 1.0), (0.0, -0.5, 1.0), (0.2, 0.4, 0.9)]


def _lambertian(irr=(1.0, 0.7, 1.3, 2.0), albedo=0.6):
    """Images of a sphere cap (normals within 25 deg of the view, lit by every light) under each light:
    S0 = E_k albedo l_k . n, no polarisation."""
    n, m, v = sphere_normals((12, 12), (6, 6), 14)
    m &= n[..., 2] > np.cos(np.radians(25))
    obs = []
    for l, e in zip(LIGHTS, irr):
        l = np.asarray(l) / np.linalg.norm(l)
        s = np.zeros((3, 12, 12))
        s[0] = e * albedo * np.clip(n @ l, 0, None)
        obs.append(Observation(s, m, n, v, l, irradiance=e))
    return obs, n, m


def test_photometric_stereo_recovers_lambertian_normals():
    obs, n, m = _lambertian()
    assert np.all(np.einsum("hwc,kc->hwk", n, np.array(LIGHTS))[m] > 0) and m.sum() > 30
    ps = photometric_stereo(obs)
    np.testing.assert_allclose(ps[m], n[m], atol=1e-9)
    assert np.all(ps[~m] == [0.0, 0.0, 1.0])                  # outside the mask: facing the camera
    # a mask of some pixels only
    sub = m.copy()
    sub[:, :6] = False
    ps = photometric_stereo(obs, mask=sub)
    np.testing.assert_allclose(ps[sub], n[sub], atol=1e-9)
    with pytest.raises(InputError, match="K >= 3 images, got 2"):
        photometric_stereo(obs[:2])


def test_photometric_stereo_turns_normals_towards_the_camera():
    """Images whose intensities are negated give b = -albedo n: the map is flipped back to face the camera."""
    obs, n, m = _lambertian()
    for o in obs:
        o.stokes = -o.stokes
    np.testing.assert_allclose(photometric_stereo(obs)[m], n[m], atol=1e-9)


def test_angular_error_deg_against_rotations_of_known_angle():
    """A map rotated about x by theta_i per pixel: the angles are theta_i, whatever the vectors' lengths."""
    theta = np.radians(np.array([[0.0, 1.0, 30.0], [60.0, 90.0, 179.0]]))
    a = np.zeros((2, 3, 3))
    a[..., 2] = 2.0                                            # not unit length
    b = np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], -1) * 0.5
    mask = np.ones((2, 3), bool)
    mask[0, 0] = False
    np.testing.assert_allclose(angular_error_deg(a, b, mask), np.degrees(theta[mask]), atol=1e-6)


def test_check_views_refuses_what_is_not_one_view():
    obs, n, m = _lambertian()
    out = check_views(obs, n.astype(np.float32))
    assert out.dtype == np.float64 and np.array_equal(out, n.astype(np.float32))
    out[:] = 0.0
    assert np.all(np.linalg.norm(n, axis=-1) > 0.99)           # a copy: the caller's map is left alone
    with pytest.raises(InputError, match="needs K >= 3 images under different lights, got 2"):
        check_views(obs[:2], n)
    tilted = np.broadcast_to(np.array([0.1, 0.0, 1.0]) / np.hypot(0.1, 1.0), n.shape).copy()
    moved = Observation(obs[1].stokes, m, n, tilted, obs[1].light_dir)                  # other view directions
    smaller = Observation(obs[2].stokes[:, :, :11], m[:, :11], n[:, :11], obs[2].view_dirs[:, :11],
                          obs[2].light_dir)                                            # another pixel grid
    for k, o in ((1, moved), (2, smaller)):
        views = [obs[0], obs[1], obs[2]]
        views[k] = o
        with pytest.raises(InputError, match=f"image {k} is not of the same view as image 0"):
            check_views(views, n)
    with pytest.raises(InputError, match=r"normals: expected shape \(12, 12, 3\), got \(12, 11, 3\)"):
        check_views(obs, n[:, :11])
    bad = n.copy()
    bad[np.argwhere(m)[0][0], np.argwhere(m)[0][1]] = np.nan
    with pytest.raises(InputError, match="non-finite values inside the mask"):
        check_views(obs, bad)
