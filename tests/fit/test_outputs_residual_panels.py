"""The "fitted - observed" panels of the fit's figures (fmbrdf_mi.fit.outputs.plots).

An exact image of the model (every object pixel at its centre) predicted
with the true parameters has no misfit: on every pixel the panel shows, the
residual is zero to float32 precision.  The object's pixels the fit does not
use differ: unlit ones carry noise (their DoLP is noise), rim pixels are
partly covered (here: half their value), and those are masked, so the panel
shows the fit's own pixel set (usable_pixels), not the whole mask.
"""
import numpy as np
import pytest

TRUE = {"eta": 1.5, "alpha": 0.25, "beta": 2.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.8}
LIGHT = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])


@pytest.fixture(scope="module")
def exact_fit():
    from fmbrdf_mi.fit import FitOptions, Observation, predict_image, usable_pixels
    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G

    set_variant()
    n, m, v = G.sphere_normals((32, 32), (16, 16), 14)
    exact = predict_image("fmbrdf", TRUE, Observation(np.ones((3, 32, 32)), m, n, v, LIGHT))
    stokes = exact.copy()
    rng = np.random.default_rng(1)
    unlit = m & (exact[0] <= 1e-3 * exact[0].max())
    stokes[:, unlit] = np.abs(rng.normal(0, 1e-3, (3, unlit.sum()))) * [[3.0], [1.0], [1.0]]
    rim = m & ~ob.erode(m, 1)
    stokes[:, rim] *= 0.5
    obs = Observation(stokes, m, n, v, LIGHT)
    idx = usable_pixels(obs, FitOptions())
    pred = predict_image("fmbrdf", TRUE, obs, idx)
    return obs, idx, pred, unlit, rim


def test_residual_is_zero_on_the_shown_pixels_and_the_others_are_masked(variant, exact_fit):
    from fmbrdf_mi import stokes_io
    from fmbrdf_mi.fit.outputs.plots import residuals, shown_pixels

    obs, idx, pred, unlit, rim = exact_fit
    shown = shown_pixels(obs.stokes, pred, obs.mask, idx)
    used = np.zeros(obs.mask.size, bool)
    used[idx] = True
    used = used.reshape(obs.mask.shape)
    np.testing.assert_array_equal(shown["intensity"], used)
    assert shown["DoLP"].sum() > 0.5 * used.sum() and not (shown["DoLP"] & ~used).any()
    res = residuals(obs.stokes, pred, obs.mask, idx)
    i_scale = np.percentile(obs.stokes[0][used], 99)
    for name, tol in (("intensity", 1e-5 * i_scale), ("DoLP", 1e-5)):
        r, _ = res[name]
        assert np.all(np.isnan(r[~shown[name]])), name
        assert np.nanmax(np.abs(r[shown[name]])) < tol, (name, np.nanmax(np.abs(r)))
    # what the panel showed before: the object's unused pixels (unlit, rim) differ by far more
    assert unlit.any() and rim.any() and not (used & (unlit | rim)).any()
    raw = np.abs(stokes_io.dolp(pred) - stokes_io.dolp(obs.stokes))
    assert np.nanmax(raw[unlit]) > 0.3 and np.nanmax(np.abs(pred[0] - obs.stokes[0])[rim]) > 0.05 * i_scale


def test_residual_in_noise_units(variant, exact_fit):
    """With var(S1) = var(S2) known, the intensity residual is in units of sqrt(var / 2), the DoLP's in sigma / S0."""
    from fmbrdf_mi.fit.outputs.plots import residuals

    obs, idx, pred, unlit, rim = exact_fit
    shifted = pred.copy()
    shifted[0] = pred[0] + 0.01
    var = np.full(obs.mask.shape, 0.02 ** 2)
    r, unit = residuals(obs.stokes, shifted, obs.mask, idx, lin_variance=var)["intensity"]
    ref, _ = residuals(obs.stokes, shifted, obs.mask, idx)["intensity"]
    assert unit == "noise s.d."
    np.testing.assert_allclose(r[np.isfinite(r)], ref[np.isfinite(ref)] / (0.02 / np.sqrt(2)), rtol=1e-12)


def test_plot_images_writes_with_hatched_unused_pixels(variant, exact_fit, tmp_path):
    from fmbrdf_mi.fit.outputs.plots import plot_images

    obs, idx, pred, unlit, rim = exact_fit
    plot_images(obs.stokes, pred, obs.mask, str(tmp_path / "images.png"), pixels=idx)
    assert (tmp_path / "images.png").stat().st_size > 0
