"""Synthetic polarimetric datasets: N rendered samples from a configuration file.

::

    from fmbrdf_mi.dataset import generate
    generate("scenes/dataset_example.toml", "out/ds")              # the whole set
    generate("scenes/dataset_example.toml", "out/ds", shard="1/4")  # a quarter of it

(``fmbrdf-mi dataset --config CONFIG --out DIR`` on the command line.)

Output layout of ``DIR``::

    dataset.json                 the configuration with defaults filled in, versions
    samples/000000.exr           Stokes S0..S3 (float32 EXR, fmbrdf_mi.stokes_io layout;
                                 header attribute "fmbrdf_mi" = the label)
    samples/000000.normal.npy    float32 (H, W, 3) unit shading normals, camera frame
                                 (x right, y up, z towards the camera), 0 outside the mask
    samples/000000.mask.png      8-bit grey, 255 where the ray through the pixel centre hits
    samples/000000.json          the label: material, light, camera, shape, render seed
    manifest.jsonl               one line per sample (its label), by index, once all exist
    manifest.shard-I-of-N.jsonl  the same for the samples of shard I (runs with a shard)

Sample ``i`` depends only on the configuration, the seed and ``i``: its
parameters come from ``numpy.random.default_rng([seed, i])`` and its Mitsuba
sampler seed is drawn from the same generator.  A sample is complete when its
label exists; every file is written under a temporary name and renamed, the
label last, so an interrupted run leaves no partial file under a final name and
a rerun renders only the missing samples.  ``shard="i/N"`` takes the samples
with ``index % N == i``.
"""
from __future__ import annotations

import io
import json
import math
import os
import re
import struct
import sys
import time
import zlib

import numpy as np

from .._paths import describe_lock, holder_alive, lock_info, read_lock, release_lock
from .config import (BUILTIN_SHAPES, FORMAT, DatasetConfig, DatasetConfigError, config_path, load_config,
                     read_config_file)

__all__ = ["generate", "load_config", "read_sample", "DatasetConfig", "DatasetConfigError",
           "parse_shard", "BUILTIN_SHAPES"]

SAMPLES_DIR = "samples"
DATASET_FILE = "dataset.json"
MANIFEST = "manifest.jsonl"
SUFFIXES = {"stokes": ".exr", "normal": ".normal.npy", "mask": ".mask.png", "label": ".json"}
#: A sample of several materials (shape.labels) also has its true label map.
LABELS_SUFFIX = ".labels.png"
_TMP = re.compile(r"^\.(\d+)\..*\.tmp\d+")


# ------------------------------------------------------------------ small helpers
def parse_shard(shard):
    """(i, n) from ``"i/n"`` or a pair; 0 <= i < n."""
    if shard is None:
        return 0, 1
    if isinstance(shard, str):
        m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", shard)
        if not m:
            raise ValueError(f"--shard {shard!r}: expected I/N with 0 <= I < N, e.g. 0/4")
        i, n = int(m.group(1)), int(m.group(2))
    else:
        i, n = (int(x) for x in shard)
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"--shard {i}/{n}: expected I/N with 0 <= I < N (shards are numbered from 0)")
    return i, n


def dumps(obj, indent=None):
    """JSON with sorted keys; floats as Python's repr (exact)."""
    return json.dumps(obj, sort_keys=True, indent=indent, separators=(",", ": ") if indent else (",", ":"),
                      allow_nan=False)


