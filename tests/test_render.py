"""Rendered Stokes images of spheres against independent references.

* S0 and DoLP per pixel against a direct ``bsdf.eval`` at the analytic normal,
  view and light of that pixel (fmbrdf_mi.scene.sphere_geometry), averaged over
  the pixel footprint on a 8 x 8 sub-pixel grid as Mitsuba's box filter does.
  A directional light is sampled exactly, so the only Monte Carlo noise is the
  random position of each of the spp samples in the pixel: its standard error
  is the sub-pixel standard deviation / sqrt(spp), and the tolerance is 5 of
  those plus the sub-pixel quadrature error (8 x 8 against 4 x 4).
* AoLP against physics: specular reflection polarised perpendicular to the
  plane of incidence, body reflection parallel to the plane of normal and view
  (radial on the image of a sphere seen head-on).
* The analytic mask against the rendered alpha (pixel coverage).
* The scene API's checks: a scene without a sensor, a huge light direction.
"""
import os

import numpy as np
import pytest

from fmbrdf_mi import scene as S
from fmbrdf_mi import stokes_io

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RES, SPP, SUB = 48, 64, 8


def _mono():
    import mitsuba as mi

    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


def reference_subpixels(mi, material, light_dir, irradiance, res, k, camera):
    """Stokes (4, H, W, k*k) in the camera frame at k x k sub-pixel centres, by bsdf.eval.

    Also returns inside (H, W): all sub-pixel centres on the sphere.
    """
    import drjit as dr

    n, v, m = S.sphere_geometry(res * k, camera=camera)
    L = np.asarray(S.check_light_dir(light_dir))
    N, V = n[m], v[m]
    # shading frame (s, t, N) per sample
    a = np.where(np.abs(N[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    s = np.cross(a, N)
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    t = np.cross(N, s)

    def local(w):
        return np.stack([np.sum(w * s, 1), np.sum(w * t, 1), np.sum(w * N, 1)]).astype(np.float32)

    bsdf = mi.load_dict(S.material_bsdf(material))
    si = dr.zeros(mi.SurfaceInteraction3f, len(N))
    si.wi = mi.Vector3f(local(V))
    wo = mi.Vector3f(local(np.broadcast_to(L, N.shape)))
    M = bsdf.eval(mi.BSDFContext(), si, wo)
    col = irradiance * np.stack([np.asarray(M[i, 0]).ravel() for i in range(4)])  # unpolarised light
    # Mitsuba's Stokes basis of the outgoing direction: x = stokes_basis(wi), y = wi x x
    xl = np.asarray(mi.mueller.stokes_basis(si.wi)).T
    x1 = xl[:, :1] * s + xl[:, 1:2] * t + xl[:, 2:] * N
    y1 = np.cross(V, x1)
    psi1 = 0.5 * np.arctan2(col[2], col[1])
    e = np.cos(psi1)[:, None] * x1 + np.sin(psi1)[:, None] * y1  # polarisation direction, world
    # camera frame of the stokes integrator: x = (ray direction) x (camera up),
    # = image right (world x) for the orthographic camera; y = V x x = image up
    xc = np.cross(-V, [0.0, 1.0, 0.0])
    xc /= np.linalg.norm(xc, axis=1, keepdims=True)
    yc = np.cross(V, xc)
    psic = np.arctan2(np.sum(e * yc, 1), np.sum(e * xc, 1))
    p = np.hypot(col[1], col[2])
    out = np.zeros((4,) + m.shape)
    out[0][m], out[3][m] = col[0], col[3]
    out[1][m], out[2][m] = p * np.cos(2 * psic), p * np.sin(2 * psic)
    sub = out.reshape(4, res, k, res, k).transpose(0, 1, 3, 2, 4).reshape(4, res, res, k * k)
    inside = m.reshape(res, k, res, k).transpose(0, 2, 1, 3).reshape(res, res, k * k).all(-1)
    return sub, inside


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_s0_and_dolp_match_bsdf_eval(camera):
    mi = _mono()
    stokes = S.render_stokes(mi.load_dict(S.sphere_scene(resolution=RES, spp=SPP, camera=camera)),
                             seed=1, progress=False)[..., 0]
    args = (mi, None, S.DEFAULT_LIGHT_DIR, S.DEFAULT_IRRADIANCE, RES)
    sub, inside = reference_subpixels(*args, SUB, camera)
    sub4, _ = reference_subpixels(*args, SUB // 2, camera)
    ref, ref4 = sub.mean(-1), sub4.mean(-1)
    sel = inside & (ref[0] > 1e-3)  # on the sphere and lit
    assert sel.sum() > 0.5 * np.pi * (RES / 2 / 1.1085) ** 2  # about half the disc is lit

    # S0: noise = sub-pixel spread / sqrt(spp)
    se0 = sub[0].std(-1) / np.sqrt(SPP)
    err0 = np.abs(stokes[0] - ref[0])
    tol0 = 5 * se0 + np.abs(ref[0] - ref4[0]) + 1e-4 * ref[0]
    assert np.all(err0[sel] <= tol0[sel]), np.max((err0 - tol0)[sel])
    z = ((stokes[0] - ref[0]) / np.maximum(se0, 1e-12))[sel & (se0 > 1e-6)]
    assert abs(z.mean()) < 0.2 and 0.7 < z.std() < 1.3, (z.mean(), z.std())  # the noise is what spp predicts

    # DoLP: linearised noise of |S_lin| / S0 over the sub-pixel samples
    p = np.hypot(ref[1], ref[2])
    d_ref = p / np.maximum(ref[0], 1e-12)
    u1, u2 = ref[1] / np.maximum(p, 1e-12), ref[2] / np.maximum(p, 1e-12)
    g = (u1[..., None] * sub[1] + u2[..., None] * sub[2] - d_ref[..., None] * sub[0]) / np.maximum(ref[0], 1e-12)[..., None]
    se_d = g.std(-1) / np.sqrt(SPP)
    d4 = np.hypot(ref4[1], ref4[2]) / np.maximum(ref4[0], 1e-12)
    d_img = stokes_io.dolp(stokes)
    tol_d = 5 * se_d + np.abs(d_ref - d4) + 2e-4
    assert np.all(np.abs(d_img - d_ref)[sel] <= tol_d[sel]), np.max((np.abs(d_img - d_ref) - tol_d)[sel])
    assert d_ref[sel].max() > 0.1  # the comparison includes strongly polarised pixels


def _wrap(a):
    """Angle difference modulo pi, in [-pi/2, pi/2)."""
    return (a + np.pi / 2) % np.pi - np.pi / 2


def test_aolp_follows_physics():
    mi = _mono()
    light = S.check_light_dir((-1.0, 1.0, 0.6))  # 59 deg from the view: strongly polarised specular
    stokes = S.render_stokes(mi.load_dict(S.sphere_scene(resolution=RES, spp=SPP, light_dir=light)),
                             seed=2, progress=False)[..., 0]
    n, v, m = S.sphere_geometry(RES)
    L = np.array(light)
    H = (L + [0, 0, 1]) / np.linalg.norm(L + [0, 0, 1])
    psi = stokes_io.aolp(stokes)

    # specular highlight (normals within 6 deg of the half vector): perpendicular
    # to the plane of incidence, which holds L and the view +z, i.e. to the
    # image direction (L_x, L_y) -- for an orthographic view, at every pixel
    spec = m & (n @ H > np.cos(np.radians(6)))
    assert spec.sum() >= 8
    dev_s = np.abs(_wrap(psi - (np.arctan2(L[1], L[0]) + np.pi / 2)))[spec]
    assert np.degrees(dev_s).max() < 5, np.degrees(dev_s).max()

    # body reflection near the silhouette, lit, far from the highlight:
    # parallel to the plane of normal and view, radial on the image
    body = m & (n[..., 2] < 0.35) & (n @ L > 0.3) & (n @ H < np.cos(np.radians(50)))
    assert body.sum() >= 20
    dev_b = np.abs(_wrap(psi - np.arctan2(n[..., 1], n[..., 0])))[body]
    assert np.degrees(dev_b).max() < 5, np.degrees(dev_b).max()
    assert stokes_io.dolp(stokes)[body].min() > 0.05


def _alpha_render(mi, scene_dict):
    scene_dict["sensor"]["film"]["pixel_format"] = "luminance_alpha"
    scene = mi.load_dict(scene_dict)
    img = np.asarray(mi.render(scene, seed=3))
    names = [f.name for f in scene.sensors()[0].film().bitmap().struct_()]
    return img[..., names.index("A")], img[..., names.index("S0.R")]


def _coverage(labels_fine, k):
    h, w = labels_fine.shape[0] // k, labels_fine.shape[1] // k
    return (labels_fine >= 0).reshape(h, k, w, k).mean(axis=(1, 3))


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_mask_matches_rendered_alpha(camera):
    mi = _mono()
    res, spp, k = 32, 64, 16
    alpha, s0 = _alpha_render(mi, S.sphere_scene(resolution=res, spp=spp, camera=camera, light_dir=(0, 0, 1)))
    _, _, mask = S.sphere_geometry(res, camera=camera)
    _, _, fine = S.sphere_geometry(res * k, camera=camera)
    cov = _coverage(np.where(fine, 0, -1), k)
    tol = 5 * np.sqrt(cov * (1 - cov) / spp) + 0.04
    assert np.all(np.abs(alpha - cov) <= tol), np.max(np.abs(alpha - cov) - tol)
    # the pixel-centre mask: every pixel whose centre is on the sphere is
    # rendered, every pixel not touched by it is empty
    assert np.all(s0[mask] > 0) and np.all(alpha[mask] > 0)
    assert np.all(alpha[cov == 0] == 0)
    assert np.all(mask[cov == 1])


def _xml(mi, name, **params):
    return mi.load_file(os.path.join(ROOT, "scenes", name), **{k: str(v) for k, v in params.items()})


@pytest.mark.parametrize("variant", ["llvm_ad_mono_polarized", "llvm_ad_spectral_polarized"])
def test_xml_scenes_equal_python_scenes(variant):
    import mitsuba as mi

    mi.set_variant(variant)
    import fmbrdf_mi

    fmbrdf_mi.register()
    pf = "luminance" if mi.is_monochromatic else "rgb"
    cases = [("sphere.xml", dict(eta=1.7, light_dir="0.3, 0.2, 1"),
              S.sphere_scene(dict(eta=1.7), resolution=20, spp=4, light_dir=(0.3, 0.2, 1)))]
    if mi.is_monochromatic:
        cases.append(("sphere_perspective.xml", {}, S.sphere_scene(resolution=20, spp=4, camera="perspective")))
    for name, params, d in cases:
        a = _xml(mi, name, width=20, height=20, spp=4, pixel_format=pf, **params)
        ra = S.render_stokes(a, seed=5, progress=False)
        rb = S.render_stokes(mi.load_dict(d), seed=5, progress=False)
        assert ra.shape == (4, 20, 20, 1 if mi.is_monochromatic else 3)
        assert ra[0].max() > 0.1
        np.testing.assert_allclose(ra, rb, rtol=0, atol=1e-5 * ra[0].max(), err_msg=name)


def test_spheres_scene_xml_python_and_geometry_agree():
    mi = _mono()
    res, spp, k = 16, 64, 16
    d = S.spheres_scene(S.EXAMPLE_MATERIALS, resolution=res, spp=spp, light_dir=(0, 0, 1))
    d["sensor"]["film"]["pixel_format"] = "luminance_alpha"
    xml = _xml(mi, "spheres.xml", width=3 * res, height=res, spp=spp, light_dir="0, 0, 1",
               pixel_format="luminance_alpha")
    imgs = [np.asarray(mi.render(scene, seed=3)) for scene in (mi.load_dict(d), xml)]
    np.testing.assert_allclose(imgs[0], imgs[1], rtol=0, atol=1e-5 * imgs[0].max())
    names = [f.name for f in xml.sensors()[0].film().bitmap().struct_()]
    alpha = imgs[0][..., names.index("A")]
    assert alpha.shape == (res, 3 * res)
    _, _, labels = S.spheres_geometry(3, res)
    _, _, fine = S.spheres_geometry(3, res * k)
    cov = _coverage(fine, k)
    tol = 5 * np.sqrt(cov * (1 - cov) / spp) + 0.04
    assert np.all(np.abs(alpha - cov) <= tol)
    # sphere i sits in cell i and has the i-th material
    cols = np.nonzero(labels >= 0)[1]
    assert np.array_equal(np.unique(labels[labels >= 0]), [0, 1, 2])
    for i in range(3):
        c = cols[labels[labels >= 0] == i]
        assert c.min() >= i * res and c.max() < (i + 1) * res
    mats = S.scene_materials(xml)
    assert [round(mats[f"sphere_{i}"]["alpha"], 5) for i in range(3)] == [m["alpha"] for m in S.EXAMPLE_MATERIALS]


def test_render_is_deterministic_in_seed_and_passes(monkeypatch):
    mi = _mono()
    scene = mi.load_dict(S.sphere_scene(resolution=16, spp=8))
    monkeypatch.setattr(S, "PASS_SAMPLES", 16 * 16 * 2)  # 4 passes of 2 spp
    assert S._n_passes(16, 16, 8) == 4
    a = S.render_stokes(scene, seed=7, progress=False)
    b = S.render_stokes(scene, seed=7, progress=False)
    c = S.render_stokes(scene, seed=8, progress=False)
    assert a.shape == (4, 16, 16, 1) and a.dtype == np.float32
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert scene.sensors()[0].sampler().sample_count() == 8  # the scene keeps its spp
    assert len({S.pass_seed(7, k) for k in range(4)} | {S.pass_seed(8, k) for k in range(4)}) == 8


def test_progress_reports_on_non_tty():
    import io

    buf = io.StringIO()
    bar = S._Progress("64x64, 8 spp", 2, delay=0.0, stream=buf)
    bar.step()
    bar.step()
    bar.close()
    lines = buf.getvalue().splitlines()
    assert 1 <= len(lines) <= 2 and "2/2 passes" in lines[-1]  # at most a line a second, and the last
    quiet = io.StringIO()
    bar = S._Progress("x", 2, delay=10.0, stream=quiet)  # fast renders say nothing
    bar.step()
    bar.close()
    assert quiet.getvalue() == ""


def test_progress_estimates_the_time_left(monkeypatch):
    """The estimate is the remaining passes at the rate of the passes after the first (which also compiles);
    after one pass, the first pass's time per pass."""
    import io

    now = [0.0]
    monkeypatch.setattr(S.time, "perf_counter", lambda: now[0])
    buf = io.StringIO()
    bar = S._Progress("x", 4, delay=0.0, stream=buf)    # starts at 0 s; passes end at 10, 12, 14 and 20 s
    now[0] = 10.0
    bar.step()
    assert bar.left() == 30.0                           # 3 passes left at 10 s a pass (the first)
    now[0] = 12.0
    bar.step()
    now[0] = 14.0
    bar.step()
    assert bar.left() == 2.0                            # (14 - 10) s / 2 passes, 1 pass left
    now[0] = 20.0
    bar.step()
    lines = buf.getvalue().splitlines()
    assert lines == ["x: [#####...............] 1/4 passes, 10.0 s (about 30.0 s left)",
                     "x: [##########..........] 2/4 passes, 12.0 s (about 4.0 s left)",
                     "x: [###############.....] 3/4 passes, 14.0 s (about 2.0 s left)",
                     "x: [####################] 4/4 passes, 20.0 s (done)"]
    assert [S._duration(t) for t in (59.94, 65, 3725)] == ["59.9 s", "1 min 05 s", "1 h 02 min"]


def test_writing_progress_estimates_the_time_left():
    """After the render, each file written is a step: silent while the steps are quick, then a line a step
    with the remaining steps at the mean time per step so far."""
    import io

    from fmbrdf_mi.render import StageProgress

    now = [0.0]
    buf = io.StringIO()
    bar = StageProgress("writing", 4, delay=2.0, stream=buf, clock=lambda: now[0])
    for t, name in [(1.0, "a"), (6.0, "b"), (9.0, "c"), (12.0, "d")]:
        now[0] = t
        bar.step(name)
    assert buf.getvalue().splitlines() == ["writing: 2/4 b, 6.0 s (about 6 s left)",
                                           "writing: 3/4 c, 9.0 s (about 3 s left)",
                                           "writing: 4/4 d, 12.0 s (done)"]
    quiet = io.StringIO()
    bar = StageProgress("writing", 2, enabled=False, delay=0.0, stream=quiet, clock=lambda: now[0])
    now[0] = 100.0
    bar.step("a")
    assert quiet.getvalue() == ""


def test_exr_round_trip_of_a_render(tmp_path):
    mi = _mono()
    stokes = S.render_stokes(mi.load_dict(S.sphere_scene(resolution=12, spp=4)), progress=False)
    p = tmp_path / "s.exr"
    stokes_io.write_stokes_exr(p, stokes, {"spp": 4})
    back, meta = stokes_io.read_stokes_exr(p)
    assert np.array_equal(back, stokes) and meta == {"spp": 4}


def test_scene_arguments_are_validated():
    _mono()
    from fmbrdf_mi import ParameterError

    with pytest.raises(ParameterError, match="eta"):
        S.sphere_scene(dict(eta=0.9))
    with pytest.raises(ParameterError, match="unknown material parameter 'roughness'"):
        S.sphere_scene(dict(roughness=0.2))
    with pytest.raises(ParameterError, match="not both"):
        S.sphere_scene(dict(r_k=1.0, k_b=0.5))
    with pytest.raises(ValueError, match="light_dir"):
        S.sphere_scene(light_dir=(0, 0, 0))
    with pytest.raises(ValueError, match="light_dir"):
        S.sphere_scene(light_dir=(0, np.nan, 1))
    with pytest.raises(ValueError, match="camera"):
        S.sphere_scene(camera="fisheye")
    with pytest.raises(ValueError, match="resolution"):
        S.sphere_scene(resolution=0)
    d = S.sphere_scene(dict(k_b=0.5), light_dir=(0, 0, 2))
    assert d["light"]["direction"] == [-0.0, -0.0, -1.0]
    assert "r_k" not in d["sphere"]["bsdf"] and d["sphere"]["bsdf"]["k_b"] == 0.5


# ---------------------------------------------------------------- the scene API's checks
def test_render_stokes_without_a_sensor(variant):
    from fmbrdf_mi import scene as S

    mi = variant
    sc = mi.load_dict({"type": "scene", "integrator": {"type": "stokes", "nested": {"type": "direct"}}})
    with pytest.raises(ValueError, match="no sensor"):
        S.render_stokes(sc, progress=False)


# ---------------------------------------------------------------- the scene API's checks: light directions
def test_render_light_dir_of_1e308():
    """Before: the norm overflowed and the light became (0, 0, 0)."""
    from fmbrdf_mi import scene as S

    assert S.check_light_dir([1e308, 0, 0]) == (1.0, 0.0, 0.0)
    v = np.array([0.1, -0.6, 0.8])
    assert S.check_light_dir(v) == tuple(v / np.linalg.norm(v))      # ordinary vectors: exactly as before
