"""Per-pixel fits of whole polarisation-camera frames: wall time and peak memory per super-pixel against size.

    python tools/bench_fullframe.py [--sizes 64,128,256] [--lights 1] [--texture smooth] [--intervals fisher]
                                    [--cli] [--json out.json] [--markdown out.md]
    python tools/bench_fullframe.py --table out.json [more.json ...]
    python tools/bench_fullframe.py --render [--render-sizes 512,1024,2448x2048] [--scenes plain,textured]
                                    [--spp N] [--json out.json] [--markdown out.md]

Data, as a camera makes them: the textured orthographic sphere of tools/bench_textured.py
(:func:`fmbrdf_mi.synthetic.spheres.textured_sphere`, the `medium` material, its ``smooth`` or ``high``
texture per super-pixel, filling a SIZE x SIZE super-pixel image: pi / 4 of it is object), captured by
:func:`fmbrdf_mi.synthetic.spheres.capture_observation` (IMX250MZR camera model, its default gain and read
noise, brightest raw pixel at 80 % of full scale; with K = 3 lights one exposure for all), camera noise known.

Each size runs in a fresh Python process (so one size's memory does not count for the next), which

* makes the captures, then resets its peak resident set (``/proc/self/clear_refs``), so the peak that
  follows is the fit's (the process's resident set before the fit, Python, NumPy, Mitsuba and the captures,
  is reported beside it);
* ``api``: ``fmbrdf_mi.fit.fit(obs, albedo="per-pixel", max_pixels=None, intervals=...)`` (``--intervals``:
  the per-pixel fit's intervals, default ``fisher``);
* ``cli`` (``--cli``, after the API fit, in its own process): the default command a user types,
  ``fmbrdf-mi fit raw.png --albedo per-pixel --max-pixels 0`` with the capture's sidecar (the camera), the
  normal map, mask, light and irradiance of the capture, everything else the command's defaults (its
  intervals and checks included); the child process's peak resident set (``RUSAGE_CHILDREN``).

``--render``: the data's own making instead, the command a user types to make a full frame,
``fmbrdf-mi render OUT.exr --raw --res WxH [-D k_s=TEXTURE.png] [--spp N]`` (the Stokes EXR, its previews, the
raw mosaic and its sidecar; a textured sphere also its true albedo maps), each size and scene (``plain``: the
built-in sphere; ``textured``: its albedo ``k_s`` a smooth one-channel texture the tool writes as a PNG) in a child
process: its wall time, CPU time (user + system: less sensitive to other work on the machine than the
wall time) and peak resident set (``os.wait4``'s ``ru_utime``, ``ru_stime`` and ``ru_maxrss`` of that child).  Sizes are raw
pixels, N or WxH; a polarisation camera's full frame is 2448x2048 (1224 x 1024 super-pixels).  The render's
progress lines pass through on stderr.

Reported per size and mode: the fitted super-pixels, wall time, peak resident set (the fit's process:
VmHWM), the peak's growth over the resident set before the fit, and both per fitted super-pixel.  The
machine's CPU, its number of cores, ``DRJIT_NUM_THREADS`` and the date head the table.  Timings are wall
clock on this machine, whatever else runs on it.
"""
import argparse
import datetime
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


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


def captures(size, K, tex, seed):
    """K textured-sphere captures of a SIZE x SIZE super-pixel frame (module docstring)."""
    from bench_textured import TRUTH, lights, texture
    from fmbrdf_mi.sensor.camera import CameraModel
    from fmbrdf_mi.synthetic.spheres import capture_observation, textured_sphere

    ks, kb = texture(tex, size)
    cam = CameraModel()
    obs, caps = [], []
    for j, light in enumerate(lights(K)[0]):
        o, cap = capture_observation(textured_sphere(TRUTH, ks, kb, res=size, light=light), cam, seed=1000 * seed + j,
                                     exposure=None if j == 0 else obs[0].meta["capture"]["exposure"])
        obs.append(o)
        caps.append(cap)
    return obs, caps, cam


def worker_api(a):
    """One size through the API, in this process; prints one JSON line."""
    import numpy as np

    from fmbrdf_mi.fit import fit

    obs, _, _ = captures(a.size, a.lights, a.texture, a.seed)
    del _
    rss0 = vm("VmRSS")
    exact = reset_peak()
    t = time.time()
    r = fit(obs if len(obs) > 1 else obs[0], albedo="per-pixel", max_pixels=None, intervals=a.intervals,
            progress=a.progress)
    dt = time.time() - t
    out = {"mode": "api", "size": a.size, "K": a.lights, "texture": a.texture, "intervals": a.intervals,
           "pixels": int(r.n_pixels), "time": dt, "peak": vm("VmHWM"), "rss_before": rss0, "peak_reset": exact,
           "converged": bool(r.converged), "params": {k: float(r.params[k]) for k in ("eta", "alpha", "beta", "kappa")}}
    if a.save_maps:
        np.savez(a.save_maps, **{k: np.asarray(v) for k, v in (r.maps or {}).items()
                                 if isinstance(v, np.ndarray)}, **{"param_" + k: v for k, v in r.params.items()})
    print("RESULT " + json.dumps(out), flush=True)


