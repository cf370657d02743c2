"""Scenes of one dataset sample: geometry of camera, light and shape; rendering.

Frames (all right-handed):

* **world**: the shape is centred at the origin and scaled into the unit sphere
  (see :data:`SHAPES`), then rotated by the sample's ``shape.rotation``;
* **camera**: x = image right, y = image up, z = from the scene towards the
  camera, which looks along -z.  It is the frame of the ``stokes`` integrator's
  Stokes vectors and of the normal maps.  The camera sits at
  ``distance * (cos(el) sin(az), sin(el), cos(el) cos(az))`` in the world,
  looking at the origin with the world's +y as "up": elevation = azimuth = 0
  puts it on +z with camera frame = world frame (as in ``fmbrdf_mi.scene``);
* the light direction is given in the camera frame (from the surface towards
  the light) and recorded in both.

Mitsuba renders in the shape's own frame (world rotated by the inverse of
``shape.rotation``): the shape is then the same object in every sample and only
parameters change, which lets one loaded scene serve many samples through
``mi.traverse`` updates.  The picture is the same as with the shape rotated.

The light's irradiance is applied by scaling the image rendered with
irradiance 1 (rendering is linear in it); the normal map and the mask come
from one ray per pixel through the pixel centre.
"""
from __future__ import annotations

import math
import time

import numpy as np

#: Built-in shapes: Mitsuba plugin and the 4x4 to_world that centres it and
#: scales it into the unit sphere (applied to Mitsuba's default shape).
SHAPES = {
    # radius 1 at the origin
    "sphere": ("sphere", np.eye(4)),
    # [-1, 1]^3 scaled by 1/sqrt(3)
    "cube": ("cube", np.diag([3 ** -0.5] * 3 + [1.0])),
    # Mitsuba's cylinder (radius 1, z in [0, 1], open ends) -> radius 0.6, z in [-0.8, 0.8]
    "cylinder": ("cylinder", np.array([[0.6, 0, 0, 0], [0, 0.6, 0, 0], [0, 0, 1.6, -0.8], [0, 0, 0, 1.0]])),
    # unit disk in the plane z = 0, facing +z (one-sided)
    "disk": ("disk", np.eye(4)),
    # [-1, 1]^2 in the plane z = 0, facing +z, scaled by 1/sqrt(2) (one-sided)
    "rectangle": ("rectangle", np.diag([2 ** -0.5] * 2 + [1.0, 1.0])),
}

_SCALARS = ("eta", "alpha", "beta", "kappa")
#: Wavelengths (nm) at which an RGB albedo's spectrum is tabulated (Mitsuba's CIE range).
WAVELENGTHS = np.linspace(360.0, 830.0, 471)


# ------------------------------------------------------------------ geometry (NumPy, float64)
def camera_frame(distance, elevation, azimuth):
    """(position, R) of the camera: R's columns are its x (right), y (up), z (back) axes in the world."""
    el, az = math.radians(elevation), math.radians(azimuth)
    back = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return distance * back, np.stack([right, up, back], axis=1)


def mesh_normalisation(positions):
    """to_world (4x4) moving a mesh's bounding-box centre to the origin and its farthest vertex to radius 1."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0 or not np.all(np.isfinite(p)):
        raise ValueError("mesh has no vertices or non-finite vertex positions")
    c = 0.5 * (p.min(0) + p.max(0))
    r = float(np.max(np.linalg.norm(p - c, axis=1)))
    if r <= 0:
        raise ValueError("mesh is degenerate (all vertices at one point)")
    m = np.eye(4) / r
    m[3, 3] = 1.0
    m[:3, 3] = -c / r
    return m


def _plain(a):
    return [[float(x) for x in row] for row in np.asarray(a)] if np.ndim(a) == 2 else [float(x) for x in a]


def sample_geometry(draw, normalisation):
    """Camera, light and shape of a sample in the world frame (for its label) and in the
    render frame (for Mitsuba).  ``draw`` is :meth:`DatasetConfig.draw`'s output."""
    R = np.asarray(draw["rotation"], dtype=np.float64)
    pos, C = camera_frame(draw["distance"], draw["elevation"], draw["azimuth"])
    l_cam = np.asarray(draw["light_dir"], dtype=np.float64)
    l_world = C @ l_cam
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3], cam_to_world[:3, 3] = C, pos
    shape_to_world = np.eye(4)
    shape_to_world[:3, :3] = R
    shape_to_world = shape_to_world @ normalisation
    # render frame = the shape's frame before its rotation
    return {
        "label": {
            "camera": {"position": _plain(pos), "to_world": _plain(cam_to_world)},
            "light": {"direction_world": _plain(l_world)},
            "shape": {"to_world": _plain(shape_to_world)},
        },
        "render": {"position": R.T @ pos, "axes": R.T @ C, "light": R.T @ l_world},
    }


# ------------------------------------------------------------------ Mitsuba
def _mi():
    import mitsuba as mi

    return mi


def _T(m):
    mi = _mi()
    return mi.ScalarTransform4f(np.asarray(m, dtype=np.float64).tolist())


