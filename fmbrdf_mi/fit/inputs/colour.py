"""Colour polarisation mosaics read for a fit: sidecar, geometry on the 4x4-period grid, samples."""
from __future__ import annotations

import collections
import os

import numpy as np

from fmbrdf_mi import scene as S
from fmbrdf_mi.geometry import sphere_normals
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs import observations as ob
from fmbrdf_mi.fit.inputs.files import builtin_sphere_geometry, capture_sidecar, user_geometry
from fmbrdf_mi.fit.inputs.observations import downsample_geometry
from fmbrdf_mi.fit.inputs.manifest import file_stem, read_image
from fmbrdf_mi.fit.inputs.options import IMAGE_OPTIONS
from fmbrdf_mi.fit.inputs.parse import check_render_parameters
from fmbrdf_mi.sensor.noise import NoiseModel
from fmbrdf_mi.sensor.samples import colour_samples


def colour_sidecar(inputs):
    """The capture sidecar of a single raw input when it describes a colour sensor, else None."""
    if isinstance(inputs, (list, tuple)):
        return colour_sidecar(inputs[0]) if len(inputs) == 1 else None
    side = capture_sidecar(inputs)
    return side if side is not None and side["sensor"].cfa is not None else None


def colour_geometry(shape, side, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                    fov=None):
    """(normals, mask, view_dirs, exact geometry or None, sphere record or None) on the period grid ``shape``: the
    user's, else the sidecar's built-in sphere (exact when orthographic, else the render's maps pooled per period)."""
    params = side.get("parameters") if side.get("scene") == "builtin:sphere" else None
    if normals is not None or sphere is not None or params is None:
        n, m, v, exact, sph = user_geometry(shape, 4, normals=normals, mask=mask, view=view, sphere=sphere,
                                            camera=camera, fov=fov)
        return n, m, v, exact, None if sph is None else dict(sph, units="4x4 periods")
    check_render_parameters(params, side["path"])
    w, h = int(params["width"]), int(params["height"])
    if (h, w) != (4 * shape[0], 4 * shape[1]):
        raise InputError(f"{side['path']}: describes a {w}x{h} render, the mosaic is {4 * shape[1]}x{4 * shape[0]}")
    if params["camera"] == "orthographic":
        exact = builtin_sphere_geometry(params, shape)
        n, m, v = sphere_normals(shape, exact.centre, exact.radius)
        return n, m, v, exact, {"centre": list(exact.centre), "radius": exact.radius,
                                "from": "sidecar (built-in sphere)", "units": "4x4 periods"}
    n, v, m = S.sphere_geometry((w, h), camera=params["camera"], fov=params["fov"], distance=params["distance"])
    return (*downsample_geometry(n, m, v, 4), None, None)


#: One colour mosaic read for a fit: its Observation on the period grid, samples, camera, noise and metadata.
ColourInput = collections.namedtuple("ColourInput", "obs samples camera noise truth side")


