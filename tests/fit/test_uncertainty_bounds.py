"""``at_bound`` and ``bound_distance_se``: flags in the parameter's own scale and in standard errors.

Before, a parameter was "at a bound" within 0.1 % of its *linear* range: a free light power, searched on
[G / 1000, 1000 G], was flagged anywhere below 1.001 G (the record's power_1 = 0.6005 +- 0.0017 was). The
expected flags below are worked out by hand from the rule in the docstring of ``uncertainty.at_bound``.
"""
import math
import types

import numpy as np

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


def _summary(values, se):
    """``summary`` of a diagonal covariance with standard errors ``se`` at ``values`` (shape and albedos)."""
    params = Parameters(get_model("fmbrdf"))
    p = types.SimpleNamespace(names=params.shape_names, bounds=Bounds(params), params=params)
    names = list(params.reported_names)
    shape = {n: values[n] for n in params.shape_names}
    st = State(shape, values["k_s"], values["k_s"] * values["r_k"])
    c = U.Covariance(names, np.diag([se[n] ** 2 for n in names]), {}, [("fisher", "")])
    return U.summary(p, st, c)


def test_a_wald_interval_cut_at_a_bound_says_it_is_open_there():
    """kappa 2 +- 3: the Wald interval [2 - 1.96 x 3, 2 + 1.96 x 3] passes kappa's lower bound 0, so it is cut
    there and its kind says so; alpha 1.4 +- 0.1 passes its upper bound 1.5; r_k 0.1 +- 0.2 passes 0 (an albedo
    is non-negative).  eta's interval stays inside (1.01, 3): no kind recorded for it.  Before, the cut
    intervals were reported as plain ``fisher`` ones (no ``interval_kind``), narrow where the data say little."""
    values = {"eta": 1.5, "alpha": 1.4, "beta": 2.0, "kappa": 2.0, "k_s": 0.8, "r_k": 0.1}
    se = {"eta": 0.01, "alpha": 0.1, "beta": 0.05, "kappa": 3.0, "k_s": 0.01, "r_k": 0.2}
    u = _summary(values, se)
    assert u["ci95"]["kappa"] == [0.0, 2.0 + U.Z95 * 3.0]
    assert u["ci95"]["alpha"] == [1.4 - U.Z95 * 0.1, 1.5]
    assert u["ci95"]["r_k"][0] == 0.0
    assert u["interval_kind"] == {"alpha": "lower fisher, upper fisher, open at the bound",
                                  "kappa": "lower fisher, open at the bound, upper fisher",
                                  "r_k": "lower fisher, open at the bound, upper fisher"}
    assert U.profiled(u["interval_kind"]) == []
    # both ends past a bound: one kind
    u = _summary(values | {"alpha": 0.05}, se | {"alpha": 2.0})
    assert u["interval_kind"]["alpha"] == U.FISHER_AT_BOUND and u["ci95"]["alpha"] == [0.01, 1.5]
    # nothing cut: no interval_kind (every interval is the Fisher one)
    assert "interval_kind" not in _summary(values | {"kappa": 20.0, "alpha": 0.3, "r_k": 1.0}, se)


def test_printed_kind_marks_an_interval_open_at_its_bound():
    """stdout's parameter line says an interval is open at its bound; the profile message does not list it."""
    from fmbrdf_mi.fit.outputs.summary import kind_text

    entry = {"uncertainty": {"interval_kind": {"kappa": "lower fisher, open at the bound, upper fisher"}}}
    assert "open at the bound" in kind_text(entry, "kappa") and kind_text(entry, "eta") == ""
    assert U.profiled({"kappa": "lower profile, open at the bound, upper fisher", "eta": U.FISHER_AT_BOUND}) == ["kappa"]
