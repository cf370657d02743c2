"""Separate optima among a multi-start fit's ends (``fmbrdf_mi.fit.uncertainty.other_optima``).

The rule is arithmetic on the starts' ends and scores (negative log-likelihoods), so these tests build
the starts by hand and check each branch against numbers worked out here: the separation in standard
errors, delta chi^2 = 2 x the score difference, and the joint threshold chi^2_p(0.95) x scale x the
sandwich's largest variance inflation.
"""
import math

import pytest

from fmbrdf_mi.fit import uncertainty as U

NAMES = ("eta", "alpha", "beta", "kappa")
BEST = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0}
SE = {"eta": 0.01, "alpha": 0.01, "beta": 0.05, "kappa": 1.0}


def start(score, converged=True, **moved):
    return {"end": dict(BEST, **moved, k_s=0.5), "score": score, "converged": converged}


def test_chi2_quantiles():
    """CHI2_95[p-1] is the 95 % quantile of chi^2_p: for even p the closed-form CDF
    1 - exp(-x/2) sum_{k<p/2} (x/2)^k / k! is 0.95 there; for p = 1, erf(sqrt(x/2)) = 0.95."""
    assert math.erf(math.sqrt(U.CHI2_95[0] / 2)) == pytest.approx(0.95, abs=1e-12)
    for p in (2, 4, 6, 8):
        x = U.CHI2_95[p - 1] / 2
        cdf = 1 - math.exp(-x) * sum(x ** k / math.factorial(k) for k in range(p // 2))
        assert cdf == pytest.approx(0.95, abs=1e-12), p


def test_a_close_second_mode_competes_and_a_far_one_does_not():
    unc = {"std_errors": SE}
    starts = [start(100.0), start(103.0, alpha=0.30, beta=1.3), start(110.0, eta=1.40)]
    optima, thr = U.other_optima(starts, BEST, unc, NAMES)
    assert thr == pytest.approx(U.CHI2_95[3])                 # four shape parameters, no inflation
    assert [o["delta_chi2"] for o in optima] == pytest.approx([6.0, 20.0])
    assert [o["distance_se"] for o in optima] == pytest.approx([6.0, 5.0])     # max over parameters: beta 0.3/0.05
    assert [o["competing"] for o in optima] == [True, False]
    text = U.optima_text(optima, thr)
    assert "6.0 worse" in text and "alpha 0.3" in text


def test_ends_within_the_separation_are_the_same_optimum():
    unc = {"std_errors": SE}
    starts = [start(100.0), start(100.5, alpha=0.25 + 1.9 * 0.01)]
    assert U.other_optima(starts, BEST, unc, NAMES)[0] == []
    # just beyond 2 SE it is another optimum
    starts = [start(100.0), start(100.5, alpha=0.25 + 2.1 * 0.01)]
    optima, _ = U.other_optima(starts, BEST, unc, NAMES)
    assert len(optima) == 1 and optima[0]["competing"]


def test_a_start_that_did_not_converge_never_competes():
    optima, thr = U.other_optima([start(100.0), start(100.1, False, eta=1.5)], BEST, {"std_errors": SE}, NAMES)
    assert len(optima) == 1 and not optima[0]["competing"] and U.optima_text(optima, thr) is None


def test_the_threshold_follows_the_sandwich_and_the_misfit_scale():
    """With the incidental-parameter sandwich the threshold is multiplied by the largest (SE / Fisher SE)^2
    (here alpha's 2^2 = 4), and with an inflated (misfit) covariance by chi^2/dof: a mode 20 worse then
    competes (threshold 9.49 x 4 x 1.5 = 56.9)."""
    unc = {"std_errors": SE, "incidental": {"fisher_std_errors": dict(SE, alpha=0.005, beta=0.04)},
           "misfit": True, "chi2_per_dof": 1.5}
    optima, thr = U.other_optima([start(100.0), start(110.0, eta=1.40)], BEST, unc, NAMES)
    assert thr == pytest.approx(U.CHI2_95[3] * 4 * 1.5)
    assert optima[0]["competing"]


def test_parameters_without_a_standard_error_are_left_out():
    """A fixed parameter (no standard error) neither separates nor counts in the threshold's degrees of freedom."""
    se = dict(SE, kappa=None)
    optima, thr = U.other_optima([start(100.0), start(101.0, kappa=30.0)], BEST, {"std_errors": se}, NAMES)
    assert optima == [] and thr == pytest.approx(U.CHI2_95[2])
    assert U.other_optima([start(100.0)], BEST, {"std_errors": SE}, NAMES) == ([], None)


def ci_of(params, se, k=1.96):
    return {n: [params[n] - k * se[n], params[n] + k * se[n]] for n in NAMES}


def test_intervals_are_widened_over_a_competing_optimum_only():
    """The hull of the estimate's interval and, around the competing optimum, an interval of the same
    half-widths (worked out by hand here); a far (non-competing) optimum widens nothing."""
    unc = {"std_errors": SE, "ci95": ci_of(BEST, SE), "method": "Fisher"}
    optima, _ = U.other_optima([start(100.0), start(103.0, alpha=0.30, beta=1.3), start(110.0, eta=1.40)],
                               BEST, unc, NAMES)
    unc["other_optima"] = {"optima": optima}
    widened = U.widen_for_optima(unc, BEST, optima)
    assert sorted(widened) == ["alpha", "beta"]
    assert unc["ci95"]["alpha"] == pytest.approx([0.25 - 0.0196, 0.30 + 0.0196])
    assert unc["ci95"]["beta"] == pytest.approx([1.0 - 0.098, 1.3 + 0.098])
    assert unc["ci95"]["eta"] == pytest.approx([1.45 - 0.0196, 1.45 + 0.0196])   # the eta=1.40 optimum is far
    assert unc["interval_kind"] == {"eta": "fisher", "alpha": "optima", "beta": "optima", "kappa": "fisher"}
    assert unc["other_optima"]["widened"]["alpha"] == pytest.approx([0.25 - 0.0196, 0.25 + 0.0196])
    assert unc["method"] == "Fisher"          # the method text is composed by the caller (uncertainty.method_text)


def test_asymmetric_intervals_keep_their_half_widths_and_profile_kinds():
    """A profile interval (asymmetric) moves with its own lower and upper half-widths; a competing optimum
    below the estimate stretches the lower end only; parameters it does not move keep their kind."""
    ci = ci_of(BEST, SE)
    ci["kappa"] = [8.0, 14.0]                       # half-widths 2 below, 4 above
    unc = {"std_errors": SE, "ci95": ci, "interval_kind": dict.fromkeys(NAMES, "fisher") | {"eta": "profile"}}
    optima, _ = U.other_optima([start(100.0), start(101.0, kappa=5.0)], BEST, unc, NAMES)
    assert optima[0]["competing"]
    U.widen_for_optima(unc, BEST, optima)
    assert unc["ci95"]["kappa"] == pytest.approx([3.0, 14.0])
    assert unc["interval_kind"]["kappa"] == "optima" and unc["interval_kind"]["eta"] == "profile"
    # nothing competing: nothing changes
    unc2 = {"std_errors": SE, "ci95": ci_of(BEST, SE)}
    optima2, _ = U.other_optima([start(100.0), start(150.0, kappa=5.0)], BEST, unc2, NAMES)
    assert U.widen_for_optima(unc2, BEST, optima2) == [] and "interval_kind" not in unc2


def test_the_summary_marks_stretched_intervals():
    from fmbrdf_mi.fit.outputs.summary import kind_text

    entry = {"uncertainty": {"interval_kind": {"alpha": "optima", "eta": "profile", "beta": "fisher"}}}
    assert kind_text(entry, "alpha") == " (widened over another optimum)"
    assert kind_text(entry, "eta") == " (profile likelihood)"
    assert kind_text(entry, "beta") == "" and kind_text(entry, "kappa") == ""


def test_stretched_intervals_stop_at_the_bounds():
    """A competing optimum near a bound stretches the interval to the bound, not past it (alpha's lower
    bound 0.2 here: 0.21 - 0.0196 would cross it)."""
    unc = {"std_errors": SE, "ci95": ci_of(BEST, SE)}
    optima, _ = U.other_optima([start(100.0), start(102.0, alpha=0.21)], BEST, unc, NAMES)
    U.widen_for_optima(unc, BEST, optima, {"alpha": (0.2, 1.0)})
    assert unc["ci95"]["alpha"] == pytest.approx([0.2, 0.25 + 0.0196])
