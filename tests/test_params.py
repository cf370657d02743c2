"""Bad parameter values (at load, through ``fmbrdf_mi.load_dict``, through traverse) raise one error that names
the parameter and its valid range."""
import math
import subprocess
import sys

import pytest
from conftest import make


@pytest.mark.parametrize("name,value,needle", [
    ("eta", 1.0, "eta"), ("eta", 0.5, "eta"), ("alpha", 0.0, "alpha"), ("alpha", -0.1, "alpha"),
    ("beta", 0.0, "beta"), ("kappa", -1.0, "kappa"), ("alpha", math.nan, "alpha"),
    ("eta", math.inf, "eta"), ("k_s", -0.5, "k_s"), ("k_b", math.nan, "k_b"),
])
def test_bad_value_at_load(variant, name, value, needle):
    mi = variant
    with pytest.raises(Exception) as err:
        make(mi, **{name: value})
    msg = str(err.value)
    assert needle in msg and ("range" in msg)


def test_both_body_albedos_rejected(variant):
    mi = variant
    with pytest.raises(Exception, match="k_b.*r_k|r_k.*k_b"):
        mi.load_dict({"type": "fmbrdf", "k_b": 0.5, "r_k": 0.5})


@pytest.mark.parametrize("name,value", [("eta", 0.9), ("alpha", -1.0), ("kappa", math.nan), ("beta", 100.0)])
def test_bad_value_through_traverse(variant, name, value):
    mi = variant
    bsdf = make(mi)
    params = mi.traverse(bsdf)
    params[name] = value
    with pytest.raises(Exception) as err:
        params.update()
    assert name in str(err.value) and "range" in str(err.value)


def test_bad_albedo_through_traverse(variant):
    mi = variant
    bsdf = make(mi)
    params = mi.traverse(bsdf)
    params["k_s.value"] = -1.0
    with pytest.raises(Exception, match="k_s"):
        params.update()


def test_defaults_are_valid_and_documented(variant):
    mi = variant
    from fmbrdf_mi.params import SCALAR_PARAMS

    bsdf = mi.load_dict({"type": "fmbrdf"})
    params = mi.traverse(bsdf)
    for name, (default, *_rest) in SCALAR_PARAMS.items():
        assert float(params[name][0]) == pytest.approx(default)


def test_unsupported_variant():
    import mitsuba as mi

    import fmbrdf_mi

    with pytest.raises(ValueError, match="scalar_spectral_polarized"):
        fmbrdf_mi.register("scalar_spectral_polarized")
    mi.set_variant("llvm_ad_mono_polarized")


def test_old_llvm_is_reported(monkeypatch):
    import drjit as dr

    from fmbrdf_mi import _llvm

    monkeypatch.setattr(dr.detail, "llvm_version", lambda: (15, 0, 7))
    with pytest.raises(_llvm.LLVMTooOldError, match="libllvm19"):
        _llvm.check_llvm()


def test_coloured_albedos_in_spectral_variant():
    """Spectral variants store RGB as upsampling coefficients (possibly negative):
    validation must look at the reflectance, not the coefficients."""
    import mitsuba as mi
    import fmbrdf_mi

    fmbrdf_mi.register("llvm_ad_spectral_polarized")
    for kb in ({"type": "rgb", "value": [0.8, 0.25, 0.15]}, {"type": "rgb", "value": [0.3, 0.3, 0.3]}):
        mi.load_dict({"type": "fmbrdf", "k_b": kb, "k_s": {"type": "rgb", "value": [0.9, 0.9, 0.2]}})
    for bad in (-0.5, math.nan):
        with pytest.raises(Exception, match=r"k_b.*valid range \[0, inf\)"):
            mi.load_dict({"type": "fmbrdf", "k_b": bad})


# ---------------------------------------------------------------- load_dict: values Mitsuba would crash on or report badly
@pytest.mark.parametrize("d,words", [
    ({"type": "fmbrdf", "eta": None}, ["fmbrdf", "'eta' is None"]),
    ({"type": "fmbrdf", "k_s": None}, ["'k_s' is None"]),
    ({"type": "scene", "s": {"type": "sphere", "bsdf": {"type": "fmbrdf", "alpha": None}}},
     ["s.bsdf", "'alpha' is None"]),
    ({"type": "orennayar", "sigma": None}, ["orennayar", "'sigma' is None"]),
    ({"type": "diffuse", "reflectance": None}, ["diffuse", "'reflectance' is None"]),
])
def test_load_dict_refuses_none_instead_of_segfaulting(d, words):
    """Before: mi.load_dict segfaulted (exit -11), taking the Python process with it: run in a child."""
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_mono_polarized'); import fmbrdf_mi\n"
            "try:\n"
            f"    fmbrdf_mi.load_dict({d!r})\n"
            "except fmbrdf_mi.ParameterError as e:\n"
            "    print('REFUSED', e)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    line = p.stdout.strip().splitlines()[-1]
    assert line.startswith("REFUSED ")
    for w in words:
        assert w in line, (w, line)


@pytest.mark.parametrize("d,words", [
    ({"type": "fmbrdf", "eta": [1, 2]}, ["'eta' must be a number"]),
    ({"type": "fmbrdf", "eta": "abc"}, ["'eta'", "must be a number"]),
    ({"type": "fmbrdf", "eta": True}, ["'eta' must be a number"]),
    ({"type": "fmbrdf", "kappa": float("nan")}, ["'kappa'", "valid range"]),
    ({"type": "fmbrdf", "k_s": "abc"}, ["'k_s' must be a number >= 0", "texture"]),
    ({"type": "fmbrdf", "k_b": [0.5, 0.5, 0.5]}, ["'k_b' must be a number >= 0", "'rgb'"]),
    ({"type": "fmbrdf", "r_k": float("nan")}, ["'r_k'", ">= 0"]),
    ({"type": "fmbrdf", "tables": 5}, ["'tables' must be text"]),
    ({"type": "orennayar", "reflectance": "x"}, ["orennayar", "'reflectance'"]),
    ({"type": "orennayar", "sigma": [0.3]}, ["orennayar", "'sigma' must be a number"]),
])
def test_load_dict_refuses_values_mitsuba_reports_with_a_traceback(variant, d, words):
    """Before: RuntimeError with Mitsuba's multi-line message (lists, k_s as a word)."""
    import fmbrdf_mi

    with pytest.raises(fmbrdf_mi.ParameterError) as e:
        fmbrdf_mi.load_dict(d)
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_load_dict_still_takes_numeric_text_and_textures(variant):
    import fmbrdf_mi

    fmbrdf_mi.load_dict({"type": "fmbrdf", "eta": "1.5", "k_b": {"type": "rgb", "value": [0.1, 0.2, 0.3]}})