def worker_cli(a):
    """One size through the default command (a child process); prints one JSON line."""
    import resource

    import numpy as np
    from PIL import Image

    from fmbrdf_mi.sensor.camera import write_sidecar

    if a.lights != 1:
        raise SystemExit("--cli: one light only (the command's manifest of several images is not made here)")
    obs, caps, cam = captures(a.size, 1, a.texture, a.seed)
    o = obs[0]
    with tempfile.TemporaryDirectory() as work:
        raw = os.path.join(work, "capture.png")
        Image.fromarray(np.ascontiguousarray(caps[0]["raw"], dtype=np.uint16)).save(raw)
        write_sidecar(raw, cam)
        np.save(os.path.join(work, "normals.npy"), np.asarray(o.normals, dtype=np.float32))
        np.save(os.path.join(work, "mask.npy"), np.asarray(o.mask, dtype=bool))
        cmd = [sys.executable, "-m", "fmbrdf_mi", "fit", raw, "--albedo", "per-pixel", "--max-pixels", "0",
               "--normals", os.path.join(work, "normals.npy"), "--mask", os.path.join(work, "mask.npy"),
               "--camera", "orthographic", "--light=" + ",".join(repr(float(v)) for v in o.light_dir),
               "--irradiance", repr(float(o.irradiance)), "--conversion-gain", repr(cam.conversion_gain),
               "--read-noise", repr(cam.read_noise), "-o", os.path.join(work, "out")]
        cmd += [] if a.progress else ["-q"]
        t = time.time()
        p = subprocess.run(cmd, env=dict(os.environ, PYTHONPATH=ROOT), capture_output=not a.progress, text=True)
        dt = time.time() - t
        if p.returncode:
            raise SystemExit(f"the fit command failed ({p.returncode}): {p.stderr[-2000:] if p.stderr else ''}")
        with open(os.path.join(work, "out", "fit.json")) as f:
            res = json.load(f)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    fitted = find_key(res, "n_pixels") or {}
    out = {"mode": "cli", "size": a.size, "K": 1, "texture": a.texture, "intervals": "default",
           "pixels": int(fitted.get("n_pixels", 0)), "time": dt, "peak": peak, "rss_before": math.nan,
           "peak_reset": False, "converged": bool(fitted.get("converged", False))}
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


def run_size(a, size, mode):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", mode, "--size", str(size), "--lights", str(a.lights),
           "--texture", a.texture, "--intervals", a.intervals, "--seed", str(a.seed)]
    cmd += ["--progress"] if a.progress else []
    p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=ROOT))
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode or not lines:
        raise SystemExit(f"size {size} ({mode}): the worker failed with exit status {p.returncode}")
    return json.loads(lines[-1][7:])


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


def run_render(size, scene, spp, work, texture):
    """One ``fmbrdf-mi render --raw`` in a child process: its wall time and peak resident set."""
    w, h = size
    out = os.path.join(work, f"{scene}_{w}x{h}.exr")
    cmd = [sys.executable, "-m", "fmbrdf_mi", "render", out, "--raw", "--res", f"{w}x{h}", "--force"]
    cmd += ["-D", f"k_s={texture}"] if scene == "textured" else []
    cmd += ["--spp", str(spp)] if spp else []
    t = time.time()
    child = subprocess.Popen(cmd, env=dict(os.environ, PYTHONPATH=ROOT), stdout=subprocess.PIPE, text=True)
    stdout = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)
    dt = time.time() - t
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        raise SystemExit(f"render {w}x{h} ({scene}) failed with exit status {child.returncode}")
    spp_used = next((int(m) for m in re.findall(r", (\d+) spp,", stdout)), None)
    written = 0
    for f in os.listdir(work):
        if f.startswith(f"{scene}_{w}x{h}"):
            written += os.path.getsize(os.path.join(work, f))
            os.remove(os.path.join(work, f))
    return {"mode": "render", "scene": scene, "width": w, "height": h, "spp": spp_used, "time": dt,
            "cpu": usage.ru_utime + usage.ru_stime, "peak": usage.ru_maxrss * 1024, "written": written}


