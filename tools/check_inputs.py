#!/usr/bin/env python3
"""Bad and unusual inputs tried as a user would: each case runs the CLI (or a few lines of API) on small
inputs and is judged handled / not handled; the cases are grouped in the classes of the robustness audit
(1: options a loss drops, 2: masks, 3: tiny or odd inputs, 4: interrupts, 5: outputs overwriting inputs,
6: unusable textures, 7: output integrity, 8: late or misleading messages, 9: ignored options; the still
open items; the newcomer's paths).

Usage (about ten minutes on 2 cores):
  DRJIT_NUM_THREADS=1 python tools/check_inputs.py --work NEW_DIR [--only PATTERN] [--json out.json]

"Handled" for a bad input: non-zero exit, no traceback, the error in one line naming the option or file,
nothing new left in the output place.  For an input that should work: exit 0 (or 3, not converged) and
what is asked for (a warning, a marked interval, a file) present.
"""
import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np

PY = sys.executable


class Ctx:
    def __init__(self, repo, work):
        self.repo, self.work = repo, work
        self.env = dict(os.environ, PYTHONPATH=repo, DRJIT_NUM_THREADS="1")

    def p(self, *a):
        return os.path.join(self.work, *a)

    def cli(self, *argv, timeout=600, cwd=None, pre=()):
        t = time.time()
        try:
            proc = subprocess.run([*pre, PY, "-m", "fmbrdf_mi", *map(str, argv)], env=self.env, cwd=cwd or self.work,
                                  capture_output=True, text=True, timeout=timeout)
            return proc.returncode, proc.stdout, proc.stderr, time.time() - t
        except subprocess.TimeoutExpired as e:
            return "timeout", e.stdout or "", e.stderr or "", time.time() - t

    def py(self, code, timeout=600):
        t = time.time()
        try:
            proc = subprocess.run([PY, "-c", code], env=self.env, cwd=self.work, capture_output=True, text=True,
                                  timeout=timeout)
            return proc.returncode, proc.stdout, proc.stderr, time.time() - t
        except subprocess.TimeoutExpired as e:
            return "timeout", e.stdout or "", e.stderr or "", time.time() - t


