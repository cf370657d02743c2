"""Dataset configuration: reading (TOML or JSON), validation, and drawing samples.

A configuration gives, for every quantity of a sample, a constant or a
distribution.  Scalar distributions::

    1.5                          a constant
    {"uniform": [lo, hi]}        uniform on [lo, hi)
    {"loguniform": [lo, hi]}     log-uniform on [lo, hi), 0 < lo
    {"choice": [a, b, ...]}      one of the values, equally likely

Every value a distribution can produce is checked against the quantity's valid
range when the configuration is read; errors name the key path, e.g.
``material.eta.uniform: high 3.5 outside (1, 3]``.  The example
``scenes/dataset_example.toml`` documents every key.

Sample ``i`` of a dataset with seed ``s`` is drawn from its own generator
``numpy.random.default_rng([s, i])``, never from a stream shared between
samples, so any subset of the samples (a shard, or what is left after an
interruption) is drawn exactly as in the whole set.
"""
from __future__ import annotations

import hashlib
import json
import math
import numbers
import os

import numpy as np

from .. import params as P
from .._paths import resolve_builtin
from .. import scene as S

FORMAT = "fmbrdf-mi-dataset/1"

#: Mitsuba's built-in shapes offered, besides meshes (.ply, .obj).
BUILTIN_SHAPES = ("sphere", "cube", "cylinder", "disk", "rectangle")
MESH_SUFFIXES = (".ply", ".obj")
CAMERAS = S.CAMERAS
#: Polarised variants a dataset can be rendered in.
VARIANTS = ("llvm_ad_spectral_polarized", "llvm_ad_mono_polarized",
            "cuda_ad_spectral_polarized", "cuda_ad_mono_polarized")

#: Defaults: those of fmbrdf_mi.scene (the ``fmbrdf-mi render`` sphere), but 16 spp.
DEFAULTS = {
    "seed": 0,
    "render": {"resolution": S.DEFAULT_RESOLUTION, "spp": 16, "variant": "llvm_ad_spectral_polarized"},
    "shape": {"type": "sphere", "rotate": False},
    "camera": {"type": S.DEFAULT_CAMERA, "distance": S.DEFAULT_DISTANCE, "fov": S.DEFAULT_FOV,
               "elevation": 0.0, "azimuth": 0.0},
    "light": {"direction": list(S.DEFAULT_LIGHT_DIR), "irradiance": S.DEFAULT_IRRADIANCE},
    "material": {k: S.DEFAULT_MATERIAL[k] for k in ("eta", "alpha", "beta", "kappa", "k_s")},
}
DEFAULT_R_K = S.DEFAULT_MATERIAL["r_k"]
SECTIONS = {
    "render": ("resolution", "spp", "variant"),
    "shape": ("type", "rotate", "labels"),
    "camera": ("type", "distance", "fov", "elevation", "azimuth"),
    "light": ("direction", "irradiance"),
    "material": ("eta", "alpha", "beta", "kappa", "k_s", "r_k", "k_b"),
}
TOP_KEYS = ("samples", "seed", "description") + tuple(SECTIONS)

#: The most samples a dataset may have: the run keeps lists of the sample indices (a shard's, those still
#: to render) and checks every sample's files, so a count far beyond what can be rendered would fill memory
#: before the first render; a larger collection is several datasets with their own seeds.
MAX_SAMPLES = 10 ** 6

INF = math.inf
MATERIAL_KEYS = SECTIONS["material"]


class DatasetConfigError(ValueError):
    """A dataset configuration is unreadable or has a bad key or value (the message names the key)."""


# ------------------------------------------------------------------ ranges
class Range:
    """An interval of valid values, printed as e.g. ``(1, 3]``."""

    def __init__(self, lo, hi, lo_incl=True, hi_incl=True):
        self.lo, self.hi, self.lo_incl, self.hi_incl = lo, hi, lo_incl, hi_incl

    def __contains__(self, v):
        return (math.isfinite(v) and (v >= self.lo if self.lo_incl else v > self.lo)
                and (v <= self.hi if self.hi_incl else v < self.hi))

    def __str__(self):
        def f(x):
            return "inf" if x == INF else "-inf" if x == -INF else f"{x:g}"
        return f"{'[' if self.lo_incl else '('}{f(self.lo)}, {f(self.hi)}{']' if self.hi_incl else ')'}"


def _material_range(name):
    _, lo, hi, lo_incl, _ = P.SCALAR_PARAMS[name]
    return Range(lo, hi, lo_incl, True)


