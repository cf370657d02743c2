"""Spheres of FMBRDF material under a directional light: scenes, geometry, rendering.

World and camera convention (shared with ``scenes/*.xml``):

* a sphere of radius 1 at the origin (:func:`sphere_scene`), or several spheres
  of radius 1 side by side along x (:func:`spheres_scene`);
* the camera on +z looking towards -z with up +y, so world x = image right,
  y = image up, z = towards the camera;
* ``light_dir`` is the unit vector from the surface *towards* the light in that
  frame (Mitsuba's directional emitter ``direction`` is its negative).

Framing: ``fov`` (degrees, horizontal) and ``distance`` (camera to the plane
z = 0) fix the width ``2 * distance * tan(fov / 2)`` seen in the plane of the
sphere centres.  The perspective camera uses them as they are; the orthographic
camera (the default) sees exactly that width everywhere, so both cameras frame
the sphere alike.  The orthographic camera is the default because it makes the
view direction the same (+z) for every pixel, so each pixel of the sphere is one
(normal, view, light) configuration of the BSDF — what the fitting code and
per-pixel comparisons want — and it models a polarisation camera with a
telecentric or long lens looking at a small sphere.

Scene keys (``mi.traverse(mi.load_dict(sphere_scene()))``)::

    sphere.bsdf.eta, sphere.bsdf.alpha, sphere.bsdf.beta, sphere.bsdf.kappa,
    sphere.bsdf.k_s.value, sphere.bsdf.r_k.value (or .k_b.value),
    light.irradiance.value, light.to_world, sensor.to_world, ...

:func:`spheres_scene` names its spheres ``sphere_0``, ``sphere_1``, ... from
left to right, so the keys are ``sphere_0.bsdf.eta`` and so on.

Rendering: :func:`render_stokes` returns the Stokes array of
:mod:`fmbrdf_mi.stokes_io`, shape (4, H, W, C), rows top to bottom, in the
``stokes`` integrator's frame (x = image right, y = image up).
"""
from __future__ import annotations

import math
import re
import numbers
import os
import sys
import threading
import time

import numpy as np

from . import geometry as G
from . import params as P
from .params import ParameterError

#: The default sphere's material: the plugin's own defaults.
DEFAULT_MATERIAL = dict(eta=1.5, alpha=0.3, beta=2.0, kappa=10.0, k_s=1.0, r_k=1.0)
#: From the upper left, in front: 35 degrees from the view direction.
DEFAULT_LIGHT_DIR = (-0.5, 0.5, 1.0)
#: Irradiance pi: a white Lambertian surface facing the light has radiance 1.
DEFAULT_IRRADIANCE = math.pi
DEFAULT_RESOLUTION = 256
DEFAULT_SPP = 64
DEFAULT_CAMERA = "orthographic"
DEFAULT_FOV = 25.0
DEFAULT_DISTANCE = 5.0
CAMERAS = ("orthographic", "perspective")
MATERIAL_KEYS = ("eta", "alpha", "beta", "kappa", "k_s", "r_k", "k_b")

#: Three materials for :func:`spheres_scene` (the defaults of scenes/spheres.xml):
#: glossy plastic with a dark body, the default material, a rough high-index one.
EXAMPLE_MATERIALS = (
    dict(eta=1.5, alpha=0.1, beta=2.0, kappa=10.0, k_s=1.0, r_k=0.3),
    dict(DEFAULT_MATERIAL),
    dict(eta=2.0, alpha=0.6, beta=1.0, kappa=50.0, k_s=1.0, r_k=1.5),
)


# ---------------------------------------------------------------- validation
def check_material(material=None):
    """Full material dict (defaults filled in) after validation.

    Raises :class:`~fmbrdf_mi.ParameterError` naming the parameter for unknown names and
    out-of-range values.  ``k_b`` replaces the default ``r_k``; giving both is an error.
    """
    material = dict(material or {})
    unknown = sorted(set(material) - set(MATERIAL_KEYS))
    if unknown:
        raise ParameterError(f"fmbrdf: unknown material parameter '{unknown[0]}'; "
                             f"expected some of {', '.join(MATERIAL_KEYS)}")
    if "r_k" in material and "k_b" in material:
        raise ParameterError("fmbrdf: give the body albedo as 'k_b' or as 'r_k' (= k_b / k_s), not both")
    out = dict(DEFAULT_MATERIAL)
    if "k_b" in material:
        del out["r_k"]
    out.update(material)
    for name in P.SCALAR_PARAMS:
        out[name] = P.check_scalar(name, out[name])
    for name in ("k_s", "r_k", "k_b"):
        if name in out and not isinstance(out[name], dict):
            value = out[name]
            if isinstance(value, numbers.Number):
                value = float(value)
            else:
                value = tuple(float(v) for v in np.asarray(value, dtype=np.float64).ravel())
                if len(value) not in (1, 3):
                    raise ParameterError(f"fmbrdf: '{name}' must be one number or three (RGB), "
                                         f"got {len(value)} values")
                value = value[0] if len(value) == 1 else value
            P.check_albedo(name, value)
            out[name] = value
    return out


