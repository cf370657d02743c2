"""Joint fits of several images of one object (fmbrdf_mi.fit.api.fitting.fit_joint) and the loss variants (loss_variants.py).

References are independent of the code under test: per-image problems built
by the single-image fit (whose Jacobian is checked against finite
differences in test_objectives_likelihood.py), brute-force NumPy losses, and
noise-free images whose optimum is the truth.
"""
import math

import numpy as np
import pytest

TRUE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)]
NEAR = {"eta": 1.5, "alpha": 0.22, "beta": 1.2, "kappa": 14.0, "k_s": 0.8, "r_k": 0.6}


@pytest.fixture(scope="module")
def variant():
    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    set_variant()


def _clean(res=24, lights=LIGHTS, params=TRUE, irradiances=None):
    """Noise-free Stokes images at the pixel centres of an orthographic sphere, one per light."""
    from fmbrdf_mi.fit.evaluate.predict import predict_image
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G

    n, m, v = G.sphere_normals((res, res), (res / 2, res / 2), res / 2 - 1)
    out = []
    for k, l in enumerate(lights):
        o = ob.Observation(np.ones((3, res, res)), m, n, v, l, 1.0 if irradiances is None else irradiances[k])
        o.stokes = predict_image("fmbrdf", params, o)
        out.append(o)
    return out


def _captures(res=16, seed=0, lights=LIGHTS):
    from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere
    from fmbrdf_mi.sensor.camera import CameraModel

    return [capture_observation(ideal_sphere(TRUE, res=res, light=l), CameraModel(), seed=seed + k)[0]
            for k, l in enumerate(lights)]


def test_joint_fit_of_noise_free_images_recovers_the_truth(variant):
    """Three lights, different relative powers, from a start 10-40 % off: the optimum of noise-free
    data is the truth, to the float32 precision of the BSDF (1e-4 relative).  (The likelihood on
    noisy captures: test_joint_fit_per_image_diagnostics_and_errors.)"""
    from fmbrdf_mi.fit.api.fitting import fit_joint

    obs = _clean(res=16, irradiances=[1.0, 0.5, 2.0])
    for loss in ("paper",):
        res = fit_joint(obs, loss=loss, init=NEAR, progress=False, max_pixels=None)
        assert res.converged, loss
        for k, v in TRUE.items():
            assert abs(res.params[k] - v) <= 1e-4 * max(v, 1.0), (loss, k, res.params[k])
        assert len(res.images) == 3 and all(im["intensity_rel_rmse"] < 1e-4 for im in res.images)


def test_joint_fisher_information_is_the_sum_of_the_images(variant):
    """The joint likelihood of independent images: J^T J of the joint fit equals the sum of the
    single-image J^T J at the same parameters (each built by the one-image code path), so the
    reported joint covariance is the inverse of that sum (to float32 noise, 1e-6 relative)."""
    from fmbrdf_mi.fit import FitOptions
    from fmbrdf_mi.fit import uncertainty as U
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, State
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.problem.data import prepare
    from fmbrdf_mi.fit.problem.problem import Problem

    obs = _captures(res=12)
    opts = FitOptions(loss="likelihood", max_pixels=None)
    st = State(*Parameters(FMBRDF).split(NEAR))
    F = []
    for o in obs:
        one = prepare([o], opts, "likelihood", single=True)    # each image as a single-image fit has it
        obj = one.objective
        pb = Problem(FMBRDF, one.evaluator, obj)
        obj.refresh(pb.parts(st), st)
        r, J = pb.residuals_and_jacobian(pb.parts(st, jac=True), st, pb.to_z(st))
        F.append(U.jacobian_in_reported(pb, st, J)[1])
    F_sum = sum(j.T @ j for j in F)
    data = prepare(obs, opts, "likelihood")
    obj, ev = data.objective, data.evaluator
    pb = Problem(FMBRDF, ev, obj)
    obj.refresh(pb.parts(st), st)
    r, J = pb.residuals_and_jacobian(pb.parts(st, jac=True), st, pb.to_z(st))
    names, Jt = U.jacobian_in_reported(pb, st, J)
    F_joint = Jt.T @ Jt
    d = np.sqrt(np.outer(np.diag(F_sum), np.diag(F_sum)))
    assert np.abs(F_joint - F_sum).max() / d.max() < 1e-5
    c = U.covariance(pb, st, J, r)
    cov, info = c.cov, dict(c.info, method=c.method)
    # NEAR is not the optimum of these captures: chi^2/dof is far above 1 there, so the covariance is the
    # inverse information inflated by chi^2/dof (the misfit rule), and says so
    assert info["misfit"] and "inflated" in info["method"]
    np.testing.assert_allclose(np.diag(cov) / info["chi2_per_dof"], np.diag(np.linalg.inv(F_sum)), rtol=1e-4)
    assert "Fisher" in info["method"]


