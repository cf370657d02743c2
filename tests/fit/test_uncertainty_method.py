"""fit.json's ``uncertainty.method``: composed once from the mechanisms applied (``uncertainty.method_text``).

The expected lines are written out here, not produced by the code under test: the estimator with its
qualifiers, then the notes, in one order whatever the order in which the mechanisms were applied.
"""
import pytest

from fmbrdf_mi.fit import uncertainty as U


def test_the_estimator_and_its_scale():
    assert U.method_text([("fisher", ""), ("known-noise", "")]) == "inverse Fisher information (known camera noise)"
    assert U.method_text([("fisher", ""), ("known-noise", ""), ("misfit", "")]) == (
        "inverse Fisher information (known camera noise), inflated by chi^2/dof (misfit)")
    assert U.method_text([("fisher", ""), ("estimated-noise", "")]) == (
        "inverse Fisher information, noise level estimated from the residuals")
    assert U.method_text([("paper-sandwich", ""), ("demosaic", "")]) == (
        "sandwich estimate for the paper's loss, leave-neighbourhood-out residuals (CR3), with the correlation "
        "of neighbouring pixels (demosaicking)")
    assert U.method_text([("not-converged", "")]) == "not computed: the fit did not converge"


def test_notes_follow_in_one_order_whatever_the_order_applied():
    applied = [("quadrature", "4 x 4 points per raw pixel (2 x 2 would bias alpha by about +0.80 SE)"),
               ("optima", ""), ("incidental-capped", 2), ("profile", ""), ("known-noise", ""), ("incidental", "")]
    want = ("incidental-parameter sandwich H^-1 (J^T J) H^-1, H = J^T J - C (the per-pixel albedos' noise removed "
            "from the information) (known camera noise); H not positive definite in 2 direction(s): their "
            "inflation capped at 10x the Fisher standard error; profile-likelihood 95 % intervals where the "
            "Fisher ones fail (interval_kind); 95 % intervals widened over a competing optimum of the likelihood "
            "(interval_kind 'optima', other_optima); pixel-area quadrature 4 x 4 points per raw pixel (2 x 2 "
            "would bias alpha by about +0.80 SE)")
    assert U.method_text(applied) == want
    assert U.method_text(applied[::-1]) == want


def test_unreliable_sandwich_note_follows_the_capped_one():
    applied = [("incidental-unreliable", "0.93"), ("known-noise", ""), ("incidental", ""), ("incidental-capped", 1)]
    want = ("incidental-parameter sandwich H^-1 (J^T J) H^-1, H = J^T J - C (the per-pixel albedos' noise removed "
            "from the information) (known camera noise); H not positive definite in 1 direction(s): their "
            "inflation capped at 10x the Fisher standard error; in one direction 0.93 of the information J^T J "
            "is the per-pixel albedos' noise (above 0.5): these standard errors and intervals understate the "
            "spread over captures and are not confidence intervals; fit several lights of the same view")
    assert U.method_text(applied) == want


def test_one_estimator_and_known_mechanisms_only():
    with pytest.raises(ValueError, match="one estimator"):
        U.method_text([("fisher", ""), ("posterior", "")])
    with pytest.raises(ValueError, match="one estimator"):
        U.method_text([("known-noise", "")])
    with pytest.raises(ValueError, match="known mechanisms"):
        U.method_text([("fisher", ""), ("bootstrap", "")])