def check_light_dir(light_dir):
    """``light_dir`` as a normalised float tuple; ValueError if not finite and non-zero."""
    try:
        v = np.asarray(light_dir, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"light_dir: expected three numbers x, y, z, got {light_dir!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"light_dir: expected three finite numbers x, y, z, got {light_dir!r}")
    if not np.any(v):
        raise ValueError("light_dir: must not be the zero vector")
    with np.errstate(over="ignore", under="ignore"):
        n = np.linalg.norm(v)
    if not 1e-150 < n < 1e150:     # (1e308, 0, 0): normalised without overflow (others exactly as before)
        v = v / np.abs(v).max()
        n = np.linalg.norm(v)
    return tuple(float(x) for x in v / n)


def _check_positive(name, value, integer=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0 or (integer and v != int(v)):
        kind = "a positive integer" if integer else "a positive number"
        raise ValueError(f"{name}: expected {kind}, got {value!r}")
    return int(v) if integer else v


def check_resolution(resolution):
    """(width, height) from an int or a pair."""
    if isinstance(resolution, numbers.Number):
        r = _check_positive("resolution", resolution, integer=True)
        return r, r
    try:
        w, h = resolution
    except (TypeError, ValueError):
        raise ValueError(f"resolution: expected an int or (width, height), got {resolution!r}") from None
    return _check_positive("resolution width", w, True), _check_positive("resolution height", h, True)


def _check_camera(camera, fov, distance):
    if camera not in CAMERAS:
        raise ValueError(f"camera: expected one of {', '.join(CAMERAS)}, got {camera!r}")
    fov = _check_positive("fov", fov)
    if fov >= 180:
        raise ValueError(f"fov: expected an angle in (0, 180) degrees, got {fov:g}")
    return camera, fov, _check_positive("distance", distance)


def _check_irradiance(irradiance):
    try:
        v = float(irradiance)
    except (TypeError, ValueError):
        raise ValueError(f"irradiance: expected a number, got {irradiance!r}") from None
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"irradiance: expected a finite number >= 0, got {irradiance!r}")
    return v


def check_mesh_file(path):
    """ValueError unless ``path`` is a .ply or .obj mesh with vertices and faces (Mitsuba reports an empty one
    as an I/O error, "No such file or directory", or a failed memory map).

    Reads only what tells: a PLY's header (``element vertex N`` / ``element face N``), an OBJ's ``v`` and
    ``f`` lines.
    """
    import os

    name = os.fspath(path)
    if os.path.isdir(name):
        raise ValueError(f"mesh file {name}: is a directory, expected a .ply or .obj file")
    size = os.path.getsize(name)
    if size == 0:
        raise ValueError(f"mesh file {name}: empty (0 bytes); a .ply or .obj mesh needs vertices and faces")
    if name.lower().endswith(".ply"):
        with open(name, "rb") as f:
            head = f.read(65536)
        if not head.startswith(b"ply"):
            raise ValueError(f"mesh file {name}: not a PLY file (it does not start with 'ply')")
        if b"end_header" not in head:
            raise ValueError(f"mesh file {name}: a PLY header without end_header (truncated or not a mesh)")
        counts = dict(re.findall(rb"^element\s+(\w+)\s+(\d+)", head.split(b"end_header")[0], re.M))
        for key, what in ((b"vertex", "vertices"), (b"face", "faces")):
            if int(counts.get(key, 0)) == 0:
                raise ValueError(f"mesh file {name}: no {what} (its header says element {key.decode()} "
                                 f"{int(counts.get(key, 0))}); a mesh needs vertices and faces")
    elif name.lower().endswith(".obj"):
        seen = set()
        with open(name, "rb") as f:
            for line in f:
                tag = line.split(None, 1)[0] if line.strip() else b""
                if tag in (b"v", b"f"):
                    seen.add(tag)
                    if len(seen) == 2:
                        break
        for key, what in ((b"v", "vertices ('v' lines)"), (b"f", "faces ('f' lines)")):
            if key not in seen:
                raise ValueError(f"mesh file {name}: no {what}; a mesh needs vertices and faces")
    return name


# ---------------------------------------------------------------- scene dicts
def _mi():
    import mitsuba as mi

    if mi.variant() is None:
        raise RuntimeError("call mi.set_variant(...) first, e.g. mi.set_variant('llvm_ad_spectral_polarized')")
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


def material_bsdf(material=None):
    """The ``fmbrdf`` BSDF dict of a material (validated, defaults filled in)."""
    m = check_material(material)
    d = {"type": "fmbrdf"}
    for k, v in m.items():
        d[k] = {"type": "rgb", "value": list(v)} if isinstance(v, tuple) else loaded_texture(v)
    return d


def half_width(fov, distance):
    return distance * math.tan(math.radians(fov) / 2)


def _sensor(mi, camera, width, height, n_cells, fov, distance, spp, seed):
    T = mi.ScalarTransform4f
    look = T().look_at(origin=[0, 0, distance], target=[0, 0, 0], up=[0, 1, 0])
    half_w = n_cells * half_width(fov, distance)  # along x, at z = 0
    if camera == "orthographic":
        sensor = {"type": "orthographic", "to_world": look @ T().scale([half_w, half_w, 1.0])}
    else:
        sensor = {"type": "perspective", "to_world": look, "fov_axis": "x",
                  "fov": math.degrees(2 * math.atan(half_w / distance))}
    sensor["film"] = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                      "pixel_format": "luminance" if mi.is_monochromatic else "rgb"}
    sensor["sampler"] = {"type": "independent", "sample_count": spp, "seed": seed}
    return sensor


