"""An :class:`Observation` from files: polarisation images, geometry, light, the camera's sidecar."""
from __future__ import annotations

import os

import numpy as np

from fmbrdf_mi import geometry as G
from fmbrdf_mi import scene as S
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.sensor import camera as C
from fmbrdf_mi.sensor import mosaic
from fmbrdf_mi.sensor import samples as SM
from fmbrdf_mi.sensor.noise import NoiseModel, box_footprint, demosaic_footprint, linear_stokes_variance
from fmbrdf_mi.fit.inputs.observations import (Observation, check_camera, check_direction, downsample_geometry,
                                               find_sphere, load_polarisation, read_mask,
                                               read_vectors)
from fmbrdf_mi.fit.inputs.options import IMAGE_OPTION
from fmbrdf_mi.fit.inputs.parse import check_number, check_render_parameters, parse_layout, parse_sphere


def check_image_options(values, where=None, name=str):
    """The image options among ``values`` checked, else InputError naming ``where`` and ``name(key)`` as written."""
    label = (lambda k: f"{where}: {name(k)}") if where else name
    for k, v in values.items():
        if k == "sphere":
            parse_sphere(v, label(k))
        elif k in IMAGE_OPTION:
            IMAGE_OPTION[k].check(v, label(k))
    white, dark = values.get("white_level"), values.get("dark_level")
    if white is not None and dark is not None and not dark < white:
        raise InputError(f"{label('dark_level')} {dark:g} must be below {name('white_level')} {white:g}")


def capture_sidecar(path):
    """The capture sidecar of the raw image ``path``, or None (none; not one file; an EXR: its metadata are its own)."""
    if not isinstance(path, (str, os.PathLike)) or os.fspath(path).lower().endswith(".exr"):
        return None
    try:
        return C.read_sidecar(path)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _builtin_sphere(meta):
    """Geometry, light, irradiance and true material of an EXR from ``fmbrdf-mi render`` (built-in scene)."""
    if meta.get("scene") != "builtin:sphere" or "parameters" not in meta:
        return None
    p = check_render_parameters(meta["parameters"], "")
    n, v, m = S.sphere_geometry((int(p["width"]), int(p["height"])), camera=p["camera"],
                                fov=p["fov"], distance=p["distance"])
    truth = {k: p[k] for k in ("eta", "alpha", "beta", "kappa", "k_s", "r_k", "k_b") if k in p}
    return {"normals": n, "view_dirs": v, "mask": m, "light_dir": p["light_dir"],
            "irradiance": p["irradiance"], "truth": truth}


def builtin_sphere_geometry(p, shape=None):
    """The exact :class:`~fmbrdf_mi.geometry.SphereGeometry` of :func:`fmbrdf_mi.scene.sphere_scene`'s sphere (render
    parameters ``p``) on a grid ``shape`` (rows, cols; default the image's) covering the image: a raw mosaic's
    samples sit off its super-pixel centres, where the pooled normal map, interpolated, would bias kappa."""
    shape = (int(p["height"]), int(p["width"])) if shape is None else tuple(shape)
    camera, fov, distance = p["camera"], float(p["fov"]), float(p["distance"])
    if camera == "orthographic":
        radius, fov = 0.5 * shape[1] / S.half_width(fov, distance), None
    else:
        radius = G.focal_length(shape[1], fov) * np.tan(np.arcsin(1.0 / distance))  # silhouette: rad = R / D
    return G.SphereGeometry(shape, (0.5 * shape[1], 0.5 * shape[0]), radius, camera, fov)


#: The grid of an image whose cells are ``cell`` x ``cell`` raw pixels: its name and its cells' in messages.
GRIDS = {2: ("polarisation image", "super-pixels"), 4: ("mosaic's 4x4 periods", "4x4 periods")}


def user_mask(mask, shape, within=None, what=None, cell=2):
    """The user's mask on the grid ``shape`` of ``cell`` x ``cell`` raw pixels (:data:`GRIDS`); a raw-mosaic
    mask keeps the cells wholly inside it.  It must select some pixel (of ``within``, named ``what``)."""
    name = f"--mask {os.fspath(mask)}" if isinstance(mask, (str, os.PathLike)) else "mask"
    grid, cells = GRIDS[cell]
    mk = read_mask(mask)
    raw = (cell * shape[0], cell * shape[1])
    if mk.shape == raw:
        mk = mk.reshape(shape[0], cell, shape[1], cell).all(axis=(1, 3))
    elif mk.shape != tuple(shape):
        raise InputError(f"{name}: shape {mk.shape} matches neither the {grid} {tuple(shape)} nor its raw mosaic "
                         f"{raw}")
    hint = f"a mask is non-zero on the object (a mask of the raw mosaic keeps the {cells} wholly inside it)"
    if within is not None and not (mk & within).any():
        raise InputError(f"{name}: selects no pixel of {what}; {hint}")
    if not mk.any():
        raise InputError(f"{name}: selects no pixel; {hint}")
    return mk


