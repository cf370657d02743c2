"""The BSDF plugin's state (fmbrdf_mi/bsdf.py): a rejected update leaves no trace, inclusive bounds survive
float32, tables never outlive the AD variables they were built from, retro-reflection, errors at load time,
registration after a variant switch, untested versions."""
import math

import numpy as np
import pytest
from _common import directions, eval_mueller
from conftest import make, make_float32
from reference import Reference

import fmbrdf_mi

GOOD = dict(eta=1.6, alpha=0.3, beta=1.7, kappa=20.0, k_s=0.8, k_b=0.6)


def _pairs():
    rng = np.random.default_rng(3)
    L = directions(rng.uniform(5, 80, 12), rng.uniform(-180, 180, 12))
    V = directions(rng.uniform(5, 80, 12), rng.uniform(-180, 180, 12))
    V[:3] = L[:3] * [-1, -1, 1]  # mirror pairs: the surface lobe matters
    return L, V


# ------------------------------------------------------------------ state rollback
@pytest.mark.parametrize("key,bad", [
    ("eta", math.nan), ("eta", 0.9), ("alpha", 0.0), ("alpha", math.inf), ("beta", 9.0),
    ("kappa", -1.0), ("k_s.value", -1.0), ("k_b.value", math.nan),
])
def test_rejected_update_is_rolled_back(variant, key, bad):
    """Before: the bad value stayed in the BSDF (NaN / negative eval) and every later valid
    update re-raised the old error."""
    mi = variant
    L, V = _pairs()
    bsdf = make(mi, **GOOD)
    before, _, _ = eval_mueller(bsdf, L, V)
    params = mi.traverse(bsdf)
    params[key] = bad
    with pytest.raises(fmbrdf_mi.ParameterError, match=key.split(".")[0]):
        params.update()
    # the value itself and what the BSDF evaluates are as before (bit for bit)
    name = key.split(".")[0]
    assert float(params[key][0]) == pytest.approx(GOOD[name], rel=1e-7)
    after, _, _ = eval_mueller(bsdf, L, V)
    np.testing.assert_array_equal(after, before)
    # a later valid update of another parameter works and gives what a fresh load gives
    params["beta"] = 2.5
    params.update()
    got, _, _ = eval_mueller(bsdf, L, V)
    want, _, _ = eval_mueller(make(mi, **dict(GOOD, beta=2.5)), L, V)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)


def test_rejected_update_in_a_scene_renders_as_before(variant):
    mi = variant
    from fmbrdf_mi import scene as S

    sc = mi.load_dict(S.sphere_scene(dict(GOOD), resolution=12, spp=2))
    ref = S.render_stokes(sc, progress=False)
    params = mi.traverse(sc)
    params["sphere.bsdf.eta"] = math.nan
    params["sphere.bsdf.k_s.value"] = -2.0
    with pytest.raises(fmbrdf_mi.ParameterError):
        params.update()
    np.testing.assert_array_equal(S.render_stokes(sc, progress=False), ref)
    params["sphere.bsdf.k_s.value"] = 0.8  # a valid update afterwards is accepted
    params.update()


# ------------------------------------------------------------------ inclusive bounds
@pytest.mark.parametrize("name,value", [
    ("alpha", 0.01), ("alpha", 0.5 * math.pi), ("beta", 0.4), ("beta", 5.0), ("kappa", 0.0),
    ("kappa", 100.0), ("eta", 3.0),
])
def test_inclusive_bounds_survive_float32(variant, name, value):
    """Before: alpha = 0.01 and pi/2 loaded, but their float32 roundings (0.0099999998,
    1.5707964) were refused by any later update, of k_s too."""
    mi = variant
    bsdf = make(mi, **{**GOOD, name: value})
    params = mi.traverse(bsdf)
    params["k_s.value"] = 0.7
    params.update()
    params[name] = value  # set through traverse: rounded to float32 here
    params["beta"] = 2.0 if name != "beta" else value
    params.update()
    other = make(mi, **GOOD)
    po = mi.traverse(other)
    po[name] = value
    po.update()


@pytest.mark.parametrize("name,value", [("alpha", 0.0099), ("alpha", 1.5708), ("eta", 1.0),
                                        ("beta", 0.3999), ("kappa", 100.01)])
def test_just_outside_the_bounds_is_still_refused(variant, name, value):
    mi = variant
    params = mi.traverse(make(mi, **GOOD))
    params[name] = value
    with pytest.raises(fmbrdf_mi.ParameterError, match=name):
        params.update()


