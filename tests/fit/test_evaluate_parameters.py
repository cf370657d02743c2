"""The parameter table: its rows, the names fit.json and the summaries show (written out by hand below),
the reported values from the albedos, and the way back from reported values to a start."""
import numpy as np
import pytest

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import Bounds, get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters

SHAPE = {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0}


def test_one_material_names_values_and_round_trip():
    t = Parameters(get_model("fmbrdf"))
    assert t.reported_names == ("eta", "alpha", "beta", "kappa", "k_s", "r_k")
    assert t.shape_names == ("eta", "alpha", "beta", "kappa")
    assert t.albedo_names == ("k_s", "r_k")
    rep = t.report(SHAPE, 0.4, 0.1)
    assert rep == {**SHAPE, "k_s": 0.4, "r_k": 0.1 / 0.4}
    assert t.report(SHAPE, 0.0, 0.1)["r_k"] == float("inf")
    shape, a_s, a_b = t.split({**SHAPE, "k_s": 0.4, "r_k": 0.25})
    assert shape == SHAPE and a_s == 0.4 and a_b == pytest.approx(0.1, rel=1e-15)
    row = t.param("alpha")
    assert (row.base, row.kind, row.key, row.lo, row.hi, row.scale) == ("alpha", "shape", "alpha", 0.01, 1.5, "log")


def test_other_models_report_both_albedos_through_their_factor():
    t = Parameters(get_model("lambert_ts"))
    assert t.reported_names == ("eta", "alpha", "k_s", "k_d")
    rep = t.report({"eta": 1.5, "alpha": 0.2}, 0.4, 0.6)
    assert rep["k_s"] == 0.5 * 0.4 and rep["k_d"] == 0.5 * 0.6
    _, a_s, a_b = t.split(rep)
    assert a_s == pytest.approx(0.4) and a_b == pytest.approx(0.6)
    assert Parameters(get_model("pplastic")).albedo_names == ("specular_reflectance", "diffuse_reflectance")


def test_split_names_what_is_missing_or_not_a_number():
    t = Parameters(get_model("fmbrdf"))
    with pytest.raises(InputError, match=r"fmbrdf parameters: missing alpha, beta, kappa, k_s, r_k"):
        t.split({"eta": 9})
    with pytest.raises(InputError, match=r"fmbrdf parameters: k_s must be a number, got 'x'"):
        t.split({**SHAPE, "k_s": "x", "r_k": 1})
    with pytest.raises(InputError, match=r"expected a dict"):
        t.split([1, 2])


def test_per_channel_albedos_and_their_nesting():
    t = Parameters(get_model("fmbrdf"), channels=("R", "G", "B"))
    assert t.reported_names == ("eta", "alpha", "beta", "kappa", "k_s[R]", "k_s[G]", "k_s[B]",
                                "r_k[R]", "r_k[G]", "r_k[B]")
    assert t.shape_names == ("eta", "alpha", "beta", "kappa")
    a_s, a_b = np.array([0.6, 0.4, 0.5]), np.array([0.42, 0.2, 0.1])
    flat = t.report(SHAPE, a_s, a_b)
    assert flat["k_s[G]"] == 0.4 and flat["r_k[B]"] == 0.1 / 0.5
    assert t.param("r_k[G]").channel == 1
    nested = t.nest(flat)
    assert nested == {**SHAPE, "k_s": {"R": 0.6, "G": 0.4, "B": 0.5},
                      "r_k": {"R": 0.42 / 0.6, "G": 0.2 / 0.4, "B": 0.1 / 0.5}}
    assert list(nested["k_s"]) == ["R", "G", "B"]


def test_materials_rows_in_report_and_optimiser_order():
    t = Parameters(get_model("pplastic"), materials=2)
    assert t.reported_names == ("eta[0]", "alpha[0]", "specular_reflectance[0]", "diffuse_reflectance[0]",
                                "eta[1]", "alpha[1]", "specular_reflectance[1]", "diffuse_reflectance[1]")
    assert t.shape_names == ("eta[0]", "alpha[0]", "eta[1]", "alpha[1]")
    values = {"eta[0]": 1.4, "alpha[0]": 0.1, "eta[1]": 1.7, "alpha[1]": 0.3}
    rep = t.report(values, np.array([0.2, 0.3]), np.array([0.5, 0.6]))
    assert rep == {"eta[0]": 1.4, "alpha[0]": 0.1, "specular_reflectance[0]": 0.2, "diffuse_reflectance[0]": 0.5,
                   "eta[1]": 1.7, "alpha[1]": 0.3, "specular_reflectance[1]": 0.3, "diffuse_reflectance[1]": 0.6}
    assert t.per_material(values)[1] == {"eta": 1.7, "alpha": 0.3}
    assert t.expand({"eta": 1.5, "alpha[1]": 0.2}) == {"eta[0]": 1.5, "eta[1]": 1.5, "alpha[1]": 0.2}
    assert t.per_material(rep) == [{"eta": 1.4, "alpha": 0.1, "specular_reflectance": 0.2, "diffuse_reflectance": 0.5},
                                   {"eta": 1.7, "alpha": 0.3, "specular_reflectance": 0.3, "diffuse_reflectance": 0.6}]
    shape, a_s, a_b = t.split({"eta": 1.5, "alpha": 0.2, "specular_reflectance": 0.3, "diffuse_reflectance": 0.4})
    assert shape == {"eta[0]": 1.5, "alpha[0]": 0.2, "eta[1]": 1.5, "alpha[1]": 0.2}
    assert a_s.tolist() == [0.3, 0.3] and a_b.tolist() == [0.4, 0.4]
    b = Bounds(Parameters(get_model("pplastic"), materials=2, bounds={"alpha": (0.05, 0.5)}))
    assert b.lims["alpha[1]"][2:] == (0.05, 0.5) and b.lims["eta[1]"][2:] == (1.01, 3.0)