def test_joint_fit_per_image_diagnostics_and_errors(variant):
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.api.fitting import fit_joint
    from fmbrdf_mi.sensor.noise import NoiseModel

    obs = _captures(res=12)
    res = fit_joint(obs, init=NEAR, intervals="fisher", progress=False, names=["a", "b", "c"])
    assert res.objective == "likelihood" and res.converged
    # the camera noise is right: every image's chi^2 / dof is ~1 (4 n samples: sd sqrt(2 / 4n) < 0.06)
    for im in res.images:
        assert abs(im["chi2_per_dof"] - 1.0) < 0.3, im
    assert [im["name"] for im in res.images] == ["a", "b", "c"]
    # the estimate within 4.5 reported standard errors of the truth (two-sided 7e-6 per parameter)
    for k, v in TRUE.items():
        assert abs(res.params[k] - v) < 4.5 * res.std_errors[k], (k, res.params[k], res.std_errors[k])
    assert sum(im["n_pixels"] for im in res.images) == res.n_pixels
    obs[1].noise = NoiseModel(gain=obs[0].noise.gain * 2, read_noise=obs[0].noise.read_noise)
    with pytest.raises(InputError, match="one camera"):
        fit_joint(obs, progress=False)
    obs[1].noise = None
    with pytest.raises(InputError, match="known for some"):
        fit_joint(obs, progress=False)
    with pytest.raises(InputError, match="no images"):
        fit_joint([], progress=False)


# ---------------------------------------------------------------- loss variants
def test_loss_variants_values_against_numpy(variant):
    """intensity: (1/M) sum ((I - Ibar) / mean Ibar)^2; dolp: the paper's weighted DoLP MSE plus
    ((mean I - mean Ibar) / mean Ibar)^2; both computed here from predicted Stokes by hand."""
    from fmbrdf_mi.fit.api.fitting import FitOptions
    from fmbrdf_mi.fit.evaluate.models import FMBRDF, State
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.objectives import loss as L
    from fmbrdf_mi.fit.problem.data import prepare, select_pixels
    from fmbrdf_mi.fit.problem.problem import Problem

    o = _clean(res=16)[0]
    rng = np.random.default_rng(1)
    o.stokes = o.stokes * (1 + 0.05 * rng.standard_normal(o.stokes.shape))
    opts = FitOptions(max_pixels=None)
    idx, _ = select_pixels(o, opts)
    st = State(*Parameters(FMBRDF).split(NEAR))
    obs_s = o.stokes.reshape(3, -1)[:, idx]
    ibar = obs_s[0]
    rhobar = np.hypot(obs_s[1], obs_s[2]) / ibar
    for loss in ("intensity", "dolp"):
        one = prepare([o], opts, loss, single=True)
        obj = one.objective
        pb = Problem(FMBRDF, one.evaluator, obj)
        parts = pb.parts(st)
        obj.refresh(parts, st)
        s = st.a_s * parts.surface + st.a_b * parts.body
        i, rho = s[0], np.hypot(s[1], s[2]) / s[0]
        if loss == "intensity":
            ref = np.mean(((i - ibar) / ibar.mean()) ** 2)
        else:
            valid = ibar > 0.02 * np.percentile(ibar, 99)
            out = (st.a_s * parts.surface[0] > st.a_b * parts.body[0]) & valid
            w = valid.astype(float)
            if out.any():
                w[out] = (valid & ~out).sum() / out.sum()
            ref = np.sum(w * (rho - rhobar) ** 2) / w.sum() + ((i.mean() - ibar.mean()) / ibar.mean()) ** 2
        assert math.isclose(obj.value(parts, st), ref, rel_tol=1e-9), loss
        # the Jacobian rows are those of the paper's objective: a directional derivative check
        z = pb.to_z(st)
        r, J = pb.residuals_and_jacobian(pb.parts(st, jac=True), st, z)
        dz = 1e-3 * rng.standard_normal(len(z))
        s1, s2 = pb.from_z(z + dz), pb.from_z(z - dz)
        fd = (obj.residuals(pb.parts(s1), s1) - obj.residuals(pb.parts(s2), s2)) / 2
        assert np.linalg.norm(J @ dz - fd) < 0.03 * np.linalg.norm(fd), loss


