"""Per-pixel fits of whole polarisation-camera frames: the default fit command's time and peak memory per
super-pixel against frame size, with its estimates for a comparison with another version of the code.

    python tools/bench_fullframe.py [--sizes 256,512,full] [--scene sphere,mesh] [--texture smooth,checker]
                                    [--lights 1,3] [--modes cli,api] [--area 4] [--code DIR] [--seed 0]
                                    [--progress] [--json out.json] [--markdown out.md]
    python tools/bench_fullframe.py --compare A.json B.json [--rtol 1e-6]
    python tools/bench_fullframe.py --table out.json [more.json ...]     (the fits of all in one table)
    python tools/bench_fullframe.py --render [--render-sizes 512,1024,2448x2048] [--scenes plain,textured]
                                    [--spp N] [--json out.json] [--markdown out.md]

Cases: every combination of the comma-separated ``--sizes`` (frames in super-pixels: ``N`` for N x N, ``WxH``,
or ``full``, a polarisation camera's whole frame, 1224 x 1024 super-pixels = 2448 x 2048 raw pixels),
``--scene``, ``--texture``, ``--lights`` and ``--modes``, each in fresh processes (so one case's memory does
not count for the next).

Data (always made by this checkout's package, whatever ``--code``), as a camera makes them: the object's
noise-free Stokes image at every raw pixel, each raw pixel the mean of the model over ``--area`` x ``--area``
points of its area (default 4: the pixel's area integrated, which the fit models with 2 x 2; the making holds
the points of the whole object at once, in float64: ``--area 2`` makes a full frame with a quarter of them),
then captured by
:func:`fmbrdf_mi.synthetic.spheres.capture_observation` (IMX250MZR camera model, its default gain and read
noise, the brightest raw pixel at 80 % of full scale; with K = 3 lights one exposure for all):

* ``sphere``: the textured orthographic sphere of :func:`fmbrdf_mi.synthetic.spheres.textured_sphere` (the
  `medium` material of tools/bench_textured.py), filling a square of side min(W, H) super-pixels (pi / 4 of
  the square: about 65 % of a full frame);
* ``mesh``: the non-spherical blob mesh of :func:`fmbrdf_mi.synthetic.mesh_object.ideal_object` (a pinhole
  camera of 20 degrees across the square, exact ray-cast geometry at every point), textured by
  :func:`fmbrdf_mi.synthetic.spheres.textured` (its share of the frame: the fitted super-pixels reported);
* textures per super-pixel of the frame (x = column / W, y = row / H): ``smooth`` k_s = 0.6 + 0.4 sin(6x)
  cos(4y), k_b = 0.4 + 0.1 cos(5x + 3y); ``checker`` 3 x 3 super-pixel squares, (k_s, k_b) = (1.0, 0.55) and
  (0.4, 0.25) alternating (tools/bench_textured.py's ``smooth`` and ``high``);
* lights: tools/bench_textured.py's (K = 1: (-0.5, 0.5, 1); K = 3: two more at 35 degrees from the view);
* the square's Stokes image, normal map and mask sit in the middle of the W x H frame, dark around it, and the
  whole frame is captured (a perspective frame's field of view is the one whose focal length is the
  square's, so that its rays are the square's).

The data come from the camera model, not from ``fmbrdf-mi render --raw``: the renderer's scenes are spheres
(a mesh needs an XML scene with uv coordinates for its texture, and ``render`` writes no normal map or mask
for it, which the command needs); and a full frame at the renderer's ``--raw`` default of 1024 samples per pixel
takes many CPU minutes per light (docs/benchmarks/speed.md) where the camera model integrates each pixel's area
with points, not random samples.  ``--render`` times the renderer's making of a frame on its own.

Modes:

* ``cli`` (default): the command a user types, ``fmbrdf-mi fit IMG [IMG IMG] --albedo per-pixel
  --max-pixels 0`` with each raw PNG's sidecar (the camera), ``--normals``, ``--mask``, ``--camera`` (and
  ``--fov``), one ``--light`` per image (three: the joint fit) and ``--irradiance`` of the captures, everything
  else the command's defaults (its intervals and checks included).  The data are written by one child
  process and fitted by another, measured alone (``os.wait4``: its wall time, CPU time = user + system, peak
  resident set); the stage times are fit.json's ``timings``.
* ``api``: ``fmbrdf_mi.fit.fit(obs, albedo="per-pixel", max_pixels=None, intervals=--intervals)`` in a
  child process that makes the captures, then resets its peak resident set (``/proc/self/clear_refs``), so the
  peak is the fit's; the resident set before the fit (Python, NumPy, Mitsuba, the captures) beside it.

``--code DIR``: the checkout whose package fits (the command's ``PYTHONPATH``; the ``api`` child's package,
which then also makes its data), e.g. ``git worktree add --detach ../old COMMIT``, to record the old code's
estimates on the same data.  Each run records its estimates (the shape parameters, the loss and a summary of
the albedo maps: count, mean, RMS and 16 pixels spread over the object), its uncertainty (standard errors,
95 % intervals) and, in ``cli`` mode, the interval check's model evaluations per profiled end; ``--compare A.json B.json`` matches the runs of the same case (mode, scene, texture, lights,
frame, area, seed) and prints, per case and overall, the largest relative difference of the estimates (of the
uncertainty for information); exit status 1 when one exceeds ``--rtol`` (default 1e-6) or a case's estimates
differ in kind, 2 when no case matches.

``--render``: the data's own making instead, the command a user types to make a full frame,
``fmbrdf-mi render OUT.exr --raw --res WxH [-D k_s=TEXTURE.png] [--spp N]`` (the Stokes EXR, its previews, the
raw mosaic and its sidecar; a textured sphere also its true albedo maps), each size and scene (``plain``: the
built-in sphere; ``textured``: its albedo ``k_s`` a smooth one-channel texture the tool writes as a PNG) in a child
process: its wall time, CPU time and peak resident set (``os.wait4``).  Sizes are raw pixels, N or WxH.  The
render's progress lines pass through on stderr.

Reported per case: the frame, the fitted super-pixels (the albedo maps' pixels), wall and CPU time, peak
resident set, the time and peak per fitted super-pixel, the captures' making (its child's wall time and peak, in
the JSON), and, between consecutive sizes of the same case, the marginal time and memory per
added super-pixel (constant when the cost is linear).  The machine's CPU, its cores, ``DRJIT_NUM_THREADS``,
the load average and the date head the table.
"""
import argparse
import datetime
import itertools
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