def sigint_default():
    """A child's Ctrl-C as in a terminal: a shell's background job (nohup ... &) inherits SIGINT ignored, and
    Python then installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt(proc):
    """Ctrl-C to the process group of ``proc``; its stderr, or None (and killed) when it runs on for 60 s."""
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return proc.communicate(timeout=60)[1]
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        return None


def err_lines(err):
    return [l for l in (err or "").strip().splitlines() if l.strip()]


def refused(res, *words, out=None):
    """(ok, why): non-zero, one line naming ``words``, no traceback, ``out`` not created."""
    rc, so, se, _ = res
    lines = err_lines(se)
    why = []
    if rc == 0 or rc == "timeout":
        why.append(f"rc={rc}")
    if "Traceback" in se:
        why.append("traceback")
    errs = [l for l in lines if "error" in l.lower()]
    if len(errs) != 1:
        why.append(f"{len(errs)} error lines")
    text = " ".join(errs).lower()
    for w in words:
        if w.lower() not in text:
            why.append(f"no '{w}'")
    if out is not None and os.path.exists(out):
        why.append(f"left {os.path.basename(out)}")
    return not why, "; ".join(why) or (errs[0][:150] if errs else "")


def worked(res, *words, where="both"):
    rc, so, se, _ = res
    why = []
    if rc not in (0, 3):
        why.append(f"rc={rc}: {err_lines(se)[-1][:150] if err_lines(se) else ''}")
    if "Traceback" in se:
        why.append("traceback")
    text = (so + se).lower()
    for w in words:
        if w.lower() not in text:
            why.append(f"no '{w}'")
    return not why, "; ".join(why) or "ok"


CASES = []


def case(klass, name):
    def deco(f):
        CASES.append((klass, name, f))
        return f
    return deco


# ---------------------------------------------------------------------------------------------------- inputs

def setup(c):
    os.makedirs(c.work, exist_ok=True)
    if not os.path.isdir(c.p("ex")):
        assert c.cli("example-data", c.p("ex"))[0] == 0
    if not os.path.exists(c.p("r_raw.png")):
        rc, so, se, _ = c.cli("render", c.p("r.exr"), "--variant", "llvm_ad_mono_polarized", "--res", "32", "--raw",
                              "--spp", "256", "-q", "--no-previews")
        assert rc == 0, se
    from PIL import Image
    Image.fromarray(np.full((8, 16), 128, np.uint8)).save(c.p("ks.png"))
    Image.fromarray(np.zeros((16, 16), np.uint8)).save(c.p("mask_empty.png"))
    Image.fromarray(np.full((7, 9), 255, np.uint8)).save(c.p("mask_size.png"))
    half = np.zeros((16, 16, 3), np.uint8)
    half[:, :8] = 255
    Image.fromarray(half).save(c.p("mask_rgb.png"))
    np.save(c.p("mask_nan.npy"), np.full((16, 16), np.nan))
    os.makedirs(c.p("mask_dir"), exist_ok=True)
    raw = np.load(c.p("ex", "raw.npy"))
    np.save(c.p("raw_bool.npy"), raw > raw.mean())
    np.save(c.p("raw_complex.npy"), raw.astype(np.complex64))
    with open(c.p("text.png"), "w") as f:
        f.write("not an image\n")
    open(c.p("empty.exr"), "wb").close()
    import OpenEXR
    tex = np.full((8, 16), 0.5, np.float32)
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(hdr, {"Y": tex}).write(c.p("ks.exr"))
    OpenEXR.File(hdr, {f"C{i:02d}": tex for i in range(12)}).write(c.p("ch12.exr"))
    OpenEXR.File(hdr, {"R": tex, "G": tex, "B": tex}).write(c.p("rgb.exr"))
    data = open(c.p("ks.exr"), "rb").read()
    open(c.p("trunc.exr"), "wb").write(data[: len(data) // 2])
    np.save(c.p("raw_nan.npy"), np.full(raw.shape, np.nan))
    os.makedirs(c.p("tex_dir"), exist_ok=True)
    OpenEXR.File(hdr, {"Y": -tex}).write(c.p("neg.exr"))
    OpenEXR.File(hdr, {"Y": np.full_like(tex, np.nan)}).write(c.p("nan.exr"))
    # the authors' layout with an all-NaN viewing-ray file
    if not os.path.isdir(c.p("blob_nan")):
        shutil.copytree(c.p("ex", "data", "blob"), c.p("blob_nan"))
        v = np.load(c.p("blob_nan", "calibration", "vpL_img.npy"))
        np.save(c.p("blob_nan", "calibration", "vpL_img.npy"), np.full_like(v, np.nan))
    with open(c.p("huge_samples.toml"), "w") as f:
        src = open(os.path.join(c.repo, "fmbrdf_mi", "scenes", "dataset_example.toml")).read()
        f.write(re.sub(r"(?m)^samples\s*=.*$", "samples = 1000000000000", src))


RAW = "r_raw.png"          # a raw render with its sidecar (the built-in sphere's geometry)
STOKES = "r.exr"           # a Stokes EXR: no camera noise model
CAP = ["ex/capture.png", "--sphere", "auto", "--mask", "ex/mask.png", "--light=-0.42,0.31,0.85",
       "--conversion-gain", "2.44", "--read-noise", "2.5"]
QUICK = ["--starts", "1", "--intervals", "fisher", "-q"]


# ---------------------------------------------------------------------------------------------------- class 1
for opt in (["--albedo", "per-pixel"], ["--albedo", "per-pixel-bilinear"],
            ["--albedo", "per-pixel", "--albedo-smooth", "0.1"], ["--intervals", "profile"],
            ["--materials", "auto:2"], ["--area-points", "4"]):
    def _f(c, opt=opt):
        out = c.p("o1_" + opt[-1].replace(":", "").replace(".", ""))
        return refused(c.cli("fit", STOKES, *opt, "-o", out, "-q"), opt[0], out=out)
    case(1, f"Stokes EXR + {' '.join(opt)}")(_f)

# ---------------------------------------------------------------------------------------------------- class 2
for m in ("mask_size.png", "mask_empty.png", "mask_nan.npy", "mask_dir", "missing.png"):
    def _f(c, m=m):
        out = c.p("o2_" + m)
        return refused(c.cli("fit", RAW, "--mask", m, "-o", out, "-q"), "mask", out=out)
    case(2, f"sidecar capture + --mask {m}")(_f)

@case(2, "sidecar capture + an RGB mask of the left half: applied")
def _rgb_mask(c):
    outs = {}
    for name, extra in (("o2_nomask", []), ("o2_rgb", ["--mask", "mask_rgb.png"])):
        res = c.cli("fit", RAW, *extra, *QUICK, "-o", c.p(name), "--force")
        if res[0] not in (0, 3):
            return False, f"{name}: rc={res[0]} {err_lines(res[2])[-1:]}"
        outs[name] = json.load(open(c.p(name, "fit.json")))["models"]["fmbrdf"]["n_pixels"]
    return outs["o2_rgb"] < 0.6 * outs["o2_nomask"], f"pixels {outs['o2_rgb']} with the mask, {outs['o2_nomask']} without"


# ---------------------------------------------------------------------------------------------------- class 3
for n in (1, 2, 3, 19):
    def _f(c, n=n):
        out = c.p(f"o3_mp{n}")
        return refused(c.cli("fit", RAW, "--max-pixels", n, "-o", out, "-q"), "max-pixels", out=out)
    case(3, f"--max-pixels {n}")(_f)


@case(3, "API fit(max_pixels=2)")
def _api_max_pixels(c):
    rc, so, se, t = c.py(
        "import fmbrdf_mi.fit as F\n"
        "try:\n"
        f"    F.fit_files({c.p(RAW)!r}, {c.p('o3_api')!r}, max_pixels=2, progress=False)\n"
        "    print('RAN')\n"
        "except Exception as e:\n"
        "    print('REFUSED', type(e).__name__, e)\n")
    ok = "REFUSED" in so and "max_pixels" in so and "\n" not in so.strip() and not os.path.exists(c.p("o3_api"))
    return ok, (so.strip() or se.strip()[-200:])[:200]


for arr in ("raw_bool.npy", "raw_complex.npy"):
    def _f(c, arr=arr):
        out = c.p("o3_" + arr)
        return refused(c.cli("fit", arr, "--conversion-gain", "2.44", "--read-noise", "2.5", "--sphere", "auto",
                             "--mask", "ex/mask.png", "--light=-0.42,0.31,0.85", "-o", out, "-q"), arr, out=out)
    case(3, f"a {arr} as the raw mosaic")(_f)


@case(3, "same image twice in a joint fit")
def _twice(c):
    out = c.p("o3_twice")
    return refused(c.cli("fit", RAW, RAW, "--light=-0.5,0.5,1", "--light=-0.5,0.5,1", "-o", out, "-q"),
                   RAW, out=out)


@case(3, "chi2/dof far below 1 (read noise stated 100x) flagged")
def _overstated(c):
    res = c.cli("fit", *CAP[:-4], "--conversion-gain", "2.44", "--read-noise", "250", *QUICK[:-1],
                "-o", c.p("o3_over"))
    return worked(res, "scatter less")


# ---------------------------------------------------------------------------------------------------- class 4
@case(4, "Ctrl-C in fit-brdf --jobs 2 stops promptly")
def _ctrl_c_brdf(c):
    d = c.p("merl_many")
    os.makedirs(d, exist_ok=True)
    for i in range(12):
        dst = os.path.join(d, f"m{i}.binary")
        if not os.path.exists(dst):
            os.symlink(c.p("ex", "merl", "glossy.binary" if i % 2 else "matte.binary"), dst)
    out = c.p("o4_brdf")
    shutil.rmtree(out, ignore_errors=True)
    ok, why = _interrupt(c, ["fit-brdf", d, "--jobs", "2", "-o", out, "-q"], 5, out)
    done = os.listdir(out) if os.path.isdir(out) else []
    return ok, f"{why}, outputs {len(done)}"


def _interrupt(c, argv, delay, out):
    proc = subprocess.Popen([PY, "-m", "fmbrdf_mi", *argv], env=c.env, cwd=c.work, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=sigint_default)
    time.sleep(delay)
    if proc.poll() is not None:
        return False, f"ended (rc={proc.returncode}) before the interrupt"
    t0 = time.time()
    se = interrupt(proc)
    if se is None:
        return False, "still running 60 s after Ctrl-C"
    return proc.returncode == 130 and time.time() - t0 < 20 and "Traceback" not in se, \
        f"rc={proc.returncode}, stopped {time.time() - t0:.1f} s after Ctrl-C"


@case(4, "Ctrl-C during a per-pixel fit: exit 130 promptly, no output directory")
def _fit_ctrl_c(c):
    out = c.p("o4_fit")
    shutil.rmtree(out, ignore_errors=True)
    ok, why = _interrupt(c, ["fit", RAW, "--albedo", "per-pixel", "-o", out, "-q"], 15, out)
    left = os.path.exists(out) and os.listdir(out)
    return ok and not left, why + (f"; left {left}" if left else "")


@case(4, "Ctrl-C during dataset: exit 130 promptly; the rerun resumes and finishes")
def _dataset_ctrl_c(c):
    out = c.p("o4_ds")
    shutil.rmtree(out, ignore_errors=True)
    ok, why = _interrupt(c, ["dataset", "--config", "builtin:dataset_example", "--samples", "200", "--out", out, "-q"],
                         4, out)
    res = c.cli("dataset", "--config", "builtin:dataset_example", "--samples", "200", "--out", out, "-q", timeout=900)
    return ok and res[0] == 0, why + f"; rerun rc={res[0]}"


@case(4, "fit --max-time 1 of a per-pixel fit: stops, exit 3")
def _max_time(c):
    res = c.cli("fit", RAW, "--albedo", "per-pixel", "--max-time", "1", "-o", c.p("o4_mt"), "-q", "--force")
    return res[0] == 3 and res[3] < 60 and "Traceback" not in res[2], f"rc={res[0]}, {res[3]:.0f} s"


# ---------------------------------------------------------------------------------------------------- class 5
@case(5, "render OUT -D k_s=OUT --force")
def _own_texture(c):
    shutil.copy(c.p("ks.exr"), c.p("self.exr"))
    before = open(c.p("self.exr"), "rb").read()
    res = c.cli("render", "self.exr", "-D", "k_s=self.exr", "--force", "--variant", "llvm_ad_mono_polarized",
                "--res", "16", "-q")
    ok, why = refused(res, "self.exr")
    same = open(c.p("self.exr"), "rb").read() == before
    return ok and same, why + ("" if same else "; input overwritten")


# ---------------------------------------------------------------------------------------------------- class 6
for tex, variant in (("text.png", "llvm_ad_mono_polarized"), ("empty.exr", "llvm_ad_mono_polarized"),
                     ("trunc.exr", "llvm_ad_mono_polarized"), ("ch12.exr", "llvm_ad_mono_polarized"),
                     ("rgb.exr", "llvm_ad_spectral_polarized"), ("missing.exr", "llvm_ad_mono_polarized")):
    def _f(c, tex=tex, variant=variant):
        out = c.p("o6_" + tex.replace(".", "_") + ".exr")
        return refused(c.cli("render", out, "-D", f"k_s={tex}", "--variant", variant, "--res", "16", "--spp", "2",
                             "-q"), tex, out=out)
    case(6, f"texture {tex} ({variant})")(_f)


# ---------------------------------------------------------------------------------------------------- class 7
@case(7, "per-pixel fit then --force shared fit: no stale maps")
def _stale(c):
    out = c.p("o7_stale")
    shutil.rmtree(out, ignore_errors=True)
    a = c.cli("fit", RAW, "--albedo", "per-pixel", *QUICK, "-o", out)
    if a[0] not in (0, 3):
        return False, f"per-pixel fit rc={a[0]} {err_lines(a[2])[-1:]}"
    had = sorted(os.listdir(out))
    b = c.cli("fit", RAW, *QUICK, "-o", out, "--force")
    left = [f for f in os.listdir(out) if f.startswith(("k_s", "k_b", "albedo"))]
    return b[0] in (0, 3) and not left, f"maps before {len([f for f in had if f.startswith(('k_s', 'k_b'))])}, " \
                                        f"after {left}"


@case(7, "two fits into one -o at once")
def _two(c):
    out = c.p("o7_two")
    shutil.rmtree(out, ignore_errors=True)
    argv = [PY, "-m", "fmbrdf_mi", "fit", RAW, "-q", "-o", out]     # the default fit: long enough to overlap
    p1 = subprocess.Popen(argv, env=c.env, cwd=c.work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(4)
    if p1.poll() is not None:
        return False, f"the first fit ended (rc={p1.returncode}) before the second started"
    p2 = subprocess.run(argv + ["--force"], env=c.env, cwd=c.work, capture_output=True, text=True, timeout=600)
    so, se = p1.communicate(timeout=600)
    rcs = (p1.returncode, p2.returncode)
    ok = sum(r in (0, 3) for r in rcs) == 1 and "Traceback" not in p2.stderr + se
    msg = (err_lines(p2.stderr) or err_lines(se) or [""])[-1][:150]
    return ok, f"rc {rcs}: {msg}"


@case(7, "render --raw of a black image refused, nothing left")
def _black(c):
    d = c.p("o7_black")
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    res = c.cli("render", os.path.join(d, "t.exr"), "--res", "16", "--spp", "2", "-q", "--raw", "-D",
                "light_dir=0,0,-1", "--variant", "llvm_ad_mono_polarized")
    ok, why = refused(res, "black")
    left = os.listdir(d)
    return ok and not left, why + (f"; left {left}" if left else "")


@case(7, "Ctrl-C during render leaves nothing")
def _render_ctrl_c(c):
    d = c.p("o7_int")
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    ok, why = _interrupt(c, ["render", os.path.join(d, "t.exr"), "--res", "256", "--spp", "65536", "-q", "--variant",
                             "llvm_ad_mono_polarized"], 8, d)
    left = os.listdir(d)
    return ok and not left, f"{why}, left {left}"


# ---------------------------------------------------------------------------------------------------- class 8
for argv, words in ((["--albedo", "per-pixel", "--albedo-smooth", "1e-200"], ["albedo-smooth"]),
                    (["--materials", "auto:2", "--albedo", "per-pixel", "--albedo-smooth", "0.1"], ["materials"]),
                    (["--materials", "auto:2", "--albedo", "per-pixel-bilinear"], ["materials"]),
                    (["--normals", "ex/mask.png"], ["normals"]),
                    (["--mask", "ex/capture.toml"], ["mask"]),
                    (["--init", "eta=abc"], ["init"])):
    def _f(c, argv=argv, words=words):
        out = c.p("o8_" + "_".join(a.strip("-").replace("/", "").replace(":", "") for a in argv)[:40])
        res = c.cli("fit", RAW, *argv, "-o", out, "-q", timeout=120)
        ok, why = refused(res, *words, out=out)
        return ok and res[3] < 60, why + f" ({res[3]:.0f} s)"
    case(8, f"fit {' '.join(argv)}")(_f)


@case(8, "per-pixel fit --init with the shape parameters only")
def _init_pp(c):
    res = c.cli("fit", RAW, "--albedo", "per-pixel", "--init", "eta=1.5,alpha=0.3,beta=2,kappa=10", *QUICK,
                "-o", c.p("o8_init"), "--force")
    return worked(res)


# ---------------------------------------------------------------------------------------------------- class 9
@case(9, "--from with an option typed at its default")
def _from_default(c):
    src = c.p("o9_src")
    if not os.path.exists(os.path.join(src, "fit.json")):
        r = c.cli("fit", RAW, *QUICK, "-o", src, "--force")
        if r[0] not in (0, 3):
            return False, f"source fit rc={r[0]}"
    out = c.p("o9_from")
    return refused(c.cli("fit", "--from", os.path.join(src, "fit.json"), "--starts", "2", "-o", out, "-q"),
                   "starts", out=out)


@case(9, "fit-brdf --force --skip-existing")
def _brdf_fs(c):
    out = c.p("o9_fs")
    return refused(c.cli("fit-brdf", "ex/merl/matte.binary", "--force", "--skip-existing", "-o", out, "-q"),
                   "skip-existing", out=out)


@case(9, "fit-brdf one file --jobs 2 says what it does")
def _brdf_jobs(c):
    out = c.p("o9_jobs")
    shutil.rmtree(out, ignore_errors=True)
    res = c.cli("fit-brdf", "ex/merl/matte.binary", "--jobs", "2", "-o", out)
    rc, so, se, _ = res
    ok = rc != 0 and "jobs" in se or ("jobs" in (so + se).lower() and rc == 0)
    return ok and "Traceback" not in se, f"rc={rc}: {[l for l in err_lines(se) + err_lines(so) if 'jobs' in l][:1]}"


# ---------------------------------------------------------------------------------------------------- still open
@case("open", "authors' object with an all-NaN vpL_img.npy")
def _nan_rays(c):
    out = c.p("oo_nan")
    return refused(c.cli("fit", "--authors", "blob_nan", "-o", out, "-q"), "vpL_img", out=out)


@case("open", "dataset samples = 10**12")
def _samples(c):
    out = c.p("oo_ds")
    return refused(c.cli("dataset", "--config", "huge_samples.toml", "--out", out, "-q", timeout=120), "samples",
                   out=out)


@case("open", "dataset --samples 10**12")
def _samples_cli(c):
    out = c.p("oo_ds2")
    return refused(c.cli("dataset", "--config", "builtin:dataset_example", "--samples", "1000000000000", "--out",
                         out, "-q", timeout=120), "samples", out=out)


# ---------------------------------------------------------------------------------------------------- newcomer
@case("newcomer", "EXR texture render pinned to one core (taskset -c 0, 300 s)")
def _one_core(c):
    out = c.p("on_core.exr")
    for f in ("on_core.exr", "on_core_k_s.exr"):
        if os.path.exists(c.p(f)):
            os.remove(c.p(f))
    res = c.cli("render", out, "-D", "k_s=ks.exr", "--variant", "llvm_ad_mono_polarized", "--res", "16", "--spp", "2",
                "--no-previews", "-q", pre=("timeout", "300", "taskset", "-c", "0"), timeout=320)
    return res[0] == 0 and os.path.exists(out), f"rc={res[0]}, {res[3]:.0f} s"


@case("newcomer", "--variant cuda_ad_mono_polarized without a GPU")
def _cuda(c):
    out = c.p("on_cuda.exr")
    res = c.cli("render", out, "--variant", "cuda_ad_mono_polarized", "--res", "16", "-q")
    return refused(res, "cuda", out=out)


@case("newcomer", "scalar_spectral_polarized: mi.load_dict after import fmbrdf_mi")
def _scalar(c):
    rc, so, se, _ = c.py("import mitsuba as mi; mi.set_variant('scalar_spectral_polarized'); import fmbrdf_mi\n"
                         "try:\n    mi.load_dict({'type': 'fmbrdf'}); print('LOADED')\n"
                         "except Exception as e:\n    print(str(e).splitlines()[-1])\n")
    line = so.strip().splitlines()[-1] if so.strip() else se.strip()[-200:]
    return "not supported" in line and "not found" not in line, line[:200]


@case("newcomer", "example-data into a fresh directory, refused on an existing one")
def _example(c):
    d = c.p("on_ex")
    shutil.rmtree(d, ignore_errors=True)
    a = c.cli("example-data", d)
    b = c.cli("example-data", d)
    ok_b, why = refused(b, "on_ex")
    return a[0] == 0 and ok_b, f"first rc={a[0]}; second: {why}"


@case("newcomer", "docs shell blocks never write into the repository (no '-o docs/')")
def _docs_paths(c):
    bad = []
    for root, _, files in os.walk(os.path.join(c.repo, "docs")):
        for f in files:
            if f.endswith(".md"):
                for i, line in enumerate(open(os.path.join(root, f)), 1):
                    if re.search(r"fmbrdf-mi .*(-o|--out)\s+docs/", line):
                        bad.append(f"{f}:{i}")
    return not bad, ", ".join(bad) or "none"


@case("newcomer", "a Wald interval cut at a bound is marked in fit.json (API summary)")
def _wald_bound(c):
    rc, so, se, _ = c.py(
        "import types, numpy as np\n"
        "from fmbrdf_mi.fit import uncertainty as U\n"
        "from fmbrdf_mi.fit.evaluate.models import Bounds, State, get_model\n"
        "from fmbrdf_mi.fit.evaluate.parameters import Parameters\n"
        "pa = Parameters(get_model('fmbrdf'))\n"
        "p = types.SimpleNamespace(names=pa.shape_names, bounds=Bounds(pa), params=pa)\n"
        "st = State({'eta': 1.5, 'alpha': 0.3, 'beta': 2.0, 'kappa': 2.0}, 0.8, 0.2)\n"
        "c = U.Covariance(list(pa.reported_names), np.diag([1e-4, 1e-4, 1e-4, 9.0, 1e-4, 1e-4]), {}, [('fisher', '')])\n"
        "print(U.summary(p, st, c).get('interval_kind'))\n")
    return "open at the bound" in so, (so.strip() or se.strip()[-200:])[:200]


@case("newcomer", "one-image per-pixel fit of a 32^2 render: kappa's interval covers the truth or says it is open")
def _pp_kappa(c):
    out = c.p("on_pp")
    res = c.cli("fit", RAW, "--albedo", "per-pixel", "-o", out, "-q", "--force")
    if res[0] not in (0, 3):
        return False, f"rc={res[0]} {err_lines(res[2])[-1:]}"
    u = json.load(open(os.path.join(out, "fit.json")))["models"]["fmbrdf"]["uncertainty"]
    lo, hi = u["ci95"]["kappa"]
    kind = (u.get("interval_kind") or {}).get("kappa", "fisher")
    ok = lo <= 10.0 <= hi or "open" in kind or "optima" in kind
    return ok, f"kappa [{lo:.3g}, {hi:.3g}] ({kind})"


# ---------------------------------------------------------------------------------------------------- more inputs
ANGLES = ["ex/i0.tif", "ex/i45.tif", "ex/i90.tif", "ex/i135.tif", "--normals", "ex/normal.npy", "--mask", "ex/mask.png",
          "--light=-0.42,0.31,0.85"]
for src, opt, words in (
        ([STOKES], ["--albedo-smooth", "0.1"], ["--albedo-smooth"]),
        ([RAW], ["--loss", "paper", "--albedo", "per-pixel"], ["--albedo per-pixel"]),
        (ANGLES, ["--albedo", "per-pixel"], ["--albedo per-pixel"]),
        (ANGLES, ["--area-points", "2"], ["--area-points"]),
        ([RAW], ["--albedo-smooth", "0"], ["--albedo-smooth"]),
        ([RAW], ["--albedo", "per-pixel", "--albedo-smooth", "nan"], ["--albedo-smooth"]),
        ([RAW], ["--albedo", "per-pixel", "--albedo-smooth", "0.1,0.2,0.3"], ["--albedo-smooth"]),
        ([RAW], ["--materials", "auto:1"], ["--materials"]),
        ([RAW], ["--materials", "auto:x"], ["--materials"]),
        ([RAW], ["--materials", "mask_size.png"], ["materials", "(7, 9)"]),
        ([RAW], ["--fix", "gamma=1"], ["--fix"]),
        ([RAW], ["--bounds", "alpha=2:3"], ["--bounds"]),
        ([RAW], ["--holdout", "0"], ["--holdout"]),
        ([RAW], ["--albedo", "per-pixel", "--init", "eta=1.5,alpha=0.3,beta=2,kappa=10,k_s=1,r_k=1"], ["--init"]),
        (["raw_nan.npy", "--conversion-gain", "2.44", "--read-noise", "2.5", "--sphere", "auto", "--mask",
          "ex/mask.png", "--light=-0.42,0.31,0.85"], [], ["raw_nan.npy"]),
        (["ex/capture.png", "--conversion-gain", "2.44", "--read-noise", "2.5", "--sphere", "auto", "--light=-0.42,0.31,0.85"],
         ["--mask", "mask_size.png"], ["mask"]),
        (["ex/capture.png", "--conversion-gain", "2.44", "--read-noise", "2.5", "--sphere", "auto", "--light=-0.42,0.31,0.85"],
         ["--mask", "mask_empty.png"], ["mask"]),
        ([], ["--from", "missing/fit.json"], ["missing/fit.json"]),
        ([], ["--from", "ex/capture.toml"], ["capture.toml"]),
):
    def _f(c, src=src, opt=opt, words=words):
        out = c.p("ox_" + re.sub(r"[^A-Za-z0-9]+", "_", " ".join(src[:1] + opt))[:50])
        res = c.cli("fit", *src, *opt, "-o", out, "-q", timeout=120)
        ok, why = refused(res, *words, out=out)
        return ok and res[3] < 60, why + f" ({res[3]:.0f} s)"
    case(8 if opt and opt[0] in ("--albedo-smooth", "--materials", "--fix", "--bounds", "--holdout", "--init") else
         (2 if "mask" in " ".join(opt) else (9 if "--from" in opt else (3 if not opt else 1))),
         f"fit {' '.join(src[:1])} {' '.join(opt)}")(_f)

for argv, words in ((["-D", "k_b=o5.exr"], ["o5.exr"]), (["-D", "k_s=tex_dir"], ["tex_dir", "directory"]),
                    (["-D", "k_s=neg.exr"], ["k_s", ">= 0"]), (["-D", "k_s=nan.exr"], ["k_s", "finite"]),
                    (["-D", "alpha=5"], ["alpha"]), (["-D", "light_dir=0,0,0"], ["light_dir"]),
                    (["--res", "0"], ["--res"]), (["--spp", "0"], ["spp", ">= 1"])):
    def _f(c, argv=argv, words=words):
        out = c.p("o5.exr")
        if "o5" in argv[-1]:
            shutil.copy(c.p("ks.exr"), out)
        else:
            for f in os.listdir(c.work):
                if f.startswith("o5"):
                    os.remove(c.p(f))
        before = sorted(os.listdir(c.work))
        res = c.cli("render", out, *argv, "--variant", "llvm_ad_mono_polarized", "--res", "16", "--spp", "2",
                    "-q", "--force", timeout=120) if "--res" not in argv and "--spp" not in argv else \
            c.cli("render", out, *argv, "--variant", "llvm_ad_mono_polarized", "-q", timeout=120)
        ok, why = refused(res, *words)
        new = sorted(set(os.listdir(c.work)) - set(before))
        return ok and not new, why + (f"; left {new}" if new else "")
    case(6 if "k_s" in argv[-1] else (5 if "o5" in argv[-1] else 8), f"render {' '.join(argv)}")(_f)


@case(9, "fit-brdf one file --skip-existing with its params.json there")
def _brdf_skip(c):
    out = c.p("o9_jobs")      # written by the --jobs case
    if not os.path.isdir(out):
        return False, "needs the --jobs case first"
    res = c.cli("fit-brdf", "ex/merl/matte.binary", "--skip-existing", "-o", out, timeout=120)
    rc, so, se, t = res
    return rc == 0 and "skip" in (so + se).lower() and t < 60, f"rc={rc}, {t:.0f} s: {err_lines(se)[-1:] }"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repo", default=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                    help="the checkout to test (PYTHONPATH of the children; default: this one)")
    ap.add_argument("--work", required=True, help="a new directory for the inputs and outputs")
    ap.add_argument("--only", default=None, help="regular expression on 'class name'")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    c = Ctx(os.path.abspath(a.repo), os.path.abspath(a.work))
    setup(c)
    rows = []
    for klass, name, f in CASES:
        if a.only and not re.search(a.only, f"{klass} {name}"):
            continue
        t = time.time()
        try:
            ok, why = f(c)
        except Exception as e:          # the audit's own failure: counted as not handled, shown
            ok, why = False, f"audit error {type(e).__name__}: {e}"
        rows.append({"class": str(klass), "case": name, "handled": bool(ok), "detail": why,
                     "s": round(time.time() - t, 1)})
        print(f"{'OK ' if ok else 'NOT'} [{klass}] {name}: {why} ({time.time() - t:.0f} s)", flush=True)
    n, h = len(rows), sum(r["handled"] for r in rows)
    print(f"\n{n} inputs tried, {h} handled, {n - h} not handled")
    for k in dict.fromkeys(r["class"] for r in rows):
        rs = [r for r in rows if r["class"] == k]
        print(f"  class {k:9s} {sum(r['handled'] for r in rs)}/{len(rs)}")
    if a.json:
        json.dump(rows, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