def test_loss_variants_recover_noise_free_truth_and_dolp_ignores_the_intensity_shape(variant):
    """On a noise-free Stokes image both variants recover the truth.  DoLP only: k_s is set by the mean
    intensity alone, so an image whose intensity is scaled by 2 gives the same shape parameters and r_k
    and twice k_s."""
    from fmbrdf_mi.fit import fit

    o = _clean(res=20, lights=LIGHTS[:1])[0]
    for loss in ("intensity", "dolp"):
        r = fit(o, loss=loss, init=NEAR, progress=False, max_pixels=None)
        assert r.converged and r.objective == loss
        for k, v in TRUE.items():
            assert abs(r.params[k] - v) <= 2e-4 * max(v, 1.0), (loss, k, r.params[k])
    o.stokes = o.stokes * 2
    r2 = fit(o, loss="dolp", init=NEAR, progress=False, max_pixels=None)
    for k, v in TRUE.items():
        assert abs(r2.params[k] - v * (2 if k == "k_s" else 1)) <= 4e-4 * max(v, 1.0), (k, r2.params[k])


def test_loss_variant_options_are_checked():
    from fmbrdf_mi.fit import InputError
    from fmbrdf_mi.fit.api.options import check_fit_options

    check_fit_options(loss="dolp")
    with pytest.raises(InputError, match="loss"):
        check_fit_options(loss="radiance")


def test_joint_fit_of_different_views(variant):
    """Each image its own view (pixel grid, sphere position and size, orthographic or perspective view
    directions): noise-free images give back the truth (float32 precision of the BSDF, 1e-4)."""
    from fmbrdf_mi.fit.api.fitting import fit_joint
    from fmbrdf_mi.fit.evaluate.predict import predict_image
    from fmbrdf_mi.fit.inputs import observations as ob
    from fmbrdf_mi import geometry as G

    views = [((16, 16), (8, 8), 7, "orthographic", None, LIGHTS[0]),
             ((14, 20), (11, 6.5), 6, "orthographic", None, LIGHTS[1]),
             ((18, 18), (9, 9), 8, "perspective", 30.0, LIGHTS[2])]
    obs = []
    for shape, c, r, cam, fov, l in views:
        n, m, v = G.sphere_normals(shape, c, r, cam, fov)
        o = ob.Observation(np.ones((3,) + shape), m, n, v, l)
        o.stokes = predict_image("fmbrdf", TRUE, o)
        obs.append(o)
    res = fit_joint(obs, loss="paper", init=NEAR, progress=False, max_pixels=None)
    assert res.converged
    for k, v in TRUE.items():
        assert abs(res.params[k] - v) <= 1e-4 * max(v, 1.0), (k, res.params[k])
    assert [im["n_pixels"] for im in res.images] == [len(p) for p in res.pixels]


def test_one_image_is_the_list_of_one():
    """fit(obs) and fit([obs]) run the same data path (problem.data.prepare): the same estimate, standard
    errors and chi^2 to the last bit, on a noisy capture (likelihood) and a noise-free Stokes image (paper's loss);
    the list's result adds the per-image block.  (The post-fit checks are functions of the result and the problem,
    which are equal.)"""
    from fmbrdf_mi.fit import fit

    cases = [(_captures(res=12)[0], {"intervals": "fisher"}),
             (_clean(res=16, lights=LIGHTS[:1])[0], {"loss": "paper", "intervals": "fisher"})]
    for o, kw in cases:
        a = fit(o, progress=False, init=NEAR, **kw)
        b = fit([o], progress=False, init=NEAR, **kw)
        assert a.converged and b.converged
        assert a.params == b.params and a.std_errors == b.std_errors and a.loss == b.loss, kw
        assert a.uncertainty.get("ci95") == b.uncertainty.get("ci95"), kw
        assert a.images is None and len(b.images) == 1 and b.images[0]["n_pixels"] == a.n_pixels
        assert list(b.pixels[0]) == list(a.pixels)