FULL = (1224, 1024)          # a polarisation camera's whole frame in super-pixels (IMX250MZR: 2448 x 2048 raw)
MESH_FOV = 20.0              # degrees across the mesh's square (ideal_object's default)
MESH_DISTANCE = 8.0
SCENES, TEXTURES, LIGHTS, MODES = ("sphere", "mesh"), ("smooth", "checker"), (1, 3), ("cli", "api")
DEFAULT_FIT_ARGS = "--albedo per-pixel --max-pixels 0"
CASE_KEYS = ("mode", "scene", "texture", "K", "width", "height", "area", "seed")


def vm(key):
    """``VmRSS`` / ``VmHWM`` of this process in bytes (/proc/self/status)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return math.nan


def reset_peak():
    """Reset this process's peak resident set (VmHWM) to its resident set (Linux: clear_refs 5)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def parse_frame(text):
    """``--sizes`` item in super-pixels: ``N`` (N x N), ``WxH`` or ``full`` -> (width, height)."""
    t = text.strip().lower()
    if t == "full":
        return FULL
    w, x, h = t.partition("x")
    try:
        w, h = int(w), int(h if x else w)
    except ValueError:
        raise SystemExit(f"--sizes: expected N, WxH (super-pixels) or full, got {text!r}") from None
    if min(w, h) < 8:
        raise SystemExit(f"--sizes: {text!r}: at least 8 super-pixels each way")
    if (w - h) % 2:
        raise SystemExit(f"--sizes: {text!r}: width - height must be even (the object's square sits in the middle)")
    return w, h


def parse_list(name, text, valid, kind=str):
    """A comma-separated option's values, each one of ``valid``."""
    try:
        vals = [kind(v.strip()) for v in text.split(",") if v.strip()]
    except ValueError:
        vals = None
    if not vals or any(v not in valid for v in vals):
        raise SystemExit(f"--{name}: expected a comma-separated list of {', '.join(map(str, valid))}, got {text!r}")
    return list(dict.fromkeys(vals))