def _scene(mi, shapes, light_dir, irradiance, sensor):
    d = {"type": "scene",
         "integrator": {"type": "stokes", "integrator": {"type": "direct"}},
         "sensor": sensor,
         "light": {"type": "directional", "direction": [-x for x in check_light_dir(light_dir)],
                   "irradiance": _check_irradiance(irradiance)}}
    d.update(shapes)
    return d


def sphere_scene(material=None, *, light_dir=DEFAULT_LIGHT_DIR, irradiance=DEFAULT_IRRADIANCE,
                 resolution=DEFAULT_RESOLUTION, spp=DEFAULT_SPP, camera=DEFAULT_CAMERA,
                 fov=DEFAULT_FOV, distance=DEFAULT_DISTANCE, seed=0):
    """Scene dict for ``mi.load_dict``: one sphere of ``material`` under a directional light.

    ``material``: dict of some of eta, alpha, beta, kappa, k_s, r_k / k_b (the
    rest from :data:`DEFAULT_MATERIAL`); k_s, r_k, k_b may be a number, an RGB
    triple or a Mitsuba texture dict.  ``irradiance`` is that of the directional
    light (a float; in spectral variants Mitsuba's D65-shaped emission spectrum
    of that luminance).  ``resolution`` is an int or (width, height).  The
    sphere's id is ``"sphere"``, the light's ``"light"``, the sensor's ``"sensor"``.
    Needs a Mitsuba variant to be set (transforms are variant types).
    """
    mi = _mi()
    width, height = check_resolution(resolution)
    camera, fov, distance = _check_camera(camera, fov, distance)
    spp = _check_positive("spp", spp, integer=True)
    shapes = {"sphere": {"type": "sphere", "bsdf": material_bsdf(material)}}
    return _scene(mi, shapes, light_dir, irradiance,
                  _sensor(mi, camera, width, height, 1, fov, distance, spp, int(seed)))


def sphere_centres(n, fov=DEFAULT_FOV, distance=DEFAULT_DISTANCE):
    """x coordinates of the centres of :func:`spheres_scene`'s ``n`` spheres (left to right)."""
    cell = 2 * half_width(fov, distance)
    return [(i - (n - 1) / 2) * cell for i in range(n)]


