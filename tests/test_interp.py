"""Tetrahedral table interpolation: exact on affine data and at nodes, continuous, clamped."""
import numpy as np
import pytest


@pytest.fixture
def Float(variant):
    import mitsuba as mi
    return mi.Float


def _table(Float, data, pattern=None):
    """A TetraTable of ``data`` (n0, n1, n2, C); ``pattern``: its triangulation
    forced (0-3), else chosen by the table (interp.orientation)."""
    import drjit as dr
    from fmbrdf_mi.model.interp import TetraTable
    orient = None if pattern is None else dr.uint32_array_t(Float)(pattern)
    return TetraTable(Float(np.ascontiguousarray(data, dtype=np.float32).ravel()), data.shape, orient)


#: The four triangulations: the long diagonal (1, s1, s2) each is built around.
DIAGONALS = {0: (1, 1, 1), 1: (1, -1, 1), 2: (1, 1, -1), 3: (1, -1, -1)}


@pytest.mark.parametrize("pattern", sorted(DIAGONALS))
def test_affine_functions_are_reproduced(Float, pattern):
    shape = (5, 7, 9)
    g = np.meshgrid(*[np.linspace(0, 1, n) for n in shape], indexing="ij")
    data = np.stack([1 + 2 * g[0] - 3 * g[1] + 0.5 * g[2], -g[2] + 4 * g[0]], axis=-1)
    t = _table(Float, data, pattern)
    u = np.random.default_rng(0).uniform(0, 1, (3, 5000))
    out = t.eval(*(Float(x) for x in u))
    assert np.allclose(np.asarray(out[0]), 1 + 2 * u[0] - 3 * u[1] + 0.5 * u[2], atol=2e-6)
    assert np.allclose(np.asarray(out[1]), -u[2] + 4 * u[0], atol=2e-6)


@pytest.mark.parametrize("pattern", sorted(DIAGONALS))
def test_nodes_exact_and_outside_clamped(Float, pattern):
    rng = np.random.default_rng(1)
    data = rng.normal(size=(4, 3, 5, 1))
    t = _table(Float, data, pattern)
    idx = np.array([(i, j, k) for i in range(4) for j in range(3) for k in range(5)]).T
    u = [Float(idx[a] / (data.shape[a] - 1)) for a in range(3)]
    assert np.allclose(np.asarray(t.eval(*u)[0]), data[idx[0], idx[1], idx[2], 0], atol=1e-6)
    far = [Float([-0.5, 1.5]), Float([-1.0, 2.0]), Float([-3.0, 7.0])]
    assert np.allclose(np.asarray(t.eval(*far)[0]), [data[0, 0, 0, 0], data[-1, -1, -1, 0]], atol=1e-6)


@pytest.mark.parametrize("pattern", sorted(DIAGONALS))
def test_interpolation_is_continuous_across_tetrahedra(Float, pattern):
    """Random node values, so a cell face split along different diagonals on
    its two sides would show as a jump of order 1 along the path."""
    data = np.random.default_rng(2).normal(size=(3, 3, 3, 1))
    t = _table(Float, data, pattern)
    # walk across the cell diagonals, where the tetrahedron changes
    s = np.linspace(0, 1, 20001)
    u = [0.5 * s, 0.5 * (1 - s) ** 2, 0.25 + 0.5 * np.sin(3 * s) ** 2]
    v = np.asarray(t.eval(*(Float(x) for x in u))[0])
    assert np.abs(np.diff(v)).max() < 1e-3


def _kuhn_reference(data, u, diag):
    """Independent NumPy interpolation on Kuhn's triangulation around ``diag``:
    mirror the cell along the axes where diag is -1, then the usual sorted
    walk from the (mirrored) base corner."""
    shape = np.array(data.shape[:3])
    f = np.clip(u.T, 0, 1) * (shape - 1)
    i = np.minimum(f.astype(int), shape - 2)
    fr = f - i
    s = np.array(diag)
    fr = np.where(s > 0, fr, 1 - fr)
    corner = i + (s < 0)
    order = np.argsort(-fr, axis=1, kind="stable")
    fs = np.take_along_axis(fr, order, 1)
    val = (1 - fs[:, 0]) * data[tuple(corner.T)]
    for step in range(3):
        ax = order[:, step]
        corner[np.arange(len(ax)), ax] += s[ax]
        w = fs[:, step] - (fs[:, step + 1] if step < 2 else 0)
        val += w * data[tuple(corner.T)]
    return val


@pytest.mark.parametrize("pattern", sorted(DIAGONALS))
def test_each_triangulation_matches_an_independent_one(Float, pattern):
    """The lookup with each forced triangulation against a NumPy reference
    written from the definition (float32 rounding: 1e-5 of values of order 1)."""
    rng = np.random.default_rng(5)
    data = rng.normal(size=(4, 5, 6, 1))
    t = _table(Float, data, pattern)
    u = rng.uniform(-0.05, 1.05, (3, 4000))
    got = np.asarray(t.eval(*(Float(x) for x in u))[0])
    np.testing.assert_allclose(got, _kuhn_reference(data[..., 0], u, DIAGONALS[pattern]), atol=1e-5)


