"""The example data of the documentation: every input file its how-to commands read, made in seconds.

    fmbrdf-mi example-data DIR            # or write_examples("DIR") from Python

A how-to page's shell commands run as written in a directory holding these
files (``tests/test_docs.py`` runs every one).  Everything is synthetic, made
by the package itself at small sizes, so that CI makes it in seconds: raw
mosaics of a 32 x 32 pixel sphere (16 x 16 super-pixels) where a real capture
has millions of pixels.  ``README.txt`` in DIR lists the files;
``truth.json`` holds the parameters they were made with.

* ``capture.png`` -- a raw 12-bit IMX250MZR mosaic (16-bit PNG) of a sphere,
  camera gain 2.44 e-/DN, read noise 2.5 e-, no sidecar (a user's own capture);
  ``raw.npy`` the same mosaic as ``.npy``; ``mask.png``, ``normal.npy`` its
  mask and normals on the super-pixel grid; ``materials.png`` the sphere made of
  two materials (left and right half, :data:`OTHER`), ``labels.png`` its labels on
  that grid, 255 off the object;
* ``a.png``, ``b.png``, ``c.png`` -- the sphere under three lights, one exposure
  and ``capture.toml``, their manifest (``c.png`` held out);
* ``i0.tif`` ... ``i135.tif`` -- the four polariser-angle images of ``capture.png``
  (each angle's raw pixels: the super-pixel grid);
* ``colour_raw.png`` (+ ``colour_raw.json``, the sidecar with the colour filter),
  ``colour_a.png``, ``colour_b.png`` (+ sidecars) -- raw colour polarisation
  mosaics (RGGB) of a sphere; ``colour_mask.png``, ``colour_normal.npy`` on
  their 4 x 4 period grid; ``colour.toml``, a manifest of the two lights;
* ``data/blob`` -- an object in the paper authors' layout (four lights; 16-bit
  raw mosaics of a 48 x 48 pixel view, camera gain 0.305 e-/DN, read noise
  2.5 e-; each raw pixel the mean of the model over its area);
* ``merl/glossy.binary``, ``merl/matte.binary`` -- MERL BRDF files tabulated
  from FMBRDF (the format's full 90 x 90 x 180 bins: 35 MB each);
* ``plane.csv`` -- camera angle and intensity of an Oren-Nayar plane, light at 30 deg;
* ``uv_halves.png`` -- a uv label image of two materials (left and right half).
"""
from __future__ import annotations

import json
import os
import shutil

import numpy as np

#: The material of the mono captures (the reported parameters, as in ``fmbrdf_mi/params.py``).
TRUTH = dict(eta=1.5, alpha=0.2, beta=2.0, kappa=10.0, k_s=1.0, r_k=0.6)
#: The second material of ``materials.png`` (its right half).
OTHER = dict(eta=1.8, alpha=0.45, beta=1.0, kappa=5.0, k_s=1.0, r_k=0.3)
#: The colour captures' shape parameters and per-channel albedos (R, G, B).
COLOUR_TRUTH = dict(eta=1.5, alpha=0.2, beta=2.0, kappa=10.0, k_s=(0.6, 0.4, 0.5), r_k=0.7)
#: Super-pixels across the mono captures, 4 x 4 periods across the colour ones.
MONO_RES, COLOUR_RES = 16, 12
#: (file, light, relative power, held out) of the mono captures; ``capture.png`` is ``a.png``'s light.
MONO_LIGHTS = [("a.png", (-0.42, 0.31, 0.85), 1.0, False), ("b.png", (0.5, 0.1, 0.86), 1.0, False),
               ("c.png", (0.1, -0.6, 0.8), 1.0, True)]
#: (file, light) of the colour captures.
COLOUR_LIGHTS = [("colour_raw.png", (0.3, 0.4, 0.87)), ("colour_a.png", (0.5, 0.3, 1.0)),
                 ("colour_b.png", (-0.5, 0.2, 1.0))]
#: The authors'-layout object's lights (ours: x right, y up, z towards the camera).
BLOB_LIGHTS = [(-0.42, 0.31, 0.85), (0.5, 0.1, 0.86), (0.1, -0.6, 0.8), (0.35, 0.45, 0.82)]
#: Its super-pixels across, the camera's field of view (deg; the object fills most of it) and the
#: points per raw pixel side over which the model is averaged: enough pixels for the normal
#: refinement, and a pixel integral finer than the fit's own area quadrature.
BLOB_RES, BLOB_FOV, BLOB_AREA = 24, 12.0, 8
#: The MERL files: name -> FMBRDF parameters (per-channel albedos).
MERL_MATERIALS = {
    "glossy": dict(eta=1.55, alpha=0.12, beta=1.7, kappa=15.0, k_s=[0.5, 0.6, 0.7], k_b=[0.3, 0.1, 0.05]),
    "matte": dict(eta=1.4, alpha=0.45, beta=0.8, kappa=5.0, k_s=[0.2, 0.2, 0.25], k_b=[0.6, 0.5, 0.3]),
}