ALBEDO = Range(0.0, INF, True, False)
RANGES = {
    "material.eta": _material_range("eta"),
    "material.alpha": _material_range("alpha"),
    "material.beta": _material_range("beta"),
    "material.kappa": _material_range("kappa"),
    "material.k_s": ALBEDO, "material.r_k": ALBEDO, "material.k_b": ALBEDO,
    "light.irradiance": Range(0.0, INF, True, False),
    # shapes are scaled into the unit sphere: the camera must stay outside it
    "camera.distance": Range(1.0, INF, False, False),
    "camera.fov": Range(0.0, 180.0, False, False),
    "camera.elevation": Range(-90.0, 90.0, False, False),
    "camera.azimuth": Range(-INF, INF, False, False),
}


# ------------------------------------------------------------------ helpers
def _err(path, msg):
    return DatasetConfigError(f"{path}: {msg}")


def _is_number(x):
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _number(path, x, rng=None):
    if not _is_number(x):
        raise _err(path, f"expected a number, got {x!r}")
    v = float(x)
    if rng is not None and v not in rng:
        raise _err(path, f"{v:g} outside {rng}")
    if not math.isfinite(v):
        raise _err(path, f"expected a finite number, got {x!r}")
    return v


def _integer(path, x, low):
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        if _is_number(x) and float(x).is_integer():
            x = int(x)
        else:
            raise _err(path, f"expected an integer, got {x!r}")
    if x < low:
        raise _err(path, f"expected an integer >= {low}, got {x}")
    return int(x)


def _table(path, x, keys):
    if not isinstance(x, dict):
        raise _err(path or "config", f"expected a table of {', '.join(keys)}, got {x!r}")
    unknown = [k for k in x if k not in keys]
    if unknown:
        where = f"{path}.{unknown[0]}" if path else unknown[0]
        raise _err(where, f"unknown key; expected one of {', '.join(keys)}")
    return x


def _single_key(path, x, kinds):
    """(kind, argument) of a one-key distribution table like {"uniform": [lo, hi]}."""
    if len(x) != 1:
        raise _err(path, f"expected one of {', '.join(kinds)} as the only key, got {', '.join(map(str, x)) or 'none'}")
    (kind, arg), = x.items()
    if kind not in kinds:
        raise _err(f"{path}.{kind}", f"unknown distribution; expected one of {', '.join(kinds)}")
    return kind, arg


# ------------------------------------------------------------------ distributions
class Const:
    def __init__(self, value):
        self.value = value

    def draw(self, rng):
        return self.value

    def canonical(self):
        return self.value


class Uniform:
    def __init__(self, lo, hi):
        self.lo, self.hi = lo, hi

    def draw(self, rng):
        return float(rng.uniform(self.lo, self.hi))

    def canonical(self):
        return {"uniform": [self.lo, self.hi]}


class LogUniform(Uniform):
    def draw(self, rng):
        # exp(log(lo)) can round below lo (0.01 -> 0.009999999999999998): clip to the range
        return float(min(max(math.exp(rng.uniform(math.log(self.lo), math.log(self.hi))), self.lo), self.hi))

    def canonical(self):
        return {"loguniform": [self.lo, self.hi]}


class Choice:
    def __init__(self, values):
        self.values = values

    def draw(self, rng):
        return self.values[int(rng.integers(len(self.values)))]

    def canonical(self):
        return {"choice": list(self.values)}


class PerChannel:
    """Three independent scalar distributions: an RGB value."""

    def __init__(self, channels):
        self.channels = channels

    def draw(self, rng):
        return [c.draw(rng) for c in self.channels]

    def canonical(self):
        return [c.canonical() for c in self.channels]


class Cone:
    """Unit vectors uniform over the solid angle of a cone (half angle in degrees)."""

    def __init__(self, axis, angle):
        self.axis, self.angle = axis, angle

    def draw(self, rng):
        u, v = rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)
        cos_max = math.cos(math.radians(self.angle))
        cos_t = 1.0 - u * (1.0 - cos_max)
        sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
        phi = 2.0 * math.pi * v
        a = np.asarray(self.axis)
        t = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        t /= np.linalg.norm(t)
        b = np.cross(a, t)
        d = cos_t * a + sin_t * (math.cos(phi) * t + math.sin(phi) * b)
        return [float(x) for x in d / np.linalg.norm(d)]

    def canonical(self):
        return {"cone": {"axis": list(self.axis), "angle": self.angle}}


