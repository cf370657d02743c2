"""A synthetic non-spherical object captured under several lights, written in the paper authors' layout.

    from fmbrdf_mi.synthetic.mesh_object import write_authors_object
    info = write_authors_object("data/blob", params, lights, res=48, seed=0)

The object is a triangle mesh (:func:`blob_mesh`: an ellipsoid with a
three-lobed bump, smooth vertex normals, rotated so that it is not
symmetric about the view axis) seen by a pinhole camera.  Geometry comes
from Mitsuba ray casts against the mesh (shading normals), once per raw
sensor pixel for the data and once per super-pixel for ``normal_GT.npy``;
the Stokes image is the model (:func:`fmbrdf_mi.fit.evaluate.predict.predict_image`)
at every raw pixel (or its mean over points of the pixel's area), captured
by :func:`fmbrdf_mi.sensor.camera.capture` (shot and read noise, 16-bit ADC,
IMX250MZR layout 90 45 / 135 0) and written as 16-bit PNG mosaics; lights,
viewing rays and normals are written in OpenCV camera axes, as the authors' scripts expect
(:mod:`fmbrdf_mi.fit.inputs.authors`).
"""
from __future__ import annotations

import json
import os

import numpy as np

from fmbrdf_mi import geometry as G
from fmbrdf_mi.fit.evaluate.pixel_model import set_variant
from fmbrdf_mi.fit.evaluate.predict import predict_image
from fmbrdf_mi.fit.inputs import observations as ob
from fmbrdf_mi.fit.inputs.authors import cv_to_ours
from fmbrdf_mi.sensor.camera import CameraModel, capture


