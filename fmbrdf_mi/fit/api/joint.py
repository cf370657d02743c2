"""Joint fits (:func:`fit_joint`): K images of one object, each its own light, geometry and mask, sharing one
material.  The likelihood is the product of the images' (one camera: the noise models agree or are all
unknown); the paper's loss runs over the union of their pixels; ``max_pixels`` is split evenly.

    res = fit_joint([obs_1, obs_2, obs_3])
    res.images[k]["chi2_per_dof"]                # how well image k is explained
"""
from __future__ import annotations

from fmbrdf_mi.fit.api.fitting import fit
from fmbrdf_mi.fit.inputs.observations import check_observations


def fit_joint(observations, options=None, *, names=None, progress=True, powers=None, **kw):
    """:func:`~fmbrdf_mi.fit.api.fitting.fit` of a list of observations; the result adds ``images``
    (per-image diagnostics) and ``pixels`` (one array per image).

    ``options`` / keywords: :class:`~fmbrdf_mi.fit.api.fitting.FitOptions` (pixel path, ``lm`` only).
    ``names``: the images' labels (default ``image0``, ...).  ``free_power=True`` estimates the light powers
    of images 1 .. K-1 relative to image 0's (:mod:`fmbrdf_mi.fit.problem.free_power`; the result's
    ``powers``); ``powers``: the relative powers the irradiances already include (default 1 each), where the
    search starts and what the fitted ones are reported against.
    """
    return fit(check_observations(observations, "fit_joint()", least=0), options, names=names, progress=progress,
               powers=powers, **kw)