def srgb_spectrum(rgb):
    """Spectral values at :data:`WAVELENGTHS` of an RGB albedo (Mitsuba's sRGB upsampling).

    Colours in [0, 1] give exactly Mitsuba's ``srgb`` spectrum (evaluated here);
    larger ones are scaled down by their maximum, upsampled and scaled back.
    Needs a spectral variant.
    """
    mi = _mi()
    rgb = np.asarray(rgb, dtype=np.float64)
    scale = float(rgb.max())
    if scale <= 0:
        return np.zeros_like(WAVELENGTHS)
    scale = max(scale, 1.0)
    tex = mi.load_dict({"type": "srgb", "color": (rgb / scale).tolist()})
    c = np.asarray(mi.traverse(tex)["value"], dtype=np.float64).ravel()
    lam = WAVELENGTHS
    if np.isinf(c[2]):
        s = np.full_like(lam, 1.0 if c[2] > 0 else 0.0)
    else:
        v = (c[0] * lam + c[1]) * lam + c[2]
        s = np.maximum(0.0, 0.5 + 0.5 * v / np.sqrt(1.0 + v * v))
    return scale * s


def _albedo_texture(value, rgb_kind):
    if rgb_kind:
        return {"type": "regular", "wavelength_min": float(WAVELENGTHS[0]),
                "wavelength_max": float(WAVELENGTHS[-1]),
                "values": ", ".join(repr(float(x)) for x in srgb_spectrum(value))}
    return {"type": "uniform", "value": float(value)}


