"""The one reweighting loop (fmbrdf_mi/fit/solve/lm.py): the order of its hooks and its three ways to stop.

The fits' own IRLS behaviour (estimates, standard errors) is pinned by the
regression record (tools/record_fits.py) and the coverage tests; here the
loop is run on a fixed-point problem with a known answer: reweighted least
squares for the median of a sample (weights 1 / |x - m|), whose limit is the
sample median.
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.solve.lm import reweighted


def test_reweighted_median_converges_to_the_median():
    x = np.array([0.0, 1.0, 2.0, 7.0, 40.0])
    w = {"w": np.ones_like(x)}

    def before(m, k):
        w["w"] = 1.0 / np.maximum(np.abs(x - m), 1e-12)
        return False

    def minimise(m, k):
        return float(np.sum(w["w"] * x) / np.sum(w["w"])), True

    m, converged, settled, n = reweighted(float(np.mean(x)), minimise, rounds=500, before=before)
    assert converged and not settled and n == 500
    assert abs(m - np.median(x)) < 1e-6


def test_hook_order_and_stops():
    log = []

    def before(x, k):
        log.append(("before", k))
        return k == 2            # settled before the third minimisation

    def minimise(x, k):
        log.append(("min", k))
        return x + 1, True

    x, converged, settled, n = reweighted(0, minimise, rounds=10, before=before)
    assert (x, converged, settled, n) == (2, True, True, 2)
    assert log == [("before", 0), ("min", 0), ("before", 1), ("min", 1), ("before", 2)]

    # a minimisation that does not converge ends the rounds
    x, converged, settled, n = reweighted(0, lambda x, k: (x + 1, False), rounds=5, before=lambda x, k: False)
    assert (x, converged, settled, n) == (1, False, False, 1)