def user_geometry(shape, cell=2, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                  fov=None):
    """(normals, mask, view_dirs, exact geometry or None, the sphere's record or None) on the image's grid
    ``shape`` of ``cell`` x ``cell`` raw pixels from a normal map with its mask (maps of the raw mosaic pooled
    per cell) or a sphere (``cx,cy,r`` in cells, or ``auto``: found in the mask); InputError without either."""
    grid, cells = GRIDS[cell]
    raw = (cell * shape[0], cell * shape[1])
    if normals is not None:
        if mask is None:
            raise InputError("normals: give the object mask too (--mask, .npy or .png, non-zero = object)")
        n, m = read_vectors(normals, "normals"), read_mask(mask)
        v = read_vectors(view, "view") if view is not None else G.pixel_rays(n.shape[:2], *check_camera(camera, fov))
        if n.shape[:2] == raw:
            n, m, v = downsample_geometry(n, m, v, cell)
        for name, a in (("normals", n), ("mask", m), ("view", v)):
            if a.shape[:2] != tuple(shape):
                raise InputError(f"{name}: shape {a.shape[:2]} does not match the {grid} {tuple(shape)} or its "
                                 f"raw mosaic {raw}")
        return n, m, v, None, None
    if sphere is None:
        unit = "" if cell == 2 else f" in {cells},"
        raise InputError(f"geometry: give a normal map (--normals N.npy --mask M.png) or a sphere (--sphere cx,cy,r"
                         f"{unit} or --sphere auto --mask M.png)")
    sphere = parse_sphere(sphere)
    if sphere == "auto" and mask is None:
        raise InputError("--sphere auto: needs --mask to find the sphere in")
    mk = None if mask is None else user_mask(mask, shape, cell=cell)
    centre, radius = find_sphere(mk) if sphere == "auto" else (sphere[:2], sphere[2])
    n, m, v = G.sphere_normals(shape, centre, radius, *check_camera(camera, fov))
    if not m.any():
        raise InputError(f"sphere: centre {tuple(centre)} and radius {radius} cover no pixel of a "
                         f"{shape[1]}x{shape[0]} image")
    m = m if mk is None else m & mk
    record = {"centre": [float(c) for c in centre], "radius": float(radius), "found_from_mask": sphere == "auto"}
    if view is not None:
        return n, m, read_vectors(view, "view", shape), None, record
    return n, m, v, G.SphereGeometry(shape, centre, radius, camera, fov), record


