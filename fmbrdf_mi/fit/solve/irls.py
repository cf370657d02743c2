"""The one reweighting loop: minimise with the objective's weights frozen, refresh them, repeat until they settle.

Iteratively reweighted least squares: the likelihood's variances come from
the model's prediction (:class:`~fmbrdf_mi.fit.objectives.objective.LikelihoodObjective`),
the paper's loss has its inlier / outlier split, the normal refinement its
variances and prior scale.  A round is ``before`` (refresh the weights from
the current estimate; says "settled" when they no longer move it), the
minimisation (:func:`fmbrdf_mi.fit.solve.lm.levenberg_marquardt`, or Adam),
then ``after`` (where a fit refreshes after minimising: the colour fit, whose
test of a settled round is its step in standard errors).  The fits differ
only in those hooks.
"""
from __future__ import annotations


def reweighted(x, minimise, *, rounds, before=None, after=None, stop_unconverged=True):
    """At most ``rounds`` rounds from ``x``; returns (x, converged of the last minimisation, settled, rounds run).

    ``before(x, k)`` and ``after(x, k)`` (k = 0, 1, ...) refresh the weights
    and return True when they are settled (the loop stops there);
    ``minimise(x, k)`` returns (x, converged).  ``stop_unconverged``: stop
    after a minimisation that did not converge (a time or iteration limit).
    """
    converged, k = False, 0
    for k in range(rounds):
        if before is not None and before(x, k):
            return x, converged, True, k
        x, converged = minimise(x, k)
        if stop_unconverged and not converged:
            break
        if after is not None and after(x, k):
            return x, converged, True, k + 1
    return x, converged, False, k + 1
