"""The mesogeometry experiment (paper sec. 6.2, fig. "ONfitting"): a planar sample seen from many camera angles.

Normal N, light L and view V lie in one plane; the light is fixed at
``light_angle`` from the normal and the camera moves through signed angles
``camera_angles`` (positive on the light's side, so that the camera angle
equal to the light angle is the retro-reflection direction).  Each input is
the mean intensity over the sample's region shared by all images.  The
intensity of a plane under a directional light of irradiance E at normal
incidence is ``E cos(theta_L) f(L, V)``; E is absorbed by the albedos.

Fitted (least squares on the intensities, as the paper's intensity loss):

* FMBRDF, intensity only, all of eta, alpha, beta, kappa, k_s, k_b free, and
  again with kappa = 0 (no microfacet correlation), to show what kappa does;
* Lambert: ``k / pi`` (closed form);
* Oren-Nayar, full form (Oren & Nayar 1994, :mod:`fmbrdf_mi.model.oren_nayar`): sigma and rho.

Synthetic check: :func:`render_oren_nayar_plane` renders a plane of the
``orennayar`` BSDF through Mitsuba and returns those mean intensities.
"""
from __future__ import annotations

import csv
import dataclasses
import math

import numpy as np


class MesoInputError(ValueError):
    """Bad input to the mesogeometry tool (one line)."""


def directions(light_angle_deg, camera_angles_deg):
    """(L, V): (n, 3) unit vectors in the x-z plane, normal z; positive camera angles on the light's side."""
    cam = np.radians(np.asarray(camera_angles_deg, dtype=np.float64))
    tl = math.radians(float(light_angle_deg))
    L = np.tile([math.sin(tl), 0.0, math.cos(tl)], (len(cam), 1))
    V = np.stack([np.sin(cam), np.zeros_like(cam), np.cos(cam)], axis=1)
    return L, V