@pytest.mark.parametrize("direction", [(0, 1, -1), (0, 1, 1), (1, 0, 1), (1, -1, 0), (1, 1, -1), (1, -1, 1)])
def test_orientation_picks_the_most_accurate_triangulation(Float, direction):
    """A table of f = (d . x)^2 (x in index units) curves only along d; the
    triangulations whose edges run across d reproduce it best (the linear
    interpolant on a simplex errs by 1/2 sum lambda_i lambda_j e_ij^T H e_ij).
    The one interp.orientation picks (from the table's values alone) has an
    RMS error at random points, measured against f itself, within 2 % of the
    smallest of all four (two or three of them can be that close), and well
    below the largest: the choice matters."""
    shape = (6, 7, 8)
    g = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    d = np.array(direction, dtype=np.float64) / np.linalg.norm(direction)
    f = lambda x0, x1, x2: (d[0] * x0 + d[1] * x1 + d[2] * x2) ** 2 / 10.0
    data = f(*g)[..., None]
    u = np.random.default_rng(6).uniform(0, 1, (3, 20000))
    exact = f(*(u[a] * (shape[a] - 1) for a in range(3)))
    rms = {}
    for p in DIAGONALS:
        got = np.asarray(_table(Float, data, p).eval(*(Float(x) for x in u))[0])
        rms[p] = np.sqrt(np.mean((got - exact) ** 2))
    chosen = int(_table(Float, data).orient[0])
    assert rms[chosen] <= 1.02 * min(rms.values()), rms
    assert rms[chosen] < 0.7 * max(rms.values())


def test_packed_table_equals_float_table_to_its_step(variant):
    """PackedTetraTable stores each channel in fixed point over its own range,
    step_c = range_c / (2^bits - 1): each node value is within half a step, so
    an interpolated value (a convex combination) is within step_c / 2 of the
    float32 table's, plus float32 rounding of the sums (1e-6 of the largest
    value).  Channels of very different ranges (a log channel over [-30, 5], a
    ratio in [-1, 1], a constant) keep their own precision."""
    import mitsuba as mi
    if not mi.variant().startswith(("llvm", "cuda")):
        pytest.skip("packed tables are for the JIT variants")
    from fmbrdf_mi.model.interp import PackedTetraTable
    Float = mi.Float
    rng = np.random.default_rng(3)
    data = rng.uniform(-1, 1, size=(6, 5, 7, 5))
    data[..., 0] = rng.uniform(-30, 5, size=(6, 5, 7))
    data[..., 3] = 0.25  # constant: range 0
    data[..., 4] *= 1e-3  # small values keep a small step
    t = _table(Float, data)
    words = [[(0, 16), (1, 16), (3, 16), (4, 16)], [(2, 13)]]
    p = PackedTetraTable(t, words)
    assert p.shape[3] == 2 and dr_width(p.values) == 6 * 5 * 7 * 2
    u = [Float(x) for x in rng.uniform(-0.1, 1.1, (3, 20000))]
    a = [np.asarray(x, dtype=np.float64) for x in t.eval(*u)]
    b = [np.asarray(x, dtype=np.float64) for x in p.eval(*u)]
    bits = {ch: b_ for w in words for ch, b_ in w}
    for k, (x, y) in enumerate(zip(a, b)):
        step = np.ptp(data[..., k]) / (2 ** bits[k] - 1)
        err = np.abs(x - y).max()
        assert err <= 0.5 * step + 1e-6 * np.abs(data[..., k]).max() + 1e-12, (k, err, step)
        if step > 0:
            assert err > 0.05 * step  # it is really quantised
    with pytest.raises(ValueError, match="every channel once"):
        PackedTetraTable(t, [[(0, 16), (1, 16)], [(2, 13)]])  # channels 3, 4 missing
    with pytest.raises(ValueError, match="64 bits"):
        PackedTetraTable(t, [[(0, 20), (1, 20), (2, 20), (3, 20)], [(4, 13)]])


def dr_width(x):
    import drjit as dr
    return dr.width(x)


def test_compact_and_float32_tables_agree(variant):
    """The plugin's default tables ("compact": every channel in 12-16-bit fixed
    point when no gradients are wanted) against tables="float32": the log
    channel within h0 = step_0 / 2, so M00 within relative e^h0 - 1; each ratio
    within h = max step_c / 2; so each Mueller element of the body term within
    (4 h + (e^h0 - 1)(1 + 4 h)) M00 after the two Stokes-frame rotations (each
    output element mixes at most 4 ratios with coefficients of modulus <= 1,
    and the ratios of a Mueller matrix are at most 1); plus float32 rounding.
    The surface term is not tabulated and equal."""
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
    assert int(compact.table.orient[0]) == int(f32.table.orient[0])  # the same triangulation
    a, _, _ = eval_mueller(compact, L, V, component=1)
    b, _, _ = eval_mueller(f32, L, V, component=1)
    err = np.abs(a - b).max(axis=(1, 2)) / b[:, 0, 0]
    steps = [float(x[0]) for x in compact.table.step]
    h0, h = 0.5 * steps[0], 0.5 * max(steps[1:])
    assert h0 < 1e-4 and h < 2e-4  # 16 bits over a log range below 13, 12 bits over a ratio range below 2
    bound = 4 * h + np.expm1(h0) * (1 + 4 * h)
    assert err.max() <= bound + 1e-6
    assert err.max() > 1e-7  # the default really is the compact table
    assert np.abs(a[:, 0, 0] / b[:, 0, 0] - 1).max() <= np.expm1(h0) + 1e-6
    s1, _, _ = eval_mueller(compact, L, V, component=0)
    s2, _, _ = eval_mueller(f32, L, V, component=0)
    np.testing.assert_array_equal(s1, s2)
    with pytest.raises(fmbrdf_mi.ParameterError, match="tables"):
        fmbrdf_mi.load_dict({"type": "fmbrdf", "tables": "half"})