def test_bounds_and_fixed_values_are_the_rows():
    t = Parameters(get_model("fmbrdf"), materials=2, bounds={"kappa": (1.0, 50.0), "alpha[1]": (0.1, 0.2)},
                   fixed={"beta": 2.0, "eta[0]": 1.4})
    assert (t.param("kappa[0]").lo, t.param("kappa[1]").hi) == (1.0, 50.0)
    assert (t.param("alpha[0]").lo, t.param("alpha[1]").lo, t.param("alpha[1]").hi) == (0.01, 0.1, 0.2)
    assert {r.name: r.fixed for r in t.shape if r.fixed is not None} == {"eta[0]": 1.4, "beta[0]": 2.0, "beta[1]": 2.0}
    assert t.with_fixed({"kappa[1]": 3.0}).param("kappa[1]").fixed == 3.0 and t.param("kappa[1]").fixed is None
    with pytest.raises(ValueError, match=r"bounds of eta\[0\]: need 1.01 <= lo < hi <= 3, got \(0.5, 2\)"):
        Parameters(get_model("fmbrdf"), materials=2, bounds={"eta": (0.5, 2.0)})
    with pytest.raises(ValueError, match=r"bounds: fmbrdf has no shape parameter 'k_s' \(it has eta, alpha, beta, "):
        Parameters(get_model("fmbrdf"), bounds={"k_s": (0.1, 0.2)})
    with pytest.raises(ValueError, match=r"fixed: fmbrdf has no shape parameter 'sigma' \(it has eta, alpha"):
        Parameters(get_model("fmbrdf"), fixed={"sigma": 0.1})


def test_albedo_maps_report_the_shape_only():
    t = Parameters(get_model("fmbrdf"), materials=2, maps=True)
    assert t.reported_names == t.shape_names == ("eta[0]", "alpha[0]", "beta[0]", "kappa[0]",
                                                 "eta[1]", "alpha[1]", "beta[1]", "kappa[1]")
    assert Parameters(get_model("fmbrdf"), maps=True).report(SHAPE, np.ones(5), np.ones(5)) == SHAPE


def test_free_powers_rows_bounds_and_defaults():
    t = Parameters(get_model("fmbrdf"), powers=[1.0, 2.0, 0.5])
    assert t.reported_names == ("eta", "alpha", "beta", "kappa", "k_s", "r_k", "power_1", "power_2")
    assert t.shape_names == ("eta", "alpha", "beta", "kappa", "power_1", "power_2")
    p = t.param("power_1")
    assert (p.kind, p.image, p.lo, p.hi, p.scale, p.grid) == ("power", 1, 0.002, 2000.0, "log", (2.0,))
    assert [r.image for r in t.powers] == [1, 2]
    shape, _, _ = t.split({**SHAPE, "k_s": 0.4, "r_k": 0.25, "power_2": 0.7})
    assert shape["power_1"] == 2.0 and shape["power_2"] == 0.7
    assert t.report({**SHAPE, "power_1": 1.9, "power_2": 0.6}, 0.4, 0.1)["power_2"] == 0.6


def test_predict_image_takes_each_material_from_its_rows():
    """A label image's prediction is, pixel by pixel, the one-material prediction with that material's values."""
    from fmbrdf_mi.fit.evaluate.predict import predict_image
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere

    p0 = {**SHAPE, "k_s": 0.5, "r_k": 0.6}
    p1 = {"eta": 1.8, "alpha": 0.4, "beta": 1.5, "kappa": 5.0, "k_s": 0.3, "r_k": 1.2}
    obs, _ = capture_observation(ideal_sphere(p0, res=12, area=1), noiseless=True)
    lab = np.arange(obs.mask.size).reshape(obs.mask.shape) % 2
    flat = {**{f"{k}[0]": v for k, v in p0.items()}, **{f"{k}[1]": v for k, v in p1.items()}}
    both = predict_image("fmbrdf", flat, obs, labels=lab)
    ref = np.where(lab[None] == 0, predict_image("fmbrdf", p0, obs), predict_image("fmbrdf", p1, obs))
    assert np.abs(both).max() > 0
    np.testing.assert_array_equal(both, ref * obs.mask[None])