def read_csv(path):
    """(camera angles in degrees, mean intensities) from a CSV with columns camera_angle_deg, intensity."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except UnicodeDecodeError:
        raise MesoInputError(f"{path}: not a text CSV file") from None
    need = ("camera_angle_deg", "intensity")
    if not rows or any(k not in rows[0] for k in need):
        raise MesoInputError(f"{path}: expected a CSV with a header row naming the columns {', '.join(need)}")
    try:
        a = np.array([float(r["camera_angle_deg"]) for r in rows])
        i = np.array([float(r["intensity"]) for r in rows])
    except (TypeError, ValueError):
        raise MesoInputError(f"{path}: camera_angle_deg and intensity must be numbers in every row") from None
    check_data(a, i, where=str(path))
    return a, i


def check_data(angles, intensities, light_angle=None, where="data"):
    if len(angles) < 4:
        raise MesoInputError(f"{where}: need at least 4 camera angles, got {len(angles)}")
    if not (np.all(np.isfinite(angles)) and np.all(np.abs(angles) < 89.0)):
        raise MesoInputError(f"{where}: camera angles must be finite and within (-89, 89) degrees")
    if not (np.all(np.isfinite(intensities)) and np.all(intensities > 0)):
        raise MesoInputError(f"{where}: intensities must be finite and > 0")
    if light_angle is not None and not (math.isfinite(light_angle) and 0 <= light_angle < 89):
        raise MesoInputError(f"--light-angle: must be in [0, 89) degrees, got {light_angle:g}")


def render_oren_nayar_plane(sigma, rho, light_angle_deg, camera_angles_deg, irradiance=1.0, res=16, spp=4,
                            form="full"):
    """Mean intensity of a large plane of ``orennayar`` (Mitsuba render, ``direct`` integrator,
    orthographic camera filled by the plane at every angle) under a directional light."""
    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    mi = set_variant()
    tl = math.radians(light_angle_deg)
    light = [-math.sin(tl), 0.0, -math.cos(tl)]  # direction of travel
    out = []
    for a in camera_angles_deg:
        t = math.radians(a)
        origin = [5.0 * math.sin(t), 0.0, 5.0 * math.cos(t)]
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct"},
            "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([20.0, 20.0, 1.0]),
                      "bsdf": {"type": "orennayar", "sigma": float(sigma), "reflectance": float(rho),
                               "form": form}},
            "light": {"type": "directional", "direction": light, "irradiance": float(irradiance)},
            "sensor": {"type": "orthographic",
                       "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0], up=[0, 1, 0])
                       @ mi.ScalarTransform4f().scale([0.5, 0.5, 1.0]),
                       "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                                "pixel_format": "luminance"},
                       "sampler": {"type": "independent", "sample_count": spp}},
        })
        img = np.asarray(mi.render(scene, seed=1), dtype=np.float64)
        out.append(float(img.mean()))
    return np.array(out)


@dataclasses.dataclass
class ModelFit:
    name: str
    params: dict
    rmse: float            # RMSE of the intensity / mean observed intensity
    predict: object = None  # angles (deg) -> intensities


def fit_lambert(angles, obs, light_angle):
    c = math.cos(math.radians(light_angle))
    k = float(np.mean(obs)) * math.pi / c  # least squares of a constant
    pred = lambda a: np.full(len(np.atleast_1d(a)), k * c / math.pi)
    return ModelFit("lambert", {"k": k}, _rel_rmse(pred(angles), obs), pred)


def oren_nayar_intensity(angles, light_angle, sigma, rho, form="full"):
    """E = 1 intensity of an Oren-Nayar plane: cos(theta_L) f (the model module's maths, Dr.Jit LLVM)."""
    import drjit as dr
    from drjit.llvm import Array3f64, Float64

    from .model.oren_nayar import oren_nayar_brdf

    L, V = directions(light_angle, angles)
    to = lambda w: Array3f64(*(Float64(w[:, k]) for k in range(3)))
    f = oren_nayar_brdf(to(L), to(V), float(sigma), float(rho), form)
    dr.eval(f)
    return np.asarray(f, dtype=np.float64) * L[:, 2]


def fit_oren_nayar(angles, obs, light_angle, form="full"):
    from .brdf_fit.fitting import levenberg_marquardt

    scale = float(np.mean(obs))
    best = None
    for s0 in (0.0, 0.2, 0.4, 0.7, 1.0, 1.4):  # rho for each start: least squares of the direct term
        x = np.array([s0, min(max(np.mean(obs) * math.pi / math.cos(math.radians(light_angle)), 1e-3), 5.0)])
        r = lambda x: (oren_nayar_intensity(angles, light_angle, np.clip(x[0], 0, 0.5 * math.pi),
                                            abs(x[1]), form) - obs) / scale
        jac = lambda x: np.stack([(r(x + e) - r(x)) / 1e-6 for e in np.eye(2) * 1e-6], axis=1)
        xs, res, _, _ = levenberg_marquardt(r, jac, x, max_evals=60, max_step=0.3)
        if best is None or res @ res < best[1] @ best[1]:
            best = (xs, res)
    sigma, rho = float(np.clip(best[0][0], 0, 0.5 * math.pi)), float(abs(best[0][1]))
    pred = lambda a: oren_nayar_intensity(a, light_angle, sigma, rho, form)
    return ModelFit("oren_nayar", {"sigma": sigma, "rho": rho, "form": form}, _rel_rmse(pred(angles), obs), pred)


def fit_fmbrdf(angles, obs, light_angle, kappa=None, progress=None):
    """FMBRDF on the intensities; ``kappa``: None (free) or a fixed value."""
    from .brdf_fit.values import evaluation_variant

    with evaluation_variant():  # once for all evaluations (a variant switch is not free)
        return _fit_fmbrdf(angles, obs, light_angle, kappa, progress)


def _fit_fmbrdf(angles, obs, light_angle, kappa, progress):
    from .brdf_fit.fitting import closed_form_albedos, levenberg_marquardt
    from .brdf_fit.values import FMBRDFValues
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, Bounds

    L, V = directions(light_angle, angles)
    ev = FMBRDFValues(L, V)
    cos_l = L[:, 2]
    bounds = Bounds(FMBRDF)
    free = ("eta", "alpha", "beta") + (("kappa",) if kappa is None else ())
    scale = float(np.mean(obs))

    def shape_of(z):
        s = {n: bounds.to_value(n, z[k]) for k, n in enumerate(free)}
        s.setdefault("kappa", kappa)
        return s

    def parts(shape):
        S, B = ev.parts(shape)
        return S * cos_l, B * cos_l

    grid = []
    for eta in (1.3, 1.6, 2.2):
        for alpha in (0.1, 0.4, 1.2):
            for beta in (0.8, 2.0, 4.0):
                for k in ((0.0, 10.0, 50.0) if kappa is None else (kappa,)):
                    sh = {"eta": eta, "alpha": alpha, "beta": beta, "kappa": k}
                    S, B = parts(sh)
                    ks, kb = closed_form_albedos(S, B, obs[:, None])
                    e = float(np.sum(((ks[0] * S + kb[0] * B) - obs) ** 2))
                    grid.append((e, sh, ks[0], kb[0]))
    grid.sort(key=lambda g: g[0])
    if progress:
        progress(f"[mesogeometry] FMBRDF ({'kappa free' if kappa is None else f'kappa = {kappa:g}'}): "
                 f"{len(grid)} start points")

    def resid(x):
        S, B = parts(shape_of(x))
        return (np.exp(x[-2]) * S + np.exp(x[-1]) * B - obs) / scale

    def jac(x):
        r0 = resid(x)
        J = np.empty((len(obs), len(x)))
        for k in range(len(x)):
            e = np.zeros(len(x))
            e[k] = 1e-4
            J[:, k] = (resid(x + e) - r0) / 1e-4
        return J

    best = None
    for _, sh, ks, kb in grid[:2]:
        sh = dict(sh, kappa=max(sh["kappa"], 0.5)) if kappa is None else sh
        x0 = np.array([bounds.to_z(n, sh[n]) for n in free] + [math.log(max(ks, 1e-6)), math.log(max(kb, 1e-6))])
        xs, r, _, _ = levenberg_marquardt(resid, jac, x0, max_evals=40, max_step=1.0)
        if best is None or r @ r < best[1] @ best[1]:
            best = (xs, r)
    x = best[0]
    shape = shape_of(x)
    params = {**{k: float(v) for k, v in shape.items()}, "k_s": float(np.exp(x[-2])), "k_b": float(np.exp(x[-1]))}

    def pred(a):
        L2, V2 = directions(light_angle, a)
        S, B = FMBRDFValues(L2, V2).parts(shape)
        return (params["k_s"] * S + params["k_b"] * B) * L2[:, 2]

    name = "fmbrdf" if kappa is None else f"fmbrdf_kappa{kappa:g}"
    return ModelFit(name, params, _rel_rmse(pred(angles), obs), pred)


def _rel_rmse(pred, obs):
    return float(np.sqrt(np.mean((pred - obs) ** 2)) / np.mean(obs))


def run_experiment(angles, obs, light_angle, progress=None):
    """All four fits: {name: ModelFit}."""
    check_data(angles, obs, light_angle)
    fits = {}
    fits["fmbrdf"] = fit_fmbrdf(angles, obs, light_angle, None, progress)
    fits["fmbrdf_kappa0"] = fit_fmbrdf(angles, obs, light_angle, 0.0, progress)
    fits["lambert"] = fit_lambert(angles, obs, light_angle)
    fits["oren_nayar"] = fit_oren_nayar(angles, obs, light_angle)
    return fits


LABELS = {"fmbrdf": "FMBRDF (κ free)", "fmbrdf_kappa0": "FMBRDF, κ = 0", "lambert": "Lambert",
          "oren_nayar": "Oren–Nayar"}
STYLES = {"fmbrdf": ("tab:red", "-"), "fmbrdf_kappa0": ("tab:red", ":"), "lambert": ("tab:blue", "--"),
          "oren_nayar": ("tab:green", "-.")}


def plot(angles, obs, light_angle, fits, path, title=""):
    """Intensity against the camera angle: observations as dots, each fit as a curve (as the paper's figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.linspace(min(angles), max(angles), 181)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), constrained_layout=True)
    ax.scatter(angles, obs, s=18, color="k", zorder=3, label="observation")
    for name, f in fits.items():
        c, ls = STYLES.get(name, ("gray", "-"))
        extra = f", κ = {f.params['kappa']:.3g}" if name == "fmbrdf" else ""
        ax.plot(a, f.predict(a), color=c, ls=ls, lw=1.6,
                label=f"{LABELS.get(name, name)}{extra} (RMSE {100 * f.rmse:.2f} %)")
    ax.axvline(light_angle, color="0.7", lw=0.8)
    ax.text(light_angle, ax.get_ylim()[0], " light", color="0.5", va="bottom", fontsize=8)
    ax.set_xlabel("camera angle θ_nv (deg; positive: light's side)")
    ax.set_ylabel("mean intensity")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