# ------------------------------------------------------------------ stale tables under AD
def _objective(mi, bsdf):
    import drjit as dr

    L, V = _pairs()
    si = dr.zeros(mi.SurfaceInteraction3f, len(L))
    si.wi = mi.Vector3f(V.T.astype(np.float32))
    M = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(L.T.astype(np.float32)))
    return dr.sum((M[0, 0] + 3.0 * M[1, 0] - 2.0 * M[2, 0] + M[1, 1])[0])


def _fd(mi, name, h):
    import drjit as dr

    # float32 tables (conftest.make_float32): the fixed-point one would swamp the difference of M11
    f = [float(dr.detach(_objective(mi, make_float32(mi, **{**GOOD, name: GOOD[name] + s * h})))[0])
         for s in (1, -1)]
    return (f[0] - f[1]) / (2 * h)


@pytest.mark.parametrize("name", ["eta", "alpha", "beta", "kappa"])
@pytest.mark.parametrize("sequence", ["reenable", "twice"])
def test_gradient_after_backward_and_reenable(variant, name, sequence):
    """Before: after a backward pass, dr.disable_grad + dr.enable_grad of the same parameter
    (Dr.Jit reuses the AD index) + params.update(), parameters_changed was not called and
    the tables stayed attached to the dead AD variable: kappa's gradient came out exactly 0.
    A second backward pass without any change gave 0 too ("twice").
    Reference: central differences, h = 1e-2 x value (truncation ~1e-4 relative, float32
    noise ~1e-5; see test_gradients.py), tolerance 2 %."""
    import drjit as dr

    mi = variant
    bsdf = make(mi, **GOOD)
    params = mi.traverse(bsdf)
    dr.enable_grad(params[name])
    params.update()
    dr.backward(_objective(mi, bsdf))
    first = float(dr.grad(params[name])[0])
    if sequence == "reenable":
        dr.disable_grad(params[name])
        dr.enable_grad(params[name])
        params.update()
    else:
        dr.clear_grad(params[name])
    dr.backward(_objective(mi, bsdf))
    again = float(dr.grad(params[name])[0])
    fd = _fd(mi, name, 1e-2 * GOOD[name])
    assert abs(fd) > 1e-5
    assert first == pytest.approx(fd, rel=2e-2)
    assert again == pytest.approx(fd, rel=2e-2), (name, sequence, first, again, fd)


def test_value_changed_without_update_is_not_evaluated_stale(variant):
    """A parameter written without params.update(): eval rebuilds (outside a render)."""
    mi = variant
    bsdf = make(mi, **GOOD)
    params = mi.traverse(bsdf)
    L, V = _pairs()
    params["alpha"] = 0.5
    got, _, _ = eval_mueller(bsdf, L, V)
    want, _, _ = eval_mueller(make(mi, **dict(GOOD, alpha=0.5)), L, V)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)


# ------------------------------------------------------------------ retro-reflection
@pytest.mark.parametrize("theta", [0.0, 20.0, 60.0, 80.0])
def test_retro_reflection_surface_block(variant, theta):
    """wi == wo.  Before: the fallback s axis (1, 0, 0) was not perpendicular to V, and the
    surface block was wrong (M11/M00 = 0.0625 instead of 1 at 60 deg).  Checked against the
    brute-force reference (its own s-axis fallback, float64) and against the limit of nearby
    non-coaxial configurations (continuity: within 1e-2 of M00 at 0.05 deg away)."""
    mi = variant
    mat = dict(eta=1.5, alpha=0.4, beta=2.0, kappa=10.0)
    bsdf = make(mi, k_s=1.0, k_b=0.0, **mat)
    ref_model = Reference(**mat)
    for phi in (0.0, 35.0, 140.0, -100.0):
        V = directions(np.array([theta]), np.array([phi]))
        L = V.copy()
        Ms, x_in, x_out = eval_mueller(bsdf, L, V, component=0)
        ref = ref_model.surface(L[0], V[0], x_in[0], x_out[0])
        m00 = ref[0, 0]
        assert m00 > 0
        assert np.abs(Ms[0] - ref).max() < 1e-3 * m00, (phi, Ms[0] / m00, ref / m00)
        # no depolarisation at normal facet incidence: the linear block is orthogonal
        lin = Ms[0, 1:3, 1:3] / Ms[0, 0, 0]
        assert abs(abs(np.linalg.det(lin)) - 1.0) < 1e-3
        # the limit of nearby configurations, approached from four sides
        eps = math.radians(0.05)
        th, ph = math.radians(theta), math.radians(phi)
        t1 = np.array([math.cos(th) * math.cos(ph), math.cos(th) * math.sin(ph), -math.sin(th)])
        t2 = np.cross(V[0], t1)
        for a in (0.0, 90.0, 180.0, 270.0):
            d = math.cos(math.radians(a)) * t1 + math.sin(math.radians(a)) * t2
            Ln = (V[0] * math.cos(eps) + d * math.sin(eps))[None]
            Mn, _, _ = eval_mueller(bsdf, Ln, V, component=0)
            assert np.abs(Mn[0] - Ms[0]).max() < 1e-2 * m00, (phi, a, Mn[0] / m00, Ms[0] / m00)