MANIFEST = """\
# capture.toml (JSON works too); paths relative to the manifest
[defaults]                 # any input option of `fmbrdf-mi fit`, shared by every image
normals = "normal.npy"
mask = "mask.png"
conversion_gain = 2.44
read_noise = 2.5
{images}"""


def _png16(path, raw):
    from PIL import Image

    Image.fromarray(np.asarray(raw).astype(np.uint16)).save(path)


def _png8(path, img):
    from PIL import Image

    Image.fromarray(np.asarray(img).astype(np.uint8), mode="L").save(path)


def _image_entry(name, light, power=None, holdout=False, comment=""):
    s = f"\n[[image]]\ninput = \"{name}\"\nlight = [{', '.join(f'{c:g}' for c in light)}]\n"
    if power is not None:
        s += f"power = {power:.1f}                # relative light power (default 1): multiplies the irradiance\n"
    s += comment
    if holdout:
        s += "holdout = true             # not fitted: predicted from the estimates (relighting check)\n"
    return s


def _mono(root, seed):
    from fmbrdf_mi.sensor.camera import CameraModel, capture
    from fmbrdf_mi.synthetic.spheres import half_labels, ideal_sphere, material_sphere

    cam = CameraModel()                      # 12-bit ADC over a 10 000 e- full well: 2.44 e-/DN
    ideals = [ideal_sphere(TRUTH, res=MONO_RES, light=light) for _, light, _, _ in MONO_LIGHTS]
    powers = [p for _, _, p, _ in MONO_LIGHTS]
    peak = max(p * float(np.max(i["stokes"][0] + np.hypot(i["stokes"][1], i["stokes"][2])) / 2)
               for i, p in zip(ideals, powers))
    exposure = 0.8 * cam.full_well / peak     # one exposure: the brightest raw pixel at 80 % of full well
    raws = [capture(i["stokes"] * p, cam, exposure=exposure, seed=seed + k)["raw"]
            for k, (i, p) in enumerate(zip(ideals, powers))]
    for (name, _, _, _), raw in zip(MONO_LIGHTS, raws):
        _png16(os.path.join(root, name), raw)
    capture_raw = capture(ideals[0]["stokes"], cam, exposure=exposure, seed=seed + 10)["raw"]
    _png16(os.path.join(root, "capture.png"), capture_raw)
    np.save(os.path.join(root, "raw.npy"), capture_raw.astype(np.uint16))
    mask = ideals[0]["mask"]
    _png8(os.path.join(root, "mask.png"), np.where(mask, 255, 0))
    np.save(os.path.join(root, "normal.npy"), ideals[0]["normals"].astype(np.float32))
    two = material_sphere([TRUTH, OTHER], half_labels(MONO_RES), res=MONO_RES, light=MONO_LIGHTS[0][1])
    _png16(os.path.join(root, "materials.png"), capture(two["stokes"], cam, exposure=exposure, seed=seed + 11)["raw"])
    _png8(os.path.join(root, "labels.png"), np.where(mask, half_labels(MONO_RES), 255))
    # the angle images of a division-of-focal-plane camera: each angle's raw pixels
    for r in range(2):
        for c in range(2):
            angle = cam.layout[r][c]
            _png16(os.path.join(root, f"i{angle}.tif"), capture_raw[r::2, c::2])
    other_view = ('# normals = "view2_normal.npy", mask = "view2_mask.png": an image of another view, '
                  'its own geometry\n')
    images = "".join(_image_entry(n, l, p if k == 0 else None, h, other_view if k == 1 else "")
                     for k, (n, l, p, h) in enumerate(MONO_LIGHTS))
    with open(os.path.join(root, "capture.toml"), "w") as f:
        f.write(MANIFEST.format(images=images))
    return {"lights": {n: list(l) for n, l, _, _ in MONO_LIGHTS}, "capture.png": list(MONO_LIGHTS[0][1]),
            "materials.png": {"light": list(MONO_LIGHTS[0][1]), "right_half": OTHER},
            "powers": {n: p for n, _, p, _ in MONO_LIGHTS}, "conversion_gain": cam.conversion_gain,
            "read_noise": cam.read_noise, "exposure_e_per_unit": exposure}