def spheres_scene(materials, *, light_dir=DEFAULT_LIGHT_DIR, irradiance=DEFAULT_IRRADIANCE,
                  resolution=DEFAULT_RESOLUTION, spp=DEFAULT_SPP, camera=DEFAULT_CAMERA,
                  fov=DEFAULT_FOV, distance=DEFAULT_DISTANCE, seed=0):
    """Scene dict with one unit sphere per material, side by side along x.

    The image is ``len(materials)`` cells side by side, each framed like
    :func:`sphere_scene`: ``resolution`` and ``fov`` are per cell (an int
    resolution r gives an image of n*r by r pixels), and the centres are one
    cell width, ``2 * distance * tan(fov / 2)``, apart (:func:`sphere_centres`).
    Spheres are ``sphere_0``, ``sphere_1``, ... from left to right.
    """
    mi = _mi()
    materials = list(materials)
    if not materials:
        raise ValueError("materials: expected at least one material")
    n = len(materials)
    cw, ch = check_resolution(resolution)
    camera, fov, distance = _check_camera(camera, fov, distance)
    spp = _check_positive("spp", spp, integer=True)
    T = mi.ScalarTransform4f
    shapes = {f"sphere_{i}": {"type": "sphere", "to_world": T().translate([x, 0.0, 0.0]),
                              "bsdf": material_bsdf(m)}
              for i, (x, m) in enumerate(zip(sphere_centres(n, fov, distance), materials))}
    return _scene(mi, shapes, light_dir, irradiance,
                  _sensor(mi, camera, n * cw, ch, n, fov, distance, spp, int(seed)))


# ---------------------------------------------------------------- geometry
def _geometry(width, height, n_cells, camera, fov, distance, centres, radius):
    """Normals, view directions, mask and sphere index at the pixel centres: spheres (world units) seen by
    :func:`_sensor`'s camera, the nearest where they overlap."""
    camera, fov, distance = _check_camera(camera, fov, distance)
    half_w = n_cells * half_width(fov, distance)
    fov = math.degrees(2 * math.atan(half_w / distance))  # of the whole image, as _sensor's
    shape = (height, width)
    X, Y = G.pixel_centres(shape)
    cam = np.array([0.0, 0.0, distance])
    normals, view, label, best = np.zeros(shape + (3,)), np.zeros(shape + (3,)), np.full(shape, -1), np.inf
    for k, c in enumerate(np.asarray(centres, dtype=np.float64)):
        if camera == "orthographic":
            s = width / (2 * half_w)  # pixels per unit length
            n, m, v = G.sphere_at(X, Y, shape, (0.5 * width + s * c[0], 0.5 * height - s * c[1]), s * radius)
        else:
            f, z = G.focal_length(width, fov), distance - c[2]
            r = f * np.tan(np.arcsin(radius / np.linalg.norm(c - cam)))  # silhouette radius at angular radius
            n, m, v = G.sphere_at(X, Y, shape, (0.5 * width + f * c[0] / z, 0.5 * height - f * c[1] / z), r,
                                  camera, fov)
        p = c + radius * n
        depth = distance - p[..., 2] if camera == "orthographic" else np.linalg.norm(p - cam, axis=-1)
        hit = m & (depth < best)
        best = np.where(hit, depth, best)
        normals[hit], view[hit], label[hit] = n[hit], v[hit], k
    return normals, view, label >= 0, label


def sphere_geometry(resolution=DEFAULT_RESOLUTION, camera=DEFAULT_CAMERA, fov=DEFAULT_FOV,
                    distance=DEFAULT_DISTANCE, centre=(0.0, 0.0, 0.0), radius=1.0):
    """Analytic geometry of :func:`sphere_scene` at the pixel centres.

    Returns ``(normals (H, W, 3), view_dirs (H, W, 3), mask (H, W) bool)``:
    unit normals and unit vectors from the surface towards the camera in the
    world frame (x right, y up, z towards the camera), rows top to bottom,
    zero where the pixel centre misses the sphere (``mask`` False).
    """
    w, h = check_resolution(resolution)
    n, v, m, _ = _geometry(w, h, 1, camera, fov, distance, [centre], radius)
    return n, v, m


def spheres_geometry(n_spheres, resolution=DEFAULT_RESOLUTION, camera=DEFAULT_CAMERA,
                     fov=DEFAULT_FOV, distance=DEFAULT_DISTANCE):
    """Geometry of :func:`spheres_scene` with ``n_spheres`` spheres (``resolution`` per cell).

    Returns ``(normals, view_dirs, labels)``: labels (H, W) is the index of the
    sphere seen at each pixel centre, -1 for background.
    """
    cw, ch = check_resolution(resolution)
    centres = [(x, 0.0, 0.0) for x in sphere_centres(n_spheres, fov, distance)]
    n, v, _, labels = _geometry(n_spheres * cw, ch, n_spheres, camera, fov, distance, centres, 1.0)
    return n, v, labels


