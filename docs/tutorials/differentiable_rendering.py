"""Tutorial 1: recover eta and alpha of an fmbrdf sphere by differentiable rendering.

The usual Mitsuba inverse-rendering loop with this package's BSDF: render a
reference with known parameters, perturb them, and let Adam bring them back
by the gradient of an image loss.  Polarisation matters: the loss compares the
whole Stokes image (S0, S1, S2), so the index of refraction is constrained by
the degree of polarisation too.

    python docs/tutorials/differentiable_rendering.py

(seconds on a laptop; under a minute on 2 shared CPU cores).  Notes:

* ``stokes`` over ``direct``: Mitsuba's ``prb`` integrators do not support
  polarisation; ``direct`` is differentiable with the default (detached)
  light sampling, which is all a directional light needs.
* ``mi.traverse`` exposes the BSDF's differentiable parameters
  (``eta``, ``alpha``, ``beta``, ``kappa``, ``k_s.value``, ``r_k.value``);
  ``params.update()`` rebuilds its body tables from the new values (and
  refuses an out-of-range value with ``fmbrdf_mi.ParameterError``, leaving
  the BSDF as it was, so the optimiser must keep them in range: clamp below).
"""
import mitsuba as mi

mi.set_variant("llvm_ad_mono_polarized")
import drjit as dr

import fmbrdf_mi  # noqa: F401  registers the "fmbrdf" plugin

TRUE = {"eta": 1.6, "alpha": 0.25}
START = {"eta": 1.3, "alpha": 0.4}
RES, SPP, STEPS = 64, 16, 60

scene = mi.load_dict({
    "type": "scene",
    # the stokes integrator writes S0..S3 as extra channels of the film
    "integrator": {"type": "stokes", "integrator": {"type": "direct"}},
    "sensor": {
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
        @ mi.ScalarTransform4f().scale([1.1, 1.1, 1]),
        "film": {"type": "hdrfilm", "width": RES, "height": RES, "pixel_format": "luminance",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": SPP},
    },
    "sphere": {
        "type": "sphere",
        "bsdf": {"type": "fmbrdf", "eta": TRUE["eta"], "alpha": TRUE["alpha"], "beta": 2.0,
                 "kappa": 10.0, "k_s": 1.0, "r_k": 0.8},
    },
    # light_dir (towards the light) = (-0.5, 0.5, 1): Mitsuba's direction is its negative
    "light": {"type": "directional", "direction": [0.5, -0.5, -1.0], "irradiance": 3.14159},
})


def stokes(image):
    """S0, S1, S2 of the stokes integrator's output.

    The film's channels are Y, then S0.R S0.G S0.B S1.R ... S3.B (names in
    ``film.bitmap().struct_()``; R = G = B in a mono variant): keep S0..S2.
    """
    return image[:, :, 1:10]


params = mi.traverse(scene)
keys = ["sphere.bsdf.eta", "sphere.bsdf.alpha"]

# The reference: rendered with the true parameters (fixed seed: the same noise every time).
reference = stokes(mi.render(scene, params, spp=SPP, seed=0))
print("film channels:", [f.name for f in scene.sensors()[0].film().bitmap().struct_()])

# Perturb the parameters, then optimise them back.
params["sphere.bsdf.eta"] = START["eta"]
params["sphere.bsdf.alpha"] = START["alpha"]
params.update()

opt = mi.ad.Adam(lr=0.02)
for k in keys:
    opt[k] = params[k]
params.update(opt)

for it in range(STEPS):
    if it == 40:
        opt.set_learning_rate(0.005)  # smaller steps at the end: the renders' noise sets the floor
    image = stokes(mi.render(scene, params, spp=SPP, seed=it + 1))
    loss = dr.mean(dr.square(image - reference), axis=None)
    dr.backward(loss)
    opt.step()
    # keep the iterates valid materials (eta in (1, 3], alpha in [0.01, pi/2])
    opt["sphere.bsdf.eta"] = dr.clip(opt["sphere.bsdf.eta"], 1.01, 3.0)
    opt["sphere.bsdf.alpha"] = dr.clip(opt["sphere.bsdf.alpha"], 0.01, 1.5)
    params.update(opt)
    if it % 10 == 0 or it == STEPS - 1:
        print(f"step {it:2d}: loss {loss.array[0]:.3e}  eta {params['sphere.bsdf.eta'][0]:.4f}  "
              f"alpha {params['sphere.bsdf.alpha'][0]:.4f}")

eta, alpha = params["sphere.bsdf.eta"][0], params["sphere.bsdf.alpha"][0]
print(f"recovered: eta {eta:.4f} (true {TRUE['eta']}), alpha {alpha:.4f} (true {TRUE['alpha']})")
assert abs(eta - TRUE["eta"]) < 0.03, eta
assert abs(alpha - TRUE["alpha"]) < 0.02, alpha
