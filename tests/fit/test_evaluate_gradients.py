"""Derivatives of the fit's loss (eq:optimization) against central finite differences.

Both derivatives the optimisers use are checked for each of the six paper
parameters: the reverse-mode gradient through the BSDF (Adam) and the
gradient 2 J^T r from the forward-mode Jacobian (Levenberg-Marquardt).  The
observation comes from other parameters, so the loss is far from zero;
steps of 1 % of each value keep float32 round-off (~1e-6 relative in the
loss) and truncation well below the 2 % tolerance.  Each check runs without
and with a known camera noise (the DoLP term then compares with the mean
DoLP a noisy camera measures, fmbrdf_mi.sensor.rice).
"""
import numpy as np
import pytest

TRUE = {"eta": 1.5, "alpha": 0.25, "beta": 2.2, "kappa": 10.0, "k_s": 1.0, "r_k": 0.8}
# alpha = 0.31: the BSDF's own reverse-mode alpha derivative is NaN at pixels whose view or
# light direction is within ~2 degrees of the normal; the fit leaves those pixels out.
AT = {"eta": 1.65, "alpha": 0.31, "beta": 1.7, "kappa": 20.0, "k_s": 1.3, "r_k": 0.1}
NAMES = list(AT)


@pytest.fixture(scope="module", params=["noise-free", "known noise"])
def problem(request):
    from fmbrdf_mi.fit import FitOptions, Observation, predict_image, usable_pixels
    from fmbrdf_mi.fit.evaluate.models import FMBRDF
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
    from fmbrdf_mi import geometry as G
    from fmbrdf_mi.fit.objectives import loss as L
    from fmbrdf_mi.fit.problem.problem import Problem

    n, m, v = G.sphere_normals((32, 32), (16, 16), 15)
    light = [0.4, 0.3, 1.0]
    obs = Observation(np.ones((3, 32, 32)), m, n, v, light)
    obs = Observation(predict_image("fmbrdf", TRUE, obs), m, n, v, light)
    idx = usable_pixels(obs, FitOptions())
    var = None
    if request.param == "known noise":  # S1, S2 noise of 3 % of S0: the DoLP model becomes a Rice mean
        var = (0.03 * obs.stokes[0].reshape(-1)[idx]) ** 2
    target = L.Target.from_stokes(obs.stokes.reshape(3, -1)[:, idx], lin_variance=var)
    ev = PixelEvaluator(FMBRDF, n.reshape(-1, 3)[idx], v.reshape(-1, 3)[idx], light)
    pb = Problem(FMBRDF, ev, target)
    shape, a_s, a_b = Parameters(FMBRDF).split(AT)
    from fmbrdf_mi.fit.evaluate.models import State

    st = State(shape, a_s, a_b)
    pb.set_weights(pb.parts(st), st)
    assert 0 < pb.obj.outliers.sum() < len(pb.obj.outliers)  # both kinds of pixels present
    return pb


def _loss_at(pb, params):
    from fmbrdf_mi.fit.evaluate.models import State

    st = State(*pb.params.split(params))
    return pb.obj.value(pb.parts(st), st)


def _paper_gradient(g, params):
    """d loss / d (eta, alpha, beta, kappa, k_s, r_k) from derivatives w.r.t. shape, a_s, a_b."""
    out = {n: g[n] for n in ("eta", "alpha", "beta", "kappa")}
    out["k_s"] = g["a_s"] + params["r_k"] * g["a_b"]
    out["r_k"] = params["k_s"] * g["a_b"]
    return out


@pytest.fixture(scope="module")
def finite_differences(problem):
    fd = {}
    for name in NAMES:
        h = 1e-2 * AT[name]
        up = _loss_at(problem, {**AT, name: AT[name] + h})
        down = _loss_at(problem, {**AT, name: AT[name] - h})
        fd[name] = (up - down) / (2 * h)
    return fd


def test_reverse_mode_gradient_matches_finite_differences(variant, problem, finite_differences):
    from fmbrdf_mi.fit.evaluate.models import State
    from fmbrdf_mi.fit.solve.optimise import loss_and_grad_reverse

    st = State(*problem.params.split(AT))
    f, g = loss_and_grad_reverse(problem, st)
    assert f == pytest.approx(_loss_at(problem, AT), rel=1e-4)
    grad = _paper_gradient(g, AT)
    for name in NAMES:
        assert abs(finite_differences[name]) > 1e-4, name
        assert grad[name] == pytest.approx(finite_differences[name], rel=2e-2), name


def test_forward_mode_jacobian_gradient_matches_finite_differences(variant, problem, finite_differences):
    from fmbrdf_mi.fit.evaluate.models import State

    st = State(*problem.params.split(AT))
    z = problem.to_z(st)
    r, J = problem.residuals_and_jacobian(problem.parts(st, jac=True), st, z)
    gz = 2 * J.T @ r
    k = len(problem.names)
    g = {n: gz[j] / problem.bounds.derivative(n, z[j]) for j, n in enumerate(problem.names)}
    g["a_s"], g["a_b"] = gz[k] / st.a_s, gz[k + 1] / st.a_b
    grad = _paper_gradient(g, AT)
    for name in NAMES:
        assert grad[name] == pytest.approx(finite_differences[name], rel=2e-2), name
