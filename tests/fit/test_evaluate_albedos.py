"""The per-channel albedo layout against NumPy's least squares and finite differences."""
import numpy as np

from fmbrdf_mi.fit.evaluate.albedos import ChannelAlbedos, ChannelModel
from fmbrdf_mi.fit.evaluate.models import get_model


def _data(seed=0):
    rng = np.random.default_rng(seed)
    chan = np.array([0, 0, 1, 1, 1, 1, 2, 2] * 2)            # 16 samples per cell, as a colour period
    S, B = rng.uniform(0.1, 1.0, (50, 16)), rng.uniform(0.1, 1.0, (50, 16))
    a_s, a_b = np.array([0.6, 0.4, 0.5]), np.array([0.3, 0.2, 0.45])
    y = a_s[chan] * S + a_b[chan] * B + rng.normal(0, 0.01, S.shape)
    w = rng.uniform(0.5, 2.0, S.shape)
    return ChannelAlbedos(chan), S, B, y, w, a_s, a_b


def test_solve_is_each_channels_weighted_least_squares():
    lay, S, B, y, w, a_s, a_b = _data()
    got_s, got_b = lay.solve(S, B, y, w)
    for g in range(3):
        m = lay.channel == g
        X = np.stack([S[:, m].ravel(), B[:, m].ravel()], 1) * np.sqrt(w[:, m].ravel())[:, None]
        ref = np.linalg.lstsq(X, y[:, m].ravel() * np.sqrt(w[:, m].ravel()), rcond=None)[0]
        assert np.allclose([got_s[g], got_b[g]], ref, rtol=1e-10), (g, got_s, got_b, ref)
        assert abs(got_s[g] - a_s[g]) < 0.02 and abs(got_b[g] - a_b[g]) < 0.02   # and near the truth


def test_columns_are_derivatives_in_log_albedo():
    lay, S, B, _, _, a_s, a_b = _data(1)
    cols = lay.columns(S, B, a_s, a_b)
    h = 1e-6
    for j in range(6):
        z = np.log(np.concatenate([a_s, a_b]))
        zp, zm = z.copy(), z.copy()
        zp[j] += h
        zm[j] -= h
        fd = (lay.mu(S, B, np.exp(zp[:3]), np.exp(zp[3:])) - lay.mu(S, B, np.exp(zm[:3]), np.exp(zm[3:]))) / (2 * h)
        assert np.allclose(cols[j], fd, rtol=1e-6, atol=1e-12), j


def test_channel_model_reports_flat_names_and_nests_them():
    lay = ChannelAlbedos(np.arange(16) % 3)
    m = ChannelModel(get_model("fmbrdf"), lay)
    shape = {"eta": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 10.0}
    a_s, a_b = np.array([0.6, 0.4, 0.5]), np.array([0.42, 0.2, 0.1])
    flat = m.report(shape, a_s, a_b)
    f = get_model("fmbrdf").albedo_factor
    assert list(flat) == ["eta", "alpha", "beta", "kappa", "k_s[R]", "k_s[G]", "k_s[B]", "r_k[R]", "r_k[G]", "r_k[B]"]
    assert np.isclose(flat["k_s[G]"], f * 0.4) and np.isclose(flat["r_k[B]"], 0.1 / 0.5)
    nested = m.nest(flat)
    assert nested["k_s"] == {"R": flat["k_s[R]"], "G": flat["k_s[G]"], "B": flat["k_s[B]"]}
    assert nested["eta"] == 1.5
