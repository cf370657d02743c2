"""Joint fits: K images of one object (different lights, possibly different views) sharing one material.

    from fmbrdf_mi.fit.api.joint import fit_joint
    res = fit_joint([obs_1, obs_2, obs_3])       # Observations: each its own light, geometry, mask
    res.params, res.std_errors                   # the six parameters, from the joint likelihood
    res.images[k]["chi2_per_dof"]                # how well image k is explained

Each image is an :class:`~fmbrdf_mi.fit.inputs.observations.Observation` with
its own light direction, irradiance (image k's light power relative to the
others; the albedos absorb a common factor), geometry, mask, samples and
footprint; they share the material (eta, alpha, beta, kappa, k_s, r_k).  The
images are independent measurements, so the likelihood of all is the product
of theirs (one camera: the noise models must agree, or be unknown for all);
the paper's loss and its variants are computed over the union of their
pixels.  All images are evaluated in one BSDF evaluation, so K images cost
about as much as one with K times the pixels.  The standard errors are the
inverse of the joint Fisher information (:mod:`fmbrdf_mi.fit.uncertainty`).
``max_pixels`` is split evenly between the images (image k's subset drawn
with seed ``seed + k``).  With ``free_power`` the relative powers of images
1 .. K-1 are estimated too (:mod:`fmbrdf_mi.fit.problem.free_power`).
"""
from __future__ import annotations

from fmbrdf_mi.fit.api.fitting import fit
from fmbrdf_mi.fit.inputs.observations import check_observations


def fit_joint(observations, options=None, *, names=None, progress=True, powers=None, **kw):
    """Estimate one material from several :class:`Observation` s of the same object: :func:`fit` of the list.

    Returns a :class:`~fmbrdf_mi.fit.result.FitResult` with ``images``
    (per-image diagnostics) and ``pixels`` (one array per image).

    ``options`` / keywords: :class:`~fmbrdf_mi.fit.api.fitting.FitOptions` (the
    pixel path and the Levenberg-Marquardt optimiser).  ``names``: labels of
    the images in the result (default ``image0``, ...).

    ``free_power=True`` (an option) estimates the light powers of images
    1 .. K-1 relative to image 0's (:mod:`fmbrdf_mi.fit.problem.free_power`);
    ``powers``: the relative powers the observations' irradiances already
    include (default 1 each): image 0's stays fixed, the others are where
    the search starts (``power_start="given"``) and what the fitted powers
    are reported against.  The result's ``powers`` and each
    image's ``power`` / ``power_se`` then hold them.
    """
    return fit(check_observations(observations, "fit_joint()", least=0), options, names=names, progress=progress,
               powers=powers, **kw)