def scalar_dist(path, x, rng=None):
    """A scalar distribution from its config value; every value it can draw lies in ``rng``."""
    if _is_number(x):
        return Const(_number(path, x, rng))
    if isinstance(x, dict):
        kind, arg = _single_key(path, x, ("uniform", "loguniform", "choice"))
        p = f"{path}.{kind}"
        if kind == "choice":
            if not isinstance(arg, list) or not arg:
                raise _err(p, f"expected a non-empty list of numbers, got {arg!r}")
            return Choice([_number(f"{p}[{i}]", v, rng) for i, v in enumerate(arg)])
        if not isinstance(arg, list) or len(arg) != 2 or not all(_is_number(v) for v in arg):
            raise _err(p, f"expected [low, high] (two numbers), got {arg!r}")
        lo, hi = float(arg[0]), float(arg[1])
        for name, v in (("low", lo), ("high", hi)):
            if not math.isfinite(v):
                raise _err(p, f"{name} {v:g} is not finite")
            if rng is not None and v not in rng:
                raise _err(p, f"{name} {v:g} outside {rng}")
        if lo > hi:
            raise _err(p, f"low {lo:g} > high {hi:g}")
        if kind == "loguniform":
            if lo <= 0:
                raise _err(p, f"low {lo:g} must be > 0 for a log-uniform distribution")
            return LogUniform(lo, hi)
        return Uniform(lo, hi)
    raise _err(path, f"expected a number or a distribution ({{uniform = [lo, hi]}}, "
                     f"{{loguniform = [lo, hi]}}, {{choice = [...]}}), got {x!r}")


def albedo_dist(path, x, allow_rgb, rng=None):
    """An albedo: a scalar distribution (grey), three of them (R, G, B), or a choice of RGB triples."""
    rng = RANGES[path] if rng is None else rng
    if isinstance(x, list):
        if len(x) != 3:
            raise _err(path, f"expected three values (R, G, B), got {len(x)}")
        d = PerChannel([scalar_dist(f"{path}[{i}]", v, rng) for i, v in enumerate(x)])
    elif isinstance(x, dict) and list(x) == ["choice"] and isinstance(x["choice"], list) \
            and any(isinstance(v, list) for v in x["choice"]):
        vals = x["choice"]
        out = []
        for i, v in enumerate(vals):
            p = f"{path}.choice[{i}]"
            if not isinstance(v, list) or len(v) != 3:
                raise _err(p, f"expected an RGB triple [r, g, b], got {v!r}")
            out.append([_number(f"{p}[{j}]", c, rng) for j, c in enumerate(v)])
        d = Choice(out)
    else:
        return scalar_dist(path, x, rng)
    if not allow_rgb:
        raise _err(path, "an RGB albedo needs a spectral variant (render.variant); "
                         "monochrome variants take one number")
    return d


def _vector(path, x):
    if not isinstance(x, list) or len(x) != 3 or not all(_is_number(v) for v in x):
        raise _err(path, f"expected three numbers [x, y, z], got {x!r}")
    v = np.array([float(c) for c in x])
    n = np.linalg.norm(v)
    if not np.all(np.isfinite(v)) or n < 1e-12:
        raise _err(path, f"expected a finite non-zero vector, got {x!r}")
    return [float(c) for c in v / n]


def direction_dist(path, x):
    """A direction: [x, y, z], {"cone": {"axis": [...], "angle": deg}} or {"choice": [[...], ...]}."""
    if isinstance(x, list):
        return Const(_vector(path, x))
    if isinstance(x, dict):
        kind, arg = _single_key(path, x, ("cone", "choice"))
        p = f"{path}.{kind}"
        if kind == "choice":
            if not isinstance(arg, list) or not arg:
                raise _err(p, f"expected a non-empty list of directions, got {arg!r}")
            return Choice([_vector(f"{p}[{i}]", v) for i, v in enumerate(arg)])
        _table(p, arg, ("axis", "angle"))
        axis = _vector(f"{p}.axis", arg.get("axis", [0.0, 0.0, 1.0]))
        if "angle" not in arg:
            raise _err(f"{p}.angle", "missing (half angle of the cone in degrees, (0, 180])")
        angle = _number(f"{p}.angle", arg["angle"], Range(0.0, 180.0, False, True))
        return Cone(axis, angle)
    raise _err(path, f"expected [x, y, z], {{cone = {{axis = [x, y, z], angle = degrees}}}} "
                     f"or {{choice = [[x, y, z], ...]}}, got {x!r}")