class SampleRenderer:
    """Renders samples, keeping one loaded scene per structure (shape, camera type).

    Only one scene is alive at a time: Dr.Jit compiles every live BSDF into
    every kernel.  Samples of the same structure only update parameters
    (``mi.traverse``), passed as opaque values so that no kernel is recompiled.
    Every parameter that varies is set for every sample (eta, alpha, beta,
    kappa when they differ from the previous sample's: the BSDF's tables depend
    on them alone), so a sample's images do not depend on which samples were
    rendered before it.  ``seconds`` accumulates the time spent per phase.
    """

    def __init__(self, cfg):
        self.cfg = cfg
        self.key = None
        self.scene = None
        self.params = None
        self._scalars = None
        self._normalisations = {}
        #: per material: {albedo name: whether it is RGB}
        self.rgb = [{k: _is_rgb(d) for k, d in m.items() if k in ("k_s", "k_b", "r_k")} for m in cfg.materials]
        #: per material: the traverse key prefix of its BSDF (inside the blend of several materials)
        from ..scene import blend_paths

        self.prefixes = ["shape.bsdf" + (f".{q}" if q else "") for q in blend_paths(len(cfg.materials))]
        self.labels = None  # with shape.labels: the last sample's label map (H, W), -1 off the mask
        self.seconds = {"load": 0.0, "update": 0.0, "render": 0.0, "geometry": 0.0}

    def normalisation(self, shape):
        if shape in SHAPES:
            return SHAPES[shape][1]
        if shape not in self._normalisations:
            mi = _mi()
            plugin = "ply" if shape.lower().endswith(".ply") else "obj"
            try:
                mesh = mi.load_dict({"type": plugin, "filename": self.cfg.mesh_path(shape)})
            except Exception as e:
                raise ValueError(f"shape.type: cannot load mesh {shape!r}: {str(e).splitlines()[-1]}") from None
            params = mi.traverse(mesh)
            positions = np.asarray(params["vertex_positions"])
            has_uv = "vertex_texcoords" in params and len(np.asarray(params["vertex_texcoords"])) > 0
            del mesh, params
            if self.cfg.several and not has_uv:
                raise ValueError(f"shape.labels: mesh {shape!r} has no uv coordinates (texcoords), which the uv "
                                 f"label image needs; give the mesh uvs or use a built-in shape")
            try:
                self._normalisations[shape] = mesh_normalisation(positions)
            except ValueError as e:
                raise ValueError(f"shape.type: mesh {shape!r}: {e}") from None
        return self._normalisations[shape]

    def _scene_dict(self, shape, camera):
        """The scene of a structure: fmbrdf_mi.scene's sensor, light and integrator around
        this shape; camera pose, light, material and seed are placeholders set per sample."""
        from .. import scene as S

        mi = _mi()
        cfg = self.cfg
        if shape in SHAPES:
            shape_dict = {"type": SHAPES[shape][0]}
        else:
            shape_dict = {"type": "ply" if shape.lower().endswith(".ply") else "obj",
                          "filename": cfg.mesh_path(shape)}
        shape_dict["to_world"] = _T(self.normalisation(shape))
        bsdfs = []
        for rgbs in self.rgb:
            bsdf = {"type": "fmbrdf"}
            for k, rgb in rgbs.items():
                # loaded as objects of their own: in a dict, Mitsuba would merge two equal textures
                bsdf[k] = mi.load_dict(_albedo_texture([1.0] * 3 if rgb else 1.0, rgb))
            bsdfs.append(bsdf)
        shape_dict["bsdf"] = S.blend_bsdfs(bsdfs, cfg.uv_labels) if cfg.several else bsdfs[0]
        w, h = cfg.resolution
        sensor = S._sensor(mi, camera, w, h, 1, S.DEFAULT_FOV, S.DEFAULT_DISTANCE, cfg.spp, 0)
        # irradiance 1: the image is scaled by the sample's irradiance
        return S._scene(mi, {"shape": shape_dict}, (0.0, 0.0, 1.0), 1.0, sensor)

    def _load(self, key):
        import gc

        mi = _mi()
        self.scene = self.params = None
        gc.collect()
        self.scene = mi.load_dict(self._scene_dict(*key))
        self.params = mi.traverse(self.scene)
        self.key = key
        self._scalars = [None] * len(self.prefixes)  # per material: (eta, alpha, beta, kappa) last set

    def close(self):
        import gc

        self.scene = self.params = None
        self.key = None
        gc.collect()

    def render(self, draw, geometry):
        """(stokes (4, H, W, C) float32, normals (H, W, 3) float32 camera frame, mask (H, W) bool)."""
        import drjit as dr

        mi = _mi()
        from ..scene import half_width, render_stokes

        t0 = time.perf_counter()
        key = (draw["shape"], draw["camera"])
        if key != self.key:
            self._load(key)
        t1 = time.perf_counter()
        p = self.params
        g = geometry["render"]
        for i, (m, prefix, rgbs) in enumerate(zip(draw["materials"] if self.cfg.several else [draw["material"]],
                                                  self.prefixes, self.rgb)):
            scalars = tuple(m[name] for name in _SCALARS)
            if scalars != self._scalars[i]:  # a change rebuilds the BSDF's tables (most of a sample's time)
                for name, value in zip(_SCALARS, scalars):
                    p[f"{prefix}.{name}"] = dr.opaque(mi.Float, value)
                self._scalars[i] = scalars
            for name, rgb in rgbs.items():
                if rgb:
                    p[f"{prefix}.{name}.values"] = mi.Float(srgb_spectrum(m[name]).astype(np.float32))
                else:
                    p[f"{prefix}.{name}.value"] = dr.opaque(mi.Float, m[name])
        pos, axes = g["position"], g["axes"]
        look = mi.ScalarTransform4f().look_at(origin=pos.tolist(), target=(pos - axes[:, 2]).tolist(),
                                              up=axes[:, 1].tolist())
        if draw["camera"] == "orthographic":
            hw = half_width(draw["fov"], draw["distance"])
            look = look @ mi.ScalarTransform4f().scale([hw, hw, 1.0])
        else:
            p["sensor.x_fov"] = float(draw["fov"])
        p["sensor.to_world"] = mi.Transform4f(look)
        light = g["light"]
        up = [0.0, 1.0, 0.0] if abs(light[1]) < 0.9 else [1.0, 0.0, 0.0]
        p["light.to_world"] = mi.Transform4f(mi.ScalarTransform4f().look_at(
            origin=[0.0, 0.0, 0.0], target=(-light).tolist(), up=up))
        p.update()
        dr.sync_thread()
        t2 = time.perf_counter()
        stokes = render_stokes(self.scene, seed=draw["render_seed"], progress=False)
        stokes = np.ascontiguousarray(stokes * np.float32(draw["irradiance"]), dtype=np.float32)
        t3 = time.perf_counter()
        normals, mask = self._pixel_centres(axes)
        t4 = time.perf_counter()
        for k, dt in zip(("load", "update", "render", "geometry"), (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            self.seconds[k] += dt
        return stokes, normals, mask

    def _pixel_centres(self, axes):
        """Shading normals (camera frame) and hit mask of one ray through each pixel centre."""
        mi = _mi()
        w, h = self.cfg.resolution
        sensor = self.scene.sensors()[0]
        x, y = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
        uv = mi.Point2f(x.ravel().astype(np.float32), y.ravel().astype(np.float32))
        ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
        si = self.scene.ray_intersect(ray)
        hit = np.asarray(si.is_valid()).reshape(h, w)
        n = np.asarray(si.sh_frame.n, dtype=np.float64).T.reshape(h, w, 3) @ axes  # -> camera frame
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        # back faces (e.g. the inside of the open cylinder, a one-sided disk seen from behind):
        # the surface faces away from the camera and the one-sided BSDF renders them black;
        # they are not part of the mask (label: shape.back_face_pixels counts them)
        front = np.asarray(si.wi.z).reshape(h, w) > 0  # wi: towards the camera, shading frame
        mask = hit & front
        self.back_face_pixels = int(np.sum(hit & ~front))
        if self.cfg.several:  # the material at each pixel centre in the mask (fmbrdf_mi.scene: as render's)
            from ..scene import labels_at

            self.labels = labels_at(si, mask.ravel(), self.cfg.uv_labels, len(self.prefixes)).reshape(h, w)
        n[~mask] = 0.0
        return n.astype(np.float32), mask


def _is_rgb(dist):
    from .config import Choice, PerChannel

    return isinstance(dist, PerChannel) or (isinstance(dist, Choice) and isinstance(dist.values[0], list))
