"""Pixel rays and the exact sphere a camera sees, in image units: one implementation for scenes, fits, synthetic data.

Image points (X, Y) are in pixels, x right, y down, a pixel's centre at
(column + 0.5, row + 0.5); directions are in the camera frame (x right, y up,
z towards the camera).  A perspective camera is a pinhole with its principal
point at the image centre and horizontal field of view ``fov`` degrees.
Callers check their arguments; these functions assume them valid.
"""
from __future__ import annotations

import numpy as np


def focal_length(width, fov):
    """Focal length in pixels of an image ``width`` pixels wide with horizontal field of view ``fov`` degrees."""
    return 0.5 * width / np.tan(np.radians(float(fov)) / 2)


def pixel_centres(shape):
    """(X, Y), each (H, W): the image coordinates of the pixel centres of an image of ``shape`` (H, W)."""
    h, w = shape
    return np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)


def view_rays(X, Y, shape, camera="orthographic", fov=None):
    """Unit view directions (..., 3) at image points (X, Y): from the surface towards the camera, minus the ray.

    ``orthographic``: (0, 0, 1) everywhere; ``perspective``: exact for any depth.
    """
    h, w = shape
    if camera == "orthographic":
        v = np.zeros(np.shape(X) + (3,))
        v[..., 2] = 1.0
        return v
    d = np.stack([-(X - 0.5 * w), Y - 0.5 * h, np.full_like(X, focal_length(w, fov))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def sphere_at(X, Y, shape, centre, radius, camera="orthographic", fov=None):
    """Unit normals (..., 3), mask and view directions of a sphere at image points (X, Y).

    The sphere's silhouette is centred on ``centre`` (x, y pixels) with
    ``radius`` pixels (orthographic); a perspective camera sees a sphere on
    the ray through ``centre`` whose angular radius is atan(``radius`` / f)
    (exact for a sphere on the optical axis given its silhouette radius; off
    axis the silhouette is an ellipse).  Normals are (0, 0, 1) outside the mask.
    """
    h, w = shape
    cx, cy = (float(c) for c in centre)
    r = float(radius)
    view = view_rays(X, Y, shape, camera, fov)
    if camera == "orthographic":
        u, v = (X - cx) / r, -(Y - cy) / r
        rr = u * u + v * v
        mask = rr < 1.0
        n = np.stack([u, v, np.sqrt(np.clip(1.0 - rr, 0.0, 1.0))], axis=-1)
    else:
        f = focal_length(w, fov)
        c_dir = np.array([cx - 0.5 * w, -(cy - 0.5 * h), -f])
        c_dir /= np.linalg.norm(c_dir)
        rad = np.sin(np.arctan(r / f))  # sphere radius at unit distance from the pinhole
        ray = -view  # from the pinhole into the scene
        b = ray @ c_dir
        disc = b * b - (1.0 - rad * rad)
        mask = disc > 0
        t = b - np.sqrt(np.clip(disc, 0.0, None))
        p = ray * t[..., None] - c_dir
        n = p / np.linalg.norm(p, axis=-1, keepdims=True)
    n = np.where(mask[..., None], n, np.array([0.0, 0.0, 1.0]))
    return n, mask, view


def pixel_rays(shape, camera="orthographic", fov=None):
    """Unit view directions (H, W, 3) at the pixel centres of an image of ``shape`` (:func:`view_rays`)."""
    return view_rays(*pixel_centres(shape), shape, camera, fov)


def sphere_normals(shape, centre, radius, camera="orthographic", fov=None):
    """Unit normals (H, W, 3), mask and view directions of a sphere at the pixel centres (:func:`sphere_at`)."""
    return sphere_at(*pixel_centres(shape), shape, centre, radius, camera, fov)


class SphereGeometry:
    """A sphere's exact normals and view directions at any image point (:func:`sphere_at`): a fit evaluates
    it at each sub-pixel sample instead of interpolating the normal map, which errs near the silhouette."""

    def __init__(self, shape, centre, radius, camera="orthographic", fov=None):
        self.shape, self.centre, self.radius, self.camera, self.fov = tuple(shape), centre, radius, camera, fov

    def at(self, X, Y):
        n, _, v = sphere_at(np.asarray(X, float), np.asarray(Y, float), self.shape, self.centre, self.radius,
                            self.camera, self.fov)
        return n, v