def _atomic_write(path, data):
    d, name = os.path.split(path)
    tmp = os.path.join(d, f".{name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def png_grey8(image):
    """PNG bytes of an 8-bit grey image (H, W) uint8 (deterministic: no time or text chunks)."""
    a = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = a.shape

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    raw = b"".join(b"\x00" + a[r].tobytes() for r in range(h))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def _npy_bytes(a):
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _versions():
    import drjit
    import mitsuba

    from .. import __version__

    return {"fmbrdf_mi": __version__, "mitsuba": mitsuba.__version__, "drjit": drjit.__version__}


def _duration(s):
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """Progress on a stream: samples done, rate, time left (a line every ``every`` s; one
    updated line on a terminal)."""

    def __init__(self, total, skipped, stream=None, enabled=True, every=2.0, label="dataset"):
        self.total, self.skipped, self.done = total, skipped, 0
        self.stream = stream or sys.stderr
        self.enabled, self.every, self.label = enabled, every, label
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self.t0 = time.perf_counter()
        self.last = -math.inf

    def rate(self):
        t = time.perf_counter() - self.t0
        return self.done / t if t > 0 else 0.0

    def line(self):
        r = self.rate()
        left = (self.total - self.done) / r if r > 0 else math.inf
        skip = f" (+{self.skipped} already done)" if self.skipped else ""
        return (f"{self.label}: {self.done}/{self.total} samples{skip}, {r:.2f} samples/s, "
                f"{_duration(left)} left")

    def step(self):
        self.done += 1
        now = time.perf_counter()
        if self.enabled and (self.tty or now - self.last >= self.every or self.done == self.total):
            self.last = now
            self.stream.write(("\r" + self.line() + "   ") if self.tty else self.line() + "\n")
            if self.tty and self.done == self.total:
                self.stream.write("\n")
            self.stream.flush()


# ------------------------------------------------------------------ the dataset directory
def sample_id(index, n):
    return f"{index:0{max(6, len(str(n - 1)))}d}"


def sample_files(index, n, several=False):
    """{kind: path relative to the dataset directory} of sample ``index`` (``several``: a dataset of
    several materials, whose samples also have ``labels``)."""
    sid = sample_id(index, n)
    out = {k: f"{SAMPLES_DIR}/{sid}{suffix}" for k, suffix in SUFFIXES.items()}
    if several:
        out["labels"] = f"{SAMPLES_DIR}/{sid}{LABELS_SUFFIX}"
    return out


def is_complete(out, index, n, several=False):
    return all(os.path.isfile(os.path.join(out, p)) for p in sample_files(index, n, several).values())


def _dataset_record(cfg):
    return {"format": FORMAT, "config": cfg.canonical(), "versions": _versions(),
            "conventions": {
                "world": "shape centred at the origin, scaled into the unit sphere, then rotated "
                         "by shape.rotation",
                "camera": "x = image right, y = image up, z = towards the camera (looks along -z); "
                          "camera.to_world maps it to the world",
                "stokes": "stokes integrator frame: x = image right, y = image up (fmbrdf_mi.stokes_io)",
                "normal": "unit shading normals in the camera frame at the pixel centres, float32 (H, W, 3)",
                "mask": "255 where the ray through the pixel centre hits the shape on a face turned towards the camera",
                **({"labels": "8-bit grey: the material (0 .. M-1, the index in material) the ray through the "
                              "pixel centre hits, 255 outside the mask; shape.labels is the uv label image"}
                   if cfg.several else {}),
                "light.direction": "camera frame, from the surface towards the light",
                "render.seed": "the seed given to fmbrdf_mi.scene.render_stokes; the image is rendered "
                               "with irradiance 1 and multiplied by light.irradiance",
            }}


def _check_dataset_file(out, cfg):
    path = os.path.join(out, DATASET_FILE)
    record = _dataset_record(cfg)
    if os.path.exists(path):
        with open(path, encoding="utf-8") as f:
            old = json.load(f)
        for key in ("format", "config", "versions"):
            if old.get(key) != record[key]:
                raise ValueError(
                    f"{out} holds a dataset made with a different {key} (see {path}); "
                    "resume it with the same config, seed and versions, or choose another --out")
        return
    _atomic_write(path, (dumps(record, indent=1) + "\n").encode())


def _clean_temporaries(samples_dir, indices):
    """Remove temporary files of interrupted writes of these samples (other shards' are left alone)."""
    removed = []
    if not os.path.isdir(samples_dir):
        return removed
    for name in os.listdir(samples_dir):
        m = _TMP.match(name)
        if m and int(m.group(1)) in indices:
            os.remove(os.path.join(samples_dir, name))
            removed.append(name)
    return removed


def write_manifest(out, indices, n, name=MANIFEST, several=False):
    """Write the manifest ``name`` listing ``indices`` (their labels, one JSON line each)."""
    lines = []
    for i in sorted(indices):
        with open(os.path.join(out, sample_files(i, n, several)["label"]), encoding="utf-8") as f:
            lines.append(dumps(json.load(f)) + "\n")
    path = os.path.join(out, name)
    _atomic_write(path, "".join(lines).encode())
    return path


# ------------------------------------------------------------------ locks
LOCK_PREFIX = ".lock.shard-"


def _lock_name(k, n):
    return f"{LOCK_PREFIX}{k}-of-{n}"


def _overlap(k1, n1, k2, n2, samples):
    """Whether shards k1/n1 and k2/n2 share a sample index below ``samples``."""
    if (k1 - k2) % math.gcd(n1, n2):
        return False  # no i with i % n1 == k1 and i % n2 == k2 (Chinese remainder theorem)
    return any(i % n2 == k2 for i in range(k1, min(samples, k1 + n1 * n2), n1))


def acquire_lock(out, k, n, samples):
    """Take the lock of shard k/n of the dataset in ``out``; ValueError if a live generator
    holds this shard or one that shares samples with it.  Locks of dead processes on this
    host are removed.  Returns the lock's path."""
    me = lock_info(shard=f"{k}/{n}")
    path = os.path.join(out, _lock_name(k, n))

    def conflicts():
        for name in sorted(os.listdir(out)):
            m = re.fullmatch(re.escape(LOCK_PREFIX) + r"(\d+)-of-(\d+)", name)
            if not m:
                continue
            other = os.path.join(out, name)
            info = read_lock(other)
            if info is None or info.get("pid") == me["pid"] and info.get("host") == me["host"]:
                continue
            k2, n2 = int(m.group(1)), int(m.group(2))
            if not _overlap(k, n, k2, n2, samples):
                continue
            if not holder_alive(info):
                try:
                    os.remove(other)  # stale: its process is gone
                except FileNotFoundError:
                    pass
                continue
            what = "this shard" if (k2, n2) == (k, n) else f"shard {k2}/{n2}, which shares samples with {k}/{n},"
            raise ValueError(f"--out {out}: another generator is rendering {what} into it: "
                             f"{describe_lock(info, other)}")

    conflicts()
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            conflicts()  # removes it if stale, raises if alive
            continue
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps(me) + "\n")
        try:
            conflicts()  # a generator of an overlapping shard that started at the same moment
        except BaseException:
            release_lock(path)
            raise
        return path
    raise ValueError(f"--out {out}: could not take the lock {path}")


