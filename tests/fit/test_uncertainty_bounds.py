"""``at_bound`` and ``bound_distance_se``: flags in the parameter's own scale and in standard errors.

Before, a parameter was "at a bound" within 0.1 % of its *linear* range: a free light power, searched on
[G / 1000, 1000 G], was flagged anywhere below 1.001 G (the record's power_1 = 0.6005 +- 0.0017 was). The
expected flags below are worked out by hand from the rule in the docstring of ``uncertainty.at_bound``.
"""
import math
import types

from fmbrdf_mi.fit import uncertainty as U
from fmbrdf_mi.fit.evaluate.models import Bounds, State, get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters


def _problem(given=(1.0, 1.0, 1.0)):
    params = Parameters(get_model("fmbrdf"), powers=list(given))
    return types.SimpleNamespace(names=params.shape_names, bounds=Bounds(params), params=params)


def _state(**kw):
    shape = {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0, "power_1": 1.0, "power_2": 1.0}
    shape.update(kw)
    return State(shape, 1.0, 1.0)


def test_equal_powers_are_not_at_a_bound():
    p = _problem()
    st = _state(power_1=1.0, power_2=0.6005)
    assert U.at_bound(p, st) == []                      # both flagged by the old linear rule
    assert U.at_bound(p, st, {"power_1": 0.002, "power_2": 0.0017}) == []
    d = U.bound_distance(p, st)
    assert math.isclose(d["power_2"][0], 0.6005 - 0.001)                       # from G / 1000
    assert math.isclose(d["power_2"][1], math.log(0.6005 / 0.001) / math.log(1e6))


def test_extreme_powers_are_at_a_bound():
    p = _problem(given=(1.0, 2.0, 1.0))
    # 1.0005 x the lower bound G / 1000 = 0.002: log distance 5e-4 of the log range ln(1e6) = 13.8 -> 3.6e-5 < 1e-3
    st = _state(power_1=0.002 * 1.0005, power_2=1000.0 * 0.9999)
    assert U.at_bound(p, st) == ["power_1", "power_2"]


def test_interval_reaching_a_bound_flags_in_standard_errors():
    p = _problem()
    st = _state(power_1=0.01, alpha=0.0105)
    assert U.at_bound(p, st) == []                      # neither within 1e-3 of its log range
    # power_1 is 0.009 from G / 1000: flagged when 1.96 SE > 0.009; alpha is 0.0005 from 0.01
    assert U.at_bound(p, st, {"power_1": 0.0045, "alpha": 0.0002}) == []
    assert U.at_bound(p, st, {"power_1": 0.0047, "alpha": 0.0003}) == ["alpha", "power_1"]
