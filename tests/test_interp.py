"""Tetrahedral table interpolation: exact on affine data and at nodes, continuous, clamped."""
import numpy as np
import pytest


@pytest.fixture
def Float(variant):
    import mitsuba as mi
    return mi.Float


def _table(Float, data):
    from fmbrdf_mi.model.interp import TetraTable
    return TetraTable(Float(np.ascontiguousarray(data, dtype=np.float32).ravel()), data.shape)


def test_affine_functions_are_reproduced(Float):
    shape = (5, 7, 9)
    g = np.meshgrid(*[np.linspace(0, 1, n) for n in shape], indexing="ij")
    data = np.stack([1 + 2 * g[0] - 3 * g[1] + 0.5 * g[2], -g[2] + 4 * g[0]], axis=-1)
    t = _table(Float, data)
    u = np.random.default_rng(0).uniform(0, 1, (3, 5000))
    out = t.eval(*(Float(x) for x in u))
    assert np.allclose(np.asarray(out[0]), 1 + 2 * u[0] - 3 * u[1] + 0.5 * u[2], atol=2e-6)
    assert np.allclose(np.asarray(out[1]), -u[2] + 4 * u[0], atol=2e-6)


def test_nodes_exact_and_outside_clamped(Float):
    rng = np.random.default_rng(1)
    data = rng.normal(size=(4, 3, 5, 1))
    t = _table(Float, data)
    idx = np.array([(i, j, k) for i in range(4) for j in range(3) for k in range(5)]).T
    u = [Float(idx[a] / (data.shape[a] - 1)) for a in range(3)]
    assert np.allclose(np.asarray(t.eval(*u)[0]), data[idx[0], idx[1], idx[2], 0], atol=1e-6)
    far = [Float([-0.5, 1.5]), Float([-1.0, 2.0]), Float([-3.0, 7.0])]
    assert np.allclose(np.asarray(t.eval(*far)[0]), [data[0, 0, 0, 0], data[-1, -1, -1, 0]], atol=1e-6)


def test_interpolation_is_continuous_across_tetrahedra(Float):
    data = np.random.default_rng(2).normal(size=(3, 3, 3, 1))
    t = _table(Float, data)
    # walk across the cell diagonals, where the tetrahedron changes
    s = np.linspace(0, 1, 20001)
    u = [0.5 * s, 0.5 * (1 - s) ** 2, 0.25 + 0.5 * np.sin(3 * s) ** 2]
    v = np.asarray(t.eval(*(Float(x) for x in u))[0])
    assert np.abs(np.diff(v)).max() < 1e-3


@pytest.mark.parametrize("n_float", [0, 1])
def test_packed_table_equals_float_table_to_its_step(variant, n_float):
    """PackedTetraTable stores packed channels as 16-bit fixed point (step
    2/32767): each node value is within half a step, so an interpolated value
    (a convex combination) is within 3.06e-5 of the float32 table's; float
    channels are bit-identical.  Values outside [-2, 2] are clipped."""
    import mitsuba as mi
    if not mi.variant().startswith(("llvm", "cuda")):
        pytest.skip("packed tables are for the JIT variants")
    from fmbrdf_mi.model.interp import PackedTetraTable
    Float = mi.Float
    rng = np.random.default_rng(3)
    data = rng.uniform(-2, 2, size=(6, 5, 7, 6 + n_float))
    data[..., 0] *= 50 if n_float else 1  # a float channel far outside [-2, 2]
    t = _table(Float, data)
    p = PackedTetraTable(t, n_float=n_float, bound=2.0)
    assert p.shape[3] == n_float + 3
    u = [Float(x) for x in rng.uniform(-0.1, 1.1, (3, 20000))]
    a = [np.asarray(x) for x in t.eval(*u)]
    b = [np.asarray(x) for x in p.eval(*u)]
    for k, (x, y) in enumerate(zip(a, b)):
        if k < n_float:
            assert np.array_equal(x, y)
        else:
            err = np.abs(x - y).max()
            assert err <= 0.5 * p.scale + 1e-6, (k, err)
            assert err > 1e-7  # it is really quantised
    clipped = PackedTetraTable(_table(Float, np.full((2, 2, 2, 2), 3.0)))
    assert np.allclose(np.asarray(clipped.eval(Float(0.3), Float(0.3), Float(0.3))[0]), 2.0, atol=1e-4)


def test_compact_and_float32_tables_agree(variant):
    """The plugin's default tables ("compact": ratios in 16-bit fixed point when
    no gradients are wanted) against tables="float32": each ratio within 3.06e-5,
    so each Mueller element of the body term within 4 x 3.06e-5 x M00 after the
    two Stokes-frame rotations (each output element mixes at most 4 ratios with
    coefficients of modulus <= 1); the surface term is not tabulated and equal."""
    from _common import directions, eval_mueller
    from conftest import make, make_float32
    import fmbrdf_mi

    mi = variant
    rng = np.random.default_rng(4)
    n = 400
    L = directions(rng.uniform(0, 85, n), rng.uniform(-180, 180, n))
    V = directions(rng.uniform(0, 85, n), rng.uniform(-180, 180, n))
    mat = dict(eta=1.7, alpha=0.5, beta=1.5, kappa=30.0)
    compact, f32 = make(mi, **mat), make_float32(mi, **mat)
    a, _, _ = eval_mueller(compact, L, V, component=1)
    b, _, _ = eval_mueller(f32, L, V, component=1)
    err = np.abs(a - b).max(axis=(1, 2)) / b[:, 0, 0]
    assert err.max() <= 4 * 3.06e-5 + 1e-6
    assert err.max() > 1e-7  # the default really is the compact table
    np.testing.assert_array_equal(a[:, 0, 0], b[:, 0, 0])  # log M00 stays float32
    s1, _, _ = eval_mueller(compact, L, V, component=0)
    s2, _, _ = eval_mueller(f32, L, V, component=0)
    np.testing.assert_array_equal(s1, s2)
    with pytest.raises(fmbrdf_mi.ParameterError, match="tables"):
        fmbrdf_mi.load_dict({"type": "fmbrdf", "tables": "half"})