# ------------------------------------------------------------------ one sample
def make_label(cfg, index, draw, geometry):
    """The label of a sample: everything needed to re-render it, as plain JSON data."""
    import mitsuba as mi

    g = geometry["label"]
    w, h = cfg.resolution
    camera = {"type": draw["camera"], "distance": draw["distance"], "fov": draw["fov"],
              "elevation": draw["elevation"], "azimuth": draw["azimuth"], "resolution": [w, h],
              "position": g["camera"]["position"], "to_world": g["camera"]["to_world"]}
    if draw["camera"] == "orthographic":
        from ..scene import half_width

        camera["half_width"] = half_width(draw["fov"], draw["distance"])
    return {
        "format": FORMAT, "index": index, "id": sample_id(index, cfg.samples), "dataset_seed": cfg.seed,
        "files": sample_files(index, cfg.samples, cfg.several),
        **({"materials": [dict(m) for m in draw["materials"]]} if cfg.several
           else {"material": dict(draw["material"])}),
        "light": {"type": "directional", "direction": draw["light_dir"],
                  "direction_world": g["light"]["direction_world"], "irradiance": draw["irradiance"]},
        "camera": camera,
        "shape": {"type": draw["shape"], "mesh": draw["shape"] not in BUILTIN_SHAPES,
                  "rotation": draw["rotation"], "to_world": g["shape"]["to_world"]},
        "render": {"integrator": "stokes(direct)", "variant": cfg.variant, "spp": cfg.spp,
                   "seed": draw["render_seed"], "mitsuba": mi.__version__},
    }


def write_sample(out, label, stokes, normals, mask, labels=None):
    """Write a sample's files, each atomically; the label last (it marks the sample complete).
    ``labels``: the true label map of several materials (H, W), -1 off the mask (written 255)."""
    from ..stokes_io import write_stokes_exr

    f = {k: os.path.join(out, p) for k, p in label["files"].items()}
    write_stokes_exr(f["stokes"], stokes, metadata=label, force=True)
    _atomic_write(f["normal"], _npy_bytes(np.ascontiguousarray(normals, dtype=np.float32)))
    _atomic_write(f["mask"], png_grey8(np.where(mask, 255, 0)))
    if labels is not None:
        _atomic_write(f["labels"], png_grey8(np.where(labels < 0, 255, labels)))
    _atomic_write(f["label"], (dumps(label, indent=1) + "\n").encode())


