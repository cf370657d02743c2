"""Pixel rays and sphere geometry (fmbrdf_mi.geometry, and the scenes' and fits' geometry built on it) against a
brute-force reference: each pixel's ray built in world units, its hits with the spheres from the roots of the
quadratic |o + t d - c|^2 = r^2, pixel by pixel, the nearest hit kept."""
import math

import numpy as np
import pytest

from fmbrdf_mi import scene as S
from fmbrdf_mi import geometry as G


def reference(w, h, camera, fov, distance, centres, radius, n_cells=1):
    """(normals, view, label) of spheres seen by a camera at (0, 0, distance) looking down -z, x right, y up, the
    image spanning 2 n_cells distance tan(fov / 2) horizontally at z = 0; label -1 where no sphere is hit."""
    half_w = n_cells * distance * math.tan(math.radians(fov) / 2)
    normals, view, label = np.zeros((h, w, 3)), np.zeros((h, w, 3)), np.full((h, w), -1)
    for row in range(h):
        for col in range(w):
            x = (2 * (col + 0.5) / w - 1) * half_w          # the pixel centre's point on the plane z = 0
            y = (1 - 2 * (row + 0.5) / h) * half_w * h / w
            if camera == "orthographic":
                o, d = np.array([x, y, distance]), np.array([0.0, 0.0, -1.0])
            else:
                o = np.array([0.0, 0.0, distance])
                d = np.array([x, y, 0.0]) - o
                d /= np.linalg.norm(d)
            best = np.inf
            for k, c in enumerate(np.asarray(centres, float)):
                oc = o - c
                ts = [t.real for t in np.roots([d @ d, 2 * d @ oc, oc @ oc - radius ** 2])
                      if abs(t.imag) < 1e-12 and 0 < t.real < best]
                if ts:
                    best = min(ts)
                    normals[row, col], view[row, col], label[row, col] = (o + best * d - c) / radius, -d, k
    return normals, view, label


@pytest.mark.parametrize("camera, fov, distance, centre, radius", [
    ("orthographic", 25.0, 5.0, (0.0, 0.0, 0.0), 1.0),
    ("orthographic", 30.0, 4.0, (0.4, -0.3, 0.2), 0.8),
    ("perspective", 25.0, 5.0, (0.0, 0.0, 0.0), 1.0),
    ("perspective", 40.0, 6.0, (0.7, 0.5, -0.5), 1.2),
])
def test_scene_sphere_geometry_matches_the_brute_force_ray_cast(camera, fov, distance, centre, radius):
    w, h = 40, 30
    want_n, want_v, label = reference(w, h, camera, fov, distance, [centre], radius)
    n, v, m = S.sphere_geometry((w, h), camera=camera, fov=fov, distance=distance, centre=centre, radius=radius)
    assert np.count_nonzero(label == 0) > 50 and np.array_equal(m, label == 0)
    np.testing.assert_allclose(n, want_n, rtol=0, atol=1e-9)  # np.roots' rounding, amplified at the silhouette
    np.testing.assert_allclose(v, want_v, rtol=0, atol=1e-12)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_spheres_geometry_matches_the_brute_force_ray_cast(camera):
    n, v, labels = S.spheres_geometry(3, 20, camera=camera)
    want_n, want_v, want = reference(60, 20, camera, S.DEFAULT_FOV, S.DEFAULT_DISTANCE,
                                     [(x, 0.0, 0.0) for x in S.sphere_centres(3)], 1.0, n_cells=3)
    assert set(np.unique(want)) == {-1, 0, 1, 2} and np.array_equal(labels, want)
    np.testing.assert_allclose(n, want_n, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v, want_v, rtol=0, atol=1e-12)


def test_pixel_rays_and_the_fits_sphere_match_the_brute_force_ray_cast():
    """The fit's sphere in image units (centre and silhouette radius in pixels) is the world sphere on the axis."""
    w = h = 36
    fov, distance = 30.0, 6.0
    want_n, want_v, label = reference(w, h, "perspective", fov, distance, [(0.0, 0.0, 0.0)], 1.0)
    t = math.tan(math.radians(fov) / 2)
    X, Y = np.meshgrid((2 * (np.arange(w) + 0.5) / w - 1) * t, (1 - 2 * (np.arange(h) + 0.5) / h) * t)
    p = np.stack([X, Y, -np.ones_like(X)], -1)  # pixel centres on the plane z = -1 of a pinhole at the origin
    want_rays = -p / np.linalg.norm(p, axis=-1, keepdims=True)
    np.testing.assert_allclose(G.pixel_rays((h, w), "perspective", fov), want_rays, rtol=0, atol=1e-15)
    r = 0.5 * w / t * math.tan(math.asin(1.0 / distance))
    n, m, v = G.sphere_normals((h, w), (w / 2, h / 2), r, camera="perspective", fov=fov)
    assert np.array_equal(m, label == 0)
    np.testing.assert_allclose(n[m], want_n[m], rtol=0, atol=1e-9)
    np.testing.assert_allclose(v[m], want_v[m], rtol=0, atol=1e-12)
    n, m, v = G.sphere_normals((h, w), (w / 2, h / 2), 10.0)  # orthographic: n = ((x - cx) / r, -(y - cy) / r, nz)
    X, Y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    assert np.array_equal(m, (X - w / 2) ** 2 + (Y - h / 2) ** 2 < 100.0)
    np.testing.assert_allclose(n[m][:, :2], np.stack([(X - w / 2) / 10, -(Y - h / 2) / 10], -1)[m],
                               rtol=0, atol=1e-15)
    assert np.all(v == [0.0, 0.0, 1.0])
