"""The BSDF keeps its last builds without gradients by the parameter values they came from
(``bsdf.py`` ``_build``): whatever path the parameters take, the tables it evaluates are those a
new BSDF builds at the current values, bit for bit, and builds with gradients are never reused."""
import drjit as dr
import numpy as np
import pytest
from conftest import make

V1 = {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0}
V2 = {"eta": 1.4, "alpha": 0.2, "beta": 1.5, "kappa": 20.0}


def _arrays(bsdf):
    """Every array the tables consist of, as bytes."""
    t = bsdf.table
    arrays = list(t.values) if isinstance(t.values, (list, tuple)) else [t.values]
    arrays += [t.orient, bsdf.factors.values, bsdf.dist.p_tab, bsdf.dist.norm, bsdf.sampler.cdf,
               bsdf.sampler.v_edges]
    arrays += list(getattr(t, "lo", [])) + list(getattr(t, "step", []))
    return [np.asarray(dr.detach(x)).tobytes() for x in arrays]


def _set(mi, params, values, grad=()):
    for k, v in values.items():
        x = mi.Float(v)
        if k in grad:
            dr.enable_grad(x)
        params[k] = x
    params.update()


@pytest.mark.parametrize("tables", ["compact", "float32"])
def test_tables_equal_a_new_bsdfs_along_any_path(variant, tables):
    mi = variant
    fresh = {name: _arrays(make(mi, tables=tables, **v)) for name, v in (("v1", V1), ("v2", V2))}
    assert fresh["v1"] != fresh["v2"]
    bsdf = make(mi, tables=tables, **V1)
    params = mi.traverse(bsdf)
    first = bsdf.table
    _set(mi, params, V2)
    assert _arrays(bsdf) == fresh["v2"]
    _set(mi, params, V1)
    assert bsdf.table is first  # reused, not rebuilt
    assert _arrays(bsdf) == fresh["v1"]
    # one parameter changed by one float32 ulp: a new build, equal to a new BSDF's
    kappa = float(np.nextafter(np.float32(V1["kappa"]), np.float32(np.inf)))
    _set(mi, params, {"kappa": kappa})
    assert bsdf.table is not first
    assert _arrays(bsdf) == _arrays(make(mi, tables=tables, **dict(V1, kappa=kappa)))


def test_builds_with_gradients_are_not_reused(variant):
    """With gradients the tables carry the AD graph of the parameters, so each such build is new;
    without them again, the build at the same values is the plain one (no graph)."""
    mi = variant
    bsdf = make(mi, **V1)
    params = mi.traverse(bsdf)
    plain = bsdf.table
    for _ in range(2):
        _set(mi, params, V1, grad=("alpha",))
        assert bsdf.table is not plain and dr.grad_enabled(bsdf.table.values)
        graph = bsdf.table
        _set(mi, params, V1, grad=("alpha",))
        assert bsdf.table is not graph
        _set(mi, params, V1)
        assert bsdf.table is plain and not dr.grad_enabled(bsdf.table.values)
    assert _arrays(bsdf) == _arrays(make(mi, **V1))
