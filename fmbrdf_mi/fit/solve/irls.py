"""The one reweighting loop: minimise with the objective's weights frozen, refresh them, repeat until they settle.

Iteratively reweighted least squares: the likelihood's variances come from
the model's prediction (:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`),
the paper's loss has its inlier / outlier split, the normal refinement its
variances and prior scale.  A round is ``before`` (refresh the weights from
the current estimate; says "settled" when they no longer move it), then the
minimisation (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`, or Adam).
The fits differ only in those two.
"""
from __future__ import annotations


def reweighted(x, minimise, *, rounds, before):
    """At most ``rounds`` rounds from ``x``; returns (x, converged of the last minimisation, settled, rounds run).

    ``before(x, k)`` (k = 0, 1, ...) refreshes the weights and returns True when they are settled (the loop
    stops there); ``minimise(x, k)`` returns (x, converged).  A minimisation that does not converge (a time
    or iteration limit) ends the rounds.
    """
    converged, k = False, 0
    for k in range(rounds):
        if before(x, k):
            return x, converged, True, k
        x, converged = minimise(x, k)
        if not converged:
            break
    return x, converged, False, k + 1
