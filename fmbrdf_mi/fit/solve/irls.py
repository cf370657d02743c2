"""The one reweighting loop (IRLS): minimise with the objective's weights frozen, refresh them, repeat.

The fits differ only in ``before`` (weights from the estimate: the likelihood's model variances
(:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`), the paper's inlier / outlier split) and
``minimise`` (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`, or Adam).
"""
from __future__ import annotations


def reweighted(x, minimise, *, rounds, before):
    """At most ``rounds`` rounds from ``x``; returns (x, converged of the last minimisation, settled, rounds run).

    ``before(x, k)`` refreshes the weights, True when settled (the loop stops); ``minimise(x, k)`` returns
    (x, converged), and a minimisation that does not converge ends the rounds.
    """
    converged, k = False, 0
    for k in range(rounds):
        if before(x, k):
            return x, converged, True, k
        x, converged = minimise(x, k)
        if not converged:
            break
    return x, converged, False, k + 1
