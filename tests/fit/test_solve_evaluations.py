"""What a fit's model evaluations cost: Levenberg-Marquardt evaluates a trial after an accepted step with the
derivatives its linearisation needs when it is accepted too, a trial after a rejected one without, and the pixel evaluator's chunks give the
same numbers as one evaluation of every pixel, in chunks large enough that the tables' per-chunk rebuild
does not dominate (:class:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator`)."""
import dataclasses

import numpy as np
import pytest

from conftest import textured_capture

from fmbrdf_mi.fit.api.options import FitOptions
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.problem.data import prepare
from fmbrdf_mi.fit.solve import optimise as O

SHAPE = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
START = dict(eta=1.6, alpha=0.4, beta=1.4, kappa=8.0)
RES = 16


@pytest.fixture(scope="module")
def obs():
    return textured_capture(SHAPE, RES, seed=5)


def counted_problem(obs, plain_trials=False):
    """A fresh per-pixel problem whose evaluator records every evaluation (shape values, with derivatives);
    ``plain_trials``: LM's trials evaluated without derivatives (each accepted point evaluated again)."""
    opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=None)
    data = prepare([obs], opts, "likelihood", single=True)
    problem = data.problem(get_model(opts.model), opts.bounds, None, opts.fixed, None)
    if plain_trials:
        base = type(problem)

        class Plain(base):
            def closed_form(self, shape, jac=False):
                return base.closed_form(self, shape)

        problem.__class__ = Plain
    calls, ev = [], problem.ev
    evaluate = ev.parts

    def parts(values, wrt=()):
        calls.append((tuple(float(values[n]) for n in problem.params.shape_names), bool(wrt)))
        return evaluate(values, wrt)

    ev.parts = parts
    st = problem.closed_form(START)[0]
    problem.set_weights(problem.parts(st), st)
    return problem, st, calls


def test_lm_evaluates_derivatives_once_per_point_and_iterates_as_before(obs):
    """A trial after an accepted step comes with its derivatives (accepted, it is linearised from the same
    evaluation), one after a rejected step without (accepted, it is evaluated again with them): no point is
    evaluated twice with derivatives, and the iterates are those of plain trials, number for number."""
    problem, st, calls = counted_problem(obs)
    ref, st_ref, ref_calls = counted_problem(obs, plain_trials=True)
    del calls[:], ref_calls[:]
    end = O.levenberg_marquardt(problem, st, max_iter=8)
    end_ref = O.levenberg_marquardt(ref, st_ref, max_iter=8)
    assert end[1] == end_ref[1] and end[0].shape == end_ref[0].shape
    assert np.array_equal(end[0].a_s, end_ref[0].a_s) and np.array_equal(end[5], end_ref[5])
    with_jac = [p for p, jac in calls if jac]
    assert len(with_jac) == len(set(with_jac)), "a point evaluated twice with derivatives"
    first = {}
    for p, jac in calls:
        assert p not in first or (not first[p] and jac), "only a value-only trial is evaluated again"
        first.setdefault(p, jac)
    assert not all(first.values()), "every trial carried derivatives, also after a rejected step"
    accepted = {p for p, jac in ref_calls if jac} - {ref_calls[0][0]}     # the start is linearised too
    saved = {p for p in accepted if first.get(p)}      # accepted trials that carried their derivatives
    assert len(saved) >= 2 and len(ref_calls) - len(calls) == len(saved)


def test_chunked_evaluation_equals_one_evaluation():
    """The evaluator's chunks (here of 5 pixels) reproduce one evaluation of all pixels bit for bit, values
    and derivatives."""
    rng = np.random.default_rng(2)
    n = rng.normal(size=(23, 3)) * [0.4, 0.4, 0.0] + [0, 0, 1.0]
    v = np.tile([0.2, -0.1, 1.0], (23, 1))
    model = get_model("fmbrdf")
    whole = PixelEvaluator(model, n, v, (-0.4, 0.3, 1.0))
    chunked = PixelEvaluator(model, n, v, (-0.4, 0.3, 1.0))
    chunked.CHUNK_DIRECTIONS = 5
    assert len(chunked._chunks()) == 5 and len(whole._chunks()) == 1
    a, b = (e.parts(SHAPE, ("eta", "kappa")) for e in (whole, chunked))
    for x, y in [(a.surface, b.surface), (a.body, b.body)] + [(a.d_surface[k], b.d_surface[k]) for k in a.d_surface]:
        assert np.array_equal(x, y)


def test_a_chunk_holds_more_directions_than_twice_the_tables_texels():
    """Each chunk of an evaluation with derivatives rebuilds the BSDF's tables and carries every
    parameter's tangent through all their texels: a chunk of fewer directions than that spends more on the
    tables than on its pixels."""
    import drjit as dr

    ev = PixelEvaluator(get_model("fmbrdf"), [[0, 0, 1.0]], [[0.2, 0, 1.0]], (-0.4, 0.3, 1.0))
    ev.parts(SHAPE, ("eta",))
    assert PixelEvaluator.CHUNK_DIRECTIONS >= 2 * dr.width(ev.bsdf.table.values)


def test_a_joint_subsample_takes_the_same_pixels_in_every_image(obs):
    """The subsample a joint fit of per-pixel albedos searches on (:func:`~fmbrdf_mi.fit.solve.driver.solve`'s
    ``explore``) holds n cells: n / K pixels of the view, each in every image, so that its albedos are
    determined by all K lights as in the fit of all pixels."""
    opts = dataclasses.replace(FitOptions(), albedo="per-pixel", max_pixels=None)
    data = prepare([obs] * 3, opts, "likelihood")
    sub = data.subsample(60)
    assert [len(p) for p in sub.image_pixels] == [20] * 3
    assert all(np.array_equal(p, sub.image_pixels[0]) for p in sub.image_pixels)
    assert np.all(np.isin(sub.image_pixels[0], data.image_pixels[0]))
    assert sub.objective.layout.n_groups == 20