# ---------------------------------------------------------------- rendering
#: Samples per pass of :func:`render_stokes` (a pass is one Mitsuba kernel launch).
PASS_SAMPLES = 1 << 22


def _n_passes(width, height, spp):
    """A divisor of spp giving passes of about PASS_SAMPLES samples (a function of the size only)."""
    want = max(1, math.ceil(width * height * spp / PASS_SAMPLES))
    divisors = [d for d in range(1, spp + 1) if spp % d == 0]
    return min(divisors, key=lambda d: (abs(math.log(d / want)), d))


def pass_seed(seed, k):
    """Sampler seed of pass ``k`` of a render with ``seed`` (deterministic, distinct per pass)."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, k]).generate_state(1)[0])


def _duration(seconds):
    """``12.3 s``, ``4 min 05 s`` or ``2 h 03 min``: a progress line's time."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    m = int(round(seconds))
    if m < 3600:
        return f"{m // 60} min {m % 60:02d} s"
    return f"{m // 3600} h {m % 3600 // 60:02d} min"


class _Progress:
    """Prints render progress on stderr once a render has taken longer than ``delay`` seconds."""

    def __init__(self, label, n_passes, enabled=True, delay=1.0, stream=None):
        self.label, self.n, self.done = label, n_passes, 0
        self.stream = stream or sys.stderr
        self.enabled, self.delay = enabled, delay
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self.t0 = self._last = self._first = self._last_step = time.perf_counter()
        self.shown = False
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = None
        if enabled and self.tty:
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()

    def _line(self):
        t = time.perf_counter() - self.t0
        frac = self.done / self.n
        bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
        if self.done == 0:
            state = "compiling and rendering"
        elif self.done == self.n:
            state = "done"
        else:
            state = f"about {_duration(self.left())} left"
        return f"{self.label}: [{bar}] {self.done}/{self.n} passes, {_duration(t)} ({state})"

    def left(self):
        """Seconds the remaining passes take at the measured rate: the passes after the first (which also
        compiles the kernel) once there are any, else the first pass's time."""
        if self.done == 0:
            return math.nan
        if self.done == 1:
            per = self._first - self.t0
        else:
            per = (self._last_step - self._first) / (self.done - 1)
        return per * (self.n - self.done)

    def _show(self, end=""):
        with self._lock:
            if self.tty:
                self.stream.write("\r" + self._line() + " " * 4 + end)
            else:
                self.stream.write(self._line() + "\n")
            self.stream.flush()
            self.shown = True

    def _tick(self):
        while not self._stop.wait(0.25):
            if time.perf_counter() - self.t0 > self.delay:
                self._show()

    def step(self):
        now = self._last_step = time.perf_counter()
        if self.done == 0:
            self._first = now
        self.done += 1
        if (self.enabled and not self.tty and now - self.t0 > self.delay
                and (self.done == self.n or now - self._last >= 1.0)):  # a line a second at most
            self._last = now
            self._show()

    def close(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.enabled and self.tty and self.shown:
            self._show(end="\n")


def render_stokes(scene, spp=None, seed=0, progress=True):
    """Render ``scene`` (a loaded ``mi.Scene`` with the ``stokes`` integrator).

    Returns the Stokes array (4, H, W, C) of :mod:`fmbrdf_mi.stokes_io`,
    float32, C = 3 (R, G, B) or C = 1 in monochrome variants.  ``spp`` defaults
    to the scene sampler's sample count.  The samples are split into equal
    passes of about :data:`PASS_SAMPLES` samples (their number depends on the
    image size and spp only; pass k uses the seed :func:`pass_seed` (seed, k)),
    so the result is a deterministic function of ``seed``.  With ``progress``,
    renders longer than a second report their progress on stderr.
    """
    import drjit as dr
    import mitsuba as mi

    from .stokes_io import stokes_from_film

    if not mi.is_polarized:
        raise ValueError(f"render_stokes: variant {mi.variant()} is not polarised; "
                         "use e.g. llvm_ad_spectral_polarized or llvm_ad_mono_polarized")
    from ._paths import check_render_size

    if not scene.sensors():
        raise ValueError("render_stokes: the scene has no sensor (camera) to render from")
    sensor = scene.sensors()[0]
    film = sensor.film()
    width, height = (int(x) for x in film.crop_size())
    check_render_size(width, height)
    sampler = sensor.sampler()
    scene_spp = int(sampler.sample_count())
    spp = _check_positive("spp", scene_spp if spp is None else spp, integer=True)
    n = _n_passes(width, height, spp)
    bar = _Progress(f"{width}x{height}, {spp} spp", n, enabled=progress)
    try:
        total = None
        for k in range(n):
            img = mi.render(scene, spp=spp // n, seed=pass_seed(seed, k))
            total = img if total is None else total + img
            dr.eval(total)
            bar.step()
        arr = np.asarray(total, dtype=np.float32) / n
    finally:
        bar.close()
        sampler.set_sample_count(scene_spp)  # mi.render(spp=...) changes it
    names = [f.name for f in film.bitmap().struct_()]
    stokes = stokes_from_film(arr, names)
    if mi.is_monochromatic and stokes.shape[-1] == 3:
        stokes = stokes[..., :1]
    return np.ascontiguousarray(stokes)


# ---------------------------------------------------------------- description
def _plain(value):
    """A traversed parameter value as a float or a list of floats (None if not numeric)."""
    import drjit as dr

    try:
        arr = np.asarray(dr.detach(value), dtype=np.float64).ravel()
    except Exception:
        return None
    if arr.size == 0:
        return None
    return float(arr[0]) if arr.size == 1 else [float(x) for x in arr]


def scene_materials(scene):
    """{shape id: {parameter: value}} of the fmbrdf BSDFs of a loaded scene (for metadata).

    Albedos given as RGB in spectral variants appear as Mitsuba's spectral
    upsampling coefficients, not as RGB.
    """
    import mitsuba as mi

    out = {}
    for key, value in mi.traverse(scene).items():
        m = re.match(r"^(.*)\.bsdf\.(eta|alpha|beta|kappa|k_s|r_k|k_b)(\.value)?$", key)
        if m:
            v = _plain(value)
            if v is not None:
                out.setdefault(m.group(1), {})[m.group(2)] = v
    return out


def scene_lights(scene):
    """[{id, light_dir}] of the directional emitters of a loaded scene (light_dir: towards the light)."""
    import mitsuba as mi

    params = mi.traverse(scene)
    out = []
    for emitter in scene.emitters():
        eid = emitter.id()
        if emitter.class_name() != "DirectionalEmitter" or f"{eid}.to_world" not in params:
            continue
        m = np.asarray(params[f"{eid}.to_world"].matrix, dtype=np.float64).reshape(4, 4)
        d = m[:3, 2]  # the emitter radiates along its local +z
        out.append({"id": eid, "light_dir": [float(x) for x in -d / np.linalg.norm(d)]})
    return out


def scene_camera(scene):
    """{type, to_world (4x4 rows), fov (perspective), resolution} of the scene's first sensor."""
    import mitsuba as mi

    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    out = {"type": sensor.class_name()}
    if "to_world" in params:
        out["to_world"] = np.asarray(params["to_world"].matrix, dtype=np.float64).reshape(4, 4).tolist()
    if "x_fov" in params:
        out["fov_x"] = _plain(params["x_fov"])
    out["resolution"] = [int(x) for x in sensor.film().crop_size()]
    return out


#: Albedo texture files (:func:`texture_bitmap`): EXR through the OpenEXR package, the others through Mitsuba.
TEXTURE_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg", ".hdr", ".pfm", ".ppm", ".tga", ".bmp")

#: What an albedo texture file must be, as the error messages say it.
TEXTURE_KINDS = f"an image file ({', '.join(TEXTURE_EXTENSIONS)}) with one channel (Y) or three (R, G, B)"

#: EXR channel layouts a texture takes, in the order Mitsuba's bitmap expects them (Y[A], RGB[A]).
_EXR_LAYOUTS = (("R", "G", "B", "A"), ("R", "G", "B"), ("Y", "A"), ("Y",))


def texture_bitmap(path):
    """The ``mi.Bitmap`` of an albedo texture file (no Mitsuba variant needed).  An EXR is read with the
    OpenEXR package (:func:`fmbrdf_mi.stokes_io.read_exr`) and handed over as an array, because Mitsuba's
    EXR reader hangs in a process allowed one CPU (cluster jobs, ``taskset``); other formats are read by
    Mitsuba.  ValueError naming the file unless it is a readable image of one channel (Y, or any one name
    in an EXR) or three (R, G, B), each optionally with alpha (:data:`TEXTURE_KINDS`)."""
    import mitsuba as mi

    path = os.fspath(path)
    if os.path.isdir(path) or not os.path.isfile(path):
        raise ValueError(f"texture {path}: {'is a directory' if os.path.isdir(path) else 'no such file'}; "
                         f"expected {TEXTURE_KINDS}")
    if path.lower().endswith(".exr"):
        from .stokes_io import read_exr

        try:
            _, channels = read_exr(path)
        except ValueError as e:
            raise ValueError(f"texture {e}; expected {TEXTURE_KINDS}") from None
        names = tuple(channels)
        order = next((c for c in _EXR_LAYOUTS if set(c) == set(names)), names if len(names) == 1 else None)
        if order is None:
            raise ValueError(f"texture {path}: {len(names)} channels ({', '.join(sorted(names))}); expected "
                             f"{TEXTURE_KINDS}")
        pixels = np.stack([np.asarray(channels[c], dtype=np.float32) for c in order], axis=-1)
        return mi.Bitmap(np.ascontiguousarray(pixels))
    try:
        bitmap = mi.Bitmap(path)
    except Exception as e:     # Mitsuba's readers raise RuntimeErrors naming the file
        why = " ".join(str(e).replace(f'"{path}": ', "").split())
        raise ValueError(f"texture {path}: not a readable image ({why}); expected {TEXTURE_KINDS}") from None
    fmt = mi.Bitmap.PixelFormat
    if bitmap.pixel_format() not in (fmt.Y, fmt.YA, fmt.RGB, fmt.RGBA):
        raise ValueError(f"texture {path}: {bitmap.channel_count()} channels ({bitmap.pixel_format().name}); "
                         f"expected {TEXTURE_KINDS}")
    return bitmap


def texture_channels(path):
    """1 (a grey texture) or 3 (R, G, B) for an albedo texture file, read and checked by :func:`texture_bitmap`."""
    import mitsuba as mi

    fmt = texture_bitmap(path).pixel_format()
    return 1 if fmt in (mi.Bitmap.PixelFormat.Y, mi.Bitmap.PixelFormat.YA) else 3


def texture_file_dict(path):
    """The Mitsuba texture dict of an albedo map file (a bitmap: .exr, .png, .jpg, ...): its values used as
    they are (``raw``: no sRGB decoding), bilinear between texels, over the shape's uv.  It names the file
    (a description a scene's metadata can hold); :func:`material_bsdf` reads the file
    (:func:`texture_bitmap`) when it builds the BSDF."""
    return {"type": "bitmap", "filename": os.path.abspath(os.fspath(path)), "raw": True}


def loaded_texture(value):
    """``value`` with a bitmap texture's file read by :func:`texture_bitmap` (``filename`` replaced by
    ``bitmap``), so that Mitsuba's own EXR reader is never used; anything else unchanged."""
    if not (isinstance(value, dict) and value.get("type") == "bitmap" and "filename" in value):
        return value
    out = {k: v for k, v in value.items() if k != "filename"}
    out["bitmap"] = texture_bitmap(value["filename"])
    return out


def _centre_hits(scene):
    """The surface interactions of the rays through each pixel's centre of ``scene``'s first sensor, which
    of them hit, and the film's (H, W)."""
    mi = _mi()
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    ys, xs = np.mgrid[0:h, 0:w]
    pos = mi.Point2f(((xs.ravel() + 0.5) / w).astype(np.float32), ((ys.ravel() + 0.5) / h).astype(np.float32))
    n = w * h
    ray, _ = sensor.sample_ray(mi.Float(np.zeros(n, np.float32)), mi.Float(np.full(n, 0.5, np.float32)), pos,
                               mi.Point2f(np.full(n, 0.5, np.float32), np.full(n, 0.5, np.float32)))
    si = scene.ray_intersect(ray)
    return si, np.asarray(si.is_valid(), bool), (h, w)


def true_albedo_maps(scene, material, channels=False):
    """The albedos the camera sees at each pixel's centre of ``scene``'s first sensor: {"k_s": (H, W),
    "k_b": (H, W)} (0 where no object is hit), for a ``material`` (:func:`check_material`'s keys) whose
    k_s, k_b or r_k may be textures: each pixel's ray is intersected with the scene and the textures
    evaluated at the hit's uv (k_b = r_k k_s when the body is given as r_k).  Monochrome values (an RGB
    texture: the mean of its channels); ``channels`` (an RGB or spectral variant): (3, H, W) maps, R, G, B
    (what a colour sensor's channels see; a grey value or texture is the same in all three).  A pixel whose
    footprint straddles a texture edge renders the mean over its area; these maps are the centre's value."""
    mi = _mi()
    si, hit, (h, w) = _centre_hits(scene)
    m = check_material(material)

    per = bool(channels) and not mi.is_monochromatic
    shape = (3, h, w) if per else (h, w)

    def values(key, default):
        v = m.get(key, default)
        if isinstance(v, dict):
            tex = mi.load_dict(loaded_texture(v))
            out = None
            if not mi.is_monochromatic and hasattr(tex, "eval_3"):
                try:
                    out = np.asarray(tex.eval_3(si), dtype=np.float64).reshape(3, -1)
                except RuntimeError:    # a one-channel bitmap in an RGB or spectral variant: grey
                    out = None
            if out is None:
                out = np.broadcast_to(np.asarray(tex.eval_1(si), dtype=np.float64).ravel(), (3, h * w))
            out = out if per else out.mean(axis=0)
            return np.where(hit, out, 0.0)
        if per:
            rgb = np.broadcast_to(np.asarray(v, dtype=np.float64).ravel(), (3,)) if np.size(v) in (1, 3) \
                else np.full(3, float(np.mean(v)))
            return np.where(hit, rgb[:, None], 0.0)
        return np.where(hit, float(np.mean(v)), 0.0)

    ks = values("k_s", P.DEFAULT_K_S)
    kb = values("k_b", 0.0) if "k_b" in m else values("r_k", P.DEFAULT_R_K) * ks
    return {"k_s": ks.reshape(shape), "k_b": kb.reshape(shape)}


def label_texture(labels, m):
    """The Mitsuba texture dict of material ``m``'s indicator over the shape's uv: 1 where the uv label image
    ``labels`` (H, W ints) is ``m``, else 0, nearest texel (no blending between materials)."""
    mi = _mi()
    ind = (np.asarray(labels) == m).astype(np.float32)[..., None]
    return {"type": "bitmap", "bitmap": mi.Bitmap(ind), "raw": True, "filter_type": "nearest"}


def materials_bsdf(materials, labels):
    """The BSDF dict of a shape made of several materials: ``materials`` a list of M material dicts
    (:func:`material_bsdf`), ``labels`` (H, W) the material of each texel of the shape's uv (0 .. M-1).
    See :func:`blend_bsdfs`."""
    return blend_bsdfs([material_bsdf(m) for m in materials], labels)


def blend_bsdfs(bsdfs, labels):
    """One BSDF dict from M BSDFs (dicts or loaded objects), ``labels`` (H, W) the index of the BSDF at
    each texel of the shape's uv (0 .. M-1).  BSDF m > 0 is blended over the ones before it with its
    indicator as the weight (``blendbsdf``), so a point inside material m's texels is material m's BSDF
    exactly; a pixel whose footprint straddles a boundary renders the mix over its area.
    :func:`blend_paths` names each BSDF's place in the result (for ``mi.traverse``)."""
    labels = np.asarray(labels)
    bsdf = bsdfs[0]
    for m in range(1, len(bsdfs)):
        bsdf = {"type": "blendbsdf", "weight": label_texture(labels, m), "bsdf_0": bsdf, "bsdf_1": bsdfs[m]}
    return bsdf


def blend_paths(count):
    """The ``mi.traverse`` key prefix of each of the ``count`` BSDFs of :func:`blend_bsdfs` under the
    blend's own key, e.g. ``["bsdf_0.bsdf_0", "bsdf_0.bsdf_1", "bsdf_1"]`` for 3 ("" for one BSDF)."""
    if count == 1:
        return [""]
    inner = blend_paths(count - 1)
    return [f"bsdf_0.{p}" if p else "bsdf_0" for p in inner] + ["bsdf_1"]


def labels_at(si, hit, labels, count):
    """The material (0 .. count-1) of :func:`blend_bsdfs`'s uv label image ``labels`` at the surface
    interactions ``si`` (flat, as NumPy ints), -1 where ``hit`` (flat bool) is false."""
    mi = _mi()
    out = np.where(hit, 0, -1)
    for m in range(1, count):
        tex = mi.load_dict(label_texture(labels, m))
        v = np.asarray(tex.eval_1(si), dtype=np.float64).ravel()
        out[hit & (v > 0.5)] = m
    return out


def true_label_map(scene, labels, count):
    """The material the camera sees at each pixel's centre of ``scene``'s first sensor (H, W): 0 .. count-1
    where the ray hits the shape, -1 elsewhere (``labels``: the uv label image of :func:`materials_bsdf`)."""
    si, hit, (h, w) = _centre_hits(scene)
    return labels_at(si, hit, labels, count).reshape(h, w)
