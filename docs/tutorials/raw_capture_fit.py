"""Tutorial 2: a synthetic raw capture, from ``fmbrdf-mi render --raw`` to ``fmbrdf-mi fit``.

What a polarisation camera would record of a sphere, and the fit that
recovers the material from it, all through the command line:

1. render the built-in sphere (alpha = 0.15, the other parameters at their
   defaults) in the monochrome polarised variant, and pass the Stokes image
   through the camera model of ``fmbrdf_mi/sensor/camera.py`` (IMX250MZR quad-Bayer
   layout, shot and read noise, 16-bit PNG) with ``--raw``; the sidecar
   ``c_raw.json`` records the camera's settings and the scene (sphere, light,
   true parameters);
2. ``fmbrdf-mi fit c_raw.png``: the likelihood of every raw sample (the gain
   and read noise come from the sidecar), from a coarse search without the
   answer, then Levenberg-Marquardt; it writes ``fit.json`` and the plots
   ``profiles.png``, ``images.png`` and ``history.png``;
3. read ``fit.json`` and compare the estimates with the truth, in units of
   the fit's own standard errors.

    python docs/tutorials/raw_capture_fit.py [OUTDIR]

A 64 x 64 render (32 x 32 super-pixels) keeps it well under a minute on 2 CPU cores;
larger images give smaller standard errors (see the benchmarks page).
"""
import json
import subprocess
import sys
import tempfile
from pathlib import Path

out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="fmbrdf_tutorial_"))
out.mkdir(parents=True, exist_ok=True)
cli = [sys.executable, "-m", "fmbrdf_mi"]          # = the fmbrdf-mi command


def run(*args):
    print("$ fmbrdf-mi", " ".join(args), flush=True)
    subprocess.run(cli + list(args), check=True)


# 1. render and capture (--force: rerunning the tutorial replaces its own outputs)
run("render", "--variant", "llvm_ad_mono_polarized", "--res", "64", "--spp", "64",
    "-D", "alpha=0.15", "--raw", "--raw-seed", "1", "-q", "--force", str(out / "c.exr"))
sidecar = json.loads((out / "c_raw.json").read_text())
print("camera:", {k: sidecar["sensor"][k] for k in ("full_well", "conversion_gain", "read_noise", "bits", "layout")})

# 2. fit the raw mosaic
run("fit", str(out / "c_raw.png"), "-o", str(out / "c_fit"), "-q", "--force")

# 3. the result
record = json.loads((out / "c_fit" / "fit.json").read_text())
truth = record["truth"]
model = record["models"]["fmbrdf"]
print(f"converged: {model['converged']}; chi2/dof {model['uncertainty']['chi2_per_dof']:.3f}")
print(f"{'':6s} {'truth':>8s} {'fit':>9s} {'SE':>8s} {'(fit - truth) / SE':>20s}")
for name in ("eta", "alpha", "beta", "kappa", "k_s", "r_k"):
    est, se = model["params"][name], model["std_errors"][name]
    print(f"{name:6s} {truth[name]:8.4g} {est:9.4g} {se:8.2g} {(est - truth[name]) / se:20.2f}")
print("weakly identified:", ", ".join(model["weakly_identified"]) or "none")
print("plots:", ", ".join(sorted(p.name for p in (out / "c_fit").glob("*.png"))), "in", out / "c_fit")

assert model["converged"]
for name in ("eta", "alpha", "beta", "k_s", "r_k"):
    # within 4.5 of the fit's own standard errors (a small object: kappa is weakly identified)
    assert abs(model["params"][name] - truth[name]) < 4.5 * model["std_errors"][name], name
assert {"profiles.png", "images.png", "history.png"} <= {p.name for p in (out / "c_fit").glob("*.png")}