def _shape_name(path, x, base_dir):
    if not isinstance(x, str) or not x:
        raise _err(path, f"expected a shape name ({', '.join(BUILTIN_SHAPES)}) or a .ply/.obj file, got {x!r}")
    if x in BUILTIN_SHAPES:
        return x
    if x.lower().endswith(MESH_SUFFIXES):
        full = os.path.join(base_dir, x)
        if not os.path.isfile(full):
            raise _err(path, f"mesh file {x!r} not found (looked for {os.path.abspath(full)})")
        try:
            S.check_mesh_file(full)
        except (OSError, ValueError) as e:
            raise _err(path, str(e)) from None
        return x
    raise _err(path, f"unknown shape {x!r}; expected one of {', '.join(BUILTIN_SHAPES)} "
                     f"or a mesh file ending in .ply or .obj")


def string_dist(path, x, check):
    if isinstance(x, dict):
        kind, arg = _single_key(path, x, ("choice",))
        p = f"{path}.choice"
        if not isinstance(arg, list) or not arg:
            raise _err(p, f"expected a non-empty list, got {arg!r}")
        return Choice([check(f"{p}[{i}]", v) for i, v in enumerate(arg)])
    return Const(check(path, x))


def _camera_name(path, x):
    if x not in CAMERAS:
        raise _err(path, f"expected one of {', '.join(CAMERAS)}, got {x!r}")
    return x


def _resolution(path, x):
    if isinstance(x, list):
        if len(x) != 2:
            raise _err(path, f"expected an integer or [width, height], got {x!r}")
        return [_integer(f"{path}[0]", x[0], 1), _integer(f"{path}[1]", x[1], 1)]
    r = _integer(path, x, 1)
    return [r, r]