def _colour(root, seed):
    from fmbrdf_mi.sensor import mosaic
    from fmbrdf_mi.sensor.camera import CameraModel, write_sidecar
    from fmbrdf_mi.synthetic.spheres import capture_colour, textured_sphere

    cam = CameraModel(cfa=mosaic.BAYER_RGGB)
    shape = {k: COLOUR_TRUTH[k] for k in ("eta", "alpha", "beta", "kappa")}
    ks = np.broadcast_to(np.asarray(COLOUR_TRUTH["k_s"], float)[:, None, None], (3, COLOUR_RES, COLOUR_RES))
    kb = COLOUR_TRUTH["r_k"] * ks
    exposure = None
    for k, (name, light) in enumerate(COLOUR_LIGHTS):
        ideal = textured_sphere(shape, ks, kb, res=COLOUR_RES, light=light)
        _, _, _, cap = capture_colour(ideal, cam, seed=seed + 20 + k, exposure=exposure)
        exposure = cap["exposure"]           # the first image's exposure for all
        path = os.path.join(root, name)
        _png16(path, cap["raw"])
        write_sidecar(path, cam)             # the camera settings, colour filter included; no geometry
        if k == 0:
            _png8(os.path.join(root, "colour_mask.png"), np.where(ideal["mask"], 255, 0))
            np.save(os.path.join(root, "colour_normal.npy"), ideal["normals"].astype(np.float32))
    text = MANIFEST.replace("capture.toml", "colour.toml").replace("normal.npy", "colour_normal.npy")
    text = text.replace("mask.png", "colour_mask.png").replace("conversion_gain = 2.44\nread_noise = 2.5\n", "")
    with open(os.path.join(root, "colour.toml"), "w") as f:
        f.write(text.format(images="".join(_image_entry(n, l) for n, l in COLOUR_LIGHTS[1:])))
    return {"lights": {n: list(l) for n, l in COLOUR_LIGHTS}, "cfa": [list(r) for r in cam.cfa]}


def _merl(root):
    from fmbrdf_mi.brdf_fit.fitting import model_brdf
    from fmbrdf_mi.brdf_fit.merl import write_merl

    os.makedirs(os.path.join(root, "merl"))
    for name, params in MERL_MATERIALS.items():
        write_merl(os.path.join(root, "merl", name + ".binary"), model_brdf(params))


def _plane(root):
    from fmbrdf_mi.mesogeometry import oren_nayar_intensity

    angles = np.arange(-80.0, 81.0, 5.0)
    intensity = 0.8 * oren_nayar_intensity(angles, 30.0, 0.6, 0.8)
    with open(os.path.join(root, "plane.csv"), "w") as f:
        f.write("camera_angle_deg,intensity\n")
        f.writelines(f"{a:g},{i:.6g}\n" for a, i in zip(angles, intensity))


def _readme(root, truth):
    with open(os.path.join(root, "README.txt"), "w") as f:
        f.write("Example data of the fmbrdf-mi documentation (fmbrdf-mi example-data).\n\n"
                + __doc__.split("\n\n", 2)[2])
    with open(os.path.join(root, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1)


def write_examples(out, *, seed=0, merl=True):
    """Write the example data (module docstring) into the new directory ``out``; returns ``out``.

    Refuses an ``out`` that exists (FileExistsError naming it); the files are
    written to a staging directory beside it that is renamed at the end, so an
    error or Ctrl-C leaves no half-written ``out``.  ``merl=False`` leaves out
    the MERL files (70 MB)."""
    import mitsuba as mi

    from fmbrdf_mi.synthetic.mesh_object import write_authors_object

    out = os.fspath(out)
    if os.path.lexists(out):
        raise FileExistsError(f"{out} exists; give a new directory")
    parent = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(parent):
        raise FileNotFoundError(f"{parent}: no such directory (the parent of {out})")
    if not mi.variant():
        mi.set_variant("llvm_ad_mono_polarized")
    stage = os.path.join(parent, f".{os.path.basename(os.path.abspath(out))}.part")
    if os.path.exists(stage):
        shutil.rmtree(stage)
    os.makedirs(stage)
    try:
        truth = {"mono": dict(TRUTH, **_mono(stage, seed)), "colour": dict(COLOUR_TRUTH, **_colour(stage, seed))}
        truth["data/blob"] = write_authors_object(os.path.join(stage, "data", "blob"), TRUTH, BLOB_LIGHTS,
                                                  res=BLOB_RES, fov=BLOB_FOV, area=BLOB_AREA, seed=seed + 30)
        if merl:
            _merl(stage)
            truth["merl"] = MERL_MATERIALS
        _plane(stage)
        truth["plane.csv"] = {"sigma": 0.6, "rho": 0.8, "albedo": 0.8, "light_angle_deg": 30.0}
        _png8(os.path.join(stage, "uv_halves.png"), np.repeat((np.arange(64) >= 32)[None, :], 32, axis=0))
        _readme(stage, truth)
        os.rename(stage, out)
    finally:
        if os.path.exists(stage):
            shutil.rmtree(stage)
    return out


HELP = "write the example data of the documentation's commands (small synthetic captures) into a new DIR"


def add_example_data_arguments(p):
    p.add_argument("out", metavar="DIR", help="a new directory for the files")
    p.add_argument("--no-merl", action="store_true", help="leave out the two MERL BRDF files (35 MB each)")
    p.add_argument("--seed", type=int, default=0, help="seed of the camera noise (default 0)")


def run_example_data(args):
    out = write_examples(args.out, seed=args.seed, merl=not args.no_merl)
    print(f"wrote the example data to {out} (README.txt lists the files)")
    return 0