def build_observation(inputs, *, normals=None, mask=None, view=None, sphere=None, camera="orthographic",
                      fov=None, light=None, irradiance=None, layout=mosaic.IMX250MZR_LAYOUT, black_level=0.0,
                      channel="mean", geometry=None, demosaic="bilinear", conversion_gain=None,
                      read_noise=None, footprint="auto", white_level=None, dark_level=None):
    """An :class:`Observation` from files (options: :func:`~fmbrdf_mi.fit.outputs.single.fit_files`'s);
    ``geometry``: (normals, mask, view_dirs) of another observation of the object.  A raw mosaic's capture sidecar
    supplies the sensor settings not given and the scene; ``meta["settings"]`` records what was used."""
    check_image_options(locals())     # the keywords, before anything is read
    sidecar = capture_sidecar(inputs)
    if sidecar is not None:
        cam = sidecar["sensor"]
        if cam.cfa is not None:
            raise InputError(f"{inputs}: a colour polarisation mosaic (sidecar {sidecar['path']}: cfa "
                             f"{''.join(c for r in cam.cfa for c in r)}); the fit command takes monochrome "
                             "mosaics only so far: fit it with fmbrdf_mi.fit.api.colour.fit_colour (docs: how-to "
                             "'Colour polarisation sensors')")
        layout = cam.layout if layout is None else layout
        black_level = cam.black_level if black_level is None else black_level
        if conversion_gain is None:
            conversion_gain, read_noise = cam.conversion_gain, cam.read_noise if read_noise is None else read_noise
        white_level = cam.white_level if white_level is None else white_level
    layout = mosaic.IMX250MZR_LAYOUT if layout is None else layout
    black_level = 0.0 if black_level is None else float(black_level)
    if isinstance(layout, str):
        layout = parse_layout(layout)
    stokes, meta = load_polarisation(inputs, layout=layout, channel=channel, black_level=black_level,
                                     demosaic=demosaic)
    array = meta.pop("_array", None)
    if array is not None and np.size(array) and black_level >= float(np.max(array)):
        name = os.fspath(inputs) if isinstance(inputs, (str, os.PathLike)) else "the angle images"
        raise InputError(f"black_level {black_level:g}: at or above every sample of {name} (the largest is "
                         f"{float(np.max(array)):g}): no usable samples; the black level is the raw value of no "
                         "light (--black-level, the manifest's or the capture sidecar's black_level)")
    if sidecar is not None:
        meta.update({k: v for k, v in sidecar.items() if k not in ("sensor", "path", C.SIDECAR_KEY)})
        meta["sidecar"] = sidecar["path"]
    shape = stokes.shape[1:]
    source = meta.get("sidecar") or (os.fspath(inputs) if isinstance(inputs, (str, os.PathLike)) else "input")
    try:
        builtin = _builtin_sphere(meta) if (normals is None and sphere is None and geometry is None) else None
        capture = meta.get("capture", {})
        dn_per_unit = check_number("capture.dn_per_input_unit", capture.get("dn_per_input_unit", 1.0),
                                   lo=0.0, lo_incl=False) if isinstance(capture, dict) else None
        if dn_per_unit is None:
            raise InputError(f"capture: expected a table, got {capture!r}")
        if builtin is not None:
            check_number("parameters.irradiance", builtin["irradiance"], lo=0.0, lo_incl=False)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
        raise InputError(f"{source}: the metadata of fmbrdf-mi render are malformed ({what})") from None
    exact = None
    if builtin is not None:
        ignored = [f for f, given in (("--view", view is not None), (f"--camera {camera}", camera != "orthographic"),
                                      ("--fov", fov is not None)) if given]
        if ignored:
            raise InputError(f"{', '.join(ignored)}: {source} is a render of the built-in sphere whose metadata give "
                             "its exact geometry (camera, field of view, view directions); drop them, or give "
                             "--normals/--mask or --sphere to use your own geometry")
        n, m, v = builtin["normals"], builtin["mask"], builtin["view_dirs"]
        if meta.get("source") == "raw mosaic" and n.shape[:2] == (2 * shape[0], 2 * shape[1]):
            n, m, v = downsample_geometry(n, m, v)
        if mask is not None and n.shape[:2] == shape:
            m = m & user_mask(mask, shape, m, f"the sphere whose geometry {source} gives")
        exact = builtin_sphere_geometry(meta["parameters"], shape)
        light = builtin["light_dir"] if light is None else light
        if irradiance is None:
            # a raw capture's DN are the Stokes image's units times the capture's DN per unit
            irradiance = builtin["irradiance"] * dn_per_unit
        meta = dict(meta, truth=builtin["truth"])
        if n.shape[:2] != shape:
            raise InputError(f"{inputs}: metadata describe a {n.shape[1]}x{n.shape[0]} image, the file is "
                             f"{shape[1]}x{shape[0]}")
    elif geometry is not None:
        n, m, v = geometry
    else:
        n, m, v, exact, sph = user_geometry(shape, normals=normals, mask=mask, view=view, sphere=sphere,
                                            camera=camera, fov=fov)
        if sph is not None:
            meta["sphere"] = sph
    light, src = check_direction(light, "light"), meta.get("source")
    var = noise = samples = None
    if src == "raw mosaic":
        samples = SM.from_raw(array, layout, black_level, white_level, dark_level)
    elif src == "angle images":
        samples = SM.from_angle_images(array, black_level, white_level, dark_level,
                                       integer=np.issubdtype(np.asarray(array).dtype, np.integer))
    if conversion_gain is not None:
        if not (conversion_gain > 0) or read_noise is None or not (read_noise >= 0):
            raise InputError(f"noise: --conversion-gain must be > 0 and --read-noise >= 0 given with it, got "
                             f"{conversion_gain}, {read_noise}")
        var = linear_stokes_variance(stokes[0], float(conversion_gain), float(read_noise),
                                     demosaic if src == "raw mosaic" else "superpixel",
                                     adc_step_e=float(conversion_gain) if samples is not None else None)
        noise = NoiseModel(float(conversion_gain), float(read_noise), samples.step if samples is not None else 0.0)
    if footprint == "auto":
        footprint = "demosaic" if src == "raw mosaic" else "point"
    fp = None if footprint == "point" else box_footprint(3) if footprint == "box" else demosaic_footprint(demosaic)
    irradiance = 1.0 if irradiance is None else float(irradiance)
    meta["settings"] = {"layout": [list(r) for r in layout], "black_level": black_level,
                        "demosaic": demosaic if src == "raw mosaic" else None, "footprint": footprint,
                        "white_level": None if samples is None else samples.white_level,
                        "dark_level": None if samples is None else samples.dark_level,
                        "conversion_gain": conversion_gain, "read_noise": read_noise,
                        "light": [float(x) for x in light], "irradiance": irradiance}
    return Observation(stokes, m, n, v, light, irradiance, meta, lin_variance=var, footprint=fp, samples=samples,
                       noise=noise, geometry=exact)