# ------------------------------------------------------------------ errors at load time
@pytest.mark.parametrize("props,needle", [
    ({"eta": 0.5}, "eta"), ({"alpha": math.nan}, "alpha"), ({"k_s": -1.0}, "k_s"),
    ({"roughness_of_the_surface": 0.3}, "roughness_of_the_surface"),
    ({"k_b": 0.5, "r_k": 0.5}, "k_b"),
])
def test_load_errors_are_parameter_errors(variant, tmp_path, props, needle):
    """Before: mi.load_dict raised RuntimeError carrying a Python traceback in its message;
    fmbrdf_mi.load_dict / load_file raise the documented ParameterError, one line."""
    mi = variant
    with pytest.raises(fmbrdf_mi.ParameterError) as e:
        fmbrdf_mi.load_dict({"type": "scene", "s": {"type": "sphere", "bsdf": {"type": "fmbrdf", **props}}})
    msg = str(e.value)
    assert needle in msg and "\n" not in msg and "Traceback" not in msg
    xml = "".join(f'<float name="{k}" value="{v}"/>' for k, v in props.items())
    path = tmp_path / "s.xml"
    path.write_text(f'<scene version="3.0.0"><shape type="sphere"><bsdf type="fmbrdf">{xml}</bsdf></shape></scene>')
    with pytest.raises(fmbrdf_mi.ParameterError) as e:
        fmbrdf_mi.load_file(str(path))
    assert needle in str(e.value) and "\n" not in str(e.value)
    # plain Mitsuba: a RuntimeError whose last line is the ParameterError
    with pytest.raises(RuntimeError, match=needle):
        mi.load_dict({"type": "fmbrdf", **props})


def test_rgb_nan_albedo_refused_in_spectral_variant():
    """Before: the spectral upsampling turned an RGB NaN into finite coefficients, accepted."""
    import mitsuba as mi

    fmbrdf_mi.register("llvm_ad_spectral_polarized")
    try:
        for name in ("k_b", "k_s", "r_k"):
            for bad in ([math.nan, 0.2, 0.3], [0.2, -0.1, 0.3]):
                with pytest.raises(fmbrdf_mi.ParameterError, match=name):
                    fmbrdf_mi.load_dict({"type": "fmbrdf", name: {"type": "rgb", "value": bad}})
    finally:
        mi.set_variant("llvm_ad_mono_polarized")


def test_registered_automatically_after_a_variant_switch():
    """Before: after mi.set_variant(other), 'fmbrdf' was unknown until register() was called."""
    import mitsuba as mi

    for v in ("llvm_ad_rgb", "scalar_rgb", "llvm_ad_spectral_polarized", "llvm_ad_mono_polarized"):
        mi.set_variant(v)
        mi.load_dict({"type": "fmbrdf", "alpha": 0.2})  # no register() call
    fmbrdf_mi.register()  # still works, idempotent


def test_untested_versions_warn(monkeypatch):
    import drjit as dr
    import mitsuba as mi

    monkeypatch.setattr(mi, "__version__", "3.7.0")
    with pytest.warns(fmbrdf_mi.UntestedVersionWarning, match="mitsuba 3.7.0"):
        fmbrdf_mi.check_versions()
    monkeypatch.setattr(dr, "__version__", "1.2.0")
    with pytest.warns(fmbrdf_mi.UntestedVersionWarning, match="drjit 1.2.0"):
        fmbrdf_mi.check_versions()