def read_sample(out, index):
    """A sample as a dict: ``stokes`` (4, H, W, C), ``normal`` (H, W, 3), ``mask`` (H, W) bool, ``label``;
    a sample of several materials also ``labels`` (H, W) int, the material at each pixel, -1 off the mask."""
    from matplotlib.image import imread

    from ..stokes_io import read_stokes_exr

    with open(os.path.join(out, DATASET_FILE), encoding="utf-8") as f:
        config = json.load(f)["config"]
    n, several = config["samples"], "labels" in config["shape"]
    files = {k: os.path.join(out, p) for k, p in sample_files(index, n, several).items()}
    with open(files["label"], encoding="utf-8") as f:
        label = json.load(f)
    stokes, _ = read_stokes_exr(files["stokes"])
    out = {"stokes": stokes, "normal": np.load(files["normal"]), "mask": imread(files["mask"]) > 0.5,
           "label": label}
    if several:
        from ..fit.inputs.labels import read_labels

        out["labels"] = read_labels(files["labels"], "labels")
    return out


# ------------------------------------------------------------------ the run
def generate(config, out, *, shard=None, seed=None, samples=None, progress=True, stream=None,
             base_dir=None):
    """Render the samples of ``config`` (a .toml/.json path or a dict) into directory ``out``.

    ``shard``: ``"i/N"`` (or ``(i, N)``) renders only samples with ``index % N == i``.
    ``seed`` and ``samples`` override the config's.  Samples already complete in
    ``out`` are kept as they are (resume); ``out`` must hold the same dataset
    (same canonical config and versions, checked against its dataset.json).
    Progress with rate and time left goes to ``stream`` (stderr) and a summary
    at the end.  Returns the summary as a dict.
    """
    stream = stream or sys.stderr
    t_start = time.perf_counter()
    if isinstance(config, (str, os.PathLike)):
        raw = read_config_file(config)
        base_dir = base_dir or os.path.dirname(os.path.abspath(config_path(config)))
    elif isinstance(config, DatasetConfig):
        if seed is not None or samples is not None:
            raise ValueError("generate(): seed= and samples= override a config given as a path or a dict, "
                             "not a loaded DatasetConfig")
        raw = None
        cfg = config
    elif isinstance(config, dict):
        raw = dict(config)
    else:
        raise DatasetConfigError(f"config: expected a .toml or .json file name, a dict or a DatasetConfig, "
                                 f"got {config!r}")
    if raw is not None:
        if seed is not None:
            raw["seed"] = seed
        if samples is not None:
            raw["samples"] = samples
        cfg = load_config(raw, base_dir=base_dir)
    k, n_shards = parse_shard(shard)
    from .. import check_variant

    check_variant(cfg.variant)     # a cuda_ variant without a device: one line before any work
    if not isinstance(out, (str, os.PathLike)) or not os.fspath(out):
        raise ValueError(f"out: expected a directory name, got {out!r}")
    out = os.fspath(out)
    from .._paths import check_output_dir

    check_output_dir(out, "--out")

    import mitsuba as mi

    previous = mi.variant()
    mi.set_variant(cfg.variant)
    import fmbrdf_mi

    fmbrdf_mi.register()
    from .render import SampleRenderer, sample_geometry

    renderer = SampleRenderer(cfg)
    lock = None
    try:
        for name in cfg.mesh_files():  # a mesh that does not load fails now, not mid-run
            renderer.normalisation(name)
        os.makedirs(os.path.join(out, SAMPLES_DIR), exist_ok=True)
        lock = acquire_lock(out, k, n_shards, cfg.samples)
        _check_dataset_file(out, cfg)
        mine = [i for i in range(cfg.samples) if i % n_shards == k]
        removed = _clean_temporaries(os.path.join(out, SAMPLES_DIR), set(mine))
        todo = [i for i in mine if not is_complete(out, i, cfg.samples, cfg.several)]
        skipped = len(mine) - len(todo)
        what = f"shard {k}/{n_shards}: {len(mine)} of {cfg.samples} samples" if n_shards > 1 \
            else f"{cfg.samples} samples"
        if progress:
            stream.write(f"dataset: {what} into {out}; {skipped} already done, {len(todo)} to render "
                         f"({cfg.resolution[0]}x{cfg.resolution[1]}, {cfg.spp} spp, {cfg.variant})"
                         + (f"; removed {len(removed)} temporary file(s) of an interrupted run" if removed else "")
                         + "\n")
            stream.flush()
        # Render grouped by scene structure (shape, camera type), so that each
        # structure's scene is loaded once; the order does not affect the output.
        # Draws are cheap: made once to sort, again when rendering (not kept: N may be large).
        order = {}
        plan = []
        for i in todo:
            draw = cfg.draw(i)
            plan.append((order.setdefault((draw["shape"], draw["camera"]), len(order)), i))
        plan.sort()

        black = []
        bar = Progress(len(todo), skipped, stream=stream, enabled=progress)
        t_render = time.perf_counter()
        t_write = 0.0
        for _, i in plan:
            draw = cfg.draw(i)
            geometry = sample_geometry(draw, renderer.normalisation(draw["shape"]))
            label = make_label(cfg, i, draw, geometry)
            stokes, normals, mask = renderer.render(draw, geometry)
            label["shape"]["back_face_pixels"] = renderer.back_face_pixels
            if not mask.any() or not np.any(stokes[0] > 0):
                black.append(i)
            t = time.perf_counter()
            if cfg.several:
                label["labels"] = {"uv_labels": cfg.labels_file,
                                   "pixels": [int(np.sum(renderer.labels == m)) for m in range(len(cfg.materials))]}
            write_sample(out, label, stokes, normals, mask, renderer.labels if cfg.several else None)
            t_write += time.perf_counter() - t
            bar.step()
        t_render = time.perf_counter() - t_render
    except (KeyboardInterrupt, RuntimeError) as e:
        from ..interrupt import interrupted

        if not interrupted(e):
            raise
        if progress:
            stream.write("\ndataset: interrupted; run the same command again to resume "
                         "(finished samples are kept)\n")
            stream.flush()
        raise KeyboardInterrupt from None
    finally:
        renderer.close()
        if lock is not None:
            release_lock(lock)
        if previous is not None and previous != cfg.variant:
            mi.set_variant(previous)
    if black and progress:
        stream.write(f"dataset: warning: {len(black)} sample(s) show nothing lit (the light behind the "
                     f"object as seen from the camera, or the object out of view): "
                     f"{', '.join(sample_id(i, cfg.samples) for i in black[:10])}"
                     f"{', ...' if len(black) > 10 else ''}\n")
        stream.flush()

    manifests = []
    if n_shards > 1:
        manifests.append(write_manifest(out, mine, cfg.samples, f"manifest.shard-{k}-of-{n_shards}.jsonl",
                                        cfg.several))
    complete = all(is_complete(out, i, cfg.samples, cfg.several) for i in range(cfg.samples))
    if complete:
        manifests.append(write_manifest(out, range(cfg.samples), cfg.samples, several=cfg.several))
    elapsed = time.perf_counter() - t_start
    rendered = len(todo)
    summary = {"out": out, "samples": cfg.samples, "shard": f"{k}/{n_shards}", "rendered": rendered,
               "skipped": skipped, "seconds": elapsed, "render_seconds": t_render,
               "samples_per_second": rendered / t_render if rendered and t_render > 0 else 0.0,
               "complete": complete, "manifests": manifests,
               "phase_seconds": dict(renderer.seconds, write=t_write)}
    if progress:
        tail = (f"{MANIFEST} lists all {cfg.samples}" if complete
                else f"{sum(is_complete(out, i, cfg.samples, cfg.several) for i in range(cfg.samples))} of "
                     f"{cfg.samples} samples exist; {MANIFEST} is written once all do")
        stream.write(f"dataset: done: rendered {rendered} samples ({skipped} already done) in "
                     f"{_duration(elapsed)} ({elapsed:.1f} s), {summary['samples_per_second']:.2f} samples/s; "
                     f"{tail}\n")
        stream.flush()
    return summary