# ------------------------------------------------------------------ the config
class DatasetConfig:
    """A validated dataset configuration (see :func:`load_config`)."""

    def __init__(self, raw, base_dir="."):
        if not isinstance(base_dir, (str, os.PathLike)):
            raise DatasetConfigError(f"base_dir: expected a directory name, got {base_dir!r}")
        self.base_dir = os.path.abspath(base_dir)
        raw = _table("", raw, TOP_KEYS)
        if "samples" not in raw:
            raise _err("samples", "missing (the number of samples N, an integer >= 1)")
        self.samples = _integer("samples", raw["samples"], 1)
        if self.samples > MAX_SAMPLES:
            raise _err("samples", f"expected an integer in [1, {MAX_SAMPLES}] (the number of samples N; more: several "
                                  f"datasets with their own seeds), got {self.samples}")
        self.seed = _integer("seed", raw.get("seed", DEFAULTS["seed"]), 0)
        if self.seed >= 2 ** 63:
            raise _err("seed", f"expected an integer < 2**63, got {self.seed}")
        desc = raw.get("description", "")
        if not isinstance(desc, str):
            raise _err("description", f"expected a string, got {desc!r}")
        self.description = desc
        sec = {name: dict(_table(name, raw.get(name, {}), keys)) for name, keys in SECTIONS.items()
               if name != "material"}  # material: a table, or a list of them (read below)

        r = sec["render"]
        self.resolution = _resolution("render.resolution", r.get("resolution", DEFAULTS["render"]["resolution"]))
        from .._paths import check_render_size

        try:  # a sample also keeps its normal map (float64, 24 bytes per pixel) and mask
            check_render_size(*self.resolution, what="render.resolution", extra_per_pixel=32)
        except ValueError as e:
            raise DatasetConfigError(str(e)) from None
        self.spp = _integer("render.spp", r.get("spp", DEFAULTS["render"]["spp"]), 1)
        self.variant = r.get("variant", DEFAULTS["render"]["variant"])
        if self.variant not in VARIANTS:
            raise _err("render.variant", f"expected one of {', '.join(VARIANTS)}, got {self.variant!r}")
        self.spectral = "spectral" in self.variant

        s = sec["shape"]
        self.shape = string_dist("shape.type", s.get("type", DEFAULTS["shape"]["type"]),
                                 lambda p, x: _shape_name(p, x, self.base_dir))
        self.rotate = s.get("rotate", DEFAULTS["shape"]["rotate"])
        if not isinstance(self.rotate, bool):
            raise _err("shape.rotate", f"expected true or false, got {self.rotate!r}")

        c = sec["camera"]
        self.camera = string_dist("camera.type", c.get("type", DEFAULTS["camera"]["type"]), _camera_name)
        self.camera_dists = {k: scalar_dist(f"camera.{k}", c.get(k, DEFAULTS["camera"][k]), RANGES[f"camera.{k}"])
                             for k in ("distance", "fov", "elevation", "azimuth")}

        li = sec["light"]
        self.light_dir = direction_dist("light.direction", li.get("direction", DEFAULTS["light"]["direction"]))
        self.irradiance = scalar_dist("light.irradiance", li.get("irradiance", DEFAULTS["light"]["irradiance"]),
                                      RANGES["light.irradiance"])

        self.labels_file = sec["shape"].get("labels")
        self.uv_labels = None
        if self.labels_file is not None:
            self.uv_labels = self._read_labels(self.labels_file)
        mats = raw.get("material", {})
        self.several = self.uv_labels is not None
        if isinstance(mats, list):
            if not self.several:
                raise _err("material", "several materials ([[material]] tables, a list) need shape.labels, "
                                       "a uv label image saying which material is where")
            count = int(self.uv_labels.max()) + 1
            if len(mats) != count:
                raise _err("shape.labels", f"{self.labels_file} has {count} materials (labels 0 .. {count - 1}) "
                                           f"but material lists {len(mats)}; give one [[material]] table per label")
            paths = [f"material[{i}]" for i in range(count)]
        else:
            if self.several:
                count = int(self.uv_labels.max()) + 1
                raise _err("material", f"shape.labels {self.labels_file} has {count} materials (labels 0 .. "
                                       f"{count - 1}): give material as {count} [[material]] tables (a list), "
                                       "one per label")
            mats, paths = [mats], ["material"]
        #: per material: {name: distribution}, and its body key ("k_b" or "r_k")
        self.materials, self.body_keys = [], []
        for path, m in zip(paths, mats):
            dists, body = self._material(path, dict(_table(path, m, MATERIAL_KEYS)))
            self.materials.append(dists)
            self.body_keys.append(body)
        self.material = self.materials[0]   # the one material of a scene without shape.labels
        self.body_key = self.body_keys[0]

    def _material(self, path, m):
        if "r_k" in m and "k_b" in m:
            raise _err(path, "give the body albedo as k_b or as r_k (= k_b / k_s), not both")
        body = "k_b" if "k_b" in m else "r_k"
        out = {}
        for k in ("eta", "alpha", "beta", "kappa"):
            out[k] = scalar_dist(f"{path}.{k}", m.get(k, DEFAULTS["material"][k]), RANGES[f"material.{k}"])
        out["k_s"] = albedo_dist(f"{path}.k_s", m.get("k_s", DEFAULTS["material"]["k_s"]), self.spectral,
                                 RANGES["material.k_s"])
        out[body] = albedo_dist(f"{path}.{body}", m.get(body, DEFAULT_R_K), self.spectral, RANGES[f"material.{body}"])
        return out, body

    def _read_labels(self, name):
        """shape.labels: the uv label image (relative to the config's directory), every material present."""
        from ..fit.errors import InputError
        from ..fit.inputs.labels import read_uv_labels

        if not isinstance(name, str) or not name.lower().endswith((".png", ".npy")):
            raise _err("shape.labels", f"expected a uv label image file name (.png or .npy, relative to the "
                                       f"config), got {name!r}")
        full = os.path.join(self.base_dir, name)
        if not os.path.isfile(full):
            raise _err("shape.labels", f"label image {name!r} not found (looked for {os.path.abspath(full)})")
        try:
            labels = read_uv_labels(full, what="shape.labels")
        except InputError as e:
            raise DatasetConfigError(str(e)) from None
        missing = sorted(set(range(int(labels.max()) + 1)) - set(np.unique(labels).tolist()))
        if missing:
            raise _err("shape.labels", f"{name} has no texel of material {missing[0]} (labels 0 .. "
                                       f"{int(labels.max())} must all be used)")
        return labels

    # ---------------------------------------------------------------- canonical form
    def mesh_files(self):
        """Mesh file names used (as written in the config)."""
        names = self.shape.values if isinstance(self.shape, Choice) else [self.shape.value]
        return sorted({n for n in names if n not in BUILTIN_SHAPES})

    def mesh_path(self, name):
        return os.path.join(self.base_dir, name)

    def canonical(self):
        """The configuration with defaults filled in, as JSON data (written to dataset.json)."""
        meshes = {}
        for name in self.mesh_files():
            with open(self.mesh_path(name), "rb") as f:
                meshes[name] = hashlib.sha256(f.read()).hexdigest()
        return {
            "samples": self.samples, "seed": self.seed, "description": self.description,
            "render": {"resolution": list(self.resolution), "spp": self.spp, "variant": self.variant},
            "shape": dict({"type": self.shape.canonical(), "rotate": self.rotate, "mesh_sha256": meshes},
                          **self._labels_canonical()),
            "camera": dict({"type": self.camera.canonical()},
                           **{k: d.canonical() for k, d in self.camera_dists.items()}),
            "light": {"direction": self.light_dir.canonical(), "irradiance": self.irradiance.canonical()},
            "material": ([{k: d.canonical() for k, d in m.items()} for m in self.materials] if self.several
                         else {k: d.canonical() for k, d in self.material.items()}),
        }

    def _labels_canonical(self):
        if not self.several:
            return {}
        with open(os.path.join(self.base_dir, self.labels_file), "rb") as f:
            sha = hashlib.sha256(f.read()).hexdigest()
        return {"labels": self.labels_file, "labels_sha256": sha}

    # ---------------------------------------------------------------- drawing
    def draw(self, index):
        """The random choices of sample ``index``: a dict of plain Python values.

        Drawn from ``numpy.random.default_rng([seed, index])`` in a fixed order;
        depends on nothing but the configuration, the seed and ``index``.
        """
        rng = np.random.default_rng([self.seed, index])
        out = {"shape": self.shape.draw(rng)}
        if self.rotate:  # uniform on SO(3): a normalised 4D Gaussian quaternion
            q = rng.standard_normal(4)
            out["rotation"] = _quat_matrix(q / np.linalg.norm(q))
        else:
            rng.standard_normal(4)  # keep the stream aligned either way
            out["rotation"] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        out["camera"] = self.camera.draw(rng)
        for k, d in self.camera_dists.items():
            out[k] = d.draw(rng)
        out["light_dir"] = self.light_dir.draw(rng)
        out["irradiance"] = self.irradiance.draw(rng)
        if self.several:  # material 0's values, then material 1's, ...
            out["materials"] = [{k: d.draw(rng) for k, d in m.items()} for m in self.materials]
        else:
            out["material"] = {k: d.draw(rng) for k, d in self.material.items()}
        out["render_seed"] = int(rng.integers(0, 2 ** 32))
        return out


