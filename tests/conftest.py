import os
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tools"))


@pytest.fixture
def variant():
    """Polarised monochrome variant with the plugin registered (float32 JIT)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


def make(mi, **kw):
    d = {"type": "fmbrdf", "k_s": 1.0, "k_b": 1.0}
    d.update(kw)
    return mi.load_dict(d)


def make_float32(mi, **kw):
    """:func:`make` with float32 tables: by default (``tables="compact"``) the
    plugin stores every Mueller ratio in 16-bit fixed point when no gradients
    are wanted (within 3.1e-5 of M00), whose rounding would swamp a central
    difference with a small step."""
    return make(mi, tables="float32", **kw)


def fresnel_T(theta, eta):
    """(T_s, T_p) at incidence angle theta (independent NumPy formula)."""
    c = np.cos(theta)
    ct = np.sqrt(1 - np.sin(theta) ** 2 / eta ** 2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 1 - rs ** 2, 1 - rp ** 2