def read_colour_input(path, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic", fov=None,
                      light=None, irradiance=None, power=1.0, black_level=None, white_level=None,
                      conversion_gain=None, read_noise=None, erode=2):
    """A :class:`ColourInput` of the raw colour mosaic ``path``: its sidecar gives the camera, and the light and
    irradiance not given; the irradiance is multiplied by ``power``."""
    path = os.fspath(path)
    side = colour_sidecar(path)
    if side is None:
        raise InputError(f"{path}: no colour capture sidecar ({os.path.splitext(path)[0]}.json with \"cfa\")")
    cam = side["sensor"]
    raw = ob.read_array(path, "raw colour mosaic")
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number):
        raise InputError(f"{path}: expected a single-channel raw mosaic, got an array of shape {raw.shape}")
    black = cam.black_level if black_level is None else float(black_level)
    white = cam.white_level if white_level is None else float(white_level)
    try:
        smp = colour_samples(raw, cam.layout, cam.cfa, black, white)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    shape = smp.values.shape[1:]
    n, m, v, exact, sph = colour_geometry(shape, side, normals=normals, mask=mask, view=view, sphere=sphere,
                                          camera=camera, fov=fov)
    params = side.get("parameters") if side.get("scene") == "builtin:sphere" else {}
    light = ob.check_direction(params.get("light_dir") if light is None and params else light, "light")
    if irradiance is None and params:
        # the raw DN are the render's units times the capture's DN per unit
        irradiance = params["irradiance"] * float(side.get("capture", {}).get("dn_per_input_unit", 1.0))
    irradiance = (1.0 if irradiance is None else float(irradiance)) * float(power)
    gain = cam.conversion_gain if conversion_gain is None else float(conversion_gain)
    rn = cam.read_noise if read_noise is None else float(read_noise)
    if not (gain > 0 and rn >= 0):
        raise InputError(f"noise: --conversion-gain must be > 0 and --read-noise >= 0, got {gain}, {rn}")
    truth = {k: params[k] for k in ("eta", "alpha", "beta", "kappa", "k_s", "r_k") if k in params} or None
    settings = {"layout": [list(r) for r in cam.layout], "cfa": [list(r) for r in cam.cfa], "black_level": black,
                "white_level": white, "conversion_gain": gain, "read_noise": rn,
                "light": [float(x) for x in light], "irradiance": irradiance, "erode": int(erode),
                "grid": "4x4 periods", "geometry": "exact sphere" if exact is not None else "maps"}
    meta = {"settings": settings, "sphere": sph, "sidecar": side["path"], "truth": truth}
    obs = ob.Observation(np.ones((3,) + tuple(shape)), ob.erode(m, int(erode)), n, v, light, irradiance,
                         geometry=exact, meta=meta)
    return ColourInput(obs, smp, cam, NoiseModel(gain, rn, 1.0), truth, side)


#: The image options a colour mosaic takes (read_colour_input's keywords; the schema's colour record's).
COLOUR_KEYS = tuple(o.name for o in IMAGE_OPTIONS if "colour" in o.records)

#: The other image options at their defaults ("not given"): ignored for colour mosaics.
_UNSET = {o.name: o.default for o in IMAGE_OPTIONS if "colour" not in o.records}


def is_colour(specs):
    """Whether the images of ``specs`` are colour mosaics (all of them); mixed sets are refused in one line."""
    flags = [not hasattr(s.input, "stokes") and colour_sidecar(s.input) is not None for s in specs]
    if any(flags) and not all(flags):
        k = flags.index(not flags[0])
        raise InputError(f"joint fit: image {k} is {'a colour' if flags[k] else 'not a colour'} mosaic and "
                         f"image 0 is {'one' if flags[0] else 'not'}; a joint fit takes images of one camera")
    return bool(flags) and all(flags)


def read_colour_inputs(specs, erode):
    """:class:`ColourInput` s of a joint fit's colour images, of one camera and only the options a mosaic takes."""
    out = []
    for k, s in enumerate(specs):
        opts = {x: v for x, v in s.options.items() if not (x in _UNSET and v == _UNSET[x])}
        bad = [x for x in opts if x not in COLOUR_KEYS]
        if bad:
            raise InputError(f"image {k} ({file_stem(s.input)}): {', '.join(bad)} not supported for a colour mosaic "
                             f"(valid: {', '.join(COLOUR_KEYS)}; layout and cfa come from the sidecar)")
        out.append(read_image(k, s, read_colour_input, power=s.power, erode=erode, **opts))
    cams = [(c.camera.layout, c.camera.cfa, c.noise.gain, c.noise.read_noise) for c in out]
    for k, c in enumerate(cams[1:], 1):
        if c != cams[0]:
            raise InputError(f"joint fit: image {k}'s camera (layout, cfa, gain, read noise) differs from image "
                             "0's; a joint fit assumes one camera")
    return out