def render_table(runs, head):
    lines = [head, "", "| scene | raw pixels | super-pixels | spp | time | CPU time | peak RSS | files written |",
             "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['scene']} | {r['width']} × {r['height']} | {r['width'] // 2} × {r['height'] // 2} | "
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
                r = run_render(size, scene, a.spp, work, texture)
                runs.append(r)
                print(f"[{time.time() - t0:.0f} s] render {size[0]}x{size[1]} ({scene}): {r['time']:.1f} s, "
                      f"peak {r['peak'] / 2 ** 30:.2f} GiB", file=sys.stderr, flush=True)
                save_runs(a, head, runs)
    return print_table(a, render_table(runs, head))


def header():
    from _common import cpu_name

    return (f"{datetime.date.today().isoformat()}, {cpu_name()}, {os.cpu_count()} cores, "
            f"DRJIT_NUM_THREADS={os.environ.get('DRJIT_NUM_THREADS', 'unset')}")


def table(runs, head):
    lines = [head, "",
             "| mode | size | K | texture | intervals | super-pixels fitted | time | time / super-pixel | peak RSS | "
             "peak − RSS before fit | per super-pixel |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        grow = r["peak"] - r["rss_before"] if not math.isnan(r["rss_before"]) else r["peak"]
        n = max(r["pixels"], 1)
        lines.append(f"| {r['mode']} | {r['size']}² | {r['K']} | {r['texture']} | {r['intervals']} | {r['pixels']} | "
                     f"{r['time']:.1f} s | {1e3 * r['time'] / n:.2f} ms | {r['peak'] / 2 ** 30:.2f} GiB | "
                     f"{'–' if math.isnan(r['rss_before']) else f'{grow / 2 ** 30:.2f} GiB'} | "
                     f"{grow / n / 1e3:.1f} kB |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="64,128,256", help="super-pixel frame sizes, comma-separated")
    p.add_argument("--lights", type=int, default=1, choices=(1, 3), help="fitted lights (one fit of all)")
    p.add_argument("--texture", default="smooth", choices=("smooth", "high"))
    p.add_argument("--intervals", default="fisher", choices=("fisher", "auto", "profile"),
                   help="the API fit's intervals")
    p.add_argument("--cli", action="store_true", help="also time the default fit command (one light)")
    p.add_argument("--no-api", action="store_true", help="skip the API fit (with --cli)")
    p.add_argument("--seed", type=int, default=0, help="camera-noise seed")
    p.add_argument("--progress", action="store_true", help="the fits' own progress lines on stderr")
    p.add_argument("--json", metavar="OUT.json", help="the runs and the table's header")
    p.add_argument("--markdown", metavar="OUT.md", help="the table")
    p.add_argument("--table", metavar="IN.json", nargs="+", help="the table of saved runs")
    p.add_argument("--render", action="store_true", help="time `fmbrdf-mi render --raw` instead of the fits")
    p.add_argument("--render-sizes", default="512,1024,2448x2048",
                   help="--render: raw-pixel sizes, N or WxH, comma-separated (default %(default)s)")
    p.add_argument("--scenes", default="plain,textured", help="--render: plain and/or textured")
    p.add_argument("--spp", type=int, help="--render: samples per pixel (default: the command's)")
    p.add_argument("--worker", choices=("api", "cli"), help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, help=argparse.SUPPRESS)
    p.add_argument("--save-maps", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        (worker_api if a.worker == "api" else worker_cli)(a)
        return 0
    if a.table:
        saved = [json.load(open(f)) for f in a.table]
        for s in saved:
            render = s["runs"] and s["runs"][0].get("mode") == "render"
            print((render_table if render else table)(s["runs"], s["header"]) + "\n")
        return 0
    if a.render:
        return main_render(a)
    try:
        sizes = [int(s) for s in a.sizes.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"--sizes: expected comma-separated integers, got {a.sizes!r}") from None
    if not sizes or min(sizes) < 8:
        raise SystemExit(f"--sizes: expected sizes of at least 8 super-pixels, got {a.sizes!r}")
    modes = ([] if a.no_api else ["api"]) + (["cli"] if a.cli else [])
    if not modes:
        raise SystemExit("--no-api: give --cli too (nothing to run)")
    head, runs, t0 = header(), [], time.time()
    for size in sizes:
        for mode in modes:
            print(f"[{time.time() - t0:.0f} s] {size}² ({mode}) ...", file=sys.stderr, flush=True)
            r = run_size(a, size, mode)
            runs.append(r)
            print(f"[{time.time() - t0:.0f} s] {size}² ({mode}): {r['pixels']} super-pixels, {r['time']:.1f} s, "
                  f"peak {r['peak'] / 2 ** 30:.2f} GiB", file=sys.stderr, flush=True)
            save_runs(a, head, runs)
    return print_table(a, table(runs, head))


if __name__ == "__main__":
    sys.exit(main())