def frame_texture(name, width, height):
    """(k_s, k_b) maps (height, width) of the texture ``name`` per super-pixel of the frame (module docstring)."""
    import numpy as np

    if name == "smooth":
        from fmbrdf_mi.synthetic.spheres import smooth_texture

        return smooth_texture(height, width)
    i, j = np.mgrid[0:height, 0:width]
    if name == "checker":
        odd = (i // 3 + j // 3) % 2 == 1
        return np.where(odd, 1.0, 0.4), np.where(odd, 0.55, 0.25)
    raise ValueError(f"texture: expected one of {', '.join(TEXTURES)}, got {name!r}")


def placement(width, height):
    """(side, column offset, row offset): the object's square in the middle of the frame."""
    side = min(width, height)
    return side, (width - side) // 2, (height - side) // 2


def frame_fov(side, width, fov=MESH_FOV):
    """Horizontal field of view (degrees) of a frame ``width`` wide whose focal length is that of a square
    ``side`` wide seeing ``fov`` degrees across: the frame's rays through the square are the square's."""
    return math.degrees(2 * math.atan(width / side * math.tan(math.radians(fov) / 2)))


def ideal_frame(scene, texture, width, height, light, area):
    """The noise-free textured object of ``scene`` in a width x height frame (module docstring): the dict of
    :func:`fmbrdf_mi.synthetic.spheres.ideal_sphere` (stokes per raw pixel, normals, mask, view directions,
    geometry of the frame) plus ``camera``, ``fov`` and the true maps."""
    import numpy as np

    from bench_textured import TRUTH
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.synthetic.mesh_object import MeshGeometry, ideal_object
    from fmbrdf_mi.synthetic.spheres import ideal_sphere, textured

    side, ox, oy = placement(width, height)
    ks, kb = frame_texture(texture, width, height)
    crop = (slice(oy, oy + side), slice(ox, ox + side))
    if scene == "sphere":
        of = lambda p: ideal_sphere(p, res=side, light=light, area=area)   # noqa: E731
        camera, fov = "orthographic", None
        geometry = G.SphereGeometry((height, width), (ox + side / 2, oy + side / 2), side / 2 - 1)
    else:
        of = lambda p: ideal_object(p, res=side, light=light, area=area, fov=MESH_FOV,   # noqa: E731
                                    distance=MESH_DISTANCE)
        camera, fov = "perspective", frame_fov(side, width)
        geometry = None
    sq = textured(of, TRUTH, ks[crop], kb[crop], side)
    if geometry is None:
        geometry = MeshGeometry(sq["geometry"].scene, (height, width), fov, MESH_DISTANCE)
    stokes = np.zeros((3, 2 * height, 2 * width))
    stokes[:, 2 * oy:2 * (oy + side), 2 * ox:2 * (ox + side)] = sq["stokes"]
    mask = np.zeros((height, width), dtype=bool)
    mask[crop] = sq["mask"]
    normals = np.zeros((height, width, 3))
    normals[..., 2] = 1.0
    normals[crop] = sq["normals"]
    view = G.pixel_rays((height, width), camera, fov)
    return {"stokes": stokes, "normals": normals, "mask": mask, "view_dirs": view,
            "light": np.asarray(light, float), "geometry": geometry, "params": sq["params"], "model": sq["model"],
            "k_s_map": ks, "k_b_map": kb, "camera": camera, "fov": fov}


def captures(a):
    """The case's K captures (module docstring): (observations, raw captures, camera, the last ideal frame)."""
    from bench_textured import lights
    from fmbrdf_mi.sensor.camera import CameraModel
    from fmbrdf_mi.synthetic.spheres import capture_observation

    cam = CameraModel()
    obs, caps, ideal = [], [], None
    for j, light in enumerate(lights(a.lights)[0]):
        ideal = ideal_frame(a.scene, a.texture, a.width, a.height, light, a.area)
        o, cap = capture_observation(ideal, cam, seed=1000 * a.seed + j,
                                     exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
        caps.append(cap)
        del ideal["stokes"]
    return obs, caps, cam, ideal


def case_of(a, mode):
    return {"mode": mode, "scene": a.scene, "texture": a.texture, "K": a.lights, "width": a.width,
            "height": a.height, "area": a.area, "seed": a.seed}


def map_summary(values):
    """Count, mean, RMS and 16 values spread over the fitted (finite: NaN elsewhere) pixels, row-major, of an
    albedo map."""
    import numpy as np

    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if not v.size:
        return {"count": 0}
    pick = np.linspace(0, v.size - 1, 16).round().astype(int)
    return {"count": int(v.size), "mean": float(v.mean()), "rms": float(np.sqrt(np.mean(v * v))),
            "values": [float(x) for x in v[pick]]}


def estimates_of(params, loss, maps):
    """A run's estimates: the scalar parameters, the loss and the albedo maps' summaries."""
    out = {"params": {k: float(v) for k, v in params.items() if isinstance(v, (int, float))}, "loss": float(loss)}
    out["maps"] = {k: map_summary(maps[k]) for k in ("k_s", "k_b") if maps and k in maps}
    return out


def worker_make(a):
    """Write the case's captures for the command (raw PNGs with sidecars, normal map, mask, info.json)."""
    import numpy as np
    from PIL import Image

    from fmbrdf_mi.sensor.camera import write_sidecar

    obs, caps, cam, ideal = captures(a)
    os.makedirs(a.out, exist_ok=True)
    images = []
    for j, cap in enumerate(caps):
        images.append(os.path.join(a.out, f"capture{j}.png"))
        Image.fromarray(np.ascontiguousarray(cap["raw"], dtype=np.uint16)).save(images[-1])
        write_sidecar(images[-1], cam)
    np.save(os.path.join(a.out, "normals.npy"), np.asarray(obs[0].normals, dtype=np.float32))
    np.save(os.path.join(a.out, "mask.npy"), np.asarray(obs[0].mask, dtype=bool))
    info = {"images": images, "lights": [[float(v) for v in o.light_dir] for o in obs],
            "irradiance": float(obs[0].irradiance), "camera": ideal["camera"], "fov": ideal["fov"],
            "object": int(np.count_nonzero(obs[0].mask))}
    with open(os.path.join(a.out, "info.json"), "w") as f:
        json.dump(info, f)


def worker_api(a):
    """One case through the API, in this process; prints one JSON line."""
    import resource

    if a.code:
        sys.path.insert(0, a.code)
    from fmbrdf_mi.fit import fit

    obs, _, _, _ = captures(a)
    object_pixels = int(obs[0].mask.sum())
    rss0 = vm("VmRSS")
    exact = reset_peak()
    u0 = resource.getrusage(resource.RUSAGE_SELF)
    t = time.time()
    r = fit(obs if len(obs) > 1 else obs[0], albedo="per-pixel", max_pixels=None, intervals=a.intervals,
            progress=a.progress)
    dt = time.time() - t
    u1 = resource.getrusage(resource.RUSAGE_SELF)
    unc = r.uncertainty or {}
    maps = r.maps or {}
    out = dict(case_of(a, "api"), intervals=a.intervals, object=object_pixels, pixels=int(r.n_pixels), time=dt,
               cpu=(u1.ru_utime + u1.ru_stime) - (u0.ru_utime + u0.ru_stime), peak=vm("VmHWM"), rss_before=rss0,
               peak_reset=exact, converged=bool(r.converged), stages={},
               estimates=estimates_of(r.params, r.loss, maps),
               uncertainty={"std_errors": dict(r.std_errors or {}), "ci95": unc.get("ci95", {})})
    print("RESULT " + json.dumps(out), flush=True)


def find_key(d, key):
    """The first dict in the JSON tree ``d`` (depth first) that has ``key``."""
    if isinstance(d, dict):
        if key in d:
            return d
        d = list(d.values())
    if isinstance(d, list):
        for v in d:
            found = find_key(v, key)
            if found:
                return found
    return None


def run_child(cmd, env, stdout=None, stderr=None, cwd=None):
    """Run ``cmd`` (``stdout``, ``stderr``: open files, or None to pass through); its exit status, wall time,
    CPU time (user + system) and peak resident set, measured for that child alone (``os.wait4``)."""
    t = time.time()
    child = subprocess.Popen(cmd, env=env, stdout=stdout, stderr=stderr, cwd=cwd)
    _, status, usage = os.wait4(child.pid, 0)
    child.returncode = os.waitstatus_to_exitcode(status)
    return child.returncode, time.time() - t, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024


def child_env(code):
    """The environment of a child that imports the package of the checkout ``code`` (run it outside any
    checkout: ``python -m`` puts the working directory first on the path), before the caller's own path."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([code] + [p for p in [os.environ.get("PYTHONPATH")] if p]))


def check_code(code):
    """SystemExit unless ``python -m fmbrdf_mi`` in :func:`child_env` imports the package of ``code``."""
    with tempfile.TemporaryDirectory() as work:
        p = subprocess.run([sys.executable, "-c", "import fmbrdf_mi; print(fmbrdf_mi.__file__)"], cwd=work,
                           env=child_env(code), capture_output=True, text=True)
    where = p.stdout.strip()
    if p.returncode or os.path.dirname(os.path.dirname(os.path.realpath(where))) != os.path.realpath(code):
        raise SystemExit(f"--code: {code}: its package is not the one imported ({where or p.stderr.strip()[-300:]})")


def case_args(case):
    return ["--scene", case["scene"], "--texture", case["texture"], "--lights", str(case["K"]),
            "--size", f"{case['width']}x{case['height']}", "--area", str(case["area"]), "--seed", str(case["seed"])]


def fit_command(info, out, quiet, fit_args=DEFAULT_FIT_ARGS):
    """The fit command of the captures ``info`` (worker_make's info.json): ``fit_args`` (default: per-pixel)."""
    data = os.path.dirname(info["images"][0])
    cmd = [sys.executable, "-m", "fmbrdf_mi", "fit", *info["images"], *shlex.split(fit_args),
           "--normals", os.path.join(data, "normals.npy"), "--mask", os.path.join(data, "mask.npy"),
           "--camera", info["camera"]]
    cmd += ["--fov", repr(info["fov"])] if info["fov"] else []
    cmd += ["--light=" + ",".join(repr(v) for v in light) for light in info["lights"]]
    cmd += ["--irradiance", repr(info["irradiance"]), "-o", out]
    return cmd + (["-q"] if quiet else [])


def read_map(path):
    """The first channel of a map EXR the command wrote (None when it wrote none)."""
    from fmbrdf_mi.stokes_io import read_exr

    if not os.path.exists(path):
        return None
    return next(iter(read_exr(path)[1].values()))


def run_cli(a, case):
    """One case through the default command: the data made by one child, fitted by another (measured)."""
    with tempfile.TemporaryDirectory() as work:
        data, out, log = (os.path.join(work, k) for k in ("data", "out", "log.txt"))
        make = [sys.executable, os.path.abspath(__file__), "--worker", "make", "--out", data, *case_args(case)]
        rc, make_time, _, make_peak = run_child(make, child_env(ROOT))
        if rc:
            raise SystemExit(f"{label(case)}: making the captures failed")
        with open(os.path.join(data, "info.json")) as f:
            info = json.load(f)
        with open(log, "w") as f:
            rc, wall, cpu, peak = run_child(fit_command(info, out, not a.progress, a.fit_args), child_env(a.code),
                                            stdout=None if a.progress else f, stderr=None if a.progress else f,
                                            cwd=work)
        if rc not in (0, 3):    # 3: the outputs written, the fit not converged (recorded as such)
            with open(log) as f:
                tail = f.read()[-2000:]
            raise SystemExit(f"{label(case)}: the fit command failed with exit status {rc}: {tail}")
        with open(os.path.join(out, "fit.json")) as f:
            res = json.load(f)
        model = find_key(res, "n_pixels") or res.get("refine_normals") or {}
        maps = {k: read_map(os.path.join(out, f"{k}.exr")) for k in ("k_s", "k_b")}
    unc = model.get("uncertainty") or {}
    return dict(case, code=a.code, intervals="the command's", fit_args=a.fit_args, object=info["object"],
                pixels=int(model.get("n_pixels", model.get("pixels", 0))),
                time=wall, cpu=cpu, peak=peak, rss_before=None, converged=bool(model.get("converged", False)),
                stages=model.get("timings") or {}, make_time=make_time, make_peak=make_peak,
                estimates=estimates_of(model.get("params", {}), model.get("loss", math.nan),
                                       {k: v for k, v in maps.items() if v is not None}),
                uncertainty={"std_errors": model.get("std_errors") or {}, "ci95": unc.get("ci95") or {}},
                profile_evaluations={n: r["evaluations"] for n, r in
                                     (unc.get("profile") or {}).get("rises", {}).items() if "evaluations" in r})


def run_api(a, case):
    """One case through the API in a child process."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "api", *case_args(case), "--intervals", a.intervals]
    cmd += (["--progress"] if a.progress else []) + (["--code", a.code] if a.code != ROOT else [])
    p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=child_env(ROOT))
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode or not lines:
        raise SystemExit(f"{label(case)}: the API worker failed with exit status {p.returncode}")
    return dict(json.loads(lines[-1][7:]), code=a.code)


def label(run):
    """A case's name, e.g. ``cli sphere smooth K=1 256x256``."""
    return (f"{run['mode']} {run['scene']} {run['texture']} K={run['K']} {run['width']}x{run['height']}"
            + (f" area={run['area']}" if run.get("area", 4) != 4 else "")
            + (f" seed={run['seed']}" if run.get("seed") else ""))


def flatten(d, prefix=""):
    """{dotted key: number} of the numbers in a JSON tree (list items as key[i])."""
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            out.update(flatten(v, f"{prefix}[{i}]"))
    elif isinstance(d, (int, float)) and not isinstance(d, bool):
        out[prefix] = float(d)
    return out


def rel_diff(x, y):
    """|x - y| / max(|x|, |y|): 0 when equal (both 0, both NaN or the same infinity), inf when one is NaN."""
    if x == y or (math.isnan(x) and math.isnan(y)):
        return 0.0
    if math.isnan(x) or math.isnan(y) or math.isinf(x) or math.isinf(y):
        return math.inf
    return abs(x - y) / max(abs(x), abs(y))


def worst(a, b):
    """(key, relative difference) of the largest difference between two JSON trees' numbers; a key in one only
    counts as infinite."""
    fa, fb = flatten(a), flatten(b)
    diffs = [(k, rel_diff(fa[k], fb[k]) if k in fa and k in fb else math.inf) for k in sorted(set(fa) | set(fb))]
    return max(diffs, key=lambda kv: kv[1], default=(None, 0.0))


def compare_runs(runs_a, runs_b, rtol):
    """Match the runs of the same case; per case (label, worst estimate key, its relative difference, worst
    uncertainty key, its relative difference, within ``rtol``), and the labels of the cases in one file only."""
    key = (lambda r: tuple(r.get(k) for k in CASE_KEYS))
    A, B = {key(r): r for r in runs_a}, {key(r): r for r in runs_b}
    rows = []
    for k in [k for k in A if k in B]:
        ek, ed = worst(A[k].get("estimates"), B[k].get("estimates"))
        uk, ud = worst(A[k].get("uncertainty"), B[k].get("uncertainty"))
        rows.append((label(A[k]), ek, ed, uk, ud, ed <= rtol))
    unmatched = [label(r) for k, r in list(A.items()) + list(B.items()) if not (k in A and k in B)]
    return rows, unmatched


def main_compare(a):
    runs = []
    for path in a.compare:
        try:
            with open(path) as f:
                runs.append([r for r in json.load(f)["runs"] if "estimates" in r])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"--compare: {path}: not a bench_fullframe JSON with runs ({exc})") from None
    rows, unmatched = compare_runs(runs[0], runs[1], a.rtol)
    for name in unmatched:
        print(f"in one file only: {name}")
    if not rows:
        print(f"--compare: no case is in both {a.compare[0]} and {a.compare[1]}", file=sys.stderr)
        return 2
    for name, ek, ed, uk, ud, ok in rows:
        print(f"{'ok  ' if ok else 'FAIL'} {name}: estimates worst {ed:.3g}{f' ({ek})' if ed else ''}; "
              f"uncertainty worst {ud:.3g}{f' ({uk})' if ud else ''}")
    bad = [r for r in rows if not r[5]]
    top = max(rows, key=lambda r: r[2])
    print(f"{len(rows)} cases, worst relative difference of the estimates {top[2]:.3g}"
          f"{f' ({top[0]}: {top[1]})' if top[2] else ''}, "
          f"tolerance {a.rtol:g}: {'FAIL' if bad else 'PASS'}")
    return 1 if bad else 0


def marginals(runs):
    """Between consecutive sizes of the same case (by fitted super-pixels, :func:`cells`): (label of the larger,
    fitted super-pixels of both, wall ms, CPU ms and peak kB per added fitted super-pixel)."""
    group = (lambda r: tuple(r.get(k) for k in CASE_KEYS if k not in ("width", "height")))
    out = []
    for _, rs in itertools.groupby(sorted(runs, key=lambda r: (group(r), cells(r))), key=group):
        rs = list(rs)
        for r0, r1 in zip(rs, rs[1:]):
            dn = cells(r1) - cells(r0)
            if dn > 0:
                out.append((label(r1), cells(r0), cells(r1), 1e3 * (r1["time"] - r0["time"]) / dn,
                            1e3 * (r1["cpu"] - r0["cpu"]) / dn, (r1["peak"] - r0["peak"]) / dn / 1e3))
    return out


def cells(run):
    """The super-pixels a run fitted: its albedo pairs (the map's fitted pixels; with K images ``pixels`` counts
    each pixel once per image it is usable in)."""
    return run.get("estimates", {}).get("maps", {}).get("k_s", {}).get("count") or run["pixels"]


def table(runs, head):
    lines = [head, "",
             "| mode | object | texture | K | frame (super-pixels) | data points / raw pixel | super-pixels fitted | "
             "time | CPU time | time / fitted | peak RSS | peak / fitted |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        n = max(cells(r), 1)
        lines.append(f"| {r['mode']} | {r['scene']} | {r['texture']} | {r['K']} | {r['width']} × {r['height']} | "
                     f"{r['area']}² | {n} | {r['time']:.1f} s | {r['cpu']:.1f} s | "
                     f"{1e3 * r['time'] / n:.2f} ms | {r['peak'] / 2 ** 30:.2f} GiB | {r['peak'] / n / 1e3:.1f} kB |")
    extra = marginals(runs)
    if extra:
        lines += ["", "| case | from → to fitted | time / added | CPU / added | peak / added |",
                  "|---|---|---|---|---|"]
        lines += [f"| {name} | {n0} → {n1} | {t:.2f} ms | {c:.2f} ms | {m:.1f} kB |" for name, n0, n1, t, c, m in extra]
    return "\n".join(lines)


def texture_png(path, size=512):
    """A smooth one-channel albedo texture (values in [28, 228] of 255; the spectral variant takes no RGB
    albedo) written to ``path``."""
    import numpy as np
    from PIL import Image

    y, x = np.mgrid[0:size, 0:size] / size
    grey = 128 + 100 * np.sin(2 * np.pi * 3 * x) * np.cos(2 * np.pi * 2 * y)
    Image.fromarray(np.round(grey).astype(np.uint8)).save(path)
    return path


def parse_res(text):
    """``512`` or ``2448x2048`` -> (width, height)."""
    w, _, h = text.strip().lower().partition("x")
    try:
        w, h = int(w), int(h or w)
    except ValueError:
        raise SystemExit(f"--render-sizes: expected N or WxH, e.g. 512 or 2448x2048, got {text!r}") from None
    if w < 2 or h < 2 or w % 2 or h % 2:
        raise SystemExit(f"--render-sizes: {text!r}: width and height must be even (the 2 x 2 mosaic)")
    return w, h


def run_render(size, scene, spp, work, texture, variant=None):
    """One ``fmbrdf-mi render --raw`` in a child process: its wall time, CPU time and peak resident set."""
    w, h = size
    out = os.path.join(work, f"{scene}_{w}x{h}.exr")
    cmd = [sys.executable, "-m", "fmbrdf_mi", "render", out, "--raw", "--res", f"{w}x{h}", "--force"]
    cmd += ["--variant", variant] if variant else []
    cmd += ["-D", f"k_s={texture}"] if scene == "textured" else []
    cmd += ["--spp", str(spp)] if spp else []
    with tempfile.TemporaryFile("w+") as f:
        rc, wall, cpu, peak = run_child(cmd, child_env(ROOT), stdout=f, cwd=work)
        f.seek(0)
        stdout = f.read()
    if rc:
        raise SystemExit(f"render {w}x{h} ({scene}) failed with exit status {rc}")
    spp_used = next((int(m) for m in re.findall(r", (\d+) spp,", stdout)), None)
    written = 0
    for f in os.listdir(work):
        if f.startswith(f"{scene}_{w}x{h}"):
            written += os.path.getsize(os.path.join(work, f))
            os.remove(os.path.join(work, f))
    return {"mode": "render", "scene": scene, "variant": variant, "width": w, "height": h, "spp": spp_used,
            "time": wall, "cpu": cpu, "peak": peak, "written": written}


def render_table(runs, head):
    lines = [head, "", "| scene | raw pixels | super-pixels | spp | time | CPU time | peak RSS | files written |",
             "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['scene']}{' (' + r['variant'] + ')' if r.get('variant') else ''} | {r['width']} × {r['height']} | {r['width'] // 2} × {r['height'] // 2} | "
                     f"{r['spp']} | {r['time']:.1f} s | {r['cpu']:.1f} s | {r['peak'] / 2 ** 30:.2f} GiB | "
                     f"{r['written'] / 2 ** 20:.1f} MiB |")
    return "\n".join(lines)


def save_runs(a, head, runs):
    """The runs so far to ``--json`` (written whole after every run, so a stopped bench keeps them)."""
    if a.json:
        with open(a.json + ".tmp", "w") as f:
            json.dump({"header": head, "runs": runs}, f, indent=1)
        os.replace(a.json + ".tmp", a.json)


def print_table(a, text):
    """Print the markdown table and write it to ``--markdown``; the exit status."""
    print(text)
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write(text + "\n")
    return 0


def main_render(a):
    sizes = [parse_res(s) for s in a.render_sizes.split(",") if s.strip()]
    scenes = [s.strip() for s in a.scenes.split(",") if s.strip()]
    bad = [s for s in scenes if s not in ("plain", "textured")]
    if bad or not scenes or not sizes:
        raise SystemExit(f"--scenes: expected plain and/or textured, got {a.scenes!r}" if bad or not scenes
                         else f"--render-sizes: expected sizes, got {a.render_sizes!r}")
    head = header() + ", load average {:.1f} at the start".format(os.getloadavg()[0])
    runs, t0 = [], time.time()
    with tempfile.TemporaryDirectory() as work:
        texture = texture_png(os.path.join(work, "texture.png"))
        for size in sizes:
            for scene in scenes:
                print(f"[{time.time() - t0:.0f} s] render {size[0]}x{size[1]} ({scene}) ...", file=sys.stderr,
                      flush=True)
                r = run_render(size, scene, a.spp, work, texture, a.variant)
                runs.append(r)
                print(f"[{time.time() - t0:.0f} s] render {size[0]}x{size[1]} ({scene}): {r['time']:.1f} s, "
                      f"peak {r['peak'] / 2 ** 30:.2f} GiB", file=sys.stderr, flush=True)
                save_runs(a, head, runs)
    return print_table(a, render_table(runs, head))


def header():
    from _common import cpu_name

    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                         text=True).stdout.strip() if shutil.which("nvidia-smi") else ""
    return (f"{datetime.date.today().isoformat()}, {cpu_name()}, {len(os.sched_getaffinity(0))} of "
            f"{os.cpu_count()} cores{', ' + gpu if gpu else ''}, "
            f"DRJIT_NUM_THREADS={os.environ.get('DRJIT_NUM_THREADS', 'unset')}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="256", help="frames in super-pixels, N, WxH or full (1224x1024), "
                   "comma-separated (default %(default)s)")
    p.add_argument("--scene", default="sphere", help="sphere and/or mesh, comma-separated (default %(default)s)")
    p.add_argument("--texture", default="smooth", help="smooth and/or checker, comma-separated (default %(default)s)")
    p.add_argument("--lights", default="1", help="1 and/or 3 fitted lights, comma-separated (default %(default)s)")
    p.add_argument("--modes", default="cli", help="cli (the fit command) and/or api, comma-separated "
                   "(default %(default)s)")
    p.add_argument("--area", type=int, default=4, help="the data's points per raw pixel side (default %(default)s)")
    p.add_argument("--intervals", default="fisher", choices=("fisher", "auto", "profile"),
                   help="the API fit's intervals (default %(default)s)")
    p.add_argument("--fit-args", default=DEFAULT_FIT_ARGS, help="cli mode: the fit's options after the images "
                   "(default %(default)r; e.g. --fit-args=--refine-normals with --lights 3)")
    p.add_argument("--code", metavar="DIR", default=ROOT, help="the checkout whose package fits (default: this one)")
    p.add_argument("--seed", type=int, default=0, help="camera-noise seed")
    p.add_argument("--progress", action="store_true", help="the fits' own progress lines on stderr")
    p.add_argument("--json", metavar="OUT.json", help="the runs and the table's header")
    p.add_argument("--markdown", metavar="OUT.md", help="the table")
    p.add_argument("--table", metavar="IN.json", nargs="+", help="the table of saved runs")
    p.add_argument("--compare", metavar=("A.json", "B.json"), nargs=2, help="the estimates of the cases in both")
    p.add_argument("--rtol", type=float, default=1e-6, help="--compare: relative tolerance (default %(default)g)")
    p.add_argument("--render", action="store_true", help="time `fmbrdf-mi render --raw` instead of the fits")
    p.add_argument("--render-sizes", default="512,1024,2448x2048",
                   help="--render: raw-pixel sizes, N or WxH, comma-separated (default %(default)s)")
    p.add_argument("--scenes", default="plain,textured", help="--render: plain and/or textured")
    p.add_argument("--spp", type=int, help="--render: samples per pixel (default: the command's)")
    p.add_argument("--variant", help="--render: the command's Mitsuba variant (default: the command's; a fit's: "
                   "--fit-args=\"... --variant cuda_ad_mono_polarized\")")
    p.add_argument("--worker", choices=("make", "api"), help=argparse.SUPPRESS)
    p.add_argument("--size", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        a.width, a.height = parse_frame(a.size)
        a.lights = int(a.lights)
        a.code = None if a.code == ROOT else a.code
        (worker_make if a.worker == "make" else worker_api)(a)
        return 0
    if a.compare:
        return main_compare(a)
    if a.table:
        saved = [json.load(open(f)) for f in a.table]
        for s in [s for s in saved if s["runs"] and s["runs"][0].get("mode") == "render"]:
            print(render_table(s["runs"], s["header"]) + "\n")
        fits = [s for s in saved if s["runs"] and s["runs"][0].get("mode") != "render"]
        if fits:       # one table of every file's fits, so that the marginals span the files
            print(table([r for s in fits for r in s["runs"]], "\n".join(s["header"] for s in fits)))
        return 0
    if a.render:
        return main_render(a)
    frames = [parse_frame(s) for s in a.sizes.split(",") if s.strip()]
    if not frames:
        raise SystemExit(f"--sizes: expected N, WxH or full, comma-separated, got {a.sizes!r}")
    if a.area < 1:
        raise SystemExit(f"--area: expected at least 1 point per raw pixel side, got {a.area}")
    a.code = os.path.abspath(a.code)
    if not os.path.isfile(os.path.join(a.code, "fmbrdf_mi", "__init__.py")):
        raise SystemExit(f"--code: {a.code} is not a checkout of the package (no fmbrdf_mi/__init__.py)")
    check_code(a.code)
    cases = [{"mode": m, "scene": s, "texture": t, "K": k, "width": w, "height": h, "area": a.area, "seed": a.seed}
             for (w, h), s, t, k, m in itertools.product(
                 frames, parse_list("scene", a.scene, SCENES), parse_list("texture", a.texture, TEXTURES),
                 parse_list("lights", a.lights, LIGHTS, int), parse_list("modes", a.modes, MODES))]
    head = header() + ", load average {:.1f} at the start".format(os.getloadavg()[0])
    head += "" if a.code == ROOT else f", fitted by the package of {a.code}"
    runs, t0 = [], time.time()
    for case in cases:
        print(f"[{time.time() - t0:.0f} s] {label(case)} ...", file=sys.stderr, flush=True)
        r = (run_cli if case["mode"] == "cli" else run_api)(a, case)
        runs.append(r)
        print(f"[{time.time() - t0:.0f} s] {label(case)}: {cells(r)} super-pixels, {r['time']:.1f} s, "
              f"CPU {r['cpu']:.1f} s, peak {r['peak'] / 2 ** 30:.2f} GiB", file=sys.stderr, flush=True)
        save_runs(a, head, runs)
    return print_table(a, table(runs, head))


if __name__ == "__main__":
    sys.exit(main())
