"""Regression record of the fits: a fixed set of small fits run through the command line, every number they write.

    python tools/record_fits.py --out now.json                     # record (inputs made in a temporary directory)
    python tools/record_fits.py --compare tools/record_fits_baseline.json   # record and compare; exit 1 if moved
    python tools/record_fits.py --work /tmp/rf --keep --out a.json  # keep inputs and fit outputs
    python tools/record_fits.py --work /tmp/rf --reuse-inputs --compare a.json   # the same input files again
    python tools/record_fits.py --compare-only a.json b.json        # compare two saved records

What it is for: the fit package (fmbrdf_mi/fit/) is refactored, and the fits must give the same numbers before
and after.  So this script touches the package only through its stable interface: it makes its inputs with
``fmbrdf-mi render`` (and, where no command makes them, with NumPy, Mitsuba and ``fmbrdf_mi.sensor.camera``, which is
outside fmbrdf_mi/fit/), runs every fit as ``python -m fmbrdf_mi fit ...`` / ``fit-brdf ...`` in a subprocess,
and reads what the commands write (fit.json, params.json).

Cases (all small: the whole run takes about 2 minutes on a 2-core machine):

  a_like_m1, a_like_m2   mono likelihood fit of a raw 12-bit mosaic (``render --raw --raw-seed``, 64 px, the
                         sidecar supplies sphere, light, gain and read noise), two materials
  b_paper_m1, b_paper_m2 the paper's loss (``--loss paper``) on the same renders' Stokes EXRs
  c_joint_free_power     joint likelihood fit of 3 raw mosaics under 3 lights of unequal irradiance (a TOML
                         manifest whose [defaults] irradiance hides the ratios) with ``--free-power``
  d_colour_24            colour fit of a 24-period sphere (``render --raw --sensor colour``, 96 px, the sphere
                         filling the frame: periods = sphere diameter in 4x4 periods, as tools/bench_fit_colour.py)
  e_refine_normals       ``--refine-normals`` on a 16 x 16 super-pixel mesh object, 3 lights, authors' layout
  f_authors              ``--authors DIR --holdout 3`` on a 24 x 24 super-pixel mesh object, 4 lights
  g_fit_brdf             ``fit-brdf`` on a synthetic MERL file (Lambert + a GGX-like lobe), 5000 samples

The mesh objects are those of fmbrdf_mi/synthetic/mesh_object.py (the code copied here, so that moving that
module changes nothing): for the same arguments the files come out byte for byte the same.
Every input is deterministic (seeded camera noise, seeded renders); text inputs are hashed with the work
directory's path replaced by <WORK>, so two work directories give the same hashes.

Record (``--out``): a flat JSON object {"<case>/<key path>": number} of every number in the outputs (estimates,
standard errors, intervals, correlations, chi^2, chi^2/dof, losses and their terms, sample and pixel counts,
powers, relighting errors, start points and ends, the normal refinement's per-iteration energies, converged
flags as 0/1, exit statuses) except timings, options, the fits' per-iteration "history" lists (their length is
kept as "<case>/.../history/length") and the reproduce/inputs/truth blocks.  "text" holds the strings (stop
reasons, weakly identified lists, ...): compared and reported, but not a failure.  "meta" (date, CPU, git commit,
versions, per-case times, commands, SHA-256 of every input file) is not compared; differing input hashes are
reported, as the first suspect when numbers move.

Compare (``--compare BASELINE``): per key the relative difference |a - b| / max(|a|, |b|); exit status 1 when any
exceeds ``--rtol`` (default 1e-9) or a key is missing or new, 0 otherwise.  Every key that moved at all is listed,
then a per-case summary.

Noise floor: two runs with fresh inputs in different work directories, a third at
load ~3.5 with the inputs reused, two cases with an empty Dr.Jit kernel cache, and every case run with 1 and 8
Dr.Jit threads (``dr.set_thread_count``) gave every number bit for bit the same (relative difference 0): rtol 1e-9
has no run-to-run noise to absorb here.

Across a refactor: the inputs go through ``fmbrdf-mi render`` (whose --raw path uses fmbrdf_mi.fit.observations'
layout parser) and fit-brdf uses fmbrdf_mi.fit.models / pixel_model, so keep the pre-refactor inputs
(``--work DIR``) and, if the input hashes differ afterwards, run ``--work DIR --reuse-inputs --compare ...`` to
tell a changed input from a changed fit.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VERSION = 1

# ---------------------------------------------------------------------------------------------------------------
# inputs

MONO = "llvm_ad_mono_polarized"
#: the two materials of cases a and b (glossy, kappa identified; rougher, body-heavy)
MATERIALS = {
    "m1": {"eta": 1.5, "alpha": 0.15, "beta": 2.0, "kappa": 10.0, "k_s": 1.0, "r_k": 1.0},
    "m2": {"eta": 1.8, "alpha": 0.4, "beta": 1.2, "kappa": 3.0, "k_s": 0.8, "r_k": 0.4},
}
#: case c: three lights of unequal irradiance, one exposure
JOINT = {"material": {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5},
         "lights": [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)],
         "irradiance": [3.0, 1.8, 4.2], "raw_exposure": 2500.0}
#: the mesh objects of cases e and f (the material and lights of tests/fit/test_inputs_authors.py)
OBJECT_MATERIAL = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
OBJECT_LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8), (0.0, 0.1, 1.0)]
OBJECT_POWERS = [1.0, 0.7, 1.2, 0.9]
OBJECT_CAMERA = {"full_well": 20000.0, "read_noise": 2.5, "bits": 16}
#: case g: per-channel Lambert + lobe albedos
MERL_KD, MERL_KS, MERL_ALPHA, MERL_F0 = (0.4, 0.2, 0.1), (1.0, 1.0, 1.0), 0.2, 0.04


def run(argv, cwd, log):
    """Run a command (list), its output to ``log``; the exit status."""
    with open(log, "w") as f:
        f.write("$ " + " ".join(argv) + "\n")
        f.flush()
        p = subprocess.run(argv, cwd=cwd, stdout=f, stderr=subprocess.STDOUT, env=_env())
    return p.returncode


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONHASHSEED", "0")
    return env


def fmbrdf(*args):
    return [sys.executable, "-m", "fmbrdf_mi", *map(str, args)]


def render(inputs, name, *args):
    """``fmbrdf-mi render`` into ``inputs`` (relative output path: the EXR's recorded command is the same
    wherever the work directory is)."""
    argv = fmbrdf("render", name, "--no-previews", "-q", *args)
    rc = run(argv, inputs, os.path.join(inputs, name + ".log"))
    if rc != 0:
        sys.exit(f"record_fits: input render failed ({rc}): {' '.join(argv)}; see {name}.log in {inputs}")
    return argv


def fmt(v):
    return ",".join(repr(float(x)) for x in np.atleast_1d(v))


def material_args(p):
    return [a for k, v in p.items() for a in ("-D", f"{k}={fmt(v)}")]


def make_renders(inputs):
    """Cases a-d: renders of the built-in sphere with raw captures; returns the commands."""
    cmds = []
    for name, p in MATERIALS.items():
        cmds.append(render(inputs, f"{name}.exr", "--variant", MONO, "--res", "64", "--spp", "64",
                           *material_args(p), "--raw", "--raw-seed", "1"))
    for j, (l, e) in enumerate(zip(JOINT["lights"], JOINT["irradiance"])):
        cmds.append(render(inputs, f"joint{j}.exr", "--variant", MONO, "--res", "48", "--spp", "64",
                           *material_args(JOINT["material"]), "-D", f"light_dir={fmt(l)}",
                           "-D", f"irradiance={e!r}", "--raw", "--raw-exposure", repr(JOINT["raw_exposure"]),
                           "--raw-seed", str(10 + j)))
    # 24 periods: 96 raw pixels, the orthographic frame exactly the sphere's diameter (radius 1 at distance 5)
    fov = math.degrees(2 * math.atan(1 / 5.0))
    cmds.append(render(inputs, "colour.exr", "--res", "96", "--spp", "64", "-D", "k_s=0.6,0.4,0.5",
                       "-D", "r_k=0.7", "-D", f"fov={fov!r}", "--raw", "--sensor", "colour", "--raw-seed", "5"))
    # the joint manifest: powers unknown to the fit (one irradiance for all; the images differ by 3 : 1.8 : 4.2)
    side = json.load(open(os.path.join(inputs, "joint0_raw.json")))
    irr0 = JOINT["irradiance"][0] * side["capture"]["dn_per_input_unit"]
    lines = ["# case c: three lights; the fit is told one irradiance (the first image's), --free-power finds the rest",
             "[defaults]", f"irradiance = {irr0!r}", ""]
    for j, l in enumerate(JOINT["lights"]):
        lines += ["[[image]]", f'input = "joint{j}_raw.png"', f"light = [{fmt(l).replace(',', ', ')}]", ""]
    with open(os.path.join(inputs, "joint.toml"), "w") as f:
        f.write("\n".join(lines))
    return cmds


# --- mesh objects in the authors' layout (NumPy + Mitsuba + fmbrdf_mi.sensor.camera: nothing from fmbrdf_mi/fit/) ---

def blob_mesh(n_theta=48, n_phi=96, axes=(1.0, 0.75, 0.85), bump=0.12, rotation_deg=(25.0, -35.0)):
    """(positions, faces, vertex normals) of an ellipsoid with a three-lobed bump, rotated."""
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
    fn = np.cross(p1 - p0, p2 - p0)
    keep = np.linalg.norm(fn, axis=1) > 1e-12
    faces, fn = faces[keep], fn[keep]
    if np.mean(np.sum(fn * (p0[keep]), axis=1)) < 0:
        faces, fn = faces[:, ::-1], -fn
    vn = np.zeros_like(pos)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    return pos, faces, vn


def _mitsuba():
    import mitsuba as mi

    if mi.variant() != MONO:
        mi.set_variant(MONO)
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


def _mesh_scene(mesh):
    mi = _mitsuba()
    pos, faces, vn = mesh
    m = mi.Mesh("blob", len(pos), len(faces), has_vertex_normals=True)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(pos.astype(np.float32).ravel())
    p["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    p["vertex_normals"] = mi.Float(vn.astype(np.float32).ravel())
    p.update()
    return mi.load_dict({"type": "scene", "blob": m})


def pinhole_rays(shape, fov_deg, distance):
    """Camera position and unit ray directions (H, W, 3) through pixel centres (x right, y up, z to camera)."""
    h, w = shape
    f = 0.5 * w / np.tan(np.radians(fov_deg) / 2)
    X, Y = np.meshgrid(np.arange(w) + 0.5 - 0.5 * w, np.arange(h) + 0.5 - 0.5 * h)
    d = np.stack([X, -Y, np.full_like(X, -f)], -1)
    return np.array([0.0, 0.0, distance]), d / np.linalg.norm(d, axis=-1, keepdims=True), f


def ray_cast(scene, origin, dirs):
    """Shading normals (H, W, 3) facing the camera and the hit mask (front faces)."""
    import drjit as dr

    mi = _mitsuba()
    h, w = dirs.shape[:2]
    d = dirs.reshape(-1, 3)
    o = np.tile(origin, (len(d), 1))
    ray = mi.Ray3f(mi.Point3f(np.ascontiguousarray(o.T, np.float32)),
                   mi.Vector3f(np.ascontiguousarray(d.T, np.float32)))
    si = scene.ray_intersect(ray)
    dr.eval(si)
    valid = np.asarray(si.is_valid())
    n = np.stack([np.asarray(si.sh_frame.n[i], np.float64) for i in range(3)], -1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    mask = valid & (np.sum(n * -d, axis=1) > 0)
    n[~mask] = (0.0, 0.0, 1.0)
    return n.reshape(h, w, 3), mask.reshape(h, w)


def model_stokes(params, normals, mask, view, light, irradiance):
    """(3, H, W) Stokes image of the fmbrdf plugin at every masked pixel under a directional light,
    in the camera's frame (x image right, y image up), 0 elsewhere: ``bsdf.eval`` per pixel, the output
    basis rotated from Mitsuba's ``stokes_basis(wi)`` to the camera's (as the fit's pixel path models it).
    The surface and body terms are evaluated at unit albedos and added in float64 with k_s and k_b = r_k k_s,
    as the package's own synthetic objects are (the images come out bit for bit the same)."""
    import drjit as dr

    mi = _mitsuba()
    import fmbrdf_mi

    p = {k: float(v) for k, v in params.items()}
    bsdf = fmbrdf_mi.load_dict({"type": "fmbrdf", "eta": p["eta"], "alpha": p["alpha"], "beta": p["beta"],
                                "kappa": p["kappa"], "k_s": 1.0, "k_b": 1.0, "tables": "float32"})
    tp = mi.traverse(bsdf)
    idx = np.flatnonzero(mask.ravel())
    n = normals.reshape(-1, 3)[idx].astype(np.float64)
    v = view.reshape(-1, 3)[idx].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    light = np.asarray(light, float) / np.linalg.norm(light)
    frame = mi.Frame3f(mi.Vector3f(np.ascontiguousarray(n.T, dtype=np.float32)))
    si = dr.zeros(mi.SurfaceInteraction3f, len(n))
    si.sh_frame = frame
    si.n = frame.n
    si.wi = frame.to_local(mi.Vector3f(np.ascontiguousarray(v.T, dtype=np.float32)))
    wo = frame.to_local(mi.Vector3f(np.ascontiguousarray(np.tile(light, (len(n), 1)).T, dtype=np.float32)))
    ex = np.array([1.0, 0.0, 0.0])
    xc = ex[None, :] - (v @ ex)[:, None] * v
    xc[np.linalg.norm(xc, axis=1) < 1e-6] = (0.0, 1.0, 0.0)
    xc /= np.linalg.norm(xc, axis=1, keepdims=True)
    xl = frame.to_local(mi.Vector3f(np.ascontiguousarray(xc.T, dtype=np.float32)))
    rot = mi.mueller.rotate_stokes_basis(si.wi, mi.mueller.stokes_basis(si.wi), xl)
    parts = []
    for a_s, a_b in ((1.0, 1e-20), (1e-20, 1.0)):        # surface, body
        tp["k_s.value"], tp["k_b.value"] = mi.Float(a_s), mi.Float(a_b)
        tp.update()
        M = bsdf.eval(mi.BSDFContext(), si, wo)
        s0, s1, s2 = (M[i, 0][0] * irradiance for i in range(3))
        s = (s0, rot[1, 1] * s1 + rot[1, 2] * s2, rot[2, 1] * s1 + rot[2, 2] * s2)
        dr.eval(s)
        parts.append(np.stack([np.asarray(c, dtype=np.float64) for c in s]))
    out = np.zeros((3, normals.shape[0] * normals.shape[1]))
    out[:, idx] = p["k_s"] * parts[0] + p["k_s"] * p["r_k"] * parts[1]
    return out.reshape(3, *normals.shape[:2])


def cv_to_ours(v):
    """OpenCV camera axes (x right, y down, z forward) <-> this package's (x right, y up, z to the camera)."""
    return np.asarray(v, dtype=np.float64) * np.array([1.0, -1.0, -1.0])


def write_authors_object(root, params, lights, powers, *, res, fov=12.0, distance=8.0, seed=0):
    """An object in the paper authors' layout (docs/howto/fit-joint.md, "The paper authors' captured-data layout"): a mesh seen by
    a pinhole camera, geometry by ray casts (per raw pixel for the data, per super-pixel for normal_GT.npy),
    the model at every raw pixel, 16-bit raw mosaics through fmbrdf_mi.sensor.camera (seed + k for image k), one
    exposure (the brightest raw pixel of all images at 80 % of full scale).  Returns the camera's gain."""
    from PIL import Image

    from fmbrdf_mi.sensor.camera import CameraModel, capture

    cam = CameraModel(**OBJECT_CAMERA)
    scene = _mesh_scene(blob_mesh())
    origin, d2, _ = pinhole_rays((2 * res, 2 * res), fov, distance)
    n2, m2 = ray_cast(scene, origin, d2)
    _, d1, f1 = pinhole_rays((res, res), fov, distance)
    n1, _ = ray_cast(scene, origin, d1)
    lights = [np.asarray(l, float) / np.linalg.norm(l) for l in lights]
    powers = np.asarray(powers, float)
    stokes = [model_stokes(params, n2, m2, -d2, l, float(p)) for l, p in zip(lights, powers)]
    exposure = 0.8 * cam.full_well / max(float(np.max(s[0] + np.hypot(s[1], s[2])) / 2) for s in stokes)
    for sub in ("calibration", "normal", os.path.join("image", "img_ud")):
        os.makedirs(os.path.join(root, sub), exist_ok=True)
    for k, s in enumerate(stokes):
        cap = capture(s, cam, exposure=exposure, seed=seed + k)
        Image.fromarray(cap["raw"].astype(np.uint16)).save(os.path.join(root, "image", "img_ud", f"{k:03d}.png"))
    np.savetxt(os.path.join(root, "calibration", "L.txt"), np.array([cv_to_ours(l) for l in lights]), delimiter=",")
    np.save(os.path.join(root, "calibration", "vpL_img.npy"), cv_to_ours(d1).astype(np.float32))
    K = np.array([[2 * f1, 0, res - 0.5], [0, 2 * f1, res - 0.5], [0, 0, 1.0]])
    np.save(os.path.join(root, "calibration", "IntrinsicL.npy"), K)
    np.save(os.path.join(root, "calibration", "intensities.npy"), powers)
    np.save(os.path.join(root, "normal", "normal_GT.npy"), cv_to_ours(n1).astype(np.float32))
    np.save(os.path.join(root, "mask_ud.npy"), m2.astype(np.uint8))
    return cam.conversion_gain


def make_objects(inputs):
    gains = {}
    gains["small"] = write_authors_object(os.path.join(inputs, "object_small"), OBJECT_MATERIAL, OBJECT_LIGHTS[:3],
                                          OBJECT_POWERS[:3], res=16, seed=3)
    gains["medium"] = write_authors_object(os.path.join(inputs, "object_medium"), OBJECT_MATERIAL, OBJECT_LIGHTS,
                                           OBJECT_POWERS, res=24, seed=11)
    return gains


# --- a MERL binary (the published format, written here: NumPy only) ---

def make_merl(path):
    """A MERL BRDF file (header 90, 90, 180; R, G, B tables of doubles over theta_h (slowest), theta_d, phi_d,
    divided by the scales 1/1500, 1.15/1500, 1.66/1500): Lambert k_d / pi plus a GGX lobe in theta_h with
    Schlick's Fresnel in theta_d over 4 cos^2 theta_d (not FMBRDF: the fit ends at a best compromise)."""
    ih, idd = np.arange(90), np.arange(90)
    th = (ih / 90.0) ** 2 * (np.pi / 2)
    td = idd / 90.0 * (np.pi / 2)
    a2 = MERL_ALPHA ** 2
    D = a2 / (np.pi * (np.cos(th) ** 2 * (a2 - 1) + 1) ** 2)
    F = MERL_F0 + (1 - MERL_F0) * (1 - np.cos(td)) ** 5
    lobe = D[:, None] * F[None, :] / (4 * np.cos(td)[None, :] ** 2)      # (theta_h, theta_d)
    scales = (1.0 / 1500, 1.15 / 1500, 1.66 / 1500)
    with open(path, "wb") as f:
        f.write(struct.pack("<3i", 90, 90, 180))
        for kd, ks, sc in zip(MERL_KD, MERL_KS, scales):
            tab = kd / np.pi + ks * lobe
            f.write((np.broadcast_to(tab[:, :, None], (90, 90, 180)) / sc).astype("<f8").tobytes())


def make_inputs(work):
    inputs = os.path.join(work, "inputs")
    if os.path.exists(inputs):
        shutil.rmtree(inputs)
    os.makedirs(inputs)
    t = time.time()
    cmds = make_renders(inputs)
    gains = make_objects(inputs)
    make_merl(os.path.join(inputs, "synthetic.binary"))
    info = {"render_commands": ["fmbrdf-mi " + " ".join(c[3:]) for c in cmds],
            "object_gains": gains, "seconds": time.time() - t}
    info["sha256"] = input_hashes(work)
    with open(os.path.join(work, "inputs.json"), "w") as f:
        json.dump(info, f, indent=1)
    return info


def input_hashes(work):
    """SHA-256 of every input file; text files with the work directory's path replaced by <WORK> (sidecars
    record the EXR's absolute path)."""
    inputs = os.path.join(work, "inputs")
    out = {}
    for d, _, files in sorted(os.walk(inputs)):
        for name in sorted(files):
            if name.endswith(".log"):
                continue
            path = os.path.join(d, name)
            data = open(path, "rb").read()
            if name.endswith((".json", ".toml", ".txt")):
                data = data.replace(os.path.abspath(work).encode(), b"<WORK>")
            out[os.path.relpath(path, inputs)] = hashlib.sha256(data).hexdigest()
    return out


# ---------------------------------------------------------------------------------------------------------------
# cases: (name, argv after "fmbrdf-mi", the output file to read), paths relative to the work directory

def cases(gains):
    g_small, g_med = repr(gains["small"]), repr(gains["medium"])
    c = []
    for m in MATERIALS:
        c.append((f"a_like_{m}", ["fit", f"inputs/{m}_raw.png", "-o", f"fits/a_like_{m}"], "fit.json"))
    for m in MATERIALS:
        c.append((f"b_paper_{m}", ["fit", f"inputs/{m}.exr", "--loss", "paper", "-o", f"fits/b_paper_{m}"],
                  "fit.json"))
    c.append(("c_joint_free_power", ["fit", "--manifest", "inputs/joint.toml", "--free-power",
                                     "-o", "fits/c_joint_free_power"], "fit.json"))
    c.append(("d_colour_24", ["fit", "inputs/colour_raw.png", "-o", "fits/d_colour_24"], "fit.json"))
    c.append(("e_refine_normals", ["fit", "--authors", "inputs/object_small", "--conversion-gain", g_small,
                                   "--read-noise", "2.5", "--refine-normals", "--max-iter", "20",
                                   "-o", "fits/e_refine_normals"], "fit.json"))
    c.append(("f_authors", ["fit", "--authors", "inputs/object_medium", "--holdout", "3", "--conversion-gain", g_med,
                            "--read-noise", "2.5", "-o", "fits/f_authors"], "fit.json"))
    c.append(("g_fit_brdf", ["fit-brdf", "inputs/synthetic.binary", "-o", "fits/g_fit_brdf", "--samples", "5000",
                             "--starts", "1", "--max-evals", "80", "--seed", "0"], "params.json"))
    return c


# ---------------------------------------------------------------------------------------------------------------
# extraction

#: subtrees that are not results (settings, provenance, clocks, per-step traces)
SKIP = {"reproduce", "inputs", "options", "timings", "time_s", "seconds", "time", "elapsed", "history",
        "arguments", "versions", "files_sha256", "command", "truth"}


def flatten(obj, prefix, nums, text):
    """Numbers (bools as 0/1) into ``nums``, strings into ``text``, keyed by their '/'-joined path."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in SKIP:
                if k == "history" and isinstance(v, list):
                    nums[f"{prefix}/history/length"] = float(len(v))
                continue
            flatten(v, f"{prefix}/{k}", nums, text)
    elif isinstance(obj, list):
        if obj and all(isinstance(x, str) for x in obj):
            if not any(_is_path(x) for x in obj):
                text[prefix] = ", ".join(obj)
        else:
            for i, v in enumerate(obj):
                flatten(v, f"{prefix}/{i}", nums, text)
    elif isinstance(obj, bool):
        nums[prefix] = float(obj)
    elif isinstance(obj, (int, float)):
        nums[prefix] = float(obj)
    elif isinstance(obj, str):
        if not _is_path(obj):
            text[prefix] = obj
    # None: no entry (a value that appears or disappears shows as a new or missing key)


def _is_path(s):
    """File names (absolute ones depend on the work directory; the fits' own output lists are not results)."""
    return os.path.isabs(s) or s.startswith(("fits/", "inputs/")) or os.sep + "fits" + os.sep in s


def record(work, reuse, only=None):
    """Make (or reuse) the inputs, run every case; (numbers, text, meta)."""
    t_all = time.time()
    os.makedirs(work, exist_ok=True)
    info_path = os.path.join(work, "inputs.json")
    if reuse:
        if not os.path.exists(info_path):
            sys.exit(f"record_fits: --reuse-inputs: no {info_path} (run once with --work {work} --keep first)")
        info = json.load(open(info_path))
        now = input_hashes(work)
        if now != info["sha256"]:
            bad = sorted(k for k in set(now) | set(info["sha256"]) if now.get(k) != info["sha256"].get(k))
            sys.exit(f"record_fits: --reuse-inputs: input files changed since they were made: {', '.join(bad)}")
        print(f"inputs: reused {len(now)} files in {work}/inputs", flush=True)
    else:
        t = time.time()
        info = make_inputs(work)
        print(f"inputs: made {len(info['sha256'])} files in {time.time() - t:.1f} s", flush=True)
    nums, text, times, argvs = {}, {}, {}, {}
    fits = os.path.join(work, "fits")
    os.makedirs(fits, exist_ok=True)
    for name, argv, outfile in cases(info["object_gains"]):
        if only and name not in only:
            continue
        out = os.path.join(work, "fits", name)
        if os.path.exists(out):
            shutil.rmtree(out)
        t = time.time()
        rc = run(fmbrdf(*argv), work, os.path.join(fits, name + ".log"))
        dt = time.time() - t
        times[name], argvs[name] = dt, "fmbrdf-mi " + " ".join(argv)
        path = os.path.join(out, outfile)
        nums[f"{name}/exit_status"] = float(rc)
        status = "ok" if rc == 0 else f"EXIT {rc}"
        if os.path.exists(path):
            flatten(json.load(open(path)), name, nums, text)
        else:
            status += f", no {outfile}"
        n_keys = sum(k.startswith(name + "/") for k in nums)
        print(f"{name:20s} {dt:6.1f} s  {status:10s} {n_keys:4d} numbers   {argvs[name]}", flush=True)
        if rc not in (0, 3):
            print(f"  log: {os.path.join(fits, name + '.log')}", file=sys.stderr)
            with open(os.path.join(fits, name + ".log")) as f:
                tail = f.read().strip().splitlines()[-5:]
            print("\n".join("  | " + l for l in tail), file=sys.stderr)
    meta = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "cpu": cpu_name(),
            "cores": os.cpu_count(), "git": git_state(), "versions": versions(), "record_fits_version": VERSION,
            "case_seconds": times, "total_seconds": time.time() - t_all, "commands": argvs,
            "render_commands": info["render_commands"], "inputs_sha256": info["sha256"]}
    return nums, text, meta


def cpu_name():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine()


def git_state():
    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    return {"commit": git("rev-parse", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--", "fmbrdf_mi")),
            "describe": git("log", "-1", "--format=%h %cd %s", "--date=short")}


def versions():
    out = {"python": sys.version.split()[0], "numpy": np.__version__}
    for mod in ("mitsuba", "drjit", "fmbrdf_mi"):
        try:
            out[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001
            out[mod] = None
    return out


# ---------------------------------------------------------------------------------------------------------------
# compare

def rel_diff(a, b):
    if a == b or (math.isnan(a) and math.isnan(b)):
        return 0.0
    if not (math.isfinite(a) and math.isfinite(b)):
        return math.inf
    return abs(a - b) / max(abs(a), abs(b))


def numbers(rec):
    return {k: v for k, v in rec.items() if k not in ("meta", "text")}


def compare(base, now, rtol, show_all=False):
    """Print what moved; True when every number is within rtol and no key is missing or new."""
    b, n = numbers(base), numbers(now)
    missing, new = sorted(set(b) - set(n)), sorted(set(n) - set(b))
    common = sorted(set(b) & set(n))
    diffs = {k: rel_diff(b[k], n[k]) for k in common}
    moved = [k for k in common if diffs[k] > 0]
    bad = [k for k in common if diffs[k] > rtol]
    hb, hn = base.get("meta", {}).get("inputs_sha256", {}), now.get("meta", {}).get("inputs_sha256", {})
    changed_inputs = sorted(k for k in set(hb) | set(hn) if hb.get(k) != hn.get(k))
    label = ("baseline", "current")
    print(f"\ncompare: {label[0]} {base.get('meta', {}).get('date')} "
          f"({(base.get('meta', {}).get('git') or {}).get('describe')}) vs {label[1]} "
          f"{now.get('meta', {}).get('date')} ({(now.get('meta', {}).get('git') or {}).get('describe')})")
    if changed_inputs:
        print(f"input files that differ ({len(changed_inputs)}): {', '.join(changed_inputs)}")
    else:
        print(f"input files: all {len(hb)} identical (SHA-256)")
    rows = common if show_all else sorted(moved, key=lambda k: (-diffs[k], k))
    if rows:
        w = max(len(k) for k in rows)
        print(f"\n{'key':{w}s}  {label[0]:>24s}  {label[1]:>24s}  {'rel. diff':>9s}")
        for k in rows:
            flag = "  > rtol" if diffs[k] > rtol else ""
            print(f"{k:{w}s}  {b[k]:24.17g}  {n[k]:24.17g}  {diffs[k]:9.2e}{flag}")
    print(f"\n  {'case':20s} {'keys':>5s} {'moved':>5s} {'>rtol':>5s}   {'largest':>9s}  (relative difference)")
    for case in sorted({k.split("/", 1)[0] for k in set(b) | set(n)}):
        ks = [k for k in common if k.startswith(case + "/")]
        mv = [k for k in ks if diffs[k] > 0]
        worst = max((diffs[k] for k in ks), default=0.0)
        nm = sum(k.startswith(case + "/") for k in missing)
        nn = sum(k.startswith(case + "/") for k in new)
        extra = (f", {nm} missing" if nm else "") + (f", {nn} new" if nn else "")
        print(f"  {case:20s} {len(ks):5d} {len(mv):5d} {sum(diffs[k] > rtol for k in ks):5d}   {worst:9.2e}{extra}")
    for title, keys in (("missing (in the baseline, not now)", missing), ("new (now, not in the baseline)", new)):
        if keys:
            print(f"\n{title}: {len(keys)}")
            for k in keys:
                print(f"  {k} = {b.get(k, n.get(k))!r}")
    tb, tn = base.get("text", {}), now.get("text", {})
    tdiff = sorted(k for k in set(tb) | set(tn) if tb.get(k) != tn.get(k))
    if tdiff:
        print(f"\ntext that differs (reported, not a failure): {len(tdiff)}")
        for k in tdiff:
            print(f"  {k}: {tb.get(k)!r} -> {tn.get(k)!r}")
    worst = max(diffs.values(), default=0.0)
    ok = not bad and not missing and not new
    print(f"\n{len(common)} numbers compared: {len(common) - len(moved)} identical, {len(moved)} moved, "
          f"{len(bad)} beyond rtol {rtol:g} (largest {worst:.2e}); {len(missing)} missing, {len(new)} new: "
          f"{'PASS' if ok else 'FAIL'}")
    return ok


# ---------------------------------------------------------------------------------------------------------------

def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", help="work directory for inputs and fit outputs (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (always kept with --work)")
    ap.add_argument("--reuse-inputs", action="store_true",
                    help="use the inputs an earlier run left in --work (checked against their recorded SHA-256)")
    ap.add_argument("--out", metavar="FILE", help="write the record (numbers, text, meta) as JSON")
    ap.add_argument("--compare", metavar="BASELINE", help="compare with a saved record; exit 1 if anything moved")
    ap.add_argument("--compare-only", nargs=2, metavar=("BASELINE", "CURRENT"),
                    help="compare two saved records and exit")
    ap.add_argument("--rtol", type=float, default=1e-9, help="relative tolerance of --compare (default 1e-9)")
    ap.add_argument("--all", action="store_true", help="--compare: list every key, not only those that moved")
    ap.add_argument("--cases", help="comma-separated subset of the cases (for debugging; --compare then looks at "
                                    "those cases only)")
    args = ap.parse_args()
    if args.compare_only:
        base, now = (json.load(open(p)) for p in args.compare_only)
        print(f"baseline: {args.compare_only[0]}\ncurrent:  {args.compare_only[1]}")
        return 0 if compare(base, now, args.rtol, args.all) else 1
    if args.reuse_inputs and not args.work:
        ap.error("--reuse-inputs needs --work DIR")
    if args.compare and not os.path.exists(args.compare):
        ap.error(f"--compare: no such file {args.compare}")
    only = set(args.cases.split(",")) if args.cases else None
    if only:
        known = {c[0] for c in cases({"small": 0.0, "medium": 0.0})}
        if only - known:
            ap.error(f"--cases: unknown {', '.join(sorted(only - known))}; the cases are {', '.join(sorted(known))}")
    work = os.path.abspath(args.work) if args.work else tempfile.mkdtemp(prefix="record_fits_")
    print(f"record_fits: work directory {work}; {cpu_name()}, {os.cpu_count()} cores", flush=True)
    try:
        nums, text, meta = record(work, args.reuse_inputs, only)
    finally:
        if not args.work and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        elif not args.work:
            print(f"kept {work}")
    rec = {"meta": meta, "text": text, **dict(sorted(nums.items()))}
    print(f"total {meta['total_seconds']:.1f} s, {len(nums)} numbers", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rec, f, indent=1)
            f.write("\n")
        print(f"wrote {args.out}")
    if args.compare:
        base = json.load(open(args.compare))
        if only:   # compare the cases that ran
            base_text = {k: v for k, v in base.get("text", {}).items() if k.split("/", 1)[0] in only}
            base = {k: v for k, v in base.items() if k == "meta" or k.split("/", 1)[0] in only}
            base["text"] = base_text
            print(f"(--cases: comparing {', '.join(sorted(only))} only)")
        return 0 if compare(base, rec, args.rtol, args.all) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