def _quat_matrix(q):
    w, x, y, z = (float(v) for v in q)
    m = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return [[float(v) for v in row] for row in m]


def config_path(path):
    """The file of a config path: ``builtin:dataset_example`` is the example shipped with the package."""
    try:
        return resolve_builtin(os.fspath(path), (".toml", ".json"), "config")
    except ValueError as e:
        raise DatasetConfigError(str(e)) from None


def read_config_file(path):
    """The raw configuration data of a .toml or .json file."""
    if not isinstance(path, (str, os.PathLike)):
        raise DatasetConfigError(f"config: expected a .toml or .json file name, got {path!r}")
    path = config_path(path)
    if not os.path.isfile(path):
        raise DatasetConfigError(f"config {path}: no such file")
    ext = os.path.splitext(path)[1].lower()
    with open(path, "rb") as f:
        data = f.read()
    try:
        if ext == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python < 3.11
                import tomli as tomllib
            return tomllib.loads(data.decode("utf-8"))
        if ext == ".json":
            return json.loads(data.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as e:  # TOMLDecodeError and JSONDecodeError are ValueErrors
        raise DatasetConfigError(f"config {path}: not valid {ext[1:].upper()} ({e})") from None
    raise DatasetConfigError(f"config {path}: expected a .toml or .json file")


def load_config(config, base_dir=None):
    """A validated :class:`DatasetConfig` from a file path or a dict.

    Mesh paths are relative to the config file's directory (for a dict: to
    ``base_dir``, by default the current directory).  Raises
    :class:`DatasetConfigError` naming the key for any bad value.
    """
    if isinstance(config, DatasetConfig):
        return config
    if isinstance(config, dict):
        return DatasetConfig(config, base_dir or ".")
    if not isinstance(config, (str, os.PathLike)):
        raise DatasetConfigError(f"config: expected a .toml or .json file name, a dict or a DatasetConfig, "
                                 f"got {config!r}")
    path = config_path(config)
    return DatasetConfig(read_config_file(path), base_dir or os.path.dirname(os.path.abspath(path)))