def blob_mesh(n_theta=48, n_phi=96, axes=(1.0, 0.75, 0.85), bump=0.12, rotation_deg=(25.0, -35.0)):
    """(positions (V, 3), faces (F, 3), vertex normals (V, 3)) of a smooth closed non-spherical surface.

    r(theta, phi) scales an ellipsoid by 1 + bump sin^2(theta) cos(3 phi); the
    vertex normals are the area-weighted means of the adjacent face normals.
    """
    th = np.linspace(0, np.pi, n_theta + 1)
    ph = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    s = 1.0 + bump * np.sin(T) ** 2 * np.cos(3 * P)
    pos = np.stack([axes[0] * s * np.sin(T) * np.cos(P), axes[1] * s * np.sin(T) * np.sin(P),
                    axes[2] * s * np.cos(T)], -1).reshape(-1, 3)
    rx, ry = np.radians(rotation_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
    Ry = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
    pos = pos @ (Ry @ Rx).T
    idx = np.arange((n_theta + 1) * n_phi).reshape(n_theta + 1, n_phi)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    p0, p1, p2 = pos[faces[:, 0]], pos[faces[:, 1]], pos[faces[:, 2]]
    fn = np.cross(p1 - p0, p2 - p0)                      # area-weighted, outward (checked below)
    keep = np.linalg.norm(fn, axis=1) > 1e-12             # degenerate triangles at the poles
    faces, fn = faces[keep], fn[keep]
    if np.mean(np.sum(fn * (p0[keep]), axis=1)) < 0:
        faces, fn = faces[:, ::-1], -fn
    vn = np.zeros_like(pos)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    return pos, faces, vn


def _scene(mesh):
    import mitsuba as mi


    set_variant()
    pos, faces, vn = mesh
    m = mi.Mesh("blob", len(pos), len(faces), has_vertex_normals=True)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(pos.astype(np.float32).ravel())
    p["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    p["vertex_normals"] = mi.Float(vn.astype(np.float32).ravel())
    p.update()
    return mi.load_dict({"type": "scene", "blob": m})


def ray_cast(scene, distance, view):
    """Shading normals (H, W, 3) facing the camera at (0, 0, ``distance``), and the hit mask (front faces only),
    of the rays from the camera along minus the view directions ``view`` (H, W, 3)."""
    import drjit as dr
    import mitsuba as mi

    h, w = view.shape[:2]
    d = -view.reshape(-1, 3)
    o = np.tile(np.array([0.0, 0.0, distance]), (len(d), 1))
    ray = mi.Ray3f(mi.Point3f(np.ascontiguousarray(o.T, np.float32)), mi.Vector3f(np.ascontiguousarray(d.T, np.float32)))
    si = scene.ray_intersect(ray)
    dr.eval(si)
    valid = np.asarray(si.is_valid())
    n = np.stack([np.asarray(si.sh_frame.n[i], np.float64) for i in range(3)], -1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    front = np.sum(n * -d, axis=1) > 0
    mask = valid & front
    n[~mask] = (0.0, 0.0, 1.0)
    return n.reshape(h, w, 3), mask.reshape(h, w)


def write_authors_object(root, params, lights, *, res=48, fov=20.0, distance=8.0, seed=0, powers=None,
                         camera=None, mesh=None, peak_fraction=0.8, area=1):
    """Write ``root`` in the authors' layout (module docstring); returns a dict of what was written.

    ``lights`` (ours: x right, y up, z towards the camera); ``res`` super-pixels
    across (the raw mosaics are 2 res x 2 res); ``powers``: relative light
    powers (written as calibration/intensities.npy); the exposure is fixed
    across images (the brightest raw pixel of the brightest image at
    ``peak_fraction`` of full scale), so the powers are the only difference.
    ``area`` > 1 makes each raw pixel the mean of the model over ``area`` x
    ``area`` points of its area (points off the mesh count 0), as a sensor
    pixel integrates and as the fit's pixel-area quadrature models it; 1
    evaluates it at the pixel centres.
    """
    from PIL import Image


    cam = camera or CameraModel(full_well=20000.0, read_noise=2.5, bits=16)
    scene = _scene(mesh or blob_mesh())
    r2 = 2 * res
    v2, v1 = (G.pixel_rays((k, k), "perspective", fov) for k in (r2, res))
    n2, m2 = ray_cast(scene, distance, v2)
    n1, m1 = ray_cast(scene, distance, v1)
    f1 = G.focal_length(res, fov)
    lights = [np.asarray(l, float) / np.linalg.norm(l) for l in lights]
    powers = np.ones(len(lights)) if powers is None else np.asarray(powers, float)
    a = int(area)
    va = v2 if a == 1 else G.pixel_rays((r2 * a, r2 * a), "perspective", fov)
    na, ma = (n2, m2) if a == 1 else ray_cast(scene, distance, va)
    stokes = []
    for l, p in zip(lights, powers):
        o = ob.Observation(np.ones((3, r2 * a, r2 * a)), ma, na, va, l, float(p))
        stokes.append(predict_image("fmbrdf", params, o).reshape(3, r2, a, r2, a).mean(axis=(2, 4)))
    exposure = peak_fraction * cam.full_well / max(float(np.max(s[0] + np.hypot(s[1], s[2])) / 2) for s in stokes)
    for sub in ("calibration", "normal", os.path.join("image", "img_ud")):
        os.makedirs(os.path.join(root, sub), exist_ok=True)
    for k, s in enumerate(stokes):
        cap = capture(s, cam, exposure=exposure, seed=seed + k)
        Image.fromarray(cap["raw"].astype(np.uint16)).save(os.path.join(root, "image", "img_ud", f"{k:03d}.png"))
    np.savetxt(os.path.join(root, "calibration", "L.txt"), np.array([cv_to_ours(l) for l in lights]),
               delimiter=",")
    np.save(os.path.join(root, "calibration", "vpL_img.npy"), cv_to_ours(-v1).astype(np.float32))
    K = np.array([[2 * f1, 0, res - 0.5], [0, 2 * f1, res - 0.5], [0, 0, 1.0]])  # raw pixels, centres at integers
    np.save(os.path.join(root, "calibration", "IntrinsicL.npy"), K)
    if not np.allclose(powers, 1.0):
        np.save(os.path.join(root, "calibration", "intensities.npy"), powers)
    np.save(os.path.join(root, "normal", "normal_GT.npy"), cv_to_ours(n1).astype(np.float32))
    np.save(os.path.join(root, "mask_ud.npy"), m2.astype(np.uint8))
    truth = {"params": dict(params), "lights": [l.tolist() for l in lights], "powers": powers.tolist(),
             "camera": {"full_well": cam.full_well, "read_noise": cam.read_noise, "bits": cam.bits,
                        "conversion_gain": cam.conversion_gain},
             "exposure_e_per_unit": exposure,
             "irradiance_dn": exposure / cam.conversion_gain}
    with open(os.path.join(root, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1)
    return truth


class MeshGeometry:
    """Exact normals and view directions of a mesh seen by a pinhole camera at any image point
    (Mitsuba ray casts; the interface of :class:`fmbrdf_mi.geometry.SphereGeometry`), for
    sub-pixel samples of a synthetic object: ``shape`` (H, W) the super-pixel grid, ``X``, ``Y`` in its
    pixels (centres at + 0.5, x right, y down); points off the mesh get (0, 0, 1)."""

    def __init__(self, scene, shape, fov, distance):
        self.scene, self.shape, self.fov, self.distance = scene, tuple(shape), float(fov), float(distance)

    def at(self, X, Y):
        X, Y = np.broadcast_arrays(np.asarray(X, float), np.asarray(Y, float))
        v = G.view_rays(X, Y, self.shape, "perspective", self.fov)
        n, _ = ray_cast(self.scene, self.distance, v.reshape(-1, 1, 3))
        return n.reshape(v.shape), v


def ideal_object(params, res=40, light=(0.45, 0.35, 1.0), model="fmbrdf", area=4, mesh=None, fov=20.0,
                 distance=8.0):
    """Noise-free Stokes (3, 2 res, 2 res) of the raw pixels of :func:`blob_mesh` (or ``mesh``) seen by a
    pinhole camera (``fov``, ``distance``), and the super-pixel geometry: the dict of
    :func:`fmbrdf_mi.synthetic.spheres.ideal_sphere` (``geometry`` a :class:`MeshGeometry`, exact at any
    point), so that :func:`~fmbrdf_mi.synthetic.spheres.capture_observation` and the textured
    captures take it as they take the sphere.  Each raw pixel is the mean of the model over ``area`` x
    ``area`` points of its area (points off the mesh count 0), as a sensor pixel integrates."""
    a = int(area)
    scene = _scene(mesh or blob_mesh())
    r2 = 2 * res
    v2 = G.pixel_rays((r2 * a, r2 * a), "perspective", fov)
    n2, m2 = ray_cast(scene, distance, v2)
    o2 = ob.Observation(np.ones((3, r2 * a, r2 * a)), m2, n2, v2, light)
    stokes = predict_image(model, params, o2).reshape(3, r2, a, r2, a).mean(axis=(2, 4))
    v1 = G.pixel_rays((res, res), "perspective", fov)
    n1, m1 = ray_cast(scene, distance, v1)
    return {"stokes": stokes, "normals": n1, "mask": m1, "view_dirs": v1, "light": np.asarray(light, float),
            "geometry": MeshGeometry(scene, (res, res), fov, distance), "params": dict(params), "model": model}
